"""Pairing camera images with the PLC's trigger latches (pure; no camera needed).

Every image carries its own (pair, role) in its pixels and every latch its pair in its counts,
so each test checks the one property that matters: a good pair is never made of the wrong two
images or the wrong counts, and every pair is accounted for (good, failed or skipped).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.frames.camera.pairing import CameraImage, PairAssembler, TriggerLatch
from core.units import wrap_counter

COUNTS_PER_MM = 20.0
SPEED_MM_S = 1000.0
AB_COUNTS = 40                      # 2 mm between trigger A and B -> 2 ms at 1000 mm/s
PAIR_NS = 10_000_000                # 10 ms between pairs
AB_NS = 2_000_000


def _image(seq: int, role: int) -> np.ndarray:
    img = np.zeros((2, 8), np.uint16)
    img[0, 0] = seq % 65536
    img[0, 1] = role
    return img


def _latch_counts(seq: int, counts0: int) -> tuple[int, int]:
    a = wrap_counter(counts0 + 1000 * seq, bits=32)
    return a, wrap_counter(a + AB_COUNTS, bits=32)


def scenario(n: int, *, seq0: int = 100, fid0: int = 1, ts0: int = 10**12, counts0: int = 5,
             skips_zero: bool = False, bits: int = 64) -> list[tuple[str, object]]:
    """Images A, B and the latch of pairs ``seq0 .. seq0 + n - 1``, in the natural order."""
    events: list[tuple[str, object]] = []
    modulus = (1 << bits) - (1 if skips_zero else 0)
    for i in range(n):
        seq = seq0 + i
        for role in (0, 1):
            k = 2 * i + role
            fid = (fid0 - 1 + k) % modulus + 1 if skips_zero else (fid0 + k) % modulus
            ts = ts0 + i * PAIR_NS + role * AB_NS
            events.append(("img", CameraImage(fid, ts, _image(seq, role))))
        a, b = _latch_counts(seq, counts0)
        events.append(("latch", TriggerLatch(seq=seq % 65536, counts_a=a, counts_b=b,
                                             speed_mm_s=SPEED_MM_S, t_s=i * 0.01)))
    return events


def run(events, *, seq0: int = 100, fid0: int = 1, flush: bool = True, **options):
    asm = PairAssembler(counts_per_mm=COUNTS_PER_MM, ab_tolerance_s=5e-4, **options)
    asm.sync(frame_id=fid0, seq=seq0 % 65536)
    frames, skips = [], []
    for kind, item in events:
        if kind == "img":
            asm.add_image(item)
        elif kind == "latch":
            asm.add_latch(item)
        elif kind == "restart_sync":
            frames += asm.take()
            asm.sync(frame_id=item[0], seq=item[1])
        frames += asm.take()
        skips += asm.take_skips()
    if flush:
        asm.flush()
    frames += asm.take()
    skips += asm.take_skips()
    return asm, frames, skips


def check_never_wrong(frames, *, counts0: int = 5, latches: bool = True) -> None:
    """Good pairs hold their own images and their own latch; seqs increase."""
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    for f in frames:
        if f.error is not None:
            assert f.image_a is None and f.image_b is None
            assert f.error.startswith(f"camera seq {f.seq}: ")
            continue
        assert f.image_a[0, 0] == f.seq % 65536 and f.image_a[0, 1] == 0
        assert f.image_b[0, 0] == f.seq % 65536 and f.image_b[0, 1] == 1
        if latches:
            assert (f.counts_a, f.counts_b) == _latch_counts(f.seq, counts0)


def by_seq(frames):
    return {f.seq: f for f in frames}


def test_clean_run_pairs_everything():
    asm, frames, skips = run(scenario(12))
    check_never_wrong(frames)
    assert [f.seq for f in frames] == list(range(100, 112))
    assert all(f.error is None for f in frames) and skips == []
    assert asm.counters["pairs"] == 12 and asm.counters["failed"] == 0


# (name, how to change the natural event list, seqs that must fail, text in their error)
def _drop(events, seq, role):
    return [e for e in events if not (e[0] == "img" and e[1].image[0, 0] == seq
                                      and e[1].image[0, 1] == role)]


def _incomplete(events, seq, role):
    out = []
    for kind, item in events:
        if kind == "img" and item.image[0, 0] == seq and item.image[0, 1] == role:
            item = CameraImage(item.frame_id, item.timestamp_ns, item.image, "missing packets")
        out.append((kind, item))
    return out


def _no_latch(events, seq):
    return [e for e in events if not (e[0] == "latch" and e[1].seq == seq)]


def _move_late(events, seq, role, by):
    i = next(i for i, e in enumerate(events) if e[0] == "img" and e[1].image[0, 0] == seq
             and e[1].image[0, 1] == role)
    ev = events.pop(i)
    events.insert(min(len(events), i + by), ev)
    return events


def _latches_late(events, by):
    """Every latch arrives ``by`` images later than it would (a slow PLC poll), in order."""
    out, waiting, images = [], [], 0
    for kind, item in events:
        if kind == "latch":
            waiting.append((images + by, (kind, item)))
            continue
        out.append((kind, item))
        images += 1
        while waiting and waiting[0][0] <= images:
            out.append(waiting.pop(0)[1])
    return out + [w[1] for w in waiting]


CASES = [
    ("B dropped", lambda ev: _drop(ev, 103, 1), {103: "image B missing"}),
    ("A dropped", lambda ev: _drop(ev, 105, 0), {105: "image A missing"}),
    ("A incomplete (packet loss)", lambda ev: _incomplete(ev, 102, 0),
     {102: "image A (frame id 5) incomplete: missing packets"}),
    ("missing latch", lambda ev: _no_latch(ev, 104), {104: "no trigger latch"}),
    ("B out of order by 5 events", lambda ev: _move_late(ev, 101, 1, 5), {}),
    ("A after B", lambda ev: _move_late(ev, 106, 0, 1), {}),
    ("latches two pairs late", lambda ev: _latches_late(ev, 5), {}),
    ("B too late (after the window)", lambda ev: _move_late(ev, 101, 1, 20),
     {101: "image B missing"}),
    ("latch repeated", lambda ev: ev[:3] + ev[2:], {}),
    ("conflicting latch before the images",
     lambda ev: [ev[2], ("latch", TriggerLatch(100, 1, 2))] + ev[:2] + ev[3:],
     {100: "two different latches"}),
]


@pytest.mark.parametrize(("name", "change", "fails"), CASES, ids=[c[0] for c in CASES])
def test_faults_fail_only_their_pair(name, change, fails):
    asm, frames, skips = run(change(scenario(12)))
    check_never_wrong(frames)
    got = by_seq(frames)
    assert sorted(got) == list(range(100, 112))  # every pair accounted for
    for seq, f in got.items():
        if seq in fails:
            assert f.error is not None and fails[seq] in f.error, (seq, f.error)
        else:
            assert f.error is None, (seq, f.error)
    assert asm.counters["failed"] == len(fails)


def test_whole_pairs_dropped_are_one_skip():
    events = [e for e in scenario(12) if not (e[0] == "img" and 103 <= e[1].image[0, 0] <= 106)]
    asm, frames, skips = run(events)
    check_never_wrong(frames)
    assert sorted(f.seq for f in frames) == [100, 101, 102, 107, 108, 109, 110, 111]
    gap = [s for s in skips if "no image of the pair" in s.reason]
    assert len(gap) == 1 and gap[0].slot == 103 and gap[0].pairs == 4
    assert asm.counters["dropped"] == 4


def test_plc_gone_fails_every_pair_never_counts_zero():
    events = [e for e in scenario(10) if e[0] == "img"]
    asm, frames, _ = run(events)
    assert len(frames) == 10 and all("no trigger latch" in f.error for f in frames)


def test_camera_missed_trigger_never_pairs_wrong_images():
    """One trigger lost in the camera (no frame id for it): A/B shift by one image."""
    events = scenario(12)
    shifted = []
    lost = False
    for kind, item in events:
        if kind == "img" and item.image[0, 0] == 104 and item.image[0, 1] == 0:
            lost = True  # camera never took it: the later images get its frame ids
            continue
        if kind == "img" and lost:
            item = CameraImage(item.frame_id - 1, item.timestamp_ns, item.image)
        shifted.append((kind, item))
    asm, frames, _ = run(shifted)
    check_never_wrong(frames)  # the A/B interval check refuses the shifted pairs
    bad = [f for f in frames if f.error]
    assert {f.seq for f in bad} >= {104, 105, 106, 107, 108, 109, 110}
    assert any("ms apart" in f.error for f in bad)


@pytest.mark.parametrize("skips_zero", [True, False])
def test_wrap_of_frame_id_seq_and_counts(skips_zero):
    bits = 16
    fid0 = 65530 if skips_zero else 65529
    counts0 = 2**32 - 1000 * 65533 - 3500  # the encoder counter wraps after 4 pairs
    events = scenario(10, seq0=65533, fid0=fid0, counts0=counts0, skips_zero=skips_zero,
                      bits=bits)
    asm, frames, skips = run(events, seq0=65533, fid0=fid0, frame_id_bits=bits,
                             frame_id_skips_zero=skips_zero)
    check_never_wrong(frames, counts0=counts0)
    assert [f.seq for f in frames] == list(range(65533, 65543))
    assert all(f.error is None for f in frames) and skips == []
    assert frames[-1].counts_a < frames[0].counts_a  # the encoder counter wrapped


def test_camera_restart_fails_open_pairs_then_resyncs():
    first = scenario(6)
    first = _drop(first, 105, 1)  # pair 105 open (A only) when the camera restarts
    second = scenario(4, seq0=110, fid0=1, ts0=5)  # ids and timestamps start again
    events = first + second[:2] + [("restart_sync", (1, 110))] + second
    asm, frames, skips = run(events)
    check_never_wrong(frames)
    got = by_seq(frames)
    assert [s for s in got if got[s].error is None] == [100, 101, 102, 103, 104, 110, 111,
                                                         112, 113]
    assert "camera restarted" in got[105].error
    assert asm.counters["restarts"] == 1
    assert any("waiting for re-synchronisation" in s.reason for s in skips)


def test_no_plc_mode_counts_left_out():
    events = [e for e in scenario(5) if e[0] == "img"]
    asm, frames, _ = run(events, latches=False)
    check_never_wrong(frames, latches=False)
    assert all(f.error is None and f.counts_a == 0 == f.counts_b for f in frames)


def test_images_before_sync_are_skipped():
    asm = PairAssembler()
    asm.add_image(CameraImage(1, 1, _image(0, 0)))
    assert asm.take() == [] and "not synchronised" in asm.take_skips()[0].reason


@pytest.mark.parametrize(("kw", "text"), [({"window": 0}, "window"),
                                          ({"frame_id_bits": 4}, "frame_id_bits"),
                                          ({"counts_per_mm": -1.0}, "counts_per_mm")])
def test_bad_options_name_the_parameter(kw, text):
    with pytest.raises(ValueError, match=text):
        PairAssembler(**kw)


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_random_faults_never_make_a_wrong_pair(data):
    n = 16
    events = scenario(n, seq0=65530, fid0=65500, counts0=2**32 - 7000, skips_zero=True, bits=16)
    for _ in range(data.draw(st.integers(0, 6))):
        kind = data.draw(st.sampled_from(["drop", "incomplete", "latch", "late"]))
        seq = 65530 + data.draw(st.integers(0, n - 1))
        role = data.draw(st.integers(0, 1))
        if kind == "drop":
            events = _drop(events, seq % 65536, role)
        elif kind == "incomplete":
            events = _incomplete(events, seq % 65536, role)
        elif kind == "latch":
            events = _no_latch(events, seq % 65536)
        elif any(e[0] == "img" and e[1].image[0, 0] == seq % 65536 and e[1].image[0, 1] == role
                 for e in events):
            events = _move_late(events, seq % 65536, role, data.draw(st.integers(1, 12)))
    asm, frames, skips = run(events, seq0=65530, fid0=65500, frame_id_bits=16,
                             frame_id_skips_zero=True)
    check_never_wrong(frames, counts0=2**32 - 7000)
    accounted = {f.seq for f in frames}
    for s in skips:
        if s.slot is not None:
            accounted |= set(range(s.slot, s.slot + s.pairs))
    # every pair up to the last one the camera or the PLC told of is accounted for; trailing
    # pairs of which neither an image nor a latch arrived never existed for the assembler
    told = [65530 + ((int(e[1].image[0, 0] if e[0] == "img" else e[1].seq) - 65530) % 65536)
            for e in events]
    assert accounted == set(range(65530, max(told) + 1))


def test_last_pair_without_images_is_reported_dropped():
    """Both images of the run's last pair lost: its latch names it, flush reports it."""
    events = _drop(_drop(scenario(6), 105, 0), 105, 1)
    asm, frames, skips = run(events)
    check_never_wrong(frames)
    assert [f.seq for f in frames] == list(range(100, 105))
    (skip,) = [s for s in skips if s.slot is not None]
    assert (skip.slot, skip.pairs) == (105, 1) and asm.counters["dropped"] == 1


