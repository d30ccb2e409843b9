"""The service's CANopen master of the piezo amplifiers: one bus, one node per head.

:class:`AmpBus` owns the CAN bus and a ``canopen`` network on it. It runs no thread of its own:
:meth:`AmpBus.poll` drains the bus without blocking, with the service's time, and every frame
passes its gate first (:class:`_Gate`): a frame of no service of a known node is counted as
``foreign``, a frame of a known service with the wrong length as ``malformed``, the master's own
frames echoed by the transport as ``own``, and none of them reaches the library (so none changes
anything). :meth:`AmpBus.amplifier` gives the :class:`CanopenAmplifier` of one node (a head's
amplifier), built from the EDS file:

* start: once it is heard (boot-up or heartbeat) the limits are read by SDO (stroke, offset
  range, slew, setpoint timeout: ``0x2200``) and the producer heartbeat time (``0x1017``), one
  expedited upload after the other (a poll waits a few milliseconds for the answers, no more);
  then NMT start (operational). A node that
  boots again, or is heard again after it was lost, is read and started anew;
* heartbeat consumer: the node's state and when it was last heard, on the service's clock; it
  is lost when it has been silent for ``heartbeat_lost_after`` heartbeat periods;
* RPDO1/2 the offset table (1 nm per bit), RPDO3 the command (enable, knives, alive counter);
* TPDO1 the status (displacement, temperature, fault bits, state);
* EMCY consumer: each emergency with its code and the fault it names.

Object indices, units and codes: :mod:`protocol.piezo_canopen`; the dictionary and PDO map:
``docs/piezo_canopen.md``. Sends go out with a time limit (a full transmit queue raises
``FieldbusError`` instead of holding up the service's cycle).
"""

from __future__ import annotations

import queue
import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.objectdictionary.datatypes import INTEGER_TYPES

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
    SdoProblem,
    cob_ids,
    describe_frame,
    expected_lengths,
    load_od,
    nm_from_um,
    sdo_upload_request,
    sdo_upload_value,
    um_from_nm,
)

__all__ = ["AmpBus", "CanopenAmplifier", "CanopenStatus", "Emergency"]

_FAULT_OF_CODE = {code: fault for fault, code in EMCY_CODES.items()}
_FAULT_OF_BITS = tuple(AmpFault(bits) for bits in range(16))
"""``AmpFault(bits)`` of each value of the status' four fault bits (built once)."""
_STATE_OF_BYTE = tuple(AmpState(min(raw, AmpState.FAULT)) for raw in range(256))
"""``AmpState(min(raw, FAULT))`` of each value of the status' state byte (built once)."""
_LIMIT_READS = ((LIMITS, 1), (LIMITS, 2), (LIMITS, 3), (LIMITS, 4), (LIMITS, 5),
                (HEARTBEAT_TIME, 0))
"""What the master reads by SDO before it starts a node, in this order."""
_LIMIT_SIGNALS = {1: "stroke_um", 2: "offset_min_um", 3: "offset_max_um", 4: "slew_max_um_ms",
                  5: "setpoint_timeout_ms"}
SEND_TIMEOUT_S = 0.005
"""Longest a send waits for room in the transmit queue by default, s."""
SDO_WAIT_S = 0.01
"""Longest a poll waits for SDO answers while the limits are read, s: the simulated node over
UDP multicast answers in 2-6 ms (a 2-core VM), so the six reads take one or two cycles."""


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


class _MasterNetwork(canopen.Network):
    """canopen's network without a notifier: :class:`AmpBus` feeds it; sends are time-limited."""

    def __init__(self, bus: Any, send_timeout_s: float) -> None:
        super().__init__(bus)
        self.send_timeout_s = send_timeout_s
        self.sent = 0
        self.own: set[int] = set()
        """COB-IDs this master sends (a transport that echoes them delivers them back)."""

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """Send one frame within :attr:`send_timeout_s` (``FieldbusError`` if it cannot)."""
        msg = can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False,
                          is_remote_frame=remote)
        try:
            self.bus.send(msg, timeout=self.send_timeout_s)
        except (can.CanError, OSError) as exc:
            raise FieldbusError(f"CAN send of 0x{can_id:03X} failed: {exc}") from None
        self.own.add(can_id)
        self.sent += 1


