"""The service's memory across restarts: what the loops learnt, kept beside the quality log.

A restarted service (a clean stop, a crash, a ``kill -9``) should not start learning again on a
machine that still runs the same knives: the runout offsets took metres of board to learn, and
the board cut meanwhile is out of the bands. :class:`LearnedMemory` keeps the learnt state in
one small JSON file (:func:`learned_state_path`: beside an SQLite log, ``run.db`` ->
``run.db.learned.json``; for a PostgreSQL log in the journal's state folder, named like the
journal) and reads it back at the next start:

* what is kept (:class:`LearnedState`): the piezo offset table in force, the feed loop's
  learnt correction, and for reading the uniformity loop's runout estimate and identified mode
  gains; with the machine id, the knife set it was learnt on (:class:`KnifeSet`: the PLC's
  knives, cutting radius and spindle speed, the amplifier's stroke) and the wall-clock time;
* written atomically (``core.fileio``, the rename only: a killed process leaves the old file or
  the new one, never a torn one) at most every :data:`SAVE_EVERY_S` seconds of service time
  while the state changes, never per pair, and once more at a clean stop;
* used at the next start only when it is fresh (younger than :data:`MAX_AGE_S`), from the same
  machine, and the machine still runs the same knives (:meth:`LearnedMemory.judge`); otherwise
  the loops learn afresh and the service says why.

A moulder's heads each keep their own state (:attr:`LearnedState.head`; the file of a head other
than ``"main"`` is ``run.db.<head>.learned.json``): a head never resumes another head's offsets.
The single head ``"main"`` keeps the file and reads the states written before heads (they hold
no ``head`` and are ``"main"``'s).

No control law lives here; :class:`controller.service.loops.ControlLoops` decides what to take.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from controller.quality.journal import default_journal_path
from controller.quality.schema import DEFAULT_HEAD, check_head
from core.fileio import atomic_write_text

FORMAT = 1
"""Version of the file's layout (``"format"``); another one is not read."""
SAVE_EVERY_S = 2.0
"""Service seconds between two writes of a changing state (a state that does not change is not
written again)."""
MAX_AGE_S = 3600.0
"""A state older than this (wall clock) is not resumed: knives warm up and wear within hours."""
RADIUS_TOL_MM = 0.05
"""Cutting radii closer than this are the same knife set (register rounding)."""
SPINDLE_TOL = 0.05
"""Spindle speeds within this fraction of each other are the same set-up (when both turn)."""
STROKE_TOL_UM = 0.05
"""Amplifier strokes closer than this are the same amplifier."""
OFFSET_CHANGE_UM = 0.005
"""A table that moved less than this (every knife) is not a change worth writing, um."""


def learned_state_path(log_path: str | Path, *, head: str = DEFAULT_HEAD) -> Path:
    """Where the learnt state of a quality log lives (see the module's docstring).

    Parameters
    ----------
    log_path : str or Path
        The quality log: an SQLite file or a ``postgresql://`` URL.
    head : str, keyword-only
        The cutterhead: ``"main"`` (``run.db.learned.json``) or a moulder's head
        (``run.db.<head>.learned.json``, beside its journal).
    """
    journal = default_journal_path(log_path, head=head)
    name = journal.name
    suffix = ".journal.jsonl"
    base = name[: -len(suffix)] if name.endswith(suffix) else name
    return journal.with_name(base + ".learned.json")


