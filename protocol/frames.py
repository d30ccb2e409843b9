"""Frames handed from the camera to the service: one encoder-registered image pair.

The hand-off between processes (a spool directory of atomically written pairs) is added here
beside the dataclass; see ``docs/frames.md``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import os
import threading
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.fileio import atomic_write_bytes


@dataclass(frozen=True)
class Frame:
    """One image pair as the camera hands it over.

    Attributes
    ----------
    seq : int
        Sequence number of the pair (matches the PLC's ``trigger_seq``, modulo 2**16).
    t_s : float
        Machine time at trigger A, seconds.
    image_a, image_b : ndarray, shape (H, W)
        Grayscale images lit by light A (azimuth 0 deg) and light B, B taken after A.
    counts_a, counts_b : int
        Feed encoder counts latched at the two triggers (wrapped counter values).
    speed_mm_s : float
        Feed speed at capture, mm/s (for motion deblurring).
    index_latch_counts : int
        Encoder counts at the spindle index pulse belonging to the imaged board patch
        (see ``docs/architecture.md``, mark-to-knife phase).
    board_id : int
        Board under the camera (0 when none).
    board_position_mm : float
        Position of image A's centre from the board's leading end, mm.
    truth : dict or None
        Simulator only: the true ``pitch_mm``, ``uniformity_cv``, ``mark_widths_mm``,
        ``depth_um``, ``shift_px`` of the imaged patch. ``None`` on a real machine.
    error : str or None
        Why the pair cannot be measured although its metadata arrived (an image file that is
        missing or unreadable); the images are then ``None``. The service logs such a pair as a
        failed measurement instead of losing it.
    """

    seq: int
    t_s: float
    image_a: np.ndarray
    image_b: np.ndarray
    counts_a: int
    counts_b: int
    speed_mm_s: float
    index_latch_counts: int = 0
    board_id: int = 0
    board_position_mm: float = 0.0
    truth: dict[str, Any] | None = field(default=None)
    error: str | None = None


# ---------------------------------------------------------------------------------------------
# Hand-off between processes: a spool directory of atomically written pairs (docs/frames.md)
# ---------------------------------------------------------------------------------------------

SPOOL_VERSION = 1
_PREFIX = "pair-"
_META_SUFFIX = ".json"
_TMP_PREFIX = ".tmp-"


def _jsonable(value: Any) -> Any:
    """``value`` with numpy arrays and scalars turned into lists and Python numbers."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def frame_metadata(frame: Frame) -> dict[str, Any]:
    """The JSON-ready metadata of a frame (everything but the images)."""
    return {
        "seq": int(frame.seq),
        "t_s": float(frame.t_s),
        "counts_a": int(frame.counts_a),
        "counts_b": int(frame.counts_b),
        "speed_mm_s": float(frame.speed_mm_s),
        "index_latch_counts": int(frame.index_latch_counts),
        "board_id": int(frame.board_id),
        "board_position_mm": float(frame.board_position_mm),
        "truth": _jsonable(frame.truth) if frame.truth is not None else None,
    }


def _encode_image(name: str, image: np.ndarray) -> tuple[str, bytes]:
    """Lossless file bytes of an image: PNG for uint8/uint16, ``.npy`` otherwise."""
    import cv2

    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grayscale image, got shape {img.shape}")
    if img.dtype in (np.uint8, np.uint16):
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:  # pragma: no cover - cv2 failure
            raise ValueError(f"{name}: PNG encoding failed")
        return ".png", buf.tobytes()
    bio = io.BytesIO()
    np.save(bio, img, allow_pickle=False)
    return ".npy", bio.getvalue()


def _decode_image(path: Path) -> np.ndarray:
    import cv2

    data = path.read_bytes()
    if path.suffix == ".npy":
        return np.load(io.BytesIO(data), allow_pickle=False)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path.name}: not a readable PNG")
    return img