class _Gate:
    """Lets a frame through to the network only when it fits a service of a known node."""

    def __init__(self, network: _MasterNetwork) -> None:
        self.network = network
        self.expected: dict[int, tuple[int, int]] = {}  # COB-ID -> (DLC, node id)
        self.counts = {"frames": 0, "foreign": 0, "malformed": 0, "own": 0}
        self.last_problem: str | None = None

    def pass_frame(self, can_id: Any, data: Any, timestamp: float, *,
                   extended: bool = False) -> int | None:
        """Deliver a frame to the library if it fits; the node id it was of, else ``None``."""
        self.counts["frames"] += 1
        if isinstance(can_id, bool) or not isinstance(can_id, int) or extended:
            self.counts["foreign"] += 1
            return None
        if can_id not in self.expected:
            self.counts["own" if can_id in self.network.own else "foreign"] += 1
            return None
        want, node_id = self.expected[can_id]
        if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) != want:
            self.counts["malformed"] += 1
            n = len(data) if isinstance(data, (bytes, bytearray, memoryview)) else type(data)
            self.last_problem = f"COB-ID 0x{can_id:03X}: {n} bytes, expected {want}"
            return None
        self.network.notify(can_id, bytes(data), timestamp)
        return node_id


class AmpBus:
    """One CAN bus with the heads' amplifiers on it (owns the bus; no thread of its own).

    Parameters
    ----------
    bus : can.BusABC
        The bus (python-can); shut down by :meth:`close`.
    eds : Path, optional, keyword-only
        The amplifiers' EDS file (default ``config/piezo_amp.eds``).
    send_timeout_s : float, keyword-only
        Longest a send may wait for room in the transmit queue, s.
    sdo_wait_s : float, keyword-only
        Longest :meth:`poll` waits for SDO answers while a read is under way, s (0: never).
    """

    def __init__(self, bus: Any, *, eds: str | Path | None = None,
                 send_timeout_s: float = SEND_TIMEOUT_S,
                 sdo_wait_s: float = SDO_WAIT_S) -> None:
        self.bus = bus
        self.eds = eds
        self.sdo_wait_s = check_positive("sdo_wait_s", sdo_wait_s, allow_zero=True)
        self.network = _MasterNetwork(bus, check_positive("send_timeout_s", send_timeout_s))
        self.gate = _Gate(self.network)
        self.now_s = 0.0
        """The service's time of the frames being handled (set by :meth:`poll`)."""
        self.amplifiers: dict[int, CanopenAmplifier] = {}
        self.heard: dict[int, int] = {}
        """Frames delivered from each node so far, by node id (a client of one node on a
        shared bus takes its own from here, whoever drained the bus)."""

    @property
    def counts(self) -> dict[str, int]:
        """Frames delivered, refused (``foreign``, ``malformed``), echoed (``own``), sent."""
        return {**self.gate.counts, "sent": self.network.sent}

    def amplifier(self, node_id: int, **options: Any) -> CanopenAmplifier:
        """The amplifier at ``node_id`` (options: :class:`CanopenAmplifier`'s)."""
        check_int("node_id", node_id, lo=1, hi=127)
        if node_id in self.amplifiers:
            raise ValueError(f"node_id {node_id} is already an amplifier on this bus")
        amp = CanopenAmplifier(self, node_id, **options)
        self.amplifiers[node_id] = amp
        return amp

    def deliver(self, can_id: Any, data: Any, now_s: float, *,
                extended: bool = False) -> int | None:
        """One received frame at ``now_s`` through the gate; the node id it was of, or ``None``.

        Never raises for what a bus may deliver.
        """
        self.now_s = float(now_s)
        node = self.gate.pass_frame(can_id, data, self.now_s, extended=extended)
        if node is not None:
            amp = self.amplifiers[node]
            amp.last_frame_s = max(self.now_s, amp.last_frame_s or self.now_s)
            self.heard[node] = self.heard.get(node, 0) + 1
        return node

    def poll(self, now_s: float, *, max_frames: int = 1000,
             only: int | None = None) -> dict[int, int]:
        """Drain the bus, then let each amplifier do what is due (SDO, NMT).

        Draining never blocks, except while an SDO read is under way (at start and after a
        reconnect): then answers are waited for, :attr:`sdo_wait_s` at most per call in all,
        so a node that answers within milliseconds has its limits read in one or two cycles.
        Every frame drained goes to its node whatever ``only`` says (each frame is decoded
        once, by the one bus); ``only`` (a node id): only that amplifier is served and waited
        for (a head's client on a bus it shares with the other heads' amplifiers).

        Returns
        -------
        dict
            Frames received from each node, by node id.

        Raises
        ------
        FieldbusError
            The bus cannot be read, or a request cannot be sent.
        """
        heard: dict[int, int] = {}
        for _ in range(max_frames):
            if not self._take(self._recv(0.0), now_s, heard):
                break
        amps = self._served(only)
        self._serve(amps, now_s)
        end = time.monotonic() + self.sdo_wait_s
        while any(a.reading for a in amps):
            left = end - time.monotonic()
            if left <= 0.0 or not self._take(self._recv(left), now_s, heard):
                break
            self._serve(amps, now_s)
        return heard

    def _recv(self, timeout_s: float) -> Any:
        try:
            return self.bus.recv(timeout=timeout_s)
        except (can.CanError, OSError, ValueError) as exc:  # a broken bus
            raise FieldbusError(f"CAN receive failed: {exc}") from None

    def _take(self, msg: Any, now_s: float, heard: dict[int, int]) -> bool:
        """One received message through the gate (counted in ``heard``); ``False``: none."""
        if msg is None:
            return False
        if not (msg.is_error_frame or msg.is_remote_frame):
            node = self.deliver(msg.arbitration_id, bytes(msg.data), now_s,
                                extended=msg.is_extended_id)
            if node is not None:
                heard[node] = heard.get(node, 0) + 1
        return True

    def serve(self, now_s: float, *, only: int | None = None) -> None:
        """What each amplifier (``only``: that node's) has due at ``now_s``: SDO, NMT start."""
        self._serve(self._served(only), now_s)

    def _served(self, only: int | None) -> list[CanopenAmplifier]:
        """The amplifiers served: every one, or node ``only``'s (none when it has none)."""
        if only is None:
            return list(self.amplifiers.values())
        return [self.amplifiers[only]] if only in self.amplifiers else []

    def _serve(self, amps: Any, now_s: float) -> None:
        self.now_s = float(now_s)
        for amp in amps:
            amp.serve(self.now_s)

    def close(self) -> None:
        """Shut the bus down (idempotent)."""
        if self.network.bus is not None:
            try:
                self.bus.shutdown()
            except (can.CanError, OSError, ValueError, AttributeError):  # closing goes on
                pass
            self.network.bus = None


