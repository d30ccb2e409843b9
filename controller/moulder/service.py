"""The moulder's service: one :class:`~controller.service.service.Service` per head, one feed.

Every head keeps all of a single head's machinery (its measurement, uniformity loop, knife
attribution, learned state, quality records with its ``head``, its amplifier and its safe state for
its offsets); the :class:`~controller.moulder.feed.MoulderFeed` coordinator writes the one feed and
the variable heads' speeds. A head whose camera goes silent or whose amplifier is lost goes to its
own safe state (its offsets) while the others stay controlled.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Mapping, Sequence
from typing import Any

from config.heads import HeadConfig
from controller.moulder.feed import FeedDecision, MoulderFeed
from controller.service.service import (
    FrameCount,
    FrameResult,
    Service,
    run_periodic,
    run_until_stopped,
)
from controller.service.status import ServiceStatus
from core.closing import close_all


class MoulderService:
    """Several heads' services and the feed coordinator, stepped together.

    Parameters
    ----------
    heads : mapping of str to Service
        Each head's service (built with ``owns_feed=False``), in the configured order.
    head_configs : sequence of HeadConfig
        The heads, same order.
    feed : MoulderFeed
        The coordinator of the one feed.
    shared : sequence, optional
        What the heads share and the moulder closes after every head (``close()``): the one
        CAN master of every head's amplifier (:class:`~controller.fieldbus.canopen_amp.AmpBus`).
    """

    def __init__(self, heads: Mapping[str, Service], head_configs: Sequence[HeadConfig], *,
                 feed: MoulderFeed, shared: Sequence[Any] = ()) -> None:
        if not heads:
            raise ValueError("heads must name at least one head's service")
        for name, svc in heads.items():
            if svc.out.owns_feed:
                raise ValueError(f"head {name!r}: its service writes the feed (owns_feed=True); "
                                 "a moulder's heads leave the feed to the coordinator")
        self.heads: dict[str, Service] = dict(heads)
        self.head_configs: tuple[HeadConfig, ...] = tuple(head_configs)
        self.feed = feed
        self.shared = tuple(shared)
        span = _common_span(feed.plc)
        self.sharing_common: tuple[str, ...] = tuple(
            name for name, svc in self.heads.items()
            if span is not None and _common_span(svc.plc) == span)
        """The heads whose PLC cycle takes the coordinator's read of the common registers."""
        self.sharing_blocks: dict[str, int] = {
            name: head for name in self.sharing_common
            if (head := _block_head(self.heads[name].plc, feed.plc)) is not None}
        """The heads (and their block's index) whose block the coordinator reads for them."""

    async def tick(self, now_s: float) -> FeedDecision:
        """One control cycle: every head's buses and supervisor, then the one feed."""
        for svc in self.heads.values():
            await svc.tick(now_s)
        await self._coordinate(now_s, lambda: self.feed.cycle(now_s))
        assert self.feed.last is not None
        return self.feed.last

    async def handle_frame(self, head: str, frame: Any, *, now_s: float) -> FrameResult:
        """Measure one pair of ``head``'s camera and control that head (its records too)."""
        try:
            svc = self.heads[head]
        except KeyError:
            raise ValueError(f"head must be one of {list(self.heads)}, got {head!r}") from None
        return await svc.handle_frame(frame, now_s=now_s)

    # ------------------------------------------------------------------ real time
    @property
    def first(self) -> Service:
        """The first head's service (its clock and safety periods are the machine's)."""
        return next(iter(self.heads.values()))

    async def plc_cycle(self) -> None:
        """Every head's PLC cycle (its registers, its supervisor), then the one feed.

        The machine-wide registers are read once: the coordinator's heartbeat and read first
        (one function 23), its words of the common span offered to every head
        (:attr:`sharing_common`); then the coordinator reads the heads' blocks
        (:attr:`sharing_blocks`) in as few requests as the map allows and offers each head its
        block, whose read then asks the PLC for nothing. A head offered no block reads its
        own; one offered nothing (the PLC did not answer) reads both itself. The coordinator
        decides after the heads' cycles.
        """
        clock = self.first.service_clock

        async def sample() -> None:
            snap = await self.feed.sample()
            words = self.feed.plc.last_common if snap is not None else None
            blocks = ({} if words is None
                      else await self.feed.read_blocks(list(self.sharing_blocks.values())))
            for name in self.sharing_common:  # none this cycle: each head reads its own
                plc = self.heads[name].plc
                plc.offer_common(words)
                plc.offer_block(blocks.get(self.sharing_blocks.get(name, -1)))

        await self._coordinate(clock.now(), sample)
        for svc in self.heads.values():
            await svc.plc_cycle()
        t = clock.now()
        await self._coordinate(t, lambda: self.feed.decide(t))

    async def _coordinate(self, t: float, step: Callable[[], Awaitable[Any]]) -> None:
        """One step of the coordinator inside the first head's supervisor boundary.

        The coordinator's own unexpected error is reported as the first head's service error
        (the one boundary), and the feed then holds the machine-wide safe state for the
        recovery time (:meth:`MoulderFeed.fault`), whichever step failed.
        """
        first = self.first
        with first.keeper.boundary(t, "feed coordinator", part="plc") as g:
            await step()
        if g.failed:
            self.feed.fault(t, hold_s=first.cfg.safety.recovery_s)

    def can_cycle(self) -> None:
        """Every head's CAN cycle (its amplifier's command and status; never waits)."""
        for svc in self.heads.values():
            svc.can_cycle()

    async def run(self, sources: Mapping[str, Any], *, stop: asyncio.Event | None = None,
                  max_frames: int | None = None) -> None:
        """Run in real time until ``stop`` is set (or ``max_frames`` pairs of all heads).

        One PLC task (every head's registers, then the feed coordinator), one CAN task (every
        head's amplifier), one frame task per head on its own source (``sources[name]``: its
        camera or spool), as :meth:`Service.run` runs one head.
        """
        missing = [n for n in self.heads if n not in sources]
        if missing:
            raise ValueError(f"sources must give every head a frame source, missing {missing}")
        stop = stop or asyncio.Event()
        cfg = self.first.cfg
        plc_period = cfg.safety.cycle_s
        can_period = min(cfg.can.command_period_s, plc_period)
        count = FrameCount(max_frames)
        tasks = [asyncio.create_task(run_periodic(can_period, self.can_cycle, stop)),
                 asyncio.create_task(run_periodic(plc_period, self.plc_cycle, stop))]
        tasks += [asyncio.create_task(svc.take_frames(sources[name], stop, count))
                  for name, svc in self.heads.items()]
        try:
            await run_until_stopped(tasks, stop)
        finally:  # every head's last pairs and records, even when one head's finish raised
            await _finish_all([(svc, sources[name]) for name, svc in self.heads.items()])

    def status(self) -> dict[str, ServiceStatus]:
        """Every head's status, by head."""
        return {name: svc.status() for name, svc in self.heads.items()}

    def close(self) -> None:
        """Close every head's service (each leaves its amplifier safe, writes its state)."""
        # every part closed even when one before it raised (no catch-all: the errors chain)
        close_all([svc.close for svc in self.heads.values()] + [self.feed.plc.close]
                  + [part.close for part in self.shared])


def _common_span(plc: Any) -> tuple[int, int] | None:
    """The ``(address, words)`` of a PLC client's first read range (``None``: not a client)."""
    protocol = getattr(plc, "protocol", None)
    ranges = getattr(protocol, "ranges", None)
    return tuple(ranges[0]) if ranges else None


def _block_head(plc: Any, coordinator: Any) -> int | None:
    """The head whose block a head's PLC client reads, if the coordinator's can read it.

    That is when the client is over a head's view of the coordinator's map; else ``None``.
    """
    regmap = getattr(getattr(plc, "protocol", None), "regmap", None)
    whole = getattr(getattr(coordinator, "protocol", None), "regmap", None)
    head = getattr(regmap, "head", None)
    if head is None or whole is None or regmap.heads != whole.heads:
        return None
    return int(head)


async def _finish_all(items: list[tuple[Service, Any]]) -> None:
    """``service.finish(source)`` of every item in order, each even when one before raised."""
    if not items:
        return
    svc, source = items[0]
    try:
        await svc.finish(source)
    finally:
        await _finish_all(items[1:])
