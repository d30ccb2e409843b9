"""Frames handed from the camera to the service: one encoder-registered image pair.

The hand-off between processes (a spool directory of atomically written pairs) is added here
beside the dataclass; see ``docs/frames.md``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import io
import json
import math
import os
import re
import stat
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import PlanerError
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
_META_NAME = re.compile(r"pair-([0-9]{1,18})\.json")


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


def _png_params() -> list[int]:
    """PNG options of the spool writer: stored (deflate level 0), no row filter.

    The cheapest lossless PNG to write and to read (0.7 + 0.8 ms per 659x493 pair, against
    17.5 + 6.4 ms at level 1 with filters), at 1.7x the bytes; any PNG reader reads it and the
    reader's header checks apply unchanged.
    """
    import cv2

    return [cv2.IMWRITE_PNG_COMPRESSION, 0, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]


def _encode_image(name: str, image: np.ndarray, fmt: str = "png") -> tuple[str, bytes]:
    """Lossless file bytes of an image: PNG for uint8/uint16 (``fmt="png"``), ``.npy`` otherwise."""
    import cv2

    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grayscale image, got shape {img.shape}")
    if fmt == "png" and img.dtype in (np.uint8, np.uint16):
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), _png_params())
        if not ok:  # pragma: no cover - cv2 failure
            raise ValueError(f"{name}: PNG encoding failed")
        return ".png", buf.tobytes()
    bio = io.BytesIO()
    np.save(bio, img, allow_pickle=False)
    return ".npy", bio.getvalue()


def _slot_of(name: str) -> int | None:
    """Slot number of a committed metadata file name ``pair-000000000042.json``."""
    m = _META_NAME.fullmatch(name)
    return int(m.group(1)) if m else None


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


# ---------------------------------------------------------------------------------------------
# Reading the spool: limits, metadata validation, safe file access (docs/frames.md)
# ---------------------------------------------------------------------------------------------

#: An unchanged, quiet spool folder is listed again after this long anyway, seconds.
RESCAN_S = 0.1
#: Largest ``seq`` (the quality log's 64-bit integers).
SEQ_MAX = 2**63 - 1
#: Largest ``board_id`` and magnitude of an encoder count (32-bit PLC registers).
U32_MAX = 2**32 - 1
#: Largest magnitude of ``speed_mm_s`` accepted, mm/s (100 m/s: no feed is that fast).
SPEED_MAX_MM_S = 1e5
#: Largest magnitude of ``t_s`` and ``board_position_mm`` accepted.
FLOAT_MAX = 1e12



class SpoolFileError(PlanerError, ValueError):
    """A spool file the reader refuses (not a regular file, too large, not decodable)."""


class MetadataRefused(SpoolFileError):
    """A metadata file that is not a pair's metadata at all (skipped, with the reason)."""


