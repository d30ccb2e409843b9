"""The cyclic work of the two buses: what the PLC cycle and the CAN cycle do each period.

* PLC cycle: heartbeat register, one read of every register, its judgement (the loops are
  built for the machine it describes), then the feed in the supervisor's state: feed-forward in
  RUN, hold or ramp down in SAFE.
* CAN cycle (never waits): drain the amplifier's frames, judge its status, step the supervisor,
  enable or zero offsets and disable, the command (RPDO3) with a new alive counter.

The composition root (:class:`controller.service.service.Service`) runs them inside the supervisor
boundary, in one task each in real time or one after the other on simulated time.
"""

from __future__ import annotations

from config.machine import MachineConfig
from controller.fieldbus.plc_client import PlcClient
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.service.actuators import Actuators
from controller.service.events import EventLog
from controller.service.loops import ControlLoops
from controller.service.safe_state import SafeStateKeeper
from controller.service.supervisor import SafetyState, SafetyStatus
from core.errors import FieldbusError

PLC_SNAPSHOT_MAX_AGE_CYCLES = 2.0
"""A pair uses the registers the tick read if they are at most this many cycles old."""


class BusCycles:
    """The PLC's and the amplifier's cycles of one service.

    Parameters
    ----------
    cfg : MachineConfig
        ``[safety] cycle_s`` (the age limit of the registers a pair uses).
    plc : PlcClient
        The PLC connection (reads).
    keeper : SafeStateKeeper
        The supervisor.
    loops : ControlLoops
        The feed loop's feed-forward, built from the registers.
    out : Actuators
        The writes.
    report : EventLog
        Counters.
    """

    def __init__(
        self,
        cfg: MachineConfig,
        plc: PlcClient,
        keeper: SafeStateKeeper,
        loops: ControlLoops,
        out: Actuators,
        report: EventLog,
    ) -> None:
        self.cfg = cfg
        self.plc = plc
        self.keeper = keeper
        self.loops = loops
        self.out = out
        self._report = report
        self._snap_t = float("-inf")  # service time of the last good register read
        self._last_actions_s: float | None = None

    # ------------------------------------------------------------------ PLC
    async def plc_io(self, t: float) -> PlcSnapshot | None:
        """Heartbeat and one read of every register; the snapshot if it makes sense."""
        sup = self.keeper.supervisor
        snap: PlcSnapshot | None = None
        try:
            await self.out.beat()
            snap = await self.plc.read()
        except FieldbusError:
            self._report.count("plc_errors")
        if snap is not None:
            sup.plc_answered(t)  # a read answered: refusals and bare writes do not count
            self._snap_t = t
            snap = self.keeper.check_snapshot(snap, t)
        if snap is not None:
            if not self.out.owns_feed:  # a moulder's head: the coordinator's feed is in force
                self.out.feed_setpoint_mm_s = snap.feed_setpoint_mm_s
            self.loops.ensure(snap)
            sup.machine_ok(not snap.estop and snap.spindle_running)
            if not snap.board_present:
                sup.measurement_not_expected(t)
        return snap

    async def plc_actions(self, t: float, snap: PlcSnapshot | None) -> None:
        """The feed in the supervisor's state: feed-forward (RUN) or hold / ramp down (SAFE)."""
        last = self._last_actions_s
        dt = 0.0 if last is None else max(0.0, t - last)
        self._last_actions_s = t
        if self.keeper.state is SafetyState.SAFE:
            await self._safe_actions(t, dt, snap)
        elif snap is not None and self.loops.ready:
            await self.loops.feed_forward(t, snap)

    async def _safe_actions(self, t: float, dt: float, snap: PlcSnapshot | None) -> None:
        if snap is None:
            return  # PLC gone or talking nonsense: no feed write; its watchdog and limits act
        current = snap.feed_setpoint_mm_s
        lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
        target = self.keeper.supervisor.safe_feed(
            current, dt_s=dt, feed_min_mm_s=lo, feed_max_mm_s=hi
        )
        if abs(target - current) > 1e-3:
            await self.out.write_feed(target, t)
        else:
            self.out.feed_setpoint_mm_s = current

    async def snapshot_for(self, t: float) -> PlcSnapshot | None:
        """The tick's registers if at most two cycles old, else a fresh read (else the last)."""
        snap: PlcSnapshot | None = self.plc.last
        max_age = PLC_SNAPSHOT_MAX_AGE_CYCLES * self.cfg.safety.cycle_s
        if snap is None or t - self._snap_t > max_age:
            try:  # the tick's snapshot is stale (PLC slow or gone): ask now
                snap = await self.plc.read()
                self.keeper.supervisor.plc_answered(t)
                self._snap_t = t
            except FieldbusError:
                self._report.count("plc_errors")
                snap = self.plc.last
        return snap

    # ------------------------------------------------------------------ CAN
    def can_cycle(self, t: float) -> SafetyStatus:
        """Drain, judge, step the supervisor, enable or go safe, the command (RPDO3)."""
        piezo = self.out.piezo
        keeper = self.keeper
        try:
            piezo.poll(now_s=t)
        except FieldbusError:
            self._report.count("can_errors")
        if piezo.last_heard_s is not None:
            keeper.supervisor.can_heard(piezo.last_heard_s)
        keeper.observe_amplifier(piezo.status, t)
        status = keeper.step(t)
        if status.state is SafetyState.SAFE:
            keeper.zero_offsets(t)
        else:
            self.out.enable(True, t)
        self.out.command(t)
        return status
