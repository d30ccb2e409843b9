"""Vanished marks: which knife left no mark, the kinematic CV, the pitch.

Synthetic measurement tables: the passes of a cutterhead over image A's field (the
mark-to-knife formula of docs/architecture.md), one or more knives whose marks another knife's
cut removed, and the marks a vision reports (cusps, widths, bottoms at the knives' BDCs). The
attribution must name the vanished knives, report the CV of the widths per knife and pass with
the vanished knife at 0 (closed form ``sqrt(1.5 / Z)`` for one knife whose pass the two
neighbours share evenly), and the pitch per knife pass ``V / (n Z)``, not the mean of the marks
found.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from config.machine import load_machine
from controller.service.attribution import (
    _vanished,
    attribute,
    attribute_or_reason,
    kinematic_cv,
)
from controller.service.events import EventLog
from controller.service.frame_result import FrameResult
from controller.service.records import QualityRecords
from protocol.frames import Frame

WRAP = 1 << 32
RPM = 6000.0


def marks_table(
    *, knives=4, vanished=(2,), pitch_mm=1.5, split=0.5, index=70_000, counts_per_mm=20.0,
    px_per_mm=12.5, width_px=640, cx_px=320.0, cutter_to_camera_mm=300.0, lead_counts=9,
):
    """The measurement, frame, registers and rig of a field where ``vanished`` left no mark.

    Pass j (knife ``j mod Z``, a later pass further upstream) has its BDC at image-A position
    ``x_j = (counts_a - index - j p cpm) / cpm - L + cx / ppm``. Consecutive visible BDCs share
    a cusp ``p / 2 + split * (gap - p)`` after the upstream one (``split = 0.5``: the middle),
    so a mark next to a vanished pass takes ``split`` (upstream) and ``1 - split`` (downstream)
    of it. Complete marks only (both cusps inside the image).
    """
    cpm = counts_per_mm
    counts_a = (index + round(cutter_to_camera_mm * cpm) + lead_counts) % WRAP
    j = np.arange(-80, 81)
    x = (counts_a - index - j * pitch_mm * cpm) / cpm - cutter_to_camera_mm + cx_px / px_per_mm
    visible = ~np.isin(np.mod(j, knives), vanished)
    order = np.argsort(x)
    xv, jv = x[order][visible[order]], j[order][visible[order]]
    gaps = np.diff(xv)
    cusps = xv[:-1] + 0.5 * pitch_mm + split * (gaps - pitch_mm)
    field = (cusps >= 0.0) & (cusps <= width_px / px_per_mm)
    first, last = np.flatnonzero(field)[[0, -1]]
    cusps = cusps[first:last + 1]
    bottoms = xv[first + 1:last + 1]
    widths = np.diff(cusps)
    meas = SimpleNamespace(
        bottoms_mm=bottoms, cusps_mm=cusps, mark_widths_mm=widths,
        pitch_mm=float(widths.mean()), uniformity_cv=float(widths.std() / widths.mean()),
        depth_um=10.0,
    )
    speed = pitch_mm * RPM / 60.0 * knives  # V = p n Z: the feed per pass is pitch_mm
    frame = SimpleNamespace(counts_a=counts_a, index_latch_counts=index, speed_mm_s=speed)
    snap = SimpleNamespace(
        knives=knives, spindle_rpm=RPM, cutter_to_camera_mm=cutter_to_camera_mm,
        counts_per_mm=cpm, feed_actual_mm_s=speed,
    )
    rig = SimpleNamespace(camera=SimpleNamespace(px_per_mm=px_per_mm, cx=cx_px),
                          encoder=SimpleNamespace(counter_bits=32))
    return meas, frame, snap, rig, np.mod(jv[first + 1:last + 1], knives)


@pytest.mark.parametrize("knives", [3, 4, 5, 6])
def test_one_vanished_knife_is_named_and_its_cv_is_the_closed_form(knives):
    for gone in range(knives):
        meas, frame, snap, rig, mark_knife = marks_table(knives=knives, vanished=(gone,))
        att = attribute(meas, frame, snap, rig)
        assert att.vanished_knives == (gone,)
        assert att.mark_knife == tuple(int(k) for k in mark_knife)
        assert att.knife_widths_mm[gone] == 0.0  # what the loop gets: width 0, not unknown
        expect = np.full(knives, 1.5)
        expect[gone] = 0.0
        expect[(gone + 1) % knives] = expect[(gone - 1) % knives] = 2.25  # 1.5 p each
        assert np.allclose(att.knife_widths_mm, expect, atol=1e-9)
        assert att.kinematic_cv == pytest.approx(math.sqrt(1.5 / knives), rel=1e-9)
        assert att.uniformity_cv == att.kinematic_cv  # reported instead of the marks' CV
        assert att.marks_cv == pytest.approx(meas.uniformity_cv)
        assert att.kinematic_cv > att.marks_cv  # the marks found understate it


@pytest.mark.parametrize("split", [0.1, 0.3, 0.7, 0.9])
def test_uneven_share_of_the_vanished_pass(split):
    meas, frame, snap, rig, _ = marks_table(knives=4, vanished=(1,), split=split)
    att = attribute(meas, frame, snap, rig)
    p = 1.5
    # the upstream neighbour (knife 2, a later pass) takes split of the missing pass
    expect = np.array([(2.0 - split) * p, 0.0, (1.0 + split) * p, p])
    assert np.allclose(att.knife_widths_mm, expect, atol=1e-9)
    assert att.kinematic_cv == pytest.approx(expect.std() / expect.mean(), rel=1e-9)
    assert att.vanished_knives == (1,)


def test_two_opposite_knives_vanished_one_mark_per_half_revolution():
    meas, frame, snap, rig, _ = marks_table(knives=4, vanished=(0, 2))
    att = attribute(meas, frame, snap, rig)
    assert att.vanished_knives == (0, 2)
    assert np.allclose(att.knife_widths_mm, [0.0, 3.0, 0.0, 3.0])
    assert att.kinematic_cv == pytest.approx(1.0)
    assert meas.pitch_mm == pytest.approx(3.0)  # the mean of the marks found: 2 passes


@pytest.mark.parametrize(("knives", "vanished"), [(4, (2,)), (4, (0, 2)), (6, (1, 4)), (3, (0,))])
def test_pitch_is_the_feed_per_pass_not_the_mean_mark_width(knives, vanished):
    meas, frame, snap, rig, _ = marks_table(knives=knives, vanished=vanished, pitch_mm=0.98)
    feed_per_pass = frame.speed_mm_s / (snap.spindle_rpm / 60.0 * snap.knives)
    att = attribute(meas, frame, snap, rig)
    assert att.feed_per_pass_mm == pytest.approx(feed_per_pass)
    assert att.pitch_mm == pytest.approx(feed_per_pass, rel=1e-9)  # BDCs: exact
    assert att.bdc_pitch_mm == att.pitch_mm == att.pass_pitch_mm  # the loops get the same
    ratio = knives / (knives - len(vanished))
    assert meas.pitch_mm == pytest.approx(ratio * 0.98, rel=0.05)  # what was logged before
    assert att.missing_passes > 0 and not att.complete


def test_pitch_is_that_of_the_cut_when_the_feed_changed_since():
    # the marks were cut at 1.25 mm per pass (L / V earlier); the feed is 20 % up by now
    meas, frame, snap, rig, _ = marks_table(knives=4, vanished=(2,), pitch_mm=1.25)
    frame.speed_mm_s = snap.feed_actual_mm_s = 1.2 * frame.speed_mm_s
    att = attribute(meas, frame, snap, rig)
    assert att.feed_per_pass_mm == pytest.approx(1.5)
    assert att.pitch_mm == pytest.approx(1.25, rel=1e-9)
    assert att.vanished_knives == (2,)
    assert att.kinematic_cv == pytest.approx(math.sqrt(1.5 / 4), rel=1e-9)


def test_without_a_vanished_knife_the_measurement_is_reported_as_it_is():
    meas, frame, snap, rig, _ = marks_table(knives=4, vanished=())
    meas.pitch_mm, meas.uniformity_cv = 1.503, 0.0123  # the vision's own numbers
    att = attribute(meas, frame, snap, rig)
    assert att.complete and att.vanished_knives == ()
    assert att.pitch_mm == 1.503 and att.marks_cv == 0.0123
    # the CV reported: that of the widths as the knives cut them (all 1.5 mm here)
    assert att.uniformity_cv == att.knife_cv == pytest.approx(0.0, abs=1e-9)
    assert att.to_json()["marks_cv"] == 0.0123
    assert np.allclose(att.knife_widths_mm, 1.5)
    assert att.kinematic_cv == pytest.approx(0.0, abs=1e-9)


def test_record_carries_the_vanished_knife_and_the_kinematic_numbers():
    meas, frame, snap, rig, _ = marks_table(knives=4, vanished=(3,))
    att = attribute(meas, frame, snap, rig)
    result = FrameResult(
        seq=7, ok=True, error=None, measurement=meas,
        knife_widths_mm=tuple(float(w) for w in att.knife_widths_mm), applied=True,
        feed_setpoint_mm_s=600.0, offsets_um=(0.0,) * 4, state="run", t_s=1.0,
        latency_s=0.01, extra={"passes": att.to_json()},
    )
    assert result.vanished_knives == (3,)
    assert result.reported_uniformity_cv == pytest.approx(math.sqrt(1.5 / 4))
    assert result.reported_pitch_mm == pytest.approx(1.5)
    records = QualityRecords(load_machine(), None, EventLog(), on_health=lambda ok: None,
                             threaded=False)
    img = np.zeros((4, 4))
    rec = records.record_of(result, Frame(seq=7, t_s=1.0, image_a=img, image_b=img,
                                          counts_a=frame.counts_a, counts_b=frame.counts_a + 24,
                                          speed_mm_s=frame.speed_mm_s, board_id=1))
    assert rec.pitch_mm == pytest.approx(1.5) and rec.uniformity_cv == pytest.approx(0.6124, 1e-3)
    assert rec.mark_widths_mm[3] == 0.0
    assert rec.extra["passes"]["vanished_knives"] == [3]
    assert rec.passed is False  # a field with a knife missing fails the class
    # beside the truth's kinematic numbers (like with like), not the marks the truth has
    truth = {"pitch_mm": 2.0, "uniformity_cv": 0.24, "pass_pitch_mm": 1.5, "kinematic_cv": 0.61}
    rec = records.record_of(result, Frame(seq=7, t_s=1.0, image_a=img, image_b=img,
                                          counts_a=frame.counts_a, counts_b=frame.counts_a + 24,
                                          speed_mm_s=frame.speed_mm_s, board_id=1, truth=truth))
    assert (rec.true_pitch_mm, rec.true_uniformity_cv) == (1.5, 0.61)
    failed = FrameResult(seq=8, ok=False, error="measurement failed: x", measurement=None,
                         knife_widths_mm=(), applied=False, feed_setpoint_mm_s=None,
                         offsets_um=(), state="run", t_s=1.1, latency_s=0.0)
    assert failed.vanished_knives == () and failed.reported_pitch_mm is None


# ------------------------------------------------------------------------------ the formulas
@pytest.mark.parametrize(
    ("widths", "expect"),
    [
        ([1.5, 1.5, 1.5, 1.5], 0.0),
        ([0.0, 2.0, 2.0, 2.0], 1 / math.sqrt(3)),  # one of Z vanished, others equal
        ([0.0, 3.0, 0.0, 3.0], 1.0),
        ([1.0, math.nan, 2.0], 1 / 3),  # a knife without a pass is left out
    ],
)
def test_kinematic_cv_formula(widths, expect):
    assert kinematic_cv(widths) == pytest.approx(expect)


@pytest.mark.parametrize("bad", [[1.0, -0.1, 1.0], [1.0, math.inf], [[1.0, 2.0]]])
def test_kinematic_cv_rejects_bad_widths(bad):
    with pytest.raises(ValueError, match="knife_widths_mm"):
        kinematic_cv(bad)


def test_kinematic_cv_of_nothing_is_nan():
    assert math.isnan(kinematic_cv([math.nan, math.nan]))
    assert math.isnan(kinematic_cv([0.0, 0.0]))


@pytest.mark.parametrize(
    ("per_knife", "marks", "expect"),
    [
        ([3, 3, 3, 3], [0, 1, 2, 3, 0, 1, 2, 3], ()),
        ([3, 3, 3, 3], [0, 1, 3, 0, 1, 3], (2,)),
        ([2, 2, 1, 1], [1, 3], (0, 2)),
        ([2, 2, 0, 1], [0, 1], (3,)),  # knife 2 had no pass: not vanished, just not there
    ],
)
def test_vanished_knives_table(per_knife, marks, expect):
    assert _vanished(per_knife, marks) == expect


def test_bad_measurements_are_a_reason_not_a_crash():
    meas, frame, snap, rig, _ = marks_table()
    meas.bottoms_mm = meas.bottoms_mm[:-1]
    att, why = attribute_or_reason(meas, frame, snap, rig)
    assert att is None and why.startswith("knife phase failed:") and "widths" in why
    meas, frame, snap, rig, _ = marks_table()
    del meas.pitch_mm
    att, why = attribute_or_reason(meas, frame, snap, rig)
    assert att is None and "AttributeError" in why
