"""Measurement in worker processes: order, crashes, hangs, the warning, the vision unchanged.

The service consumes the workers' results in sequence order (the loops see the pairs in order)
even when a later pair finishes first: a gate file makes pair 0's measurement wait until pair
1's is done, so the out-of-order finish is certain, not a matter of timing. A worker that dies
or hangs gives failed records naming the reason and is started again; nothing hangs.
"""

from __future__ import annotations

import asyncio
import os
import signal
import time
from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from config.machine import load_machine, machine_from_dict
from controller.quality.log import QualityLog
from controller.service.events import EventKind
from controller.service.supervisor import SafetyState
from controller.workers.pool import (
    MeasurementWorkerError,
    MeasureWorkerPool,
    available_cores,
    open_worker_pool,
    plan_workers,
)
from core.errors import ConfigError, MeasurementError
from planer.hil import Scenario, sim_config_for
from tests.support.plant_support import record_frames, run_for

SCENARIO = Scenario(runout_um=(0.0, 4.0, -2.0, 2.0), initial_feed_mm_s=800.0)
BACKSTOP_S = 60.0  # a worker waiting for a gate gives up after this (a broken test, not a pass)


# ---------------------------------------------------------------------------------------------
# measurers for the worker processes (picklable: module-level, plain data)


def _truth_of(frame) -> dict:
    tr = frame.truth
    return {k: tr[k] for k in ("pitch_mm", "mark_widths_mm", "bottoms_mm", "uniformity_cv",
                               "depth_um", "shift_px")}


@dataclass(frozen=True)
class TableMeasurers:
    """Factory of :class:`TableMeasurer` (what the simulator says each pair shows).

    ``table`` maps ``(counts_a, counts_b)`` to the pair's true marks; ``gates`` names, per pair,
    what happens first: ``("wait", file)`` waits until the file exists, ``("touch", file)``
    creates it after measuring, ``("kill",)`` kills the worker, ``("hang",)`` never returns,
    ``("bug",)`` raises what the vision never raises.
    """

    table: dict
    gates: dict

    def __call__(self, shape):
        return TableMeasurer(self.table, self.gates)


class TableMeasurer:
    def __init__(self, table, gates):
        self.table, self.gates = table, gates

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None):
        key = (counts_a, counts_b)
        gate = self.gates.get(key, ())
        if gate[:1] == ("wait",):
            end = time.monotonic() + BACKSTOP_S
            while not Path(gate[1]).exists() and time.monotonic() < end:
                time.sleep(0.001)
        elif gate[:1] == ("kill",):
            os.kill(os.getpid(), signal.SIGKILL)
        elif gate[:1] == ("hang",):
            while True:
                time.sleep(0.05)
        elif gate[:1] == ("bug",):
            raise Exception("a bug in the measurer")  # noqa: TRY002 - not a vision error
        if key not in self.table:
            raise MeasurementError(f"no truth for counts {key}")
        tr = self.table[key]
        out = SimpleNamespace(
            pitch_mm=float(tr["pitch_mm"]),
            mark_widths_mm=np.asarray(tr["mark_widths_mm"], dtype=float),
            bottoms_mm=np.asarray(tr["bottoms_mm"], dtype=float),
            uniformity_cv=float(tr["uniformity_cv"]),
            depth_um=float(tr["depth_um"]),
            shift_px=float(tr["shift_px"]),
            confidence=1.0,
            pid=os.getpid(),
        )
        if gate[:1] == ("touch",):
            Path(gate[1]).touch()
        return out


class InProcessTruth:
    """The plant's own measurer until the service runs (in this process)."""

    def __init__(self, frames):
        self.frames = frames

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None):
        tr = _truth_of(self.frames[(counts_a, counts_b)])
        return SimpleNamespace(confidence=1.0, **{k: (np.asarray(v, float) if isinstance(
            v, (list, tuple)) else v) for k, v in tr.items()})


# ---------------------------------------------------------------------------------------------
# the plant with the service in RUN, and pairs to submit


def _plant(tmp_path):
    from planer.hil import InProcessPlant

    cfg = load_machine()
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    frames: dict = {}
    plant = InProcessPlant(cfg, sim_config_for(SCENARIO), render_images=False,
                           measurer_factory=lambda shape: InProcessTruth(frames))
    record_frames(plant, frames)
    return plant


