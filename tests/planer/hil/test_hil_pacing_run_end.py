"""The HIL's pace against the wall clock and the judgement of how a run ended (pure parts)."""

from __future__ import annotations

import asyncio

import pytest

from planer.hil.pacing import MAX_CATCH_UP_S, Pacer
from planer.hil.run_end import RunEnd, judge_run_end, note_run_end


class FakeWall:
    """A wall clock that only moves when the pacer sleeps or the test says so."""

    def __init__(self) -> None:
        self.t = 100.0
        self.slept: list[float] = []

    def clock(self) -> float:
        return self.t

    async def sleep(self, s: float) -> None:
        self.slept.append(s)
        self.t += s


def _run(coro):
    return asyncio.run(coro)


def test_the_pacer_holds_simulated_time_to_the_factor():
    wall = FakeWall()
    pacer = Pacer(2.0, clock=wall.clock, sleep=wall.sleep)

    async def go():
        for sim in (5.0, 5.5, 6.0, 7.0):
            await pacer.wait(sim)

    _run(go())
    # simulated 5.0 is the origin; 0.5 s of simulation at 2x is 0.25 s of wall, and so on
    assert wall.slept == pytest.approx([0.0, 0.25, 0.25, 0.5])
    assert wall.t == pytest.approx(101.0) and pacer.behind_s == 0.0


def test_a_run_slower_than_the_pace_is_not_hurried_afterwards():
    wall = FakeWall()
    pacer = Pacer(1.0, clock=wall.clock, sleep=wall.sleep)

    async def go():
        await pacer.wait(0.0)
        wall.t += 2.0  # a step took 2 s of wall for 0.1 s of simulation
        await pacer.wait(0.1)
        await pacer.wait(0.6)  # from here on the pace holds again: 0.5 s later
        wall.t += 0.1  # a little late: within MAX_CATCH_UP_S, made up
        await pacer.wait(1.0)

    _run(go())
    assert wall.slept == pytest.approx([0.0, 0.0, 0.5, 0.3])
    assert pacer.behind_s == pytest.approx(1.9) and 0.1 < MAX_CATCH_UP_S


def test_no_pace_only_yields_and_bad_factors_are_refused():
    wall = FakeWall()
    pacer = Pacer(None, clock=wall.clock, sleep=wall.sleep)
    _run(pacer.wait(0.0))
    _run(pacer.wait(50.0))
    assert wall.slept == [0, 0] and wall.t == 100.0
    for bad in (0, -1.0, float("nan"), float("inf"), "1"):
        with pytest.raises(ValueError, match="pace factor"):
            Pacer(bad)


def _passing_summary() -> dict:
    return {"done": {"a": True, "b": True}, "checks": {}, "passed": True}


def test_a_run_the_time_limit_cut_fails_and_names_the_limit():
    s = _passing_summary()
    said: list[str] = []
    end = note_run_end(s, distance_m=60.0, travelled_m=35.2, max_sim_s=60.0,
                       time_limit_hit=True, say=said.append)
    assert end is RunEnd.TIME_LIMIT and s["run_end"]["reason"] == "max_sim_s"
    assert s["done"]["distance_reached"] is False and s["passed"] is False
    text = s["checks"]["distance_reached"]["text"]
    assert "max_sim_s 60 s" in text and "35.20 m of the 60 m" in text
    assert said == [f"planer hil: t{text[1:]}"]


def test_a_run_that_went_its_distance_keeps_its_verdict():
    s = _passing_summary()
    said: list[str] = []
    assert note_run_end(s, distance_m=5.0, travelled_m=5.0004, max_sim_s=60.0,
                        time_limit_hit=False, say=said.append) is RunEnd.DISTANCE
    assert s["done"]["distance_reached"] is True and s["passed"] is True and said == []
    s = _passing_summary()
    s["done"]["b"] = False
    s["passed"] = False
    note_run_end(s, distance_m=5.0, travelled_m=6.0, max_sim_s=60.0, time_limit_hit=True)
    assert s["done"]["distance_reached"] is True and s["passed"] is False


def test_a_run_that_stopped_short_for_another_reason_fails_too():
    assert judge_run_end(distance_m=5.0, travelled_m=4.9, time_limit_hit=False) \
        is RunEnd.STOPPED
    s = _passing_summary()
    note_run_end(s, distance_m=5.0, travelled_m=4.9, max_sim_s=60.0, time_limit_hit=False)
    assert s["run_end"]["reason"] == "stopped" and not s["passed"]
