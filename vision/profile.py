"""Column averaging (seed section 2.1) and sub-pixel resampling of column profiles.

The cuttermarks run across the board (q = 0), so averaging each undistorted column turns an
image into an intensity profile along the feed, averaging out albedo texture, fibre roughness and
sensor noise.  Image B is resampled at ``u + shift_px`` to bring it onto A's columns.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from core.checks import check_finite, check_int
from vision import kernels


def column_profile(rows: np.ndarray) -> np.ndarray:
    """Mean of each column.

    Parameters
    ----------
    rows : ndarray, shape (n_rows, width)
        Undistorted image, or a band of (binned) rows of it.

    Returns
    -------
    ndarray, shape (width,), float64
        Column means, same intensity units as ``rows``.
    """
    arr = np.asarray(rows)
    if arr.ndim != 2 or arr.shape[0] < 1:
        raise ValueError(f"rows must be a non-empty 2-D array, got shape {arr.shape}")
    if arr.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        arr = arr.astype(np.float32)
    total = cv2.reduce(arr, 0, cv2.REDUCE_SUM, dtype=cv2.CV_64F)
    return total.ravel() / arr.shape[0]


def overlap(
    width: int, shift_px: float, *, columns: tuple[int, int] | None = None, taps: int = 2
) -> tuple[int, int]:
    """A's columns whose partner ``u + shift_px`` in B can be interpolated inside ``columns``.

    Parameters
    ----------
    width : int
        Profile length, pixels.
    shift_px : float
        Registration shift.
    columns : tuple of int, optional
        ``(c0, c1)``, the valid columns of both profiles (default: all).
    taps : int, optional
        Interpolation half-width, samples (2 for cubic).

    Returns
    -------
    tuple of int
        ``(u0, u1)`` with ``u0 < u1`` (empty overlap gives ``u0 >= u1``).
    """
    w = check_int("width", width, lo=1)
    d = check_finite("shift_px", shift_px)
    c0, c1 = (0, w) if columns is None else columns
    u0 = max(c0, math.ceil(c0 + taps - 1 - d))
    u1 = min(c1, math.floor(c1 - taps - 1 - d) + 1)
    return u0, u1


def shift_profile(
    profile: np.ndarray, *, shift_px: float, start: int = 0, count: int | None = None
) -> np.ndarray:
    """Resample a profile at ``start + shift_px + i`` (i = 0..count-1) by cubic convolution.

    Keys' cubic (a = -0.5) keeps the sharp intensity steps at the cusps better than linear
    interpolation, whose smoothing would differ between A (not resampled) and B.

    Parameters
    ----------
    profile : ndarray, shape (n,)
        Samples at integer positions ``0..n-1``.
    shift_px : float
        Sub-pixel offset added to every position.
    start : int, optional
        First output position before the shift.
    count : int, optional
        Number of output samples (default: up to the end of ``profile``).

    Returns
    -------
    ndarray, shape (count,), float64
        Interpolated values.

    Raises
    ------
    ValueError
        A position lacks its four neighbours inside the profile.
    """
    p = np.asarray(profile, dtype=np.float64)
    n = p.size
    d = check_finite("shift_px", shift_px)
    if count is None:
        count = n - start
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count!r}")
    base = math.floor(d)
    t = d - base
    i0 = start + base
    if t == 0:
        if i0 < 0 or i0 + count > n:
            raise ValueError(f"shift_px={d:.3f} reaches outside a profile of {n} samples")
        return p[i0 : i0 + count].copy()
    if i0 - 1 < 0 or i0 + count + 2 > n:
        raise ValueError(
            f"shift_px={d:.3f} with start={start}, count={count} reaches outside a profile "
            f"of {n} samples"
        )
    a = -0.5
    w_m1 = a * t * (t - 1) ** 2
    w_0 = (a + 2) * t**3 - (a + 3) * t**2 + 1
    s = 1 - t
    w_p1 = (a + 2) * s**3 - (a + 3) * s**2 + 1
    w_p2 = a * s * (s - 1) ** 2
    # w_m1 p[i0 - 1 + i] + w_0 p[i0 + i] + w_p1 p[i0 + 1 + i] + w_p2 p[i0 + 2 + i], summed
    # left to right as numpy's slices were, in one compiled pass
    return kernels.cubic_shift(np.ascontiguousarray(p), int(i0), int(count), float(w_m1),
                               float(w_0), float(w_p1), float(w_p2))
