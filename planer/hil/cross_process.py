"""Cross-process HIL: ``planer sim`` in a private network namespace and the real-time service.

Order of start (the machine's clock must not run ahead of a service still starting on
a busy host): the service is built first (its imports, quality log, CAN bus; nothing contacted
yet) for a Modbus port chosen here, then ``planer sim`` is started on that port, and the service
runs as soon as the simulator says ``ready``. While it runs, the service's bus thread (the event
loop that runs the PLC and CAN cycles) is at real-time priority where permitted
(:func:`core.realtime.realtime_thread`; its measurement workers and every thread it starts run
at normal priority); what it and the simulator's interfaces got is said once.

The summary maps machine time (the frames' ``frame_t_s``) onto service time: the simulated
clock slows itself when the host cannot keep up, so besides the offset the achieved rate
(``sim_time_factor``: machine seconds per service second) is estimated from the frames.
"""

from __future__ import annotations

import asyncio
import enum
import math
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from config.loading import default_path
from controller.service.frame_result import FrameResult
from core.errors import FieldbusError
from planer.hil.run_end import note_run_end
from planer.hil.scenario import Progress, Scenario, machine_config_for, sim_config_for, sim_document
from planer.hil.summary import PROGRESS_LEGEND, BoardTravel, _progress_line, _service_summary


# ---------------------------------------------------------------------------------- cross-process
def cross_process_possible() -> tuple[bool, str]:
    """Whether the cross-process HIL can run here, and if not, why."""
    from protocol import can_transport

    try:
        import msgpack  # noqa: F401
    except ImportError:
        return False, "python-can's udp_multicast needs the msgpack package, not installed"
    if can_transport.in_private_netns():
        return True, "inside a private network namespace"
    if not can_transport.private_netns_available():
        return False, "unshare -rn (private network namespace) is not permitted here"
    return True, "private network namespace available"


