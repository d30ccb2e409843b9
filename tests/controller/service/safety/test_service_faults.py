"""The service under faults of its own and garbage from its world, on simulated time.

Each test closes the loop with the in-process simulator
(``tests/controller/service/test_service_loop.py``'s
plant: the measurer reads the simulator's truth), brings the service to RUN, then breaks one
thing: the vision raises an unexpected exception type, the PLC answers nonsense or refuses
reads, the clock jumps back, the camera's clock restarts, the control code or the tick raises,
the quality log fails. The service must never raise out of ``tick``/``handle_frame``, must keep
the heartbeats going, must put the machine in the safe state (offsets 0, amplifier disabled,
no feed outside the limits) and must recover by itself; every pair gets exactly one record.
"""

from __future__ import annotations

import asyncio
import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from controller.quality.log import QualityLog
from controller.service.events import EventKind
from controller.service.supervisor import SafetyState
from protocol.frames import Frame
from protocol.spool import SpoolReader, SpoolWriter
from tests.controller.service.test_service_loop import SCENARIO, TruthMeasurer, make_plant
from tests.support.plant_support import run_for


def _events(svc, since, kind):
    """(t, text) of the service's events of ``kind`` (None: every kind) since ``since``."""
    return [(e.t_s, e.text) for e in svc.events
            if e.t_s >= since and (kind is None or e.kind is kind)]


def _amp_safe(plant) -> bool:
    core = plant.amp.core
    return all(v == 0.0 for v in core.offsets_um) and core.last_command["enable"] == 0


async def _running_plant(tmp_path, seconds=3.0, **kw):
    plant, measurer = make_plant(tmp_path, **kw)
    await plant.start()
    await run_for(plant, seconds)
    assert plant.service.state is SafetyState.RUN
    assert np.abs(plant.service.offsets_um).max() > 0.5  # learnt offsets to protect
    return plant, measurer


def _records(tmp_path):
    with QualityLog(tmp_path / "q.sqlite", create=False) as log:
        return log.records()


async def _close_and_check_log(plant, tmp_path):
    """Close the plant; the quality log holds every pair the service handled, once, in order."""
    await plant.close()
    recs = _records(tmp_path)
    assert [r.seq for r in recs] == [r.seq for r in plant.service.results]
    return recs


