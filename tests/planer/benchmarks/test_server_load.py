"""The server-load benchmark's own parts: who used the CPU, the clients' process and its nice."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys

import pytest

from planer.benchmarks import server_load
from planer.benchmarks.figures import latency_stats, proc_cpu_s


def test_cpu_time_of_a_process_and_of_its_children():
    spin = ("import sys, time\nt = time.process_time()\n"
            "while time.process_time() - t < 0.3: pass\n"
            "print('burnt', flush=True)\nsys.stdin.read()\n")
    child = subprocess.Popen([sys.executable, "-c", spin], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "burnt"  # 0.3 s of CPU used, now it waits
        assert proc_cpu_s(child.pid) >= 0.25
        assert child.pid in server_load._children(os.getpid())
        tree = server_load._tree_cpu_s(os.getpid())
        assert tree["servers"] >= 0.25  # a child's CPU is counted as the servers' process's
        assert tree["service"] == pytest.approx(proc_cpu_s(os.getpid()), abs=0.5)
    finally:
        child.communicate("")
    assert proc_cpu_s(child.pid) == 0.0  # gone: nothing
    assert proc_cpu_s(child.pid, missing=None) is None and proc_cpu_s(None) == 0.0


def test_latency_stats_name_their_median_as_each_bench_does():
    values = [1.0, 2.0, 3.0, 4.0, 100.0]
    assert latency_stats(values) == {"median": 3.0, "p99": pytest.approx(96.16), "max": 100.0}
    assert latency_stats(values, middle="p50") == {"p50": 3.0, "p99": pytest.approx(96.16),
                                                   "max": 100.0}
    assert latency_stats([]) == {}


def test_the_clients_process_takes_its_nice_and_stops_when_told():
    ctx = multiprocessing.get_context("spawn")
    out, stop = ctx.Queue(), ctx.Event()
    stop.set()  # told to stop at once: no server needed
    base = os.nice(0)
    p = ctx.Process(target=server_load.load_for,
                    args=(None, None, 600.0, {"idle": 0, "sse": 0, "opcua_readers": 0,
                                              "opcua_sub_ms": 10.0}, out),
                    kwargs={"stop": stop, "nice": 7})
    p.start()
    counts = out.get(timeout=120.0)
    p.join(60.0)
    assert p.exitcode == 0
    assert counts["nice"] == min(19, base + 7) and counts["cpu_s"] >= 0.0
    assert counts["load_s"] < 600.0  # stopped by the event, not by its time
    assert os.nice(0) == base  # this process kept its own


def test_load_nice_is_checked():
    with pytest.raises(SystemExit, match="--load-nice"):
        server_load.main(["--load-nice", "20"])
