"""Scenario faults of the machine: a knife that chips, a change of wood, pairs lost or spoiled."""

from __future__ import annotations

import numpy as np
import pytest

from config.faults import FaultKind, parse_fault
from config.sim import load_sim
from core.errors import ConfigError
from plant_sim.machine.machine import Machine


@pytest.fixture(scope="module")
def sim_cfg():
    return load_sim()


def _run(m: Machine, seconds: float) -> list:
    frames = []
    for _ in range(round(seconds / 0.02)):
        frames += m.advance(0.02)
    return frames


def test_a_knife_chips_at_a_distance_and_cuts_deeper_from_then_on(sim_cfg):
    m = Machine(sim_cfg, seed=0, render_images=False)
    before = list(m.standout_um())
    m.inject("knife_chip", knife=2, step_um=6.0, at_travel_mm=1000.0)
    _run(m, 1.0)  # 800 mm at 800 mm/s: not yet
    assert m.standout_um() == before
    _run(m, 0.5)
    (chip,) = m.faults.chips
    assert chip["knife"] == 2 and 1000.0 <= chip["travel_mm"] < 1000.0 + 800.0 * 0.02 + 1e-6
    assert np.allclose(np.subtract(m.standout_um(), before), [0.0, 0.0, 6.0, 0.0])
    # the passes of knife 2 cut after the chip are 6 um deeper than before it
    p = m.passes(1)
    board_x_at_chip = m.boards.at(chip["travel_mm"], 0.0)[1]
    k2 = p.knife == 2
    # (a board's own x runs from its trailing end: the passes cut later lie at smaller x)
    early = p.bottom_um[k2 & (p.x_mm > board_x_at_chip + 5)]
    late = p.bottom_um[k2 & (p.x_mm < board_x_at_chip - 5)]
    assert np.median(early) - np.median(late) == pytest.approx(6.0, abs=0.5)


def test_a_knife_chip_at_a_time_and_its_checks(sim_cfg):
    m = Machine(sim_cfg, seed=0, render_images=False)
    m.inject("knife_chip", knife=0, step_um=-3.0, at_s=0.5)
    _run(m, 0.6)
    assert m.faults.chips[0]["knife"] == 0 and m.faults.chips[0]["step_um"] == -3.0
    with pytest.raises(ValueError, match=r"knife_chip\.knife must be in \[0, 3\]"):
        m.inject("knife_chip", knife=5)
    with pytest.raises(ConfigError, match=r"step_um must be in \[-50, 50\]"):
        m.inject("knife_chip", step_um=80.0)


def test_the_wood_changes_when_the_board_reaches_the_cutter(sim_cfg):
    m = Machine(sim_cfg, seed=0, render_images=True)
    m.inject("species_change", species="oak", board_id=2)
    assert m.capture.assembler.renderer.wood.name == "spruce"
    first_at = sim_cfg.board.first_at_mm + sim_cfg.board.length_mm + sim_cfg.board.gap_mm
    while m.feed_position_mm < first_at - 20.0:
        m.advance(0.02)
    assert m.faults.species_now == "spruce"
    _run(m, 0.1)
    assert m.faults.species_now == "oak"
    assert m.capture.assembler.renderer.wood.name == "oak"


def test_a_species_must_be_one_the_simulator_knows():
    with pytest.raises(ConfigError, match=r"faults\[0\]\.species must be one of .*oak.*"):
        parse_fault({"kind": "species_change", "species": "balsa"}, "faults[0]")
    with pytest.raises(ConfigError, match="species must be one of"):
        parse_fault({"kind": "species_change", "species": 3}, "faults[0]")
    assert FaultKind.SPECIES_CHANGE.check({"species": "oak"}) == {"species": "oak"}


@pytest.mark.parametrize("fraction", [0.3, 0.8])
def test_a_dropout_loses_that_share_of_the_pairs_meanwhile(sim_cfg, fraction):
    ref = _run(Machine(sim_cfg, seed=4, render_images=False), 4.0)
    m = Machine(sim_cfg, seed=4, render_images=False)
    m.inject("measurement_dropout", at_s=1.0, duration_s=2.0, fraction=fraction)
    got = _run(m, 4.0)
    inside = [f for f in ref if 1.0 <= f.t_s < 3.0]
    assert m.faults.pairs_dropped == len(ref) - len(got)
    assert abs(m.faults.pairs_dropped / len(inside) - fraction) < 0.25
    assert {f.seq for f in got} <= {f.seq for f in ref}
    assert all(f.seq in {g.seq for g in got} for f in ref if not 1.0 <= f.t_s < 3.0)


def test_a_spoiled_pair_arrives_with_an_error_or_a_black_image_b(sim_cfg):
    m = Machine(sim_cfg, seed=1, render_images=False)
    m.inject("measurement_dropout", duration_s=1.0, fraction=1.0, spoil=1)
    frames = _run(m, 1.2)
    hit = [f for f in frames if f.t_s < 1.0]
    assert hit and all(f.error and "light B did not fire" in f.error for f in hit)
    assert all(f.error is None for f in frames if f.t_s >= 1.0)
    assert m.faults.pairs_spoiled == len(hit)
    img = Machine(sim_cfg, seed=1, render_images=True)
    img.inject("measurement_dropout", duration_s=1.0, fraction=1.0, spoil=1)
    f = _run(img, 0.8)[0]
    assert f.error is None and not np.any(f.image_b) and np.any(f.image_a)
