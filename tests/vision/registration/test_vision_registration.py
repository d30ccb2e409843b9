"""Registration: encoder shift across counter wrap (seed Eq. 5-6) and refinement from the images."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.errors import RegistrationError
from vision.registration.registrar import (
    Registrar,
    Registration,
    encoder_shift_px,
    refine_shift,
)
from vision.registration.shift_estimators import mark_period_px, shading_free_texture, shading_shift

# -- encoder shift ---------------------------------------------------------------------------

WRAP_TABLE = [
    # counts_a, counts_b, bits, difference in counts
    (100, 130, 32, 30),
    (130, 100, 32, -30),
    (2**32 - 10, 20, 32, 30),  # forward across the 32-bit wrap
    (20, 2**32 - 10, 32, -30),  # backward across it
    (65530, 4, 16, 10),  # forward across the 16-bit wrap
    (4, 65530, 16, -10),
    (65535, 0, 16, 1),
    (-5, 25, 32, 30),  # two's-complement (signed register) reading
    (-3, 2**32 - 1, 32, 2),
    (0, 2**31 - 1, 32, 2**31 - 1),  # largest forward difference
    (0, 2**31, 32, -(2**31)),  # half a turn reads as backward
    (123, 123, 16, 0),
]


@pytest.mark.parametrize("a, b, bits, diff", WRAP_TABLE)
def test_encoder_shift_is_signed_modular_difference(a, b, bits, diff):
    assert encoder_shift_px(a, b, px_per_count=0.625, counter_bits=bits) == pytest.approx(
        0.625 * diff
    )


def test_encoder_shift_scales_with_px_per_count():
    # seed Eq. 6: d = SR x displacement; 0.2425 px/count is the seed's rig
    assert encoder_shift_px(1000, 1100, px_per_count=0.2425) == pytest.approx(24.25)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"counts_a": 0, "counts_b": 1, "px_per_count": 0.5, "counter_bits": 24}, "counter_bits"),
        ({"counts_a": 2**16, "counts_b": 1, "px_per_count": 0.5, "counter_bits": 16}, "counts_a"),
        ({"counts_a": 0, "counts_b": 2**32, "px_per_count": 0.5}, "counts_b"),
        ({"counts_a": 0, "counts_b": -(2**31) - 1, "px_per_count": 0.5}, "counts_b"),
        ({"counts_a": 1.5, "counts_b": 1, "px_per_count": 0.5}, "counts_a"),
        ({"counts_a": 0, "counts_b": 1, "px_per_count": 0.0}, "px_per_count"),
        ({"counts_a": 0, "counts_b": 1, "px_per_count": float("nan")}, "px_per_count"),
    ],
)
def test_encoder_shift_rejects_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        encoder_shift_px(**kwargs)


# -- refinement from the images ----------------------------------------------------------------

SLANT = math.radians(82.0)


def _board(seed: int, rows: int, n: int, *, texture: float = 0.05) -> tuple[np.ndarray, ...]:
    """Periodic board fields on n columns: albedo (rows, n) and a band-limited mark slope (n,)."""
    rng = np.random.default_rng(seed)
    kx = np.fft.rfftfreq(n)
    spec = rng.standard_normal((rows, kx.size)) + 1j * rng.standard_normal((rows, kx.size))
    spec *= np.exp(-((kx * 8.0) ** 2))  # fibres elongated along x
    spec[:, 0] = 0
    fib = np.fft.irfft(spec, n=n, axis=1)
    albedo = 0.5 * (1 + texture * fib / (fib.std() or 1.0))
    period = n / 48.0  # marks of ~21 px on 1024 columns
    k = np.arange(1, 12)
    x = np.arange(n)
    # band-limited sawtooth slope, amplitude 0.015
    saw = sum(((-1) ** (j + 1)) / j * np.sin(2 * np.pi * j * x / period) for j in k)
    slope = 0.015 * saw / np.abs(saw).max()
    return albedo, slope


def _fourier_shift(a: np.ndarray, d: float) -> np.ndarray:
    """Sample a periodic signal (last axis) at x - d (band-limited interpolation)."""
    n = a.shape[-1]
    f = np.fft.rfftfreq(n)
    return np.fft.irfft(np.fft.rfft(a, axis=-1) * np.exp(-2j * np.pi * f * d), n=n, axis=-1)


def _pair(d: float, *, seed: int = 0, width: int = 640, rows: int = 32, texture: float = 0.05,
          noise: float = 0.002, other_board: bool = False,
          along_feed_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Images A, B of one board; ``along_feed_only``: every row has the same albedo (1-D)."""
    n = 1024
    albedo, slope = _board(seed, rows, n, texture=texture)
    if along_feed_only:
        albedo = np.repeat(albedo[:1], rows, axis=0)
    rng = np.random.default_rng(seed + 100)

    def shot(alb: np.ndarray, p: np.ndarray, sign: float) -> np.ndarray:
        img = alb * (math.cos(SLANT) + sign * p * math.sin(SLANT))[None, :]
        return img[:, :width] + noise * rng.standard_normal((alb.shape[0], width))

    a = shot(albedo, slope, -1.0)
    if other_board:
        albedo, slope = _board(seed + 1, rows, n, texture=texture)
        if along_feed_only:
            albedo = np.repeat(albedo[:1], rows, axis=0)
    b = shot(_fourier_shift(albedo, d), _fourier_shift(slope, d), +1.0)
    return a.astype(np.float32), b.astype(np.float32)


