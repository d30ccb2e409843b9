"""The moulder benchmark's wiring (``planer bench --only moulder``) on a short run.

The moulder's service as ``planer serve`` runs it (``MoulderService`` from
``machine_moulder.toml``): four heads, each its own service with its own amplifier node, all on
one CAN master, the common registers read once per cycle, one pool of measurement workers; every
pair handed to a head comes back as that head's result, the counts add up per head and over all
heads, the coordinator writes the feed, and the text names every head. No timing is asserted.
"""

from __future__ import annotations

import asyncio
import json

import pytest

N_PAIRS = 4


@pytest.fixture(scope="module")
def frames_and_machine():
    from planer.benchmarks.moulder import _moulder_frames

    return _moulder_frames(N_PAIRS, seed=3)


def _run(tmp_path, frames_and_machine, **kw):
    from planer.benchmarks import moulder

    frames, machine = frames_and_machine
    return asyncio.run(moulder._run(frames, machine, rate_hz=25.0, workdir=tmp_path, **kw))


def test_four_heads_share_one_pool_and_every_pair_comes_back_to_its_head(
        tmp_path, frames_and_machine):
    from planer.benchmarks import moulder

    out = _run(tmp_path, frames_and_machine, workers=1)
    heads = out["heads"]
    assert list(heads) == [name for name, _ in moulder.moulder_heads()]
    assert [h["node_id"] for h in heads.values()] == [node for _, node in moulder.moulder_heads()]
    for name, h in heads.items():
        assert h["pairs_in"] == N_PAIRS, name
        assert h["handled"] + h["dropped"] + h["unfinished"] == h["pairs_in"], name
        assert h["dropped"] == 0 and h["unfinished"] == 0, name  # the queue holds them all
        assert h["measured"] + h["failed"] == h["handled"], name
        assert h["applied"] <= h["measured"], name
        assert h["state"] == "run" and h["safe_entries"] == 0, (name, h["events"])
        for key in ("p50_ms", "p99_ms", "max_ms", "breakdown_ms", "writes_feed"):
            assert key in h, (name, key)
    o = out["overall"]
    for key in ("pairs_in", "handled", "measured", "applied", "failed", "dropped"):
        assert o[key] == sum(h[key] for h in heads.values()), key
    assert o["handled"] == len(moulder.moulder_heads()) * N_PAIRS and o["measured"] >= 1
    assert out["workers"] == 1 and out["workers_shared"]
    assert out["meets"]["nothing_dropped"]  # every pair handled (a flagged one too)
    assert not any(h["writes_feed"] for h in heads.values())  # the coordinator does
    assert out["feed"]["cycles"] > 0 and out["feed"]["plc_errors"] == 0
    assert out["common_read_shared_by"] == list(heads)
    assert not out["at_target_rate"]  # 25 pairs/s a head: a wiring run, not the target
    for key in ("cpu_ms_per_pair", "service_cpu_ms_per_pair", "workers_cpu_ms_per_pair",
                "plc_cpu_ms_per_pair", "stand_in_cpu_ms_per_pair", "cores_busy",
                "service_loop_cpu_ms_per_pair", "service_threads_cpu_ms_per_pair"):
        assert o[key] is not None and o[key] >= 0, key
    assert o["workers_cpu_ms_per_pair"] > 0  # the pairs were measured in the worker
    assert [p.name for p in tmp_path.glob("*.sqlite")] == ["moulder.sqlite"]  # one log
    json.dumps(out)  # what --json prints
    text = moulder.text({**out, "machine": {"cores": 2, "load_avg": [1.0, 1.0, 1.0]}})
    assert all(f"{name} (node {node})" in text for name, node in moulder.moulder_heads())
    assert f"{o['handled']}/{o['pairs_in']} handled" in text


def test_without_workers_each_head_measures_in_the_service_process(tmp_path,
                                                                   frames_and_machine):
    out = _run(tmp_path, frames_and_machine, workers=0)
    assert out["workers"] == 0 and out["overall"]["workers_cpu_ms_per_pair"] == 0
    assert all(h["handled"] + h["dropped"] == N_PAIRS for h in out["heads"].values())


def test_bench_takes_the_moulder_part_only_when_named():
    import argparse

    from planer.commands import bench

    parser = argparse.ArgumentParser()
    bench.configure(parser)
    assert parser.parse_args(["--only", "moulder"]).only == ["moulder"]
    assert "moulder" in bench.PARTS and "moulder" not in bench.DEFAULT_PARTS


@pytest.mark.parametrize("kw, name", [
    ({"heads": 5}, "heads"), ({"heads": 0}, "heads"), ({"workers": -1}, "workers"),
    ({"rate_hz": 0.0}, "rate_hz"), ({"rate_hz": float("nan")}, "rate_hz"),
])
def test_run_refuses_nonsense_naming_the_parameter(kw, name):
    from planer.benchmarks import moulder

    with pytest.raises(ValueError, match=name):
        moulder.run(quick=True, **kw)


def test_the_heads_are_the_configuration_files_and_the_simulated_moulders():
    """The bench's heads come from ``machine_moulder.toml``; its pairs are the simulator's."""
    from config.loading import default_path
    from config.sim import load_sim
    from planer.benchmarks import moulder

    heads = moulder.moulder_heads()
    assert len(heads) == 4 and len({node for _, node in heads}) == 4  # a node id each
    sim = load_sim(default_path(moulder.MOULDER_SIM))
    assert [name for name, _ in heads] == [h.name for h in sim.heads]
