"""What the service reports as it runs: typed events, one enum kind each.

The service appends a :class:`ServiceEvent` to ``Service.events`` (and calls ``on_event``) for
every change a person or a composition (HIL summary, benchmark, OPC UA, web page) follows:
safe-state entries and recoveries, bus and amplifier problems, refused setpoints, log trouble.
Consumers test ``event.kind``; ``event.text`` is the line shown to people.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

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
    "uniformity_skipped",
)
"""The service's counters (``Service.counters``), all starting at 0."""


class EventKind(enum.Enum):
    """Kinds of service events (the value is a short stable name for logs and JSON)."""

    SAFE_STATE = "safe_state"
    """The supervisor entered the safe state; the text names what is missing."""
    RECOVERED = "recovered"
    """Everything held for ``recovery_s``: control resumed."""
    AMPLIFIER_PROBLEM = "amplifier_problem"
    AMPLIFIER_HEALTHY = "amplifier_healthy"
    PLC_DATA_INVALID = "plc_data_invalid"
    PLC_DATA_VALID = "plc_data_valid"
    FEED_REFUSED = "feed_refused"
    """A feed setpoint was refused by the PLC or could not be written."""
    FEED_ACCEPTED = "feed_accepted"
    OFFSETS_NOT_SENT = "offsets_not_sent"
    OFFSETS_NOT_ZEROED = "offsets_not_zeroed"
    CLOCK_WENT_BACK = "clock_went_back"
    CAMERA_CLOCK_WENT_BACK = "camera_clock_went_back"
    PAIRS_MISSED = "pairs_missed"
    """Pairs that never reached the service (a gap in the sequence numbers)."""
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
    """

    t_s: float
    kind: EventKind
    text: str
    reason: str | None = None

    def to_dict(self) -> dict[str, object]:
        """JSON-ready form: ``{"t_s", "kind", "text"}`` (and ``"reason"`` when set)."""
        out: dict[str, object] = {"t_s": self.t_s, "kind": self.kind.value, "text": self.text}
        if self.reason is not None:
            out["reason"] = self.reason
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

    def emit(self, t_s: float, kind: EventKind, text: str, *, reason: str | None = None) -> None:
        """Record one event and hand it to ``on_event``."""
        event = ServiceEvent(t_s, kind, text, reason)
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
