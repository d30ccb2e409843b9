"""The hand-off between processes: a spool folder of atomically written pairs (docs/frames.md).

:class:`SpoolWriter` writes each pair's images, then its metadata file last (the commit);
:class:`SpoolReader` reads committed pairs in slot order, never a half-written one, refusing
what is not a pair with the reason (:mod:`protocol.spool_files` holds the files' format and
checks).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import threading
import time
from collections import deque
from pathlib import Path

from core.fileio import atomic_write_bytes
from protocol.frames import Frame
from protocol.spool_files import (
    _META_NAME,
    _META_SUFFIX,
    _PREFIX,
    _TMP_PREFIX,
    SPOOL_VERSION,
    MetadataRefused,
    Skip,
    SpoolFileError,
    SpoolLimits,
    _encode_image,
    _slot_of,
    decode_metadata,
    decode_spool_image,
    frame_metadata,
    read_spool_file,
)

#: An unchanged, quiet spool folder is listed again after this long anyway, seconds.
RESCAN_S = 0.1


def _committed_slots(directory: Path) -> list[int]:
    try:
        names = os.listdir(directory)
    except FileNotFoundError:
        return []
    return sorted(s for s in (_slot_of(n) for n in names) if s is not None)


class SpoolWriter:
    """Writes frames into a spool directory, each pair atomically, pruning old pairs.

    A pair ``n`` (the writer's slot number, increasing by one per pair and continued after the
    highest slot present when a writer restarts) is the files ``pair-<n>.a.png``,
    ``pair-<n>.b.png`` and ``pair-<n>.json``. Each is written under a temporary dot-name,
    flushed and fsync'ed, then renamed; the metadata file is renamed LAST: it is the commit
    marker, so a reader never sees a pair whose images are incomplete.

    Parameters
    ----------
    directory : str or Path
        The spool directory (created if missing).
    keep : int
        How many committed pairs to keep; older ones are deleted (metadata first).
    fsync : bool
        fsync files and the directory (crash safety); tests may turn it off for speed.
    image_format : {"png", "npy"}
        ``"npy"`` writes raw ``.npy`` images: no PNG decode for the reader (about 0.5 ms less
        per pair at 659x493), twice the bytes.
    """

    def __init__(self, directory: str | Path, *, keep: int = 100, fsync: bool = True,
                 image_format: str = "png") -> None:
        if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
            raise ValueError(f"keep must be an integer >= 1, got {keep!r}")
        if image_format not in ("png", "npy"):
            raise ValueError(f"image_format must be 'png' or 'npy', got {image_format!r}")
        self.image_format = image_format
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.keep = keep
        self.fsync = fsync
        for name in os.listdir(self.directory):  # leftovers of a killed writer
            if name.startswith(_TMP_PREFIX):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self.directory / name)
        slots = _committed_slots(self.directory)
        while slots and not self._is_pair(slots[-1]):  # a stray file does not set the numbering
            slots.pop()
        self._slots: list[int] = slots
        self.next_slot = (slots[-1] + 1) if slots else 0
        self.written = 0

    def _is_pair(self, slot: int) -> bool:
        try:
            data, _ = read_spool_file(self.directory, f"{_PREFIX}{slot:012d}{_META_SUFFIX}",
                                      max_bytes=SpoolLimits.max_meta_bytes)
            decode_metadata(data, slot=slot)
        except (OSError, SpoolFileError):
            return False
        return True

    def write(self, frame: Frame) -> Path:
        """Write one pair atomically; returns the path of its metadata file (the commit marker)."""
        slot = self.next_slot
        stem = f"{_PREFIX}{slot:012d}"
        meta = frame_metadata(frame)
        meta["version"] = SPOOL_VERSION
        meta["slot"] = slot
        d = self.directory
        for key, img in (("image_a", frame.image_a), ("image_b", frame.image_b)):
            if img is None:  # a machine run without rendering: metadata only
                meta[key] = None
                continue
            suffix, data = _encode_image(key, img, self.image_format)
            final = f"{stem}.{key[-1]}{suffix}"
            atomic_write_bytes(d / final, data, durable=self.fsync, tmp_prefix=_TMP_PREFIX)
            meta[key] = final
        body = json.dumps(meta, separators=(",", ":"), allow_nan=False).encode()
        final_meta = d / f"{stem}{_META_SUFFIX}"
        # the commit, after the images are durable
        atomic_write_bytes(final_meta, body, durable=self.fsync, tmp_prefix=_TMP_PREFIX)
        self.next_slot = slot + 1
        self.written += 1
        self._slots.append(slot)
        self._prune()
        return final_meta

    def _prune(self) -> None:
        while len(self._slots) > self.keep:
            old = self._slots.pop(0)
            stem = f"{_PREFIX}{old:012d}"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.directory / f"{stem}{_META_SUFFIX}")  # uncommit first
            for name in os.listdir(self.directory):
                if name.startswith(stem + "."):
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(self.directory / name)


class SpoolReader:
    """Returns the pairs a :class:`SpoolWriter` commits, in slot order, one per ``poll``.

    Every committed metadata file gives either a :class:`Frame` (with ``error`` set when its
    images or fields are bad: the service logs a failed measurement) or a :class:`Skip`
    (:meth:`take_skips`: not a pair's metadata, vanished, refused file). A bad file never stops
    the reader nor makes it read earlier pairs again: the reader remembers each slot it has
    handled (and the identity of its file) as long as the file is there, so a new file at an
    old slot (a writer restarted on an emptied folder) is read, an old one never twice.

    Parameters
    ----------
    directory : str or Path
        The spool directory (need not exist yet).
    start : {"new", "all"}
        ``"new"`` skips pairs already committed when the reader is made (a live camera);
        ``"all"`` returns them too.
    limits : SpoolLimits, keyword-only, optional
        Size, pixel and shape limits (default :class:`SpoolLimits()`).

    Attributes
    ----------
    read : int
        Frames returned (failed ones included).
    skipped : int
        Metadata files that gave no frame (each reported as a :class:`Skip`).
    missed : int
        Pairs that never reached the reader: pruned or removed before they were read (a gap
        in the slot numbers that the pairs' ``seq`` confirms), reported as one :class:`Skip`.
    """

    def __init__(self, directory: str | Path, *, start: str = "new",
                 limits: SpoolLimits | None = None) -> None:
        if start not in ("new", "all"):
            raise ValueError(f"start must be 'new' or 'all', got {start!r}")
        if limits is not None and not isinstance(limits, SpoolLimits):
            raise ValueError(f"limits must be SpoolLimits, got {type(limits).__name__}")
        self.directory = Path(directory)
        self.limits = limits or SpoolLimits()
        self._lock = threading.Lock()
        self._done: dict[int, tuple[int, int] | None] = {}  # slot -> (inode, mtime) of its file
        self._dir_mtime: int | None = None
        self._listed_at = -math.inf
        self._pending: list[int] = []
        self._skips: deque[Skip] = deque(maxlen=10_000)
        self._bad_names: set[str] = set()
        self._last: tuple[int, int] | None = None  # (slot, seq) of the last valid pair
        self._last_seq: int | None = None
        self.read = 0
        self.skipped = 0
        self.missed = 0
        #: slot being read now and its metadata frame once decoded (for a time-out report)
        self.current: tuple[int, Frame | None] | None = None
        #: number of the pair read now (increases by one per slot handled)
        self.serial = 0
        if start == "new":
            for slot in self._listing():
                self._done[slot] = self._identity(slot)

    # -- listing ------------------------------------------------------------------------------

    def _listing(self) -> dict[int, str]:
        try:
            names = os.listdir(self.directory)
        except OSError:  # not there (yet), not a folder, no permission: no pairs now
            return {}
        out: dict[int, str] = {}
        for name in names:
            m = _META_NAME.fullmatch(name)
            if m:
                out[int(m.group(1))] = name
            elif (name.startswith(_PREFIX) and name.endswith(_META_SUFFIX)
                  and name not in self._bad_names and len(self._bad_names) < 10_000):
                self._bad_names.add(name)
                self._skip(Skip(name, "not a pair's name (pair-<digits>.json)"))
        return out

    def _identity(self, slot: int) -> tuple[int, int] | None:
        try:  # a str path: no Path object per handled file and scan (latency)
            st = os.lstat(os.path.join(self.directory, f"{_PREFIX}{slot:012d}{_META_SUFFIX}"))
        except OSError:
            return None
        return (st.st_ino, st.st_mtime_ns)

    def _scan(self) -> None:
        """List the folder unless it is unchanged and quiet (saves CPU while no pair comes).

        Listed when its mtime changed, when that mtime is recent (within :data:`RESCAN_S` of
        now: a change within one tick of the file system's coarse clock leaves the mtime as it
        was), and every :data:`RESCAN_S` anyway.
        """
        try:
            mtime: int | None = os.stat(self.directory).st_mtime_ns
        except OSError:
            mtime = None
        now = time.monotonic()
        if (mtime is not None and mtime == self._dir_mtime
                and now - self._listed_at < RESCAN_S
                and time.time_ns() - mtime > RESCAN_S * 1e9):
            self._pending = []
            return
        self._dir_mtime, self._listed_at = mtime, now
        present = self._listing()
        with self._lock:
            for slot in [s for s in self._done if s not in present]:
                del self._done[slot]  # gone: a new file there later is a new pair
            for slot in list(self._done):  # a handled file replaced: a new pair there
                ident = self._done[slot]
                if ident is not None and self._identity(slot) not in (ident, None):
                    del self._done[slot]
            self._pending = sorted(s for s in present if s not in self._done)

    def _skip(self, skip: Skip) -> None:
        self._skips.append(skip)
        self.skipped += 1

    @property
    def pending(self) -> int:
        """Pairs the last listing found, not read yet (``poll`` returns them without a listing)."""
        return len(self._pending)

    def note_committed(self, slots: list[int], *, max_age_s: float = 1.0) -> bool:
        """Read these committed pairs next without listing the folder; whether it was taken.

        For a reader told of each commit (inotify: ``controller.frames.spool_watch``): a listing
        costs 0.2-2 ms with the interpreter lock held. Slots already handled are left out unless
        their file was replaced (a new identity). Not taken (``False``: the next ``poll``
        lists) when the last listing is older than ``max_age_s``: the listing forgets
        pruned pairs and finds what no event named.
        """
        if time.monotonic() - self._listed_at > max_age_s:
            return False
        with self._lock:
            pending = set(self._pending)
            for slot in slots:
                if slot in self._done:
                    ident = self._done[slot]
                    if ident is None or self._identity(slot) in (ident, None):
                        continue
                    del self._done[slot]  # replaced: a new pair there
                pending.add(slot)
            self._pending = sorted(pending)
        return True

    def take_skips(self) -> list[Skip]:
        """The skips reported since the last call (thread-safe), oldest first."""
        out = []
        while True:
            try:
                out.append(self._skips.popleft())
            except IndexError:
                return out

    # -- reading ------------------------------------------------------------------------------

    def poll(self) -> Frame | None:
        """The next frame, or ``None`` when there is none yet (never blocks on a file)."""
        while True:
            if not self._pending:
                self._scan()
                if not self._pending:
                    return None
            slot = self._pending.pop(0)
            with self._lock:
                if slot in self._done:
                    continue
            self.serial += 1
            self.current = (slot, None)
            with self._lock:
                self._done[slot] = None  # handled, even if reading it raises (a bug): no loop
            got, ident = self._read_pair(slot)  # on an error ``current`` names the pair
            self.current = None
            with self._lock:
                self._done[slot] = ident
            if isinstance(got, Frame):
                self.read += 1
                return got
            if got is not None:
                self._skip(got)

    def _read_pair(self, slot: int) -> tuple[Frame | Skip | None, tuple[int, int] | None]:
        meta_name = f"{_PREFIX}{slot:012d}{_META_SUFFIX}"
        try:
            data, st = read_spool_file(self.directory, meta_name,
                                       max_bytes=self.limits.max_meta_bytes)
        except FileNotFoundError:
            return Skip(meta_name, "vanished (pruned) before it was read", slot), None
        except SpoolFileError as exc:
            return Skip(meta_name, str(exc), slot), None
        ident = (st.st_ino, st.st_mtime_ns)
        try:
            meta = decode_metadata(data, slot=slot)
        except MetadataRefused as exc:
            return Skip(meta_name, str(exc), slot), ident
        fields = dict(meta.fields)
        if not meta.seq_ok:  # keep the sequence: no false gap for the service to report
            fields["seq"] = 0 if self._last_seq is None else self._last_seq + 1
        frame = Frame(image_a=None, image_b=None, **fields)  # type: ignore[arg-type]
        self.current = (slot, frame)
        self._note_gap(slot, fields["seq"] if meta.seq_ok else None, meta_name)
        self._last_seq = fields["seq"]
        if meta.problems:
            return dataclasses.replace(
                frame, error=f"invalid metadata in {meta_name}: " + "; ".join(meta.problems)
            ), ident
        if meta.images[0] is None:
            return frame, ident  # a run without rendering: metadata only
        images = []
        for key, name in zip(("image_a", "image_b"), meta.images, strict=True):
            try:
                img_data, _ = read_spool_file(self.directory, name,
                                              max_bytes=self.limits.max_image_bytes)
                images.append(decode_spool_image(img_data, name, limits=self.limits))
            except FileNotFoundError:
                return dataclasses.replace(frame, error=f"unreadable image: {key} {name}: "
                                           "missing"), ident
            except SpoolFileError as exc:
                return dataclasses.replace(frame, error=f"unreadable image: {key} {name}: "
                                           f"{exc}"), ident
        a, b = images
        if a.shape != b.shape or a.dtype != b.dtype:
            return dataclasses.replace(
                frame, error=f"unreadable image: image_a is {a.shape[1]}x{a.shape[0]} "
                f"{a.dtype}, image_b {b.shape[1]}x{b.shape[0]} {b.dtype}"), ident
        return dataclasses.replace(frame, image_a=a, image_b=b), ident

    def _note_gap(self, slot: int, seq: int | None, name: str) -> None:
        """Count pairs between the last valid one and this one that never reached the reader.

        Only when the slot numbers and the ``seq`` agree (one writer, one pair per slot): a
        stray file or a restarted writer makes no false gap.
        """
        last, self._last = self._last, (None if seq is None else (slot, seq))
        if last is None or seq is None:
            return
        n = slot - last[0] - 1
        if n > 0 and seq - last[1] - 1 == n:
            with self._lock:
                handled = sum(1 for s in range(last[0] + 1, slot) if s in self._done) \
                    if n <= 10_000 else 0
            n -= handled
            if n > 0:
                self.missed += n
                first = f"{_PREFIX}{last[0] + 1:012d}{_META_SUFFIX}"
                self._skips.append(Skip(f"{first}..{_PREFIX}{slot - 1:012d}{_META_SUFFIX}",
                                        "pruned or removed before it was read", last[0] + 1, n))

    def successor(self, *, skip_slot: int | None) -> SpoolReader:
        """A reader that continues where this one is, with ``skip_slot`` handled.

        For the threaded source: it abandons a pair that takes too long (this reader stays
        busy with it in its old thread), or a reader thread that died, and reads on with the
        successor.
        """
        new = SpoolReader.__new__(SpoolReader)
        with self._lock:
            new.__dict__.update({k: v for k, v in self.__dict__.items()
                                 if k not in ("_lock", "_done", "_pending", "_skips")})
            new._done = dict(self._done)
        new._lock = threading.Lock()
        if skip_slot is not None:
            new._done[skip_slot] = None
        new._pending = []
        new._skips = self._skips  # one report queue
        new._bad_names = set(self._bad_names)
        new.current = None
        return new
