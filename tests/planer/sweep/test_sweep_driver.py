"""Running sweeps: results.csv as runs finish, Ctrl-C, progress, plots, Dask local and remote.

The Dask tests bind 127.0.0.1 only and are bounded in time: a local cluster of two worker
processes, and a separately started ``dask scheduler`` + one ``dask worker`` (subprocesses,
killed at the end) reached through ``planer sweep --scheduler``.
"""

from __future__ import annotations

import io
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from planer.cli import main
from planer.sweep.design import load_sweep, sweep_from_dict
from planer.sweep.driver import (
    ProgressBar,
    ResultsWriter,
    columns,
    read_results,
    run_sweep,
)
from planer.sweep.plots import OUTCOMES, outcome_figure, save_plots
from planer.sweep.point import OUTCOME_COLUMNS, error_row, prepare

TINY = """\
base = "default"
seeds = [0, 1]
[fixed]
distance_m = 0.5
[grid]
"sim.piezo.resonance_hz" = [300.0]
"""
BOUND_S = 180.0


def _jobs(n_values=3, seeds=(0,)):
    sw = sweep_from_dict({"base": "default", "seeds": list(seeds),
                          "grid": {"sim.piezo.hysteresis": [0.1 * i for i in range(n_values)]}})
    jobs, bases = prepare(sw)
    return sw, jobs, bases


def _fake_row(i):
    row = {k: "" for k in OUTCOME_COLUMNS}
    row["final_true_cv"] = f"{0.01 * (i + 1):g}"
    return row


def test_results_file_holds_each_row_as_soon_as_it_is_added_and_is_sorted_at_the_end(tmp_path):
    path = tmp_path / "results.csv"
    w = ResultsWriter(path, columns(["k"]))
    assert read_results(path) == []
    w.add({"run": "2", "seed": "0", "k": "a,b", **_fake_row(2)})
    assert [r["run"] for r in read_results(path)] == ["2"]
    w.add({"run": "0", "seed": "0", "k": "[1, 2]", **_fake_row(0)})
    assert [r["run"] for r in read_results(path)] == ["2", "0"]
    w.close(sort=True)
    rows = read_results(path)
    assert [r["run"] for r in rows] == ["0", "2"]
    assert rows[1]["k"] == "a,b" and rows[0]["k"] == "[1, 2]"  # quoted by the csv module
    assert list(rows[0]) == ["run", "seed", "k", *OUTCOME_COLUMNS]


def test_ctrl_c_keeps_the_finished_rows(tmp_path):
    sw, jobs, bases = _jobs()

    def interrupted(js):
        yield js[2].point.index, _fake_row(2)
        yield js[0].point.index, _fake_row(0)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_sweep(jobs, tmp_path, keys=sw.keys, bases=bases, results=interrupted,
                  progress=io.StringIO())
    rows = read_results(tmp_path / "results.csv")
    assert [r["run"] for r in rows] == ["2", "0"]  # in the order they finished
    assert rows[0]["sim.piezo.hysteresis"] == "0.2" and rows[0]["final_true_cv"] == "0.03"


def test_failed_runs_are_rows_and_every_run_is_one_row(tmp_path):
    sw, jobs, bases = _jobs(n_values=2, seeds=(4, 5))
    failing = {1, 2}

    def some_fail(js):
        for j in reversed(js):
            i = j.point.index
            yield i, error_row("RuntimeError: boom\nsecond line") if i in failing else _fake_row(i)

    bar = io.StringIO()
    rows = run_sweep(jobs, tmp_path, keys=sw.keys, bases=bases, results=some_fail, progress=bar)
    assert rows == read_results(tmp_path / "results.csv")
    assert [r["run"] for r in rows] == ["0", "1", "2", "3"]
    assert [r["seed"] for r in rows] == ["4", "5", "4", "5"]
    assert [bool(r["error"]) for r in rows] == [i in failing for i in range(4)]
    assert rows[1]["error"] == "RuntimeError: boom second line" and rows[1]["final_true_cv"] == ""
    lines = bar.getvalue().splitlines()
    assert len(lines) == 4 and "4/4 runs, 2 failed" in lines[-1]


def test_progress_bar_counts_and_estimates_the_time_left():
    t = [100.0]
    out = io.StringIO()
    bar = ProgressBar(4, stream=out, width=8, clock=lambda: t[0])
    t[0] = 110.0
    bar.update(failed=False)
    assert bar.text() == "sweep [##......] 1/4 runs, 0 failed, 0:10, 0:30 left"
    t[0] = 160.0
    bar.update(failed=True)
    assert "[####....] 2/4 runs, 1 failed, 1:00, 1:00 left" in out.getvalue().splitlines()[-1]


def _plot_rows():
    rows = []
    for i, (k, r, cv) in enumerate([("4", "60", "0.01"), ("2", "60", "0.04"), ("6", "60", ""),
                                    ("4", "30", "0.02"), ("2", "30", "0.2")]):
        row = {"run": str(i), "seed": "0", "knives": k, "radius": r, "fixed": "1",
               **_fake_row(i)}
        row["final_true_cv"] = cv
        rows.append(row)
    rows[2]["error"] = "RuntimeError: x"
    return rows


