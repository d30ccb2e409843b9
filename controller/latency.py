"""The service process tuned for a short, steady pair-to-setpoint latency.

Where the tail of the latency came from (``planer bench``, ``docs/service.md``, "Latency") and
what takes it out of the control path:

* database commits (an fsync each, 7-35 ms on a virtual disk): the record is written after the
  setpoints by a writer thread, in batches (:mod:`controller.quality_records`);
* the garbage collector: a full collection walks every object the imports made (numpy, scipy,
  OpenCV, the vision's set-up), several ms; :func:`tune_for_latency` freezes what exists after
  the set-up (``gc.freeze``), so a collection only walks what the pairs made;
* the interpreter lock handed between threads: a thread that computes (the records' writer, the
  spool reader, the measurement thread) holds it up to the switch interval (5 ms by default)
  while the event loop waits to write a setpoint; :func:`tune_for_latency` shortens it;
* a busy host: every other process takes its share of the cores. The service's event loop (its
  bus thread: PLC and CAN cycles, a pair's control) runs at real-time priority
  (:func:`core.realtime.realtime_thread`, ``BUS_RT_PRIORITY``), and :func:`prioritize` gives
  the threads and processes doing a pair's heavy work (the measurement, the records' writer: it
  holds the interpreter lock at times) a raised nice value (:data:`MEASURE_NICE`), so they are
  not starved either; they stay under the fair scheduler, never real time.

:class:`GcPauses` records the collector's pauses for the benchmark.
"""

from __future__ import annotations

import gc
import sys
import time
from typing import Any

SWITCH_INTERVAL_S = 0.0005
"""Interpreter lock switch interval of the service process, s (Python's default: 0.005)."""
MEASURE_NICE = -10
"""Nice value of the measurement (thread or worker processes) and the records' writer: ahead of
normal processes on a busy host, still under the fair scheduler."""


def prioritize(service: Any, *, nice: int = MEASURE_NICE, source: Any = None) -> None:
    """Give the service's measurement thread and records' writer the nice value ``nice``.

    Applied by each thread as it starts its work (where the OS permits; otherwise they run at
    normal priority). Worker processes take it from ``MeasureWorkerPool(nice=...)``. A frame
    ``source`` with a reader thread (``raise_reader``: the spool's) has it scheduled with the
    bus thread: light I/O work a pair waits for.
    """
    service.measurement.thread_nice = int(nice)
    service.records.writer_nice = int(nice)
    raise_reader = getattr(source, "raise_reader", None)
    if callable(raise_reader):
        raise_reader()


def tune_for_latency(*, switch_interval_s: float = SWITCH_INTERVAL_S) -> dict[str, Any]:
    """Tune this process after its set-up: freeze the heap, shorten the lock's switch interval.

    Call once the service is built (measurer set up, buses opened), before the first pair.
    Objects made later are collected as usual; the frozen ones are never walked again.

    Parameters
    ----------
    switch_interval_s : float
        ``sys.setswitchinterval``, s (> 0).

    Returns
    -------
    dict
        ``frozen`` (objects moved to the permanent generation), ``switch_interval_s`` (before:
        ``previous_switch_interval_s``).
    """
    if not switch_interval_s > 0:
        raise ValueError(f"switch_interval_s must be > 0, got {switch_interval_s!r}")
    previous = sys.getswitchinterval()
    gc.collect()
    gc.freeze()
    sys.setswitchinterval(switch_interval_s)
    return {"frozen": gc.get_freeze_count(), "switch_interval_s": switch_interval_s,
            "previous_switch_interval_s": previous}


class GcPauses:
    """The garbage collector's pauses while active (``with GcPauses() as pauses: ...``).

    Attributes
    ----------
    pauses_ms : list of (int, float)
        ``(generation, pause in ms)`` of each collection, in order.
    """

    def __init__(self) -> None:
        self.pauses_ms: list[tuple[int, float]] = []
        self._t0 = 0.0

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
        else:
            self.pauses_ms.append((int(info.get("generation", -1)),
                                   (time.perf_counter() - self._t0) * 1e3))

    def __enter__(self) -> GcPauses:
        gc.callbacks.append(self._callback)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)

    def summary(self) -> dict[str, Any]:
        """``collections``, ``full`` (generation 2), ``max_pause_ms``, ``total_ms``."""
        pauses = [p for _, p in self.pauses_ms]
        return {
            "collections": len(pauses),
            "full": sum(1 for g, _ in self.pauses_ms if g == 2),
            "max_pause_ms": max(pauses, default=0.0),
            "total_ms": sum(pauses),
        }