async def _running_plant(tmp_path):
    plant = _plant(tmp_path)
    await plant.start()
    res = await run_for(plant, 2.0)
    assert plant.service.state is SafetyState.RUN and res
    return plant


async def _collect_pairs(plant, n):
    """The next ``n`` pairs of the plant (the service's cycles go on meanwhile)."""
    out = []
    while len(out) < n:
        frames = plant.driver.step(plant.cfg.safety.cycle_s)
        await plant.service.tick(plant.clock())
        out += frames
    return out[:n]


def _pool(table, gates, *, workers=2, timeout_s=BACKSTOP_S):
    return MeasureWorkerPool(TableMeasurers(table, gates), workers=workers,
                             timeout_s=timeout_s).start()


def _seqs_in_log(tmp_path):
    with QualityLog(tmp_path / "q.sqlite", create=False) as log:
        return [r for r in log.records()]


# ---------------------------------------------------------------------------------------------


def test_results_are_consumed_in_sequence_order_when_a_later_pair_finishes_first(tmp_path):
    async def main():
        plant = await _running_plant(tmp_path)
        svc = plant.service
        pairs = await _collect_pairs(plant, 6)
        table = {(f.counts_a, f.counts_b): _truth_of(f) for f in pairs}
        gate = str(tmp_path / "pair1-done")
        gates = {(pairs[0].counts_a, pairs[0].counts_b): ("wait", gate),
                 (pairs[1].counts_a, pairs[1].counts_b): ("touch", gate)}
        pool = _pool(table, gates)
        svc.pipeline.use_workers(pool)
        seen = []  # what the loops were given, in the order given
        apply = svc.loops.apply

        async def recording_apply(att, measured_at, snap, t):
            seen.append(measured_at)
            return await apply(att, measured_at, snap, t)

        svc.loops.apply = recording_apply
        n_before = len(svc.results)
        try:
            for f in pairs:
                await svc.pipeline.submit(f)
                assert svc.pipeline.in_flight <= pool.capacity
            await svc.pipeline.drain()
        finally:
            pool.close()
        res = svc.results[n_before:]
        await plant.close()
        return pairs, res, seen

    pairs, res, seen = asyncio.run(main())
    # pair 1 finished before pair 0 (the gate), yet the results came in sequence order
    assert Path(tmp_path / "pair1-done").exists()
    assert [r.seq for r in res] == [f.seq for f in pairs]
    assert all(r.ok and r.applied for r in res), [r.error for r in res]
    pids = {r.measurement.pid for r in res}
    assert len(pids) == 2 and os.getpid() not in pids  # measured in both workers
    assert seen == sorted(seen) and len(seen) == len(pairs)  # the loops saw them in order
    logged = [r.seq for r in _seqs_in_log(tmp_path)]
    assert logged[-len(pairs):] == [f.seq for f in pairs]  # and the records too, once each
    assert len(logged) == len(set(logged))


@pytest.mark.parametrize("kind, reason", [
    (("kill",), "measurement worker 0 died (killed by SIGKILL)"),
    (("hang",), "took longer than 1 s for a pair (killed)"),
])
def test_a_worker_that_dies_or_hangs_gives_failed_records_not_a_hang(tmp_path, kind, reason):
    async def main():
        plant = await _running_plant(tmp_path)
        svc = plant.service
        pairs = await _collect_pairs(plant, 4)
        table = {(f.counts_a, f.counts_b): _truth_of(f) for f in pairs}
        bad = pairs[1]
        pool = _pool(table, {(bad.counts_a, bad.counts_b): kind}, workers=1,
                     timeout_s=1.0 if kind == ("hang",) else BACKSTOP_S)
        svc.pipeline.use_workers(pool)
        n_before = len(svc.results)
        try:
            for f in pairs:
                await svc.pipeline.submit(f)
            await asyncio.wait_for(svc.pipeline.drain(), BACKSTOP_S)
            restarts = pool.restarts
        finally:
            pool.close()
        res = svc.results[n_before:]
        events = [e for e in svc.events if e.kind is EventKind.SERVICE_ERROR]
        counters = dict(svc.counters)
        await plant.close()
        return pairs, res, events, restarts, counters

    pairs, res, events, restarts, counters = asyncio.run(main())
    assert [r.seq for r in res] == [f.seq for f in pairs]
    by_seq = {r.seq: r for r in res}
    failed = by_seq[pairs[1].seq]
    assert not failed.ok and reason in failed.error and failed.error.startswith(
        "measurement failed: ")
    assert by_seq[pairs[0].seq].ok  # before it: measured
    assert by_seq[pairs[3].seq].ok  # after it: the worker was started again and measured
    assert restarts >= 1 and counters["worker_restarts"] == restarts
    assert any(reason in e.text and "started again" in e.text for e in events)
    logged = {r.seq: r for r in _seqs_in_log(tmp_path)}
    assert not logged[pairs[1].seq].ok and reason in logged[pairs[1].seq].error


