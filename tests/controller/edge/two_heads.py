"""Two real heads' services standing in for a moulder: ``heads`` and ``head_configs``.

Each head is an in-process plant (the simulator's machine on a direct register bus and its own
virtual CAN amplifier) with its own :class:`~controller.service.service.Service`, built as the
single-head tests build one; the composition has exactly what the servers follow in a moulder
(``heads``: name -> Service in order, ``head_configs``). Simulated time, no sleeping.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from config.heads import Face, HeadConfig
from planer.hil import InProcessPlant, load_scenario, machine_config_for, sim_config_for
from tests.support.plant_support import record_frames, truth_measurer

HEAD_CONFIGS = (
    HeadConfig(name="bottom", face=Face.BOTTOM, node_id=2, target_pitch_mm=1.5, knives=4,
               rpm=6000.0, rpm_min=6000.0, rpm_max=6000.0),
    HeadConfig(name="top", face=Face.TOP, node_id=5, target_pitch_mm=1.0, knives=4,
               rpm=6000.0, rpm_min=4000.0, rpm_max=8000.0),
)


@dataclass
class TwoHeads:
    """The stand-in moulder: the heads' services in order and their configurations."""

    heads: dict[str, Any]
    head_configs: tuple[HeadConfig, ...]
    plants: dict[str, Any]

    async def step(self, n: int) -> None:
        """``n`` control cycles of every head (pairs measured by the true marks)."""
        for _ in range(n):
            for plant in self.plants.values():
                await plant.step()

    async def close(self) -> None:
        for plant in self.plants.values():
            await plant.close()


async def two_heads(tmp_path: Path, *, steps: int = 200, safe_head: str | None = "top",
                    safe_steps: int = 50) -> TwoHeads:
    """Both heads after ``steps`` cycles; then ``safe_head``'s amplifier falls silent and
    ``safe_steps`` more cycles run (that head's service is in its safe state, the other runs).

    Each head's target pitch is its configuration's; its log is its own file in ``tmp_path``.
    """
    plants: dict[str, Any] = {}
    for i, hc in enumerate(HEAD_CONFIGS):
        sc = replace(load_scenario("default"), target_pitch_mm=hc.target_pitch_mm, seed=i)
        cfg = machine_config_for(sc, log_path=tmp_path / f"{hc.name}.sqlite")
        frames: dict = {}
        plant = InProcessPlant(cfg, sim_config_for(sc), seed=i, render_images=False,
                               plc_transport="direct",
                               measurer_factory=lambda shape, f=frames: truth_measurer(f))
        record_frames(plant, frames)
        await plant.start()
        plant.service.keep_results = True
        plants[hc.name] = plant
    heads = TwoHeads({name: p.service for name, p in plants.items()}, HEAD_CONFIGS, plants)
    await heads.step(steps)
    if safe_head is not None:
        plants[safe_head].can_fault("can_silence", 1e6)
        await heads.step(safe_steps)
    return heads


def moulder_fixture(tmp_path_factory):
    """A module fixture's body: the two heads started, closed after (``pytest.fixture`` it)."""
    loop = asyncio.new_event_loop()
    th = loop.run_until_complete(two_heads(tmp_path_factory.mktemp("two_heads")))
    try:
        yield th
    finally:
        loop.run_until_complete(th.close())
        loop.close()


def follow_all(followed) -> list:
    """Every item the servers' follower takes from ``followed`` now (one look)."""
    from controller.edge.feed import Mailbox, follow_once

    box = Mailbox(1 << 16)
    follow_once(followed, {}, box)
    assert box.dropped == 0
    return box.take(0.0)
