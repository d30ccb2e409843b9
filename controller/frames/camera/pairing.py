"""Pairing camera images A/B with the PLC's trigger latches (pure, sans-I/O).

The encoder-driven trigger fires twice per pair: trigger A (light A) then trigger B (light B).
The camera numbers its images (``frame_id``, the GigE Vision block id, wrapping at
``frame_id_bits``) and stamps them (``timestamp_ns``, the camera's clock); the PLC latches the
encoder counts of both triggers with the pair's ``trigger_seq`` (u16, wraps at 2**16). After a
:meth:`PairAssembler.sync` (image ``frame_id`` is trigger A of pair ``seq``), image ``k`` images
later belongs to pair ``seq + k // 2``, as A when ``k`` is even, else B. A pair is handed out
only with the latch of its own ``seq``:

* a pair whose image is incomplete (GVSP packet loss, timeout) or missing -> failed frame naming
  the image and the frame id;
* a pair without its latch (the PLC poll missed it, the PLC is gone) -> failed frame;
* a pair whose A/B interval on the camera clock contradicts its latches (a trigger the camera
  missed would swap A and B) -> failed frame;
* pairs of which no image arrived -> one :class:`~protocol.spool_files.Skip` per run of them;
* frame ids and timestamps that disagree on the order (a camera restart) -> the open pairs
  fail, the assembler waits for the next :meth:`PairAssembler.sync`; images until then are
  skipped.

Out-of-order images are put in their place as long as their pair is open (``window`` pairs).
Pairs leave in ``seq`` order. Nothing here reads a clock or a device.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.checks import check_int, check_positive
from core.units import counter_difference, wrap_counter
from protocol.frames import Frame
from protocol.spool_files import Skip

__all__ = ["AB_TOLERANCE", "CameraImage", "PairAssembler", "TriggerLatch"]

#: Default tolerance of the A/B interval check, relative to the interval the latches give (a
#: trigger missed by the camera makes the interval the rest of the pair period instead).
AB_TOLERANCE = 0.5


@dataclass(frozen=True)
class CameraImage:
    """One buffer from the camera.

    Attributes
    ----------
    frame_id : int
        The camera's image number (GigE Vision block id), wrapping at ``frame_id_bits``.
    timestamp_ns : int
        The camera's timestamp of the exposure, nanoseconds (camera clock).
    image : ndarray, shape (H, W), or None
        The image (``None`` when the buffer is unusable).
    status : str
        ``"ok"``, or why the buffer is unusable (``"missing packets"``, ``"timeout"``, ...).
    """

    frame_id: int
    timestamp_ns: int
    image: np.ndarray | None
    status: str = "ok"


@dataclass(frozen=True)
class TriggerLatch:
    """The PLC's latches of one pair (``trigger_*`` registers, docs/register_map.md).

    Attributes
    ----------
    seq : int
        ``trigger_seq`` as read (any integer; taken modulo ``2**seq_bits``).
    counts_a, counts_b : int
        Encoder counts latched at trigger A and B (wrapped 32-bit counter).
    index_latch_counts : int
        Encoder counts at the spindle index pulse for this pair.
    board_id : int
        Board under the camera.
    board_position_mm : float
        Position of image A's centre from the board's leading end, mm.
    speed_mm_s : float
        Feed speed at the pair, mm/s (0: unknown).
    t_s : float
        Machine time of the latch, seconds.
    counts_per_mm : float
        Encoder resolution the PLC reports (0: unknown); with ``speed_mm_s`` it gives the A/B
        interval the camera's time stamps are checked against.
    """

    seq: int
    counts_a: int
    counts_b: int
    index_latch_counts: int = 0
    board_id: int = 0
    board_position_mm: float = 0.0
    speed_mm_s: float = 0.0
    t_s: float = 0.0
    counts_per_mm: float = 0.0


def _latched(latch: TriggerLatch) -> tuple[int, int, int]:
    """What the PLC latched for a pair (a re-read may differ in time, speed, position only)."""
    return (int(latch.counts_a), int(latch.counts_b), int(latch.index_latch_counts))


@dataclass
class _Open:
    """A pair being assembled: its images by role (0 = A, 1 = B)."""

    images: dict[int, CameraImage] = field(default_factory=dict)


class PairAssembler:
    """Assemble :class:`Frame` pairs from camera images and PLC latches (pure).

    Parameters
    ----------
    latches : bool, keyword-only
        Pair with PLC latches (the machine). ``False``: no PLC (``planer acquire`` without
        ``--plc``); pairs carry counts 0 and ``seq`` from the frame ids.
    window : int, keyword-only
        Pairs an incomplete pair waits for a late image or its latch, counted in pairs whose
        images arrived after it (no clock).
    frame_id_bits, seq_bits, counter_bits : int, keyword-only
        Widths of the camera's frame id, of ``trigger_seq`` and of the encoder counter.
    frame_id_skips_zero : bool, keyword-only
        The frame id runs ``1 .. 2**frame_id_bits - 1`` and skips 0 when it wraps (GigE Vision
        1.x block ids, Aravis' fake cameras); else ``0 .. 2**frame_id_bits - 1``.
    counts_per_mm : float or None, keyword-only
        Encoder resolution (``None``: the latch's ``counts_per_mm``, when it has one): the A/B
        interval on the camera clock is checked against the latches'
        ``(counts_b - counts_a) / counts_per_mm / speed_mm_s`` (when the speed is known).
    ab_tolerance_s : float or None, keyword-only
        Largest accepted difference of that check, seconds (``None``: ``AB_TOLERANCE`` times
        the latches' interval).
    max_jump_pairs : int, keyword-only
        A frame id more than this many pairs ahead is a camera restart, not a drop.

    Attributes
    ----------
    counters : dict
        ``images``, ``pairs`` (good), ``failed``, ``dropped`` (pairs without any image),
        ``skipped_images``, ``restarts``, ``latches``.
    """

    def __init__(self, *, latches: bool = True, window: int = 4, frame_id_bits: int = 64,
                 frame_id_skips_zero: bool = False, seq_bits: int = 16, counter_bits: int = 32,
                 counts_per_mm: float | None = None, ab_tolerance_s: float | None = None,
                 max_jump_pairs: int = 10_000) -> None:
        self.use_latches = bool(latches)
        self.window = check_int("window", window, lo=1, hi=1000)
        self.frame_id_bits = check_int("frame_id_bits", frame_id_bits, lo=8, hi=64)
        self.frame_id_skips_zero = bool(frame_id_skips_zero)
        self.seq_bits = check_int("seq_bits", seq_bits, lo=8, hi=64)
        self.counter_bits = check_int("counter_bits", counter_bits, lo=8, hi=64)
        self.counts_per_mm = (None if counts_per_mm is None
                              else check_positive("counts_per_mm", counts_per_mm))
        self.ab_tolerance_s = (None if ab_tolerance_s is None
                               else check_positive("ab_tolerance_s", ab_tolerance_s))
        self.max_jump_pairs = check_int("max_jump_pairs", max_jump_pairs, lo=1)
        self.counters = dict.fromkeys(("images", "pairs", "failed", "dropped", "skipped_images",
                                       "restarts", "latches"), 0)
        self._out: list[Frame] = []
        self._skips: list[Skip] = []
        self._synced = False
        self._seq0 = 0           # running seq of pair index 0
        self._last_fid = 0       # last frame id seen and its image index k
        self._last_k = 0
        self._max_k = -1         # highest image index seen
        self._ts_k = -1          # highest complete image's index and its timestamp
        self._ts = 0
        self._next_p = 0         # lowest pair index not yet handed out
        self._open: dict[int, _Open] = {}
        self._latches: dict[int, TriggerLatch | str] = {}  # running seq -> latch or conflict
        self._seq_ref: int | None = None  # a recent running seq (unwraps trigger_seq)
        self._max_latch_seq: int | None = None
        self._gap: tuple[int, int] | None = None  # (first seq, pairs) without any image
        self._behind: tuple[int, int] | None = None  # last far-behind image (fid, ts)

    # -- inputs --------------------------------------------------------------------------------

    @property
    def next_seq(self) -> int:
        """The ``seq`` the next pair handed out gets (continues across a restart)."""
        return self._seq0 + self._next_p

    @property
    def synced(self) -> bool:
        """Whether images are being mapped to pairs (after :meth:`sync`, until a restart)."""
        return self._synced

    def sync(self, *, frame_id: int, seq: int) -> None:
        """Image ``frame_id`` is trigger A of pair ``seq`` (``trigger_seq``, wrapped or not).

        Pending pairs of an earlier synchronisation are handed out first (as they are).
        """
        check_int("frame_id", frame_id)
        check_int("seq", seq)
        self._finish_open("camera re-synchronised before the pair was complete")
        ref = self._seq_ref
        running = int(seq) if ref is None else ref + counter_difference(seq, ref,
                                                                          bits=self.seq_bits)
        self._seq0 = running
        self._seq_ref = running
        self._last_fid = self._fid(frame_id)
        self._last_k = 0
        self._max_k = -1
        self._ts_k = -1
        self._ts = 0
        self._next_p = 0
        self._behind = None
        self._synced = True
        self._latches = {s: v for s, v in self._latches.items() if s >= running}
        if self._max_latch_seq is not None and self._max_latch_seq < running:
            self._max_latch_seq = None

    def _fid(self, frame_id: int) -> int:
        """A frame id on the camera's counter: ``0 .. modulus - 1`` (1 less when 0 is skipped)."""
        if self.frame_id_skips_zero:
            return (int(frame_id) - 1) % ((1 << self.frame_id_bits) - 1)
        return wrap_counter(frame_id, bits=self.frame_id_bits)

    def _fid_step(self, later: int, earlier: int) -> int:
        """Signed images from ``earlier`` to ``later`` (two :meth:`_fid` values), across wrap."""
        if not self.frame_id_skips_zero:
            return counter_difference(later, earlier, bits=self.frame_id_bits)
        modulus = (1 << self.frame_id_bits) - 1  # odd: no power of two, counted here
        half = modulus // 2
        return (later - earlier + half) % modulus - half

    def add_latch(self, latch: TriggerLatch) -> None:
        """A latch record from the PLC (a repeated read of the same latch is ignored)."""
        if not isinstance(latch, TriggerLatch):
            raise ValueError(f"latch must be a TriggerLatch, got {type(latch).__name__}")
        if not self.use_latches:
            return
        ref = self._seq_ref if self._seq_ref is not None else int(latch.seq)
        running = ref + counter_difference(latch.seq, ref, bits=self.seq_bits)
        if self._synced and running < self._seq0 + self._next_p:
            return  # its pair is already handed out (or precedes the synchronisation)
        old = self._latches.get(running)
        if old is None:
            self._latches[running] = latch
            self.counters["latches"] += 1
        elif isinstance(old, TriggerLatch) and _latched(old) != _latched(latch):
            self._latches[running] = "two different latches for this seq"
        self._seq_ref = running
        if self._max_latch_seq is None or running > self._max_latch_seq:
            self._max_latch_seq = running
        self._emit()

    def add_image(self, image: CameraImage) -> None:
        """One camera buffer (any order within the window)."""
        if not isinstance(image, CameraImage):
            raise ValueError(f"image must be a CameraImage, got {type(image).__name__}")
        self.counters["images"] += 1
        fid = int(image.frame_id)
        if not self._synced:
            self._skip_image(fid, "camera not synchronised with the trigger sequence (yet)")
            return
        ts = int(image.timestamp_ns)
        ok = image.status == "ok" and image.image is not None
        if not ok and (ts <= 0 or (self.frame_id_skips_zero and self._fid(fid) == self._fid(0))):
            # a failed buffer without its frame id / time stamp cannot be placed: its pair
            # fails (or is reported dropped) by the window; it must not look like a restart
            self._skip_image(fid, f"{image.status} buffer without frame id or time stamp")
            return
        k = self._last_k + self._fid_step(self._fid(fid), self._last_fid)
        if self._max_k >= 0 and k < 2 * (self._next_p - self.window):
            # far behind the pairs handed out: a straggler, or the first images of a camera
            # that restarted (ids and timestamps from the start again); two in a row: restart
            prev, self._behind = self._behind, ((self._fid(fid), ts) if ok else None)
            if ok and prev is not None and self._fid_step(self._fid(fid), prev[0]) == 1 \
                    and ts > prev[1]:
                self._behind = None
                self.restart(f"camera restarted (frame id went back to {fid})")
                self._skip_image(fid, "camera restarted: waiting for re-synchronisation")
            else:
                self._skip_image(fid, "far behind the pairs handed out (late, or the camera "
                                 "restarted)")
            return
        self._behind = None
        if k - self._max_k > 2 * self.max_jump_pairs and self._max_k >= 0 and not ok:
            self._skip_image(fid, f"{image.status} buffer with a frame id far ahead")
            return
        if ok and self._ts_k >= 0 and ((k > self._ts_k and ts < self._ts)
                                       or (k < self._ts_k and ts > self._ts)
                                       or k - self._max_k > 2 * self.max_jump_pairs):
            self.restart(f"camera restarted (frame id {fid} at {ts} ns disagrees with image "
                         f"{self._ts_k} of this run at {self._ts} ns)")
            self._skip_image(fid, "camera restarted: waiting for re-synchronisation")
            return
        self._last_fid, self._last_k = self._fid(fid), k
        if k < 0:
            self._skip_image(fid, "precedes the synchronisation point")
            return
        p, role = divmod(k, 2)
        if p < self._next_p:
            self._skip_image(fid, f"arrived after its pair seq {self._seq0 + p} was handed out")
            return
        self._max_k = max(self._max_k, k)
        if ok and k > self._ts_k:
            self._ts_k, self._ts = k, ts
        slot = self._open.setdefault(p, _Open())
        if role in slot.images:
            self._skip_image(fid, "repeated frame id")
            return
        slot.images[role] = image
        self._emit()

    def restart(self, reason: str) -> None:
        """The camera restarted: open pairs fail with ``reason``; wait for :meth:`sync`."""
        self.counters["restarts"] += 1
        self._finish_open(reason)
        self._synced = False

    def flush(self) -> None:
        """Hand out every open pair as it is (end of an acquisition)."""
        self._finish_open("acquisition ended before the pair was complete")

    # -- outputs -------------------------------------------------------------------------------

    def take(self) -> list[Frame]:
        """Frames handed out since the last call (good and failed), in ``seq`` order."""
        out, self._out = self._out, []
        return out

    def take_skips(self) -> list[Skip]:
        """Images and dropped pairs that gave no frame since the last call."""
        out, self._skips = self._skips, []
        return out

    # -- internals -----------------------------------------------------------------------------

    def _end_gap(self) -> None:
        """Report the run of pairs without any image that just ended, as one skip."""
        if self._gap is None:
            return
        first, n = self._gap
        self._gap = None
        name = f"camera seq {first}" if n == 1 else f"camera seq {first}..{first + n - 1}"
        self._skips.append(Skip(name, "no image of the pair arrived (dropped by the camera or "
                                "the network)", first, n))

    def _skip_image(self, fid: int, reason: str) -> None:
        self.counters["skipped_images"] += 1
        self._skips.append(Skip(f"camera frame id {fid}", reason))

    def _finish_open(self, reason: str) -> None:
        if not self._synced:
            return
        last = max(self._open, default=self._next_p - 1)
        latched = (None if not self.use_latches or self._max_latch_seq is None
                   else self._max_latch_seq - self._seq0)
        if latched is not None and latched - self._next_p <= self.max_jump_pairs:
            # pairs the PLC latched but of which no image arrived (the last ones of a run
            # included) are reported as dropped, never lost without a word
            last = max(last, latched)
        while self._next_p <= last:
            self._hand_out(self._next_p, incomplete=reason)
        self._open.clear()
        self._end_gap()

    def _emit(self) -> None:
        """Hand out pairs from ``_next_p`` on while they are complete or given up."""
        while self._synced:
            p = self._next_p
            seq = self._seq0 + p
            slot = self._open.get(p)
            have = len(slot.images) if slot else 0
            later_images = self._max_k >= 2 * (p + self.window)
            latch_known = (not self.use_latches or seq in self._latches
                           or (self._max_latch_seq is not None and self._max_latch_seq > seq))
            if have == 2 and latch_known:
                self._hand_out(p)
            elif later_images:
                self._hand_out(p, incomplete="given up")
            else:
                return

    def _hand_out(self, p: int, *, incomplete: str | None = None) -> None:
        seq = self._seq0 + p
        slot = self._open.pop(p, None)
        self._next_p = p + 1
        latch = self._latches.pop(seq, None) if self.use_latches else None
        images = slot.images if slot else {}
        if not images:
            self.counters["dropped"] += 1
            if self._gap is None:
                self._gap = (seq, 0)
            self._gap = (self._gap[0], self._gap[1] + 1)
            return
        self._end_gap()
        problems = []
        for role, name in ((0, "A"), (1, "B")):
            img = images.get(role)
            if img is None:
                missing = "missing"
                if incomplete and incomplete != "given up":
                    missing += f" ({incomplete})"
                problems.append(f"image {name} {missing}")
            elif img.status != "ok" or img.image is None:
                status = img.status if img.status != "ok" else "no image data"
                problems.append(f"image {name} (frame id {img.frame_id}) incomplete: {status}")
        if self.use_latches:
            if latch is None:
                problems.append("no trigger latch from the PLC for this seq")
            elif isinstance(latch, str):
                problems.append(latch)
                latch = None
        if not problems and latch is not None:
            problems.extend(self._check_latch(images[0], images[1], latch))
        if problems:
            self._fail(seq, images, latch, "; ".join(problems))
            return
        a, b = images[0], images[1]
        if a.image.shape != b.image.shape or a.image.dtype != b.image.dtype:
            self._fail(seq, images, latch, f"image A is {a.image.shape}, image B "
                       f"{b.image.shape}")
            return
        self.counters["pairs"] += 1
        if latch is None:
            self._out.append(Frame(seq=seq, t_s=a.timestamp_ns * 1e-9, image_a=a.image,
                                   image_b=b.image, counts_a=0, counts_b=0, speed_mm_s=0.0))
            return
        self._out.append(Frame(
            seq=seq, t_s=latch.t_s, image_a=a.image, image_b=b.image,
            counts_a=wrap_counter(latch.counts_a, bits=self.counter_bits),
            counts_b=wrap_counter(latch.counts_b, bits=self.counter_bits),
            speed_mm_s=float(latch.speed_mm_s),
            index_latch_counts=wrap_counter(latch.index_latch_counts, bits=self.counter_bits),
            board_id=int(latch.board_id), board_position_mm=float(latch.board_position_mm)))

    def _check_latch(self, a: CameraImage, b: CameraImage, latch: TriggerLatch) -> list[str]:
        out = []
        d_counts = counter_difference(latch.counts_b, latch.counts_a, bits=self.counter_bits)
        if d_counts <= 0:
            out.append(f"latch counts_b {latch.counts_b} is not after counts_a {latch.counts_a}")
        dt_s = (int(b.timestamp_ns) - int(a.timestamp_ns)) * 1e-9
        if dt_s <= 0:
            out.append(f"image B is not after image A on the camera clock ({dt_s * 1e3:.3f} ms)")
        elif not out and latch.speed_mm_s > 0 and (self.counts_per_mm or latch.counts_per_mm):
            expected_s = d_counts / (self.counts_per_mm or latch.counts_per_mm) / latch.speed_mm_s
            tolerance_s = (self.ab_tolerance_s if self.ab_tolerance_s is not None
                           else AB_TOLERANCE * expected_s)
            if abs(dt_s - expected_s) > tolerance_s:
                out.append(f"images A/B are {dt_s * 1e3:.3f} ms apart, the latches say "
                           f"{expected_s * 1e3:.3f} ms (a trigger missed by the camera?)")
        return out

    def _fail(self, seq: int, images: dict[int, CameraImage], latch: TriggerLatch | None,
              reason: str) -> None:
        self.counters["failed"] += 1
        first = images.get(0) or images.get(1)
        t_s = latch.t_s if latch is not None else (first.timestamp_ns * 1e-9 if first else 0.0)
        self._out.append(Frame(seq=seq, t_s=t_s, image_a=None, image_b=None, counts_a=0,
                               counts_b=0, speed_mm_s=0.0, error=f"camera seq {seq}: {reason}"))
