"""A moulder's service wired as ``machine.toml`` says: a service per head, the feed coordinator.

Every head gets what one head's ``open_service`` opens, for its own part of the machine: a
Modbus TCP client over its head's view of the register map (its block read with function 23;
the common registers the coordinator reads once per cycle for every head), a client of its
amplifier (its node id) on ONE CAN connection the heads share (one CANopen master,
:class:`~controller.fieldbus.canopen_amp.AmpBus`: every frame received and decoded once), its
rig, its view of the ONE quality log the heads share (each record with its ``head``, its own
journal and learned state; one connection, one journal thread and one database thread for every
head's records: :class:`~controller.quality.write_ahead.WriterGroup`); the coordinator a Modbus
client of its own over the common registers (the feed, the heartbeat). Nothing is contacted
until the first cycle. :func:`share_workers` gives every head's pipeline one pool of
measurement worker processes, each head's pairs measured with its own rig.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from config.machine import MachineConfig, eds_path, head_config, registers_path, rig_path
from controller.moulder.feed import MoulderFeed
from controller.moulder.service import MoulderService


def open_moulder_service(
    cfg: MachineConfig,
    *,
    clock: Callable[[], float] = time.monotonic,
    threaded: bool = True,
    log_path: Path | str | None = None,
    can_bus: Any = None,
) -> MoulderService:
    """Every head's service and the coordinator of a ``machine.toml`` with ``[[heads]]``.

    Parameters
    ----------
    cfg : MachineConfig
        The configuration (two or more heads; one head is ``open_service``'s).
    clock : callable
        Monotonic seconds.
    threaded : bool
        Measure and log in worker threads (real time).
    log_path : Path or str, optional
        Override ``[log] path`` (a file, or a ``postgresql://`` URL).
    can_bus : can.BusABC, optional
        Use this bus instead of opening the first head's ``[can]`` bus: every head on that bus
        has its amplifier on it (the moulder closes it); a head naming another bus gets that
        one opened.
    """
    from config.rig import load_rig
    from controller.fieldbus.canopen_amp import AmpBus
    from controller.fieldbus.piezo_client import PiezoClient, default_send_timeout_s, open_bus
    from controller.fieldbus.plc_client import PlcClient
    from controller.fieldbus.plc_protocol import Backoff
    from controller.laws.moulder_feed import MoulderFeedConfig, MoulderFeedLaw
    from controller.quality.log import open_quality_log
    from controller.quality.write_ahead import WriterGroup
    from controller.service.measurement import VisionMeasurers
    from controller.service.service import Service, default_log_path
    from protocol.registers import RegisterMap

    path = default_log_path(cfg, log_path)
    regmap = RegisterMap.load(registers_path(cfg))

    def plc(view: RegisterMap) -> PlcClient:
        return PlcClient.tcp(cfg.plc.host, cfg.plc.port, unit_id=cfg.plc.unit_id,
                             timeout_s=cfg.plc.timeout_s, regmap=view,
                             backoff=Backoff(cfg.plc.backoff_initial_s, cfg.plc.backoff_max_s),
                             clock=clock)

    heads: dict[str, Service] = {}
    opened: list[Any] = []
    masters: dict[tuple, AmpBus] = {}  # one CAN connection per bus the heads name
    # ONE connection to the log and one pair of writer threads for every head's records
    writers = WriterGroup(open_quality_log(path, machine_id=cfg.log.machine_id or None))
    opened.append(writers.close)
    try:
        for i, hc in enumerate(cfg.heads):
            hcfg = head_config(cfg, hc.name)
            where = (hcfg.can.interface, hcfg.can.channel, tuple(sorted(
                (k, repr(v)) for k, v in dict(hcfg.can.options).items())))
            if where not in masters:
                bus = can_bus if can_bus is not None and not masters else open_bus(
                    hcfg.can.interface, hcfg.can.channel, dict(hcfg.can.options))
                opened.append(bus.shutdown)  # until its master owns it (a bad EDS: closed)
                masters[where] = AmpBus(bus, eds=eds_path(hcfg), send_timeout_s=(
                    default_send_timeout_s(hcfg.can.command_period_s)))
                opened[-1] = masters[where].close
            piezo = PiezoClient(None, knives=hc.knives or 4, node_id=hcfg.can.node_id,
                                eds=eds_path(hcfg), command_period_s=hcfg.can.command_period_s,
                                offsets_period_s=hcfg.can.offsets_period_s,
                                stroke_um=hcfg.stroke_um, ampbus=masters[where])
            log = writers.head_log()  # the head's view: its sink joins the one group
            rig = load_rig(rig_path(hcfg))
            svc = Service(hcfg, plc=plc(regmap.for_head(i)), piezo=piezo, rig=rig, log=log,
                          clock=clock, threaded=threaded,
                          measurer_factory=VisionMeasurers(rig, defects=hcfg.quality.defects),
                          pairs_per_s=hcfg.frames.pairs_per_s, owns_feed=False)
            opened.append(svc.close)  # the service closes its view (the shared parts stay open)
            log.set_quality_class(svc.quality_class, head=hc.name)
            heads[hc.name] = svc
        feed = MoulderFeed(heads, cfg.heads, plc=plc(regmap), law=MoulderFeedLaw(
            MoulderFeedConfig(rate_max_mm_s2=_rate_max(cfg))))
    except BaseException:
        for close in reversed(opened):
            close()
        raise
    return MoulderService(heads, cfg.heads, feed=feed, shared=(*masters.values(), writers))


def share_workers(moulder: MoulderService, workers: int, *, shape: tuple[int, int] | None,
                  timeout_s: float, nice: int | None = None, depth: int | None = None,
                  cores: int | None = None) -> tuple[Any, str | None]:
    """Start ONE pool of measurement workers for every head; each head measures in it.

    Each head's pipeline gets the pool as a
    :class:`~controller.workers.pool.PoolForFactory` of its own measurer factory (its rig:
    the workers are given every head's factory once). Blocks while the workers set up (run
    it off the event loop).

    Parameters
    ----------
    moulder : MoulderService
        The heads.
    workers : int
        Worker processes (0: none, each head measures in the service's process).
    shape : tuple of int, optional
        ``(height, width)`` of the images.
    timeout_s : float
        Longest a pair may take in a worker, s.
    nice : int, optional
        Nice value of the workers.
    depth : int, optional
        Pairs a worker holds at once (default the pool's).
    cores : int, optional
        Cores available (more workers than that become one per core, with a warning).

    Returns
    -------
    (MeasureWorkerPool or None, str or None)
        The started pool (the caller closes it, after the moulder) and the planner's warning.
    """
    from controller.workers.pool import (
        DEFAULT_DEPTH,
        MeasureWorkerPool,
        PoolForFactory,
        available_cores,
        plan_workers,
    )
    from core.checks import check_int

    check_int("workers", workers, lo=0)
    if workers == 0:
        return None, None
    n, warning = plan_workers(workers, cores=available_cores() if cores is None else cores)
    first = moulder.first
    pool = MeasureWorkerPool(first.measurement.factory, workers=n, shape=shape,
                             timeout_s=timeout_s, nice=nice,
                             depth=DEFAULT_DEPTH if depth is None else depth)
    pool.start()
    try:
        for svc in moulder.heads.values():  # each head's pairs measured with its own rig
            svc.pipeline.use_workers(PoolForFactory(pool, svc.measurement.factory))
    except BaseException:
        pool.close()
        raise
    return pool, warning


def _rate_max(cfg: MachineConfig) -> float:
    """The feed's rate limit: the feed loop's (``[feed_loop] rate_max_mm_s2``, its default)."""
    from controller.laws.feed_loop import FeedLoopConfig

    return float(cfg.feed_loop.get("rate_max_mm_s2", FeedLoopConfig.rate_max_mm_s2))