def test_outcome_figure_has_a_panel_per_varied_key_and_the_base_line(tmp_path):
    rows = _plot_rows()
    bases = {"knives": "4", "radius": "60", "fixed": "1"}
    fig = outcome_figure(rows, ["knives", "radius", "fixed"], bases, "final_true_cv")
    axes = fig.axes
    assert [ax.get_xlabel() for ax in axes] == ["knives", "radius"]
    # the knives panel's line joins the runs at radius 60 (base): knives 2 and 4, not the error
    line = [ln for ln in axes[0].get_lines()
            if ln.get_linestyle() == "-" and ln.get_color() == "tab:blue"][0]
    assert list(line.get_xdata()) == [2.0, 4.0]
    assert list(line.get_ydata()) == [0.04, 0.01]
    # a key varied together with another (knives with their runout lists): with the group
    # its line takes the runs that change both
    linked = [{**r, "radius": "60", "runout": f"[{r['knives']}]"} for r in rows]
    bases["runout"] = "[4]"
    keys3 = ["knives", "runout", "radius"]
    lone = outcome_figure(linked, keys3, bases, "final_true_cv")
    joined = outcome_figure(linked, keys3, bases, "final_true_cv",
                            groups=[("knives", "runout")])

    def line_x(fig):
        return [list(ln.get_xdata()) for ln in fig.axes[0].get_lines()
                if ln.get_linestyle() == "-" and ln.get_color() == "tab:blue"]

    assert line_x(lone) == [[4.0]]  # alone: only the base plant has its runout at base
    assert line_x(joined) == [[2.0, 4.0]]
    with pytest.raises(ValueError, match="outcome"):
        outcome_figure(rows, ["knives"], bases, "nope")
    paths = save_plots(rows, ["knives", "radius"], bases, tmp_path, stem="s")
    assert [p.name for p in paths] == [f"s_{o[0]}.png" for o in OUTCOMES]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in paths)


# ------------------------------------------------------------------------------ real runs on Dask
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sweep")
    path = folder / "tiny.toml"
    path.write_text(TINY)
    sw = load_sweep(path)
    jobs, bases = prepare(sw)
    serial = run_sweep(jobs, folder / "serial", keys=sw.keys, bases=bases, workers=0,
                       progress=io.StringIO())
    return path, sw, jobs, bases, serial


def test_the_same_seed_gives_the_same_row_on_a_local_cluster_of_two_workers(tiny, tmp_path):
    pytest.importorskip("distributed")
    _, sw, jobs, bases, serial = tiny
    assert all(r["error"] == "" for r in serial), [r["error"] for r in serial]
    assert serial[0]["final_true_cv"] != serial[1]["final_true_cv"]  # two seeds, two boards
    rows = run_sweep(jobs, tmp_path, keys=sw.keys, bases=bases, workers=2,
                     progress=io.StringIO())
    assert rows == serial


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_sweep_runs_on_a_separately_started_scheduler_and_worker(tiny, tmp_path):
    pytest.importorskip("distributed")
    _, _, _, _, serial = tiny
    path = tmp_path / "one.toml"  # seed 0 only: run 0 of the tiny sweep
    path.write_text(TINY.replace("seeds = [0, 1]", "seeds = [0]"))
    dask = Path(sys.executable).parent / "dask"
    if not dask.exists():
        pytest.skip("the dask command is not installed")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = []
    try:
        procs.append(subprocess.Popen(
            [str(dask), "scheduler", "--host", "127.0.0.1", "--port", str(port),
             "--no-dashboard", "--dashboard-address", "127.0.0.1:0", "--idle-timeout", "300s"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=tmp_path))
        procs.append(subprocess.Popen(
            [str(dask), "worker", address, "--host", "127.0.0.1", "--nworkers", "1",
             "--nthreads", "1", "--no-dashboard", "--dashboard-address", "127.0.0.1:0",
             "--death-timeout", "60"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=tmp_path))
        out = tmp_path / "out"
        done = subprocess.run(
            [sys.executable, "-m", "planer.cli", "sweep", str(path), "--scheduler", address,
             "--out", str(out), "--no-plots"],
            capture_output=True, text=True, timeout=BOUND_S, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        assert f"on scheduler {address}" in done.stderr and "1/1 runs" in done.stderr
        assert read_results(out / "results.csv") == serial[:1]
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=10)


@pytest.mark.parametrize(
    "argv, words",
    [
        (["sweep", "missing.toml", "--out", "o"], ["config file not found", "missing.toml"]),
        (["sweep", "{f}", "--out", "o", "--workers", "-1"], ["--workers must be >= 0"]),
        (["sweep", "{f}", "--out", "o", "--scheduler", "127.0.0.1:1"], ["tcp://HOST:PORT"]),
        (["sweep", "{bad}", "--out", "o"], ["run 0", "sim.piezo.hysteresis must be <= 0.5"]),
    ],
)
def test_command_errors_are_one_line(argv, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ok.toml").write_text(TINY)
    (tmp_path / "bad.toml").write_text(TINY.replace("resonance_hz\" = [300.0]",
                                                    "hysteresis\" = [0.6]"))
    argv = [a.format(f="ok.toml", bad="bad.toml") for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("planer sweep: error: ")
    for w in words:
        assert w in err[0], (w, err[0])