@dataclass(frozen=True)
class SpoolLimits:
    """What the spool reader accepts, checked before anything is decoded.

    Attributes
    ----------
    max_meta_bytes : int
        Largest metadata file, bytes.
    max_image_bytes : int
        Largest image file, bytes.
    max_pixels : int
        Largest ``width * height`` of an image, from its header (refuses decompression bombs).
    image_shape : tuple of int or None
        ``(height, width)`` every image must have (the rig's camera); ``None``: any size within
        ``max_pixels``, but A and B alike.
    pair_timeout_s : float
        Longest time reading and decoding one pair may take, seconds (the threaded source
        gives up on a pair that takes longer and delivers it as failed).
    """

    max_meta_bytes: int = 1 << 20
    max_image_bytes: int = 64 << 20
    max_pixels: int = 4096 * 4096
    image_shape: tuple[int, int] | None = None
    pair_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        for name in ("max_meta_bytes", "max_image_bytes", "max_pixels"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if self.image_shape is not None:
            shape = tuple(self.image_shape)
            if (len(shape) != 2 or any(isinstance(d, bool) or not isinstance(d, int) or d < 1
                                       for d in shape)):
                raise ValueError(f"image_shape must be (height, width) >= 1, got {shape!r}")
            if shape[0] * shape[1] > self.max_pixels:
                raise ValueError(f"image_shape {shape} exceeds max_pixels {self.max_pixels}")
            object.__setattr__(self, "image_shape", shape)
        t = self.pair_timeout_s
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (0 < t < math.inf):
            raise ValueError(f"pair_timeout_s must be a positive number, got {t!r}")


@dataclass(frozen=True)
class Skip:
    """A spool file that gave no frame, or pairs that never reached the reader.

    Attributes
    ----------
    file : str
        The file's name in the spool folder (for a gap: ``first..last`` of the missing names).
    reason : str
        Why, in one line (``not JSON: ...``, ``vanished before it was read``, ...).
    slot : int or None
        The slot of the pair (the first one of a gap).
    pairs : int
        Pairs it stands for: 1, or the length of a gap.
    """

    file: str
    reason: str
    slot: int | None = None
    pairs: int = 1

    def __str__(self) -> str:
        n = "" if self.pairs == 1 else f" ({self.pairs} pairs)"
        return f"{self.file}: {self.reason}{n}"


@dataclass(frozen=True)
class PairMetadata:
    """A pair's metadata, checked field by field (:func:`decode_metadata`).

    Attributes
    ----------
    fields : dict
        ``Frame`` keyword values; a field with a problem holds its default (0).
    images : tuple of (str or None)
        File names of image A and B (``None``: no image).
    problems : tuple of str
        One text per invalid field, naming it (``board_id 10**20 is out of range 0..``).
    seq_ok : bool
        Whether ``seq`` itself is valid (else ``fields["seq"]`` is 0).
    """

    fields: dict[str, Any]
    images: tuple[str | None, str | None]
    problems: tuple[str, ...]
    seq_ok: bool


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _int_field(name: str, v: Any, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{name} must be an integer, got {_short(v)}")
    lo = -hi if name in _SIGNED else 0
    if not lo <= v <= hi:
        raise ValueError(f"{name} {_short(v)} is out of range {lo}..{hi}")
    return v


#: Encoder counts: 32-bit counters, wrapped (unsigned) or as differences (signed).
_SIGNED = ("counts_a", "counts_b", "index_latch_counts")


def _float_field(name: str, v: Any, hi: float) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{name} must be a number, got {_short(v)}")
    try:
        f = float(v)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f) or abs(f) > hi:
        raise ValueError(f"{name} {_short(v)} is out of range -{hi:g}..{hi:g}")
    return f


#: name -> (checker, upper bound, default or None when required)
_FIELDS: dict[str, tuple[Any, Any, Any]] = {
    "seq": (_int_field, SEQ_MAX, None),
    "t_s": (_float_field, FLOAT_MAX, None),
    "counts_a": (_int_field, U32_MAX, None),
    "counts_b": (_int_field, U32_MAX, None),
    "speed_mm_s": (_float_field, SPEED_MAX_MM_S, None),
    "index_latch_counts": (_int_field, U32_MAX, 0),
    "board_id": (_int_field, U32_MAX, 0),
    "board_position_mm": (_float_field, FLOAT_MAX, 0.0),
}


def decode_metadata(data: bytes, *, slot: int) -> PairMetadata:
    """Check a pair's metadata file field by field.

    Parameters
    ----------
    data : bytes
        The metadata file's content.
    slot : int
        The slot its name says (``pair-<slot>.json``); a ``slot`` key must agree.

    Returns
    -------
    PairMetadata
        Valid fields, image names and one problem text per invalid field: such a pair is
        delivered as a failed frame naming the fields.

    Raises
    ------
    MetadataRefused
        Not a pair's metadata at all (empty, not UTF-8 JSON, not an object, no integer
        ``seq``, another slot): the file is skipped and reported.
    """
    if not data:
        raise MetadataRefused("empty file (0 bytes)")
    try:
        obj = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        text = " ".join(str(exc).split())[:120] or type(exc).__name__
        raise MetadataRefused(f"not JSON: {text}") from None
    if not isinstance(obj, dict):
        raise MetadataRefused(f"not a JSON object but {type(obj).__name__}")
    if "seq" not in obj:
        raise MetadataRefused("no 'seq': not a pair's metadata")
    seq = obj["seq"]
    if isinstance(seq, bool) or not isinstance(seq, int):
        raise MetadataRefused(f"seq must be an integer, got {_short(seq)}")
    if "slot" in obj and (isinstance(obj["slot"], bool) or obj["slot"] != slot):
        raise MetadataRefused(f"its slot {_short(obj['slot'])} differs from its name's {slot}")
    problems: list[str] = []
    version = obj.get("version", SPOOL_VERSION)
    if isinstance(version, bool) or version != SPOOL_VERSION:
        problems.append(f"version {_short(version)} is not supported (this reader: "
                        f"{SPOOL_VERSION})")
    fields: dict[str, Any] = {}
    seq_ok = True
    for name, (check, hi, default) in _FIELDS.items():
        if name not in obj:
            if default is None:
                problems.append(f"{name} missing")
                fields[name] = 0 if check is _int_field else 0.0
            else:
                fields[name] = default
            continue
        try:
            fields[name] = check(name, obj[name], hi)
        except ValueError as exc:
            problems.append(str(exc))
            fields[name] = 0 if check is _int_field else 0.0
            seq_ok = seq_ok and name != "seq"
    truth = obj.get("truth")
    if truth is not None and not isinstance(truth, dict):
        problems.append(f"truth must be an object or null, got {type(truth).__name__}")
        truth = None
    fields["truth"] = truth
    stem = f"{_PREFIX}{slot:012d}."
    names: list[str | None] = []
    for key in ("image_a", "image_b"):
        v = obj.get(key)
        if v is not None and not (isinstance(v, str) and v.startswith(stem)
                                  and v.endswith((".png", ".npy")) and "/" not in v
                                  and "\0" not in v and ".." not in v):
            problems.append(f"{key} {_short(v)} is not a file of this pair "
                            f"({stem}a.png/.npy in the spool folder)")
            v = None
        names.append(v)
    if (names[0] is None) != (names[1] is None) and not problems:
        problems.append("one image named, the other missing")
    return PairMetadata(fields=fields, images=(names[0], names[1]), problems=tuple(problems),
                        seq_ok=seq_ok)


_OPEN_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)


