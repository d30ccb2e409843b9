"""``planer serve`` says what priority it got: its loop raised, its pages' process lowered.

The real ``planer serve`` with ``--http``: no PLC answers and the CAN bus is python-can's
``virtual`` one, so it waits in the safe state; its ``priority:`` line is read, then it is
stopped. The servers' process is looked at from outside (``/proc``) and must run below the loop.
"""

from __future__ import annotations

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the web extra (uvicorn) is not installed")

ROOT = Path(__file__).resolve().parents[3]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _children_nice(pid: int) -> list[int]:
    """Nice values of the processes whose parent is ``pid`` (``/proc``)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            if int(fields[1]) == pid:
                out.append(int(fields[16]))  # field 19 of stat: nice
    return out


def test_serve_says_its_loop_is_raised_and_its_pages_run_below_it(tmp_path):
    (tmp_path / "machine.toml").write_text(
        f'[plc]\nport = {_free_port()}\ntimeout_s = 0.05\n'
        '[can]\ninterface = "virtual"\nchannel = "serve-priority-test"\n'
        f'[frames]\nspool_dir = "{tmp_path / "spool"}"\n'
        f'[log]\npath = "{tmp_path / "quality.sqlite"}"\n'
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for key in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "INVOCATION_ID",
                "JOURNAL_STREAM"):
        env.pop(key, None)
    p = subprocess.Popen(
        [sys.executable, "-m", "planer.cli", "serve", "--config", str(tmp_path / "machine.toml"),
         "--http", f"127.0.0.1:{_free_port()}"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in p.stdout], daemon=True).start()
    said: list[str] = []
    try:
        end = time.monotonic() + 180.0  # a backstop for a broken run only
        while "ready" not in said:
            try:
                said.append(lines.get(timeout=0.5).rstrip("\n"))
            except queue.Empty:
                assert p.poll() is None and time.monotonic() < end, said
        servers_nice = _children_nice(p.pid)
        own_nice = os.getpriority(os.PRIO_PROCESS, p.pid)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=120)
    finally:
        p.kill()
    assert p.returncode == 0, err
    line = next(ln for ln in said if ln.startswith("priority: "))
    m = re.match(r"priority: service bus (SCHED_FIFO 9|nice -10|normal \(.+?\)); measurement "
                 r"and records asked for nice -10; pages and OPC UA \(their own process\) at "
                 r"nice (\d+); CPU wake-up: ", line)
    assert m, line
    assert int(m.group(2)) == min(19, own_nice + 10)
    assert int(m.group(2)) in servers_nice  # what it said is what the process runs at
