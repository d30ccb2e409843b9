"""The constrained optimum of the offsets: the exact QP against an enumeration of its faces."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.limits import project_zero_mean_box
from controller.laws.offset_qp import best_offsets_um, box_qp
from controller.laws.uniformity_loop import second_difference


def enumerate_faces(h, c, bound):
    """Oracle: the best stationary point over every face of the box (exact for a convex QP)."""
    n = c.size
    best, best_val = None, np.inf
    for pattern in itertools.product((-1, 0, 1), repeat=n):
        side = np.array(pattern)
        free = side == 0
        o = side * bound
        if free.any():
            nf = int(free.sum())
            kkt = np.block([[h[np.ix_(free, free)], np.ones((nf, 1))],
                            [np.ones((1, nf)), np.zeros((1, 1))]])
            rhs = np.concatenate([c[free] - h[np.ix_(free, ~free)] @ o[~free], [-o[~free].sum()]])
            o = o.astype(float)
            o[free] = np.linalg.lstsq(kkt, rhs, rcond=None)[0][:nf]
        if abs(o.sum()) > 1e-9 or np.any(np.abs(o) > bound + 1e-9):
            continue
        val = 0.5 * o @ h @ o - c @ o
        if val < best_val:
            best, best_val = o, val
    return best, best_val


def objective(h, c, o):
    return 0.5 * o @ h @ o - c @ o


@settings(max_examples=60, deadline=None)
@given(
    knives=st.integers(2, 6),
    seed=st.integers(0, 10_000),
    bound=st.floats(0.5, 15.0),
    spread=st.floats(0.0, 0.6),
)
def test_the_qp_is_the_exact_constrained_optimum(knives, seed, bound, spread):
    rng = np.random.default_rng(seed)
    d = second_difference(knives)
    a = np.eye(knives) + spread * rng.standard_normal((knives, knives))
    a += np.diag(np.full(knives, 0.5))  # keep the actuator invertible
    s = rng.normal(0.0, 10.0, knives)
    o = best_offsets_um(s, width_operator=d, actuator=a, bound_um=bound)
    assert abs(o.sum()) <= 1e-9 * max(1.0, bound)
    assert np.all(np.abs(o) <= bound + 1e-12)
    wa = d @ a
    h, c = wa.T @ wa, wa.T @ (d @ s)
    _, oracle = enumerate_faces(h, c, bound)
    assert objective(h, c, o) <= oracle + 1e-9 * max(1.0, abs(oracle))


@settings(max_examples=40, deadline=None)
@given(
    s=st.lists(st.floats(-30.0, 30.0), min_size=2, max_size=8),
    bound=st.floats(0.5, 20.0),
)
def test_kkt_conditions_hold_at_the_solution(s, bound):
    s = np.asarray(s)
    z = s.size
    d = second_difference(z)
    o = best_offsets_um(s, width_operator=d, actuator=np.eye(z), bound_um=bound)
    grad = d.T @ d @ (o - s)
    free = np.abs(np.abs(o) - bound) > 1e-7
    scale = max(1.0, float(np.max(np.abs(grad))))
    if free.any():
        nu = -grad[free].mean()
        assert np.allclose(grad[free] + nu, 0.0, atol=1e-7 * scale)
        # at a bound the gradient (plus the equality's multiplier) points outward
        up, lo = (o >= bound - 1e-7), (o <= -bound + 1e-7)
        assert np.all(-(grad[up] + nu) >= -1e-7 * scale)
        assert np.all(grad[lo] + nu >= -1e-7 * scale)


def test_inside_the_stroke_the_optimum_is_the_runout():
    s = np.array([0.0, 2.5, -1.5, 1.0])
    o = best_offsets_um(s, width_operator=second_difference(4), actuator=np.eye(4), bound_um=18.0)
    assert np.allclose(o, s - s.mean(), atol=1e-9)
    gain = 0.25 * np.eye(4)  # a weak actuator needs four times the offsets
    o4 = best_offsets_um(s, width_operator=second_difference(4), actuator=gain, bound_um=18.0)
    assert np.allclose(o4, 4 * (s - s.mean()), atol=1e-9)


def test_saturated_optimum_beats_the_clipped_runout_in_width_cv():
    """Stroke 10 um, 2 um margin, runout (0, 15, -8, 5) plus 0.5 um eccentricity."""
    s = np.array([0.5, 15.0, -8.5, 5.0])
    d = second_difference(4)
    o = best_offsets_um(s, width_operator=d, actuator=np.eye(4), bound_um=8.0)
    clipped = project_zero_mean_box(s - s.mean(), bound=8.0)
    assert np.linalg.norm(d @ (o - s)) < 0.85 * np.linalg.norm(d @ (clipped - s))
    assert np.allclose(o, [-4.5, 8.0, -8.0, 4.5], atol=1e-9)


def test_scale_of_the_width_operator_does_not_matter():
    s = np.array([0.5, 15.0, -8.5, 5.0, 2.0])
    d = second_difference(5)
    a = best_offsets_um(s, width_operator=d, actuator=np.eye(5), bound_um=6.0)
    b = best_offsets_um(s, width_operator=1e-3 * d, actuator=np.eye(5), bound_um=6.0)
    assert np.allclose(a, b, atol=1e-9)


def test_a_warm_start_anywhere_gives_the_same_optimum():
    s = np.array([0.5, 15.0, -8.5, 5.0])
    d = second_difference(4)
    ref = best_offsets_um(s, width_operator=d, actuator=np.eye(4), bound_um=8.0)
    rng = np.random.default_rng(1)
    for _ in range(10):
        start = rng.normal(0.0, 20.0, 4)
        o = best_offsets_um(s, width_operator=d, actuator=np.eye(4), bound_um=8.0, start_um=start)
        assert np.allclose(o, ref, atol=1e-9)


@pytest.mark.parametrize(
    ("h", "c", "bound", "name"),
    [
        (np.eye(3), np.zeros(2), 1.0, "hessian"),
        (np.eye(2), np.array([np.nan, 0.0]), 1.0, "finite"),
        (np.eye(2), np.zeros(2), 0.0, "bound"),
    ],
)
def test_bad_inputs_are_refused(h, c, bound, name):
    with pytest.raises(ValueError, match=name):
        box_qp(h, c, bound=bound)
