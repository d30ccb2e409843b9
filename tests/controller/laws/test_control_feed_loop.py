"""Feed loop: configuration, law, delay handling, limits (simulated time only)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.feed_loop import (
    FeedLoop,
    FeedLoopConfig,
    integral_gain,
    pitch_ceiling_mm,
)
from core.errors import ConfigError


class BoardPlant:
    """Feed drive (first-order lag + acceleration limit), cut pitch logged along the board, and a
    camera L downstream that reports the mean pitch of the board window it sees."""

    def __init__(
        self,
        *,
        scale: float = 1.03,
        knives: int = 4,
        bandwidth_hz: float = 5.0,
        accel_mm_s2: float = 3000.0,
        cutter_to_camera_mm: float = 300.0,
        window_mm: float = 40.0,
        feed_mm_s: float = 50.0,
        dt_s: float = 0.005,
    ) -> None:
        self.scale, self.knives, self.dt = scale, knives, dt_s
        self.tau = 1.0 / (2 * math.pi * bandwidth_hz)
        self.accel = accel_mm_s2
        self.L, self.W = cutter_to_camera_mm, window_mm
        self.v = feed_mm_s
        self.x = 0.0
        self.log_x = [0.0]
        self.log_p = [math.nan]

    def true_pitch(self, rpm: float) -> float:
        return self.scale * self.v / (rpm / 60.0 * self.knives)

    def step(self, feed_setpoint: float, rpm: float, duration_s: float) -> None:
        for _ in range(round(duration_s / self.dt)):
            dv = (feed_setpoint - self.v) * self.dt / self.tau
            lim = self.accel * self.dt
            self.v += min(max(dv, -lim), lim)
            self.x += self.v * self.dt
            self.log_x.append(self.x)
            self.log_p.append(self.true_pitch(rpm))

    def measure(self) -> float | None:
        lo, hi = self.x - self.L - self.W / 2, self.x - self.L + self.W / 2
        if lo <= self.W:  # no board cut yet in the window
            return None
        xs = np.asarray(self.log_x)
        ps = np.asarray(self.log_p)
        sel = (xs >= lo) & (xs <= hi)
        # board-length weighted mean of the cut pitch over the window
        dx = np.diff(xs, prepend=xs[0])[sel]
        return float(np.sum(ps[sel] * dx) / np.sum(dx))


def run_closed_loop(cfg, plant, rpm_of_t, *, t_end_s, measure_every_s=0.1):
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=plant.v, now_s=0.0)
    t = 0.0
    out = []
    while t < t_end_s - 1e-9:
        rpm = rpm_of_t(t)
        meas = plant.measure()
        feed = loop.update(measured_pitch_mm=meas, spindle_rpm=rpm, now_s=t)
        out.append((t, feed, plant.true_pitch(rpm), loop.status, plant.v))
        plant.step(feed, rpm, measure_every_s)
        t += measure_every_s
    return loop, out


# -- configuration -------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("sample_time_s", 0.0),
        ("target_pitch_mm", -1.0),
        ("knives", 0),
        ("knives", 2.5),
        ("feed_max_mm_s", 40.0),
        ("rate_max_mm_s2", 0.0),
        ("ki", 2.0),
        ("settle_s", -0.1),
        ("correction_min", 1.2),
        ("correction_max", 0.9),
        ("initial_feed_mm_s", 5000.0),
        ("depth_max_um", math.nan),
    ],
)
def test_config_rejects_bad_values_naming_the_field(key, value):
    with pytest.raises(ValueError, match=key):
        FeedLoopConfig(**{key: value})


def test_config_from_mapping_names_unknown_and_bad_keys():
    cfg = FeedLoopConfig.from_mapping({"ki": 0.3}, target_pitch_mm=1.2)
    assert cfg.ki == 0.3 and cfg.target_pitch_mm == 1.2
    with pytest.raises(ConfigError, match="feed_loop.kp"):
        FeedLoopConfig.from_mapping({"kp": 1.0})
    with pytest.raises(ConfigError, match="feed_loop.ki"):
        FeedLoopConfig.from_mapping({"ki": -1.0})


def test_pitch_setpoint_respects_depth_ceiling():
    cfg = FeedLoopConfig(target_pitch_mm=3.0, depth_max_um=10.0, radius_mm=60.0)
    p = cfg.pitch_setpoint_mm
    assert p == pytest.approx(pitch_ceiling_mm(10.0, 60.0))
    assert p * p / (8 * 60.0) * 1e3 == pytest.approx(10.0)  # depth at the ceiling
    loose = FeedLoopConfig(target_pitch_mm=1.5, depth_max_um=10.0)
    assert loose.pitch_setpoint_mm == 1.5


def test_integral_gain_schedule_is_a_fixed_fraction_of_the_delay():
    for delay in (0.3, 1.0, 6.0):
        g = integral_gain(0.5, 0.1, delay)
        assert g * (delay + 0.1) / 0.1 == pytest.approx(0.5)
    assert integral_gain(0.5, 0.1, 0.0) == pytest.approx(0.5)


# -- the law -------------------------------------------------------------------------------
def test_feed_forward_without_measurements_gives_target_pitch_times_speed():
    cfg = FeedLoopConfig(rate_max_mm_s2=1e6, initial_feed_mm_s=100.0)
    loop = FeedLoop(cfg)
    for i, rpm in enumerate([6000.0, 6000.0, 4500.0, 9000.0]):
        feed = loop.update(measured_pitch_mm=None, spindle_rpm=rpm, now_s=0.1 * (i + 1))
        expect = min(max(1.5 * rpm / 60 * 4, cfg.feed_min_mm_s), cfg.feed_max_mm_s)
        if i:
            assert feed == pytest.approx(expect)
    assert loop.status == "no_measurement"
    assert loop.correction == 1.0


def test_rate_limit_uses_time_differences():
    cfg = FeedLoopConfig(rate_max_mm_s2=400.0)
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=100.0, now_s=0.0)
    f1 = loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=0.25)
    assert f1 == pytest.approx(200.0)
    f2 = loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=0.25)  # no time passed
    assert f2 == pytest.approx(200.0)
    f3 = loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=1.0)
    assert f3 == pytest.approx(500.0)
    with pytest.raises(ValueError, match="now_s"):
        loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=0.5)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"measured_pitch_mm": -1.0}, "measured_pitch_mm"),
        ({"measured_pitch_mm": math.nan}, "measured_pitch_mm"),
        ({"spindle_rpm": -5.0}, "spindle_rpm"),
        ({"now_s": math.inf}, "now_s"),
        ({"measured_pitch_mm": 1.5, "measured_at_s": 99.0}, "measured_at_s"),
    ],
)
def test_update_rejects_bad_inputs(kwargs, name):
    loop = FeedLoop(FeedLoopConfig())
    args = {"measured_pitch_mm": None, "spindle_rpm": 6000.0, "now_s": 1.0} | kwargs
    with pytest.raises(ValueError, match=name):
        loop.update(**args)


def test_cut_interval_integrates_the_setpoint_history():
    cfg = FeedLoopConfig(rate_max_mm_s2=1e6, cutter_to_camera_mm=300.0, window_mm=40.0)
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=100.0, now_s=0.0)
    for i in range(1, 41):  # 100 mm/s for 2 s, then 300 mm/s (rpm 3000, Z 4, p 1.5 -> 300)
        rpm = 1000.0 if i <= 20 else 3000.0
        loop.update(measured_pitch_mm=None, spindle_rpm=rpm, now_s=0.1 * i)
    # at t = 4.0: board moved 100 * 2.1 + 300 * 1.9 mm since t = 0 (setpoints from the update)
    lo, hi = loop.cut_interval_s(4.0)
    # 320 mm back from 4.0 at 300 mm/s reaches t = 2.1 - (320 - 570) / ... : all in the fast part
    assert hi == pytest.approx(4.0 - 280.0 / 300.0)
    assert lo == pytest.approx(4.0 - 320.0 / 300.0)
    # further back than the history: None
    assert loop.cut_interval_s(0.5) is None


def test_measurement_during_transient_is_not_trusted_and_holds_the_correction():
    cfg = FeedLoopConfig(rate_max_mm_s2=200.0)
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=50.0, now_s=0.0)
    statuses = []
    for i in range(1, 33):
        loop.update(measured_pitch_mm=1.0, spindle_rpm=6000.0, now_s=0.1 * i)
        statuses.append(loop.status)
    # the ramp 50 -> 600 mm/s lasts 2.75 s; the board seen until 3.2 s was cut during it
    assert statuses[0] == "no_history"
    assert set(statuses) == {"no_history", "transient"}
    assert loop.correction == 1.0
    # the board cut at steady feed eventually arrives and is used
    for i in range(33, 120):
        loop.update(measured_pitch_mm=1.5 * 1.03, spindle_rpm=6000.0, now_s=0.1 * i)
    assert loop.status == "accepted"
    assert loop.correction < 1.0


def test_implausible_measurement_is_rejected():
    cfg = FeedLoopConfig(rate_max_mm_s2=1e6)
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=600.0, now_s=0.0)
    for i in range(1, 30):
        loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=0.1 * i)
    loop.update(measured_pitch_mm=4.0, spindle_rpm=6000.0, now_s=3.0)
    assert loop.status == "implausible"
    assert loop.correction == 1.0


@pytest.mark.parametrize("scale", [1.03, 0.97, 1.10])
@pytest.mark.parametrize("rpm", [3000.0, 6000.0, 9000.0])
def test_closed_loop_removes_model_error(scale, rpm):
    cfg = FeedLoopConfig(rate_max_mm_s2=1000.0)
    plant = BoardPlant(scale=scale)
    t_end = 6.0 + 25.0 * (300.0 / (1.5 * rpm / 15)) * 1.0
    loop, log = run_closed_loop(cfg, plant, lambda t: rpm, t_end_s=t_end)
    true_p = np.array([r[2] for r in log])
    assert abs(true_p[-1] / cfg.target_pitch_mm - 1) < 0.002
    assert loop.correction == pytest.approx(1.0 / scale, rel=0.003)
    # no overshoot beyond the target by more than 0.5 % (the start-up ramp is below target)
    err = true_p / cfg.target_pitch_mm - 1
    if scale > 1:
        ramp_end = int(np.argmax(err > 0))
        assert err[ramp_end:].min() > -0.005
    else:
        assert err.max() < 0.005


def test_closed_loop_reaches_2_percent_within_3_m_of_board_at_600_mm_s():
    cfg = FeedLoopConfig(rate_max_mm_s2=1000.0)
    plant = BoardPlant(scale=1.03)
    _, log = run_closed_loop(cfg, plant, lambda t: 6000.0, t_end_s=12.0)
    t = np.array([r[0] for r in log])
    feed = np.array([r[1] for r in log])
    err = np.abs(np.array([r[2] for r in log]) / 1.5 - 1)
    board_mm = np.concatenate([[0.0], np.cumsum(feed[:-1] * np.diff(t))])
    ok = np.nonzero(err > 0.02)[0]
    first_ok = ok[-1] + 1
    assert board_mm[first_ok] < 3000.0


def test_clamp_does_not_wind_up():
    # at 12000 rpm the target needs 1200 mm/s > feed_max: the feed saturates, the pitch is low
    cfg = FeedLoopConfig(rate_max_mm_s2=2000.0)
    plant = BoardPlant(scale=1.03, feed_mm_s=600.0)
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=600.0, now_s=0.0)
    t = 0.0
    for _ in range(150):
        feed = loop.update(measured_pitch_mm=plant.measure(), spindle_rpm=12000.0, now_s=t)
        plant.step(feed, 12000.0, 0.1)
        t += 0.1
    assert feed == cfg.feed_max_mm_s
    # the correction learnt the model error, not the saturation
    assert loop.correction == pytest.approx(1 / 1.03, rel=0.01)
    # the spindle slows: the pitch is right at once, without the overshoot of a wound-up integral
    worst = 0.0
    for _ in range(100):
        feed = loop.update(measured_pitch_mm=plant.measure(), spindle_rpm=6000.0, now_s=t)
        plant.step(feed, 6000.0, 0.1)
        t += 0.1
        if plant.v < 0.99 * feed or abs(plant.v - feed) > 1.0:
            continue  # drive still moving
        worst = max(worst, abs(plant.true_pitch(6000.0) / 1.5 - 1))
    assert worst < 0.01


def test_reset_keeps_a_learnt_correction_and_validates():
    loop = FeedLoop(FeedLoopConfig())
    loop.reset(feed_mm_s=300.0, correction=0.97)
    assert loop.correction == pytest.approx(0.97)
    assert loop.feed_mm_s == 300.0
    with pytest.raises(ValueError, match="feed_mm_s"):
        loop.reset(feed_mm_s=5.0)
    with pytest.raises(ValueError, match="correction"):
        loop.reset(correction=3.0)


# -- properties ----------------------------------------------------------------------------
step = st.tuples(
    st.floats(0.0, 0.6),  # dt
    st.one_of(st.none(), st.floats(0.01, 20.0)),  # measured pitch
    st.floats(0.0, 15000.0),  # rpm
    st.floats(0.0, 0.3),  # measurement age
)


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(step, min_size=1, max_size=80),
    fmin=st.floats(10.0, 200.0),
    span=st.floats(10.0, 2000.0),
    rate=st.floats(10.0, 5000.0),
)
def test_setpoint_stays_in_limits_and_rate(steps, fmin, span, rate):
    cfg = FeedLoopConfig(feed_min_mm_s=fmin, feed_max_mm_s=fmin + span, rate_max_mm_s2=rate)
    loop = FeedLoop(cfg)
    loop.reset(now_s=0.0)
    t, prev = 0.0, loop.feed_mm_s
    for dt, meas, rpm, age in steps:
        t += dt
        feed = loop.update(
            measured_pitch_mm=meas, spindle_rpm=rpm, now_s=t, measured_at_s=max(t - age, 0.0)
        )
        assert math.isfinite(feed)
        assert cfg.feed_min_mm_s <= feed <= cfg.feed_max_mm_s
        assert abs(feed - prev) <= rate * dt * (1 + 1e-9) + 1e-9
        assert (
            cfg.correction_min * (1 - 1e-12) <= loop.correction <= cfg.correction_max * (1 + 1e-12)
        )
        prev = feed


# -- setpoints that never reached the machine ------------------------------------------------
def _history_loop(feeds, *, reject_at=(), same_instant=False):
    """A loop stepped through ``feeds`` (as spindle speeds giving those feeds), rejecting some."""
    cfg = FeedLoopConfig(rate_max_mm_s2=1e6, cutter_to_camera_mm=300.0, window_mm=40.0)
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=100.0, now_s=0.0)
    for i, feed in enumerate(feeds, start=1):
        rpm = feed / (1.5 * 4) * 60.0  # feed-forward p* n Z = feed
        t = 0.1 * i
        if same_instant and i in reject_at:  # an accepted setpoint at t, then a refused one
            loop.update(measured_pitch_mm=None, spindle_rpm=rpm * 0.9, now_s=t)
        loop.update(measured_pitch_mm=None, spindle_rpm=rpm, now_s=t)
        if i in reject_at:
            loop.reject()
    return loop


@pytest.mark.parametrize("same_instant", [False, True])
def test_a_rejected_setpoint_leaves_no_trace_in_the_history(same_instant):
    """A refused or failed write never happened: the history integrates what was in force."""
    feeds = [100.0] * 10 + [400.0] * 20
    truth = [100.0] * 10 + [100.0] * 20 if not same_instant else None
    refused = set(range(11, 31))  # every change to 400 mm/s refused by the PLC
    loop = _history_loop(feeds, reject_at=refused, same_instant=same_instant)
    if truth is not None:
        ref = _history_loop(truth)
        assert loop.cut_interval_s(3.0) == pytest.approx(ref.cut_interval_s(3.0))
        assert loop.feed_mm_s == pytest.approx(ref.feed_mm_s) == 100.0
    else:  # the refused setpoint at t gives way to the accepted one at the same instant
        assert loop.feed_mm_s == pytest.approx(0.9 * 400.0)
        lo, hi = loop.cut_interval_s(3.0)
        assert hi == pytest.approx(3.0 - 280.0 / 360.0)
    # rejecting twice, or before any update, changes nothing more
    before = (loop.feed_mm_s, loop.cut_interval_s(3.0))
    loop.reject()
    assert (loop.feed_mm_s, loop.cut_interval_s(3.0)) == before
    fresh = FeedLoop(FeedLoopConfig())
    fresh.reject()
    assert fresh.feed_mm_s == FeedLoopConfig().feed_min_mm_s


def test_rejected_setpoint_is_retried_from_the_feed_in_force():
    """After a rejection the rate limit counts from the setpoint that is really in force."""
    loop = FeedLoop(FeedLoopConfig(rate_max_mm_s2=400.0))
    loop.reset(feed_mm_s=100.0, now_s=0.0)
    assert loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=0.25) == 200.0
    loop.reject()
    assert loop.feed_mm_s == 100.0
    # 0.25 s later the next attempt moves at most 100 mm/s from 100 mm/s, not from 200
    assert loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=0.5) == 200.0


# -- the drive's own limits ----------------------------------------------------------------
def _run_with_drive(cfg, plant, *, t_end_s, observe, dt_s=0.02, measure_every=5):
    """A 20 ms cycle: the drive's actual feed reported every cycle (``observe``), a measurement
    every ``measure_every`` cycles; the plant's own encoder scale is the model error."""
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=plant.v, now_s=0.0)
    out = []
    for i in range(round(t_end_s / dt_s)):
        t = i * dt_s
        if observe:
            loop.observe_drive(now_s=t, feed_actual_mm_s=plant.v, spindle_rpm=6000.0)
        meas = plant.measure() if i % measure_every == 0 else None
        feed = loop.update(measured_pitch_mm=meas, spindle_rpm=6000.0, now_s=t)
        out.append((t, feed, plant.true_pitch(6000.0), loop.correction))
        plant.step(feed, 6000.0, dt_s)
    return loop, out


