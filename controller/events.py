"""What the service reports as it runs: typed events, one enum kind each.

The service appends a :class:`ServiceEvent` to ``Service.events`` (and calls ``on_event``) for
every change a person or a composition (HIL summary, benchmark, OPC UA, web page) follows:
safe-state entries and recoveries, bus and amplifier problems, refused setpoints, log trouble.
Consumers test ``event.kind``; ``event.text`` is the line shown to people.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["EventKind", "ServiceEvent"]


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
    """

    t_s: float
    kind: EventKind
    text: str

    def to_dict(self) -> dict[str, object]:
        """JSON-ready form: ``{"t_s", "kind", "text"}``."""
        return {"t_s": self.t_s, "kind": self.kind.value, "text": self.text}
