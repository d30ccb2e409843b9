"""``planer bench`` part ``sim``: real-time factor of the machine model (simulated s per wall s).

Two runs of the shipped ``config/sim.toml`` with the service's traffic played in-process (a
the command, the offset table and a heartbeat every 10 ms, as the controller sends them):
the model alone (``render_images=False``: frames carry counts and truth, no images) and with
image rendering at the configured 10 pairs/s. Timing starts once a board is under the camera,
so every pair is assembled (and rendered); set-up (the renderer's maps) is reported apart.
Each is timed over three consecutive windows of ``sim_s`` and the median window counts (a
shared host's other jobs come and go). Targets: >= 100 without images, >= 10 with;
the earlier minimums (20 and 1) are reported beside them.

Floors, measured in the same run so that a reader can judge the figures on whatever host ran
them (these shared hosts vary about 3x from day to day): ``python_call_ns``, one Python method
call doing a ``math.exp`` (the model is a few dozen such calls per PLC cycle), and
``remap_pair_ms``, one ``cv2.remap`` of both full images with float maps (the vision's floor).
The ratios ``model_only.calls_per_cycle`` (CPU time per PLC cycle in such calls) and
``with_images.remaps_per_pair`` (CPU time per simulated pair in such remaps) move with the
code, hardly with the host; so does ``cpu_real_time_factor`` (simulated seconds per second of
this process's CPU time), while ``real_time_factor`` is what a run gets on the host as it is.

``modbus_latency``: a real ``planer sim`` process (images rendered by its worker, time scale 1)
answering reads of the whole register map over Modbus TCP on 127.0.0.1, timed from request
to response (target: p99 <= 5 ms whatever the renderer does), and the time scale the
simulator achieved. ``echo_latency``: the same reads against a bare server that answers every
request with a fixed reply (the host's scheduling floor; same priority options). Both can time
from a client at real-time priority (``client_realtime``), so that the number is the server's
and not the measuring client's own wait for a core.
"""

from __future__ import annotations

import time
from typing import Any

TARGET_MODEL = 100.0
TARGET_IMAGES = 10.0
MINIMUM_MODEL = 20.0
MINIMUM_IMAGES = 1.0
TARGET_MODBUS_P99_MS = 5.0
WINDOWS = 3


