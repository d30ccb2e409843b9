"""Which knife cut which mark: the spindle index latch and the encoder counts (pure functions).

A mark's lowest point lies where its knife passed bottom dead centre (BDC). The PLC latches the
encoder count at the spindle index pulse (knife 0 at BDC) nearest to the moment the board point
at the image centre of trigger A was under the cutter (``index_latch_counts``). A point at
image-A position ``x_mm`` (``u / px_per_mm``; the image centre is at ``cx / px_per_mm``) was
under the cutter at the count::

    c = counts_a - (L + x_mm - cx / px_per_mm) * counts_per_mm

and was cut by pass number ``(c - index_latch_counts) / (pitch_mm * counts_per_mm)`` counted
from that index pulse, so its knife is that number rounded, modulo ``Z`` (knife k+1 passes BDC
after knife k). The counters wrap (``2**counter_bits``): count differences are taken as signed
modular differences, so a wrap between the latches changes nothing.

Strong runout (:func:`attribute_marks`): a knife cutting much shallower than its neighbours
leaves a narrow mark whose BDC lies outside it (the vision then reports a bottom at the mark's
cusp), or no mark at all; the mean mark width is then not the board travel per knife pass. The
phase and the travel per pass are therefore fitted to the bottoms that lie inside their marks
only, every mark is given a pass of its own (in order along the board), and the passes between
the first and the last mark that got no mark are the knives that left none.
"""

from __future__ import annotations

import itertools
import operator
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from core.checks import check_finite, check_int, check_positive
from core.units import counter_difference


def wrapped_difference(a: int, b: int, *, counter_bits: int = 32) -> int:
    """Signed difference ``a - b`` of two wrapping counter values.

    Parameters
    ----------
    a, b : int
        Counter readings in ``[0, 2**counter_bits)``.
    counter_bits : int
        Width of the counter.

    Returns
    -------
    int
        The difference in ``[-2**(bits-1), 2**(bits-1))``.
    """
    bits = check_int("counter_bits", counter_bits, lo=2, hi=64)
    modulus = 1 << bits
    a = check_int("a", a, lo=0, hi=modulus - 1)
    b = check_int("b", b, lo=0, hi=modulus - 1)
    return counter_difference(a, b, bits=bits)


def pass_numbers(
    bottom_x_mm: Sequence[float],
    *,
    counts_a: int,
    index_latch_counts: int,
    cutter_to_camera_mm: float,
    counts_per_mm: float,
    px_per_mm: float,
    cx_px: float,
    pitch_mm: float,
    counter_bits: int = 32,
) -> np.ndarray:
    """Knife pass number (from the latched index pulse, not rounded) of each mark bottom.

    Parameters
    ----------
    bottom_x_mm : sequence of float, shape (n,)
        Positions of the marks' lowest points in image A's frame (``u / px_per_mm``), mm.
    counts_a : int
        Encoder counts latched at trigger A.
    index_latch_counts : int
        Encoder counts at the spindle index pulse (knife 0 at BDC), see the module docstring.
    cutter_to_camera_mm : float
        Distance ``L`` from the cutter to the image centre along the board, mm.
    counts_per_mm : float
        Encoder counts per mm of board travel.
    px_per_mm : float
        Image scale, px/mm.
    cx_px : float
        Column of the optical axis (image centre) in the undistorted image, px.
    pitch_mm : float
        Board travel per knife pass (the pitch), mm.
    counter_bits : int
        Width of the wrapping encoder counter.

    Returns
    -------
    ndarray, shape (n,)
        Pass numbers; integers for exact data, knife = ``round(...) mod Z``.
    """
    x = np.asarray(bottom_x_mm, dtype=float)
    if x.ndim != 1 or not np.all(np.isfinite(x)):
        raise ValueError("bottom_x_mm must be a finite 1-D sequence")
    length = check_finite("cutter_to_camera_mm", cutter_to_camera_mm)
    cpm = check_positive("counts_per_mm", counts_per_mm)
    ppm = check_positive("px_per_mm", px_per_mm)
    cx = check_finite("cx_px", cx_px)
    pitch = check_positive("pitch_mm", pitch_mm)
    base = wrapped_difference(counts_a, index_latch_counts, counter_bits=counter_bits)
    return (base - (length + x - cx / ppm) * cpm) / (pitch * cpm)


