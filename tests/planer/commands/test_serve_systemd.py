"""``planer serve`` as a systemd unit: the notification protocol on a real socket, journal lines.

The real ``planer serve`` process runs with a ``SOCK_DGRAM`` Unix socket bound in a temporary
folder as its ``NOTIFY_SOCKET`` (systemd's part played by the test), ``WATCHDOG_USEC`` set and
``INVOCATION_ID`` set as under the journal; no PLC answers and the CAN bus is python-can's
in-process ``virtual`` one, so the service waits in the safe state and says so.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _messages_until(sock, done, proc, backstop_s=180.0):
    """Datagrams received until ``done(messages)``; the process ending first fails the test.

    The backstop only bounds a broken run.
    """
    got: list[str] = []
    end = time.monotonic() + backstop_s
    sock.settimeout(0.5)
    while not done(got):
        try:
            got.append(sock.recv(4096).decode())
        except TimeoutError:
            if proc.poll() is not None:
                break
            assert time.monotonic() < end, got
    return got


def test_serve_speaks_sd_notify_and_writes_journal_lines(tmp_path):
    (tmp_path / "machine.toml").write_text(
        f'[plc]\nport = {_free_port()}\ntimeout_s = 0.05\n'
        '[can]\ninterface = "virtual"\nchannel = "sd-notify-test"\n'
        f'[frames]\nspool_dir = "{tmp_path / "spool"}"\n'
        f'[log]\npath = "{tmp_path / "quality.sqlite"}"\n'
    )
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NOTIFY_SOCKET": str(tmp_path / "notify"),
           "WATCHDOG_USEC": "200000", "INVOCATION_ID": "0123456789abcdef"}
    env.pop("WATCHDOG_PID", None)
    env.pop("JOURNAL_STREAM", None)
    p = subprocess.Popen(
        [sys.executable, "-m", "planer.cli", "serve", "--config", str(tmp_path / "machine.toml"),
         "--status-every", "0.2"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        def serving(m):
            return (any("READY=1" in x for x in m) and sum(x == "WATCHDOG=1" for x in m) >= 3
                    and any(x.startswith("STATUS=waiting in the safe state") for x in m))

        got = _messages_until(sock, serving, p)
        assert p.poll() is None, p.communicate()[1]
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=120)
        got += _messages_until(sock, lambda m: any("STOPPING=1" in x for x in m), p, 10)
    finally:
        p.kill()
        sock.close()
    assert p.returncode == 0, err
    ready = next(x for x in got if "READY=1" in x)
    assert got.index(ready) < len(got) - 1 and got[-1].startswith("STOPPING=1")
    assert ready.startswith("READY=1\nSTATUS=serving")
    waiting = [x for x in got if x.startswith("STATUS=waiting in the safe state")]
    assert "not answering" in waiting[0] and "\n" not in waiting[0]
    lines = out.splitlines()
    assert "ready" in lines
    waits = [ln for ln in lines if "waiting in the safe state" in ln]
    assert waits and all(ln.startswith("waiting in the safe state") for ln in waits)
    assert not any(ln.startswith("t=") for ln in lines + err.splitlines())  # the journal stamps
