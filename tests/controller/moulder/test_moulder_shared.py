"""What a moulder's heads share in real time: one read of the common registers per PLC cycle,
one CAN master for every amplifier, one pool of measurement workers."""

from __future__ import annotations

import asyncio
import itertools
from dataclasses import replace
from pathlib import Path

import can
import pytest

from config.loading import default_path
from config.machine import load_machine
from planer.hil import load_scenario
from planer.hil.moulder import MoulderPlant
from planer.hil.scenario import machine_config_for, sim_config_for

_chan = itertools.count()


def _plant(tmp_path: Path) -> MoulderPlant:
    sc = load_scenario("moulder")
    cfg = machine_config_for(sc, log_path=tmp_path / "m.sqlite")
    return MoulderPlant(cfg, sim_config_for(sc), seed=0, log_path=tmp_path / "m.sqlite",
                        render_images=False)


def _count_requests(plc) -> list[str]:
    """Record the kind of every request ``plc``'s bus gets (``read``, ``read_write``,
    ``write``)."""
    seen: list[str] = []
    for name in ("read", "read_write", "write"):
        inner = getattr(plc.bus, name)

        async def wrapped(*args, _inner=inner, _name=name):
            seen.append(_name)
            return await _inner(*args)

        setattr(plc.bus, name, wrapped)
    return seen


def test_the_common_registers_are_read_once_per_plc_cycle_for_every_head(tmp_path):
    plant = _plant(tmp_path)
    moulder = plant.service

    async def go():
        try:
            for _ in range(5):
                await plant.step()
            assert list(moulder.sharing_common) == list(moulder.heads)
            coordinator = _count_requests(moulder.feed.plc)
            heads = {name: _count_requests(svc.plc) for name, svc in moulder.heads.items()}
            cycles = moulder.feed.counts["cycles"]
            beat = moulder.feed.heartbeat
            await moulder.plc_cycle()
            # its heartbeat and the common registers in one function 23, then every head's
            # block in one read (the map's [heads] read_across); the heads ask for nothing
            assert coordinator[:2] == ["read_write", "read"], coordinator
            assert "write" not in coordinator[:2]
            assert all(seen == [] for seen in heads.values()), heads
            assert moulder.feed.plc.last["heartbeat_service"] == beat + 1
            assert moulder.feed.counts["cycles"] == cycles + 1
            assert moulder.feed.last is not None and moulder.feed.last.feed_mm_s is not None
            for name, svc in moulder.heads.items():  # what each head would have read itself
                shared = svc.plc.last.values
                own = (await svc.plc.read()).values
                assert shared == own, name
                assert heads[name] == ["read", "read_write"]  # the offers were used once
        finally:
            await plant.close()

    asyncio.run(go())


def test_without_the_coordinators_read_each_head_reads_its_own(tmp_path):
    plant = _plant(tmp_path)
    moulder = plant.service

    async def go():
        try:
            for _ in range(3):
                await plant.step()

            async def refused(*_args) -> None:
                from core.errors import FieldbusError

                raise FieldbusError("PLC gone")

            moulder.feed.plc.beat_and_read = refused  # the coordinator's read fails this cycle
            heads = {name: _count_requests(svc.plc) for name, svc in moulder.heads.items()}
            await moulder.plc_cycle()
            assert all(seen == ["read", "read_write"] for seen in heads.values()), heads
            assert moulder.feed.last.feed_mm_s is None and moulder.feed.last.safe
            assert moulder.feed.counts["plc_errors"] == 1
        finally:
            await plant.close()

    asyncio.run(go())


def test_without_the_coordinators_block_read_each_head_reads_its_block(tmp_path):
    plant = _plant(tmp_path)
    moulder = plant.service

    async def go():
        try:
            for _ in range(3):
                await plant.step()

            async def refused(*_args) -> None:
                from core.errors import FieldbusError

                raise FieldbusError("PLC gone")

            moulder.feed.plc.read_blocks = refused  # the common read answers, the blocks not
            heads = {name: _count_requests(svc.plc) for name, svc in moulder.heads.items()}
            await moulder.plc_cycle()
            # the common registers offered, each head's block its own function 23
            assert all(seen == ["read_write"] for seen in heads.values()), heads
            assert moulder.feed.counts["plc_errors"] == 1
            assert moulder.feed.last.feed_mm_s is not None  # decided on the common registers
            for name, svc in moulder.heads.items():
                assert svc.plc.last.values == (await svc.plc.read()).values, name
        finally:
            await plant.close()

    asyncio.run(go())