def knives_from_passes(
    passes: np.ndarray, knives: int, *, align_phase: bool = False
) -> np.ndarray:
    """Knife index of each mark from its pass number: ``round(pass) mod Z``.

    Parameters
    ----------
    passes : ndarray, shape (n,)
        Pass numbers (:func:`pass_numbers`).
    knives : int
        Number of knives ``Z``.
    align_phase : bool
        Remove the common fractional part of the pass numbers (their circular mean) before
        rounding: a constant latch or encoder offset below half a pitch then changes nothing.

    Returns
    -------
    ndarray of int, shape (n,)
        Knife index in ``[0, Z)`` of each mark.
    """
    z = check_int("knives", knives, lo=1)
    n = np.asarray(passes, dtype=float)
    if n.ndim != 1 or not np.all(np.isfinite(n)):
        raise ValueError("passes must be a finite 1-D array")
    if align_phase and n.size:
        n = n - phase_offset(n)
    return np.mod(np.rint(n).astype(np.int64), z)


def phase_offset(passes: np.ndarray) -> float:
    """Circular mean of the fractional parts of pass numbers, in ``[-0.5, 0.5)`` passes."""
    n = np.asarray(passes, dtype=float)
    if n.size == 0:
        return 0.0
    return _phase_of(_mean_resultant(n))


def _mean_resultant(n: np.ndarray) -> complex:
    """``mean(exp(2 pi i n))`` of a non-empty float array of pass numbers."""
    return complex(_mean(np.exp(2j * np.pi * n)))


def _mean(a: np.ndarray) -> np.floating | np.complexfloating:
    """``a.mean()`` of a non-empty 1-D array, without its wrapper: the same sum and division."""
    return np.add.reduce(a) / a.size


def _phase_of(resultant: complex) -> float:
    # np.angle's value (its arctan2) without its wrapper
    return float(np.arctan2(resultant.imag, resultant.real)) / (2.0 * np.pi)


def _spread_of(resultant: complex) -> float:
    # |mean exp(2 pi i n)| of exact pass numbers may round to just above 1: spread 0, not NaN
    r = min(float(np.abs(resultant)), 1.0)
    return float(np.sqrt(-2.0 * np.log(max(r, 1e-300))) / (2.0 * np.pi))


def phase_spread(passes: np.ndarray) -> float:
    """Spread of the fractional parts of pass numbers around their circular mean, in passes.

    ``sqrt(-2 ln R) / (2 pi)`` with ``R`` the mean resultant length; 0 for exact data. Above
    about 0.15 the attribution of marks to knives is doubtful and the measurement should not
    drive the uniformity loop.
    """
    n = np.asarray(passes, dtype=float)
    if n.size == 0:
        return float("nan")
    return _spread_of(_mean_resultant(n))


@dataclass(frozen=True)
class PassAttribution:
    """The marks of one field attributed to knife passes (:func:`attribute_marks`).

    Attributes
    ----------
    passes : ndarray of int, shape (n,)
        Pass number of each mark (from the latched index pulse, common phase removed); strictly
        decreasing along the image (a later pass lies further upstream).
    knife : ndarray of int, shape (n,)
        Knife of each mark, ``passes mod Z``.
    reliable : ndarray of bool, shape (n,)
        Whether the mark's bottom lies inside it (these alone set the phase and ``pass_mm``).
    pass_mm : float
        Board travel per knife pass fitted to the reliable bottoms, mm.
    phase : float
        Common fractional part removed from the pass numbers, passes.
    spread : float
        :func:`phase_spread` of the reliable bottoms, passes.
    passes_per_knife : ndarray of int, shape (Z,)
        Passes of each knife from the first mark's pass to the last mark's.
    """

    passes: np.ndarray
    knife: np.ndarray
    reliable: np.ndarray
    pass_mm: float
    phase: float
    spread: float
    passes_per_knife: np.ndarray

    @property
    def n_passes(self) -> int:
        """Knife passes from the first mark's to the last mark's (both included)."""
        return int(self.passes_per_knife.sum())

    @property
    def missing(self) -> int:
        """Passes in that span that left no mark."""
        return self.n_passes - int(self.passes.size)

    def knife_widths(self, widths_mm: Sequence[float]) -> np.ndarray:
        """Mean mark width of each knife per pass: a pass without a mark counts as width 0.

        Parameters
        ----------
        widths_mm : sequence of float, shape (n,)
            Width of each mark, mm.

        Returns
        -------
        ndarray, shape (Z,)
            Width per knife, mm; ``nan`` for a knife that left no mark in the field (the
            uniformity loop takes it as 0). Without missing passes: the mean width of its marks.
        """
        z = self.passes_per_knife.size
        w = np.asarray(widths_mm, dtype=float)
        if w.shape != self.knife.shape or not np.isfinite(w).all():
            raise ValueError(f"widths_mm must be {self.knife.size} finite values")
        # bincount adds each knife's widths in mark order (from 0.0), as a loop over the marks
        sums = np.bincount(self.knife, weights=w, minlength=z)
        has = np.bincount(self.knife, minlength=z) > 0
        return np.divide(sums, self.passes_per_knife, out=np.full(z, np.nan), where=has)


