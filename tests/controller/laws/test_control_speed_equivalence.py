"""The fast paths of the per-pair control and checks give what the straightforward code gives.

The per-pair path works in plain floats and sets up once what it can. Each
test here holds a fast path against the straightforward numpy computation it replaced (written
out below as the reference): bit for bit where the arithmetic is the same (attribution, feed
history, offset history, mean and std of a few values), within 1e-12 where only the rounding
differs (the QP's fast path, the uniformity step, the identification's DFT). No timing here.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.actuator_id import ActuatorIdentifier, circulant_from_mode_gains
from controller.laws.feed_loop import FeedLoop, FeedLoopConfig, integral_gain
from controller.laws.knife_phase import PassAttribution, attribute_marks, pass_numbers
from controller.laws.limits import project_zero_mean_box
from controller.laws.offset_history import OffsetHistory
from controller.laws.offset_qp import OffsetPlanner, _active_set, box_qp
from controller.laws.uniformity_loop import (
    UniformityLoop,
    UniformityLoopConfig,
    linear_widths_mm,
    second_difference,
    width_sensitivity_mm_per_um,
)
from controller.service.attribution import _vanished, kinematic_cv, mean_std

# ------------------------------------------------------------------------------ the box QP


def _problem(knives: int, seed: int, spread: float) -> tuple[np.ndarray, np.ndarray]:
    """``H`` (PD on the zero-sum subspace) and ``W A`` of a random actuator."""
    rng = np.random.default_rng(seed)
    a = np.eye(knives) + spread * rng.standard_normal((knives, knives)) + 0.5 * np.eye(knives)
    wa = second_difference(knives) @ a
    h = wa.T @ wa
    return h / float(np.max(np.diag(h))), a


def _zero_sum(rng: np.random.Generator, knives: int) -> np.ndarray:
    o = rng.normal(0.0, 1.0, knives)
    return o - o.mean()


def _objective(h: np.ndarray, c: np.ndarray, o: np.ndarray) -> float:
    return float(0.5 * o @ h @ o - c @ o)


@pytest.mark.parametrize("knives", [2, 3, 4, 6, 8])
@pytest.mark.parametrize("edge", [-1e-3, -1e-12, 0.0, 1e-12, 1e-3, 0.5])
def test_box_qp_fast_path_agrees_with_the_iteration_on_and_near_the_box_edge(knives, edge):
    """The unconstrained optimum placed just inside, on, and just outside the box."""
    rng = np.random.default_rng(knives)
    h, _ = _problem(knives, knives, 0.3)
    target = _zero_sum(rng, knives)
    bound = 3.0
    target *= bound * (1.0 + edge) / np.max(np.abs(target))  # largest entry at the edge
    c = h @ target  # the unconstrained zero-sum minimiser is ``target`` (nu = 0)
    start = project_zero_mean_box(_zero_sum(rng, knives), bound=bound)
    fast = box_qp(h, c, bound=bound, start=start)
    slow = _active_set(h, c, bound, start)
    assert abs(fast.sum()) <= 1e-12 * bound and np.all(np.abs(fast) <= bound)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-9 * bound)
    assert _objective(h, c, fast) <= _objective(h, c, slow) + 1e-12 * max(1.0, abs(
        _objective(h, c, slow)))
    if edge < 0:  # inside: the unconstrained optimum itself
        np.testing.assert_allclose(fast, target, rtol=0, atol=1e-12 * bound)


@settings(max_examples=80, deadline=None)
@given(
    knives=st.integers(2, 8),
    seed=st.integers(0, 10_000),
    bound=st.floats(0.05, 20.0),
    scale=st.floats(0.01, 3.0),
    spread=st.floats(0.0, 0.5),
)
def test_box_qp_fast_path_agrees_with_the_iteration(knives, seed, bound, scale, spread):
    rng = np.random.default_rng(seed)
    h, _ = _problem(knives, seed, spread)
    c = h @ (_zero_sum(rng, knives) * bound * scale)
    start = project_zero_mean_box(_zero_sum(rng, knives) * bound, bound=bound)
    fast = box_qp(h, c, bound=bound, start=start)
    slow = _active_set(h, c, bound, start)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-9 * max(1.0, bound))
    assert np.all(np.abs(fast) <= bound) and abs(fast.sum()) <= 1e-12 * max(1.0, bound) * knives


def _best_offsets_reference(s, w, a, bound, start):
    """The straightforward best_offsets_um: H and c built per call, the active set from start."""
    wa = w @ a
    h = wa.T @ wa
    c = wa.T @ (w @ s)
    scale = float(np.max(np.abs(np.diag(h)))) or 1.0
    return _active_set(h / scale, c / scale, bound, start)


@settings(max_examples=80, deadline=None)
@given(
    knives=st.integers(2, 8),
    seed=st.integers(0, 10_000),
    bound=st.floats(0.5, 20.0),
    runout=st.floats(0.1, 40.0),
    spread=st.floats(0.0, 0.4),
)
def test_the_planner_set_up_once_gives_the_straightforward_optimum(knives, seed, bound, runout,
                                                                  spread):
    rng = np.random.default_rng(seed)
    _, a = _problem(knives, seed, spread)
    w = second_difference(knives)
    planner = OffsetPlanner(width_operator=w, actuator=a)
    for _ in range(3):  # one set-up, several disturbances
        s = rng.normal(0.0, runout, knives)
        start = project_zero_mean_box(_zero_sum(rng, knives) * bound, bound=bound)
        got = planner.best_offsets_um(s, bound_um=bound, start_um=start)
        ref = _best_offsets_reference(s, w, a, bound, start)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * max(1.0, bound))
        assert np.all(np.abs(got) <= bound) and abs(got.sum()) <= 1e-12 * bound * knives


@pytest.mark.parametrize("bad", [[1.0, math.nan, 0.0, 0.0], [1.0, 2.0, 3.0]])
def test_the_planner_refuses_bad_disturbances(bad):
    planner = OffsetPlanner(width_operator=second_difference(4), actuator=np.eye(4))
    with pytest.raises(ValueError, match="disturbance_um"):
        planner.best_offsets_um(bad, bound_um=5.0)


# ----------------------------------------------------------------------- the uniformity step


def _identify_reference(state: dict, o: np.ndarray, y: np.ndarray, ident: ActuatorIdentifier):
    """The straightforward identification step (numpy FFT and masks); updates ``state``."""
    om = np.fft.fft(o, norm="ortho")
    ym = np.fft.fft(y, norm="ortho")
    past = state["past"]
    z = ident.knives
    if past:  # a jump of the width errors with the table steady: start the differences again
        o1, y1 = past[-1]
        steady = np.max(np.abs(om - o1)[1:]) < 0.5 * ident.min_step_um
        if steady and np.any(np.abs((ym - y1) - state["gains"] * (om - o1))[1:] > ident.jump_um):
            past.clear()
    if len(past) == ident.lag:
        o0, y0 = past[0]
        do, dy = om - o0, ym - y0
        moved = np.abs(do) >= ident.min_step_um
        moved[0] = False
        ratio = np.where(moved, dy / np.where(moved, do, 1.0), 0.0)
        moved &= (np.abs(ratio) >= 0.25 * ident.gain_min) & (np.abs(ratio) <= 1.5 * ident.gain_max)
        moved &= np.abs(np.angle(ratio)) <= ident.gate_phase
        # a confident mode takes only differences that agree with its estimate
        a = state["raw"]
        n = state["n"]
        res = (state["syy"] - 2.0 * np.real(np.conj(a) * state["soy"])
               + np.abs(a) ** 2 * state["soo"])
        sigma = np.sqrt(np.maximum(res, 0.0) / np.maximum(n - 1.0, 1.0))
        se = _stderr_reference(state, ident)
        confident = (n >= ident.min_samples - 1e-9) & (2.0 * se < np.abs(a))
        agree = (np.abs(dy - a * do)
                 <= np.maximum(0.5 * np.abs(a), 3.0 * se) * np.abs(do) + 3.0 * sigma)
        outlier = moved & confident & ~agree
        moved &= ~outlier
        state["rejected"] = np.where(outlier, state["rejected"] + 1,
                                     np.where(moved, 0, state["rejected"]))
        lam = np.where(moved, ident.forget, 1.0)
        state["soo"] = lam * state["soo"] + np.where(moved, np.abs(do) ** 2, 0.0)
        state["soy"] = lam * state["soy"] + np.where(moved, np.conj(do) * dy, 0.0)
        state["syy"] = lam * state["syy"] + np.where(moved, np.abs(dy) ** 2, 0.0)
        state["n"] = lam * state["n"] + np.where(moved, 1.0, 0.0)
        for m in np.flatnonzero(state["rejected"] >= ident.reject_reset):
            for k in {int(m), (z - int(m)) % z}:
                state["soo"][k] = state["syy"][k] = state["n"][k] = 0.0
                state["soy"][k] = 0.0
                state["rejected"][k] = 0
        if np.any(moved):
            _fit_reference(state, ident)
            # a mode that was confident and lost all confidence is learnt afresh
            conf = _confidence_reference(state, ident)
            lost = [m for m in range(1, z) if conf[m] <= 0.0 and state["confident"][m]]
            state["confident"] |= conf > 0.0
            if lost:
                for m in lost:
                    for k in {m, (z - m) % z}:
                        state["soo"][k] = state["syy"][k] = state["n"][k] = 0.0
                        state["soy"][k] = 0.0
                        state["rejected"][k] = 0
                        state["confident"][k] = False
                _fit_reference(state, ident)
    past.append((om, ym))
    del past[: max(0, len(past) - ident.lag)]


def _stderr_reference(state: dict, ident: ActuatorIdentifier) -> np.ndarray:
    """The fit's standard error and the prior's pull in quadrature, per mode."""
    a, n, soo = state["raw"], state["n"], state["soo"]
    res = state["syy"] - 2.0 * np.real(np.conj(a) * state["soy"]) + np.abs(a) ** 2 * soo
    w = soo + ident.prior_um2
    fit = np.maximum(res, 0.0) / np.maximum(n - 1.0, 1.0) / w
    pull = ident.prior_um2 * np.abs(1.0 - a) / w
    return np.sqrt(fit + pull ** 2)


def _confidence_reference(state: dict, ident: ActuatorIdentifier) -> np.ndarray:
    n = state["n"]
    se = np.where(n >= 1.5, _stderr_reference(state, ident), np.inf)
    conf = np.clip(1.0 - 2.0 * se / np.maximum(np.abs(state["raw"]), 1e-12), 0.0, 1.0)
    conf[n < ident.min_samples - 1e-9] = 0.0
    conf[0] = 1.0
    return conf


def _fit_reference(state: dict, ident: ActuatorIdentifier) -> None:
    z = ident.knives
    a = (state["soy"] + ident.prior_um2) / (state["soo"] + ident.prior_um2)
    if z % 2 == 0:
        a[z // 2] = a[z // 2].real
    a[0] = 1.0
    for m in range(1, (z + 1) // 2):
        a[z - m] = np.conj(a[m])
    state["raw"] = a.copy()
    low = np.where(_confidence_reference(state, ident) > 0.0, ident.gain_min,
                   max(ident.gain_min, ident.unconfirmed_gain_min))
    mag = np.clip(np.abs(a), low, ident.gain_max)
    phase = np.clip(np.angle(a), -ident.phase_max, ident.phase_max)
    a = mag * np.exp(1j * phase)
    if z % 2 == 0:
        a[z // 2] = a[z // 2].real
    for m in range(1, (z + 1) // 2):
        a[z - m] = np.conj(a[m])
    a[0] = 1.0
    state["gains"] = a


def _id_state(knives: int) -> dict:
    """The reference identification's starting state."""
    return {"past": [], "soo": np.zeros(knives), "soy": np.zeros(knives, complex),
            "syy": np.zeros(knives), "n": np.zeros(knives), "rejected": np.zeros(knives, int),
            "raw": np.ones(knives, complex), "gains": np.ones(knives, complex),
            "confident": np.zeros(knives, bool)}


