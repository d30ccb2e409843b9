"""The service's small parts on their own: service clock, frame intake, measurement failures."""

from __future__ import annotations

import asyncio
import math
from itertools import pairwise
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.service.clock import ServiceClock
from controller.service.events import EventKind, EventLog
from controller.service.intake import FrameIntake, frame_metadata
from controller.service.measurement import VISION_ERRORS, MeasurementStage, failure_reason
from core.errors import MeasurementError, RegistrationError


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=40))
def test_service_time_never_goes_back_and_follows_the_clock_forward(raw):
    report = EventLog()
    clock = ServiceClock(lambda: 0.0, report)
    out = [clock.now(t) for t in raw]
    assert all(b >= a for a, b in pairwise(out))
    # each forward step of the raw clock is a forward step of the same size
    for (r0, r1), (t0, t1) in zip(pairwise(raw), pairwise(out), strict=True):
        if r1 >= r0:
            assert t1 - t0 == pytest.approx(r1 - r0, abs=1e-6)
    backs = sum(1 for a, b in pairwise(raw) if b < a)
    jumps = [e for e in report.events if e.kind is EventKind.CLOCK_WENT_BACK]
    assert len(jumps) <= backs  # reported, at most once per jump back


def test_service_clock_refuses_a_time_that_is_not_finite():
    clock = ServiceClock(lambda: math.nan, EventLog())
    with pytest.raises(ValueError, match="now_s"):
        clock.now()
    with pytest.raises(ValueError, match="now_s"):
        clock.now(math.inf)


def _frame(seq, t_s, **kw):
    return SimpleNamespace(seq=seq, t_s=t_s, board_id=kw.get("board_id", 1),
                           board_position_mm=kw.get("board_position_mm", 10.0))


@pytest.mark.parametrize(
    ("seqs", "missed"),
    [([1, 2, 3], 0), ([1, 4], 2), ([5, 3, 4], 0), ([1, 2, 10, 11, 20], 15), (["x", 2, 3], 0)],
)
def test_intake_counts_pairs_that_never_arrived(seqs, missed):
    report = EventLog()
    intake = FrameIntake(report)
    for i, s in enumerate(seqs):
        intake.arrive(_frame(s, 0.1 * i), 1.0 + 0.1 * i)
    assert report.counters["missed"] == missed
    gaps = [e for e in report.events if e.kind is EventKind.PAIRS_MISSED]
    assert sum(int(e.text.split()[0]) for e in gaps) == missed


def test_intake_maps_the_camera_clock_by_the_smallest_delay_and_restarts_after_a_jump_back():
    report = EventLog()
    intake = FrameIntake(report)
    delays = [0.05, 0.02, 0.08]
    taken = [intake.arrive(_frame(i, 10.0 + i), 110.0 + i + d) for i, d in enumerate(delays)]
    # service time of trigger A = machine time + the smallest delay seen so far, never later
    # than the arrival
    assert taken[0] == pytest.approx(110.05)
    assert taken[1] == pytest.approx(111.02)
    assert taken[2] == pytest.approx(112.02)
    t = intake.arrive(_frame(3, 0.5), 113.5)  # the camera restarted its clock
    assert t == pytest.approx(113.5)
    assert [e.kind for e in report.events] == [EventKind.CAMERA_CLOCK_WENT_BACK]
    assert intake.arrive(_frame(4, math.nan), 114.0) == 114.0  # no machine time: arrival


@pytest.mark.parametrize(
    ("field", "value"),
    [("t_s", math.nan), ("seq", -1), ("board_id", "b"), ("board_position_mm", math.inf),
     ("seq", None)],
)
def test_frame_metadata_replaces_an_odd_field_and_names_it(field, value):
    f = _frame(3, 1.5)
    setattr(f, field, value)
    meta, odd = frame_metadata(f)
    assert set(odd) == {field} and odd[field] == repr(value)
    assert meta[field] == 0
    good = {"t_s": 1.5, "seq": 3, "board_id": 1, "board_position_mm": 10.0}
    assert {k: v for k, v in meta.items() if k != field} == {
        k: v for k, v in good.items() if k != field}


@pytest.mark.parametrize(
    ("exc", "start"),
    [
        (RegistrationError("confidence 0.1"), "registration failed: confidence 0.1"),
        (MeasurementError("saturated pair"), "measurement failed: saturated pair"),
        (IndexError("index 9"), "measurement failed: IndexError: index 9"),
        (cv2.error("bad"), "measurement failed: cv2.error: bad"),
        (MemoryError(), "measurement failed: MemoryError"),
    ],
)
def test_every_vision_error_is_a_failed_measurement_with_its_reason(exc, start):
    assert isinstance(exc, VISION_ERRORS)
    assert failure_reason(exc).startswith(start)

    class Raising:
        def measure(self, a, b, **kw):
            raise exc

    stage = MeasurementStage(None, lambda shape: Raising(), threaded=False)
    frame = SimpleNamespace(image_a=np.zeros((4, 6)), image_b=np.zeros((4, 6)), counts_a=1,
                            counts_b=2, speed_mm_s=600.0)
    error, meas = asyncio.run(stage.measure(frame))
    assert meas is None and error == failure_reason(exc)


def test_the_measurer_is_built_once_per_shape_and_replaced_with_the_factory():
    built = []
    stage = MeasurementStage(None, lambda shape: built.append(shape) or shape, threaded=False)
    assert stage.measurer((4, 6)) == (4, 6) and stage.measurer((4, 6)) == (4, 6)
    assert stage.measurer((8, 6)) == (8, 6) and built == [(4, 6), (8, 6)]
    stage.set_factory(lambda shape: ("new", shape))
    assert stage.measurer((4, 6)) == ("new", (4, 6))
