"""Uniformity loop: width model, learning law, stroke, hold-off, against the kinematic model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.limits import project_zero_mean_box
from controller.uniformity_loop import (
    UniformityLoop,
    UniformityLoopConfig,
    linear_widths_mm,
    second_difference,
    width_cv,
)
from core.errors import ConfigError

R_MM = 60.0


def envelope_marks(relative_depth_um, *, pitch_mm, radius_mm=R_MM, revolutions=12):
    """Complete marks of the lower envelope of the tip parabolas ``b_j + (x - x_j)^2 / 2R``.

    Same-curvature parabolas differ by lines, so the envelope is the lower envelope of the lines
    ``-x_j/R x + b_j + x_j^2/2R`` (convex hull trick). Returns (widths_mm, knife) of the marks of
    the middle revolutions (whole revolutions, steady state).
    """
    z = np.asarray(relative_depth_um, dtype=float)
    knives = z.size
    n = knives * revolutions
    xj = np.arange(n) * pitch_mm
    b = z[np.arange(n) % knives] * 1e-3  # positive: the tip stays higher, cuts less deep
    slope = -xj / radius_mm
    icpt = b + xj**2 / (2 * radius_mm)
    hull: list[int] = []

    def cross(i, k):
        return (icpt[k] - icpt[i]) / (slope[i] - slope[k])

    for j in range(n):
        while len(hull) >= 2 and cross(hull[-2], j) <= cross(hull[-2], hull[-1]):
            hull.pop()
        hull.append(j)
    cusps = np.array([cross(hull[i], hull[i + 1]) for i in range(len(hull) - 1)])
    marks = np.array(hull[1:-1])  # complete marks
    widths = np.diff(cusps)
    lo, hi = 3 * knives, (revolutions - 3) * knives  # passes of the middle revolutions
    keep = (marks >= lo) & (marks < hi)
    return widths[keep], marks[keep] % knives


def knife_means(widths_mm, knife, knives):
    """Mean mark width of each knife, NaN for a knife without marks."""
    w = np.asarray(widths_mm, dtype=float)
    k = np.asarray(knife, dtype=int)
    return np.array([w[k == j].mean() if np.any(k == j) else math.nan for j in range(knives)])


def per_knife_widths(relative_depth_um, pitch_mm, knives):
    w, k = envelope_marks(relative_depth_um, pitch_mm=pitch_mm)
    w_k = knife_means(w, k, knives)
    return w_k, width_cv(w_k)  # steady state: every mark of a knife alike; vanished = 0


def run_ilc(runout_um, *, pitch_mm=1.5, iterations=8, noise_mm=0.0, seed=0, cfg=None):
    runout = np.asarray(runout_um, dtype=float)
    cfg = cfg or UniformityLoopConfig(knives=runout.size, radius_mm=R_MM)
    loop = UniformityLoop(cfg)
    rng = np.random.default_rng(seed)
    cvs, offsets = [], []
    t = 0.0
    for _ in range(iterations + 1):
        w_k, cv = per_knife_widths(loop.offsets_um - runout, pitch_mm, runout.size)
        cvs.append(cv)
        offsets.append(loop.offsets_um)
        noisy = w_k + noise_mm * rng.standard_normal(w_k.size)
        t += 1.0
        loop.update(knife_widths_mm=noisy, pitch_mm=pitch_mm, now_s=t, cut_at_s=t - 0.5)
    return np.array(cvs), np.array(offsets), loop


# -- width model -----------------------------------------------------------------------------
def test_second_difference_is_circulant_and_kills_constants():
    for z in (1, 2, 3, 4, 7):
        d = second_difference(z)
        assert np.allclose(d @ np.ones(z), 0.0)
        assert np.allclose(d, d.T)
        assert np.allclose(np.roll(np.roll(d, 1, 0), 1, 1), d)
    lam = np.sort(np.linalg.eigvalsh(second_difference(6)))
    expect = np.sort(-4 * np.sin(np.pi * np.arange(6) / 6) ** 2)
    assert np.allclose(lam, expect)


@settings(max_examples=40, deadline=None)
@given(
    z=st.lists(st.floats(-4.0, 4.0), min_size=2, max_size=8),
    pitch=st.floats(1.0, 3.0),
)
def test_linear_width_model_matches_the_envelope_while_every_mark_exists(z, pitch):
    lin = linear_widths_mm(z, pitch_mm=pitch, radius_mm=R_MM)
    if lin.min() < 0.05 * pitch:
        return  # near vanishing: not the linear regime
    w_k, _ = per_knife_widths(z, pitch, len(z))
    assert np.allclose(w_k, lin, atol=1e-9)  # exact for parabolas of one curvature


def test_a_deeper_knife_makes_its_own_mark_wider():
    z = np.zeros(4)
    z[1] = -3.0  # knife 1 cuts 3 um deeper
    w_k, _ = per_knife_widths(z, 1.5, 4)
    g = R_MM / 1.5 * 1e-3
    assert w_k[1] == pytest.approx(1.5 + 2 * 3.0 * g)
    assert w_k[0] == pytest.approx(1.5 - 3.0 * g) and w_k[2] == pytest.approx(1.5 - 3.0 * g)
    assert w_k[3] == pytest.approx(1.5)


def test_offsets_equal_to_runouts_make_every_mark_equal():
    runout = np.array([0.0, 2.5, -1.5, 1.0])
    for shift in (0.0, 3.0):
        w_k, cv = per_knife_widths(runout + shift - runout, 1.5, 4)
        assert cv < 1e-9
        assert np.allclose(w_k, 1.5)
    _, cv0 = per_knife_widths(-runout, 1.5, 4)
    assert cv0 >= 0.10


def test_a_much_too_shallow_knife_leaves_no_mark_and_the_linear_width_is_negative():
    z = np.array([0.0, 25.0, 0.0, 0.0])  # knife 1 25 um shallower
    w_k, _ = per_knife_widths(z, 1.5, 4)
    assert math.isnan(w_k[1])
    assert linear_widths_mm(z, pitch_mm=1.5, radius_mm=R_MM)[1] < 0


# -- configuration ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("knives", 0),
        ("radius_mm", 0.0),
        ("stroke_um", -1.0),
        ("margin_um", 25.0),
        ("gain", 0.0),
        ("gain", 1.5),
        ("deadband_mm", -0.1),
        ("measurements_per_step", 0),
    ],
)
def test_config_rejects_bad_values_naming_the_field(key, value):
    with pytest.raises(ValueError, match=key):
        UniformityLoopConfig(**{key: value})


def test_config_from_mapping():
    cfg = UniformityLoopConfig.from_mapping({"gain": 0.3}, knives=6)
    assert cfg.gain == 0.3 and cfg.knives == 6 and cfg.offset_limit_um == 18.0
    with pytest.raises(ConfigError, match="uniformity_loop.learning_rate"):
        UniformityLoopConfig.from_mapping({"learning_rate": 0.3})


# -- learning law ----------------------------------------------------------------------------
def test_converges_from_the_default_runout_within_a_few_iterations():
    runout = np.array([0.0, 2.5, -1.5, 1.0])
    cvs, offsets, loop = run_ilc(runout, iterations=12)
    assert cvs[0] >= 0.10
    assert cvs[3] <= 0.05  # gamma = 0.4: the error shrinks by 0.6 per iteration
    assert np.all(np.diff(cvs[:6]) < 0)
    assert cvs[-1] < 0.005  # down to the deadband (0.005 mm)
    assert np.allclose(offsets.sum(axis=1), 0.0, atol=1e-9)
    assert np.all(np.abs(offsets) <= loop.cfg.offset_limit_um + 1e-12)
    assert np.allclose(offsets[-1], runout - runout.mean(), atol=0.25)
    # each iteration multiplies the width error by (1 - gamma) in the linear regime
    ratios = cvs[1:6] / cvs[:5]
    assert np.allclose(ratios, 1 - loop.cfg.gain, atol=0.01)


def test_converges_with_measurement_noise():
    runout = np.array([0.0, 2.5, -1.5, 1.0])
    finals = []
    for seed in range(5):
        cvs, offsets, _ = run_ilc(runout, iterations=20, noise_mm=0.02, seed=seed)
        assert cvs[0] >= 0.10
        assert np.all(cvs[5:] <= 0.05)
        finals.append(cvs[8:].mean())
    assert np.mean(finals) < 0.03


def test_averaging_measurements_reduces_noise():
    runout = np.array([0.0, 2.5, -1.5, 1.0])
    cfg = UniformityLoopConfig(measurements_per_step=4)
    loop = UniformityLoop(cfg)
    rng = np.random.default_rng(3)
    t = 0.0
    for _ in range(40):
        w_k, _ = per_knife_widths(loop.offsets_um - runout, 1.5, 4)
        t += 1.0
        loop.update(
            knife_widths_mm=w_k + 0.03 * rng.standard_normal(4),
            pitch_mm=1.5,
            now_s=t,
            cut_at_s=t - 0.5,
        )
    assert loop.steps == 10
    _, cv = per_knife_widths(loop.offsets_um - runout, 1.5, 4)
    assert cv < 0.03


def test_a_missing_mark_is_pushed_deeper_until_it_reappears():
    runout = np.array([2.0, -20.0, 3.0, 1.0])  # knife 1 far too short: no mark at first
    w0, _ = per_knife_widths(-runout, 1.5, 4)
    assert math.isnan(w0[1])
    cvs, offsets, loop = run_ilc(runout, iterations=20)
    assert offsets[1, 1] < 0  # its offset went down first (cuts deeper)
    assert cvs[-1] <= 0.01
    assert np.all(np.abs(offsets) <= loop.cfg.offset_limit_um + 1e-12)
    assert np.allclose(offsets.sum(axis=1), 0.0, atol=1e-9)


def test_stroke_limit_without_windup():
    cfg = UniformityLoopConfig()
    far = np.array([0.0, 40.0, 0.0, 0.0])  # needs 30 um on knife 1: beyond the 18 um limit
    cvs, offsets, loop = run_ilc(far, iterations=15, cfg=cfg)
    assert np.max(np.abs(offsets)) == pytest.approx(cfg.offset_limit_um)
    assert np.allclose(offsets.sum(axis=1), 0.0, atol=1e-9)
    assert cvs[-1] < cvs[0]
    # the runout returns to a reachable value: the stored offsets are the projected ones, so the
    # distance to the new solution shrinks by about (1 - gain) from the very first step
    near = np.array([0.0, 2.5, -1.5, 1.0])
    target = near - near.mean()
    dist = [np.linalg.norm(loop.offsets_um - target)]
    t = 100.0
    for _ in range(8):
        w_k, _ = per_knife_widths(loop.offsets_um - near, 1.5, 4)
        t += 1.0
        loop.update(knife_widths_mm=w_k, pitch_mm=1.5, now_s=t, cut_at_s=t - 0.5)
        dist.append(np.linalg.norm(loop.offsets_um - target))
    assert np.all(np.array(dist[1:]) <= 0.66 * np.array(dist[:-1]))
    _, cv = per_knife_widths(loop.offsets_um - near, 1.5, 4)
    assert cv <= 0.05


@settings(max_examples=25, deadline=None)
@given(
    runout=st.lists(st.floats(-8.0, 8.0), min_size=2, max_size=8),
    pitch=st.floats(1.0, 2.5),
)
def test_converges_for_any_reachable_runout(runout, pitch):
    cvs, offsets, loop = run_ilc(runout, pitch_mm=pitch, iterations=30)
    assert cvs[-1] <= 0.01 or cvs[-1] <= 0.1 * cvs[0]
    assert np.all(np.abs(offsets) <= loop.cfg.offset_limit_um + 1e-12)
    assert np.allclose(offsets.sum(axis=1), 0.0, atol=1e-9)


def test_single_knife_has_nothing_to_equalise():
    loop = UniformityLoop(UniformityLoopConfig(knives=1))
    out = loop.update(knife_widths_mm=[1.5], pitch_mm=1.5, now_s=1.0)
    assert np.array_equal(out, [0.0])


def test_hold_off_until_the_previous_offsets_are_visible():
    cfg = UniformityLoopConfig(settle_s=0.05, holdoff_s=2.0)
    loop = UniformityLoop(cfg)
    w = [1.4, 1.7, 1.3, 1.6]
    loop.update(knife_widths_mm=w, pitch_mm=1.5, now_s=10.0, cut_at_s=9.5)
    assert loop.status == "stepped"
    first = loop.offsets_um
    # board cut before the change (+ settle): not yet showing the new offsets
    loop.update(knife_widths_mm=w, pitch_mm=1.5, now_s=10.4, cut_at_s=10.03)
    assert loop.status == "waiting" and np.array_equal(loop.offsets_um, first)
    loop.update(knife_widths_mm=w, pitch_mm=1.5, now_s=10.8, cut_at_s=10.06)
    assert loop.status == "stepped"
    # without a cut time: the hold-off counts from the change
    loop.update(knife_widths_mm=w, pitch_mm=1.5, now_s=12.0)
    assert loop.status == "waiting"
    loop.update(knife_widths_mm=w, pitch_mm=1.5, now_s=12.81)
    assert loop.status == "stepped"


def test_reset_with_offsets_waits_for_them():
    loop = UniformityLoop(UniformityLoopConfig())
    loop.reset([30.0, 0.0, 0.0, 0.0], now_s=5.0)
    assert loop.offsets_um.sum() == pytest.approx(0.0, abs=1e-9)
    assert np.max(np.abs(loop.offsets_um)) <= 18.0
    loop.update(knife_widths_mm=[1.4, 1.7, 1.3, 1.6], pitch_mm=1.5, now_s=5.1, cut_at_s=4.8)
    assert loop.status == "waiting"


def test_deadband_and_no_marks():
    loop = UniformityLoop(UniformityLoopConfig(deadband_mm=0.01))
    loop.update(knife_widths_mm=[1.5, 1.505, 1.495, 1.5], pitch_mm=1.5, now_s=1.0)
    assert loop.status == "deadband"
    loop.update(knife_widths_mm=[math.nan] * 4, pitch_mm=1.5, now_s=2.0)
    assert loop.status == "no_marks"
    assert np.array_equal(loop.offsets_um, np.zeros(4))


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"knife_widths_mm": [1.5, 1.5, 1.5]}, "knife_widths_mm"),
        ({"knife_widths_mm": [1.5, -1.0, 1.5, 1.5]}, "knife_widths_mm"),
        ({"knife_widths_mm": [1.5, math.inf, 1.5, 1.5]}, "knife_widths_mm"),
        ({"pitch_mm": 0.0}, "pitch_mm"),
        ({"now_s": math.nan}, "now_s"),
        ({"cut_at_s": math.nan}, "cut_at_s"),
    ],
)
def test_update_rejects_bad_inputs(kwargs, name):
    loop = UniformityLoop(UniformityLoopConfig())
    args = {"knife_widths_mm": [1.5] * 4, "pitch_mm": 1.5, "now_s": 1.0} | kwargs
    with pytest.raises(ValueError, match=name):
        loop.update(**args)


@settings(max_examples=60, deadline=None)
@given(
    v=st.lists(st.floats(-100.0, 100.0), min_size=1, max_size=9),
    bound=st.floats(0.5, 30.0),
)
def test_projection_is_zero_mean_in_box_and_idempotent(v, bound):
    p = project_zero_mean_box(np.array(v), bound=bound)
    assert abs(p.sum()) <= 1e-9 * max(1.0, bound * len(v))
    assert np.all(np.abs(p) <= bound + 1e-12)
    assert np.allclose(project_zero_mean_box(p, bound=bound), p, atol=1e-9)
    # optimality: no feasible random point is closer
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = project_zero_mean_box(p + rng.normal(0, bound, len(v)), bound=bound)
        assert np.linalg.norm(np.array(v) - p) <= np.linalg.norm(np.array(v) - q) + 1e-9


# -- against the simulator's surface (when plant_sim.surface exists) -------------------------
def test_against_plant_sim_surface():
    surface = pytest.importorskip("plant_sim.surface")
    for name in ("Cutterhead", "passes_steady", "envelope"):
        if not hasattr(surface, name):
            pytest.skip(f"plant_sim.surface has no {name} yet")
    runout = (0.0, 2.5, -1.5, 1.0)
    head = surface.Cutterhead(knives=4, radius_mm=R_MM, runout_um=runout)
    rpm, feed = 6000.0, 600.0  # pitch 1.5 mm
    x = np.linspace(0.0, 120.0, 24001)

    def measure(offsets):
        passes = surface.passes_steady(
            head,
            spindle_rpm=rpm,
            feed_mm_s=feed,
            x_start_mm=0.0,
            x_end_mm=120.0,
            offsets_um=offsets,
        )
        s = surface.envelope(x, passes)
        w = np.asarray(s.widths_mm)
        return knife_means(w, np.asarray(s.knife), 4), float(np.std(w) / np.mean(w))

    loop = UniformityLoop(UniformityLoopConfig())
    _, cv0 = measure(loop.offsets_um)
    assert cv0 >= 0.10
    t = 0.0
    for _ in range(5):
        w_k, _ = measure(loop.offsets_um)
        t += 1.0
        loop.update(knife_widths_mm=w_k, pitch_mm=1.5, now_s=t, cut_at_s=t - 0.5)
    _, cv = measure(loop.offsets_um)
    assert cv <= 0.05


def test_knife_attribution_off_by_one_makes_learning_diverge():
    # why controller.knife_phase matters: a shifted attribution turns each mode by 2 pi m / Z,
    # and |1 - gamma exp(j theta)| > 1 for theta >= pi/2 (Z = 4)
    runout = np.array([0.0, 2.5, -1.5, 1.0])
    loop = UniformityLoop(UniformityLoopConfig())
    cvs, t = [], 0.0
    for _ in range(6):
        w_k, cv = per_knife_widths(loop.offsets_um - runout, 1.5, 4)
        cvs.append(cv)
        t += 1.0
        loop.update(knife_widths_mm=np.roll(w_k, 1), pitch_mm=1.5, now_s=t, cut_at_s=t - 0.5)
    assert np.all(np.diff(cvs) > 0)


def test_vanishing_threshold_of_a_neighbour_mark():
    # one knife standing out by d: its neighbours' marks vanish at d = f^2 / R (linear model
    # exact for parabolas), the opposite knife's at 2 f^2 / R (Z = 4)
    f = 1.5
    d1 = f * f / R_MM * 1e3
    w_below, _ = per_knife_widths(np.array([-0.98 * d1, 0, 0, 0]), f, 4)
    w_above, _ = per_knife_widths(np.array([-1.02 * d1, 0, 0, 0]), f, 4)
    assert np.all(np.isfinite(w_below)) and math.isnan(w_above[1]) and math.isnan(w_above[3])
    w_one, _ = per_knife_widths(np.array([-2.02 * d1, 0, 0, 0]), f, 4)
    assert np.sum(np.isfinite(w_one)) == 1 and w_one[0] == pytest.approx(4 * f)
