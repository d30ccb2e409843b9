"""Design checks with python-control: margins across the feed range, steps, ILC per mode."""

from __future__ import annotations

import math

import control as ct
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.design import (
    DESIGN_FEEDS_MM_S,
    MIN_GAIN_MARGIN_DB,
    MIN_PHASE_MARGIN_DEG,
    FeedPlant,
    feed_delay_samples,
    feed_disturbance_response,
    feed_loop_frd,
    feed_loop_margins,
    feed_loop_model,
    feed_step,
    margins,
    mode_eigenvalues,
    settling_time_s,
    uniformity_closed_loop_radius,
    uniformity_delay_samples,
    uniformity_loop_margins,
    uniformity_loop_model,
)
from controller.laws.feed_loop import FeedLoop, FeedLoopConfig
from controller.laws.uniformity_loop import UniformityLoopConfig
from tests.controller.laws.test_control_feed_loop import BoardPlant

CFG = FeedLoopConfig()


def closed_loop_radius(model, *, gain=1.0, extra_delay=0):
    """Largest closed-loop pole magnitude of the feed loop (state space, exact shift registers)."""
    p = ct.ss(model.plant * ct.tf([1.0], [1.0] + [0.0] * extra_delay, model.plant.dt))
    c = ct.feedback(ct.ss(model.filter), ct.ss(model.model), sign=+1)
    cl = ct.feedback(gain * c * p, 1)
    return float(np.max(np.abs(np.linalg.eigvals(cl.A))))


def test_delay_samples_follow_the_feed():
    d100, m100 = feed_delay_samples(100.0, CFG)
    d1000, m1000 = feed_delay_samples(1000.0, CFG)
    assert d100 == 30 + 1 and m100 == 4  # 300 mm at 100 mm/s = 3 s; 40 mm window = 0.4 s
    assert d1000 == 3 + 1 and m1000 == 1
    with pytest.raises(ValueError, match="feed_mm_s"):
        feed_delay_samples(0.0, CFG)


@pytest.mark.parametrize(
    "case",
    [
        {},
        {"model_delay_error_samples": -1},
        {"model_delay_error_samples": +1},
        {"plant": FeedPlant(drive_bandwidth_hz=10.0)},
        {"plant": FeedPlant(drive_bandwidth_hz=2.0, drive_order=2)},
        {"plant": FeedPlant(latency_samples=2)},
        {"gain_scale": 1.5},
    ],
    ids=["nominal", "model-1", "model+1", "drive10Hz", "drive2Hz2nd", "latency2", "gain1.5"],
)
def test_feed_loop_margins_across_the_feed_range(case):
    rows = feed_loop_margins(CFG, DESIGN_FEEDS_MM_S, **case)
    assert [r.feed_mm_s for r in rows] == list(DESIGN_FEEDS_MM_S)
    for r in rows:
        assert r.margins.gain_margin_db >= MIN_GAIN_MARGIN_DB, r
        assert r.margins.phase_margin_deg >= MIN_PHASE_MARGIN_DEG, r
        assert r.margins.stability_margin >= 0.5, r


def test_gain_schedule_keeps_the_margins_alike_across_the_feed_range():
    rows = feed_loop_margins(CFG, DESIGN_FEEDS_MM_S)
    gm = [r.margins.gain_margin_db for r in rows]
    pm = [r.margins.phase_margin_deg for r in rows]
    assert max(gm) - min(gm) < 2.0
    assert max(pm) - min(pm) < 6.0
    # the crossover scales with the inverse delay: the delay margin is a fixed share of it
    ratios = [
        r.margins.delay_margin_s
        / ((r.delay_samples + 0.5 * (r.window_samples - 1)) * CFG.sample_time_s)
        for r in rows
    ]
    assert min(ratios) > 2.0
    assert max(ratios) / min(ratios) < 1.3


def test_too_high_a_gain_is_fragile_to_a_delay_model_error():
    # g = 0.64 per sample at 600 mm/s: fine with an exact internal model (the Smith-predictor
    # structure), but one sample of delay error destroys the margins; the design gain keeps them
    hot = FeedLoopConfig(ki=1.5)
    (exact,) = feed_loop_margins(hot, (600.0,), gain_scale=3.0)
    assert exact.margins.gain_margin_db >= MIN_GAIN_MARGIN_DB
    for err in (-1, 1):
        (row,) = feed_loop_margins(hot, (600.0,), gain_scale=3.0, model_delay_error_samples=err)
        assert row.margins.gain_margin_db < MIN_GAIN_MARGIN_DB
        assert row.margins.phase_margin_deg < MIN_PHASE_MARGIN_DEG