def _finite(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def _numbers(name: str, values: Any, n: int | None = None) -> tuple[float, ...]:
    if not isinstance(values, (list, tuple)):
        raise ValueError(f"{name} must be a list of numbers, got {values!r}")
    if n is not None and len(values) != n:
        raise ValueError(f"{name} must have {n} values, got {len(values)}")
    return tuple(_finite(f"{name}[{i}]", v) for i, v in enumerate(values))


@dataclass(frozen=True)
class KnifeSet:
    """What makes learnt offsets valid: the knives the machine runs and who drives them.

    Attributes
    ----------
    knives : int
        Knives on the cutterhead (the PLC's register).
    radius_mm : float
        Cutting radius (the PLC's register), mm.
    spindle_rpm : float
        Spindle speed (the PLC's register; 0 while it stands), rev/min.
    stroke_um : float or None
        The amplifier's reported stroke, um (``None``: not reported yet).
    """

    knives: int
    radius_mm: float
    spindle_rpm: float
    stroke_um: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.knives, bool) or not isinstance(self.knives, int) or self.knives < 1:
            raise ValueError(f"knives must be a whole number >= 1, got {self.knives!r}")
        if not _finite("radius_mm", self.radius_mm) > 0:
            raise ValueError(f"radius_mm must be > 0, got {self.radius_mm!r}")
        if not _finite("spindle_rpm", self.spindle_rpm) >= 0:
            raise ValueError(f"spindle_rpm must be >= 0, got {self.spindle_rpm!r}")
        if self.stroke_um is not None and not _finite("stroke_um", self.stroke_um) > 0:
            raise ValueError(f"stroke_um must be > 0, got {self.stroke_um!r}")

    def differs(self, now: KnifeSet) -> str | None:
        """Why ``now`` is not this knife set (``None``: the same one).

        The spindle speed counts only when both turn; the stroke only when both are known.
        """
        if now.knives != self.knives:
            return f"knives {self.knives} then, {now.knives} now"
        if abs(now.radius_mm - self.radius_mm) > RADIUS_TOL_MM:
            return f"cutting radius {self.radius_mm:g} mm then, {now.radius_mm:g} mm now"
        if (self.spindle_rpm > 0 and now.spindle_rpm > 0
                and abs(now.spindle_rpm / self.spindle_rpm - 1.0) > SPINDLE_TOL):
            return f"spindle {self.spindle_rpm:.0f} rpm then, {now.spindle_rpm:.0f} rpm now"
        if (self.stroke_um is not None and now.stroke_um is not None
                and abs(now.stroke_um - self.stroke_um) > STROKE_TOL_UM):
            return f"amplifier stroke {self.stroke_um:g} µm then, {now.stroke_um:g} µm now"
        return None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON."""
        return {"knives": self.knives, "radius_mm": self.radius_mm,
                "spindle_rpm": self.spindle_rpm, "stroke_um": self.stroke_um}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> KnifeSet:
        """From :meth:`to_dict`'s form; ``ValueError`` naming a bad field."""
        stroke = d.get("stroke_um")
        return cls(knives=d.get("knives"), radius_mm=d.get("radius_mm"),  # type: ignore[arg-type]
                   spindle_rpm=d.get("spindle_rpm"),  # type: ignore[arg-type]
                   stroke_um=None if stroke is None else stroke)


