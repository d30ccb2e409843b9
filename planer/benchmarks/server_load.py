"""Client load on the servers while the loop runs: idle sockets, event streams, OPC UA hammer.

``python -m planer.benchmarks.server_load`` runs ``planer hil --in-process --http ... --opcua
... --json`` twice, quiet and under load, and prints both summaries' pair latency, pairs,
safe entries and the load's own counts as JSON. The load, from this process, on loopback
only, bounded in count and time:

- ``--idle N`` TCP connections to the page's port that send nothing, topped up (at most
  ``--idle-rate`` new ones a second) as the server closes them;
- ``--sse N`` clients of ``/api/live/stream`` reading what they get;
- ``--opcua-readers N`` OPC UA clients reading a variable in a loop, and one client with a
  subscription of ``--opcua-sub-ms`` to every ``State/Machine`` variable.

The clients run in a process of their own (:func:`load_for`), ``--load-nice N`` added to its
nice value: on a plant the clients are other machines, here they share the cores with the
service, and at nice 0 they take as much CPU as the service's loop. That process raises its
own ``RLIMIT_NOFILE`` soft limit to the hard one and keeps 256 descriptors for itself (the idle
sockets get the rest, at most ``--idle``). Each run's ``cpu_s`` says who used the CPU while the
run went: the service's process (``planer hil``), the servers' process and the clients;
``priority`` what the run's loop thread was granted (``planer hil`` raises it as ``planer serve``
raises its bus thread: ``SCHED_FIFO`` where permitted; ``--no-realtime`` runs it with its loop
at normal priority, to compare) and ``loadavg`` the host's load averages at the run's start and
end.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["Load", "free_port", "load_for", "main", "run_hil"]


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Load:
    """The clients, with their counts (``counts``)."""

    def __init__(self, http_port: int | None, opcua_port: int | None, *, idle: int, sse: int,
                 opcua_readers: int, opcua_sub_ms: float, idle_rate: int = 2000) -> None:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
        self.http_port, self.opcua_port = http_port, opcua_port
        self.idle_target = max(0, min(idle, soft - 256 - sse - 2 * opcua_readers))
        self.sse, self.readers, self.sub_ms = sse, opcua_readers, opcua_sub_ms
        self.idle_rate = idle_rate
        self.held: list[socket.socket] = []
        self.counts: dict[str, Any] = {
            "nofile_soft": soft, "idle_target": self.idle_target, "idle_opened": 0,
            "idle_closed_by_server": 0, "idle_connect_failed": 0, "idle_held_max": 0,
            "sse_200": 0, "sse_503": 0, "sse_other": 0, "sse_events": 0, "sse_failed": 0,
            "sse_no_answer": 0, "sse_cut": 0,
            "opcua_connected": 0, "opcua_refused": 0, "opcua_reads": 0, "opcua_read_errors": 0,
            "opcua_sub_changes": 0, "opcua_sub_ok": False, "opcua_sub_revised_ms": None,
        }

    # -- idle sockets ---------------------------------------------------------------------------
    def _open_idle(self, n: int) -> None:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setblocking(False)
            err = s.connect_ex(("127.0.0.1", self.http_port))
            if err not in (0, errno.EINPROGRESS):
                self.counts["idle_connect_failed"] += 1
                s.close()
                continue
            self.held.append(s)
            self.counts["idle_opened"] += 1

    def _sweep_idle(self) -> None:
        alive = []
        for s in self.held:
            try:
                data = s.recv(1, socket.MSG_PEEK)
                gone = data == b""
            except BlockingIOError:
                gone = False
            except OSError:
                gone = True
            if gone:
                self.counts["idle_closed_by_server"] += 1
                s.close()
            else:
                alive.append(s)
        self.held = alive
        self.counts["idle_held_max"] = max(self.counts["idle_held_max"], len(alive))

    async def idle(self, until: float) -> None:
        """Hold ``idle_target`` idle connections, topping up ``idle_rate`` a second."""
        while time.monotonic() < until:
            self._sweep_idle()
            self._open_idle(min(self.idle_rate, self.idle_target - len(self.held)))
            await asyncio.sleep(1.0)

    # -- event streams --------------------------------------------------------------------------
    async def _stream(self, until: float) -> None:
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", self.http_port)
        except OSError:
            self.counts["sse_failed"] += 1
            return
        try:
            writer.write(b"GET /api/live/stream HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                         b"Accept: text/event-stream\r\n\r\n")
            await writer.drain()
            try:
                status = await asyncio.wait_for(reader.readline(), 30.0)
            except (OSError, asyncio.TimeoutError):  # closed unanswered, or no answer in 30 s
                self.counts["sse_no_answer"] += 1
                return
            code = status.split()[1] if len(status.split()) > 1 else b""
            key = {b"200": "sse_200", b"503": "sse_503"}.get(code, "sse_other")
            self.counts[key] += 1
            while code == b"200" and time.monotonic() < until:
                line = await asyncio.wait_for(reader.readline(), max(0.1, until - time.monotonic()))
                if not line:
                    break
                if line.startswith(b"data: "):
                    self.counts["sse_events"] += 1
        except (OSError, asyncio.TimeoutError, IndexError):
            self.counts["sse_cut"] += 1  # the stream ended before the run did
        finally:
            writer.close()

    # -- OPC UA ---------------------------------------------------------------------------------
    async def _reader(self, until: float) -> None:
        from asyncua import Client

        client = Client(f"opc.tcp://127.0.0.1:{self.opcua_port}", timeout=10)
        try:
            await client.connect()
        except _client_errors():  # refused is counted
            self.counts["opcua_refused"] += 1
            return
        self.counts["opcua_connected"] += 1
        try:
            node = await _find(client, "State/Machine/Values/FeedSpeed")
            while time.monotonic() < until:
                try:
                    await node.read_value()
                    self.counts["opcua_reads"] += 1
                except _client_errors():  # a refused read is counted
                    self.counts["opcua_read_errors"] += 1
                    await asyncio.sleep(0.1)
        finally:
            with contextlib.suppress(Exception):
                await client.disconnect()

    async def _subscriber(self, until: float) -> None:
        from asyncua import Client

        counts = self.counts

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                counts["opcua_sub_changes"] += 1

        client = Client(f"opc.tcp://127.0.0.1:{self.opcua_port}", timeout=10)
        try:
            await client.connect()
            sub = await client.create_subscription(self.sub_ms, Handler())
            counts["opcua_sub_revised_ms"] = sub.parameters.RequestedPublishingInterval
            nodes = [await _find(client, f"State/Machine/{p}") for p in
                     ("Values/FeedSpeed", "Values/AbsoluteRunsTotal", "Flags/FeedRuns",
                      "Overview/CurrentState")]
            await sub.subscribe_data_change(nodes)
            counts["opcua_sub_ok"] = True
            await asyncio.sleep(max(0.0, until - time.monotonic()))
        except _client_errors():  # a refused subscriber is counted
            counts["opcua_refused"] += 1
        finally:
            with contextlib.suppress(Exception):
                await client.disconnect()

    async def run(self, until: float) -> None:
        """All the clients until ``until`` (monotonic s)."""
        jobs = []
        if self.http_port is not None:
            jobs.append(self.idle(until))
            jobs += [self._stream(until) for _ in range(self.sse)]
        if self.opcua_port is not None:
            jobs.append(self._subscriber(until))
            jobs += [self._reader(until) for _ in range(self.readers)]
        await asyncio.gather(*jobs, return_exceptions=True)
        for s in self.held:
            s.close()
        self.held = []


def load_for(http_port: int | None, opcua_port: int | None, seconds: float,
             kwargs: dict[str, Any], out: Any, *, stop: Any = None, nice: int = 0) -> None:
    """Run a :class:`Load` (a process target); put its counts on ``out``.

    It runs for ``seconds`` or until ``stop`` (a ``multiprocessing`` event) is set, with
    ``nice`` added to this process's nice value. The counts carry ``cpu_s``: the CPU time
    (user + system) the clients used, s.
    """
    import logging
    import resource

    if nice:
        os.nice(nice)
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    clients = Load(http_port, opcua_port, **kwargs)
    until = time.monotonic() + seconds

    async def until_done() -> None:
        task = asyncio.create_task(clients.run(until))
        while not task.done() and not (stop is not None and stop.is_set()):
            await asyncio.sleep(0.5)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        for sock in clients.held:  # cancelled before it closed them
            sock.close()

    started = time.monotonic()
    asyncio.run(until_done())
    use = resource.getrusage(resource.RUSAGE_SELF)
    clients.counts["load_s"] = round(time.monotonic() - started, 1)
    clients.counts["cpu_s"] = round(use.ru_utime + use.ru_stime, 1)
    clients.counts["nice"] = os.nice(0)
    out.put(clients.counts)


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                if int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(entry.name))
    return out


def _tree_cpu_s(pid: int) -> dict[str, float]:
    """CPU time so far of ``planer hil`` (``service``) and its servers' process (``servers``)."""
    from planer.benchmarks.figures import proc_cpu_s

    servers = sum(proc_cpu_s(c) or 0.0 for c in _children(pid))
    return {"service": proc_cpu_s(pid) or 0.0, "servers": servers}


