"""A simulated-time run held to the wall clock (``planer hil --pace``, ``--http``, ``--opcua``).

The in-process HIL steps the machine as fast as the CPU allows: a 6 m run is over in seconds,
too fast for anyone watching its pages or its OPC UA server. :class:`Pacer` holds it to
``factor`` simulated seconds per wall second (1: real time). A run that cannot keep up runs as
fast as it can; it is not hurried afterwards to make up the time lost.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable

__all__ = ["MAX_CATCH_UP_S", "Pacer"]

MAX_CATCH_UP_S = 0.25
"""Wall seconds a paced run may be behind before the pace starts over from where it is."""


class Pacer:
    """Hold a simulated-time run to ``factor`` simulated seconds per wall second.

    Parameters
    ----------
    factor : float or None
        Simulated seconds per wall second (> 0); ``None``: as fast as it goes (each wait only
        yields to the event loop).
    clock : callable, keyword-only
        The wall clock, s (monotonic).
    sleep : callable, keyword-only
        ``await sleep(seconds)``.

    Attributes
    ----------
    behind_s : float
        Wall seconds the run fell behind the pace, summed over the times it was more than
        :data:`MAX_CATCH_UP_S` behind (and the pace started over).
    """

    def __init__(
        self,
        factor: float | None,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
    ) -> None:
        if factor is not None and not (isinstance(factor, (int, float))
                                       and math.isfinite(factor) and factor > 0):
            raise ValueError(f"pace factor must be a number > 0 (or None), got {factor!r}")
        self.factor = None if factor is None else float(factor)
        self._clock = clock
        self._sleep = sleep
        self._origin: tuple[float, float] | None = None  # (wall, simulated) at the start
        self.behind_s = 0.0

    async def wait(self, sim_t_s: float) -> None:
        """Wait until the wall clock reaches simulated time ``sim_t_s`` at the pace."""
        if self.factor is None:
            await self._sleep(0)  # a real suspension: Ctrl-C (task cancel) lands here
            return
        now = self._clock()
        if self._origin is None:
            self._origin = (now, float(sim_t_s))
        wall0, sim0 = self._origin
        due = wall0 + (float(sim_t_s) - sim0) / self.factor
        if due > now:
            await self._sleep(due - now)
            return
        if now - due > MAX_CATCH_UP_S:  # too slow for the pace: go on from here
            self.behind_s += now - due
            self._origin = (now, float(sim_t_s))
        await self._sleep(0)
