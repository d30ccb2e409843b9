"""Slope to height by frequency-domain integration (seed ref. [17], Frankot-Chellappa in 1-D).

A profile is not periodic: integrating its slope with a plain FFT wraps the end onto the start and
rings.  Here the height is extended *evenly* about both ends (a mirror image), which is
continuous and periodic; its slope is then the *odd* extension of the measured slope.  On that
extension the Fourier series becomes a sine series for the slope and a cosine series for the
height, so the integration is exact with real transforms of the profile's own length:

    slope  p[n] = sum_m b_m sin(pi m (n + 1/2) / N)     (DST-II)
    height h[n] = -sum_m b_m N dx / (pi m) cos(pi m (n + 1/2) / N)     (DCT-II)

The transform length ``N`` is fixed once per profile length with ``scipy.fft.next_fast_len``;
shorter profiles are padded with zero slope (the height continues flat beyond the end, still
continuous).  Heights come out absolute in micrometres (``dx`` in mm, times 1000) with zero mean
over the profile.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft

from core.checks import check_1d, check_int, check_positive
from vision import ffts


class Integrator:
    """Frequency-domain integrator for profiles of up to ``max_len`` samples.

    Parameters
    ----------
    max_len : int
        Longest profile, samples.
    dx_mm : float
        Sample spacing, millimetres (``1 / px_per_mm``).
    """

    def __init__(self, max_len: int, *, dx_mm: float) -> None:
        self.max_len = check_int("max_len", max_len, lo=2)
        self.dx_mm = check_positive("dx_mm", dx_mm)
        n = scipy.fft.next_fast_len(self.max_len, real=True)
        self.nfft = n
        m = np.arange(n, dtype=np.float64)
        factor = np.zeros(n)
        factor[1:] = -n * self.dx_mm * 1000.0 / (math.pi * m[1:])
        self._factor = factor  # applied to DST coefficient m-1 -> DCT coefficient m, in um

    def __call__(self, slope: np.ndarray) -> np.ndarray:
        """Integrate a slope profile.

        Parameters
        ----------
        slope : ndarray, shape (n,), n <= max_len
            ``p = dz/dx`` at samples ``dx_mm`` apart.

        Returns
        -------
        ndarray, shape (n,)
            Height, micrometres, zero mean.
        """
        p = np.asarray(slope, dtype=np.float64)
        n = p.size
        if p.ndim != 1 or n < 2 or n > self.max_len:
            raise ValueError(f"slope must be 1-D with 2..{self.max_len} samples, got {p.shape}")
        coef = ffts.dst2(p, self.nfft)
        dct = np.empty(self.nfft)
        dct[0] = 0.0
        dct[1:] = coef[:-1] * self._factor[1:]
        h = ffts.idct2(dct)[:n]
        return h - h.sum() / h.size


def integrate_slope(slope: np.ndarray, *, dx_mm: float) -> np.ndarray:
    """Height from slope by frequency-domain integration (one-off convenience wrapper).

    Parameters
    ----------
    slope : ndarray, shape (n,)
        ``p = dz/dx`` (dimensionless) at samples ``dx_mm`` apart.
    dx_mm : float
        Sample spacing, millimetres.

    Returns
    -------
    ndarray, shape (n,)
        Height, micrometres, zero mean.
    """
    p = check_1d("slope", slope)
    return Integrator(p.size, dx_mm=dx_mm)(p)