@pytest.mark.parametrize("feed", [100.0, 300.0, 1000.0])
def test_margins_agree_with_closed_loop_poles(feed):
    model = feed_loop_model(CFG, feed)
    m = margins(feed_loop_frd(model))
    gm = 10 ** (m.gain_margin_db / 20)
    assert closed_loop_radius(model) < 1.0
    assert closed_loop_radius(model, gain=0.95 * gm) < 1.0
    assert closed_loop_radius(model, gain=1.05 * gm) > 1.0
    # phase margin as delay margin: a few samples less extra delay is fine, more is not
    dm = m.delay_margin_s / CFG.sample_time_s
    assert closed_loop_radius(model, extra_delay=math.floor(dm) - 1) < 1.0
    assert closed_loop_radius(model, extra_delay=math.ceil(dm) + 1) > 1.0


@pytest.mark.parametrize("feed", DESIGN_FEEDS_MM_S)
def test_step_of_the_model_error_leaves_no_steady_state_error(feed):
    model = feed_loop_model(CFG, feed)
    assert abs(ct.dcgain(feed_disturbance_response(model))) < 1e-9  # integral action
    t, err = feed_step(model, model_error=0.03)
    assert abs(err[-1]) < 1e-3 * 0.03
    assert err.min() > -0.1 * 0.03  # overshoot (past zero) bounded by 10 % of the step
    assert err.max() <= 0.03 * (1 + 1e-9)
    settle = settling_time_s(t, err, band=0.05 * 0.03)
    assert settle * feed < 3500.0  # within 3.5 m of board at every feed


def test_code_settles_like_the_design_model():
    # the FeedLoop class against a board plant at 600 mm/s: time to 5 % of a 3 % model error
    rpm = 6000.0
    plant = BoardPlant(scale=1.03, feed_mm_s=600.0)
    loop = FeedLoop(CFG)
    loop.reset(feed_mm_s=600.0, now_s=0.0)
    t, log = 0.0, []
    # run at the model's feed first so the history is steady, then close the loop
    for _ in range(15):
        plant.step(600.0, rpm, 0.1)
        loop.update(measured_pitch_mm=None, spindle_rpm=rpm, now_s=t)
        t += 0.1
    t0 = t
    for _ in range(150):
        feed = loop.update(measured_pitch_mm=plant.measure(), spindle_rpm=rpm, now_s=t)
        log.append((t - t0, plant.true_pitch(rpm) / 1.5 - 1))
        plant.step(feed, rpm, 0.1)
        t += 0.1
    tt, e = np.array(log).T
    t_m, e_m = feed_step(feed_loop_model(CFG, 600.0), model_error=0.03)

    def time_constant(t, err):  # log-linear fit of the decay between 1 % and 0.05 %
        sel = (np.abs(err) < 0.01) & (np.abs(err) > 0.0005) & (t > 0)
        slope = np.polyfit(t[sel], np.log(np.abs(err[sel])), 1)[0]
        return -1.0 / slope

    tau_code, tau_model = time_constant(tt, e), time_constant(t_m, e_m)
    assert tau_model == pytest.approx(CFG.sample_time_s / 0.0714, rel=0.1)  # ~1 / g samples
    assert tau_code == pytest.approx(tau_model, rel=0.15)


# -- uniformity loop ---------------------------------------------------------------------------
def test_mode_eigenvalues():
    for z in (2, 3, 4, 8):
        lam = np.sort(mode_eigenvalues(z))
        assert np.allclose(lam, np.sort(-4 * np.sin(np.pi * np.arange(z) / z) ** 2))


CAMERAS = (300.0, 1000.0, 2000.0)
UCFG = UniformityLoopConfig()


def test_uniformity_delay_follows_the_feed_and_the_camera():
    d, m = uniformity_delay_samples(600.0, UCFG, cutter_to_camera_mm=300.0)
    assert (d, m) == (math.ceil((0.05 + 0.5) / 0.1) + 1, 1)
    d2, m2 = uniformity_delay_samples(50.0, UCFG, cutter_to_camera_mm=2000.0)
    assert d2 == math.ceil((0.05 + 40.0) / 0.1) + 1 and m2 == 8
    with pytest.raises(ValueError, match="cutter_to_camera_mm"):
        uniformity_delay_samples(600.0, UCFG, cutter_to_camera_mm=0.0)


def test_uniformity_margins_hold_over_the_feed_range_at_every_camera_distance():
    rows = uniformity_loop_margins(UCFG, DESIGN_FEEDS_MM_S, CAMERAS)
    assert len(rows) == len(DESIGN_FEEDS_MM_S) * len(CAMERAS)
    for r in rows:
        assert r.margins.gain_margin_db >= MIN_GAIN_MARGIN_DB, r
        assert r.margins.phase_margin_deg >= MIN_PHASE_MARGIN_DEG, r
    # the schedule keeps the margins alike: the crossover follows the delay
    gms = [r.margins.gain_margin_db for r in rows]
    assert max(gms) - min(gms) < 0.6


@settings(max_examples=12, deadline=None)
@given(feed=st.floats(50.0, 1000.0), camera=st.floats(300.0, 2000.0))
def test_uniformity_margins_at_any_feed_and_camera(feed, camera):
    mdl = uniformity_loop_model(UCFG, feed, cutter_to_camera_mm=camera)
    m = margins(feed_loop_frd(mdl))
    assert m.gain_margin_db >= MIN_GAIN_MARGIN_DB
    assert m.phase_margin_deg >= MIN_PHASE_MARGIN_DEG


