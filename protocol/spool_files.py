"""The spool's files: names, a pair's metadata, safe reads, checked decoding (docs/frames.md).

A pair ``n`` is ``pair-<n>.a.png`` / ``.b.png`` (or ``.npy``) and ``pair-<n>.json``, the
metadata file being the commit marker. Here: the names, the metadata as written
(:func:`frame_metadata`) and as checked field by field (:func:`decode_metadata`), reading a
file without following links or blocking (:func:`read_spool_file`) and an image's header
checked against the :class:`SpoolLimits` before it is decoded (:func:`decode_spool_image`).
:mod:`protocol.spool` writes and reads the folder with them.
"""

from __future__ import annotations

import errno
import io
import json
import math
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from core.errors import PlanerError

if TYPE_CHECKING:
    from protocol.frames import Frame

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
