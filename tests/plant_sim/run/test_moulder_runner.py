"""``planer sim`` over a moulder: the MoulderRunner wired from ``config/sim_moulder.toml``.

Real interfaces on simulated time: the PLC in its own process (Modbus TCP on 127.0.0.1, read by
the service's ``PlcClient`` over each head's view of the map), the four amplifier nodes on one
virtual CAN bus (the service's ``canopen`` master), each head's spool in a temporary folder. The
wall clock is a fake one that moves only when the runner sleeps; nothing waits for the world.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest

from config.sim import load_sim
from plant_sim.run.moulder_runner import MoulderRunner, runner_for
from plant_sim.run.runner import SimRunner, parse_banner
from protocol import can_transport
from protocol.piezo_canopen import NmtState
from protocol.spool import SpoolReader

HEADS = ("bottom", "right", "left", "top")
KNIVES = {"bottom": 4, "right": 2, "left": 2, "top": 6}
RPM = {"bottom": 6000.0, "right": 9000.0, "left": 9000.0, "top": 6000.0}
NODES = {"bottom": 2, "right": 3, "left": 4, "top": 5}
_channels = itertools.count()


class FakeClock:
    """Wall clock that moves only when the runner sleeps (simulated time)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now

    async def sleep(self, dt: float) -> None:
        self.now += dt
        await asyncio.sleep(0)


def moulder_cfg(tmp_path: Path, *, small_images: bool = False):
    """The shipped moulder on a free port, a virtual bus of its own, spools in ``tmp_path``."""
    cfg = load_sim("config/sim_moulder.toml")
    channel = f"moulder-runner-{next(_channels)}"
    cfg = dataclasses.replace(
        cfg,
        modbus=dataclasses.replace(cfg.modbus, port=0),
        can=dataclasses.replace(cfg.can, interface="virtual", channel=channel),
        frames=dataclasses.replace(cfg.frames, spool_dir=str(tmp_path / "spool"), keep=500),
    )
    if small_images:  # the same machine, cheaper images
        optics = dataclasses.replace(cfg.camera.optics, width=160, height=120)
        heads = tuple(dataclasses.replace(h, camera=dataclasses.replace(h.camera, optics=optics))
                      for h in cfg.heads)
        cfg = dataclasses.replace(cfg, declared_heads=heads, camera=dataclasses.replace(
            cfg.camera, optics=optics))
    return cfg


def spool_frames(folder: Path) -> list:
    reader = SpoolReader(folder, start="all")
    out = []
    while (f := reader.poll()) is not None:
        out.append(f)
    return out


def every_node_started(amps) -> bool:
    """Every node operational and its limits read (the master's view): what the service drives.

    Operational alone is not it: a node heard again after its heartbeat was lost (this file's
    ``can_silence``) is read anew by SDO while it stays operational, its limits ``None`` for
    those few cycles (the service's bound is zero meanwhile: ``test_piezo_client.py``,
    ``test_limits_are_read_anew_after_a_reconnect``).
    """
    return all(a.nmt_state is NmtState.OPERATIONAL and a.limits is not None
               for a in amps.values())


async def until(cond, runner, *, limit_s: float, what: str) -> None:
    """Yield to the runner until ``cond()``; fails past ``limit_s`` of machine time."""
    while not cond():
        if runner.machine.t_s > limit_s:
            raise AssertionError(f"{what}: not by t={limit_s} s of machine time")
        await asyncio.sleep(0)


def test_a_moulder_file_needs_the_moulder_runner(tmp_path):
    cfg = moulder_cfg(tmp_path)
    with pytest.raises(ValueError, match=r"SimRunner runs one machine.*MoulderRunner"):
        SimRunner.from_config(cfg, render_images=False, out=None)


