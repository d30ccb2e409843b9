"""The measurement workers' scaling (``planer bench``, ``service`` part; issue 11, item 3).

The measurement's throughput in this process (one core) and in 1..N worker processes
(N = the cores available), each fed as fast as it takes pairs, results taken in sequence
order, the configurations taking turns over several rounds (median); ``ratio`` = pairs/s with
N workers over pairs/s with one.
"""

from __future__ import annotations

import asyncio
import statistics
import time
from typing import Any


async def _pool_rate(pool: Any, frames: list, facts: Any) -> float:
    """Pairs/s of ``pool`` fed as fast as it takes them, results taken in sequence order."""
    from vision.selfcal import SelfCalibrator

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
        ``cores``, ``in_process_pairs_per_s`` (one thread, OpenCV on one thread), ``rows``
        (``workers``, ``pairs_per_s``, ``ratio`` to one worker, ``per_worker`` = ratio / N,
        ``rounds_pairs_per_s``); every worker runs OpenCV on one thread here, so the ratio is
        the processes' own.
    """
    import cv2

    from controller.measure_workers import MeasureWorkerPool, available_cores
    from controller.measurement import MeasurementStage, VisionMeasurers
    from vision.selfcal import SelfCalibrator

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
            t0 = time.perf_counter()
            for f in work:
                stage.measure_now(f, facts, {"calibrator": cal})
            return len(work) / (time.perf_counter() - t0)
        finally:
            cv2.setNumThreads(threads)

    pools = [MeasureWorkerPool(factory, workers=n, shape=frames[0].image_a.shape,
                               threads_per_worker=1) for n in range(1, top + 1)]
    here: list[float] = []
    rates: list[list[float]] = [[] for _ in pools]
    try:
        for pool in pools:
            pool.start()
        for f in work[:4]:
            stage.measure_now(f, facts, {"calibrator": cal})
        for _ in range(max(1, rounds)):
            here.append(in_process())
            for pool, got in zip(pools, rates, strict=True):
                got.append(asyncio.run(_pool_rate(pool, work, facts)))
    finally:
        for pool in pools:
            pool.close()
    rows = [{"workers": n, "pairs_per_s": statistics.median(got), "rounds_pairs_per_s": got}
            for n, got in enumerate(rates, start=1)]
    base = rows[0]["pairs_per_s"]
    for row in rows:
        row["ratio"] = row["pairs_per_s"] / base
        row["per_worker"] = row["ratio"] / row["workers"]
    return {"cores": cores, "in_process_pairs_per_s": statistics.median(here), "rows": rows,
            "target_per_worker": 0.8, "pairs": len(work), "rounds": max(1, rounds)}
