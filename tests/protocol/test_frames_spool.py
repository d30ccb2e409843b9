"""Spool reader: each bad file gives a failed frame or a reported skip, never a stop or replay."""

from __future__ import annotations

import asyncio
import json
import os
import struct
import threading
import zlib
from pathlib import Path

import numpy as np
import pytest

from config.machine import FramesConfig
from controller.frames.source import SpoolFrameSource, open_frame_source
from core.errors import MeasurementError
from core.imageio import png_header
from protocol import spool as spool_mod
from protocol.frames import Frame
from protocol.spool import SpoolReader, SpoolWriter
from protocol.spool_files import SEQ_MAX, SpoolLimits, decode_metadata, read_spool_file

SHAPE = (12, 20)


def _img(seed: int, dtype=np.uint8, shape=SHAPE) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 200, shape).astype(dtype)


def _frame(seq: int, **kw) -> Frame:
    base = dict(seq=seq, t_s=0.1 * seq, image_a=_img(seq), image_b=_img(seq + 100),
                counts_a=10 * seq, counts_b=10 * seq + 5, speed_mm_s=600.0, board_id=1,
                board_position_mm=5.0 * seq)
    base.update(kw)
    return Frame(**base)


def _spool(tmp_path: Path, n: int, *, keep: int = 50, first_seq: int = 1) -> SpoolWriter:
    w = SpoolWriter(tmp_path, keep=keep, fsync=False)
    for s in range(first_seq, first_seq + n):
        w.write(_frame(s))
    return w


def _meta_path(d: Path, slot: int) -> Path:
    return d / f"pair-{slot:012d}.json"


def _edit_meta(d: Path, slot: int, **changes) -> None:
    p = _meta_path(d, slot)
    doc = json.loads(p.read_text())
    doc.update(changes)
    p.write_text(json.dumps(doc))


def _drain(r: SpoolReader) -> list[Frame]:
    out = []
    while (f := r.poll()) is not None:
        out.append(f)
    return out


def _png(width: int, height: int, *, idat: bytes = b"", depth: int = 8, colour: int = 0) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return (struct.pack(">I", len(body)) + kind + body
                + struct.pack(">I", zlib.crc32(kind + body)))

    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat)
            + chunk(b"IEND", b""))


# --------------------------------------------------------------------------------------------
# bad images: a failed frame naming the file and the reason


def _broken_a(tmp_path: Path, content: bytes | None, **limits) -> Frame:
    _spool(tmp_path, 2)
    a = tmp_path / "pair-000000000000.a.png"
    if content is not None:
        a.write_bytes(content)
    r = SpoolReader(tmp_path, start="all", limits=SpoolLimits(**limits))
    got = _drain(r)
    assert [f.seq for f in got] == [1, 2]  # the next pair is read as usual
    assert got[1].error is None and got[1].image_a.shape == SHAPE
    bad = got[0]
    assert bad.error and bad.image_a is None and bad.image_b is None
    assert "pair-000000000000.a.png" in bad.error
    assert (bad.board_id, bad.counts_a) == (1, 10)  # the metadata still reaches the record
    return bad


def test_zero_byte_image(tmp_path):
    assert "empty file" in _broken_a(tmp_path, b"").error


