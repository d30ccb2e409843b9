"""The learnt state per cutterhead: a moulder's head never resumes another head's state.

The single head ``"main"`` keeps the file it always had and reads the states written before
heads (no ``head`` in the file); every other head has its own file beside its own journal.
"""

from __future__ import annotations

import json

import pytest

from controller.quality.journal import default_journal_path
from controller.quality.learned_state import (
    KnifeSet,
    LearnedMemory,
    LearnedState,
    learned_memory_of,
    learned_state_path,
)

KS = KnifeSet(knives=4, radius_mm=60.0, spindle_rpm=6000.0, stroke_um=20.0)
NOW = 1.7e9


def _clock() -> float:
    return NOW


def _beside(log_path, head: str = "main") -> LearnedMemory:
    return LearnedMemory.beside(log_path, machine_id="planer-7", head=head, wall_clock=_clock)


def test_each_head_has_its_own_file_and_main_keeps_the_old_one(tmp_path):
    log = tmp_path / "run.db"
    assert learned_state_path(log) == tmp_path / "run.db.learned.json"
    assert learned_state_path(log, head="main") == tmp_path / "run.db.learned.json"
    assert learned_state_path(log, head="top") == tmp_path / "run.db.top.learned.json"
    assert learned_state_path(log, head="bottom") == tmp_path / "run.db.bottom.learned.json"
    # beside the head's journal, as the single head's is beside the log's
    assert (learned_state_path(log, head="top").name.removesuffix(".learned.json")
            == default_journal_path(log, head="top").name.removesuffix(".journal.jsonl"))
    with pytest.raises(ValueError, match="head"):
        learned_state_path(log, head="Top")


def test_heads_save_and_resume_their_own_states(tmp_path):
    log = tmp_path / "run.db"
    offsets = {"bottom": [1.0, -1.0, 0.5, -0.5], "top": [-2.0, 2.0, 0.0, 0.0]}
    for head, table in offsets.items():
        mem = _beside(log, head)
        assert mem.save(mem.make(KS, table, feed_correction=0.97), 0.0)
    for head, table in offsets.items():
        back, problem = _beside(log, head).load()
        assert problem is None and back is not None
        assert back.head == head and list(back.offsets_um) == table
        assert _beside(log, head).judge(back, KS) is None
    assert _beside(log, "left").load() == (None, None)  # no file: learns afresh
    assert _beside(log).load() == (None, None)


def test_a_head_never_resumes_another_heads_state(tmp_path):
    top = _beside(tmp_path / "run.db", "top")
    state = top.make(KS, [0.0, 1.0, -1.0, 0.0], feed_correction=1.0)
    why = _beside(tmp_path / "run.db", "bottom").judge(state, KS)
    assert why == "learnt on head 'top', this is head 'bottom'"
    # even when handed the other head's file (a copied or renamed file)
    assert top.save(state, 0.0)
    bottom = LearnedMemory(top.path, machine_id="planer-7", head="bottom", wall_clock=_clock)
    back, problem = bottom.load()
    assert problem is None and "head 'top'" in bottom.judge(back, KS)


def test_the_single_head_reads_the_state_written_before_heads(tmp_path):
    log = tmp_path / "run.db"
    old = {  # the file as the planer before heads wrote it: no "head"
        "format": 1, "machine_id": "planer-7", "saved_at_unix": NOW - 60.0,
        "knife_set": KS.to_dict(), "offsets_um": [0.5, 3.0, -3.5, 0.0],
        "feed_correction": 0.98, "runout_estimate_um": None, "mode_gains": None,
    }
    learned_state_path(log).write_text(json.dumps(old))
    main = _beside(log)
    back, problem = main.load()
    assert problem is None and back.head == "main"
    assert main.judge(back, KS) is None
    assert list(back.offsets_um) == [0.5, 3.0, -3.5, 0.0]
    # a moulder head given that file by mistake does not take it
    assert "head 'main'" in LearnedMemory(main.path, machine_id="planer-7", head="top",
                                           wall_clock=_clock).judge(back, KS)


def test_the_state_names_its_head_in_the_file_and_refuses_a_bad_one(tmp_path):
    mem = _beside(tmp_path / "run.db", "left")
    assert mem.save(mem.make(KS, [0.0] * 4, feed_correction=1.0), 0.0)
    assert json.loads(mem.path.read_text())["head"] == "left"
    with pytest.raises(ValueError, match="head"):
        LearnedState(machine_id="m", knife_set=KS, saved_at_unix=NOW, offsets_um=[0.0] * 4,
                     head="Left")
    with pytest.raises(ValueError, match="head"):
        LearnedMemory(tmp_path / "x.json", machine_id="m", head="")


def test_the_memory_of_a_log_is_its_heads(tmp_path):
    class Log:
        path = tmp_path / "run.db"
        machine_id = "planer-7"

    assert learned_memory_of(Log()).path == tmp_path / "run.db.learned.json"
    mem = learned_memory_of(Log(), head="top")
    assert mem.path == tmp_path / "run.db.top.learned.json" and mem.head == "top"