def attribute_marks(
    bottom_x_mm: Sequence[float],
    cusps_x_mm: Sequence[float] | None,
    *,
    counts_a: int,
    index_latch_counts: int,
    cutter_to_camera_mm: float,
    counts_per_mm: float,
    px_per_mm: float,
    cx_px: float,
    pass_guide_mm: float,
    knives: int,
    min_inset_mm: float = 0.0,
    counter_bits: int = 32,
) -> PassAttribution:
    """Give every mark its knife pass, robust to narrow and missing marks.

    1. Reliable bottoms: those at least ``min_inset_mm`` inside both cusps of their mark (a
       bottom clipped to a cusp is not where its knife passed BDC).
    2. Travel per pass: the gaps between consecutive reliable bottoms, in whole passes of
       ``pass_guide_mm`` (rounded; refined twice), and the least-squares slope of their
       positions over those pass counts.
    3. Phase: circular mean of the reliable bottoms' pass numbers; ``spread`` is their
       :func:`phase_spread`.
    4. Passes: a reliable mark takes its bottom's pass (rounded); every other mark the pass
       nearest its centre that keeps the marks in order, one pass per mark.

    Parameters
    ----------
    bottom_x_mm : sequence of float, shape (n,)
        Lowest point of each mark, image-A frame, mm, increasing.
    cusps_x_mm : sequence of float, shape (n + 1,), or None
        Cusps bounding the marks, mm; ``None``: every bottom is taken as reliable and as the
        mark's centre.
    counts_a, index_latch_counts, cutter_to_camera_mm, counts_per_mm, px_per_mm, cx_px,
    counter_bits
        As in :func:`pass_numbers`.
    pass_guide_mm : float
        Rough board travel per knife pass (e.g. ``V / (n Z)``), good to about 15 %, mm.
    knives : int
        Number of knives ``Z``.
    min_inset_mm : float
        Smallest distance of a reliable bottom from both its cusps, mm (about one sample).

    Returns
    -------
    PassAttribution

    Raises
    ------
    ValueError
        Bad inputs; fewer than two reliable bottoms; two reliable bottoms on one pass; marks
        that cannot be given one pass each in order.
    """
    z = check_int("knives", knives, lo=1)
    guide = check_positive("pass_guide_mm", pass_guide_mm)
    inset = check_positive("min_inset_mm", min_inset_mm, allow_zero=True)
    b, centre, reliable = _reliable_bottoms(bottom_x_mm, cusps_x_mm, inset)
    # board travel after the index pulse, mm (falls with x): pass_numbers with a pitch of 1 mm
    length = check_finite("cutter_to_camera_mm", cutter_to_camera_mm)
    cpm = check_positive("counts_per_mm", counts_per_mm)
    ppm = check_positive("px_per_mm", px_per_mm)
    cx = check_finite("cx_px", cx_px)
    base = wrapped_difference(counts_a, index_latch_counts, counter_bits=counter_bits)
    travel = (base - (length + b - cx / ppm) * cpm) / (1.0 * cpm)
    t_fwd = travel[reliable]
    t_rel = t_fwd[::-1]  # increasing
    gaps = t_rel[1:] - t_rel[:-1]
    t_dev = t_rel - _mean(t_rel)
    pitch = _travel_per_pass(gaps, t_dev, guide)
    resultant = _mean_resultant(t_fwd / pitch)
    phase = _phase_of(resultant)
    spread = _spread_of(resultant)
    # order along the image: q = -(pass number) increases with x; an unreliable mark by its
    # centre (every mark reliable: the bottoms alone)
    if t_fwd.size < travel.size:
        travel_c = (base - (length + centre - cx / ppm) * cpm) / (1.0 * cpm)
        travel = np.where(reliable, travel, travel_c)
    q = np.rint(-(travel / pitch - phase)).astype(np.int64).tolist()
    q = _one_pass_per_mark(q, reliable.tolist())
    passes = np.array(q, dtype=np.int64)
    np.negative(passes, out=passes)
    knife = passes % z  # (floor modulo, as Python's: in [0, Z))
    first, span = -max(q), max(q) - min(q) + 1  # passes first .. first + span - 1, by knife
    per_knife = np.array([span // z + ((k - first) % z < span % z) for k in range(z)],
                         dtype=np.intp)
    return PassAttribution(
        passes=passes,
        knife=knife,
        reliable=reliable,
        pass_mm=pitch,
        phase=phase,
        spread=spread,
        passes_per_knife=per_knife,
    )


def _reliable_bottoms(bottom_x_mm: Sequence[float], cusps_x_mm: Sequence[float] | None,
                      inset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bottoms (checked), the marks' centres and which bottoms are reliable (step 1)."""
    b = np.asarray(bottom_x_mm, dtype=float)
    if b.ndim != 1 or not np.isfinite(b).all():
        raise ValueError("bottom_x_mm must be a finite 1-D sequence")
    if cusps_x_mm is None:
        centre = b
        reliable = np.ones(b.size, dtype=bool)
    else:
        c = np.asarray(cusps_x_mm, dtype=float)
        if c.shape != (b.size + 1,) or not np.isfinite(c).all():
            raise ValueError(f"cusps_x_mm must be {b.size + 1} finite values, got {c.shape}")
        left, right = c[:-1], c[1:]
        if (right <= left).any():  # (np.diff(c) <= 0 for finite values)
            raise ValueError("cusps_x_mm must increase")
        centre = 0.5 * (left + right)
        reliable = np.minimum(b - left, right - b) >= inset
    if (b[1:] < b[:-1]).any():
        raise ValueError("bottom_x_mm must not decrease")
    n_reliable = int(np.count_nonzero(reliable))
    if n_reliable < 2:
        raise ValueError(f"{n_reliable} mark bottoms inside their marks, need 2")
    return b, centre, reliable


def _travel_per_pass(gaps: np.ndarray, t_dev: np.ndarray, guide: float) -> float:
    """Board travel per knife pass from the reliable bottoms' gaps, refined twice (step 2)."""
    pitch = guide
    last_steps = None
    count = np.zeros(gaps.size + 1)
    for _ in range(3):
        steps_a = np.rint(gaps / pitch)
        steps = steps_a.tolist()  # (the tests and the comparison in plain floats: cheaper)
        low = min(steps)
        if low < 1:
            j = steps.index(low)  # the first smallest, as np.argmin
            raise ValueError(
                f"two mark bottoms {gaps[j]:.3f} mm apart on one pass of {pitch:.3f} mm"
            )
        if steps == last_steps:
            break  # the same counts give the same slope again
        last_steps = steps
        np.add.accumulate(steps_a, out=count[1:])
        dc = count - _mean(count)
        pitch = float(dc @ t_dev / (dc @ dc))
        if not pitch > 0:
            raise ValueError("mark bottoms do not advance along the board")
    return pitch


def _one_pass_per_mark(q: list[int], rel: list[bool]) -> list[int]:
    """Passes in order along the image, one per mark (step 4): unreliable marks fitted between.

    ``q`` is the rounded order number of each mark (minus its pass number); reliable marks keep
    theirs, every other mark takes the nearest one after its predecessor and before its
    successor.
    """
    q = list(q)
    q_rel = list(itertools.compress(q, rel))
    if min(map(operator.sub, q_rel[1:], q_rel), default=1) < 1:
        raise ValueError("two mark bottoms on one knife pass")
    for i in range(1, len(q)):  # forward: after the previous mark
        if not rel[i]:
            q[i] = max(q[i], q[i - 1] + 1)
    for i in range(len(q) - 2, -1, -1):  # backward: before the next mark
        if not rel[i]:
            q[i] = min(q[i], q[i + 1] - 1)
    if min(map(operator.sub, q[1:], q), default=1) < 1:
        raise ValueError("marks do not fit one per knife pass between the reliable bottoms")
    return q
