"""In-process HIL: the simulated machine and the service in one process, on simulated time.

With ``realtime`` (``planer hil --in-process`` asks for it) a paced run's event loop -- the
thread that steps the machine, reads the PLC, measures each pair and writes its setpoints, i.e.
every stage on a pair's path -- is raised as ``planer serve`` raises its bus thread
(:func:`core.realtime.realtime_thread`: ``SCHED_FIFO`` at ``BUS_RT_PRIORITY`` with
``SCHED_RESET_ON_FORK``, else nice -10; ``RLIMIT_RTTIME`` guard), together with the light threads
that share its interpreter lock (the simulated PLC's Modbus server, the feed of the servers'
process). The servers' process itself (pages, OPC UA: whatever serves clients) runs at nice +10
(:mod:`controller.edge.process`), so client load never takes a core from the loop. Here the
simulated machine's images are rendered on that same thread (there are no render workers in
one process); a paced run blocks every cycle (the pacer's sleep, the Modbus round trip), and a
run that stops blocking for 0.5 s of CPU is dropped to normal scheduling by the guard (the
summary's ``priority.demoted``). An unpaced run is a batch computation and is not raised.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from config.machine import MachineConfig
from controller.service.service import FrameResult, Service
from planer.hil.interrupt import raise_if_cancel_lost
from planer.hil.pacing import Pacer
from planer.hil.run_end import note_run_end
from planer.hil.scenario import Progress, Scenario, machine_config_for, sim_config_for
from planer.hil.summary import PROGRESS_LEGEND, BoardTravel, _progress_line, _service_summary

# ---------------------------------------------------------------------------------- in-process
_channels = itertools.count()


class InProcessPlant:
    """The simulated machine and the service wired together in one process (simulated time).

    Every :meth:`step` advances the plant by one control cycle through the simulator's one
    :class:`~plant_sim.run.driver.PlantDriver` (amplifier node, queued PLC writes, machine, PLC
    registers, interface faults), runs one :meth:`Service.tick` and hands the pairs captured in
    that cycle to :meth:`Service.handle_frame` -- all at the machine's time, so a run is
    deterministic and as fast as the CPU allows.

    Parameters
    ----------
    cfg : MachineConfig
        The service's configuration (``log.path`` is the quality log unless ``log`` is given).
    sim_cfg : SimConfig
        The simulator's configuration.
    seed : int
        Simulator seed.
    plc_transport : {"direct", "tcp"}
        ``direct``: :class:`MachineRegisterBus`; ``tcp``: the simulator's Modbus server on an
        ephemeral 127.0.0.1 port, served from its own thread (call :meth:`start` first).
    measurer_factory : callable, optional
        ``factory(shape)``; default the vision pipeline's ``Measurer(rig, shape)``.
    log : QualityLog or None or "config"
        The quality log; ``"config"`` opens ``cfg.log.path``.
    render_images : bool
        Render the camera images (``False``: frames carry counts and truth only; for control
        tests with a measurer that reads the truth).
    """

    def __init__(
        self,
        cfg: MachineConfig,
        sim_cfg: Any,
        *,
        seed: int = 0,
        plc_transport: str = "direct",
        measurer_factory: Callable[[tuple[int, int]], Any] | None = None,
        log: Any = "config",
        render_images: bool = True,
    ) -> None:
        import can

        from config.machine import registers_path, rig_path
        from config.rig import load_rig
        from controller.fieldbus.plc_client import PlcClient
        from controller.fieldbus.plc_protocol import Backoff
        from controller.quality.log import is_database_url, open_quality_log
        from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
        from plant_sim.interfaces.register_bus import MachineRegisterBus
        from plant_sim.machine.machine import Machine
        from plant_sim.run.driver import PlantDriver
        from protocol.registers import RegisterMap

        if plc_transport not in ("direct", "tcp"):
            raise ValueError(f"plc_transport must be direct or tcp, got {plc_transport!r}")
        self.cfg = cfg
        self.sim_cfg = sim_cfg
        self.machine = Machine(sim_cfg, seed=seed, render_images=render_images)
        self.regmap = RegisterMap.load(registers_path(cfg))
        self.plc_transport = plc_transport
        self.server: Any = None
        self.direct_bus: Any = None
        backoff = Backoff(cfg.plc.backoff_initial_s, cfg.plc.backoff_max_s)
        if plc_transport == "direct":
            self.direct_bus = MachineRegisterBus(self.machine, self.regmap)
            self.plc = PlcClient(self.direct_bus, self.regmap, backoff=backoff, clock=self.clock)
        else:
            from plant_sim.interfaces.plc_server import PlcServer

            self.server = PlcServer(self.machine, register_map=self.regmap, host="127.0.0.1",
                                    port=0, queue_writes=True)
            self.plc = None  # type: ignore[assignment]
            self._backoff = backoff
        self.rig = load_rig(rig_path(cfg))
        if measurer_factory is None:  # the vision with the PLC's R and Z, self-calibrating
            from controller.service.measurement import VisionMeasurers

            measurer_factory = VisionMeasurers(self.rig, defects=cfg.quality.defects)
        self._measurer_factory = measurer_factory
        opened_log = log == "config"
        if opened_log:  # before the buses: an unusable log path leaves nothing open
            path = Path(cfg.log.path)
            if not is_database_url(path):  # a PostgreSQL URL is no folder to make
                path.parent.mkdir(parents=True, exist_ok=True)
            log = open_quality_log(path, machine_id=cfg.log.machine_id or None)
        self.log = log
        self.service: Service | None = None
        buses: list[Any] = []
        try:
            self.start_id = log.last_id if log is not None else 0
            channel = f"planer-hil-{os.getpid()}-{next(_channels)}"
            self._channel = channel
            self._opened_log = opened_log
            self.svc_bus = can.Bus(interface="virtual", channel=channel)
            buses.append(self.svc_bus)
            amp_bus = can.Bus(interface="virtual", channel=channel)
            buses.append(amp_bus)
            knives = sim_cfg.cutterhead.knives
            self.amp = AmpNode(amp_bus,
                               AmpNodeCore(self.machine, knives=knives, node_id=sim_cfg.can.node_id,
                                           eds=sim_cfg.can.eds, seed=seed),
                               own_bus=True)
            self.piezo = self._piezo_client()
            self._io: Any = None
            self.driver = PlantDriver(self.machine, amp=self.amp, plc=self.server,
                                      plc_switch=self)
            self.start_mm = self.machine.feed_position_mm
            if self.plc is not None:
                self._make_service()
        except BaseException:
            for bus in buses:
                bus.shutdown()
            if opened_log and log is not None:
                log.close()
            raise

    def _piezo_client(self) -> Any:
        """The service's CANopen master of the amplifier on :attr:`svc_bus`."""
        from config.machine import eds_path
        from controller.fieldbus.piezo_client import PiezoClient

        cfg = self.cfg
        return PiezoClient(
            self.svc_bus, knives=self.sim_cfg.cutterhead.knives, node_id=cfg.can.node_id,
            eds=eds_path(cfg), command_period_s=cfg.can.command_period_s,
            offsets_period_s=cfg.can.offsets_period_s, stroke_um=cfg.stroke_um,
        )

    def clock(self) -> float:
        """Machine time, s (the service's injected clock)."""
        return float(self.machine.t_s)

    def _make_service(self) -> None:
        self.service = Service(
            self.cfg, plc=self.plc, piezo=self.piezo, rig=self.rig, log=self.log,
            clock=self.clock, threaded=False, measurer_factory=self._measurer_factory,
            pairs_per_s=self.sim_cfg.camera.pairs_per_s,
        )
        self.service.keep_results = True
        if self.log is not None:
            self.log.set_quality_class(self.service.quality_class)

    async def start(self) -> None:
        """Start the Modbus server (``tcp``) and connect the service's client to it."""
        from controller.fieldbus.plc_client import PlcClient
        from plant_sim.interfaces.thread import InterfaceLoop

        if self.server is not None and self.service is None:
            self._io = InterfaceLoop("hil-plc")
            host, port = await self._io.run_async(self.server.start())
            self._addr = (host, port)
            self.plc = PlcClient.tcp(
                host, port, unit_id=self.regmap.unit_id, timeout_s=self.cfg.plc.timeout_s,
                regmap=self.regmap, backoff=self._backoff, clock=self.clock,
            )
            self._make_service()

    @property
    def travelled_mm(self) -> float:
        """Table travel since the plant was made, mm."""
        return self.machine.feed_position_mm - self.start_mm

    def set_up(self, up: bool) -> None:
        """The driver's switch of the PLC's Modbus side (server or direct bus; synchronous)."""
        if self.server is None:
            self.direct_bus.down = not up
        elif self._io is not None:
            self._io.run(self.server.start() if up else self.server.stop())

    async def plc_down(self, duration_s: float) -> None:
        """Kill the PLC's Modbus side for ``duration_s`` machine seconds (server stopped)."""
        self.driver.inject("modbus_restart", duration_s=float(duration_s))

    def can_fault(self, kind: str, duration_s: float, **params: float) -> None:
        """``can_silence`` (the amplifier sends nothing) or ``can_drop`` for ``duration_s``."""
        from plant_sim.interfaces.amp_node import CAN_FAULTS

        if kind not in CAN_FAULTS:
            raise ValueError(f"kind must be can_silence or can_drop, got {kind!r}")
        self.driver.inject(kind, duration_s=duration_s, **params)  # the registry checks them

    async def stop_service(self, *, kill: bool = False) -> None:
        """Stop the service, the plant running on (:meth:`idle` steps it meanwhile).

        ``kill=False``: a clean stop (:meth:`Service.close`: amplifier disabled with zero
        offsets, the learnt state written, records and buses closed). ``kill=True``: what a
        ``kill -9`` leaves -- the service's code stops mid-run and only what the operating
        system does happens: its CAN and PLC connections and the log's file close, nothing
        is written or sent on the way out (the amplifier times out by itself).
        """
        svc = self.service
        assert svc is not None, "no service running"
        if kill:
            self.svc_bus.shutdown()
            if self.plc is not None:
                self.plc.close()
            if self.log is not None and self._opened_log:
                self.log.close()
        else:
            svc.close()
        self.service = None

    async def start_service(self) -> Service:
        """A new service on the same plant, quality log and bus channels (a restart)."""
        import can

        from controller.fieldbus.plc_client import PlcClient
        from controller.fieldbus.plc_protocol import Backoff
        from controller.quality.log import open_quality_log
        from plant_sim.interfaces.register_bus import MachineRegisterBus

        assert self.service is None, "stop the running service first"
        cfg = self.cfg
        if self._opened_log:
            self.log = open_quality_log(Path(cfg.log.path), machine_id=cfg.log.machine_id or None)
        self.svc_bus = can.Bus(interface="virtual", channel=self._channel)
        self.piezo = self._piezo_client()
        backoff = Backoff(cfg.plc.backoff_initial_s, cfg.plc.backoff_max_s)
        if self.plc_transport == "direct":
            self.direct_bus = MachineRegisterBus(self.machine, self.regmap)
            self.plc = PlcClient(self.direct_bus, self.regmap, backoff=backoff, clock=self.clock)
            self._make_service()
        else:
            host, port = self._addr
            self.plc = PlcClient.tcp(
                host, port, unit_id=self.regmap.unit_id, timeout_s=cfg.plc.timeout_s,
                regmap=self.regmap, backoff=backoff, clock=self.clock,
            )
            self._make_service()
        assert self.service is not None
        return self.service

    def idle(self) -> list[Any]:
        """One control cycle of the plant alone (no service: stopped or not yet restarted).

        The pairs captured meanwhile are returned, not measured: no service reads them.
        """
        return self.driver.step(self.cfg.safety.cycle_s)

    async def step(self) -> list[FrameResult]:
        """One control cycle; returns the results of the pairs captured in it."""
        assert self.service is not None, "call start() first"
        frames = self.driver.step(self.cfg.safety.cycle_s)
        t = self.clock()
        await self.service.tick(t)
        out = []
        for fr in frames:
            out.append(await self.service.handle_frame(fr, now_s=t))
        return out

    async def close(self) -> None:
        """Close the service (buses, log), the amplifier node and the server."""
        if self.service is not None:
            self.service.close()
        else:
            self.svc_bus.shutdown()
            if self.log is not None:
                self.log.close()
        self.amp.close()
        if self._io is not None:
            try:
                await self._io.run_async(self.server.stop())
            finally:
                self._io.close()


