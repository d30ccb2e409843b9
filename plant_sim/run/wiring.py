"""Wiring a :class:`~plant_sim.run.runner.SimRunner` from a ``SimConfig`` (``planer sim``'s way).

The PLC in its own process, the amplifier (a CANopen node) on the configured CAN bus, the spool
writer and the render workers: built here, closed again (our bus) if any later part fails. Kept
apart from the runner, which only steps and serves what it is given.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from core.realtime import RENDER_NICE
from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
from plant_sim.interfaces.plc_process import PlcProcess
from protocol.can_transport import bus_from_config, describe_bus
from protocol.registers import RegisterMap

__all__ = ["wire_runner"]


def wire_runner(
    cls: Any,
    cfg: Any,
    *,
    machine: Any = None,
    seed: int = 0,
    render_images: bool = True,
    render_workers: int = 2,
    render_nice: int | None = RENDER_NICE,
    realtime_interfaces: bool = True,
    time_scale: float | None = None,
    modbus_port: int | None = None,
    spool_dir: str | Path | None = None,
    sink: Any = None,
    can_bus: Any = None,
    **kwargs: Any,
) -> Any:
    """Build ``cls`` (a ``SimRunner``) as ``cfg`` says: ``[modbus]``, ``[can]``, ``[frames]``.

    Modbus is served from its own process, CAN read on its own thread and, for a machine
    built here with ``render_images``, the images rendered by ``render_workers`` processes.

    Parameters
    ----------
    cls : type
        The runner class (``SimRunner.from_config`` passes its own).
    cfg : config.sim.SimConfig
        The simulator configuration (``[run]`` gives the time scale and step).
    machine : Machine, optional
        Default: ``plant_sim.machine.machine.Machine(cfg, seed=seed)`` with deferred rendering.
    render_images : bool
        Render the camera's images (default machine only).
    render_workers : int
        Worker processes rendering images and writing the spool (>= 1, in order): two take
        twice the CPU share of a busy host, so the clock slows less.
    render_nice : int or None
        Nice value of the render workers (default
        :data:`~plant_sim.interfaces.thread.RENDER_NICE`: they yield to the interfaces and the
        service); ``None``: as this process.
    realtime_interfaces : bool
        The PLC process and the CAN receive thread ask for real-time scheduling (a real
        PLC does not stop answering because a PC is busy); the banner says what they got.
    time_scale, modbus_port, spool_dir : optional
        Override ``[run] time_scale``, ``[modbus] port``, ``[frames] spool_dir``.
    sink : FrameSink, optional
        Use this sink instead of a spool directory.
    can_bus : can.BusABC, optional
        Use this bus instead of opening ``[can]``.
    **kwargs
        Passed to the constructor (``clock``, ``sleep``, ``out``...).
    """
    from protocol.spool import SpoolWriter

    render = None
    if machine is None:
        from plant_sim.machine.machine import Machine
        from plant_sim.run.render_worker import RenderPool

        machine = Machine(cfg, seed=seed, render_images=False)
        if render_images:
            machine.assembler.defer_rendering()
            render = (RenderPool, render_workers)
    rmap = RegisterMap.load()
    plc = PlcProcess(
        machine,
        register_map=rmap,
        host=cfg.modbus.host,
        port=cfg.modbus.port if modbus_port is None else modbus_port,
        unit_id=cfg.modbus.unit_id,
        realtime=realtime_interfaces,
    )
    own_bus = can_bus is None
    bus = bus_from_config(cfg.can) if own_bus else can_bus
    try:  # a failure from here on (unusable spool folder, bad option) closes our bus
        core = AmpNodeCore(machine, knives=cfg.cutterhead.knives, node_id=cfg.can.node_id,
                           eds=cfg.can.eds, seed=seed)
        amp = AmpNode(bus, core, own_bus=own_bus)
        if sink is None:
            directory = Path(spool_dir if spool_dir is not None else cfg.frames.spool_dir)
            sink = SpoolWriter(directory, keep=cfg.frames.keep)
        if render is not None:  # a spool is written by the one render worker
            pool_cls, workers = render
            spool = sink if isinstance(sink, SpoolWriter) else None
            render = pool_cls(cfg, seed=seed, workers=workers, writer=spool,
                              nice=render_nice)
        runner = cls(
            machine,
            plc=plc,
            amp=amp,
            sink=sink,
            render=render,
            threaded_interfaces=True,
            realtime_interfaces=realtime_interfaces,
            time_scale=cfg.run.time_scale if time_scale is None else time_scale,
            step_s=cfg.run.step_s,
            **kwargs,
        )
    except BaseException:
        if own_bus:
            bus.shutdown()
        raise
    runner.description["can"] = describe_bus(cfg.can.interface, cfg.can.channel)
    return runner

