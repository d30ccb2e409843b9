"""core.realtime: raising, lowering and guarding the priority of the bus threads.

The fallbacks are checked with an ``os`` stand-in; the real OS is asked only for a short-lived
thread, and the real-time assertions apply where this host permits real-time scheduling.
"""

from __future__ import annotations

import os
import resource
import signal
import threading

import pytest

from core import realtime


class FakeOs:
    """An ``os`` stand-in with the Linux scheduling calls: records, refuses when told to."""

    SCHED_OTHER = 0
    SCHED_FIFO = 1
    SCHED_RESET_ON_FORK = 0x40000000
    PRIO_PROCESS = 0

    def __init__(self, *, fifo_ok: bool, nice_ok: bool, policy: int = 0) -> None:
        self.fifo_ok, self.nice_ok, self.policy = fifo_ok, nice_ok, policy
        self.asked: list[tuple] = []

    @staticmethod
    def sched_param(priority: int) -> tuple:
        return ("param", priority)

    def sched_getscheduler(self, pid: int) -> int:
        return self.policy

    def sched_setscheduler(self, pid: int, policy: int, param: tuple) -> None:
        self.asked.append(("sched", pid, policy, param))
        if policy & ~self.SCHED_RESET_ON_FORK == self.SCHED_FIFO and not self.fifo_ok:
            raise PermissionError(1, "Operation not permitted")
        self.policy = policy & ~self.SCHED_RESET_ON_FORK

    def setpriority(self, which: int, who: int, value: int) -> None:
        self.asked.append(("nice", which, who, value))
        if not self.nice_ok:
            raise PermissionError(13, "Permission denied")


RESET = FakeOs.SCHED_RESET_ON_FORK


@pytest.mark.parametrize(("fifo_ok", "nice_ok", "granted"), [
    (True, True, "SCHED_FIFO 7"),
    (False, True, "nice -5"),
    (False, False, "normal"),
])
def test_raise_asks_fifo_with_reset_on_fork_then_nice_then_says_why(fifo_ok, nice_ok, granted):
    fake = FakeOs(fifo_ok=fifo_ok, nice_ok=nice_ok)
    got = realtime.raise_priority(rt_priority=7, nice=-5, os_module=fake)
    assert got.startswith(granted)
    # the calling thread, real time, and every thread it starts later at normal priority
    assert fake.asked[0] == ("sched", 0, FakeOs.SCHED_FIFO | RESET, ("param", 7))
    if fifo_ok:
        assert fake.asked[1:] == []  # nothing else touched once real time is granted
    else:  # normal policy with reset-on-fork (children at nice 0), then the nice value
        assert fake.asked[1] == ("sched", 0, FakeOs.SCHED_OTHER | RESET, ("param", 0))
        assert fake.asked[2] == ("nice", FakeOs.PRIO_PROCESS, 0, -5)
    if granted == "normal":
        assert "Operation not permitted" in got and "Permission denied" in got


def test_raise_without_reset_on_fork_asks_the_bare_policy():
    fake = FakeOs(fifo_ok=True, nice_ok=True)
    realtime.raise_priority(rt_priority=3, reset_on_fork=False, os_module=fake)
    assert fake.asked == [("sched", 0, FakeOs.SCHED_FIFO, ("param", 3))]


@pytest.mark.parametrize(("policy", "expect_sched"), [
    (FakeOs.SCHED_FIFO, True),    # a real-time thread goes back to SCHED_OTHER first
    (FakeOs.SCHED_OTHER, False),  # a normal one only gets its nice value
])
def test_lower_drops_real_time_then_sets_nice(policy, expect_sched):
    fake = FakeOs(fifo_ok=True, nice_ok=True, policy=policy)
    assert realtime.lower_priority(12, os_module=fake) == "nice 12"
    scheds = [a for a in fake.asked if a[0] == "sched"]
    assert scheds == ([("sched", 0, FakeOs.SCHED_OTHER, ("param", 0))] if expect_sched else [])
    assert fake.asked[-1] == ("nice", FakeOs.PRIO_PROCESS, 0, 12)
    assert fake.policy == FakeOs.SCHED_OTHER
    refused = realtime.lower_priority(12, os_module=FakeOs(fifo_ok=False, nice_ok=False))
    assert refused.startswith("normal") and "Permission denied" in refused


def test_interfaces_reexport_the_one_definition():
    from plant_sim.interfaces import thread as interfaces

    for name in ("raise_priority", "lower_priority", "guard_realtime", "RENDER_NICE",
                 "INTERFACE_RT_PRIORITY", "INTERFACE_NICE", "RT_CPU_LIMIT_S"):
        assert getattr(interfaces, name) is getattr(realtime, name)
    assert realtime.BUS_RT_PRIORITY < realtime.INTERFACE_RT_PRIORITY  # the machine side first