@pytest.mark.parametrize("accel", [20.0, 50.0])
def test_a_drive_that_ramps_slowly_teaches_no_false_model_error(accel):
    """The loop's rate (500 mm/s^2) outruns a drive of 20-50 mm/s^2: with the drive's actual
    feed reported the correction learns the true model error only; without, it winds down."""
    cfg = FeedLoopConfig(rate_max_mm_s2=500.0)
    runs = {}
    for observe in (True, False):
        plant = BoardPlant(scale=1.0, feed_mm_s=800.0, accel_mm_s2=accel, dt_s=0.005)
        runs[observe] = _run_with_drive(cfg, plant, t_end_s=6.0, observe=observe)
    loop, out = runs[True]
    assert min(c for *_, c in out) > 0.995  # no wind-up while the drive lagged
    assert min(f for _, f, *_ in out) > 0.995 * 600.0
    _, blind = runs[False]
    assert min(c for *_, c in blind) < 0.95  # what the setpoints alone teach (the old fault)


def test_a_lagging_drive_still_lets_the_loop_learn_the_true_model_error():
    """Bandwidth 0.3 Hz (time constant 0.53 s, far beyond settle_s): the correction converges
    to the plant's scale error from the drive's readings."""
    cfg = FeedLoopConfig(rate_max_mm_s2=2000.0)
    plant = BoardPlant(scale=1.03, feed_mm_s=800.0, bandwidth_hz=0.3, dt_s=0.005)
    loop, out = _run_with_drive(cfg, plant, t_end_s=25.0, observe=True)
    assert loop.correction == pytest.approx(1 / 1.03, rel=0.005)
    assert abs(out[-1][2] / 1.5 - 1) < 0.005


