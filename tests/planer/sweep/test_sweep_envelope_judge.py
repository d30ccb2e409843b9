"""The envelope's verdict per plant: the criteria against the plant's references."""

from __future__ import annotations

from planer.sweep.envelope import PlantRefs, _label, judge_plant, markdown


def _row(final, settled="1500", safe="0", pitch="in band", closed="0", error=""):
    return {"final_true_cv": final, "cv_003_settled_after_mm": settled, "safe_entries": safe,
            "pitch_verdict": pitch, "loop_closed_at_mm": closed, "max_offset_um": "4",
            "final_pitch_error": "0.001", "error": error}


REACHABLE = PlantRefs(zero_cv=0.224, optimum_cv=0.0, optimum_c=26.0, hot_cv=None, hot_c=None,
                      camera_mm=300.0)
HELD = PlantRefs(zero_cv=0.224, optimum_cv=0.198, optimum_c=70.0, hot_cv=0.191, hot_c=92.0,
                 camera_mm=300.0)


def test_a_plant_that_converges_in_time_passes():
    got = judge_plant([_row("0.0006"), _row("0.0007", settled="3200")], REACHABLE)
    assert got["verdict"] == "pass"
    assert got["final"] == "0.0006-0.0007" and got["settled"] == "1.50-3.20"


def test_late_convergence_safe_entries_and_a_bad_pitch_are_misses():
    rows = [_row("0.0006", settled="3400"), _row("0.0006", settled=""),
            _row("0.0006", safe="2", pitch="off")]
    got = judge_plant(rows, REACHABLE)
    assert "CV <= 0.03 late in 2 of 3" in got["verdict"]
    assert "safe entries" in got["verdict"] and "pitch off" in got["verdict"]
    # the camera's delay counts: settled 3.2 m after a loop that closed at 0.2 m is 3.4 m
    assert "late" in judge_plant([_row("0.001", settled="3200", closed="200")],
                                 REACHABLE)["verdict"]
    assert judge_plant([_row("0.001", pitch="ramp not finished")], REACHABLE)["verdict"] == "pass"


def test_the_cv_is_judged_against_the_optimum_within_the_heat():
    assert judge_plant([_row("0.212", settled="")], HELD)["verdict"] == "pass"  # 7 % above
    assert judge_plant([_row("0.230", settled="")], HELD)["verdict"] == "CV above the optimum"
    assert judge_plant([_row("0.26", settled="")], HELD)["verdict"] == (
        "CV above the zero table; CV above the optimum")
    table = [{"plant": "resonance_hz 60", "refs": HELD,
              **judge_plant([_row("0.212", settled="")], HELD)}]
    assert "0.198 (70 °C; 0.191 at 92 °C)" in markdown(table)


def test_the_label_names_the_varied_keys_and_leaves_runouts_out():
    assert _label({}) == "base"
    assert _label({"sim.piezo.resonance_hz": 60.0, "sim.piezo.hysteresis": 0.35}) == (
        "resonance_hz 60, hysteresis 0.35")
    assert _label({"sim.cutterhead.knives,sim.cutterhead.runout_um,sim.feed.max_mm_s":
                   [8, [0.0] * 8, 1500.0]}) == "knives 8, max_mm_s 1500"


def test_a_held_pattern_is_named_and_the_optimum_over_every_pattern_shown_beside():
    refs = PlantRefs(zero_cv=0.224, optimum_cv=0.213, optimum_c=33.0, hot_cv=None, hot_c=None,
                     camera_mm=300.0, patterns=(1,), held=(2,), every_cv=0.198, every_c=70.0)
    # judged against the optimum the loop may reach (0.213), not the one over every pattern
    assert judge_plant([_row("0.2119", settled="")], refs)["verdict"] == "pass"
    assert "CV above the optimum" in judge_plant([_row("0.240", settled="")], refs)["verdict"]
    text = markdown([{"plant": "60 Hz", "refs": refs, **judge_plant([_row("0.2119")], refs)}])
    assert "0.213 (pattern 2 held; every pattern: 0.198 at 70 °C)" in text
