"""The loop under client load (the small version of planer/benchmarks/server_load.py).

An in-process HIL run with the pages and OPC UA on, while another process holds idle sockets
to the page's port, reads the event stream and hammers OPC UA (readers and a 10 ms
subscription). The properties: no pair lost, no safe entry, the quality log whole, the loop's
own cycle gaps bounded, and none of the clients' sockets in the loop's process (its file
descriptors stay where they were). No wall-clock speed is compared.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import time
from dataclasses import replace

import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the web extra (uvicorn) is not installed")
pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")

from controller.edge.compose import serving  # noqa: E402
from controller.edge.limits import ServerLimits  # noqa: E402
from planer.benchmarks.server_load import load_for  # noqa: E402

LOAD = {"idle": 600, "sse": 12, "opcua_readers": 6, "opcua_sub_ms": 10.0, "idle_rate": 600}
LIMITS = ServerLimits(http_max_connections=64, http_max_sse=8, opcua_max_connections=5,
                      http_header_timeout_s=2.0)


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


async def _heartbeat(gaps: list[float]) -> None:
    """The loop's own cycle: how late a 10 ms sleep comes back."""
    while True:
        t = time.perf_counter()
        await asyncio.sleep(0.01)
        gaps.append(time.perf_counter() - t)


def test_the_loop_keeps_its_pairs_while_clients_pile_on_the_servers(tmp_path):
    from planer.hil import InProcessHil, load_scenario, machine_config_for

    scenario = replace(load_scenario("default"), distance_m=6.0)
    log = tmp_path / "hil.sqlite"
    cfg = machine_config_for(scenario, log_path=log)
    runner = InProcessHil(scenario, log_path=log, plc_transport="direct")
    ctx = multiprocessing.get_context("spawn")
    counts_q = ctx.Queue()
    gaps: list[float] = []
    fds: dict[str, int] = {}

    async def main() -> tuple[dict, dict]:
        async with serving(cfg, lambda: getattr(runner, "service", None), http="127.0.0.1:0",
                           opcua="opc.tcp://127.0.0.1:0", limits=LIMITS) as servers:
            http_port = int(servers.url.rsplit(":", 1)[1].strip("/"))
            opcua_port = int(servers.endpoint.rsplit(":", 1)[1])
            # whatever serves clients runs below the loop: the servers' process at nice +10
            fds["servers_nice"] = servers.info["nice"]
            fds["own_nice"] = os.getpriority(os.PRIO_PROCESS, 0)
            fds["before"] = _fds()
            load = ctx.Process(target=load_for, args=(http_port, opcua_port, 600.0, LOAD,
                                                      counts_q), daemon=True)
            load.start()
            # the run starts once the load is on the servers (their own report says so)
            await asyncio.to_thread(servers.wait_stats, lambda s: s.get("http", {}).get(
                "evicted", 0) + s.get("http", {}).get("refused", 0) > 0, 120.0)
            beat = asyncio.create_task(_heartbeat(gaps))
            peak = [0]

            async def watch_fds() -> None:
                while True:
                    peak[0] = max(peak[0], _fds())
                    await asyncio.sleep(0.2)

            watcher = asyncio.create_task(watch_fds())
            try:
                summary = await runner.run()
            finally:
                beat.cancel()
                watcher.cancel()
                load.terminate()
                await asyncio.to_thread(load.join, 30.0)
            fds["peak"] = peak[0]
            stats = servers.stats()
        return summary, stats

    summary, stats = asyncio.run(main())
    # the load reached the servers
    http, opcua = stats["http"], stats["opcua"]
    assert http["evicted"] + http["refused"] + http["header_timeouts"] > 0, http
    assert opcua["published"] > 0
    assert fds["servers_nice"] == min(19, fds["own_nice"] + 10), fds
    # ... and not the loop's process: no client socket here
    assert fds["peak"] - fds["before"] < 50, fds
    # the loop lost nothing and never went safe
    assert summary["counts"]["measurements"] > 0
    assert summary["service"]["missed"] == 0
    assert summary["safe_entries"]["count"] == 0
    q = summary["quality_log"]
    assert q["ok"] and q["records"] == q["expected"]
    # the loop's own cycle: a 10 ms sleep never came back seconds late
    gaps.sort()
    assert gaps and gaps[-1] < 1.0, gaps[-5:]
    assert gaps[int(0.99 * (len(gaps) - 1))] < 0.3, gaps[-20:]
