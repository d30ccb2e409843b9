"""Camera calibration from checkerboard images (seed §4.2): corners, board model, intrinsics.

Pure functions: arrays in, arrays out, no file I/O (``planer calibrate`` reads the images and
writes the rig file).

The camera model is OpenCV's pinhole model with ``dist = (k1, k2, p1, p2, k3)``. The seed's
reduced Brown model (its Eq. 7, radial distortion by one coefficient k1) is ``model="k1"``:
``dist = (k1, 0, 0, 0, 0)``. Unlike the seed, the principal point ``(cx, cy)`` is estimated,
not assumed at the image centre (a webcam's may lie 90 px away from it).

Corner finding: ``cv2.findChessboardCorners`` then ``cv2.cornerSubPix`` with a search window
sized to the board (half-width 0.6 x the smallest corner spacing, at most 11 px: OpenCV's usual
11 px window drifts onto the neighbouring corners when the squares are smaller than about 15 px).
Where the classic detector finds no board (strong blur, noise, low contrast) the sector-based
``cv2.findChessboardCornersSB`` is tried; its corners are already sub-pixel and are kept as they
are. See ``docs/calibration.md`` for the measurements behind these choices.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from core.checks import check_image, check_int, check_positive
from core.errors import MeasurementError

MODELS = ("k1", "full")
"""Distortion models: ``"k1"`` (seed Eq. 7, k1 only) and ``"full"`` (all five coefficients)."""

MIN_IMAGES = 3
"""Fewest usable board views that :func:`calibrate` accepts."""

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
_SUBPIX_MAX_HALF_PX = 11
_SUBPIX_MIN_HALF_PX = 2
_SUBPIX_SPACING_FRACTION = 0.6
_CALIB_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
_FLAGS = {
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "full": 0,
}
_PATTERN_RE = re.compile(r"^\s*(\d+)\s*[xX×]\s*(\d+)\s*$")


@dataclass(frozen=True)
class CalibrationResult:
    """Intrinsics estimated from several views of a checkerboard.

    Attributes
    ----------
    fx, fy : float
        Focal lengths, pixels.
    cx, cy : float
        Principal point, pixels (column, row).
    dist : tuple of 5 float
        ``(k1, k2, p1, p2, k3)`` in OpenCV order; model ``"k1"`` gives ``(k1, 0, 0, 0, 0)``.
    rms_px : float
        Root-mean-square reprojection error over all corners of all images, pixels.
    n_images : int
        Number of views used.
    per_image_error_px : tuple of float
        RMS reprojection error of each view, pixels, in the order of the input.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float]
    rms_px: float
    n_images: int
    per_image_error_px: tuple[float, ...]

    @property
    def k1(self) -> float:
        """Second-order radial distortion coefficient (seed Eq. 7)."""
        return self.dist[0]

    def camera_matrix(self) -> np.ndarray:
        """The 3x3 camera matrix ``K`` (pixels)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def parse_pattern(text: str) -> tuple[int, int]:
    """Parse a board's inner-corner count written ``"COLSxROWS"`` (e.g. ``"7x7"``, ``"9x6"``).

    Parameters
    ----------
    text : str
        Inner corners per row, ``x``, inner corners per column.

    Returns
    -------
    (cols, rows) : tuple of int
        Both at least 2.

    Raises
    ------
    ValueError
        The text is not of that form; the message names ``--pattern``.
    """
    m = _PATTERN_RE.match(text) if isinstance(text, str) else None
    if m is None:
        raise ValueError(f"--pattern must be COLSxROWS inner corners, e.g. 7x7, got {text!r}")
    cols, rows = int(m.group(1)), int(m.group(2))
    if cols < 2 or rows < 2:
        raise ValueError(f"--pattern needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


def _check_pattern(pattern: Sequence[int]) -> tuple[int, int]:
    try:
        cols, rows = pattern
    except (TypeError, ValueError):
        raise ValueError(f"pattern must be (cols, rows), got {pattern!r}") from None
    cols = check_int("pattern[0] (cols)", cols, lo=2)
    rows = check_int("pattern[1] (rows)", rows, lo=2)
    return cols, rows


def board_points(pattern: Sequence[int], square_mm: float) -> np.ndarray:
    """Inner corners of a flat checkerboard in its own frame.

    Parameters
    ----------
    pattern : (cols, rows)
        Inner corners per row and per column.
    square_mm : float
        Side of one square, millimetres (> 0).

    Returns
    -------
    ndarray, shape (cols * rows, 3), float32
        ``(x, y, 0)`` in millimetres, row by row (x fastest): the order of :func:`find_corners`.
    """
    cols, rows = _check_pattern(pattern)
    square = check_positive("square_mm", square_mm)
    pts = np.zeros((rows * cols, 3), np.float32)
    pts[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square
    return pts


def _to_gray_u8(image: np.ndarray) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        if arr.dtype != np.uint8:
            arr = _scale_u8(arr)
        code = cv2.COLOR_BGR2GRAY if arr.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        arr = cv2.cvtColor(arr, code)
    arr = check_image("image", arr)
    return arr if arr.dtype == np.uint8 else _scale_u8(arr)


def _scale_u8(arr: np.ndarray) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float64)
    lo, hi = float(a.min()), float(a.max())
    if hi <= lo:
        return np.zeros(a.shape, np.uint8)
    return np.round((a - lo) * (255.0 / (hi - lo))).astype(np.uint8)


def _min_spacing_px(corners: np.ndarray, pattern: tuple[int, int]) -> float:
    cols, rows = pattern
    grid = corners.reshape(rows, cols, 2)
    along = np.linalg.norm(np.diff(grid, axis=1), axis=2)
    across = np.linalg.norm(np.diff(grid, axis=0), axis=2)
    return float(min(along.min(), across.min()))


def subpix_half_window_px(corners: np.ndarray, pattern: Sequence[int]) -> int:
    """Half-width of the ``cornerSubPix`` search window for a board seen this large.

    Parameters
    ----------
    corners : ndarray, shape (cols * rows, 2)
        Approximate corners in the order of :func:`board_points`, pixels.
    pattern : (cols, rows)
        Inner corners per row and per column.

    Returns
    -------
    int
        ``floor(0.6 * smallest neighbour spacing)`` clipped to [2, 11] pixels, so that the
        window never reaches the neighbouring corners.
    """
    pat = _check_pattern(pattern)
    spacing = _min_spacing_px(np.asarray(corners, float).reshape(-1, 2), pat)
    half = int(np.floor(_SUBPIX_SPACING_FRACTION * spacing))
    return int(np.clip(half, _SUBPIX_MIN_HALF_PX, _SUBPIX_MAX_HALF_PX))


def find_corners(image: np.ndarray, *, pattern: Sequence[int] = (7, 7)) -> np.ndarray | None:
    """Find a checkerboard's inner corners to sub-pixel accuracy.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        Grayscale or BGR image; any integer or float dtype (scaled to 8 bits when not uint8).
    pattern : (cols, rows)
        Inner corners per row and per column.

    Returns
    -------
    ndarray, shape (cols * rows, 2), float32, or None
        Corner positions ``(column, row)`` in pixels, in the order of :func:`board_points`;
        ``None`` when the whole board is not found.
    """
    cols, rows = _check_pattern(pattern)
    gray = _to_gray_u8(image)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, (cols, rows), None, flags)
    if found and corners is not None and len(corners) == cols * rows:
        half = subpix_half_window_px(corners.reshape(-1, 2), (cols, rows))
        refined = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
        return np.ascontiguousarray(refined.reshape(-1, 2), dtype=np.float32)
    sb_flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    found, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=sb_flags)
    if found and corners is not None and len(corners) == cols * rows:
        return np.ascontiguousarray(corners.reshape(-1, 2), dtype=np.float32)
    return None


def _check_image_size(image_size: Sequence[int]) -> tuple[int, int]:
    try:
        width, height = image_size
    except (TypeError, ValueError):
        raise ValueError(f"image_size must be (width, height), got {image_size!r}") from None
    width = check_int("image_size[0] (width)", width, lo=8)
    height = check_int("image_size[1] (height)", height, lo=2)
    return width, height


def calibrate(
    corner_sets: Sequence[np.ndarray],
    image_size: Sequence[int],
    *,
    pattern: Sequence[int],
    square_mm: float = 1.0,
    model: str = "k1",
) -> CalibrationResult:
    """Estimate the camera's intrinsics from the corners of several board views.

    Parameters
    ----------
    corner_sets : sequence of ndarray, each shape (cols * rows, 2)
        Corners of each view in pixels, as returned by :func:`find_corners`.
    image_size : (width, height)
        Size of the images, pixels.
    pattern : (cols, rows)
        Inner corners per row and per column.
    square_mm : float
        Side of one square, millimetres; the intrinsics do not depend on it.
    model : {"k1", "full"}
        ``"k1"``: radial k1 only, k2 = k3 = p1 = p2 = 0 (seed Eq. 7); ``"full"``: all five.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    ValueError
        A bad argument (named), or fewer than 3 usable views (the message says how many).
    MeasurementError
        OpenCV cannot fit the views (e.g. all taken from one pose) or the fit is not finite.
    """
    cols, rows = _check_pattern(pattern)
    width, height = _check_image_size(image_size)
    if model not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
    obj = board_points((cols, rows), square_mm)
    img_pts = []
    for i, corners in enumerate(corner_sets):
        if corners is None:
            continue
        arr = np.asarray(corners, dtype=np.float32)
        if arr.shape != (cols * rows, 2):
            raise ValueError(
                f"corner_sets[{i}] must have shape ({cols * rows}, 2) for a {cols}x{rows} "
                f"pattern, got {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"corner_sets[{i}] contains NaN or infinite values")
        img_pts.append(arr.reshape(-1, 1, 2))
    if len(img_pts) < MIN_IMAGES:
        raise ValueError(
            f"calibration needs at least {MIN_IMAGES} images with a {cols}x{rows} board, "
            f"got {len(img_pts)} usable"
        )
    obj_pts = [obj.reshape(-1, 1, 3)] * len(img_pts)
    try:
        rms, k_mat, dist, rvecs, tvecs = cv2.calibrateCamera(
            obj_pts,
            img_pts,
            (width, height),
            None,
            None,
            flags=_FLAGS[model],
            criteria=_CALIB_CRITERIA,
        )
    except cv2.error as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "cv2.error"
        raise MeasurementError(f"calibration failed: {msg}") from None
    dist5 = np.zeros(5)
    flat = np.asarray(dist, float).ravel()
    dist5[: min(5, flat.size)] = flat[:5]
    fx, fy, cx, cy = (
        float(k_mat[0, 0]),
        float(k_mat[1, 1]),
        float(k_mat[0, 2]),
        float(k_mat[1, 2]),
    )
    values = np.array([fx, fy, cx, cy, rms, *dist5])
    if not np.all(np.isfinite(values)) or fx <= 0 or fy <= 0:
        raise MeasurementError(
            "calibration failed: no finite, positive focal length (are the views all alike?)"
        )
    errors = []
    for pts, rvec, tvec in zip(img_pts, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(obj, rvec, tvec, k_mat, dist)
        errors.append(float(np.sqrt(np.mean(np.sum((proj - pts) ** 2, axis=2)))))
    return CalibrationResult(
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        dist=tuple(float(v) for v in dist5),  # type: ignore[arg-type]
        rms_px=float(rms),
        n_images=len(img_pts),
        per_image_error_px=tuple(errors),
    )