@pytest.mark.parametrize("true_d", [6.3, 15.0, 31.7])
@pytest.mark.parametrize("encoder_error", [-20.0, -7.5, 0.0, 11.0, 20.0])
def test_refine_shift_recovers_true_shift_despite_encoder_error(true_d, encoder_error):
    a, b = _pair(true_d, seed=int(true_d * 10))
    reg = refine_shift(a, b, encoder_shift_px=true_d + encoder_error)
    assert reg.shift_px == pytest.approx(true_d, abs=0.25)
    assert reg.encoder_shift_px == pytest.approx(true_d + encoder_error)
    assert 0.5 < reg.confidence <= 1.0
    assert reg.fine_score > 0.9  # albedo and mirrored shading agree on the delay


def test_shading_alone_locks_onto_the_wrong_mark_but_texture_does_not():
    # The mark period is ~21 px: a guess 17 px off refines (by shading only) onto the
    # neighbouring mark, one period away; the texture stage lands within a pixel or two.
    true_d = 12.0
    a, b = _pair(true_d, seed=3)
    pa, pb = a.mean(axis=0), b.mean(axis=0)
    wrong, score = shading_shift(pa, pb, guess_px=true_d + 17.0, reach_px=6)
    assert wrong - true_d == pytest.approx(1024 / 48, abs=0.5) and score > 0.9
    reg = Registrar(a.shape[1])
    coarse = reg.coarse(shading_free_texture(a, pa), shading_free_texture(b, pb),
                        encoder_shift_px=true_d + 17.0)
    assert coarse.shift_px == pytest.approx(true_d, abs=2.0)
    # too far from any mirrored shading within the window: no shift, a low score
    lost, _ = shading_shift(pa, pb, guess_px=true_d + 10.5, reach_px=3)
    assert np.isnan(lost)


def test_refine_shift_subpixel_accuracy_over_fractions():
    errs = []
    for frac in np.linspace(0.0, 0.9, 7):
        d = 14.0 + frac
        a, b = _pair(d, seed=7)
        errs.append(refine_shift(a, b, encoder_shift_px=d + 9.0).shift_px - d)
    assert max(abs(e) for e in errs) < 0.2


def test_untextured_pair_is_an_error_not_a_guess():
    a, b = _pair(15.0, texture=0.0, noise=0.0005)
    with pytest.raises(RegistrationError):
        refine_shift(a, b, encoder_shift_px=18.0)


