"""The compiled forms of the self-calibration's and the registered profile's steps give, bit
for bit, what the numpy forms they replace give (random inputs, old form == new form)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vision import ffts, kernels
from vision.calibration import selfcal
from vision.calibration.selfcal import (
    SCATTER_GRID_MM,
    Calibration,
    apply_calibration,
    fit_calibration,
    kinematic_slope,
    scatter_transfer,
)
from vision.marks import dominant_period_px, repeat_period_px
from vision.slope import RatioSlope


def _old_fit(slope, model, *, dx_mm, marks, scatter_grid_mm=SCATTER_GRID_MM,
             min_confidence=0.5):
    """fit_calibration as it was: numpy for the model's span and the grid's lengths."""
    p = np.asarray(slope, dtype=np.float64)
    m = np.asarray(model, dtype=np.float64)
    inside = np.isfinite(m)
    idx = np.flatnonzero(inside)
    if idx.size < 16 or marks < 2:
        return Calibration()
    lo, hi = int(idx[0]), int(idx[-1]) + 1
    mm = m[lo:hi].copy()
    mm[~inside[lo:hi]] = 0.0
    pm = p[lo:hi]
    n = hi - lo
    pad = min(n, int(math.ceil(12.0 * float(max(scatter_grid_mm)) / dx_mm)))
    nf = 2 * cv2.getOptimalDFTSize((n + pad + 1) // 2)
    x = selfcal._unit_axis(n)
    if not pm.max() > pm.min():
        return Calibration()
    ells = tuple(e for e in scatter_grid_mm if e > 0)
    n_l = len(ells)
    guard = min(n // 4, int(math.ceil(2 * float(max(scatter_grid_mm)) / dx_mm)))
    sel = slice(guard, n - guard)
    y = pm[sel]
    dev = y - y.sum() / y.size
    var = float(dev @ dev) / y.size
    if not var > 0:
        return Calibration()
    design = np.empty((n_l + 3, y.size))
    design[0] = mm[sel]
    if n_l:
        mean = mm.sum() / mm.size
        padded = np.zeros((1, nf))
        padded[0, :n] = mm
        padded -= mean
        padded[0, n:] = 0.0
        spec = cv2.dft(padded)
        blurred = cv2.dft(spec * selfcal._transfers_packed(nf, dx_mm, ells),
                          flags=cv2.DFT_INVERSE | cv2.DFT_SCALE | cv2.DFT_ROWS)
        design[1 : n_l + 1] = blurred[:, sel]
        design[1 : n_l + 1] += mean
    design[n_l + 1] = 1.0
    design[n_l + 2] = x[sel]
    rss = np.full(n_l + 1, np.nan)
    coef_a = np.zeros(n_l + 1)
    coef_b = np.zeros(n_l + 1)
    gram_all = design @ design.T
    rhs_all = design @ y
    i, resid = kernels.blur_fits(gram_all, rhs_all, float(y @ y), 0.0 in scatter_grid_mm, rss,
                                 coef_a, coef_b, y.size, var)
    if i < 0:
        return Calibration()
    gain = float(coef_a[i] + coef_b[i])
    f = min(1.0, max(0.0, float(coef_b[i]) / gain))
    ell = 0.0 if i == 0 else float(ells[i - 1])
    explained = min(1.0, max(0.0, 1.0 - resid))
    conf = explained * min(1.0, marks / 4.0)
    scatter_conf = conf if ell > 0 and f > 0.05 else 0.0
    return Calibration(gain=gain, gain_confidence=conf, scatter_mm=ell if f > 0.05 else 0.0,
                       scatter_fraction=f if f > 0.05 else 0.0, scatter_confidence=scatter_conf,
                       trusted=conf >= min_confidence and 0.25 <= gain <= 4.0)


def _old_apply(slope, calibration, *, dx_mm, pitch_mm, min_gain_loss=0.03,
               regularisation=0.03, deblur=True):
    """apply_calibration as it was: the transfer function and the filter in numpy."""
    p = np.asarray(slope, dtype=np.float64) / calibration.gain
    f, ell = calibration.scatter_fraction, calibration.scatter_mm
    if not deblur or not selfcal.deblurs(calibration, pitch_mm=pitch_mm,
                                         min_gain_loss=min_gain_loss):
        return p
    n = p.size
    nf = 2 * n
    ext = np.empty(nf)
    ext[:n] = p
    ext[n:] = p[::-1]
    h = scatter_transfer(nf, dx_mm=dx_mm, scatter_mm=ell, fraction=f)
    out = ffts.irfft(ffts.rfft(ext, nf) * h / (h * h + regularisation), nf)
    return out[:n]


def _marks_profile(rng, n):
    """A measured-like slope of arcs (gain, blur, noise, trend) and its kinematic model."""
    dx = float(rng.uniform(0.04, 0.12))
    x = np.arange(n) * dx
    pitch = float(rng.uniform(0.6, 2.5))
    cusps = np.arange(x[0] + rng.uniform(0, pitch), x[-1], pitch)
    cusps = cusps + rng.normal(0, 0.05 * pitch, cusps.size)
    cusps.sort()
    bottoms = 0.5 * (cusps[:-1] + cusps[1:]) + rng.normal(0, 0.03, cusps.size - 1)
    model = kinematic_slope(x, cusps, bottoms, radius_mm=60.0)
    true = np.nan_to_num(model)
    slope = rng.uniform(0.5, 2.0) * true + rng.normal(0, rng.choice([1e-5, 1e-4, 1e-3]), n)
    slope += rng.uniform(-1e-3, 1e-3) + rng.uniform(-1e-5, 1e-5) * np.arange(n)
    return slope, model, dx, cusps.size - 1, pitch


@pytest.mark.parametrize("seed", range(40))
def test_fit_calibration_equals_its_numpy_form(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(40, 900))
    slope, model, dx, marks, _ = _marks_profile(rng, n)
    grid = SCATTER_GRID_MM if seed % 4 else (0.1, 0.2, 0.0)
    if seed % 5 == 1:  # holes inside the model's span, NaNs at its ends
        model = model.copy()
        model[rng.integers(0, n, 8)] = np.nan
    if seed % 7 == 2:  # a constant slope over the span
        slope = np.full(n, 0.01)
    if seed % 9 == 3:  # a NaN in the slope
        slope = slope.copy()
        slope[n // 2] = np.nan
    new = fit_calibration(slope, model, dx_mm=dx, marks=marks, scatter_grid_mm=grid)
    old = _old_fit(slope, model, dx_mm=dx, marks=marks, scatter_grid_mm=grid)
    assert repr(new) == repr(old)  # every field, every bit (repr of floats round-trips)


@pytest.mark.parametrize("finite, marks", [(0, 5), (1, 5), (15, 5), (16, 5), (17, 5), (60, 1),
                                            (60, 2)])
def test_fit_calibration_with_too_little_model_or_marks_equals_its_numpy_form(finite, marks):
    """The early returns (fewer than 16 samples of the model, fewer than 2 marks) as before."""
    rng = np.random.default_rng(finite * 10 + marks)
    slope, model, dx, _, _ = _marks_profile(rng, 200)
    model = model.copy()
    model[:] = np.nan
    start = int(rng.integers(0, 200 - finite + 1))
    model[start:start + finite] = rng.standard_normal(finite)  # a span of `finite` samples
    new = fit_calibration(slope, model, dx_mm=dx, marks=marks)
    old = _old_fit(slope, model, dx_mm=dx, marks=marks)
    assert repr(new) == repr(old)
    if finite < 16 or marks < 2:  # nothing to calibrate on: the identity
        assert new == Calibration()


def test_fit_calibration_refuses_mismatched_lengths():
    with pytest.raises(ValueError, match="slope and model"):
        fit_calibration(np.zeros(40), np.zeros(41), dx_mm=0.08, marks=4)


def test_model_span_edge_cases_equal_numpy():
    out = np.empty(8)
    assert kernels.model_span(np.full(8, np.nan), np.zeros(8), out) == (0, 0, 0, False)
    m = np.array([np.nan, 1.0, np.nan, 2.0, np.nan, np.nan, 3.0, np.nan])
    for p in (np.array([0, 1, 1, 1, 1, 1, 1, 0.0]), np.array([0, -np.inf, -np.inf, 5, 0, 0, 0, 0]),
              np.array([0, 1, 2, 3, np.nan, 5, 6, 7.0]), np.array([9, 0.0, -0.0, 0, 0, 0, 0, 9])):
        lo, hi, count, varies = kernels.model_span(m, p, out)
        assert (lo, hi, count) == (1, 7, 3)
        assert varies == bool(p[1:7].max() > p[1:7].min())
        np.testing.assert_array_equal(out[:6], [1, 0, 2, 0, 0, 3])


@pytest.mark.parametrize("seed", range(30))
def test_apply_calibration_equals_its_numpy_form(seed):
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(16, 1400))
    slope = rng.normal(size=n) * 0.01
    cal = Calibration(gain=float(rng.uniform(0.3, 3)), gain_confidence=0.9,
                      scatter_mm=float(rng.choice([0.0, 0.05, rng.uniform(0.01, 0.8)])),
                      scatter_fraction=float(rng.choice([0.0, rng.uniform(0, 1)])),
                      trusted=True)
    dx = float(rng.uniform(0.03, 0.15))
    pitch = float(rng.uniform(0.3, 3))
    reg = float(rng.choice([0.03, rng.uniform(1e-4, 0.5)]))
    for deblur in (True, False):
        new = apply_calibration(slope, cal, dx_mm=dx, pitch_mm=pitch, regularisation=reg,
                                deblur=deblur)
        old = _old_apply(slope, cal, dx_mm=dx, pitch_mm=pitch, regularisation=reg,
                         deblur=deblur)
        np.testing.assert_array_equal(new, old)
        assert new.tobytes() == old.tobytes()  # the zeros' signs too


@pytest.mark.parametrize("seed", range(20))
def test_wiener_terms_equal_numpy(seed):
    rng = np.random.default_rng(200 + seed)
    nf = int(rng.integers(4, 3000))
    dx, ell, f = float(rng.uniform(0.01, 0.2)), float(rng.uniform(0, 1)), float(rng.uniform(0, 1))
    reg = float(rng.uniform(1e-4, 0.5))
    nu = selfcal._frequencies(nf, dx)
    h, den = np.empty(nu.size), np.empty(nu.size)
    kernels.wiener_terms(nu, 2.0 * math.pi * ell, f, reg, h, den)
    old_h = scatter_transfer(nf, dx_mm=dx, scatter_mm=ell, fraction=f)
    assert h.tobytes() == old_h.tobytes()
    assert den.tobytes() == (old_h * old_h + reg).tobytes()


def _old_ratio_slope(rs: RatioSlope, ratio):
    r = np.asarray(ratio, dtype=np.float64)
    den = r * rs._ca * rs._tan_a - rs._b
    with np.errstate(divide="ignore", invalid="ignore"):
        p = (r - 1.0) / den
    return np.where(den != 0, p, np.nan)


@pytest.mark.parametrize("seed", range(20))
def test_ratio_slope_equals_its_numpy_form(seed):
    rng = np.random.default_rng(300 + seed)
    rs = RatioSlope(slant_deg=float(rng.uniform(5, 60)), azimuth_a_deg=float(rng.uniform(-20, 20)),
                    azimuth_b_deg=float(rng.uniform(160, 200)),
                    slant_b_deg=None if seed % 2 else float(rng.uniform(5, 60)))
    r = np.exp(rng.normal(0, 0.3, int(rng.integers(1, 900))))
    if seed % 3 == 0:  # a ratio where the denominator vanishes, and a NaN, an inf, a zero
        r[0] = rs._b / rs._ca / rs._tan_a
        r[-1:] = [np.nan, np.inf, 0.0][seed % 9 // 3]
    old = _old_ratio_slope(rs, r)
    new, finite = rs.finite(r)
    assert new.tobytes() == old.tobytes()
    assert rs(r).tobytes() == old.tobytes()
    assert finite == bool(np.all(np.isfinite(old)))
    r2 = r[: r.size // 2 * 2].reshape(2, -1) if r.size > 1 else r.reshape(1, 1)
    assert rs(r2).tobytes() == _old_ratio_slope(rs, r2).tobytes()  # 2-D: the same numbers
    strided = r[::2]  # a view that is not contiguous, and a scalar
    assert rs(strided).tobytes() == _old_ratio_slope(rs, strided).tobytes()
    assert rs(r[0]).shape == () and rs(r[0]).tobytes() == _old_ratio_slope(rs, r[0]).tobytes()


def _old_repeat_period(signal, *, max_multiple=8, tolerance=0.02):
    """repeat_period_px as it was: the power spectrum in numpy."""
    import scipy.fft

    s = np.asarray(signal, dtype=np.float64)
    s = s - s.sum() / s.size
    n = s.size
    t = dominant_period_px(s)
    if not math.isfinite(t):
        return math.nan
    s = kernels.smooth5(s)
    ks = [k for k in range(1, max_multiple + 1) if k * t <= n / 3.0]
    if not ks:
        return t
    nfft = scipy.fft.next_fast_len(2 * n, real=True)
    spec = ffts.rfft(s, nfft)
    dots = ffts.irfft(spec.real**2 + spec.imag**2, nfft)[:n]
    return float(kernels.repeat_lag(s, np.ascontiguousarray(dots), t,
                                     np.asarray(ks, dtype=np.float64), tolerance))


@pytest.mark.parametrize("seed", range(20))
def test_repeat_period_and_power_spectrum_equal_their_numpy_form(seed):
    rng = np.random.default_rng(400 + seed)
    n = int(rng.integers(40, 1000))
    u = np.arange(n)
    period = rng.uniform(5, n / 6)
    s = np.sin(2 * np.pi * u / period) + 0.3 * np.sin(2 * np.pi * u / (period * 4))
    s += rng.normal(0, rng.uniform(0.01, 1), n)
    new, old = repeat_period_px(s), _old_repeat_period(s)
    assert np.asarray(new).tobytes() == np.asarray(old).tobytes()
    spec = rng.normal(size=n) + 1j * rng.normal(size=n)
    spec[0] = complex(-0.0, 0.0)
    assert kernels.power_spectrum(spec).tobytes() == (spec.real**2 + spec.imag**2).tobytes()


@pytest.mark.parametrize("seed", range(10))
def test_any_nonpositive_equals_numpy(seed):
    rng = np.random.default_rng(500 + seed)
    a, b = rng.uniform(0.1, 2, int(rng.integers(1, 50))), rng.uniform(0.1, 2, 30)
    if seed % 2:
        (a if seed % 4 == 1 else b)[int(rng.integers(0, 10))] = [0.0, -0.0, -1e-300, np.nan][
            seed // 2 % 4]
    assert kernels.any_nonpositive(a, b) == bool(np.any(a <= 0) or np.any(b <= 0))


def _old_knife_means(values, *, knives, phase):
    v = np.asarray(values, dtype=np.float64)
    sums = [0.0] * knives
    counts = [0] * knives
    for i, value in enumerate(v.tolist()):
        k = (phase + i) % knives
        sums[k] += value
        counts[k] += 1
    return np.array([s / c if c > 0 else math.nan for s, c in zip(sums, counts, strict=True)])


@pytest.mark.parametrize("seed", range(20))
def test_knife_means_and_kinematic_depths_equal_their_python_forms(seed):
    from vision.calibration.selfcal import kinematic_depths_um
    from vision.marks import knife_means

    rng = np.random.default_rng(600 + seed)
    m = int(rng.integers(0, 60))
    values = rng.normal(1.0, 0.3, m) * 10 ** rng.uniform(-3, 3)
    knives = int(rng.integers(1, 9))
    phase = int(rng.integers(-10, 10))
    new = knife_means(values, knives=knives, phase=phase)
    assert new.tobytes() == _old_knife_means(values, knives=knives, phase=phase).tobytes()
    cusps = np.sort(rng.uniform(0, 50, m + 1))
    bottoms = 0.5 * (cusps[:-1] + cusps[1:]) + rng.normal(0, 0.1, m)
    r = float(rng.uniform(20, 120))
    old = 1000.0 * ((cusps[:-1] - bottoms) ** 2 + (cusps[1:] - bottoms) ** 2) / (4.0 * r)
    assert kinematic_depths_um(cusps, bottoms, radius_mm=r).tobytes() == old.tobytes()


@pytest.mark.parametrize("cusps, bottoms", [
    (np.zeros(3), np.zeros(3)),  # one cusp too few
    (np.zeros(5), np.zeros(3)),  # one too many
    (np.zeros((2, 3)), np.zeros(2)),  # not 1-D
    (np.zeros(1), np.zeros((1, 1))),
])
def test_kinematic_depths_refuse_cusps_that_do_not_bracket_the_bottoms(cusps, bottoms):
    from vision.calibration.selfcal import kinematic_depths_um

    with pytest.raises(ValueError, match="cusps_mm") as exc:
        kinematic_depths_um(cusps, bottoms, radius_mm=60.0)
    assert str(np.shape(cusps)) in str(exc.value) and str(np.shape(bottoms)) in str(exc.value)


class _OldCalibrator:
    """SelfCalibrator.update's smoothing as it was (numpy arrays of two)."""

    def __init__(self, weight=0.3, min_confidence=0.5):
        self.weight, self.min_confidence = weight, min_confidence
        self._log_gain, self._scatter, self._w, self._n = 0.0, np.zeros(2), 0.0, 0.0

    def update(self, estimate):
        decay = 1.0 - self.weight
        c = float(estimate.gain_confidence)
        w_old = decay * self._w
        self._w = w_old + c
        self._n = decay * self._n + 1.0
        if c > 0 and estimate.gain > 0:
            vec = np.array([estimate.scatter_mm, estimate.scatter_fraction])
            self._log_gain = (w_old * self._log_gain + c * math.log(estimate.gain)) / self._w
            self._scatter = (w_old * self._scatter + c * vec) / self._w
        conf = self._w / self._n if self._n > 0 else 0.0
        return Calibration(
            gain=math.exp(self._log_gain), gain_confidence=conf,
            scatter_mm=float(self._scatter[0]), scatter_fraction=float(self._scatter[1]),
            scatter_confidence=conf if self._scatter[1] > 0 else 0.0,
            trusted=conf >= self.min_confidence)


