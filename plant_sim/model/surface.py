"""Surface kinematics of a planing cutterhead: knife passes and the planed profile they leave.

The planed surface is the lower envelope of the knife-tip circles: every knife pass at bottom
dead centre (BDC) leaves a circular arc of the tip radius, and each sample of the surface belongs
to the pass whose arc lies lowest there. Pitch, depth and (non-)uniformity of the cuttermarks come
out of this geometry; nothing is painted on.

Conventions (docs/architecture.md)
----------------------------------
- Board coordinate ``x_mm`` increases toward +x, the direction of feed. The cutterhead is fixed
  in the machine, so in board coordinates it moves toward -x: a later pass lies at a smaller
  ``x_mm``. Knife ``k + 1`` passes BDC after knife ``k``.
- Heights are in micrometres relative to the nominal cut plane; negative is deeper.
  ``runout_um[k] > 0``: knife ``k`` stands further out and cuts deeper. ``offsets_um[k] > 0``
  (piezo): the cutterhead is moved up while knife ``k`` cuts, so it cuts less deep.
- A mark's lowest point lies where its knife passed BDC.

The envelope is computed exactly: two tip circles of equal radius cross once (their difference
is monotonic in ``x``), so the lower envelope is found by pruning passes that own no interval,
and the cusps are the exact circle intersections.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from core.checks import check_finite, check_int, check_positive

__all__ = [
    "Cutterhead",
    "Passes",
    "RunoutDrift",
    "Surface",
    "concat_passes",
    "envelope",
    "passes_steady",
    "pitch_per_pass_mm",
]


def _per_knife(name: str, values: Sequence[float], knives: int) -> tuple[float, ...]:
    """``values`` as a tuple of ``knives`` finite floats (a ``ValueError`` names ``name[i]``)."""
    try:
        out = tuple(float(v) for v in values)
    except TypeError:
        raise ValueError(f"{name} must be a sequence of numbers, got {values!r}") from None
    if len(out) != knives:
        raise ValueError(f"{name} must have one value per knife ({knives}), got {len(out)}")
    for i, v in enumerate(out):
        check_finite(f"{name}[{i}]", v)
    return out


@dataclass(frozen=True)
class RunoutDrift:
    """Slow change of each knife's stand-out over machine time: warm-up and wear.

    Knife ``k`` stands out by an extra::

        drift_k(t) = warmup_um[k] * (1 - exp(-t / warmup_tau_s[k])) - wear_um_per_min[k] * t / 60

    micrometres at machine time ``t >= 0`` (0 before): the warm-up approaches its amplitude
    with its time constant (thermal growth of the knife and its seat), the wear takes the tip
    back linearly. ``drift_k(0) = 0``: at the start every knife stands at its runout.

    Parameters
    ----------
    warmup_um : tuple of float, shape (Z,)
        Warm-up amplitude of each knife, um (positive: stands further out when warm).
    warmup_tau_s : tuple of float, shape (Z,)
        Warm-up time constant of each knife, seconds (> 0).
    wear_um_per_min : tuple of float, shape (Z,)
        Wear rate of each knife (its tip recedes), um per minute (>= 0).
    """

    warmup_um: tuple[float, ...]
    warmup_tau_s: tuple[float, ...]
    wear_um_per_min: tuple[float, ...]

    def __post_init__(self) -> None:
        try:
            z = len(self.warmup_um)
        except TypeError:
            raise ValueError(f"warmup_um must be a sequence of numbers, got "
                             f"{self.warmup_um!r}") from None
        if not 1 <= z <= 64:
            raise ValueError(f"warmup_um must hold one value per knife (1..64), got {z}")
        amp = _per_knife("warmup_um", self.warmup_um, z)
        tau = _per_knife("warmup_tau_s", self.warmup_tau_s, z)
        wear = _per_knife("wear_um_per_min", self.wear_um_per_min, z)
        for i, v in enumerate(tau):
            check_positive(f"warmup_tau_s[{i}]", v)
        for i, v in enumerate(wear):
            check_positive(f"wear_um_per_min[{i}]", v, allow_zero=True)
        object.__setattr__(self, "warmup_um", amp)
        object.__setattr__(self, "warmup_tau_s", tau)
        object.__setattr__(self, "wear_um_per_min", wear)

    @property
    def knives(self) -> int:
        """Number of knives Z."""
        return len(self.warmup_um)

    @property
    def active(self) -> bool:
        """Whether any knife drifts at all."""
        return any(self.warmup_um) or any(self.wear_um_per_min)

    def knife_um(self, knife: int, t_s: float) -> float:
        """``drift_k(t)`` of one knife, um (the machine model's per-pass call: no arrays)."""
        if not t_s > 0.0:
            return 0.0
        warm = self.warmup_um[knife] * -math.expm1(-t_s / self.warmup_tau_s[knife])
        return warm - self.wear_um_per_min[knife] * t_s / 60.0

    def drift_um(self, t_s: float) -> np.ndarray:
        """``drift_k(t)`` of every knife at machine time ``t_s``, shape (Z,), um."""
        t = check_finite("t_s", t_s)
        return np.array([self.knife_um(k, t) for k in range(self.knives)])


@dataclass(frozen=True)
class Cutterhead:
    """A cutterhead with ``knives`` knives at tip radius ``radius_mm``.

    Parameters
    ----------
    knives : int
        Number of knives Z (1..64).
    radius_mm : float
        Nominal tip radius R, millimetres (> 0).
    runout_um : tuple of float, length ``knives``
        Radial runout of each knife, micrometres; positive stands further out (cuts deeper).
    eccentricity_um : float
        Eccentricity of the cutterhead on its spindle, micrometres: knife ``k`` stands out by an
        extra ``eccentricity_um * cos(2 pi k / knives)``.
    drift : RunoutDrift or None
        Warm-up and wear of the knives over machine time (``None``: the runout stays put).
    """

    knives: int
    radius_mm: float
    runout_um: tuple[float, ...]
    eccentricity_um: float = 0.0
    drift: RunoutDrift | None = None

    def __post_init__(self) -> None:
        check_int("knives", self.knives, lo=1, hi=64)
        check_positive("radius_mm", self.radius_mm)
        try:
            runout = tuple(float(v) for v in self.runout_um)
        except TypeError:
            raise ValueError(
                f"runout_um must be a sequence of numbers, got {self.runout_um!r}"
            ) from None
        if len(runout) != self.knives:
            raise ValueError(
                f"runout_um must have one value per knife ({self.knives}), got {len(runout)}"
            )
        for i, v in enumerate(runout):
            check_finite(f"runout_um[{i}]", v)
            if abs(v) > 1000.0 * self.radius_mm:
                raise ValueError(f"runout_um[{i}] is larger than the radius: {v!r}")
        check_finite("eccentricity_um", self.eccentricity_um)
        object.__setattr__(self, "runout_um", runout)
        object.__setattr__(self, "radius_mm", float(self.radius_mm))
        object.__setattr__(self, "eccentricity_um", float(self.eccentricity_um))
        if self.drift is not None:
            if not isinstance(self.drift, RunoutDrift):
                raise ValueError(f"drift must be a RunoutDrift or None, got {self.drift!r}")
            if self.drift.knives != self.knives:
                raise ValueError(f"drift must have one value per knife ({self.knives}), got "
                                 f"{self.drift.knives}")

    def standout_um(self, t_s: float = 0.0) -> np.ndarray:
        """Effective radial stand-out of each knife at machine time ``t_s``, shape (Z,), um.

        Runout plus eccentricity, plus the :class:`RunoutDrift` at ``t_s`` (none at 0).
        """
        k = np.arange(self.knives)
        ecc = self.eccentricity_um * np.cos(2 * np.pi * k / self.knives)
        out = np.asarray(self.runout_um) + ecc
        if self.drift is not None:
            out = out + self.drift.drift_um(t_s)
        return out


@dataclass(frozen=True)
class Passes:
    """Knife passes at BDC: a plain container of equally long arrays.

    Attributes
    ----------
    x_mm : ndarray of float, shape (N,)
        Board coordinate of the cutterhead axis at each pass, millimetres.
    bottom_um : ndarray of float, shape (N,)
        Height of the tip's lowest point relative to the nominal cut plane, micrometres
        (negative = deeper): ``-standout_k + offset``.
    knife : ndarray of int, shape (N,)
        Index of the knife that makes the pass.
    radius_mm : float
        Tip radius R, millimetres.
    """

    x_mm: np.ndarray
    bottom_um: np.ndarray
    knife: np.ndarray
    radius_mm: float

    def __post_init__(self) -> None:
        x = np.asarray(self.x_mm, dtype=float).reshape(-1)
        b = np.asarray(self.bottom_um, dtype=float).reshape(-1)
        k = np.asarray(self.knife).reshape(-1)
        if k.size and not np.issubdtype(k.dtype, np.integer):
            if not np.all(k == np.round(k)):
                raise ValueError("knife must hold integer knife indices")
        k = k.astype(np.int64)
        if not (x.size == b.size == k.size):
            raise ValueError(
                f"x_mm, bottom_um and knife must have equal lengths, got {x.size}, {b.size}, "
                f"{k.size}"
            )
        if not np.all(np.isfinite(x)):
            raise ValueError("x_mm contains NaN or infinite values")
        if not np.all(np.isfinite(b)):
            raise ValueError("bottom_um contains NaN or infinite values")
        check_positive("radius_mm", self.radius_mm)
        object.__setattr__(self, "x_mm", x)
        object.__setattr__(self, "bottom_um", b)
        object.__setattr__(self, "knife", k)
        object.__setattr__(self, "radius_mm", float(self.radius_mm))

    def __len__(self) -> int:
        return int(self.x_mm.size)

    def sorted(self) -> Passes:
        """The same passes ordered by ``x_mm`` (stable)."""
        order = np.argsort(self.x_mm, kind="stable")
        return Passes(self.x_mm[order], self.bottom_um[order], self.knife[order], self.radius_mm)

    def select(self, mask: np.ndarray) -> Passes:
        """The passes where the boolean (or index) ``mask`` selects."""
        if isinstance(mask, np.ndarray) and mask.ndim == 1:
            # 1-D parts of arrays __post_init__ has checked need no second check (this runs
            # several times per simulated pair)
            out = object.__new__(Passes)
            object.__setattr__(out, "x_mm", self.x_mm[mask])
            object.__setattr__(out, "bottom_um", self.bottom_um[mask])
            object.__setattr__(out, "knife", self.knife[mask])
            object.__setattr__(out, "radius_mm", self.radius_mm)
            return out
        return Passes(self.x_mm[mask], self.bottom_um[mask], self.knife[mask], self.radius_mm)

    def slice(self, x_lo_mm: float, x_hi_mm: float, *, margin_mm: float = 0.0) -> Passes:
        """Passes with ``x_lo_mm - margin_mm <= x_mm <= x_hi_mm + margin_mm``."""
        lo = check_finite("x_lo_mm", x_lo_mm) - margin_mm
        hi = check_finite("x_hi_mm", x_hi_mm) + margin_mm
        return self.select((self.x_mm >= lo) & (self.x_mm <= hi))

    def concat(self, *others: Passes) -> Passes:
        """These passes followed by ``others`` (same radius)."""
        return concat_passes([self, *others])


def concat_passes(parts: Sequence[Passes]) -> Passes:
    """Join several :class:`Passes` of the same tip radius into one.

    Raises
    ------
    ValueError
        ``parts`` is empty or the radii differ.
    """
    if not parts:
        raise ValueError("parts must hold at least one Passes")
    r = parts[0].radius_mm
    for i, p in enumerate(parts):
        if not math.isclose(p.radius_mm, r, rel_tol=1e-12):
            raise ValueError(f"parts[{i}].radius_mm differs: {p.radius_mm} vs {r}")
    return Passes(
        np.concatenate([p.x_mm for p in parts]),
        np.concatenate([p.bottom_um for p in parts]),
        np.concatenate([p.knife for p in parts]),
        r,
    )


def pitch_per_pass_mm(*, spindle_rpm: float, feed_mm_s: float, knives: int) -> float:
    """Feed per knife pass, ``feed / (rpm / 60 * Z)``, millimetres."""
    return feed_mm_s / (spindle_rpm / 60.0 * knives)


def _reach_mm(radius_mm: float, rise_um: float) -> float:
    """Distance from a tip circle's bottom at which the circle has risen by ``rise_um``."""
    y = min(rise_um * 1e-3, radius_mm)
    return math.sqrt(max(2.0 * radius_mm * y - y * y, 0.0))


def passes_steady(
    head: Cutterhead,
    *,
    spindle_rpm: float,
    feed_mm_s: float,
    x_start_mm: float,
    x_end_mm: float,
    offsets_um: Sequence[float] | None = None,
    phase_mm: float = 0.0,
) -> Passes:
    """Knife passes of a cutterhead at constant spindle speed and feed.

    Knife 0 passes BDC at board coordinate ``phase_mm`` (and every ``Z`` passes from there);
    later passes lie toward -x, so the knife index decreases (mod Z) with increasing ``x_mm``.
    Passes are generated beyond ``[x_start_mm, x_end_mm]`` far enough for :func:`envelope` to be
    exact over the whole range.

    Parameters
    ----------
    head : Cutterhead
        Knives, radius, runout.
    spindle_rpm : float
        Spindle speed, revolutions per minute (> 0).
    feed_mm_s : float
        Feed speed, mm/s (> 0).
    x_start_mm, x_end_mm : float
        Board range to be planed, millimetres (``x_start_mm < x_end_mm``).
    offsets_um : sequence of float, length Z, optional
        Piezo offset while each knife cuts, micrometres; positive moves the head up.
    phase_mm : float
        Board coordinate of a BDC pass of knife 0, millimetres.

    Returns
    -------
    Passes
        Sorted by ``x_mm``; pass spacing ``feed_mm_s / (spindle_rpm / 60 * Z)``.
    """
    rpm = check_positive("spindle_rpm", spindle_rpm)
    feed = check_positive("feed_mm_s", feed_mm_s)
    x0 = check_finite("x_start_mm", x_start_mm)
    x1 = check_finite("x_end_mm", x_end_mm)
    if not x1 > x0:
        raise ValueError(f"x_end_mm must be > x_start_mm, got {x_end_mm!r} <= {x_start_mm!r}")
    phase = check_finite("phase_mm", phase_mm)
    z = head.knives
    if offsets_um is None:
        offsets = np.zeros(z)
    else:
        offsets = np.asarray(
            [check_finite(f"offsets_um[{i}]", v) for i, v in enumerate(offsets_um)]
        )
        if offsets.size != z:
            raise ValueError(f"offsets_um must have one value per knife ({z}), got {offsets.size}")
    pitch = pitch_per_pass_mm(spindle_rpm=rpm, feed_mm_s=feed, knives=z)
    r = head.radius_mm
    if pitch > 0.5 * r:
        raise ValueError(
            f"feed_mm_s too high for spindle_rpm: {pitch:.3g} mm per pass exceeds "
            f"R/2 = {r / 2:g} mm"
        )
    bottoms = -head.standout_um() + offsets
    spread = float(bottoms.max() - bottoms.min())
    margin = _reach_mm(r, spread + 1e3 * (r - math.sqrt(r * r - pitch * pitch))) + 2 * pitch
    j0 = math.floor((x0 - margin - phase) / pitch)
    j1 = math.ceil((x1 + margin - phase) / pitch)
    if j1 - j0 > 50_000_000:
        raise ValueError("x_end_mm - x_start_mm spans too many passes (> 5e7)")
    j = np.arange(j0, j1 + 1)
    knife = np.mod(-j, z)
    return Passes(phase + j * pitch, bottoms[knife], knife, r)


def _crossings(x: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    """Abscissa where the lower arcs of consecutive circles cross, shape (N-1,), mm.

    Circle ``i`` has centre ``(x[i], c[i])`` (mm) and radius ``r``; ``x`` is strictly increasing.
    Right of the crossing, circle ``i + 1`` is the lower one.
    """
    dx = x[1:] - x[:-1]
    dc = c[1:] - c[:-1]
    d = np.hypot(dx, dc)
    h = np.sqrt(np.maximum(r * r - 0.25 * d * d, 0.0))
    return 0.5 * (x[1:] + x[:-1]) + h * dc / d


_MIN_MARK_MM = 1e-7
"""Passes owning less than this times the radius (2 nm at R = 20 mm) are dropped: such
slivers only arise from passes a fraction of a micrometre apart with different heights (the
feed crawling to a stop), whose crossings lie near the circles' equator, where rounding
decides their order and the marks' depths come out meaningless."""


def _lower_hull(x: np.ndarray, c: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the passes on the lower envelope and the crossings between them.

    ``x`` strictly increasing. A pass whose left crossing is not left of its right crossing
    (by ``_MIN_MARK_MM * r``) owns no interval and is dropped; non-adjacent such passes are
    dropped together (alternating parity), which is exact, until every interval is non-empty.
    """
    idx = np.arange(x.size)
    while True:
        s = _crossings(x[idx], c[idx], r)
        bad = np.zeros(idx.size, dtype=bool)
        if idx.size > 2:
            bad[1:-1] = s[:-1] >= s[1:] - _MIN_MARK_MM * r
        if not bad.any():
            return idx, s
        pos = np.flatnonzero(bad)
        even = pos[pos % 2 == 0]
        drop = even if even.size else pos[pos % 2 == 1]
        keep = np.ones(idx.size, dtype=bool)
        keep[drop] = False
        idx = idx[keep]


@dataclass(frozen=True)
class Surface:
    """A planed profile sampled at ``x_mm`` and the true cuttermarks that made it.

    Attributes
    ----------
    x_mm : ndarray, shape (M,)
        Sample positions (board coordinate), millimetres, as given to :func:`envelope`.
    height_um : ndarray, shape (M,)
        Height of the surface at ``x_mm``, micrometres (negative = below the nominal cut plane).
    owner : ndarray of int, shape (M,)
        Index (into the ``passes`` given to :func:`envelope`) of the pass that cut each sample.
    cusps_mm : ndarray, shape (H-1,)
        Exact positions where ownership switches between consecutive envelope passes, sorted.
    widths_mm : ndarray, shape (H-2,)
        Width (cusp to cusp) of every complete mark, i.e. of every envelope pass with a
        neighbour on both sides.
    depths_um : ndarray, shape (H-2,)
        Depth of each complete mark: mean height of its two cusps minus its lowest point.
    bottoms_mm : ndarray, shape (H-2,)
        Position of each complete mark's lowest point (its BDC, or the nearer cusp if the BDC
        lies outside the mark).
    knife : ndarray of int, shape (H-2,)
        Knife that cut each complete mark.
    mark_pass : ndarray of int, shape (H-2,)
        Index (into ``passes``) of the pass of each complete mark.
    passes : Passes
        The envelope passes (sorted by ``x_mm``), for exact evaluation by :meth:`height_at`.
    cusp_heights_um : ndarray, shape (H-1,)
        Height at each cusp, micrometres.
    source : Passes or None
        The passes given to :func:`envelope` (``mark_pass`` indexes them), envelope or not:
        :meth:`metrics` counts the passes that left no mark from them.
    """

    x_mm: np.ndarray
    height_um: np.ndarray
    owner: np.ndarray
    cusps_mm: np.ndarray
    widths_mm: np.ndarray
    depths_um: np.ndarray
    bottoms_mm: np.ndarray
    knife: np.ndarray
    mark_pass: np.ndarray
    passes: Passes
    cusp_heights_um: np.ndarray = field(default_factory=lambda: np.zeros(0))
    source: Passes | None = None

    @property
    def x_range_mm(self) -> tuple[float, float]:
        """Board range over which :meth:`height_at` is valid (within reach of the passes)."""
        r = self.passes.radius_mm
        return float(self.passes.x_mm[0] - r), float(self.passes.x_mm[-1] + r)

    def height_at(self, x_mm: np.ndarray) -> np.ndarray:
        """Exact height of the envelope at arbitrary board positions, micrometres.

        Parameters
        ----------
        x_mm : array_like
            Positions, millimetres, any shape; must lie within a tip radius of an envelope pass.
        """
        x = np.asarray(x_mm, dtype=float)
        p = self.passes
        j = np.searchsorted(self.cusps_mm, x)
        dx = x - p.x_mm[j]
        r = p.radius_mm
        if np.any(np.abs(dx) > r) or not np.all(np.isfinite(x)):
            raise ValueError("x_mm lies outside the reach of the knife passes")
        return p.bottom_um[j] + 1e3 * (r - np.sqrt(r * r - dx * dx))

    def __call__(self, x_mm: np.ndarray) -> np.ndarray:
        """Same as :meth:`height_at` (a Surface is a height function)."""
        return self.height_at(x_mm)

    def marks_between(self, x_lo_mm: float, x_hi_mm: float) -> np.ndarray:
        """Boolean mask over the complete marks whose both cusps lie in ``[x_lo_mm, x_hi_mm]``."""
        lo = check_finite("x_lo_mm", x_lo_mm)
        hi = check_finite("x_hi_mm", x_hi_mm)
        left = self.cusps_mm[:-1]
        right = self.cusps_mm[1:]
        return (left >= lo) & (right <= hi)

    def metrics(self, x_lo_mm: float, x_hi_mm: float) -> dict[str, object]:
        """True cuttermark metrics over the complete marks inside ``[x_lo_mm, x_hi_mm]``.

        Returns
        -------
        dict
            ``pitch_mm`` (mean width), ``uniformity_cv`` (population std / mean of the widths),
            ``depth_um`` (mean depth), ``mark_widths_mm`` (list), ``mark_depths_um`` (list),
            ``cusps_mm`` (list, the cusps bounding those marks), ``knife`` (list), ``n_marks``.
            With no complete mark the numbers are NaN and the lists empty. From the knife
            passes between the first and the last of those marks (when the surface knows its
            ``source`` passes): ``knife_widths_mm`` (list, width sum of each knife's marks per
            pass of that knife; 0 for a knife whose passes left no mark, NaN for one without
            a pass there), ``vanished_knives`` (list of those with passes and no mark),
            ``pass_pitch_mm`` (the marks' width sum per pass) and ``kinematic_cv`` (population
            std / mean of ``knife_widths_mm``, NaN ones left out).
        """
        sel = self.marks_between(x_lo_mm, x_hi_mm)
        w = self.widths_mm[sel]
        d = self.depths_um[sel]
        idx = np.flatnonzero(sel)
        cusps = np.unique(np.concatenate([self.cusps_mm[idx], self.cusps_mm[idx + 1]]))
        if w.size == 0:
            pitch = cv = depth = math.nan
        else:
            pitch = float(w.mean())
            cv = float(w.std() / pitch)
            depth = float(d.mean())
        return {
            "pitch_mm": pitch,
            "uniformity_cv": cv,
            "depth_um": depth,
            "mark_widths_mm": [float(v) for v in w],
            "mark_depths_um": [float(v) for v in d],
            "cusps_mm": [float(v) for v in cusps],
            "knife": [int(v) for v in self.knife[sel]],
            "n_marks": int(w.size),
            **self._kinematics(sel),
        }

    def _kinematics(self, sel: np.ndarray) -> dict[str, object]:
        """Widths per knife and pass over the selected marks' passes (see :meth:`metrics`)."""
        src = self.source
        if src is None or not np.any(sel) or len(src) == 0:
            return {"knife_widths_mm": [], "vanished_knives": [], "pass_pitch_mm": math.nan,
                    "kinematic_cv": math.nan}
        knives = int(src.knife.max()) + 1
        x_marks = src.x_mm[self.mark_pass[sel]]
        inside = (src.x_mm >= x_marks.min()) & (src.x_mm <= x_marks.max())
        _, first = np.unique(src.x_mm[inside], return_index=True)  # one pass per position
        per_knife = np.bincount(src.knife[inside][first], minlength=knives)
        w = self.widths_mm[sel]
        sums = np.bincount(self.knife[sel], weights=w, minlength=knives)
        marked = np.bincount(self.knife[sel], minlength=knives) > 0
        widths = np.full(knives, math.nan)
        has = per_knife > 0
        widths[has] = sums[has] / per_knife[has]
        finite = widths[has]
        mean = float(finite.mean())
        return {
            "knife_widths_mm": [float(v) for v in widths],
            "vanished_knives": [int(k) for k in np.flatnonzero(has & ~marked)],
            "pass_pitch_mm": float(w.sum() / per_knife.sum()),
            "kinematic_cv": float(finite.std() / mean) if mean > 0 else math.nan,
        }


def envelope(x_mm: np.ndarray, passes: Passes) -> Surface:
    """The planed surface: lower envelope of the knife-tip circles, sampled at ``x_mm``.

    Parameters
    ----------
    x_mm : array_like, shape (M,)
        Board positions to sample, millimetres (any order); each must lie within a tip radius
        of the pass that owns it.
    passes : Passes
        Knife passes (any order; at least one).

    Returns
    -------
    Surface
        Heights ``z = bottom + (R - sqrt(R^2 - (x - x_j)^2))`` of the lowest circle (um) and the
        true marks (exact cusps). Where several passes share one ``x_mm`` only the lowest counts.

    Raises
    ------
    ValueError
        No passes, non-finite samples, or a sample out of reach of every pass.
    """
    x = np.asarray(x_mm, dtype=float).reshape(-1)
    if x.size == 0:
        raise ValueError("x_mm must hold at least one sample")
    if not np.all(np.isfinite(x)):
        raise ValueError("x_mm contains NaN or infinite values")
    if len(passes) == 0:
        raise ValueError("passes must hold at least one pass")
    r = passes.radius_mm
    # sort by x, then by bottom so that the first of equal x is the lowest
    order = np.lexsort((passes.bottom_um, passes.x_mm))
    xs = passes.x_mm[order]
    first = np.ones(xs.size, dtype=bool)
    first[1:] = xs[1:] > xs[:-1]
    order = order[first]
    xs = passes.x_mm[order]
    bs = passes.bottom_um[order]
    hull, s = _lower_hull(xs, r + 1e-3 * bs, r)
    env_idx = order[hull]
    xe = xs[hull]
    be = bs[hull]
    env = Passes(xe, be, passes.knife[env_idx], r)

    j = np.searchsorted(s, x)
    dx = x - xe[j]
    if np.any(np.abs(dx) > r):
        raise ValueError("x_mm lies outside the reach of the knife passes")
    height = be[j] + 1e3 * (r - np.sqrt(r * r - dx * dx))

    # cusp heights (on the left circle of each crossing)
    dxc = s - xe[:-1]
    cusp_h = be[:-1] + 1e3 * (r - np.sqrt(np.maximum(r * r - dxc * dxc, 0.0)))
    left, right = s[:-1], s[1:]
    xm = xe[1:-1]
    widths = right - left
    bottom_x = np.clip(xm, left, right)
    dxb = bottom_x - xm
    low = be[1:-1] + 1e3 * (r - np.sqrt(r * r - dxb * dxb))
    depths = 0.5 * (cusp_h[:-1] + cusp_h[1:]) - low
    return Surface(
        x_mm=x,
        height_um=height,
        owner=env_idx[j],
        cusps_mm=s,
        widths_mm=widths,
        depths_um=depths,
        bottoms_mm=bottom_x,
        knife=env.knife[1:-1],
        mark_pass=env_idx[1:-1],
        passes=env,
        cusp_heights_um=cusp_h,
        source=passes,
    )
