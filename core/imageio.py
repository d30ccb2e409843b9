"""Reading images for the command line (the only image file I/O of the measurement path).

Every failure is a :class:`~core.errors.MeasurementError` with one line naming the file, so
``planer`` reports it without a traceback.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from core.errors import MeasurementError


def read_gray(path: str | Path) -> np.ndarray:
    """Read an image file as a single-channel array, keeping its bit depth.

    Parameters
    ----------
    path : str or Path
        Image file (PNG, TIFF, BMP, JPEG, ... anything OpenCV reads), 8 or 16 bits.

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
