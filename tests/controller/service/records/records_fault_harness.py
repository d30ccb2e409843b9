"""A real-time run of the service in its own process, watched from the PLC's side.

The test process plays the plant: the simulated machine stepped in real time, its PLC behind
the real Modbus TCP server (127.0.0.1), which notes the time of every new service heartbeat it
receives. The pairs the machine's camera takes (counts and truth, no images) go to the service
process over its stdin. The service process (``python -m
tests.controller.service.records.records_fault_harness PORT LOG``) is the real-time service
(``Service.run``, ``threaded``) with a measurer that reads each pair's truth and the amplifier
node on an in-process virtual CAN bus; it says on stdout, one JSON object a line, every event
(``{"event": kind, "text": ...}``), every pair handled (``{"result": seq}``) and every record
durable (``{"stored": seq}``). Its status is read every 0.2 s, as ``planer serve``, the web page
and the OPC UA server read it.

So a stall of the service's event loop shows as a gap in the heartbeats the PLC received, and
the service can be killed (SIGKILL) like any process.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import pickle
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[4]
STEP_S = 0.005
"""Real-time step of the plant, s."""
STATUS_EVERY_S = 0.2
"""The service's status is read this often, as displays do (``Service.status()``), s."""


# ------------------------------------------------------------------------------ the service side
def _child(port: int, log: str) -> None:  # pragma: no cover - runs in the service process
    import can

    from config.machine import load_machine, registers_path, rig_path
    from config.rig import load_rig
    from controller.fieldbus.piezo_client import PiezoClient
    from controller.fieldbus.plc_client import PlcClient
    from controller.fieldbus.plc_protocol import Backoff
    from controller.frames.source import QueueFrameSource
    from controller.quality.log import open_quality_log
    from controller.service.service import Service
    from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
    from plant_sim.machine.machine import Machine
    from protocol.registers import RegisterMap
    from tests.support.plant_support import truth_measurer

    cfg = load_machine()
    cfg = cfg.with_changes(plc=replace(cfg.plc, host="127.0.0.1", port=port))
    from config.sim import default_sim

    sim = default_sim()
    out_lock = threading.Lock()

    def say(obj: dict) -> None:
        with out_lock:
            sys.stdout.write(json.dumps(obj) + "\n")
            sys.stdout.flush()

    frames: dict = {}
    rig = load_rig(rig_path(cfg))
    plc = PlcClient.tcp("127.0.0.1", port, unit_id=cfg.plc.unit_id, timeout_s=cfg.plc.timeout_s,
                        regmap=RegisterMap.load(registers_path(cfg)),
                        backoff=Backoff(cfg.plc.backoff_initial_s, cfg.plc.backoff_max_s))
    channel = f"records-fault-{os.getpid()}"
    piezo = PiezoClient(can.Bus(interface="virtual", channel=channel), knives=4,
                        command_period_s=cfg.can.command_period_s,
                        offsets_period_s=cfg.can.offsets_period_s, stroke_um=cfg.stroke_um)
    amp_machine = Machine(sim, seed=3, render_images=False)
    amp = AmpNode(can.Bus(interface="virtual", channel=channel),
                  AmpNodeCore(amp_machine, knives=amp_machine.knives),
                  own_bus=True)
    service = Service(cfg, plc=plc, piezo=piezo, rig=rig, log=open_quality_log(log),
                      threaded=True, measurer_factory=lambda shape: truth_measurer(frames),
                      pairs_per_s=sim.camera.pairs_per_s)
    service.on_event = lambda e: say({"event": e.kind.value, "text": e.text})
    service.on_result = lambda r: say({"result": int(r.seq)})
    service.records.on_stored = lambda seq, at: say({"stored": int(seq)})

    async def main() -> None:
        loop = asyncio.get_running_loop()
        source = QueueFrameSource(maxsize=1000)
        stop = asyncio.Event()

        def take(frame: Any) -> None:
            frames[(frame.counts_a, frame.counts_b)] = frame
            source.put(frame)

        def read_frames() -> None:  # a thread: the plant's pairs, length-prefixed pickles
            stdin = sys.stdin.buffer
            while True:
                head = stdin.read(4)
                if len(head) < 4:
                    loop.call_soon_threadsafe(stop.set)
                    return
                frame = pickle.loads(stdin.read(struct.unpack("<I", head)[0]))
                loop.call_soon_threadsafe(take, frame)

        async def pump_amp() -> None:
            t0 = time.monotonic()
            while not stop.is_set():
                amp.pump(time.monotonic() - t0)
                await asyncio.sleep(0.005)

        async def displays() -> None:  # what planer serve, the web page and OPC UA read
            while not stop.is_set():
                service.status()
                await asyncio.sleep(STATUS_EVERY_S)

        threading.Thread(target=read_frames, daemon=True).start()
        pump = asyncio.create_task(pump_amp())
        shown = asyncio.create_task(displays())
        say({"ready": True})
        try:
            await service.run(source, stop=stop)
        finally:
            stop.set()
            await asyncio.gather(pump, shown, return_exceptions=True)
            service.close()
            amp.close()
            say({"closed": True})

    asyncio.run(main())
    os._exit(0)  # the stdin reader thread blocks in a read: no interpreter shutdown to wait for


