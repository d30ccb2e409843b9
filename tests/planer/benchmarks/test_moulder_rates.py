"""The moulder's rate sweep: rates checked, rows taken from each run, the highest rate that meets
the target, its table, figure and command line (runs given by a stand-in of ``moulder.run``'s
result shape; the moulder run itself is tested in test_moulder_bench.py)."""

from __future__ import annotations

import json

import pytest

from planer.benchmarks import moulder_rates as mr

TARGET = 10.0


def _result(rate: float, p99: float | None, *, dropped: int = 0, heads: int = 4) -> dict:
    """A ``moulder.run`` result's shape at ``rate`` a head with this p99 and drops."""
    n = 150 * heads
    return {
        "rate_hz_per_head": rate,
        "target_p99_ms": TARGET,
        "workers": 2,
        "heads": {f"h{i}": {} for i in range(heads)},
        "overall": {"pairs_in": n, "handled": n - dropped, "dropped": dropped,
                    "pairs_per_s": rate * heads, "p50_ms": None if p99 is None else p99 / 3,
                    "p99_ms": p99, "max_ms": None if p99 is None else 2 * p99,
                    "cpu_ms_per_pair": 4.0, "cores_busy": rate * heads * 4.0 / 1000},
        "meets": {"p99": p99 is not None and p99 <= TARGET, "nothing_dropped": dropped == 0},
        "machine": {"cores": 2, "load_avg": [0.5, 0.5, 0.5],
                    "load_avg_after": [0.7, 0.6, 0.5]},
    }


def _runner(table: dict[float, tuple[float | None, int]]):
    calls = []

    def run(quick, *, rate_hz):
        calls.append((quick, rate_hz))
        p99, dropped = table[rate_hz]
        return _result(rate_hz, p99, dropped=dropped)

    return run, calls


@pytest.mark.parametrize("text, rates", [
    ("100", (100.0,)),
    ("100,25, 50", (25.0, 50.0, 100.0)),
    ("12.5,88", (12.5, 88.0)),
])
def test_good_rates_are_sorted(text, rates):
    assert mr.parse_rates(text) == rates


@pytest.mark.parametrize("text, named", [
    ("", "at least one"),
    ("25,x", "'x'"),
    ("25,-5", "'-5'"),
    ("0", "'0'"),
    ("inf", "'inf'"),
    ("nan", "'nan'"),
    ("25,25", "twice"),
    ("25,,50", "''"),
])
def test_bad_rates_are_refused_naming_the_entry(text, named):
    with pytest.raises(ValueError, match="rates") as exc:
        mr.parse_rates(text)
    assert named in str(exc.value)


@pytest.mark.parametrize("table, best", [
    ({25: (8.0, 0), 50: (9.0, 0), 100: (40.0, 0)}, 50.0),
    ({25: (8.0, 0), 50: (9.0, 0), 100: (9.5, 0)}, 100.0),
    ({25: (12.0, 0), 50: (9.0, 0), 100: (40.0, 0)}, None),  # a slower rate missed: none
    ({25: (8.0, 0), 50: (9.0, 3), 100: (9.5, 0)}, 25.0),  # drops miss the target too
    ({25: (8.0, 0), 50: (None, 0), 100: (9.5, 0)}, 25.0),  # no latency at all: missed
])
def test_the_highest_rate_meeting_the_target_and_every_slower_one(table, best):
    run, calls = _runner(table)
    out = mr.sweep(list(table)[::-1], run=run)
    assert [c[1] for c in calls] == sorted(table)  # slowest first
    assert out["highest_meeting_hz_per_head"] == best
    assert out["highest_meeting_pairs_per_s"] == (None if best is None else 4 * best)
    assert [r["rate_hz_per_head"] for r in out["rows"]] == sorted(table)
    for r in out["rows"]:
        p99, dropped = table[r["rate_hz_per_head"]]
        assert set(r) == set(mr.ROW_KEYS)
        assert r["p99_ms"] == p99 and r["dropped"] == dropped
        assert r["meets"] == (p99 is not None and p99 <= TARGET and dropped == 0)


def test_a_sweep_reports_each_rate_before_and_after_it():
    run, calls = _runner({25: (8.0, 0), 100: (40.0, 0)})
    lines = []
    out = mr.sweep((25, 100), quick=True, progress=lines.append, run=run)
    assert all(q is True for q, _ in calls)
    assert len(lines) == 4 and "1/2" in lines[0] and "2/2" in lines[2]
    assert "meets" in lines[1] and "MISSES" in lines[3]
    assert out["machine"] == {"cores": 2, "load_avg": [0.5, 0.5, 0.5],
                              "load_avg_after": [0.7, 0.6, 0.5]}
    table = mr.text(out)
    assert "25 pairs/s a head (100 pairs/s)" in table
    assert table.count("MISSED") == 1


def test_the_figure_is_a_png_with_the_target_and_the_cores(tmp_path):
    run, _ = _runner({25: (8.0, 0), 50: (9.0, 0), 75: (11.0, 0), 100: (None, 5)})
    out = mr.sweep((25, 50, 75, 100), run=run)
    fig = mr.figure(out)
    ax, ax2 = fig.axes
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "target p99 10 ms" in labels and "missed" in labels
    p99 = next(line for line in ax.get_lines() if line.get_label().startswith("p99"))
    assert list(p99.get_xdata()) == [100.0, 200.0, 300.0]  # the run without latency left out
    assert list(ax2.get_lines()[0].get_ydata()) == pytest.approx([0.4, 0.8, 1.2, 1.6])
    path = mr.save_figure(out, tmp_path / "rates.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_command_line_prints_json_and_writes_the_figure(tmp_path, monkeypatch, capsys):
    from planer.benchmarks import moulder

    run, calls = _runner({25: (8.0, 0), 50: (30.0, 0)})
    monkeypatch.setattr(moulder, "run", run)
    fig = tmp_path / "r.png"
    assert mr.main(["--rates", "50,25", "--quick", "--json", "--figure", str(fig)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["highest_meeting_hz_per_head"] == 25.0 and out["figure"] == str(fig)
    assert fig.stat().st_size > 0 and calls == [(True, 25.0), (True, 50.0)]


@pytest.mark.parametrize("args, named", [
    (["--rates", "25,abc"], "'abc'"),
    (["--figure", "/nonexistent/folder/x.png"], "/nonexistent/folder"),
])
def test_the_command_line_refuses_bad_arguments_in_one_line(args, named, capsys):
    with pytest.raises(SystemExit) as exc:
        mr.main(args)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert named in err and len(err.splitlines()) == 1
