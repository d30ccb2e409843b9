"""In-process HIL: a paced run's loop raised as planer serve raises its bus thread, said once.

The real OS is asked in one short paced run (the real-time assertions apply where this host
permits real-time scheduling); what is said when it is refused or the guard drops it is checked
with ``core.realtime`` stand-ins.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
from dataclasses import replace

import pytest

from core import realtime
from planer.hil import InProcessHil, load_scenario


def _hil(tmp_path, lines, **kw) -> InProcessHil:
    sc = replace(load_scenario("default"), distance_m=1.0)
    return InProcessHil(sc, log_path=tmp_path / "hil.sqlite", progress=lines.append,
                        progress_every=1, **kw)


def test_a_paced_run_raises_its_loop_with_the_plc_thread_and_drops_it_after(tmp_path):
    lines: list[str] = []
    seen: list[tuple[int, int]] = []
    base = os.getpriority(os.PRIO_PROCESS, 0)

    def progress(line: str) -> None:
        lines.append(line)
        if " pitch " in line and " feed " in line:  # a pair's progress line, from the loop
            seen.append((os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK,
                         os.getpriority(os.PRIO_PROCESS, 0)))

    hil = _hil(tmp_path, lines, plc_transport="tcp", pace=50.0, realtime=True)
    hil.progress = progress
    try:
        summary = asyncio.run(hil.run())
    finally:
        realtime.lower_priority(base)  # whatever happened, the test process goes on normal
    prio = summary["priority"]
    said = [ln for ln in lines if ln.startswith("priority:")]
    assert said and prio["loop"] in said[0]
    assert seen, lines
    if prio["loop"].startswith("SCHED_FIFO"):
        assert prio["loop"] == f"SCHED_FIFO {realtime.BUS_RT_PRIORITY}"
        assert all(policy == os.SCHED_FIFO for policy, _ in seen)
        assert "hil-plc" in prio["with"]  # the simulated PLC answers the loop's reads
        assert prio["demoted"] is False  # a paced run blocks every cycle
    elif prio["loop"].startswith("nice"):
        assert all(nice == realtime.INTERFACE_NICE for _, nice in seen)
    else:
        assert prio["with"] == [] and "not permitted" in said[0]
    # afterwards the thread runs as before the run, and nothing is left registered
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert os.getpriority(os.PRIO_PROCESS, 0) == base
    assert threading.get_native_id() not in realtime.realtime_threads()


def test_an_unpaced_run_is_a_batch_computation_and_stays_normal(tmp_path):
    lines: list[str] = []
    hil = _hil(tmp_path, lines, realtime=True)  # pace None: as fast as it goes
    with hil._raised():
        policy = os.sched_getscheduler(0)
    assert policy == os.SCHED_OTHER
    assert hil._priority_now()["loop"].startswith("normal (not paced")
    assert not [ln for ln in lines if ln.startswith("priority:")]


def test_without_realtime_nothing_is_asked(tmp_path, monkeypatch):
    asked: list = []
    monkeypatch.setattr(realtime, "realtime_thread", lambda **kw: asked.append(kw))
    hil = _hil(tmp_path, [], pace=1.0)
    with hil._raised():
        pass
    assert asked == [] and hil._priority_now()["loop"] == "normal (not asked)"


def _fake_realtime(monkeypatch, granted: str, raised: dict) -> list[dict]:
    calls: list[dict] = []

    @contextlib.contextmanager
    def fake(**kw):
        calls.append(kw)
        yield granted

    monkeypatch.setattr(realtime, "realtime_thread", fake)
    monkeypatch.setattr(realtime, "realtime_threads", lambda: dict(raised))
    return calls


def test_a_refused_raise_is_said_with_no_threads_raised(tmp_path, monkeypatch):
    refused = "normal (SCHED_FIFO: Operation not permitted; nice -10: Permission denied)"
    calls = _fake_realtime(monkeypatch, refused, {})
    lines: list[str] = []
    hil = _hil(tmp_path, lines, pace=1.0, realtime=True)
    with hil._raised():
        prio = hil._priority_now()
    assert calls and calls[0]["rt_priority"] == realtime.BUS_RT_PRIORITY
    assert prio == {"loop": refused, "with": [], "demoted": False}
    said = [ln for ln in lines if ln.startswith("priority:")]
    assert len(said) == 1 and refused in said[0] and "not permitted" in said[0]


@pytest.mark.parametrize("still_raised", [True, False])
def test_a_loop_the_guard_dropped_is_reported_demoted_once(tmp_path, monkeypatch,
                                                           still_raised):
    me = threading.get_native_id()
    raised = {me: "MainThread"} if still_raised else {}
    _fake_realtime(monkeypatch, "SCHED_FIFO 9", raised)
    lines: list[str] = []
    hil = _hil(tmp_path, lines, pace=1.0, realtime=True)
    with hil._raised():
        first = hil._priority_now()
        second = hil._priority_now()
    assert first["demoted"] is (not still_raised) and second == first
    dropped = [ln for ln in lines if "dropped to normal scheduling" in ln]
    assert len(dropped) == (0 if still_raised else 1)
