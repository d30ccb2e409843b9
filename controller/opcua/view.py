"""What the machine shows over OPC UA, computed from the service (pure, no I/O, no asyncua).

:class:`MachineView` follows the service through the three things the composition root hands
it -- ``ServiceStatus`` snapshots (``controller.service.status``), ``ServiceEvent`` events
(``controller.service.events``) and ``FrameResult`` results (``controller.service.frame_result``)
-- and
answers with the values of the OPC 40550 (Woodworking) variables and the events to fire. The server
(:mod:`controller.opcua.server`) only writes what this module computes.

The mapping (``docs/opcua.md`` explains it for plant engineers):

- ``CurrentState`` (``WwUnitStateEnumeration``): ``OFFLINE`` before the first status, ``WORKING``
  in RUN with the feed running, ``READY`` in RUN with the feed stopped, ``STANDBY`` while the
  supervisor confirms a recovery, ``ERROR`` in the safe state.
- ``CurrentMode`` (``WwUnitModeEnumeration``): ``OTHER`` before the first status, ``AUTOMATIC`` in
  RUN (closed loop), ``SEMIAUTOMATIC`` in the safe state (feed held or ramped, no correction).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from controller.quality.defect_fields import DEFECT_KINDS, BoardGrades, pair_fields
from controller.quality.schema import QualityClass, judge
from controller.service.events import EventKind, ServiceEvent
from controller.service.frame_result import FrameResult
from controller.service.status import ServiceStatus

__all__ = [
    "FLAG_NAMES",
    "MANUFACTURER_NAMES",
    "VALUE_NAMES",
    "MachineView",
    "UnitMode",
    "UnitState",
    "WwEvent",
    "WwEventCategory",
    "as_number",
]


class UnitState(enum.IntEnum):
    """``WwUnitStateEnumeration`` (Woodworking ``i=21``)."""

    OFFLINE = 0
    STANDBY = 1
    READY = 2
    WORKING = 3
    ERROR = 4


class UnitMode(enum.IntEnum):
    """``WwUnitModeEnumeration`` (Woodworking ``i=20``)."""

    OTHER = 0
    AUTOMATIC = 1
    SEMIAUTOMATIC = 2
    MANUAL = 3
    SETUP = 4
    SLEEP = 5


class WwEventCategory(enum.IntEnum):
    """``WwEventCategoryEnumeration`` (Woodworking ``i=3004``)."""

    OTHER = 0
    DIAGNOSTIC = 1
    INFORMATION = 2
    WARNING = 3
    ALARM = 4
    ERROR = 5


FLAG_NAMES = (
    "MachineOn", "PowerPresent", "MachineInitialized", "Emergency", "Calibrated", "Error",
    "Warning", "Alarm", "RecipeInRun", "FeedRuns", "Moving", "WorkpiecePresent",
)
"""The ``State/Machine/Flags`` variables we serve (all ``Boolean``; the first nine mandatory)."""

VALUE_NAMES = (
    "FeedSpeed", "AbsoluteLength", "RelativeLength", "AbsolutePiecesIn", "RelativePiecesIn",
    "AbsolutePiecesOut", "RelativePiecesOut", "AbsoluteRunsGood", "RelativeRunsGood",
    "AbsoluteRunsTotal", "RelativeRunsTotal",
)
"""The ``State/Machine/Values`` variables we serve (``FeedSpeed`` Double m/min, the rest UInt64;
lengths in mm)."""

MANUFACTURER_NAMES: Mapping[str, str] = {
    "PitchMm": "Double", "UniformityCv": "Double", "DepthUm": "Double",
    "KnifeWidthsMm": "Double[]", "PiezoOffsetsUm": "Double[]", "Confidence": "Double",
    "QualityClass": "String", "Passed": "Boolean", "MeasurementOk": "Boolean",
    "MeasurementError": "String", "SafeReason": "String", "FeedSetpointMmS": "Double",
    "LastBoardPairs": "Int64", "LastBoardPairsOk": "Int64", "LastBoardPassRate": "Double",
    "LastBoardMeanPitchMm": "Double", "LastBoardMeanUniformityCv": "Double",
    "BoardTravelM": "Double", "KnifeWearUmPerM": "Double[]", "KnifeReserveUm": "Double[]",
    "JointingState": "String", "JointingForecast": "String", "JointingDueM": "Double",
    "JointingDueBoards": "Double", "JointingDueH": "Double", "JointingKnife": "Int64",
    "JointingTrend": "String",
    "KnifeChips": "Int64", "LastChippedKnife": "Int64", "LastChipRunoutStepUm": "Double",
    "LastChipCause": "String",
    "BoardGrade": "Int64", "LastBoardId": "Int64", "LastBoardGrade": "Int64",
    "LastBoardGradeReason": "String", "LastBoardDefects": "Int64",
    **{"LastBoard" + "".join(w.title() for w in k.split("_")): "Int64" for k in DEFECT_KINDS},
}
"""``ManufacturerSpecific`` variables (our namespace) and their data types; NaN = not known.
The planing defects (``[quality] defects = true``): ``BoardGrade`` (the board under the camera
so far) and ``LastBoardGrade`` (the last finished board), ASTM D1666 1..5, 0 = not graded;
``LastBoardDefects`` and one count per kind (``LastBoardTornGrain`` ... ``LastBoardSnipe``)."""
#: The per-kind count variables, by defect kind.
DEFECT_COUNT_NAMES: Mapping[str, str] = {
    k: "LastBoard" + "".join(w.title() for w in k.split("_")) for k in DEFECT_KINDS}
MANUFACTURER_INITIAL: Mapping[str, int] = {"JointingKnife": -1, "LastChippedKnife": -1}
"""Integer variables whose "none" is -1 (a knife index), not 0."""

_EVENT_CATEGORY = {
    EventKind.SAFE_STATE: WwEventCategory.ERROR,
    EventKind.SERVICE_ERROR: WwEventCategory.ERROR,
    EventKind.AMPLIFIER_PROBLEM: WwEventCategory.ALARM,
    EventKind.PLC_DATA_INVALID: WwEventCategory.ALARM,
    EventKind.FRAME_SOURCE_FAILED: WwEventCategory.ALARM,
    EventKind.RECORDS_LOST: WwEventCategory.ALARM,
    EventKind.LOG_FAILED: WwEventCategory.WARNING,
    EventKind.LOG_REFUSED_RECORD: WwEventCategory.WARNING,
    EventKind.FEED_REFUSED: WwEventCategory.WARNING,
    EventKind.OFFSETS_NOT_SENT: WwEventCategory.WARNING,
    EventKind.OFFSETS_REFUSED: WwEventCategory.WARNING,
    EventKind.OFFSETS_NOT_ZEROED: WwEventCategory.WARNING,
    EventKind.PAIRS_MISSED: WwEventCategory.WARNING,
    EventKind.CLOCK_WENT_BACK: WwEventCategory.WARNING,
    EventKind.CAMERA_CLOCK_WENT_BACK: WwEventCategory.WARNING,
    EventKind.CLOSE_PROBLEM: WwEventCategory.WARNING,
    EventKind.RECORDS_SAVED: WwEventCategory.WARNING,
    EventKind.KNIFE_CHIPPED: WwEventCategory.ALARM,
    EventKind.JOINTING_DUE: WwEventCategory.WARNING,
}
"""Service events that become Woodworking events; the rest (``RECOVERED``, ``*_HEALTHY``,
``*_VALID``, ``FEED_ACCEPTED``, ``LOG_RECOVERED``, ``PIEZO_LIMITS``) are ``INFORMATION``."""

def knife_condition_values(s: ServiceStatus | None) -> dict[str, Any]:
    """The knife condition's ``ManufacturerSpecific`` values of a status (NaN / -1: none).

    ``BoardTravelM``, ``KnifeWearUmPerM`` and ``KnifeReserveUm`` (per knife), the jointing
    forecast (``JointingState``: ``fitting``, ``not_due``, ``due`` or "" before the first
    table; ``JointingForecast`` its line; ``JointingDueM``, ``JointingDueBoards``,
    ``JointingDueH``, ``JointingKnife`` when due; ``JointingTrend``: ``unknown`` while fitting,
    ``none``: no significant wear trend, not due, no figures, or ``significant``), and the
    chipped knives (``KnifeChips`` counted, the last one's ``LastChipCause``: ``runout_step``
    or ``nick``, ``LastChippedKnife`` (-1 for a nick: not told apart) and
    ``LastChipRunoutStepUm``).
    """
    kc = (s.knife_condition if s is not None else None) or {}
    knives = kc.get("knives") or ()
    chip = ((s.alerts or {}).get("knife_chipped") if s is not None else None) or {}
    knife = kc.get("knife")
    last_chip = chip.get("knife")
    return {
        "BoardTravelM": as_number(kc.get("board_travel_m")),
        "KnifeWearUmPerM": [as_number(k.get("drift_um_per_m")) for k in knives],
        "KnifeReserveUm": [as_number(k.get("reserve_um")) for k in knives],
        "JointingState": str(kc.get("state") or ""),
        "JointingForecast": str(kc.get("text") or ""),
        "JointingDueM": as_number(kc.get("due_in_m")),
        "JointingDueBoards": as_number(kc.get("due_in_boards")),
        "JointingDueH": as_number(kc.get("due_in_h")),
        "JointingKnife": int(knife) if isinstance(knife, int) else -1,
        "JointingTrend": str(kc.get("trend") or ""),
        "KnifeChips": int(s.counters.get("knife_chips", 0)) if s is not None else 0,
        "LastChippedKnife": int(last_chip) if isinstance(last_chip, int) else -1,
        "LastChipRunoutStepUm": as_number(chip.get("runout_step_um")),
        "LastChipCause": str(chip.get("cause") or ""),
    }


_SEVERITY = {
    WwEventCategory.ERROR: 800, WwEventCategory.ALARM: 700, WwEventCategory.WARNING: 500,
    WwEventCategory.INFORMATION: 200,
}


@dataclass(frozen=True)
class WwEvent:
    """One Woodworking event (``WwBaseEventType``) to fire.

    Attributes
    ----------
    t_s : float
        Service time of the event, s.
    message_id : str
        ``MessageId``: the service event kind (``"safe_state"``).
    message : str
        ``Message`` (the line people read).
    category : WwEventCategory
        ``EventCategory``.
    severity : int
        ``Severity`` (1..1000).
    path_parts : tuple of str
        ``PathParts``: where in the machine (``("Machine", "Service")``).
    """

    t_s: float
    message_id: str
    message: str
    category: WwEventCategory
    severity: int
    path_parts: tuple[str, ...] = ("Machine", "Service")


def as_number(v: Any) -> float:
    """``v`` as a float; NaN when it is none (``None``, not a number)."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return math.nan
    return f


class MachineView:
    """The OPC UA picture of the machine, updated from the service.

    Parameters
    ----------
    quality_class : QualityClass or None
        The class each measurement is judged against (``Passed``); ``None``: not judged.
    calibrated : bool
        ``Flags/Calibrated``: the rig file the measurement uses is calibrated.
    workpiece_gap_s : float
        A board counts as gone (``WorkpiecePresent`` false, one piece out) when no pair arrived
        for this long in service time, s.
    """

    def __init__(
        self,
        *,
        quality_class: QualityClass | None = None,
        calibrated: bool = True,
        workpiece_gap_s: float = 1.0,
    ) -> None:
        if not workpiece_gap_s > 0:
            raise ValueError(f"workpiece_gap_s must be > 0, got {workpiece_gap_s}")
        self.quality_class = quality_class
        self.calibrated = bool(calibrated)
        self.workpiece_gap_s = float(workpiece_gap_s)
        self._status: ServiceStatus | None = None
        self._length_mm = 0.0
        self._last_t_s: float | None = None
        self._last_feed_mm_s = math.nan
        self._last_pair_t_s: float | None = None
        self._present = False
        self._pieces_in = 0
        self._pieces_out = 0
        self._runs_total = 0
        self._runs_good = 0
        self._board: list[FrameResult] = []
        self._last_board: dict[str, float] = {}
        self._last_result: FrameResult | None = None
        self._passed: bool | None = None
        self._grades = BoardGrades()
        self._board_grade: dict[str, Any] | None = None  # the board under the camera so far
        self._last_board_grade: dict[str, Any] | None = None

    # --- inputs -------------------------------------------------------------------------------

    def update(self, status: ServiceStatus) -> None:
        """Take a status snapshot: state, feed, offsets; integrates the planed length.

        The length grows by the actual feed of the previous snapshot times the service time
        since it (snapshots with ``t_s`` going back add nothing).
        """
        t = status.t_s
        feed = self._last_feed_mm_s  # the feed last reported holds until this snapshot
        if t is not None and self._last_t_s is not None and t > self._last_t_s and feed > 0:
            self._length_mm += feed * (t - self._last_t_s)
        if t is not None:
            self._last_t_s = t if self._last_t_s is None else max(self._last_t_s, t)
            self._last_feed_mm_s = as_number(status.feed_actual_mm_s)
            self._check_board_gone(t)
        self._status = status

    def result(self, r: FrameResult) -> None:
        """Take one pair's result: a board is present; a run counted; the measurement shown."""
        if not self._present:
            self._present = True
            self._pieces_in += 1
            self._board = []
        self._last_pair_t_s = float(r.t_s)
        self._board.append(r)
        self._last_result = r
        self._grade(r)
        self._runs_total += 1
        self._passed = self._judge(r)
        if self._passed:
            self._runs_good += 1

    def event(self, e: ServiceEvent) -> WwEvent:
        """The Woodworking event for a service event."""
        cat = _EVENT_CATEGORY.get(e.kind, WwEventCategory.INFORMATION)
        return WwEvent(
            t_s=float(e.t_s), message_id=e.kind.value, message=e.text, category=cat,
            severity=_SEVERITY[cat],
        )

    # --- outputs ------------------------------------------------------------------------------

    @property
    def status(self) -> ServiceStatus | None:
        """The last status snapshot taken (``None`` before the first)."""
        return self._status

    @property
    def current_state(self) -> UnitState:
        """``Overview/CurrentState``."""
        s = self._status
        if s is None or s.t_s is None:
            return UnitState.OFFLINE
        if s.state == "run":
            return UnitState.WORKING if as_number(s.feed_actual_mm_s) > 0 else UnitState.READY
        if not s.missing:  # safe, nothing missing: confirming the recovery
            return UnitState.STANDBY
        return UnitState.ERROR

    @property
    def current_mode(self) -> UnitMode:
        """``Overview/CurrentMode``."""
        s = self._status
        if s is None or s.t_s is None:
            return UnitMode.OTHER
        return UnitMode.AUTOMATIC if s.state == "run" else UnitMode.SEMIAUTOMATIC

    def flags(self) -> dict[str, bool]:
        """``State/Machine/Flags`` by name (:data:`FLAG_NAMES`)."""
        s = self._status
        known = s is not None and s.t_s is not None
        missing = set(s.missing) if s is not None else set()
        feed_runs = known and as_number(s.feed_actual_mm_s) > 0
        last = self._last_result
        warning = known and (
            s.log_problem is not None or s.records_pending > 0
            or (last is not None and not last.ok) or self._passed is False
        )
        return {
            "MachineOn": known and "plc" not in missing and "machine" not in missing,
            "PowerPresent": known and "plc" not in missing,
            "MachineInitialized": known,
            "Emergency": False,
            "Calibrated": self.calibrated,
            "Error": self.current_state is UnitState.ERROR,
            "Warning": bool(warning),
            "Alarm": bool(missing & {"machine", "amplifier", "plc_data", "service"}),
            "RecipeInRun": known and s.state == "run",
            "FeedRuns": bool(feed_runs),
            "Moving": bool(feed_runs),
            "WorkpiecePresent": self._present,
        }

    def values(self) -> dict[str, float | int]:
        """``State/Machine/Values`` by name (:data:`VALUE_NAMES`)."""
        s = self._status
        feed_mm_s = as_number(s.feed_actual_mm_s) if s is not None else math.nan
        length = int(round(self._length_mm))
        return {
            "FeedSpeed": feed_mm_s * 0.06,  # mm/s -> m/min
            "AbsoluteLength": length, "RelativeLength": length,
            "AbsolutePiecesIn": self._pieces_in, "RelativePiecesIn": self._pieces_in,
            "AbsolutePiecesOut": self._pieces_out, "RelativePiecesOut": self._pieces_out,
            "AbsoluteRunsGood": self._runs_good, "RelativeRunsGood": self._runs_good,
            "AbsoluteRunsTotal": self._runs_total, "RelativeRunsTotal": self._runs_total,
        }

    def manufacturer(self) -> dict[str, Any]:
        """``ManufacturerSpecific`` by name (:data:`MANUFACTURER_NAMES`)."""
        s = self._status
        r = self._last_result
        m = r.measurement if r is not None and r.ok else None
        offsets: Sequence[float] = s.offsets_um if s is not None else (
            r.offsets_um if r is not None else ())
        return {
            "PitchMm": as_number(r.reported_pitch_mm if m is not None else None),
            "UniformityCv": as_number(r.reported_uniformity_cv if m is not None else None),
            "DepthUm": as_number(getattr(m, "depth_um", None)),
            "KnifeWidthsMm": [as_number(w) for w in (r.knife_widths_mm if r is not None else ())],
            "PiezoOffsetsUm": [as_number(v) for v in offsets],
            "Confidence": as_number(getattr(r.measurement, "confidence", None)) if r else math.nan,
            "QualityClass": self.quality_class.name if self.quality_class else "",
            "Passed": bool(self._passed),
            "MeasurementOk": bool(r is not None and r.ok),
            "MeasurementError": (r.error or "") if r is not None else "",
            "SafeReason": (s.safe_reason or "") if s is not None else "",
            "FeedSetpointMmS": as_number(s.feed_setpoint_mm_s) if s is not None else math.nan,
            "LastBoardPairs": int(self._last_board.get("pairs", 0)),
            "LastBoardPairsOk": int(self._last_board.get("pairs_ok", 0)),
            "LastBoardPassRate": self._last_board.get("pass_rate", math.nan),
            "LastBoardMeanPitchMm": self._last_board.get("mean_pitch_mm", math.nan),
            "LastBoardMeanUniformityCv": self._last_board.get("mean_uniformity_cv", math.nan),
            **knife_condition_values(s),
            **self._grade_values(),
        }

    def _grade(self, r: FrameResult) -> None:
        """The board's grade so far with this pair's defects (when looked for, on a board)."""
        board = r.extra.get("board_id")
        found = pair_fields(r.surface) if r.surface is not None else {}  # refused too
        if not isinstance(board, int) or board <= 0 or not found:
            return
        if self._board_grade is not None and self._board_grade["board_id"] != board:
            self._last_board_grade = self._board_grade
        pos = r.extra.get("board_position_mm")
        self._board_grade = {"board_id": board, **self._grades.add(
            board, found["defects"], pos if isinstance(pos, (int, float)) else None)}

    def _grade_values(self) -> dict[str, Any]:
        cur, last = self._board_grade, self._last_board_grade
        counts = (last or {}).get("board_defect_counts") or dict.fromkeys(DEFECT_KINDS, 0)
        return {
            "BoardGrade": int(cur["board_grade"]) if cur else 0,
            "LastBoardId": int(last["board_id"]) if last else 0,
            "LastBoardGrade": int(last["board_grade"]) if last else 0,
            "LastBoardGradeReason": last["board_grade_reason"] if last else "",
            "LastBoardDefects": int(sum(counts.values())),
            **{name: int(counts[k]) for k, name in DEFECT_COUNT_NAMES.items()},
        }

    def all_values(self) -> dict[str, Any]:
        """Every served value by its path below the machine (``"State/Machine/Flags/Error"``)."""
        out: dict[str, Any] = {
            "State/Machine/Overview/CurrentState": int(self.current_state),
            "State/Machine/Overview/CurrentMode": int(self.current_mode),
        }
        out.update({f"State/Machine/Flags/{k}": v for k, v in self.flags().items()})
        out.update({f"State/Machine/Values/{k}": v for k, v in self.values().items()})
        out.update({f"ManufacturerSpecific/{k}": v for k, v in self.manufacturer().items()})
        return out

    # --- internals ----------------------------------------------------------------------------

    def _judge(self, r: FrameResult) -> bool | None:
        if not r.ok or self.quality_class is None:
            return None
        try:
            return bool(judge(r.measurement, self.quality_class))
        except (TypeError, ValueError, AttributeError):
            return None

    def _check_board_gone(self, t_s: float) -> None:
        if (self._present and self._last_pair_t_s is not None
                and t_s - self._last_pair_t_s > self.workpiece_gap_s):
            self._present = False
            self._pieces_out += 1
            self._last_board = self._summarise(self._board)
            self._board = []
            if self._board_grade is not None:  # the graded board left too
                self._last_board_grade, self._board_grade = self._board_grade, None

    def _summarise(self, board: Sequence[FrameResult]) -> dict[str, float]:
        ok = [r for r in board if r.ok]
        pitches = [as_number(r.reported_pitch_mm) for r in ok]
        cvs = [as_number(r.reported_uniformity_cv) for r in ok]
        judged = [self._judge(r) for r in ok]
        judged = [j for j in judged if j is not None]

        def mean(xs: list[float]) -> float:
            xs = [x for x in xs if math.isfinite(x)]
            return sum(xs) / len(xs) if xs else math.nan

        return {
            "pairs": len(board), "pairs_ok": len(ok),
            "pass_rate": sum(judged) / len(judged) if judged else math.nan,
            "mean_pitch_mm": mean(pitches), "mean_uniformity_cv": mean(cvs),
        }
