"""The service in closed loop with the in-process simulator, on simulated time.

The measurer here reads the simulator's truth of each pair (no images rendered), so these tests
exercise the service -- supervisor, loops, buses, log -- independently of the vision pipeline;
``tests/planer/hil/test_hil.py`` runs the whole chain with the real pipeline.
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from config.machine import load_machine
from controller.quality.log import QualityLog
from controller.service.events import EventKind
from controller.service.supervisor import SafetyState
from core.errors import MeasurementError, RegistrationError
from planer.hil import Scenario, sim_config_for
from tests.support.plant_support import record_frames, run_for

SCENARIO = Scenario(runout_um=(0.0, 4.0, -2.0, 2.0), initial_feed_mm_s=800.0)


class TruthMeasurer:
    """Returns the simulator's truth of the pair (looked up by its encoder counts)."""

    def __init__(self, frames: dict) -> None:
        self.frames = frames
        self.fail_with: Exception | None = None
        self.calls = 0
        self.before_failure = None  # callable run when a failure is raised

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None):
        self.calls += 1
        if self.fail_with is not None:
            if self.before_failure is not None:
                self.before_failure()
            raise self.fail_with
        tr = self.frames[(counts_a, counts_b)].truth
        widths = np.asarray(tr["mark_widths_mm"], dtype=float)
        return SimpleNamespace(
            pitch_mm=float(tr["pitch_mm"]),
            mark_widths_mm=widths,
            bottoms_mm=np.asarray(tr["bottoms_mm"], dtype=float),
            uniformity_cv=float(tr["uniformity_cv"]),
            depth_um=float(tr["depth_um"]),
            shift_px=float(tr["shift_px"]),
            confidence=1.0,
        )


def make_plant(tmp_path, *, plc_transport="direct", log="config", **safety):
    """The in-process plant with a truth-reading measurer (and ``log``: "config" = q.sqlite)."""
    from planer.hil import InProcessPlant

    cfg = load_machine()
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    if safety:
        cfg = cfg.with_changes(safety=replace(cfg.safety, **safety))
    frames: dict = {}
    measurer = TruthMeasurer(frames)
    plant = InProcessPlant(
        cfg,
        sim_config_for(SCENARIO),
        plc_transport=plc_transport,
        measurer_factory=lambda shape: measurer,
        render_images=False,
        log=log,
    )
    record_frames(plant, frames)
    return plant, measurer




def test_loop_closes_logs_everything_and_stays_in_limits(tmp_path):
    async def main():
        plant, _ = make_plant(tmp_path)
        await plant.start()
        res = await run_for(plant, 6.0)
        svc = plant.service
        assert svc.state is SafetyState.RUN
        assert len(res) > 40 and all(r.ok for r in res)
        # the feed moves from 800 mm/s (2 mm pitch) to the target 1.5 mm * n * Z
        snap = plant.plc.last
        target_feed = 1.5 * snap.spindle_rpm / 60 * snap.knives
        assert plant.machine.register_values()["feed_setpoint_mm_s"] == pytest.approx(
            target_feed, rel=0.01
        )
        feeds = [r.feed_setpoint_mm_s for r in res]
        assert all(snap.feed_min_mm_s <= f <= snap.feed_max_mm_s for f in feeds)
        # the uniformity loop learnt offsets (zero mean, inside the stroke) that the amplifier got
        offs = np.asarray(svc.offsets_um)
        assert np.abs(offs).max() > 0.5 and abs(offs.mean()) < 0.01
        assert np.abs(offs).max() <= plant.cfg.stroke_um
        amp_table = plant.amp.core.offsets_um[: len(offs)]
        assert np.allclose(amp_table, offs, atol=1e-3)
        # true uniformity fell well below where it started
        cvs = [r.truth["uniformity_cv"] for r in res]
        assert cvs[0] > 0.1 and np.mean(cvs[-5:]) < 0.5 * cvs[0]
        await plant.close()
        with QualityLog(tmp_path / "q.sqlite", create=False) as log:
            recs = log.records()
        assert len(recs) == len(res)
        assert [r.seq for r in recs] == [r.seq for r in res]
        assert all(r.ok and r.passed is not None for r in recs)
        # heartbeats went to the PLC every cycle: its watchdog never tripped after the start
        assert not plant.machine.register_values()["faults"] & 8

    asyncio.run(main())


