"""The uniformity loop: learn per-knife piezo offsets that make every knife cut the same mark.

Pure and clock-injected. Width model (parabolic tip circles, small differences; derivation in
``docs/control_design.md``): with relative depths ``z_k = offset_k - runout_k`` (um, positive =
knife k cuts less deep) and pitch ``f`` (mm), the mark of knife k is::

    width_k = f + (R / f) * 1e-3 * (z_{k-1} - 2 z_k + z_{k+1})   =  f + G * (D z)_k

``D`` is the circulant second difference (knife numbering follows the rotation, so the
neighbours of knife 0 are Z-1 and 1). A knife cutting deeper (smaller ``z_k``) makes its own
mark wider and both neighbours narrower; a constant ``z`` (the mean offset, i.e. the board
thickness) changes no width. ``D`` is singular on the constants, so the law uses its
pseudo-inverse on the zero-mean subspace::

    offsets <- P_box( offsets - gamma * D^+ (w - mean(w)) / G )

``P_box`` is the Euclidean projection onto zero mean and ``|offset| <= stroke - margin``; the
stored offsets are the projected ones, so a correction that the stroke cannot follow does not
wind up. With the exact model each learning step multiplies the width error by ``1 - gamma``;
for a true sensitivity ``alpha G`` the factor is ``1 - gamma alpha``, convergent for
``0 < gamma alpha < 2``.

A knife that left no mark (``nan``) cuts too shallow relative to its neighbours: its linearised
width is <= 0. It is taken as 0, which under-states its error (``alpha <= 1`` for that
direction) but pushes it the right way: the step lowers its offset (it cuts deeper) until the
mark reappears.

One learning step is taken only when the measured board was cut after the previous offsets took
effect (``cut_at_s >= t_change + settle_s``; without a cut time, ``now_s >= t_change +
holdoff_s``); :meth:`controller.feed_loop.FeedLoop.cut_interval_s` gives the cut time.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.feed_loop import config_from_mapping
from controller.limits import check_time_forward, project_zero_mean_box
from core.checks import check_finite, check_int, check_positive, check_range

#: Values of :attr:`UniformityLoop.status` after an update.
STATUSES = ("stepped", "waiting", "averaging", "deadband", "no_marks", "idle")


def second_difference(knives: int) -> np.ndarray:
    """Circulant second difference ``(D z)_k = z_{k-1} - 2 z_k + z_{k+1}`` (indices mod Z).

    Parameters
    ----------
    knives : int
        Number of knives ``Z`` (>= 1).

    Returns
    -------
    ndarray, shape (Z, Z)
        ``D``; for Z = 1 the zero matrix, for Z = 2 ``[[-2, 2], [2, -2]]``.
    """
    z = check_int("knives", knives, lo=1)
    d = np.zeros((z, z))
    for k in range(z):
        d[k, k] -= 2.0
        d[k, (k - 1) % z] += 1.0
        d[k, (k + 1) % z] += 1.0
    return d


def width_sensitivity_mm_per_um(pitch_mm: float, radius_mm: float) -> float:
    """``G = R / f * 1e-3``: change of a mark width (mm) per um of second difference of depth."""
    return check_positive("radius_mm", radius_mm) / check_positive("pitch_mm", pitch_mm) * 1e-3


def linear_widths_mm(
    relative_depth_um: Sequence[float], *, pitch_mm: float, radius_mm: float
) -> np.ndarray:
    """Mark width of each knife predicted by the linearised model (may be <= 0: mark vanishes).

    Parameters
    ----------
    relative_depth_um : sequence of float, shape (Z,)
        ``z_k = offset_k - runout_k``, um (positive = cuts less deep).
    pitch_mm, radius_mm : float
        Pitch ``f`` and cutting radius ``R``, mm.

    Returns
    -------
    ndarray, shape (Z,)
        ``f + G * D z``, mm.
    """
    z = np.asarray(relative_depth_um, dtype=float)
    if z.ndim != 1 or z.size < 1 or not np.all(np.isfinite(z)):
        raise ValueError("relative_depth_um must be a finite 1-D sequence")
    g = width_sensitivity_mm_per_um(pitch_mm, radius_mm)
    return pitch_mm + g * (second_difference(z.size) @ z)


@dataclass(frozen=True)
class UniformityLoopConfig:
    """Parameters of the uniformity loop (validated on construction; errors name the field).

    Attributes
    ----------
    knives : int
        Knives ``Z``.
    radius_mm : float
        Cutting radius ``R``, mm.
    stroke_um : float
        Piezo stroke: offsets stay within ``+-(stroke_um - margin_um)``, um.
    margin_um : float
        Reserve kept from the stroke for the actuator's own dynamics and hysteresis, um.
    gain : float
        Learning gain ``gamma`` in (0, 1]; 0.4 keeps >= 6 dB and 45 deg even with a
        one-step-late measurement (``controller.design``).
    sample_time_s : float
        Nominal interval between measurements, seconds (documentation of the cadence; the
        hold-off uses times, not counts).
    deadband_mm : float
        No step while every knife's width error ``|w_k - mean(w)|`` is within it, mm.
    settle_s : float
        Time for new offsets to take effect (CAN, amplifier, next revolution), seconds.
    holdoff_s : float
        Hold-off after a step when the caller gives no cut time (``cut_at_s``), seconds; should
        exceed the transport delay ``L / V_f`` plus the window.
    measurements_per_step : int
        Valid measurements averaged into one learning step (noise).
    """

    knives: int = 4
    radius_mm: float = 60.0
    stroke_um: float = 20.0
    margin_um: float = 2.0
    gain: float = 0.4
    sample_time_s: float = 0.1
    deadband_mm: float = 0.005
    settle_s: float = 0.05
    holdoff_s: float = 2.0
    measurements_per_step: int = 1

    def __post_init__(self) -> None:
        check_int("knives", self.knives, lo=1)
        check_positive("radius_mm", self.radius_mm)
        check_positive("stroke_um", self.stroke_um)
        check_range("margin_um", self.margin_um, 0.0, self.stroke_um)
        if self.margin_um >= self.stroke_um:
            raise ValueError(f"margin_um must be < stroke_um, got {self.margin_um!r}")
        check_range("gain", self.gain, 1e-6, 1.0)
        check_positive("sample_time_s", self.sample_time_s)
        check_positive("deadband_mm", self.deadband_mm, allow_zero=True)
        check_positive("settle_s", self.settle_s, allow_zero=True)
        check_positive("holdoff_s", self.holdoff_s, allow_zero=True)
        check_int("measurements_per_step", self.measurements_per_step, lo=1)

    @classmethod
    def from_mapping(
        cls, mapping: Mapping[str, Any] | None, *, prefix: str = "uniformity_loop", **overrides: Any
    ) -> UniformityLoopConfig:
        """Build from a ``[uniformity_loop]`` TOML table; ``overrides`` win."""
        return config_from_mapping(cls, mapping, prefix, **overrides)

    @property
    def offset_limit_um(self) -> float:
        """Largest magnitude of an offset, ``stroke_um - margin_um``."""
        return self.stroke_um - self.margin_um


class UniformityLoop:
    """Iterative learning of per-knife offsets from per-knife mean mark widths.

    Parameters
    ----------
    cfg : UniformityLoopConfig
        Geometry, stroke and learning gain.

    Notes
    -----
    ``offsets_um`` always has zero mean and every entry within ``cfg.offset_limit_um``.
    ``status`` tells what the last update did (one of :data:`STATUSES`).
    """

    def __init__(self, cfg: UniformityLoopConfig) -> None:
        if not isinstance(cfg, UniformityLoopConfig):
            raise ValueError(f"cfg must be a UniformityLoopConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        self._d_pinv = np.linalg.pinv(second_difference(cfg.knives))
        self.reset()

    def reset(
        self, offsets_um: Sequence[float] | None = None, *, now_s: float | None = None
    ) -> None:
        """Start again from ``offsets_um`` (projected into the stroke) or from zero.

        Parameters
        ----------
        offsets_um : sequence of float, shape (Z,), optional
            Offsets in force (e.g. learnt on the previous board), um; default zeros.
        now_s : float, optional
            When they took effect; the first learning step then waits until they are visible.
        """
        z = self.cfg.knives
        if offsets_um is None:
            start = np.zeros(z)
        else:
            start = np.asarray(offsets_um, dtype=float)
            if start.shape != (z,) or not np.all(np.isfinite(start)):
                raise ValueError(f"offsets_um must be {z} finite values, got {offsets_um!r}")
            start = project_zero_mean_box(start, bound=self.cfg.offset_limit_um)
        self._offsets = start
        self._t_change = None if now_s is None else check_finite("now_s", now_s)
        self._t_last = self._t_change
        self._acc: list[np.ndarray] = []
        self.status = "idle"
        self.steps = 0

    @property
    def offsets_um(self) -> np.ndarray:
        """Current offsets per knife, um (a copy; zero mean, inside the stroke)."""
        return self._offsets.copy()

    def update(
        self,
        *,
        knife_widths_mm: Sequence[float],
        pitch_mm: float,
        now_s: float,
        cut_at_s: float | None = None,
    ) -> np.ndarray:
        """Take one measurement; return the offsets to apply (um, one per knife).

        Parameters
        ----------
        knife_widths_mm : sequence of float, shape (Z,)
            Mean mark width of each knife in the measured window, mm; ``nan`` where the knife
            left no mark.
        pitch_mm : float
            Measured pitch (mean mark width), mm.
        now_s : float
            Current time, seconds (never decreasing).
        cut_at_s : float, optional
            When the first mark of the measured window was cut, seconds (e.g. from
            :meth:`controller.feed_loop.FeedLoop.cut_interval_s`); without it the hold-off is
            ``holdoff_s`` after the last change.

        Returns
        -------
        ndarray, shape (Z,)
            Offsets in um (a copy of :attr:`offsets_um`).
        """
        cfg = self.cfg
        t = check_time_forward(now_s, self._t_last)
        self._t_last = t
        f = check_positive("pitch_mm", pitch_mm)
        w = np.asarray(knife_widths_mm, dtype=float)
        if w.shape != (cfg.knives,):
            raise ValueError(f"knife_widths_mm must have {cfg.knives} values, got shape {w.shape}")
        if np.any(np.isinf(w)) or np.any(w[np.isfinite(w)] < 0):
            raise ValueError("knife_widths_mm must be >= 0, finite or nan")
        if cut_at_s is not None:
            check_finite("cut_at_s", cut_at_s)
        if self._t_change is not None:
            visible = (
                cut_at_s >= self._t_change + cfg.settle_s
                if cut_at_s is not None
                else t >= self._t_change + cfg.holdoff_s
            )
            if not visible:
                self.status = "waiting"
                return self.offsets_um
        if np.all(np.isnan(w)) or cfg.knives == 1:
            self.status = "no_marks"
            return self.offsets_um
        self._acc.append(np.nan_to_num(w, nan=0.0))  # a vanished mark has width 0
        if len(self._acc) < cfg.measurements_per_step:
            self.status = "averaging"
            return self.offsets_um
        w_mean = np.mean(self._acc, axis=0)
        self._acc.clear()
        err = w_mean - w_mean.mean()
        if float(np.max(np.abs(err))) <= cfg.deadband_mm:
            self.status = "deadband"
            return self.offsets_um
        step = -cfg.gain * (self._d_pinv @ err) / width_sensitivity_mm_per_um(f, cfg.radius_mm)
        new = project_zero_mean_box(self._offsets + step, bound=cfg.offset_limit_um)
        self._offsets = new
        self._t_change = t
        self.steps += 1
        self.status = "stepped"
        return self.offsets_um


def width_cv(widths_mm: Sequence[float]) -> float:
    """Coefficient of variation (population std / mean) of mark widths; nan counts as 0."""
    w = np.nan_to_num(np.asarray(widths_mm, dtype=float), nan=0.0)
    m = float(w.mean()) if w.size else math.nan
    return float(w.std() / m) if m > 0 else math.nan
