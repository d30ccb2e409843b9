"""A moulder's service wired as ``machine.toml`` says: a service per head, the feed coordinator.

Every head gets what one head's ``open_service`` opens, for its own part of the machine: a
Modbus TCP client over its head's view of the register map (its block read with function 23),
a CAN connection of its own on the configured bus to its amplifier (its node id), its rig, its
connection to the quality log (each record with its ``head``, its own journal and learned
state); the coordinator a Modbus client of its own over the common registers (the feed, the
heartbeat). Nothing is contacted until the first cycle.
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
    """
    from config.rig import load_rig
    from controller.fieldbus.piezo_client import PiezoClient, open_bus
    from controller.fieldbus.plc_client import PlcClient
    from controller.fieldbus.plc_protocol import Backoff
    from controller.laws.moulder_feed import MoulderFeedConfig, MoulderFeedLaw
    from controller.quality.log import database_url, is_database_url, open_quality_log
    from controller.service.measurement import VisionMeasurers
    from controller.service.service import Service, default_log_path
    from protocol.registers import RegisterMap

    if log_path is None:
        path: Path | str = default_log_path(cfg)
    elif is_database_url(log_path):
        path = database_url(log_path)
    else:
        path = Path(log_path)
        path.parent.mkdir(parents=True, exist_ok=True)
    regmap = RegisterMap.load(registers_path(cfg))

    def plc(view: RegisterMap) -> PlcClient:
        return PlcClient.tcp(cfg.plc.host, cfg.plc.port, unit_id=cfg.plc.unit_id,
                             timeout_s=cfg.plc.timeout_s, regmap=view,
                             backoff=Backoff(cfg.plc.backoff_initial_s, cfg.plc.backoff_max_s),
                             clock=clock)

    heads: dict[str, Service] = {}
    opened: list[Any] = []
    try:
        for i, hc in enumerate(cfg.heads):
            hcfg = head_config(cfg, hc.name)
            bus = open_bus(hcfg.can.interface, hcfg.can.channel, dict(hcfg.can.options))
            opened.append(bus.shutdown)
            piezo = PiezoClient(bus, knives=hc.knives or 4, node_id=hcfg.can.node_id,
                                eds=eds_path(hcfg), command_period_s=hcfg.can.command_period_s,
                                offsets_period_s=hcfg.can.offsets_period_s,
                                stroke_um=hcfg.stroke_um)
            log = open_quality_log(path, machine_id=cfg.log.machine_id or None)
            opened.append(log.close)
            rig = load_rig(rig_path(hcfg))
            svc = Service(hcfg, plc=plc(regmap.for_head(i)), piezo=piezo, rig=rig, log=log,
                          clock=clock, threaded=threaded,
                          measurer_factory=VisionMeasurers(rig, defects=hcfg.quality.defects),
                          pairs_per_s=hcfg.frames.pairs_per_s, owns_feed=False)
            opened[-2:] = [svc.close]  # the service closes its bus and its log
            log.set_quality_class(svc.quality_class, head=hc.name)
            heads[hc.name] = svc
        feed = MoulderFeed(heads, cfg.heads, plc=plc(regmap), law=MoulderFeedLaw(
            MoulderFeedConfig(rate_max_mm_s2=_rate_max(cfg))))
    except BaseException:
        for close in reversed(opened):
            close()
        raise
    return MoulderService(heads, cfg.heads, feed=feed)


def _rate_max(cfg: MachineConfig) -> float:
    """The feed's rate limit: the feed loop's (``[feed_loop] rate_max_mm_s2``, its default)."""
    from controller.laws.feed_loop import FeedLoopConfig

    return float(cfg.feed_loop.get("rate_max_mm_s2", FeedLoopConfig.rate_max_mm_s2))
