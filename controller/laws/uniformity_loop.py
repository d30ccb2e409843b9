"""The uniformity loop: learn per-knife piezo offsets that make every knife cut the same mark.

Pure and clock-injected. Width model (parabolic tip circles, small differences; derivation in
``docs/control_design.md``): with relative depths ``z_k = a_k - runout_k`` (um, positive = knife
k cuts less deep; ``a = A o`` the actuator's effective response to the offset table ``o``) and
pitch ``f`` (mm), the mark of knife k is::

    width_k = f + (R / f) * 1e-3 * (z_{k-1} - 2 z_k + z_{k+1})   =  f + G * (D z)_k

``D`` is the circulant second difference (knife numbering follows the rotation, so the
neighbours of knife 0 are Z-1 and 1). A knife cutting deeper (smaller ``z_k``) makes its own
mark wider and both neighbours narrower; a constant ``z`` (the mean offset, i.e. the board
thickness) changes no width.

Law: a learning update on every image pair against the surface the loop predicts (the Smith
predictor form, as the feed loop's). The measured board was cut ``L / V`` seconds ago with the
table in force then, ``o_cut`` (:class:`controller.laws.offset_history.OffsetHistory`, cut times
from :meth:`controller.laws.feed_loop.FeedLoop.cut_interval_s`), so each pair is a direct estimate
of
the runout as the loop sees it::

    y     = D^+ (w - mean(w)) / G              width errors in um of offset (= A o_cut - s)
    s_est = A_hat o_cut - y                    the runout; no integrator, nothing to wind up
    o*    = argmin_{sum o = 0, |o| <= b} || D (A_hat o - s_est) ||      (controller.laws.offset_qp)
    o    += g (o* - o),   g = ki Ts / (T_delay + Ts)

Before any table the loop sent shows at the camera every pair is an open-loop estimate of the
same runout: those are averaged (``g = 1 / n``, the first one taken whole), so the first table
goes out with the first pair and the measured board follows one transport delay later.

``A_hat`` is the actuator's effective gain per knife mode, identified online from the same pairs
(:class:`controller.laws.actuator_id.ActuatorIdentifier`: a slow or hysteretic piezo). With an exact
model each pair moves the offsets a fraction ``g`` of the way to the constrained optimum and the
measured board follows one transport delay later; for a true/model gain ratio ``alpha`` per mode
the loop is the feed loop's ``C = g / (z - 1 + g - g z^-d)`` around ``alpha z^-d``: the margins
are the same at every feed (``controller.laws.design``). The stored offsets are always a convex
combination of feasible tables: zero mean, inside the stroke, no windup.

A hysteretic stack is not linear: a small cycle moves the cut by a few per cent of the table, a
full-stroke one by most of it (hysteresis 0.35: 0.05 for a 1 um cycle, 0.4-0.7 at 15 um). When
the identification finds a pattern's gain growing with the amplitude at which it was measured
(``ActuatorIdentifier.amplitude_slope``, a describing function affine in the amplitude), each
step is planned twice: with the gains at the measured table's amplitudes, then with the gains
at the middle of that step (the secant of the response over it), so that a gain learnt on
small moves does not throw the table far past the one the plant needs (``id_amplitude``).

Never worse than doing nothing. The identification covers the whole phase circle (a resonance
below the knife passing frequency turns a knife pattern around) with a confidence per pattern;
a pattern the actuator cannot move (gain confidently below ``gain_min``, or large moves that
moved nothing) is held at zero, said once (:meth:`UniformityLoop.take_notices`), and the others
are learnt; when no pattern can be moved the loop holds. With a pattern held a step is taken
only as far as it does not raise the model's spread (:meth:`UniformityLoop.model_spread_um`).
Whatever the model says, :class:`controller.laws.uniformity_guard.TableGuard` judges the tables
by the measured boards: a learning step that made them worse is undone (back to the best table
measured, status ``undone``), and after ``guard_max_undos`` undos that held the loop keeps the
best table (status ``holding``, :attr:`UniformityLoop.hold_reason`). A recovery after the safe
state restores that table when the last one was worse
(:meth:`UniformityLoop.recovery_table_um`). Design and measured
figures: ``docs/control_design.md``, section 8.

A knife that left no mark (width 0, or ``nan`` for a knife without a pass in the window) is taken
as width 0, which under-states its error but pushes it the right way. Such pairs do not enter
the identification, nor do pairs with a mark narrower than ``id_min_width_frac`` of the pitch:
the width model is linear only while every mark exists (a vanished mark's width is clipped at 0,
so the knife patterns look about half as responsive as they are: at pitch 0.5 mm the
alternating pattern of a 0.93 actuator was learnt at 0.42-0.63 from the first steps), and a
nearly vanished mark is measured short (0.05-0.13 mm short at 0.1-0.3 of a 0.5 mm pitch).
Their neighbours meet half way across the vanished knife, so the estimate errs along that knife
alone and under-states how far it must come back: the step along it is taken whole
(``vanished_step``, :func:`bring_back`). Such pairs never set the guard's best
table (their clipped score is not comparable). A pair whose widths moved from the last pair
taken by more than the table's change can make (merged marks, marks on the wrong knives) is
kept out of the loop, the identification and the guard (status ``unexplained``,
``change_tol_frac``; :class:`controller.laws.change_screen.ChangeScreen`).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.laws.actuator_id import ActuatorIdentifier, circulant_from_mode_gains
from controller.laws.change_screen import ChangeScreen
from controller.laws.feed_loop import config_from_mapping, integral_gain
from controller.laws.limits import check_time_forward, project_zero_mean_box
from controller.laws.offset_history import OffsetHistory
from controller.laws.offset_qp import OffsetPlanner, best_offsets_um
from controller.laws.plain_floats import numpy_sum
from controller.laws.uniformity_guard import TableGuard, Verdict
from controller.laws.uniformity_status import AuthorityNotice, authority_notice, describe_loop
from core.checks import check_finite, check_int, check_positive, check_range

#: Values of :attr:`UniformityLoop.status` after an update.
STATUSES = ("stepped", "waiting", "no_marks", "idle", "undone", "holding", "unexplained")

DEFAULT_MARGIN_UM = 0.01
"""Default reserve from the stroke, um: ten steps of the CAN codec (1 nm, rounded to the nearest
step, so a sent offset may exceed the planned one by 0.5 nm). The simulated amplifier refuses an
offset beyond its stroke and raises the stroke-limit bit when the displacement reaches it (at
exactly the table's value without hysteresis); with the matched input shaper the displacement
of a zero-mean table never exceeds the table, and hysteresis only takes some off."""

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
        Piezo stroke at start: offsets stay within ``+-(stroke_um - margin_um)``, um (the
        amplifier's own stroke replaces it at run time: :meth:`UniformityLoop.set_limit_um`).
    margin_um : float
        Reserve kept from the stroke, um (at most half the stroke is kept back). The default,
        :data:`DEFAULT_MARGIN_UM`, covers the CAN codec's rounding only: the amplifier accepts
        offsets within its stroke (1 nm steps) and the displacement of a zero-mean table stays
        within the table (``docs/control_design.md``, "The stroke"); a stack that overshoots
        needs a larger one.
    ki : float
        Learning gain per loop delay (the per-pair gain is ``ki Ts / (T_delay + Ts)``); 2.0
        keeps >= 7 dB and >= 62 deg at every feed and camera distance (``controller.laws.design``).
    sample_time_s : float
        Nominal interval between measurements, seconds.
    settle_s : float
        Time for a new table to take effect at the cutter (CAN, amplifier, next revolution), s.
    holdoff_s : float
        Without cut times (``cut_at_s``) a table counts as visible this long after it was sent,
        seconds; should exceed the transport delay ``L / V_f`` plus the window.
    history_s : float
        How far back the table history reaches (longest transport delay plus the window), s.
    identify : bool
        Identify the actuator's gain per knife mode online (else it is taken as ideal).
    id_lag_pairs, id_min_step_um, id_memory, id_prior_um2, gain_min, gain_max
        The identification's parameters (:class:`controller.laws.actuator_id.ActuatorIdentifier`);
        a knife pattern whose gain is confidently below ``gain_min`` is held (the actuator
        cannot move it).
    id_min_width_frac : float
        A pair enters the identification only when every knife's mark is at least this fraction
        of the pitch wide (a vanished or nearly vanished mark is outside the linear width model
        and under-states the actuator's gain); 0 takes every pair whose marks all exist.
    change_tol_frac : float
        A pair whose widths moved from the last pair the loop took by more than the change of
        the table at the cut can make (``4 gain_max |o - o_prev|`` um of relative depth, ``4``
        the largest eigenvalue of ``D``) plus this fraction of the pitch (``change_tol_frac f``
        mm of width, ``f / G`` um) is kept out of the loop, of the identification and of the
        guard (status ``unexplained``): its marks were given to the wrong knives or measured
        wrong (at pitch 0.5 mm a merged mark read ``[2.0, 0, 0, 0]`` between pairs reading
        ``[0.47, 0.77, 0, 0.76]``). 0 switches the check off.
    change_patience : int
        Unexplained pairs in a row after which the next is taken as the new reference (the
        world changed: a knife, the wood), and taken.
    vanished_step : bool
        Take the step along a vanished knife's own width whole (:func:`bring_back`): its
        estimate is censored and under-states the move, so the scheduled
        gain would crawl out of the vanished region (40 pairs at pitch 0.5 mm).
    id_amplitude : bool
        Plan with each pattern's gain taken at the table's amplitude when the identification
        finds that the gain depends on it (a hysteretic stack: ``ActuatorIdentifier.
        amplitude_slope``): a step is planned with the gains at its middle amplitude, the
        secant of the actuator's response over the step.
    guard : bool
        Watch the measured result of the learning (:class:`controller.laws.uniformity_guard.
        TableGuard`): undo a step that made the board worse, hold the best table.
    guard_window, guard_rel_tol, guard_abs_tol_um, guard_patience, guard_max_undos
        The guard's parameters.
    """

    knives: int = 4
    radius_mm: float = 60.0
    stroke_um: float = 20.0
    margin_um: float = DEFAULT_MARGIN_UM
    ki: float = 2.0
    sample_time_s: float = 0.1
    settle_s: float = 0.05
    holdoff_s: float = 2.0
    history_s: float = 120.0
    identify: bool = True
    id_lag_pairs: int = 5
    id_min_step_um: float = 0.5
    id_memory: float = 200.0
    id_prior_um2: float = 1.0
    id_min_width_frac: float = 0.25
    change_tol_frac: float = 0.3
    change_patience: int = 3
    vanished_step: bool = True
    id_amplitude: bool = True
    gain_min: float = 0.1
    gain_max: float = 2.0
    guard: bool = True
    guard_window: int = 3
    guard_rel_tol: float = 0.2
    guard_abs_tol_um: float = 0.3
    guard_patience: int = 3
    guard_max_undos: int = 3

    def __post_init__(self) -> None:
        check_int("knives", self.knives, lo=1)
        check_positive("radius_mm", self.radius_mm)
        check_positive("stroke_um", self.stroke_um)
        check_range("margin_um", self.margin_um, 0.0, self.stroke_um)
        if self.margin_um >= self.stroke_um:
            raise ValueError(f"margin_um must be < stroke_um, got {self.margin_um!r}")
        check_range("ki", self.ki, 1e-6, 3.0)
        check_positive("sample_time_s", self.sample_time_s)
        check_positive("settle_s", self.settle_s, allow_zero=True)
        check_positive("holdoff_s", self.holdoff_s, allow_zero=True)
        check_positive("history_s", self.history_s)
        if not isinstance(self.identify, bool):
            raise ValueError(f"identify must be true or false, got {self.identify!r}")
        if not isinstance(self.id_amplitude, bool):
            raise ValueError(f"id_amplitude must be true or false, got {self.id_amplitude!r}")
        check_int("id_lag_pairs", self.id_lag_pairs, lo=1)
        check_positive("id_min_step_um", self.id_min_step_um)
        check_range("id_memory", self.id_memory, 1.0, 1e9)
        check_positive("id_prior_um2", self.id_prior_um2)
        check_range("id_min_width_frac", self.id_min_width_frac, 0.0, 1.0)
        check_range("change_tol_frac", self.change_tol_frac, 0.0, 10.0)
        check_int("change_patience", self.change_patience, lo=1)
        if not isinstance(self.vanished_step, bool):
            raise ValueError(f"vanished_step must be true or false, got {self.vanished_step!r}")
        check_range("gain_min", self.gain_min, 1e-3, 1.0)
        check_range("gain_max", self.gain_max, 1.0, 100.0)
        if not isinstance(self.guard, bool):
            raise ValueError(f"guard must be true or false, got {self.guard!r}")
        check_int("guard_window", self.guard_window, lo=1)
        check_range("guard_rel_tol", self.guard_rel_tol, 0.0, 10.0)
        check_range("guard_abs_tol_um", self.guard_abs_tol_um, 0.0, 100.0)
        check_int("guard_patience", self.guard_patience, lo=1)
        check_int("guard_max_undos", self.guard_max_undos, lo=1)

    @classmethod
    def from_mapping(
        cls, mapping: Mapping[str, Any] | None, *, prefix: str = "uniformity_loop", **overrides: Any
    ) -> UniformityLoopConfig:
        """Build from a ``[uniformity_loop]`` TOML table; ``overrides`` win."""
        return config_from_mapping(cls, mapping, prefix, **overrides)

    @property
    def offset_limit_um(self) -> float:
        """Largest magnitude of an offset at the configured stroke, um."""
        return offset_limit_um(self.stroke_um, self.margin_um)


def offset_limit_um(stroke_um: float, margin_um: float) -> float:
    """``stroke - margin``, but never less than half the stroke (a small amplifier), um."""
    return max(stroke_um - margin_um, 0.5 * stroke_um)


class UniformityLoop:
    """Delay-aware learning of per-knife offsets from per-knife mean mark widths.

    Parameters
    ----------
    cfg : UniformityLoopConfig
        Geometry, stroke and learning gain.

    Notes
    -----
    ``offsets_um`` always has zero mean and every entry within :attr:`limit_um`. ``status``
    tells what the last update did (one of :data:`STATUSES`). A learning step never raises
    the model's width spread (:meth:`model_spread_um`); what the camera measures of its
    effect is judged by the guard (:class:`controller.laws.uniformity_guard.TableGuard`).
    """

    def __init__(self, cfg: UniformityLoopConfig) -> None:
        if not isinstance(cfg, UniformityLoopConfig):
            raise ValueError(f"cfg must be a UniformityLoopConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        z = cfg.knives
        self._d = second_difference(z)
        self._d_pinv = np.linalg.pinv(self._d)
        self._d_pinv_rows = _rows(self._d_pinv)
        self._plan: tuple[tuple, OffsetPlanner, tuple[tuple[float, ...], ...]] | None = None
        self._a_plan: np.ndarray | None = None  # the matrix planned with, when not the model's
        self._stroke = cfg.stroke_um
        self._ident = ActuatorIdentifier(
            z,
            lag_pairs=cfg.id_lag_pairs,
            min_step_um=cfg.id_min_step_um,
            memory=cfg.id_memory,
            prior_um2=cfg.id_prior_um2,
            gain_min=cfg.gain_min,
            gain_max=cfg.gain_max,
        )
        self._guard = TableGuard(
            z, window=cfg.guard_window, rel_tol=cfg.guard_rel_tol,
            abs_tol_um=cfg.guard_abs_tol_um, patience=cfg.guard_patience,
            max_undos=cfg.guard_max_undos,
        )
        self._history = OffsetHistory(z, horizon_s=cfg.history_s)
        self._screen = ChangeScreen(gain_max=cfg.gain_max, tol_frac=cfg.change_tol_frac,
                                    patience=cfg.change_patience)
        self._disturbance: np.ndarray | None = None
        self._estimate: np.ndarray | None = None
        self._estimates = 0  # open-loop estimates (board cut with the starting table)
        self._open_table: list[float] | None = [0.0] * z
        self._held: frozenset[int] = frozenset()  # modes the actuator cannot move
        self._notices: list[AuthorityNotice] = []
        self._told: set[tuple] = set()
        self.reset()

    # -- state ------------------------------------------------------------------------------
    def reset(
        self,
        offsets_um: Sequence[float] | None = None,
        *,
        now_s: float | None = None,
        forget: bool = False,
    ) -> None:
        """Start again from ``offsets_um`` (projected into the stroke) or from zero.

        Parameters
        ----------
        offsets_um : sequence of float, shape (Z,), optional
            Offsets in force (e.g. learnt on the previous board), um; default zeros.
        now_s : float, optional
            When they took effect: board cut before then (plus ``settle_s``) is not learnt from.
            Without it they count as always in force.
        forget : bool
            Also forget the runout estimate, the identified actuator gains, the best table and
            what the loop said of the actuator (a new machine).
        """
        z = self.cfg.knives
        if offsets_um is None:
            start = np.zeros(z)
        else:
            start = np.asarray(offsets_um, dtype=float)
            if start.shape != (z,) or not np.all(np.isfinite(start)):
                raise ValueError(f"offsets_um must be {z} finite values, got {offsets_um!r}")
            start = project_zero_mean_box(start, bound=self.limit_um)
        t = -math.inf if now_s is None else check_finite("now_s", now_s)
        self._offsets = start
        self._history.restart(start, t)
        self._t_last = None if now_s is None else t
        self._undo: tuple[np.ndarray, bool, np.ndarray | None] | None = None
        self._reverted_at: float | None = None  # the guard's undo: waiting for its boards
        self._screen.reset()
        self._guard.reset(forget=forget)
        if forget:
            self._disturbance = None
            self._estimate = None
            self._estimates = 0
            self._open_table = start.tolist()
            self._ident.reset()
            self._held = frozenset()
            self._told = set()
            self._notices = []
        self.status = "idle"
        self.steps = 0
        self.last_gain = 0.0

    @property
    def unexplained(self) -> int:
        """Pairs kept out as unexplained since the last reset (:class:`ChangeScreen`)."""
        return self._screen.unexplained

    @property
    def offsets_um(self) -> np.ndarray:
        """Current offsets per knife, um (a copy; zero mean, inside the limit)."""
        return self._offsets.copy()

    @property
    def stroke_um(self) -> float:
        """The stroke the loop plans within (configured, or the amplifier's), um."""
        return self._stroke

    @property
    def limit_um(self) -> float:
        """Largest magnitude of an offset, um (the stroke less the margin)."""
        return offset_limit_um(self._stroke, self.cfg.margin_um)

    @property
    def mode_gains(self) -> np.ndarray:
        """Identified effective actuator gain per Fourier mode of the knives (complex, (Z,))."""
        return self._ident.mode_gains

    @property
    def identifier(self) -> ActuatorIdentifier:
        """The actuator's identification (its gains, confidence and mode states)."""
        return self._ident

    @property
    def guard(self) -> TableGuard:
        """The watch over the measured result (best table, undos)."""
        return self._guard

    @property
    def held_modes(self) -> frozenset[int]:
        """Knife patterns (Fourier modes ``1..Z-1``) held: the actuator cannot move them."""
        return self._held

    @property
    def holding(self) -> bool:
        """Whether the loop holds the best table and learns no more (see :attr:`hold_reason`)."""
        return self.hold_reason is not None

    @property
    def hold_reason(self) -> str | None:
        """Why the loop holds its best table, or ``None`` while it learns.

        ``made_worse`` (undone too often), ``no_authority`` (no knife pattern the actuator can
        move).
        """
        if self.cfg.guard and self._guard.holding:
            return "made_worse"
        if self.cfg.knives > 1 and len(self._held) >= self.cfg.knives - 1:
            return "no_authority"
        return None

    @property
    def runout_estimate_um(self) -> np.ndarray | None:
        """The runout as the loop sees it (zero mean, um), ``None`` before a measurement."""
        return None if self._disturbance is None else self._disturbance.copy()

    def recovery_table_um(self, fallback_um: Sequence[float] | None = None) -> np.ndarray:
        """The table to restore after a safe state, within the limit.

        The last one (``fallback_um``, e.g. the last one sent; default the offsets in force)
        unless the guard found the boards cut lately worse than its best, or holds: then the
        best table measured.
        """
        best = (self._guard.best_table_um
                if self.cfg.guard and self._guard.worse_than_best() else None)
        if best is None:
            best = self.offsets_um if fallback_um is None else np.asarray(fallback_um, float)
        if self._held:
            best = best - _mode_projector(self.cfg.knives, self._held) @ best
        return project_zero_mean_box(best - best.mean(), bound=self.limit_um)

    def take_notices(self) -> list[AuthorityNotice]:
        """What the loop has to say of the actuator since the last call (each thing once)."""
        out, self._notices = self._notices, []
        return out

    def describe(self) -> dict[str, Any]:
        """Plain JSON of what the loop knows and does (the status snapshot's ``uniformity``)."""
        return describe_loop(self)

    def set_limit_um(self, stroke_um: float, *, now_s: float | None = None) -> np.ndarray:
        """Plan within a new stroke from now on (e.g. the amplifier's, read over CAN).

        The offsets in force are re-planned at once when they lie outside the new limit: the
        best table within it for the runout estimate (or, before any measurement, the one whose
        widths come nearest to the present table's). A larger stroke is used by the next
        learning steps.

        Parameters
        ----------
        stroke_um : float
            The stroke, um (> 0); the loop keeps ``margin_um`` of it (at most half).
        now_s : float, optional
            When a re-planned table goes out (default: the last update's time).

        Returns
        -------
        ndarray, shape (Z,)
            The offsets to apply, um (unchanged when they fit).
        """
        self._stroke = check_positive("stroke_um", stroke_um)
        self._undo = None  # a table from before the change is never taken back
        bound = self.limit_um
        if np.max(np.abs(self._offsets)) <= bound + 1e-12:
            return self.offsets_um
        a_hat = self._ident.matrix()
        target = self._disturbance if self._disturbance is not None else a_hat @ self._offsets
        new = project_zero_mean_box(
            best_offsets_um(target, width_operator=self._d, actuator=a_hat, bound_um=bound),
            bound=bound,
        )
        t = now_s if now_s is not None else self._t_last
        self._set(new, -math.inf if t is None else check_finite("now_s", t))
        self._undo = None
        self._guard.reset()
        return self.offsets_um

    def reject(self) -> np.ndarray:
        """The offsets the last update returned never reached the amplifier.

        They leave the history (the board is cut with the table really in force) and
        :attr:`offsets_um` goes back to that table. What the update learnt stays. After
        :meth:`set_limit_um` nothing is taken back (the old table may not fit the new stroke).

        Returns
        -------
        ndarray, shape (Z,)
            The offsets in force, um.
        """
        if self._undo is not None:
            prev, appended, replaced = self._undo
            self._undo = None
            if appended or replaced is not None:
                self._history.pop(replaced)
            self._offsets = prev
        return self.offsets_um

    def _set(self, new: np.ndarray, t: float) -> None:
        prev = self._offsets
        self._offsets = new
        appended, replaced = False, None
        if new.tolist() != prev.tolist():  # (np.array_equal: same shape, finite values)
            if math.isfinite(t):  # never before the newest entry (a re-plan stamped ahead)
                n0 = len(self._history)
                replaced = self._history.append(new, max(t, self._history.last_change_s))
                appended = len(self._history) > n0
            else:
                self._history.restart(new)
        self._undo = (prev, appended, replaced)

    # -- the law ----------------------------------------------------------------------------
    def update(
        self,
        *,
        knife_widths_mm: Sequence[float],
        pitch_mm: float,
        now_s: float,
        cut_at_s: float | None = None,
        cut_until_s: float | None = None,
    ) -> np.ndarray:
        """Take one measurement; return the offsets to apply (um, one per knife).

        Parameters
        ----------
        knife_widths_mm : sequence of float, shape (Z,)
            Mean mark width of each knife in the measured window, mm; ``nan`` where the knife
            left no mark.
        pitch_mm : float
            Measured travel per knife pass, mm.
        now_s : float
            Current time, seconds (never decreasing).
        cut_at_s, cut_until_s : float, optional
            When the first and the last mark of the measured window were cut, seconds (from
            :meth:`controller.laws.feed_loop.FeedLoop.cut_interval_s`); ``cut_until_s`` defaults to
            ``cut_at_s``. Without them the table in force counts as the measured board's once
            it has been in force for ``holdoff_s``.

        Returns
        -------
        ndarray, shape (Z,)
            Offsets in um (a copy of :attr:`offsets_um`).
        """
        cfg = self.cfg
        t = check_time_forward(now_s, self._t_last)
        self._t_last = t
        f = check_positive("pitch_mm", pitch_mm)
        ws = _checked_widths(knife_widths_mm, cfg.knives, cut_at_s, cut_until_s)
        self._undo = None
        self.last_gain = 0.0
        if all(math.isnan(v) for v in ws) or cfg.knives == 1:
            self.status = "no_marks"
            return self.offsets_um
        if cut_at_s is not None:
            t0 = cut_at_s - cfg.settle_s
            t1 = (cut_at_s if cut_until_s is None else cut_until_s) - cfg.settle_s
            o_cut = self._history.mean_over(t0, t1)
            delay_s = t - 0.5 * (t0 + t1)
        elif t >= self._history.last_change_s + cfg.holdoff_s:
            o_cut, delay_s, t0 = self._history.latest(), cfg.holdoff_s, t - cfg.holdoff_s
        else:
            o_cut, delay_s, t0 = None, 0.0, -math.inf
        if o_cut is None:
            self.status = "waiting"
            return self.offsets_um
        o_c = o_cut.tolist()
        err = [0.0 if math.isnan(v) else v for v in ws]  # a vanished mark has width 0
        err_mean = _mean(err)
        err = [v - err_mean for v in err]
        gain_g = width_sensitivity_mm_per_um(f, cfg.radius_mm)
        if self._screen.unexplained_pair(o_c, [v / gain_g for v in err], f,
                                         cfg.change_tol_frac * f / gain_g):
            self.status = "unexplained"
            return self.offsets_um
        y = [v / gain_g for v in _matvec(self._d_pinv_rows, err)]
        if cfg.identify and self._identifiable(ws, f):  # (the guard's "comparable" too)
            self._ident.add(o_c, y)
            self._review_modes(t)
        elif cfg.identify:
            self._ident.interrupt()  # outside the linear model: no difference across it
        planner, a_rows = self._planner()
        amps = None
        if cfg.identify and cfg.id_amplitude and self._ident.amplitude_dependent():
            # a gain that grows with the amplitude (hysteresis): the gains where the table is
            amps = self._ident.mode_amplitudes(o_c)
            planner, a_rows = self._planner(self._ident.gains_at(amps))
        s_est = _runout_estimate(a_rows, o_c, y)
        g = min(integral_gain(cfg.ki, cfg.sample_time_s, delay_s), 1.0)
        if self._open_table is not None and _allclose(o_c, self._open_table):
            # board cut with the table the loop started from: open-loop estimates of the same
            # runout, so the first one is taken whole and the next ones averaged in
            g = max(g, 1.0 / (self._estimates + 1))
            self._estimates += 1
        else:
            self._open_table = None  # the loop's own tables show: the scheduled gain from now
        self._estimate = np.array(s_est)  # what this pair's step plans against
        prev = s_est if self._disturbance is None else self._disturbance.tolist()
        self._disturbance = np.array([p + g * (v - p) for p, v in zip(prev, s_est, strict=True)])
        seen = self._identifiable(ws, f)
        if self._judge(o_c, math.sqrt(sum(v * v for v in err) / len(err)) / gain_g, t, t0,
                       comparable=seen):
            return self.offsets_um
        bound = self.limit_um
        hold = self._hold_table() if self._held else None
        best_a = planner.best_offsets_um(s_est, bound_um=bound, start_um=self._offsets,
                                         hold_um=hold)
        if amps is not None:  # the secant over the step: the gains at its middle amplitude
            mid = 0.5 * (amps + self._ident.mode_amplitudes(best_a))
            planner, a_rows = self._planner(self._ident.gains_at(mid))
            s_est = _runout_estimate(a_rows, o_c, y)
            self._estimate = np.array(s_est)
            best_a = planner.best_offsets_um(s_est, bound_um=bound, start_um=self._offsets,
                                             hold_um=hold)
        if hold is not None:  # the penalty holds nearly: the held patterns exactly where held
            p = _mode_projector(cfg.knives, self._held)
            best_a = project_zero_mean_box(best_a - p @ best_a + p @ hold, bound=bound)
        best = best_a.tolist()
        now = self._offsets.tolist()
        new = _zero_mean_in_box([o + g * (b - o) for o, b in zip(now, best, strict=True)], bound)
        if cfg.vanished_step and not self._held and not all(v > 0.0 for v in ws):
            new = bring_back(new, best_a, ws, self._d @ np.array(a_rows), bound)
        if self._held:  # the hold's penalty only nearly holds: never a step the model regrets
            new, g = _monotone_step(self._offsets, new, g, self.model_spread_um)
        self._set(new, t)
        self.last_gain = g
        self.steps += 1
        self.status = "stepped"
        return self.offsets_um

    def _identifiable(self, widths_mm: list[float], pitch_mm: float) -> bool:
        """Whether a pair's marks are all inside the linear width model (wide enough to learn from).

        A vanished mark (width 0, or ``nan``) clips the width response and a nearly vanished one
        is measured short: differences across such pairs read the actuator's gain low.
        """
        floor = self.cfg.id_min_width_frac * pitch_mm
        return all(v > 0.0 and v >= floor for v in widths_mm)  # (nan compares false)

    def _judge(self, o_cut: list[float], score_um: float, t: float, t0: float, *,
               comparable: bool = True) -> bool:
        """The guard's word on one pair; whether the update ends here (waiting, undone, held)."""
        if not self.cfg.guard and not self.holding:
            return False
        if self._reverted_at is not None:
            if t0 < self._reverted_at:  # board cut before the undo showed: not judged
                self.status = "waiting"
                return True
            self._reverted_at = None
        verdict = (self._guard.observe(o_cut, score_um, comparable=comparable)
                   if self.cfg.guard else Verdict.KEEP)
        if verdict is Verdict.UNDO or (verdict is Verdict.HOLD or self.holding):
            if verdict is Verdict.UNDO:
                self._guard.reverted()
                self._reverted_at = t + self.cfg.settle_s
            self._to_best(t)
            self.status = "undone" if verdict is Verdict.UNDO else "holding"
            if self.holding:
                self._tell(t)
            return True
        return False

    def _to_best(self, t: float) -> None:
        """Go back to the best table measured (zero before one)."""
        best = self._guard.best_table_um
        if best is None:
            best = np.zeros(self.cfg.knives)
        if self._held:  # without the patterns the actuator cannot move
            best = best - _mode_projector(self.cfg.knives, self._held) @ best
        new = project_zero_mean_box(best - best.mean(), bound=self.limit_um)
        if new.tolist() != self._offsets.tolist():
            self._set(new, t)

    def _review_modes(self, t: float) -> None:
        """Hold the knife patterns the actuator cannot move (at zero)."""
        states = self._ident.mode_states()
        held = frozenset(m for m, st in enumerate(states)
                         if m > 0 and st in ("no_authority", "unidentifiable"))
        if held == self._held:
            return
        new_modes = held - self._held
        self._held = held
        if new_modes and not self.holding:
            # the held patterns go to zero at once; the others stay
            hold = self._hold_table()
            p = _mode_projector(self.cfg.knives, held)
            table = self._offsets - p @ self._offsets + p @ hold
            new = project_zero_mean_box(table - table.mean(), bound=self.limit_um)
            if new.tolist() != self._offsets.tolist():
                self._set(new, t)
        if new_modes:
            self._tell(t)

    def _hold_table(self) -> np.ndarray:
        """Where the held patterns are kept: zero (moving them would only heat the amplifier)."""
        return np.zeros(self.cfg.knives)

    def _tell(self, t: float) -> None:
        """Say once what the actuator cannot do (a new held pattern, or the hold)."""
        key = (self.hold_reason, tuple(sorted(self._held)))
        if key in self._told:
            return
        self._told.add(key)
        self._notices.append(authority_notice(self, t))

    def model_spread_um(self, offsets_um: Sequence[float]) -> float:
        """The model's width spread of a table, ``|| D (A_hat o - s_est) ||``, um.

        ``s_est`` the last pair's estimate of the runout (what its step planned against); 0
        before a measurement. The model CV is this times ``G / (f sqrt(Z))``.
        """
        if self._estimate is None:
            return 0.0
        a_hat = self._a_plan if self._a_plan is not None else self._ident.shared_matrix()
        z = a_hat @ np.asarray(offsets_um, float) - self._estimate
        return float(np.linalg.norm(self._d @ z))

    def _planner(
        self, gains: np.ndarray | None = None
    ) -> tuple[OffsetPlanner, tuple[tuple[float, ...], ...]]:
        """The QP set up for the identified actuator, and its matrix by rows (once per estimate).

        ``gains``: plan with these mode gains instead (the identified ones taken at the
        table's amplitudes, :meth:`controller.laws.actuator_id.ActuatorIdentifier.gains_at`).
        """
        ident = self._ident
        key = (ident.version, self._held, None if gains is None else tuple(gains.tolist()))
        if self._plan is None or self._plan[0] != key:
            a_hat = ident.shared_matrix() if gains is None else circulant_from_mode_gains(gains)
            hold = _mode_projector(self.cfg.knives, self._held) if self._held else None
            planner = OffsetPlanner(width_operator=self._d, actuator=a_hat, hold=hold)
            self._plan = (key, planner, _rows(a_hat))
            self._a_plan = None if gains is None else a_hat
        return self._plan[1], self._plan[2]

    def predicted_widths_mm(self, pitch_mm: float) -> np.ndarray | None:
        """Widths the offsets in force will cut by the loop's model (``None`` before a pair)."""
        if self._disturbance is None:
            return None
        z = self._ident.matrix() @ self._offsets - self._disturbance
        return linear_widths_mm(z, pitch_mm=pitch_mm, radius_mm=self.cfg.radius_mm)


def bring_back(new: np.ndarray, target: np.ndarray, widths_mm: list[float], da: np.ndarray,
               bound: float) -> np.ndarray:
    """The step toward ``target`` along each vanished knife's own width, taken whole.

    A vanished mark's width is censored: its linear width ``w_k`` is some value <= 0, read
    as 0. For parabolic tip circles the neighbours then meet half way between where they
    would meet knife k, so they measure ``w_{k+-1} + w_k / 2``: the estimate's error lies
    along knife k's relative depth alone and under-states how far knife k must come back.
    The planned table's width of knife k is thus at most what knife k needs, and moving
    the table there at once cannot overshoot it (the other knives keep the scheduled gain).
    Per vanished knife (``width <= 0`` or ``nan``), when the rest of the step toward
    ``target`` widens its mark, the table moves along ``(D A)_k`` (the least move that
    changes its width by that much) until its modelled width is ``target``'s. ``da`` is ``D A``,
    the second difference of the planned response (shape (Z, Z)).
    """
    gone = [k for k, v in enumerate(widths_mm) if not v > 0.0]
    if not gone:
        return new
    out = new
    for k in gone:
        v = da[k]
        c = float((target - out) @ v) / float(v @ v)
        if c > 0.0:  # (the estimate pushes a vanished knife back, never further away)
            out = out + c * v
    return project_zero_mean_box(out - out.mean(), bound=bound)


def _mode_projector(knives: int, modes: frozenset[int]) -> np.ndarray:
    """The real projector onto the Fourier modes ``modes`` of the knives (and their conjugates)."""
    mask = np.zeros(knives, complex)
    for m in modes:
        mask[m] = mask[(knives - m) % knives] = 1.0
    return circulant_from_mode_gains(mask)


def _monotone_step(
    old: np.ndarray, new: np.ndarray, g: float, spread: Callable[[np.ndarray], float]
) -> tuple[np.ndarray, float]:
    """``new``, or the largest of its halved steps from ``old`` that does not raise ``spread``.

    Both tables are feasible, so every point between is (the set is convex). Returns the table
    and its gain (0 and ``old`` when every halving raises the spread).
    """
    before = spread(old)
    tol = 1e-9 * max(1.0, before)
    frac = 1.0
    for _ in range(6):
        cand = new if frac == 1.0 else old + frac * (new - old)
        if spread(cand) <= before + tol:
            return cand, g * frac
        frac *= 0.5
    return old.copy(), 0.0


def _runout_estimate(a_rows: tuple[tuple[float, ...], ...], o_cut: list[float],
                     y: list[float]) -> list[float]:
    """``A_hat o_cut - y`` less its mean: the runout as the model sees it, um."""
    s_est = [v - e for v, e in zip(_matvec(a_rows, o_cut), y, strict=True)]
    s_mean = _mean(s_est)
    return [v - s_mean for v in s_est]


def _checked_widths(knife_widths_mm: Sequence[float], knives: int, cut_at_s: float | None,
                    cut_until_s: float | None) -> list[float]:
    """:meth:`UniformityLoop.update`'s inputs checked; the widths as plain floats.

    Plain floats from here: Z is small, numpy calls cost more than they do.
    """
    w = np.asarray(knife_widths_mm, dtype=float)
    if w.shape != (knives,):
        raise ValueError(f"knife_widths_mm must have {knives} values, got shape {w.shape}")
    ws = w.tolist()
    if any(math.isinf(v) or v < 0 for v in ws):  # (nan < 0 is false)
        raise ValueError("knife_widths_mm must be >= 0, finite or nan")
    if cut_at_s is not None:
        check_finite("cut_at_s", cut_at_s)
    if cut_until_s is not None:
        check_finite("cut_until_s", cut_until_s)
    return ws


def _zero_mean_in_box(values: list[float], bound: float) -> np.ndarray:
    """``project_zero_mean_box(np.array(values), bound=bound)``, its common case in plain floats.

    A table whose shift to zero mean lies inside the box is that shift (the projection's own
    first test); the mean is numpy's (:func:`~controller.laws.plain_floats.numpy_sum`), so the
    result is the projection's bit for bit. Otherwise (or for values that are not finite) the
    projection itself.
    """
    n = len(values)
    if n and bound > 0 and all(map(math.isfinite, values)):
        m = numpy_sum(values) / n
        shifted = [v - m for v in values]
        if max(map(abs, shifted)) <= bound:
            return np.array(shifted)
    return project_zero_mean_box(np.array(values), bound=bound)


def _rows(matrix: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in matrix)


def _matvec(rows: tuple[tuple[float, ...], ...], v: list[float]) -> list[float]:
    return [sum(map(operator.mul, row, v)) for row in rows]


def _mean(v: list[float]) -> float:
    return sum(v) / len(v)


def _allclose(a: list[float], b: list[float]) -> bool:
    """``np.allclose(a, b, atol=1e-9)`` (rtol 1e-5) on plain floats."""
    return all(abs(x - y) <= 1e-9 + 1e-5 * abs(y) for x, y in zip(a, b, strict=True))


def width_cv(widths_mm: Sequence[float]) -> float:
    """Coefficient of variation (population std / mean) of mark widths; nan counts as 0."""
    w = np.nan_to_num(np.asarray(widths_mm, dtype=float), nan=0.0)
    m = float(w.mean()) if w.size else math.nan
    return float(w.std() / m) if m > 0 else math.nan
