"""Orientation of the cuttermarks in the image (camera roll) and averaging along the marks.

A camera rolled by ``roll`` about its axis sees the board point ``xi = (u - cx) cos(roll) +
(v - cy) sin(roll)`` (along the feed, pixels) at pixel ``(u, v)``; the marks are lines of constant
``xi``, tilted from the image columns, and the board moves along ``(cos(roll), sin(roll))``.
Averaging plain columns smears a mark over ``height * tan(roll)`` pixels -- a whole mark at 3 deg
on a 493-row image.

**Estimate** (:class:`RollEstimator`).  The shear ``u' = u + (v - cy) tan(roll)`` makes the marks
vertical: row ``v`` resampled at ``u' - (v - cy) tan(roll)``.  For every candidate angle on a grid
the sheared high-passed log rows are summed (in the Fourier domain: one phase ramp per row and
angle, set up once), and the power of the sum measures how well the marks line up; the marks
add coherently only at the true angle, noise and albedo not at all.  Both images vote (their
powers add).  Parabolic peak on the grid; confidence ``1 - P_min / P_max`` (0: no preferred
direction), 0 when the peak lies on the grid's edge.

**Average** (:class:`Shearer`).  The binned rows are resampled along the marks with a
``cv2.remap`` table built once per roll estimate (cached), so the column means of the result are
means along the marks.  Sample ``u'`` of the result lies ``(u' - cx) cos(roll)`` pixels from the
image centre along the feed, and the board's motion ``D`` (px along the feed) becomes a shift of
``D / cos(roll)`` along ``u'``.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft

from core.checks import check_int, check_positive
from vision import check_kernels, ffts


@dataclass(frozen=True)
class Orientation:
    """The marks' direction in the image.

    Attributes
    ----------
    roll_deg : float
        Angle of the feed direction from the image x axis, turning +x toward +v (rows run
        down: clockwise on the screen), degrees.
        The marks run at ``roll_deg`` from the image columns.
    confidence : float
        In [0, 1]: ``1 - P_min / P_max`` of the alignment power over the searched angles;
        0 when the best angle lies on the edge of the search.
    """

    roll_deg: float
    confidence: float


CLIP_SIGMAS = 3.0
"""High-passed log rows are clipped at this many robust standard deviations (all rows')."""
CLIP_SAMPLES = 1024
"""About this many samples (every k-th of the rows) give the clip's robust deviation."""


def _highpassed_log_rows(rows: np.ndarray, highpass_px: int) -> np.ndarray:
    """High-passed log rows, clipped at :data:`CLIP_SIGMAS` robust standard deviations.

    The marks' sawtooth lies well inside the clip (a uniform spread: its robust deviation is
    0.74 of its half-height); a pit's or a chip's shadow does not, and clipped it no longer
    outvotes the marks across the field with its own direction (a pit across the feed at
    86 deg pulled the estimate 3 deg off).
    """
    r = np.log(np.maximum(np.asarray(rows, dtype=np.float32), np.float32(1e-3)))
    smooth = cv2.blur(r, (highpass_px, 1), borderType=cv2.BORDER_REFLECT)
    hp = r - smooth
    # the median of ~1000 samples (its level within ~4 %: plenty for a clip at 3 sigmas; a
    # quickselect over thousands costs tens of microseconds on a pair)
    step = max(1, hp.size // CLIP_SAMPLES)
    check_kernels.clip_robust(hp, step, CLIP_SIGMAS)  # in place, one compiled call
    return hp


class RollEstimator:
    """Estimates the roll of a pair from its binned rows (set up once per row layout).

    The rows are averaged into ``groups`` groups of equally many adjacent rows (evenly spaced,
    so that the alignment power needs only the groups' lag products): with ``S_g(f)`` the
    spectrum of group ``g`` and ``R_l(f) = sum_g S_(g+l)(f) conj(S_g(f))`` (summed over the
    images), the power of the sum sheared by ``tan(a)`` is
    ``sum_f R_0 + 2 sum_(l>0) Re(R_l exp(-2 pi i f tan(a) D l))`` (``D``: the groups' spacing),
    one matrix-vector product over all angles (its matrix set up once).

    Parameters
    ----------
    row_v_px : ndarray, shape (n_rows,)
        Undistorted image row (pixels) at the centre of each binned row (evenly spaced).
    width : int
        Columns of the binned rows.
    cy : float
        Image row of the optical axis, pixels.
    centre_deg : float, optional
        Centre of the search (the rig's roll), degrees.
    max_roll_deg : float, optional
        Half-width of the search around ``centre_deg``, degrees (one grid step more is
        searched, so a roll of ``max_roll_deg`` is not on the edge).
    step_deg : float, optional
        Grid of the search, degrees (parabolic peak between).
    groups : int, optional
        Adjacent binned rows are averaged into at most this many groups (of equally many rows;
        the remainder, fewer than ``groups`` rows, is left out evenly at both ends).
    highpass_px : int, optional
        Running mean removed from the log rows (illumination, albedo trends), pixels.
    max_frequency : float, optional
        Highest frequency used, cycles per pixel.
    """

    def __init__(
        self,
        row_v_px: np.ndarray,
        width: int,
        *,
        cy: float,
        centre_deg: float = 0.0,
        max_roll_deg: float = 5.0,
        step_deg: float = 0.5,
        groups: int = 16,
        highpass_px: int = 41,
        max_frequency: float = 0.25,
    ) -> None:
        v = np.asarray(row_v_px, dtype=np.float64)
        if v.ndim != 1 or v.size < 2:
            raise ValueError(f"row_v_px must hold at least 2 rows, got shape {v.shape}")
        self.width = check_int("width", width, lo=16)
        check_positive("max_roll_deg", max_roll_deg)
        check_positive("step_deg", step_deg)
        self.highpass_px = check_int("highpass_px", highpass_px, lo=3)
        g = min(check_int("groups", groups, lo=2), v.size)
        size = v.size // g
        first = (v.size - g * size) // 2
        self._rows = slice(first, first + g * size)
        self._groups, self._size = g, size
        self._group_v = v[self._rows].reshape(g, size).mean(axis=1) - cy
        spacing = np.diff(self._group_v)
        if not np.allclose(spacing, spacing[0], rtol=1e-6, atol=1e-6 * abs(spacing[0]) + 1e-9):
            raise ValueError("row_v_px must be evenly spaced")
        n_steps = int(math.ceil(max_roll_deg / step_deg)) + 1
        self.angles_deg = centre_deg + step_deg * np.arange(-n_steps, n_steps + 1)
        tan = np.tan(np.radians(self.angles_deg))
        reach = float(np.max(np.abs(self._group_v))) * float(np.max(np.abs(tan)))
        self.nfft = scipy.fft.next_fast_len(self.width + 2 * int(math.ceil(reach)) + 2)
        k = int(max_frequency * self.nfft) + 1
        k0 = max(1, int(self.nfft / self.highpass_px))
        freq = np.arange(k0, k) / self.nfft
        self._k = (k0, k)
        # Power(angle) = sum over (lag, f) of w_l [Re R_l cos(theta) + Im R_l sin(theta)],
        # theta = 2 pi f tan(angle) D l: the matrix of both parts, set up once.
        lag = np.arange(g, dtype=np.float64)
        theta = (2.0 * np.pi * float(spacing[0]) * tan[:, None, None] * lag[None, :, None]
                 * freq[None, None, :])
        weight = np.where(lag == 0, 1.0, 2.0)[None, :, None]
        self._lag_nfft = n_lag = scipy.fft.next_fast_len(2 * g - 1)
        # R_l = ifft over the groups of |X_k|^2 (X: the spectra's FFT along the groups), so
        # the power is also one product with |X_k(f)|^2 directly: the inverse FFT folded in,
        # W[a, k, f] = (1 / L) sum_l w_l cos(theta[a, l, f] - 2 pi k l / L).
        phase = 2.0 * np.pi * np.outer(np.arange(n_lag), lag) / n_lag  # (L, lags)
        w_cos = np.einsum("alf,kl->akf", weight * np.cos(theta), np.cos(phase))
        w_sin = np.einsum("alf,kl->akf", weight * np.sin(theta), np.sin(phase))
        self._matrix = ((w_cos + w_sin) / n_lag).reshape(tan.size, -1).astype(np.float32)
        self._taper = np.hanning(self.width).astype(np.float32)

    def _group_means(self, rows: np.ndarray) -> np.ndarray:
        src = np.asarray(rows)
        if src.ndim != 2 or src.shape[1] != self.width or src.shape[0] < self._rows.stop:
            raise ValueError(f"rows must have shape (>= {self._rows.stop}, {self.width}), "
                             f"got {src.shape}")
        part = src[self._rows].reshape(self._groups, self._size, self.width)
        return part.sum(axis=1, dtype=np.float32) * np.float32(1.0 / self._size)

    def _group_power(self, grouped: np.ndarray) -> np.ndarray:
        """``|X_k(f)|^2`` summed over the images (``X``: FFT along the groups of the spectra).

        ``grouped`` has shape (images, groups, width).
        """
        n_img = grouped.shape[0]
        hp = _highpassed_log_rows(grouped.reshape(-1, self.width), self.highpass_px)
        hp *= self._taper[None, :]
        k0, k = self._k
        spec = ffts.rfft(hp, self.nfft, axis=1)[:, k0:k]
        spec = spec.reshape(n_img, self._groups, k - k0)
        # Lag products along the groups by one FFT each way (zero-padded: no wrap-around).
        over_g = ffts.fft(spec, self._lag_nfft, axis=1)
        return (over_g.real**2 + over_g.imag**2).sum(axis=0, dtype=np.float32)

    def _power(self, group_power: np.ndarray) -> np.ndarray:
        return np.einsum("tk,k->t", self._matrix, group_power.ravel()).astype(np.float64)

    def power(self, rows: np.ndarray) -> np.ndarray:
        """Alignment power of one image's binned rows at every searched angle.

        Parameters
        ----------
        rows : ndarray, shape (n_rows, width)
            Positive binned rows (undistorted).

        Returns
        -------
        ndarray, shape (n_angles,)
            Power of the sheared sum of the high-passed log rows.
        """
        return self._power(self._group_power(self._group_means(rows)[None]))

    def estimate(self, grouped: np.ndarray) -> Orientation:
        """Roll from the group means already formed (e.g. by :class:`vision.front_end.FrontEnd`).

        Parameters
        ----------
        grouped : ndarray, shape (n_images, groups, width)
            Positive mean of each group's rows, per image (the groups of this estimator).

        Returns
        -------
        Orientation
        """
        g = np.asarray(grouped, dtype=np.float32)
        if g.ndim != 3 or g.shape[1:] != (self._groups, self.width):
            raise ValueError(f"grouped must have shape (n, {self._groups}, {self.width}), "
                             f"got {g.shape}")
        return orientation_from_power(self._power(self._group_power(g)), self.angles_deg)

    def __call__(self, *rows: np.ndarray) -> Orientation:
        """Roll from one or more images' binned rows (their powers add).

        Returns
        -------
        Orientation
        """
        if not rows:
            raise ValueError("at least one image's rows are needed")
        grouped = np.stack([self._group_means(r) for r in rows])
        power = self._power(self._group_power(grouped))
        return orientation_from_power(power, self.angles_deg)


def orientation_from_power(power: np.ndarray, angles_deg: np.ndarray) -> Orientation:
    """Parabolic peak and confidence of an alignment power over a grid of angles.

    Parameters
    ----------
    power : ndarray, shape (n,)
        Alignment power per angle.
    angles_deg : ndarray, shape (n,)
        Evenly spaced angles, degrees.

    Returns
    -------
    Orientation
    """
    p = np.asarray(power, dtype=np.float64)
    a = np.asarray(angles_deg, dtype=np.float64)
    i = int(np.argmax(p))
    top = float(p[i])
    if not top > 0:
        return Orientation(float(a[a.size // 2]), 0.0)
    conf = float(np.clip(1.0 - float(p.min()) / top, 0.0, 1.0))
    if i == 0 or i == p.size - 1:
        return Orientation(float(a[i]), 0.0)
    y0, y1, y2 = p[i - 1], p[i], p[i + 1]
    curv = y0 - 2 * y1 + y2
    frac = float(np.clip(0.5 * (y0 - y2) / curv, -0.5, 0.5)) if curv < 0 else 0.0
    return Orientation(float(a[i] + frac * (a[1] - a[0])), conf)


class Shearer:
    """Resamples binned rows along the marks (tables cached per roll).

    Parameters
    ----------
    row_v_px : ndarray, shape (n_rows,)
        Undistorted image row at the centre of each binned row, pixels.
    width : int
        Columns of the binned rows.
    cy : float
        Image row of the optical axis, pixels.
    min_smear_px : float, optional
        Rolls whose shear moves no row by more than this are not resampled.
    cache : int, optional
        Number of remap tables kept (keyed by the roll rounded to 0.005 deg).
    """

    def __init__(self, row_v_px: np.ndarray, width: int, *, cy: float,
                 min_smear_px: float = 0.1, cache: int = 8) -> None:
        self._dv = (np.asarray(row_v_px, dtype=np.float32) - np.float32(cy))[:, None]
        self.width = check_int("width", width, lo=2)
        self.min_smear_px = float(min_smear_px)
        self._cache: OrderedDict[float, tuple[np.ndarray, np.ndarray, int]] = OrderedDict()
        self._size = int(cache)
        self._u = np.arange(self.width, dtype=np.float32)[None, :]

    def margin_px(self, roll_deg: float) -> int:
        """Columns at either end whose sheared samples fall outside the rows."""
        reach = float(np.max(np.abs(self._dv))) * abs(math.tan(math.radians(roll_deg)))
        return 0 if reach <= self.min_smear_px else int(math.ceil(reach)) + 2

    def _table(self, roll_deg: float) -> tuple[np.ndarray, np.ndarray, int]:
        key = round(roll_deg / 0.005) * 0.005
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        t = np.float32(math.tan(math.radians(key)))
        mx = np.ascontiguousarray(self._u - self._dv * t, dtype=np.float32)
        my = np.ascontiguousarray(
            np.broadcast_to(np.arange(self._dv.shape[0], dtype=np.float32)[:, None], mx.shape)
        )
        m1, m2 = cv2.convertMaps(mx, my, cv2.CV_16SC2)
        entry = (m1, m2, self.margin_px(key))
        self._cache[key] = entry
        if len(self._cache) > self._size:
            self._cache.popitem(last=False)
        return entry

    def __call__(self, rows: np.ndarray, roll_deg: float) -> tuple[np.ndarray, int]:
        """Rows resampled so that the marks run along the columns.

        Parameters
        ----------
        rows : ndarray, shape (n_rows, width)
            Binned rows.
        roll_deg : float
            Roll, degrees.

        Returns
        -------
        rows : ndarray, shape (n_rows, width)
            Sheared rows (``float32``; the input itself when the roll is negligible).
        margin : int
            Columns at either end that are not valid (edge samples repeated).
        """
        if self.margin_px(roll_deg) == 0:
            return rows, 0
        m1, m2, margin = self._table(roll_deg)
        src = np.asarray(rows)
        if src.dtype not in (np.uint8, np.uint16, np.float32):
            src = src.astype(np.float32)
        out = cv2.remap(src, m1, m2, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        return out, margin


class Rotator:
    """Rotates binned rows so that the feed runs along the rows (tables cached per roll).

    The albedo texture of wood is elongated along the fibres (the feed).  Sheared rows keep the
    fibres tilted by the roll while the board also moves ``D sin(roll)`` across them, which
    pulls a texture correlation along the fibres; in rotated rows the fibres lie along the
    rows and the motion is along them too.  Used for the texture registration only (the
    profiles come from the sheared rows, which keep every row for every column).

    Parameters
    ----------
    row_v_px : ndarray, shape (n_rows,)
        Undistorted image row at the centre of each binned row (evenly spaced), pixels.
    width : int
        Columns of the binned rows.
    cx, cy : float
        Optical axis, pixels.
    min_shift_px : float, optional
        Rolls that move no sample by more than this are not resampled.
    cache : int, optional
        Number of tables kept.
    """

    def __init__(self, row_v_px: np.ndarray, width: int, *, cx: float, cy: float,
                 min_shift_px: float = 0.1, cache: int = 8) -> None:
        v = np.asarray(row_v_px, dtype=np.float64)
        self._v = v
        self._step = float(v[1] - v[0]) if v.size > 1 else 1.0
        self.width = check_int("width", width, lo=2)
        self._cx, self._cy = float(cx), float(cy)
        self.min_shift_px = float(min_shift_px)
        self._cache: OrderedDict[float, tuple[np.ndarray, np.ndarray, slice]] = OrderedDict()
        self._size = int(cache)

    def _reach(self, roll_deg: float) -> float:
        s = abs(math.sin(math.radians(roll_deg)))
        rows = float(np.max(np.abs(self._v - self._cy)))
        return s * (max(self._cx, self.width - self._cx) + rows)

    def _table(self, roll_deg: float) -> tuple[np.ndarray, np.ndarray, slice]:
        key = round(roll_deg / 0.005) * 0.005
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        c, s = math.cos(math.radians(key)), math.sin(math.radians(key))
        du = np.arange(self.width, dtype=np.float64)[None, :] - self._cx
        dv = (self._v - self._cy)[:, None]
        mx = self._cx + du * c - dv * s
        my = ((self._cy + du * s + dv * c) - self._v[0]) / self._step
        n = self._v.size
        ok = np.all((my >= 0) & (my <= n - 1), axis=1)
        rows = np.flatnonzero(ok)
        valid = slice(int(rows[0]), int(rows[-1]) + 1) if rows.size else slice(0, 0)
        m1, m2 = cv2.convertMaps(mx.astype(np.float32), my.astype(np.float32), cv2.CV_16SC2)
        entry = (m1, m2, valid)
        self._cache[key] = entry
        if len(self._cache) > self._size:
            self._cache.popitem(last=False)
        return entry

    def __call__(self, rows: np.ndarray, roll_deg: float, *,
                 normalise: bool = False) -> np.ndarray:
        """Rows along the feed: ``(n_valid, width)`` (the input itself for a negligible roll).

        Only the rows whose samples all come from inside the band are returned (at least 2;
        with fewer, the input).  ``normalise``: each camera row is first divided by its mean,
        which removes patterns fixed to the camera's rows (grain stripes of the illumination)
        before they are tilted into the rotated rows.
        """
        if self._reach(roll_deg) <= self.min_shift_px:
            return rows
        m1, m2, valid = self._table(roll_deg)
        if valid.stop - valid.start < 2:
            return rows
        src = np.asarray(rows)
        if normalise:
            src = src.astype(np.float32)
            mean = src.mean(axis=1, keepdims=True)
            src = src / np.where(mean > 0, mean, np.float32(1.0))
        elif src.dtype not in (np.uint8, np.uint16, np.float32):
            src = src.astype(np.float32)
        out = cv2.remap(src, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out[valid]