# ------------------------------------------------------------------------------ the plant side
class _WatchedMachine:
    """The machine as the PLC server sees it, noting when each new heartbeat value arrives."""

    def __init__(self, machine: Any) -> None:
        self.machine = machine
        self.beats: list[float] = []

    def register_values(self) -> dict:
        return self.machine.register_values()

    def set_feed_setpoint(self, feed_mm_s: float) -> None:
        self.machine.set_feed_setpoint(feed_mm_s)

    def set_service_heartbeat(self, value: int) -> None:
        if value != self.machine.heartbeat_service:
            self.beats.append(time.monotonic())
        self.machine.set_service_heartbeat(value)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.machine, name)


@dataclass
class ServiceProcess:
    """What the service process said, as it said it (filled by a reader thread)."""

    proc: subprocess.Popen
    events: list[tuple[float, str, str]] = field(default_factory=list)
    results: list[int] = field(default_factory=list)
    stored: list[int] = field(default_factory=list)
    result_times: list[float] = field(default_factory=list)
    closed: bool = False
    cond: threading.Condition = field(default_factory=threading.Condition)

    def read(self) -> None:
        for raw in self.proc.stdout:  # type: ignore[union-attr]
            try:
                obj = json.loads(raw)
            except ValueError:
                continue
            with self.cond:
                now = time.monotonic()
                if "event" in obj:
                    self.events.append((now, obj["event"], obj["text"]))
                elif "result" in obj:
                    self.results.append(obj["result"])
                    self.result_times.append(now)
                elif "stored" in obj:
                    self.stored.append(obj["stored"])
                elif obj.get("closed"):
                    self.closed = True
                self.cond.notify_all()

    def wait(self, predicate, timeout_s: float, what: str) -> None:
        with self.cond:
            if not self.cond.wait_for(predicate, timeout_s):
                raise AssertionError(f"timed out waiting for {what}; events {self.events}")


class Plant:
    """The machine in real time, its PLC's Modbus server, and the service process."""

    def __init__(self, log: str, *, seed: int = 3) -> None:
        from config.sim import default_sim
        from plant_sim.machine.machine import Machine

        self.log = log
        self.machine = Machine(default_sim(), seed=seed, render_images=False)
        self.watched = _WatchedMachine(self.machine)
        self.server: Any = None
        self.service: ServiceProcess | None = None
        self._stop = asyncio.Event()
        self._outbox: list[bytes] = []
        self._out_cond = threading.Condition()

    async def start(self) -> None:
        from plant_sim.interfaces.plc_server import PlcServer

        self.server = PlcServer(self.watched, host="127.0.0.1", port=0)
        _, port = await self.server.start()
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        proc = subprocess.Popen(
            [sys.executable, "-m", "tests.controller.service.records.records_fault_harness",
             str(port), self.log], cwd=REPO, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            text=False)
        self.service = ServiceProcess(proc)
        threading.Thread(target=self.service.read, daemon=True).start()
        threading.Thread(target=self._send, daemon=True).start()
        self._stepper = asyncio.create_task(self._step())

    def _send(self) -> None:
        """A thread: the pairs to the service's stdin (never blocks the plant's loop)."""
        assert self.service is not None
        stdin = self.service.proc.stdin
        while True:
            with self._out_cond:
                self._out_cond.wait_for(lambda: self._outbox)
                batch, self._outbox[:] = list(self._outbox), []
            for blob in batch:
                if blob == b"":
                    with contextlib.suppress(OSError):
                        stdin.close()  # type: ignore[union-attr]
                    return
                try:
                    stdin.write(struct.pack("<I", len(blob)) + blob)  # type: ignore[union-attr]
                    stdin.flush()  # type: ignore[union-attr]
                except OSError:  # the service is gone
                    return

    async def _step(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            await asyncio.sleep(STEP_S)
            now = time.monotonic()
            dt, last = min(now - last, 0.05), now
            for frame in self.machine.advance(dt):
                blob = pickle.dumps(replace(frame, image_a=None, image_b=None))
                with self._out_cond:
                    self._outbox.append(blob)
                    self._out_cond.notify()
            self.server.refresh()

    def events_after(self, t0: float, kind: str) -> list[str]:
        assert self.service is not None
        with self.service.cond:
            return [text for t, k, text in self.service.events if t >= t0 and k == kind]

    async def wait(self, predicate, timeout_s: float, what: str) -> None:
        """Wait (in a thread: the plant keeps running) until the service said ``predicate``."""
        assert self.service is not None
        await asyncio.to_thread(self.service.wait, predicate, timeout_s, what)

    def max_gap_s(self, t0: float, t1: float) -> float:
        """Longest time between two heartbeats the PLC received within ``[t0, t1]``."""
        beats = [t for t in self.watched.beats if t0 <= t <= t1]
        assert len(beats) >= 2, "no heartbeats received"
        return max(b - a for a, b in zip(beats, beats[1:], strict=False))

    async def stop(self, *, timeout_s: float = 120.0) -> int:
        """End the pairs (the service stops and closes); its exit code."""
        with self._out_cond:
            self._outbox.append(b"")
            self._out_cond.notify()
        assert self.service is not None
        try:
            rc = await asyncio.to_thread(self.service.proc.wait, timeout_s)
        finally:
            await self.close()
        return rc

    def kill(self) -> None:
        """SIGKILL the service process."""
        assert self.service is not None
        self.service.proc.kill()
        self.service.proc.wait(60)

    async def close(self) -> None:
        self._stop.set()
        with contextlib.suppress(asyncio.CancelledError):
            await self._stepper
        if self.service is not None and self.service.proc.poll() is None:
            self.kill()
        with self._out_cond:
            self._outbox.append(b"")
            self._out_cond.notify()
        await self.server.stop()


if __name__ == "__main__":  # pragma: no cover - the service process
    _child(int(sys.argv[1]), sys.argv[2])
