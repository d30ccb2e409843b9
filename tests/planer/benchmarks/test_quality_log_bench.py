"""The quality log's write-path benchmark: every record handed in is in the log, counted once."""

from __future__ import annotations

from controller.quality import write_ahead
from controller.quality.log import QualityLog
from planer.benchmarks import quality_log


def test_sample_records_are_a_moulders_heads_in_turn_with_a_profile_every_tenth():
    recs = quality_log.sample_records(21, heads=("bottom", "top"))
    assert [r.head for r in recs[:4]] == ["bottom", "top", "bottom", "top"]
    assert [i for i, r in enumerate(recs) if "profile" in r.extra] == [0, 10, 20]
    assert len(recs[0].extra["profile"]["x_mm"]) == 800 and all(r.ok for r in recs)


def test_every_record_reaches_the_log_and_the_figures_add_up(tmp_path):
    out = quality_log.run(records=24, rate_hz=1000.0, heads=("bottom", "top"), folder=tmp_path)
    assert out["all_logged"] and out["records"] == out["logged"] == 24
    assert 1 <= out["journal_appends"] <= 24 and 1 <= out["db_transactions"] <= 24
    assert out["records_per_append"] == 24 / out["journal_appends"]
    assert out["cpu_ms_per_record"] > 0 and out["records_per_cpu_s"] > 0
    with QualityLog(tmp_path / "quality.sqlite", create=False) as log:
        assert [r.head for r in log.records()].count("top") == 12
    assert "records per CPU-second" in quality_log.text(out)


def test_the_heads_are_the_moulders_and_a_given_folder_is_used_as_it_is(tmp_path, monkeypatch):
    from config.loading import default_path
    from config.machine import load_machine

    names = tuple(h.name for h in load_machine(default_path("machine_moulder.toml")).heads)
    assert quality_log.moulder_heads() == names
    assert {r.head for r in quality_log.sample_records(8)} == set(names)

    def no_temporary_folder(*args, **kw):
        raise AssertionError("a temporary folder made although a folder was given")

    made = []  # the writer groups the bench opens: one shared, or one per head

    class CountedGroup(write_ahead.WriterGroup):
        def __init__(self, *args, **kw):
            super().__init__(*args, **kw)
            made.append(self)

    monkeypatch.setattr(quality_log.tempfile, "TemporaryDirectory", no_temporary_folder)
    monkeypatch.setattr(write_ahead, "WriterGroup", CountedGroup)
    for shared in (True, False):
        folder = tmp_path / f"shared-{shared}"
        folder.mkdir()
        made.clear()
        out = quality_log.run(records=16, rate_hz=1000.0, heads=("bottom", "top"),
                              folder=folder, shared=shared)
        assert out["all_logged"] and out["shared_writer"] is shared
        assert len(made) == (1 if shared else 2)
        assert out["records_per_transaction"] == 16 / out["db_transactions"]
        assert (folder / "quality.sqlite").exists()


def test_made_records_are_the_sample_records_made_by_the_journal_thread(tmp_path):
    out = quality_log.run(records=12, rate_hz=1000.0, heads=("bottom", "top"),
                          folder=tmp_path, made=True)
    assert out["all_logged"] and out["made"] and out["records"] == out["logged"] == 12
    with QualityLog(tmp_path / "quality.sqlite", create=False) as log:
        stored = log.records()
    want = quality_log.sample_records(12, heads=("bottom", "top"))

    def key(r):
        return r.head, r.seq

    assert [(key(r), r.extra) for r in sorted(stored, key=key)] == [
        (key(r), r.extra) for r in sorted(want, key=key)]  # each head's in its order
    assert "records made by the journal thread" in quality_log.text(out)