def test_open_moulder_service_puts_every_amplifier_on_one_master(tmp_path):
    from controller.moulder.compose import open_moulder_service, share_workers

    cfg = load_machine(default_path("machine_moulder.toml"))
    channel = f"moulder-shared-{next(_chan)}"
    bus = can.Bus(interface="virtual", channel=channel)
    moulder = open_moulder_service(cfg, log_path=tmp_path / "q.sqlite", can_bus=bus,
                                   threaded=False)
    try:
        masters = {id(svc.piezo.ampbus) for svc in moulder.heads.values()}
        assert len(masters) == 1 and moulder.shared[0].bus is bus
        nodes = sorted(moulder.shared[0].amplifiers)
        assert nodes == sorted(hc.node_id for hc in cfg.heads) == [2, 3, 4, 5]
        assert all(svc.piezo.shared for svc in moulder.heads.values())
        assert share_workers(moulder, 0, shape=None, timeout_s=1.0) == (None, None)
        with pytest.raises(ValueError, match="workers"):
            share_workers(moulder, -1, shape=None, timeout_s=1.0)
    finally:
        moulder.close()
    assert moulder.shared[0].network.bus is None  # closed once, after every head
    with pytest.raises(ValueError, match="node_id 2 is already an amplifier"):  # one master
        open_moulder_service(replace(cfg, declared_heads=cfg.declared_heads[:1] * 2),
                             log_path=tmp_path / "r.sqlite",
                             can_bus=can.Bus(interface="virtual", channel=channel))


def test_share_workers_gives_every_head_one_pool_with_its_own_factory(tmp_path):
    from controller.moulder.compose import open_moulder_service, share_workers
    from controller.workers.pool import PoolForFactory

    cfg = load_machine(default_path("machine_moulder.toml"))
    bus = can.Bus(interface="virtual", channel=f"moulder-shared-{next(_chan)}")
    moulder = open_moulder_service(cfg, log_path=tmp_path / "q.sqlite", can_bus=bus,
                                   threaded=False)
    pool = None
    try:
        pool, warning = share_workers(moulder, 1, shape=None, timeout_s=5.0, cores=2)
        assert warning is None and pool is not None and pool.workers == 1
        views = [svc.measurement._pool for svc in moulder.heads.values()]
        assert all(isinstance(v, PoolForFactory) and v.pool is pool for v in views)
        assert [v.factory for v in views] == [svc.measurement.factory
                                              for svc in moulder.heads.values()]
    finally:
        moulder.close()
        if pool is not None:
            pool.close()


def test_the_coordinators_own_error_in_its_read_holds_the_feed_safe_as_in_its_law(tmp_path):
    """An unexpected error of the coordinator's sample (not the PLC's trouble) in the real-time
    PLC cycle: reported once, the feed held safe for the recovery time, then governed again."""
    plant = _plant(tmp_path)
    moulder = plant.service

    async def go():
        try:
            for _ in range(3):
                await plant.step()
            real = moulder.feed.sample

            async def broken():
                raise RuntimeError("a bug in the coordinator's read")

            moulder.feed.sample = broken
            await moulder.plc_cycle()
            moulder.feed.sample = real
            assert moulder.feed.counts["faults"] == 1
            assert moulder.feed.last.safe and moulder.feed.last.feed_mm_s is None
            await moulder.plc_cycle()  # within the recovery time: the safe path, not the law
            assert moulder.feed.last.safe
            assert moulder.feed.counts["safe_cycles"] >= 1
            errors = [e for e in moulder.first.events if e.kind.value == "service_error"]
            assert errors and "a bug in the coordinator's read" in errors[-1].text
        finally:
            await plant.close()

    asyncio.run(go())
