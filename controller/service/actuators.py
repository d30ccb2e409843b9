"""Actuator outputs: the PLC's feed setpoint and heartbeat, the piezo offsets and commands.

One :class:`Actuators` owns what the service puts on the two buses and remembers what is in
force: the feed setpoint the PLC took, the offsets the amplifier got, the heartbeat and alive
counters. Bus trouble is counted (``plc_errors``, ``can_errors``) and a refused feed setpoint
reported once (``FEED_REFUSED`` ... ``FEED_ACCEPTED``); nothing here decides *what* to send.

The piezo offsets stay within the bound the CAN client holds (``controller/laws/limits.py``: the
smaller of the amplifier's reported stroke and ``machine.toml``'s, narrowed by refused tables,
zero until the amplifier has reported). Each change of that bound is reported once
(``PIEZO_LIMITS`` events, one line saying which stroke is used and why), each refused table too
(``OFFSETS_REFUSED``, counter ``tables_refused``), and the control loops are told the bound in
force (``on_stroke``: ``ControlLoops.set_limit_um``, see :meth:`Actuators.sync_loop_limit`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from controller.fieldbus.piezo_client import PiezoClient
from controller.fieldbus.plc_client import PlcClient
from controller.service.events import EventKind, EventLog, exc_name
from controller.service.supervisor import AmplifierMonitor
from core.errors import FieldbusError, ModbusRefused

_LOG = logging.getLogger("controller.service.service")


class Actuators:
    """The service's writes to the PLC and the piezo amplifier.

    Parameters
    ----------
    plc : PlcClient
        The one PLC connection.
    piezo : PiezoClient
        The one CAN connection to the amplifier.
    report : EventLog
        Events and counters.
    amp_monitor : AmplifierMonitor
        Told what the amplifier is commanded to do at each command (RPDO3).
    stroke_um : float
        ``machine.toml``'s stroke, um; the bound in force is the CAN client's
        (:attr:`PiezoClient.limit`), never above the smaller of this and the amplifier's.
    owns_feed : bool
        This service writes the PLC's feed setpoint and heartbeat (a single head). ``False``:
        one head of a moulder, whose feed and heartbeat the moulder's coordinator writes
        (:mod:`controller.moulder.feed`); the head's feed proposals then go nowhere
        (:meth:`write_feed` returns ``True`` without a request) and the feed in force is the
        PLC's, read back every cycle.
    """

    def __init__(
        self,
        plc: PlcClient,
        piezo: PiezoClient,
        report: EventLog,
        amp_monitor: AmplifierMonitor,
        *,
        stroke_um: float,
        owns_feed: bool = True,
    ) -> None:
        self.plc = plc
        self.owns_feed = bool(owns_feed)
        self.piezo = piezo
        self._report = report
        self._amp_monitor = amp_monitor
        self.config_stroke_um = float(stroke_um)
        self.on_stroke: Callable[[float, float], Any] | None = None
        """``on_stroke(limit_um, t)``: the control loops told the bound in force (they return
        the offsets to apply, or ``None``): ``ControlLoops.set_limit_um``."""
        self._loop_limit: float | None = None  # the bound the loops were last told
        self.heartbeat = 0
        """The PLC heartbeat register's value (16 bits), one step per PLC cycle."""
        self.alive = 0
        """The CAN alive counter (8 bits), one step per command (RPDO3)."""
        self.feed_setpoint_mm_s: float | None = None
        """The feed setpoint in force (the last one the PLC took, or read back), mm/s."""
        self.offsets_um: tuple[float, ...] = ()
        """The piezo offsets in force (as sent), um."""
        self._feed_refused = False

    # ------------------------------------------------------------------ PLC
    async def beat(self) -> None:
        """Write the next heartbeat value (``FieldbusError`` if the PLC does not take it)."""
        if not self.owns_feed:  # a moulder's head: the coordinator beats
            return
        self.heartbeat = (self.heartbeat + 1) & 0xFFFF
        await self.plc.write_heartbeat(self.heartbeat)

    async def write_feed(self, feed_mm_s: float, t: float) -> bool:
        """Write the feed setpoint; whether the PLC took it (a refusal is reported once).

        A moulder's head (``owns_feed`` false) writes nothing and returns ``True``: the
        coordinator decides the one feed from every head's learnt correction.
        """
        if not self.owns_feed:
            return True
        try:
            await self.plc.write_feed(feed_mm_s)
        except ModbusRefused as exc:
            self._feed_not_taken(t, f"feed setpoint refused: {exc}")
            return False
        except FieldbusError:
            self._report.count("plc_errors")
            return False
        except ValueError as exc:  # outside the limits the PLC reported: never sent
            self._feed_not_taken(t, f"feed setpoint not sent: {exc}")
            return False
        if self._feed_refused:
            self._feed_refused = False
            self._report.emit(t, EventKind.FEED_ACCEPTED, "feed setpoint accepted again")
        self.feed_setpoint_mm_s = feed_mm_s
        return True

    def _feed_not_taken(self, t: float, text: str) -> None:
        self._report.count("setpoint_refused")
        if not self._feed_refused:  # once until a write goes through again
            self._feed_refused = True
            self._report.emit(t, EventKind.FEED_REFUSED, text)

    # ------------------------------------------------------------------ piezo
    def set_knives(self, knives: int) -> None:
        """A machine with ``knives`` knives: the amplifier's table and zero offsets."""
        if self.piezo.knives != knives:
            self.piezo.set_knives(knives)
        self.offsets_um = (0.0,) * knives

    def enable(self, on: bool, t: float) -> None:
        """Enable or disable the amplifier (goes out with the next command)."""
        self.piezo.set_enable(on, now_s=t)

    @property
    def stroke_um(self) -> float:
        """The bound on every piezo offset now, um (the CAN client's: 0 until reported)."""
        return self.piezo.stroke_um

    def set_offsets(self, offsets_um: Sequence[float] | np.ndarray, t: float) -> tuple[float, ...]:
        """Send per-knife offsets within the bound in force; the offsets as sent.

        A table beyond the bound is re-planned (nearest table with the same mean inside it).

        Raises
        ------
        FieldbusError
            The bus refused the frame (the offsets in force stay what they were).
        """
        self.offsets_um = self.piezo.set_offsets(np.asarray(offsets_um, dtype=float), now_s=t)
        return self.offsets_um

    def zero_offsets(self, t: float, safe_offsets_um: Sequence[float] | None = None) -> None:
        """Disable the amplifier and send the safe offsets (zero): the safe piezo state.

        Raises
        ------
        FieldbusError
            The bus refused the frame.
        """
        k = self.piezo.knives
        if not k:
            return
        self.piezo.set_enable(False, now_s=t)
        offs = (0.0,) * k if safe_offsets_um is None else safe_offsets_um
        self.offsets_um = self.piezo.set_offsets(offs, now_s=t)

    def command(self, t: float) -> None:
        """The command (RPDO3) with a new alive counter (the amplifier's setpoint timeout).

        A bus that refuses it is counted (``can_errors``), not raised: the amplifier's own
        timeout ramps its offsets to zero.
        """
        self._amp_monitor.commanded(self.piezo.enable, now_s=t)
        following = (self.alive + 1) & 0xFF
        try:
            if self.piezo.tick(alive_counter=following, now_s=t):
                self.alive = following  # only a command sent moves it: none skipped
        except FieldbusError:
            self._report.count("can_errors")
        self.offsets_um = self.piezo.offsets_um  # a re-planned table is the one in force
        self.report_limits(t)
        self.sync_loop_limit(t)

    # ------------------------------------------------------------------ limits
    def report_limits(self, t: float) -> None:
        """Report what the CAN client noted: the bound changed, a table refused, an EMCY."""
        for note in self.piezo.take_notes():
            if note.kind == "emergency":  # the amplifier's EMCY; its status bits drive safety
                self._report.count("amp_emergencies")
                _LOG.warning("%s", note.text)
            elif note.kind == "refused":
                self._report.count("tables_refused")
                _LOG.warning("%s", note.text)
                self._report.emit(t, EventKind.OFFSETS_REFUSED, note.text, data=note.data)
            else:
                _LOG.info("%s", note.text)
                self._report.emit(t, EventKind.PIEZO_LIMITS, note.text, data=note.data)

    def sync_loop_limit(self, t: float) -> None:
        """Tell the control loops the bound in force (``on_stroke``) when it changed.

        The uniformity loop then plans within it (keeping its own margin) and returns the
        offsets to apply, re-planned if the table in force does not fit: sent at once while the
        amplifier is enabled (in the safe state they wait for the recovery, which restores
        them). Until the amplifier reported its limits nothing is told (the client holds the
        offsets at zero meanwhile).
        """
        limit = self.piezo.stroke_um
        if self.on_stroke is None or self.piezo.limit.stroke_um is None or limit <= 0.0:
            return
        if self._loop_limit is not None and abs(self._loop_limit - limit) < 1e-9:
            return
        offs = self.on_stroke(limit, t)
        self._loop_limit = limit
        if offs is not None and self.piezo.enable:
            try:
                self.set_offsets(offs, t)
            except FieldbusError:
                self._report.count("can_errors")

    def limits(self) -> dict[str, Any]:
        """The bound in force, its origin, the refused tables and reconnects (plain JSON).

        ``OffsetLimit.to_dict()`` plus ``tables_refused`` and ``reconnects``: for the status,
        the quality records and the HIL summary.
        """
        return {
            **self.piezo.limit.to_dict(),
            "tables_refused": self.piezo.tables_refused,
            "reconnects": self.piezo.reconnects,
        }

    def leave_safe(self, t: float) -> str | None:
        """At close: amplifier disabled with zero offsets, one last command; the problem or None."""
        try:
            self.zero_offsets(t)
            self.alive = (self.alive + 1) & 0xFF
            self.piezo.send_command(alive_counter=self.alive, now_s=t)
        except (FieldbusError, ValueError) as exc:  # closing goes on; the amplifier times out
            return f"{exc_name(exc)}: {exc}"
        return None

    def record_fields(self) -> dict[str, Any]:
        """What each quality record carries of the piezo's limits (``extra["piezo"]``).

        ``limit_um`` and its ``source`` now, and the running counts ``tables_refused`` and
        ``safe_entries``: a jump between two records shows a refused table or a safe-state
        entry between them, even one no pair was measured in.
        """
        lim = self.piezo.limit
        return {
            "limit_um": lim.limit_um,
            "source": lim.source,
            "tables_refused": self._report.counters.get("tables_refused", 0),
            "safe_entries": self._report.counters.get("safe_entries", 0),
        }

    def describe(self) -> dict[str, Any]:
        """What is in force: ``feed_setpoint_mm_s``, ``offsets_um``, ``enabled``."""
        return {
            "feed_setpoint_mm_s": self.feed_setpoint_mm_s,
            "offsets_um": tuple(self.offsets_um),
            "enabled": bool(self.piezo.enable),
        }
