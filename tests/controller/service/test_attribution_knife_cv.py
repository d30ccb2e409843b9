"""The CV a pair reports: the widths as the knives cut them (``_knife_model_cv``).

Each mark's width is its knife's plus a trend along the field; the fitted widths' CV is exact
for widths that repeat per knife along a steady or steadily changing feed, and holds the read
noise of ``K + 1`` fitted values instead of one per mark.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from controller.service.attribution import KNIFE_MODEL_MIN_DOF, _knife_model_cv, attribute
from tests.controller.service.test_vanished_attribution import marks_table


def knife_model_cv(w, knife, x) -> float:
    """The attribution's knife model CV of arrays (as it calls it: plain floats and labels)."""
    return _knife_model_cv(np.asarray(w, dtype=float).tolist(), np.asarray(knife).tolist(),
                           np.asarray(x, dtype=float).tolist())


def _field(knife_widths, n=35, trend_per_mm=0.0, pitch=1.5):
    z = len(knife_widths)
    knife = np.arange(n) % z
    x = pitch * np.arange(n)
    w = np.asarray(knife_widths, dtype=float)[knife] + trend_per_mm * (x - x.mean())
    return w, knife, x


@pytest.mark.parametrize("knife_widths, trend", [
    ((1.5, 1.52, 1.47, 1.51), 0.0),
    ((1.3, 1.74, 1.06, 1.9), 0.0),
    ((1.5, 1.52, 1.47, 1.51), 2e-4),  # the feed rising 0.7 % over the field
    ((1.0, 2.0), -1e-3),
    ((0.6, 0.66, 0.63, 0.6, 0.57, 0.6, 0.66, 0.61), 1e-4),
])
def test_widths_that_repeat_per_knife_give_their_own_cv(knife_widths, trend):
    w, knife, x = _field(knife_widths, trend_per_mm=trend)
    assert knife_model_cv(w, knife, x) == pytest.approx(w.std() / w.mean(), rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("true_widths", [(1.5,) * 4, (1.49, 1.517, 1.487, 1.511)])
def test_read_noise_enters_once_per_knife_not_once_per_mark(true_widths):
    """Width noise 0.02 mm (30 DN of read noise): the marks' own CV shows ~0.013 over the true
    one, the knives' about sqrt(K / n) of that."""
    w0, knife, x = _field(true_widths)
    true_cv = w0.std() / w0.mean()
    rng = np.random.default_rng(5)
    raw_err, model_err = [], []
    for _ in range(60):
        w = w0 + 0.02 * rng.standard_normal(w0.size)
        raw_err.append(abs(w.std() / w.mean() - true_cv))
        model_err.append(abs(knife_model_cv(w, knife, x) - true_cv))
    assert np.median(raw_err) > 0.006
    assert np.median(model_err) < 0.45 * np.median(raw_err)
    assert np.quantile(model_err, 0.9) < 0.0075


def test_few_marks_give_the_marks_own_cv():
    w, knife, x = _field((1.4, 1.6, 1.5, 1.45), n=4 + 1 + KNIFE_MODEL_MIN_DOF - 1)
    w = w + np.linspace(0.0, 0.03, w.size) ** 2  # not of the model
    assert knife_model_cv(w, knife, x) == pytest.approx(w.std() / w.mean(), rel=1e-12)
    assert math.isnan(knife_model_cv([], [], []))


def test_the_pair_reports_the_knives_cv_and_keeps_the_marks_own():
    meas, frame, snap, rig, mark_knife = marks_table(knives=4, vanished=())
    rng = np.random.default_rng(2)
    noise = 0.02 * rng.standard_normal(meas.mark_widths_mm.size)
    meas.mark_widths_mm = meas.mark_widths_mm + noise
    meas.uniformity_cv = float(meas.mark_widths_mm.std() / meas.mark_widths_mm.mean())
    att = attribute(meas, frame, snap, rig)
    assert att.complete
    assert att.uniformity_cv == att.knife_cv == pytest.approx(
        knife_model_cv(meas.mark_widths_mm, mark_knife, meas.bottoms_mm), rel=1e-12)
    assert att.uniformity_cv < 0.5 * att.marks_cv  # true CV 0: the knives' is nearer
    assert att.to_json()["uniformity_cv"] == pytest.approx(att.uniformity_cv)
    assert att.to_json()["marks_cv"] == pytest.approx(meas.uniformity_cv)


def _exact_model_cv(w, labels, x):
    """The knife model's CV in exact rational arithmetic (one width per label + a trend)."""
    ws, xs = [Fraction(float(v)) for v in w], [Fraction(float(v)) for v in x]
    groups: dict[int, list] = {}
    for label, wi, xi in zip(labels, ws, xs, strict=True):
        groups.setdefault(int(label), []).append((wi, xi))
    mean = sum(ws) / len(ws)
    means = {k: (sum(a for a, _ in g) / len(g), sum(b for _, b in g) / len(g))
             for k, g in groups.items()}
    sxx = sum((b - means[k][1]) ** 2 for k, g in groups.items() for _, b in g)
    sxw = sum((b - means[k][1]) * (a - means[k][0]) for k, g in groups.items() for a, b in g)
    between = sum(len(g) * (means[k][0] - mean) ** 2 for k, g in groups.items())
    return math.sqrt(float((between + (sxw * sxw / sxx if sxx else 0)) / len(ws))) / float(mean)


def test_knife_model_cv_is_the_least_squares_fit_over_the_knives_as_labelled():
    """Any integer labels (negative, gaps, unsorted): the fit of one width per label + a trend,
    the ``np.unique`` grouping's least squares (``lstsq``, itself good to ~1e-10 here) to
    rounding, and the exact fit's (rational arithmetic) to 1e-11."""
    rng = np.random.default_rng(11)
    for i in range(300):
        n = int(rng.integers(1, 50))
        labels = rng.choice([-3, 0, 2, 5, 7, 40], size=n)
        w = rng.uniform(0.5, 3.0, n) if i % 2 else 1.5 + 0.01 * rng.standard_normal(n)
        x = np.sort(rng.uniform(0.0, 40.0, n))
        knives, group = np.unique(labels, return_inverse=True)
        got = knife_model_cv(w, labels, x)
        if n - knives.size - 1 < KNIFE_MODEL_MIN_DOF:
            assert got == pytest.approx(float(w.std() / w.mean()), rel=1e-12)
            continue
        design = np.zeros((n, knives.size + 1))
        design[np.arange(n), group] = 1.0
        design[:, -1] = x - x.mean()
        coef, *_ = np.linalg.lstsq(design, w, rcond=None)
        assert got == pytest.approx(float((design @ coef).std() / w.mean()), rel=1e-9)
        assert got == pytest.approx(_exact_model_cv(w, labels, x), rel=1e-11)


def test_positions_that_do_not_spread_within_a_knife_fit_no_trend():
    """Every knife's marks at one position: the trend column lies in the knives' span, the
    least-squares projection is the knives' mean widths (no trend), as lstsq's minimum norm."""
    rng = np.random.default_rng(3)
    knife = np.arange(24) % 4
    w = 1.5 + 0.02 * rng.standard_normal(24)
    x = 10.0 * knife.astype(float)
    means = np.array([w[knife == k].mean() for k in range(4)])[knife]
    assert knife_model_cv(w, knife, x) == pytest.approx(means.std() / w.mean(), rel=1e-12)
