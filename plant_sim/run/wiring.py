"""Wiring a :class:`~plant_sim.run.runner.SimRunner` from a ``SimConfig`` (``planer sim``'s way).

The PLC in its own process, the amplifier (a CANopen node) on the configured CAN bus, the spool
writer and the render workers: built here, closed again (our bus) if any later part fails. Kept
apart from the runner, which only steps and serves what it is given.

A configuration with ``[[heads]]`` (or a :class:`~plant_sim.machine.moulder.Moulder` given) is
wired as a moulder (:func:`wire_moulder`): every head's block on the one PLC, every head's
amplifier node on the one bus, each head's spool ``<spool_dir>/<head name>``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from core.realtime import RENDER_NICE
from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
from plant_sim.interfaces.plc_process import PlcProcess
from protocol.can_transport import bus_from_config, describe_bus
from protocol.registers import RegisterMap

__all__ = ["wire_moulder", "wire_runner"]


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
        Use this sink instead of a spool directory (a moulder: a mapping of head name to
        sink, :func:`wire_moulder`).
    can_bus : can.BusABC, optional
        Use this bus instead of opening ``[can]``.
    **kwargs
        Passed to the constructor (``clock``, ``sleep``, ``out``...).
    """
    from protocol.spool import SpoolWriter

    if wants_moulder(cfg, machine):
        return wire_moulder(cls, cfg, machine=machine, seed=seed, render_images=render_images,
                            render_workers=render_workers, render_nice=render_nice,
                            realtime_interfaces=realtime_interfaces, time_scale=time_scale,
                            modbus_port=modbus_port, spool_dir=spool_dir, sinks=sink,
                            can_bus=can_bus, **kwargs)
    renders = False
    if machine is None:
        from plant_sim.machine.machine import Machine

        machine = Machine(cfg, seed=seed, render_images=False)
        if render_images:
            machine.assembler.defer_rendering()
            renders = True

    def parts() -> dict[str, Any]:
        from plant_sim.run.render_worker import RenderPool

        out = sink
        if out is None:
            out = SpoolWriter(Path(spool_dir if spool_dir is not None else cfg.frames.spool_dir),
                              keep=cfg.frames.keep)
        render = None
        if renders:  # a spool is written by the one render worker
            spool = out if isinstance(out, SpoolWriter) else None
            render = RenderPool(cfg, seed=seed, workers=render_workers, writer=spool,
                                nice=render_nice)
        return {"sink": out, "render": render}

    return _wire(cls, cfg, machine,
                 core=lambda: AmpNodeCore(machine, knives=cfg.cutterhead.knives,
                                          node_id=cfg.can.node_id, eds=cfg.can.eds, seed=seed),
                 parts=parts, realtime_interfaces=realtime_interfaces, time_scale=time_scale,
                 modbus_port=modbus_port, can_bus=can_bus, **kwargs)