@pytest.mark.parametrize("heads", ["one", "moulder"])
def test_a_failed_wiring_closes_the_bus_it_opened_one_head_or_several(tmp_path, monkeypatch,
                                                                       heads):
    """One wiring for both: the spool folder unusable, the bus opened for it is shut down."""
    from config.sim import default_sim
    from plant_sim.run import wiring

    cfg = moulder_cfg(tmp_path) if heads == "moulder" else dataclasses.replace(
        default_sim(), modbus=dataclasses.replace(default_sim().modbus, port=0),
        can=dataclasses.replace(default_sim().can, interface="virtual",
                                channel=f"moulder-runner-{next(_channels)}"))
    opened = []

    def bus_from_config(can_cfg):
        opened.append(can_transport.bus_from_config(can_cfg))
        return opened[-1]

    monkeypatch.setattr(wiring, "bus_from_config", bus_from_config)
    (tmp_path / "a_file").write_text("not a folder")
    with pytest.raises(OSError):
        runner_for(cfg, render_images=False, spool_dir=tmp_path / "a_file" / "spool", out=None)
    assert len(opened) == 1 and opened[0]._is_shutdown  # python-can's own flag


def test_a_single_head_file_is_wired_as_before(tmp_path):
    from config.sim import default_sim

    cfg = default_sim()
    cfg = dataclasses.replace(
        cfg, modbus=dataclasses.replace(cfg.modbus, port=0),
        can=dataclasses.replace(cfg.can, interface="virtual", channel="moulder-runner-single"),
        frames=dataclasses.replace(cfg.frames, spool_dir=str(tmp_path / "spool")))
    runner = runner_for(cfg, render_images=False, out=None)
    try:
        assert type(runner) is SimRunner
        assert runner.sink.directory == tmp_path / "spool"
    finally:
        asyncio.run(runner.close())


def test_every_head_served_on_modbus_can_and_its_own_spool(tmp_path):
    """The moulder in the runner: each head's PLC block (its own spindle), the top head's
    setpoint written over Modbus, each node answering SDO and heartbeat on its own id, a CAN
    fault addressed to one head, every head's pairs in its own spool."""
    from controller.fieldbus.canopen_amp import AmpBus
    from controller.fieldbus.plc_client import PlcClient

    cfg = moulder_cfg(tmp_path)
    clock, lines = FakeClock(), []
    runner = runner_for(cfg, seed=2, render_images=False, clock=clock,
                                   sleep=clock.sleep, out=lines.append, progress_every_s=1.0,
                                   realtime_interfaces=False)
    assert isinstance(runner, MoulderRunner)
    assert {n: s.directory for n, s in runner.sinks.items()} == {
        n: tmp_path / "spool" / n for n in HEADS}
    runner.schedule(1.0, "can_silence", head="left", duration_s=0.5)
    master = AmpBus(can_transport.open_bus("virtual", cfg.can.channel), sdo_wait_s=0.0)
    amps = {n: master.amplifier(NODES[n], knives=KNIVES[n]) for n in HEADS}
    seen: dict[str, object] = {}

    async def service() -> None:
        await until(lambda: runner.plc.running, runner, limit_s=60.0, what="Modbus up")
        port = runner.plc.port
        clients = {n: PlcClient.tcp("127.0.0.1", port, head=i) for i, n in enumerate(HEADS)}
        try:
            def nodes_up() -> bool:
                master.poll(runner.machine.t_s)
                return every_node_started(amps)

            await until(nodes_up, runner, limit_s=60.0, what="every node read and started")
            seen["limits"] = {n: a.limits for n, a in amps.items()}
            seen["before"] = {n: (await c.read()).values for n, c in clients.items()}
            await clients["top"].write_spindle_setpoint(8000.0)
            top = runner.machine.heads["top"]
            await until(lambda: top.spindle.setpoint_rpm == 8000.0, runner, limit_s=60.0,
                        what="the top head's setpoint applied")
            seen["after"] = {n: (await c.read()).values for n, c in clients.items()}
            await until(lambda: min(runner.frames_by_head.values()) >= 2, runner,
                        limit_s=60.0, what="pairs from every head")
            nodes_up()
            seen["heartbeats"] = {n: a.counts["heartbeats"] for n, a in amps.items()}
        finally:
            for c in clients.values():
                c.close()
            runner.request_stop()

    async def main():
        return (await asyncio.gather(runner.run(), service()))[0]

    try:
        summary = asyncio.run(main())
    finally:
        master.close()
    before, after = seen["before"], seen["after"]
    for n in HEADS:  # each head's own block
        assert before[n]["knives"] == KNIVES[n]
        assert before[n]["spindle_rpm"] == pytest.approx(RPM[n], rel=0.01)
        assert before[n]["spindle_setpoint_rpm"] == RPM[n]
    assert [before[n]["spindle_rpm_min"] for n in HEADS] == [6000.0, 9000.0, 9000.0, 4000.0]
    assert [before[n]["spindle_rpm_max"] for n in HEADS] == [6000.0, 9000.0, 9000.0, 8000.0]
    assert after["top"]["spindle_setpoint_rpm"] == 8000.0
    assert all(after[n]["spindle_setpoint_rpm"] == RPM[n] for n in HEADS[:3])
    assert runner.machine.heads["top"].spindle_rpm > 6000.0  # it ran up towards 8000
    # each node read by SDO and started on its own id; every node's heartbeats heard
    assert all(seen["limits"][n] is not None and seen["limits"][n].stroke_um > 0 for n in HEADS)
    assert all(seen["heartbeats"][n] > 0 for n in HEADS)
    assert master.counts["foreign"] == 0 and runner.amp.core.refused == 0
    assert summary.faults == ["can_silence[left]@1.000"]
    # every head's pairs, in its own spool, in order
    assert summary.frames_by_head == runner.frames_by_head
    for n in HEADS:
        frames = spool_frames(tmp_path / "spool" / n)
        assert len(frames) == summary.frames_by_head[n] >= 2
        assert [f.seq for f in frames] == sorted(f.seq for f in frames)
        assert frames[0].image_a is None  # no images asked for
    banner = parse_banner(lines)
    assert banner["heads"] == ", ".join(HEADS)
    assert banner["frames"] == f"spool {tmp_path / 'spool'}/<head> keep 500"
    assert [line.split(":")[0] for line in lines if line.startswith("head ")] == [
        f"head {n}" for n in HEADS]
    assert "head top: face top, node 5, block 3" in "\n".join(lines)
    progress = [line for line in lines if line.startswith("t=")]
    assert progress and "spindle bottom=" in progress[0] and "frames bottom=" in progress[0]


