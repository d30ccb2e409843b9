"""Scheduling priority of the threads that talk to the machine: raise, lower, guard.

A real PLC does not stop answering because a PC is busy, and a service must send its
``RPDO3`` every 20 ms whatever else the host runs (the amplifier's setpoint timeout is
100 ms). So the threads that serve or drive a fieldbus ask the OS to run them first:

* :func:`raise_priority`: ``SCHED_FIFO`` at a low real-time priority, else a raised nice value,
  else normal priority with the reason (never raises). The policy is asked with
  ``SCHED_RESET_ON_FORK``: every thread and process the raised thread creates afterwards
  (executor workers, OpenCV's and BLAS's thread pools, subprocesses) starts at normal
  priority, so heavy work never inherits real time by accident.
* :func:`lower_priority`: back to ``SCHED_OTHER`` (if real time) at a nice value; the heavy
  parts (render workers, measurement threads) call it.
* :func:`guard_realtime`: a safety net. ``RLIMIT_RTTIME`` makes the kernel send ``SIGXCPU`` to
  a real-time thread that runs ``limit_s`` of CPU without blocking, and the handler drops every
  thread raised here back to normal scheduling, so a bug that spins cannot lock the host (the
  kernel's real-time throttling, 95 % of each second by default, is the last net).
* :func:`cpu_wakeup_latency`: while a block runs, ask the kernel (PM QoS,
  ``/dev/cpu_dma_latency``) to keep every core's wake-up latency at most so many
  microseconds: an idle core then polls instead of halting (on a virtual machine: instead of
  leaving the CPU to the host), so a pair that arrives, a Modbus answer and the thread that
  waits for them are on a core at once. Costs power and, on a shared host, CPU time of the
  host while idle; the setting real-time Linux deployments use (``tuned``'s
  latency-performance profile).
* :func:`realtime_thread`: the three together around a block (the service's bus thread while
  the service runs), restoring normal priority and the previous guard afterwards. Threads that
  share the interpreter lock with the raised one (``others``) are raised with it: a thread at
  normal priority descheduled by a CPU hog *while holding the lock* would otherwise keep the
  real-time thread waiting for tens of milliseconds (priority inversion; measured: 25-45 ms
  waits of the service's bus thread behind its spool reader under six hogs).

On Linux these act on the calling *thread* (``sched_setscheduler(0)`` and
``setpriority(PRIO_PROCESS, 0)`` name the thread); elsewhere on the process. Real-time
scheduling needs ``CAP_SYS_NICE`` or an ``RLIMIT_RTPRIO`` (``ulimit -r``) of at least the
priority asked; inside an unprivileged user namespace (``unshare -r``) only the latter works.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterable, Iterator
from typing import Any

__all__ = [
    "BUS_RT_PRIORITY",
    "INTERFACE_NICE",
    "INTERFACE_RT_PRIORITY",
    "RENDER_NICE",
    "RT_CPU_LIMIT_S",
    "cpu_wakeup_latency",
    "guard_realtime",
    "lower_priority",
    "raise_priority",
    "raise_thread",
    "realtime_threads",
    "realtime_thread",
]

INTERFACE_RT_PRIORITY = 10
"""SCHED_FIFO priority of the simulated PLC process and the CAN receive thread (1..99; low:
above every normal process, below the kernel's own real-time threads)."""
BUS_RT_PRIORITY = 9
"""SCHED_FIFO priority of the service's bus thread (the event loop that runs the PLC and CAN
cycles): just below the simulated machine's interfaces, so on one host the machine side answers
first."""
INTERFACE_NICE = -10
"""Nice value asked for when real-time scheduling is not permitted."""
RENDER_NICE = 0
"""Nice value of the simulator's render workers: normal. Lowered (nice 10) against six CPU
hogs they got about 2-3 % of a core each, the simulated clock fell to 0.13-0.17 and the machine
was held for its images long enough for the service to see "can gone" (docs/simulator.md)."""
RT_CPU_LIMIT_S = 0.5
"""CPU seconds a real-time thread may run without blocking before the kernel signals it
(``RLIMIT_RTTIME``); it then drops to normal scheduling instead of starving the host."""

_lock = threading.Lock()
_raised: dict[int, str] = {}  # native thread id -> name, threads at real-time priority


def realtime_threads() -> dict[int, str]:
    """Threads of this process raised to real time by :func:`raise_priority`: id -> name."""
    with _lock:
        return dict(_raised)


def _why(exc: BaseException) -> str:
    return str(getattr(exc, "strerror", None) or exc)


CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"
"""The kernel's PM QoS request for the CPUs' wake-up latency (held while the file is open)."""


@contextlib.contextmanager
def cpu_wakeup_latency(max_us: int | None, *,
                       device: str = CPU_LATENCY_DEVICE) -> Iterator[str]:
    """Keep every core's wake-up latency at most ``max_us`` while the block runs (PM QoS).

    The request holds while the device file is open and ends when it is closed (also when the
    process dies). Never raises for the request: without the device or the permission (it
    needs root) the block runs as the system has it, and the yielded text says why.

    Parameters
    ----------
    max_us : int or None
        Largest wake-up latency, us (0: idle cores poll); ``None`` or negative: leave it.
    device : str
        The PM QoS device.

    Yields
    ------
    str
        ``"cores wake within N us"`` or ``"as the system has it (reason)"``.
    """
    if max_us is None or isinstance(max_us, bool) or int(max_us) < 0:
        yield "as the system has it (not asked)"
        return
    try:
        fd = os.open(device, os.O_WRONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        yield f"as the system has it ({device}: {_why(exc)})"
        return
    try:
        try:
            os.write(fd, int(max_us).to_bytes(4, "little", signed=True))
        except OSError as exc:
            yield f"as the system has it ({device}: {_why(exc)})"
            return
        yield f"cores wake within {int(max_us)} us"
    finally:
        os.close(fd)


def _set_normal(o: Any) -> None:
    """``SCHED_OTHER`` for the calling thread, if it is real time (raises ``OSError``)."""
    other = getattr(o, "SCHED_OTHER", None)
    get = getattr(o, "sched_getscheduler", None)
    if other is None or get is None:
        return
    if get(0) != other:
        o.sched_setscheduler(0, other, o.sched_param(0))


def _nice(o: Any, nice: int) -> None:
    if hasattr(o, "setpriority"):
        o.setpriority(o.PRIO_PROCESS, 0, int(nice))
    else:
        o.nice(int(nice) - o.nice(0))


def raise_priority(*, rt_priority: int = INTERFACE_RT_PRIORITY, nice: int = INTERFACE_NICE,
                   reset_on_fork: bool = True, os_module: Any = None) -> str:
    """Ask the OS to schedule the calling thread (Linux: thread; elsewhere process) first.

    Tries ``SCHED_FIFO`` at ``rt_priority``, then a nice value of ``nice``; never raises.

    Parameters
    ----------
    rt_priority : int
        Real-time priority, 1..99.
    nice : int
        Nice value to fall back on, -20..19.
    reset_on_fork : bool
        Ask with ``SCHED_RESET_ON_FORK`` (where offered): threads and processes created by this
        thread start at normal priority.
    os_module : module, optional
        The ``os`` module (tests inject a stand-in).

    Returns
    -------
    str
        What was granted, e.g. ``"SCHED_FIFO 10"`` or ``"nice -10"``, or ``"normal (...)"``
        with the reason when neither was permitted.
    """
    o = os if os_module is None else os_module
    reset = int(getattr(o, "SCHED_RESET_ON_FORK", 0)) if reset_on_fork else 0
    reasons = []
    fifo = getattr(o, "SCHED_FIFO", None)
    if fifo is not None and hasattr(o, "sched_setscheduler"):
        try:
            o.sched_setscheduler(0, fifo | reset, o.sched_param(int(rt_priority)))
        except (OSError, ValueError) as exc:
            reasons.append(f"SCHED_FIFO: {_why(exc)}")
        else:
            if os_module is None:
                with _lock:
                    _raised[threading.get_native_id()] = threading.current_thread().name
            return f"SCHED_FIFO {int(rt_priority)}"
    else:
        reasons.append("SCHED_FIFO: not offered by this OS")
    if reset and hasattr(o, "SCHED_OTHER"):
        with contextlib.suppress(OSError, ValueError):  # children start at nice 0
            o.sched_setscheduler(0, o.SCHED_OTHER | reset, o.sched_param(0))
    try:
        _nice(o, nice)
        return f"nice {int(nice)}"
    except (OSError, ValueError, AttributeError) as exc:
        reasons.append(f"nice {int(nice)}: {_why(exc)}")
    return f"normal ({'; '.join(reasons)})"


def raise_thread(native_id: int, *, rt_priority: int = INTERFACE_RT_PRIORITY,
                 nice: int = INTERFACE_NICE, name: str = "") -> str:
    """:func:`raise_priority` for another thread of this process (Linux: by its native id).

    Returns what was granted, as :func:`raise_priority`; never raises.
    """
    tid = int(native_id)
    reasons = []
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                              os.sched_param(int(rt_priority)))
    except (OSError, ValueError, AttributeError) as exc:
        reasons.append(f"SCHED_FIFO: {_why(exc)}")
    else:
        with _lock:
            _raised[tid] = name or str(tid)
        return f"SCHED_FIFO {int(rt_priority)}"
    try:
        os.setpriority(os.PRIO_PROCESS, tid, int(nice))
        return f"nice {int(nice)}"
    except (OSError, ValueError, AttributeError) as exc:
        reasons.append(f"nice {int(nice)}: {_why(exc)}")
    return f"normal ({'; '.join(reasons)})"


def _lower_thread(native_id: int, nice: int) -> None:
    """Another thread of this process back to ``SCHED_OTHER`` at ``nice`` (never raises)."""
    tid = int(native_id)
    with contextlib.suppress(OSError, ValueError, AttributeError):
        if os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK != os.SCHED_OTHER:
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
    with _lock:
        _raised.pop(tid, None)
    with contextlib.suppress(OSError, ValueError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, tid, int(nice))


def lower_priority(nice: int = RENDER_NICE, *, os_module: Any = None) -> str:
    """Normal scheduling at nice value ``nice`` for the calling thread (Linux; else process).

    A real-time thread goes back to ``SCHED_OTHER`` first. Never raises.

    Returns
    -------
    str
        ``"nice 10"``, or ``"normal (...)"`` with the reason.
    """
    o = os if os_module is None else os_module
    try:
        _set_normal(o)
    except (OSError, ValueError) as exc:
        return f"normal (SCHED_OTHER: {_why(exc)})"
    if os_module is None:
        with _lock:
            _raised.pop(threading.get_native_id(), None)
    try:
        _nice(o, nice)
        return f"nice {int(nice)}"
    except (OSError, ValueError, AttributeError) as exc:
        return f"normal (nice {int(nice)}: {_why(exc)})"


def _demote_all(signum: int = 0, frame: Any = None) -> None:  # pragma: no cover - on a spin
    """``SIGXCPU``: every thread raised here back to normal scheduling."""
    with _lock:
        tids = list(_raised)
        _raised.clear()
    for tid in tids:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))


