"""The simulator's interfaces on their own thread: an asyncio loop that only serves them.

The machine is stepped on one thread; a :class:`~plant_sim.plc_server.PlcServer` in the same
process (the in-process HIL with ``--plc tcp``, a ``SimRunner`` built with
``threaded_interfaces`` and a ``PlcServer``) runs on an :class:`InterfaceLoop` so that it
answers whatever the stepping does. ``planer sim`` goes further and serves Modbus from a process
of its own (:mod:`plant_sim.plc_process`). :class:`ServedPlc` switches a threaded server off and
on for the ``modbus_restart`` fault (synchronously: the switch has happened when the call
returns).

Lock/queue discipline (see :mod:`plant_sim.plc_server`): the interface thread reads the register
snapshot the stepping thread publishes (under the server's lock) and queues accepted writes; the
stepping thread applies them in order before it advances the machine.

Priority (:func:`raise_priority`, :func:`lower_priority`): a real PLC does not stop answering
because a PC is busy, so the PLC process and the CAN receive thread ask the OS for real-time
scheduling (``SCHED_FIFO`` at a low priority; else a raised nice value; else they run at normal
priority and the banner says so), while the render workers run at a lowered one and the stepping
thread at normal priority: on a loaded host the interfaces and the service win.
"""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import Coroutine
from concurrent.futures import Future
from typing import Any, TypeVar

T = TypeVar("T")


class InterfaceLoop:
    """An asyncio event loop running on its own (daemon) thread.

    Parameters
    ----------
    name : str
        Thread name.
    """

    def __init__(self, name: str = "plant-interfaces") -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_forever()

    def submit(self, coro: Coroutine[Any, Any, T]) -> Future[T]:
        """Run ``coro`` on the interface loop; returns its future (thread-safe)."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    def run(self, coro: Coroutine[Any, Any, T], *, timeout_s: float = 30.0) -> T:
        """Run ``coro`` on the interface loop and wait for its result (re-raising its error)."""
        return self.submit(coro).result(timeout=timeout_s)

    async def run_async(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run ``coro`` on the interface loop; await its result from another loop."""
        return await asyncio.wrap_future(self.submit(coro))

    @property
    def alive(self) -> bool:
        """Whether the loop's thread runs."""
        return self._thread.is_alive()

    def close(self) -> None:
        """Stop the loop and join its thread (idempotent)."""
        if self._thread.is_alive():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(timeout=10)
        if not self._thread.is_alive() and not self.loop.is_closed():
            self.loop.close()


class ServedPlc:
    """A :class:`~plant_sim.plc_server.PlcServer` served from an :class:`InterfaceLoop`.

    Parameters
    ----------
    plc : PlcServer
        The server (built with ``queue_writes=True``).
    io : InterfaceLoop
        The loop it listens on.
    """

    def __init__(self, plc: Any, io: InterfaceLoop) -> None:
        self.plc = plc
        self.io = io

    def set_up(self, up: bool) -> None:
        """Listen (``True``) or stop listening and drop every client (``False``)."""
        self.io.run(self.plc.start() if up else self.plc.stop())


# ---------------------------------------------------------------------------------------------
# Priority: the interfaces answer like a PLC's, the heavy parts yield (issue 14)
# ---------------------------------------------------------------------------------------------

INTERFACE_RT_PRIORITY = 10
"""SCHED_FIFO priority of the PLC process and the CAN receive thread (1..99; low: above every
normal process, below the kernel's own real-time threads)."""
INTERFACE_NICE = -10
"""Nice value asked for when real-time scheduling is not permitted."""
RENDER_NICE = 0
"""Nice value of the render workers: normal. Lowered (nice 10) against six CPU hogs they got
about 2-3 % of a core each, the simulated clock fell to 0.13-0.17 and the machine was held for
its images long enough for the service to see "can gone" (measured; docs/simulator.md)."""
RT_CPU_LIMIT_S = 0.5
"""CPU seconds a real-time PLC process may run without blocking before the kernel signals it
(``RLIMIT_RTTIME``); it then drops to normal scheduling instead of starving the host."""


