"""The service in real time (``Service.run``) against the real Modbus server and a CAN node."""

from __future__ import annotations

import asyncio


def test_run_in_real_time_applies_every_pair(tmp_path):
    from config.sim import default_sim
    from planer.benchmarks.service import _run
    from plant_sim.machine import Machine

    machine = Machine(default_sim(), seed=3)
    frames: list = []
    while len(frames) < 6:
        frames += machine.advance(0.05)
    out = asyncio.run(_run(frames[:6], machine, rate_hz=25.0, workdir=tmp_path))
    assert (out["width"], out["height"]) == (659, 493)
    assert out["pairs"] == 6 and out["applied"] + out["failed"] == 6 and out["applied"] >= 4
    assert 0 < out["median_ms"] <= out["p99_ms"] <= out["max_ms"]
    # every pair was logged by the real-time path (worker-thread append)
    from controller.quality_log import QualityLog

    with QualityLog(tmp_path / "bench.sqlite", create=False) as log:
        assert len(log) == 6

