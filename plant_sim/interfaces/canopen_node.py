"""The simulated piezo amplifier as a CANopen slave: a ``canopen`` local node from the EDS.

:class:`CanopenAmpNode` puts one head's amplifier (the machine's ``piezo_command``,
``set_piezo_offsets``, ``piezo_status`` and its amplifier's ``limits()``) on a CAN bus as node
``node_id`` of ``config/piezo_amp.eds``; several share one :class:`OutboxNetwork`:

* NMT: it boots (boot-up message), waits pre-operational, acts on PDOs only when operational;
  NMT start / stop / pre-operational / reset from the master as CiA 301 says (a reset boots it
  again);
* heartbeat every ``0x1017`` ms of machine time (its NMT state), sent by :meth:`pump`;
* SDO server: the whole dictionary, the limits (``0x2200``) and status (``0x2100``) read live
  from the amplifier model;
* RPDO1/2 the offset table (a table outside the offset range is refused and raises the
  stroke-limit bit), RPDO3 the command (a command for another number of knives is refused);
* TPDO1 the status every 10 ms of machine time; an EMCY when a fault bit rises, and the
  "no error" EMCY when all have cleared.

Sans-I/O: :class:`OutboxNetwork` is a ``canopen`` network without a bus; frames reach it through
:meth:`~canopen.Network.notify` (``plant_sim.interfaces.amp_node.AmpNodeCore.on_frame``) and what
the nodes send is collected in its outbox for the caller to put on a bus. Time is the
machine's, passed in; nothing here runs a thread or reads a clock.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import canopen
from canopen.nmt import NMT_STATES

from protocol.piezo_canopen import (
    EMCY_CODES,
    HEARTBEAT_TIME,
    LIMITS,
    MAX_KNIVES,
    STATUS,
    STATUS_PERIOD_S,
    AmpFault,
    Frame,
    NmtState,
    cob_ids,
    load_od,
    nm_from_um,
    um_from_nm,
)

__all__ = ["CanopenAmpNode", "OutboxNetwork"]

log = logging.getLogger(__name__)

_STATE_OF_NAME = {name: NmtState(code) for code, name in NMT_STATES.items()
                  if code in NmtState._value2member_map_}
"""Our :class:`NmtState` of each state name the library's ``nmt.state`` gives (its
``INITIALISING`` is the boot-up state, 0)."""


class _NoTask:
    """What ``send_periodic`` returns here: heartbeats run on machine time (:meth:`pump`)."""

    def stop(self) -> None:  # noqa: D102
        pass

    def update(self, data: bytes) -> None:  # noqa: D102
        pass


class OutboxNetwork(canopen.Network):
    """A ``canopen`` network with no bus: what its nodes send is kept in :attr:`outbox`."""

    def __init__(self) -> None:
        super().__init__(None)
        self.outbox: list[Frame] = []

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """Keep the frame for :meth:`take`."""
        self.outbox.append((int(can_id), bytes(data)))

    def send_periodic(self, can_id: int, data: bytes, period: float,
                      remote: bool = False) -> Any:
        """No wall-clock task: the nodes send their heartbeats from :meth:`CanopenAmpNode.pump`."""
        return _NoTask()

    def take(self) -> list[Frame]:
        """The frames sent since the last call, in order."""
        out, self.outbox = self.outbox, []
        return out


class CanopenAmpNode:
    """One amplifier on an :class:`OutboxNetwork`.

    Parameters
    ----------
    network : OutboxNetwork
        The network (the bus) it is on.
    node_id : int
        Its node id (1..127).
    machine : object
        The head's machine side: ``piezo_command(enable=, alive_counter=)``,
        ``set_piezo_offsets(table)``, ``piezo_status()`` and ``amp.limits()`` (or
        ``piezo_limits()``).
    knives : int, keyword-only
        Knives of the head.
    eds : Path, optional, keyword-only
        The EDS file (default ``config/piezo_amp.eds``).
    """

    def __init__(self, network: OutboxNetwork, node_id: int, machine: Any, *, knives: int = 4,
                 eds: str | Path | None = None) -> None:
        if not 1 <= int(knives) <= MAX_KNIVES:
            raise ValueError(f"knives must be in 1..{MAX_KNIVES}, got {knives!r}")
        self.machine = machine
        self.knives = int(knives)
        od = load_od(node_id, eds)
        self.od = od
        self.node_id = node_id
        self.cob_ids = cob_ids(node_id)
        self.node = canopen.LocalNode(node_id, od)
        network.add_node(self.node)
        self.network = network
        self.node.add_read_callback(self._on_read)
        self.node.rpdo.read(from_od=True)
        self.node.tpdo.read(from_od=True)
        for n in (1, 2, 3):
            self.node.rpdo[n].add_callback(self._on_rpdo)
        self._slots = {id(pdo): _byte_slots(pdo) for pdo in (
            self.node.rpdo[1], self.node.rpdo[2], self.node.rpdo[3], self.node.tpdo[1])}
        """Each PDO's variables as byte ranges of its data (``None``: one not byte-aligned),
        from its mapping read above: a local node's PDO maps are read once (an SDO write of
        its mapping objects changes the dictionary, not the maps)."""
        self.offsets_um = [0.0] * MAX_KNIVES
        """The offset table received, um (all eight; the head plays its first ``knives``)."""
        self.last_command: dict[str, int] | None = None
        """The last command received: ``enable``, ``knives``, ``alive_counter``."""
        self._stroke_fault = False
        self._faults_sent = AmpFault(0)
        self._next_status_s: float | None = None
        self._next_heartbeat_s: float | None = None
        self.refused = 0
        self.pdos = 0
        self._boot()

    # -- NMT -----------------------------------------------------------------------------------

    def _boot(self) -> None:
        """Boot-up message, then pre-operational (heartbeats from :meth:`pump`, machine time).

        Through the library's own NMT slave: initialising sends the boot-up message; its
        transition to pre-operational starts its heartbeat task, which the network makes a
        no-op (:meth:`OutboxNetwork.send_periodic`).
        """
        self.node.nmt.state = "INITIALISING"
        self.node.nmt.state = "PRE-OPERATIONAL"

    @property
    def nmt_state(self) -> NmtState:
        """The node's NMT state (the library's ``nmt.state``)."""
        name = self.node.nmt.state
        state = _STATE_OF_NAME.get(name)
        if state is None:
            raise ValueError(f"nmt state {name!r} is none of {list(_STATE_OF_NAME)}")
        return state

    @property
    def heartbeat_period_s(self) -> float:
        """Its producer heartbeat time (0x1017, writable by SDO), s (0: none)."""
        return int(self.node.sdo[HEARTBEAT_TIME].raw) / 1000.0

    # -- received (handed over by the network's notify) ----------------------------------------

    def _on_rpdo(self, pdo: Any) -> None:
        if self.nmt_state is not NmtState.OPERATIONAL:
            return  # PDOs are acted on only when operational
        self.pdos += 1
        if pdo is self.node.rpdo[3]:
            self._command(self._received(pdo))
        else:
            first = 0 if pdo is self.node.rpdo[1] else 4
            for k, raw in enumerate(self._received(pdo)):
                self.offsets_um[first + k] = um_from_nm(raw)
            self._table()

    def _received(self, pdo: Any) -> list[Any]:
        """The raw values of a received PDO's variables (``var.raw`` of each, in order).

        Decoded from the PDO's data by the variables' dictionary entries directly: what
        ``var.raw`` gives, without its per-variable lookups and log records.
        """
        slots = self._slots.get(id(pdo))
        if slots is None:
            return [v.raw for v in pdo]
        data = pdo.data
        return [od.decode_raw(data[a:b]) for a, b, od in slots]

    def _send(self, pdo: Any, values: Sequence[int]) -> None:
        """Set a transmit PDO's variables to ``values`` (as ``var.raw = v``) and send it."""
        slots = self._slots.get(id(pdo))
        if slots is None:
            for var, v in zip(pdo, values, strict=True):
                var.raw = v
        else:
            data = pdo.data
            for (a, b, od), v in zip(slots, values, strict=True):
                data[a:b] = od.encode_raw(v)
            pdo.update()
        pdo.transmit()

    def _command(self, values: Sequence[int]) -> None:
        enable, knives, alive = (int(v) for v in values[:3])
        self.last_command = {"enable": enable, "knives": knives, "alive_counter": alive}
        if knives != self.knives:
            self.refused += 1
            log.info("command for %d knives refused (the head has %d)", knives, self.knives)
            return
        try:
            self.machine.piezo_command(enable=bool(enable), alive_counter=alive)
        except ValueError as exc:
            self.refused += 1
            log.info("command refused: %s", exc)

    def _table(self) -> None:
        try:
            self.machine.set_piezo_offsets(self.offsets_um[: self.knives])
        except ValueError as exc:
            self.refused += 1
            self._stroke_fault = True
            log.info("offsets refused: %s", exc)
            return
        self._stroke_fault = False

    def _limits(self) -> Any:
        report = getattr(self.machine, "piezo_limits", None) or getattr(
            getattr(self.machine, "amp", None), "limits", None)
        return None if report is None else report()

    def _on_read(self, *, index: int, subindex: int, od: Any) -> int | None:
        """SDO reads of the live objects: the limits and the status."""
        if index == LIMITS:
            lim = self._limits()
            if lim is None:
                return None
            return {1: min(65535, round(float(lim.stroke_um) * 1000.0)),
                    2: nm_from_um(lim.offset_min_um), 3: nm_from_um(lim.offset_max_um),
                    4: int(round(lim.slew_max_um_ms)),
                    5: int(round(lim.setpoint_timeout_ms))}.get(subindex)
        if index == STATUS:
            return self._status_raw().get(subindex)
        return None

    # -- sent (machine time) -------------------------------------------------------------------

    def _fault(self) -> AmpFault:
        st = self.machine.piezo_status()
        fault = AmpFault(int(getattr(st, "fault", 0)) & 0x0F)
        return fault | AmpFault.STROKE_LIMIT if self._stroke_fault else fault

    def _status_raw(self) -> dict[int, int]:
        st = self.machine.piezo_status()
        disp = max(-32.768, min(32.767, float(st.displacement_um)))
        return {1: nm_from_um(disp), 2: int(round(float(st.temperature_c) * 10.0)),
                3: int(self._fault()), 4: int(st.state)}

    def pump(self, now_s: float) -> None:
        """Send what is due at machine time ``now_s``: heartbeat, TPDO1 status, EMCY.

        A late call sends each once and re-aligns its schedule (no burst of backlog).
        """
        state = self.nmt_state
        if state is NmtState.BOOT_UP:  # reset by the master: boot again
            self._boot()
            state = NmtState.PRE_OPERATIONAL
        if self._next_status_s is None or self._next_heartbeat_s is None:
            self._next_status_s = self._next_heartbeat_s = now_s
        if now_s >= self._next_heartbeat_s - 1e-9:
            period = self.heartbeat_period_s
            if period > 0:
                self._next_heartbeat_s = _next(self._next_heartbeat_s, period, now_s)
                self.network.send_message(self.cob_ids["heartbeat"], bytes([state]))
        if state is not NmtState.OPERATIONAL:
            return
        if now_s >= self._next_status_s - 1e-9:
            self._next_status_s = _next(self._next_status_s, STATUS_PERIOD_S, now_s)
            raw = self._status_raw()
            pdo = self.node.tpdo[1]
            self._send(pdo, [raw[sub] for sub in range(1, len(pdo) + 1)])
            self._emergencies(AmpFault(raw[3]))

    def _emergencies(self, fault: AmpFault) -> None:
        if fault == self._faults_sent:
            return  # nothing rose, nothing cleared
        risen = fault & ~self._faults_sent
        for bit in AmpFault:
            if bit in risen:
                self.node.emcy.send(EMCY_CODES[bit], register=0x01)
        if self._faults_sent and not fault:
            self.node.emcy.reset()  # code 0x0000: no error any more
        self._faults_sent = fault


def _byte_slots(pdo: Any) -> tuple[tuple[int, int, Any], ...] | None:
    """``(first byte, end byte, dictionary entry)`` of each variable of ``pdo``, in order.

    ``None`` when one is not whole bytes at a byte boundary (its value then goes through the
    library's bit handling: ``var.raw``).
    """
    slots = []
    for var in pdo:
        byte, bit = divmod(int(var.offset), 8)
        if bit or var.length % 8 or var.length != len(var.od):
            return None
        slots.append((byte, byte + var.length // 8, var.od))
    return tuple(slots)


def _next(scheduled: float, period: float, now_s: float) -> float:
    nxt = scheduled + period
    if nxt <= now_s:  # fell behind: the next one a period from now
        nxt = now_s + period
    return nxt
