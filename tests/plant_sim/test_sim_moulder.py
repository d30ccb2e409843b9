"""The simulated moulder: four heads, each its own machine, on one feed (sim_moulder.toml)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from config.sim import FaultSpec, default_sim, load_sim
from plant_sim.machine.machine import Machine
from plant_sim.machine.moulder import Moulder, head_seed
from protocol.frames import Frame
from protocol.registers import HeadFault, MachineState, PlcFault

FEED_MM_S = 600.0
# the design's heads: knives, rpm, position along the feed
HEADS = {"bottom": (4, 6000.0, 0.0), "right": (2, 9000.0, 400.0), "left": (2, 9000.0, 700.0),
         "top": (6, 6000.0, 1100.0)}


@pytest.fixture(scope="module")
def cfg():
    return load_sim("config/sim_moulder.toml")


def _run(m: Moulder, seconds: float, step_s: float = 0.05) -> dict[str, list[Frame]]:
    out: dict[str, list[Frame]] = {n: [] for n in m.names}
    for _ in range(round(seconds / step_s)):
        for name, fr in m.advance(step_s):
            out[name].append(fr)
    return out


def _key(fr: Frame) -> tuple:
    return (fr.seq, fr.t_s, fr.counts_a, fr.counts_b, fr.index_latch_counts, fr.board_id,
            fr.board_position_mm, fr.speed_mm_s, repr(sorted((fr.truth or {}).items())))


def test_the_moulder_file_builds_four_heads_on_one_feed(cfg):
    m = Moulder(cfg, seed=1, render_images=False)
    assert m.names == tuple(HEADS) and m.head_count == 4
    assert m.node_ids == {"bottom": 2, "right": 3, "left": 4, "top": 5}
    assert m.positions_mm == {n: v[2] for n, v in HEADS.items()}
    machines = list(m.heads.values())
    assert all(h.feed is m.owner.feed and h.encoder is m.owner.encoder for h in machines)
    assert [h.owns_feed for h in machines] == [True, False, False, False]
    assert [h.knives for h in machines] == [v[0] for v in HEADS.values()]
    assert len({h.seed for h in machines}) == 4 and machines[0].seed == 1
    assert machines[1].seed == head_seed(1, 1)


def test_every_head_sees_the_same_feed_and_cuts_its_own_pitch(cfg):
    m = Moulder(cfg, seed=2, render_images=False)
    frames = _run(m, 6.0)
    assert m.feed_speed_mm_s == pytest.approx(FEED_MM_S)
    positions = {h.feed_position_mm for h in m.heads.values()}
    speeds = {h.feed_speed_mm_s for h in m.heads.values()}
    assert len(positions) == 1 and len(speeds) == 1  # one feed under all
    # pairs taken at one instant by two heads saw one feed speed and one encoder count
    by_time: dict[float, set] = {}
    for fs in frames.values():
        for fr in fs:
            by_time.setdefault(fr.t_s, set()).add((fr.speed_mm_s, fr.counts_a))
    together = [t for t, v in by_time.items()
                if sum(1 for fs in frames.values() for fr in fs if fr.t_s == t) > 1]
    assert len(together) > 10  # the heads' cameras trigger on one clock
    assert all(len(by_time[t]) == 1 for t in together)
    for name, (z, rpm, _) in HEADS.items():
        truth = [fr.truth["pitch_mm"] for fr in frames[name][-10:]]
        want = FEED_MM_S / (rpm / 60.0 * z)  # V / (n Z) of its own spindle
        assert np.mean(truth) == pytest.approx(want, rel=0.01), name
        assert m.pitch_mm(name) == pytest.approx(want, rel=0.01), name
        assert m.truth()[name]["last_pitch_mm"] == truth[-1]


def test_the_variable_head_follows_its_setpoint_and_the_fixed_ones_refuse(cfg):
    m = Moulder(cfg, seed=3, render_images=False)
    _run(m, 1.0)
    m.set_spindle_setpoint(3, 8000.0)
    assert m.head_register_values(3)["spindle_setpoint_rpm"] == 8000.0
    frames = _run(m, 6.0)
    top = m.head_register_values(3)
    assert top["spindle_rpm"] == pytest.approx(8000.0, rel=0.005)
    assert (top["spindle_rpm_min"], top["spindle_rpm_max"]) == (4000.0, 8000.0)
    pitch = np.mean([fr.truth["pitch_mm"] for fr in frames["top"][-10:]])
    assert pitch == pytest.approx(FEED_MM_S / (8000.0 / 60.0 * 6), rel=0.01)
    for i, name in enumerate(("bottom", "right", "left")):  # the others run on unchanged
        assert m.head_register_values(i)["spindle_rpm"] == pytest.approx(HEADS[name][1],
                                                                          rel=0.005)
        with pytest.raises(ValueError, match="rpm must be in"):
            m.set_spindle_setpoint(i, 8000.0)
    with pytest.raises(ValueError, match="rpm must be in"):
        m.set_spindle_setpoint(3, 8100.0)
    with pytest.raises(ValueError, match="i must be"):
        m.set_spindle_setpoint(4, 6000.0)


def test_a_board_reaches_each_head_later_by_its_position(cfg):
    m = Moulder(cfg, seed=4, render_images=False)
    frames = _run(m, 5.0)
    cpm = cfg.encoder.counts_per_mm
    lead_at_camera = {}
    for name in m.names:
        fr = next(f for f in frames[name] if f.board_id == 1)
        # the feed travel at which board 1's leading end passed the head's camera
        lead_at_camera[name] = fr.counts_a / cpm - fr.board_position_mm
    cam = {h.name: h.camera.cutter_to_camera_mm for h in m.head_configs}
    b = cfg.board
    for name, (_, _, pos) in HEADS.items():
        assert lead_at_camera[name] == pytest.approx(b.first_at_mm + pos + cam[name],
                                                     abs=1.0 / cpm + 1e-6), name
    # the top head's first pair of the board comes later than the bottom's by ~1100 mm of feed
    first = {n: next(f.t_s for f in frames[n] if f.board_id == 1) for n in m.names}
    assert first["top"] - first["bottom"] == pytest.approx(1100.0 / FEED_MM_S, abs=0.1 + 1e-9)


def test_a_fault_on_one_head_changes_only_that_head(cfg):
    ref = _run(Moulder(cfg, seed=5, render_images=False), 4.0)
    m = Moulder(cfg, seed=5, render_images=False)
    m.inject("knife_chip", head="right", knife=1, step_um=20.0, at_s=1.0)
    m.inject("piezo_fault", head="left", at_s=1.5)
    m.inject("measurement_dropout", head="top", fraction=1.0, duration_s=10.0, at_s=2.0)
    got = _run(m, 4.0)
    assert [_key(f) for f in got["bottom"]] == [_key(f) for f in ref["bottom"]]
    late = [f for f in got["right"] if f.t_s > 2.5]
    ref_late = [f for f in ref["right"] if f.t_s > 2.5]
    assert late and len(late) == len(ref_late)
    cv, ref_cv = (np.mean([f.truth["uniformity_cv"] for f in fs]) for fs in (late, ref_late))
    assert cv > ref_cv + 0.1  # the chipped knife's marks
    assert [_key(f) for f in got["right"] if f.t_s < 1.0] == [
        _key(f) for f in ref["right"] if f.t_s < 1.0]
    assert [f.t_s for f in got["top"]] == [f.t_s for f in ref["top"] if f.t_s < 2.0]
    faults = [m.head_register_values(i)["head_faults"] for i in range(4)]
    assert faults == [0, 0, HeadFault.AMPLIFIER, HeadFault.CAMERA_SILENT]
    assert m.register_values()["faults"] & PlcFault.PIEZO_AMPLIFIER  # the machine's register


def test_a_stopped_spindle_on_one_head_stops_the_feed_under_all(cfg):
    m = Moulder(cfg, seed=6, render_images=False)
    _run(m, 1.0)
    assert m.machine_state() & MachineState.SPINDLE_RUNNING
    m.inject("spindle_stop", head="left")
    _run(m, 3.0)
    assert m.feed_speed_mm_s == 0.0
    assert not m.machine_state() & MachineState.SPINDLE_RUNNING
    assert m.head_register_values(2)["head_faults"] == HeadFault.SPINDLE
    assert [m.head_register_values(i)["head_faults"] for i in (0, 1, 3)] == [0, 0, 0]
    m.inject("reset")  # every head
    _run(m, 8.0)
    assert m.feed_speed_mm_s == pytest.approx(FEED_MM_S)


def test_faults_are_routed_by_head_and_kind(cfg):
    m = Moulder(cfg, seed=7, render_images=False)
    with pytest.raises(ValueError, match="strikes one head: give head="):
        m.inject("knife_chip", knife=0, step_um=5.0)
    with pytest.raises(ValueError, match="head must be one of bottom, right, left, top"):
        m.inject("knife_chip", head="side", knife=0, step_um=5.0)
    with pytest.raises(ValueError, match="knife_chip.knife"):
        m.inject("knife_chip", head="right", knife=3, step_um=5.0)  # right has two knives
    m.inject("feed_fault")  # the machine's: on the owner of the feed
    assert m.owner.fault_bits & PlcFault.FEED_DRIVE
    m.inject("estop")  # every head
    assert all(h.estop for h in m.heads.values())
    m.inject("can_silence", head="top", duration_s=0.5)
    assert m.take_interface_events() == [{"kind": "can_silence", "t_s": 0.0,
                                          "duration_s": 0.5, "head": "top"}]
    # faults of the file go where they name
    chip = FaultSpec("knife_chip", {"knife": 2, "step_um": 10.0}, head="top")
    m2 = Moulder(dataclasses.replace(cfg, faults=(chip,)), seed=7, render_images=False)
    assert m2.heads["top"].faults.chips and not any(
        h.faults.chips for n, h in m2.heads.items() if n != "top")
    with pytest.raises(ValueError, match="strikes one head"):
        Moulder(dataclasses.replace(cfg, faults=(FaultSpec("spindle_stop"),)), seed=7)


def test_an_encoder_wrap_keeps_every_heads_pairs_whole(cfg):
    m = Moulder(cfg, seed=8, render_images=False)
    _run(m, 2.0)
    m.inject("encoder_wrap", counts_before_wrap=3000)
    frames = _run(m, 3.0)
    mod = 1 << cfg.encoder.counter_bits
    for name, fs in frames.items():
        assert fs, name
        for fr in fs:  # A to B: 2 ms at 600 mm/s, 24 counts, through the wrap too
            assert (fr.counts_b - fr.counts_a) % mod == pytest.approx(24, abs=1), name
    counts = [fr.counts_a for fs in frames.values() for fr in fs]
    assert max(counts) > mod - 3000 and min(counts) < 3 * FEED_MM_S * cfg.encoder.counts_per_mm


def test_a_one_head_moulder_is_the_machine():
    cfg = default_sim()
    m = Moulder(cfg, seed=9, render_images=False)
    alone = Machine(cfg, seed=9, render_images=False)
    assert m.names == ("main",)
    got = [fr for _, fr in m.advance(3.0)]
    want = alone.advance(3.0)
    assert got and [_key(f) for f in got] == [_key(f) for f in want]
    assert m.register_values() == alone.register_values()
    assert m.head_register_values(0) == alone.head_register_values(0)


def test_rendered_heads_have_their_own_wood_and_noise(cfg):
    small = dataclasses.replace(cfg, camera=dataclasses.replace(
        cfg.camera, optics=dataclasses.replace(cfg.camera.optics, width=160, height=120)))
    heads = tuple(dataclasses.replace(h, camera=dataclasses.replace(
        h.camera, optics=small.camera.optics)) for h in small.heads)
    small = dataclasses.replace(small, declared_heads=heads)
    m = Moulder(small, seed=10, render_images=True)
    frames = _run(m, 3.0, step_s=0.1)
    bottom, right = frames["bottom"][0], frames["right"][0]
    assert bottom.image_a is not None and bottom.image_a.shape == right.image_a.shape
    assert not np.array_equal(bottom.image_a, right.image_a)


def test_the_plc_serves_each_heads_block_and_routes_the_setpoint(cfg):
    """The moulder behind the simulated PLC (MachineRegisterBus) as a head's client sees it."""
    import asyncio

    from controller.fieldbus.plc_client import PlcClient
    from plant_sim.interfaces.register_bus import MachineRegisterBus
    from protocol.registers import RegisterMap

    m = Moulder(cfg, seed=11, render_images=False)
    _run(m, 1.0)
    rmap = RegisterMap.load()

    async def run() -> None:
        bus = MachineRegisterBus(m, rmap)
        await bus.connect()
        clients = [PlcClient(bus, rmap.for_head(i)) for i in range(4)]
        snaps = [await c.read() for c in clients]
        assert [s.values["knives"] for s in snaps] == [4, 2, 2, 6]
        assert [round(s.values["spindle_rpm_max"]) for s in snaps] == [6000, 9000, 9000, 8000]
        assert len({s.values["encoder_counts"] for s in snaps}) == 1  # common: one encoder
        await clients[3].write_spindle_setpoint(7000.0)
        assert m.heads["top"].spindle.setpoint_rpm == 7000.0
        assert m.heads["bottom"].spindle.setpoint_rpm == 6000.0

    asyncio.run(run())


def test_the_feed_starts_once_at_time_zero_with_every_heads_interlock(cfg, monkeypatch):
    from plant_sim.model.feed_drive import FeedDrive

    starts: list[tuple[float, bool]] = []
    real = FeedDrive.start_cycle

    def counted(self, t_s, dt_s):
        starts.append((t_s, self.enabled))
        real(self, t_s, dt_s)

    monkeypatch.setattr(FeedDrive, "start_cycle", counted)
    m = Moulder(cfg, seed=3, render_images=False)
    assert starts == [(0.0, True)]  # once, by the owner with every head on it
    starts.clear()
    m.advance(cfg.plc.cycle_s * 3.5)
    assert len(starts) == 3  # then once a cycle
    # a spindle stopped at t = 0 on a later head keeps the feed off from the first cycle
    stopped = dataclasses.replace(cfg, faults=(FaultSpec("spindle_stop", head="top"),))
    starts.clear()
    Moulder(stopped, seed=3, render_images=False)
    assert starts == [(0.0, False)]
