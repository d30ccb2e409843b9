"""``planer hil``: a run cut by its time limit fails and says so; with servers it is paced and
its final state stays served until Ctrl-C (the real command in a subprocess)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from planer.hil.cross_process import free_port
from tests.support import pg_support
from tests.support.interrupt import ended_or_stacks, planer_argv

SCENARIO = """
[{name}]
distance_m = {distance_m}
seed = 0
runout_um = [0.0, 4.0, -2.0, 2.0]
initial_feed_mm_s = 800.0
target_pitch_mm = 1.5
max_sim_s = {max_sim_s}
"""


def _scenario(tmp_path: Path, name: str, distance_m: float, max_sim_s: float) -> Path:
    p = tmp_path / f"{name}.toml"
    p.write_text(SCENARIO.format(name=name, distance_m=distance_m, max_sim_s=max_sim_s))
    return p


def _hil(*args: str) -> list[str]:
    return [sys.executable, "-m", "planer.cli", "hil", "--in-process", "--plc", "direct",
            *args]


def test_a_run_its_time_limit_cuts_fails_and_says_so(tmp_path):
    """5 m asked, 1 s of machine time allowed: about 0.65 m run; the command fails (exit 1)."""
    sc = _scenario(tmp_path, "cut", 5.0, 1.0)
    out = subprocess.run(_hil("--scenario", str(sc), "--log", str(tmp_path / "c.sqlite")),
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 1, out.stderr
    assert "planer hil: the time limit cut the run: max_sim_s 1 s of machine time" in out.stderr
    cut = [ln for ln in out.stdout.splitlines() if ln.startswith("  run cut short")]
    assert len(cut) == 1 and "of the 5 m asked" in cut[0], out.stdout
    assert "  [ ] The time limit cut the run" in out.stdout
    assert out.stdout.rstrip().endswith("NOT PASSED")


def test_a_run_that_goes_its_distance_says_so_in_json(tmp_path):
    sc = _scenario(tmp_path, "short", 0.3, 30.0)
    out = subprocess.run(_hil("--json", "--scenario", str(sc),
                              "--log", str(tmp_path / "s.sqlite")),
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode in (0, 1), out.stderr
    summary = json.loads(out.stdout)
    assert summary["run_end"]["reason"] == "distance"
    assert summary["run_end"]["board_travel_m"] >= 0.3 == summary["run_end"]["distance_m"]
    assert summary["done"]["distance_reached"] is True
    assert summary["checks"]["distance_reached"]["ok"] is True
    assert summary["pace"] is None  # no servers, no --pace: as fast as it goes
    assert "cut the run" not in out.stderr


def test_with_http_the_run_is_paced_and_its_end_served_until_ctrl_c(tmp_path):
    sc = _scenario(tmp_path, "short", 0.5, 30.0)
    port = free_port()
    # started as a background command of a script (SIGINT ignored): Ctrl-C stops it all the same
    proc = subprocess.Popen(
        planer_argv("hil", "--in-process", "--plc", "direct", "--json", "--scenario", str(sc),
                    "--log", str(tmp_path / "w.sqlite"), "--http", f"127.0.0.1:{port}",
                    "--pace", "2", sigint="ignored"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        summary = json.loads(proc.stdout.readline())  # the run is over: its summary
        said = []
        for line in proc.stderr:  # then the servers hold its end
            said.append(line)
            if "until Ctrl-C" in line:
                break
        assert said and f"serving its final state at http://127.0.0.1:{port}/" in said[-1], said
        assert proc.poll() is None  # still serving
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/live", timeout=120) as r:
            live = json.load(r)
        last = live["status"]["last_measurement"]
        assert last["seq"] == summary["measurements"][-1]["seq"]
        assert summary["pace"] == 2.0
        # paced: the wall clock went at least half the simulated time (a busy host only slows)
        assert summary["wall_time_s"] >= summary["sim_time_s"] / 2.0 - 0.05
        proc.send_signal(signal.SIGINT)
        rest = ended_or_stacks(proc, "planer hil --http after Ctrl-C")[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == (0 if summary["passed"] else 1), rest
    assert "planer hil: stopped serving" in rest


@pytest.mark.parametrize("pace", ["0", "-1", "nan"])
def test_a_pace_that_is_not_a_positive_number_is_refused(tmp_path, pace):
    out = subprocess.run(_hil("--pace", pace, "--distance-m", "0.1"),
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 2 and f"--pace must be a number > 0, got {float(pace)}" in out.stderr


pg_server = pg_support.pg_server  # the fixtures (skip without PostgreSQL's binaries)
fresh_db = pg_support.fresh_db


def test_a_postgresql_log_is_printed_as_its_url(tmp_path, fresh_db):
    """The URL keeps its ``//`` in the text summary (``pathlib.Path`` folds it to one)."""
    assert fresh_db.startswith("postgresql://")
    out = subprocess.run(_hil("--distance-m", "0.3", "--log", fresh_db),
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode in (0, 1), out.stderr
    shown = [ln for ln in out.stdout.splitlines() if ln.startswith("  quality log")]
    assert len(shown) == 1 and shown[0].split()[2] == fresh_db, out.stdout
    assert "postgresql:/" + fresh_db[len("postgresql://"):] not in out.stdout + out.stderr


@pytest.mark.parametrize("server", ["--opcua", "--http"])
def test_a_busy_port_is_one_error_line_and_nothing_else(tmp_path, server):
    """No ``coroutine ... was never awaited`` warning after the error."""
    import socket

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen(1)
        port = held.getsockname()[1]
        where = f"opc.tcp://127.0.0.1:{port}" if server == "--opcua" else f"127.0.0.1:{port}"
        out = subprocess.run(_hil("--distance-m", "0.1", "--log", str(tmp_path / "b.sqlite"),
                                  server, where),
                             capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 2, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("planer hil: error:"), out.stderr
    assert str(port) in lines[0]
