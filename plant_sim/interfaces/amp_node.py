"""The piezo amplifier's CAN node: the machine's piezo side as a CANopen slave on a python-can bus.

:class:`AmpNodeCore` is sans-I/O: it takes received frames with the machine time and returns the
frames to send. Inside it the amplifier is a ``canopen`` local node built from
``config/piezo_amp.eds`` (:class:`~plant_sim.interfaces.canopen_node.CanopenAmpNode`; more than
one can share the core's network, :meth:`AmpNodeCore.add_node`). :class:`AmpNode` pumps a
python-can bus through it.

Behaviour (see ``docs/piezo_canopen.md``):

* boot-up, then pre-operational; the master reads the limits by SDO and starts it (NMT);
* RPDO3 (the command: enable, knives, alive counter) -> ``machine.piezo_command(enable=,
  alive_counter=)`` (resets the machine's setpoint timeout; when commands stop, the machine
  ramps the offsets to zero by itself); a command whose ``knives`` differs from the head's is
  refused (not forwarded, so it does not keep the amplifier alive);
* RPDO1/RPDO2 (the offset table) -> ``machine.set_piezo_offsets(table[:knives])``; offsets the
  machine refuses (beyond the stroke) are not applied and raise the stroke-limit fault bit in
  the status (and an EMCY) until valid offsets arrive;
* TPDO1 (the status) every 10 ms and the heartbeat every 100 ms of machine time, from
  ``machine.piezo_status()``;
* frames of no service of its nodes (its own echoed, unknown ids, wrong lengths) are ignored.

:meth:`AmpNode.start_receiving` reads the bus on a thread of its own (``planer sim``), so frames
leave the bus at once whatever the stepping thread does. That thread stamps each frame with its
arrival on the wall clock; with a time base (:meth:`AmpNode.set_timebase`: the runner's mapping
of wall time to machine time) a frame reaches the machine at the machine time it arrived, not
earlier, so a stepping thread that catches up after a stall does not pile a stall's commands
onto one instant and then run on without any (which the setpoint timeout would judge as
silence).

Faults: ``drop_rx`` drops a fraction of received frames, or all of them in a time window;
``silence`` stops the node sending in a time window (the CAN side going silent); either for
every node on the bus or for one (``node_id``: one head's amplifier on a moulder's bus).
"""

from __future__ import annotations

import logging
import math
import queue
import random
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from plant_sim.interfaces.canopen_node import CanopenAmpNode, OutboxNetwork
from protocol.piezo_canopen import Frame, expected_lengths

log = logging.getLogger(__name__)

RX_POLL_S = 0.05
"""How long the receiving thread waits on the bus before it checks whether to stop, s."""
RX_START_TIMEOUT_S = 10.0
"""How long :meth:`AmpNode.start_receiving` waits for its thread to have set its priority, s."""
ARRIVAL_TOLERANCE_S = 1e-9
"""A frame whose machine arrival time is this close after ``now_s`` is delivered now, s."""
DEFAULT_NODE_ID = 2
"""The amplifier's node id unless configured (``[can] node_id``)."""
CAN_FAULTS: Mapping[str, str] = {"can_drop": "drop_rx", "can_silence": "silence"}
"""The registry's CAN faults (:class:`config.faults.FaultKind`) and the node's own name of each
(:meth:`AmpNodeCore.inject`): what :meth:`AmpNodeCore.play` plays."""


class AmpMachine(Protocol):
    """What the node needs of the machine (see ``plant_sim/machine/machine.py``)."""

    def piezo_command(self, *, enable: bool, alive_counter: int) -> None: ...  # noqa: D102
    def set_piezo_offsets(self, offsets_um: Sequence[float]) -> None: ...  # noqa: D102
    def piezo_status(self) -> Any: ...  # noqa: D102


@dataclass
class _Window:
    start_s: float
    end_s: float
    fraction: float = 1.0
    node_id: int | None = None  # None: every node on the bus

    def active(self, now_s: float, node_id: int | None = None) -> bool:
        if self.node_id is not None and self.node_id != node_id:
            return False
        return self.start_s <= now_s < self.end_s