@pytest.mark.parametrize(
    ("feed", "camera"), [(50.0, 300.0), (300.0, 1000.0), (300.0, 2000.0), (1000.0, 2000.0)]
)
def test_uniformity_margins_agree_with_the_closed_loop_poles(feed, camera):
    """GM and PM from the frequency response against the exact characteristic polynomial.

    A gain error of the identified actuator gain is a real ``alpha``, a phase error a complex
    one: the loop must be stable just inside each margin and unstable just outside it.
    """
    mdl = uniformity_loop_model(UCFG, feed, cutter_to_camera_mm=camera)
    m = margins(feed_loop_frd(mdl))
    gm = 10 ** (m.gain_margin_db / 20)
    assert uniformity_closed_loop_radius(mdl, 1.0) < 1.0
    assert uniformity_closed_loop_radius(mdl, 0.95 * gm) < 1.0
    assert uniformity_closed_loop_radius(mdl, 1.05 * gm) > 1.0
    pm = math.radians(m.phase_margin_deg)
    for sign in (1, -1):
        assert uniformity_closed_loop_radius(mdl, np.exp(sign * 1j * (pm - 0.03))) < 1.0
        assert uniformity_closed_loop_radius(mdl, np.exp(sign * 1j * (pm + 0.03))) > 1.0
    # an actuator weaker than identified only slows the loop down
    for alpha in (0.05, 0.2, 0.5):
        assert uniformity_closed_loop_radius(mdl, alpha) < 1.0


def test_uniformity_closed_loop_radius_matches_the_state_space_interconnection():
    mdl = uniformity_loop_model(UCFG, 300.0, cutter_to_camera_mm=300.0, mode_gain=1.7)
    c = ct.feedback(ct.ss(mdl.filter), ct.ss(mdl.model), sign=+1)
    cl = ct.feedback(c * ct.ss(mdl.plant), 1)
    ss_radius = float(np.max(np.abs(np.linalg.eigvals(cl.A))))
    assert uniformity_closed_loop_radius(mdl, 1.7) == pytest.approx(ss_radius, rel=1e-6)


@pytest.mark.parametrize(
    ("case", "gm_min", "pm_min"),
    [
        ({"mode_gain": 0.5}, MIN_GAIN_MARGIN_DB, MIN_PHASE_MARGIN_DEG),  # weaker than identified
        ({"mode_gain": 1.5}, 3.0, MIN_PHASE_MARGIN_DEG),  # stronger: GM >= 7.7 dB = x2.4 nominal
        ({"model_delay_error_samples": 1}, MIN_GAIN_MARGIN_DB, MIN_PHASE_MARGIN_DEG),
        ({"model_delay_error_samples": -1}, MIN_GAIN_MARGIN_DB, MIN_PHASE_MARGIN_DEG),
        ({"latency_samples": 2}, MIN_GAIN_MARGIN_DB, MIN_PHASE_MARGIN_DEG),
    ],
)
def test_uniformity_robustness_cases_stay_stable(case, gm_min, pm_min):
    rows = uniformity_loop_margins(UCFG, DESIGN_FEEDS_MM_S, CAMERAS, **case)
    assert min(r.margins.gain_margin_db for r in rows) >= gm_min
    assert min(r.margins.phase_margin_deg for r in rows) >= pm_min


# -- the identified actuator's error disc ---------------------------------------------------------
def test_a_confident_gain_keeps_every_mode_stable_with_margin():
    """Confidence > 0 means two standard errors inside half the gain: the loop of every knife
    mode stays stable with a stability margin > 0.3 at every feed and camera distance, for a
    true gain anywhere on that disc (phase included)."""
    from controller.laws.design import identified_disc_rows
    from controller.laws.uniformity_loop import UniformityLoopConfig

    rows = identified_disc_rows(UniformityLoopConfig(), 0.5, points=12)
    assert len(rows) == 15
    for r in rows:
        assert r.robust_radius >= 1.0 - 1e-9
        assert r.worst_pole_radius < 1.0
        assert r.worst_margin > 0.3


def test_a_gain_turned_around_is_what_the_loop_cannot_survive_unidentified():
    """The 100 Hz piezo's alternating pattern (-0.23 against an assumed +1): unstable, the
    error grows by about 2 % a pair (the measured CV on main rose 0.16 -> 0.68 in 100 pairs)."""
    from controller.laws.design import uniformity_closed_loop_radius, uniformity_loop_model
    from controller.laws.uniformity_loop import UniformityLoopConfig

    mdl = uniformity_loop_model(UniformityLoopConfig(), 600.0, cutter_to_camera_mm=300.0)
    assert 1.0 < uniformity_closed_loop_radius(mdl, -0.23) < 1.05
    assert uniformity_closed_loop_radius(mdl, 1.0) < 1.0
