"""Uniformity loop where marks vanish (pitch 0.5 mm): the step along a vanished knife taken
whole, pairs whose widths the table's change cannot explain kept out, and the guard's best
table chosen only from pairs on which every knife left a mark."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.laws.uniformity_guard import TableGuard, Verdict
from controller.laws.uniformity_loop import (
    UniformityLoop,
    UniformityLoopConfig,
    linear_widths_mm,
)
from core.errors import ConfigError
from tests.controller.laws.test_control_uniformity_loop import R_MM, per_knife_widths

RUNOUT = np.array([0.0, 4.0, -2.0, 2.0])
PITCH = 0.5


def _delayed_run(vanished_step: bool, gain: float, *, delay: int = 10, pairs: int = 120):
    """The loop on the exact marks of the tip circles, each pair cut ``delay`` pairs earlier.

    Returns the pairs that showed a vanished mark and the widest linear width (the width model
    without clipping) any step left a knife with that was vanished on the pair it learnt from.
    """
    loop = UniformityLoop(UniformityLoopConfig(knives=4, radius_mm=R_MM,
                                               vanished_step=vanished_step))
    tables, vanished, widest, dt = [], 0, -math.inf, 0.1
    for i in range(pairs):
        t = (i + 1) * dt
        tables.append(loop.offsets_um)
        w, _ = per_knife_widths(gain * tables[max(0, i - delay)] - RUNOUT, PITCH, 4)
        gone = np.isnan(w)
        vanished += bool(gone.any())
        loop.update(knife_widths_mm=np.nan_to_num(w, nan=0.0), pitch_mm=PITCH, now_s=t,
                    cut_at_s=t - delay * dt)
        if gone.any():
            lin = linear_widths_mm(gain * loop.offsets_um - RUNOUT, pitch_mm=PITCH,
                                   radius_mm=R_MM)
            widest = max(widest, float(lin[gone].max()))
    return vanished, widest


@pytest.mark.parametrize("gain", [0.6, 0.7, 0.8, 0.93, 1.0])
def test_the_step_along_a_vanished_knife_is_taken_whole_and_never_overshoots(gain):
    """A vanished mark's width is read as 0 while its linear width is below 0: the estimate
    under-states how far the knife must come back, along that knife alone (its neighbours meet
    half way). With the scheduled gain the loop crawls out of the vanished region; the step
    along the vanished knife taken whole leaves it sooner (fewer pairs with a vanished mark),
    and no such step leaves the knife's modelled width beyond the pitch (it aims at the pitch
    with a model gain of 1 against a true one at most 1)."""
    with_step, widest = _delayed_run(True, gain)
    without, _ = _delayed_run(False, gain)
    assert with_step < without
    assert widest <= PITCH


def _zero_table_pair(loop, t, widths):
    """A pair at ``t`` of board cut with the starting (zero) table."""
    loop.update(knife_widths_mm=widths, pitch_mm=PITCH, now_s=t, cut_at_s=0.5)
    return loop.status


def _started_loop():
    loop = UniformityLoop(UniformityLoopConfig(knives=4, radius_mm=R_MM))
    w, _ = per_knife_widths(-RUNOUT, PITCH, 4)  # the zero table: knives 0 and 2 vanished
    assert _zero_table_pair(loop, 1.0, np.nan_to_num(w, nan=0.0)) == "stepped"
    return loop, np.nan_to_num(w, nan=0.0)


@pytest.mark.parametrize(
    "widths, status",
    [
        ([1.996, 0.0, 0.0, 0.0], "unexplained"),  # one mark spanning a revolution (HIL)
        ([1.164, 0.286, 0.257, 0.317], "unexplained"),  # marks on the wrong knives (HIL)
        ([0.968, 0.516, 0.0, 0.518], "unexplained"),  # knife 0's mark read twice as wide
        ([0.0, 1.20, 0.0, 0.80], "stepped"),  # 0.04 mm off: measurement noise
        ([0.05, 1.19, 0.0, 0.76], "stepped"),  # knife 0 just appearing
    ],
)
def test_a_pair_the_table_cannot_explain_is_kept_out(widths, status):
    """Board cut with the same table as the pair before: its widths may differ by noise, not
    by a quarter revolution. The unexplained pair leaves the offsets, the estimate and the
    guard alone."""
    loop, _ = _started_loop()
    before, guard_pairs = loop.offsets_um, len(loop.guard._pairs)
    assert _zero_table_pair(loop, 1.1, np.array(widths)) == status
    if status == "unexplained":
        assert np.array_equal(loop.offsets_um, before)
        assert len(loop.guard._pairs) == guard_pairs
        assert loop.unexplained == 1


def test_after_patience_unexplained_pairs_the_next_one_is_taken():
    """A lasting change (a knife, the wood) is taken after ``change_patience`` pairs."""
    loop, _ = _started_loop()
    new = np.array([0.968, 0.516, 0.0, 0.518])
    statuses = [_zero_table_pair(loop, 1.1 + 0.1 * k, new) for k in range(5)]
    assert statuses == ["unexplained"] * 3 + ["stepped"] * 2
    assert loop.unexplained == 3


def test_a_width_change_the_table_made_is_taken():
    """The widths after the loop's own first table (about 2 um moved) differ from the zero
    table's by up to 0.5 mm: explained by the table, taken."""
    loop, w0 = _started_loop()
    table = loop.offsets_um
    w1, _ = per_knife_widths(table - RUNOUT, PITCH, 4)
    w1 = np.nan_to_num(w1, nan=0.0)
    assert np.max(np.abs(w1 - w0)) > 0.3
    loop.update(knife_widths_mm=w1, pitch_mm=PITCH, now_s=5.0, cut_at_s=4.0)
    assert loop.status == "stepped"


