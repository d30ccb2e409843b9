"""What the service did with one image pair (:class:`FrameResult`, handed to ``on_result``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class FrameResult:
    """What the service did with one image pair.

    Attributes
    ----------
    seq : int
        The pair's sequence number.
    ok : bool
        Whether the measurement succeeded and passed the plausibility checks.
    error : str or None
        Why not (``"registration failed: ..."``, ``"implausible: ..."``).
    measurement : object or None
        The vision result (``x_mm``, ``pitch_mm``, ``mark_widths_mm``, ...).
    knife_widths_mm : tuple of float
        Mean mark width per knife, mm (NaN where no mark of that knife was seen).
    applied : bool
        Whether setpoints were updated from it (``ok`` and state ``RUN``).
    feed_setpoint_mm_s : float or None
        Feed setpoint in force after the pair, mm/s.
    offsets_um : tuple of float
        Piezo offsets in force after the pair, um.
    state : str
        Supervisor state after the pair (``"run"`` / ``"safe"``).
    t_s : float
        Service time when the pair arrived, s.
    latency_s : float
        Wall-clock seconds from the pair's arrival (the call of :meth:`Service.handle_frame`)
        to its setpoints on the wire (or to the decision not to send any).
    truth : dict or None
        The simulator's truth of the imaged patch (``Frame.truth``).
    counts_a : int
        Encoder counts at trigger A (board travel).
    frame_t_s : float
        Machine time of the pair (trigger A), s.
    record_id : int or None
        Id of the quality record (``None`` while it waits in the journal).
    extra : dict
        ``timing_ms`` (``plc_read_ms``, ``measure_ms``, ``control_ms``), ``safe_reason``,
        ``passes`` (the attribution's summary), ``profile`` (a decimated profile, some pairs),
        ``plc_feed_setpoint_mm_s`` (the PLC's setpoint in force, for the record while the
        service has written none).
    """

    seq: int
    ok: bool
    error: str | None
    measurement: Any
    knife_widths_mm: tuple[float, ...]
    applied: bool
    feed_setpoint_mm_s: float | None
    offsets_um: tuple[float, ...]
    state: str
    t_s: float
    latency_s: float
    truth: dict[str, Any] | None = None
    counts_a: int = 0
    frame_t_s: float = 0.0
    record_id: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)
