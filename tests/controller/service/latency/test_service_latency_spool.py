"""The spool's short path: a committed pair read without listing the folder.

* the inotify events name the committed slots (or say they cannot: overflow, a stray name);
* ``SpoolReader.note_committed`` reads those pairs without a listing, never a pair twice, a
  replaced file again, and lists again once its last listing is old;
* the ``.npy`` header remembered per header bytes and size gives what ``npy_header`` gives,
  and a damaged file still raises;
* the bench's camera prunes a pair by its names; its spool-only switch.
"""

from __future__ import annotations

import io
import os
import struct

import numpy as np
import pytest

from controller.frames.spool_watch import IN_CLOSE_WRITE, IN_MOVED_TO, IN_Q_OVERFLOW, summarize
from protocol.frames import Frame
from protocol.spool import SpoolReader, SpoolWriter

BACKSTOP_S = 60.0


def _event(name: bytes, mask: int = IN_MOVED_TO) -> bytes:
    padded = name + b"\0" * (16 - len(name) % 16) if name else b""
    return struct.pack("iIII", 1, mask, 0, len(padded)) + padded


def _frame(seq: int) -> Frame:
    image = (np.arange(6 * 9, dtype=np.uint16).reshape(6, 9) * (seq + 1)).astype(np.uint8)
    return Frame(seq=seq, t_s=0.01 * seq, image_a=image, image_b=image[::-1].copy(),
                 counts_a=seq, counts_b=seq + 1, speed_mm_s=600.0)


@pytest.mark.parametrize(("events", "slots"), [
    ([(b"pair-000000000007.json", IN_MOVED_TO)], [7]),
    ([(b"pair-000000000003.a.npy", IN_MOVED_TO), (b".tmp-x.json", IN_CLOSE_WRITE),
      (b"pair-000000000003.json", IN_MOVED_TO), (b"pair-000000000004.json", IN_MOVED_TO)],
     [3, 4]),
    ([(b"pair-000000000001.a.png", IN_CLOSE_WRITE)], []),
    ([(b"pair-000000000002.json", IN_MOVED_TO), (b"", IN_Q_OVERFLOW)], None),  # events lost
    ([(b"other.json", IN_MOVED_TO)], None),  # a commit name the reader must judge itself
    ([], []),
])
def test_the_events_name_the_committed_slots_or_say_they_cannot(events, slots):
    assert summarize(b"".join(_event(n, m) for n, m in events)).slots == slots


def _writer_and_reader(tmp_path, n_before: int = 2):
    writer = SpoolWriter(tmp_path, keep=50, fsync=False, image_format="npy")
    for seq in range(n_before):
        writer.write(_frame(seq))
    reader = SpoolReader(tmp_path, start="all")
    got = [reader.poll() for _ in range(n_before)]  # listed once: the pairs there
    assert [int(f.seq) for f in got] == list(range(n_before))
    return writer, reader


def test_a_noted_commit_is_read_without_a_listing(tmp_path, monkeypatch):
    writer, reader = _writer_and_reader(tmp_path)
    writer.write(_frame(2))
    writer.write(_frame(3))
    listings = []
    real_listing = SpoolReader._listing
    monkeypatch.setattr(SpoolReader, "_listing",
                        lambda self: listings.append(1) or real_listing(self))
    assert reader.note_committed([3, 2, 1])  # 1 was read already: left out
    assert reader.pending == 2
    frames = [reader.poll(), reader.poll()]
    assert [int(f.seq) for f in frames] == [2, 3]  # in slot order
    assert np.array_equal(frames[1].image_a, _frame(3).image_a)
    assert listings == []
    assert reader.note_committed([2, 3]) and reader.pending == 0  # never a pair twice


def test_a_replaced_file_at_a_noted_slot_is_read_again(tmp_path):
    writer, reader = _writer_and_reader(tmp_path)
    writer.next_slot = 1  # a writer restarted: a new pair at an old slot
    os.unlink(tmp_path / "pair-000000000001.json")
    writer.write(_frame(9))
    assert reader.note_committed([1])
    frame = reader.poll()
    assert frame is not None and int(frame.seq) == 9


def test_an_old_listing_makes_the_reader_list_again(tmp_path):
    writer, reader = _writer_and_reader(tmp_path)
    writer.write(_frame(2))
    assert not reader.note_committed([2], max_age_s=0.0)
    assert reader.pending == 0
    frame = reader.poll()  # lists, and finds it anyway
    assert frame is not None and int(frame.seq) == 2


def test_a_fresh_reader_lists_before_it_takes_a_note(tmp_path):
    SpoolWriter(tmp_path, keep=5, fsync=False).write(_frame(0))
    assert not SpoolReader(tmp_path, start="all").note_committed([0])


def test_the_spool_source_reads_woken_pairs_in_order(tmp_path):
    import asyncio

    from controller.frames.source import SpoolFrameSource
    from controller.frames.spool_watch import SpoolWatch

    if not SpoolWatch(tmp_path).active:
        pytest.skip("no inotify here")
    source = SpoolFrameSource(SpoolReader(tmp_path), poll_s=3600.0)  # only events deliver
    writer = SpoolWriter(tmp_path, keep=50, fsync=False, image_format="npy")

    async def main():
        out = []
        for seq in range(6):
            writer.write(_frame(seq))
            out.append(await asyncio.wait_for(source.next(), BACKSTOP_S))
        return out

    try:
        frames = asyncio.run(main())
    finally:
        source.close()
    assert [int(f.seq) for f in frames] == list(range(6))
    assert all(np.array_equal(f.image_b, _frame(int(f.seq)).image_b) for f in frames)


def _npy(array: np.ndarray) -> bytes:
    bio = io.BytesIO()
    np.save(bio, array, allow_pickle=False)
    return bio.getvalue()


@pytest.mark.parametrize("array", [
    np.zeros((3, 5), np.uint8), np.zeros((5, 3), np.uint8), np.ones((4, 4), ">u2"),
    np.asfortranarray(np.arange(12, dtype=np.uint16).reshape(3, 4)),
])
def test_the_remembered_npy_header_is_the_header(array):
    from core.imageio import _parse_npy_header, npy_header

    data = _npy(array)
    for _ in range(2):  # parsed, then remembered
        assert npy_header(data) == _parse_npy_header(data)
    head = npy_header(data)
    assert head.fortran_order == (array.flags.f_contiguous and not array.flags.c_contiguous)
    assert data[head.data_offset:] == array.tobytes(order="F" if head.fortran_order else "C")


def test_a_truncated_npy_file_is_refused_after_a_good_one_with_its_header():
    from core.errors import MeasurementError
    from core.imageio import npy_header

    data = _npy(np.zeros((3, 5), np.uint8))
    npy_header(data)
    with pytest.raises(MeasurementError, match="truncated"):
        npy_header(data[:-1])


def test_the_bench_camera_prunes_a_pair_by_its_names(tmp_path):
    from planer.benchmarks.service import _prune_slot

    for slot in (3, 4):
        for suffix in (".a.png", ".b.png", ".json"):
            (tmp_path / f"pair-{slot:012d}{suffix}").write_bytes(b"x")
    _prune_slot(tmp_path, 4, "png")
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "pair-000000000003.a.png", "pair-000000000003.b.png", "pair-000000000003.json"]


def test_the_bench_refuses_an_unknown_spool_only_switch(monkeypatch):
    from planer.benchmarks import service

    monkeypatch.setenv(service.ONLY_VIA_ENV, "camera")
    with pytest.raises(ValueError, match=service.ONLY_VIA_ENV):
        service.run(quick=True)