def test_a_measurer_bug_in_a_worker_is_a_service_error_and_the_safe_state(tmp_path):
    async def main():
        plant = await _running_plant(tmp_path)
        svc = plant.service
        pairs = await _collect_pairs(plant, 2)
        table = {(f.counts_a, f.counts_b): _truth_of(f) for f in pairs}
        pool = _pool(table, {(pairs[0].counts_a, pairs[0].counts_b): ("bug",)}, workers=1)
        svc.pipeline.use_workers(pool)
        n_before = len(svc.results)
        try:
            for f in pairs:
                await svc.pipeline.submit(f)
            await svc.pipeline.drain()
        finally:
            pool.close()
        res = svc.results[n_before:]
        state = svc.state
        await plant.close()
        return res, state, svc

    res, state, svc = asyncio.run(main())
    assert not res[0].ok and "MeasurementWorkerError" in res[0].error
    assert "a bug in the measurer" in res[0].error
    assert state is SafetyState.SAFE  # as for the same bug in process: the boundary acts
    assert svc.counters["errors"] >= 1


def test_workers_measure_as_this_process_does_and_the_calibrator_folds_in_order(tmp_path):
    from config.machine import rig_path
    from config.rig import load_rig
    from config.sim import default_sim
    from controller.service.measurement import MachineFacts, MeasurementStage, VisionMeasurers
    from plant_sim.machine.machine import Machine

    machine = Machine(default_sim(), seed=4)
    frames: list = []
    while len(frames) < 5:
        frames += machine.advance(0.05)
    frames = frames[:5]
    regs = machine.register_values()
    facts = MachineFacts(float(regs["cutterhead_radius_mm"]), int(regs["knives"]),
                         float(regs["spindle_rpm"]))
    factory = VisionMeasurers(load_rig(rig_path(load_machine())))

    class Snap(SimpleNamespace):
        def __getitem__(self, key):
            return getattr(self, key)

    snap = Snap(cutterhead_radius_mm=facts.radius_mm, knives=facts.knives,
                spindle_rpm=facts.spindle_rpm)
    here = MeasurementStage(None, factory, threaded=False)
    workers = MeasurementStage(None, factory, threaded=False)

    async def main():
        expected = [await here.measure(f, snap) for f in frames]
        with MeasureWorkerPool(factory, workers=2, shape=frames[0].image_a.shape) as pool:
            pool.start()
            workers.use_workers(pool)
            # the first pair's roll back first: the others, in flight at once, use it
            # wherever they go (before it their worker would be the first one's)
            started = [workers.start(frames[0], snap)]
            got = [await workers.finish(started[0])]
            started += [workers.start(f, snap) for f in frames[1:]]
            got += [await workers.finish(p) for p in started[1:]]
        return expected, got, started

    expected, got, started = asyncio.run(main())
    assert {p.worker for p in started} == {0, 1}  # through both workers' shared memory
    # the first pair with the same (fresh) calibrator: the same numbers; the later ones were
    # measured with the calibrator of the pairs finished before them (the first only)
    for i, ((e_err, e), (g_err, g)) in enumerate(zip(expected, got, strict=True)):
        assert e_err is None and g_err is None
        rel = 1e-9 if i == 0 else 1e-3
        assert g.pitch_mm == pytest.approx(e.pitch_mm, rel=rel)
        np.testing.assert_allclose(g.mark_widths_mm, e.mark_widths_mm, rtol=rel)
    # the board's calibrator saw every pair once, in order: as measured here
    board = frames[0].board_id
    mine = here.calibrator(board, facts)
    (master,) = workers._masters.values()  # noqa: SLF001 - the folded state itself
    assert master.pairs == mine.pairs == len(frames)
    assert master.update(got[0][1].calibration).gain == pytest.approx(
        mine.update(expected[0][1].calibration).gain, rel=1e-9)