@settings(max_examples=30, deadline=None)
@given(knives=st.integers(2, 8), seed=st.integers(0, 10_000), lag=st.integers(1, 4))
def test_the_identification_in_plain_numbers_follows_the_fft_version(knives, seed, lag):
    rng = np.random.default_rng(seed)
    ident = ActuatorIdentifier(knives, lag_pairs=lag, min_step_um=0.3, memory=20.0)
    state = _id_state(knives)
    truth = np.fft.fft(np.r_[0.7, 0.2, np.zeros(knives - 2)])  # a lagging actuator
    runout = rng.normal(0.0, 5.0, knives)
    for _ in range(25):
        o = rng.normal(0.0, 3.0, knives)
        y = np.real(np.fft.ifft(truth * np.fft.fft(o))) - runout + rng.normal(0, 0.05, knives)
        ident.add(o, y)
        _identify_reference(state, o, y, ident)
        np.testing.assert_allclose(ident.mode_gains, state["gains"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ident.excitation_um2, state["soo"], rtol=1e-12, atol=1e-12)
    assert np.allclose(ident.matrix(), circulant_from_mode_gains(ident.mode_gains), atol=0)
    assert ident.matrix() is not ident.matrix()  # a copy each time, the shared one set up once


def _uniformity_reference(loop: UniformityLoop, widths, pitch, now, cut_at, cut_until, state):
    """The straightforward uniformity step (numpy throughout) from a copy of the loop's state.

    Returns the offsets it would apply; ``state`` is the reference identification's.
    """
    cfg = loop.cfg
    w = np.asarray(widths, dtype=float)
    t0 = cut_at - cfg.settle_s
    t1 = cut_until - cfg.settle_s
    o_cut = loop._history.mean_over(t0, t1)
    if o_cut is None:
        return None
    delay = now - 0.5 * (t0 + t1)
    err = np.nan_to_num(w, nan=0.0)
    err = err - err.mean()
    y = np.linalg.pinv(second_difference(cfg.knives)) @ err / width_sensitivity_mm_per_um(
        pitch, cfg.radius_mm)
    if np.all(np.isfinite(w)) and np.all(w > 0) and np.all(w >= cfg.id_min_width_frac * pitch):
        _identify_reference(state, o_cut, y, loop._ident)  # every mark in the linear regime
    else:
        state["past"].clear()
    a_hat = circulant_from_mode_gains(state["gains"])
    s_est = a_hat @ o_cut - y
    s_est -= s_est.mean()
    g = min(integral_gain(cfg.ki, cfg.sample_time_s, delay), 1.0)
    if loop._open_table is not None and np.allclose(o_cut, loop._open_table, atol=1e-9):
        g = max(g, 1.0 / (loop._estimates + 1))
    offsets = loop.offsets_um
    bound = loop.limit_um
    best = _best_offsets_reference(s_est, second_difference(cfg.knives), a_hat, bound, offsets)
    return project_zero_mean_box(offsets + g * (best - offsets), bound=bound)


@pytest.mark.parametrize(("knives", "runout_um", "stroke_um"), [
    (4, [0.5, 15.0, -8.5, 5.0], 20.0),  # the bound active at first
    (4, [1.0, -2.0, 0.5, 0.3], 20.0),  # well inside
    (2, [3.0, -3.0], 5.0),
    (3, [4.0, -1.0, 2.0], 2.0),  # a small stroke: the box decides
    (6, [1.0, -4.0, 2.0, 0.0, 6.0, -2.5], 8.0),
])
def test_the_uniformity_step_in_plain_numbers_follows_the_numpy_version(knives, runout_um,
                                                                        stroke_um):
    """Closed loop on the linear width model with a lagging actuator; step by step."""
    runout = np.asarray(runout_um, dtype=float)
    cfg = UniformityLoopConfig(knives=knives, stroke_um=stroke_um, id_min_step_um=0.1,
                               id_lag_pairs=2)
    loop = UniformityLoop(cfg)
    state = _id_state(knives)
    actuator = circulant_from_mode_gains(np.fft.fft(np.r_[0.8, 0.15, np.zeros(knives - 2)]))
    pitch = 1.5
    steps = 0
    for k in range(1, 40):
        now = 0.1 * k
        o_board = loop._history.mean_over(now - 0.35 - cfg.settle_s, now - 0.3 - cfg.settle_s)
        o_board = loop.offsets_um if o_board is None else o_board
        w = linear_widths_mm(actuator @ o_board - runout, pitch_mm=pitch, radius_mm=cfg.radius_mm)
        w = np.where(w > 0, w, np.nan)  # a vanished mark
        ref = _uniformity_reference(copy.deepcopy(loop), w, pitch, now, now - 0.35, now - 0.3,
                                    state)
        got = loop.update(knife_widths_mm=w, pitch_mm=pitch, now_s=now, cut_at_s=now - 0.35,
                          cut_until_s=now - 0.3)
        if ref is None:
            assert loop.status == "waiting"
            continue
        steps += 1
        assert loop.status == "stepped"
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * stroke_um)
        assert np.all(np.abs(got) <= loop.limit_um) and abs(got.sum()) <= 1e-12 * stroke_um
        np.testing.assert_allclose(loop.mode_gains, state["gains"], rtol=0, atol=1e-12)
    assert steps > 20