async def _find(client: Any, path: str) -> Any:
    objects = client.nodes.objects
    own = await client.get_namespace_index("urn:smart-planer:machine")
    return client.get_node(f"ns={own};s=SmartPlaner.{path.replace('/', '.')}") \
        if objects is not None else None


def run_hil(distance_m: float, log: Path, *, http_port: int, opcua_port: int,
            load: dict[str, Any] | None, max_s: float = 900.0,
            load_nice: int = 0, realtime: bool = True) -> dict[str, Any]:
    """``planer hil --in-process`` with the servers on (paced at real time), under load.

    The load (if any) runs in a process of its own (``load_nice`` added to its nice value)
    while the run goes; Ctrl-C once its summary is out (the command then serves its final
    state). ``realtime=False`` runs it with ``--no-realtime`` (its loop at normal priority).
    Returns the run's JSON summary's key figures, the load's counts and ``cpu_s``
    (CPU time from the servers' start to the summary, s: ``service``, ``servers``, ``load``).
    """
    import multiprocessing
    import signal
    import threading

    argv = [sys.executable, "-m", "planer.cli", "hil", "--in-process", "--distance-m",
            str(distance_m), "--log", str(log), "--json",
            "--http", f"127.0.0.1:{http_port}", "--opcua", f"opc.tcp://127.0.0.1:{opcua_port}"]
    if not realtime:
        argv.append("--no-realtime")
    errfile = tempfile.TemporaryFile()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=errfile, text=True)
    summary_lines: list[str] = []
    over = threading.Event()

    def read() -> None:
        for line in proc.stdout:  # type: ignore[union-attr]
            if line.startswith("{"):
                summary_lines.append(line)
                over.set()
        over.set()

    threading.Thread(target=read, daemon=True).start()
    counts = None
    cpu: dict[str, Any] = {}
    loadavg = {"start": [round(x, 2) for x in os.getloadavg()]}
    try:
        _wait_port(http_port, proc, 120.0)
        _wait_port(opcua_port, proc, 120.0)
        cpu0 = _tree_cpu_s(proc.pid)
        if load is not None:
            ctx = multiprocessing.get_context("spawn")
            out, stop = ctx.Queue(), ctx.Event()
            clients = ctx.Process(target=load_for, args=(http_port, opcua_port, max_s, load,
                                                         out), kwargs={"stop": stop,
                                                                       "nice": load_nice},
                                  daemon=True)
            clients.start()
            over.wait(max_s)
            cpu1 = _tree_cpu_s(proc.pid)
            stop.set()
            try:
                counts = out.get(timeout=120.0)
            finally:
                clients.join(30.0)
                if clients.is_alive():
                    clients.kill()
            cpu["load"] = counts.get("cpu_s")
        else:
            over.wait(max_s)
            cpu1 = _tree_cpu_s(proc.pid)
        cpu.update({k: round(cpu1[k] - cpu0[k], 1) for k in cpu1})
        loadavg["end"] = [round(x, 2) for x in os.getloadavg()]
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)  # stop serving the final state
        proc.wait(60.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    errfile.seek(0)
    err = errfile.read().decode(errors="replace")
    try:
        summary = json.loads(summary_lines[-1])
    except (ValueError, IndexError):
        raise RuntimeError(f"planer hil gave no summary (exit {proc.returncode}): "
                           f"{err[-2000:]}") from None
    return {
        "latency_ms": summary.get("latency_ms"),
        "pairs": summary["counts"]["measurements"],
        "pairs_per_s": round(summary["counts"]["measurements"] / summary["wall_time_s"], 2),
        "missed": summary["service"].get("missed"),
        "safe_entries": summary["safe_entries"]["count"],
        "pace_behind_s": summary.get("pace_behind_s"),
        "quality_log": {k: summary["quality_log"][k] for k in ("records", "expected", "ok")},
        "passed": summary["passed"],
        "wall_time_s": summary.get("wall_time_s"),
        "cpu_s": cpu,
        "priority": summary.get("priority"),
        "loadavg": loadavg,
        "servers_lines": [ln for ln in err.splitlines() if "planer servers" in ln][-20:],
        "priority_lines": [ln for ln in err.splitlines() if ln.startswith("priority:")],
        "load": counts,
    }


def _wait_port(port: int, proc: subprocess.Popen, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"planer hil ended before serving (exit {proc.returncode})")
        with socket.socket() as s:
            s.settimeout(1.0)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise RuntimeError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")


def main(argv: list[str] | None = None) -> int:
    """Quiet run, then the loaded run; both as JSON on stdout."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--distance-m", type=float, default=60.0)
    p.add_argument("--idle", type=int, default=20_000)
    p.add_argument("--idle-rate", type=int, default=2000)
    p.add_argument("--sse", type=int, default=200)
    p.add_argument("--opcua-readers", type=int, default=50)
    p.add_argument("--opcua-sub-ms", type=float, default=10.0)
    p.add_argument("--skip-quiet", action="store_true")
    p.add_argument("--no-realtime", action="store_true",
                   help="planer hil --no-realtime: the run's loop at normal priority (compare)")
    p.add_argument("--load-nice", type=int, default=0, metavar="N",
                   help="added to the clients' process's nice value (0..19; default 0)")
    args = p.parse_args(argv)
    import logging

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)  # the clients' own complaints
    for name in ("idle", "sse", "opcua_readers"):
        if getattr(args, name) < 0:
            raise SystemExit(f"--{name.replace('_', '-')} must be >= 0")
    if not 0 <= args.load_nice <= 19:
        raise SystemExit(f"--load-nice must be within 0..19, got {args.load_nice}")
    with tempfile.TemporaryDirectory(prefix="planer-load-") as tmp:
        out: dict[str, Any] = {"host": {"cores": os.cpu_count(),
                                        "loadavg_start": list(os.getloadavg())}}
        if not args.skip_quiet:
            out["quiet"] = run_hil(args.distance_m, Path(tmp) / "quiet.sqlite",
                                   http_port=free_port(), opcua_port=free_port(), load=None,
                                   realtime=not args.no_realtime)
        out["loaded"] = run_hil(
            args.distance_m, Path(tmp) / "loaded.sqlite", http_port=free_port(),
            opcua_port=free_port(),
            load={"idle": args.idle, "sse": args.sse, "opcua_readers": args.opcua_readers,
                  "opcua_sub_ms": args.opcua_sub_ms, "idle_rate": args.idle_rate},
            load_nice=args.load_nice, realtime=not args.no_realtime)
        if "quiet" in out:
            q, loaded = out["quiet"]["latency_ms"], out["loaded"]["latency_ms"]
            with contextlib.suppress(KeyError, TypeError, ZeroDivisionError):
                out["p99_ratio"] = round(loaded["p99"] / q["p99"], 2)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


def _client_errors() -> tuple[type[BaseException], ...]:
    """What an OPC UA client meets when the server refuses or drops it (asyncua imported)."""
    from asyncua.ua import UaError

    return (OSError, asyncio.TimeoutError, ConnectionError, UaError)
