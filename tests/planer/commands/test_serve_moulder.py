"""``planer serve`` of a moulder against ``planer sim`` of the moulder: two processes, real time.

The shipped four-head moulder (``config/sim_moulder.toml``, ``config/machine_moulder.toml``) in
two real processes, the way docs/simulator.md "Running the moulder" runs them by hand: both in
one private network namespace (``unshare``: only ``lo``, multicast routed on it) so that the one
CAN bus of the four amplifiers crosses processes over python-can's ``udp_multicast`` without
leaving the host; Modbus on 127.0.0.1 of that namespace; spools, quality log and the
simulator's output in the test's folder. ``planer serve`` is stopped with SIGTERM once every
head's loop is closed (its progress line in ``run`` at the feed the heads need); the simulator
(``--duration`` as a backstop) is stopped after it. Skipped where the cross-process HIL cannot
run (``planer.hil.cross_process.cross_process_possible``: no ``msgpack`` for python-can's
``udp_multicast``, or no ``unshare``/``ip`` permitted to make the namespace).

A second test serves the moulder with nothing answering (no PLC on its port, CAN on python-can's
in-process ``virtual`` bus) as systemd runs it (``INVOCATION_ID`` set): every head says why it
waits, without run times of its own (the journal stamps lines), and SIGTERM stops it cleanly.
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from config.machine import load_machine
from config.sim import load_sim
from planer.hil.cross_process import cross_process_possible, free_port
from protocol.can_transport import netns_argv

ROOT = Path(__file__).resolve().parents[3]
HEADS = ("bottom", "right", "left", "top")
FASTEST_FEED_MM_S = 600.0
"""The fastest feed at which every head of the shipped moulder meets its target."""

# In the namespace: the simulator in the background (its output to a file) until it says
# "ready", then the service; the service's process id first, its exit code passed on; both
# stopped when the driver is (the test's end, or the test process dying: _die_with_parent).
DRIVER = r"""
trap 'kill -TERM $sim $serve 2>/dev/null; exit 143' TERM INT HUP
"$PY" -m planer.cli sim --config "$SIM_TOML" --port "$PORT" --duration 600 >"$SIM_OUT" 2>&1 &
sim=$!
until grep -qx ready "$SIM_OUT"; do
    kill -0 "$sim" 2>/dev/null || { echo "sim ended before ready"; exit 97; }
    sleep 0.1
done
"$PY" -m planer.cli serve --config "$MACHINE_TOML" --workers 1 --status-every 1 2>&1 &
serve=$!
echo "serve pid $serve"
wait "$serve"
rc=$?
kill -TERM "$sim" 2>/dev/null
wait "$sim"
echo "sim exit $?"
exit "$rc"
"""

class Lines:
    """A process's output lines, read by a thread; ``until(done)`` waits for a condition."""

    def __init__(self, stream) -> None:
        self.lines: list[str] = []
        self._q: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            self._q.put(line.rstrip("\n"))
        self._q.put(None)

    def until(self, done, *, backstop_s: float) -> bool:
        """Take lines until ``done(lines)`` (True) or the output ends (False).

        The backstop only bounds a broken run.
        """
        end = time.monotonic() + backstop_s
        while not done(self.lines):
            assert time.monotonic() < end, "\n".join(self.lines[-30:])
            try:
                line = self._q.get(timeout=1.0)
            except queue.Empty:
                continue
            if line is None:
                return False
            self.lines.append(line)
        return True

    def rest(self, timeout_s: float) -> None:
        """Every line until the output ends (fails past ``timeout_s``)."""
        self.until(lambda _lines: False, backstop_s=timeout_s)


