"""From the two raw images to what the measurement needs: group means, profiles, texture rows.

The measurement never needs a whole undistorted image: it averages columns (along the marks),
registers a band of texture rows and estimates the marks' direction from a few row groups.
:class:`FrontEnd` does all set-up once per camera and image shape and then, per image:

1. sums groups of ``k0`` adjacent rows of the *distorted* image (numpy, integer sums; ``k0``
   from the worst roll searched, as before: a mark leans by at most ``roll_smear_px`` across
   one group) -- the only pass over the full image;
2. for the orientation, sums those into ``groups`` equal groups and undistorts only them
   (a ``groups x width`` remap);
3. for the profile, sums ``m`` of the ``k0``-row groups into coarse bins -- ``m`` as large as
   the measured roll allows (a mark smears by at most ``roll_smear_px`` across a bin, a column
   drifts by at most ``max_drift_px`` with the lens distortion) -- and resamples them with one
   remap whose table undistorts *and* shears along the marks at once (one table per roll,
   cached), then averages the columns;
4. for the texture registration, resamples only the texture rows, undistorted *and* rotated to
   the feed at once (again one cached table per roll).

Every table goes from the binned distorted image straight to the output grid, built by OpenCV's
``initUndistortRectifyMap`` with a "new camera matrix" that holds the output grid's affine map
(bin spacing, shear or rotation), so each output sample is interpolated once.  The tables are
``float32``: on this OpenCV build a remap through float tables runs 2-3x faster than through
fixed-point (``CV_16SC2``) ones (measured, docs/performance.md).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from config.rig import Camera
from core.checks import check_image, check_int, check_positive
from vision import check_kernels, kernels
from vision.calibration.undistort import Undistorter

_ROLL_KEY_DEG = 0.005
"""Rolls are rounded to this grid for the cached tables (a shear error below 0.01 px)."""


@dataclass(frozen=True)
class _Table:
    """One cached remap table and what it covers."""

    map_x: np.ndarray
    map_y: np.ndarray
    rows: slice  # source rows (of the k0-row bins) the table reads from
    factor: int  # k0-row bins summed per source row
    valid: slice  # texture: output rows inside the band; profile: source bins of the band
    parts: dict[tuple[int | None, int | None, int | None], tuple[np.ndarray, np.ndarray]] = (
        field(default_factory=dict))  # contiguous copies of row selections, made once

    def part(self, key: slice) -> tuple[np.ndarray, np.ndarray]:
        """The tables of the output rows ``key`` (contiguous, cached)."""
        k = (key.start, key.stop, key.step)
        hit = self.parts.get(k)
        if hit is None:
            if len(self.parts) > 8:
                self.parts.clear()
            hit = self.parts[k] = (np.ascontiguousarray(self.map_x[key]),
                                   np.ascontiguousarray(self.map_y[key]))
        return hit


class Binned:
    """One image summed into ``k0``-row bins (what :meth:`FrontEnd.bin` returns).

    Attributes
    ----------
    bins : ndarray, shape (n_bins, width)
        Row sums of the distorted image: ``uint16`` for 8-bit images, else ``float32``.
    level : float
        Mean level of the image as a fraction of its full scale.
    saturated : bool
        Most columns are at >= 98 % of full scale.
    groups : ndarray, shape (groups, width), float32, or None
        Sums of the orientation's row groups (of the ``k0``-row bins), made when the
        orientation is first estimated from the image (``None`` until then).
    """

    __slots__ = ("bins", "groups", "level", "saturated", "_norm", "_plain")

    def __init__(self, bins: np.ndarray, level: float, saturated: bool) -> None:
        self.bins = bins
        self.level = level
        self.saturated = saturated
        self.groups: np.ndarray | None = None
        self._norm: np.ndarray | None = None
        self._plain: np.ndarray | None = None  # the unsheared profile's bins


def full_scale(dtype: np.dtype, peak: float) -> float:
    """Full-scale value of an image.

    255 for 8 bits; for 16-bit containers the smallest of 10, 12, 14 or 16 bits that holds
    ``peak`` (cameras store 10-14-bit data in them); 1.0 for float images in [0, 1].
    """
    if dtype == np.uint8:
        return 255.0
    if np.issubdtype(dtype, np.integer) or peak > 1.0:
        for bits in (10, 12, 14, 16):
            if peak <= (1 << bits) - 1:
                return float((1 << bits) - 1)
        return max(65535.0, peak)
    return 1.0


class FrontEnd:
    """Binning, undistortion, shear and rotation of one camera and image shape (set up once).

    Parameters
    ----------
    camera : config.rig.Camera
        Intrinsics, distortion and the rig's roll.
    shape : tuple of int
        ``(height, width)`` of the images, pixels.
    max_roll_deg : float
        Half-width of the roll search around the rig's roll, degrees (sets ``k0``).
    roll_smear_px : float, optional
        Largest smear of a mark across one bin, pixels.
    max_drift_px : float, optional
        Largest horizontal drift of an undistorted column across one bin (lens), pixels.
    max_bin_rows : int, optional
        Largest bin of the profile, image rows.
    texture_rows : int, optional
        ``k0``-row bins (evenly spread) whose texture registers the pair.
    groups : int, optional
        Row groups of the orientation estimate (equal groups of adjacent bins).
    cache : int, optional
        Remap tables kept per kind (keyed by the roll on a 0.005 deg grid).

    Attributes
    ----------
    undistort : vision.calibration.undistort.Undistorter
        The ``k0``-row binning and its geometry (``bin_rows``, ``row_band``, ``columns``).
    width : int
        Columns of every output (the undistorted columns that see the image).
    row_v_px : ndarray, shape (n_rows,)
        Undistorted image row at the centre of each ``k0``-row bin of the band.
    """

    def __init__(self, camera: Camera, shape: tuple[int, int], *, max_roll_deg: float,
                 roll_smear_px: float = 0.5, max_drift_px: float = 0.25,
                 max_bin_rows: int = 32, texture_rows: int = 96, groups: int = 16,
                 cache: int = 16) -> None:
        self.camera = camera
        # compiled (or loaded from the cache) here, never on a frame; the checks' loops too
        kernels.warm_up()
        check_kernels.warm_up()
        self.roll_smear_px = check_positive("roll_smear_px", roll_smear_px)
        self.max_drift_px = check_positive("max_drift_px", max_drift_px)
        check_int("max_bin_rows", max_bin_rows, lo=1)
        self._cache_size = check_int("cache", cache, lo=1)
        worst = math.tan(math.radians(abs(camera.roll_deg) + max_roll_deg))
        k0_cap = 16
        if worst > 0:
            k0_cap = max(1, min(16, int(roll_smear_px / worst)))
        self.undistort = Undistorter(camera, shape, max_bin_rows=k0_cap)
        und = self.undistort
        self.shape = und.shape
        self.k0 = und.bin_rows
        c0, c1 = und.columns
        self.columns = (c0, c1)
        self.width = c1 - c0
        band = und.row_band
        self.band = band
        self.row_v_px = und.first_row_px + self.k0 * np.arange(band.start, band.stop)
        # farthest bin of the band from the optical axis's row, pixels
        self._reach_rows_px = float(np.max(np.abs(self.row_v_px - camera.cy)))
        n_rows = band.stop - band.start
        self._k = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy],
                            [0.0, 0.0, 1.0]])
        self._dist = np.asarray(camera.dist, dtype=np.float64)
        self._identity = not np.any(self._dist)
        # Largest profile bin the lens allows (the roll may allow less, per pair).
        drift = und.drift_px_per_row
        k_lens = max_bin_rows if drift <= 0 else int(max_drift_px / drift)
        self.max_factor = max(1, min(max_bin_rows, k_lens) // self.k0)
        # Texture rows: evenly spread over the band (indices into the band's bins).
        self.texture_rows = np.unique(
            np.linspace(0, n_rows - 1, min(n_rows, texture_rows)).round().astype(int))
        # Orientation groups: equal groups of adjacent bins, centred in the band.
        g = min(check_int("groups", groups, lo=2), n_rows)
        size = n_rows // g
        first = band.start + (n_rows - g * size) // 2
        self._group_rows = slice(first, first + g * size)
        self._group_count, self._group_size = g, size
        self.group_v_px = self.row_v_px[first - band.start: first - band.start + g * size
                                        ].reshape(g, size).mean(axis=1)
        # The orientation needs frequencies up to a quarter cycle per pixel only: its groups
        # are undistorted at every second column (each the mean of two).
        self.group_step = 2 if self.width >= 64 else 1
        self._group_table = self._build(
            out_v=self.group_v_px, src_first=und.first_row_px + self.k0 * (first + (size - 1) / 2),
            src_step=self.k0 * size, rows=self._group_rows, factor=size,
            col_step=self.group_step)
        self._tables: dict[str, OrderedDict[tuple[float, int], _Table]] = {
            "profile": OrderedDict(), "texture": OrderedDict()}

    # -- tables -----------------------------------------------------------------------------

    def _build(self, *, out_v: np.ndarray, src_first: float, src_step: float, rows: slice,
               factor: int, tan_roll: float = 0.0, rotate_deg: float | None = None,
               col_step: int = 1) -> _Table:
        """A remap table from binned distorted rows to an output grid.

        Output pixel ``(p, i)`` (column ``p`` of the ``width`` undistorted columns, row ``i``
        centred on undistorted row ``out_v[i]``, evenly spaced) samples the undistorted image
        at ``(c0 + p - (v - cy) tan_roll, v)``, or -- ``rotate_deg`` given -- rotated about the
        optical axis so that the feed runs along the rows.  The source is the image summed
        into rows centred on ``src_first + j * src_step`` (image rows).  With ``col_step`` > 1
        output column ``p`` lies at ``c0 + col_step * p + (col_step - 1) / 2``: bilinear
        sampling midway between the columns averages them (a decimated row).
        """
        cam = self.camera
        c0, _ = self.columns
        width = self.width // col_step
        c0 = c0 + (col_step - 1) / 2
        n_out = int(np.size(out_v))
        v0 = float(out_v[0])
        step = float(out_v[1] - out_v[0]) if n_out > 1 else 1.0
        fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
        # Undistorted pixel (u, v) of output (p, i), affine: (u, v) = A @ (p, i, 1).
        if rotate_deg is None:
            a = np.array([[float(col_step), -step * tan_roll, c0 - (v0 - cy) * tan_roll],
                          [0.0, step, v0]])
        else:
            c, s = math.cos(math.radians(rotate_deg)), math.sin(math.radians(rotate_deg))
            # u = cx + du c - dv s, v = cy + du s + dv c, du = c0 + p - cx, dv = v0 + i step - cy
            a = np.array([[c, -step * s, cx + (c0 - cx) * c - (v0 - cy) * s],
                          [s, step * c, cy + (c0 - cx) * s + (v0 - cy) * c]])
        # Normalised camera coordinates of output (p, i): M @ (p, i, 1); newK = M^-1.
        m = np.array([[a[0, 0] / fx, a[0, 1] / fx, (a[0, 2] - cx) / fx],
                      [a[1, 0] / fy, a[1, 1] / fy, (a[1, 2] - cy) / fy],
                      [0.0, 0.0, 1.0]])
        size = (width, n_out)
        if self._identity:
            p, i = np.meshgrid(np.arange(width, dtype=np.float64),
                               np.arange(n_out, dtype=np.float64))
            mx = a[0, 0] * p + a[0, 1] * i + a[0, 2]
            my = a[1, 0] * p + a[1, 1] * i + a[1, 2]
        else:
            mx, my = cv2.initUndistortRectifyMap(self._k, self._dist, None, np.linalg.inv(m),
                                                 size, cv2.CV_32FC1)
        src_y = (np.asarray(my, dtype=np.float64) - src_first) / src_step
        valid = slice(0, n_out)
        if rotate_deg is not None:
            # Rows whose samples all come from inside the band of bins (as orientation.Rotator).
            p, i = np.meshgrid(np.arange(self.width, dtype=np.float64),
                               np.arange(n_out, dtype=np.float64))
            v_und = a[1, 0] * p + a[1, 1] * i + a[1, 2]
            lo, hi = float(self.row_v_px[0]), float(self.row_v_px[-1])
            ok = np.flatnonzero(np.all((v_und >= lo - 1e-6) & (v_und <= hi + 1e-6), axis=1))
            valid = slice(int(ok[0]), int(ok[-1]) + 1) if ok.size else slice(0, 0)
        return _Table(np.ascontiguousarray(mx, dtype=np.float32),
                      np.ascontiguousarray(src_y, dtype=np.float32), rows, factor, valid)

    def _cached(self, kind: str, key: tuple[float, int], make: object) -> _Table:
        cache = self._tables[kind]
        hit = cache.get(key)
        if hit is not None:
            cache.move_to_end(key)
            return hit
        table = make()  # type: ignore[operator]
        cache[key] = table
        if len(cache) > self._cache_size:
            cache.popitem(last=False)
        return table

    @staticmethod
    def roll_key(roll_deg: float) -> float:
        """The roll rounded to the tables' grid, degrees."""
        return round(roll_deg / _ROLL_KEY_DEG) * _ROLL_KEY_DEG

    def margin_px(self, roll_deg: float, *, min_smear_px: float = 0.1) -> int:
        """Columns at either end whose sheared samples fall outside the band (0: no shear)."""
        dv = self._reach_rows_px
        reach = dv * abs(math.tan(math.radians(roll_deg)))
        return 0 if reach <= min_smear_px else int(math.ceil(reach)) + 2

    def rotates(self, roll_deg: float, *, min_shift_px: float = 0.1) -> bool:
        """Whether the texture rows are rotated at this roll (else taken as they are)."""
        s = abs(math.sin(math.radians(roll_deg)))
        cx = self.camera.cx - self.columns[0]
        dv = self._reach_rows_px
        return s * (max(cx, self.width - cx) + dv) > min_shift_px

    def profile_factor(self, roll_deg: float, *, shear: bool) -> int:
        """``k0``-row bins summed per profile bin at this roll."""
        if not shear:
            return self.max_factor
        tan = abs(math.tan(math.radians(roll_deg)))
        return max(1, min(self.max_factor, int(self.roll_smear_px / (self.k0 * tan))))

    def _profile_table(self, roll_deg: float, shear: bool) -> _Table:
        key = self.roll_key(roll_deg) if shear else 0.0
        m = self.profile_factor(key, shear=shear)

        def make() -> _Table:
            band = self.band
            n = (band.stop - band.start) // m
            first = band.start + ((band.stop - band.start) - n * m) // 2
            # Output: the bins inside the band; source: as many whole bins around them as
            # the image holds (a lens may sample a little beyond the band's first and last).
            start = first - m * (first // m)
            stop = first + n * m + m * ((self.undistort.bins - first - n * m) // m)
            centres = self.undistort.first_row_px + self.k0 * (first + m * np.arange(n)
                                                               + (m - 1) / 2)
            tan = math.tan(math.radians(key)) if shear else 0.0
            src_first = self.undistort.first_row_px + self.k0 * (start + (m - 1) / 2)
            table = self._build(out_v=centres, src_first=src_first, src_step=self.k0 * m,
                                rows=slice(start, stop), factor=m, tan_roll=tan)
            return _Table(table.map_x, table.map_y, table.rows, m,
                          slice((first - start) // m, (first - start) // m + n))

        return self._cached("profile", (key, m), make)

    def _texture_table(self, roll_deg: float, rotate: bool) -> _Table:
        key = self.roll_key(roll_deg) if rotate else 0.0

        def make() -> _Table:
            band = self.band
            full = self._build(out_v=self.row_v_px,
                               src_first=self.undistort.first_row_px + self.k0 * band.start,
                               src_step=self.k0, rows=band, factor=1,
                               rotate_deg=key if rotate else None)
            pick = self.texture_rows
            if rotate:
                n_valid = full.valid.stop - full.valid.start
                if n_valid < 2:
                    return _Table(full.map_x[:0], full.map_y[:0], band, 1, slice(0, 0))
                pick = pick[pick < n_valid] + full.valid.start
            return _Table(np.ascontiguousarray(full.map_x[pick]),
                          np.ascontiguousarray(full.map_y[pick]), band, 1, full.valid)

        return self._cached("texture", (key, 1), make)

    # -- per image --------------------------------------------------------------------------

    def bin(self, image: np.ndarray, name: str) -> Binned:
        """Sum an image into ``k0``-row bins (and the orientation's groups); judge its level.

        Parameters
        ----------
        image : ndarray, shape (height, width)
            Distorted grayscale image.
        name : str
            Parameter name for errors.

        Returns
        -------
        Binned
        """
        img = check_image(name, image)
        if img.shape != self.shape:
            raise ValueError(
                f"{name} has shape {img.shape}, the measurer was set up for {self.shape}")
        # The level from the unsheared profile's bins (the band's rows), which the profile
        # then reuses; the orientation's groups are summed only when it asks for them.
        t = self._profile_table(0.0, False)
        c0, c1 = self.columns
        if img.dtype == np.uint8 and self.k0 > 1:
            bins, plain, col = self._bin_compiled(img, t)
        else:
            bins = self.undistort.bin_image(img)
            plain = self._profile_bins(bins, t)
            col = cv2.reduce(plain[t.valid, c0:c1], 0, cv2.REDUCE_SUM,
                             dtype=cv2.CV_64F).ravel()
        per_pixel = col / ((t.valid.stop - t.valid.start) * t.factor * self.k0)
        full = full_scale(img.dtype, float(per_pixel.max()))
        level = float(per_pixel.sum() / per_pixel.size) / full
        saturated = bool(np.count_nonzero(per_pixel >= 0.98 * full) > 0.5 * per_pixel.size)
        out = Binned(bins, level, saturated)
        out._plain = plain
        return out

    def _bin_compiled(self, img: np.ndarray, t: _Table
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`bin`'s sums of an 8-bit image in one compiled pass (the same integers).

        The ``k0``-row bins, the unsheared profile's bins (``t.factor`` of them summed over
        ``t.rows``) and the column sums of those over ``t.valid`` and the columns.
        """
        und = self.undistort
        m = t.factor
        w = img.shape[1]
        bins = np.empty((und.bins, w), dtype=np.uint16)
        n_plain = (t.rows.stop - t.rows.start) // m
        acc = np.uint16 if m * self.k0 <= 257 else np.float32
        plain = np.empty((n_plain, w), dtype=acc)
        c0, c1 = self.columns
        col = np.empty(c1 - c0)
        scratch = np.empty(c1 - c0, dtype=np.uint32 if acc == np.uint16 else np.float64)
        kernels.bin_rows(np.ascontiguousarray(img), und.first_image_row, self.k0, bins,
                         t.rows.start, m, plain, t.valid.start, t.valid.stop, c0, c1, scratch,
                         col)
        return bins, plain, col

    def _groups(self, bins: np.ndarray) -> np.ndarray:
        """Sums of the orientation's row groups, shape (groups, width), float32."""
        g, size = self._group_count, self._group_size
        if bins.dtype == np.uint16 and size <= 256 and bins.flags.c_contiguous:
            # one compiled pass, the same float32 sums (integers below 2**24: exact)
            out = np.empty((g, bins.shape[1]), dtype=np.float32)
            kernels.group_sums(bins, self._group_rows.start, size, out)
            return out
        part = bins[self._group_rows]
        return part.reshape(g, size, part.shape[1]).sum(axis=1, dtype=np.float32)

    def _profile_bins(self, bins: np.ndarray, table: _Table) -> np.ndarray:
        """The ``k0``-row bins summed ``table.factor`` at a time over the table's rows."""
        part = bins[table.rows]
        m = table.factor
        if m > 1:
            acc = np.uint16 if part.dtype == np.uint16 and m * self.k0 <= 257 else np.float32
            if acc == np.uint16 and part.flags.c_contiguous:  # the same sums, one pass
                out = np.empty((part.shape[0] // m, part.shape[1]), dtype=np.uint16)
                kernels.group_sums(part, 0, m, out)
                return out
            part = part.reshape(-1, m, part.shape[1]).sum(axis=1, dtype=acc)
        return part

    def group_means(self, *images: Binned) -> np.ndarray:
        """Undistorted group means of the orientation estimate.

        Returns
        -------
        ndarray, shape (n_images, groups, width // group_step), float32
            Mean of each group's ``k0``-row sums, undistorted at the group's centre row
            :attr:`group_v_px`, every :attr:`group_step`-th column (the mean of that many).
        """
        t = self._group_table
        out = np.empty((len(images), self._group_count, t.map_x.shape[1]), dtype=np.float32)
        for n, img in enumerate(images):
            if img.groups is None:
                img.groups = self._groups(img.bins)
            cv2.remap(img.groups, t.map_x, t.map_y, cv2.INTER_LINEAR, dst=out[n],
                      borderMode=cv2.BORDER_REPLICATE)
        out *= np.float32(1.0 / self._group_size)
        return out

    def profile(self, image: Binned, roll_deg: float) -> np.ndarray:
        """Column means along the marks at this roll (sums of ``k0`` image rows).

        Parameters
        ----------
        image : Binned
            The image's bins.
        roll_deg : float
            The marks' direction, degrees (a negligible roll is not sheared).

        Returns
        -------
        ndarray, shape (width,), float64
            Mean over the band's rows of the undistorted image, sheared along the marks
            (sample ``p`` at undistorted column ``c0 + p`` on the optical axis's row); in
            units of one ``k0``-row bin.
        """
        return mean_profile(*self.profile_rows(image, roll_deg))

    def profile_rows(self, image: Binned, roll_deg: float) -> tuple[np.ndarray, int]:
        """The profile's bins before they are averaged (see :meth:`profile`).

        Returns
        -------
        rows : ndarray, shape (n_bins, width)
            Sums of ``factor`` ``k0``-row bins each, undistorted and sheared along the marks
            (``uint16`` or ``float32``; a view of the image's bins when nothing is resampled).
        factor : int
            ``k0``-row bins summed per row: ``rows.mean(axis=0) / factor`` is the profile.
        """
        shear = self.margin_px(roll_deg) > 0
        t = self._profile_table(roll_deg, shear)
        if not shear and image._plain is not None:
            part = image._plain
        else:
            part = self._profile_bins(image.bins, t)
        if self._identity and not shear:
            c0, c1 = self.columns
            return part[t.valid, c0:c1], t.factor
        # cubic along the marks: the shear's fractional shifts vary by row, and a linear
        # blend's smoothing would differ from a sheared to an unsheared profile
        kind = cv2.INTER_CUBIC if shear else cv2.INTER_LINEAR
        return cv2.remap(part, t.map_x, t.map_y, kind, borderMode=cv2.BORDER_REPLICATE), t.factor

    def texture(self, image: Binned, roll_deg: float, profile: np.ndarray, *,
                columns: slice | None = None) -> TextureRows:
        """The shading-free texture rows: undistorted, rotated to the feed at a sizeable roll.

        Parameters
        ----------
        image : Binned
            The image's bins.
        roll_deg : float
            The feed's direction, degrees.
        profile : ndarray, shape (width,)
            The image's unsheared column profile (:meth:`profile` at a negligible roll): the
            shading divided out of rows that are not rotated.
        columns : slice, optional
            A window of the output columns (``0 <= start < stop <= width``, step 1): only it is
            resampled (default: all ``width``).

        Returns
        -------
        TextureRows
            ``rows / profile - 1`` of the texture rows (``float32``), made when indexed: a
            registration that needs only every third row never resamples the others.
        """
        cols = slice(0, self.width) if columns is None else columns
        if (not isinstance(cols.start, int) or not isinstance(cols.stop, int)
                or not 0 <= cols.start < cols.stop <= self.width or cols.step not in (None, 1)):
            raise ValueError(f"columns must be a window of 0..{self.width}, got {columns}")
        n_cols = cols.stop - cols.start
        rotate = self.rotates(roll_deg)
        t = self._texture_table(roll_deg, rotate) if rotate else None
        if t is not None and t.map_x.shape[0] > 0:
            src = image.bins[t.rows]
            if image._norm is None:
                image._norm = self._over_row_means(src)
            # rotated rows carry their own shading: divided by the profile of the rows taken
            return TextureRows(_remapper(image._norm, t, cols), t.map_x.shape[0], n_cols, None)
        t = self._texture_table(0.0, False)
        src = image.bins[t.rows]
        prof = np.asarray(profile)[cols]
        if self._identity:
            c0 = self.columns[0] + cols.start
            c1 = c0 + n_cols
            pick = self.texture_rows
            return TextureRows(lambda key: src[pick[key], c0:c1], pick.size, n_cols, prof)

        return TextureRows(_remapper(src, t, cols), t.map_x.shape[0], n_cols, prof)

    def _over_row_means(self, src: np.ndarray) -> np.ndarray:
        """``src`` (``float32``) divided row by row by its mean over the columns (1 if <= 0)."""
        c0, c1 = self.columns
        if src.dtype == np.uint16 and src.ndim == 2 and 0 < c1 - c0 < 65537:
            # The same numbers in two passes instead of five: a row's integer sum is exact in
            # float32 below 2**24 (numpy's float32 mean adds exact integers then), the mean
            # and each quotient one correctly rounded float32 division either way.
            sums = src[:, c0:c1].sum(axis=1, dtype=np.uint32)
            if sums.size and int(sums.max()) < 1 << 24:
                means = sums.astype(np.float32) / np.float32(c1 - c0)
                means[~(means > 0)] = np.float32(1.0)
                out = np.empty(src.shape, dtype=np.float32)
                kernels.rows_over(src, means, out)
                return out
        f = src.astype(np.float32)
        mean = f[:, c0:c1].mean(axis=1, keepdims=True)
        f /= np.where(mean > 0, mean, np.float32(1.0))
        return f


def mean_profile(rows: np.ndarray, factor: int) -> np.ndarray:
    """The column means of :meth:`FrontEnd.profile_rows` (in units of one ``k0``-row bin)."""
    if rows.dtype == np.uint16 and rows.flags.c_contiguous and rows.shape[0] < 65537:
        # integer sums in one compiled pass: the same float64 values as cv2.reduce's
        total = np.empty(rows.shape[1])
        kernels.column_sums(rows, np.empty(rows.shape[1], dtype=np.uint32), total)
    else:
        total = cv2.reduce(rows, 0, cv2.REDUCE_SUM, dtype=cv2.CV_64F).ravel()
    return total / (rows.shape[0] * factor)


def _remapper(src: np.ndarray, table: _Table, columns: slice) -> object:
    """``rows(key)``: the table's output rows ``key`` (a slice), ``columns``, from ``src``."""
    whole = columns.start == 0 and columns.stop == table.map_x.shape[1]

    def rows(key: slice) -> np.ndarray:
        mx, my = table.part(key)
        if not whole:  # strided views: OpenCV reads them in place
            mx, my = mx[:, columns], my[:, columns]
        return cv2.remap(src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    return rows


class TextureRows:
    """Shading-free texture rows made on demand (what :meth:`FrontEnd.texture` returns).

    Indexing with a slice of rows gives ``rows / profile - 1`` of those rows only (``float32``,
    shape ``(k, width)``); ``np.asarray`` gives all of them.

    Parameters
    ----------
    rows : callable
        ``rows(key)``: the raw rows selected by the slice ``key``.
    count, width : int
        Shape of all the rows.
    profile : ndarray, shape (width,), or None
        Column profile the rows are divided by (``None``: each selection by its own).
    """

    def __init__(self, rows: object, count: int, width: int,
                 profile: np.ndarray | None) -> None:
        self._rows = rows
        self.shape = (int(count), int(width))
        self.ndim = 2
        self._profile = profile
        self._inv: np.ndarray | None = None  # 1 / profile, made when rows are first taken

    def __getitem__(self, key: slice) -> np.ndarray:
        if not isinstance(key, slice):
            raise TypeError("texture rows are selected by a slice")
        rows = self._rows(key)  # type: ignore[operator]
        inv = self._inv
        if inv is None:
            if self._profile is not None:
                inv = self._inv = _inverse(self._profile)
            elif rows.dtype == np.float32 and rows.ndim == 2 and rows.shape[0] > 0:
                # cv2.reduce's float64 column means, inverted in float32: one compiled pass
                inv = np.empty(rows.shape[1], dtype=np.float32)
                kernels.inverse_column_means(np.ascontiguousarray(rows),
                                             np.empty(rows.shape[1]), inv)
            else:
                inv = _inverse(cv2.reduce(rows, 0, cv2.REDUCE_AVG, dtype=cv2.CV_64F).ravel())
        if (rows.dtype in (np.uint16, np.float32) and rows.ndim == 2 and rows.size
                and inv.shape == (rows.shape[1],)):
            tex = np.empty(rows.shape, dtype=np.float32)
            kernels.scaled_less_one(np.ascontiguousarray(rows), inv, tex)  # the same numbers
            return tex
        tex = np.multiply(rows, inv[None, :], dtype=np.float32)
        tex -= np.float32(1.0)
        return tex

    def __array__(self, dtype: object = None, copy: object = None) -> np.ndarray:
        out = self[:]
        return out if dtype is None else out.astype(dtype, copy=False)

    def __len__(self) -> int:
        return self.shape[0]


def _inverse(profile: np.ndarray) -> np.ndarray:
    """``1 / profile`` (0 where it is not positive), ``float32``."""
    prof = np.asarray(profile, dtype=np.float32)
    out = np.zeros(prof.shape, dtype=np.float32)
    return np.divide(np.float32(1.0), prof, out=out, where=prof > 0)
