"""The learnt state across restarts: the file, its judgement, its writes, the warm start."""

from __future__ import annotations

import json
import math

import pytest

from config.machine import SafetyConfig
from controller.quality.learned_state import (
    MAX_AGE_S,
    KnifeSet,
    LearnedMemory,
    LearnedState,
    learned_state_path,
)
from controller.service.supervisor import WARM_START_CONFIRM_S, SafetyState, Supervisor

KS = KnifeSet(knives=4, radius_mm=60.0, spindle_rpm=6000.0, stroke_um=20.0)


class Clock:
    def __init__(self, t: float = 1.7e9) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _memory(tmp_path, clock=None, **kw):
    return LearnedMemory(tmp_path / "q.sqlite.learned.json", machine_id="planer-7",
                         wall_clock=clock or Clock(), **kw)


def test_the_file_lives_beside_the_log_or_in_the_journal_state_folder(tmp_path, monkeypatch):
    assert learned_state_path(tmp_path / "run.db") == tmp_path / "run.db.learned.json"
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    p = learned_state_path("postgresql://qa:secret@db.example:5433/planer")
    assert p == tmp_path / "state" / "planer" / "qa@db.example_5433_planer.learned.json"
    assert "secret" not in str(p)


def test_a_saved_state_reads_back_whole(tmp_path):
    mem = _memory(tmp_path)
    st = mem.make(KS, [0.5, 3.0, -3.5, 0.0], feed_correction=0.98,
                  runout_estimate_um=[0.1, 4.0, -2.0, 2.0],
                  mode_gains=[1, 0.9 + 0.1j, 0.8, 0.9 - 0.1j])
    assert mem.save(st, 0.0)
    back, problem = mem.load()
    assert problem is None and back == st
    assert mem.judge(back, KS) is None
    assert json.loads(mem.path.read_text())["machine_id"] == "planer-7"
    assert not list(tmp_path.glob(".*tmp"))  # the rename left no temporary file


@pytest.mark.parametrize(
    ("now", "words"),
    [
        (KnifeSet(3, 60.0, 6000.0, 20.0), "knives 4 then, 3 now"),
        (KnifeSet(4, 59.0, 6000.0, 20.0), "cutting radius"),
        (KnifeSet(4, 60.0, 4500.0, 20.0), "spindle 6000 rpm then, 4500 rpm now"),
        (KnifeSet(4, 60.0, 6000.0, 10.0), "amplifier stroke"),
    ],
)
def test_another_knife_set_is_relearnt_and_says_why(tmp_path, now, words):
    mem = _memory(tmp_path)
    why = mem.judge(mem.make(KS, [0.0] * 4, feed_correction=1.0), now)
    assert why is not None and words in why


def test_what_is_not_known_or_not_turning_does_not_count_against_the_state(tmp_path):
    mem = _memory(tmp_path)
    st = mem.make(KS, [0.0] * 4, feed_correction=1.0)
    assert mem.judge(st, KnifeSet(4, 60.0, 0.0, None)) is None  # spindle stood, amp silent
    assert mem.judge(st, KnifeSet(4, 60.02, 6100.0, 20.0)) is None  # within the tolerances


def test_an_old_state_or_another_machine_is_not_resumed(tmp_path):
    clock = Clock()
    mem = _memory(tmp_path, clock)
    st = mem.make(KS, [0.0] * 4, feed_correction=1.0)
    clock.t += MAX_AGE_S + 1
    assert "min ago" in mem.judge(st, KS)
    other = LearnedMemory(mem.path, machine_id="planer-8", wall_clock=clock)
    clock.t -= MAX_AGE_S + 1
    assert "machine 'planer-7'" in other.judge(st, KS)


@pytest.mark.parametrize(
    "content",
    ["{not json", json.dumps({"format": 99}), json.dumps([1, 2]),
     json.dumps({"format": 1, "machine_id": "m", "saved_at_unix": 1.0, "offsets_um": [1.0],
                 "knife_set": {"knives": 4, "radius_mm": 60.0, "spindle_rpm": 6000.0}})],
)
def test_a_damaged_file_is_no_state_and_says_why(tmp_path, content):
    mem = _memory(tmp_path)
    mem.path.write_text(content)
    state, problem = mem.load()
    assert state is None and problem is not None and str(mem.path) in problem


