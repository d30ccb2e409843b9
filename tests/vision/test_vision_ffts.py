"""vision.ffts: scipy.fft's numbers bit for bit, without its dispatch."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.fft

from vision import ffts


def _rows(rng: np.random.Generator, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    return rng.standard_normal(shape).astype(dtype)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("n", [600, 640, 1024, 500])
def test_rfft_is_scipys_padded_or_truncated(dtype: type, n: int) -> None:
    rng = np.random.default_rng(n)
    x = _rows(rng, (620,), dtype)
    got = ffts.rfft(x, n)
    want = scipy.fft.rfft(x, n=n)
    assert got.dtype == want.dtype
    assert np.array_equal(got, want)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_rfft_along_rows(dtype: type) -> None:
    rng = np.random.default_rng(3)
    x = _rows(rng, (12, 659), dtype)
    for axis in (1, -1):
        assert np.array_equal(ffts.rfft(x, 720, axis=axis), scipy.fft.rfft(x, n=720, axis=axis))
    assert np.array_equal(ffts.rfft(x, 16, axis=0), scipy.fft.rfft(x, n=16, axis=0))


def test_rfft_of_integers_is_float64() -> None:
    x = np.arange(50)
    got = ffts.rfft(x, 64)
    assert got.dtype == np.complex128
    assert np.array_equal(got, scipy.fft.rfft(x, n=64))


@pytest.mark.parametrize("real_input", [True, False])
def test_irfft_is_scipys(real_input: bool) -> None:
    rng = np.random.default_rng(5)
    spec = scipy.fft.rfft(rng.standard_normal(1280))
    power = spec.real**2 + spec.imag**2
    s = power if real_input else spec
    for n in (1280, 1279, 1000):
        assert np.array_equal(ffts.irfft(s, n), scipy.fft.irfft(s, n=n))


@pytest.mark.parametrize("dtype", [np.complex128, np.complex64])
def test_fft_along_the_groups(dtype: type) -> None:
    rng = np.random.default_rng(7)
    x = (rng.standard_normal((2, 6, 40)) + 1j * rng.standard_normal((2, 6, 40))).astype(dtype)
    got = ffts.fft(x, 16, axis=1)
    want = scipy.fft.fft(x, n=16, axis=1)
    assert got.dtype == want.dtype
    assert np.array_equal(got, want)


def test_dst2_and_idct2_are_scipys() -> None:
    rng = np.random.default_rng(11)
    p = rng.standard_normal(611)
    for n in (611, 640):
        assert np.array_equal(ffts.dst2(p, n), scipy.fft.dst(p, type=2, n=n))
    c = rng.standard_normal(640)
    assert np.array_equal(ffts.idct2(c), scipy.fft.idct(c, type=2))


@pytest.mark.parametrize("axis", [-1, 1, 0])
def test_dct2_and_idct2_along_an_axis(axis: int) -> None:
    rng = np.random.default_rng(17)
    x = rng.standard_normal((3, 212))
    assert np.array_equal(ffts.dct2(x, axis=axis), scipy.fft.dct(x, type=2, axis=axis))
    assert np.array_equal(ffts.idct2(x, axis=axis), scipy.fft.idct(x, type=2, axis=axis))


def test_without_pocketfft_the_public_functions(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(13)
    x = rng.standard_normal((3, 100))
    want = (ffts.rfft(x, 128, axis=1), ffts.irfft(x[0, :65], 128),
            ffts.fft(x + 0j, 128, axis=1), ffts.dst2(x[0], 128), ffts.idct2(x[1]), ffts.dct2(x))
    monkeypatch.setattr(ffts, "_pocketfft", None)
    got = (ffts.rfft(x, 128, axis=1), ffts.irfft(x[0, :65], 128),
           ffts.fft(x + 0j, 128, axis=1), ffts.dst2(x[0], 128), ffts.idct2(x[1]), ffts.dct2(x))
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g, w)
