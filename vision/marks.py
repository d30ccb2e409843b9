"""Cuttermark metrics from a height profile: cusps, widths, depths, pitch, uniformity.

A rotary-planed surface is a chain of circular arcs of the tip radius R, one per knife pass,
meeting in sharp cusps.  Along the feed the slope is therefore a sawtooth: it rises as ``1/R``
inside every mark and falls abruptly at every cusp, by the distance between the two marks' lowest
points over R (the feed per knife over R, whatever the knives' runout does to the widths).
:func:`find_marks` finds the cusps as those falls, fits every mark's arc (one common curvature,
one lowest point per mark, samples near the cusps left out because blur and pixel averaging round
them) and places each cusp where its two arcs meet, to a small fraction of a pixel.

Definitions (the issue's): a *complete* mark lies between two detected cusps; its width is cusp
to cusp, its depth the mean of its two cusp heights minus its lowest point; pitch = mean width;
uniformity = coefficient of variation of the widths (population standard deviation / mean).
Also here: :func:`knife_means` (per-knife averages given the mark-to-knife phase), :func:`corr2`
(seed Eq. 8) and the period estimates used to detrend the illumination.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.signal

from core.checks import check_int
from core.errors import MeasurementError
from vision import ffts, kernels, marks_kernels


@dataclass(frozen=True)
class Marks:
    """The complete cuttermarks of a profile.

    Attributes
    ----------
    cusps_mm : ndarray, shape (n + 1,)
        Cusp positions bounding the ``n`` complete marks, mm.
    bottoms_mm : ndarray, shape (n,)
        Position of each mark's lowest point, mm.
    widths_mm : ndarray, shape (n,)
        Cusp-to-cusp widths, mm.
    depths_um : ndarray, shape (n,)
        Mean of the two cusp heights minus the lowest point, um.
    cusp_heights_um : ndarray, shape (n + 1,)
        Height at each cusp, um.
    pitch_mm : float
        Mean width, mm.
    uniformity_cv : float
        Population standard deviation of the widths over their mean.
    depth_um : float
        Mean depth, um.
    """

    cusps_mm: np.ndarray
    bottoms_mm: np.ndarray
    widths_mm: np.ndarray
    depths_um: np.ndarray
    cusp_heights_um: np.ndarray
    pitch_mm: float
    uniformity_cv: float
    depth_um: float


def corr2(a: np.ndarray, b: np.ndarray) -> float:
    """Correlation coefficient of two equally shaped arrays (seed Eq. 8, MATLAB's corr2).

    Parameters
    ----------
    a, b : array_like, same shape
        Profiles (or images).

    Returns
    -------
    float
        ``sum((a - mean a)(b - mean b)) / sqrt(sum((a - mean a)^2) sum((b - mean b)^2))``;
        NaN when either is constant.
    """
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"a and b differ in shape: {x.shape} vs {y.shape}")
    if x.size < 2:
        raise ValueError("corr2 needs at least 2 samples")
    x = x - x.mean()
    y = y - y.mean()
    den = math.sqrt(float(np.sum(x * x)) * float(np.sum(y * y)))
    return float(np.sum(x * y) / den) if den > 0 else math.nan


def knife_means(values: np.ndarray, *, knives: int, phase: int) -> np.ndarray:
    """Mean of a per-mark quantity for each knife.

    Mark ``i`` (in order along +x) was cut by knife ``(phase + i) mod knives``.

    Parameters
    ----------
    values : array_like, shape (n,)
        One value per complete mark (widths, depths, ...).
    knives : int
        Number of knives Z.
    phase : int
        Knife of the first mark.

    Returns
    -------
    ndarray, shape (knives,)
        Mean per knife; NaN for a knife without a mark.
    """
    z = check_int("knives", knives, lo=1)
    ph = check_int("phase", phase)
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 1:
        raise ValueError(f"values must be 1-D, got shape {v.shape}")
    # bincount's sums (in order of the marks) in one compiled pass, the quotients on Python
    # floats: the same numbers without four numpy calls on a handful of marks
    sums = np.zeros(z)
    counts = np.zeros(z, dtype=np.int64)
    kernels.knife_sums(np.ascontiguousarray(v), z, ph, sums, counts)
    return np.array([s / c if c > 0 else math.nan
                     for s, c in zip(sums.tolist(), counts.tolist(), strict=True)])


_HANNING: dict[int, np.ndarray] = {}


def _hanning(n: int) -> np.ndarray:
    """``np.hanning(n)``, cached (a measurer's profiles have few lengths)."""
    w = _HANNING.get(n)
    if w is None:
        if len(_HANNING) > 64:
            _HANNING.clear()
        w = _HANNING[n] = np.hanning(n)
    return w


def dominant_period_px(signal: np.ndarray, *, min_period_px: float = 4.0) -> float:
    """Strongest period of a profile (periodogram peak, refined by a parabola).

    Parameters
    ----------
    signal : ndarray, shape (n,)
        Slope or height profile.
    min_period_px : float, optional
        Shortest period considered, samples.

    Returns
    -------
    float
        Period, samples; NaN when the profile holds fewer than two periods of anything.
    """
    s = np.asarray(signal, dtype=np.float64)
    n = s.size
    if n < 8:
        return math.nan
    s = (s - s.sum() / n) * _hanning(n)
    nfft = scipy.fft.next_fast_len(4 * n, real=True)
    spec = ffts.rfft(s, nfft)
    k_lo = max(1, int(math.ceil(2.0 * nfft / n)))  # at least two periods in the profile
    k_hi = min(spec.size - 2, int(nfft / min_period_px))
    if k_hi <= k_lo:
        return math.nan
    return nfft / kernels.spectrum_peak(spec, k_lo, k_hi)


def repeat_period_px(
    signal: np.ndarray, *, max_multiple: int = 8, tolerance: float = 0.02
) -> float:
    """Period after which a mark pattern repeats exactly: a whole revolution of the cutterhead.

    With knife runout the marks differ from knife to knife, so the profile repeats only after
    ``Z`` marks.  The dominant (per-knife) period ``T`` is found first; then the smallest
    multiple ``k T`` whose self-correlation ``corr(s[u], s[u + k T])`` is within ``tolerance``
    of the best multiple's is taken and refined by a parabola over integer lags.

    Parameters
    ----------
    signal : ndarray, shape (n,)
        Slope-like profile (illumination trend already mostly removed).
    max_multiple : int, optional
        Largest multiple of ``T`` tried (also limited to a third of the profile).
    tolerance : float, optional
        How close to the best self-correlation the chosen multiple must be.

    Returns
    -------
    float
        Period, samples; NaN when no period is found.
    """
    s = np.asarray(signal, dtype=np.float64)
    s = s - s.sum() / s.size
    n = s.size
    t = dominant_period_px(s)
    if not math.isfinite(t):
        return math.nan

    # Lightly smoothed, so that the sharp cusp steps do not make the score depend on where
    # the (fractional) period falls between samples.
    s = kernels.smooth5(s)
    ks = [k for k in range(1, max_multiple + 1) if k * t <= n / 3.0]
    if not ks:
        return t
    # Every lag's dot product from one FFT; the energies, the three lags around each multiple
    # and their parabolas in one compiled loop.
    nfft = scipy.fft.next_fast_len(2 * n, real=True)
    spec = ffts.rfft(s, nfft)
    dots = ffts.irfft(kernels.power_spectrum(spec), nfft)[:n]  # spec.real**2 + spec.imag**2
    return float(kernels.repeat_lag(s, np.ascontiguousarray(dots), t,
                                     np.asarray(ks, dtype=np.float64), tolerance))


def cusp_steps(slope: np.ndarray, *, baseline: int = 2) -> np.ndarray:
    """Slope step between the ``baseline`` samples after and before each sample gap.

    ``steps[i]`` is ``mean(slope[i+1 : i+1+baseline]) - mean(slope[i+1-baseline : i+1])``, the
    change of slope across the gap between samples ``i`` and ``i + 1`` (0 where undefined).
    A cusp is a large negative step: the slope falls from the end of one arc, ``+(x_c - b_l)/R``,
    to the start of the next, ``-(b_r - x_c)/R``; the step is the distance between the two
    marks' lowest points ``b`` over R, which is the feed per knife over R at every cusp, however
    uneven the widths are.
    """
    p = np.asarray(slope, dtype=np.float64)
    return _steps_from_cumsum(_cumsum0(p), int(baseline))


def _cumsum0(values: np.ndarray) -> np.ndarray:
    """``[0, cumsum(values)]``."""
    c = np.empty(values.size + 1)
    c[0] = 0.0
    np.cumsum(values, out=c[1:])
    return c


def _steps_from_cumsum(c: np.ndarray, k: int) -> np.ndarray:
    """:func:`cusp_steps` from the slope's :func:`_cumsum0`."""
    n = c.size - 1
    out = np.zeros(n)
    if n < 2 * k + 1:
        return out
    mid = c[k : n - k + 1]  # c[i + 1] for i = k - 1 .. n - k - 1
    out[k - 1 : n - k] = ((c[2 * k :] - mid) - (mid - c[: n - 2 * k + 1])) / k
    return out


def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D float array, by one partition (numpy's own costs ~5x more)."""
    n = values.size
    if n == 0:
        return math.nan
    lo, hi = (n - 1) // 2, n // 2
    part = np.partition(values, (lo, hi))
    return float((part[lo] + part[hi]) / 2.0)


def _quantile(values: np.ndarray, q: float) -> float:
    """``np.quantile(values, q)`` (numpy's default linear method) by one partition."""
    n = values.size
    pos = (n - 1) * q
    lo = int(math.floor(pos))
    hi = min(lo + 1, n - 1)
    part = np.partition(values, (lo, hi))
    a, b = float(part[lo]), float(part[hi])
    t = pos - lo
    return b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t


def _peaks(values: np.ndarray, *, distance: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.signal.find_peaks(values, height=0.0, distance=distance)``: indices, heights.

    Strict local maxima, vectorised; scipy itself decides the rare cases it defines by a
    sequential rule (a plateau inside the signal, two candidates closer than ``distance``).
    """
    x = values
    mid = x[1:-1]
    rise = x[:-2] < mid
    tie = rise & (mid == x[2:])
    if np.any(tie[:-1]):  # a plateau that does not run to the end: scipy's midpoint rule
        cand, props = scipy.signal.find_peaks(x, height=0.0, distance=distance)
        return cand, props["peak_heights"]
    cand = np.flatnonzero(rise & (mid > x[2:])) + 1
    heights = x[cand]
    keep = heights >= 0.0
    cand, heights = cand[keep], heights[keep]
    if cand.size > 1 and np.any(np.diff(cand) < distance):  # scipy's priority rule
        cand, props = scipy.signal.find_peaks(x, height=0.0, distance=distance)
        return cand, props["peak_heights"]
    return cand, heights


def periodic_noise(slope: np.ndarray) -> float:
    """Robust standard deviation of one slope sample from differences one repeat period apart.

    The marks repeat after one cutterhead revolution (:func:`repeat_period_px`), so
    ``p(u + T) - p(u)`` (``p(u + T)`` interpolated linearly) holds the noise of two samples and
    not the marks; the few samples next to a cusp that the interpolation smears are outvoted
    by the median.  On a board without marks it is the sample noise, as the sample-to-sample
    differences give it for white noise (and more than they do for smooth noise).

    Parameters
    ----------
    slope : ndarray, shape (n,)
        Slope profile.

    Returns
    -------
    float
        Noise of one sample; ``inf`` when no repeat period of at least 4 samples is found.
    """
    p = np.asarray(slope, dtype=np.float64)
    period = repeat_period_px(p)
    if not (math.isfinite(period) and 4.0 <= period <= p.size / 2):
        return math.inf
    shift = int(math.floor(period))
    t = period - shift
    ahead = (1.0 - t) * p[shift:-1] + t * p[shift + 1:]
    d = ahead - p[: ahead.size]
    return 1.4826 * _median(np.abs(d - _median(d))) / math.sqrt(2.0)


def find_marks(
    x_mm: np.ndarray,
    height_um: np.ndarray,
    *,
    slope: np.ndarray | None = None,
    min_marks: int = 2,
    min_step: float = 0.35,
    min_snr: float = 5.0,
    guard: int = 2,
    refine: bool = True,
) -> Marks:
    """Find the cusps and complete marks of a height profile.

    1. Cusps, to a sample: the large negative steps of the slope (:func:`cusp_steps`), every
       step larger than ``min_step`` times the typical one (90th percentile of the candidates),
       at least 3 samples apart, provided the typical step stands ``min_snr`` times above the
       slope's noise; without those the noise put inside a mark (:func:`without_false_cusps`),
       with the smaller steps that bound a narrow mark (:func:`with_narrow_marks`).
    2. Arcs: between cusps the surface is an arc of the common tip radius R, so the slope is a
       line of one common gradient ``kappa = 1/R``: ``p = kappa (x - b_k)`` with ``b_k`` the
       mark's lowest point.  ``kappa`` is the pooled within-mark regression of slope on x, ``b_k``
       each mark's own offset, and the arc's height ``e_k`` at ``b_k`` comes from the height
       samples; samples within ``guard`` of a cusp (rounded by blur and pixel averaging) are left
       out, so marks as narrow as ``2 guard + 2`` samples are still measured.
    3. Each cusp, to a small fraction of a sample: where its two neighbouring arcs meet.  Cusps
       at either end whose outer arc cannot be measured are dropped (their marks are not
       complete); inner ones keep the sample position.

    Parameters
    ----------
    x_mm : ndarray, shape (n,)
        Evenly spaced positions along the feed, mm (increasing).
    height_um : ndarray, shape (n,)
        Height, um.
    slope : ndarray, shape (n,), optional
        Slope ``dz/dx`` of the same profile (default: the gradient of the height).
    min_marks : int, optional
        Fewer complete marks raise :class:`MeasurementError`.
    min_step : float, optional
        Smallest cusp step as a fraction of the typical one.
    min_snr : float, optional
        Smallest typical cusp step in units of the slope's noise (robust standard deviation
        of a sample): below it the profile holds no marks (noise on a flat board is not taken
        for marks).  The noise comes from the sample-to-sample differences; when the steps
        fall short of it, also from the differences one repeat period apart
        (:func:`periodic_noise`), and the smaller is used: marks of a few samples whose cusps
        are rounded (0.5 mm at 12.5 px/mm, subsurface scattering) fill most of the
        sample-to-sample differences themselves, one period apart they cancel.
    guard : int, optional
        Samples left out on either side of a cusp when fitting the arcs.
    refine : bool, optional
        Refine with the arcs (``False``: sample positions, sample heights).

    Returns
    -------
    Marks

    Raises
    ------
    MeasurementError
        Fewer than ``min_marks`` complete marks.
    """
    x = np.asarray(x_mm, dtype=np.float64)
    h = np.asarray(height_um, dtype=np.float64)
    if x.shape != h.shape or x.ndim != 1:
        raise ValueError(f"x_mm and height_um must be 1-D of one length, got {x.shape}, {h.shape}")
    n = h.size
    if n < 8:
        raise MeasurementError(f"profile too short for cuttermarks: {n} samples")
    dx = (x[-1] - x[0]) / (n - 1)
    if not dx > 0:
        raise ValueError("x_mm must increase")
    p = np.gradient(h, dx * 1000.0) if slope is None else np.asarray(slope, dtype=np.float64)
    if p.shape != h.shape:
        raise ValueError(f"slope must have the profile's length {n}, got {p.shape}")
    # Candidates, the slope's noise floor (robust, from its sample-to-sample differences: the
    # cusps are few, and inside a mark the slope changes by only dx / R per sample) and the
    # typical step in one compiled call; scipy's rules where peaks tie or crowd.
    cum_p, cand, size, noise, typical, simple = kernels.cusp_candidates(
        np.ascontiguousarray(p))
    if not simple:
        cand, size = _peaks(-_steps_from_cumsum(cum_p, 2))
        if cand.size:
            d = p[1:] - p[:-1]
            noise = 1.4826 * _median(np.abs(d - _median(d))) / math.sqrt(2.0)
            typical = _quantile(size, 0.9)
    if cand.size:
        if typical < min_snr * noise:  # fine marks: their own cusps may be the differences
            noise = min(noise, periodic_noise(p))
        if typical < min_snr * noise:  # the steps are noise: no cuttermarks to be seen
            cand, size = cand[:0], size[:0]
    gaps = _cusp_gaps(p, cum_p, cand, size, typical, noise, min_step=min_step, guard=guard,
                      refine=refine)
    if gaps.size < min_marks + 1:
        _too_few(gaps.size - 1, x, min_marks)
    if refine:
        cusps_s, cusp_h, bottoms_s, bottom_h = _arc_model(h, p, gaps, dx, guard, cum_p)
    else:
        cusps_s, cusp_h, bottoms_s, bottom_h = _sample_marks(h, gaps)
    if cusps_s.size < min_marks + 1:
        _too_few(cusps_s.size - 1, x, min_marks)
    cusps = x[0] + cusps_s * dx
    bottoms = x[0] + bottoms_s * dx
    widths = cusps[1:] - cusps[:-1]
    depths = 0.5 * (cusp_h[:-1] + cusp_h[1:]) - bottom_h
    pitch = float(widths.sum() / widths.size)
    return Marks(
        cusps_mm=cusps,
        bottoms_mm=bottoms,
        widths_mm=widths,
        depths_um=depths,
        cusp_heights_um=cusp_h,
        pitch_mm=pitch,
        uniformity_cv=_std(widths) / pitch,
        depth_um=float(depths.sum() / depths.size),
    )


def _std(values: np.ndarray) -> float:
    """``values.std()`` (1-D float64) without numpy's method overhead: the same operations.

    ``ndarray.std`` is ``sqrt(sum((v - sum(v) / n) ** 2) / n)`` with pairwise sums, as here.
    """
    d = values - values.sum() / values.size
    return math.sqrt(float((d * d).sum()) / values.size)


WEAK_STEP = 0.12
"""Smallest step (fraction of the typical one) of a cusp that :func:`with_narrow_marks` tests."""
NARROW_MARK_Z = 5.0
"""How many standard errors the lowest points either side of such a cusp must lie apart."""


def _cusp_gaps(p: np.ndarray, cum_p: np.ndarray, cand: np.ndarray, size: np.ndarray,
               typical: float, noise: float, *, min_step: float, guard: int, refine: bool
               ) -> np.ndarray:
    """The cusps to a sample (``i + 0.5``: between samples ``i`` and ``i + 1``) of the candidates.

    The steps of at least ``min_step`` of the typical one; refined: without the false ones
    (:func:`without_false_cusps`) and with the weaker ones of narrow marks
    (:func:`with_narrow_marks`).
    """
    if refine and cand.dtype == np.int64 and size.dtype == np.float64:
        # the composition below in one compiled call (marks_kernels.cusp_gaps: the same
        # operations in the same order)
        return marks_kernels.cusp_gaps(
            np.ascontiguousarray(p, dtype=np.float64),
            np.ascontiguousarray(cum_p, dtype=np.float64), np.ascontiguousarray(cand),
            np.ascontiguousarray(size), float(typical), float(noise), float(min_step),
            int(guard), WEAK_STEP, NARROW_MARK_Z)
    return _cusp_gaps_composed(p, cum_p, cand, size, typical, noise, min_step=min_step,
                               guard=guard, refine=refine)


def _cusp_gaps_composed(p: np.ndarray, cum_p: np.ndarray, cand: np.ndarray, size: np.ndarray,
                        typical: float, noise: float, *, min_step: float, guard: int,
                        refine: bool) -> np.ndarray:
    """:func:`_cusp_gaps` from its parts (the reference of the compiled one)."""
    strong = size >= min_step * typical
    gaps = cand[strong].astype(np.float64) + 0.5
    if not refine or gaps.size < 3:
        return gaps
    gaps = without_false_cusps(p, gaps, cum_p, guard=guard, min_step=min_step)
    weak = ~strong & (size >= WEAK_STEP * typical)
    if not weak.any() or gaps.size < 3:
        return gaps
    order = np.argsort(-size[weak], kind="stable")
    more = with_narrow_marks(p, gaps, cand[weak][order] + 0.5, cum_p,
                             all_gaps=cand[size >= WEAK_STEP * typical] + 0.5,
                             typical_step=typical, noise=noise, guard=guard)
    if more.size == gaps.size:
        return gaps
    return without_false_cusps(p, more, cum_p, guard=guard, min_step=min_step)


def without_false_cusps(slope: np.ndarray, gaps: np.ndarray, cum_p: np.ndarray, *,
                        guard: int = 2, min_step: float = 0.35) -> np.ndarray:
    """The candidate cusps without those the noise put inside a mark.

    At a true cusp the slope falls from one arc's line to the next, ``kappa (x - b_k)`` to
    ``kappa (x - b_(k+1))``, by the distance between the two marks' lowest points: at least
    one knife pass.  A cusp the noise made (a fall of two samples' means that the read noise
    pushed over ``min_step`` of the typical one) splits one arc: the lines either side are the
    same, ``b_(k+1) = b_k``.  Each piece's lowest point ``b`` comes from all its samples (the
    fit of :func:`vision.kernels.arc_model`: one common ``kappa``, pooled over the pieces, the
    samples next to a cusp left out, or, in a piece too short for that, kept), so its noise is
    a fraction of the two-sample step's.  A cusp whose pieces' lowest points lie less than
    ``min_step`` times the median distance apart is dropped.

    Parameters
    ----------
    slope : ndarray, shape (n,)
        Slope profile.
    gaps : ndarray, shape (g,)
        Candidate cusps to a sample, ascending (between samples ``i`` and ``i + 1``:
        ``i + 0.5``).
    cum_p : ndarray, shape (n + 1,)
        ``[0, cumsum(slope)]``.
    guard : int, optional
        As in :func:`find_marks`.
    min_step : float, optional
        Smallest distance of neighbouring lowest points as a fraction of their median one.

    Returns
    -------
    ndarray, shape (g',)
        The cusps kept (all of them when fewer than three distances can be measured or the
        pieces show no common curvature).
    """
    p = np.ascontiguousarray(slope, dtype=np.float64)
    g = np.ascontiguousarray(gaps, dtype=np.float64)
    false = marks_kernels.false_cusps(p, np.ascontiguousarray(cum_p, dtype=np.float64), g,
                                      int(guard), float(min_step))
    return gaps[~false] if false.any() else gaps


def with_narrow_marks(slope: np.ndarray, gaps: np.ndarray, weak: np.ndarray,
                      cum_p: np.ndarray, *, all_gaps: np.ndarray, typical_step: float,
                      noise: float, guard: int = 2, min_fall: float = WEAK_STEP,
                      z: float = NARROW_MARK_Z) -> np.ndarray:
    """The cusps with those of the weaker candidates that bound a mark of their own.

    A mark of a few samples (0.36 mm at 0.5 mm pitch, 12.5 px/mm: a knife cutting shallower
    than its neighbours) has both its cusps within the two samples either side that the step
    of :func:`cusp_steps` averages: each fall is measured at a fifth to a third of a full
    one and fails ``min_step``, while a vanished knife's neighbours make falls of two passes
    the typical one. Each weaker candidate (largest first) is put to the arc model instead:
    the piece of the profile it would split, fitted either side as a line of the common
    gradient ``kappa`` (pooled over the pieces between *all* candidates, so that marks not
    yet resolved do not flatten it), must show lowest points ``b`` that advance by at least
    ``min_fall`` of the typical fall (over ``kappa``) and by ``z`` standard errors of their
    difference (the slope's noise over the pieces' samples); such a candidate is added.
    Both pieces must hold ``2 guard`` samples: a shorter one may straddle a cusp already found
    (the noise's candidate a sample or two beside a true cusp), whose two lines would make
    its lowest point advance as a mark's does.
    A candidate that splits a piece holding a mark not yet resolved passes too; the caller's
    :func:`without_false_cusps` then drops it once the marks either side are resolved.

    Parameters
    ----------
    slope : ndarray, shape (n,)
        Slope profile.
    gaps : ndarray, shape (g,)
        The cusps so far, to a sample, ascending.
    weak : ndarray, shape (w,)
        Weaker candidates to a sample, in the order to try them.
    cum_p : ndarray, shape (n + 1,)
        ``[0, cumsum(slope)]``.
    all_gaps : ndarray
        Every candidate (``gaps`` and ``weak``), ascending: the pieces for ``kappa``.
    typical_step : float
        The typical fall of the slope at a cusp (:func:`find_marks`).
    noise : float
        The slope's noise, one sample.
    guard : int, optional
        As in :func:`find_marks`.
    min_fall, z : float, optional
        See above.

    Returns
    -------
    ndarray
        The cusps, ascending (``gaps`` itself when none is added).
    """
    out = marks_kernels.narrow_cusps(
        np.ascontiguousarray(slope, dtype=np.float64),
        np.ascontiguousarray(cum_p, dtype=np.float64),
        np.ascontiguousarray(gaps, dtype=np.float64),
        np.ascontiguousarray(weak, dtype=np.float64),
        np.ascontiguousarray(all_gaps, dtype=np.float64), int(guard), float(typical_step),
        float(noise), float(min_fall), float(z))
    return gaps if out.size == gaps.size else out


def _too_few(found: int, x: np.ndarray, need: int) -> None:
    raise MeasurementError(
        f"too few cuttermarks: found {max(found, 0)} complete marks in "
        f"{x[-1] - x[0]:.1f} mm of profile, need {need}"
    )


def _sample_marks(
    h: np.ndarray, gaps: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cusps at the higher sample of each step, bottoms at the lowest sample between."""
    n = h.size
    lo = np.floor(gaps).astype(int)
    hi = np.minimum(lo + 1, n - 1)
    idx = np.where(h[hi] > h[lo], hi, lo)
    pairs = zip(idx[:-1], idx[1:], strict=True)
    bot = np.array([a + int(np.argmin(h[a : b + 1])) for a, b in pairs])
    return idx.astype(np.float64), h[idx], bot.astype(np.float64), h[bot]


def _arc_model(
    h: np.ndarray, p: np.ndarray, gaps: np.ndarray, dx: float, guard: int, cum_p: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cusps, cusp heights, bottoms (in samples) and bottom heights of the arc model.

    Compiled (:func:`vision.kernels.arc_model`); the samples themselves
    (:func:`_sample_marks`) where the model does not apply.
    """
    ok, cusp, cusp_h, bottoms, bottom_h = kernels.arc_model(
        np.ascontiguousarray(h), np.ascontiguousarray(p),
        np.ascontiguousarray(gaps, dtype=np.float64), float(dx), int(guard),
        np.ascontiguousarray(cum_p))
    if not ok:  # (the compiled model raises no floating-point warnings; numpy might)
        with np.errstate(invalid="ignore", divide="ignore"):
            return _sample_marks(h, gaps)
    return cusp, cusp_h, bottoms, bottom_h