def raise_priority(*, rt_priority: int = INTERFACE_RT_PRIORITY, nice: int = INTERFACE_NICE,
                   os_module: Any = None) -> str:
    """Ask the OS to schedule the calling thread (Linux: thread; elsewhere process) first.

    Tries ``SCHED_FIFO`` at ``rt_priority``, then a nice value of ``nice``; never raises.

    Parameters
    ----------
    rt_priority : int
        Real-time priority, 1..99.
    nice : int
        Nice value to fall back on, -20..19.
    os_module : module, optional
        The ``os`` module (tests inject a stand-in).

    Returns
    -------
    str
        What was granted, e.g. ``"SCHED_FIFO 10"`` or ``"nice -10"``, or ``"normal (...)"``
        with the reason when neither was permitted.
    """
    o = os if os_module is None else os_module
    reasons = []
    fifo = getattr(o, "SCHED_FIFO", None)
    if fifo is not None and hasattr(o, "sched_setscheduler"):
        try:
            o.sched_setscheduler(0, fifo, o.sched_param(int(rt_priority)))
            return f"SCHED_FIFO {int(rt_priority)}"
        except (OSError, ValueError) as exc:
            reasons.append(f"SCHED_FIFO: {getattr(exc, 'strerror', None) or exc}")
    else:
        reasons.append("SCHED_FIFO: not offered by this OS")
    try:
        if hasattr(o, "setpriority"):
            o.setpriority(o.PRIO_PROCESS, 0, int(nice))
        else:
            o.nice(int(nice) - o.nice(0))
        return f"nice {int(nice)}"
    except (OSError, ValueError, AttributeError) as exc:
        reasons.append(f"nice {int(nice)}: {getattr(exc, 'strerror', None) or exc}")
    return f"normal ({'; '.join(reasons)})"


def lower_priority(nice: int = RENDER_NICE, *, os_module: Any = None) -> str:
    """Give the calling thread (Linux; elsewhere process) the nice value ``nice``; never raises.

    Returns
    -------
    str
        ``"nice 10"``, or ``"normal (...)"`` with the reason.
    """
    o = os if os_module is None else os_module
    try:
        if hasattr(o, "setpriority"):
            o.setpriority(o.PRIO_PROCESS, 0, int(nice))
        else:
            o.nice(int(nice) - o.nice(0))
        return f"nice {int(nice)}"
    except (OSError, ValueError, AttributeError) as exc:
        return f"normal (nice {int(nice)}: {getattr(exc, 'strerror', None) or exc})"


def guard_realtime(*, limit_s: float = RT_CPU_LIMIT_S) -> bool:
    """Drop the process to normal scheduling if it ever runs ``limit_s`` without blocking.

    A safety net for a real-time process (a bug that spins would otherwise take a core from
    the host): ``RLIMIT_RTTIME`` makes the kernel send ``SIGXCPU``, and the handler switches
    the main thread back to ``SCHED_OTHER``. Call from the main thread. Returns whether the
    guard is in place.
    """
    import resource
    import signal

    if not (hasattr(resource, "RLIMIT_RTTIME") and hasattr(signal, "SIGXCPU")):
        return False

    def demote(signum: int, frame: Any) -> None:  # pragma: no cover - only on a spin
        import contextlib

        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    try:
        us = int(limit_s * 1e6)
        hard = resource.getrlimit(resource.RLIMIT_RTTIME)[1]
        if hard != resource.RLIM_INFINITY:
            us = min(us, hard)
        resource.setrlimit(resource.RLIMIT_RTTIME, (us, hard))
        signal.signal(signal.SIGXCPU, demote)
    except (OSError, ValueError):
        return False
    return True
