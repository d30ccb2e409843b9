"""The pair path's FFTs without the dispatch layers' call overhead.

``scipy.fft``'s functions reach their transforms (pocketfft, ``scipy.fft._pocketfft``) through
the uarray backend dispatch and argument normalisation: 5-7 us a call, more than a 1-D
transform of a profile costs itself; ``numpy.fft`` adds 3-4 us.  These functions call the same
transforms with the arguments scipy would pass them (zero-padding or truncation along the axis
as ``_fix_shape_1d`` does it, no scaling forward, ``1/n`` backward, one worker): the same
numbers, bit for bit.  Without the module (a scipy that moved it) they fall back to
``scipy.fft`` itself.
"""

from __future__ import annotations

import numpy as np
import scipy.fft

try:  # scipy's own binding of pocketfft (private; present since scipy 1.4)
    from scipy.fft._pocketfft import pypocketfft as _pocketfft
except ImportError:  # pragma: no cover - a scipy without it: the public functions
    _pocketfft = None

_FORWARD = 0  # no scaling
_BACKWARD = 2  # scaled by 1/n


def _fit(x: np.ndarray, n: int, axis: int) -> np.ndarray:
    """``x`` zero-padded or truncated to ``n`` samples along ``axis`` (scipy's ``_fix_shape``)."""
    size = x.shape[axis]
    if size == n:
        return x
    if size > n:
        index = [slice(None)] * x.ndim
        index[axis] = slice(0, n)
        return x[tuple(index)]
    shape = list(x.shape)
    shape[axis] = n
    out = np.zeros(shape, dtype=x.dtype)
    index = [slice(None)] * x.ndim
    index[axis] = slice(0, size)
    out[tuple(index)] = x
    return out


def _floats(x: np.ndarray) -> np.ndarray:
    """Float32 and float64 as they are, anything else as float64 (scipy's ``_asfarray``)."""
    a = np.asarray(x)
    if a.dtype in (np.float32, np.float64):
        return a
    return a.astype(np.float64)


def rfft(x: np.ndarray, n: int, axis: int = -1) -> np.ndarray:
    """``scipy.fft.rfft(x, n=n, axis=axis)`` of a real array.

    Parameters
    ----------
    x : ndarray
        Real samples (float32 stays single precision, as in scipy).
    n : int
        Transform length (zero-padded or truncated along ``axis``).
    axis : int, optional
        Axis transformed.

    Returns
    -------
    ndarray
        The ``n // 2 + 1`` complex coefficients along ``axis``.
    """
    if _pocketfft is None:
        return scipy.fft.rfft(x, n=n, axis=axis)
    a = _floats(x)
    axis = axis % a.ndim
    return _pocketfft.r2c(_fit(a, n, axis), (axis,), True, _FORWARD, None, 1)


def irfft(spectrum: np.ndarray, n: int) -> np.ndarray:
    """``scipy.fft.irfft(spectrum, n=n)`` along the last axis (a real spectrum as complex).

    Parameters
    ----------
    spectrum : ndarray
        The ``n // 2 + 1`` coefficients (real or complex) along the last axis.
    n : int
        Length of the real output.

    Returns
    -------
    ndarray
        Real samples, scaled by ``1 / n``.
    """
    if _pocketfft is None:
        return scipy.fft.irfft(spectrum, n=n)
    s = np.asarray(spectrum)
    if not np.iscomplexobj(s):
        s = _floats(s) + 0.0j
    axis = s.ndim - 1
    return _pocketfft.c2r(_fit(s, n // 2 + 1, axis), (axis,), n, False, _BACKWARD, None, 1)


def fft(x: np.ndarray, n: int, axis: int = -1) -> np.ndarray:
    """``scipy.fft.fft(x, n=n, axis=axis)`` of a complex array.

    Parameters
    ----------
    x : ndarray
        Complex samples (complex64 stays single precision).
    n : int
        Transform length along ``axis``.
    axis : int, optional
        Axis transformed.

    Returns
    -------
    ndarray
        The ``n`` complex coefficients along ``axis``.
    """
    a = np.asarray(x)
    if _pocketfft is None or not np.iscomplexobj(a):
        return scipy.fft.fft(a, n=n, axis=axis)
    axis = axis % a.ndim
    return _pocketfft.c2c(_fit(a, n, axis), (axis,), True, _FORWARD, None, 1)


def dst2(x: np.ndarray, n: int) -> np.ndarray:
    """``scipy.fft.dst(x, type=2, n=n)`` of a 1-D real array (unnormalised).

    Parameters
    ----------
    x : ndarray, shape (m,)
        Real samples.
    n : int
        Transform length (zero-padded or truncated).

    Returns
    -------
    ndarray, shape (n,)
    """
    if _pocketfft is None:
        return scipy.fft.dst(x, type=2, n=n)
    a = _fit(_floats(x), n, 0)
    return _pocketfft.dst(a, 2, (0,), _FORWARD, None, 1, None)


def dct2(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """``scipy.fft.dct(x, type=2, axis=axis)`` of a real array (unnormalised).

    Parameters
    ----------
    x : ndarray
        Real samples.
    axis : int, optional
        Axis transformed.

    Returns
    -------
    ndarray
        Same shape as ``x``.
    """
    if _pocketfft is None:
        return scipy.fft.dct(x, type=2, axis=axis)
    a = _floats(x)
    return _pocketfft.dct(a, 2, (axis % a.ndim,), _FORWARD, None, 1, None)


def idct2(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """``scipy.fft.idct(x, type=2, axis=axis)`` of a real array (a DCT-III scaled by ``1 / (2 n)``).

    Parameters
    ----------
    x : ndarray
        DCT-II coefficients along ``axis``.
    axis : int, optional
        Axis transformed.

    Returns
    -------
    ndarray
        Same shape as ``x``.
    """
    if _pocketfft is None:
        return scipy.fft.idct(x, type=2, axis=axis)
    a = _floats(x)
    return _pocketfft.dct(a, 3, (axis % a.ndim,), _BACKWARD, None, 1, None)