def test_images_of_different_boards_do_not_register():
    a, b = _pair(15.0, other_board=True)
    with pytest.raises(RegistrationError):
        refine_shift(a, b, encoder_shift_px=15.0)


def test_shift_larger_than_the_image_is_an_error():
    a, b = _pair(15.0)
    with pytest.raises(RegistrationError, match="overlap"):
        refine_shift(a, b, encoder_shift_px=700.0)


def test_registrar_checks_its_inputs():
    with pytest.raises(ValueError, match="band_px"):
        Registrar(100, band_px=(9, 5))
    with pytest.raises(ValueError, match="width"):
        Registrar(4)
    reg = Registrar(64)
    with pytest.raises(ValueError, match="shape"):
        reg(np.zeros((4, 64)), np.zeros((4, 63)), encoder_shift_px=0.0)
    with pytest.raises(ValueError, match="encoder_shift_px"):
        reg(np.zeros((4, 64)), np.zeros((4, 64)), encoder_shift_px=float("nan"))


def test_shading_free_texture_removes_column_shading_exactly():
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.4, 0.6, (16, 50))
    shading = rng.uniform(0.5, 1.5, 50)
    rows = albedo * shading[None, :]
    tex = shading_free_texture(rows, rows.mean(axis=0))
    expect = albedo / albedo.mean(axis=0)[None, :]
    expect -= expect.mean(axis=1, keepdims=True)
    np.testing.assert_allclose(tex, expect, atol=1e-5)


# -- albedo along the feed only: the column profiles register the pair ------------------------


@pytest.mark.parametrize("true_d", [9.4, 23.7])
@pytest.mark.parametrize("encoder_error", [-20.0, 0.0, 14.0])
def test_albedo_along_the_feed_only_registers_on_the_column_profiles(true_d, encoder_error):
    a, b = _pair(true_d, seed=int(true_d * 10), along_feed_only=True)
    pa, pb = a.mean(axis=0), b.mean(axis=0)
    reg = Registrar(a.shape[1])
    tex_a, tex_b = shading_free_texture(a, pa), shading_free_texture(b, pb)
    with pytest.raises(RegistrationError):  # no 2-D texture left after the division
        reg.coarse(tex_a, tex_b, encoder_shift_px=true_d + encoder_error)
    res = reg(tex_a, tex_b, encoder_shift_px=true_d + encoder_error, profile_a=pa, profile_b=pb)
    assert res.source == "profile"
    assert res.shift_px == pytest.approx(true_d, abs=0.25)
    assert res.coarse_shift_px == pytest.approx(true_d, abs=1.0)
    assert reg.min_profile_confidence <= res.confidence <= 1.0


def test_profile_stage_alone_finds_the_shift_that_plain_correlation_misses():
    # Correlating the log-profiles themselves pits the albedo peak against the mirrored,
    # periodic shading; the robust correlation of their first differences does not.
    true_d = 15.3
    a, b = _pair(true_d, seed=11, along_feed_only=True)
    pa, pb = a.mean(axis=0), b.mean(axis=0)
    reg = Registrar(a.shape[1]).coarse_profile(pa, pb, encoder_shift_px=true_d - 16.0)
    assert reg.shift_px == pytest.approx(true_d, abs=0.5)
    la, lb = np.log(pa), np.log(pb)
    lags = np.arange(-10, 41)
    plain = [np.corrcoef(la[60:560], lb[60 + k : 560 + k])[0, 1] for k in lags]
    assert abs(lags[int(np.argmax(plain))] - true_d) > 2.0


def test_different_boards_with_albedo_along_the_feed_do_not_register():
    a, b = _pair(15.0, other_board=True, along_feed_only=True)
    with pytest.raises(RegistrationError, match="cannot register"):
        refine_shift(a, b, encoder_shift_px=15.0)


