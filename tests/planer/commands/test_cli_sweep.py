"""``planer sweep``: one column per name in results.csv, plot titles inside their figures,
and a quiet Ctrl-C (the real command on a local Dask cluster)."""

from __future__ import annotations

import csv
import io
import os
import signal
import subprocess

import pytest

from planer.sweep.design import sweep_from_dict
from planer.sweep.driver import read_results, run_sweep
from planer.sweep.plots import OUTCOMES, outcome_figure
from planer.sweep.point import OUTCOME_COLUMNS, error_row, prepare
from tests.support.interrupt import ended_or_stacks, planer_argv


def _pitch_sweep():
    sw = sweep_from_dict({"base": "default", "seeds": [0],
                          "grid": {"target_pitch_mm": [1.4, 1.6]}})
    return sw, *prepare(sw)


def test_a_varied_key_that_is_an_outcome_is_one_column_with_the_runs_value(tmp_path):
    sw, jobs, bases = _pitch_sweep()
    assert "target_pitch_mm" in sw.keys and "target_pitch_mm" in OUTCOME_COLUMNS

    def one_fails(js):
        for j in js:
            if j.point.index == 0:
                yield 0, error_row("RuntimeError: boom")
            else:
                yield j.point.index, {**{k: "" for k in OUTCOME_COLUMNS},
                                      "target_pitch_mm": "1.6", "final_true_cv": "0.02"}

    run_sweep(jobs, tmp_path, keys=sw.keys, bases=bases, results=one_fails,
              progress=io.StringIO())
    with (tmp_path / "results.csv").open(newline="") as fh:
        header = next(csv.reader(fh))
    assert header.count("target_pitch_mm") == 1 and len(header) == len(set(header)), header
    rows = read_results(tmp_path / "results.csv")
    by_run = {r["run"]: r for r in rows}
    # the failed run keeps its input; the other its value
    assert by_run["0"]["target_pitch_mm"] == "1.4" and by_run["0"]["error"]
    assert by_run["1"]["target_pitch_mm"] == "1.6" and by_run["1"]["final_true_cv"] == "0.02"


@pytest.mark.parametrize("n_keys", [1, 2, 4])
def test_every_plot_title_lies_inside_its_figure(n_keys):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    keys = ["target_pitch_mm"] + [f"sim.piezo.k{j}" for j in range(n_keys - 1)]
    rows = []
    for i, pitch in enumerate(["1.4", "1.5", "1.6"]):
        row = {"run": str(i), "seed": "0", "target_pitch_mm": pitch, "error": "",
               **{name: "0.5" for name, *_ in OUTCOMES}}
        row.update({k: str(i % 2) for k in keys[1:]})
        rows.append(row)
    rows[0]["cv_settled_after_mm"] = ""  # never settled: the longest title
    for name, *_ in OUTCOMES:
        fig = outcome_figure(rows, keys, {"target_pitch_mm": "1.5"}, name)
        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        box = fig.get_suptitle() and fig._suptitle.get_window_extent(canvas.get_renderer())
        assert box.x0 >= 0 and box.x1 <= fig.bbox.width, (name, n_keys, box)
        assert box.y0 >= 0 and box.y1 <= fig.bbox.height, (name, n_keys, box)
        assert "over the sweep (3 runs, 0 failed" in " ".join(fig.get_suptitle().split())


def _sweep_file(tmp_path):
    sweep = tmp_path / "s.toml"
    sweep.write_text('base = "default"\nseeds = [0]\n[fixed]\ndistance_m = 1.0\n'
                     '[grid]\n"target_pitch_mm" = [1.4, 1.5, 1.6]\n')
    return sweep


def test_ctrl_c_while_the_local_cluster_starts_says_nothing_of_dask(tmp_path):
    """Ctrl-C to the group in the sweep's first seconds, while Dask's cluster and its worker
    process start: the workers are born deaf to it, the cluster is closed once up."""
    proc = subprocess.Popen(
        planer_argv("sweep", str(_sweep_file(tmp_path)), "--workers", "1",
                    "--out", str(tmp_path / "out")),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
        start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        first = proc.stderr.readline()
        assert " runs of default " in first, first
        os.killpg(proc.pid, signal.SIGINT)
        _, rest = ended_or_stacks(proc, "planer sweep after an early Ctrl-C")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, rest
    assert rest.strip().splitlines() == ["planer sweep: interrupted"], rest


def test_a_ctrl_c_held_while_the_cluster_starts_is_raised_after_it_and_a_second_at_once():
    from planer.sweep.driver import _ctrl_c_held

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        done = []
        with pytest.raises(KeyboardInterrupt):
            with _ctrl_c_held():
                signal.raise_signal(signal.SIGINT)
                done.append("the block went on")
        assert done == ["the block went on"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        with pytest.raises(KeyboardInterrupt):
            with _ctrl_c_held():
                signal.raise_signal(signal.SIGINT)
                signal.raise_signal(signal.SIGINT)
                done.append("not reached")
        assert done == ["the block went on"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)


def test_ctrl_c_of_a_sweep_on_a_local_cluster_says_nothing_of_dask(tmp_path):
    """Ctrl-C reaches the whole process group, as in a terminal: one line, exit code 130.

    Started with SIGINT ignored (a background command of a script; a test runner started with
    ``&`` passes that on to what it starts): one Ctrl-C stops it all the same. From a terminal
    (SIGINT default) the command takes the same path once the CLI has started.
    """
    proc = subprocess.Popen(
        planer_argv("sweep", str(_sweep_file(tmp_path)), "--workers", "1",
                    "--out", str(tmp_path / "out"), sigint="ignored"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
        start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        said = []
        for line in proc.stderr:  # the first run finished: the next one is running
            said.append(line)
            if line.startswith("sweep ["):
                break
        assert said and said[-1].startswith("sweep [") and " 1/3 runs" in said[-1], said
        os.killpg(proc.pid, signal.SIGINT)
        _, rest = ended_or_stacks(proc, "planer sweep after Ctrl-C")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, rest
    assert rest.strip().splitlines() == ["planer sweep: interrupted"], rest
    assert [r["run"] for r in read_results(tmp_path / "out" / "results.csv")] != []