def test_truncated_image(tmp_path):
    _spool(tmp_path / "w", 1)
    whole = (tmp_path / "w" / "pair-000000000000.a.png").read_bytes()
    assert "truncated" in _broken_a(tmp_path / "t", whole[: len(whole) // 2]).error


def test_decompression_bomb_is_refused_from_its_header(tmp_path, monkeypatch):
    import cv2

    bomb = _png(16000, 16000, idat=zlib.compress(b"\0" * 16001 * 4))
    sizes = []
    real = cv2.imdecode

    def spy(buf, flags):
        sizes.append(len(buf))
        return real(buf, flags)

    monkeypatch.setattr(cv2, "imdecode", spy)
    err = _broken_a(tmp_path, bomb, max_pixels=4096 * 4096).error
    assert "16000x16000" in err and "limit" in err
    assert sizes and len(bomb) not in sizes  # never handed to the decoder
    assert png_header(bomb).pixels == 16000 * 16000


def test_image_of_another_size_than_the_rigs(tmp_path):
    import cv2

    other = cv2.imencode(".png", _img(5, shape=(SHAPE[0], SHAPE[1] + 1)))[1].tobytes()
    err = _broken_a(tmp_path, other, image_shape=SHAPE).error
    assert f"{SHAPE[1] + 1}x{SHAPE[0]} px" in err and "camera" in err


def test_images_a_and_b_of_different_size(tmp_path):
    w = SpoolWriter(tmp_path, fsync=False)
    w.write(_frame(1, image_b=_img(3, shape=(SHAPE[0], SHAPE[1] + 2))))
    f = SpoolReader(tmp_path, start="all").poll()
    assert f.image_a is None and "image_a is 20x12" in f.error and "image_b 22x12" in f.error


def test_colour_and_damaged_pngs(tmp_path):
    import cv2

    ok, rgb = cv2.imencode(".png", np.zeros((*SHAPE, 3), np.uint8))
    assert "channels" in _broken_a(tmp_path / "c", rgb.tobytes()).error
    _spool(tmp_path / "g", 1)
    good = (tmp_path / "g" / "pair-000000000000.a.png").read_bytes()
    damaged = good[:40] + bytes(b ^ 0x5A for b in good[40:-12]) + good[-12:]
    assert "damaged" in _broken_a(tmp_path / "d", damaged).error
    assert "not a PNG" in _broken_a(tmp_path / "n", b"GIF89a" + b"\0" * 40).error


def test_fifo_symlink_directory_are_refused_without_blocking(tmp_path):
    for kind in ("fifo", "symlink", "dir", "missing"):
        d = tmp_path / kind
        _spool(d, 2)
        a = d / "pair-000000000000.a.png"
        a.unlink()
        if kind == "fifo":
            os.mkfifo(a)
        elif kind == "symlink":
            a.symlink_to("/etc/hostname")
        elif kind == "dir":
            a.mkdir()
        got = _drain(SpoolReader(d, start="all"))
        want = {"fifo": "FIFO", "symlink": "symbolic link", "dir": "directory",
                "missing": "missing"}[kind]
        assert [f.seq for f in got] == [1, 2] and want in got[0].error, kind
        assert got[1].error is None


def test_image_names_outside_the_pair_are_refused(tmp_path):
    _spool(tmp_path, 4)
    _edit_meta(tmp_path, 0, image_a="../../etc/hostname")
    _edit_meta(tmp_path, 1, image_a="/etc/hostname")
    _edit_meta(tmp_path, 2, image_a="pair-000000000003.a.png")  # another pair's image
    got = _drain(SpoolReader(tmp_path, start="all"))
    for f in got[:3]:
        assert "invalid metadata" in f.error and "image_a" in f.error and f.image_a is None
    assert got[3].error is None


def test_read_spool_file_limits(tmp_path):
    (tmp_path / "big").write_bytes(b"x" * 101)
    with pytest.raises(spool_mod.SpoolFileError, match="too large"):
        read_spool_file(tmp_path, "big", max_bytes=100)
    for name in ("../big", "a/b", "..", ""):
        with pytest.raises(spool_mod.SpoolFileError, match="plain file name"):
            read_spool_file(tmp_path, name, max_bytes=100)
    with pytest.raises(FileNotFoundError):
        read_spool_file(tmp_path, "gone", max_bytes=100)


# --------------------------------------------------------------------------------------------
# metadata: field by field


@pytest.mark.parametrize("field, value", [
    ("seq", 10**20), ("seq", -1), ("board_id", 10**20), ("board_id", 2**32),
    ("counts_a", 2**40), ("counts_b", "7"), ("index_latch_counts", 1.5), ("t_s", None),
    ("t_s", 1e300), ("speed_mm_s", 1e9), ("board_position_mm", True), ("truth", [1, 2]),
    ("version", 2),
])
def test_invalid_field_gives_a_failed_frame_naming_it(tmp_path, field, value):
    _spool(tmp_path, 3)
    _edit_meta(tmp_path, 1, **{field: value})
    r = SpoolReader(tmp_path, start="all")
    got = _drain(r)
    assert [f.seq for f in got] == [1, 2, 3]  # an invalid seq continues the sequence
    bad = got[1]
    assert bad.error.startswith("invalid metadata in pair-000000000001.json") and field in bad.error
    assert bad.image_a is None and got[2].error is None and r.skipped == 0


def test_missing_required_field(tmp_path):
    _spool(tmp_path, 1)
    p = _meta_path(tmp_path, 0)
    doc = json.loads(p.read_text())
    del doc["counts_b"]
    p.write_text(json.dumps(doc))
    f = SpoolReader(tmp_path, start="all").poll()
    assert "counts_b missing" in f.error


def test_schema_limits_are_accepted(tmp_path):
    w = SpoolWriter(tmp_path, fsync=False)
    w.write(_frame(SEQ_MAX, board_id=2**32 - 1, counts_a=2**32 - 1, counts_b=-(2**32 - 1),
                   t_s=-1e12, board_position_mm=1e12, speed_mm_s=-1e5))
    f = SpoolReader(tmp_path, start="all").poll()
    assert f.error is None and f.seq == SEQ_MAX and f.board_id == 2**32 - 1


@pytest.mark.parametrize("content, reason", [
    (b"", "empty file"), (b"\xff\xfe garbage", "not JSON"), (b"[1, 2]", "not a JSON object"),
    (b'{"a": 1}', "no 'seq'"), (b'{"seq": "three"}', "seq must be an integer"),
    (b'{"seq": 1, "slot": 5}', "differs from its name"), (b"[" * 100_000, "not JSON"),
    (b'{"seq": 1' + b"1" * 5000 + b"}", "not JSON"),
])
def test_not_metadata_is_skipped_with_file_and_reason(tmp_path, content, reason):
    _spool(tmp_path, 3)
    _meta_path(tmp_path, 1).write_bytes(content)
    r = SpoolReader(tmp_path, start="all")
    assert [f.seq for f in _drain(r)] == [1, 3]
    skips = r.take_skips()
    assert [s.file for s in skips] == ["pair-000000000001.json"] and reason in skips[0].reason
    assert r.skipped == 1 and r.take_skips() == []


def test_oversized_metadata_is_skipped(tmp_path):
    _spool(tmp_path, 2)
    _edit_meta(tmp_path, 0, truth={"pad": "x" * 2000})
    r = SpoolReader(tmp_path, start="all", limits=SpoolLimits(max_meta_bytes=1000))
    assert [f.seq for f in _drain(r)] == [2]
    assert "too large" in r.take_skips()[0].reason


def test_garbage_high_slot_neither_stops_nor_replays(tmp_path):
    w = _spool(tmp_path, 3)
    r = SpoolReader(tmp_path, start="all")
    assert [f.seq for f in _drain(r)] == [1, 2, 3]
    garbage = _meta_path(tmp_path, 999999999999)
    garbage.write_bytes(b"\x00garbage")
    for s in (4, 5):
        w.write(_frame(s))
    assert [f.seq for f in _drain(r)] == [4, 5]  # today: stopped at the garbage
    assert [s.file for s in r.take_skips()] == [garbage.name]
    garbage.unlink()
    w.write(_frame(6))
    assert [f.seq for f in _drain(r)] == [6]  # today: replayed the spool from slot 0
    assert r.take_skips() == [] and r.missed == 0


def test_writer_restart_ignores_a_stray_high_slot(tmp_path):
    _spool(tmp_path, 2)
    _meta_path(tmp_path, 10**17).write_bytes(b"garbage")
    w = SpoolWriter(tmp_path, fsync=False)
    assert w.next_slot == 2
    w.write(_frame(3))
    r = SpoolReader(tmp_path, start="all")
    assert [f.seq for f in _drain(r)] == [1, 2, 3] and len(r.take_skips()) == 1


def test_bad_file_names_are_reported_once(tmp_path):
    _spool(tmp_path, 1)
    (tmp_path / "pair-²³.json").write_text("{}")
    (tmp_path / ("pair-" + "9" * 200 + ".json")).write_text("{}")
    r = SpoolReader(tmp_path, start="all")
    assert [f.seq for f in _drain(r)] == [1]
    assert sorted(s.file for s in r.take_skips()) == sorted(
        ["pair-²³.json", "pair-" + "9" * 200 + ".json"])
    assert _drain(r) == [] and r.take_skips() == []


def test_writer_restarted_on_emptied_folder_is_followed(tmp_path):
    _spool(tmp_path, 3)
    r = SpoolReader(tmp_path, start="all")
    assert len(_drain(r)) == 3
    for p in tmp_path.iterdir():
        p.unlink()
    _spool(tmp_path, 5, first_seq=1)  # slots 0..4 again, new files
    assert [f.seq for f in _drain(r)] == [1, 2, 3, 4, 5]


# --------------------------------------------------------------------------------------------
# gaps and skips: true counts


def test_pairs_pruned_before_they_were_read_are_counted_truly(tmp_path):
    w = SpoolWriter(tmp_path, keep=2, fsync=False)
    r = SpoolReader(tmp_path, start="all")
    w.write(_frame(1))
    assert r.poll().seq == 1
    for s in range(2, 9):  # 7 pairs, only the newest 2 survive
        w.write(_frame(s))
    assert [f.seq for f in _drain(r)] == [7, 8]
    (gap,) = r.take_skips()
    assert r.missed == 5 == gap.pairs and gap.slot == 1 and "pruned" in gap.reason


def test_seq_jump_without_missing_slots_is_not_a_gap(tmp_path):
    w = SpoolWriter(tmp_path, fsync=False)
    w.write(_frame(1))
    w.write(_frame(10**18))  # a camera restart or a wild value: not 10**18 lost pairs
    r = SpoolReader(tmp_path, start="all")
    assert len(_drain(r)) == 2 and r.missed == 0 and r.take_skips() == []


def test_metadata_decoder_is_pure():
    meta = decode_metadata(b'{"seq": 3, "t_s": 1, "counts_a": 1, "counts_b": 2, '
                           b'"speed_mm_s": 5, "board_id": 99999999999}', slot=0)
    assert meta.seq_ok and meta.fields["seq"] == 3 and meta.images == (None, None)
    assert len(meta.problems) == 1 and "board_id" in meta.problems[0]
    with pytest.raises(MeasurementError):
        png_header(b"")


# --------------------------------------------------------------------------------------------
# the threaded source: off the event loop, with a time limit per pair


def test_threaded_source_delivers_in_order_with_skips(tmp_path):
    async def main():
        _spool(tmp_path, 3)
        _meta_path(tmp_path, 1).write_text("nonsense")
        src = SpoolFrameSource(SpoolReader(tmp_path, start="all"), poll_s=0.001)
        got = []
        for _ in range(50):
            f = await src.next(timeout_s=0.2)
            if f is not None:
                got.append(f.seq)
            if len(got) == 2:
                break
        skips = src.take_skips()
        src.close()
        return got, skips, src

    got, skips, src = asyncio.run(main())
    assert got == [1, 3] and [s.file for s in skips] == ["pair-000000000001.json"]
    assert src.received == 2 and not src._thread.is_alive()


def test_a_pair_that_takes_too_long_is_given_up(tmp_path, monkeypatch):
    _spool(tmp_path, 3)
    entered, release = threading.Event(), threading.Event()
    real = spool_mod.decode_spool_image

    def slow(data, name, *, limits):
        if name.startswith("pair-000000000001."):
            entered.set()
            release.wait(20)
        return real(data, name, limits=limits)

    monkeypatch.setattr(spool_mod, "decode_spool_image", slow)
    now = [0.0]

    async def main():
        src = SpoolFrameSource(SpoolReader(tmp_path, start="all",
                                           limits=SpoolLimits(pair_timeout_s=2.0)),
                               poll_s=0.001, clock=lambda: now[0])
        first = await src.next(timeout_s=10)
        assert entered.wait(10)  # the reader thread is stuck in pair 1
        assert await src.next(timeout_s=0.01) is None  # the event loop is not
        now[0] += 2.5  # past the time limit (simulated clock)
        late = await src.next(timeout_s=10)
        third = await src.next(timeout_s=10)
        release.set()
        src.close()
        return first, late, third, src

    first, late, third, src = asyncio.run(main())
    assert first.seq == 1 and first.error is None
    assert late.seq == 2 and "longer than 2 s" in late.error and late.image_a is None
    assert third.seq == 3 and third.error is None and src.abandoned == 1


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_reader_thread_killed_by_a_bug_is_restarted_past_the_pair(tmp_path, monkeypatch):
    _spool(tmp_path, 3)
    real = spool_mod.decode_metadata

    def buggy(data, *, slot):
        if slot == 1:
            raise RuntimeError("boom")
        return real(data, slot=slot)

    monkeypatch.setattr(spool_mod, "decode_metadata", buggy)
    monkeypatch.setattr("threading.excepthook", lambda args: None)  # keep the output clean

    async def main():
        src = SpoolFrameSource(SpoolReader(tmp_path, start="all"), poll_s=0.001)
        got = [await src.next(timeout_s=10) for _ in range(2)]
        skips = src.take_skips()
        src.close()
        return got, skips, src

    got, skips, src = asyncio.run(main())
    assert [f.seq for f in got] == [1, 3] and src.restarts == 1
    assert [(s.file, s.reason) for s in skips] == [("pair-000000000001.json",
                                                     "reader error: RuntimeError: boom")]


def test_open_frame_source_uses_the_rigs_image_size(tmp_path):
    cfg = FramesConfig(source="spool", spool_dir=tmp_path / "spool", image_width=SHAPE[1],
                       image_height=SHAPE[0])
    src = open_frame_source(cfg)
    try:
        assert isinstance(src, SpoolFrameSource)
        assert src.reader.limits.image_shape == SHAPE and (tmp_path / "spool").is_dir()
    finally:
        src.close()


def test_read_gray_refuses_a_bomb_before_decoding(tmp_path):
    from core.imageio import read_gray

    p = tmp_path / "bomb.png"
    p.write_bytes(_png(16000, 16000, idat=zlib.compress(b"\0" * 16001 * 4)))
    with pytest.raises(MeasurementError, match="16000x16000 px exceeds"):
        read_gray(p)
    p.write_bytes(p.read_bytes()[:-12])
    with pytest.raises(MeasurementError, match="truncated"):
        read_gray(p)


def test_a_change_hidden_by_a_coarse_folder_mtime_is_found_by_the_rescan(tmp_path, monkeypatch):
    import types

    w = _spool(tmp_path, 1)
    clock = {"mono": 100.0, "wall_ns": 0}
    stub = types.SimpleNamespace(monotonic=lambda: clock["mono"],
                                 time_ns=lambda: clock["wall_ns"])
    monkeypatch.setattr(spool_mod, "time", stub)
    r = SpoolReader(tmp_path, start="all")
    clock["wall_ns"] = os.stat(tmp_path).st_mtime_ns + 10**12  # the folder looks quiet
    assert r.poll().seq == 1 and r.poll() is None
    before = os.stat(tmp_path)
    w.write(_frame(2))
    os.utime(tmp_path, ns=(before.st_atime_ns, before.st_mtime_ns))  # same clock tick
    assert r.poll() is None  # unchanged and quiet: not listed (saves CPU)
    clock["mono"] += spool_mod.RESCAN_S * 1.01
    assert r.poll().seq == 2  # the periodic listing finds it
