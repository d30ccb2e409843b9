"""The checks' compiled loops against their numpy definitions (vision.check_kernels)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vision import check_kernels, kernels
from vision.calibration.illumination import running_mean
from vision.orientation import CLIP_SAMPLES, CLIP_SIGMAS, _highpassed_log_rows
from vision.registration.consistency import _without_slow, marks_shading_agreement
from vision.registration.defect_rows import _screened, rows_disagreement

kernels.warm_up()


def _agreement_by_numpy(la, lb, x, c, b, max_samples):
    inside = (x >= c[0]) & (x <= c[-1])
    k = np.searchsorted(c, x[inside], side="right") - 1
    ok = (k >= 0) & (k < b.size)
    step = max(1, -(-int(np.count_nonzero(ok)) // max_samples))
    idx = np.flatnonzero(inside)[ok][::step]
    xs = x[idx]
    p = xs - b[k[ok][::step]]
    t = (xs - 0.5 * (xs[0] + xs[-1])) / (0.5 * (xs[-1] - xs[0]))
    basis = np.stack([t**3, t**2, t, np.ones_like(t)], axis=1)
    cols = np.stack([p, la[idx], lb[idx]], axis=1)
    resid = cols - basis @ np.linalg.lstsq(basis, cols, rcond=None)[0]
    corr = [np.corrcoef(resid[:, 0], resid[:, q])[0, 1] for q in (1, 2)]
    return -corr[0], corr[1]


def test_marks_agreement_is_the_correlation_after_a_cubic():
    rng = np.random.default_rng(3)
    for trial in range(40):
        n = int(rng.integers(200, 1500))
        x = np.sort(rng.uniform(0, 40, n))
        c = np.sort(rng.uniform(-2, 42, int(rng.integers(3, 20))))
        b = 0.5 * (c[1:] + c[:-1]) + rng.normal(0, 0.1, c.size - 1)
        la = rng.normal(size=n) + np.sin(x)
        lb = rng.normal(size=n) - np.sin(x)
        max_samples = int(rng.integers(50, 800))
        # the compiled loop against its numpy definition
        got = check_kernels.marks_agreement(la, lb, x, c, b, max_samples)
        if not np.count_nonzero((x >= c[0]) & (x <= c[-1])) >= 16:
            assert math.isnan(got[0]) and math.isnan(got[1])
            continue
        want = _agreement_by_numpy(la, lb, x, c, b, max_samples)
        # the residuals' means are ~0 after the cubic, so corrcoef is the same correlation
        assert got[0] == pytest.approx(want[0], abs=1e-9), trial
        assert got[1] == pytest.approx(want[1], abs=1e-9), trial
        # the check is that loop on the log-profiles less their slow part
        whole = marks_shading_agreement(la, lb, x, c, b, max_samples=max_samples)
        slow_free = check_kernels.marks_agreement(*_without_slow(la, lb, x, c), x, c, b,
                                                  max_samples)
        assert (whole.score_a, whole.score_b) == slow_free, trial


def _without_slow_by_definition(log_profile, x, cusps):
    """The log-profile less its running mean over 8 marks, its ends' values held."""
    length = 8.0 * (cusps[-1] - cusps[0]) / (cusps.size - 1) / ((x[-1] - x[0]) / (x.size - 1))
    if not 1.0 <= length <= log_profile.size:
        return log_profile
    mean = running_mean(log_profile, length)
    lead = (log_profile.size - mean.size) // 2
    full = np.concatenate([np.full(lead, mean[0]), mean,
                           np.full(log_profile.size - lead - mean.size, mean[-1])])
    return log_profile - full


def test_the_slow_part_is_each_profiles_running_mean_exactly():
    rng = np.random.default_rng(17)
    for trial in range(30):
        n = int(rng.integers(20, 1500))
        x = np.cumsum(rng.uniform(0.05, 0.1, n))
        c = np.sort(rng.uniform(x[0], x[-1], int(rng.integers(2, 60))))
        la, lb = rng.normal(size=n) + x, rng.normal(size=n) - 0.3 * x
        got_a, got_b = _without_slow(la, lb, x, c)
        np.testing.assert_array_equal(got_a, _without_slow_by_definition(la, x, c), str(trial))
        np.testing.assert_array_equal(got_b, _without_slow_by_definition(lb, x, c), str(trial))
        # the compiled one the measurement calls: the same values
        comp_a, comp_b = check_kernels.without_slow(la, lb, x, c)
        np.testing.assert_array_equal(comp_a, got_a, str(trial))
        np.testing.assert_array_equal(comp_b, got_b, str(trial))


def _log_ratio(a, b, s, cols):
    la = np.log(np.maximum(a[:, cols].astype(np.float64), 0.5))
    return np.log(np.maximum(b[:, cols + s].astype(np.float64), 0.5)) - la


