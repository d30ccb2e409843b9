"""Self-calibration of the photometric measurement from the knife kinematics.

Each mark is an arc of the cutting radius R (known from the machine), so between its two cusps the
true slope is ``p(x) = (x - b_k) / R`` (``b_k``: the mark's lowest point): a sawtooth whose shape
is fixed by the cusp and bottom positions alone -- which the photometry finds right even when its
scale is wrong.  The measured slope is, to first order,

    p_m = g [(1 - f) p + f K_l * p] + c + d x,

with ``g`` the photometric gain (a light's slant off the rig file's, the reflectance's departure
from Lambert, the contrast lost to light scattered under the surface), ``K_l`` a two-sided
exponential of length ``l`` (subsurface scattering along the fibres, fraction ``f``) and a
residual illumination trend.  :func:`fit_calibration` fits ``g``, ``f`` (least squares, linear)
for every ``l`` on a grid and keeps the best; its confidence is the fraction of the slope's
variance the model explains, scaled down for few marks.  :func:`apply_calibration` divides the
gain out and, where the scattering costs more than a few per cent of the marks' contrast, undoes
the blur (Wiener).  :class:`SelfCalibrator` smooths the estimates over the pairs of one board.

Kinematic depth (:func:`kinematic_depths_um`): from the positions alone, a mark's depth is
``((c_left - b)^2 + (c_right - b)^2) / (4 R)`` -- beside the photometric depth, so a real
difference (fibre spring-back, tear-out, chatter) shows instead of being calibrated away.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft

from core.checks import check_positive

SCATTER_GRID_MM = (0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8)


@dataclass(frozen=True)
class Calibration:
    """Photometric calibration of one pair (or smoothed over pairs).

    Attributes
    ----------
    gain : float
        Measured slope over true slope (1: the rig file is right).
    gain_confidence : float
        In [0, 1]; 0 when not estimated.
    scatter_mm : float
        Length of the subsurface scattering along the fibres, mm (0: none found).
    scatter_fraction : float
        Fraction of the light that is scattered.
    scatter_confidence : float
        In [0, 1].
    trusted : bool
        The calibration is confident enough to be applied.
    deblurred : bool
        The scattering blur was undone (set by the pipeline once applied).
    """

    gain: float = 1.0
    gain_confidence: float = 0.0
    scatter_mm: float = 0.0
    scatter_fraction: float = 0.0
    scatter_confidence: float = 0.0
    trusted: bool = False
    deblurred: bool = False


def kinematic_slope(x_mm: np.ndarray, cusps_mm: np.ndarray, bottoms_mm: np.ndarray, *,
                    radius_mm: float) -> np.ndarray:
    """True slope of a chain of arcs of radius R between the given cusps.

    Parameters
    ----------
    x_mm : ndarray, shape (n,)
        Positions, mm.
    cusps_mm : ndarray, shape (m + 1,)
        Cusps bounding ``m`` marks, mm (increasing).
    bottoms_mm : ndarray, shape (m,)
        Lowest point of each mark, mm.
    radius_mm : float
        Cutting radius, mm.

    Returns
    -------
    ndarray, shape (n,)
        ``(x - b_k) / R`` inside mark ``k``; NaN outside the marks.
    """
    r = check_positive("radius_mm", radius_mm)
    x = np.asarray(x_mm, dtype=np.float64)
    c = np.asarray(cusps_mm, dtype=np.float64)
    b = np.asarray(bottoms_mm, dtype=np.float64)
    k = np.searchsorted(c, x, side="right") - 1
    inside = (k >= 0) & (k < b.size)
    out = np.full(x.shape, np.nan)
    out[inside] = (x[inside] - b[k[inside]]) / r
    return out


def kinematic_depths_um(cusps_mm: np.ndarray, bottoms_mm: np.ndarray, *,
                        radius_mm: float) -> np.ndarray:
    """Depth of each mark from its cusps and lowest point (arc of radius R), um.

    Returns
    -------
    ndarray, shape (m,)
        ``1000 ((c_k - b_k)^2 + (c_(k+1) - b_k)^2) / (4 R)``.
    """
    r = check_positive("radius_mm", radius_mm)
    c = np.asarray(cusps_mm, dtype=np.float64)
    b = np.asarray(bottoms_mm, dtype=np.float64)
    return 1000.0 * ((c[:-1] - b) ** 2 + (c[1:] - b) ** 2) / (4.0 * r)


def _exp_transfer(n_fft: int, dx_mm: float, scatter_mm: float) -> np.ndarray:
    """Transfer function of the unit two-sided exponential of length ``scatter_mm``."""
    nu = scipy.fft.rfftfreq(n_fft, d=dx_mm)
    return 1.0 / (1.0 + (2.0 * math.pi * scatter_mm * nu) ** 2)


_TRANSFERS: dict[tuple[int, float, tuple[float, ...]], np.ndarray] = {}


def _transfers(n_fft: int, dx_mm: float, ells: tuple[float, ...]) -> np.ndarray:
    """Exponential transfer functions for several lengths (cached: set up once per size)."""
    key = (n_fft, round(dx_mm, 9), ells)
    h = _TRANSFERS.get(key)
    if h is None:
        if len(_TRANSFERS) > 32:
            _TRANSFERS.clear()
        h = _TRANSFERS[key] = np.stack([_exp_transfer(n_fft, dx_mm, e) for e in ells])
    return h


def fit_calibration(
    slope: np.ndarray,
    model: np.ndarray,
    *,
    dx_mm: float,
    marks: int,
    scatter_grid_mm: tuple[float, ...] = SCATTER_GRID_MM,
    min_confidence: float = 0.5,
) -> Calibration:
    """Gain and scattering that best map the kinematic slope onto the measured one.

    Parameters
    ----------
    slope : ndarray, shape (n,)
        Measured slope (uncalibrated).
    model : ndarray, shape (n,)
        Kinematic slope (:func:`kinematic_slope`); NaN outside the marks.
    dx_mm : float
        Sample spacing, mm.
    marks : int
        Number of complete marks (confidence falls below 4).
    scatter_grid_mm : tuple of float, optional
        Scattering lengths tried, mm.
    min_confidence : float, optional
        Below this gain confidence the calibration is not trusted; nor is a gain outside
        0.25-4 (no rig is that far off: the marks are not what the kinematics say).

    Returns
    -------
    Calibration
    """
    p = np.asarray(slope, dtype=np.float64)
    m = np.asarray(model, dtype=np.float64)
    inside = np.isfinite(m)
    if np.count_nonzero(inside) < 16 or marks < 2:
        return Calibration()
    idx = np.flatnonzero(inside)
    lo, hi = int(idx[0]), int(idx[-1]) + 1
    mm = np.where(inside, m, 0.0)[lo:hi]
    pm = p[lo:hi]
    n = hi - lo
    nf = scipy.fft.next_fast_len(2 * n)
    x = np.linspace(-1.0, 1.0, n)
    if not float(np.var(pm)) > 0:
        return Calibration()
    ells = np.asarray([e for e in scatter_grid_mm if e > 0], dtype=np.float64)
    mean = mm.mean()
    blurred_all = np.empty((0, n))
    if ells.size:
        h = _transfers(nf, dx_mm, tuple(ells))
        spec = scipy.fft.rfft(mm - mean, n=nf)
        blurred_all = scipy.fft.irfft(spec[None, :] * h, n=nf, axis=1)[:, :n] + mean
    # One sample range for every length (the widest guard: the blurred model is wrong within
    # ~2 l of the profile's ends), so that all fits share their sums: normal equations, batched.
    guard = min(n // 4, int(math.ceil(2 * float(max(scatter_grid_mm)) / dx_mm)))
    sel = slice(guard, n - guard)
    y = pm[sel]
    var = float(np.var(y))
    if not var > 0:
        return Calibration()
    common = np.stack([mm[sel], np.ones(y.size), x[sel]])  # (3, m)
    blurred = blurred_all[:, sel]  # (L, m)
    cc = np.einsum("im,jm->ij", common, common)
    cy = np.einsum("im,m->i", common, y)
    yy = float(np.einsum("m,m->", y, y))
    best: tuple[float, float, float, float] | None = None  # residual, gain, f, l
    fits: list[tuple[float, float, float, float]] = []
    if 0.0 in scatter_grid_mm:
        try:
            coef = np.linalg.solve(cc, cy)
            rss = yy - float(coef @ cy)
            fits.append((rss, float(coef[0]), 0.0, 0.0))
        except np.linalg.LinAlgError:
            pass
    if ells.size:
        bc = np.einsum("lm,jm->lj", blurred, common)  # (L, 3)
        bb = np.einsum("lm,lm->l", blurred, blurred)
        by = np.einsum("lm,m->l", blurred, y)
        gram = np.zeros((ells.size, 4, 4))
        gram[:, 0, 0] = cc[0, 0]
        gram[:, 0, 1] = gram[:, 1, 0] = bc[:, 0]
        gram[:, 1, 1] = bb
        gram[:, 0, 2:] = cc[0, 1:]
        gram[:, 2:, 0] = cc[1:, 0]
        gram[:, 1, 2:] = bc[:, 1:]
        gram[:, 2:, 1] = bc[:, 1:]
        gram[:, 2:, 2:] = cc[1:, 1:]
        rhs = np.concatenate([np.broadcast_to(cy[:1], (ells.size, 1)), by[:, None],
                              np.broadcast_to(cy[1:], (ells.size, 2))], axis=1)
        try:
            coefs = np.linalg.solve(gram, rhs[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            coefs = np.full((ells.size, 4), np.nan)
        rss = yy - np.einsum("lk,lk->l", coefs, rhs)
        for i, ell in enumerate(ells):
            fits.append((float(rss[i]), float(coefs[i, 0]), float(coefs[i, 1]), float(ell)))
    m_count = y.size
    for rss_i, a_, b_, ell in fits:
        if not np.isfinite(rss_i):
            continue
        g = a_ + b_
        if not g > 0 or a_ < -0.05 * g:
            continue
        resid = max(rss_i, 0.0) / m_count / var
        f = float(np.clip(b_ / g, 0.0, 1.0))
        if best is None or resid < best[0]:
            best = (resid, g, f, ell)
    if best is None:
        return Calibration()
    resid, g, f, ell = best
    explained = float(np.clip(1.0 - resid, 0.0, 1.0))
    conf = explained * min(1.0, marks / 4.0)
    scatter_conf = conf if ell > 0 and f > 0.05 else 0.0
    return Calibration(gain=g, gain_confidence=conf, scatter_mm=ell if f > 0.05 else 0.0,
                       scatter_fraction=f if f > 0.05 else 0.0, scatter_confidence=scatter_conf,
                       trusted=conf >= min_confidence and 0.25 <= g <= 4.0)


def scatter_transfer(n_fft: int, *, dx_mm: float, scatter_mm: float,
                     fraction: float) -> np.ndarray:
    """``(1 - f) + f K_l`` in the frequency domain (rfft of length ``n_fft``)."""
    return (1.0 - fraction) + fraction * _exp_transfer(n_fft, dx_mm, scatter_mm)


def apply_calibration(slope: np.ndarray, calibration: Calibration, *, dx_mm: float,
                      pitch_mm: float, min_gain_loss: float = 0.03,
                      regularisation: float = 0.03, deblur: bool = True) -> np.ndarray:
    """Slope with the gain divided out and, where it pays, the scattering blur undone.

    Parameters
    ----------
    slope : ndarray, shape (n,)
        Measured slope.
    calibration : Calibration
        As from :func:`fit_calibration` (or smoothed).
    dx_mm : float
        Sample spacing, mm.
    pitch_mm : float
        Mark pitch, mm: the blur is undone only when it costs the marks' fundamental more than
        ``min_gain_loss`` of its contrast.
    min_gain_loss, regularisation : float, optional
        Threshold above, and the Wiener constant of the deconvolution (``H / (H^2 + c)``
        amplifies no frequency more than ``1 / (2 sqrt(c))``: 2.9x for 0.03).
    deblur : bool, optional
        ``False``: divide the gain out only.

    Returns
    -------
    ndarray, shape (n,)
        Calibrated slope.
    """
    p = np.asarray(slope, dtype=np.float64) / calibration.gain
    f, ell = calibration.scatter_fraction, calibration.scatter_mm
    if f <= 0 or ell <= 0 or not deblur:
        return p
    loss = f * (1.0 - 1.0 / (1.0 + (2.0 * math.pi * ell / pitch_mm) ** 2))
    if loss < min_gain_loss:
        return p
    n = p.size
    ext = np.concatenate([p, p[::-1]])  # even extension: no wrap-around jump
    nf = ext.size
    h = scatter_transfer(nf, dx_mm=dx_mm, scatter_mm=ell, fraction=f)
    out = scipy.fft.irfft(scipy.fft.rfft(ext) * h / (h * h + regularisation), n=nf)
    return out[:n]


class SelfCalibrator:
    """Smooths the calibration over the pairs of one board (keep one per board).

    Parameters
    ----------
    weight : float, optional
        Weight of a new estimate of full confidence in the running mean (0-1).
    min_confidence : float, optional
        The smoothed calibration is trusted once its accumulated confidence reaches this.
    """

    def __init__(self, *, weight: float = 0.3, min_confidence: float = 0.5) -> None:
        if not 0.0 < weight <= 1.0:
            raise ValueError(f"weight must be in (0, 1], got {weight!r}")
        self.weight = float(weight)
        self.min_confidence = float(min_confidence)
        self.reset()

    def reset(self) -> None:
        """Forget the board (a new one comes)."""
        self._log_gain = 0.0
        self._scatter = np.zeros(2)  # scatter_mm, fraction
        self._w = 0.0  # exponentially weighted sum of confidences
        self._n = 0.0  # ... of ones
        self.pairs = 0

    def update(self, estimate: Calibration) -> Calibration:
        """Fold in one pair's estimate; return the smoothed calibration.

        Parameters
        ----------
        estimate : Calibration
            One pair's :func:`fit_calibration`.

        Returns
        -------
        Calibration
            Confidence-weighted, exponentially forgetting means (of the log gain and of the
            scattering); its confidence is the equally weighted mean of the pairs' confidences,
            so it stays low while only poor estimates came.
        """
        self.pairs += 1
        decay = 1.0 - self.weight
        c = float(estimate.gain_confidence)
        w_old = decay * self._w
        self._w = w_old + c
        self._n = decay * self._n + 1.0
        if c > 0 and estimate.gain > 0:
            vec = np.array([estimate.scatter_mm, estimate.scatter_fraction])
            self._log_gain = (w_old * self._log_gain + c * math.log(estimate.gain)) / self._w
            self._scatter = (w_old * self._scatter + c * vec) / self._w
        conf = self._w / self._n if self._n > 0 else 0.0
        return Calibration(
            gain=math.exp(self._log_gain), gain_confidence=conf,
            scatter_mm=float(self._scatter[0]), scatter_fraction=float(self._scatter[1]),
            scatter_confidence=conf if self._scatter[1] > 0 else 0.0,
            trusted=conf >= self.min_confidence,
        )
