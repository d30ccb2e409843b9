"""The measurement workers' scaling (``planer bench``, ``service`` part).

The measurement's throughput in this process (one core) and in 1..N worker processes
(N = the cores available), each fed as fast as it takes pairs, results taken in sequence
order, the configurations taking turns over several rounds (median); ``ratio`` = pairs/s with
N workers over pairs/s with one, ``ratio_to_in_process`` = over pairs/s in this process. The CPU
time per pair of this process (the service's side: copying the pair into shared memory, the
messages, the event loop) and of the workers (the measurement and their side of the messages)
shows where a shortfall of the ratio goes.
"""

from __future__ import annotations

import asyncio
import os
import statistics
import time
from typing import Any


def _cpu_s(pid: int | None) -> float | None:
    """CPU time process ``pid`` used so far, s (``None``: not readable).

    The scheduler's nanoseconds of each of its threads (``/proc/PID/task/*/schedstat``), else
    the clock ticks of ``/proc/PID/stat`` (10 ms: too coarse for a short round).
    """
    if pid is None:
        return None
    try:
        total_ns = 0
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/schedstat") as fh:
                total_ns += int(fh.read().split()[0])
        return total_ns * 1e-9
    except (OSError, ValueError, IndexError):
        pass
    from planer.benchmarks.figures import proc_cpu_s

    return proc_cpu_s(pid, missing=None)


async def _pool_rate(pool: Any, frames: list, facts: Any) -> float:
    """Pairs/s of ``pool`` fed as fast as it takes them, results taken in sequence order."""
    from vision.calibration.selfcal import SelfCalibrator

    cal = SelfCalibrator()
    warm = [pool.submit(f, facts=facts, calibrator=cal) for f in frames[:pool.workers * 2]]
    for fut in warm:  # each worker set up for the facts (the first pairs build the measurer)
        await fut
    in_flight: list = []
    t0 = time.perf_counter()
    for f in frames:
        in_flight.append(pool.submit(f, facts=facts, calibrator=cal))
        if len(in_flight) >= pool.capacity:
            outcome = await in_flight.pop(0)
            for est in outcome.estimates:
                cal.update(est)
    for fut in in_flight:
        await fut
    return len(frames) / (time.perf_counter() - t0)


def scaling(frames: list, rig: Any, facts: Any, *, max_workers: int | None = None,
            repeat: int = 3, rounds: int = 5) -> dict[str, Any]:
    """Pairs/s of the measurement in this process and in 1..N worker processes.

    Every configuration is measured ``rounds`` times, the configurations taking turns (a shared
    machine's load changes from second to second: each gets the same mix), and the median of
    its rounds is its figure.

    Parameters
    ----------
    frames : list of Frame
        The pairs (measured ``repeat`` times over in each round).
    rig : Rig
        The rig.
    facts : MachineFacts
        The machine's facts (the measurer's set-up).
    max_workers : int, optional
        Largest N (default: the cores available).
    repeat : int
        Passes over ``frames`` per round.
    rounds : int
        Rounds per configuration.

    Returns
    -------
    dict
        ``cores``, ``in_process_pairs_per_s`` (one thread, OpenCV on one thread),
        ``in_process_cpu_us_per_pair``, ``rows`` (``workers``, ``pairs_per_s``, ``ratio`` to
        one worker, ``per_worker`` = ratio / N, ``ratio_to_in_process``,
        ``rounds_pairs_per_s``, ``service_cpu_us_per_pair`` this process's CPU time per pair,
        ``worker_cpu_us_per_pair`` all workers' together, ``None`` where not readable),
        ``load_avg`` at the end; every worker runs OpenCV on one thread here, so the ratio is
        the processes' own.
    """
    import cv2

    from controller.service.measurement import MeasurementStage, VisionMeasurers
    from controller.workers.pool import MeasureWorkerPool, available_cores
    from vision.calibration.selfcal import SelfCalibrator

    cores = available_cores()
    top = max(1, cores if max_workers is None else max_workers)
    work = list(frames) * max(1, repeat)
    factory = VisionMeasurers(rig)
    stage = MeasurementStage(None, factory, threaded=False)
    cal = SelfCalibrator()

    def in_process() -> float:
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            c0, t0 = time.process_time(), time.perf_counter()
            for f in work:
                stage.measure_now(f, facts, {"calibrator": cal})
            dt = time.perf_counter() - t0
            here_cpu.append((time.process_time() - c0) / len(work))
            return len(work) / dt
        finally:
            cv2.setNumThreads(threads)

    def pool_rate(pool: Any, n: int) -> float:
        before = [_cpu_s(pid) for pid in pool.pids]
        c0 = time.process_time()
        rate = asyncio.run(_pool_rate(pool, work, facts))
        done = len(work) + pool.workers * 2  # the warm-up pairs too
        cpu[n][0].append((time.process_time() - c0) / done)
        after = [_cpu_s(pid) for pid in pool.pids]
        if None not in before and None not in after and pool.restarts == 0:
            cpu[n][1].append(sum(a - b for a, b in zip(after, before, strict=True)) / done)
        return rate

    pools = [MeasureWorkerPool(factory, workers=n, shape=frames[0].image_a.shape,
                               threads_per_worker=1) for n in range(1, top + 1)]
    here: list[float] = []
    here_cpu: list[float] = []
    rates: list[list[float]] = [[] for _ in pools]
    cpu: list[tuple[list[float], list[float]]] = [([], []) for _ in pools]
    try:
        for pool in pools:
            pool.start()
        for f in work[:4]:
            stage.measure_now(f, facts, {"calibrator": cal})
        for r in range(max(1, rounds)):
            here.append(in_process())
            order = range(len(pools)) if r % 2 == 0 else reversed(range(len(pools)))
            for n in order:  # every other round in reverse: none always follows the same one
                rates[n].append(pool_rate(pools[n], n))
    finally:
        for pool in pools:
            pool.close()
    rows = [{"workers": n, "pairs_per_s": statistics.median(got), "rounds_pairs_per_s": got,
             "service_cpu_us_per_pair": _median_us(cpu[n - 1][0]),
             "worker_cpu_us_per_pair": _median_us(cpu[n - 1][1])}
            for n, got in enumerate(rates, start=1)]
    base = rows[0]["pairs_per_s"]
    inproc = statistics.median(here)
    for row in rows:
        row["ratio"] = row["pairs_per_s"] / base
        row["per_worker"] = row["ratio"] / row["workers"]
        row["ratio_to_in_process"] = row["pairs_per_s"] / inproc
    return {"cores": cores, "in_process_pairs_per_s": inproc, "rows": rows,
            "in_process_cpu_us_per_pair": _median_us(here_cpu),
            "target_per_worker": 0.8, "pairs": len(work), "rounds": max(1, rounds),
            "load_avg": [round(x, 2) for x in os.getloadavg()]}


def _median_us(per_pair_s: list[float]) -> float | None:
    """Median of per-pair CPU times, us (``None`` when none could be read)."""
    return statistics.median(per_pair_s) * 1e6 if per_pair_s else None
