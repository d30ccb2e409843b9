"""Atomic file writing (core/fileio.py): all or nothing, no temporary files left behind."""

from __future__ import annotations

import json

import pytest

from controller.quality.log import QualityRecord, record_to_json
from core.fileio import atomic_write_bytes, atomic_write_text, atomic_writer


def test_replaces_whole_file_text_and_bytes(tmp_path):
    p = tmp_path / "a.txt"
    atomic_write_text(p, "old\n")
    atomic_write_text(p, "new ü\n")
    assert p.read_text(encoding="utf-8") == "new ü\n"
    atomic_write_bytes(p, b"\x00\xff", durable=False)
    assert p.read_bytes() == b"\x00\xff"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.txt"]


@pytest.mark.parametrize("exc", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_failure_leaves_the_old_file_and_no_temporary(tmp_path, exc):
    p = tmp_path / "a.csv"
    atomic_write_text(p, "complete\n")
    with pytest.raises(type(exc)):
        with atomic_writer(p, newline="", tmp_prefix=".tmp-") as fh:
            fh.write("half a ro")
            raise exc
    assert p.read_text() == "complete\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.csv"]


def test_missing_folder_is_an_oserror(tmp_path):
    with pytest.raises(OSError):
        atomic_write_text(tmp_path / "no" / "a.txt", "x")


def test_record_to_json_round_trips_the_fields():
    rec = QualityRecord(t_s=1.5, wall_time="2026-01-01T00:00:00+00:00", seq=3, board_id=1,
                        board_position_mm=10.0, ok=True, pitch_mm=1.5,
                        mark_widths_mm=(1.4, float("nan")), extra={"state": "run"})
    d = json.loads(record_to_json(rec))
    assert d["seq"] == 3 and d["pitch_mm"] == 1.5 and d["mark_widths_mm"] == [1.4, None]
    assert d["extra"] == {"state": "run"} and d["ok"] is True


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_new_files_follow_the_umask_and_replaced_files_keep_their_mode(tmp_path, umask):
    import os
    import stat

    old = os.umask(umask)
    try:
        p = tmp_path / "fig.png"
        atomic_write_bytes(p, b"x", durable=False)
        assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask
        with open(tmp_path / "plain.txt", "w") as fh:  # the same as open() gives
            fh.write("x")
        assert stat.S_IMODE((tmp_path / "plain.txt").stat().st_mode) == 0o666 & ~umask
        os.chmod(p, 0o640)
        atomic_write_text(p, "again", durable=False)
        assert stat.S_IMODE(p.stat().st_mode) == 0o640
    finally:
        os.umask(old)
