"""planer.hil.stress: the rows it makes of ``planer hil --json`` runs, its hogs, its table.

No HIL is run here (that is a measurement, ``python -m planer.hil.stress``): a stand-in command
prints a summary.
"""

from __future__ import annotations

import json
import os
import sys

import pytest

from planer.hil import stress


def _summary(*, passed=True, cv=0.01, handled=(True, True), safe=2, unexplained=0,
             factor=0.9, failed=()):
    done = {"final_uniformity_le_0.05": True, "faults_handled": all(handled)}
    done.update({k: False for k in failed})
    return {
        "passed": passed, "final": {"uniformity_cv": cv, "pitch_mm": 1.5},
        "faults": [{"kind": "modbus_restart", "handled": h} for h in handled],
        "safe_entries": {"count": safe, "unexplained": unexplained},
        "sim_time_factor": factor, "done": done,
    }


@pytest.mark.parametrize(("summary", "code", "passed"), [
    (_summary(), 0, True),
    (_summary(passed=False, handled=(True, False)), 1, False),
    (_summary(), 1, False),  # the exit code disagrees: not a pass
])
def test_a_row_reads_the_summary(summary, code, passed):
    row = stress.parse_run(json.dumps(summary) + "\n", "line 1\nline 2\n", exit_code=code,
                           run=3, scenario="faults", wall_s=12.5)
    assert row.passed is passed and (row.run, row.scenario, row.wall_s) == (3, "faults", 12.5)
    assert row.final_cv == summary["final"]["uniformity_cv"]
    assert row.faults == 2
    assert row.faults_handled == sum(f["handled"] for f in summary["faults"])
    assert row.safe_entries == 2 and row.time_factor == 0.9
    assert row.failed_checks == [k for k, v in summary["done"].items() if not v]
    assert row.stderr_tail == ([] if passed else ["line 1", "line 2"])


@pytest.mark.parametrize("stdout", ["", "not json", "[1, 2]", '{"passed": tr'])
def test_a_run_without_a_summary_is_a_failed_row_saying_so(stdout):
    row = stress.parse_run(stdout, "Traceback ...\nboom", exit_code=2, run=1, scenario="d",
                           wall_s=1.0)
    assert not row.passed and row.failed_checks == ["no summary (exit code 2)"]
    assert row.stderr_tail == ["Traceback ...", "boom"]


def test_table_tallies_each_scenario_and_names_the_failures():
    rows = [
        stress.parse_run(json.dumps(_summary()), "", exit_code=0, run=1, scenario="default",
                         wall_s=30.0),
        stress.parse_run(json.dumps(_summary(passed=False, failed=("settled_within_3m",))),
                         "why it failed", exit_code=1, run=1, scenario="faults", wall_s=40.0),
    ]
    text = stress.format_table(rows)
    assert text.splitlines()[0] == stress.TABLE_HEAD.splitlines()[0]
    assert "default: 1/1 passed" in text and "faults: 0/1 passed" in text
    assert "faults run 1 failed: settled_within_3m" in text and "    why it failed" in text


def test_run_stress_runs_each_scenario_in_a_fresh_process(tmp_path):
    """A stand-in ``planer`` prints a summary naming its arguments: every run is one process
    with its own log, and the rows come in run order, scenarios interleaved."""
    script = ("import json, sys; a = sys.argv[1:]; "
              "print(json.dumps({'passed': True, 'final': {'uniformity_cv': 0.01}, "
              "'faults': [], 'safe_entries': {'count': 0}, 'done': {'ok': True}, "
              "'sim_time_factor': float(len(a))}))")
    seen = []
    rows = stress.run_stress(["default", "faults"], runs=2, hogs=0, folder=tmp_path,
                             planer=[sys.executable, "-c", script], on_row=seen.append)
    assert [(r.scenario, r.run) for r in rows] == [("default", 1), ("faults", 1),
                                                   ("default", 2), ("faults", 2)]
    assert seen == rows and all(r.passed for r in rows)
    # hil --json --scenario NAME --log PATH: six arguments
    assert {r.time_factor for r in rows} == {6.0}
    assert sorted(p.name for p in tmp_path.glob("*.err")) == [
        "default-1.err", "default-2.err", "faults-1.err", "faults-2.err"]
    with pytest.raises(ValueError, match="runs"):
        stress.run_stress(["default"], runs=0)


def test_hogs_run_during_the_block_and_are_ended_after():
    with stress.cpu_hogs(2) as pids:
        assert len(pids) == 2
        for pid in pids:
            os.kill(pid, 0)  # alive
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    with pytest.raises(ValueError, match="count"):
        with stress.cpu_hogs(-1):
            pass