class InProcessHil:
    """A scenario on :class:`InProcessPlant`: simulator and service in one process.

    Parameters
    ----------
    scenario : Scenario
        What to run.
    log_path : Path
        Quality log (created or continued).
    plc_transport : {"direct", "tcp"}
        How the service reaches the PLC (see :class:`InProcessPlant`).
    progress : callable, optional
        Receives progress lines.
    progress_every : int
        Measurements between progress lines.
    pace : float or None
        Simulated seconds per wall second (1: real time, for pages and OPC UA clients to
        follow); ``None``: as fast as the CPU allows (:class:`~planer.hil.pacing.Pacer`).
    realtime : bool
        Raise the run's thread (and the light threads sharing its interpreter lock) as the
        service's bus thread is raised, for a paced run (``pace``; an unpaced run is a batch
        computation and stays at normal priority); the summary's ``priority`` says what was
        granted and whether the guard dropped it (see the module's description).
    """

    def __init__(
        self,
        scenario: Scenario,
        *,
        log_path: Path,
        plc_transport: str = "direct",
        progress: Progress | None = None,
        progress_every: int = 10,
        pace: float | None = None,
        realtime: bool = False,
    ) -> None:
        self.pace = Pacer(pace).factor  # checked here; each run paces itself afresh
        self.realtime = bool(realtime)
        self.priority: dict[str, Any] = {"loop": "normal (not asked)", "with": [],
                                         "demoted": False}
        """What the run's thread was granted (``loop``), the threads raised with it
        (``with``), and whether the ``RLIMIT_RTTIME`` guard dropped them (``demoted``)."""
        self.scenario = scenario
        self.log_path = Path(log_path)
        self.plc_transport = plc_transport
        self.progress = progress
        self.progress_every = progress_every
        self.cfg = machine_config_for(scenario, log_path=self.log_path)
        self.sim_cfg = sim_config_for(scenario)

    def _say(self, line: str) -> None:
        if self.progress is not None:
            self.progress(line)

    @contextlib.contextmanager
    def _raised(self) -> Any:
        """The run's thread raised for the block (with ``realtime``), said once."""
        if not self.realtime:
            yield
            return
        if self.pace is None:  # a batch computation, not a loop that keeps time: it never
            # blocks, and the guard would only drop it after 0.5 s of a core
            self.priority = {"loop": "normal (not paced: the run goes as fast as it can)",
                             "with": [], "demoted": False}
            yield
            return
        from core.realtime import BUS_RT_PRIORITY, realtime_thread

        # the threads alive now share the interpreter lock and are light: the simulated PLC's
        # Modbus server (tcp), the servers' feed and reports; a descheduled holder of the lock
        # would keep the raised thread waiting (priority inversion)
        others = [t for t in threading.enumerate() if t is not threading.current_thread()]
        with realtime_thread(rt_priority=BUS_RT_PRIORITY, others=others) as granted:
            raised = granted.startswith(("SCHED_FIFO", "nice"))
            names = [t.name for t in others] if raised else []
            self.priority = {"loop": granted, "with": names, "demoted": False}
            self._say(f"priority: run loop (plant, PLC, measurement, setpoints) {granted}"
                      + (f" with {', '.join(names)}" if names else "")
                      + ("" if raised else "; not permitted to raise it: on a busy host the "
                         "pairs wait for a core"))
            yield

    def _priority_now(self) -> dict[str, Any]:
        """:attr:`priority`, ``demoted`` as of now (the guard empties the raised threads)."""
        from core.realtime import realtime_threads

        if self.priority["loop"].startswith("SCHED_FIFO"):
            demoted = threading.get_native_id() not in realtime_threads()
            if demoted and not self.priority["demoted"]:
                self._say("priority: the run loop ran 0.5 s of CPU without blocking and was "
                          "dropped to normal scheduling (RLIMIT_RTTIME)")
            self.priority["demoted"] = demoted
        return dict(self.priority)

    async def run(self) -> dict[str, Any]:
        """Run the scenario; return the summary (see :func:`summarize`)."""
        sc, cfg = self.scenario, self.cfg
        plant = InProcessPlant(cfg, self.sim_cfg, seed=sc.seed, plc_transport=self.plc_transport)
        try:
            await plant.start()
        except BaseException:  # e.g. Modbus cannot listen: close the buses and the log
            await plant.close()
            raise
        with self._raised():
            return await self._run_on(plant)

    async def _run_on(self, plant: InProcessPlant) -> dict[str, Any]:
        """The scenario on the started ``plant`` (closed at the end); the summary."""
        sc, cfg = self.scenario, self.cfg
        service = self.service = plant.service  # others may follow it (OPC UA)
        assert service is not None
        service.on_event = lambda e: self._say(f"t={e.t_s:7.3f} s  {e.text}")
        pending = sorted(sc.faults, key=lambda f: f.at_s)
        pacer = Pacer(self.pace)
        n_last = n_seen = 0
        travel = BoardTravel(self.sim_cfg.encoder.counts_per_mm)
        wall0 = time.perf_counter()
        self._say(
            f"hil (in-process, simulated time, PLC {self.plc_transport}, CAN virtual): "
            f"scenario {sc.name}, {sc.distance_m:g} m of board, target pitch "
            f"{cfg.quality.target_pitch_mm} mm"
        )
        self._say(PROGRESS_LEGEND)
        try:
            while plant.travelled_mm < sc.distance_m * 1000.0 and plant.clock() < sc.max_sim_s:
                t = plant.clock()
                while pending and pending[0].at_s <= t + 1e-9:
                    f = pending.pop(0)
                    if f.kind.interface:  # the driver plays it (registry: config.faults)
                        what = "Modbus server down" if f.kind == "modbus_restart" else f.kind
                        self._say(f"t={t:7.3f} s  fault: {what} for {f.duration_s:g} s")
                        plant.driver.inject(f.kind.value, **f.params)
                    # machine faults are in the simulator's [faults] table already
                await plant.step()
                await pacer.wait(plant.clock())  # a real suspension: Ctrl-C lands here
                raise_if_cancel_lost()  # or was lost on its way (in a wait_for): end all the same
                n = len(service.results)
                for r in service.results[n_seen:]:
                    travel.add(r)
                n_seen = n
                if n >= n_last + self.progress_every:
                    n_last = n
                    self._say(_progress_line(service.results[-1], travel))
            wall = time.perf_counter() - wall0
        finally:
            await plant.close()
        snap = plant.plc.last
        summary = _service_summary(
            service,
            cfg,
            sc.faults,
            counts_per_mm=snap.counts_per_mm if snap else self.sim_cfg.encoder.counts_per_mm,
            log_path=self.log_path,
            start_id=plant.start_id,
            final_cv_max=sc.final_cv_max,
            extra={
                "mode": "in-process",
                "scenario": sc.name,
                "plc_transport": self.plc_transport,
                "sim_time_s": round(plant.clock(), 3),
                "wall_time_s": round(wall, 3),
                "board_travel_m": round(plant.travelled_mm / 1000, 3),
                "pace": pacer.factor,
                "pace_behind_s": round(pacer.behind_s, 3),
                "priority": self._priority_now(),
            },
        )
        note_run_end(summary, distance_m=sc.distance_m, travelled_m=plant.travelled_mm / 1000,
                     max_sim_s=sc.max_sim_s, time_limit_hit=plant.clock() >= sc.max_sim_s,
                     say=self._say)
        return summary