# ------------------------------------------------------------------- attribution, bit for bit


def _attribute_reference(b, c, *, counts_a, index_latch_counts, cutter_to_camera_mm,
                         counts_per_mm, px_per_mm, cx_px, pass_guide_mm, knives, min_inset_mm):
    """The straightforward attribute_marks (numpy throughout, three refinements)."""
    b = np.asarray(b, dtype=float)
    c = np.asarray(c, dtype=float)
    centre = 0.5 * (c[:-1] + c[1:])
    reliable = np.minimum(b - c[:-1], c[1:] - b) >= min_inset_mm
    kw = dict(counts_a=counts_a, index_latch_counts=index_latch_counts,
              cutter_to_camera_mm=cutter_to_camera_mm, counts_per_mm=counts_per_mm,
              px_per_mm=px_per_mm, cx_px=cx_px, pitch_mm=1.0)
    travel = pass_numbers(b, **kw)
    travel_c = pass_numbers(centre, **kw)
    t_rel = travel[reliable][::-1]
    gaps = np.diff(t_rel)
    pitch = pass_guide_mm
    for _ in range(3):
        steps = np.rint(gaps / pitch)
        count = np.concatenate(([0.0], np.cumsum(steps)))
        dc = count - count.mean()
        pitch = float(dc @ (t_rel - t_rel.mean()) / (dc @ dc))
    n_rel = travel[reliable] / pitch
    resultant = np.mean(np.exp(2j * np.pi * n_rel))
    phase = float(np.angle(resultant)) / (2.0 * np.pi)
    spread = float(np.sqrt(-2.0 * np.log(max(float(np.abs(resultant)), 1e-300))) / (2 * np.pi))
    q = np.rint(-(np.where(reliable, travel, travel_c) / pitch - phase)).astype(np.int64)
    for i in range(1, q.size):
        if not reliable[i]:
            q[i] = max(q[i], q[i - 1] + 1)
    for i in range(q.size - 2, -1, -1):
        if not reliable[i]:
            q[i] = min(q[i], q[i + 1] - 1)
    span = -np.arange(int(q.min()), int(q.max()) + 1)
    return dict(passes=-q, knife=np.mod(-q, knives), reliable=reliable, pass_mm=pitch,
                phase=phase, spread=spread,
                passes_per_knife=np.bincount(np.mod(span, knives), minlength=knives))


