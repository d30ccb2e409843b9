"""Shared entry-point checks: each raises ``ValueError`` naming the offending parameter."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def check_finite(name: str, value: float) -> float:
    """Return ``value`` as float, or raise ``ValueError`` if it is not a finite number."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def check_positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    """Return ``value`` as float, or raise ``ValueError`` if it is not (strictly) positive."""
    v = check_finite(name, value)
    if v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be {bound}, got {value!r}")
    return v


def check_range(name: str, value: float, lo: float, hi: float) -> float:
    """Return ``value`` as float, or raise ``ValueError`` if it lies outside ``[lo, hi]``."""
    v = check_finite(name, value)
    if not lo <= v <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}], got {value!r}")
    return v


def check_int(name: str, value: int, *, lo: int | None = None, hi: int | None = None) -> int:
    """Return ``value`` as int, or raise ``ValueError`` if it is not an integer within bounds."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    v = int(value)
    if lo is not None and v < lo:
        raise ValueError(f"{name} must be >= {lo}, got {v}")
    if hi is not None and v > hi:
        raise ValueError(f"{name} must be <= {hi}, got {v}")
    return v


def check_image(name: str, image: np.ndarray) -> np.ndarray:
    """Check a single-channel image: a 2-D, non-empty, real-valued array with finite values."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D (grayscale) image, got shape {arr.shape}")
    if arr.shape[0] < 2 or arr.shape[1] < 8:
        raise ValueError(f"{name} is too small: shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(f"{name} must be an integer or float image, got dtype {arr.dtype}")
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def check_same_shape(names: Sequence[str], *arrays: np.ndarray) -> None:
    """Raise ``ValueError`` unless all arrays share one shape; the message names both."""
    shapes = [np.shape(a) for a in arrays]
    for n, s in zip(names[1:], shapes[1:], strict=False):
        if s != shapes[0]:
            raise ValueError(f"{names[0]} and {n} differ in shape: {shapes[0]} vs {s}")


def check_1d(name: str, values: np.ndarray, *, min_len: int = 2) -> np.ndarray:
    """Return ``values`` as a finite 1-D float array of at least ``min_len`` samples."""
    arr = np.asarray(values, dtype=float)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if arr.size < min_len:
        raise ValueError(f"{name} needs at least {min_len} samples, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr
