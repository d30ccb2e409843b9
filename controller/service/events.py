"""What the service reports as it runs: typed events, one enum kind each.

The service appends a :class:`ServiceEvent` to ``Service.events`` (and calls ``on_event``) for
every change a person or a composition (HIL summary, benchmark, OPC UA, web page) follows:
safe-state entries and recoveries, bus and amplifier problems, refused setpoints, log trouble.
Consumers test ``event.kind`` and read ``event.reason`` / ``event.data`` (plain values);
``event.text`` is the line shown to people and is never parsed.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["COUNTERS", "EventKind", "EventLog", "ServiceEvent", "exc_name"]

COUNTERS = (
    "frames",
    "ok",
    "failed",
    "applied",
    "safe_entries",
    "recoveries",
    "plc_errors",
    "can_errors",
    "setpoint_refused",
    "log_errors",
    "errors",
    "missed",
    "amp_faults",
    "amp_emergencies",
    "uniformity_skipped",
    "tables_refused",
    "knife_chips",
    "targets_unreachable",
    "measurements_failing",
    "spool_skipped",
)
"""The service's counters (``Service.counters``), all starting at 0."""


class EventKind(enum.Enum):
    """Kinds of service events (the value is a short stable name for logs and JSON)."""

    SAFE_STATE = "safe_state"
    """The supervisor entered the safe state; ``reason`` names what is missing, ``data`` holds
    ``missing`` (the sources and conditions, ``controller.service.supervisor.SOURCES`` names) and
    ``recovery_s`` (how long everything must hold before RUN: the back-off)."""
    RECOVERED = "recovered"
    """Everything held for the recovery time: control resumed (``data``: ``safe_s``)."""
    PIEZO_LIMITS = "piezo_limits"
    """The bound on the piezo offsets changed: the amplifier reported its limits, or was lost
    (a reconnect: held at zero until it reports again). ``data``: ``OffsetLimit.to_dict()``."""
    OFFSETS_REFUSED = "offsets_refused"
    """The amplifier refused an offset table. ``data``: ``table_um`` (refused), ``limit_um``
    (the narrowed bound, ``None`` if nothing smaller exists), ``replanned_um`` (the table sent
    instead, ``None`` likewise): a refused table is never sent again unchanged."""
    AMPLIFIER_PROBLEM = "amplifier_problem"
    AMPLIFIER_HEALTHY = "amplifier_healthy"
    PLC_DATA_INVALID = "plc_data_invalid"
    PLC_DATA_VALID = "plc_data_valid"
    FEED_REFUSED = "feed_refused"
    """A feed setpoint was refused by the PLC or could not be written."""
    FEED_ACCEPTED = "feed_accepted"
    UNIFORMITY_NO_AUTHORITY = "uniformity_no_authority"
    """The uniformity loop found that the actuator cannot help, said once per finding: a knife
    pattern it cannot move (held), or the loop holds its best table (the learning made the
    board worse, or no pattern can be moved). ``data``: ``hold_reason``, ``held_modes``,
    ``mode_gains`` (``[magnitude, phase_deg]`` per pattern), ``mode_states``, ``confidence``,
    ``table_um``, ``best_score_um``, ``undos`` (``controller.laws.uniformity_status``)."""
    OFFSETS_NOT_SENT = "offsets_not_sent"
    OFFSETS_NOT_ZEROED = "offsets_not_zeroed"
    CLOCK_WENT_BACK = "clock_went_back"
    CAMERA_CLOCK_WENT_BACK = "camera_clock_went_back"
    PAIRS_MISSED = "pairs_missed"
    """A gap in the camera's sequence numbers (text: the count of numbers, then the jump)."""
    SPOOL_SKIPPED = "spool_skipped"
    """A spool file that gave no pair, or pairs pruned before they were read: one per file."""
    FRAME_SOURCE_FAILED = "frame_source_failed"
    LOG_FAILED = "log_failed"
    LOG_REFUSED_RECORD = "log_refused_record"
    LOG_RECOVERED = "log_recovered"
    RECORDS_SAVED = "records_saved"
    """Records the log did not take, saved to a file at stop (the text names it)."""
    RECORDS_LOST = "records_lost"
    SERVICE_ERROR = "service_error"
    """The service's own code failed unexpectedly (the supervisor boundary caught it)."""
    CLOSE_PROBLEM = "close_problem"
    LEARNED_STATE_RESUMED = "learned_state_resumed"
    """The loops start from the state a previous service learnt on the same knives
    (``controller.quality.learned_state``). ``data``: ``path``, ``age_s``, ``offsets_um``,
    ``feed_correction``, ``warm`` (the machine was running: the feed is held at start)."""
    LEARNED_STATE_DISCARDED = "learned_state_discarded"
    """A learnt state was found and not used (``reason``: another machine, too old, the knife set
    changed, unreadable): the loops learn afresh. ``data``: ``path``."""
    TARGET_UNREACHABLE = "target_unreachable"
    """The pitch stays off its target with the feed at the machine's limit (``reason``: "feed at
    its maximum" / "feed at its minimum") or the target lowered to the depth ceiling.
    ``data``: ``target_pitch_mm``, ``reachable_pitch_mm``, ``measured_pitch_mm``, ``limit``."""
    TARGET_REACHABLE = "target_reachable"
    """The target pitch is reachable again (the condition of ``TARGET_UNREACHABLE`` cleared)."""
    KNIFE_CHIPPED = "knife_chipped"
    """A knife chipped, moved or nicked (``data["cause"]``): ``runout_step``, one knife's mark
    width changed suddenly and stays changed (``controller.service.alerts.KnifeChipMonitor``;
    ``data``: ``knife``, ``width_change_mm``, ``runout_step_um`` (its estimate), ``seq``,
    ``t_s``), or ``nick``, the defect detector's ridge along the board at one place on
    consecutive pairs (``controller.service.alerts.KnifeNickMonitor``; ``data``:
    ``knife`` ``None`` (not told apart), ``y_mm`` across the camera's field, ``ridge_um``,
    ``seq``, ``t_s``)."""
    JOINTING_DUE = "jointing_due"
    """The knives' wear takes the finish out of its class soon: the forecast of
    :class:`controller.laws.knife_condition.KnifeConditionTracker` came within
    ``JOINTING_WARN_BOARDS`` boards (said once per knife set). ``data``: ``knife``,
    ``due_in_m``, ``due_in_boards``, ``due_in_h``."""
    MEASUREMENTS_FAILING = "measurements_failing"
    """Pairs keep failing to measure (``data``: ``failed``, ``of``, ``last_error``): a board is
    present but the camera, lights or vision do not deliver."""
    MEASUREMENTS_RECOVERED = "measurements_recovered"
    """Pairs measure again after ``MEASUREMENTS_FAILING``."""


@dataclass(frozen=True)
class ServiceEvent:
    """One event of the service.

    Attributes
    ----------
    t_s : float
        Service time of the event, seconds.
    kind : EventKind
        What happened.
    text : str
        The line shown to people (stderr, logs).
    reason : str or None
        For ``SAFE_STATE``: why, without the ``"safe state: "`` prefix (``"plc gone, can
        gone"``), so consumers need not parse ``text``; ``None`` for the other kinds.
    data : Mapping or None
        Plain values of the event for programs (see each :class:`EventKind`); ``None`` when
        the kind has none.
    """

    t_s: float
    kind: EventKind
    text: str
    reason: str | None = None
    data: Mapping[str, Any] | None = None

    def to_dict(self) -> dict[str, object]:
        """JSON-ready form: ``{"t_s", "kind", "text"}`` (and ``"reason"``, ``"data"`` when set)."""
        out: dict[str, object] = {"t_s": self.t_s, "kind": self.kind.value, "text": self.text}
        if self.reason is not None:
            out["reason"] = self.reason
        if self.data is not None:
            out["data"] = dict(self.data)
        return out


class EventLog:
    """Where every part of the service reports: the events in order and the counters.

    One instance is shared by the parts of one service (``Service.events`` is its list,
    ``Service.counters`` its dictionary); ``on_event`` (settable at any time) is called for
    each event as it happens.
    """

    def __init__(self) -> None:
        self.events: list[ServiceEvent] = []
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self.on_event: Callable[[ServiceEvent], None] | None = None

    def emit(
        self,
        t_s: float,
        kind: EventKind,
        text: str,
        *,
        reason: str | None = None,
        data: Mapping[str, Any] | None = None,
    ) -> None:
        """Record one event and hand it to ``on_event``."""
        event = ServiceEvent(t_s, kind, text, reason, None if data is None else dict(data))
        self.events.append(event)
        if self.on_event is not None:
            self.on_event(event)

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to the counter ``name``."""
        self.counters[name] += n


def exc_name(exc: BaseException) -> str:
    """``IndexError``, ``cv2.error``: the exception's type as a reader recognises it."""
    cls = type(exc)
    mod = cls.__module__
    return cls.__qualname__ if mod in ("builtins", "__main__") else f"{mod}.{cls.__qualname__}"
