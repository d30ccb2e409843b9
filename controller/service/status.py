"""A read-only snapshot of the service for displays and servers (OPC UA, a web page, ``serve``).

``Service.status()`` returns a :class:`ServiceStatus`: frozen, built from the parts' state at
the moment of the call, safe to hand to another thread; ``to_dict()`` gives plain JSON.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from controller.quality.schema import vision_fields
from controller.service.frame_result import FrameResult


def _json_float(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def _number(v: object) -> float | None:
    try:
        return float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None


@dataclass(frozen=True)
class MeasurementSummary:
    """The last pair the service handled, in brief.

    Attributes
    ----------
    seq : int
        The pair's sequence number.
    ok : bool
        Measured and plausible.
    error : str or None
        Why not.
    pitch_mm : float or None
        Pitch per knife pass, mm (``ok`` pairs).
    uniformity_cv : float or None
        Mark-width coefficient of variation (``ok`` pairs).
    applied : bool
        Whether setpoints were updated from it.
    t_s : float
        Service time of its arrival, s.
    latency_ms : float
        Arrival to setpoints on the wire, ms.
    roll_deg : float or None
        The camera's roll the vision measured on the pair, degrees.
    calibration_state : str or None
        The self-calibration: ``off``, ``applied`` or ``untrusted`` (``None``: not known).
    calibration_gain : float or None
        Its photometric gain (``applied`` / ``untrusted``).
    depth_um, kinematic_depth_um : float or None
        Mark depth, photometric (calibrated) and from the kinematics, um (``ok`` pairs).
    """

    seq: int
    ok: bool
    error: str | None
    pitch_mm: float | None
    uniformity_cv: float | None
    applied: bool
    t_s: float
    latency_ms: float
    roll_deg: float | None = None
    calibration_state: str | None = None
    calibration_gain: float | None = None
    depth_um: float | None = None
    kinematic_depth_um: float | None = None

    @classmethod
    def of(cls, r: FrameResult) -> MeasurementSummary:
        """The summary of a frame result."""
        pitch = r.reported_pitch_mm
        cv = r.reported_uniformity_cv
        vis = vision_fields(r.measurement, ok=r.ok) if r.measurement is not None else {}
        depth = _json_float(_number(getattr(r.measurement, "depth_um", None))) if r.ok else None
        return cls(
            seq=int(r.seq),
            ok=bool(r.ok),
            error=r.error,
            pitch_mm=None if pitch is None else float(pitch),
            uniformity_cv=None if cv is None else float(cv),
            applied=bool(r.applied),
            t_s=float(r.t_s),
            latency_ms=float(r.latency_s) * 1e3,
            roll_deg=vis.get("roll_deg"),
            calibration_state=vis.get("calibration_state"),
            calibration_gain=vis.get("calibration_gain"),
            depth_um=depth,
            kinematic_depth_um=vis.get("kinematic_depth_um"),
        )


@dataclass(frozen=True)
class ServiceStatus:
    """What the service is doing now.

    Attributes
    ----------
    t_s : float or None
        Service time of the last cycle or pair, s (``None`` before the first).
    state : str
        ``"run"`` or ``"safe"``.
    safe_reason : str or None
        Why it is safe (``"plc gone, can gone"``, ``"confirming recovery"``); ``None`` in RUN.
    missing : tuple of str
        Sources gone and conditions failing (``controller.service.supervisor.SOURCES`` names).
    feed_setpoint_mm_s : float or None
        Feed setpoint in force, mm/s.
    feed_actual_mm_s : float or None
        The PLC's last reported actual feed, mm/s.
    offsets_um : tuple of float
        Piezo offsets in force, um.
    amplifier_enabled : bool
        Whether the amplifier is commanded on.
    last_measurement : MeasurementSummary or None
        The last pair handled.
    counters : Mapping[str, int]
        The service's counters (``frames``, ``ok``, ``failed``, ``applied``, ...), read-only.
    log_problem : str or None
        The quality log's trouble in one line; ``None`` when healthy.
    records_pending : int
        Quality records kept aside (journal or memory) waiting for the log.
    alerts : Mapping or None
        What the operator must be told (``controller.service.alerts.OperatorAlerts.describe``):
        ``target_unreachable`` (its reason, the target and the pitch the machine can hold),
        ``measurements_failing`` (failed of the last pairs, the last error) while they last, and
        the last ``knife_chipped`` (knife, runout step); ``None`` values when there is nothing.
    piezo_limits : Mapping or None
        The bound on the piezo offsets in force and where it comes from (the amplifier's
        reported stroke or ``machine.toml``'s, ``controller.service.actuators.Actuators.limits``).
    uniformity : Mapping or None
        The uniformity loop's state (``controller.laws.uniformity_status.describe_loop``): what
        it does (``status``, ``hold_reason``), the actuator's gain, phase, confidence and state
        per knife pattern (``modes``), the patterns it cannot move (``held_modes``), the best
        table measured; ``None`` before the loops exist.
    """

    t_s: float | None
    state: str
    safe_reason: str | None
    missing: tuple[str, ...]
    feed_setpoint_mm_s: float | None
    feed_actual_mm_s: float | None
    offsets_um: tuple[float, ...]
    amplifier_enabled: bool
    last_measurement: MeasurementSummary | None
    counters: Mapping[str, int]
    log_problem: str | None = None
    records_pending: int = 0
    alerts: Mapping[str, Any] | None = None
    piezo_limits: Mapping[str, Any] | None = None
    uniformity: Mapping[str, Any] | None = None
    knife_condition: Mapping[str, Any] | None = None

    @staticmethod
    def freeze(counters: Mapping[str, int]) -> Mapping[str, int]:
        """A read-only copy of ``counters``."""
        return MappingProxyType(dict(counters))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON (no NaN): the fields, ``last_measurement`` as a dict or ``None``."""
        last = self.last_measurement
        return {
            "t_s": self.t_s,
            "state": self.state,
            "safe_reason": self.safe_reason,
            "missing": list(self.missing),
            "feed_setpoint_mm_s": _json_float(self.feed_setpoint_mm_s),
            "feed_actual_mm_s": _json_float(self.feed_actual_mm_s),
            "offsets_um": [_json_float(v) for v in self.offsets_um],
            "amplifier_enabled": self.amplifier_enabled,
            "last_measurement": None if last is None else {
                "seq": last.seq, "ok": last.ok, "error": last.error,
                "pitch_mm": _json_float(last.pitch_mm),
                "uniformity_cv": _json_float(last.uniformity_cv),
                "applied": last.applied, "t_s": last.t_s, "latency_ms": last.latency_ms,
                "roll_deg": _json_float(last.roll_deg),
                "calibration_state": last.calibration_state,
                "calibration_gain": _json_float(last.calibration_gain),
                "depth_um": _json_float(last.depth_um),
                "kinematic_depth_um": _json_float(last.kinematic_depth_um),
            },
            "counters": dict(self.counters),
            "log_problem": self.log_problem,
            "records_pending": self.records_pending,
            "alerts": None if self.alerts is None else {
                k: None if v is None else dict(v) for k, v in self.alerts.items()},
            "piezo_limits": None if self.piezo_limits is None else dict(self.piezo_limits),
            "uniformity": None if self.uniformity is None else dict(self.uniformity),
            "knife_condition": None if self.knife_condition is None
            else dict(self.knife_condition),
        }
