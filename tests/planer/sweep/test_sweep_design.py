"""Sweep files and their grids (pure): combinations, linked keys, duplicates, bad files."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from config.loading import default_path
from core.errors import ConfigError
from planer.sweep.design import (
    Sweep,
    canonical,
    expand,
    grid_combinations,
    load_sweep,
    sweep_from_dict,
)

ROBUSTNESS = default_path("sweeps/robustness.toml")


def _doc(grid, **kw):
    return {"base": "default", "seeds": [0], "grid": grid, **kw}


@pytest.mark.parametrize(
    "grid, n",
    [
        ({"a.x": [1]}, 1),
        ({"target_pitch_mm": [1.0, 1.5], "sim.piezo.hysteresis": [0.0, 0.1, 0.2]}, 6),
        ({"sim.a.b": [1, 2], "sim.a.c": [1, 2], "machine.q.r": [1, 2, 3, 4]}, 16),
    ],
)
def test_a_grid_gives_every_combination_once_first_axis_slowest(grid, n):
    grid = {k.replace("a.x", "sim.a.x"): v for k, v in grid.items()}
    sw = sweep_from_dict(_doc(grid))
    combos = grid_combinations(sw.grids[0])
    assert len(combos) == n == math.prod(len(v) for v in grid.values())
    assert len({tuple(sorted(c.items())) for c in combos}) == n
    first = next(iter(grid))
    # the first key changes only every n / len(values) combinations
    block = n // len(grid[first])
    assert [c[first] for c in combos] == [v for v in grid[first] for _ in range(block)]


def test_linked_keys_vary_together():
    key = "sim.cutterhead.knives,sim.cutterhead.runout_um"
    sw = sweep_from_dict(_doc({key: [[2, [0, 3]], [3, [0, 1, 2]]], "target_pitch_mm": [1, 2]}))
    combos = grid_combinations(sw.grids[0])
    assert len(combos) == 4
    for c in combos:
        assert len(c["sim.cutterhead.runout_um"]) == c["sim.cutterhead.knives"]
    assert sw.keys == ("sim.cutterhead.knives", "sim.cutterhead.runout_um", "target_pitch_mm")


def test_expand_numbers_points_runs_each_seed_and_drops_repeats_of_the_base():
    doc = {"base": "default", "seeds": [3, 5], "fixed": {"distance_m": 0.5},
           "grid": [{"sim.spindle.rpm": [4500.0, 6000.0]},
                    {"target_pitch_mm": [1.5, 2.0]},
                    {"sim.spindle.rpm": [4500]}]}
    sw = sweep_from_dict(doc)
    bases = {"sim.spindle.rpm": 6000, "target_pitch_mm": 1.5}
    pts = expand(sw, bases)
    # grid 0: 2 x 2 seeds; grid 1: 1.5 is the base plant again (dropped), 2.0 new;
    # grid 2: 4500 (int) is 4500.0 again (dropped)
    assert [p.index for p in pts] == list(range(6))
    assert [p.seed for p in pts] == [3, 5] * 3
    assert all(p.values["distance_m"] == 0.5 for p in pts)
    assert pts[4].values == {"distance_m": 0.5, "target_pitch_mm": 2.0}
    # without base values only literal repeats go (grid 2's 4500 is grid 0's)
    assert len(expand(sw)) == 2 * (2 + 2)


@pytest.mark.parametrize(
    "value, text",
    [(4, "4"), (4.0, "4"), (0.03, "0.03"), ([0.0, 4, -2.5], "[0, 4, -2.5]"), (True, "true"),
     ("spruce", "spruce")],
)
def test_canonical_text_of_values(value, text):
    assert canonical(value) == text


@pytest.mark.parametrize(
    "doc, words",
    [
        ({"seeds": [0], "grid": {"target_pitch_mm": [1]}}, ["missing key base"]),
        (_doc({"target_pitch_mm": [1]}, seeds=[]), ["seeds"]),
        (_doc({"target_pitch_mm": [1]}, seeds=[0, -1]), ["seeds[1]"]),
        (_doc({"target_pitch_mm": [1]}, seeds=[1, 1]), ["seeds", "twice"]),
        (_doc({"seed": [1, 2]}), ["grid", "'seed'"]),
        (_doc({"sim": [1, 2]}), ["'sim'"]),
        (_doc({"sim.": [1, 2]}), ["'sim.'"]),
        (_doc({"sim..x": [1, 2]}), ["'sim..x'"]),
        (_doc({"plc.port": [1, 2]}), ["'plc.port'"]),
        (_doc({"sim.piezo.damping": []}), ["sim.piezo.damping", "non-empty"]),
        (_doc({"sim.piezo.damping": 0.2}), ["sim.piezo.damping", "list"]),
        (_doc({"sim.a.b,sim.a.c": [[1, 2], [1]]}), ["[1]", "2 values"]),
        (_doc({"sim.a.b,sim.a.b": [[1, 2]]}), ["twice"]),
        (_doc({"sim.a.b": [1], "sim.a.b,sim.a.c": [[1, 2]]}), ["sim.a.b", "varied twice"]),
        (_doc({"sim.a.b": [1]}, fixed={"sim.a.b": 2}), ["sim.a.b", "fixed and varied"]),
        (_doc({"sim.a.b": [1]}, fixed={"bogus": 2}), ["fixed", "bogus"]),
        (_doc({"sim.a.b": [1]}, extra=1), ["unknown key extra"]),
        (_doc([]), ["grid", "at least one"]),
        (_doc("x"), ["grid", "table"]),
        (_doc([{"sim.a.b": [1]}, {"nope": [1]}]), ["grid[1]", "nope"]),
        (_doc({"sim.a.b": list(range(400)), "sim.a.c": list(range(400))}), ["more than"]),
    ],
)
def test_bad_sweep_files_are_refused_naming_the_key(doc, words):
    with pytest.raises(ConfigError) as err:
        sweep_from_dict(doc)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_load_sweep_names_the_file_and_resolves_a_base_beside_it(tmp_path):
    (tmp_path / "mine.toml").write_text("[slow]\ndistance_m = 1.0\n")
    f = tmp_path / "sweep.toml"
    f.write_text('base = "mine.toml:slow"\nseeds = [1]\n[grid]\ntarget_pitch_mm = [1.0]\n')
    sw = load_sweep(f)
    assert sw.base == f"{tmp_path / 'mine.toml'}:slow"
    assert sw.source == f and sw.seeds == (1,)
    f.write_text('base = "default"\n[grid]\nwhat = [1]\n')
    with pytest.raises(ConfigError, match=r"sweep\.toml: grid: unknown key 'what'"):
        load_sweep(f)


def _covered(sw: Sweep, key: str) -> list:
    vals = [sw.fixed[key]] if key in sw.fixed else []
    for grid in sw.grids:
        for group, values in grid:
            if key in group:
                vals.extend(v[group.index(key)] for v in values)
    return vals


@pytest.mark.parametrize(
    "key, lo, hi",
    [
        ("sim.cutterhead.knives", 2, 6),
        ("sim.cutterhead.radius_mm", 30, 120),
        ("sim.spindle.rpm", 4500, 9000),
        ("sim.piezo.resonance_hz", 150, 800),
        ("sim.piezo.hysteresis", 0.0, 0.3),
        ("sim.feed.bandwidth_hz", 1.0, 3.0),
        ("sim.camera.cutter_to_camera_mm", 300, 2000),
        ("target_pitch_mm", 1.0, 2.5),
    ],
)
def test_the_robustness_sweep_covers_the_ranges_of_issue_9(key, lo, hi):
    vals = _covered(load_sweep(ROBUSTNESS), key)
    assert min(vals) == lo and hi in vals
    if key == "sim.cutterhead.knives":
        assert set(range(2, 7)) <= set(vals)


def test_the_robustness_sweep_covers_runout_from_tiny_to_15_um():
    sw = load_sweep(ROBUSTNESS)
    runouts = _covered(sw, "sim.cutterhead.runout_um")
    spans = [max(r) - min(r) for r in runouts]
    assert min(spans) <= 1.0 and max(max(abs(x) for x in r) for r in runouts) == 15.0
    assert Path(sw.source) == ROBUSTNESS


@pytest.mark.parametrize("path", sorted(default_path("sweeps").glob("*.toml")),
                         ids=lambda p: p.name)
def test_every_shipped_sweep_file_is_accepted_by_the_loaders(path):
    from planer.sweep.point import prepare

    sw = load_sweep(path)
    jobs, _ = prepare(sw)
    assert 0 < len(jobs) <= len(expand(sw, None))  # duplicates of the base run once
    assert {j.point.seed for j in jobs} == set(sw.seeds)


def test_the_plant_sweeps_cover_every_plant_of_the_closed_loop_table():
    """Base, cameras 1000/2000 mm, saturated, 150 Hz, hysteresis 0.30, stroke mismatch,
    vanished knife, and the drift plant in its own file, each with 3 seeds."""
    from planer.sweep.point import build_machine_config, build_sim_config, prepare

    plants = set()
    for name in ("plants.toml", "plants_drift.toml"):
        sw = load_sweep(default_path(f"sweeps/{name}"))
        assert len(sw.seeds) == 3
        for job in prepare(sw)[0]:
            sim, mach = build_sim_config(job), build_machine_config(job)
            runout = tuple(job.scenario.runout_um or sim.cutterhead.runout_um)
            drift = sim.cutterhead.drift
            plants.add((sim.camera.cutter_to_camera_mm, sim.piezo.resonance_hz,
                        sim.piezo.hysteresis, sim.piezo.stroke_um, mach.stroke_um,
                        max(runout) - min(runout) > 20.0,
                        bool(drift is not None and drift.active)))
    expected = {
        (300.0, 800.0, 0.03, 20.0, 20.0, False, False),  # base
        (1000.0, 800.0, 0.03, 20.0, 20.0, False, False),
        (2000.0, 800.0, 0.03, 20.0, 20.0, False, False),
        (300.0, 800.0, 0.03, 10.0, 10.0, True, False),  # saturated
        (300.0, 150.0, 0.03, 20.0, 20.0, False, False),
        (300.0, 800.0, 0.30, 20.0, 20.0, False, False),
        (300.0, 800.0, 0.03, 10.0, 20.0, True, False),  # stroke mismatch
        (300.0, 800.0, 0.03, 20.0, 20.0, True, False),  # vanished knife
        (300.0, 800.0, 0.03, 20.0, 20.0, False, True),  # drift
    }
    assert plants == expected
