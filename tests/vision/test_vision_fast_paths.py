"""The faster formulations give what the plain formulas give."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal

from vision import marks as vm
from vision.calibration.illumination import Detrender, running_mean
from vision.orientation import RollEstimator
from vision.registration.registrar import Registrar
from vision.slope import RatioSlope, slope_from_ratio


def _interp_running_mean(values: np.ndarray, length: float) -> np.ndarray:
    """The definition: piecewise-constant signal, window integrals by np.interp."""
    v = np.asarray(values, dtype=np.float64)
    n = v.shape[0]
    half = 0.5 * length
    m0 = math.ceil(half - 0.5)
    centres = np.arange(m0, n - m0, dtype=np.float64)
    knots = np.arange(n + 1, dtype=np.float64) - 0.5
    cum = np.concatenate((np.zeros((1,) + v.shape[1:]), np.cumsum(v, axis=0)))
    cols = [cum] if v.ndim == 1 else [cum[:, j] for j in range(v.shape[1])]
    out = [(np.interp(centres + half, knots, c) - np.interp(centres - half, knots, c)) / length
           for c in cols]
    return out[0] if v.ndim == 1 else np.stack(out, axis=1)


@pytest.mark.parametrize("seed", range(6))
def test_running_mean_is_the_window_integral_exactly(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 900))
    length = float(rng.choice([1.0, 2.0, 7.0, rng.uniform(1, n), rng.uniform(1, n / 3)]))
    v = rng.normal(size=n).cumsum()
    np.testing.assert_array_equal(running_mean(v, length), _interp_running_mean(v, length))
    m = rng.normal(size=(n, 4))
    np.testing.assert_array_equal(running_mean(m, length), _interp_running_mean(m, length))


def test_plain_detrend_set_up_once_equals_the_least_squares_fit():
    rng = np.random.default_rng(1)
    d = Detrender(500, degree=3)
    v = rng.normal(size=300) + np.linspace(0, 3, 300) ** 2
    for _ in range(2):  # the second call uses the cached pseudo-inverse
        trend = d.trend(v, start=40)
        basis = d._basis[40:340]
        coef, *_ = np.linalg.lstsq(basis, v, rcond=None)
        np.testing.assert_allclose(trend, basis @ coef, rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", range(20))
def test_peaks_median_quantile_equal_numpy_and_scipy(seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=int(rng.integers(10, 400)))
    if seed % 3 == 0:
        x = np.round(x, 1)  # plateaus and exact ties
    if seed % 4 == 1:
        x[-2:] = 0.0  # the undefined ends of cusp_steps
    want, props = scipy.signal.find_peaks(x, height=0.0, distance=3)
    got, heights = vm._peaks(x)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(heights, props["peak_heights"])
    assert vm._median(x) == np.median(x)
    for q in (0.1, 0.5, 0.9):
        assert vm._quantile(x, q) == np.quantile(x, q)


def test_repeat_period_self_correlation_from_one_fft():
    rng = np.random.default_rng(4)
    u = np.arange(700)
    s = ((u % 23.7) / 23.7 - 0.5) * (1 + 0.3 * ((u // 24) % 3 == 0)) + 0.02 * rng.normal(size=700)
    period = vm.repeat_period_px(s)
    # three marks repeat (every third is deeper): the period is three marks, refined
    assert period == pytest.approx(3 * 23.7, abs=0.3)
    sm = np.convolve(s - s.mean(), np.ones(5) / 5.0, mode="same")
    lag = int(round(period))
    a, b = sm[:-lag], sm[lag:]
    direct = float(a @ b) / math.sqrt(float(a @ a) * float(b @ b))
    assert direct > 0.9


@pytest.mark.parametrize("kw", [dict(slant_deg=82.0), dict(slant_deg=78.0, slant_b_deg=84.0),
                                dict(slant_deg=75.0, azimuth_a_deg=10.0, azimuth_b_deg=200.0)])
def test_ratio_slope_set_up_once_equals_seed_eq4(kw):
    r = np.random.default_rng(2).uniform(0.3, 2.0, 500)
    np.testing.assert_array_equal(RatioSlope(**kw)(r), slope_from_ratio(r, **kw))


def test_roll_power_by_lag_products_equals_the_sheared_sums():
    rng = np.random.default_rng(5)
    n_rows, width = 48, 300
    row_v = 100.0 + 5.0 * np.arange(n_rows)
    est = RollEstimator(row_v, width, cy=220.0, groups=12)
    rows = rng.uniform(50, 200, (n_rows, width)).astype(np.float32)
    power = est.power(rows)
    # the definition: for every angle, the power of the groups' spectra sheared and summed
    g = est._group_means(rows)
    from vision.orientation import _highpassed_log_rows
    hp = _highpassed_log_rows(g, est.highpass_px) * est._taper[None, :]
    k0, k = est._k
    spec = np.fft.rfft(hp.astype(np.float64), n=est.nfft, axis=1)[:, k0:k]
    freq = np.arange(k0, k) / est.nfft
    tan = np.tan(np.radians(est.angles_deg))
    shift = tan[:, None] * est._group_v[None, :]
    total = np.einsum("tgf,gf->tf", np.exp(-2j * np.pi * shift[:, :, None] * freq), spec)
    want = (np.abs(total) ** 2).sum(axis=1)
    np.testing.assert_allclose(power, want, rtol=2e-4)
    with pytest.raises(ValueError, match="evenly"):
        RollEstimator(np.array([0.0, 1.0, 3.0, 4.0]), width, cy=0.0, groups=4)


def _brute_ncc(ta: np.ndarray, tb: np.ndarray, reg: Registrar, guess: float) -> tuple:
    lo, hi, u0, u1 = reg._lag_window(guess, reg.width)
    a = reg.band_pass(ta).astype(np.float64)[:, u0:u1]
    b = reg.band_pass(tb).astype(np.float64)
    lags = np.arange(lo, hi + 1)
    ncc = np.array([(a * b[:, u0 + L : u1 + L]).sum()
                    / math.sqrt((a * a).sum() * (b[:, u0 + L : u1 + L] ** 2).sum())
                    for L in lags])
    return lags, ncc


@pytest.mark.parametrize("guess", [-9.5, 0.0, 12.0, 30.6])
def test_texture_correlation_of_width_length_equals_the_direct_sums(guess):
    rng = np.random.default_rng(7)
    width, rows, shift = 320, 24, 11
    base = rng.normal(size=(rows, width + 80)).astype(np.float32)
    ta = base[:, 40 : 40 + width]
    tb = base[:, 40 - shift : 40 - shift + width] + 0.3 * rng.normal(size=(rows, width)).astype(
        np.float32)
    reg = Registrar(width, search_px=20.0)
    res = reg.coarse(ta, tb, encoder_shift_px=guess)
    lags, ncc = _brute_ncc(ta, tb, reg, guess)
    i = int(np.argmax(ncc))
    assert lags[i] == round(res.shift_px)
    assert res.peak_ncc == pytest.approx(ncc[i] + 0.25 * (ncc[i - 1] - ncc[i + 1]) ** 2
                                         / (2 * (2 * ncc[i] - ncc[i - 1] - ncc[i + 1])),
                                         abs=2e-4)
    assert res.shift_px == pytest.approx(shift, abs=0.3)


def test_quick_texture_pass_is_kept_only_when_strong():
    rng = np.random.default_rng(8)
    width, rows = 300, 96
    base = rng.normal(size=(rows, width + 60)).astype(np.float32)
    ta = base[:, 30 : 30 + width]
    tb = base[:, 21 : 21 + width]  # shift 9 px
    reg = Registrar(width)
    quick = reg._quick_texture(ta, tb, 9.0)
    full = reg.coarse(ta, tb, encoder_shift_px=9.0)
    assert quick is not None and quick.confidence >= reg.strong_confidence
    assert quick.shift_px == pytest.approx(full.shift_px, abs=0.1)
    noisy_b = tb + 6.0 * rng.normal(size=tb.shape).astype(np.float32)
    weak = reg._quick_texture(ta, noisy_b, 9.0)
    assert weak is None or weak.confidence >= reg.strong_confidence
    assert Registrar(width, quick_rows=0)._quick_texture(ta, tb, 9.0) is None


def test_a_gain_only_calibration_scales_the_profile_and_keeps_the_marks():
    from tests.support.vision_boards import render_board
    from vision.pipeline import Measurer

    board = render_board(4, slant_a_error_deg=3.0, slant_b_error_deg=3.0,
                         runout_um=(0.0, 2.0, -1.0, 1.0))
    kw = dict(counts_a=board.counts_a, counts_b=board.counts_b)
    shape = board.image_a.shape
    plain = Measurer(board.rig, shape).measure(board.image_a, board.image_b, **kw)
    cal = Measurer(board.rig, shape, radius_mm=60.0).measure(board.image_a, board.image_b, **kw)
    c = cal.calibration
    assert c is not None and c.trusted and not c.deblurred and c.gain > 1.2
    np.testing.assert_allclose(cal.height_um, plain.height_um / c.gain, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(cal.slope, plain.slope / c.gain, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(cal.cusps_mm, plain.cusps_mm)
    assert cal.depth_um == pytest.approx(plain.depth_um / c.gain, rel=1e-12)
    assert cal.uncalibrated_depth_um == pytest.approx(plain.depth_um, rel=1e-12)


def test_the_board_calibrator_searches_the_roll_every_few_pairs(monkeypatch):
    from tests.support.vision_boards import render_board
    from vision.calibration.selfcal import SelfCalibrator
    from vision.pipeline import Measurer

    board = render_board(5, roll_deg=2.0, runout_um=(0.0, 2.0, -1.0, 1.0), height=240)
    m = Measurer(board.rig, board.image_a.shape, radius_mm=60.0)
    searches = []
    real = m.roll_estimator.estimate
    monkeypatch.setattr(m.roll_estimator, "estimate", lambda g: searches.append(1) or real(g))

    def measure(cal):
        return m.measure(board.image_a, board.image_b, counts_a=board.counts_a,
                         counts_b=board.counts_b, calibrator=cal)

    cal = SelfCalibrator(roll_every=4)
    results = [measure(cal) for _ in range(9)]
    assert len(searches) == 3  # pairs 1, 5 and 9
    first = results[0]
    assert first.roll_deg == pytest.approx(2.0, abs=0.05) and first.roll_confidence > 0.8
    for r in results[1:4]:  # the board's roll, not searched again
        assert (r.roll_deg, r.roll_confidence) == (first.roll_deg, first.roll_confidence)
        np.testing.assert_allclose(r.height_um, results[0].height_um, rtol=0, atol=1e-6)
    cal.reset()  # a new board: searched at once
    measure(cal)
    assert len(searches) == 4
    every = SelfCalibrator(roll_every=1)
    for _ in range(3):
        measure(every)
    assert len(searches) == 7
    with pytest.raises(ValueError, match="roll_every"):
        SelfCalibrator(roll_every=0)
    unsure = SelfCalibrator()
    unsure.note_roll(1.0, 0.1, min_confidence=0.3)  # not confident: not kept
    assert unsure.known_roll() is None


def test_selfcal_transfer_tables_do_not_depend_on_which_spacing_came_first():
    """Two spacings equal to 1e-9 mm share one cached table, computed at the rounded spacing:
    the same table whichever of them a process met first (a pair's numbers never depend on
    the pairs measured before it)."""
    from vision.calibration import selfcal

    dx1 = 0.08 * math.cos(math.radians(0.41))
    dx2 = dx1 + 3e-12  # a roll estimate's last digits
    assert round(dx1, 9) == round(dx2, 9) and dx1 != dx2
    ells = (0.01, 0.03)
    tables = []
    for order in ((dx1, dx2), (dx2, dx1)):
        selfcal._transfers_at.cache_clear()
        got = [selfcal._transfers(1266, dx, ells).copy() for dx in order]
        np.testing.assert_array_equal(got[0], got[1])
        tables.append(got[0])
    np.testing.assert_array_equal(tables[0], tables[1])
    direct = np.stack([selfcal._exp_transfer(1266, round(dx1, 9), e) for e in ells])
    np.testing.assert_array_equal(tables[0], direct)
    selfcal._transfers_at.cache_clear()
