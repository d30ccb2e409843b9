"""The service's CAN client of the piezo amplifier: a CANopen master of one node over python-can.

The service owns one :class:`PiezoClient`. Under it is :mod:`controller.fieldbus.canopen_amp`
(:class:`~controller.fieldbus.canopen_amp.AmpBus` and the amplifier's
:class:`~controller.fieldbus.canopen_amp.CanopenAmplifier`, built from ``config/piezo_amp.eds``).
Every control cycle the service calls :meth:`PiezoClient.tick` with its alive counter: the
command (RPDO3: enable, knives, alive counter) goes out every ``command_period_s``; the offset
table (RPDO1, and RPDO2 for more than four knives) when it changes and at least every
``offsets_period_s``. :meth:`PiezoClient.poll` drains received frames without blocking, reads
the amplifier's limits by SDO once it is heard and starts it (NMT), and keeps the last status
(TPDO1), its heartbeat and when it was last heard: when it falls silent,
:meth:`PiezoClient.silent_for` grows and the supervisor declares CAN gone. Its loss as a node
is its heartbeat's (the heartbeat consumer): heard again after that, it is a reconnect.

Limits (``controller/laws/limits.py``'s :class:`~controller.laws.limits.OffsetLimit`): the amplifier
reports its stroke and accepted offsets in its dictionary (``0x2200``, read by SDO); the client
sends offsets within the smaller of that and ``machine.toml``'s stroke, and zeros until the
amplifier has reported (at start, and again after every reconnect: booted again, or heard
again after its heartbeat was lost). A table the amplifier refuses (stroke-limit bit in its
status once the table had ``refusal_grace_s`` to arrive) narrows the bound below it and is
re-planned from the offsets asked for: never resent unchanged. What changed is queued in
:attr:`notes` for the service to report, with the amplifier's emergencies (EMCY).

The bus is any ``can.BusABC``: from the configuration through :func:`open_bus`
(``protocol/can_transport.py``), or a ``virtual`` bus in tests. Time is passed in (``now_s``);
nothing here runs a thread, and a poll blocks only while the limits are read, a few
milliseconds at most (``AmpBus.sdo_wait_s``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from controller.fieldbus.canopen_amp import SEND_TIMEOUT_S, AmpBus, CanopenAmplifier
from controller.laws.limits import AmpLimits, OffsetLimit
from core.checks import check_finite, check_int, check_positive
from core.errors import FieldbusError
from protocol.piezo_canopen import MAX_KNIVES, AmpFault

DEFAULT_NODE_ID = 2
"""The amplifier's node id unless configured (``[can] node_id``)."""
WIRE_BOUND_UM = 32.767
"""The largest offset the table carries (INTEGER16, 1 nm per bit), um."""
REFUSAL_GRACE_S = 0.05
"""A stroke-limit bit counts as a refusal of the table in force once it has been out this long
(a status sent before the table arrived speaks of the one before), s."""