def test_fine_fit_is_blind_to_the_sign_of_each_frequency():
    # Albedo (same sign in A and B) and mirrored shading (opposite signs) vote alike: negating
    # one log-profile (B -> 1 / B) leaves the fit unchanged.
    a, b = _pair(14.35, seed=5)
    pa, pb = a.mean(axis=0).astype(np.float64), b.mean(axis=0).astype(np.float64)
    reg = Registrar(a.shape[1])
    shift, score = reg.fine(pa, pb, guess_px=15.0)
    flipped, score_flipped = reg.fine(pa, 1.0 / pb, guess_px=15.0)
    assert shift == pytest.approx(14.35, abs=0.1)
    assert flipped == pytest.approx(shift, abs=1e-9)
    assert score_flipped == pytest.approx(score, abs=1e-9)
    assert 0.5 < score <= 1.0


def test_fine_fit_needs_the_coarse_shift_within_a_quarter_mark():
    a, b = _pair(14.0, seed=5)
    pa, pb = a.mean(axis=0), b.mean(axis=0)
    reg = Registrar(a.shape[1], fine_px=2)
    shift, score = reg.fine(pa, pb, guess_px=16.0)  # the true delay on the window's edge
    assert math.isnan(shift) and score > 0.9
    _, score = reg.fine(pa, pb, guess_px=18.0)  # not in the window: incoherent
    assert score < reg.min_fine_score
    # Sign-blind, the fit aliases at half a mark (~21.3 px here): hence the coarse stages.
    shift, score = reg.fine(pa, pb, guess_px=14.0 + 1024 / 96)
    assert shift == pytest.approx(14.0 + 1024 / 96, abs=0.3) and score > 0.9


def test_mark_period_from_the_profile():
    a, _ = _pair(10.0, texture=0.0, noise=0.0005)
    assert mark_period_px(a.mean(axis=0)) == pytest.approx(1024 / 48, rel=0.02)
    assert math.isnan(mark_period_px(np.full(200, 0.5)))


def test_untextured_pair_registers_on_shading_only_within_half_a_mark():
    # No albedo at all: unambiguous only when the encoder is trusted to better than half a mark
    # (~21 px marks here): +-6 px is, the default +-20 px is not.
    true_d = 15.4
    a, b = _pair(true_d, texture=0.0, noise=0.0005)
    pa, pb = a.mean(axis=0), b.mean(axis=0)
    tex = shading_free_texture(a, pa), shading_free_texture(b, pb)
    narrow = Registrar(a.shape[1], search_px=6.0)
    reg = narrow(*tex, encoder_shift_px=true_d + 4.0, profile_a=pa, profile_b=pb)
    assert reg.source == "shading"
    assert reg.shift_px == pytest.approx(true_d, abs=0.25)
    period = 1024 / 48
    assert reg.confidence <= (1 - 2 * 6.0 / period) + 1e-9
    with pytest.raises(RegistrationError):
        Registrar(a.shape[1])(*tex, encoder_shift_px=true_d + 4.0, profile_a=pa, profile_b=pb)


@pytest.mark.parametrize(
    "texture, profile, expect",
    [
        ((10.0, 0.3), (10.8, 0.4), 10.8),  # agree: the more confident
        ((10.0, 0.3), (None, 0.0), 10.0),  # one only
        ((10.0, 0.3), (17.0, 0.6), 17.0),  # disagree, but one is strong
        ((10.0, 0.3), (17.0, 0.35), None),  # disagree, neither strong: an error
    ],
)
def test_choice_between_the_coarse_stages(texture, profile, expect):
    reg = Registrar(200)

    def result(shift, conf, source):
        if shift is None:
            return None
        return Registration(shift_px=shift, confidence=conf, encoder_shift_px=12.0, source=source)

    tex = result(*texture, "texture")
    prof = result(*profile, "profile")
    if expect is None:
        with pytest.raises(RegistrationError, match="disagree"):
            reg._choose(tex, prof)
    else:
        assert reg._choose(tex, prof).shift_px == expect
