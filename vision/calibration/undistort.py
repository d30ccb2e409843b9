"""Lens correction with OpenCV's camera model, full-frame or straight into binned row bands.

The undistorted image uses the same camera matrix ``K`` as the distorted one
(``cv2.initUndistortRectifyMap(K, dist, None, K, ...)``), so undistorted column ``u`` lies
``(u - cx) / px_per_mm`` mm from the optical axis along the feed.

:class:`Undistorter` does all set-up once per camera and image shape: the fixed-point remap
tables for the whole frame and, for the fast measurement path, tables that undistort a
*vertically binned* image.  The cuttermarks run along the image rows' normal (q = 0), and the
measurement averages every column anyway, so adjacent rows may be summed before the remap as
long as the distortion moves a column by less than ``max_smear_px`` over one bin.  This cuts the
remap work (the dominant cost) by the bin factor.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from config.rig import Camera
from core.checks import check_image, check_int, check_positive


def _camera_matrix(camera: Camera) -> np.ndarray:
    return np.array(
        [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]],
        dtype=np.float64,
    )


class Undistorter:
    """Undistort images of one camera and one image shape (tables built once).

    Parameters
    ----------
    camera : config.rig.Camera
        Intrinsics and distortion ``(k1, k2, p1, p2, k3)``.
    shape : tuple of int
        ``(height, width)`` of the images, pixels.
    max_smear_px : float, optional
        Largest horizontal drift of an undistorted column across one vertical bin, pixels;
        sets :attr:`bin_rows`.
    max_bin_rows : int, optional
        Upper bound of the vertical bin factor.

    Attributes
    ----------
    bin_rows : int
        Rows summed per bin in :meth:`binned_rows`.
    row_band : slice
        Binned rows whose samples are all inside the distorted image over :attr:`columns`.
    columns : tuple of int
        ``(c0, c1)``: undistorted columns that see the image on the middle row.
    first_row_px : float
        Undistorted image row at the centre of binned row 0 (binned row ``j`` is centred on
        ``first_row_px + j * bin_rows``).
    bins : int
        Binned rows of :meth:`bin_image` (``height // bin_rows``).
    first_image_row : int
        Image row where the first bin starts.
    """

    def __init__(
        self,
        camera: Camera,
        shape: tuple[int, int],
        *,
        max_smear_px: float = 0.25,
        max_bin_rows: int = 16,
    ) -> None:
        if len(shape) != 2:
            raise ValueError(f"shape must be (height, width), got {shape!r}")
        h = check_int("shape[0] (height)", shape[0], lo=2)
        w = check_int("shape[1] (width)", shape[1], lo=8)
        check_positive("max_smear_px", max_smear_px)
        check_int("max_bin_rows", max_bin_rows, lo=1)
        self.shape = (h, w)
        self.camera = camera
        k = _camera_matrix(camera)
        dist = np.asarray(camera.dist, dtype=np.float64)
        self._identity = not np.any(dist)

        mx, my = cv2.initUndistortRectifyMap(k, dist, None, k, (w, h), cv2.CV_32FC1)
        self._map1, self._map2 = cv2.convertMaps(mx, my, cv2.CV_16SC2)

        # Vertical bin factor from the columns' horizontal drift per row.
        drift = float(np.max(np.abs(np.diff(mx, axis=0)))) if h > 1 else 0.0
        bins = bin_factor_for(drift, max_smear_px=max_smear_px, max_bin_rows=max_bin_rows)
        bins = max(1, min(bins, h // 2))
        self.bin_rows = bins
        self.drift_px_per_row = drift
        hb = h // bins
        self._r0 = (h - hb * bins) // 2
        self._hb = hb
        self.bins = hb
        self.first_image_row = self._r0  # first image row of the bins

        # Tables from the binned output grid (u, j) to binned-source coordinates.
        centre = self._r0 + (bins - 1) / 2.0
        self.first_row_px = float(centre)
        newk = np.array(
            [[camera.fx, 0.0, camera.cx], [0.0, camera.fy / bins, (camera.cy - centre) / bins],
             [0.0, 0.0, 1.0]],
            dtype=np.float64,
        )
        bx, by = cv2.initUndistortRectifyMap(k, dist, None, newk, (w, hb), cv2.CV_32FC1)
        by = ((by - centre) / bins).astype(np.float32)
        inside = (bx >= 0) & (bx <= w - 1) & (by >= 0) & (by <= hb - 1)
        mid = inside[hb // 2]
        cols = np.flatnonzero(mid)
        if cols.size < 8:
            raise ValueError("camera distortion leaves too few valid columns in the image")
        c0, c1 = int(cols[0]), int(cols[-1]) + 1
        rows_ok = np.all(inside[:, c0:c1], axis=1)
        rows = np.flatnonzero(rows_ok)
        if rows.size == 0:
            raise ValueError("camera distortion leaves no fully valid row in the image")
        self.columns = (c0, c1)
        self.row_band = slice(int(rows[0]), int(rows[-1]) + 1)
        # Float maps: with this OpenCV build a remap through float32 tables runs 2-3x faster
        # than through fixed-point (CV_16SC2) ones (measured; docs/performance.md).
        self._bmap_x = np.ascontiguousarray(bx, dtype=np.float32)
        self._bmap_y = np.ascontiguousarray(by, dtype=np.float32)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Undistort a whole image.

        Parameters
        ----------
        image : ndarray, shape (height, width)
            Distorted grayscale image, any OpenCV depth.

        Returns
        -------
        ndarray, shape (height, width)
            Undistorted image, same dtype; samples from outside the frame are 0.
        """
        img = check_image("image", image)
        if img.shape != self.shape:
            raise ValueError(
                f"image has shape {img.shape}, the undistorter was built for {self.shape}"
            )
        if img.dtype == np.float64 or img.dtype == np.int64:
            img = img.astype(np.float32)
        return cv2.remap(img, self._map1, self._map2, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def bin_image(self, image: np.ndarray) -> np.ndarray:
        """Sum groups of :attr:`bin_rows` adjacent rows (no undistortion).

        Parameters
        ----------
        image : ndarray, shape (height, width)
            Distorted grayscale image.

        Returns
        -------
        ndarray, shape (height // bin_rows, width)
            Row sums: ``uint16`` for 8-bit input, ``float32`` otherwise.
        """
        img = np.asarray(image)
        k, hb, r0 = self.bin_rows, self._hb, self._r0
        part = img[r0 : r0 + hb * k]
        if k == 1:
            return part if part.dtype in (np.uint8, np.uint16, np.float32) else part.astype(
                np.float32
            )
        acc = np.uint16 if img.dtype == np.uint8 else np.float32
        return part.reshape(hb, k, part.shape[1]).sum(axis=1, dtype=acc)

    def binned_rows(self, image: np.ndarray) -> np.ndarray:
        """Undistorted image reduced to binned rows (the fast measurement path).

        Row ``j`` of the result holds the sum of :attr:`bin_rows` undistorted rows centred
        on row ``r0 + j * bin_rows + (bin_rows - 1) / 2``.  Only rows in :attr:`row_band` and
        columns in :attr:`columns` are guaranteed to come from inside the frame.

        Parameters
        ----------
        image : ndarray, shape (height, width)
            Distorted grayscale image (``uint8``, ``uint16`` or float).

        Returns
        -------
        ndarray, shape (height // bin_rows, width)
            ``uint16`` (8-bit input) or ``float32`` sums of ``bin_rows`` pixels.
        """
        binned = self.bin_image(image)
        if self._identity:
            return binned
        return cv2.remap(binned, self._bmap_x, self._bmap_y, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)


def bin_factor_for(drift_px_per_row: float, *, max_smear_px: float = 0.25,
                   max_bin_rows: int = 8) -> int:
    """Vertical bin factor that keeps the column drift over one bin below ``max_smear_px``.

    Parameters
    ----------
    drift_px_per_row : float
        Largest horizontal drift of an undistorted column per image row, pixels.
    max_smear_px, max_bin_rows : float, int
        Limits as in :class:`Undistorter`.

    Returns
    -------
    int
        Bin factor, ``1 <= k <= max_bin_rows``.
    """
    if drift_px_per_row <= 0:
        return max_bin_rows
    return max(1, min(max_bin_rows, math.floor(max_smear_px / drift_px_per_row)))
