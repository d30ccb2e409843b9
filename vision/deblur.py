"""Motion deblurring of column profiles along the feed (Wiener, as the seed suggests).

During an exposure of ``exposure_ms`` the board moves ``speed_mm_s * exposure_ms / 1000`` mm, so
every image is convolved along x with a box of ``blur_px = speed * exposure * px_per_mm`` pixels.
Column averaging commutes with that blur, so the 1-D column profiles are deconvolved instead of
the images.  The profile is extended evenly about both ends (no wrap-around jump) by working in
the DCT-II domain, where a symmetric filter is a product: the box's transfer function is
``sinc(f * blur_px)`` at ``f = k / (2 N)`` cycles per pixel, and the Wiener filter is
``H / (H^2 + k_reg)``.
"""

from __future__ import annotations

import numpy as np
import scipy.fft

from core.checks import check_int, check_positive
from vision import ffts


def blur_length_px(speed_mm_s: float, *, exposure_ms: float, px_per_mm: float) -> float:
    """Length of the motion blur, pixels: ``speed * exposure / 1000 * px_per_mm``.

    Parameters
    ----------
    speed_mm_s : float
        Feed speed at capture, mm/s.
    exposure_ms : float
        Exposure time, ms.
    px_per_mm : float
        Image scale along the feed.

    Returns
    -------
    float
    """
    v = check_positive("speed_mm_s", speed_mm_s, allow_zero=True)
    e = check_positive("exposure_ms", exposure_ms, allow_zero=True)
    s = check_positive("px_per_mm", px_per_mm)
    return v * e / 1000.0 * s


class Deblurrer:
    """Wiener deconvolution of profiles of one length with a box PSF along x.

    Parameters
    ----------
    length : int
        Profile length, samples (fixed; the transform size is chosen once).
    regularisation : float, optional
        Wiener constant ``k_reg`` (noise-to-signal power ratio); larger is smoother.
    """

    def __init__(self, length: int, *, regularisation: float = 0.01) -> None:
        self.length = check_int("length", length, lo=2)
        self.regularisation = check_positive("regularisation", regularisation)
        self.nfft = scipy.fft.next_fast_len(self.length, real=True)
        self._freq = np.arange(self.nfft) / (2.0 * self.nfft)  # cycles per pixel
        self._cache: tuple[float, np.ndarray] | None = None

    def gain(self, blur_px: float) -> np.ndarray:
        """Wiener gain per DCT-II coefficient for a box of ``blur_px`` pixels."""
        b = check_positive("blur_px", blur_px, allow_zero=True)
        if self._cache is not None and self._cache[0] == b:
            return self._cache[1]
        h = np.sinc(self._freq * b)
        g = h / (h * h + self.regularisation)
        g *= 1.0 / g[0]  # keep the mean level
        self._cache = (b, g)
        return g

    def __call__(self, profile: np.ndarray, *, blur_px: float) -> np.ndarray:
        """Deconvolve one profile.

        Parameters
        ----------
        profile : ndarray, shape (length,) or (k, length)
            Column profile(s) blurred by a box of ``blur_px`` pixels along x.
        blur_px : float
            Blur length, pixels.

        Returns
        -------
        ndarray, same shape
        """
        p = np.asarray(profile, dtype=np.float64)
        if p.shape[-1] != self.length:
            raise ValueError(f"profile must have {self.length} samples, got {p.shape[-1]}")
        if blur_px <= 0:
            return p.copy()
        n, L = self.nfft, self.length
        if n > L:
            pad = [(0, 0)] * (p.ndim - 1) + [(0, n - L)]
            p = np.pad(p, pad, mode="edge")
        coef = ffts.dct2(p)
        coef *= self.gain(blur_px)
        return ffts.idct2(coef)[..., :L]


def wiener_deblur(profile: np.ndarray, *, blur_px: float, regularisation: float = 0.01
                  ) -> np.ndarray:
    """Deconvolve a profile blurred by a box of ``blur_px`` pixels (one-off wrapper).

    Parameters
    ----------
    profile : ndarray, shape (n,)
        Column profile.
    blur_px : float
        Blur length, pixels.
    regularisation : float, optional
        Wiener constant.

    Returns
    -------
    ndarray, shape (n,)
    """
    p = np.asarray(profile, dtype=np.float64)
    return Deblurrer(p.shape[-1], regularisation=regularisation)(p, blur_px=blur_px)
