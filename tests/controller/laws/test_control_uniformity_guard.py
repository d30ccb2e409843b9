"""The uniformity loop's guard: the best table by measured score, undo, hold."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.uniformity_guard import TableGuard, Verdict

Z = 4


def table(v):
    return np.array([v, -v, 0.5 * v, -0.5 * v])


def feed(guard, pairs):
    return [guard.observe(t, s) for t, s in pairs]


def test_the_first_pair_is_the_best_until_a_window_does_better():
    g = TableGuard(Z, window=3)
    assert g.best_table_um is None and g.threshold_um() == float("inf")
    g.observe(table(0.0), 8.0)
    assert np.allclose(g.best_table_um, 0.0) and g.best_score_um == 8.0
    feed(g, [(table(1.0), 6.0), (table(2.0), 4.0)])  # window mean 6.0: better
    assert g.best_score_um == pytest.approx(6.0)
    assert np.allclose(g.best_table_um, table(1.0))  # the window's mean table


def test_a_board_worse_for_patience_pairs_is_undone():
    g = TableGuard(Z, window=3, rel_tol=0.2, abs_tol_um=0.3, patience=3)
    feed(g, [(table(0.0), 5.0)] * 3)
    limit = 5.0 * 1.2 + 0.3
    verdicts = feed(g, [(table(1.0), limit + 1.0)] * 6)
    # the window's mean passes the limit at the second worse pair; then three in a row
    assert verdicts[:3] == [Verdict.KEEP] * 3
    assert verdicts[3] is Verdict.UNDO
    assert np.allclose(g.best_table_um, 0.0)


def test_noise_below_the_tolerance_is_never_undone():
    rng = np.random.default_rng(0)
    g = TableGuard(Z)
    for k in range(500):
        assert g.observe(table(0.01 * k), max(0.0, 2.0 + 0.1 * rng.standard_normal())) \
            is Verdict.KEEP


def test_an_undo_that_held_counts_and_enough_of_them_hold():
    g = TableGuard(Z, window=2, patience=1, max_undos=2)
    feed(g, [(table(0.0), 5.0)] * 2)
    for k in range(2):
        verdicts = feed(g, [(table(3.0), 20.0)] * 2)
        assert verdicts[-1] is Verdict.UNDO
        g.reverted()
        # the best table's boards again: as good as before
        verdicts = feed(g, [(table(0.0), 5.1)] * 2)
        assert g.undos == k + 1
    assert verdicts[-1] is Verdict.HOLD and g.holding
    assert g.observe(table(0.0), 0.1) is Verdict.HOLD  # held until forgotten
    g.reset()
    assert g.holding
    g.reset(forget=True)
    assert not g.holding and g.best_table_um is None


def test_an_undo_into_a_changed_world_does_not_count_and_rebases_the_best():
    g = TableGuard(Z, window=2, patience=1, max_undos=1)
    feed(g, [(table(0.0), 5.0)] * 2)
    assert feed(g, [(table(3.0), 20.0)] * 2)[-1] is Verdict.UNDO
    g.reverted()
    assert feed(g, [(table(0.0), 18.0)] * 2)[-1] is Verdict.KEEP  # the best is no better now
    assert g.undos == 0 and not g.holding
    assert g.best_score_um == pytest.approx(18.0)


@settings(max_examples=60, deadline=None)
@given(scores=st.lists(st.floats(0.0, 10.0), min_size=3, max_size=40),
       window=st.integers(1, 4))
def test_the_best_table_is_the_window_with_the_lowest_mean_score(scores, window):
    """Without an undo, the best is the first pair or the lowest window mean seen."""
    g = TableGuard(Z, window=window, rel_tol=1e9, abs_tol_um=1e9)  # never worse
    tables = [table(float(k)) for k in range(len(scores))]
    for t, s in zip(tables, scores, strict=True):
        assert g.observe(t, s) is Verdict.KEEP
    cands = [(scores[0], tables[0])]
    for i in range(window - 1, len(scores)):
        cands.append((float(np.mean(scores[i - window + 1:i + 1])),
                      np.mean(tables[i - window + 1:i + 1], axis=0)))
    best = min(c[0] for c in cands)
    assert g.best_score_um == pytest.approx(best, abs=1e-12)
    assert any(np.allclose(g.best_table_um, t) for s, t in cands if abs(s - best) <= 1e-12)


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"window": 0}, "window"), ({"rel_tol": -0.1}, "rel_tol"),
    ({"abs_tol_um": -1.0}, "abs_tol_um"), ({"patience": 0}, "patience"),
    ({"max_undos": 0}, "max_undos"),
])
def test_bad_parameters_are_refused(kwargs, name):
    with pytest.raises(ValueError, match=name):
        TableGuard(Z, **kwargs)


def test_bad_pairs_are_refused():
    g = TableGuard(Z)
    with pytest.raises(ValueError, match="table_um"):
        g.observe([0.0, 1.0], 1.0)
    with pytest.raises(ValueError, match="score_um"):
        g.observe(table(0.0), -1.0)
