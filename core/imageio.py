"""Reading images: files for the command line, and header checks done before any decoding.

Every failure is a :class:`~core.errors.MeasurementError` with one line naming the file (or
the problem), so ``planer`` reports it without a traceback. :func:`png_header` and
:func:`npy_header` read an image's size from its first bytes, so a reader can refuse a
decompression bomb (a small file of huge pixel count) before it allocates anything.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import sys
import tokenize
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import MeasurementError

#: Largest image :func:`read_gray` decodes, pixels (a PNG's size is checked before decoding).
READ_MAX_PIXELS = 64 * 2**20


def read_gray(path: str | Path, *, max_pixels: int = READ_MAX_PIXELS) -> np.ndarray:
    """Read an image file as a single-channel array, keeping its bit depth.

    Parameters
    ----------
    path : str or Path
        Image file (PNG, TIFF, BMP, JPEG, ... anything OpenCV reads), 8 or 16 bits.
    max_pixels : int, keyword-only
        Largest width x height accepted; a PNG's header is checked before it is decoded (a
        decompression bomb is refused without allocating it).

    Returns
    -------
    ndarray, shape (height, width)
        ``uint8`` or ``uint16`` (float images as ``float32``); colour images are converted to
        gray with OpenCV's BGR weights.

    Raises
    ------
    MeasurementError
        The file is missing, is a directory, cannot be read or decoded, or is empty.
    """
    import cv2

    p = Path(path)
    if not p.exists():
        raise MeasurementError(f"image not found: {p}")
    if p.is_dir():
        raise MeasurementError(f"image path is a directory, not a file: {p}")
    try:
        data = np.fromfile(p, dtype=np.uint8)
    except OSError as exc:
        raise MeasurementError(f"cannot read image {p}: {exc.strerror or exc}") from None
    if data.size == 0:
        raise MeasurementError(f"image file is empty: {p}")
    if data[:8].tobytes() == PNG_SIGNATURE:
        try:
            head = png_header(data.tobytes())
        except MeasurementError as exc:
            raise MeasurementError(f"{exc}: {p}") from None
        if head.pixels > max_pixels:
            raise MeasurementError(f"image of {head.width}x{head.height} px exceeds the limit "
                                   f"of {max_pixels} pixels: {p}")
    with _quiet_native_stderr():
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise MeasurementError(f"not a readable image (corrupt or unknown format): {p}")
    if img.ndim == 3:
        channels = img.shape[2]
        if channels == 1:
            img = img[:, :, 0]
        elif channels == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif channels == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        else:
            raise MeasurementError(f"unsupported image with {channels} channels: {p}")
    if img.ndim != 2:
        raise MeasurementError(f"unsupported image shape {img.shape}: {p}")
    if img.dtype not in (np.uint8, np.uint16):
        img = img.astype(np.float32)
    return img


@contextlib.contextmanager
def _quiet_native_stderr() -> Iterator[None]:
    """Silence what native decoders (libpng, OpenCV's log) print on a corrupt file.

    The error is reported once, as an exception, by :func:`read_gray`; their own lines on
    file descriptor 2 would break the command line's one-line error contract.
    """
    import cv2

    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable descriptor 2 (embedded interpreters)
        saved = -1
    try:
        if saved >= 0:
            with open(os.devnull, "wb") as null:
                os.dup2(null.fileno(), 2)
        yield
    finally:
        if saved >= 0:
            os.dup2(saved, 2)
            os.close(saved)
        cv2.utils.logging.setLogLevel(level)


# ---------------------------------------------------------------------------------------------
# header checks (pure: bytes in, sizes out)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
_PNG_MAX_DIM = 2**31 - 1  # the PNG specification's limit per dimension
_PNG_BIT_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
PNG_COLOUR_TYPES = {0: "grayscale", 2: "RGB", 3: "palette", 4: "grayscale+alpha", 6: "RGBA"}


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header says, read before decoding.

    Attributes
    ----------
    width, height : int
        Image size, pixels.
    dtype : str
        Sample type after decoding (``"uint8"``, ``"uint16"``; for ``.npy`` the stored one).
    channels : int
        Samples per pixel (1 = grayscale).
    fortran_order : bool
        ``.npy`` only: the samples stored column by column.
    data_offset : int
        ``.npy`` only: where the samples start in the file, bytes.
    """

    width: int
    height: int
    dtype: str
    channels: int = 1
    fortran_order: bool = False
    data_offset: int = 0

    @property
    def pixels(self) -> int:
        """``width * height``."""
        return self.width * self.height


def png_header(data: bytes) -> ImageHeader:
    """Size and sample type of a PNG file from its signature and IHDR chunk (no decoding).

    The IHDR chunk's CRC is checked, and the file must end with the IEND chunk (a truncated
    file is refused here, not by the decoder).

    Parameters
    ----------
    data : bytes
        The whole file.

    Raises
    ------
    MeasurementError
        Empty, not a PNG, a damaged header, an invalid size or bit depth, or truncated.
    """
    if len(data) == 0:
        raise MeasurementError("empty file (0 bytes)")
    if data[:8] != PNG_SIGNATURE:
        raise MeasurementError("not a PNG file (bad signature)")
    if len(data) < 33:
        raise MeasurementError(f"truncated PNG: {len(data)} bytes, shorter than its header")
    length, ctype = struct.unpack(">I4s", data[8:16])
    if ctype != b"IHDR" or length != 13:
        raise MeasurementError("damaged PNG: the first chunk is not a valid IHDR")
    body = data[16:29]
    (crc,) = struct.unpack(">I", data[29:33])
    if zlib.crc32(data[12:29]) != crc:
        raise MeasurementError("damaged PNG: IHDR checksum mismatch")
    width, height, depth, colour, compression, filt, interlace = struct.unpack(">IIBBBBB", body)
    if not (1 <= width <= _PNG_MAX_DIM and 1 <= height <= _PNG_MAX_DIM):
        raise MeasurementError(f"invalid PNG size {width}x{height}")
    if colour not in _PNG_BIT_DEPTHS or depth not in _PNG_BIT_DEPTHS[colour]:
        raise MeasurementError(f"invalid PNG colour type {colour} with bit depth {depth}")
    if compression != 0 or filt != 0 or interlace not in (0, 1):
        raise MeasurementError("invalid PNG header (compression, filter or interlace method)")
    if not data.endswith(_PNG_IEND):
        raise MeasurementError("truncated PNG: no IEND chunk at the end")
    channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}[colour]
    dtype = "uint16" if depth == 16 else "uint8"
    return ImageHeader(width=width, height=height, dtype=dtype, channels=channels)


