"""Supervisor stage and safe state: what the service watches, and what it does when it must stop.

:class:`SafeStateKeeper` wraps the pure :class:`~controller.service.supervisor.Supervisor`
(timeouts and
conditions) and the :class:`~controller.service.supervisor.AmplifierMonitor` with the service's
side of
them: it judges the PLC's registers and the amplifier's status, steps the supervisor, reports
safe-state entries (``SAFE_STATE`` with its ``reason`` and, in ``data``, the sources ``missing``
and the recovery time of the back-off) and recoveries, and puts the piezo in its safe state at
once (offsets zero, amplifier disabled) whichever cycle noticed.

It also holds the service's one supervisor boundary (:meth:`SafeStateKeeper.boundary`): the
only place in ``controller/`` that catches a bare ``Exception``. Every entry point (each bus
cycle, each pair, the frame task) runs its own code inside it; an error nobody expected is
logged with its traceback, recorded (``SERVICE_ERROR``, counter ``errors``), fails the
``service`` condition and puts the machine in the safe state while the heartbeats go on.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from config.machine import SafetyConfig
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.service.actuators import Actuators
from controller.service.events import EventKind, EventLog, exc_name
from controller.service.supervisor import AmplifierMonitor, SafetyState, SafetyStatus, Supervisor
from core.errors import FieldbusError

_LOG = logging.getLogger("controller.service.service")

REASONS = {
    "plc": "plc gone",
    "can": "can gone",
    "measurement": "measurement gone",
    "machine": "machine not running",
    "plc_data": "plc data invalid",
    "amplifier": "piezo amplifier not tracking",
    "log": "quality log failing",
    "service": "service error",
}
"""How each missing source or failing condition reads in a safe-state reason."""


@dataclass
class Guarded:
    """What :meth:`SafeStateKeeper.boundary` saw: ``failed``, the error, the status it left."""

    failed: bool = False
    status: SafetyStatus | None = None
    error: BaseException | None = None


class Boundary:
    """The context of :meth:`SafeStateKeeper.boundary` (a class: entered ~10 times a pair).

    The one supervisor boundary of the service (every entry point runs inside it): the
    service must survive anything its own code does -- the heartbeats go on, the machine
    goes to the safe state and the fault is recorded -- so here, and only here, any
    ``Exception`` is caught (:meth:`SafeStateKeeper.fault`); a ``BaseException`` that is not
    one (a cancellation) goes on. Expected trouble (buses, vision, log) is handled by name
    where it arises.
    """

    __slots__ = ("_keeper", "_t", "_where", "_part", "_guarded")

    def __init__(self, keeper: SafeStateKeeper, t: float, where: str, part: str) -> None:
        self._keeper, self._t, self._where, self._part = keeper, t, where, part
        self._guarded = Guarded()

    def __enter__(self) -> Guarded:
        return self._guarded

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> bool:
        if exc is None or not isinstance(exc, Exception):
            return False
        guarded = self._guarded
        guarded.failed = True
        guarded.error = exc
        guarded.status = self._keeper.fault(self._t, self._where, exc, part=self._part)
        return True


class SafeStateKeeper:
    """The supervisor with the service's reports and safe-state actions.

    Parameters
    ----------
    cfg : SafetyConfig
        Timeouts, recovery time and the safe action.
    report : EventLog
        Events and counters.
    actuators : Actuators
        Where the safe piezo state goes (zero offsets, disabled).
    amp_monitor : AmplifierMonitor
        The judge of the amplifier's status (shared with the actuators).
    now_s : float
        Start time (service clock), s.
    """

    def __init__(
        self,
        cfg: SafetyConfig,
        report: EventLog,
        actuators: Actuators,
        amp_monitor: AmplifierMonitor,
        *,
        now_s: float,
    ) -> None:
        self.supervisor = Supervisor(cfg, now_s=now_s)
        self.amp_monitor = amp_monitor
        self._report = report
        self._actuators = actuators
        self.on_recovered: Callable[[float], None] | None = None
        """Called on the return to RUN (the loops restart from the feed in force)."""
        self.status: SafetyStatus | None = None
        """The supervisor's last decision (``None`` before the first cycle)."""
        self.plc_problem: str | None = None
        self.amp_problem: str | None = None
        self._faulty: set[str] = set()  # parts whose last run raised: "plc", "can", "pair"
        self.last_error: str | None = None

    @property
    def state(self) -> SafetyState:
        """The supervisor's state."""
        return self.supervisor.state

    def describe(self, missing: Sequence[str]) -> str:
        """A safe-state reason: ``"plc gone, plc data invalid (knives 9 ...)"`` or ``"start"``."""
        parts = []
        for m in missing:
            text = REASONS.get(m, f"{m} gone")
            if m == "plc_data" and self.plc_problem:
                text += f" ({self.plc_problem})"
            if m == "amplifier" and self.amp_problem:
                text += f" ({self.amp_problem})"
            parts.append(text)
        return ", ".join(parts) or "start"

    def safe_reason(self) -> str | None:
        """Why the service is in the safe state now (``None`` in RUN)."""
        if self.supervisor.state is not SafetyState.SAFE:
            return None
        missing = self.status.missing if self.status is not None else ()
        return self.describe(missing) if missing else "confirming recovery"

    # ------------------------------------------------------------------ judging
    def check_snapshot(self, snap: PlcSnapshot, t: float) -> PlcSnapshot | None:
        """``snap`` if its registers make sense, else ``None`` (reported, supervisor told)."""
        problem = snap.problem()
        if problem != self.plc_problem:
            if problem is not None:
                self._report.emit(t, EventKind.PLC_DATA_INVALID, f"PLC data invalid: {problem}")
            elif self.plc_problem is not None:
                self._report.emit(t, EventKind.PLC_DATA_VALID, "PLC data valid again")
        self.plc_problem = problem
        self.supervisor.set_ok("plc_data", problem is None)
        return snap if problem is None else None

    def observe_amplifier(self, status: Any, t: float) -> None:
        """Judge the amplifier's last status; a confirmed problem fails the condition."""
        problem = self.amp_monitor.observe(status, now_s=t)
        if problem is not None and self.amp_problem is None:
            self._report.count("amp_faults")
            self._report.emit(t, EventKind.AMPLIFIER_PROBLEM, f"piezo amplifier: {problem}")
        elif problem is None and self.amp_problem is not None:
            self._report.emit(t, EventKind.AMPLIFIER_HEALTHY, "piezo amplifier healthy again")
        self.amp_problem = problem
        self.supervisor.set_ok("amplifier", problem is None)

    # ------------------------------------------------------------------ deciding
    def step(self, t: float) -> SafetyStatus:
        """Step the supervisor; on entering SAFE zero the offsets at once, on RUN resume."""
        sup = self.supervisor
        safe_since = sup.since_s
        status = sup.step(t)
        self.status = status
        if status.changed:
            if status.state is SafetyState.SAFE:
                self._report.count("safe_entries")
                reason = self.describe(status.missing)
                wait = sup.recovery_required_s
                again = f" (recovery after {wait:.2f} s: back-off)" if sup.backoff_level > 1 else ""
                self._report.emit(t, EventKind.SAFE_STATE, f"safe state: {reason}{again}",
                                  reason=reason, data={"missing": list(status.missing),
                                                       "recovery_s": wait,
                                                       "backoff_level": sup.backoff_level})
                self.zero_offsets(t)  # at once, whichever cycle noticed (non-blocking CAN)
            else:
                self._report.count("recoveries")
                self._report.emit(t, EventKind.RECOVERED, "recovered: control resumed",
                                  data={"safe_s": t - safe_since})
                if self.on_recovered is not None:
                    self.on_recovered(t)
        return status

    def zero_offsets(self, t: float) -> bool:
        """The safe piezo state (offsets zero, disabled); whether the bus took it."""
        try:
            self._actuators.zero_offsets(
                t, self.supervisor.safe_offsets_um(self._actuators.piezo.knives)
            )
        except FieldbusError:
            self._report.count("can_errors")
            return False
        return True

    def clean(self, part: str) -> None:
        """A run of ``part`` ended without an unexpected error (clears it and a pair's)."""
        self._faulty.discard(part)
        self._faulty.discard("pair")
        self.supervisor.set_ok("service", not self._faulty)

    def report_once(self, t: float, kind: EventKind, text: str) -> None:
        """Report ``text`` unless it is the last error reported (the same every cycle)."""
        if text != self.last_error:
            self.last_error = text
            self._report.emit(t, kind, text)

    # ------------------------------------------------------------------ the boundary
    def boundary(self, t: float, where: str, *, part: str = "pair") -> Boundary:
        """Run the body; an unexpected error of the service's own code becomes a safe state.

        ``part`` (``"plc"``, ``"can"``, ``"pair"``, ``"source"``) is cleared by the next clean
        run of that part (a pair's error by any clean run); until then the ``service``
        condition fails. The body's ``Guarded`` (``with keeper.boundary(...) as g``) says
        whether it failed.
        """
        return Boundary(self, t, where, part)

    def fault(self, t: float, where: str, exc: BaseException, *, part: str) -> SafetyStatus:
        """Record an unexpected error, go safe (offsets zero, disabled), keep the beat."""
        self._report.count("errors")
        self._faulty.add(part)
        self.supervisor.set_ok("service", False)
        text = f"service error in {where}: {exc_name(exc)}: {exc}"
        if text != self.last_error:  # the same error every cycle is reported once
            _LOG.error("%s", text, exc_info=exc)
        self.report_once(t, EventKind.SERVICE_ERROR, text)
        if not self.zero_offsets(t):
            self._report.emit(t, EventKind.OFFSETS_NOT_ZEROED,
                              "piezo offsets could not be zeroed: the CAN bus refused them")
        status = self.step(t)
        self._actuators.command(t)
        return status
