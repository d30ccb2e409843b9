"""A 2-D surface map of one registered pair: the slope along the feed and the albedo.

The two lights lie along the feed (azimuths 0 and 180 deg), so the pair observes the surface's
slope *along the feed* only: ``p = dz/dx`` comes from the ratio ``I_B / I_A`` by seed Eq. 4
(:func:`vision.slope.slope_from_ratio`) at every pixel once B is registered onto A.  The slope
*across* the feed, ``q = dz/dy``, enters both images alike (through ``1 / sqrt(1 + p^2 + q^2)``)
and cancels in the ratio: it is not observed, and a ridge running exactly along the feed shows
only in the albedo.  The albedo is the mean of the two registered images over their common
shading ``cos(sigma)``, relative to its mean over the field (1 = typical wood).

:class:`SurfaceMapper` does the set-up once per camera, lights and image shape: one remap table
per roll (cached) from row-binned *distorted* images to a grid turned to the feed -- columns
along the feed every ``bin_cols`` px, rows across it every ``bin_rows * merge_rows`` image rows
-- undistorted at once.  The source rows are first averaged over ``merge_rows`` rows and
``bin_cols`` columns (``cv2.resize``'s area integers; for ``uint16`` row bins
:func:`vision.defects.map_kernels.column_means_u16`, the same integers faster), so the remap and
every step after it run on the coarse grid.  On that grid the board's motion between the
shots is a shift along the columns alone, so B is registered with the measurement's shift
(``Measurement.shift_px``, px along the feed) by a linear
interpolation along the rows, in one compiled pass with the ratio and the
albedo (:func:`vision.defects.map_kernels.register_ratio`; the albedo only where asked for: the
detectors do not read it).  With ``bin_rows = 1`` and
``bin_cols = 1`` the map has the camera's full resolution; the
:class:`vision.pipeline.Measurer`'s :class:`vision.defects.detect.DefectFinder` builds it from
the row bins the Measurer has already summed, on ~0.16 x 0.4 mm samples, so the map costs one small
remap per image and no further pass over the images.

Map coordinates: column ``j`` lies ``col0_px + j * col_step_px - cx`` px from the optical axis
along the feed,
row ``i`` ``row0_px + i * row_step_px - cy`` px across it; :meth:`SurfaceMap.image_xy_mm` turns
them into A's undistorted image frame (mm from its top-left corner, x = columns).
"""

from __future__ import annotations

import functools
import math
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from config.rig import Camera, Lights
from core.checks import check_finite, check_int
from vision.defects import map_kernels

_U16 = np.dtype(np.uint16)

_ROLL_KEY_DEG = 0.05
"""Rolls are rounded to this grid for the cached tables (a row moves < 0.3 px over 659 px)."""