@pytest.mark.parametrize("seed", range(10))
def test_self_calibrator_update_equals_its_numpy_form(seed):
    from vision.calibration.selfcal import SelfCalibrator

    rng = np.random.default_rng(700 + seed)
    weight = float(rng.uniform(0.05, 1.0))
    new, old = SelfCalibrator(weight=weight), _OldCalibrator(weight=weight)
    for _ in range(40):
        est = Calibration(gain=float(rng.choice([0.0, rng.uniform(0.2, 4)])),
                          gain_confidence=float(rng.choice([0.0, rng.uniform(0, 1)])),
                          scatter_mm=float(rng.choice(SCATTER_GRID_MM)),
                          scatter_fraction=float(rng.choice([0.0, rng.uniform(0, 1)])))
        assert repr(new.update(est)) == repr(old.update(est))
        assert new._scatter.tobytes() == old._scatter.tobytes()
        assert type(new._scatter) is np.ndarray and new._scatter.dtype == np.float64


@pytest.mark.parametrize("seed", range(10))
def test_fine_shift_fit_equals_its_numpy_form(seed):
    from vision.registration.shift_estimators import FineShiftFit

    rng = np.random.default_rng(800 + seed)
    width = int(rng.integers(200, 1300))
    fit = FineShiftFit(width, fine_px=3, max_frequency=0.25, min_overlap_px=64)
    la, lb = rng.normal(size=width - 1), rng.normal(size=width - 1)
    lb[5:] = la[:-5] + 0.1 * lb[5:]
    guess = float(rng.uniform(2, 8))
    import vision.registration.shift_estimators as se

    new_result = fit(la, lb, guess)
    # the numpy form, step for step
    w, i0, m = la.size, int(round(guess)), fit.fine_px + 2
    u0, u1 = max(0, -i0) + m, min(w, w - i0) - m
    n = u1 - u0
    both = np.empty((2, n))
    both[0], both[1] = la[u0:u1], lb[u0 + i0 : u1 + i0]
    both -= both.mean(axis=1, keepdims=True)
    both *= fit._taper(n)
    spec = ffts.rfft(both, fit.nfft, axis=1)[:, : fit._kmax]
    score = np.empty(fit._fine_real.shape[0])
    total = kernels.delay_scores(spec[0], spec[1], fit._fine_real, score)
    j = int(np.argmax(score))
    if j == 0 or j == score.size - 1:
        old_result = (math.nan, float(score[j]) / total)
    else:
        frac, peak = se._parabolic_peak(score, j)
        old_result = (i0 + float(fit._fine_grid[j]) + frac * fit._FINE_STEP_PX, peak / total)
    assert repr(new_result) == repr(old_result)


