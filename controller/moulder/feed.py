"""The moulder's one feed: the coordinator that writes it, and the variable heads' speeds.

Each head's service learns its own model error (its feed loop's correction, from its own pairs
against the feed the drive really ran: ``FeedLoop.observe_drive``) but writes no feed
(``Service(owns_feed=False)``). Once per PLC cycle the coordinator asks the pure law
(:class:`controller.laws.moulder_feed.MoulderFeedLaw`) for the fastest feed at which every head
meets its target and the speed of each variable head, writes them (the feed to the common
registers, a speed to its head's block), beats the PLC's heartbeat, and tells every head's feed
loop the feed now in force.

Safe state, machine-wide where it must be: when a head's supervisor misses a machine-wide source
(the PLC, its data, the machine), every head is in its safe state, or the coordinator's own code
failed (:meth:`MoulderFeed.fault`: for the recovery time), the feed goes to the safe state
(``[safety] safe_state``: hold or ramp down) and no speed is written. A head in its safe state
for a reason of its own (its camera silent, its amplifier's heartbeat lost, its own code's error
on a pair) keeps its held correction in the law: the others go on at the feed they need.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from config.heads import HeadConfig
from controller.fieldbus.plc_client import PlcClient
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.laws.moulder_feed import HeadFeed, MoulderFeedLaw
from controller.service.supervisor import SafetyState
from core.errors import FieldbusError, ModbusRefused

MACHINE_WIDE = frozenset({"plc", "plc_data", "machine"})
"""Missing sources of a head's supervisor that stop the whole machine's feed (a head's own
unexpected error -- its pair, its frame source -- is that head's safe state only; the
coordinator's own is machine-wide: :attr:`MoulderFeed.faulted`)."""

FEED_WRITE_DEADBAND_MM_S = 0.05
"""A feed setpoint is written when it moved by more than this (mm/s)."""



@dataclass(frozen=True)
class FeedDecision:
    """One cycle of the coordinator: what it decided and why.

    Attributes
    ----------
    t_s : float
        Service time, s.
    feed_mm_s : float or None
        The feed in force after the cycle (``None``: the PLC gave no registers).
    safe : bool
        The machine-wide safe state governed the feed.
    limiting : tuple of str
        The heads that set the feed (empty in the safe state).
    spindle_setpoints_rpm : mapping
        The variable heads' speed setpoints of this cycle, by head.
    """

    t_s: float
    feed_mm_s: float | None
    safe: bool
    limiting: tuple[str, ...] = ()
    spindle_setpoints_rpm: Mapping[str, float] | None = None


class MoulderFeed:
    """Writes the moulder's one feed and its variable heads' speeds (one PLC cycle at a time).

    Parameters
    ----------
    heads : mapping of str to Service
        Every head's service (config order), built with ``owns_feed=False``.
    head_configs : sequence of HeadConfig
        The heads (targets, speed ranges), same order.
    plc : PlcClient
        The coordinator's PLC connection (the common registers: feed, heartbeat).
    law : MoulderFeedLaw
        The pure law.
    """

    def __init__(
        self,
        heads: Mapping[str, Any],
        head_configs: Sequence[HeadConfig],
        *,
        plc: PlcClient,
        law: MoulderFeedLaw,
    ) -> None:
        names = [h.name for h in head_configs]
        if list(heads) != names:
            raise ValueError(f"heads must be the configured heads {names}, got {list(heads)}")
        self.heads = dict(heads)
        self.head_configs = tuple(head_configs)
        self.plc = plc
        self.law = law
        self.heartbeat = 0
        self.last: FeedDecision | None = None
        self.counts = {"cycles": 0, "feed_writes": 0, "speed_writes": 0, "plc_errors": 0,
                       "refused": 0, "safe_cycles": 0, "faults": 0}
        self._fault_until = -math.inf
        self._last_t: float | None = None
        self._snap: PlcSnapshot | None = None  # sample()'s registers, for decide()

    # ------------------------------------------------------------------ the cycle
    async def cycle(self, t: float) -> FeedDecision:
        """Heartbeat, read, decide, write; the decision (never raises for the PLC's trouble)."""
        await self.sample()
        return await self.decide(t)

    async def sample(self) -> PlcSnapshot | None:
        """The cycle's first half: the heartbeat, then one read of the common registers.

        Both in one function 23 transaction where the map offers it
        (:meth:`PlcClient.beat_and_read`). A moulder's PLC cycle takes it before the heads'
        own reads and offers its words to each head (:meth:`PlcClient.offer_common`): the
        machine-wide registers are read once per cycle. ``None`` when the PLC did not answer
        (:meth:`decide` then writes nothing).
        """
        self._snap = None
        try:
            self.heartbeat = (self.heartbeat + 1) & 0xFFFF
            self._snap = await self.plc.beat_and_read(self.heartbeat)
        except FieldbusError:
            self.counts["plc_errors"] += 1
        return self._snap

    async def read_blocks(self, heads: Sequence[int]) -> dict[int, list[int]]:
        """The blocks of ``heads`` in as few requests as the map allows, for the heads' reads.

        :meth:`PlcClient.read_blocks`; empty when the PLC did not answer (each head then reads
        its own block).
        """
        if not heads:
            return {}
        try:
            return await self.plc.read_blocks(heads)
        except FieldbusError:
            self.counts["plc_errors"] += 1
            return {}

    async def decide(self, t: float) -> FeedDecision:
        """The cycle's second half on the registers :meth:`sample` read: decide, write."""
        self.counts["cycles"] += 1
        dt = 0.0 if self._last_t is None else max(0.0, t - self._last_t)
        self._last_t = t
        snap, self._snap = self._snap, None
        if snap is None or snap.problem() is not None:  # no answer, or nonsense: no write
            self.last = FeedDecision(t, None, True)  # (the PLC's watchdog acts)
            return self.last
        if t < self._fault_until or self.machine_safe():
            self.counts["safe_cycles"] += 1
            sup = next(iter(self.heads.values())).keeper.supervisor
            feed = sup.safe_feed(snap.feed_setpoint_mm_s, dt_s=dt,
                                 feed_min_mm_s=snap.feed_min_mm_s,
                                 feed_max_mm_s=snap.feed_max_mm_s)
            await self._write_feed(feed, snap)
            self.last = FeedDecision(t, feed, True)
            return self.last
        if self.last is None or self.last.safe:  # (again) from the feed in force, no jump
            self.law.reset(feed_mm_s=_feed_in_force(snap), now_s=t)
        cmd = self.law.update(self.head_feeds(), now_s=t, feed_min_mm_s=snap.feed_min_mm_s,
                              feed_max_mm_s=snap.feed_max_mm_s)
        feed = await self._write_feed(float(cmd.feed_mm_s), snap)
        for name, rpm in dict(cmd.spindle_setpoints_rpm).items():
            await self._write_speed(name, float(rpm))
        for svc in self.heads.values():
            loop = svc.loops.feed_loop
            snap_h = svc.plc.last
            if loop is not None and snap_h is not None:
                loop.follow_setpoint(now_s=svc.loops.loop_time(t), feed_mm_s=feed,
                                     spindle_rpm=max(float(snap_h.spindle_rpm), 0.0))
        self.last = FeedDecision(t, feed, False, tuple(cmd.limiting),
                                 dict(cmd.spindle_setpoints_rpm))
        return self.last

    def fault(self, t: float, *, hold_s: float) -> None:
        """The coordinator's own cycle failed unexpectedly at ``t``.

        The feed goes to the machine-wide safe state (:meth:`decide`'s safe path, which needs
        no law) for ``hold_s``; then the law starts again from the feed in force.
        """
        self._fault_until = max(self._fault_until, t + float(hold_s))
        self.counts["faults"] += 1
        self.last = FeedDecision(t, None, True)

    def machine_safe(self) -> bool:
        """Whether the machine-wide safe state governs the feed (see the module's text)."""
        states = []
        for svc in self.heads.values():
            status = svc.keeper.status
            safe = svc.keeper.state is SafetyState.SAFE
            states.append(safe)
            if safe and status is not None and MACHINE_WIDE.intersection(status.missing):
                return True
        return all(states)

    def head_feeds(self) -> list[HeadFeed]:
        """What the law needs of every head now (its learnt correction, its speed)."""
        out = []
        for hc in self.head_configs:
            svc = self.heads[hc.name]
            loop = svc.loops.feed_loop
            snap: PlcSnapshot | None = svc.plc.last
            rpm = float(snap.spindle_rpm) if snap is not None else 0.0
            knives = int(snap.knives) if snap is not None else int(hc.knives or 0)
            ready = loop is not None and snap is not None and rpm > 0.0 and knives > 0
            lo, hi = _speed_range(hc, snap)
            out.append(HeadFeed(
                name=hc.name,
                knives=max(knives, 1),
                target_pitch_mm=(loop.pitch_setpoint_mm if loop is not None
                                 else hc.target_pitch_mm),
                rpm_min=lo,
                rpm_max=hi,
                correction=loop.correction if loop is not None else 1.0,
                spindle_rpm=max(rpm, 0.0),
                takes_part=ready,
            ))
        return out

    # ------------------------------------------------------------------ writes
    async def _write_feed(self, feed: float, snap: PlcSnapshot) -> float:
        current = snap.feed_setpoint_mm_s
        if abs(feed - current) <= FEED_WRITE_DEADBAND_MM_S:
            return current
        try:
            await self.plc.write_feed(feed)
        except (ModbusRefused, ValueError):
            self.counts["refused"] += 1
            return current
        except FieldbusError:
            self.counts["plc_errors"] += 1
            return current
        self.counts["feed_writes"] += 1
        return feed

    async def _write_speed(self, name: str, rpm: float) -> None:
        """One head's speed setpoint (the law keeps the deadband); a failed write is retried."""
        plc = self.heads[name].plc
        try:
            await plc.write_spindle_setpoint(rpm)
        except (ModbusRefused, ValueError):
            self.counts["refused"] += 1
            self.law.forget_setpoint(name)
            return
        except FieldbusError:
            self.counts["plc_errors"] += 1
            self.law.forget_setpoint(name)
            return
        self.counts["speed_writes"] += 1

    def describe(self) -> dict[str, Any]:
        """The last decision and the counts (plain JSON)."""
        d = self.last
        return {
            "feed_mm_s": None if d is None else d.feed_mm_s,
            "safe": None if d is None else d.safe,
            "limiting": [] if d is None else list(d.limiting),
            "spindle_setpoints_rpm": {} if d is None else dict(d.spindle_setpoints_rpm or {}),
            **self.counts,
        }


def _feed_in_force(snap: PlcSnapshot) -> float:
    """The feed the law starts from, within the PLC's limits.

    The PLC's setpoint; its actual feed where the setpoint reads 0 (a PLC just restarted).
    """
    lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
    feed = snap.feed_setpoint_mm_s if snap.feed_setpoint_mm_s > 0 else snap.feed_actual_mm_s
    return min(max(float(feed), lo), hi)


def _plc_speed_range(snap: PlcSnapshot | None) -> tuple[float, float] | None:
    """The head's drive's setpoint range from its block (``None``: none, or nonsense)."""
    if snap is None or "spindle_rpm_min" not in snap.values or "spindle_rpm_max" not in snap.values:
        return None
    lo, hi = float(snap["spindle_rpm_min"]), float(snap["spindle_rpm_max"])
    return (lo, hi) if math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi else None


def _speed_range(hc: HeadConfig, snap: PlcSnapshot | None) -> tuple[float, float]:
    """The range the coordinator may set a head's speed in.

    A head configured at one speed is fixed at its measured speed (never a speed write); one
    configured with a range gets that range within its drive's (the PLC's block); one that
    leaves its speed to the PLC (no ``rpm`` keys) gets the drive's range. No sound range in
    common: fixed at its measured speed.
    """
    rpm = float(snap.spindle_rpm) if snap is not None else float(hc.rpm or 0.0)
    plc = _plc_speed_range(snap)
    if hc.rpm_min is None or hc.rpm_max is None:  # the PLC's
        return plc if plc is not None else (rpm, rpm)
    if not hc.variable:
        return rpm, rpm
    lo, hi = float(hc.rpm_min), float(hc.rpm_max)
    if plc is not None:
        lo, hi = max(lo, plc[0]), min(hi, plc[1])
    return (lo, hi) if lo <= hi else (rpm, rpm)