def to_toml(doc: Mapping[str, Any]) -> str:
    """A document of tables, sub-tables and plain values as TOML text (``tomli_w``).

    Paths are written as strings; a value TOML cannot hold (NaN, infinity, ``None``, other
    objects) raises ``ValueError`` naming it.
    """
    import tomli_w

    def plain(v: Any, key: str) -> Any:
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, enum.Enum):
            return plain(v.value, key)
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"cannot write {key} = {v!r} to TOML")
        if isinstance(v, Mapping):
            return {str(k): plain(x, f"{key}.{k}" if key else str(k)) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [plain(x, f"{key}[{i}]") for i, x in enumerate(v)]
        if v is None or not isinstance(v, (bool, int, float, str)):
            raise ValueError(f"cannot write {key} = {v!r} ({type(v).__name__}) to TOML")
        return v

    return tomli_w.dumps(plain(doc, ""))


def _die_with_parent() -> None:  # pragma: no cover - runs in the child
    """Ask Linux to SIGTERM the simulator when ``planer hil`` dies (no orphaned simulators)."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


SIM_LINES_SAID = ("priority:", "slow host")
"""Lines of the simulator (besides faults) passed on to the progress: what its interfaces were
granted, and a clock that slowed itself."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (for the simulator's Modbus server)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def gap_stats_ms(times_s: Sequence[float]) -> dict[str, float | int] | None:
    """Gaps between successive times (s), in ms: ``p50``, ``p99``, ``max``, ``n``.

    ``over_100`` counts the gaps longer than the amplifier's 100 ms setpoint timeout; ``None``
    below two times.
    """
    if len(times_s) < 2:
        return None
    gaps = sorted((b - a) * 1e3 for a, b in zip(times_s, times_s[1:], strict=False))
    n = len(gaps)
    return {"p50": round(gaps[n // 2], 2), "p99": round(gaps[min(n - 1, int(0.99 * n))], 2),
            "max": round(gaps[-1], 2), "over_100": sum(g > 100.0 for g in gaps), "n": n}


def latency_stats_ms(durations_s: Sequence[float]) -> dict[str, float | int] | None:
    """``p50``, ``p99``, ``max`` (ms) and ``n`` of durations in seconds; ``None`` if none."""
    if not durations_s:
        return None
    ms = sorted(d * 1e3 for d in durations_s)
    n = len(ms)
    return {"p50": round(ms[n // 2], 3), "p99": round(ms[min(n - 1, int(0.99 * n))], 3),
            "max": round(ms[-1], 3), "n": n}


def time_factor(results: Sequence[FrameResult]) -> float | None:
    """Machine seconds per service second over the run, from the frames' times.

    The least-squares slope of the frames' machine time (``frame_t_s``) against their arrival
    on the service's clock (``t_s``); ``None`` with fewer than two frames or no spread. 1.0: the
    simulator kept real time; below: its clock slowed itself.
    """
    pts = [(r.t_s, r.frame_t_s) for r in results
           if math.isfinite(r.t_s) and math.isfinite(r.frame_t_s)]
    if len(pts) < 2:
        return None
    n = len(pts)
    mt = sum(p[0] for p in pts) / n
    mf = sum(p[1] for p in pts) / n
    var = sum((p[0] - mt) ** 2 for p in pts)
    if var <= 0:
        return None
    return sum((p[0] - mt) * (p[1] - mf) for p in pts) / var


class _SimProcess:
    """``planer sim`` as a child process: banner parsed, output drained in a thread."""

    def __init__(self, argv: Sequence[str], progress: Progress | None) -> None:
        self.proc = subprocess.Popen(
            list(argv), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
            preexec_fn=_die_with_parent,
        )
        self.progress = progress
        self.lines: list[str] = []
        self.banner: dict[str, str] = {}
        self.said: list[str] = []  # the SIM_LINES_SAID lines, in order
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        from plant_sim.run.runner import parse_banner

        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            self.lines.append(line)
            if line.startswith(SIM_LINES_SAID):
                self.said.append(line)
                if self.progress is not None:
                    self.progress(f"sim: {line}")
            if not self._ready.is_set():
                if line.strip() == "ready":
                    self.banner = parse_banner(self.lines)
                    self._ready.set()
            elif self.progress is not None and "fault" in line:
                self.progress(f"sim: {line}")
        self._ready.set()

    def wait_ready(self, timeout_s: float) -> dict[str, str]:
        if not self._ready.wait(timeout_s) or not self.banner:
            tail = "; ".join(self.lines[-5:])
            raise FieldbusError(f"planer sim did not become ready: {tail or 'no output'}")
        return self.banner

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._thread.join(timeout=5)
        return int(self.proc.returncode or 0)


async def run_cross_process(
    scenario: Scenario,
    *,
    log_path: Path,
    progress: Progress | None = None,
    progress_every: int = 10,
    workdir: Path | None = None,
    on_service: Callable[[Any], None] | None = None,
) -> dict[str, Any]:
    """The simulator as a separate ``planer sim`` process, the service here, in real time.

    Must run where both processes share a loopback-only network (a private namespace; see
    :func:`cross_process_possible`). CAN: ``udp_multicast`` on the namespace's ``lo``; Modbus:
    127.0.0.1 on a free port; frames: a spool directory.

    Parameters
    ----------
    scenario : Scenario
        What to run.
    log_path : Path
        Quality log (created or continued).
    progress : callable, optional
        Receives progress lines.
    progress_every : int
        Measurements between progress lines.
    workdir : Path, optional
        Folder for the simulator's configuration and frame spool, kept afterwards. Default: a
        temporary folder removed when the run ends (also on errors and Ctrl-C), after the
        simulator has stopped.
    """
    if workdir is not None:
        folder = Path(workdir)
        folder.mkdir(parents=True, exist_ok=True)
        return await _run_cross_process(scenario, folder, log_path=Path(log_path),
                                        progress=progress, progress_every=progress_every,
                                        on_service=on_service)
    with tempfile.TemporaryDirectory(prefix="planer-hil-") as tmp:
        return await _run_cross_process(scenario, Path(tmp), log_path=Path(log_path),
                                        progress=progress, progress_every=progress_every,
                                        on_service=on_service)


def _configs(scenario: Scenario, tmp: Path, log_path: Path) -> tuple[Path, Any, Any]:
    """The simulator's config file in ``tmp`` and both configs, built once for the run.

    Returns ``(sim_toml, sim_cfg, cfg)``: the simulator's file (CAN over UDP multicast on the
    namespace's loopback, the spool in ``tmp``), its loaded config, and the service's config
    meeting it (PLC on a free port of 127.0.0.1, the same CAN group, the spool).
    """
    from config.machine import CanConfig

    spool = tmp / "spool"
    group = "239.74.163.2"
    can_port = 43113
    doc = sim_document(scenario)
    doc["can"] = {"interface": "udp_multicast", "channel": group,
                  "options": {"port": can_port}}
    doc["frames"] = {**doc.get("frames", {}), "spool_dir": str(spool)}
    doc.setdefault("run", {})["time_scale"] = scenario.time_scale
    doc["faults"] = {"inject": [f.table() for f in scenario.faults]}
    cam = doc.setdefault("camera", {})
    if not cam.get("rig"):
        cam["rig"] = str(default_path("rig.toml"))
    elif scenario.sim_config is not None and not Path(cam["rig"]).is_absolute():
        cam["rig"] = str(Path(scenario.sim_config).parent / cam["rig"])  # the copy lives in tmp
    sim_toml = tmp / "sim.toml"
    sim_toml.write_text(to_toml(doc))
    sim_cfg = sim_config_for(scenario, machine_faults=False)

    cfg = machine_config_for(scenario, log_path=log_path)
    host = "127.0.0.1"
    port = free_port(host)
    optics = sim_cfg.camera.optics
    cfg = cfg.with_changes(
        plc=replace(cfg.plc, host=host, port=port),
        can=CanConfig(interface="udp_multicast", channel=group,
                      options={"port": can_port},
                      command_period_s=cfg.can.command_period_s,
                      offsets_period_s=cfg.can.offsets_period_s, node_id=cfg.can.node_id,
                      eds=cfg.can.eds),
        frames=replace(cfg.frames, source="spool", spool_dir=spool,
                       pairs_per_s=sim_cfg.camera.pairs_per_s,
                       image_width=optics.width, image_height=optics.height),
    )
    return sim_toml, sim_cfg, cfg


async def _run_cross_process(
    scenario: Scenario,
    tmp: Path,
    *,
    log_path: Path,
    progress: Progress | None,
    progress_every: int,
    on_service: Callable[[Any], None] | None = None,
) -> dict[str, Any]:
    from controller.fieldbus.piezo_client import open_bus
    from controller.runtime import RuntimeOptions, ServiceRuntime

    say = progress or (lambda _line: None)
    sim_toml, sim_cfg, cfg = _configs(scenario, tmp, log_path)
    port = cfg.plc.port
    # the service first (imports, log, CAN bus; nothing contacted yet): the machine's clock
    # starts with the simulator, and the service must be there when it does
    runtime = ServiceRuntime(
        cfg, log_path=log_path, can_bus=open_bus(cfg.can.interface, cfg.can.channel,
                                                 dict(cfg.can.options)),
        options=RuntimeOptions(min_workers=HIL_MEASURE_WORKERS, realtime=True,
                               realtime_others=True),
        say=lambda line: say(f"hil (cross-process): {line}"))
    argv = [sys.executable, "-m", "planer.cli", "sim", "--config", str(sim_toml),
            "--seed", str(scenario.seed), "--port", str(port)]
    sim: _SimProcess | None = None
    try:
        service = await runtime.open()
        if runtime.pool is not None:
            say(f"service: measuring in {runtime.pool.workers} worker process(es)")
        say(f"hil (cross-process): starting {' '.join(argv[2:])}")
        sim = _SimProcess(argv, progress)
        banner = sim.wait_ready(60.0)
        say(f"sim ready: modbus {banner['modbus']}, can {banner.get('can')}, "
            f"frames {banner.get('frames')}")
        start_id = service.log.last_id
        service.keep_results = True
        if on_service is not None:  # e.g. the OPC UA server follows it
            on_service(service)
        runtime.open_source()
        stop = asyncio.Event()
        cpm = sim_cfg.encoder.counts_per_mm
        travel = BoardTravel(cpm)
        state = {"n_last": 0}

        def on_result(r: FrameResult) -> None:
            travel.add(r)
            n = len(service.results)
            if n >= state["n_last"] + progress_every:
                state["n_last"] = n
                say(_progress_line(r, travel))
            if travel.measured_mm >= scenario.distance_m * 1000.0:
                stop.set()

        service.on_result = on_result

        async def time_limit() -> None:
            await asyncio.sleep(scenario.max_sim_s / scenario.time_scale + 10.0)
            state["time_limit_hit"] = 1
            stop.set()

        limiter = asyncio.create_task(time_limit())
        cycles = _timed(service, "can_cycle")  # when the CAN cycle ran (the amplifier's view)
        reads = _timed_reads(service.plc.bus)  # request to answer of each register read
        # the measurement runs in worker processes: every other thread here is light I/O that
        # shares the interpreter lock with the bus thread (spool reader, log writer), raised
        # with it so that none is descheduled by a hog while holding it
        t_start = service.clock()
        service.on_event = lambda e: say(f"t={e.t_s - t_start:7.3f} s  {e.text}")
        say(PROGRESS_LEGEND)
        wall0 = time.perf_counter()
        running = asyncio.create_task(runtime.run(stop=stop))
        await asyncio.sleep(0)  # the run raised the bus thread: say what it got
        _say_priority(say, runtime)
        try:
            await running
        finally:
            limiter.cancel()
        wall = time.perf_counter() - wall0
    finally:
        try:
            runtime.close()
        finally:
            code = sim.stop() if sim is not None else 0
    granted, others = runtime.granted, runtime.others
    factor = time_factor(service.results)
    summary = _service_summary(
        service,
        cfg,
        scenario.faults,
        counts_per_mm=cpm,
        log_path=log_path,
        start_id=start_id,
        time_offset_s=_estimate_offset(service.results),
        t_start_s=t_start,
        final_cv_max=scenario.final_cv_max,
        extra={
            "mode": "cross-process",
            "scenario": scenario.name,
            "wall_time_s": round(wall, 3),
            "sim_banner": banner,
            "sim_time_factor": None if factor is None else round(factor, 3),
            "priority": {"service_bus": granted,
                         "service_threads": [t.name for t in others],
                         "sim": next((x.partition(": ")[2] for x in sim.said
                                      if x.startswith("priority:")), None)},
            "sim_said": list(sim.said),
            "can_cycle_gaps_ms": gap_stats_ms(cycles),
            "sim_command_gaps_ms": _command_gaps(sim.lines),
            "plc_read_ms": latency_stats_ms(reads),
        },
    )
    summary["sim_exit_code"] = code
    note_run_end(summary, distance_m=scenario.distance_m, travelled_m=travel.measured_mm / 1000,
                 max_sim_s=scenario.max_sim_s, time_limit_hit=bool(state.get("time_limit_hit")),
                 say=progress)
    return summary


HIL_MEASURE_WORKERS = 1
"""Worker processes measuring for the service in the cross-process HIL (at least; more if
``[service] workers`` asks). In the service's own process the measurement thread holds the
interpreter lock most of the time; descheduled by a CPU hog while holding it, it kept the
real-time bus thread from sending the amplifier's command for up to 90-210 ms (measured under six
hogs: over the amplifier's 100 ms setpoint timeout). In a process of its own it cannot."""


def _say_priority(say: Progress, runtime: Any) -> None:
    granted, others = runtime.granted, runtime.others
    raised = granted.startswith(("SCHED_FIFO", "nice"))
    say(f"service: bus thread {granted}" + (
        f" (with {', '.join(t.name for t in others)})" if raised and others else "")
        + ("" if raised else "; not permitted to raise it: on a busy host its cycles may run late"))


def _command_gaps(lines: Sequence[str]) -> dict[str, float | int] | None:
    """The service's commands as the simulator received them, from its progress lines.

    ``max``: the longest wall gap between two commands (RPDO3), ms; ``over_100``: the
    progress lines (one per machine second) with a gap over 100 ms.
    """
    gaps = []
    for line in lines:
        _, sep, rest = line.partition("command gap max=")
        if sep:
            try:
                gaps.append(float(rest.split()[0]))
            except (ValueError, IndexError):
                continue
    if not gaps:
        return None
    return {"max": max(gaps), "over_100": sum(g > 100.0 for g in gaps), "lines": len(gaps)}


def _timed(obj: Any, name: str) -> list[float]:
    """Wrap method ``name`` of ``obj`` (instance attribute) to note each call's clock time."""
    times: list[float] = []
    orig = getattr(obj, name)

    def timed(*args: Any, **kwargs: Any) -> Any:
        times.append(time.monotonic())
        return orig(*args, **kwargs)

    setattr(obj, name, timed)
    return times


def _timed_reads(bus: Any) -> list[float]:
    """Note how long each answered read of ``bus`` took, s (wraps its ``read`` coroutine).

    One Modbus request and its answer, without the client's queueing.
    """
    took: list[float] = []
    orig = bus.read

    async def read(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        words = await orig(*args, **kwargs)
        took.append(time.perf_counter() - t0)  # answered reads only (errors raise)
        return words

    bus.read = read
    return took


def _estimate_offset(results: Sequence[FrameResult]) -> float:
    """Service time minus machine time (lowest arrival delay of the frames)."""
    offs = [r.t_s - r.frame_t_s for r in results]
    return min(offs) if offs else 0.0