@dataclass(frozen=True)
class LimitNote:
    """Something about the offsets' bound the service reports (:attr:`PiezoClient.notes`).

    Attributes
    ----------
    kind : str
        ``"limits"`` (the bound changed: reported, lost at a reconnect, invalid report),
        ``"refused"`` (a table was refused) or ``"emergency"`` (the amplifier sent an EMCY).
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
    """The amplifier's last status (TPDO1).

    Attributes
    ----------
    displacement_um, temperature_c : float
        Actual displacement and temperature.
    fault : int
        Fault bits (over-temperature, stroke limit, setpoint timeout, overcurrent).
    state : int
        0 disabled, 1 enabled, 2 ramping to zero, 3 fault.
    t_s : float
        Time received, seconds.
    """

    displacement_um: float
    temperature_c: float
    fault: int
    state: int
    t_s: float

    @property
    def setpoint_timeout(self) -> bool:
        """Whether the amplifier reports a setpoint timeout (it ramps to zero)."""
        return bool(self.fault & AmpFault.SETPOINT_TIMEOUT)


_OPEN_ERRORS: tuple[type[BaseException], ...] = (
    can.CanError,  # CanInterfaceNotImplementedError, CanInitializationError, ...
    OSError,  # no such device, permission, address in use
    ValueError,  # unknown interface or channel, bad option values
    TypeError,  # an option the interface does not take
    ImportError,  # the interface's optional package is missing
)
"""What opening a CAN bus may raise (each becomes a ``FieldbusError``)."""


def default_send_timeout_s(command_period_s: float) -> float:
    """The longest a send waits for room in the transmit queue unless given, s.

    ``min(SEND_TIMEOUT_S, command_period_s / 4)``: a full queue never holds up a cycle.
    """
    return min(SEND_TIMEOUT_S, command_period_s / 4)


def open_bus(interface: str, channel: str, options: dict[str, Any] | None = None) -> Any:
    """Open a python-can bus from configuration values.

    Uses ``protocol.can_transport.open_bus`` (it knows the project's transports: udp_multicast
    in a private network namespace, remote, socketcan).

    Raises
    ------
    FieldbusError
        The bus cannot be opened.
    """
    from protocol import can_transport

    try:
        return can_transport.open_bus(interface=interface, channel=channel, **dict(options or {}))
    except FieldbusError:
        raise
    except _OPEN_ERRORS as exc:  # what python-can and the transports raise for a bad bus
        raise FieldbusError(f"cannot open CAN bus {interface}:{channel}: {exc}") from None


class PiezoClient:
    """Offsets and enable to the amplifier; its status and heartbeat back (a CANopen master).

    Parameters
    ----------
    bus : can.BusABC
        An open python-can bus (the client owns it; :meth:`close` shuts it down).
    knives : int
        Number of knives Z (1..8).
    node_id : int
        The amplifier's node id (1..127, ``[can] node_id``).
    eds : Path, optional
        The amplifier's EDS file (default ``config/piezo_amp.eds``).
    command_period_s : float
        Period of the command (RPDO3), s.
    offsets_period_s : float
        Longest interval between two transmissions of the offset table, s.
    stroke_um : float
        ``machine.toml``'s stroke: offsets stay within the smaller of it and the amplifier's
        (:attr:`limit`), um.
    heartbeat_lost_after : float
        Heartbeat periods of silence after which the amplifier is lost: heard again, it is a
        reconnect and its limits are read anew.
    refusal_grace_s : float
        Time a table has to reach the amplifier before a stroke-limit bit refuses it, s.
    send_timeout_s : float
        Longest a send may wait for room in the transmit queue, s (default
        ``min(0.005, command_period_s / 4)``): a full queue raises ``FieldbusError`` instead of
        holding up the cycle; the amplifier's setpoint timeout acts on its own. Not with
        ``ampbus`` (``ValueError``): the shared master's own is in force.
    ampbus : AmpBus, optional
        A master the client shares with other heads' clients (one CAN connection for every
        amplifier of a moulder: each frame received and decoded once). ``bus`` is then
        ``ampbus.bus``, or ``None``; the client does not own it (:meth:`close` leaves it open,
        its opener closes it) and serves only its own node.
    """

    def __init__(
        self,
        bus: Any,
        *,
        knives: int,
        node_id: int = DEFAULT_NODE_ID,
        eds: str | Path | None = None,
        command_period_s: float = 0.02,
        offsets_period_s: float = 0.2,
        stroke_um: float = 20.0,
        heartbeat_lost_after: float = 3.0,
        refusal_grace_s: float = REFUSAL_GRACE_S,
        send_timeout_s: float | None = None,
        ampbus: AmpBus | None = None,
    ) -> None:
        self.knives = check_int("knives", knives, lo=1, hi=MAX_KNIVES)
        self.command_period_s = check_positive("command_period_s", command_period_s)
        self.offsets_period_s = check_positive("offsets_period_s", offsets_period_s)
        self.limit = OffsetLimit(check_positive("stroke_um", stroke_um),
                                 wire_bound_um=WIRE_BOUND_UM)
        """The bound on the offsets in force (machine.toml, the amplifier, refusals)."""
        self.refusal_grace_s = check_positive("refusal_grace_s", refusal_grace_s, allow_zero=True)
        if ampbus is not None and bus is not None and bus is not ampbus.bus:
            raise ValueError("bus must be the shared master's bus (ampbus.bus) or None")
        if ampbus is not None and send_timeout_s is not None:
            raise ValueError(f"send_timeout_s is the shared master's (AmpBus(send_timeout_s=...))"
                             f", not a client's: got {send_timeout_s!r} with ampbus")
        self.shared = ampbus is not None
        """The bus is shared with other heads' clients (not closed by :meth:`close`)."""
        if ampbus is None:
            ampbus = AmpBus(bus, eds=eds, send_timeout_s=(
                default_send_timeout_s(self.command_period_s) if send_timeout_s is None
                else min(check_positive("send_timeout_s", send_timeout_s),
                         self.command_period_s / 2)))
        self.ampbus = ampbus
        self.send_timeout_s = ampbus.network.send_timeout_s
        """The longest a send waits for room in the transmit queue, s (the master's)."""
        self.bus = self.ampbus.bus
        self.amp: CanopenAmplifier = self.ampbus.amplifier(
            node_id, knives=self.knives, heartbeat_lost_after=heartbeat_lost_after)
        """The amplifier's node (SDO, NMT, PDOs, heartbeat, EMCY)."""
        self._heard_mark = 0  # the bus's count of this node's frames already taken
        self.enable = False
        self.offsets_um: tuple[float, ...] = (0.0,) * self.knives
        self._wanted: tuple[float, ...] = self.offsets_um  # as asked for, before the bound
        self._sent_offsets: tuple[float, ...] | None = None
        self._table_since_s: float | None = None  # when the table in force first went out
        self._table_refused = False  # the table in force was refused (re-planned once)
        self.notes: list[LimitNote] = []
        """Changes of the bound, refusals and emergencies not yet reported (the service drains
        them)."""
        self.reconnects = 0
        self.tables_refused = 0
        self._last_command_s = float("-inf")
        self._last_offsets_s = float("-inf")
        self._seen = {"restarts": 0, "limits_read": 0, "status": None}
        self.last_heard_s: float | None = None
        """When the amplifier was last heard (its heartbeat, status or any frame of its
        services), s (``None``: never): the supervisor's CAN timeout counts from it."""
        self.status: AmpStatus | None = None
        self.nmt_state: int | None = None
        self.received = 0
        self.send_errors = 0

    @property
    def sent(self) -> int:
        """Frames sent."""
        return self.ampbus.network.sent

    @property
    def counts(self) -> dict[str, int]:
        """The bus's frames (``foreign``, ``malformed``...) and the amplifier's services."""
        return {**self.ampbus.counts, **self.amp.counts}

    # ------------------------------------------------------------------ setpoints
    @property
    def stroke_um(self) -> float:
        """The bound on every offset now, um (:attr:`limit`; 0 until the amplifier reported)."""
        return self.limit.limit_um

    def set_knives(self, knives: int) -> None:
        """Change the number of knives (offsets reset to zero)."""
        k = check_int("knives", knives, lo=1, hi=MAX_KNIVES)
        if k != self.knives:
            self.knives = k
            self.amp.knives = k
            self.offsets_um = (0.0,) * k
            self._wanted = self.offsets_um
            self._sent_offsets = None

    def _checked(self, offsets_um: Sequence[float]) -> tuple[float, ...]:
        try:  # plain floats, checked at once; a bad value is named below
            vals = tuple(map(float, offsets_um.tolist() if hasattr(offsets_um, "tolist")
                             else offsets_um))
        except (TypeError, ValueError):
            vals = ()
        if not vals or not all(map(math.isfinite, vals)):
            vals = tuple(check_finite(f"offsets_um[{k}]", v) for k, v in enumerate(offsets_um))
        if len(vals) != self.knives:
            raise ValueError(f"offsets_um must have {self.knives} values, got {len(vals)}")
        return vals

    def _planned(self, vals: Sequence[float]) -> tuple[float, ...]:
        lim = self.limit.limit_um
        s = math.floor(lim * 1000.0 + 1e-6) / 1000.0  # on the wire's grid
        # a table inside the bound is the plan (replan_offsets' own first test, in plain floats)
        planned = vals if vals and max(map(abs, vals)) <= lim else self.limit.plan(vals)
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
    def _sending(self, send: Any, *args: Any) -> None:
        try:
            send(*args)
        except FieldbusError:
            self.send_errors += 1
            raise

    def _send_offsets(self, now_s: float) -> None:
        self._sending(self.amp.set_offsets, self.offsets_um)
        if self.offsets_um != self._sent_offsets:  # a new table (not the periodic repeat)
            self._table_since_s = now_s
            self._table_refused = False
        self._sent_offsets = self.offsets_um
        self._last_offsets_s = now_s

    def send_command(self, *, alive_counter: int, now_s: float) -> None:
        """Send the command now (RPDO3: enable, knives, alive counter mod 256)."""
        self._sending(lambda: self.amp.command(enable=self.enable,
                                               alive_counter=int(alive_counter) & 0xFF))
        self._last_command_s = now_s

    def tick(self, *, alive_counter: int, now_s: float) -> bool:
        """Cyclic transmissions due at ``now_s``: the command, and the offsets if stale.

        Returns
        -------
        bool
            Whether the command went out (with ``alive_counter``); the caller moves its
            counter on only then, so the amplifier sees every value in turn.

        Raises
        ------
        FieldbusError
            The bus refused a frame.
        """
        t = check_finite("now_s", now_s)
        sent = t - self._last_command_s >= self.command_period_s * 0.5  # jitter never skips one
        if sent:
            self.send_command(alive_counter=alive_counter, now_s=t)
        if (
            self._sent_offsets != self.offsets_um
            or t - self._last_offsets_s >= self.offsets_period_s
        ):
            self._send_offsets(t)
        return sent

    def poll(self, *, now_s: float, max_frames: int = 1000) -> int:
        """Drain received frames, then SDO and NMT as due; frames from the amplifier.

        Raises
        ------
        FieldbusError
            The bus cannot be read, or a request cannot be sent.
        """
        try:
            self.ampbus.poll(now_s, max_frames=max_frames,
                             only=self.amp.node_id if self.shared else None)
        finally:
            self._after(now_s)
        return self._take_heard()

    def _take_heard(self) -> int:
        """Frames of the amplifier delivered since the last call (by whichever client drained)."""
        total = self.ampbus.heard.get(self.amp.node_id, 0)
        heard, self._heard_mark = total - self._heard_mark, total
        self.received += heard
        return heard

    def handle(self, arbitration_id: Any, data: Any, *, now_s: float) -> int:
        """Process one received frame as :meth:`poll` does; 1 if it came from the amplifier.

        Anything a bus may deliver is taken: a frame of no service of the amplifier (foreign,
        malformed, our own echoed) changes nothing and is counted (:attr:`counts`).
        """
        self.ampbus.deliver(arbitration_id, data, now_s)
        try:
            self.ampbus.serve(now_s, only=self.amp.node_id if self.shared else None)
        finally:
            self._after(now_s)
        return self._take_heard()

    def _after(self, now_s: float) -> None:
        """What the frames handed over changed: reconnects, limits, the status, emergencies."""
        amp, seen = self.amp, self._seen
        if amp.restarts != seen["restarts"]:
            seen["restarts"] = amp.restarts
            self._reconnected(now_s)
        if amp.limits_read != seen["limits_read"]:
            seen["limits_read"] = amp.limits_read
            self._limits_reported(amp.limits, amp.limits_problem, now_s)
        st = amp.status
        if st is not None and st is not seen["status"]:
            seen["status"] = st
            self.status = AmpStatus(displacement_um=st.displacement_um,
                                    temperature_c=st.temperature_c, fault=int(st.fault),
                                    state=int(st.state), t_s=st.t_s)
            if st.fault & AmpFault.STROKE_LIMIT:
                self._refused(now_s)
        for e in amp.take_emergencies():
            what = "cleared" if e.cleared else (e.fault.name.lower().replace("_", "-")
                                                if e.fault is not None else "unknown")
            self._note("emergency", e.t_s, f"piezo amplifier emergency 0x{e.code:04X}: {what}",
                       {"code": e.code, "register": e.register, "fault": what})
        self.nmt_state = None if amp.nmt_state is None else int(amp.nmt_state)
        self.last_heard_s = amp.last_frame_s

    # ------------------------------------------------------------------ limits
    def _limits_reported(self, lim: AmpLimits | None, problem: str | None, now_s: float) -> None:
        if lim is None:  # a report that makes no sense: as if none came (said each time)
            if self.limit.amp_lost():
                self._replan()
            self._note("limits", now_s, f"piezo amplifier's limits invalid ({problem}): "
                       f"{self.limit.describe()}", self.limit.to_dict())
            return
        if self.limit.amp_reported(lim):
            self._replan()
            self._note("limits", now_s, self.limit.describe(), self.limit.to_dict())

    def _reconnected(self, now_s: float) -> None:
        """Booted again or heard again after it was lost: it may have been replaced."""
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
        """Shut the bus down (a shared bus is left to its opener)."""
        if not self.shared:
            self.ampbus.close()