def test_a_node_is_started_once_read_even_when_heard_again_while_operational():
    """The ordering that made the test above fail under load, forced on simulated time.

    The runner's nodes answer SDO from a receiving thread: on a loaded machine the six reads
    of a node may take most of a second of machine time (asked again after each 0.1 s
    time-out), so the left head's ``can_silence`` at 1.0 s can find it just started. Here,
    in lockstep: node 3 is read and started, then silent for 0.5 s (lost after 0.3 s); node
    2 is read only near the end of the silence, so its first operational heartbeat comes
    with node 3's first one after it. Node 3, heard again, is read anew while it stays
    operational: every node reads OPERATIONAL while its limits are ``None``. Started is
    operational *and* read (:func:`every_node_started`).
    """
    import can

    from config.sim import default_sim
    from controller.fieldbus.canopen_amp import AmpBus
    from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
    from plant_sim.machine.machine import Machine

    channel = f"moulder-runner-{next(_channels)}"
    machines = [Machine(default_sim(), seed=i, render_images=False) for i in range(2)]
    core = AmpNodeCore(machines[0], knives=4, node_id=2)
    core.add_node(3, machines[1], knives=4)
    sim = AmpNode(can.Bus(interface="virtual", channel=channel), core, own_bus=True)
    master = AmpBus(can.Bus(interface="virtual", channel=channel), sdo_wait_s=0.0)
    amps = {2: master.amplifier(2), 3: master.amplifier(3)}
    core.inject("silence", node_id=3, start_s=0.5, duration_s=0.5)
    operational_unread, started_at, limits_then = [], None, {}
    try:
        for i in range(1, 151):  # 10 ms steps
            t = i * 0.01
            for m in machines:
                m.advance(0.01)
            sim.pump(t)
            master.poll(t, only=3 if t < 0.9 else None)  # node 2 read from 0.9 s on
            if all(a.nmt_state is NmtState.OPERATIONAL for a in amps.values()):
                operational_unread += [n for n, a in amps.items() if a.limits is None]
            if started_at is None and every_node_started(amps):
                started_at, limits_then = t, {n: a.limits for n, a in amps.items()}
    finally:
        sim.close()
        master.close()
    # the ordering happened: node 3 lost, heard again operational, read anew meanwhile
    assert amps[3].restarts == 1 and amps[3].limits_read == 2 and amps[2].limits_read == 1
    assert 3 in operational_unread
    assert started_at is not None and started_at > 1.0  # once node 3 was read again
    assert all(lim is not None and lim.stroke_um > 0 for lim in limits_then.values())