@settings(max_examples=80, deadline=None)
@given(
    knives=st.integers(1, 6),
    pitch=st.floats(0.8, 3.0),
    guide_error=st.floats(-0.12, 0.12),
    latch=st.integers(0, (1 << 32) - 1),
    noise=st.floats(0.0, 0.03),
    narrow=st.integers(0, 5),
    drop=st.integers(0, 3),
    seed=st.integers(0, 1000),
)
def test_attribution_is_bit_for_bit_the_straightforward_one(knives, pitch, guide_error, latch,
                                                            noise, narrow, drop, seed):
    rng = np.random.default_rng(seed)
    cpm, ppm, cx, length = 100.0, 16.0, 329.5, 300.0
    counts_a = (latch + round(length * cpm) + 37) % (1 << 32)
    j = np.arange(40, -41, -1)  # later passes lie upstream: x increases with j falling
    base = (counts_a - latch) % (1 << 32)  # the counts since the latch, wrap included
    x = (base - j * pitch * cpm) / cpm - length + cx / ppm
    keep = (x >= 0) & (x <= 659 / ppm)
    x = x[keep]
    if drop and x.size > 8:  # a knife left no mark: its mark merges into the neighbour's
        x = np.delete(x, 3)
    x = np.sort(x + rng.normal(0.0, noise * pitch, x.size))
    cusps = np.r_[x[0] - 0.5 * pitch, 0.5 * (x[:-1] + x[1:]), x[-1] + 0.5 * pitch]
    bottoms = x.copy()
    for i in rng.choice(x.size, size=min(narrow, x.size), replace=False):
        bottoms[i] = cusps[i] + 0.01  # a bottom clipped to its cusp: not reliable
    kw = dict(counts_a=counts_a, index_latch_counts=latch, cutter_to_camera_mm=length,
              counts_per_mm=cpm, px_per_mm=ppm, cx_px=cx, pass_guide_mm=pitch * (1 + guide_error),
              knives=knives, min_inset_mm=1.0 / ppm)
    try:
        ref = _attribute_reference(bottoms, cusps, **kw)
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return  # the reference has no checks: cases the checks refuse are not compared
    try:
        got = attribute_marks(bottoms, cusps, **kw)
    except ValueError:
        return  # refused by a check of the real function (two bottoms on a pass, ...)
    for name, value in ref.items():
        mine = getattr(got, name)
        if isinstance(value, np.ndarray):
            assert mine.dtype.kind == value.dtype.kind and np.array_equal(mine, value), name
        else:
            assert mine == value, name  # bit for bit


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 10.0), min_size=1, max_size=12))
def test_mean_and_std_of_a_few_values_are_numpy_s_to_rounding(values):
    a = np.asarray(values, dtype=float)
    mean, std = mean_std(values)
    assert mean == pytest.approx(float(a.mean()), rel=1e-13, abs=1e-300)
    assert std == pytest.approx(float(a.std()), rel=1e-9, abs=1e-12)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.one_of(st.floats(0.0, 5.0), st.just(math.nan)), min_size=1, max_size=8))