def _slot_of(name: str) -> int | None:
    """Slot number of a committed metadata file name ``pair-000000000042.json``."""
    if not (name.startswith(_PREFIX) and name.endswith(_META_SUFFIX)):
        return None
    digits = name[len(_PREFIX) : -len(_META_SUFFIX)]
    return int(digits) if digits.isdigit() else None


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
    """

    def __init__(self, directory: str | Path, *, keep: int = 100, fsync: bool = True) -> None:
        if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
            raise ValueError(f"keep must be an integer >= 1, got {keep!r}")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.keep = keep
        self.fsync = fsync
        for name in os.listdir(self.directory):  # leftovers of a killed writer
            if name.startswith(_TMP_PREFIX):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self.directory / name)
        slots = _committed_slots(self.directory)
        self._slots: list[int] = slots
        self.next_slot = (slots[-1] + 1) if slots else 0
        self.written = 0

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
            suffix, data = _encode_image(key, img)
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
    """Returns the complete pairs a :class:`SpoolWriter` commits, in order, one per ``poll``.

    Only committed metadata files are read; temporary (dot) files are ignored. A pair pruned
    while it was being read is skipped. A writer restarted on the same directory continues the
    slot numbers; a writer restarted on an emptied directory (slots lower than the last read)
    is detected and followed from its first pair.

    Parameters
    ----------
    directory : str or Path
        The spool directory (need not exist yet).
    start : {"new", "all"}
        ``"new"`` skips pairs already committed when the reader is made (a live camera);
        ``"all"`` returns them too.

    Attributes
    ----------
    read, skipped : int
        Pairs returned, and pairs that vanished or were unreadable.
    """

    def __init__(self, directory: str | Path, *, start: str = "new") -> None:
        if start not in ("new", "all"):
            raise ValueError(f"start must be 'new' or 'all', got {start!r}")
        self.directory = Path(directory)
        slots = _committed_slots(self.directory)
        self.last_slot = slots[-1] if (slots and start == "new") else -1
        self._pending: list[int] = []
        self.read = 0
        self.skipped = 0

    def _scan(self) -> None:
        slots = _committed_slots(self.directory)
        new = [s for s in slots if s > self.last_slot]
        if not new and slots and slots[-1] < self.last_slot:
            # a new writer restarted the numbering in an emptied directory
            self.last_slot = -1
            new = slots
        self._pending = new

    def poll(self) -> Frame | None:
        """The next complete frame, or ``None`` when there is none yet (never blocks)."""
        while True:
            if not self._pending:
                self._scan()
                if not self._pending:
                    return None
            slot = self._pending.pop(0)
            self.last_slot = max(self.last_slot, slot)
            frame = self._load(slot)
            if frame is not None:
                self.read += 1
                return frame
            self.skipped += 1

    def _load(self, slot: int) -> Frame | None:
        """The pair of ``slot``; ``None`` when its metadata is gone or unusable.

        A pair whose metadata is fine but whose image cannot be read comes back with
        ``error`` set and no images, so that the service can log it as a failed measurement.
        """
        meta_path = self.directory / f"{_PREFIX}{slot:012d}{_META_SUFFIX}"
        try:
            meta = json.loads(meta_path.read_bytes())
            frame = Frame(
                seq=int(meta["seq"]),
                t_s=float(meta["t_s"]),
                image_a=None,  # type: ignore[arg-type]
                image_b=None,  # type: ignore[arg-type]
                counts_a=int(meta["counts_a"]),
                counts_b=int(meta["counts_b"]),
                speed_mm_s=float(meta["speed_mm_s"]),
                index_latch_counts=int(meta.get("index_latch_counts", 0)),
                board_id=int(meta.get("board_id", 0)),
                board_position_mm=float(meta.get("board_position_mm", 0.0)),
                truth=meta.get("truth"),
            )
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return None  # vanished (pruned) or not a pair's metadata: counted as skipped
        try:
            images = [
                None if meta.get(k) is None else _decode_image(self.directory / str(meta[k]))
                for k in ("image_a", "image_b")
            ]
        except (OSError, ValueError) as exc:
            return dataclasses.replace(frame, error=f"unreadable image: {exc}")
        return dataclasses.replace(frame, image_a=images[0], image_b=images[1])


class InProcessSource:
    """A frame source fed directly in the same process (fast tests, ``planer hil`` in-process).

    Thread-safe. When full, the oldest frame is dropped (a camera overwrites its buffer).

    Parameters
    ----------
    maxlen : int
        Frames buffered at most.

    Attributes
    ----------
    dropped : int
        Frames lost because the buffer was full.
    """

    def __init__(self, maxlen: int = 64) -> None:
        if isinstance(maxlen, bool) or not isinstance(maxlen, int) or maxlen < 1:
            raise ValueError(f"maxlen must be an integer >= 1, got {maxlen!r}")
        self._q: deque[Frame] = deque(maxlen=maxlen)
        self._lock = threading.Lock()
        self.dropped = 0

    def put(self, frame: Frame) -> None:
        """Hand a frame over."""
        with self._lock:
            if len(self._q) == self._q.maxlen:
                self.dropped += 1
            self._q.append(frame)

    write = put  # the same call as SpoolWriter.write, so the runner takes either sink

    def poll(self) -> Frame | None:
        """The oldest buffered frame, or ``None`` (never blocks)."""
        with self._lock:
            return self._q.popleft() if self._q else None

    def __len__(self) -> int:
        return len(self._q)
