"""The ``planer sim`` runner on simulated time, and the frame spool's atomic hand-off."""

from __future__ import annotations

import asyncio
import dataclasses
import importlib.util
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
from plant_sim.interfaces.plc_server import PlcServer
from plant_sim.run.runner import SimRunner, parse_banner
from protocol import can_transport
from protocol.frame_queue import InProcessSource
from protocol.frames import Frame
from protocol.registers import RegisterMap
from protocol.spool import SpoolReader, SpoolWriter
from tests.support import canopen_frames
from tests.support.fake_machine import FakeMachine

REPO = Path(__file__).resolve().parents[2]
RMAP = RegisterMap.load()
HAVE_MACHINE = importlib.util.find_spec("plant_sim.machine.machine") is not None


class FakeClock:
    """Wall clock that moves only when the runner sleeps (simulated time)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.slept: list[float] = []

    def __call__(self) -> float:
        return self.now

    async def sleep(self, dt: float) -> None:
        assert dt >= 0
        self.slept.append(dt)
        self.now += dt
        await asyncio.sleep(0)


def _runner(
    machine,
    clock,
    *,
    time_scale=1.0,
    step_s=0.001,
    sink=None,
    channel="run-0",
    lines=None,
    plc=True,
):
    bus = can_transport.open_bus("virtual", channel)
    amp = AmpNode(bus, AmpNodeCore(machine, knives=machine.knives), own_bus=True)
    return SimRunner(
        machine,
        plc=PlcServer(machine, port=0) if plc else None,
        amp=amp,
        sink=sink,
        time_scale=time_scale,
        step_s=step_s,
        clock=clock,
        sleep=clock.sleep,
        out=(lines.append if lines is not None else None),
        progress_every_s=0.1,
    )


@pytest.mark.parametrize("time_scale", [1.0, 4.0, 0.5])
def test_machine_time_follows_scaled_clock(time_scale):
    m, clock, lines = FakeMachine(), FakeClock(), []
    sink = InProcessSource(maxlen=100)
    runner = _runner(
        m, clock, time_scale=time_scale, sink=sink, lines=lines, channel=f"run-{time_scale}"
    )
    summary = asyncio.run(runner.run(duration_s=0.5))
    assert m.t_s == pytest.approx(0.5, abs=1e-9)
    assert summary.steps == 500
    # wall (fake) time spent = machine time / time_scale, to within one step
    assert summary.wall_time_s == pytest.approx(0.5 / time_scale, abs=0.001 / time_scale + 1e-9)
    assert summary.real_time_factor == pytest.approx(time_scale, rel=0.01)
    frames = [sink.poll() for _ in range(len(sink))]
    assert [f.seq for f in frames] == [1, 2, 3, 4, 5] and summary.frames == 5
    assert summary.can_sent == 1 + 5  # no master starts it: boot-up, heartbeat every 100 ms
    banner = parse_banner(lines)
    assert banner["modbus"] == f"127.0.0.1:{runner.plc.port}"
    assert banner["can"] and banner["frames"] == "in-process"
    assert lines.index("ready") == 3
    assert sum(line.startswith("t=") for line in lines) == 5
    assert not runner.plc.running


def test_modbus_and_can_served_while_running():
    """A client in the same loop writes a setpoint and sends offsets while the machine runs."""
    from pymodbus.client import AsyncModbusTcpClient

    m, clock = FakeMachine(), FakeClock()
    runner = _runner(m, clock, step_s=0.01, channel="run-io")
    service_bus = can_transport.open_bus("virtual", "run-io")

    async def client():
        while not runner.plc.running:
            await asyncio.sleep(0)
        c = AsyncModbusTcpClient("127.0.0.1", port=runner.plc.port, timeout=2)
        await c.connect()
        words = RMAP.encode("feed_setpoint_mm_s", 432.5)
        rr = await c.write_registers(RMAP["feed_setpoint_mm_s"].address, words, device_id=1)
        assert not rr.isError()
        hb = []
        for _ in range(3):
            r = await c.read_holding_registers(RMAP["heartbeat_plc"].address, count=1, device_id=1)
            hb.append(r.registers[0])
            await asyncio.sleep(0.01)
        c.close()
        import can

        for fid, data in [  # the amplifier is a CANopen node: started, then commanded
            canopen_frames.start(),
            canopen_frames.command(True, 4, 9),
            *canopen_frames.offsets([1.0, 2.0, 3.0, 4.0]),
        ]:
            service_bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        while m.alive_counters != [9] or list(m.offsets_um) != [1.0, 2.0, 3.0, 4.0]:
            await asyncio.sleep(0)
        runner.request_stop()
        return hb

    async def main():
        return await asyncio.gather(runner.run(duration_s=1000.0), client())

    summary, hb = asyncio.run(main())
    service_bus.shutdown()
    assert m.feed_setpoint == 432.5
    assert hb == sorted(hb) and hb[-1] > hb[0]  # the PLC heartbeat moves between reads
    assert summary.modbus_requests >= 4 and summary.modbus_refused == 0
    assert 0 < m.t_s < 1000.0


def test_from_config_plays_the_interface_faults_the_machine_hands_over(tmp_path):
    from config.sim import default_sim

    cfg = default_sim()
    cfg = dataclasses.replace(
        cfg,
        modbus=dataclasses.replace(cfg.modbus, port=0),
        can=dataclasses.replace(cfg.can, interface="virtual", channel="run-faults"),
        frames=dataclasses.replace(cfg.frames, spool_dir=str(tmp_path / "spool"), keep=3),
    )
    m, clock, lines = FakeMachine(knives=cfg.cutterhead.knives), FakeClock(), []
    m.inject("modbus_restart", at_s=0.2, duration_s=0.1)
    m.inject("can_silence", at_s=0.4, duration_s=0.1)
    m.inject("belt_slip", at_s=0.1, px=3)  # the machine's own: left to it
    runner = SimRunner.from_config(
        cfg, machine=m, clock=clock, sleep=clock.sleep, out=lines.append, progress_every_s=10.0
    )
    up: list[tuple[float, bool]] = []
    orig_step = runner._step

    def spy():
        orig_step()
        up.append((m.t_s, runner.plc.running))

    runner._step = spy
    import can

    master = can_transport.open_bus("virtual", "run-faults")
    fid, data = canopen_frames.start()  # the amplifier starts sending its status
    master.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
    summary = asyncio.run(runner.run(duration_s=0.7))
    master.shutdown()
    assert summary.faults == ["modbus_restart@0.200", "can_silence@0.400"]
    assert m.injected == [("belt_slip", {"at_s": 0.1, "px": 3})]
    down = [t for t, running in up if not running]
    assert down and min(down) == pytest.approx(0.201, abs=1e-6)
    assert max(down) == pytest.approx(0.300, abs=1e-6)
    assert any("down at t=0.200" in line for line in lines)
    assert summary.can_sent == 1 + 70 + 7 - 10 - 1  # boot-up; 100 ms of silence: 10 + 1 fewer
    spool = sorted(p.name for p in (tmp_path / "spool").iterdir())
    assert spool == [f"pair-{k:012d}.{s}" for k in (4, 5, 6) for s in ("a.png", "b.png", "json")]


# ---------------------------------------------------------------------------------- spool
def _frame(seq: int, dtype=np.uint8, shape=(6, 10)) -> Frame:
    rng = np.random.default_rng(seq)
    if np.issubdtype(dtype, np.integer):
        hi = np.iinfo(dtype).max
        a = rng.integers(0, hi, shape, endpoint=True).astype(dtype)
        b = rng.integers(0, hi, shape, endpoint=True).astype(dtype)
    else:
        a, b = rng.random(shape).astype(dtype), rng.random(shape).astype(dtype)
    return Frame(
        seq=seq,
        t_s=seq * 0.1,
        image_a=a,
        image_b=b,
        counts_a=2**32 - 5 + seq,
        counts_b=seq * 7,
        speed_mm_s=812.5,
        index_latch_counts=-3 + seq,
        board_id=42,
        board_position_mm=1234.5,
        truth={
            "pitch_mm": np.float64(1.5),
            "mark_widths_mm": np.array([1.0, 2.0]),
            "cv": float("nan"),
        },
    )


def _same(f: Frame, g: Frame) -> None:
    for k in (
        "seq",
        "t_s",
        "counts_a",
        "counts_b",
        "speed_mm_s",
        "index_latch_counts",
        "board_id",
        "board_position_mm",
    ):
        assert getattr(f, k) == getattr(g, k), k
    for k in ("image_a", "image_b"):
        a, b = getattr(f, k), getattr(g, k)
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), k


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_spool_round_trip_lossless_in_order(tmp_path, dtype):
    w = SpoolWriter(tmp_path, keep=10, fsync=False)
    r = SpoolReader(tmp_path)
    frames = [_frame(s, dtype) for s in range(1, 5)]
    for f in frames:
        w.write(f)
    got = [r.poll() for _ in range(4)]
    assert r.poll() is None
    for f, g in zip(frames, got, strict=True):
        _same(f, g)
        assert g.truth == {"pitch_mm": 1.5, "mark_widths_mm": [1.0, 2.0], "cv": None}
    ext = ".npy" if dtype == np.float32 else ".png"
    assert (tmp_path / f"pair-000000000000.a{ext}").exists()


@pytest.mark.parametrize("crash_after_replaces", [0, 1, 2])
def test_half_written_pair_is_never_returned(tmp_path, monkeypatch, crash_after_replaces):
    w = SpoolWriter(tmp_path, keep=10, fsync=False)
    r = SpoolReader(tmp_path, start="all")
    w.write(_frame(1))
    calls = {"n": 0}
    real_replace = os.replace

    def crashing_replace(src, dst):
        if calls["n"] == crash_after_replaces:
            raise KeyboardInterrupt("killed mid-write")
        calls["n"] += 1
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", crashing_replace)
    with pytest.raises(KeyboardInterrupt):
        w.write(_frame(2))
    monkeypatch.setattr(os, "replace", real_replace)
    assert r.poll().seq == 1
    assert r.poll() is None  # the torn pair 2 is invisible
    # a restarted writer removes the leftovers and continues the slot numbers
    w2 = SpoolWriter(tmp_path, keep=10, fsync=False)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]
    assert w2.next_slot == 1
    w2.write(_frame(3))
    g = r.poll()
    assert g is not None and g.seq == 3 and r.poll() is None and r.skipped <= 1


WRITER_SCRIPT = textwrap.dedent(
    """
    import sys, numpy as np
    from protocol.frames import Frame
    from protocol.spool import SpoolWriter
    w = SpoolWriter(sys.argv[1], keep=1000, fsync=True)
    rng = np.random.default_rng(0)
    seq = 0
    while True:
        seq += 1
        img = rng.integers(0, 255, (200, 300), endpoint=True).astype(np.uint8)
        w.write(Frame(seq=seq, t_s=seq * 0.1, image_a=img, image_b=255 - img,
                      counts_a=seq, counts_b=seq + 1, speed_mm_s=1.0))
    """
)


def test_killing_the_writer_loses_nothing_committed(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", WRITER_SCRIPT, str(tmp_path)], cwd=REPO)
    reader = SpoolReader(tmp_path, start="all")
    seen = []
    deadline = time.monotonic() + 20.0
    try:
        while len(seen) < 8 and time.monotonic() < deadline:
            f = reader.poll()
            if f is None:
                time.sleep(0.002)
                continue
            seen.append(f)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    assert len(seen) >= 8
    # everything committed before the kill is complete and readable, in order, no gaps
    while (f := reader.poll()) is not None:
        seen.append(f)
    committed = sorted(tmp_path.glob("pair-*.json"))
    assert [f.seq for f in seen] == list(range(1, len(committed) + 1))
    assert reader.skipped == 0
    for f in seen:
        assert np.array_equal(f.image_a.astype(int) + f.image_b, np.full((200, 300), 255))
    for p in committed:
        meta = json.loads(p.read_text())
        assert (tmp_path / meta["image_a"]).exists() and (tmp_path / meta["image_b"]).exists()


def test_pruning_keeps_the_newest_and_reader_follows(tmp_path):
    w = SpoolWriter(tmp_path, keep=3, fsync=False)
    r = SpoolReader(tmp_path)
    for s in range(1, 11):
        w.write(_frame(s))
    assert len(list(tmp_path.glob("pair-*.json"))) == 3
    assert len(list(tmp_path.iterdir())) == 9
    assert [r.poll().seq for _ in range(3)] == [8, 9, 10] and r.poll() is None


def test_reader_start_new_skips_backlog_and_follows_a_writer_restarted_on_empty_dir(tmp_path):
    w = SpoolWriter(tmp_path, keep=10, fsync=False)
    for s in range(1, 4):
        w.write(_frame(s))
    r_new, r_all = SpoolReader(tmp_path), SpoolReader(tmp_path, start="all")
    assert r_new.poll() is None
    assert [r_all.poll().seq for _ in range(3)] == [1, 2, 3]
    w.write(_frame(4))
    assert r_new.poll().seq == 4
    for p in tmp_path.iterdir():
        p.unlink()
    w2 = SpoolWriter(tmp_path, keep=10, fsync=False)  # numbering starts again at 0
    w2.write(_frame(1))
    assert r_new.poll().seq == 1 and r_new.poll() is None


def test_frames_without_images_carry_metadata_only(tmp_path):
    w, r = SpoolWriter(tmp_path, keep=5, fsync=False), SpoolReader(tmp_path)
    w.write(dataclasses.replace(_frame(7), image_a=None, image_b=None))
    g = r.poll()
    assert g.seq == 7 and g.image_a is None and g.image_b is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pair-000000000000.json"]


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="keep"):
        SpoolWriter(tmp_path, keep=0)
    with pytest.raises(ValueError, match="start"):
        SpoolReader(tmp_path, start="old")
    with pytest.raises(ValueError, match="image_a"):
        SpoolWriter(tmp_path).write(dataclasses.replace(_frame(1), image_a=np.zeros((2, 3, 3))))


def test_in_process_source_drops_oldest_when_full():
    src = InProcessSource(maxlen=3)
    assert src.poll() is None
    for s in range(1, 6):
        src.put(_frame(s))
    assert src.dropped == 2
    assert [src.poll().seq for _ in range(3)] == [3, 4, 5] and src.poll() is None


# ---------------------------------------------------------------------------------- the CLI
@pytest.mark.skipif(not HAVE_MACHINE, reason="plant_sim.machine.machine not available yet")
def test_planer_sim_cli_prints_where_it_listens_and_stops_on_sigterm(tmp_path):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "planer.cli",
            "sim",
            "--port",
            "0",
            "--no-images",
            "--spool",
            str(tmp_path / "spool"),
            "--time-scale",
            "5",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line.strip())
            if line.strip() == "ready":
                break
        banner = parse_banner(lines)
        host, port = banner["modbus"].rsplit(":", 1)
        assert host == "127.0.0.1" and int(port) > 0
        assert banner["can"].startswith("virtual")
        assert banner["frames"].startswith("spool ")
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped at t=" in out


def _cfg_for(tmp_path, channel):
    from config.sim import default_sim

    cfg = default_sim()
    return dataclasses.replace(
        cfg,
        modbus=dataclasses.replace(cfg.modbus, port=0),
        can=dataclasses.replace(cfg.can, interface="virtual", channel=channel),
        frames=dataclasses.replace(cfg.frames, spool_dir=str(tmp_path / "spool")),
    )


def _unclosed(caplog) -> list[str]:
    import gc

    gc.collect()
    return [r.getMessage() for r in caplog.records if "not properly shut down" in r.getMessage()]


def test_start_up_failures_close_the_can_bus(tmp_path, caplog):
    """Modbus cannot listen, or the spool folder is unusable: no bus is left open."""
    import socket

    from core.errors import FieldbusError

    cfg = _cfg_for(tmp_path, "run-startfail")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        runner = SimRunner.from_config(cfg, machine=FakeMachine(knives=cfg.cutterhead.knives),
                                       modbus_port=port, out=None)
        with pytest.raises(FieldbusError):
            asyncio.run(runner.run(duration_s=0.1))
    assert runner.amp.bus._is_shutdown  # python-can's own flag
    (tmp_path / "a_file").write_text("not a folder")
    with pytest.raises(OSError):
        SimRunner.from_config(cfg, machine=FakeMachine(knives=cfg.cutterhead.knives),
                              spool_dir=tmp_path / "a_file" / "spool", out=None)
    del runner
    assert _unclosed(caplog) == []
