"""The simulator's interfaces on their own thread: an asyncio loop that only serves them.

The machine is stepped on one thread; a :class:`~plant_sim.interfaces.plc_server.PlcServer` in the
same
process (the in-process HIL with ``--plc tcp``, a ``SimRunner`` built with
``threaded_interfaces`` and a ``PlcServer``) runs on an :class:`InterfaceLoop` so that it
answers whatever the stepping does. ``planer sim`` goes further and serves Modbus from a process
of its own (:mod:`plant_sim.interfaces.plc_process`). :class:`ServedPlc` switches a threaded
server off and
on for the ``modbus_restart`` fault (synchronously: the switch has happened when the call
returns).

Lock/queue discipline (see :mod:`plant_sim.interfaces.plc_server`): the interface thread reads the
register
snapshot the stepping thread publishes (under the server's lock) and queues accepted writes; the
stepping thread applies them in order before it advances the machine.

Priority (:mod:`core.realtime`, one definition for the simulator and the service, re-exported
here): a real PLC does not stop answering because a PC is busy, so the PLC process and the CAN
receive thread ask the OS for real-time scheduling (``SCHED_FIFO`` at a low priority, with
``SCHED_RESET_ON_FORK``; else a raised nice value; else they run at normal priority and the
banner says so), while the render workers and the stepping thread run at normal priority: on a
loaded host the interfaces and the service's bus thread win.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Coroutine
from concurrent.futures import Future
from typing import Any, TypeVar

from core.realtime import (
    INTERFACE_NICE,
    INTERFACE_RT_PRIORITY,
    RENDER_NICE,
    RT_CPU_LIMIT_S,
    guard_realtime,
    lower_priority,
    raise_priority,
)

__all__ = [
    "INTERFACE_NICE",
    "INTERFACE_RT_PRIORITY",
    "RENDER_NICE",
    "RT_CPU_LIMIT_S",
    "InterfaceLoop",
    "ServedPlc",
    "guard_realtime",
    "lower_priority",
    "raise_priority",
]

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
    """A :class:`~plant_sim.interfaces.plc_server.PlcServer` served from an :class:`InterfaceLoop`.

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

