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

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft

from core.checks import check_positive
from vision import ffts, kernels

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
    if c.ndim != 1 or b.ndim != 1:
        raise ValueError("cusps_mm and bottoms_mm must be 1-D")
    out = kernels.arc_slopes(np.ascontiguousarray(x).ravel(), np.ascontiguousarray(c),
                             np.ascontiguousarray(b), float(r))
    return out.reshape(x.shape)


def kinematic_depths_um(cusps_mm: np.ndarray, bottoms_mm: np.ndarray, *,
                        radius_mm: float) -> np.ndarray:
    """Depth of each mark from its cusps and lowest point (arc of radius R), um.

    Returns
    -------
    ndarray, shape (m,)
        ``1000 ((c_k - b_k)^2 + (c_(k+1) - b_k)^2) / (4 R)``.

    Raises
    ------
    ValueError
        A radius not > 0; cusps and lowest points that are not 1-D with one more cusp.
    """
    r = check_positive("radius_mm", radius_mm)
    c = np.ascontiguousarray(cusps_mm, dtype=np.float64)
    b = np.ascontiguousarray(bottoms_mm, dtype=np.float64)
    if c.ndim != 1 or b.ndim != 1 or c.size != b.size + 1:
        raise ValueError(f"cusps_mm must be 1-D with one more value than bottoms_mm, got "
                         f"shapes {c.shape} and {b.shape}")
    # 1000 ((c[:-1] - b)^2 + (c[1:] - b)^2) / (4 r), numpy's operations, one compiled pass
    return kernels.arc_depths(c, b, float(r))


@functools.lru_cache(maxsize=64)
def _frequencies(n_fft: int, dx_mm: float) -> np.ndarray:
    """``scipy.fft.rfftfreq(n_fft, d=dx_mm)``, read-only (a measurer has few profile lengths)."""
    nu = scipy.fft.rfftfreq(n_fft, d=dx_mm)
    nu.flags.writeable = False
    return nu


def _exp_transfer(n_fft: int, dx_mm: float, scatter_mm: float) -> np.ndarray:
    """Transfer function of the unit two-sided exponential of length ``scatter_mm``."""
    nu = _frequencies(n_fft, dx_mm)
    return 1.0 / (1.0 + (2.0 * math.pi * scatter_mm * nu) ** 2)


def _transfers(n_fft: int, dx_mm: float, ells: tuple[float, ...]) -> np.ndarray:
    """Exponential transfer functions for several lengths (cached: set up once per size).

    Computed at ``dx_mm`` rounded to 1e-9 mm, the cache's key, so a pair's tables never depend
    on which pair came first (a roll's ``cos`` moves the spacing in its last digits). The
    table is shared: read it, never write it.
    """
    return _transfers_at(n_fft, round(dx_mm, 9), ells)


@functools.lru_cache(maxsize=32)
def _transfers_at(n_fft: int, dx_key: float, ells: tuple[float, ...]) -> np.ndarray:
    """:func:`_transfers` at the rounded spacing ``dx_key`` (read-only: shared)."""
    h = np.stack([_exp_transfer(n_fft, dx_key, e) for e in ells])
    h.flags.writeable = False
    return h


def _transfers_packed(n_fft: int, dx_mm: float, ells: tuple[float, ...]) -> np.ndarray:
    """:func:`_transfers` in OpenCV's packed real-spectrum layout (``n_fft`` even).

    The packed spectrum is ``[Re0, Re1, Im1, ..., Re(n/2)]``; a real transfer function scales
    both parts of each frequency alike.
    """
    return _packed_at(n_fft, round(dx_mm, 9), ells)


