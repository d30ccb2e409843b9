"""Soak (planer/hil/soak.py): memory and open files stay flat over a run with faults.

The hour-long run is ``python -m planer.hil.soak``; here a minute of machine time with a fault
every few seconds, the truth-reading measurer and no images, so it is quick.
"""

from __future__ import annotations

import asyncio
import dataclasses

import pytest

from planer.hil.soak import FAULT_CYCLE, SoakSample, flatness, format_table, run_soak


@pytest.fixture(scope="module")
def soak(tmp_path_factory):
    log = tmp_path_factory.mktemp("soak") / "soak.sqlite"
    return asyncio.run(run_soak(duration_s=60.0, fault_every_s=5.0, sample_every_s=10.0,
                                render_images=False, trace=False, log_path=log))


def test_short_soak_keeps_memory_and_files_flat(soak):
    samples = [SoakSample(**s) for s in soak["samples"]]
    assert [s.machine_s for s in samples] == pytest.approx([10.0 * i for i in range(7)], abs=0.01)
    # every kind of the cycle was played, twice over; the run went on measuring and logging
    assert soak["faults"] == 11 >= 2 * len(FAULT_CYCLE) - 1
    assert soak["pairs"] > 400 and samples[-1].records == soak["pairs"]
    assert samples[-1].safe_entries >= 2  # the Modbus restarts and CAN silences tripped it
    assert {"plc gone", "can gone"} <= set(soak["safe_reasons"])
    after = [s for s in samples if s.machine_s >= 20.0]  # after one round of every fault
    # open files: the Modbus restarts and the CAN faults leave no socket or handle behind
    assert len({s.fds for s in after}) == 1, [s.fds for s in samples]
    flat = soak["flatness"]
    assert flat["from_s"] == pytest.approx(20.0) and flat["fds"] == 0
    # Python objects: nothing kept per pair (a leaked result or frame is several objects each)
    assert abs(flat["objects_per_pair"]) < 0.5, flat
    assert flat["rss_mb"] < 20.0, flat  # no gross leak outside Python either


def _sample(t, *, objects=1000, fds=10, pairs=None, traced=1.0, rss=100.0):
    return SoakSample(machine_s=t, wall_s=t / 10, rss_mb=rss, traced_mb=traced, objects=objects,
                      fds=fds, pairs=int(t * 9) if pairs is None else pairs, pair_ms_p50=2.0,
                      pair_ms_p99=5.0, safe_entries=0, records=int(t * 9), faults=0)


def test_flatness_measures_growth_after_the_warm_up():
    flat_run = [_sample(t, objects=5000 if t == 0 else 1000) for t in range(0, 3601, 600)]
    f = flatness(flat_run)
    assert f["from_s"] == 1200 and f["to_s"] == 3600  # the first quarter is warm-up
    assert f["objects"] == 0 and f["fds"] == 0 and f["traced_mb_per_h"] == 0
    leaky = [dataclasses.replace(s, objects=1000 + 3 * s.pairs, fds=10 + int(s.machine_s // 600),
                                 traced_mb=1.0 + s.machine_s / 3600)
             for s in flat_run]
    f = flatness(leaky)
    assert f["objects_per_pair"] == pytest.approx(3.0) and f["fds"] == 4
    assert f["traced_mb_per_h"] == pytest.approx(1.0)
    assert flatness(flat_run[:1]) == {}
    table = format_table(flat_run)
    assert table.count("\n") == len(flat_run) + 1 and "| 60.0 min |" in table