class AmpNodeCore:
    """Sans-I/O amplifier node(s): CANopen slaves on one network, with the bus's faults.

    Parameters
    ----------
    machine : AmpMachine
        The machine model (the head's).
    knives : int
        Number of knives Z whose offsets go to the machine (1..8).
    node_id : int
        The amplifier's node id (1..127).
    eds : Path, optional
        The EDS file (default ``config/piezo_amp.eds``).
    seed : int
        Seed of the random frame dropping.

    Attributes
    ----------
    received, dropped, ignored, sent : int
        Counts of frames received (before dropping), dropped by the fault, ignored (own or
        unknown ids, wrong lengths), frames sent.
    """

    def __init__(
        self,
        machine: AmpMachine,
        *,
        knives: int,
        node_id: int = DEFAULT_NODE_ID,
        eds: str | Path | None = None,
        seed: int = 0,
    ) -> None:
        self.network = OutboxNetwork()
        self.nodes: list[CanopenAmpNode] = []
        self._expected: dict[int, int] = {}
        self._node_of: dict[int, int] = {}  # COB-ID -> the node id whose service it is
        self.node = self.add_node(node_id, machine, knives=knives, eds=eds)
        """The head's amplifier (the first node)."""
        self.machine = machine
        self._rng = random.Random(seed)
        self._drop: list[_Window] = []
        self._silence: list[_Window] = []
        self.received = self.dropped = self.ignored = self.sent = 0

    def add_node(self, node_id: int, machine: AmpMachine, *, knives: int,
                 eds: str | Path | None = None) -> CanopenAmpNode:
        """Another amplifier on the same bus (another head), node ``node_id``."""
        if any(n.node_id == node_id for n in self.nodes):
            raise ValueError(f"node_id {node_id} is already an amplifier on this bus")
        node = CanopenAmpNode(self.network, node_id, machine, knives=knives, eds=eds)
        self.nodes.append(node)
        self._expected.update(expected_lengths(node.od, node_id, receiver="node"))
        for cob in node.cob_ids.values():
            self._node_of[cob] = node_id
        return node

    @property
    def knives(self) -> int:
        """Knives of the head (the first node's)."""
        return self.node.knives

    @property
    def command_id(self) -> int:
        """COB-ID of the head's command (RPDO3)."""
        return self.node.cob_ids["rpdo3"]

    @property
    def offsets_um(self) -> list[float]:
        """The head's offset table as received, um (eight values)."""
        return self.node.offsets_um

    @property
    def last_command(self) -> dict[str, int] | None:
        """The head's last command received (``enable``, ``knives``, ``alive_counter``)."""
        return self.node.last_command

    @property
    def refused(self) -> int:
        """Commands and tables the amplifiers refused."""
        return sum(n.refused for n in self.nodes)

    # ------------------------------------------------------------------ faults
    def play(self, fault: str, params: Mapping[str, Any], *, start_s: float,
             node_id: int | None = None) -> None:
        """Play a CAN fault of the registry (:class:`config.faults.FaultKind`) from ``start_s``.

        ``can_drop`` drops received frames (``fraction``, ``duration_s``), ``can_silence``
        sends nothing for ``duration_s``: :meth:`inject`'s ``drop_rx`` and ``silence``, on
        node ``node_id`` only (a moulder's head) or every node. ``params`` are the fault's
        checked parameters (others than those are not the node's and are left).

        Raises
        ------
        ValueError
            Not a CAN fault, or what :meth:`inject` refuses.
        """
        what = CAN_FAULTS.get(fault)
        if what is None:
            raise ValueError(f"fault must be one of {', '.join(CAN_FAULTS)}, got {fault!r}")
        own = {k: float(v) for k, v in params.items() if k in ("fraction", "duration_s")}
        self.inject(what, node_id=node_id, start_s=start_s, **own)

    def inject(self, fault: str, *, node_id: int | None = None, **params: float) -> None:
        """Inject a fault.

        Parameters
        ----------
        fault : str
            ``"drop_rx"``: drop received frames, each with probability ``fraction`` (default 1)
            from ``start_s`` (default now: 0) for ``duration_s`` (default forever);
            ``"silence"``: send nothing from ``start_s`` for ``duration_s``;
            ``"clear"``: remove every injected fault.
        node_id : int, optional
            Only that node's frames (one head's amplifier on a moulder's bus): the frames of
            its services (and an NMT command naming it) are dropped, what it sends is
            silenced; default every node on the bus.
        **params : float
            ``fraction``, ``start_s``, ``duration_s``.

        Raises
        ------
        ValueError
            Unknown fault or parameter, a parameter out of range, or ``node_id`` of no node.
        """
        if fault == "clear":
            self._drop.clear()
            self._silence.clear()
            return
        if node_id is not None and all(n.node_id != node_id for n in self.nodes):
            raise ValueError(f"node_id must be one of {[n.node_id for n in self.nodes]}, "
                             f"got {node_id!r}")
        unknown = set(params) - {"fraction", "start_s", "duration_s"}
        if unknown:
            raise ValueError(f"unknown parameter {sorted(unknown)[0]} for fault {fault}")
        start = float(params.get("start_s", 0.0))
        dur = float(params.get("duration_s", math.inf))
        frac = float(params.get("fraction", 1.0))
        if not 0.0 <= frac <= 1.0:
            raise ValueError(f"fraction must be in [0, 1], got {frac!r}")
        if not dur >= 0:
            raise ValueError(f"duration_s must be >= 0, got {dur!r}")
        if fault == "drop_rx":
            self._drop.append(_Window(start, start + dur, frac, node_id))
        elif fault == "silence":
            self._silence.append(_Window(start, start + dur, node_id=node_id))
        else:
            raise ValueError(f"unknown amplifier fault {fault!r} (drop_rx, silence, clear)")

    def _dropping(self, now_s: float, node_id: int | None) -> bool:
        for w in self._drop:
            if w.active(now_s, node_id) and (w.fraction >= 1.0
                                             or self._rng.random() < w.fraction):
                return True
        return False

    def _addressee(self, arbitration_id: int, data: bytes) -> int | None:
        """The node a received frame is for (an NMT command: the node it names; 0: all)."""
        if arbitration_id == 0 and len(data) == 2:
            return data[1] or None
        return self._node_of.get(arbitration_id)

    # ------------------------------------------------------------------ receive
    def on_frame(self, arbitration_id: int, data: bytes, now_s: float) -> bool:
        """Handle one received frame; whether it reached a node (a service of its nodes)."""
        self.received += 1
        if self._drop and self._dropping(now_s, self._addressee(arbitration_id, data)):
            self.dropped += 1
            return False
        want = self._expected.get(arbitration_id)
        if want is None or len(data) != want:
            self.ignored += 1  # its own frames echoed, unknown ids, wrong lengths
            return False
        self.network.notify(arbitration_id, bytes(data), now_s)
        return True

    # ------------------------------------------------------------------ send
    def poll(self, now_s: float) -> list[Frame]:
        """Frames due at machine time ``now_s`` and the answers to what was received.

        The status every 10 ms, the heartbeat every 100 ms, SDO answers; none while silenced.

        A late call sends each frame once and re-aligns its schedule (no bursts of backlog).
        """
        for node in self.nodes:
            node.pump(now_s)
        out = self.network.take()
        silent = [w for w in self._silence if w.start_s <= now_s < w.end_s]
        if silent:
            if any(w.node_id is None for w in silent):
                return []
            quiet = {w.node_id for w in silent}
            out = [f for f in out if self._node_of.get(f[0]) not in quiet]
        self.sent += len(out)
        return out


