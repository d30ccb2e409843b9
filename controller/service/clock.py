"""Service time: the injected clock, never going backwards (one per service)."""

from __future__ import annotations

import math
from collections.abc import Callable

from controller.service.events import EventKind, EventLog

CLOCK_JITTER_S = 1e-9
"""A step back smaller than this is rounding, not a clock that went back (held, not reported)."""


class ServiceClock:
    """Hands out service time: ``now_s`` or the clock, never decreasing.

    A clock that jumps backwards (a badly set system clock, a restarted time source) would
    blind every timeout and stop the cyclic frames; the service time then continues from where
    it was and advances with the clock from there (the jump is reported once,
    ``CLOCK_WENT_BACK``).

    Parameters
    ----------
    clock : callable
        Monotonic seconds (simulated time in tests and the in-process HIL).
    report : EventLog
        Where the jump is reported.
    """

    def __init__(self, clock: Callable[[], float], report: EventLog) -> None:
        self.clock = clock
        self._report = report
        self._shift = 0.0  # added to the clock after it went backwards
        self.last_s: float | None = None
        """The last service time handed out (``None`` before the first)."""

    def now(self, now_s: float | None = None) -> float:
        """Service time of ``now_s`` (default: the clock), s; ``ValueError`` if not finite."""
        raw = self.clock() if now_s is None else float(now_s)
        if not math.isfinite(raw):
            raise ValueError(f"now_s must be finite, got {raw!r}")
        t = raw + self._shift
        last = self.last_s
        if last is not None and t < last:
            if last - t > CLOCK_JITTER_S:  # not the rounding of the shift itself
                self._shift += last - t
                self._report.emit(last, EventKind.CLOCK_WENT_BACK,
                                  f"clock went back by {last - t:.3f} s: service time continues")
            t = last
        self.last_s = t
        return t