@pytest.mark.parametrize(
    "exc,reason",
    [
        (RegistrationError("confidence 0.1"), "registration failed"),
        (MeasurementError("saturated pair"), "measurement failed"),
    ],
)
def test_failed_measurement_changes_no_setpoint_and_is_logged(tmp_path, exc, reason):
    async def main():
        plant, measurer = make_plant(tmp_path)
        await plant.start()
        await run_for(plant, 3.0)  # loop closed, learning
        svc = plant.service
        assert svc.state is SafetyState.RUN and svc.counters["applied"] > 5
        seen = {}

        def snapshot():  # the setpoints in force when the failing pair is being measured
            seen["feed"] = plant.machine.register_values()["feed_setpoint_mm_s"]
            seen["offsets"] = list(plant.amp.core.offsets_um)
            seen["service"] = (svc.feed_setpoint_mm_s, svc.offsets_um)
            seen["sent"] = plant.piezo.sent

        measurer.fail_with = exc
        measurer.before_failure = snapshot
        failed = []
        while not failed:
            failed = await plant.step()
        r = failed[0]
        assert not r.ok and r.error.startswith(reason) and not r.applied
        assert plant.machine.register_values()["feed_setpoint_mm_s"] == seen["feed"]
        assert list(plant.amp.core.offsets_um) == seen["offsets"]
        assert (svc.feed_setpoint_mm_s, svc.offsets_um) == seen["service"]
        assert plant.piezo.sent == seen["sent"]  # not a single frame went out for it
        last = plant.log.records()[-1]
        assert not last.ok and last.error.startswith(reason) and last.pitch_mm is None
        assert last.passed is None and last.seq == r.seq
        assert last.feed_setpoint_mm_s == pytest.approx(seen["service"][0])
        await plant.close()

    asyncio.run(main())


def _event_times(svc, kind):
    return [e.t_s for e in svc.events if e.kind is kind]


@pytest.mark.parametrize("transport", ["direct", "tcp"])
def test_plc_gone_safe_within_timeout_then_recovers(tmp_path, transport):
    async def main():
        plant, _ = make_plant(tmp_path, plc_transport=transport)
        await plant.start()
        await run_for(plant, 3.0)
        svc = plant.service
        cfg = plant.cfg.safety
        assert svc.state is SafetyState.RUN
        n_before = len(svc.results)
        t_down = plant.clock()
        await plant.plc_down(1.5)
        await run_for(plant, 1.5)
        safe = [t for t in _event_times(svc, EventKind.SAFE_STATE) if t >= t_down]
        assert safe and cfg.plc_timeout_s <= safe[0] - t_down <= cfg.plc_timeout_s + 2 * cfg.cycle_s
        assert "plc" in [e.text for e in svc.events if e.t_s == safe[0]][0]
        # offsets went to zero and the amplifier was disabled while the PLC was gone
        assert all(v == 0.0 for v in plant.amp.core.offsets_um)
        assert plant.amp.core.last_command["enable"] == 0
        t_up = plant.clock()
        await run_for(plant, 3.0)
        rec = [t for t in _event_times(svc, EventKind.RECOVERED) if t > t_up]
        bound = cfg.recovery_s + plant.cfg.plc.backoff_max_s + 2 * cfg.cycle_s
        assert rec and rec[0] - t_up <= bound
        assert svc.state is SafetyState.RUN
        after = [r for r in svc.results[n_before:] if r.t_s > rec[0]]
        assert after and any(r.applied for r in after)
        assert np.abs(plant.amp.core.offsets_um).max() > 0.5  # learnt offsets restored
        assert plant.plc.reconnects >= 2
        await plant.close()
        with QualityLog(tmp_path / "q.sqlite", create=False) as log:
            assert [r.seq for r in log.records()] == [r.seq for r in svc.results]

    asyncio.run(main())