def _old_shift_profile(profile, *, shift_px, start=0, count=None):
    """shift_profile's cubic as numpy slices (the form it replaces)."""
    p = np.asarray(profile, dtype=np.float64)
    if count is None:
        count = p.size - start
    base = math.floor(shift_px)
    t = shift_px - base
    i0 = start + base
    if t == 0:
        return p[i0 : i0 + count].copy()
    a = -0.5
    w_m1 = a * t * (t - 1) ** 2
    w_0 = (a + 2) * t**3 - (a + 3) * t**2 + 1
    s = 1 - t
    w_p1 = (a + 2) * s**3 - (a + 3) * s**2 + 1
    w_p2 = a * s * (s - 1) ** 2
    return (w_m1 * p[i0 - 1 : i0 - 1 + count] + w_0 * p[i0 : i0 + count]
            + w_p1 * p[i0 + 1 : i0 + 1 + count] + w_p2 * p[i0 + 2 : i0 + 2 + count])


@pytest.mark.parametrize("seed", range(20))
def test_shift_profile_and_feed_positions_equal_their_numpy_forms(seed):
    from vision.profile import shift_profile

    rng = np.random.default_rng(900 + seed)
    n = int(rng.integers(16, 2000))
    p = rng.uniform(10, 200, n)
    d = float(rng.choice([rng.uniform(-5, 5), float(rng.integers(-3, 4))]))
    start = int(rng.integers(6, 10))
    count = int(rng.integers(0, n - 20))
    new = shift_profile(p, shift_px=d, start=start, count=count)
    assert new.tobytes() == _old_shift_profile(p, shift_px=d, start=start, count=count).tobytes()
    with pytest.raises(ValueError, match="count"):
        shift_profile(p, shift_px=d, start=start, count=-1)
    c0, u0, cx = int(rng.integers(0, 40)), int(rng.integers(0, 40)), float(rng.uniform(200, 900))
    cos_roll = math.cos(math.radians(float(rng.uniform(-5, 5))))
    ppm = float(rng.uniform(5, 40))
    cols = c0 + u0 + np.arange(count)
    old = (cx + (cols - cx) * cos_roll) / ppm
    new = np.empty(count)
    kernels.feed_positions(c0 + u0, cx, cos_roll, ppm, new)
    assert new.tobytes() == old.tobytes()