def test_deferred_steps_add_up_instead_of_freezing_the_feed():
    """25 mm/s^2 moves 0.5 mm/s per 20 ms cycle: each step alone is inside a 0.5 mm/s write
    deadband. Deferred (not written), they add up and the feed still ramps at the full rate;
    rejected instead, the rate limit starts again every cycle and the feed never moves."""
    cfg = FeedLoopConfig(rate_max_mm_s2=25.0)
    finals = {}
    for how in ("defer", "reject"):
        loop = FeedLoop(cfg)
        loop.reset(feed_mm_s=700.0, now_s=0.0)
        in_force = 700.0
        for i in range(1, 201):  # 4 s
            feed = loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=i * 0.02)
            if abs(feed - in_force) <= 0.5:
                getattr(loop, how)()
            else:
                in_force = feed
            assert loop.feed_mm_s == in_force
        finals[how] = in_force
    assert finals["defer"] == pytest.approx(700.0 - 25.0 * 4.0, abs=0.6)
    assert finals["reject"] == 700.0


def test_defer_takes_the_setpoint_out_of_the_history_like_reject():
    cfg = FeedLoopConfig(rate_max_mm_s2=1e6, cutter_to_camera_mm=300.0, window_mm=40.0)
    loop = FeedLoop(cfg)
    loop.reset(feed_mm_s=600.0, now_s=0.0)
    loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=1.0)
    before = (loop.feed_mm_s, loop.cut_interval_s(1.5))
    loop.update(measured_pitch_mm=None, spindle_rpm=6010.0, now_s=1.2)
    loop.defer()
    assert (loop.feed_mm_s, loop.cut_interval_s(1.5)) == before


def test_cut_interval_follows_the_drive_when_it_reports():
    """Setpoint 600 mm/s but the drive ran at 300 mm/s: the board seen at 2 s was cut 1 s
    before (300 mm at 300 mm/s), not 0.5 s."""
    loop = FeedLoop(FeedLoopConfig(rate_max_mm_s2=1e6, cutter_to_camera_mm=300.0,
                                   window_mm=40.0))
    loop.reset(feed_mm_s=600.0, now_s=0.0)
    for i in range(101):
        t = i * 0.02
        loop.observe_drive(now_s=t, feed_actual_mm_s=300.0, spindle_rpm=6000.0)
        loop.update(measured_pitch_mm=None, spindle_rpm=6000.0, now_s=t)
    lo, hi = loop.cut_interval_s(2.0)
    assert (lo + hi) / 2 == pytest.approx(1.0, abs=1e-9)
    assert hi - lo == pytest.approx(40.0 / 300.0, abs=1e-9)
