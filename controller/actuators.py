"""Actuator outputs: the PLC's feed setpoint and heartbeat, the piezo offsets and commands.

One :class:`Actuators` owns what the service puts on the two buses and remembers what is in
force: the feed setpoint the PLC took, the offsets the amplifier got, the heartbeat and alive
counters. Bus trouble is counted (``plc_errors``, ``can_errors``) and a refused feed setpoint
reported once (``FEED_REFUSED`` ... ``FEED_ACCEPTED``); nothing here decides *what* to send.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from controller.events import EventKind, EventLog, exc_name
from controller.piezo_client import PiezoClient
from controller.plc_client import PlcClient
from controller.safety import AmplifierMonitor
from core.errors import FieldbusError, ModbusRefused


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
        Told what the amplifier is commanded to do at each ``PIEZO_COMMAND``.
    stroke_um : float
        Offsets are clipped to ``[-stroke_um, stroke_um]``, um.
    """

    def __init__(
        self,
        plc: PlcClient,
        piezo: PiezoClient,
        report: EventLog,
        amp_monitor: AmplifierMonitor,
        *,
        stroke_um: float,
    ) -> None:
        self.plc = plc
        self.piezo = piezo
        self._report = report
        self._amp_monitor = amp_monitor
        self.stroke_um = float(stroke_um)
        self.heartbeat = 0
        """The PLC heartbeat register's value (16 bits), one step per PLC cycle."""
        self.alive = 0
        """The CAN alive counter (8 bits), one step per ``PIEZO_COMMAND``."""
        self.feed_setpoint_mm_s: float | None = None
        """The feed setpoint in force (the last one the PLC took, or read back), mm/s."""
        self.offsets_um: tuple[float, ...] = ()
        """The piezo offsets in force (as sent), um."""
        self._feed_refused = False

    # ------------------------------------------------------------------ PLC
    async def beat(self) -> None:
        """Write the next heartbeat value (``FieldbusError`` if the PLC does not take it)."""
        self.heartbeat = (self.heartbeat + 1) & 0xFFFF
        await self.plc.write_heartbeat(self.heartbeat)

    async def write_feed(self, feed_mm_s: float, t: float) -> bool:
        """Write the feed setpoint; whether the PLC took it (a refusal is reported once)."""
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

    def set_offsets(self, offsets_um: Sequence[float] | np.ndarray, t: float) -> tuple[float, ...]:
        """Send per-knife offsets, clipped to the stroke; the offsets as sent.

        Raises
        ------
        FieldbusError
            The bus refused the frame (the offsets in force stay what they were).
        """
        s = self.stroke_um
        self.offsets_um = self.piezo.set_offsets(
            np.clip(np.asarray(offsets_um, dtype=float), -s, s), now_s=t
        )
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
        """``PIEZO_COMMAND`` with a new alive counter (the amplifier's setpoint timeout).

        A bus that refuses it is counted (``can_errors``), not raised: the amplifier's own
        timeout ramps its offsets to zero.
        """
        self._amp_monitor.commanded(self.piezo.enable, now_s=t)
        self.alive = (self.alive + 1) & 0xFF
        try:
            self.piezo.tick(alive_counter=self.alive, now_s=t)
        except FieldbusError:
            self._report.count("can_errors")

    def leave_safe(self, t: float) -> str | None:
        """At close: amplifier disabled with zero offsets, one last command; the problem or None."""
        try:
            self.zero_offsets(t)
            self.alive = (self.alive + 1) & 0xFF
            self.piezo.send_command(alive_counter=self.alive, now_s=t)
        except (FieldbusError, ValueError) as exc:  # closing goes on; the amplifier times out
            return f"{exc_name(exc)}: {exc}"
        return None

    def describe(self) -> dict[str, Any]:
        """What is in force: ``feed_setpoint_mm_s``, ``offsets_um``, ``enabled``."""
        return {
            "feed_setpoint_mm_s": self.feed_setpoint_mm_s,
            "offsets_um": tuple(self.offsets_um),
            "enabled": bool(self.piezo.enable),
        }
