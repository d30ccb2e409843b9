"""Figures every bench reports the same way: latency statistics and a process's CPU time."""

from __future__ import annotations

import os

import numpy as np

__all__ = ["latency_stats", "proc_cpu_s"]


def latency_stats(values: list[float], *, middle: str = "median") -> dict[str, float]:
    """The median, ``p99`` and ``max`` of ``values`` (ms), or ``{}`` for none.

    ``middle`` is the median's key: ``"median"`` in the service bench's figures, ``"p50"`` in the
    moulder bench's (:mod:`planer.benchmarks.moulder`; each its JSON's contract).
    """
    if not values:
        return {}
    a = np.asarray(values, dtype=float)
    return {middle: float(np.median(a)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max())}


def proc_cpu_s(pid: int | None, *, missing: float | None = 0.0) -> float | None:
    """User + system CPU seconds of process ``pid`` so far (``/proc/PID/stat``, 10 ms ticks).

    ``missing`` when it cannot be read (no ``pid``, the process gone).
    """
    if pid is None:
        return missing
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            fields = fh.read().rsplit(b")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return missing
