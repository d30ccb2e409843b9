"""The service process tuned for a short, steady pair-to-setpoint latency.

Where the tail of the latency came from (``planer bench``, ``docs/service.md``, "Latency") and
what takes it out of the control path:

* database commits (an fsync each, 7-35 ms on a virtual disk): the record is written after the
  setpoints by a writer thread, in batches (:mod:`controller.service.records`);
* the garbage collector: a full collection walks every object the imports made (numpy, scipy,
  OpenCV, the vision's set-up), several ms; :func:`tune_for_latency` freezes what exists after
  the set-up (``gc.freeze``), so a collection only walks what the pairs made; and the
  collections that remain (0.2-3.4 ms each, one every 20-30 pairs, triggered by whichever
  allocation crossed the threshold: in the middle of a pair's control, or on the spool reader's
  thread while the event loop waits for the lock) run between pairs (:class:`IdleCollector`,
  :func:`collect_between_pairs`);
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
IDLE_GC_BACKSTOP = 20
"""While :class:`IdleCollector` runs the collections between pairs, the automatic collection's
first threshold is this many times the normal one: a backstop that collects by itself only when
that many objects were made without a pair (no pairs coming, or one that never ends)."""


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


def tune_for_latency(*, switch_interval_s: float = SWITCH_INTERVAL_S,
                     idle_gc: bool = True) -> dict[str, Any]:
    """Tune this process after its set-up: freeze the heap, shorten the lock's switch interval.

    Call once the service is built (measurer set up, buses opened), before the first pair.
    Objects made later are collected as usual (between pairs with ``idle_gc``); the frozen ones
    are never walked again.

    Parameters
    ----------
    switch_interval_s : float
        ``sys.setswitchinterval``, s (> 0).
    idle_gc : bool
        Install an :class:`IdleCollector`: the collections run between pairs
        (:func:`collect_between_pairs`, called by the pair pipeline after each record).

    Returns
    -------
    dict
        ``frozen`` (objects moved to the permanent generation), ``switch_interval_s`` (before:
        ``previous_switch_interval_s``), ``idle_gc``.
    """
    if not switch_interval_s > 0:
        raise ValueError(f"switch_interval_s must be > 0, got {switch_interval_s!r}")
    previous = sys.getswitchinterval()
    gc.collect()
    gc.freeze()
    sys.setswitchinterval(switch_interval_s)
    if idle_gc and _installed is None:
        IdleCollector().install()
    return {"frozen": gc.get_freeze_count(), "switch_interval_s": switch_interval_s,
            "previous_switch_interval_s": previous, "idle_gc": _installed is not None}


class IdleCollector:
    """The garbage collector run between pairs (:meth:`collect_due`), not in the middle of one.

    Installed (:meth:`install`, process-wide: the collector is), the automatic collection's
    first threshold is raised ``backstop`` times; :meth:`collect_due`, called where a pause
    costs nothing (after a pair's record, by :func:`collect_between_pairs`), collects the
    generation the normal thresholds make due, as the automatic collection would have: the same
    generations, the same counts, at a chosen moment. (CPython also puts a full collection off
    while few objects survived the last one; here it runs when the counts say so: with the
    set-up frozen it walks only what the pairs left, one every ~120 young collections.)

    Parameters
    ----------
    backstop : int
        Multiple of the normal first threshold the automatic collection keeps (>= 2).

    Attributes
    ----------
    collections : list of int
        Number of collections :meth:`collect_due` ran, per generation.
    """

    def __init__(self, *, backstop: int = IDLE_GC_BACKSTOP) -> None:
        if isinstance(backstop, bool) or not isinstance(backstop, int) or backstop < 2:
            raise ValueError(f"backstop must be an int >= 2, got {backstop!r}")
        self.backstop = backstop
        self.thresholds: tuple[int, int, int] = gc.get_threshold()  # type: ignore[assignment]
        self.collections = [0, 0, 0]

    def install(self) -> IdleCollector:
        """Raise the automatic threshold; :func:`collect_between_pairs` uses this collector."""
        global _installed
        if _installed is not None and _installed is not self:
            _installed.uninstall()
        self.thresholds = gc.get_threshold()  # type: ignore[assignment]
        t0, t1, t2 = self.thresholds
        if t0 > 0:  # collection not switched off altogether
            gc.set_threshold(t0 * self.backstop, t1, t2)
        _installed = self
        return self

    def uninstall(self) -> None:
        """The automatic thresholds as they were."""
        global _installed
        if _installed is self:
            gc.set_threshold(*self.thresholds)
            _installed = None

    def due(self) -> bool:
        """Whether a generation is due by the normal thresholds (:meth:`collect_due` would run).

        CPython's rule: the youngest generation's count over its threshold (0: switched off).
        """
        t0 = self.thresholds[0]
        return t0 > 0 and gc.get_count()[0] > t0

    def collect_due(self) -> int | None:
        """Collect the generation that is due by the normal thresholds, if any.

        Returns
        -------
        int or None
            The generation collected (0, 1 or 2), ``None`` when none was due.
        """
        if not self.due():
            return None
        _, t1, t2 = self.thresholds
        _, c1, c2 = gc.get_count()
        gen = 2 if (c1 > t1 and c2 > t2) else 1 if c1 > t1 else 0
        gc.collect(gen)
        self.collections[gen] += 1
        return gen


_installed: IdleCollector | None = None


def idle_collector() -> IdleCollector | None:
    """The installed :class:`IdleCollector` (``None``: the automatic collection as usual)."""
    return _installed


def collect_between_pairs() -> int | None:
    """Run the installed :class:`IdleCollector` (none installed: nothing; the generation, or None).

    Costs one ``gc.get_count`` when nothing is due.
    """
    return None if _installed is None else _installed.collect_due()


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
