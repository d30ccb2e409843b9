"""One sweep run: values reach the loaders (errors name the dotted key), outcome row, a real run."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from config.machine import load_machine
from config.sim import load_sim
from core.errors import ConfigError
from planer.hil.scenario import load_scenario
from planer.sweep.design import Point, sweep_from_dict
from planer.sweep.point import (
    OUTCOME_COLUMNS,
    base_values,
    build_machine_config,
    build_sim_config,
    fastest_feed_mm_s,
    make_job,
    outcome_row,
    prepare,
    run_job,
    settled_after_mm,
)

BASE = load_scenario("default")


def _job(values, seed=0):
    return make_job(Point(index=7, seed=seed, values=values), BASE)


def test_dotted_values_reach_the_simulator_and_the_service():
    job = _job({"sim.piezo.resonance_hz": 150.0, "sim.camera.cutter_to_camera_mm": 700.0,
                "machine.piezo.stroke_um": 12.0, "target_pitch_mm": 2.0,
                "sim.cutterhead.knives": 2, "sim.cutterhead.runout_um": [0.0, 3.0]})
    sim = build_sim_config(job)
    cfg = build_machine_config(job)
    assert sim.piezo.resonance_hz == 150.0
    assert sim.camera.cutter_to_camera_mm == 700.0
    assert sim.cutterhead.knives == 2 and sim.cutterhead.runout_um == (0.0, 3.0)
    assert cfg.stroke_um == 12.0
    assert cfg.quality.target_pitch_mm == 2.0
    assert job.scenario.seed == 0 and job.scenario.target_pitch_mm == 2.0
    # the rest is the base plant
    shipped = load_sim()
    assert sim.spindle == shipped.spindle and sim.feed.bandwidth_hz == shipped.feed.bandwidth_hz
    # the shipped documents are not changed by a job
    assert load_sim().piezo.resonance_hz == shipped.piezo.resonance_hz


def test_the_service_target_may_come_from_the_machine_key_instead_of_the_scenario():
    cfg = build_machine_config(_job({"machine.quality.target_pitch_mm": 2.2}))
    assert cfg.quality.target_pitch_mm == 2.2
    cfg = build_machine_config(_job({}))
    assert cfg.quality.target_pitch_mm == BASE.target_pitch_mm


@pytest.mark.parametrize(
    "values, words",
    [
        ({"sim.cutterhead.knives": 2}, ["run 7", "sim.cutterhead.knives=2",
                                        "sim.cutterhead.runout_um must have 2 values"]),
        ({"sim.piezo.hysteresis": 0.6}, ["sim.piezo.hysteresis must be <= 0.5"]),
        ({"sim.cutterhead.knifes": 3}, ["unknown key sim.cutterhead.knifes"]),
        ({"sim.spindle.rpm.x": 3}, ["sim.spindle.rpm.x", "is a value, not a table"]),
        ({"machine.piezo.stroke_um": -1.0}, ["machine.piezo.stroke_um must be > 0"]),
        ({"machine.nope.x": 1}, ["unknown key machine.nope"]),
        ({"target_pitch_mm": -1.0}, ["grid.target_pitch_mm must be > 0"]),
        ({"runout_um": [0.0, "x"]}, ["grid.runout_um[1]"]),
    ],
)
def test_bad_values_are_refused_by_the_loaders_naming_run_and_dotted_key(values, words):
    with pytest.raises(ConfigError) as err:
        _job(values)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_base_values_are_the_base_plant_s():
    keys = ("sim.cutterhead.knives", "sim.cutterhead.runout_um", "sim.piezo.resonance_hz",
            "sim.feed.bandwidth_hz", "machine.piezo.stroke_um", "target_pitch_mm",
            "sim.piezo.lead_fraction", "machine.quality.target_pitch_mm")
    got = base_values(BASE, keys)
    sim = load_sim()
    assert got["sim.cutterhead.knives"] == len(BASE.runout_um)
    assert tuple(got["sim.cutterhead.runout_um"]) == BASE.runout_um
    assert got["sim.piezo.resonance_hz"] == sim.piezo.resonance_hz
    assert got["sim.feed.bandwidth_hz"] == sim.feed.bandwidth_hz
    assert got["sim.piezo.lead_fraction"] == sim.piezo.lead_fraction
    assert got["machine.piezo.stroke_um"] == load_machine().stroke_um
    assert got["target_pitch_mm"] == got["machine.quality.target_pitch_mm"] == BASE.target_pitch_mm


@pytest.mark.parametrize(
    "target, radius, rpm, knives, feed_max",
    [(1.5, 60.0, 6000.0, 4, 1000.0),   # 600: below the machine's limit
     (2.5, 30.0, 6000.0, 4, 1000.0),   # the depth ceiling sqrt(8 R d) = 2.19 mm binds
     (2.5, 60.0, 9000.0, 6, 1000.0)],  # the machine's feed limit binds
)
def test_fastest_feed_is_the_target_under_the_depth_ceiling_times_n_z(target, radius, rpm,
                                                                     knives, feed_max):
    job = _job({"target_pitch_mm": target, "sim.cutterhead.radius_mm": radius,
                "sim.spindle.rpm": rpm, "sim.cutterhead.knives": knives,
                "sim.cutterhead.runout_um": [0.0] * knives, "sim.feed.max_mm_s": feed_max})
    sim, cfg = build_sim_config(job), build_machine_config(job)
    p = min(target, math.sqrt(8 * radius * cfg.quality.depth_max_um * 1e-3))
    assert fastest_feed_mm_s(sim, cfg) == pytest.approx(min(p * rpm / 60 * knives, feed_max))


def test_outcome_row_reduces_the_summary():
    job = _job({})
    sim, cfg = build_sim_config(job), build_machine_config(job)
    meas = [{"ok": True, "uniformity_cv": 0.1 * i, "feed_setpoint_mm_s": 500.0 + i}
            for i in range(8)] + [{"ok": False, "uniformity_cv": None,
                                   "feed_setpoint_mm_s": None}]
    summary = {"target_pitch_mm": 1.5, "final": {"uniformity_cv": 0.02, "pitch_mm": 1.53},
               "converged": {"uniformity_settled_after_mm": 1200.0,
                             "pitch_settled_after_mm": None},
               "measurements": meas, "limits": {"max_abs_offset_um": 5.0},
               "safe_entries": {"count": 2}, "sim_time_s": 9.5, "board_travel_m": 5.01}
    row = outcome_row(summary, sim, cfg)
    assert list(row) == list(OUTCOME_COLUMNS)
    assert float(row["final_pitch_error"]) == pytest.approx(0.02)
    assert float(row["final_measured_cv"]) == pytest.approx(0.5)  # mean of the last 5 measured
    assert float(row["final_feed_mm_s"]) == pytest.approx(505.0)
    fastest = fastest_feed_mm_s(sim, cfg)
    assert float(row["feed_ratio"]) == pytest.approx(505.0 / fastest, rel=1e-5)
    assert float(row["offset_ratio"]) == pytest.approx(5.0 / cfg.stroke_um)
    assert row["cv_settled_after_mm"] == "1200" and row["pitch_settled_after_mm"] == ""
    assert row["cv_003_settled_after_mm"] == ""  # no reference in this summary
    assert (row["safe_entries"], row["measurements"], row["ok_measurements"]) == ("2", "9", "8")
    assert row["error"] == ""
    # default plant: 800 -> 600 mm/s at 2000 mm/s^2, 8 Hz: the ramp ends within 0.2 m; the
    # pitch never settled in this summary
    assert 0.0 < float(row["ramp_end_mm"]) < 200.0
    assert row["loop_closed_at_mm"] == "" and row["pitch_verdict"] == "off"


def test_the_pitch_verdict_of_a_slow_plc_and_of_a_capped_target():
    summary = {"target_pitch_mm": 1.5, "final": {"uniformity_cv": 0.001, "pitch_mm": 1.75},
               "converged": {"reference_at_mm": 300.0, "pitch_settled_after_mm": None},
               "measurements": [], "limits": {}, "board_travel_m": 8.0}
    job = _job({"sim.feed.accel_max_mm_s2": 10.0})
    row = outcome_row(summary, build_sim_config(job), build_machine_config(job))
    assert float(row["ramp_end_mm"]) == pytest.approx(13638.2, abs=0.1)
    assert row["pitch_verdict"] == "ramp not finished"
    assert row["loop_closed_at_mm"] == "300"
    # 8 knives at 1.5 mm need 1200 mm/s, the cap is 1000: judged at the reachable 1.25 mm
    job = _job({"sim.cutterhead.knives": 8, "sim.cutterhead.runout_um": [0.0] * 8})
    meas = [{"board_travel_mm": 100.0 * i, "true_pitch_mm": 1.3 if i < 7 else 1.251}
            for i in range(1, 60)]
    summary = {**summary, "final": {"uniformity_cv": 0.001, "pitch_mm": 1.251},
               "converged": {"reference_at_mm": 300.0, "pitch_settled_after_mm": 400.0},
               "measurements": meas}
    row = outcome_row(summary, build_sim_config(job), build_machine_config(job))
    assert float(row["final_pitch_error"]) == pytest.approx(1.251 / 1.5 - 1)
    assert row["pitch_verdict"] == "capped, in band"  # from 0.7 m, the ramp ends at 0.3 m
    late = [{**m, "true_pitch_mm": 1.3} if m["board_travel_mm"] < 2000.0 else m for m in meas]
    row = outcome_row({**summary, "measurements": late}, build_sim_config(job),
                      build_machine_config(job))
    assert row["pitch_verdict"] == "capped, late"


@pytest.mark.parametrize(
    ("cvs", "expect"),
    [([0.2, 0.1, 0.02, 0.01], 300.0),      # inside from the third measurement after the ref
     ([0.01, 0.02], 0.0),                   # always inside
     ([0.2, 0.02, 0.04, 0.01], 400.0),      # a later excursion counts
     ([0.2, 0.02, 0.04], None),             # the last one is outside: never settled
     ([None, 0.2, None, 0.01, None], 400.0)],  # measurements without truth are skipped
)
def test_settled_after_is_the_travel_from_which_every_later_cv_is_inside(cvs, expect):
    meas = [{"board_travel_mm": 50.0 + 100.0 * (i + 1), "true_uniformity_cv": cv}
            for i, cv in enumerate(cvs)]
    meas.insert(0, {"board_travel_mm": 0.0, "true_uniformity_cv": 0.5})  # before the reference
    got = settled_after_mm(meas, 50.0, max_cv=0.03)
    assert got == expect
    assert settled_after_mm(meas, None, max_cv=0.03) is None


@pytest.fixture(scope="module")
def tiny_jobs():
    sw = sweep_from_dict({"base": "default", "seeds": [0, 1], "fixed": {"distance_m": 0.5},
                          "grid": {"sim.piezo.hysteresis": [0.1]}})
    jobs, _ = prepare(sw)
    return jobs


def test_a_real_run_is_a_full_row(tiny_jobs):
    # (the same seed giving the same row, here and on Dask workers:
    # tests/planer/sweep/test_sweep_driver.py)
    i1, row, wall = run_job(tiny_jobs[1])
    assert i1 == 1 and wall > 0
    assert row["error"] == "", row["error"]
    assert int(row["measurements"]) >= int(row["ok_measurements"]) > 0
    assert float(row["board_travel_m"]) >= 0.5 and float(row["sim_time_s"]) > 0
    assert 0.0 <= float(row["final_true_cv"]) < 1.0
    assert float(row["final_measured_cv"]) >= 0.0
    assert row["safe_entries"] == "0"
    assert float(row["stroke_um"]) == build_machine_config(tiny_jobs[1]).stroke_um


def test_a_failed_run_is_an_error_row_not_an_exception(tiny_jobs):
    job = tiny_jobs[0]
    bad = replace(job, sim_doc={**job.sim_doc, "piezo": {"damping": 7.0}})
    index, row, _ = run_job(bad)
    assert index == job.point.index
    assert "sim.piezo.damping" in row["error"]
    assert all(row[c] == "" for c in OUTCOME_COLUMNS if c != "error")
