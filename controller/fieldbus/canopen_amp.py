"""The service's CANopen master of the piezo amplifiers: one bus, one node per head.

:class:`AmpBus` owns the CAN bus and a ``canopen`` network on it; every frame the bus delivers
passes its gate first (:class:`_Gate`): a frame of no service of a known node is counted as
``foreign``, a frame of a known service with the wrong length as ``malformed``, and neither
reaches the library (so neither changes anything). :meth:`AmpBus.amplifier` gives the
:class:`CanopenAmplifier` of one node (a head's amplifier), built from the EDS file:

* start: the limits read by SDO (stroke, offset range, slew, setpoint timeout: ``0x2200``) and
  the producer heartbeat time (``0x1017``), then NMT start (operational);
* heartbeat consumer: the node's state and when it was last heard, on the service's clock; it
  is lost when it has been silent for ``heartbeat_lost_after`` heartbeat periods;
* RPDO1/2 the offset table (1 nm per bit), RPDO3 the command (enable, knives, alive counter);
* TPDO1 the status (displacement, temperature, fault bits, state);
* EMCY consumer: each emergency with its code and the fault it names.

Object indices, units and codes: :mod:`protocol.piezo_canopen`; the dictionary and PDO map:
``docs/piezo_canopen.md``. Callbacks run on the bus's notifier thread and only assign values
(the service's cycle reads them); the clock is injected.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen

from controller.laws.limits import AmpLimits
from core.checks import check_int, check_positive
from core.errors import FieldbusError
from protocol.piezo_canopen import (
    EMCY_CODES,
    HEARTBEAT_TIME,
    LIMITS,
    MAX_KNIVES,
    AmpFault,
    AmpState,
    NmtState,
    cob_ids,
    describe_frame,
    load_od,
    nm_from_um,
    pdo_length,
    um_from_nm,
)

__all__ = ["AmpBus", "CanopenAmplifier", "CanopenStatus", "Emergency"]

_FAULT_OF_CODE = {code: fault for fault, code in EMCY_CODES.items()}


@dataclass(frozen=True)
class CanopenStatus:
    """The amplifier's last TPDO1.

    Attributes
    ----------
    displacement_um, temperature_c : float
        Sensed displacement, um; temperature, degC.
    fault : AmpFault
        Fault bits.
    state : AmpState
        Output state.
    t_s : float
        When it was received (service clock), s.
    """

    displacement_um: float
    temperature_c: float
    fault: AmpFault
    state: AmpState
    t_s: float


@dataclass(frozen=True)
class Emergency:
    """One EMCY message: its code, the fault it names (``None``: cleared or not ours), when."""

    code: int
    register: int
    fault: AmpFault | None
    t_s: float

    @property
    def cleared(self) -> bool:
        """Whether it says every error is gone (code 0x0000)."""
        return self.code == 0


class _Gate(can.Listener):
    """Lets a frame through to the network only when it fits a service of a known node."""

    def __init__(self, network: canopen.Network) -> None:
        self.network = network
        self.expected: dict[int, int | None] = {0x000: 2}  # COB-ID -> DLC (None: any)
        self.counts = {"frames": 0, "foreign": 0, "malformed": 0}
        self.last_problem: str | None = None

    def expect(self, can_id: int, dlc: int | None) -> None:
        self.expected[can_id] = dlc

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        self.counts["frames"] += 1
        cid = msg.arbitration_id
        if msg.is_extended_id or cid not in self.expected:
            self.counts["foreign"] += 1
            return
        want = self.expected[cid]
        if want is not None and msg.dlc != want:
            self.counts["malformed"] += 1
            self.last_problem = f"COB-ID 0x{cid:03X}: {msg.dlc} bytes, expected {want}"
            return
        self.network.notify(cid, msg.data, msg.timestamp)


class AmpBus:
    """One CAN bus with the heads' amplifiers on it (owns the bus and its notifier thread).

    Parameters
    ----------
    bus : can.BusABC
        The bus (python-can); shut down by :meth:`close`.
    clock : callable, keyword-only
        Monotonic seconds of the service (heartbeats and statuses are stamped with it).
    eds : Path, optional, keyword-only
        The amplifiers' EDS file (default ``config/piezo_amp.eds``).
    """

    def __init__(self, bus: Any, *, clock: Callable[[], float] = time.monotonic,
                 eds: str | Path | None = None) -> None:
        self.bus = bus
        self.clock = clock
        self.eds = eds
        self.network = canopen.Network(bus)
        self.gate = _Gate(self.network)
        self.network.listeners = [self.gate]
        self.network.connect()  # the notifier on the given bus
        self.amplifiers: dict[int, CanopenAmplifier] = {}

    @property
    def counts(self) -> dict[str, int]:
        """Frames the bus delivered, and those refused: ``foreign``, ``malformed``."""
        return dict(self.gate.counts)

    def amplifier(self, node_id: int, **options: Any) -> CanopenAmplifier:
        """The amplifier at ``node_id`` (options: :class:`CanopenAmplifier`'s)."""
        check_int("node_id", node_id, lo=1, hi=127)
        if node_id in self.amplifiers:
            raise ValueError(f"node_id {node_id} is already an amplifier on this bus")
        amp = CanopenAmplifier(self, node_id, **options)
        self.amplifiers[node_id] = amp
        return amp

    def close(self) -> None:
        """Stop the notifier and shut the bus down (idempotent)."""
        if self.network.bus is not None:
            self.network.disconnect()


class CanopenAmplifier:
    """One head's piezo amplifier as a CANopen remote node.

    Parameters
    ----------
    ampbus : AmpBus
        The bus it is on.
    node_id : int
        Its node id (1..127).
    knives : int, keyword-only
        Knives of its head (1..8): the offset table's length.
    heartbeat_lost_after : float, keyword-only
        Heartbeat periods of silence after which the amplifier counts as lost.
    sdo_timeout_s : float, keyword-only
        Time limit of each SDO request at start, s.
    """

    def __init__(self, ampbus: AmpBus, node_id: int, *, knives: int = 4,
                 heartbeat_lost_after: float = 3.0, sdo_timeout_s: float = 0.5) -> None:
        self.ampbus = ampbus
        self.node_id = node_id
        self.knives = check_int("knives", knives, lo=1, hi=MAX_KNIVES)
        self.heartbeat_lost_after = check_positive("heartbeat_lost_after", heartbeat_lost_after)
        od = load_od(node_id, ampbus.eds)
        self.od = od
        self.node = ampbus.network.add_node(node_id, od)
        self.node.sdo.RESPONSE_TIMEOUT = check_positive("sdo_timeout_s", sdo_timeout_s)
        ids = cob_ids(node_id)
        gate = ampbus.gate
        gate.expect(ids["heartbeat"], 1)
        gate.expect(ids["emcy"], 8)
        gate.expect(ids["sdo_tx"], 8)
        gate.expect(ids["tpdo1"], pdo_length(od, 0x1A00))
        self.node.rpdo.read(from_od=True)
        self.node.tpdo.read(from_od=True)
        self.node.tpdo[1].add_callback(self._on_status)
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.node.emcy.add_callback(self._on_emcy)
        self._lock = threading.Lock()
        self.limits: AmpLimits | None = None
        """What the amplifier enforces, read at :meth:`start`."""
        self.heartbeat_period_s: float | None = None
        self.nmt_state: NmtState | None = None
        self.last_heard_s: float | None = None
        self.status: CanopenStatus | None = None
        self.emergencies: list[Emergency] = []
        self.counts = {"heartbeats": 0, "statuses": 0, "emergencies": 0, "tables": 0,
                       "commands": 0}

    # -- start ---------------------------------------------------------------------------------

    def start(self) -> AmpLimits:
        """Read the limits and the heartbeat time by SDO, then start the node (operational).

        Raises
        ------
        FieldbusError
            The node does not answer (SDO time-out or abort), naming the object.
        ValueError
            The limits it reports make no sense (``AmpLimits.from_signals``).
        """
        sdo = self.node.sdo
        try:
            lim = sdo[LIMITS]
            signals = {
                "stroke_um": um_from_nm(lim[1].raw),
                "offset_min_um": um_from_nm(lim[2].raw),
                "offset_max_um": um_from_nm(lim[3].raw),
                "slew_max_um_ms": float(lim[4].raw),
                "setpoint_timeout_ms": float(lim[5].raw),
            }
            period_ms = int(sdo[HEARTBEAT_TIME].raw)
        except (canopen.SdoCommunicationError, canopen.SdoAbortedError) as exc:
            raise FieldbusError(f"piezo amplifier node {self.node_id}: SDO read of its limits "
                                f"failed: {exc}") from None
        self.limits = AmpLimits.from_signals(signals)
        self.heartbeat_period_s = period_ms / 1000.0 if period_ms > 0 else None
        self.node.nmt.state = "OPERATIONAL"
        return self.limits

    def stop(self) -> None:
        """NMT stop: the node leaves operational (PDOs no longer acted on)."""
        self.node.nmt.state = "STOPPED"

    # -- outputs -------------------------------------------------------------------------------

    def command(self, *, enable: bool, alive_counter: int) -> None:
        """RPDO3: enable, the head's knives and the master's alive counter."""
        pdo = self.node.rpdo[3]  # maps COMMAND's enable, knives, alive counter
        for var, value in zip(pdo, (int(bool(enable)), self.knives, int(alive_counter) & 0xFF),
                              strict=True):
            var.raw = value
        self._send(pdo)
        self.counts["commands"] += 1

    def set_offsets(self, offsets_um: Sequence[float]) -> None:
        """RPDO1 (knives 1-4) and, for more knives, RPDO2 (5-8): the table, 1 nm per bit.

        Raises
        ------
        ValueError
            Not one value per knife, or a value outside the wire's +-32.767 um (naming it).
        """
        vals = [float(v) for v in offsets_um]
        if len(vals) != self.knives:
            raise ValueError(f"offsets_um must have {self.knives} values, got {len(vals)}")
        raws = [nm_from_um(v, name=f"offset of knife {k + 1}") for k, v in enumerate(vals)]
        raws += [0] * (MAX_KNIVES - len(raws))
        for first, pdo_no in ((0, 1), (4, 2)):  # each maps four of OFFSETS' knives, in order
            if first >= self.knives:
                break
            pdo = self.node.rpdo[pdo_no]
            for var, raw in zip(pdo, raws[first:first + 4], strict=True):
                var.raw = raw
            self._send(pdo)
        self.counts["tables"] += 1

    def _send(self, pdo: Any) -> None:
        try:
            pdo.transmit()
        except can.CanError as exc:
            raise FieldbusError(f"piezo amplifier node {self.node_id}: {exc}") from None

    # -- inputs (the notifier's thread) --------------------------------------------------------

    def _on_heartbeat(self, state: int) -> None:
        now = self.ampbus.clock()
        with self._lock:
            self.nmt_state = (NmtState(state) if state in NmtState._value2member_map_
                              else None)
            self.last_heard_s = now
            self.counts["heartbeats"] += 1

    def _on_status(self, pdo: Any) -> None:
        disp, temp, fault, state = (var.raw for var in pdo)  # STATUS' four objects, in order
        status = CanopenStatus(
            displacement_um=um_from_nm(disp),
            temperature_c=temp / 10.0,
            fault=AmpFault(fault & 0x0F),
            state=AmpState(min(state, AmpState.FAULT)),
            t_s=self.ampbus.clock(),
        )
        with self._lock:
            self.status = status
            self.counts["statuses"] += 1

    def _on_emcy(self, err: Any) -> None:
        e = Emergency(code=int(err.code), register=int(err.register),
                      fault=_FAULT_OF_CODE.get(int(err.code)), t_s=self.ampbus.clock())
        with self._lock:
            self.emergencies.append(e)
            del self.emergencies[:-100]  # the newest hundred
            self.counts["emergencies"] += 1

    # -- what the service asks -----------------------------------------------------------------

    def lost(self, now_s: float) -> bool:
        """Whether its heartbeat has been silent too long (or never came)."""
        if self.last_heard_s is None or self.heartbeat_period_s is None:
            return True
        return now_s - self.last_heard_s > self.heartbeat_lost_after * self.heartbeat_period_s

    def take_emergencies(self) -> list[Emergency]:
        """The emergencies received since the last call, oldest first."""
        with self._lock:
            out, self.emergencies = self.emergencies, []
        return out

    def describe(self, can_id: int, data: bytes) -> str:
        """A frame of this node read against its EDS (one line)."""
        return describe_frame(can_id, data, {self.node_id: self.od}).line(can_id, data)