def _die_with_parent() -> None:  # pragma: no cover - runs in the child
    """Linux: SIGTERM the driver when the test process dies (no simulator left running)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _end(p: subprocess.Popen) -> None:
    """End the process group ``p`` leads (started with ``start_new_session``) if it still runs."""
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


PROGRESS = re.compile(r"^t=\s*[\d.]+ s  \[(\w+)\] #(\d+)  (\w+)  ok \d+/\d+  pitch (\S+) mm  "
                      r".*  feed ([\d.]+) mm/s")


def _loops_closed(lines: list[str], targets: dict[str, float], tolerance: float) -> bool:
    """Every head's latest progress line, past its 20th pair, in ``run``, its pitch within
    ``tolerance`` of its target, the feed the heads need (+-3 %)."""
    latest: dict[str, tuple[int, str, float, float]] = {}
    for ln in lines:
        m = PROGRESS.match(ln)
        if m:
            latest[m[1]] = (int(m[2]), m[3], float(m[4]), float(m[5]))
    for head, target in targets.items():
        if head not in latest:
            return False
        n, state, pitch, feed = latest[head]
        if not (n >= 20 and state == "run" and abs(pitch / target - 1.0) <= tolerance
                and abs(feed / FASTEST_FEED_MM_S - 1.0) <= 0.03):
            return False
    return True


def _write_configs(tmp_path: Path, port: int) -> tuple[Path, Path]:
    group = "239.74.163.2"
    sim = tmp_path / "sim.toml"
    sim.write_text(
        'base = "sim_moulder.toml"\n'
        f'[can]\ninterface = "udp_multicast"\nchannel = "{group}"\n'
        f'[frames]\nspool_dir = "{tmp_path / "spool"}"\n')
    machine = tmp_path / "machine.toml"
    machine.write_text(
        'base = "machine_moulder.toml"\n'
        f'[plc]\nport = {port}\n'
        f'[can]\ninterface = "udp_multicast"\nchannel = "{group}"\n'
        f'[frames]\nspool_dir = "{tmp_path / "spool"}"\n'
        f'[log]\npath = "{tmp_path / "quality.sqlite"}"\nprint_every = 10\n')
    return sim, machine


def _records(path: Path) -> list[dict]:
    with sqlite3.connect(path) as db:
        db.row_factory = sqlite3.Row
        rows = db.execute("SELECT head, t_s, ok, pitch_mm, target_pitch_mm, feed_setpoint_mm_s, "
                          "extra_json FROM records ORDER BY record_id").fetchall()
    return [{**dict(r), "state": json.loads(r["extra_json"] or "{}").get("state")} for r in rows]


def test_serve_moulder_against_planer_sim_in_real_time(tmp_path):
    ok, why = cross_process_possible()
    if not ok:
        pytest.skip(f"serve against sim across processes not possible here: {why}")
    sim_toml, machine_toml = _write_configs(tmp_path, free_port())
    sim_cfg = load_sim(str(sim_toml))
    cfg = load_machine(str(machine_toml))
    assert [h.name for h in cfg.heads] == [h.name for h in sim_cfg.heads] == list(HEADS)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PY": sys.executable,
           "SIM_TOML": str(sim_toml), "MACHINE_TOML": str(machine_toml),
           "PORT": str(cfg.plc.port), "SIM_OUT": str(tmp_path / "sim.out")}
    for var in ("INVOCATION_ID", "JOURNAL_STREAM", "NOTIFY_SOCKET", "WATCHDOG_USEC"):
        env.pop(var, None)
    p = subprocess.Popen(netns_argv(["sh", "-c", DRIVER]), cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         start_new_session=True, preexec_fn=_die_with_parent)
    try:
        out = Lines(p.stdout)
        assert out.until(lambda lines: any(ln.startswith("serve pid ") for ln in lines),
                         backstop_s=180), out.lines
        serve_pid = int(next(ln for ln in out.lines if ln.startswith("serve pid ")).split()[-1])
        targets = {h.name: h.target_pitch_mm for h in cfg.heads}
        closed = out.until(lambda lines: _loops_closed(lines, targets, cfg.quality.tolerance),
                           backstop_s=240)
        sim_said = (tmp_path / "sim.out").read_text()
        assert closed, "\n".join(out.lines[-40:]) + "\n--- sim\n" + sim_said[-3000:]
        os.kill(serve_pid, signal.SIGTERM)
        out.rest(120)
        rc = p.wait(timeout=60)
    finally:
        _end(p)  # the driver, the simulator and the service (one process group)
    lines = out.lines
    text = "\n".join(lines)
    assert rc == 0, text
    assert "sim exit 0" in lines, text
    assert "ready" in lines, text
    for i, h in enumerate(cfg.heads):  # one line per head: its face, target, node, spool
        line = next(ln for ln in lines if ln.startswith(f"head {h.name}: "))
        assert f"{h.face}, target pitch {h.target_pitch_mm} mm" in line, line
        assert f"node {h.node_id}" in line and f"node {2 + i}" in line, line
        assert f"frames {tmp_path / 'spool' / h.name}," in line, line
        assert any(re.match(rf"t=\s*[\d.]+ s  \[{h.name}\] recovered", ln) for ln in lines), h
        stopped = next(ln for ln in lines if ln.startswith(f"stopped [{h.name}]: "))
        pairs, measured = map(int, re.match(r"stopped \[\w+\]: (\d+) pairs, (\d+) measured",
                                            stopped).groups())
        assert pairs >= 20 and measured >= 10, stopped
    assert lines.index("ready") < min(i for i, ln in enumerate(lines) if "recovered" in ln)
    # the event loop raised as one head's bus thread is (whatever the host granted)
    assert any(ln.startswith("priority: service bus (every head and the feed) ")
               for ln in lines), text

    records = _records(tmp_path / "quality.sqlite")
    assert {r["head"] for r in records} == set(HEADS)
    feed_min, feed_max = sim_cfg.feed.min_mm_s, sim_cfg.feed.max_mm_s
    setpoints = [r["feed_setpoint_mm_s"] for r in records]
    assert all(feed_min <= f <= feed_max for f in setpoints), (min(setpoints), max(setpoints))
    # the coordinator wrote it: the simulator starts at 600 mm/s and nothing else writes the feed
    assert max(setpoints) - min(setpoints) > 1.0, (min(setpoints), max(setpoints))
    for h in cfg.heads:
        mine = [r for r in records if r["head"] == h.name]
        assert all(r["target_pitch_mm"] == h.target_pitch_mm for r in mine), h.name
        run = [r for r in mine if r["state"] == "run" and r["ok"]]
        assert len(run) >= 5, (h.name, [r["state"] for r in mine])
        # the loop closed: the pitch at its target, the feed the heads need
        pitch = sum(r["pitch_mm"] for r in run[-5:]) / 5
        assert abs(pitch / h.target_pitch_mm - 1.0) <= cfg.quality.tolerance, (h.name, run[-5:])
        assert abs(run[-1]["feed_setpoint_mm_s"] / FASTEST_FEED_MM_S - 1.0) <= 0.03, run[-1]


def test_serve_moulder_under_the_journal_says_why_each_head_waits(tmp_path):
    (tmp_path / "machine.toml").write_text(
        'base = "machine_moulder.toml"\n'
        f'[plc]\nport = {free_port()}\ntimeout_s = 0.05\n'
        '[can]\ninterface = "virtual"\nchannel = "serve-moulder-journal"\n'
        f'[frames]\nspool_dir = "{tmp_path / "spool"}"\n'
        f'[log]\npath = "{tmp_path / "quality.sqlite"}"\n')
    env = {**os.environ, "PYTHONPATH": str(ROOT), "INVOCATION_ID": "0123456789abcdef"}
    for var in ("JOURNAL_STREAM", "NOTIFY_SOCKET", "WATCHDOG_USEC"):
        env.pop(var, None)
    p = subprocess.Popen(
        [sys.executable, "-m", "planer.cli", "serve", "--config", str(tmp_path / "machine.toml"),
         "--status-every", "0.2"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)
    try:
        out = Lines(p.stdout)

        def every_head_waits(lines):
            return all(any(ln.startswith(f"[{h}] waiting in the safe state") for ln in lines)
                       for h in HEADS)

        assert out.until(every_head_waits, backstop_s=180), out.lines
        p.send_signal(signal.SIGTERM)
        out.rest(120)
        rc = p.wait(timeout=60)
    finally:
        _end(p)
    lines = out.lines
    assert rc == 0, lines
    assert "ready" in lines
    waits = [ln for ln in lines if "waiting in the safe state" in ln]
    assert all(re.match(r"\[\w+\] waiting in the safe state: PLC 127\.0\.0\.1:\d+ not "
                        r"answering", ln) for ln in waits), waits
    assert not any(ln.startswith("t=") for ln in lines), lines  # the journal stamps them
    for h in HEADS:
        assert any(ln.startswith(f"stopped [{h}]: ") for ln in lines), h
