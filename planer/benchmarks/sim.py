"""``planer bench`` part ``sim``: real-time factor of the machine model (simulated s per wall s).

Two runs of the shipped ``config/sim.toml`` with the service's traffic played in-process (a
PIEZO_COMMAND, the offset table and a heartbeat every 10 ms, as the controller sends them):
the model alone (``render_images=False``: frames carry counts and truth, no images) and with
image rendering at the configured 10 pairs/s. Timing starts once a board is under the camera,
so every pair is assembled (and rendered); set-up (the renderer's maps) is reported apart.
Targets (issue 3): >= 20 without images, >= 1 with.

``modbus_latency``: a real ``planer sim`` process (images rendered by its worker, time scale 1)
answering reads of the whole register map over Modbus TCP on 127.0.0.1, timed from request
to response (target issue 14: p99 <= 5 ms whatever the renderer does), and the time scale the
simulator achieved.
"""

from __future__ import annotations

import time
from typing import Any

TARGET_MODEL = 20.0
TARGET_IMAGES = 1.0
TARGET_MODBUS_P99_MS = 5.0


def _measure(render: bool, sim_s: float) -> dict[str, Any]:
    from config.sim import load_sim
    from plant_sim.machine import Machine

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
    t0 = time.perf_counter()
    pairs = play(sim_s)
    wall = time.perf_counter() - t0
    return {
        "sim_s": sim_s,
        "wall_s": round(wall, 4),
        "real_time_factor": round(sim_s / wall, 2),
        "pairs": pairs,
        "setup_s": round(setup_s, 3),
    }


def modbus_latency(*, duration_s: float = 15.0, reads_per_s: float = 100.0,
                   time_scale: float = 1.0, images: bool = True) -> dict[str, Any]:
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

    Returns
    -------
    dict
        ``reads``, ``p50_ms``, ``p99_ms``, ``max_ms`` (request to response), ``errors``
        (exception responses, must be 0), ``achieved_time_scale`` (simulated s per wall s,
        from the simulator's ``stopped`` line), ``slow_host_line`` (its slow-down notice, if
        any).
    """
    import os
    import re
    import socket
    import struct
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    import numpy as np

    from plant_sim.runner import parse_banner
    from protocol.registers import RegisterMap

    first, count = RegisterMap.load().span()
    root = Path(__file__).resolve().parents[2]
    with tempfile.TemporaryDirectory(prefix="planer-bench-sim-") as tmp:
        argv = [sys.executable, "-m", "planer.cli", "sim", "--port", "0", "--spool",
                str(Path(tmp) / "spool"), "--time-scale", str(time_scale), "--progress", "1000"]
        if not images:
            argv.append("--no-images")
        env = {**os.environ, "PYTHONPATH": str(root)}
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=env, cwd=tmp)
        try:
            lines = []
            assert proc.stdout is not None
            for line in proc.stdout:
                lines.append(line.strip())
                if line.strip() == "ready":
                    break
            host, port = parse_banner(lines)["modbus"].rsplit(":", 1)
            lat: list[float] = []
            errors = 0
            with socket.create_connection((host, int(port)), timeout=5.0) as sock:
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
            proc.terminate()
            out, _ = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    ms = np.asarray(lat) * 1e3
    stopped = re.search(r"real-time factor ([0-9.]+)", out)
    slow = [ln for ln in out.splitlines() if ln.startswith("slow host")]
    return {
        "reads": int(ms.size),
        "p50_ms": round(float(np.percentile(ms, 50)), 3),
        "p99_ms": round(float(np.percentile(ms, 99)), 3),
        "max_ms": round(float(ms.max()), 3),
        "errors": int(errors),
        "achieved_time_scale": float(stopped.group(1)) if stopped else None,
        "slow_host_line": slow[0] if slow else None,
        "target_p99_ms": TARGET_MODBUS_P99_MS,
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
        ``pairs``, ``setup_s``), ``modbus_latency`` (:func:`modbus_latency`), ``pairs_per_s``
        of the camera and the ``targets``.
    """
    from config.sim import load_sim

    model = _measure(False, 2.0 if quick else 10.0)
    images = _measure(True, 1.0 if quick else 4.0)
    latency = modbus_latency(duration_s=3.0 if quick else 15.0)
    return {
        "model_only": model,
        "with_images": images,
        "modbus_latency": latency,
        "pairs_per_s": load_sim().camera.pairs_per_s,
        "targets": {"model_only": TARGET_MODEL, "with_images": TARGET_IMAGES},
        "meets_targets": bool(
            model["real_time_factor"] >= TARGET_MODEL
            and images["real_time_factor"] >= TARGET_IMAGES
        ),
    }