def _old_remove_slow(height_um, period_px):
    """remove_slow's subtractions as numpy slices (the form it replaces)."""
    from vision.calibration.illumination import running_mean

    h = np.asarray(height_um, dtype=np.float64)
    n = h.size
    if not (math.isfinite(period_px) and 4.0 <= period_px <= n / 2):
        return h
    slow = running_mean(h, period_px)
    m0 = (n - slow.size) // 2
    out = h.copy()
    out[m0 : m0 + slow.size] -= slow
    out[:m0] -= slow[0]
    out[m0 + slow.size :] -= slow[-1]
    out -= out.sum() / n
    return out


@pytest.mark.parametrize("seed", range(20))
def test_remove_slow_and_finite_profiles_equal_their_numpy_forms(seed):
    from vision.pipeline import remove_slow
    from vision.registration.registrar import Registrar

    rng = np.random.default_rng(1000 + seed)
    n = int(rng.integers(8, 1500))
    h = np.cumsum(rng.normal(size=n)) + np.sin(np.arange(n) / 3.0)
    period = float(rng.choice([rng.uniform(4, max(4.0, n / 2)), 4.0, n / 2, 3.0, math.nan]))
    assert remove_slow(h, period).tobytes() == _old_remove_slow(h, period).tobytes()
    reg = Registrar(64, search_px=5.0, min_overlap_px=32)
    pa, pb = rng.uniform(1, 2, 64), rng.uniform(1, 2, 64)
    if seed % 2:
        (pa if seed % 4 == 1 else pb)[int(rng.integers(0, 64))] = [np.nan, np.inf, -np.inf][
            seed // 4 % 3]
        with pytest.raises(ValueError, match="finite"):
            reg._profiles(pa, pb)
    else:
        a, b = reg._profiles(pa, pb)
        assert a is pa and b is pb
    assert kernels.all_finite(pa, pb) == bool(np.all(np.isfinite(pa)) and np.all(np.isfinite(pb)))