# ---------------------------------------------------------------------------------------------
# how many workers, the warning, the configuration


@pytest.mark.parametrize("requested, cores, n, warns", [
    (1, 2, 1, False), (2, 2, 2, False), (3, 2, 2, True), (8, 1, 1, True), (4, 16, 4, False),
])
def test_more_workers_than_cores_is_one_warning_and_one_worker_per_core(requested, cores, n,
                                                                         warns):
    got, warning = plan_workers(requested, cores=cores)
    assert got == n == min(requested, cores)
    assert (warning is not None) == warns
    if warns:
        assert "\n" not in warning and warning.startswith("warning: ")
        assert f"{requested} measurement workers" in warning and f"in {cores} process" in warning


@pytest.mark.parametrize("requested, cores, name", [
    (0, 2, "requested"), (-1, 2, "requested"), (True, 2, "requested"), (2, 0, "cores"),
    (1.5, 2, "requested"),
])
def test_plan_workers_refuses_nonsense_naming_it(requested, cores, name):
    with pytest.raises(ValueError, match=name):
        plan_workers(requested, cores=cores)


def test_open_worker_pool_starts_no_process_for_zero_and_caps_at_the_cores():
    assert open_worker_pool(lambda shape: None, 0) == (None, None)
    with pytest.raises(ValueError, match="workers"):
        open_worker_pool(lambda shape: None, -2)
    pool, warning = open_worker_pool(TableMeasurers({}, {}), 3, cores=1)
    try:
        assert pool.workers == 1 and "only 1 core available" in warning
        assert all(pid is not None for pid in pool.pids)
    finally:
        pool.close()
    assert available_cores() >= 1


@pytest.mark.parametrize("table, workers", [({}, 0), ({"workers": 0}, 0), ({"workers": 3}, 3)])
def test_service_workers_key_is_read(table, workers):
    assert machine_from_dict({"service": table}).service.workers == workers


@pytest.mark.parametrize("table, message", [
    ({"workers": -1}, "service.workers must be >= 0"),
    ({"workers": 1.5}, "service.workers must be an integer"),
    ({"worker": 2}, "unknown key service.worker"),
])
def test_service_workers_key_is_checked_naming_it(table, message):
    with pytest.raises(ConfigError, match=message):
        machine_from_dict({"service": table})


def test_serve_refuses_negative_workers_in_one_line(capsys):
    from planer.cli import main

    assert main(["serve", "--workers", "-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--workers" in err


def test_a_closed_pool_answers_failed_not_never():
    async def main():
        pool = MeasureWorkerPool(TableMeasurers({}, {}), workers=1)
        pool.close()
        frame = SimpleNamespace(image_a=None, image_b=None, counts_a=0, counts_b=0,
                                speed_mm_s=0.0)
        return await pool.submit(frame)

    out = asyncio.run(main())
    assert out.error == "measurement workers closed" and out.measurement is None
    assert issubclass(MeasurementWorkerError, Exception)
    assert not issubclass(MeasurementWorkerError, (ValueError, RuntimeError))


@pytest.mark.parametrize("size", [0, 100, 16_384, 17_300, 60_000])
def test_a_workers_reply_is_one_write_that_recv_reads_back(size):
    # The reply goes out as header and body in one write (a worker descheduled between two
    # writes kept the bus thread waiting); Connection.recv must read it as it reads send().
    import multiprocessing
    from unittest import mock

    from controller.workers.process import _send_whole

    a, b = multiprocessing.Pipe()
    payload = ("done", 7, bytes(range(256)) * (size // 256), {"k": [1.5, None]})
    writes = []
    real = os.write
    with mock.patch("controller.workers.process.os.write",
                    side_effect=lambda fd, data: writes.append(len(data)) or real(fd, data)):
        _send_whole(a, payload)
    assert b.recv() == payload
    assert len(writes) == 1
    a.close()
    b.close()