def test_no_file_is_no_state_and_no_complaint(tmp_path):
    assert _memory(tmp_path).load() == (None, None)


def test_a_changing_state_is_written_every_few_seconds_not_per_pair(tmp_path):
    mem = _memory(tmp_path, save_every_s=2.0)
    written = []
    for i in range(100):  # 10 s of pairs at 10 per second, the offsets moving every pair
        t = i * 0.1
        st = mem.make(KS, [0.01 * i, -0.01 * i, 0.0, 0.0], feed_correction=1.0)
        if mem.offer(lambda st=st: st, t):
            written.append(t)
    assert written == pytest.approx([0.0, 2.0, 4.0, 6.0, 8.0])
    # a state that stops changing is not written again
    same = mem.make(KS, [0.01 * 99, -0.01 * 99, 0.0, 0.0], feed_correction=1.0)
    assert mem.offer(lambda: same, 10.0)
    assert not mem.offer(lambda: same, 20.0)
    assert mem.writes == 6


def test_a_write_that_fails_is_reported_not_raised(tmp_path):
    (tmp_path / "blocked").write_text("a file where the folder should be")
    mem = LearnedMemory(tmp_path / "blocked" / "x.learned.json", machine_id="m")
    assert not mem.save(mem.make(KS, [0.0] * 4, feed_correction=1.0), 0.0)
    assert mem.problem is not None


def test_bad_states_are_refused_naming_the_field():
    with pytest.raises(ValueError, match="offsets_um must have 4"):
        LearnedState("m", KS, 0.0, (0.0, 0.0))
    with pytest.raises(ValueError, match="feed_correction"):
        LearnedState("m", KS, 0.0, (0.0,) * 4, feed_correction=math.nan)
    with pytest.raises(ValueError, match="knives"):
        KnifeSet(0, 60.0, 6000.0)


# ---------------------------------------------------------------------------- warm start
SAFETY = SafetyConfig(cycle_s=0.02, plc_timeout_s=0.5, can_timeout_s=0.3,
                      measurement_timeout_s=2.0, recovery_s=0.3, safe_state="ramp_down",
                      safe_feed_mm_s=400.0, ramp_mm_s2=500.0)


def _start(warm: bool):
    sup = Supervisor(SAFETY, now_s=0.0)
    if warm:
        sup.warm_start(0.0)
    feeds, t, feed, run_at = [], 0.0, 600.0, None
    while t < 1.0:
        sup.plc_answered(t)
        sup.can_heard(t)
        sup.measurement_valid(t)
        st = sup.step(t)
        if st.state is SafetyState.RUN and run_at is None:
            run_at = t
        if st.state is SafetyState.SAFE:
            feed = sup.safe_feed(feed, dt_s=0.02, feed_min_mm_s=50.0, feed_max_mm_s=1000.0)
            feeds.append(feed)
        t = round(t + 0.02, 9)
    return sup, feeds, run_at


def test_a_warm_start_holds_the_feed_and_runs_after_a_short_confirmation():
    sup, feeds, run_at = _start(warm=True)
    assert set(feeds) == {600.0}
    assert run_at == pytest.approx(WARM_START_CONFIRM_S, abs=0.021)
    assert sup.ran and not sup.warm
    cold, cold_feeds, cold_run = _start(warm=False)
    assert min(cold_feeds) < 600.0 - 100.0  # the cold start ramps toward the safe feed
    assert cold_run == pytest.approx(SAFETY.recovery_s, abs=0.021)


def test_a_warm_start_ends_when_the_machine_stops_and_after_the_first_run():
    sup = Supervisor(SAFETY, now_s=0.0)
    sup.warm_start(0.0)
    sup.machine_ok(False)
    assert not sup.warm
    assert sup.safe_feed(600.0, dt_s=0.1, feed_min_mm_s=50.0, feed_max_mm_s=1000.0) == 550.0
    sup2, _, _ = _start(warm=True)
    sup2.warm_start(2.0)  # once it has run, a warm start is no longer possible
    assert not sup2.warm
