"""Cross-process HIL: ``planer sim`` in a private network namespace and the real-time service."""

from __future__ import annotations

import asyncio
import enum
import math
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
from controller.service import FrameResult
from core.errors import FieldbusError
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
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        from plant_sim.runner import parse_banner

        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            self.lines.append(line)
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


async def _run_cross_process(
    scenario: Scenario,
    tmp: Path,
    *,
    log_path: Path,
    progress: Progress | None,
    progress_every: int,
    on_service: Callable[[Any], None] | None = None,
) -> dict[str, Any]:
    from config.machine import CanConfig
    from controller.frame_source import open_frame_source
    from controller.piezo_client import open_bus
    from controller.service import open_service

    say = progress or (lambda _line: None)
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
    argv = [sys.executable, "-m", "planer.cli", "sim", "--config", str(sim_toml),
            "--seed", str(scenario.seed), "--port", "0"]
    say(f"hil (cross-process): starting {' '.join(argv[2:])}")
    sim = _SimProcess(argv, progress)
    service = None
    try:
        banner = sim.wait_ready(60.0)
        host, _, port = banner["modbus"].rpartition(":")
        say(f"sim ready: modbus {banner['modbus']}, can {banner.get('can')}, "
            f"frames {banner.get('frames')}")
        optics = sim_cfg.camera.optics
        cfg = cfg.with_changes(
            plc=replace(cfg.plc, host=host, port=int(port)),
            can=CanConfig(interface="udp_multicast", channel=group,
                          options={"port": can_port},
                          command_period_s=cfg.can.command_period_s,
                          offsets_period_s=cfg.can.offsets_period_s, dbc=cfg.can.dbc),
            frames=replace(cfg.frames, source="spool", spool_dir=spool,
                           pairs_per_s=sim_cfg.camera.pairs_per_s,
                           image_width=optics.width, image_height=optics.height),
        )
        # the bus is opened here so that it is shut down if the service cannot start (log)
        bus = open_bus(cfg.can.interface, cfg.can.channel, dict(cfg.can.options))
        try:
            service = open_service(cfg, threaded=True, log_path=log_path, can_bus=bus)
        except BaseException:
            bus.shutdown()
            raise
        start_id = service.log.last_id
        service.keep_results = True
        if on_service is not None:  # e.g. the OPC UA server follows it
            on_service(service)
        t_start = service.clock()
        service.on_event = lambda e: say(f"t={e.t_s - t_start:7.3f} s  {e.text}")
        say(PROGRESS_LEGEND)
        source = open_frame_source(cfg.frames)
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
            stop.set()

        limiter = asyncio.create_task(time_limit())
        wall0 = time.perf_counter()
        try:
            await service.run(source, stop=stop)
        finally:
            limiter.cancel()
        wall = time.perf_counter() - wall0
    finally:
        if service is not None:
            service.close()
        code = sim.stop()
    summary = _service_summary(
        service,
        cfg,
        scenario.faults,
        counts_per_mm=cpm,
        log_path=log_path,
        start_id=start_id,
        time_offset_s=_estimate_offset(service.results),
        t_start_s=t_start,
        extra={
            "mode": "cross-process",
            "scenario": scenario.name,
            "wall_time_s": round(wall, 3),
            "sim_banner": banner,
        },
    )
    summary["sim_exit_code"] = code
    return summary


def _estimate_offset(results: Sequence[FrameResult]) -> float:
    """Service time minus machine time (lowest arrival delay of the frames)."""
    offs = [r.t_s - r.frame_t_s for r in results]
    return min(offs) if offs else 0.0