@dataclass(frozen=True)
class SurfaceMap:
    """Slope along the feed and albedo of one registered pair, on a grid turned to the feed.

    Attributes
    ----------
    slope_along_feed : ndarray of float32, shape (rows, cols)
        ``dz/dx`` along the feed (dimensionless); the pair's constant imbalance removed
        (a surface tilt along the feed cannot be told from it); 0 where ``valid`` is False.
    albedo : ndarray of float32, shape (rows, cols), or None
        Reflectance relative to the map's mean (1 = typical); 0 where ``valid`` is False;
        ``None`` where the mapper was asked not to make it (``albedo=False``).
    valid : ndarray of bool, shape (rows, cols)
        Both shots see the point, inside the images.
    col0_px : float
        Undistorted image column (along the feed at roll 0) of map column 0.
    row0_px, row_step_px : float
        Undistorted row of map row 0 and the rows' spacing, pixels.
    roll_deg : float
        Direction of the feed in the image the grid was turned to, degrees.
    cx, cy : float
        Principal point (the centre of the turn), pixels.
    px_per_mm : float
        Image scale.
    shadow_slope : float
        The slope Eq. 4 gives where one light is fully shadowed (its bound, ``1 / tan(slant)``
        for equal slants): slopes near it are cast shadows or steeper walls.
    col_step_px : float
        Spacing of the map's columns, pixels along the feed.
    """

    slope_along_feed: np.ndarray
    albedo: np.ndarray | None
    valid: np.ndarray
    col0_px: float
    row0_px: float
    row_step_px: float
    roll_deg: float
    cx: float
    cy: float
    px_per_mm: float
    shadow_slope: float = math.inf
    col_step_px: float = 1.0

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of the map."""
        return self.slope_along_feed.shape  # type: ignore[return-value]

    @functools.cached_property
    def _valid_extent(self) -> tuple[np.ndarray, np.ndarray]:
        """``(valid_rows, valid_cols)``, both found in one compiled pass (once per map).

        The :class:`SurfaceMapper`'s maps come with them (found in the ratio's pass).
        """
        rows, cols = map_kernels.valid_extent(np.ascontiguousarray(self.valid))
        rows.flags.writeable = False
        cols.flags.writeable = False
        return rows, cols

    @property
    def valid_cols(self) -> np.ndarray:
        """Map columns with at least one valid sample (found once per map; read-only)."""
        return self._valid_extent[1]

    @property
    def valid_rows(self) -> np.ndarray:
        """Map rows with at least one valid sample (found once per map; read-only)."""
        return self._valid_extent[0]

    @property
    def cols_per_mm(self) -> float:
        """Map columns per mm along the feed."""
        return self.px_per_mm / self.col_step_px

    def feed_mm(self, cols: np.ndarray | float) -> np.ndarray:
        """Position along the feed of map columns, mm from the optical axis."""
        c = np.asarray(cols, dtype=np.float64)
        return (self.col0_px + c * self.col_step_px - self.cx) / self.px_per_mm

    def across_mm(self, rows: np.ndarray | float) -> np.ndarray:
        """Position across the feed of map rows, mm from the optical axis."""
        r = np.asarray(rows, dtype=np.float64)
        return (self.row0_px + r * self.row_step_px - self.cy) / self.px_per_mm

    def image_xy_mm(self, cols: np.ndarray | float, rows: np.ndarray | float
                    ) -> tuple[np.ndarray, np.ndarray]:
        """A's undistorted image frame of map points: ``(x_mm, y_mm)`` from its top-left corner.

        Parameters
        ----------
        cols, rows : array_like
            Map column and row (fractional allowed).

        Returns
        -------
        tuple of ndarray
            ``x = u / px_per_mm`` (columns, along the feed at roll 0), ``y = v / px_per_mm``.
        """
        xi = self.feed_mm(cols) * self.px_per_mm
        eta = self.across_mm(rows) * self.px_per_mm
        c, s = math.cos(math.radians(self.roll_deg)), math.sin(math.radians(self.roll_deg))
        u = self.cx + xi * c - eta * s
        v = self.cy + xi * s + eta * c
        return u / self.px_per_mm, v / self.px_per_mm

    def heights_um(self) -> np.ndarray:
        """The slope integrated along each row, um (each row's valid mean removed).

        Returns
        -------
        ndarray of float64, shape (rows, cols)
            ``1000 * cumulative integral of p dx`` per row (trapezoid, ``dx`` one column);
            only the along-feed integral is observed, so rows are not tied to each other.
        """
        p = np.where(self.valid, self.slope_along_feed, 0.0).astype(np.float64)
        dx_um = 1000.0 / self.cols_per_mm
        h = np.zeros_like(p)
        h[:, 1:] = np.cumsum(0.5 * (p[:, 1:] + p[:, :-1]), axis=1) * dx_um
        n = np.maximum(self.valid.sum(axis=1, keepdims=True), 1)
        return h - (h * self.valid).sum(axis=1, keepdims=True) / n


@dataclass(frozen=True)
class _Taps:
    """Where each grid point samples the coarse source (:func:`map_kernels.remap_pair`'s table).

    ``x0``, ``y0``: ``floor`` of the remap coordinates (int32); ``ax``, ``ay``: the fractions
    (float32, exact); ``off``: ``y0 * width + x0`` (uint32; 0 on rows not ``inside``);
    ``inside``: the rows whose four taps all lie inside the source.
    """

    off: np.ndarray
    ax: np.ndarray
    ay: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    inside: np.ndarray

    @classmethod
    def of(cls, mx: np.ndarray, my: np.ndarray, width: int, height: int) -> _Taps:
        """The taps of float32 remap coordinates ``mx``, ``my`` on a ``height x width`` source."""
        fx, fy = np.floor(mx), np.floor(my)
        ax, ay = mx - fx, my - fy  # exact in float32: OpenCV's fractions
        with np.errstate(invalid="ignore"):
            x0 = np.clip(fx, -2, width + 1).astype(np.int32)
            y0 = np.clip(fy, -2, height + 1).astype(np.int32)
        ok = (x0 >= 0) & (x0 + 1 <= width - 1) & (y0 >= 0) & (y0 + 1 <= height - 1)
        inside = ok.all(axis=1)
        off = np.where(inside[:, None], y0.astype(np.int64) * width + x0, 0).astype(np.uint32)
        return cls(off, np.ascontiguousarray(ax, dtype=np.float32),
                   np.ascontiguousarray(ay, dtype=np.float32), x0, y0, inside)


class SurfaceMapper:
    """Builds :class:`SurfaceMap` of one camera, lights and image shape (tables set up once).

    Parameters
    ----------
    camera : config.rig.Camera
        Intrinsics, distortion and scale.
    lights : config.rig.Lights
        The two lights' slants and azimuths (seed Eq. 4).
    shape : tuple of int
        ``(height, width)`` of the images, pixels.
    bin_rows : int, optional
        Image rows summed per source row (1: the camera's resolution).
    first_row_px : float, optional
        Image row at the centre of source row 0 (default ``(bin_rows - 1) / 2``).
    columns : tuple of int, optional
        Undistorted columns the map covers (default the whole width).
    source_rows : int, optional
        Source rows per image (default: as many whole bins as fit below ``first_row_px``).
    merge_rows : int, optional
        Source rows averaged into one map row.
    middle_row : bool, optional
        Take only the middle source row of each ``merge_rows`` block (odd ``merge_rows``;
        the map's rows keep their centres and spacing), where the source rows average more
        pixels than the map needs.
    bin_cols : int, optional
        Image columns averaged into one map column.
    cache : int, optional
        Tables kept (one per roll on a 0.05 deg grid).
    """

    def __init__(self, camera: Camera, lights: Lights, shape: tuple[int, int], *,
                 bin_rows: int = 1, first_row_px: float | None = None,
                 columns: tuple[int, int] | None = None, source_rows: int | None = None,
                 merge_rows: int = 1, bin_cols: int = 1, middle_row: bool = False,
                 cache: int = 8) -> None:
        if len(shape) != 2:
            raise ValueError(f"shape must be (height, width), got {shape!r}")
        self.height = check_int("shape[0] (height)", shape[0], lo=2)
        self.width = check_int("shape[1] (width)", shape[1], lo=8)
        self.bin_rows = check_int("bin_rows", bin_rows, lo=1)
        self.merge_rows = check_int("merge_rows", merge_rows, lo=1)
        self.bin_cols = check_int("bin_cols", bin_cols, lo=1, hi=self.width // 8)
        if middle_row and self.merge_rows % 2 == 0:
            raise ValueError(f"middle_row needs an odd merge_rows, got {merge_rows}")
        self.middle_row = bool(middle_row) and self.merge_rows > 1
        self.first_row_px = ((self.bin_rows - 1) / 2.0 if first_row_px is None
                             else check_finite("first_row_px", first_row_px))
        c0, c1 = (0, self.width) if columns is None else (int(columns[0]), int(columns[1]))
        if not 0 <= c0 < c1 <= self.width:
            raise ValueError(f"columns must lie within 0..{self.width}, got {columns!r}")
        self.columns = (c0, c1)
        self.n_src = ((self.height - int(round(self.first_row_px - (self.bin_rows - 1) / 2))
                       ) // self.bin_rows if source_rows is None
                      else check_int("source_rows", source_rows, lo=2))
        # the coarse source: merge_rows x bin_cols blocks of the source rows
        self._n_red = self.n_src // self.merge_rows
        self._w_red = self.width // self.bin_cols
        if self._n_red < 2:
            raise ValueError(f"merge_rows must leave >= 2 rows of {self.n_src}, "
                             f"got {merge_rows}")
        self.camera = camera
        self._k = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy],
                            [0.0, 0.0, 1.0]])
        self._dist = np.asarray(camera.dist, dtype=np.float64)
        self._identity = not np.any(self._dist)
        slant_a, slant_b = lights.slants_deg
        ta, tb = math.tan(math.radians(slant_a)), math.tan(math.radians(slant_b))
        self._ka = math.cos(math.radians(lights.azimuth_a_deg)) * ta
        self._kb = math.cos(math.radians(lights.azimuth_b_deg)) * tb
        if self._ka == self._kb:
            raise ValueError("the lights must stand on opposite sides along the feed")
        # the row bins' usual case: uint16, the middle row of each block or columns alone,
        # one compiled pass (:meth:`_coarse`)
        self._strided = self.middle_row or (self.merge_rows == 1 and self.bin_cols > 1)
        self._u16_pass = self._strided and self.bin_cols <= 32768
        self._cache_size = check_int("cache", cache, lo=1)
        self._tables: OrderedDict[float, tuple[_Taps, np.ndarray]] = OrderedDict()
        map_kernels.warm_up()  # compiled (or loaded from the cache) here, never on a frame

    @property
    def col0_px(self) -> float:
        """Undistorted column of map column 0."""
        return self.columns[0] + (self.bin_cols - 1) / 2.0

    @property
    def row0_px(self) -> float:
        """Undistorted row of map row 0."""
        return self.first_row_px + (self.merge_rows - 1) / 2.0 * self.bin_rows

    def _table(self, roll_deg: float) -> tuple[_Taps, np.ndarray]:
        """Remap taps (x, y in coarse source cells) and validity of the grid turned by roll."""
        key = round(roll_deg / _ROLL_KEY_DEG) * _ROLL_KEY_DEG
        hit = self._tables.get(key)
        if hit is not None:
            self._tables.move_to_end(key)
            return hit
        cam = self.camera
        c0, c1 = self.columns
        sc = float(self.bin_cols)
        width, n_out = (c1 - c0) // self.bin_cols, self._n_red
        step, v0 = float(self.bin_rows * self.merge_rows), self.row0_px
        c, s = math.cos(math.radians(key)), math.sin(math.radians(key))
        cx, cy, fx, fy = cam.cx, cam.cy, cam.fx, cam.fy
        # undistorted pixel of output (p, i): u = cx + xi c - eta s, v = cy + xi s + eta c,
        # xi = col0 + p sc - cx, eta = v0 + i step - cy
        x0 = self.col0_px
        a = np.array([[sc * c, -step * s, cx + (x0 - cx) * c - (v0 - cy) * s],
                      [sc * s, step * c, cy + (x0 - cx) * s + (v0 - cy) * c]])
        if self._identity:
            p, i = np.meshgrid(np.arange(width, dtype=np.float64),
                               np.arange(n_out, dtype=np.float64))
            mx = a[0, 0] * p + a[0, 1] * i + a[0, 2]
            my = a[1, 0] * p + a[1, 1] * i + a[1, 2]
        else:
            m = np.array([[a[0, 0] / fx, a[0, 1] / fx, (a[0, 2] - cx) / fx],
                          [a[1, 0] / fy, a[1, 1] / fy, (a[1, 2] - cy) / fy],
                          [0.0, 0.0, 1.0]])
            mx, my = cv2.initUndistortRectifyMap(self._k, self._dist, None, np.linalg.inv(m),
                                                 (width, n_out), cv2.CV_32FC1)
        # distorted pixel -> coarse source cell (centres of merge_rows x bin_cols blocks)
        src_x = (np.asarray(mx, dtype=np.float64) - (sc - 1) / 2) / sc
        src_y = ((np.asarray(my, dtype=np.float64) - self.first_row_px) / self.bin_rows
                 - (self.merge_rows - 1) / 2) / self.merge_rows
        valid = ((src_x >= 0) & (src_x <= self._w_red - 1) & (src_y >= 0)
                 & (src_y <= self._n_red - 1))
        hit = (_Taps.of(np.ascontiguousarray(src_x, dtype=np.float32),
                        np.ascontiguousarray(src_y, dtype=np.float32),
                        self._w_red, self._n_red), valid)
        self._tables[key] = hit
        if len(self._tables) > self._cache_size:
            self._tables.popitem(last=False)
        return hit

    def coarse_source(self, rows: np.ndarray) -> np.ndarray:
        """The coarse source of one image's source rows (what :meth:`__call__` remaps).

        Made once where several maps of the same pair are made (``coarse`` of
        :meth:`__call__`): float32, shape ``(rows // merge_rows, width // bin_cols)``.
        """
        if np.shape(rows) != (self.n_src, self.width):
            raise ValueError(f"rows must have shape {(self.n_src, self.width)}, "
                             f"got {np.shape(rows)}")
        return np.ascontiguousarray(self._coarse(rows))

    def _coarse(self, rows: np.ndarray) -> np.ndarray:
        """The source rows averaged over ``merge_rows x bin_cols`` blocks, float32."""
        src = r = np.asarray(rows)
        m = self.merge_rows
        if self._u16_pass and src.dtype == _U16 and src.flags.c_contiguous:
            # one compiled pass straight to float32, INTER_AREA's integers (2 columns: ~4x
            # faster than a linear resize at half the width and its float copy; 6: ~4x faster
            # than a loop per block)
            out = np.empty((self._n_red, self._w_red), dtype=np.float32)
            map_kernels.column_means_u16(src, (m - 1) // 2, m, self.bin_cols, out)
            return out
        if r.dtype not in (np.uint8, np.uint16, np.int16, np.float32, np.float64):
            r = r.astype(np.float32)
        if self._strided:
            # the middle source row of each block: a strided view
            r = r[(m - 1) // 2:self._n_red * m:m, :self._w_red * self.bin_cols]
            if self.bin_cols == 2 and r.dtype == np.uint16:
                # pairs of columns: a linear resize at exactly half the width samples between
                # them (weights 1/2, 1/2), the same integers as INTER_AREA's
                r = cv2.resize(r, (self._w_red, self._n_red), interpolation=cv2.INTER_LINEAR)
            elif self.bin_cols > 1:
                r = cv2.resize(r, (self._w_red, self._n_red), interpolation=cv2.INTER_AREA)
        elif self.merge_rows > 1 or self.bin_cols > 1:
            r = cv2.resize(r[:self._n_red * self.merge_rows, :self._w_red * self.bin_cols],
                           (self._w_red, self._n_red), interpolation=cv2.INTER_AREA)
        return r.astype(np.float32, copy=False)

    def _given(self, coarse: np.ndarray, name: str) -> np.ndarray:
        """A coarse source handed in (:meth:`coarse_source`'s), checked: float32, its shape."""
        if (not isinstance(coarse, np.ndarray) or coarse.dtype != np.float32
                or coarse.shape != (self._n_red, self._w_red)):
            raise ValueError(f"{name} must be a float32 array of shape "
                             f"{(self._n_red, self._w_red)}, got "
                             f"{getattr(coarse, 'dtype', type(coarse).__name__)} "
                             f"{np.shape(coarse)}")
        return np.ascontiguousarray(coarse)

    def __call__(self, rows_a: np.ndarray, rows_b: np.ndarray, *, shift_px: float,
                 roll_deg: float = 0.0, albedo: bool = True,
                 coarse: tuple[np.ndarray | None, np.ndarray | None] | None = None
                 ) -> SurfaceMap:
        """The map of one pair from its row-binned images.

        Parameters
        ----------
        rows_a, rows_b : ndarray, shape (n_src, width)
            Sums (or means) of ``bin_rows`` adjacent rows of the distorted images A and B
            (with ``bin_rows = 1`` the images themselves); any real dtype.
        shift_px : float
            Board motion from A to B along the feed, pixels (``Measurement.shift_px``).
        roll_deg : float, optional
            Direction of the feed in the image (``Measurement.roll_deg``), degrees.
        albedo : bool, optional
            Also the albedo (``SurfaceMap.albedo``; the detectors do not read it: the
            :class:`vision.defects.detect.DefectFinder` leaves it out, ``None``).
        coarse : tuple of ndarray or None, optional
            The coarse sources of A and B already made from ``rows_a`` and ``rows_b``
            (:meth:`coarse_source`: made once where several maps of one pair are made);
            either ``None``: made here from its rows.

        Returns
        -------
        SurfaceMap
        """
        d = check_finite("shift_px", shift_px) / self.bin_cols  # map columns
        roll = check_finite("roll_deg", roll_deg)
        for name, r in (("rows_a", rows_a), ("rows_b", rows_b)):
            if np.shape(r) != (self.n_src, self.width):
                raise ValueError(f"{name} must have shape {(self.n_src, self.width)}, "
                                 f"got {np.shape(r)}")
        taps, valid = self._table(roll)
        ca, cb = (None, None) if coarse is None else coarse
        slope = np.empty(valid.shape, dtype=np.float32)
        alb = np.empty_like(slope) if albedo else np.empty((0, 0), dtype=np.float32)
        both = np.empty(valid.shape, dtype=bool)
        # one call: both images at once, cv2.remap's numbers (INTER_LINEAR, BORDER_REPLICATE),
        # then B registered onto A (b_reg[:, j] = b[:, j + d], linear), Eq. 4, the albedo,
        # and the map's valid rows and columns
        extent = map_kernels.map_pair(
            self._given(ca, "coarse[0]") if ca is not None
            else np.ascontiguousarray(self._coarse(rows_a)),
            self._given(cb, "coarse[1]") if cb is not None
            else np.ascontiguousarray(self._coarse(rows_b)), taps.off, taps.ax, taps.ay,
            taps.x0, taps.y0, taps.inside, valid, d, self._ka, self._kb, slope, alb, both)
        smap = SurfaceMap(
            slope_along_feed=slope, albedo=alb if albedo else None, valid=both,
            col0_px=self.col0_px, row0_px=self.row0_px,
            row_step_px=float(self.bin_rows * self.merge_rows),
            roll_deg=float(round(roll / _ROLL_KEY_DEG) * _ROLL_KEY_DEG),
            cx=float(self.camera.cx), cy=float(self.camera.cy),
            px_per_mm=float(self.camera.px_per_mm),
            shadow_slope=min(abs(1.0 / self._ka), abs(1.0 / self._kb)),
            col_step_px=float(self.bin_cols))
        for ix in extent:
            ix.flags.writeable = False
        smap.__dict__["_valid_extent"] = extent  # what its cached property would find
        return smap


def surface_map(image_a: np.ndarray, image_b: np.ndarray, *, camera: Camera, lights: Lights,
                shift_px: float, roll_deg: float = 0.0) -> SurfaceMap:
    """The map of one pair at the camera's full resolution (a one-off :class:`SurfaceMapper`).

    Parameters
    ----------
    image_a, image_b : ndarray, shape (height, width)
        The distorted images lit by light A and light B, B taken after A.
    camera, lights : config.rig.Camera, config.rig.Lights
        The rig.
    shift_px : float
        Board motion along the feed between the shots, pixels (the registration's).
    roll_deg : float, optional
        Direction of the feed in the image, degrees.

    Returns
    -------
    SurfaceMap
    """
    a, b = np.asarray(image_a), np.asarray(image_b)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(f"image_a and image_b must be 2-D of one shape, got {a.shape}, "
                         f"{b.shape}")
    mapper = SurfaceMapper(camera, lights, a.shape)  # type: ignore[arg-type]
    return mapper(a, b, shift_px=shift_px, roll_deg=roll_deg)
