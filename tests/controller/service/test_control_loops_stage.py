"""The loops stage around the uniformity loop: the stroke at run time, a table not sent."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import numpy as np
import pytest

from config.machine import machine_from_dict
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.service.events import EventLog
from controller.service.loops import ControlLoops
from core.errors import FieldbusError


class FakeActuators:
    """Records what went out; refuses offsets while ``fail`` is set."""

    def __init__(self, owns_feed=True):
        self.owns_feed = owns_feed
        self.fail = False
        self.sent = []
        self.offsets_um = ()
        self.feed_setpoint_mm_s = None
        self.piezo = SimpleNamespace(knives=4)

    def set_knives(self, knives):
        self.piezo.knives = knives

    def set_offsets(self, offsets_um, t):
        if self.fail:
            raise FieldbusError("bus refused the frame")
        self.offsets_um = tuple(float(v) for v in offsets_um)
        self.sent.append((t, self.offsets_um))
        return self.offsets_um

    async def write_feed(self, feed_mm_s, t):
        self.feed_setpoint_mm_s = feed_mm_s
        return True


def _snap(**values):
    return PlcSnapshot(values={
        "knives": 4, "feed_min_mm_s": 50.0, "feed_max_mm_s": 1000.0, "spindle_rpm": 6000.0,
        "cutterhead_radius_mm": 60.0, "cutter_to_camera_mm": 300.0, "feed_setpoint_mm_s": 600.0,
        "feed_actual_mm_s": 600.0,
    } | values, t_s=0.0)


def _stage(owns_feed=True):
    cfg = machine_from_dict({"piezo": {"stroke_um": 20.0}})  # machine.toml says 20 um
    rig = SimpleNamespace(camera=SimpleNamespace(cx=320.0, px_per_mm=16.0))
    amp = SimpleNamespace(untracked_s=None)
    report = EventLog()
    return ControlLoops(cfg, rig, FakeActuators(owns_feed), report, amp, pairs_per_s=10.0)


RUNOUT = np.array([0.5, 15.0, -8.5, 5.0])


def _widths(offsets):
    from controller.laws.uniformity_loop import linear_widths_mm

    w = linear_widths_mm(np.asarray(offsets) - RUNOUT, pitch_mm=1.5, radius_mm=60.0)
    return np.where(w > 0, w, np.nan)


def test_the_amplifier_s_stroke_holds_for_loops_built_later_and_replans_the_table():
    stage = _stage()
    assert stage.set_limit_um(10.0, 0.0) is None  # before the first register read
    stage.ensure(_snap())
    uni = stage.uniformity_loop
    margin = uni.cfg.margin_um
    assert uni.stroke_um == 10.0 and uni.limit_um == pytest.approx(10.0 - margin)
    t = 0.0
    for _ in range(5):
        t += 1.0
        stage._learn_offsets(_widths(uni.offsets_um), 1.5, (t - 0.5, t - 0.45), t)
    assert max(abs(v) for v in stage.out.offsets_um) <= 10.0 - margin + 1e-9
    # the amplifier reports a smaller stroke still: the table is re-planned at once
    out = stage.set_limit_um(6.0, t + 0.01)
    assert np.max(np.abs(out)) <= 6.0 - margin + 1e-9 and abs(out.sum()) < 1e-9
    assert np.allclose(stage._learned_offsets, out)  # a recovery restores the re-planned table


def test_a_table_the_bus_refused_leaves_the_loop_s_history():
    stage = _stage()
    stage.ensure(_snap())
    uni = stage.uniformity_loop
    stage.out.fail = True
    assert not stage._learn_offsets(_widths(np.zeros(4)), 1.5, (0.5, 0.55), 1.0)
    assert np.array_equal(uni.offsets_um, np.zeros(4))  # the zero table stays in force
    assert stage._report.counters["can_errors"] == 1
    stage.out.fail = False
    assert stage._learn_offsets(_widths(np.zeros(4)), 1.5, (1.5, 1.55), 2.0)
    assert stage.out.sent and np.any(np.array(stage.out.sent[-1][1]) != 0.0)


def test_apply_passes_both_ends_of_the_cut_interval():
    stage = _stage()
    stage.ensure(_snap())
    seen = {}
    orig = stage.uniformity_loop.update

    def spy(**kw):
        seen.update(kw)
        return orig(**kw)

    stage.uniformity_loop.update = spy
    stage.feed_loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=0.0)  # a history
    stage.feed_loop.cut_interval_s = lambda measured_at: (measured_at - 0.6, measured_at - 0.5)
    att = SimpleNamespace(pass_pitch_mm=1.5, knife_widths_mm=_widths(np.zeros(4)),
                          bdc_pitch_mm=1.5)
    asyncio.run(stage.apply(att, 5.0, _snap(), 5.0))
    assert seen["cut_at_s"] == 4.4 and seen["cut_until_s"] == 4.5


@pytest.mark.parametrize(("ratio", "learns"), [(1.0, True), (1.15, True), (0.87, True),
                                               (0.5, False), (2.0, False), (0.75, False),
                                               (4 / 3, False)])
def test_a_pair_whose_passes_do_not_fit_the_cut_feed_does_not_teach_offsets(ratio, learns):
    """A fast feed change between the cut and the pair: the guide V/(nZ) counts two passes
    per gap, every other knife looks vanished, the fitted travel per pass is half the feed per
    pass of the cut; the uniformity loop must not learn from it."""
    stage = _stage()
    stage.ensure(_snap())
    calls = []
    orig = stage.uniformity_loop.update
    stage.uniformity_loop.update = lambda **kw: calls.append(kw) or orig(**kw)
    # 800 mm/s until 3.4 s, then 300 mm/s: the board at the camera (300 mm back) at 4.0 s was
    # cut at 800 mm/s, 2.0 mm per pass (6000 rpm, 4 knives); the guide at 4.0 s says 0.75
    for i in range(41):
        stage.board_speed.record(0.1 * i, 800.0 if i < 34 else 300.0, 400.0)
    assert stage.board_speed.pass_travel_mm(4.0, back_mm=300.0) == pytest.approx(2.0)
    widths = _widths(np.zeros(4))
    widths[1] = 0.0  # what the mistaken attribution reports
    att = SimpleNamespace(pass_pitch_mm=1.5, knife_widths_mm=widths, bdc_pitch_mm=ratio * 2.0,
                          feed_per_pass_mm=0.75)
    snap = _snap(feed_actual_mm_s=300.0)
    asyncio.run(stage.apply(att, 4.0, snap, 4.0))
    assert bool(calls) is learns
    assert stage._report.counters["uniformity_skipped"] == (0 if learns else 1)
    assert np.array_equal(stage.uniformity_loop.offsets_um == 0.0, np.full(4, not learns))


def test_a_head_that_owns_no_feed_applies_without_a_turn_of_the_loop():
    """A moulder's head (``owns_feed`` false): its feed is the coordinator's, so a pair's
    control writes none and goes on without a task or a turn of the event loop in between
    (what ran in that turn would delay the pair); it applies as before."""
    async def run(owns_feed):
        stage = _stage(owns_feed)
        calls = []
        write = stage.out.write_feed

        async def counted(feed_mm_s, t):
            calls.append(feed_mm_s)
            return await write(feed_mm_s, t)

        stage.out.write_feed = counted
        stage.ensure(_snap())
        turned = []
        asyncio.get_running_loop().call_soon(turned.append, True)
        att = SimpleNamespace(pass_pitch_mm=1.5, knife_widths_mm=_widths(np.zeros(4)),
                              bdc_pitch_mm=1.5)
        applied = await stage.apply(att, 5.0, _snap(), 5.0)
        return applied, bool(turned), len(calls), stage._report.counters.get("applied")

    assert asyncio.run(run(False)) == (True, False, 0, 1)
    assert asyncio.run(run(True)) == (True, True, 1, 1)