def _disagreement_by_numpy(a, b, d, u0, u1):
    s = int(round(d))
    lo, hi = max(u0, -s), min(u1, a.shape[1] - s)
    step = max(2, (hi - lo) // 200)
    first = np.arange(lo, lo + step * ((hi - 1 - lo) // step), step)
    both = np.concatenate([_log_ratio(a, b, s, first), _log_ratio(a, b, s, first + 1)], axis=1)
    mean = both.mean(axis=0)
    dev = both - mean
    noise = 0.5 * np.mean((dev[:, first.size:] - dev[:, :first.size]) ** 2)
    return math.sqrt(max(np.mean(dev**2) - noise, 0.0) / np.var(mean))


def _screen_by_numpy(a, b, d, u0, u1, limit, min_run_px, min_samples):
    s = int(round(d))
    lo, hi = max(u0, -s), min(u1, a.shape[1] - s)
    ratio = _log_ratio(a, b, s, np.arange(lo, hi, 2))
    mag = np.abs(ratio - ratio.mean(axis=0))
    hits = (mag > limit * 0.8 * mag.mean()).astype(np.uint8)
    run = (min_run_px + 1) // 2
    hits = cv2.morphologyEx(hits, cv2.MORPH_OPEN, np.ones((1, run), np.uint8))
    return int(np.count_nonzero(hits)) >= (min_samples + 1) // 2, mag / (0.8 * mag.mean())


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_row_checks_are_their_definitions(dtype):
    rng = np.random.default_rng(7)
    decided = set()
    for trial in range(30):
        n, w = int(rng.integers(3, 40)), int(rng.integers(100, 1200))
        base = rng.uniform(500, 3000, w)
        a = (base * (1 + rng.normal(0, 0.02, (n, w)))).astype(dtype)
        b = np.roll(base, 7) * (1 + rng.normal(0, 0.02, (n, w)))
        if trial % 2:  # a defect: a few rows over some columns
            b[n // 3: n // 3 + 2, w // 3: w // 3 + int(rng.integers(2, 30))] *= 1.5
        b = b.astype(dtype)
        d, u0, u1 = 7 + rng.uniform(-0.4, 0.4), 5, w - 15
        assert rows_disagreement(a, b, d, u0, u1) == pytest.approx(
            _disagreement_by_numpy(a, b, d, u0, u1), rel=1e-3)
        for limit in (3.0, 6.0):
            want, level = _screen_by_numpy(a, b, d, u0, u1, limit, 5, 4)
            if np.any(np.abs(level - limit) < 1e-3):  # a sample on the limit: rounding decides
                continue
            assert _screened(a, b, d, u0, u1, limit, 5, 4) == want, (trial, limit)
            decided.add(want)
    assert decided == {True, False}


def test_the_roll_rows_clip_at_the_robust_deviation():
    rng = np.random.default_rng(11)
    rows = rng.uniform(50, 200, (32, 500)).astype(np.float32)
    rows[3, 100:140] = 2.0  # a pit's shadow
    hp = _highpassed_log_rows(rows, 41)
    r = np.log(rows)
    raw = r - cv2.blur(r, (41, 1), borderType=cv2.BORDER_REFLECT)
    step = max(1, raw.size // CLIP_SAMPLES)
    limit = CLIP_SIGMAS * 1.4826 * float(np.median(np.abs(raw.ravel()[::step])))
    np.testing.assert_array_equal(hp, np.clip(raw, -limit, limit))
    assert np.abs(raw).max() > limit  # the shadow was clipped


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_check_ratios_are_both_samplings_exactly(dtype):
    rng = np.random.default_rng(13)
    for _ in range(25):
        n, w = int(rng.integers(1, 12)), int(rng.integers(40, 900))
        a = rng.uniform(0, 3000, (n, w)).astype(dtype)
        b = rng.uniform(0, 3000, (n, w)).astype(dtype)
        a[0, :3] = 0  # below the 0.5 floor
        s = int(rng.integers(-15, 16))
        lo, hi = max(3, -s), min(w - 5, w - s)
        step = max(2, (hi - lo) // int(rng.integers(5, 200)))
        screen = np.empty((n, (hi - lo + 1) // 2), dtype=np.float32)
        pairs = np.empty((n, 2 * ((hi - 1 - lo) // step)), dtype=np.float32)
        check_kernels.check_ratios(a, b, s, lo, step, screen, pairs)
        want_screen, want_pairs = np.empty_like(screen), np.empty_like(pairs)
        check_kernels.ratios_every_second(a, b, s, lo, want_screen)
        check_kernels.ratios_pairs(a, b, s, lo, step, want_pairs)
        np.testing.assert_array_equal(screen, want_screen)
        np.testing.assert_array_equal(pairs, want_pairs)
