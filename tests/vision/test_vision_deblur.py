"""Motion blur length and Wiener deblurring of column profiles."""

from __future__ import annotations

import numpy as np
import pytest

from vision.deblur import Deblurrer, blur_length_px, wiener_deblur


def test_blur_length_formula():
    # 1 m/s for 0.1 ms at 12.5 px/mm: 0.1 mm = 1.25 px
    assert blur_length_px(1000.0, exposure_ms=0.1, px_per_mm=12.5) == pytest.approx(1.25)
    assert blur_length_px(0.0, exposure_ms=0.1, px_per_mm=12.5) == 0.0
    with pytest.raises(ValueError, match="speed_mm_s"):
        blur_length_px(-1.0, exposure_ms=0.1, px_per_mm=12.5)
    with pytest.raises(ValueError, match="px_per_mm"):
        blur_length_px(1.0, exposure_ms=0.1, px_per_mm=0.0)


def _pixelated_sawtooth(n: int, period: float, blur: float, up: int = 40) -> tuple[np.ndarray, ...]:
    """Pixel-integrated sawtooth intensity, sharp and blurred by a box of ``blur`` pixels."""
    xf = (np.arange(n * up) + 0.5) / up
    sig = 3.0 + (xf % period) / period
    sharp = sig.reshape(n, up).mean(axis=1)
    k = max(1, int(round(blur * up)))
    blurred_f = np.convolve(np.pad(sig, k, mode="edge"), np.ones(k) / k, mode="same")[k:-k]
    return sharp, blurred_f.reshape(n, up).mean(axis=1)


@pytest.mark.parametrize("blur, gain", [(2.0, 0.8), (4.0, 0.6), (6.0, 0.6)])
def test_wiener_restores_box_blurred_profile(blur, gain):
    sharp, blurred = _pixelated_sawtooth(600, 17.3, blur)
    restored = wiener_deblur(blurred, blur_px=blur, regularisation=0.003)
    inner = slice(40, -40)
    err_before = np.sqrt(np.mean((blurred - sharp)[inner] ** 2))
    err_after = np.sqrt(np.mean((restored - sharp)[inner] ** 2))
    assert err_after < gain * err_before
    assert restored.mean() == pytest.approx(blurred.mean(), rel=1e-3)


def test_zero_blur_is_identity_and_shapes_are_checked():
    d = Deblurrer(50)
    p = np.random.default_rng(0).uniform(1, 2, 50)
    np.testing.assert_array_equal(d(p, blur_px=0.0), p)
    both = d(np.stack([p, 2 * p]), blur_px=3.0)
    np.testing.assert_allclose(both[1], 2 * both[0])
    with pytest.raises(ValueError, match="samples"):
        d(np.ones(49), blur_px=1.0)
    with pytest.raises(ValueError, match="regularisation"):
        Deblurrer(50, regularisation=0.0)