def _in_thread(fn):
    """Run ``fn`` on a fresh thread; its result (re-raising its error)."""
    out: dict = {}

    def run() -> None:
        try:
            out["v"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed back to the test
            out["e"] = exc

    t = threading.Thread(target=run)
    t.start()
    t.join(60)
    assert not t.is_alive()
    if "e" in out:
        raise out["e"]
    return out["v"]


def test_realtime_thread_raises_children_start_normal_and_it_ends_normal():
    """The real OS: inside the block the thread is raised (where permitted), a thread it starts
    runs at normal priority (reset on fork), and afterwards it is back at normal priority."""
    def body():
        base = os.getpriority(os.PRIO_PROCESS, 0)
        with realtime.realtime_thread(rt_priority=2) as granted:
            inside = os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK
            registered = threading.get_native_id() in realtime.realtime_threads()
            child = _in_thread(lambda: (os.sched_getscheduler(0), os.getpriority(
                os.PRIO_PROCESS, 0)))
        after = os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, 0)
        left = threading.get_native_id() in realtime.realtime_threads()
        return base, granted, inside, registered, child, after, left

    base, granted, inside, registered, child, after, left = _in_thread(body)
    assert granted.startswith(("SCHED_FIFO 2", "nice", "normal ("))
    if granted.startswith("SCHED_FIFO"):
        assert inside == os.SCHED_FIFO and registered
    assert child[0] == os.SCHED_OTHER and child[1] >= 0  # never real time nor a raised nice
    assert after == (os.SCHED_OTHER, base) and not left


def test_guard_sets_the_cpu_limit_and_a_handler_that_demotes_raised_threads():
    old_handler = signal.getsignal(signal.SIGXCPU)
    old_limit = resource.getrlimit(resource.RLIMIT_RTTIME)
    try:
        assert realtime.guard_realtime(limit_s=0.25)
        soft, hard = resource.getrlimit(resource.RLIMIT_RTTIME)
        assert soft == (250_000 if hard == resource.RLIM_INFINITY else min(250_000, hard))
        handler = signal.getsignal(signal.SIGXCPU)
        assert callable(handler)
        # not from the main thread: refused, nothing changed
        assert _in_thread(lambda: realtime.guard_realtime(limit_s=1.0)) is False

        def raised_then_demoted():
            granted = realtime.raise_priority(rt_priority=2)
            handler(signal.SIGXCPU, None)  # what the kernel's signal would do
            return granted, os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK

        granted, policy = _in_thread(raised_then_demoted)
        if granted.startswith("SCHED_FIFO"):
            assert policy == os.SCHED_OTHER
        assert realtime.realtime_threads() == {}
    finally:
        signal.signal(signal.SIGXCPU, old_handler)
        resource.setrlimit(resource.RLIMIT_RTTIME, old_limit)


def test_realtime_thread_restores_the_guard_it_set():
    old_handler = signal.getsignal(signal.SIGXCPU)
    old_limit = resource.getrlimit(resource.RLIMIT_RTTIME)
    base = os.getpriority(os.PRIO_PROCESS, 0)
    try:
        with realtime.realtime_thread(rt_priority=2) as granted:
            during = resource.getrlimit(resource.RLIMIT_RTTIME)
        if granted.startswith("SCHED_FIFO"):
            assert during[0] == int(realtime.RT_CPU_LIMIT_S * 1e6)
        assert resource.getrlimit(resource.RLIMIT_RTTIME) == old_limit
        assert signal.getsignal(signal.SIGXCPU) == old_handler
        assert os.sched_getscheduler(0) == os.SCHED_OTHER
        assert os.getpriority(os.PRIO_PROCESS, 0) == base
    finally:
        signal.signal(signal.SIGXCPU, old_handler)
        resource.setrlimit(resource.RLIMIT_RTTIME, old_limit)
        realtime.lower_priority(base)


def test_realtime_thread_raises_the_threads_sharing_its_lock_and_lowers_them_after():
    """``others``: light threads raised with the caller for the block, normal afterwards."""
    started, release = threading.Event(), threading.Event()
    policies: list = []

    def light():
        started.set()
        release.wait(60)

    t = threading.Thread(target=light, name="light-io")
    t.start()
    started.wait(60)

    def body():
        with realtime.realtime_thread(rt_priority=2, others=[t]) as granted:
            policies.append(os.sched_getscheduler(t.native_id) & ~os.SCHED_RESET_ON_FORK)
            names = set(realtime.realtime_threads().values())
        policies.append(os.sched_getscheduler(t.native_id))
        return granted, names

    try:
        granted, names = _in_thread(body)
    finally:
        release.set()
        t.join(60)
    if granted.startswith("SCHED_FIFO"):
        assert policies[0] == os.SCHED_FIFO and "light-io" in names
    assert policies[-1] == os.SCHED_OTHER and "light-io" not in realtime.realtime_threads().values()