def _measure(render: bool, sim_s: float, *, windows: int = WINDOWS) -> dict[str, Any]:
    """Real-time factor of the machine model, the median of ``windows`` windows of ``sim_s``.

    Returns
    -------
    dict
        ``sim_s``, ``wall_s`` and ``pairs`` of the median window, ``real_time_factor``,
        ``window_factors`` (every window's), ``cpu_real_time_factor`` (simulated s per s of
        this process's CPU time, median window: what the code costs, whatever else the host
        runs), ``cycle_us`` and ``cpu_cycle_us`` (wall and CPU time per PLC cycle), with
        images ``ms_per_pair`` and ``cpu_ms_per_pair`` (per simulated pair), ``setup_s``.
    """
    from config.sim import load_sim
    from plant_sim.machine.machine import Machine

    cfg = load_sim()
    t0 = time.perf_counter()
    m = Machine(cfg, seed=1, render_images=render)
    setup_s = time.perf_counter() - t0
    offsets = [float(v) for v in m.standout_um()]
    step = 0.01

    def play(duration_s: float) -> int:
        frames = 0
        for i in range(int(round(duration_s / step))):
            m.piezo_command(enable=True, alive_counter=i % 256)
            m.set_piezo_offsets(offsets)
            m.set_service_heartbeat(i % 65536)
            m.register_values()
            frames += len(m.advance(step))
        return frames

    play(0.6)  # the first board reaches the camera
    runs = []
    for _ in range(max(1, int(windows))):
        t0, c0 = time.perf_counter(), time.process_time()
        pairs = play(sim_s)
        runs.append((time.perf_counter() - t0, pairs, time.process_time() - c0))
    wall, pairs, _ = sorted(runs)[len(runs) // 2]
    cpu = sorted(c for _, _, c in runs)[len(runs) // 2]
    out: dict[str, Any] = {
        "sim_s": sim_s,
        "wall_s": round(wall, 4),
        "real_time_factor": round(sim_s / wall, 2),
        "window_factors": [round(sim_s / w, 2) for w, _, _ in runs],
        "cpu_real_time_factor": round(sim_s / cpu, 2) if cpu > 0 else None,
        "pairs": pairs,
        "cycle_us": round(wall / (sim_s / cfg.plc.cycle_s) * 1e6, 2),
        "cpu_cycle_us": round(cpu / (sim_s / cfg.plc.cycle_s) * 1e6, 2),
        "setup_s": round(setup_s, 3),
    }
    if render and pairs:
        out["ms_per_pair"] = round(wall / pairs * 1e3, 3)
        out["cpu_ms_per_pair"] = round(cpu / pairs * 1e3, 3)
    return out


def floors(*, repeat: int = 5) -> dict[str, float]:
    """Two floors of this host, measured now (best of ``repeat``).

    Returns
    -------
    dict
        ``python_call_ns``: one Python method call computing a ``math.exp`` (ns);
        ``remap_pair_ms``: one ``cv2.remap`` of both full images of the shipped camera with
        float maps (ms).
    """
    import math
    import timeit

    import cv2
    import numpy as np

    from config.sim import load_sim

    class _Part:
        def __init__(self) -> None:
            self.x = 0.5

        def step(self, dt: float) -> float:
            self.x += (1.0 - self.x) * (1.0 - math.exp(-dt / 0.1))
            return self.x

    part = _Part()
    n = 20000
    call_ns = min(timeit.repeat(lambda: part.step(0.002), number=n, repeat=repeat)) / n * 1e9
    o = load_sim().camera.optics
    rng = np.random.default_rng(0)
    a, b = (rng.random((o.height + 14, o.width + 20), dtype=np.float32) for _ in range(2))
    cols, rows = np.meshgrid(np.arange(o.width, dtype=np.float32) + 10.3,
                             np.arange(o.height, dtype=np.float32) + 7.2)

    def remap() -> None:
        cv2.remap(a, cols, rows, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        cv2.remap(b, cols, rows, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    remap_ms = min(timeit.repeat(remap, number=20, repeat=repeat)) / 20 * 1e3
    return {"python_call_ns": round(call_ns, 1), "remap_pair_ms": round(remap_ms, 3)}


_ECHO_SERVER = """
import asyncio, os, sys, struct
if sys.argv[1] == "1":
    from plant_sim.interfaces.thread import raise_priority
    raise_priority()
REPLY_WORDS = int(sys.argv[2])
async def handle(r, w):
    try:
        while True:
            head = await r.readexactly(7)
            body = await r.readexactly(struct.unpack(">H", head[4:6])[0] - 1)
            pdu = bytes([3, 2 * REPLY_WORDS]) + bytes(2 * REPLY_WORDS)
            w.write(head[:4] + struct.pack(">HB", len(pdu) + 1, head[6]) + pdu)
    except (asyncio.IncompleteReadError, ConnectionError):
        w.close()
async def main():
    srv = await asyncio.start_server(handle, "127.0.0.1", 0)
    print("modbus: 127.0.0.1:%d" % srv.sockets[0].getsockname()[1], flush=True)
    print("ready", flush=True)
    await srv.serve_forever()
asyncio.run(main())
"""


def echo_latency(*, duration_s: float = 10.0, reads_per_s: float = 100.0,
                 realtime: bool = False, client_realtime: bool = False) -> dict[str, Any]:
    """Time the same reads against a bare asyncio server (fixed reply): the host's floor.

    Parameters
    ----------
    duration_s, reads_per_s : float
        As :func:`modbus_latency`.
    realtime : bool
        The server asks for the PLC process's priority (``SCHED_FIFO`` 10).
    client_realtime : bool
        The timing client runs at that priority too (in a process of its own).

    Returns
    -------
    dict
        ``reads``, ``p50_ms``, ``p99_ms``, ``max_ms``, ``errors``.
    """
    import subprocess
    import sys

    from protocol.registers import RegisterMap

    _, count = RegisterMap.load().span()
    argv = [sys.executable, "-c", _ECHO_SERVER, "1" if realtime else "0", str(count)]
    return _time_server(argv, duration_s=duration_s, reads_per_s=reads_per_s,
                        client_realtime=client_realtime, popen=subprocess.Popen)[0]


def modbus_latency(*, duration_s: float = 15.0, reads_per_s: float = 100.0,
                   time_scale: float = 1.0, images: bool = True,
                   client_realtime: bool = False,
                   realtime_interfaces: bool = True) -> dict[str, Any]:
    """Time whole-map Modbus reads against a ``planer sim`` process.

    Parameters
    ----------
    duration_s : float
        Wall seconds of reading (after the simulator printed ``ready``).
    reads_per_s : float
        Read rate, Hz (the service reads at its cycle rate).
    time_scale : float
        The simulator's ``--time-scale``.
    images : bool
        Render images (the renderer busy) or ``--no-images``.
    client_realtime : bool
        Time from a client at real-time priority (its own process): the server's latency
        without the client's own wait for a core.
    realtime_interfaces : bool
        ``False`` runs ``planer sim --no-realtime`` (its interfaces at normal priority, render
        workers not lowered: the comparison).

    Returns
    -------
    dict
        ``reads``, ``p50_ms``, ``p99_ms``, ``max_ms`` (request to response), ``errors``
        (exception responses, must be 0), ``achieved_time_scale`` (simulated s per wall s,
        from the simulator's ``stopped`` line), ``slow_host_line`` (its slow-down notice, if
        any), ``priority`` (the simulator's ``priority:`` banner line).
    """
    import os
    import re
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    with tempfile.TemporaryDirectory(prefix="planer-bench-sim-") as tmp:
        argv = [sys.executable, "-m", "planer.cli", "sim", "--port", "0", "--spool",
                str(Path(tmp) / "spool"), "--time-scale", str(time_scale), "--progress", "1000"]
        if not images:
            argv.append("--no-images")
        if not realtime_interfaces:
            argv.append("--no-realtime")
        env = {**os.environ, "PYTHONPATH": str(root)}

        def popen(cmd: list[str], **kw: Any) -> Any:
            return subprocess.Popen(cmd, env=env, cwd=tmp, **kw)

        res, out = _time_server(argv, duration_s=duration_s, reads_per_s=reads_per_s,
                                client_realtime=client_realtime, popen=popen)
    stopped = re.search(r"real-time factor ([0-9.]+)", out)
    slow = [ln for ln in out.splitlines() if ln.startswith("slow host")]
    prio = [ln for ln in out.splitlines() if ln.startswith("priority:")]
    return {
        **res,
        "achieved_time_scale": float(stopped.group(1)) if stopped else None,
        "slow_host_line": slow[0] if slow else None,
        "priority": prio[0] if prio else None,
        "target_p99_ms": TARGET_MODBUS_P99_MS,
    }


def _time_server(argv: list[str], *, duration_s: float, reads_per_s: float,
                 client_realtime: bool, popen: Any) -> tuple[dict[str, Any], str]:
    """Time whole-map reads against the server ``argv`` starts; its statistics and output.

    ``argv`` prints a ``modbus: host:port`` line, then ``ready``; it is stopped afterwards.
    """
    import json
    import subprocess
    import sys

    from plant_sim.run.runner import parse_banner

    proc = popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line.strip())
            if line.strip() == "ready":
                break
        host, port = parse_banner(lines)["modbus"].rsplit(":", 1)
        if client_realtime:  # a client process of its own at the interfaces' priority
            code = ("import json, sys; from plant_sim.interfaces.thread import raise_priority; "
                    "raise_priority(); from planer.benchmarks.sim import _read_loop; "
                    "print(json.dumps(_read_loop(sys.argv[1], int(sys.argv[2]), "
                    "float(sys.argv[3]), float(sys.argv[4]))))")
            client = subprocess.run(
                [sys.executable, "-c", code, host, port, str(duration_s), str(reads_per_s)],
                capture_output=True, text=True, check=True, timeout=duration_s + 120)
            lat, errors = json.loads(client.stdout.strip().splitlines()[-1])
        else:
            lat, errors = _read_loop(host, int(port), duration_s, reads_per_s)
        proc.terminate()
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return _stats(lat, errors), "\n".join(lines) + "\n" + (out or "")


def _read_loop(host: str, port: int, duration_s: float,
               reads_per_s: float) -> tuple[list[float], int]:
    """Whole-map FC3 reads at ``reads_per_s`` for ``duration_s``: latencies (s) and errors."""
    import socket
    import struct

    from protocol.registers import RegisterMap

    first, count = RegisterMap.load().span()
    lat: list[float] = []
    errors = 0
    with socket.create_connection((host, port), timeout=5.0) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        period = 1.0 / reads_per_s
        t_end = time.perf_counter() + duration_s
        tid = 0
        while time.perf_counter() < t_end:
            tid = (tid + 1) & 0xFFFF
            req = struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, first, count)
            t0 = time.perf_counter()
            sock.sendall(req)
            reply = _recv_adu(sock)
            lat.append(time.perf_counter() - t0)
            errors += reply[7] != 3 or struct.unpack(">H", reply[:2])[0] != tid
            time.sleep(max(0.0, period - (time.perf_counter() - t0)))
    return lat, int(errors)


def _stats(lat: list[float], errors: int) -> dict[str, Any]:
    import numpy as np

    ms = np.asarray(lat) * 1e3
    return {
        "reads": int(ms.size),
        "p50_ms": round(float(np.percentile(ms, 50)), 3),
        "p99_ms": round(float(np.percentile(ms, 99)), 3),
        "max_ms": round(float(ms.max()), 3),
        "errors": int(errors),
    }


def _recv_adu(sock: Any) -> bytes:
    """One Modbus TCP response (header and PDU)."""
    import struct

    head = b""
    while len(head) < 7:
        chunk = sock.recv(7 - len(head))
        if not chunk:
            raise ConnectionError("the simulator closed the connection")
        head += chunk
    n = struct.unpack(">H", head[4:6])[0] - 1
    body = b""
    while len(body) < n:
        chunk = sock.recv(n - len(body))
        if not chunk:
            raise ConnectionError("the simulator closed the connection")
        body += chunk
    return head + body


def run(quick: bool) -> dict[str, Any]:
    """Measure the real-time factors.

    Parameters
    ----------
    quick : bool
        Shorter runs (2 s and 1 s simulated instead of 10 s and 4 s).

    Returns
    -------
    dict
        ``model_only`` and ``with_images`` (each ``sim_s``, ``wall_s``, ``real_time_factor``,
        ``window_factors``, ``cpu_real_time_factor``, ``pairs``, ``cycle_us``,
        ``cpu_cycle_us``, ``setup_s``; with images also ``ms_per_pair``, ``cpu_ms_per_pair``;
        each with its ratio to a floor, ``calls_per_cycle`` and ``remaps_per_pair``),
        ``floors`` (:func:`floors`), ``modbus_latency`` (:func:`modbus_latency`),
        ``pairs_per_s`` of the camera, the ``targets``, the earlier ``minimums`` and
        whether they are met.
    """
    from config.sim import load_sim

    base = floors()
    model = _measure(False, 2.0 if quick else 10.0)
    images = _measure(True, 1.0 if quick else 4.0)
    model["calls_per_cycle"] = round(model["cpu_cycle_us"] * 1e3 / base["python_call_ns"], 1)
    if "cpu_ms_per_pair" in images:
        images["remaps_per_pair"] = round(images["cpu_ms_per_pair"] / base["remap_pair_ms"], 2)
    latency = modbus_latency(duration_s=3.0 if quick else 15.0)
    return {
        "model_only": model,
        "with_images": images,
        "floors": base,
        "modbus_latency": latency,
        "pairs_per_s": load_sim().camera.pairs_per_s,
        "targets": {"model_only": TARGET_MODEL, "with_images": TARGET_IMAGES},
        "meets_targets": bool(
            model["real_time_factor"] >= TARGET_MODEL
            and images["real_time_factor"] >= TARGET_IMAGES
        ),
        "minimums": {"model_only": MINIMUM_MODEL, "with_images": MINIMUM_IMAGES},
        "meets_minimums": bool(
            model["real_time_factor"] >= MINIMUM_MODEL
            and images["real_time_factor"] >= MINIMUM_IMAGES
        ),
    }