def test_can_silent_sends_zero_offsets_then_recovers(tmp_path):
    async def main():
        plant, _ = make_plant(tmp_path)
        await plant.start()
        await run_for(plant, 3.0)
        svc = plant.service
        cfg = plant.cfg.safety
        learnt = np.asarray(svc.offsets_um)
        assert np.abs(learnt).max() > 0.5
        t0 = plant.clock()
        plant.can_fault("can_silence", 1.0)
        await run_for(plant, 0.9)
        safe = [t for t in _event_times(svc, EventKind.SAFE_STATE) if t >= t0]
        assert safe and cfg.can_timeout_s <= safe[0] - t0 <= cfg.can_timeout_s + 2 * cfg.cycle_s
        assert "can" in [e.text for e in svc.events if e.t_s == safe[0]][0]
        assert svc.offsets_um == (0.0,) * len(learnt)
        assert all(v == 0.0 for v in plant.amp.core.offsets_um)  # the amplifier got the zeros
        assert plant.amp.core.last_command["enable"] == 0
        in_safe = [r for r in svc.results if r.t_s > safe[0]]
        assert in_safe and all(not r.applied and r.state == "safe" for r in in_safe)
        await run_for(plant, 1.5)
        assert svc.state is SafetyState.RUN
        assert np.allclose(plant.amp.core.offsets_um[: len(learnt)], svc.offsets_um, atol=1e-3)
        assert np.abs(svc.offsets_um).max() > 0.5
        await plant.close()

    asyncio.run(main())


def test_measurements_gone_ramps_feed_down_then_recovers(tmp_path):
    async def main():
        plant, measurer = make_plant(tmp_path, measurement_timeout_s=1.0, ramp_mm_s2=200.0)
        await plant.start()
        await run_for(plant, 3.0)
        svc = plant.service
        cfg = plant.cfg.safety
        feed0 = plant.machine.register_values()["feed_setpoint_mm_s"]
        measurer.fail_with = RegistrationError("no texture")
        t0 = plant.clock()
        feeds = []
        end = t0 + 2.5
        while plant.clock() < end:
            await plant.step()
            feeds.append((plant.clock(), plant.machine.register_values()["feed_setpoint_mm_s"]))
        safe = [t for t in _event_times(svc, EventKind.SAFE_STATE) if t >= t0]
        assert safe and safe[0] - t0 <= cfg.measurement_timeout_s + 0.2
        # ramped down after entering the safe state, never faster than the configured rate
        after = [(t, f) for t, f in feeds if t > safe[0]]
        assert after[-1][1] < feed0 - 50
        pairs = zip(after[:-1], after[1:], strict=True)
        rates = [(f0 - f1) / (t1 - t0_) for (t0_, f0), (t1, f1) in pairs]
        assert max(rates) <= cfg.ramp_mm_s2 * 1.01
        assert min(f for _, f in after) >= cfg.safe_feed_mm_s - 1e-6
        measurer.fail_with = None
        await run_for(plant, 2.0)
        assert svc.state is SafetyState.RUN
        assert svc.results[-1].applied
        await plant.close()

    asyncio.run(main())


def test_log_that_never_works_keeps_the_machine_safe_and_the_records(tmp_path):
    """No control without a record of it: a dead log holds the service in the safe state."""

    class BrokenLog:
        path = tmp_path / "broken.sqlite"

        def __init__(self):
            self.calls = 0

        def append(self, record):
            self.calls += 1
            raise OSError("disk full")

        def set_quality_class(self, qc):
            pass

        last_id = 0

        def close(self):
            pass

    async def main():
        log = BrokenLog()
        plant, _ = make_plant(tmp_path, log=log)
        await plant.start()
        res = await run_for(plant, 2.0)
        svc = plant.service
        assert res and all(r.record_id is None for r in res)
        # every record the log did not take is counted; the log is tried again for each pair
        assert svc.counters["log_errors"] == len(res) and log.calls >= len(res)
        assert len([e for e in svc.events if e.kind is EventKind.LOG_FAILED]) == 1
        assert svc.state is SafetyState.SAFE and not any(r.applied for r in res[1:])
        status = svc.status()
        assert "log" in status.missing and "quality log" in status.safe_reason
        assert status.log_problem and status.records_pending == len(res)
        await plant.close()
        # what the log never took was kept in the journal beside it, every pair once, in order
        (saved,) = tmp_path.glob("broken.sqlite.journal*")
        seqs = [json.loads(line)["record"]["seq"] for line in saved.read_text().splitlines()]
        assert seqs == [r.seq for r in res]
        assert any(e.kind is EventKind.RECORDS_SAVED and str(saved) in e.text
                   for e in svc.events)

    asyncio.run(main())