class AmpNode:
    """The amplifier node on a python-can bus (thin I/O around :class:`AmpNodeCore`).

    Parameters
    ----------
    bus : can.BusABC
        An open bus (the node does not own it unless ``own_bus``).
    core : AmpNodeCore
        The sans-I/O node.
    own_bus : bool
        Shut the bus down in :meth:`close`.
    """

    def __init__(self, bus: Any, core: AmpNodeCore, *, own_bus: bool = False) -> None:
        self.bus = bus
        self.core = core
        self.own_bus = own_bus
        self.send_errors = 0
        self._rx: queue.SimpleQueue[tuple[float, Any]] | None = None
        self._early: deque[tuple[float, Any]] = deque()  # received, not yet due on machine time
        self._stamp: Callable[[], float] = time.monotonic
        self._to_machine: Callable[[float], float] | None = None
        self._last_command_stamp: float | None = None
        self.command_gap_max_s = 0.0
        """Longest wall gap between two commands (RPDO3) received on the receiving
        thread since :meth:`take_command_gap` (the service's side of the setpoint timeout)."""
        self._rx_stop = threading.Event()
        self._rx_thread: threading.Thread | None = None
        self._rx_started = threading.Event()
        self.rx_priority: str | None = None

    def set_timebase(self, clock: Callable[[], float],
                     to_machine: Callable[[float], float] | None) -> None:
        """Stamp received frames with ``clock`` and hand each over at ``to_machine(stamp)``.

        Parameters
        ----------
        clock : callable
            Wall clock the receiving thread stamps frames with, s.
        to_machine : callable or None
            Machine time of a wall stamp (the runner's current mapping); ``None``: every frame
            is handed over at the next :meth:`receive`.
        """
        self._stamp = clock
        self._to_machine = to_machine

    def start_receiving(self, *, realtime: bool = False) -> None:
        """Read the bus on a thread of its own (frames are queued for :meth:`receive`).

        So frames are taken off the bus at once, however busy the stepping thread is; the
        machine still sees them at its own time, in the order received. ``realtime``: the
        thread asks for real-time scheduling (:func:`core.realtime.raise_priority`);
        :attr:`rx_priority` says what it got.
        """
        if self._rx_thread is not None:
            return
        self._rx = queue.SimpleQueue()
        self._rx_thread = threading.Thread(target=self._read_bus, args=(realtime,),
                                           name="amp-node-rx", daemon=True)
        self._rx_thread.start()
        self._rx_started.wait(RX_START_TIMEOUT_S)

    def _read_bus(self, realtime: bool = False) -> None:
        import can

        from core.realtime import raise_priority

        assert self._rx is not None
        try:
            self.rx_priority = raise_priority() if realtime else "normal (not asked)"
        finally:
            self._rx_started.set()
        while not self._rx_stop.is_set():
            try:
                msg = self.bus.recv(timeout=RX_POLL_S)
            except (can.CanError, OSError, ValueError) as exc:  # bus shut down under us
                if not self._rx_stop.is_set():
                    log.warning("CAN receive failed: %s", exc)
                return
            if msg is not None:
                stamp = self._stamp()
                if msg.arbitration_id == self.core.command_id:
                    last = self._last_command_stamp
                    if last is not None and stamp - last > self.command_gap_max_s:
                        self.command_gap_max_s = stamp - last
                    self._last_command_stamp = stamp
                self._rx.put((stamp, msg))

    @property
    def receiving(self) -> bool:
        """Whether the bus is read on the node's own thread (:meth:`start_receiving`)."""
        return self._rx_thread is not None

    def take_command_gap(self) -> float:
        """:attr:`command_gap_max_s` so far, and start the next window, s."""
        gap, self.command_gap_max_s = self.command_gap_max_s, 0.0
        return gap

    def receive(self, now_s: float, *, max_frames: int = 1000) -> int:
        """Hand received frames to the core (non-blocking); returns how many were read.

        With a time base (:meth:`set_timebase`) a frame that arrived after machine time
        ``now_s`` (the machine runs behind the wall clock and is catching up) waits for a later
        call; the frames keep their order.
        """
        n = 0
        while n < max_frames:
            if self._rx is not None:
                if self._early:
                    stamp, msg = self._early[0]
                else:
                    try:
                        stamp, msg = self._rx.get_nowait()
                    except queue.Empty:
                        break
                    self._early.append((stamp, msg))
                to_machine = self._to_machine
                if to_machine is not None and to_machine(stamp) > now_s + ARRIVAL_TOLERANCE_S:
                    break  # not yet arrived on the machine's clock
                self._early.popleft()
            else:
                msg = self.bus.recv(timeout=0.0)
                if msg is None:
                    break
            n += 1
            if msg.is_error_frame or msg.is_remote_frame:
                continue
            if msg.is_extended_id:  # CANopen's predefined connection set is 11-bit
                self.core.received += 1
                self.core.ignored += 1
                continue
            self.core.on_frame(msg.arbitration_id, bytes(msg.data), now_s)
        return n

    def transmit(self, now_s: float) -> int:
        """Send the frames due at ``now_s``; returns how many were sent."""
        import can

        sent = 0
        for fid, data in self.core.poll(now_s):
            try:
                self.bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
                sent += 1
            except (can.CanError, OSError) as exc:
                self.send_errors += 1
                log.warning("CAN send failed: %s", exc)
        return sent

    def pump(self, now_s: float) -> None:
        """Receive everything pending, then send what is due."""
        self.receive(now_s)
        self.transmit(now_s)

    def close(self) -> None:
        """Stop the receiving thread; shut the bus down if the node owns it."""
        self._rx_stop.set()
        if self._rx_thread is not None:
            self._rx_thread.join(timeout=5)
        if self.own_bus:
            self.bus.shutdown()