def guard_realtime(*, limit_s: float = RT_CPU_LIMIT_S) -> bool:
    """Drop the raised threads to normal scheduling if one runs ``limit_s`` without blocking.

    ``RLIMIT_RTTIME`` (soft limit; the hard one is left) makes the kernel send ``SIGXCPU``, and
    the handler switches every thread :func:`raise_priority` raised back to ``SCHED_OTHER``.
    Call from the main thread (Python runs signal handlers there). Returns whether the guard is
    in place.
    """
    import resource
    import signal

    if not (hasattr(resource, "RLIMIT_RTTIME") and hasattr(signal, "SIGXCPU")):
        return False
    try:
        us = int(limit_s * 1e6)
        hard = resource.getrlimit(resource.RLIMIT_RTTIME)[1]
        if hard != resource.RLIM_INFINITY:
            us = min(us, hard)
        signal.signal(signal.SIGXCPU, _demote_all)
        resource.setrlimit(resource.RLIMIT_RTTIME, (us, hard))
    except (OSError, ValueError):  # ValueError: not the main thread
        return False
    return True


@contextlib.contextmanager
def realtime_thread(*, rt_priority: int = BUS_RT_PRIORITY, nice: int = INTERFACE_NICE,
                    limit_s: float = RT_CPU_LIMIT_S,
                    others: Iterable[threading.Thread] = ()) -> Iterator[str]:
    """Run the block with the calling thread raised (:func:`raise_priority`) and guarded.

    Yields what was granted. Afterwards the thread is back at normal priority with the nice
    value it had, and the ``SIGXCPU`` handler and ``RLIMIT_RTTIME`` are what they were. The
    guard is set only when called from the main thread and real time was granted.

    Parameters
    ----------
    rt_priority, nice : int
        As :func:`raise_priority`.
    limit_s : float
        CPU seconds without blocking before a raised thread is dropped (:func:`guard_realtime`).
    others : iterable of threading.Thread
        Light threads sharing the interpreter lock with this one (I/O: a spool reader, a log
        writer; never the heavy work), raised alike for the block (:func:`raise_thread`) and
        back at normal priority afterwards (nice 0).
    """
    import resource
    import signal

    try:
        before = os.getpriority(os.PRIO_PROCESS, 0)
    except (AttributeError, OSError):
        before = 0
    granted = raise_priority(rt_priority=rt_priority, nice=nice)
    if granted.startswith(("SCHED_FIFO", "nice")):
        raised = [t for t in others if t.native_id is not None and t.is_alive()]
        for t in raised:
            raise_thread(t.native_id, rt_priority=rt_priority, nice=nice, name=t.name)
    else:
        raised = []
    restore: tuple[Any, Any] | None = None
    if granted.startswith("SCHED_FIFO") and threading.current_thread() is threading.main_thread():
        with contextlib.suppress(AttributeError, OSError, ValueError):
            restore = (signal.getsignal(signal.SIGXCPU),
                       resource.getrlimit(resource.RLIMIT_RTTIME))
        if not guard_realtime(limit_s=limit_s):
            restore = None
    try:
        yield granted
    finally:
        for t in raised:
            _lower_thread(t.native_id, 0)  # type: ignore[arg-type]
        lower_priority(before)
        if restore is not None:
            handler, limits = restore
            with contextlib.suppress(OSError, ValueError):
                resource.setrlimit(resource.RLIMIT_RTTIME, limits)
                signal.signal(signal.SIGXCPU, handler)