@dataclass(frozen=True)
class LearnedState:
    """What the loops learnt on one knife set.

    Attributes
    ----------
    machine_id : str
        The machine (the quality log's id).
    knife_set : KnifeSet
        What it was learnt on.
    saved_at_unix : float
        Wall-clock time of the save, s since the epoch.
    offsets_um : tuple of float
        The piezo offset table in force (zero mean), one per knife, um.
    feed_correction : float
        The feed loop's learnt correction factor ``exp(x)``.
    runout_estimate_um : tuple of float or None
        The uniformity loop's runout estimate (for people and reports; not resumed).
    mode_gains : tuple of (float, float) or None
        The identified actuator gain per knife mode, (real, imaginary) (likewise).
    head : str
        The cutterhead it was learnt on (``"main"``: the single head, and every state saved
        before heads).
    """

    machine_id: str
    knife_set: KnifeSet
    saved_at_unix: float
    offsets_um: tuple[float, ...]
    feed_correction: float = 1.0
    runout_estimate_um: tuple[float, ...] | None = None
    mode_gains: tuple[tuple[float, float], ...] | None = field(default=None)
    head: str = DEFAULT_HEAD

    def __post_init__(self) -> None:
        if not isinstance(self.machine_id, str) or not self.machine_id:
            raise ValueError(f"machine_id must be a non-empty string, got {self.machine_id!r}")
        check_head("head", self.head)
        if not isinstance(self.knife_set, KnifeSet):
            raise ValueError(f"knife_set must be a KnifeSet, got {self.knife_set!r}")
        _finite("saved_at_unix", self.saved_at_unix)
        z = self.knife_set.knives
        object.__setattr__(self, "offsets_um", _numbers("offsets_um", self.offsets_um, z))
        if not 0.0 < _finite("feed_correction", self.feed_correction) < 100.0:
            raise ValueError(f"feed_correction must be in (0, 100), got {self.feed_correction!r}")
        if self.runout_estimate_um is not None:
            object.__setattr__(self, "runout_estimate_um",
                               _numbers("runout_estimate_um", self.runout_estimate_um, z))
        if self.mode_gains is not None:
            if not isinstance(self.mode_gains, (list, tuple)) or len(self.mode_gains) != z:
                raise ValueError(f"mode_gains must hold {z} (real, imag) pairs")
            object.__setattr__(self, "mode_gains", tuple(
                _numbers(f"mode_gains[{i}]", g, 2) for i, g in enumerate(self.mode_gains)))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON (the file's content)."""
        return {
            "format": FORMAT,
            "machine_id": self.machine_id,
            "head": self.head,
            "saved_at_unix": self.saved_at_unix,
            "knife_set": self.knife_set.to_dict(),
            "offsets_um": list(self.offsets_um),
            "feed_correction": self.feed_correction,
            "runout_estimate_um": (None if self.runout_estimate_um is None
                                   else list(self.runout_estimate_um)),
            "mode_gains": (None if self.mode_gains is None
                           else [list(g) for g in self.mode_gains]),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LearnedState:
        """From :meth:`to_dict`'s form; ``ValueError`` naming what is wrong."""
        if not isinstance(d, Mapping):
            raise ValueError(f"the learnt state must be a JSON object, got {type(d).__name__}")
        if d.get("format") != FORMAT:
            raise ValueError(f"format must be {FORMAT}, got {d.get('format')!r}")
        ks = d.get("knife_set")
        if not isinstance(ks, Mapping):
            raise ValueError(f"knife_set must be an object, got {ks!r}")
        return cls(
            machine_id=d.get("machine_id"),  # type: ignore[arg-type]
            knife_set=KnifeSet.from_dict(ks),
            saved_at_unix=d.get("saved_at_unix"),  # type: ignore[arg-type]
            offsets_um=d.get("offsets_um"),  # type: ignore[arg-type]
            feed_correction=d.get("feed_correction", 1.0),
            runout_estimate_um=d.get("runout_estimate_um"),
            mode_gains=d.get("mode_gains"),
            head=d.get("head", DEFAULT_HEAD),  # a state saved before heads: the single head's
        )


class LearnedMemory:
    """One service's learnt state on disk: read once at start, written while it changes.

    Parameters
    ----------
    path : Path
        The file (its folder is created at the first write).
    machine_id : str
        This machine; a state of another one is never resumed.
    wall_clock : callable
        Seconds since the epoch (``time.time``); the age of a state across processes.
    save_every_s : float
        Service seconds between two writes of a changing state.
    max_age_s : float
        A state older than this is not resumed, s.
    head : str
        This cutterhead; a state of another head is never resumed.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        machine_id: str,
        wall_clock: Callable[[], float] = time.time,
        save_every_s: float = SAVE_EVERY_S,
        max_age_s: float = MAX_AGE_S,
        head: str = DEFAULT_HEAD,
    ) -> None:
        self.path = Path(path)
        self.head = check_head("head", head)
        if not isinstance(machine_id, str) or not machine_id:
            raise ValueError(f"machine_id must be a non-empty string, got {machine_id!r}")
        self.machine_id = machine_id
        self.wall_clock = wall_clock
        if not (math.isfinite(save_every_s) and save_every_s >= 0):
            raise ValueError(f"save_every_s must be a finite number >= 0, got {save_every_s!r}")
        if not (math.isfinite(max_age_s) and max_age_s > 0):
            raise ValueError(f"max_age_s must be a finite number > 0, got {max_age_s!r}")
        self.save_every_s = float(save_every_s)
        self.max_age_s = float(max_age_s)
        self._saved: LearnedState | None = None
        self._saved_t: float | None = None
        self.writes = 0
        """Files written by this service."""
        self.problem: str | None = None
        """The last write's trouble (``None`` when it went through)."""

    @classmethod
    def beside(cls, log_path: str | Path, *, machine_id: str, head: str = DEFAULT_HEAD,
               **kw: Any) -> LearnedMemory:
        """``head``'s memory on the quality log at ``log_path`` (:func:`learned_state_path`)."""
        return cls(learned_state_path(log_path, head=head), machine_id=machine_id, head=head,
                   **kw)

    def load(self) -> tuple[LearnedState | None, str | None]:
        """The state on disk and, when it cannot be used at all, why.

        Returns
        -------
        (LearnedState or None, str or None)
            ``(state, None)``; ``(None, None)`` when there is no file; ``(None, reason)`` when
            the file is unreadable or not a learnt state.
        """
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None, None
        except (OSError, UnicodeDecodeError) as exc:
            return None, f"learnt state {self.path} unreadable: {exc}"
        try:
            return LearnedState.from_dict(json.loads(text)), None
        except ValueError as exc:  # json.JSONDecodeError is a ValueError
            return None, f"learnt state {self.path} not usable: {exc}"

    def judge(self, state: LearnedState, now: KnifeSet) -> str | None:
        """Why ``state`` must not be resumed on the machine as it is ``now`` (``None``: resume)."""
        if state.machine_id != self.machine_id:
            return f"learnt on machine {state.machine_id!r}, this is {self.machine_id!r}"
        if state.head != self.head:
            return f"learnt on head {state.head!r}, this is head {self.head!r}"
        age = self.wall_clock() - state.saved_at_unix
        if age > self.max_age_s:
            return f"learnt {age / 60:.0f} min ago (older than {self.max_age_s / 60:.0f} min)"
        if age < -60.0:
            return "saved in the future (the clock went back)"
        why = state.knife_set.differs(now)
        return None if why is None else f"the knife set changed: {why}"

    def make(
        self,
        knife_set: KnifeSet,
        offsets_um: Sequence[float],
        *,
        feed_correction: float,
        runout_estimate_um: Sequence[float] | None = None,
        mode_gains: Sequence[complex] | None = None,
    ) -> LearnedState:
        """A state of this machine stamped now."""
        return LearnedState(
            machine_id=self.machine_id, head=self.head, knife_set=knife_set,
            saved_at_unix=self.wall_clock(),
            offsets_um=tuple(float(v) for v in offsets_um), feed_correction=feed_correction,
            runout_estimate_um=(None if runout_estimate_um is None
                                else tuple(float(v) for v in runout_estimate_um)),
            mode_gains=(None if mode_gains is None
                        else tuple((float(complex(g).real), float(complex(g).imag))
                                   for g in mode_gains)),
        )

    def changed(self, state: LearnedState) -> bool:
        """Whether ``state`` differs from the one last written (what is worth writing)."""
        old = self._saved
        if old is None or old.knife_set != state.knife_set:
            return True
        if abs(old.feed_correction - state.feed_correction) > 1e-4:
            return True
        return any(abs(a - b) > OFFSET_CHANGE_UM
                   for a, b in zip(old.offsets_um, state.offsets_um, strict=True))

    def due(self, t: float) -> bool:
        """Whether a write at service time ``t`` keeps to :attr:`save_every_s`."""
        return self._saved_t is None or t - self._saved_t >= self.save_every_s - 1e-9

    def offer(self, state_of: Callable[[], LearnedState | None], t: float) -> bool:
        """Write the state ``state_of()`` gives if due and changed; whether it was written."""
        if not self.due(t):
            return False
        state = state_of()
        if state is None or not self.changed(state):
            return False
        return self.save(state, t)

    def save(self, state: LearnedState, t: float) -> bool:
        """Write ``state`` now (atomically); whether it went through (:attr:`problem` if not)."""
        text = json.dumps(state.to_dict(), indent=1, allow_nan=False) + "\n"
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # the rename makes it atomic for a killed process; no fsync in the control loop
            atomic_write_text(self.path, text, durable=False)
        except OSError as exc:
            self.problem = f"learnt state not written to {self.path}: {exc}"
            self._saved_t = t  # try again only after the interval
            return False
        self.problem = None
        self._saved, self._saved_t = state, t
        self.writes += 1
        return True


def learned_memory_of(log: Any, *, head: str = DEFAULT_HEAD) -> LearnedMemory | None:
    """``head``'s memory beside a quality log (``None``: a log without a path or a machine)."""
    path = getattr(log, "path", None)
    machine_id = getattr(log, "machine_id", None)
    if not path or not isinstance(machine_id, str) or not machine_id:
        return None
    return LearnedMemory.beside(path, machine_id=machine_id, head=head)