_NPY_KINDS = "biuf"  # bool, signed, unsigned, float: no objects, strings or structures
#: What numpy's header parser raises on a damaged header (found by
#: tests/protocol/test_fuzz_frames.py).
_NPY_HEADER_ERRORS = (ValueError, SyntaxError, TypeError, KeyError, IndexError, OverflowError,
                      RecursionError, MemoryError, tokenize.TokenError)


_NPY_HEADS: dict[tuple[bytes, int], ImageHeader] = {}
"""Headers already parsed, by header bytes and file size (a camera writes the same one)."""
_NPY_HEADS_MAX = 16


def _npy_header_key(data: bytes) -> tuple[bytes, int] | None:
    """The header's bytes (magic, version, length, dictionary) and the file size, if well-formed."""
    if len(data) < 12 or data[:6] != b"\x93NUMPY" or data[6] not in (1, 2, 3):
        return None
    size = (10 + int.from_bytes(data[8:10], "little") if data[6] == 1
            else 12 + int.from_bytes(data[8:12], "little"))
    return (bytes(data[:size]), len(data)) if size <= 4096 and len(data) >= size else None


def npy_header(data: bytes) -> ImageHeader:
    """Size, sample type and layout of a ``.npy`` file from its header (no array is built).

    The header's parse (``ast.literal_eval``, about 0.1 ms) is remembered per header bytes and
    file size: the result depends on nothing else.

    Raises
    ------
    MeasurementError
        Empty, not a ``.npy`` file, not a 2-D numeric array, or shorter than its header says.
    """
    if len(data) == 0:
        raise MeasurementError("empty file (0 bytes)")
    key = _npy_header_key(data)
    head = _NPY_HEADS.get(key) if key is not None else None
    if head is None:
        head = _parse_npy_header(data)  # raises on a bad header: nothing remembered
        if key is not None:
            if len(_NPY_HEADS) >= _NPY_HEADS_MAX:
                _NPY_HEADS.clear()
            _NPY_HEADS[key] = head
    return head


def _parse_npy_header(data: bytes) -> ImageHeader:
    bio = io.BytesIO(data)
    try:
        major, _minor = np.lib.format.read_magic(bio)
        if major == 1:
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(bio)
        elif major in (2, 3):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(bio)
        else:
            raise ValueError(f"unsupported .npy version {major}")
    except _NPY_HEADER_ERRORS as exc:
        text = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise MeasurementError(f"not a readable .npy file: {text}") from None
    if dtype.hasobject or dtype.kind not in _NPY_KINDS or dtype.fields is not None:
        raise MeasurementError(f".npy array of type {dtype} is not a numeric image")
    if len(shape) != 2 or min(shape) < 1:
        raise MeasurementError(f".npy array of shape {shape} is not a 2-D image")
    offset = bio.tell()
    need = offset + shape[0] * shape[1] * dtype.itemsize
    if len(data) != need:
        raise MeasurementError(f"truncated .npy file: {len(data)} bytes, its header says {need}")
    return ImageHeader(width=int(shape[1]), height=int(shape[0]), dtype=str(dtype),
                       fortran_order=bool(fortran), data_offset=offset)