def _pdo_layout(pdo: Any) -> tuple[tuple[int, Any], ...] | None:
    """``(byte offset, object)`` of each value a PDO maps, in order.

    ``None``: a value is off the byte grid, or the PDO maps nothing.
    """
    layout = []
    for var in pdo:
        if var.offset % 8 or var.length % 8 or len(var.od) != var.length:
            return None
        layout.append((var.offset // 8, var.od))
    return tuple(layout) or None


def _pdo_packer(pdo: Any, layout: tuple[tuple[int, Any], ...] | None) -> struct.Struct | None:
    """One ``struct`` giving a PDO's data from its values as each object's ``encode_raw`` does.

    Only for a PDO whose objects are integers without limits (``encode_raw`` then converts
    with ``int`` and packs with the object's own ``struct``), laid end to end over the whole
    data; ``None`` otherwise (its values then go one by one through ``encode_raw``).
    """
    if layout is None:
        return None
    fmt, at = "<", 0
    for offset, od_var in layout:
        packer = od_var.STRUCT_TYPES.get(od_var.data_type)
        if (offset != at or od_var.data_type not in INTEGER_TYPES or packer is None
                or od_var.min is not None or od_var.max is not None
                or packer.size * 8 != len(od_var)):
            return None
        code = packer.format.lstrip("<>=!@")
        if struct.calcsize("<" + code) != packer.size:  # a 24/40/48/56-bit object: no struct
            return None
        fmt += code
        at += packer.size
    return struct.Struct(fmt) if at == len(pdo.data) else None


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
        An SDO request not answered within this time (service clock) is asked again, s.
    """

    def __init__(self, ampbus: AmpBus, node_id: int, *, knives: int = 4,
                 heartbeat_lost_after: float = 3.0, sdo_timeout_s: float = 0.1) -> None:
        self.ampbus = ampbus
        self.node_id = node_id
        self.knives = check_int("knives", knives, lo=1, hi=MAX_KNIVES)
        self.heartbeat_lost_after = check_positive("heartbeat_lost_after", heartbeat_lost_after)
        self.sdo_timeout_s = check_positive("sdo_timeout_s", sdo_timeout_s)
        od = load_od(node_id, ampbus.eds)
        self.od = od
        self.node = ampbus.network.add_node(node_id, od)
        for cob, dlc in expected_lengths(od, node_id, receiver="master").items():
            ampbus.gate.expected[cob] = (dlc, node_id)
        self.cob_ids = cob_ids(node_id)
        self.node.rpdo.read(from_od=True)
        self.node.tpdo.read(from_od=True)
        self._layouts = {no: _pdo_layout(self.node.rpdo[no]) for no in (1, 2, 3)}
        self._packers = {no: _pdo_packer(self.node.rpdo[no], self._layouts[no])
                         for no in (1, 2, 3)}
        self._status_layout = _pdo_layout(self.node.tpdo[1])
        self.node.tpdo[1].add_callback(self._on_status)
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.node.emcy.add_callback(self._on_emcy)
        self.limits: AmpLimits | None = None
        """What the amplifier enforces, read by SDO once it was heard (``None`` until then)."""
        self.limits_problem: str | None = None
        """Why the limits it reported make no sense (``AmpLimits.from_signals``), or ``None``."""
        self.limits_read = 0
        """Completed reads of the limits (valid or not): a new one when this grows."""
        self.restarts = 0
        """Times it booted again or was heard again after it was lost."""
        self.heartbeat_period_s: float | None = int(od[HEARTBEAT_TIME].default) / 1000.0
        """Its producer heartbeat time (the EDS's until read by SDO), s."""
        self.nmt_state: NmtState | None = None
        self.last_heard_s: float | None = None
        """When its last heartbeat came (service clock), s: the heartbeat consumer's."""
        self.last_frame_s: float | None = None
        """When its last frame of any service came (heartbeat, status, EMCY, SDO), s."""
        self._status: CanopenStatus | None = None
        self._status_in: tuple[bytes, float] | None = None  # the last TPDO1 not yet decoded
        self.emergencies: list[Emergency] = []
        self.wanted = NmtState.OPERATIONAL
        """The NMT state the master keeps it in (:meth:`stop` makes it STOPPED)."""
        self._reads: list[tuple[int, int]] = []  # SDO reads to do, the first one asked
        self._values: dict[tuple[int, int], Any] = {}
        self._asked_s = 0.0
        self._start_sent_at = -1  # the heartbeat count at which NMT start last went out
        self.sdo_problem: str | None = None
        self.counts = {"heartbeats": 0, "statuses": 0, "emergencies": 0, "tables": 0,
                       "commands": 0, "sdo_reads": 0, "sdo_retries": 0, "sdo_errors": 0,
                       "nmt_starts": 0}

    # -- start: SDO reads, then NMT start ------------------------------------------------------

    def start(self) -> None:
        """Read the limits and the heartbeat time by SDO, then start the node (non-blocking).

        The reads go out one after the other as :meth:`serve` (called by :meth:`AmpBus.poll`)
        finds the answers; :attr:`limits` is set and NMT start sent when the last one is in.
        """
        self.limits = None
        self.limits_problem = None
        self._values = {}
        self._reads = list(_LIMIT_READS)
        self.wanted = NmtState.OPERATIONAL
        self._ask(self.ampbus.now_s)

    @property
    def reading(self) -> bool:
        """Whether an SDO read of its limits is under way."""
        return bool(self._reads)

    def stop(self) -> None:
        """NMT stop: the node leaves operational (PDOs no longer acted on)."""
        self.wanted = NmtState.STOPPED
        self.node.nmt.state = "STOPPED"

    def _ask(self, now_s: float) -> None:
        index, sub = self._reads[0]
        self._asked_s = now_s
        self.ampbus.network.send_message(self.node.sdo.rx_cobid, sdo_upload_request(index, sub))
        self.counts["sdo_reads"] += 1

    def serve(self, now_s: float) -> None:
        """Take the SDO answers received, ask what is next or again, start the node when due."""
        sdo = self.node.sdo
        while True:
            try:
                response = sdo.responses.get_nowait()
            except queue.Empty:
                break
            self._answer(response, now_s)
        if self.last_heard_s is None:
            return  # never heard: nothing to ask
        if self.limits is None and self.limits_problem is None and not self._reads:
            self.start()
        elif self._reads and now_s - self._asked_s > self.sdo_timeout_s:
            self.counts["sdo_retries"] += 1
            self._ask(now_s)
        beats = self.counts["heartbeats"]
        if (self.limits is not None and self.wanted is NmtState.OPERATIONAL
                and self.nmt_state in (NmtState.PRE_OPERATIONAL, NmtState.STOPPED)
                and beats != self._start_sent_at):
            self._start_sent_at = beats  # once per heartbeat that says it is not operational
            self.node.nmt.state = "OPERATIONAL"
            self.counts["nmt_starts"] += 1

    def _answer(self, response: bytes, now_s: float) -> None:
        if not self._reads:
            return  # a late answer to a request asked again: the first one was taken
        index, sub = self._reads[0]
        try:
            raw = sdo_upload_value(response, index, sub)
            value = self.od.get_variable(index, sub).decode_raw(raw)
        except (SdoProblem, struct.error) as exc:  # asked again after the time-out
            self.counts["sdo_errors"] += 1
            self.sdo_problem = f"node {self.node_id}: {exc}"
            return
        self._values[(index, sub)] = value
        self._reads.pop(0)
        if self._reads:
            self._ask(now_s)
        else:
            self._limits_in()

    def _limits_in(self) -> None:
        v = self._values
        signals = {name: float(v[(LIMITS, sub)]) for sub, name in _LIMIT_SIGNALS.items()}
        for sub in (1, 2, 3):  # lengths in nm
            signals[_LIMIT_SIGNALS[sub]] = um_from_nm(int(v[(LIMITS, sub)]))
        period_ms = int(v[(HEARTBEAT_TIME, 0)])
        self.heartbeat_period_s = period_ms / 1000.0 if period_ms > 0 else None
        try:
            self.limits = AmpLimits.from_signals(signals)
        except ValueError as exc:
            self.limits, self.limits_problem = None, str(exc)
        self.limits_read += 1
        self._start_sent_at = -1  # start it at once (its last heartbeat said pre-operational)

    # -- outputs -------------------------------------------------------------------------------

    def command(self, *, enable: bool, alive_counter: int) -> None:
        """RPDO3: enable, the head's knives and the master's alive counter."""
        # RPDO3 maps COMMAND's enable, knives, alive counter
        self._transmit(3, (int(bool(enable)), self.knives, int(alive_counter) & 0xFF))
        self.counts["commands"] += 1

    def set_offsets(self, offsets_um: Sequence[float]) -> None:
        """RPDO1 (knives 1-4) and, for more knives, RPDO2 (5-8): the table, 1 nm per bit.

        Raises
        ------
        ValueError
            Not one value per knife, or a value outside the wire's +-32.767 um (naming it).
        FieldbusError
            The bus refused a frame.
        """
        vals = [float(v) for v in offsets_um]
        if len(vals) != self.knives:
            raise ValueError(f"offsets_um must have {self.knives} values, got {len(vals)}")
        raws = [nm_from_um(v, name=f"offset of knife {k + 1}") for k, v in enumerate(vals)]
        raws += [0] * (MAX_KNIVES - len(raws))
        for first, pdo_no in ((0, 1), (4, 2)):  # each maps four of OFFSETS' knives, in order
            if first >= self.knives:
                break
            self._transmit(pdo_no, raws[first:first + 4])
        self.counts["tables"] += 1

    def _transmit(self, pdo_no: int, values: Sequence[int]) -> None:
        """Set RPDO ``pdo_no``'s mapped values, in order, and send it once.

        The bytes are the library's (each value encoded by its object's ``encode_raw`` at its
        place in the PDO's data, as ``var.raw = value`` sets them) without its per-value
        logging: in one ``struct`` for a PDO of integers end to end (:func:`_pdo_packer`); a
        map with a value off the byte grid goes through the library itself.
        """
        pdo = self.node.rpdo[pdo_no]
        layout = self._layouts[pdo_no]
        packer = self._packers[pdo_no]
        packed = None
        if (packer is not None and len(values) == len(layout or ())
                and not any(isinstance(v, (bytes, bytearray)) for v in values)):
            try:  # (bytes go raw through encode_raw, never through int())
                packed = packer.pack(*[int(v) for v in values])
            except (struct.error, TypeError, ValueError, OverflowError):
                packed = None  # one by one below: the library's error, where it raises it
        if packed is not None:
            pdo.data[:] = packed
            pdo.update()
        elif layout is None or len(layout) != len(values):
            for var, value in zip(pdo, values, strict=True):
                var.raw = value
        else:
            data = pdo.data
            for (at, od_var), value in zip(layout, values, strict=True):
                raw = od_var.encode_raw(value)
                data[at:at + len(raw)] = raw
            pdo.update()
        pdo.transmit()

    # -- inputs (handed over by AmpBus, at its now_s) ------------------------------------------

    def _on_heartbeat(self, state: int) -> None:
        now = self.ampbus.now_s
        heard_before = self.last_heard_s is not None
        if heard_before and (state == NmtState.BOOT_UP or self.lost(now)):
            self._restarted()
        self.nmt_state = (NmtState(state) if state in NmtState._value2member_map_ else None)
        self.last_heard_s = now if self.last_heard_s is None else max(self.last_heard_s, now)
        self.counts["heartbeats"] += 1

    def _restarted(self) -> None:
        """Booted again, or heard again after it was lost: read and start it anew."""
        self.restarts += 1
        self.limits = None
        self.limits_problem = None
        self._reads = []

    @property
    def status(self) -> CanopenStatus | None:
        """The amplifier's last TPDO1 (``None`` before the first), a new object per frame.

        Decoded when first asked for: of the statuses a poll drains (two per node at a 20 ms
        cycle) only the last is read.
        """
        if self._status_in is not None:
            data, t_s = self._status_in
            self._status_in = None
            self._status = self._status_of(self._status_values(data), t_s)
        return self._status

    def _on_status(self, pdo: Any) -> None:
        layout = self._status_layout
        if layout is None or len(layout) != 4:  # off the byte grid: the library's reading now
            self._status_in = None
            self._status = self._status_of(tuple(var.raw for var in pdo), self.ampbus.now_s)
        else:  # its bytes, decoded when asked for (``status``)
            self._status_in = (bytes(pdo.data), self.ampbus.now_s)
        self.counts["statuses"] += 1

    def _status_values(self, data: bytes) -> tuple[int, ...]:
        """STATUS' four values from a TPDO1's bytes (what ``var.raw`` of each reads).

        By its layout, without the library's per-value logging.
        """
        layout = self._status_layout
        assert layout is not None
        return tuple(od_var.decode_raw(data[at:at + len(od_var) // 8]) for at, od_var in layout)

    @staticmethod
    def _status_of(values: Sequence[int], t_s: float) -> CanopenStatus:
        disp, temp, fault, state = values
        return CanopenStatus(
            displacement_um=um_from_nm(disp),
            temperature_c=temp / 10.0,
            fault=_FAULT_OF_BITS[fault & 0x0F],
            state=(_STATE_OF_BYTE[state] if 0 <= state < 256
                   else AmpState(min(state, AmpState.FAULT))),
            t_s=t_s,
        )

    def _on_emcy(self, err: Any) -> None:
        e = Emergency(code=int(err.code), register=int(err.register),
                      fault=_FAULT_OF_CODE.get(int(err.code)), t_s=self.ampbus.now_s)
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
        out, self.emergencies = self.emergencies, []
        return out

    def describe(self, can_id: int, data: bytes) -> str:
        """A frame of this node read against its EDS (one line)."""
        return describe_frame(can_id, data, {self.node_id: self.od}).line(can_id, data)