def test_pairs_at_another_pitch_are_not_compared():
    """A vanished mark's clipped deviation scales with the pitch: across a pitch change of more
    than 5 % the pair is taken and becomes the reference."""
    loop, _ = _started_loop()
    w, _ = per_knife_widths(-RUNOUT, 0.6, 4)
    loop.update(knife_widths_mm=np.nan_to_num(w, nan=0.0), pitch_mm=0.6, now_s=1.1,
                cut_at_s=0.5)
    assert loop.status == "stepped"


def test_the_check_is_off_at_zero():
    loop = UniformityLoop(UniformityLoopConfig(knives=4, radius_mm=R_MM, change_tol_frac=0.0))
    w, _ = per_knife_widths(-RUNOUT, PITCH, 4)
    assert _zero_table_pair(loop, 1.0, np.nan_to_num(w, nan=0.0)) == "stepped"
    assert _zero_table_pair(loop, 1.1, np.array([1.996, 0.0, 0.0, 0.0])) == "stepped"


@pytest.mark.parametrize(
    "key, value",
    [("change_tol_frac", -0.1), ("change_tol_frac", 11.0), ("change_patience", 0),
     ("vanished_step", 1)],
)
def test_bad_keys_are_refused(key, value):
    with pytest.raises((ValueError, ConfigError), match=key):
        UniformityLoopConfig(**{key: value})


# -- the guard's best table ------------------------------------------------------------------
def test_a_table_under_which_a_knife_vanished_is_never_the_best():
    """Its score (the clipped widths') is low, and not comparable with the others'."""
    guard = TableGuard(4, window=3, patience=3)
    seen = (0.0, 1.0, -1.0, 0.0)
    vanished = (0.0, 2.0, -2.0, 0.0)
    for _ in range(3):
        guard.observe(seen, 2.0)
    for _ in range(3):
        guard.observe(vanished, 0.5, comparable=False)
    assert guard.best_table_um.tolist() == list(seen)
    assert guard.best_score_um == pytest.approx(2.0)


def test_no_best_before_a_comparable_window_and_nothing_undone():
    guard = TableGuard(4, window=3, patience=1)
    for score in (0.5, 3.0, 9.0, 9.0, 9.0):
        assert guard.observe((0.0, 1.0, -1.0, 0.0), score, comparable=False) is Verdict.KEEP
    assert guard.best_table_um is None


def test_pairs_with_a_vanished_knife_still_count_against_the_best():
    """A clipped score under-states the spread: already worse than the best, it is worse."""
    guard = TableGuard(4, window=3, patience=3, rel_tol=0.2, abs_tol_um=0.3)
    for _ in range(3):
        guard.observe((0.0, 1.0, -1.0, 0.0), 1.0)
    verdicts = [guard.observe((0.0, 3.0, -3.0, 0.0), 5.0, comparable=False) for _ in range(5)]
    assert Verdict.UNDO in verdicts
    assert guard.best_table_um.tolist() == [0.0, 1.0, -1.0, 0.0]