# ------------------------------------------------------------------ the vision raises anything
@pytest.mark.parametrize(
    "exc",
    [
        IndexError("index 700 is out of bounds for axis 1 with size 659"),
        FloatingPointError("overflow encountered in multiply"),
        ZeroDivisionError("float division by zero"),
        KeyError("profile"),
        RuntimeError("worker died"),
        cv2.error("OpenCV(5.0) error: (-215:Assertion failed) !_src.empty()"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_unexpected_vision_exception_is_a_logged_failure(tmp_path, exc):
    async def main():
        plant, measurer = await _running_plant(tmp_path)
        svc = plant.service
        correction = svc.feed_loop.correction
        offsets = list(plant.amp.core.offsets_um)
        measurer.fail_with = exc
        failed = []
        while len(failed) < 3:
            failed += await plant.step()  # must not raise
        assert all(not r.ok and not r.applied for r in failed)
        name = "cv2.error" if isinstance(exc, cv2.error) else type(exc).__name__
        assert all(name in r.error for r in failed)
        # nothing learnt from them: the correction and the offsets stayed
        assert svc.feed_loop.correction == correction
        assert list(plant.amp.core.offsets_um) == offsets
        measurer.fail_with = None
        await run_for(plant, 0.5)
        assert svc.state is SafetyState.RUN
        recs = await _close_and_check_log(plant, tmp_path)
        bad = [r for r in recs if r.seq in {f.seq for f in failed}]
        assert len(bad) == 3 and all(not r.ok and name in r.error for r in bad)

    asyncio.run(main())


class VisionBug(Exception):
    """An exception type nobody names: not in ``VISION_ERRORS``."""


def test_vision_exception_of_an_unknown_kind_is_a_failed_pair_and_a_service_fault(tmp_path):
    async def main():
        plant, measurer = await _running_plant(tmp_path)
        svc = plant.service
        t0 = plant.clock()
        measurer.fail_with = VisionBug("nobody expected this")
        failed = []
        while not failed:
            failed += await plant.step()  # must not raise
        assert not failed[0].ok and not failed[0].applied
        assert "VisionBug" in failed[0].error and "measurement failed" in failed[0].error
        errors = _events(svc, t0, EventKind.SERVICE_ERROR)
        assert errors and "VisionBug" in errors[0][1]
        assert svc.state is SafetyState.SAFE
        await run_for(plant, 0.1)  # the amplifier got the safe commands
        assert _amp_safe(plant)
        measurer.fail_with = None
        await run_for(plant, 1.5)
        assert svc.state is SafetyState.RUN
        recs = await _close_and_check_log(plant, tmp_path)
        bad = [r for r in recs if r.seq == failed[0].seq]
        assert len(bad) == 1 and not bad[0].ok and "VisionBug" in bad[0].error

    asyncio.run(main())


# ------------------------------------------------------------------ the PLC answers garbage
NAN = [0x7FC0, 0x0000]
INF = [0x7F80, 0x0000]


def _corrupt_reads(plant, garbage):
    """Make every PLC read answer ``garbage``: register name -> value, or raw words (a list)."""
    bus = plant.direct_bus
    orig = bus.read
    regmap = plant.regmap

    async def read(address, count):
        words = await orig(address, count)
        for name, v in garbage.items():
            reg = regmap[name]
            i = reg.address - address
            words[i : i + reg.count] = v if isinstance(v, list) else regmap.encode(name, v)
        return words

    bus.read = read
    return lambda: setattr(bus, "read", orig)


GARBAGE = {
    "knives_0": {"knives": 0},
    "knives_9": {"knives": 9},
    "rpm_nan": {"spindle_rpm": NAN},
    "rpm_inf": {"spindle_rpm": INF},
    "counts_per_mm_0": {"counts_per_mm": 0.0},
    "limits_inverted": {"feed_min_mm_s": 1000.0, "feed_max_mm_s": 50.0},
    "feed_max_nan": {"feed_max_mm_s": NAN},
    "feed_setpoint_nan": {"feed_setpoint_mm_s": NAN},
    "cutter_to_camera_0": {"cutter_to_camera_mm": 0.0},
    "radius_negative": {"cutterhead_radius_mm": -5.0},
}


@pytest.mark.parametrize("case", sorted(GARBAGE))
def test_plc_garbage_goes_safe_writes_nothing_and_recovers(tmp_path, case):
    async def main():
        plant, _ = await _running_plant(tmp_path)
        svc = plant.service
        cfg = plant.cfg.safety
        feed0 = plant.machine.register_values()["feed_setpoint_mm_s"]
        refused0 = svc.counters["setpoint_refused"]
        restore = _corrupt_reads(plant, GARBAGE[case])
        t0 = plant.clock()
        hb0 = plant.machine.heartbeat_service
        res = await run_for(plant, 1.0)  # no exception out of tick / handle_frame
        safe = _events(svc, t0, EventKind.SAFE_STATE)
        assert safe and safe[0][0] - t0 <= 2 * cfg.cycle_s + 1e-9
        assert "plc data" in safe[0][1]
        assert svc.state is SafetyState.SAFE and _amp_safe(plant)
        # nothing was written to the feed while the PLC's data made no sense
        assert plant.machine.register_values()["feed_setpoint_mm_s"] == feed0
        assert svc.counters["setpoint_refused"] == refused0
        assert plant.machine.heartbeat_service != hb0  # the heartbeat went on
        assert res and all(not r.applied for r in res)
        restore()
        t1 = plant.clock()
        await run_for(plant, 1.0)
        rec = _events(svc, t1, EventKind.RECOVERED)
        assert rec and rec[0][0] - t1 <= cfg.recovery_s + 3 * cfg.cycle_s
        assert np.abs(plant.amp.core.offsets_um).max() > 0.5  # learnt offsets restored
        await _close_and_check_log(plant, tmp_path)

    asyncio.run(main())


def test_plc_refusing_reads_is_a_plc_gone(tmp_path):
    """A PLC that answers heartbeat writes but refuses every read is not a working PLC."""
    from protocol.register_bus import BusRefused

    async def main():
        plant, _ = await _running_plant(tmp_path)
        svc = plant.service
        cfg = plant.cfg.safety

        async def refuse(address, count):
            raise BusRefused(2, "read refused")

        orig = plant.direct_bus.read
        plant.direct_bus.read = refuse
        t0 = plant.clock()
        await run_for(plant, 1.0)
        safe = _events(svc, t0, EventKind.SAFE_STATE)
        assert safe and safe[0][0] - t0 <= cfg.plc_timeout_s + 2 * cfg.cycle_s
        assert "plc" in safe[0][1] and _amp_safe(plant)
        plant.direct_bus.read = orig
        await run_for(plant, 1.0)
        assert svc.state is SafetyState.RUN
        await plant.close()

    asyncio.run(main())


# ------------------------------------------------------------------ time
def test_service_clock_going_backwards_keeps_heartbeats_and_timeouts(tmp_path):
    async def main():
        plant, _ = await _running_plant(tmp_path)
        svc = plant.service
        t = plant.clock()
        sent = plant.piezo.sent
        hb = plant.machine.heartbeat_service
        for i in range(10):  # the clock jumped 5 s back and crawls on from there
            plant.amp.receive(plant.clock())
            plant.machine.advance(0.02)
            plant.amp.transmit(plant.clock())
            await svc.tick(t - 5.0 + 0.02 * i)
        # a command (RPDO3) every cycle (plus the periodic offsets), the PLC heartbeat moved
        assert plant.piezo.sent - sent >= 9
        assert plant.machine.heartbeat_service != hb
        assert svc.state is SafetyState.RUN
        # the CAN timeout still works on that clock
        plant.can_fault("can_silence", 1.0)
        t1 = t - 5.0 + 0.2
        for i in range(30):
            plant.machine.advance(0.02)
            await svc.tick(t1 + 0.02 * i)
        assert svc.state is SafetyState.SAFE and "can" in svc.status().missing
        await plant.close()

    asyncio.run(main())


def test_camera_clock_restart_does_not_stop_the_feed_loop_learning(tmp_path):
    async def main():
        plant, _ = await _running_plant(tmp_path)
        svc = plant.service
        handle = svc.handle_frame

        async def restarted_camera(frame, **kw):  # the camera's clock restarted from 0
            return await handle(replace(frame, t_s=frame.t_s - 1000.0), **kw)

        svc.handle_frame = restarted_camera
        statuses = []
        end = plant.clock() + 3.0
        while plant.clock() < end:
            if await plant.step():
                statuses.append(svc.feed_loop.status)
        assert statuses[-10:].count("accepted") >= 5, statuses
        await plant.close()

    asyncio.run(main())


# ------------------------------------------------------------------ the service's own faults
def test_control_exception_goes_safe_logs_the_pair_and_recovers(tmp_path):
    async def main():
        plant, _ = await _running_plant(tmp_path)
        svc = plant.service
        loop = svc.uniformity_loop
        orig = loop.update

        def broken(**kw):
            raise IndexError("bug in the control code")

        loop.update = broken
        t0 = plant.clock()
        res = []
        while not res:
            res = await plant.step()
        assert not res[0].applied
        await run_for(plant, 0.1)
        assert svc.state is SafetyState.SAFE and _amp_safe(plant)
        assert any("IndexError" in e for _, e in _events(svc, t0, None))
        loop.update = orig
        await run_for(plant, 1.5)
        assert svc.state is SafetyState.RUN
        await _close_and_check_log(plant, tmp_path)

    asyncio.run(main())


def test_tick_exception_keeps_heartbeat_goes_safe_and_recovers(tmp_path, caplog):
    async def main():
        plant, _ = await _running_plant(tmp_path)
        svc = plant.service

        async def broken(t, snap):
            raise FloatingPointError("overflow in the feed-forward")

        orig = svc.loops.feed_forward
        svc.loops.feed_forward = broken
        t0 = plant.clock()
        hb = plant.machine.heartbeat_service
        await run_for(plant, 0.2)  # must not raise
        assert plant.machine.heartbeat_service != hb
        assert svc.state is SafetyState.SAFE and _amp_safe(plant)
        errors = _events(svc, t0, EventKind.SERVICE_ERROR)
        assert len(errors) == 1 and "FloatingPointError" in errors[0][1]  # once, not per cycle
        # the supervisor boundary logged the traceback, once
        logged = [r for r in caplog.records
                  if r.name == "controller.service.service" and r.exc_info]
        assert len(logged) == 1 and logged[0].exc_info[0] is FloatingPointError
        svc.loops.feed_forward = orig
        await run_for(plant, 1.0)
        assert svc.state is SafetyState.RUN
        await plant.close()

    asyncio.run(main())


def test_close_leaves_the_amplifier_disabled_with_zero_offsets(tmp_path):
    async def main():
        plant, _ = await _running_plant(tmp_path)
        assert np.abs(plant.amp.core.offsets_um).max() > 0.5
        plant.service.close()
        plant.amp.receive(plant.clock())
        assert _amp_safe(plant)
        plant.service = None
        plant.svc_bus = type("Closed", (), {"shutdown": lambda self: None})()
        plant.log = None
        await plant.close()

    asyncio.run(main())


# ------------------------------------------------------------------ the quality log
class FlakyLog:
    """A quality log whose appends fail while ``broken`` (disk full), else go to a real log."""

    def __init__(self, path):
        self.path = path
        self.log = QualityLog(path)
        self.broken = False
        self.calls = 0

    def append(self, record):
        self.calls += 1
        if self.broken:
            raise OSError(28, "No space left on device")
        return self.log.append(record)

    def set_quality_class(self, qc):
        self.log.set_quality_class(qc)

    @property
    def last_id(self):
        return self.log.last_id

    def close(self):
        self.log.close()


def test_log_failure_goes_safe_keeps_the_records_and_writes_them_later(tmp_path):
    async def main():
        log = FlakyLog(tmp_path / "q.sqlite")
        plant, _ = make_plant(tmp_path, log=log)
        await plant.start()
        await run_for(plant, 3.0)
        svc = plant.service
        assert svc.state is SafetyState.RUN
        log.broken = True
        t0 = plant.clock()
        during = await run_for(plant, 1.0)
        assert len(during) >= 5
        assert svc.state is SafetyState.SAFE and _amp_safe(plant)
        ev = _events(svc, t0, None)
        assert any("quality log" in e and "held" in e for _, e in ev), ev
        assert any(e.startswith("safe state") and "log" in e for _, e in ev), ev
        assert all(not r.applied for r in during[1:])
        log.broken = False
        after = await run_for(plant, 1.5)
        assert after and svc.state is SafetyState.RUN and any(r.applied for r in after)
        await _close_and_check_log(plant, tmp_path)  # none lost while the disk was full

    asyncio.run(main())


def test_records_unwritten_at_close_are_saved_beside_the_log(tmp_path):
    async def main():
        log = FlakyLog(tmp_path / "q.sqlite")
        plant, _ = make_plant(tmp_path, log=log)
        await plant.start()
        await run_for(plant, 2.0)
        log.broken = True
        during = await run_for(plant, 0.5)
        assert during
        await plant.close()
        saved = sorted(tmp_path.glob("q.sqlite.journal*"))
        assert len(saved) == 1
        lines = saved[0].read_text().splitlines()
        assert [json.loads(x)["record"]["seq"] for x in lines] == [r.seq for r in during]
        assert any("NOT in the quality log" in ev.text for ev in plant.service.events)

    asyncio.run(main())


def test_pair_with_unusable_metadata_is_still_logged(tmp_path):
    async def main():
        plant, _ = await _running_plant(tmp_path)
        svc = plant.service
        handle = svc.handle_frame

        async def odd_metadata(frame, **kw):
            return await handle(replace(frame, board_position_mm=math.nan, board_id=-1), **kw)

        svc.handle_frame = odd_metadata
        res = []
        while not res:
            res = await plant.step()
        svc.handle_frame = handle
        recs = await _close_and_check_log(plant, tmp_path)
        assert recs[-1].seq == res[0].seq

    asyncio.run(main())


# ------------------------------------------------------------------ unreadable pairs
def test_spool_pair_with_broken_image_is_delivered_as_unreadable(tmp_path):
    img = np.zeros((20, 40), np.uint8)
    w = SpoolWriter(tmp_path, keep=10, fsync=False)
    for seq in (1, 2, 3):
        w.write(Frame(seq=seq, t_s=seq * 0.1, image_a=img, image_b=img, counts_a=seq,
                      counts_b=seq + 1, speed_mm_s=600.0))
    (tmp_path / "pair-000000000000.a.png").write_bytes(b"not a png")
    meta = tmp_path / "pair-000000000001.json"
    doc = json.loads(meta.read_text())
    doc["seq"] = "three"  # a metadata file no reader can make a frame of
    meta.write_text(json.dumps(doc))
    r = SpoolReader(tmp_path, start="all")
    f0 = r.poll()
    assert f0.seq == 1 and f0.error and "image" in f0.error
    f2 = r.poll()  # the bad metadata is skipped (counted), not raised
    assert f2.seq == 3 and f2.error is None and r.skipped == 1
    assert r.poll() is None


def test_unreadable_pair_is_logged_as_failed(tmp_path):
    async def main():
        plant, measurer = await _running_plant(tmp_path)
        svc = plant.service
        calls = measurer.calls
        handle = svc.handle_frame

        async def unreadable(frame, **kw):
            return await handle(replace(frame, error="image_a: not a readable PNG"), **kw)

        svc.handle_frame = unreadable
        res = []
        while not res:
            res = await plant.step()
        svc.handle_frame = handle
        assert not res[0].ok and res[0].error.startswith("unreadable pair")
        assert measurer.calls == calls  # not measured
        await plant.close()
        assert not _records(tmp_path)[-1].ok

    asyncio.run(main())


# ------------------------------------------------------------------ geometry from the PLC
def test_uniformity_loop_takes_the_radius_from_the_plc(tmp_path):
    from config.machine import load_machine
    from config.sim import sim_from_dict
    from planer.hil import InProcessPlant, sim_document

    async def main():
        doc = sim_document(SCENARIO)
        doc["cutterhead"]["radius_mm"] = 80.0
        frames: dict = {}
        plant = InProcessPlant(load_machine(), sim_from_dict(doc), log=None, render_images=False,
                               measurer_factory=lambda shape: TruthMeasurer(frames))
        await plant.start()
        await run_for(plant, 0.2)
        assert plant.plc.last["cutterhead_radius_mm"] == 80.0
        assert plant.service.feed_loop.cfg.radius_mm == 80.0
        assert plant.service.uniformity_loop.cfg.radius_mm == 80.0
        await plant.close()

    asyncio.run(main())


def test_pairs_that_never_arrived_are_reported(tmp_path):
    async def main():
        plant, _ = await _running_plant(tmp_path)
        svc = plant.service
        handle = svc.handle_frame

        async def camera_skips(frame, **kw):  # the spool pruned two pairs the service never saw
            return await handle(replace(frame, seq=frame.seq + 2), **kw)

        svc.handle_frame = camera_skips
        t0 = plant.clock()
        res = []
        while not res:
            res = await plant.step()
        assert svc.counters["missed"] == 2
        assert any("2 sequence number(s) without a pair" in e and "jumped" in e
                   for _, e in _events(svc, t0, None))
        await _close_and_check_log(plant, tmp_path)

    asyncio.run(main())