def _wire(cls: Any, cfg: Any, machine: Any, *, core: Callable[[], Any],
          parts: Callable[[], dict[str, Any]], realtime_interfaces: bool = True,
          time_scale: float | None = None, modbus_port: int | None = None, can_bus: Any = None,
          **kwargs: Any) -> Any:
    """The runner ``cls`` over ``machine``: its PLC process, its amplifier's node(s) on the bus.

    ``core()`` builds the amplifier's :class:`AmpNodeCore`, ``parts()`` the runner's frame
    sink(s) and render pool(s) (as keyword arguments of ``cls``). A failure from the bus on
    (an unusable spool folder, a bad option) closes the bus we opened.
    """
    plc = _plc(cfg, machine, modbus_port, realtime_interfaces)
    own_bus = can_bus is None
    bus = bus_from_config(cfg.can) if own_bus else can_bus
    try:
        amp = AmpNode(bus, core(), own_bus=own_bus)
        runner = cls(
            machine,
            plc=plc,
            amp=amp,
            **parts(),
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


def wants_moulder(cfg: Any, machine: Any) -> bool:
    """Whether to wire a moulder: a ``Moulder`` given, or none and ``[[heads]]`` declared."""
    if machine is None:
        return bool(cfg.declared_heads)
    from plant_sim.machine.moulder import Moulder

    return isinstance(machine, Moulder)


def _plc(cfg: Any, machine: Any, modbus_port: int | None, realtime: bool) -> PlcProcess:
    return PlcProcess(
        machine,
        register_map=RegisterMap.load(),
        host=cfg.modbus.host,
        port=cfg.modbus.port if modbus_port is None else modbus_port,
        unit_id=cfg.modbus.unit_id,
        realtime=realtime,
    )


def wire_moulder(cls: Any, cfg: Any, *, machine: Any = None, seed: int = 0,
                 render_images: bool = True, render_workers: int = 2,
                 render_nice: int | None = RENDER_NICE, spool_dir: str | Path | None = None,
                 sinks: Any = None, **options: Any) -> Any:
    """A :class:`~plant_sim.run.moulder_runner.MoulderRunner` wired as ``cfg`` says.

    As :func:`wire_runner`, for a moulder: the PLC process serves the common registers and
    every head's block; ONE bus (``[can]``) carries every head's amplifier node (its
    ``node_id``); head ``name`` writes to the spool ``<spool_dir>/<name>`` (the service side's
    default spool of that head, ``config.machine.head_config``); with ``render_images`` (the
    moulder built here) each head has its own :class:`~plant_sim.run.render_worker.RenderPool`
    of ``max(1, render_workers // heads)`` workers (its camera, optics and seed
    :func:`~plant_sim.machine.moulder.head_seed`), which writes that head's spool.

    Parameters
    ----------
    cls : type
        The runner class: a ``MoulderRunner`` (sub)class (``RUNS_HEADS``).
    machine : Moulder, optional
        Default: ``Moulder(cfg, seed=seed, render_images=False)``, rendering deferred.
    sinks : mapping of str to FrameSink, optional
        Each head's sink instead of its spool directory.
    seed, render_images, render_workers, render_nice, spool_dir
        As :func:`wire_runner`.
    **options
        As :func:`wire_runner` (``realtime_interfaces``, ``time_scale``, ``modbus_port``,
        ``can_bus``) and the constructor's.
    """
    from config.sim import head_sim_config
    from plant_sim.machine.moulder import Moulder, head_seed
    from plant_sim.run.driver import MoulderDriver
    from plant_sim.run.render_worker import RenderPool
    from protocol.spool import SpoolWriter

    if not getattr(cls, "RUNS_HEADS", False):
        raise ValueError(f"{getattr(cls, '__name__', cls)} runs one machine; a sim.toml with "
                         "several [[heads]] needs plant_sim.run.moulder_runner.MoulderRunner "
                         "(runner_for(cfg) picks the runner)")
    renders = False
    if machine is None:
        machine = Moulder(cfg, seed=seed, render_images=False)
        if render_images:
            for m in machine.heads.values():
                m.assembler.defer_rendering()
            renders = True
    names = tuple(machine.names)

    def parts() -> dict[str, Any]:
        out = sinks
        if out is None:
            root = Path(spool_dir if spool_dir is not None else cfg.frames.spool_dir)
            out = {n: SpoolWriter(root / n, keep=cfg.frames.keep) for n in names}
        pools = None
        if renders:
            workers = max(1, int(render_workers) // len(names))
            pools = {n: RenderPool(head_sim_config(cfg, n), seed=head_seed(seed, i),
                                   workers=workers, nice=render_nice,
                                   writer=out[n] if isinstance(out[n], SpoolWriter) else None)
                     for i, n in enumerate(names)}
        return {"sinks": out, "renders": pools}

    return _wire(cls, cfg, machine,
                 core=lambda: MoulderDriver.amp_core(machine, eds=cfg.can.eds, seed=seed),
                 parts=parts, **options)
