"""The piezo offsets' bound: re-planning a table inside it, and where the bound comes from."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from controller.laws.limits import (
    MIN_LIMIT_UM,
    REFUSAL_SHRINK,
    AmpLimits,
    OffsetLimit,
    project_zero_mean_box,
    replan_offsets,
)

tables = st.lists(st.floats(-40.0, 40.0, allow_nan=False), min_size=1, max_size=8)
limits = st.floats(0.0, 25.0)


@given(tables, limits)
def test_replanned_tables_stay_within_the_limit_and_keep_the_mean(table, limit):
    v = np.asarray(table)
    out = replan_offsets(v, limit_um=limit)
    assert out.shape == v.shape
    assert np.all(np.abs(out) <= limit + 1e-9)
    assert out.mean() == pytest.approx(min(max(v.mean(), -limit), limit), abs=1e-7)
    if np.abs(v).max() <= limit:
        np.testing.assert_array_equal(out, v)  # inside: untouched


@given(tables, st.floats(0.5, 25.0))
def test_the_replanned_table_is_the_nearest_one_with_that_mean(table, limit):
    """KKT: out = clip(v - c, -L, L) for one scalar c, so no feasible table is nearer."""
    v = np.asarray(table)
    out = replan_offsets(v, limit_um=limit)
    mean = float(np.clip(out.mean(), -limit, limit))
    rng = np.random.default_rng(0)
    d0 = np.linalg.norm(out - v)
    for _ in range(20):  # random feasible tables with the same mean are never nearer
        w = rng.uniform(-limit, limit, v.size)
        w = project_zero_mean_box(w, bound=limit, mean=mean)
        assert np.linalg.norm(w - v) >= d0 - 1e-7


@pytest.mark.parametrize(
    ("values", "bound", "mean", "expected"),
    [
        ([1.0, -1.0], 5.0, 0.0, [1.0, -1.0]),
        ([12.0, 0.0, 0.0, 0.0], 10.0, 0.0, [9.0, -3.0, -3.0, -3.0]),
        ([30.0, 0.0, 0.0, 0.0], 10.0, 0.0, [10.0, -10 / 3, -10 / 3, -10 / 3]),
        ([5.0, 5.0], 3.0, 3.0, [3.0, 3.0]),
        ([0.0, 0.0, 0.0], 2.0, -2.0, [-2.0, -2.0, -2.0]),
        ([4.0, 0.0], 3.0, 1.0, [3.0, -1.0]),
        ([1.0, 2.0, 3.0], 5.0, 0.5, [-0.5, 0.5, 1.5]),  # shifted to the mean: inside the box
        ([1.0, 2.0, 12.0], 5.0, 0.0, [-3.0, -2.0, 5.0]),  # ... an entry beyond it: not a shift
    ],
)
def test_projection_with_a_mean_table(values, bound, mean, expected):
    np.testing.assert_allclose(project_zero_mean_box(np.asarray(values), bound=bound, mean=mean),
                               expected, atol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"values": np.array([np.nan]), "bound": 1.0}, "NaN"),
        ({"values": np.array([]), "bound": 1.0}, "non-empty"),
        ({"values": np.array([1.0]), "bound": 0.0}, "bound"),
        ({"values": np.array([1.0]), "bound": 1.0, "mean": 2.0}, "mean"),
    ],
)
def test_projection_refuses_bad_input(kwargs, needle):
    with pytest.raises(ValueError, match=needle):
        project_zero_mean_box(**kwargs)


@pytest.mark.parametrize(
    ("table", "limit", "needle"),
    [([1.0, np.inf], 1.0, "NaN or infinite"), ([[1.0]], 1.0, "1-D"), ([1.0], -1.0, "limit_um")],
)
def test_replan_refuses_bad_input(table, limit, needle):
    with pytest.raises(ValueError, match=needle):
        replan_offsets(table, limit_um=limit)


# ------------------------------------------------------------------ the bound and its origin
@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"stroke_um": 0.0}, "stroke_um"),
        ({"stroke_um": float("nan")}, "stroke_um"),
        ({"offset_min_um": 0.5}, "offset_min_um <= 0 <= offset_max_um"),
        ({"offset_max_um": -0.5}, "offset_min_um <= 0 <= offset_max_um"),
        ({"slew_max_um_ms": -1.0}, "slew_max_um_ms"),
        ({"setpoint_timeout_s": -0.1}, "setpoint_timeout_s"),
    ],
)
def test_amp_limits_that_make_no_sense_are_refused(kwargs, needle):
    good = {"stroke_um": 10.0, "offset_min_um": -10.0, "offset_max_um": 10.0}
    with pytest.raises(ValueError, match=needle):
        AmpLimits(**{**good, **kwargs})


def _amp(stroke, lo=None, hi=None):
    return AmpLimits(stroke_um=stroke, offset_min_um=-stroke if lo is None else lo,
                     offset_max_um=stroke if hi is None else hi)


@pytest.mark.parametrize(
    ("config", "amp", "limit", "source"),
    [
        (20.0, None, 0.0, "unknown"),
        (20.0, _amp(10.0), 10.0, "amplifier"),
        (20.0, _amp(30.0), 20.0, "machine.toml"),
        (20.0, _amp(20.0), 20.0, "machine.toml"),
        (20.0, _amp(30.0, lo=-5.0), 5.0, "amplifier"),
        (40.0, _amp(50.0), 32.767, "machine.toml"),  # the wire's bound
    ],
)
def test_the_bound_is_the_smaller_stroke(config, amp, limit, source):
    lim = OffsetLimit(config, wire_bound_um=32.767)
    if amp is not None:
        assert lim.amp_reported(amp)
        assert not lim.amp_reported(amp)  # the same report again: no change
    assert lim.limit_um == pytest.approx(limit) and lim.source == source
    d = lim.to_dict()
    assert d["limit_um"] == lim.limit_um and d["source"] == source
    assert d["config_stroke_um"] == min(config, 32.767)
    text = lim.describe()
    assert (f"{limit:.3f} µm" in text) if amp is not None else ("held at zero" in text)


@given(tables, st.floats(1.0, 30.0), st.floats(1.0, 30.0))
def test_stroke_never_exceeded_when_machine_toml_is_wrong(table, config, amp_stroke):
    lim = OffsetLimit(config)
    assert np.all(lim.plan(table) == 0.0)  # nothing but zeros before the amplifier reported
    lim.amp_reported(_amp(amp_stroke))
    out = lim.plan(table)
    assert np.all(np.abs(out) <= min(config, amp_stroke) + 1e-9)


@given(st.lists(st.floats(-20.0, 20.0, allow_nan=False), min_size=2, max_size=8))
def test_refusals_never_let_a_refused_table_out_again(table):
    """Each refusal narrows the bound below the refused table: every later plan differs."""
    lim = OffsetLimit(20.0)
    lim.amp_reported(_amp(15.0))
    wanted = np.asarray(table)
    refused: list[np.ndarray] = []
    for _ in range(30):
        out = lim.plan(wanted)
        for r in refused:
            assert not np.array_equal(out, r)
            assert np.abs(out).max() < np.abs(r).max()
        if not np.any(out):
            break
        new = lim.table_refused(out)
        refused.append(out)
        assert new is not None and new <= REFUSAL_SHRINK * np.abs(out).max() + 1e-12
        assert new == 0.0 or new >= MIN_LIMIT_UM
    else:
        pytest.fail("the bound never reached zero")
    assert lim.table_refused(np.zeros(len(table))) is None  # nothing smaller than zeros
    assert lim.source == ("refused table" if refused else "amplifier")
    # the amplifier lost and found again (a reconnect): the narrowing is forgotten
    assert lim.amp_lost() and lim.limit_um == 0.0
    lim.amp_reported(_amp(15.0))
    assert lim.limit_um == 15.0 and lim.refused_bound_um is None