def test_each_heads_images_are_rendered_as_the_moulder_renders_them(tmp_path):
    """With images: one render worker per head writes that head's spool, pair for pair the
    images the in-process moulder renders (its camera, its seed)."""
    from plant_sim.machine.moulder import Moulder

    cfg = moulder_cfg(tmp_path, small_images=True)
    clock = FakeClock()
    runner = runner_for(cfg, seed=4, render_images=True, render_workers=4,
                                   clock=clock, sleep=clock.sleep, out=None,
                                   realtime_interfaces=False, render_nice=None)
    assert all(r.workers == 1 for r in runner.renders.values())
    summary = asyncio.run(runner.run(duration_s=3.0))
    own = Moulder(cfg, seed=4, render_images=True)
    expect: dict[str, list] = {n: [] for n in HEADS}
    while own.t_s < runner.machine.t_s - 1e-9:
        for n, f in own.advance(cfg.run.step_s):
            expect[n].append(f)
    for n in HEADS:
        got = spool_frames(tmp_path / "spool" / n)
        assert len(got) == summary.frames_by_head[n] == len(expect[n]) >= 1, n
        for a, b in zip(expect[n], got, strict=True):
            assert a.seq == b.seq and a.counts_b == b.counts_b
            assert np.array_equal(a.image_a, b.image_a) and np.array_equal(a.image_b, b.image_b)
    first = [spool_frames(tmp_path / "spool" / n)[0].image_a for n in ("bottom", "right")]
    assert not np.array_equal(*first)  # heads do not share their images


def test_sinks_and_renders_must_name_every_head(tmp_path):
    from plant_sim.machine.moulder import Moulder

    cfg = moulder_cfg(tmp_path)
    m = Moulder(cfg, seed=0, render_images=False)
    with pytest.raises(ValueError, match="sinks must name every head"):
        MoulderRunner(m, sinks={"bottom": None})
    with pytest.raises(TypeError, match="not sink="):
        MoulderRunner(m, sinks=dict.fromkeys(HEADS), sink=None)


def test_the_shipped_moulder_spools_are_where_the_service_looks():
    """Head ``name`` of sim_moulder.toml writes ``<spool_dir>/<name>``: the spool the service
    of machine_moulder.toml reads for that head."""
    from config.machine import head_config, load_machine

    sim = load_sim("config/sim_moulder.toml")
    machine = load_machine("config/machine_moulder.toml")
    assert [h.name for h in machine.heads] == [h.name for h in sim.heads]
    assert [h.node_id for h in machine.heads] == [h.node_id for h in sim.heads]
    for h in sim.heads:
        assert head_config(machine, h.name).frames.spool_dir == Path(sim.frames.spool_dir) / h.name


def test_planer_sim_runs_the_moulder_and_names_its_heads(tmp_path):
    """``planer sim --config config/sim_moulder.toml``: the banner names the heads and their
    spools, SIGTERM stops it with each head's pairs counted."""
    import signal
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[3]
    proc = subprocess.Popen(
        [sys.executable, "-m", "planer.cli", "sim", "--config", "config/sim_moulder.toml",
         "--port", "0", "--no-images", "--no-realtime", "--spool", str(tmp_path / "spool"),
         "--time-scale", "5"],
        cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line.strip())
            if line.strip() == "ready":
                break
        banner = parse_banner(lines)
        assert banner["heads"] == ", ".join(HEADS)
        assert banner["frames"] == f"spool {tmp_path / 'spool'}/<head> keep 50"
        assert int(banner["modbus"].rsplit(":", 1)[1]) > 0
        assert f"head bottom: face bottom, node 2, block 0, spool {tmp_path / 'spool'}/bottom" \
            in lines[lines.index("heads: " + banner["heads"]) + 1]
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    stopped = [line for line in out.splitlines() if line.startswith("stopped at t=")]
    assert len(stopped) == 1
    assert "(bottom " in stopped[0] and ", top " in stopped[0]
