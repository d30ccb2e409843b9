"""The service's CAN client of the piezo amplifier: python-can bus + the DBC codec.

The service owns one :class:`PiezoClient`. Every control cycle it calls :meth:`PiezoClient.tick`
with its heartbeat: ``PIEZO_COMMAND`` (enable, knives, alive counter) goes out every
``command_period_s``; ``PIEZO_OFFSETS_*`` go out when the offsets change and at least every
``offsets_period_s``. :meth:`PiezoClient.poll` drains received frames without blocking and keeps
the last ``PIEZO_STATUS`` / ``AMP_HEARTBEAT`` and the time the amplifier was last heard; when it
falls silent, :meth:`PiezoClient.silent_for` grows and the supervisor declares CAN gone.

Limits (``controller/laws/limits.py``'s :class:`~controller.laws.limits.OffsetLimit`): the amplifier
reports its stroke and accepted offsets in ``PIEZO_LIMITS`` (with every heartbeat); the client
sends offsets within the smaller of that and ``machine.toml``'s stroke, and zeros until the
amplifier has reported (at start, and again after every reconnect: silent for longer than
``reconnect_after_s``). A table the amplifier refuses (stroke-limit bit in ``PIEZO_STATUS``
once the table had ``refusal_grace_s`` to arrive) narrows the bound below it and is re-planned
from the offsets asked for: never resent unchanged. What changed is queued in :attr:`notes`
for the service to report.

The bus is any ``can.BusABC``: from the configuration through
:func:`open_bus` (``protocol/can_transport.py`` when present, else ``can.Bus``), or a
``virtual`` bus in tests. Time is passed in (``now_s``); nothing here reads a clock.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import can

from controller.laws.limits import AmpLimits, OffsetLimit
from core.checks import check_finite, check_int, check_positive
from core.errors import FieldbusError
from protocol.piezo_can import (
    FAULT_SETPOINT_TIMEOUT,
    FAULT_STROKE_LIMIT,
    HEARTBEAT,
    LIMITS,
    OFFSETS,
    STATUS,
    PiezoCodec,
)

RECONNECT_AFTER_S = 0.3
"""Silent for longer than this (the default CAN timeout), the amplifier is taken as reconnected
when heard again: its limits are read anew, s."""
REFUSAL_GRACE_S = 0.05
"""A stroke-limit bit counts as a refusal of the table in force once it has been out this long
(a status sent before the table arrived speaks of the one before), s."""


@dataclass(frozen=True)
class LimitNote:
    """Something about the offsets' bound the service reports (:attr:`PiezoClient.notes`).

    Attributes
    ----------
    kind : str
        ``"limits"`` (the bound changed: reported, lost at a reconnect, invalid report) or
        ``"refused"`` (a table was refused).
    t_s : float
        When, s.
    text : str
        One line for people.
    data : dict
        Plain values (``OffsetLimit.to_dict()``; for a refusal ``table_um``, ``limit_um``,
        ``replanned_um``).
    """

    kind: str
    t_s: float
    text: str
    data: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class AmpStatus:
    """The amplifier's last ``PIEZO_STATUS``.

    Attributes
    ----------
    displacement_um, temperature_c : float
        Actual displacement and temperature.
    fault : int
        Fault bits (over-temperature, stroke limit, setpoint timeout, overcurrent).
    state : int
        0 disabled, 1 enabled, 2 ramping to zero, 3 fault.
    alive_counter : int
        The amplifier's own counter.
    t_s : float
        Time received, seconds.
    """

    displacement_um: float
    temperature_c: float
    fault: int
    state: int
    alive_counter: int
    t_s: float

    @property
    def setpoint_timeout(self) -> bool:
        """Whether the amplifier reports a setpoint timeout (it ramps to zero)."""
        return bool(self.fault & FAULT_SETPOINT_TIMEOUT)


_OPEN_ERRORS: tuple[type[BaseException], ...] = (
    can.CanError,  # CanInterfaceNotImplementedError, CanInitializationError, ...
    OSError,  # no such device, permission, address in use
    ValueError,  # unknown interface or channel, bad option values
    TypeError,  # an option the interface does not take
    ImportError,  # the interface's optional package is missing
)
"""What opening a CAN bus may raise (each becomes a ``FieldbusError``)."""


def open_bus(interface: str, channel: str, options: dict[str, Any] | None = None) -> Any:
    """Open a python-can bus from configuration values.

    Uses ``protocol.can_transport.open_bus`` when that module provides it (it knows the
    project's transports: udp_multicast in a private network namespace, remote, socketcan),
    else ``can.Bus(interface=..., channel=..., **options)``.

    Raises
    ------
    FieldbusError
        The bus cannot be opened.
    """
    opts = dict(options or {})
    try:
        from protocol import can_transport  # type: ignore[attr-defined]

        opener = getattr(can_transport, "open_bus", None)
    except ImportError:
        opener = None
    try:
        if opener is not None:
            return opener(interface=interface, channel=channel, **opts)
        return can.Bus(interface=interface, channel=channel, **opts)
    except FieldbusError:
        raise
    except _OPEN_ERRORS as exc:  # what python-can and the transports raise for a bad bus
        raise FieldbusError(f"cannot open CAN bus {interface}:{channel}: {exc}") from None


class PiezoClient:
    """Offsets and enable to the amplifier; its status and heartbeat back.

    Parameters
    ----------
    bus : can.BusABC
        An open python-can bus (the client owns it; :meth:`close` shuts it down).
    codec : PiezoCodec
        The DBC codec (``PiezoCodec.load()``).
    knives : int
        Number of knives Z (1..8).
    command_period_s : float
        Period of ``PIEZO_COMMAND``, s.
    offsets_period_s : float
        Longest interval between two ``PIEZO_OFFSETS`` transmissions, s.
    stroke_um : float
        ``machine.toml``'s stroke: offsets stay within the smaller of it and the amplifier's
        (:attr:`limit`), um.
    reconnect_after_s : float
        Silence after which the amplifier's limits are read anew when it is heard again, s.
    refusal_grace_s : float
        Time a table has to reach the amplifier before a stroke-limit bit refuses it, s.
    send_timeout_s : float
        Longest a send may wait for room in the transmit queue, s (default
        ``min(0.005, command_period_s / 4)``): a full queue raises ``FieldbusError`` instead of
        holding up the cycle; the amplifier's setpoint timeout acts on its own.
    """

    def __init__(
        self,
        bus: Any,
        codec: PiezoCodec,
        *,
        knives: int,
        command_period_s: float = 0.02,
        offsets_period_s: float = 0.2,
        stroke_um: float = 20.0,
        reconnect_after_s: float = RECONNECT_AFTER_S,
        refusal_grace_s: float = REFUSAL_GRACE_S,
        send_timeout_s: float | None = None,
    ) -> None:
        self.bus = bus
        self.codec = codec
        self.knives = check_int("knives", knives, lo=1, hi=8)
        self.command_period_s = check_positive("command_period_s", command_period_s)
        self.offsets_period_s = check_positive("offsets_period_s", offsets_period_s)
        self.send_timeout_s = (
            min(0.005, self.command_period_s / 4)
            if send_timeout_s is None
            else min(check_positive("send_timeout_s", send_timeout_s), self.command_period_s / 2)
        )
        lo, hi = codec.signal_range(OFFSETS[0], "offset_knife_0")
        self.limit = OffsetLimit(check_positive("stroke_um", stroke_um),
                                 wire_bound_um=min(-lo, hi))
        """The bound on the offsets in force (machine.toml, the amplifier, refusals)."""
        self.reconnect_after_s = check_positive("reconnect_after_s", reconnect_after_s)
        self.refusal_grace_s = check_positive("refusal_grace_s", refusal_grace_s, allow_zero=True)
        self.enable = False
        self.offsets_um: tuple[float, ...] = (0.0,) * self.knives
        self._wanted: tuple[float, ...] = self.offsets_um  # as asked for, before the bound
        self._sent_offsets: tuple[float, ...] | None = None
        self._table_since_s: float | None = None  # when the table in force first went out
        self._table_refused = False  # the table in force was refused (re-planned once)
        self.notes: list[LimitNote] = []
        """Changes of the bound and refusals not yet reported (the service drains them)."""
        self.reconnects = 0
        self.tables_refused = 0
        self._last_command_s = float("-inf")
        self._last_offsets_s = float("-inf")
        self.last_heard_s: float | None = None
        self.status: AmpStatus | None = None
        self.nmt_state: int | None = None
        self.sent = 0
        self.received = 0
        self.send_errors = 0

    # ------------------------------------------------------------------ setpoints
    @property
    def stroke_um(self) -> float:
        """The bound on every offset now, um (:attr:`limit`; 0 until the amplifier reported)."""
        return self.limit.limit_um

    def set_knives(self, knives: int) -> None:
        """Change the number of knives (offsets reset to zero)."""
        k = check_int("knives", knives, lo=1, hi=8)
        if k != self.knives:
            self.knives = k
            self.offsets_um = (0.0,) * k
            self._wanted = self.offsets_um
            self._sent_offsets = None

    def _checked(self, offsets_um: Sequence[float]) -> tuple[float, ...]:
        vals = tuple(check_finite(f"offsets_um[{k}]", v) for k, v in enumerate(offsets_um))
        if len(vals) != self.knives:
            raise ValueError(f"offsets_um must have {self.knives} values, got {len(vals)}")
        return vals

    def _planned(self, vals: Sequence[float]) -> tuple[float, ...]:
        s = math.floor(self.limit.limit_um * 1000.0 + 1e-6) / 1000.0  # on the wire's grid
        planned = self.limit.plan(vals)
        return tuple(min(max(round(float(v), 3), -s), s) + 0.0 for v in planned)

    def clamp(self, offsets_um: Sequence[float]) -> tuple[float, ...]:
        """Offsets within the bound in force, rounded to the bus resolution (0.001 um).

        A table inside the bound is only rounded; one outside is re-planned
        (:func:`controller.laws.limits.replan_offsets`: nearest table with the same mean).
        """
        return self._planned(self._checked(offsets_um))

    def set_offsets(self, offsets_um: Sequence[float], *, now_s: float) -> tuple[float, ...]:
        """Set the per-knife offsets; sent at once when they changed.

        Returns
        -------
        tuple of float
            The offsets as sent (within :attr:`stroke_um`, 0.001 um resolution).
        """
        self._wanted = self._checked(offsets_um)
        self.offsets_um = self._planned(self._wanted)
        if self.offsets_um != self._sent_offsets:
            self._send_offsets(now_s)
        return self.offsets_um

    def _replan(self) -> None:
        """The bound changed: the offsets asked for, within it (sent by the next tick)."""
        self.offsets_um = self._planned(self._wanted)

    def _note(self, kind: str, t_s: float, text: str, data: dict[str, Any]) -> None:
        self.notes.append(LimitNote(kind, t_s, text, data))

    def take_notes(self) -> list[LimitNote]:
        """The notes not yet reported (and forget them)."""
        out, self.notes = self.notes, []
        return out

    def set_enable(self, enable: bool, *, now_s: float) -> None:
        """Enable or disable the amplifier; a change goes out with the next :meth:`tick`."""
        en = bool(enable)
        if en != self.enable:
            self.enable = en
            self._last_command_s = float("-inf")

    # ------------------------------------------------------------------ wire
    def _send(self, frame: tuple[int, bytes]) -> None:
        arb, data = frame
        msg = can.Message(arbitration_id=arb, data=data, is_extended_id=False)
        try:
            self.bus.send(msg, timeout=self.send_timeout_s)
        except (can.CanError, OSError) as exc:
            self.send_errors += 1
            raise FieldbusError(f"CAN send of 0x{arb:X} failed: {exc}") from None
        self.sent += 1

    def _send_offsets(self, now_s: float) -> None:
        for frame in self.codec.encode_offsets(self.offsets_um):
            self._send(frame)
        if self.offsets_um != self._sent_offsets:  # a new table (not the periodic repeat)
            self._table_since_s = now_s
            self._table_refused = False
        self._sent_offsets = self.offsets_um
        self._last_offsets_s = now_s

    def send_command(self, *, alive_counter: int, now_s: float) -> None:
        """Send ``PIEZO_COMMAND`` now (enable, knives, alive counter mod 256)."""
        self._send(
            self.codec.encode_command(
                enable=self.enable, knives=self.knives, alive_counter=int(alive_counter) & 0xFF
            )
        )
        self._last_command_s = now_s

    def tick(self, *, alive_counter: int, now_s: float) -> None:
        """Cyclic transmissions due at ``now_s``: the command, and the offsets if stale.

        Raises
        ------
        FieldbusError
            The bus refused a frame.
        """
        t = check_finite("now_s", now_s)
        if t - self._last_command_s >= self.command_period_s * 0.5:  # jitter never skips one
            self.send_command(alive_counter=alive_counter, now_s=t)
        if (
            self._sent_offsets != self.offsets_um
            or t - self._last_offsets_s >= self.offsets_period_s
        ):
            self._send_offsets(t)

    def poll(self, *, now_s: float, max_frames: int = 1000) -> int:
        """Drain received frames without blocking; return how many were from the amplifier."""
        heard = 0
        for _ in range(max_frames):
            try:
                msg = self.bus.recv(timeout=0.0)
            except (can.CanError, OSError, ValueError) as exc:  # a broken bus
                raise FieldbusError(f"CAN receive failed: {exc}") from None
            if msg is None:
                break
            heard += self.handle(msg.arbitration_id, bytes(msg.data), now_s=now_s)
        return heard

    def handle(self, arbitration_id: int, data: bytes, *, now_s: float) -> int:
        """Process one received frame (pure); 1 if it came from the amplifier, else 0."""
        try:
            name, sig = self.codec.decode(arbitration_id, data)
        except ValueError:
            return 0  # foreign or malformed frame: ignore
        if name not in (STATUS, HEARTBEAT, LIMITS):
            return 0  # our own frames echoed by some transports
        if self.last_heard_s is not None and now_s - self.last_heard_s > self.reconnect_after_s:
            self._reconnected(now_s)
        if name == STATUS:
            self.status = AmpStatus(
                displacement_um=float(sig["displacement_um"]),
                temperature_c=float(sig["temperature_c"]),
                fault=int(sig["fault"]),
                state=int(sig["state"]),
                alive_counter=int(sig["alive_counter"]),
                t_s=now_s,
            )
            if self.status.fault & FAULT_STROKE_LIMIT:
                self._refused(now_s)
        elif name == HEARTBEAT:
            self.nmt_state = int(sig["nmt_state"])
        else:
            self._limits_reported(sig, now_s)
        self.received += 1
        self.last_heard_s = now_s if self.last_heard_s is None else max(self.last_heard_s, now_s)
        return 1

    # ------------------------------------------------------------------ limits
    def _limits_reported(self, sig: dict[str, float | int], now_s: float) -> None:
        try:
            lim = AmpLimits.from_signals(sig)
        except ValueError as exc:  # a report that makes no sense: as if none came
            if self.limit.amp_lost():
                self._replan()
                self._note("limits", now_s, f"piezo amplifier's limits invalid ({exc}): "
                           f"{self.limit.describe()}", self.limit.to_dict())
            return
        if self.limit.amp_reported(lim):
            self._replan()
            self._note("limits", now_s, self.limit.describe(), self.limit.to_dict())

    def _reconnected(self, now_s: float) -> None:
        """Heard again after a silence: the amplifier may have restarted or been replaced."""
        self.reconnects += 1
        if self.limit.amp_lost():
            self._replan()
            self._note("limits", now_s, f"piezo amplifier heard again: "
                       f"{self.limit.describe()}", self.limit.to_dict())

    def _refused(self, now_s: float) -> None:
        """A stroke-limit bit: the table in force was refused (or drove the actuator to its end)."""
        since = self._table_since_s
        table = self._sent_offsets
        if (table is None or since is None or self._table_refused
                or now_s - since < self.refusal_grace_s):
            return  # nothing sent yet, already re-planned, or the status predates the table
        self._table_refused = True
        self.tables_refused += 1
        limit = self.limit.table_refused(table)
        if limit is not None:
            self._replan()
        replanned = None if limit is None else list(self.offsets_um)
        if limit is None:
            text = (f"piezo amplifier refused the zero table {list(table)} µm: nothing smaller "
                    "to send")
        else:
            text = (f"piezo amplifier refused the table {list(table)} µm: re-planned within "
                    f"+-{limit:.3f} µm as {replanned} µm")
        self._note("refused", now_s, text, {"table_um": list(table), "limit_um": limit,
                                            "replanned_um": replanned})

    def silent_for(self, now_s: float) -> float:
        """Seconds since the amplifier was last heard (infinite if never)."""
        if self.last_heard_s is None:
            return float("inf")
        return now_s - self.last_heard_s

    def close(self) -> None:
        """Shut the bus down."""
        try:
            self.bus.shutdown()
        except (can.CanError, OSError, ValueError, AttributeError):  # a broken bus: closing goes on
            pass
