"""The service latency benchmark (``planer bench``, ``service`` part) waits on events, not clocks.

It must start feeding pairs once the service reported RUN (or fail clearly after a deadline)
and stop only after the last pair was handled, however long the measurement takes. The slow
measurement below makes a fixed wait after the last pair lose that pair.
"""

from __future__ import annotations

import asyncio
import time

import pytest

N_PAIRS = 4


@pytest.fixture(scope="module")
def frames_and_machine():
    from config.sim import default_sim
    from plant_sim.machine.machine import Machine

    machine = Machine(default_sim(), seed=2)
    frames: list = []
    while len(frames) < N_PAIRS:
        frames += machine.advance(0.05)
    return frames[:N_PAIRS], machine


def test_bench_handles_every_pair_even_when_the_last_one_is_slow(
    tmp_path, monkeypatch, frames_and_machine
):
    import vision.pipeline as vp
    from planer.benchmarks import service as bench

    frames, machine = frames_and_machine
    last = (frames[-1].counts_a, frames[-1].counts_b)
    real = vp.Measurer

    class SlowLast(real):  # the last pair takes longer than any fixed grace period
        def measure(self, image_a, image_b, **kw):
            out = super().measure(image_a, image_b, **kw)
            if (kw["counts_a"], kw["counts_b"]) == last:
                time.sleep(0.4)
            return out

    monkeypatch.setattr(vp, "Measurer", SlowLast)
    out = asyncio.run(bench._run(frames, machine, rate_hz=25.0, workdir=tmp_path))
    assert out["pairs"] == N_PAIRS
    assert out["applied"] + out["failed"] <= N_PAIRS and out["applied"] >= 1


def test_bench_fails_clearly_when_the_service_never_runs(tmp_path, monkeypatch,
                                                         frames_and_machine):
    from planer.benchmarks import service as bench
    from plant_sim.interfaces.amp_node import AmpNode

    monkeypatch.setattr(AmpNode, "pump", lambda self, now_s: None)  # the amplifier is silent
    frames, machine = frames_and_machine
    with pytest.raises(RuntimeError, match="not in RUN.*can gone"):
        asyncio.run(bench._run(frames, machine, rate_hz=25.0, workdir=tmp_path,
                               ready_timeout_s=1.0))