@functools.lru_cache(maxsize=32)
def _packed_at(n_fft: int, dx_key: float, ells: tuple[float, ...]) -> np.ndarray:
    """:func:`_transfers_packed` at the rounded spacing ``dx_key`` (read-only: shared)."""
    full = _transfers_at(n_fft, dx_key, ells)
    h = np.empty((len(ells), n_fft))
    h[:, 0] = full[:, 0]
    h[:, 1:-1:2] = full[:, 1:-1]
    h[:, 2:-1:2] = full[:, 1:-1]
    h[:, -1] = full[:, -1]
    h.flags.writeable = False
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
    p = np.ascontiguousarray(slope, dtype=np.float64)
    m = np.ascontiguousarray(model, dtype=np.float64)
    if p.shape != m.shape or p.ndim != 1:
        raise ValueError(f"slope and model must be 1-D of one length, got {p.shape}, {m.shape}")
    # the model's finite span, its NaNs as 0 and whether the slope varies there, one pass
    span = np.empty(m.size)
    lo, hi, inside, varies = kernels.model_span(m, p, span)
    if inside < 16 or marks < 2:
        return Calibration()
    n = hi - lo
    mm = span[:n]
    pm = p[lo:hi]
    widest, ells, plain = _grid(tuple(scatter_grid_mm))
    # Zero-padding for a linear (not circular) blur: 12 lengths of the widest kernel leave a
    # wrap-around of e^-12 (~6e-6) of it; never more than the profile's own length.
    pad = min(n, int(math.ceil(12.0 * widest / dx_mm)))
    nf = 2 * cv2.getOptimalDFTSize((n + pad + 1) // 2)  # even: OpenCV's packed spectra
    x = _unit_axis(n)
    if not varies:  # a constant slope: nothing to calibrate on
        return Calibration()
    n_l = len(ells)
    # One sample range for every length (the widest guard: the blurred model is wrong within
    # ~2 l of the profile's ends), so that all fits share their sums: normal equations, batched.
    guard = min(n // 4, int(math.ceil(2 * widest / dx_mm)))
    sel = slice(guard, n - guard)
    y = pm[sel]
    dev = y - y.sum() / y.size
    var = float(dev @ dev) / y.size
    if not var > 0:
        return Calibration()
    # Rows: the model, each blurred model, ones, x; all their products in one einsum.
    design = np.empty((n_l + 3, y.size))
    design[0] = mm[sel]
    if n_l:
        mean = mm.sum() / mm.size
        padded = np.zeros((1, nf))
        padded[0, :n] = mm
        padded -= mean
        padded[0, n:] = 0.0
        # OpenCV's real DFTs (packed spectra): every length's blur in one inverse of 9 rows
        spec = cv2.dft(padded)
        blurred = cv2.dft(spec * _transfers_packed(nf, dx_mm, ells),
                          flags=cv2.DFT_INVERSE | cv2.DFT_SCALE | cv2.DFT_ROWS)
        design[1 : n_l + 1] = blurred[:, sel]
        design[1 : n_l + 1] += mean
    design[n_l + 1] = 1.0
    design[n_l + 2] = x[sel]
    rss = np.full(n_l + 1, np.nan)  # fit 0: no scattering; fit 1 + i: length ells[i]
    coef_a = np.zeros(n_l + 1)
    coef_b = np.zeros(n_l + 1)
    gram_all = design @ design.T  # 12 x 12 from ~600 samples: below BLAS's threading size
    rhs_all = design @ y
    # every fit's small solve, and the best admissible one (a positive gain, not mostly a
    # negative unblurred part), in one compiled call
    i, resid = kernels.blur_fits(gram_all, rhs_all, float(y @ y), plain, rss,
                                 coef_a, coef_b, y.size, var)
    if i < 0:
        return Calibration()
    gain = float(coef_a[i] + coef_b[i])
    f = min(1.0, max(0.0, float(coef_b[i]) / gain))
    ell = 0.0 if i == 0 else float(ells[i - 1])
    explained = min(1.0, max(0.0, 1.0 - resid))
    conf = explained * min(1.0, marks / 4.0)
    scatter_conf = conf if ell > 0 and f > 0.05 else 0.0
    return Calibration(gain=gain, gain_confidence=conf, scatter_mm=ell if f > 0.05 else 0.0,
                       scatter_fraction=f if f > 0.05 else 0.0, scatter_confidence=scatter_conf,
                       trusted=conf >= min_confidence and 0.25 <= gain <= 4.0)


@functools.lru_cache(maxsize=16)
def _grid(scatter_grid_mm: tuple[float, ...]) -> tuple[float, tuple[float, ...], bool]:
    """A scattering grid's widest length, its positive lengths and whether it holds 0."""
    grid = tuple(scatter_grid_mm)
    return (float(max(grid)), tuple(e for e in grid if e > 0), 0.0 in grid)


@functools.lru_cache(maxsize=64)
def _unit_axis(n: int) -> np.ndarray:
    """``np.linspace(-1, 1, n)``, read-only (profiles of one measurer have few lengths)."""
    x = np.linspace(-1.0, 1.0, n)
    x.flags.writeable = False
    return x


def deblurs(calibration: Calibration, *, pitch_mm: float, min_gain_loss: float = 0.03) -> bool:
    """Whether :func:`apply_calibration` undoes a scattering blur (else it divides the gain).

    The blur is undone only when it costs the marks' fundamental more than ``min_gain_loss``
    of its contrast.
    """
    f, ell = calibration.scatter_fraction, calibration.scatter_mm
    if f <= 0 or ell <= 0:
        return False
    loss = f * (1.0 - 1.0 / (1.0 + (2.0 * math.pi * ell / pitch_mm) ** 2))
    return loss >= min_gain_loss


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
    if not deblur or not deblurs(calibration, pitch_mm=pitch_mm, min_gain_loss=min_gain_loss):
        return p
    n = p.size
    nf = 2 * n
    ext = np.empty(nf)  # even extension: no wrap-around jump
    ext[:n] = p
    ext[n:] = p[::-1]
    # scatter_transfer's h and the Wiener denominator h h + c in one compiled pass (the same
    # operations: 2 pi l is the same Python product as in _exp_transfer)
    nu = _frequencies(nf, dx_mm)
    h = np.empty(nu.size)
    den = np.empty(nu.size)
    kernels.wiener_terms(nu, 2.0 * math.pi * ell, f, regularisation, h, den)
    out = ffts.irfft(ffts.rfft(ext, nf) * h / den, nf)
    return out[:n]


class SelfCalibrator:
    """What the measurement learns over the pairs of one board (keep one per board).

    The photometric calibration is smoothed over the pairs; the camera's roll, a property of
    the rig that the board's pairs all share, is searched for once and then again only every
    ``roll_every`` pairs (the pairs between use the last confident estimate: the orientation
    estimated once per board and re-checked, not on every pair).

    Parameters
    ----------
    weight : float, optional
        Weight of a new estimate of full confidence in the running mean (0-1).
    min_confidence : float, optional
        The smoothed calibration is trusted once its accumulated confidence reaches this.
    roll_every : int, optional
        The roll is searched for on every this many pairs (1: on every pair).
    """

    def __init__(self, *, weight: float = 0.3, min_confidence: float = 0.5,
                 roll_every: int = 8) -> None:
        if not 0.0 < weight <= 1.0:
            raise ValueError(f"weight must be in (0, 1], got {weight!r}")
        if int(roll_every) != roll_every or roll_every < 1:
            raise ValueError(f"roll_every must be an integer >= 1, got {roll_every!r}")
        self.weight = float(weight)
        self.min_confidence = float(min_confidence)
        self.roll_every = int(roll_every)
        self.reset()

    def reset(self) -> None:
        """Forget the board (a new one comes)."""
        self._log_gain = 0.0
        self._scatter = np.zeros(2)  # scatter_mm, fraction
        self._w = 0.0  # exponentially weighted sum of confidences
        self._n = 0.0  # ... of ones
        self.pairs = 0
        self._roll: tuple[float, float] | None = None  # roll_deg, confidence
        self._roll_age = 0  # pairs measured with it since it was searched for

    def known_roll(self) -> tuple[float, float] | None:
        """``(roll_deg, confidence)`` for this pair, or ``None`` when the roll is due a search.

        Every call that returns a roll counts one pair measured with it.
        """
        if self._roll is None or self._roll_age + 1 >= self.roll_every:
            return None
        self._roll_age += 1
        return self._roll

    def note_roll(self, roll_deg: float, confidence: float, *, min_confidence: float) -> None:
        """A searched roll: kept for the next pairs when at least ``min_confidence``."""
        self._roll_age = 0
        if math.isfinite(confidence) and confidence >= min_confidence:
            self._roll = (float(roll_deg), float(confidence))

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
            self._log_gain = (w_old * self._log_gain + c * math.log(estimate.gain)) / self._w
            # the two running means on Python floats (numpy's element-wise operations, in its
            # order), kept as the array the workers' wire carries
            s0, s1 = self._scatter.tolist()
            w = self._w
            self._scatter = np.array([(w_old * s0 + c * float(estimate.scatter_mm)) / w,
                                      (w_old * s1 + c * float(estimate.scatter_fraction)) / w])
        conf = self._w / self._n if self._n > 0 else 0.0
        scatter_mm, fraction = self._scatter.tolist()
        return Calibration(
            gain=math.exp(self._log_gain), gain_confidence=conf,
            scatter_mm=scatter_mm, scatter_fraction=fraction,
            scatter_confidence=conf if fraction > 0 else 0.0,
            trusted=conf >= self.min_confidence,
        )