def test_kinematic_cv_is_the_numpy_formula(widths):
    w = np.asarray(widths, dtype=float)
    w = w[np.isfinite(w)]
    mean = float(w.mean()) if w.size else math.nan
    ref = float(w.std() / mean) if mean > 0 else math.nan
    got = kinematic_cv(widths)
    assert got == pytest.approx(ref, rel=1e-9, abs=1e-12) or (math.isnan(got) and math.isnan(ref))


@settings(max_examples=100, deadline=None)
@given(knives=st.integers(1, 8), data=st.data())
def test_widths_per_knife_and_vanished_knives_are_the_bincount_formulas(knives, data):
    marks = data.draw(st.lists(st.integers(0, knives - 1), max_size=30))
    per = data.draw(st.lists(st.integers(0, 9), min_size=knives, max_size=knives))
    per = [max(p, 1) if k in marks else p for k, p in enumerate(per)]
    widths = data.draw(st.lists(st.floats(0.0, 5.0), min_size=len(marks), max_size=len(marks)))
    knife = np.asarray(marks, dtype=np.int64)
    ppk = np.asarray(per, dtype=np.intp)
    marked = np.bincount(knife, minlength=knives) > 0
    assert _vanished(ppk.tolist(), knife.tolist()) == tuple(
        int(k) for k in np.flatnonzero((ppk > 0) & ~marked))
    pa = PassAttribution(passes=-knife, knife=knife, reliable=np.ones(knife.size, bool),
                         pass_mm=1.0, phase=0.0, spread=0.0, passes_per_knife=ppk)
    sums = np.bincount(knife, weights=np.asarray(widths, dtype=float), minlength=knives)
    ref = np.full(knives, np.nan)
    ref[marked] = sums[marked] / ppk[marked]
    np.testing.assert_array_equal(pa.knife_widths(widths), ref)  # NaN where NaN, else exact