def _file_kind(mode: int) -> str:
    for test, kind in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISDIR, "a directory"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symbolic link")):
        if test(mode):
            return kind
    return "not a regular file"


def read_spool_file(directory: Path, name: str, *, max_bytes: int) -> tuple[bytes, os.stat_result]:
    """The bytes of a regular file ``name`` directly inside ``directory`` (never blocks).

    Opened with ``O_NOFOLLOW | O_NONBLOCK``: a symbolic link, FIFO, device, socket or
    directory is refused without reading; so is a name with a path separator or ``..``.

    Returns
    -------
    data : bytes
    st : os.stat_result
        ``fstat`` of the opened file (its identity: ``st_ino``, ``st_mtime_ns``).

    Raises
    ------
    FileNotFoundError
        The file vanished (pruned).
    SpoolFileError
        Any other refusal, with the reason.
    """
    if not name or "/" in name or "\0" in name or name in (".", "..") or ".." in name:
        raise SpoolFileError(f"not a plain file name: {_short(name)}")
    try:
        fd = os.open(os.path.join(directory, name), _OPEN_FLAGS)
    except FileNotFoundError:
        raise
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise SpoolFileError("a symbolic link (refused)") from None
        if exc.errno == errno.ENXIO:
            raise SpoolFileError("a socket or device (refused)") from None
        raise SpoolFileError(f"cannot open: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise SpoolFileError(f"{_file_kind(st.st_mode)}, not a regular file (refused)")
        if st.st_size > max_bytes:
            raise SpoolFileError(f"too large: {st.st_size} bytes (limit {max_bytes})")
        chunks, total = [], 0
        while total <= max_bytes:
            try:
                chunk = os.read(fd, min(1 << 20, max_bytes + 1 - total))
            except BlockingIOError:
                raise SpoolFileError("would block (refused)") from None
            except OSError as exc:
                raise SpoolFileError(f"read error: {exc.strerror or exc}") from None
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
        if total > max_bytes:
            raise SpoolFileError(f"too large: grew beyond {max_bytes} bytes while read")
        return b"".join(chunks), st
    finally:
        os.close(fd)


def _c_order_npy(data: bytes, head: Any) -> np.ndarray | None:
    """A C-ordered ``.npy`` image straight from its bytes, or ``None`` (``np.load`` reads it).

    ``head`` is ``npy_header``'s (it checked the header and the size): no second parse.
    """
    if head.fortran_order:
        return None
    flat = np.frombuffer(data, dtype=np.dtype(head.dtype), count=head.pixels,
                         offset=head.data_offset)
    return flat.reshape(head.height, head.width).copy()  # writable, its own memory


def decode_spool_image(data: bytes, name: str, *, limits: SpoolLimits) -> np.ndarray:
    """Check an image's header against ``limits``, then decode it (PNG or ``.npy``).

    Raises
    ------
    SpoolFileError
        Empty, truncated, damaged, too many pixels, not grayscale, or another size than
        ``limits.image_shape``; the message says which.
    """
    from core.errors import MeasurementError
    from core.imageio import npy_header, png_header

    is_npy = name.endswith(".npy")
    try:
        head = npy_header(data) if is_npy else png_header(data)
    except MeasurementError as exc:
        raise SpoolFileError(str(exc)) from None
    if head.pixels > limits.max_pixels:
        raise SpoolFileError(f"{head.width}x{head.height} px exceeds the limit of "
                             f"{limits.max_pixels} pixels (not decoded)")
    if head.channels != 1:
        raise SpoolFileError(f"{head.channels} channels, expected a grayscale image")
    if limits.image_shape is not None and (head.height, head.width) != limits.image_shape:
        h, w = limits.image_shape
        raise SpoolFileError(f"{head.width}x{head.height} px, the camera's images are {w}x{h}")
    if is_npy:
        try:  # a C-ordered array straight from its bytes (the header was checked), else np.load
            img = _c_order_npy(data, head)
            if img is None:
                img = np.load(io.BytesIO(data), allow_pickle=False)
        except (ValueError, OSError, EOFError, TypeError, MemoryError) as exc:
            raise SpoolFileError(f"not a readable .npy file: {type(exc).__name__}") from None
    else:
        import cv2

        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SpoolFileError("damaged PNG (the decoder refused it)")
    if img.shape != (head.height, head.width):
        raise SpoolFileError(f"decoded shape {img.shape} differs from its header")
    return img


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
        try:  # a str path: no Path object per handled file and scan (issue 11, latency)
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

        For a reader told of each commit (inotify: ``controller.spool_watch``): a listing
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