def test_failed_buffer_without_frame_id_is_no_restart():
    events = scenario(8, fid0=100)
    events.insert(5, ("img", CameraImage(0, 0, None, "missing packets")))
    asm, frames, skips = run(events, fid0=100, frame_id_bits=16, frame_id_skips_zero=True)
    check_never_wrong(frames)
    assert asm.counters["restarts"] == 0 and all(f.error is None for f in frames)
    assert any("without frame id" in s.reason for s in skips)


def test_next_seq_continues_across_a_restart_without_plc():
    asm = PairAssembler(latches=False)
    asm.sync(frame_id=1, seq=0)
    for i in range(4):
        asm.add_image(CameraImage(1 + i, 1000 + i, _image(i // 2, i % 2)))
    asm.restart("test")
    assert [f.seq for f in asm.take()] == [0, 1] and asm.next_seq == 2
    asm.sync(frame_id=1, seq=asm.next_seq)  # ids start again, seq goes on
    asm.add_image(CameraImage(1, 5, _image(2, 0)))
    asm.add_image(CameraImage(2, 6, _image(2, 1)))
    (f,) = asm.take()
    assert f.seq == 2 and f.error is None


def test_reread_latch_with_new_time_and_speed_is_the_same_latch():
    events = scenario(4)
    again = [("latch", TriggerLatch(seq=e[1].seq, counts_a=e[1].counts_a,
                                    counts_b=e[1].counts_b, speed_mm_s=SPEED_MM_S + 3.0,
                                    t_s=e[1].t_s + 0.001)) for e in events if e[0] == "latch"]
    asm, frames, _ = run([again[0], events[3]] + events[:3] + events[4:])
    check_never_wrong(frames)
    assert all(f.error is None for f in frames) and len(frames) == 4


def test_ab_check_uses_the_plcs_counts_per_mm_by_default():
    """No counts_per_mm given to the assembler: the latch's own (read from the PLC) is used."""
    events = []
    for kind, item in scenario(8):
        if kind == "latch":
            item = TriggerLatch(seq=item.seq, counts_a=item.counts_a, counts_b=item.counts_b,
                                speed_mm_s=SPEED_MM_S, counts_per_mm=COUNTS_PER_MM)
        elif item.image[0, 0] >= 103:  # the camera missed trigger A of pair 103: ids shift
            if (item.image[0, 0], item.image[0, 1]) == (103, 0):
                continue
            item = CameraImage(item.frame_id - 1, item.timestamp_ns, item.image)
        events.append((kind, item))
    asm = PairAssembler()
    asm.sync(frame_id=1, seq=100)
    for kind, item in events:
        (asm.add_image if kind == "img" else asm.add_latch)(item)
    asm.flush()
    frames = asm.take()
    check_never_wrong(frames)
    assert [f.seq for f in frames if f.error is None] == [100, 101, 102]