# --------------------------------------------------------------- histories, bit for bit


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), knives=st.integers(1, 6))
def test_the_offset_history_mean_is_the_numpy_sum(seed, knives):
    rng = np.random.default_rng(seed)
    hist = OffsetHistory(knives, horizon_s=100.0)
    hist.restart(rng.normal(0, 5, knives), 0.0)
    t = 0.0
    for _ in range(15):
        t += float(rng.uniform(0.01, 0.2))
        hist.append(rng.normal(0, 5, knives), t)
    for _ in range(20):
        t0, t1 = sorted(rng.uniform(0.0, t + 0.3, 2))
        got = hist.mean_over(t0, t1)
        i0 = int(np.searchsorted(hist._t, t0, side="right")) - 1
        i1 = int(np.searchsorted(hist._t, t1, side="right")) - 1
        if i0 == i1 or t1 <= t0:
            np.testing.assert_array_equal(got, hist._v[i0])
            continue
        acc = np.zeros(knives)
        for i in range(i0, i1 + 1):
            a = max(t0, hist._t[i])
            b = t1 if i == i1 else min(t1, hist._t[i + 1])
            acc += np.asarray(hist._v[i]) * max(b - a, 0.0)
        np.testing.assert_array_equal(got, acc / (t1 - t0))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_the_feed_loop_s_pitch_statistics_are_the_straightforward_sums(seed):
    rng = np.random.default_rng(seed)
    loop = FeedLoop(FeedLoopConfig())
    t = 0.0
    for _ in range(30):
        t += float(rng.uniform(0.005, 0.2))
        loop.update(measured_pitch_mm=None, spindle_rpm=float(rng.uniform(3000, 9000)), now_s=t)
    ts, ps = loop._hist_t, loop._hist_p
    for _ in range(20):
        t0, t1 = sorted(rng.uniform(ts[0] - 0.1, t + 0.1, 2))
        got = loop._pitch_stats(t0, t1)
        i0 = int(np.searchsorted(ts, t0, side="right")) - 1
        i1 = int(np.searchsorted(ts, t1, side="right")) - 1
        if i0 < 0:
            assert got is None
            continue
        vals = ps[i0: i1 + 1]
        if t1 <= t0 or i0 == i1:
            assert got == (vals[0], vals[0], vals[0])
            continue
        total = 0.0
        for i in range(i0, i1 + 1):
            a = max(t0, ts[i])
            b = t1 if i == i1 else min(t1, ts[i + 1])
            total += ps[i] * max(b - a, 0.0)
        assert got == (min(vals), max(vals), total / (t1 - t0))
