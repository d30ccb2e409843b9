"""The whole measurement of one image pair: images in, profile and cuttermark metrics out.

Steps (all set-up done once per rig and image shape in :class:`Measurer`):

1. undistort both images straight into vertically binned rows (:mod:`vision.undistort`);
2. column profiles (:mod:`vision.profile`) and shading-free textures;
3. registration: encoder shift (seed Eq. 5-6), refined from the images -- coarse on the albedo
   (2-D texture, or the 1-D column profiles), fine on the column profiles
   (:mod:`vision.registration`);
4. optional flat-field correction of each profile in the camera frame, then Wiener deblurring along
   the feed when the motion blur is sizeable (:mod:`vision.deblur`);
5. B resampled onto A's columns over the overlap; log-ratio detrended against LED imbalance and
   fall-off (:mod:`vision.illumination`); slope by seed Eq. 4 (:mod:`vision.slope`);
6. frequency-domain integration to height in micrometres (:mod:`vision.integrate`);
7. cusps, widths, depths, pitch, uniformity (:mod:`vision.marks`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from config.rig import Rig
from core.checks import check_image, check_int, check_positive
from core.errors import MeasurementError
from vision.deblur import Deblurrer, blur_length_px
from vision.illumination import Detrender, flat_field_correct, running_mean
from vision.integrate import Integrator
from vision.marks import find_marks, knife_means, repeat_period_px
from vision.orientation import Orientation, RollEstimator, Rotator, Shearer
from vision.profile import column_profile, overlap, shift_profile
from vision.registration import (
    Registrar,
    Registration,
    encoder_shift_px,
    shading_free_texture,
)
from vision.selfcal import (
    Calibration,
    SelfCalibrator,
    apply_calibration,
    fit_calibration,
    kinematic_depths_um,
    kinematic_slope,
)
from vision.slope import slope_from_ratio
from vision.undistort import Undistorter


@dataclass(frozen=True)
class Measurement:
    """One measured pair.

    Attributes
    ----------
    x_mm : ndarray, shape (n,)
        Positions along the feed in A's frame (undistorted column / px_per_mm), mm.
    height_um : ndarray, shape (n,)
        Surface height, um (zero mean over the profile).
    slope : ndarray, shape (n,)
        Surface slope ``dz/dx``.
    pitch_mm : float
        Mean mark width, mm.
    mark_widths_mm, mark_depths_um : ndarray, shape (m,)
        Per complete mark, mm and um.
    cusps_mm : ndarray, shape (m + 1,)
        Cusps bounding the complete marks, mm.
    bottoms_mm : ndarray, shape (m,)
        Lowest point of each complete mark, mm.
    uniformity_cv : float
        Coefficient of variation of the widths.
    depth_um : float
        Mean mark depth, um.
    shift_px, encoder_shift_px : float
        Registration used, and the encoder's own shift, pixels.
    confidence : float
        Registration confidence in [0, 1].
    blur_px : float
        Motion blur length the profiles were deconvolved for (0: not deblurred), pixels.
    roll_deg : float
        Direction of the feed (and normal of the marks) in the image, degrees from the x axis;
        the profile was averaged along the marks at this angle.
    roll_confidence : float
        Confidence of the per-pair roll estimate in [0, 1] (below the measurer's threshold the
        rig's roll is used instead).
    calibration : vision.selfcal.Calibration or None
        Self-calibration from the kinematics (``None``: no cutting radius given, off).  When
        ``calibration.trusted`` the profile, slope and depths are calibrated with it.
    kinematic_depth_um : float
        Mean depth of the marks from their cusps and lowest points with the cutting radius, um
        (NaN without the radius).
    uncalibrated_depth_um : float
        ``depth_um`` before the self-calibration, um (NaN without the radius).
    knife_widths_mm : ndarray, shape (knives,), or None
        Mean width per knife, marks attributed in turn from the first complete mark (relative
        phase; ``None`` without the number of knives).
    """

    x_mm: np.ndarray
    height_um: np.ndarray
    slope: np.ndarray
    pitch_mm: float
    mark_widths_mm: np.ndarray
    mark_depths_um: np.ndarray
    cusps_mm: np.ndarray
    bottoms_mm: np.ndarray
    uniformity_cv: float
    depth_um: float
    shift_px: float
    encoder_shift_px: float
    confidence: float
    blur_px: float = 0.0
    roll_deg: float = 0.0
    roll_confidence: float = math.nan
    calibration: Calibration | None = None
    kinematic_depth_um: float = math.nan
    uncalibrated_depth_um: float = math.nan
    knife_widths_mm: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON dict of the measurement.

        The contract keys (``x_mm``, ``height_um``, ``pitch_mm``, ``mark_widths_mm``,
        ``uniformity_cv``, ``depth_um``, ``shift_px``) plus extras.
        """

        def floats(a: np.ndarray, digits: int) -> list[float]:
            return [round(float(v), digits) for v in np.asarray(a)]

        return {
            "x_mm": floats(self.x_mm, 5),
            "height_um": floats(self.height_um, 4),
            "pitch_mm": float(self.pitch_mm),
            "mark_widths_mm": floats(self.mark_widths_mm, 5),
            "uniformity_cv": float(self.uniformity_cv),
            "depth_um": float(self.depth_um),
            "shift_px": float(self.shift_px),
            "mark_depths_um": floats(self.mark_depths_um, 4),
            "cusps_mm": floats(self.cusps_mm, 5),
            "bottoms_mm": floats(self.bottoms_mm, 5),
            "marks": int(len(self.mark_widths_mm)),
            "encoder_shift_px": float(self.encoder_shift_px),
            "confidence": float(self.confidence) if math.isfinite(self.confidence) else None,
            "blur_px": float(self.blur_px),
            "roll_deg": round(float(self.roll_deg), 4),
            "roll_confidence": _finite_or_none(self.roll_confidence, 3),
            "kinematic_depth_um": _finite_or_none(self.kinematic_depth_um, 4),
            "uncalibrated_depth_um": _finite_or_none(self.uncalibrated_depth_um, 4),
            "calibration": _calibration_json(self.calibration),
            "knife_widths_mm": (None if self.knife_widths_mm is None else
                                [_finite_or_none(v, 5) for v in self.knife_widths_mm]),
        }


def _finite_or_none(value: float | None, digits: int) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), digits)


def _calibration_json(cal: Calibration | None) -> dict[str, Any]:
    if cal is None:
        return {"state": "off", "reason": "no cutting radius given (--radius-mm)"}
    return {
        "state": "applied" if cal.trusted else "untrusted",
        "gain": _finite_or_none(cal.gain, 4),
        "gain_confidence": _finite_or_none(cal.gain_confidence, 3),
        "scatter_mm": _finite_or_none(cal.scatter_mm, 3),
        "scatter_fraction": _finite_or_none(cal.scatter_fraction, 3),
        "scatter_confidence": _finite_or_none(cal.scatter_confidence, 3),
        "deblurred": bool(cal.deblurred),
    }


def _full_scale(dtype: np.dtype, peak: float) -> float:
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


def remove_slow(height_um: np.ndarray, period_px: float) -> np.ndarray:
    """Height minus its running mean over one repeat period (held constant near the ends).

    A running mean over exactly one cutterhead revolution annihilates the marks (and the
    knives' runout pattern, periodic with the revolution), so what it keeps is what varies more
    slowly: the integrated low-frequency noise of the slope and residual illumination.

    Parameters
    ----------
    height_um : ndarray, shape (n,)
        Integrated height, um.
    period_px : float
        Repeat period of the marks, samples (NaN, < 4 or > n / 2: returned unchanged).

    Returns
    -------
    ndarray, shape (n,)
        Height with its slow part removed, zero mean.
    """
    h = np.asarray(height_um, dtype=np.float64)
    n = h.size
    if not (math.isfinite(period_px) and 4.0 <= period_px <= n / 2):
        return h
    slow = running_mean(h, period_px)
    m0 = (n - slow.size) // 2
    slow = np.pad(slow, (m0, n - slow.size - m0), mode="edge")
    out = h - slow
    return out - out.mean()


def vertical_shift(rows: np.ndarray, shift_rows: float) -> np.ndarray:
    """Rows resampled at ``j + shift_rows`` (linear, edge rows repeated).

    Parameters
    ----------
    rows : ndarray, shape (n_rows, width)
        Binned rows.
    shift_rows : float
        Offset, binned rows.

    Returns
    -------
    ndarray, shape (n_rows, width)
        The input itself when the offset is below 0.01 row, else ``float32``.
    """
    if abs(shift_rows) < 0.01:
        return rows
    n = rows.shape[0]
    pos = np.clip(np.arange(n) + shift_rows, 0, n - 1)
    i0 = np.minimum(np.floor(pos).astype(int), n - 2) if n > 1 else np.zeros(n, int)
    t = (pos - i0).astype(np.float32)[:, None]
    r = np.asarray(rows, dtype=np.float32)
    if n == 1:
        return r
    return (1 - t) * r[i0] + t * r[i0 + 1]


def check_rig_size(rig: Rig, shape: tuple[int, int]) -> None:
    """Refuse images of another size than the rig's camera was calibrated at.

    With ``[camera] width``/``height`` in the rig file they must match; without them the
    principal point must lie in the middle half of the image (a rig calibrated at twice the
    size puts it near a corner, and the pitch would come out wrong by the size ratio).

    Parameters
    ----------
    rig : config.rig.Rig
        The rig.
    shape : tuple of int
        ``(height, width)`` of the images, pixels.

    Raises
    ------
    ValueError
        The sizes differ; the message names both.
    """
    h, w = int(shape[0]), int(shape[1])
    cam = rig.camera
    if cam.width is not None or cam.height is not None:
        rw = w if cam.width is None else cam.width
        rh = h if cam.height is None else cam.height
        if (rw, rh) != (w, h):
            raise ValueError(
                f"the rig file was calibrated at {rw}x{rh} pixels, the images are {w}x{h}"
            )
        return
    if not (0.25 * w <= cam.cx <= 0.75 * w and 0.25 * h <= cam.cy <= 0.75 * h):
        rw, rh = round(2 * cam.cx + 1), round(2 * cam.cy + 1)
        raise ValueError(
            f"the rig file's principal point ({cam.cx:g}, {cam.cy:g}) belongs to images of about "
            f"{rw}x{rh} pixels, the images are {w}x{h}: the rig was calibrated at another size"
        )


class Measurer:
    """Measures image pairs of one rig and one image shape (all set-up done here, once).

    Parameters
    ----------
    rig : config.rig.Rig
        Camera, lights and encoder.
    shape : tuple of int
        ``(height, width)`` of the images, pixels.
    flat_field : tuple of two ndarray, optional
        Images A and B of a flat board (same shape and lights): their column profiles become the
        illumination reference of each light.
    search_px : float, optional
        Largest encoder error the registration searches for, pixels.
    detrend_degree : int, optional
        Degree of the illumination polynomial removed from the log-ratio (default 3, or 1 with a
        flat field).
    min_marks : int, optional
        Fewer complete marks are an error.
    min_overlap : float, optional
        Smallest overlap of A and B as a fraction of the image width.
    deblur_min_px : float, optional
        Profiles are deconvolved when the motion blur exceeds this many pixels.
    regularisation : float, optional
        Wiener constant of the deblurring.
    texture_rows : int, optional
        Binned rows (evenly spread) whose texture registers the pair.
    register : bool, optional
        Refine the encoder shift from the images (default).  ``False`` uses the encoder's shift
        as it is (the seed's method; for experiments), with confidence NaN.
    max_roll_deg : float, optional
        The marks' direction is searched within this many degrees of the rig's ``roll_deg``
        (0: no search, the rig's roll is used as it is).
    roll_smear_px : float, optional
        Largest smear of a mark across one vertical bin at the largest roll searched, pixels
        (sets the bin factor).
    min_roll_confidence : float, optional
        A per-pair roll estimate less confident than this is not used (the rig's roll is).
    radius_mm : float, optional
        Cutting radius of the knives, mm: turns the self-calibration from the kinematics on
        (:mod:`vision.selfcal`) and gives the kinematic depth.
    knives : int, optional
        Number of knives: per-knife mean widths (relative phase).
    remove_slow : bool, optional
        Subtract from the height its running mean over one cutterhead revolution (the marks'
        repeat period, which the mean annihilates): what varies more slowly is the integrated
        low-frequency noise and residual illumination, not measurable anyway (see
        :func:`remove_slow`).
    """

    def __init__(
        self,
        rig: Rig,
        shape: tuple[int, int],
        *,
        flat_field: tuple[np.ndarray, np.ndarray] | None = None,
        search_px: float = 20.0,
        detrend_degree: int | None = None,
        min_marks: int = 2,
        min_overlap: float = 0.25,
        deblur_min_px: float = 1.0,
        regularisation: float = 0.003,
        texture_rows: int = 96,
        register: bool = True,
        max_roll_deg: float = 5.0,
        roll_smear_px: float = 0.5,
        min_roll_confidence: float = 0.3,
        radius_mm: float | None = None,
        knives: int | None = None,
        remove_slow: bool = True,
    ) -> None:
        self.rig = rig
        check_rig_size(rig, shape)
        self.max_roll_deg = check_positive("max_roll_deg", max_roll_deg, allow_zero=True)
        self.min_roll_confidence = float(min_roll_confidence)
        self.radius_mm = None if radius_mm is None else check_positive("radius_mm", radius_mm)
        self.knives = None if knives is None else check_int("knives", knives, lo=1)
        self.remove_slow = bool(remove_slow)
        worst = math.tan(math.radians(abs(rig.camera.roll_deg) + self.max_roll_deg))
        max_bins = 16
        if worst > 0:
            max_bins = max(1, min(16, int(check_positive("roll_smear_px", roll_smear_px) / worst)))
        self.undistort = Undistorter(rig.camera, shape, max_bin_rows=max_bins)
        self.shape = self.undistort.shape
        c0, c1 = self.undistort.columns
        self._c0 = c0
        self.width = c1 - c0
        self.px_per_mm = rig.camera.px_per_mm
        self.min_marks = check_int("min_marks", min_marks, lo=1)
        self.register = bool(register)
        if not 0.0 < min_overlap < 1.0:
            raise ValueError(f"min_overlap must be in (0, 1), got {min_overlap!r}")
        self.min_overlap_px = max(32, int(round(min_overlap * self.width)))
        self.deblur_min_px = check_positive("deblur_min_px", deblur_min_px, allow_zero=True)
        self.registrar = Registrar(
            self.width, search_px=search_px, min_overlap_px=min(self.min_overlap_px, self.width - 1)
        )
        band = self.undistort.row_band
        n_rows = band.stop - band.start
        k = self.undistort.bin_rows
        row_v = self.undistort.first_row_px + k * np.arange(band.start, band.stop)
        cy = rig.camera.cy
        self._cx = rig.camera.cx
        self.roll_estimator = (
            RollEstimator(row_v, self.width, cy=cy, centre_deg=rig.camera.roll_deg,
                          max_roll_deg=self.max_roll_deg)
            if self.max_roll_deg > 0 and n_rows >= 2 else None
        )
        self.shearer = Shearer(row_v, self.width, cy=cy)
        self.rotator = Rotator(row_v, self.width, cx=rig.camera.cx - c0, cy=cy)
        self._texture_rows = np.unique(
            np.linspace(0, n_rows - 1, min(n_rows, texture_rows)).round().astype(int)
        )
        if detrend_degree is None:
            detrend_degree = 1 if flat_field is not None else 3
        self.detrender = Detrender(self.width, degree=detrend_degree)
        self.integrator = Integrator(self.width, dx_mm=1.0 / self.px_per_mm)
        self.deblurrer = Deblurrer(self.width, regularisation=regularisation)
        lights = rig.lights
        slant_a, slant_b = lights.slants_deg
        self._angles = {
            "slant_deg": slant_a,
            "azimuth_a_deg": lights.azimuth_a_deg,
            "azimuth_b_deg": lights.azimuth_b_deg,
            "slant_b_deg": None if slant_b == slant_a else slant_b,
        }
        slope_from_ratio(np.ones(1), **self._angles)  # validates the light geometry once
        self._flat: tuple[np.ndarray, np.ndarray] | None = None
        if flat_field is not None:
            if len(flat_field) != 2:
                raise ValueError("flat_field must be a pair of images (A, B)")
            _, ref_a = self._rows_and_profile(flat_field[0], "flat_a")
            _, ref_b = self._rows_and_profile(flat_field[1], "flat_b")
            if np.any(ref_a <= 0) or np.any(ref_b <= 0):
                raise MeasurementError("flat-field images have dark columns")
            self._flat = (ref_a, ref_b)

    # -- pieces -------------------------------------------------------------------------------

    def _rows_and_profile(self, image: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
        img = check_image(name, image)
        if img.shape != self.shape:
            raise ValueError(
                f"{name} has shape {img.shape}, the measurer was set up for {self.shape}"
            )
        c0, c1 = self.undistort.columns
        rows = self.undistort.binned_rows(img)[self.undistort.row_band, c0:c1]
        profile = column_profile(rows)
        k = self.undistort.bin_rows
        full = _full_scale(img.dtype, float(profile.max()) / k) * k
        level = float(profile.mean()) / full
        if level < 0.01:
            raise MeasurementError(
                f"{name} is black (mean level {100 * level:.2f} % of full scale)"
            )
        if np.count_nonzero(profile >= 0.98 * full) > 0.5 * profile.size:
            raise MeasurementError(f"{name} is saturated (most pixels at full scale)")
        return rows, profile

    def blur_px(self, speed_mm_s: float | None) -> float:
        """Motion blur length for a feed speed (0 when the speed or exposure is unknown)."""
        exposure = self.rig.camera.exposure_ms
        if speed_mm_s is None or exposure is None:
            return 0.0
        return blur_length_px(abs(speed_mm_s), exposure_ms=exposure, px_per_mm=self.px_per_mm)

    def _heights(self, slope: np.ndarray, cos_roll: float, period_px: float) -> np.ndarray:
        height = self.integrator(slope) * cos_roll
        return remove_slow(height, period_px) if self.remove_slow else height

    def orientation(self, rows_a: np.ndarray, rows_b: np.ndarray) -> Orientation:
        """Direction of the marks from both images' binned rows (the rig's roll when off)."""
        if self.roll_estimator is None:
            return Orientation(self.rig.camera.roll_deg, math.nan)
        return self.roll_estimator(rows_a, rows_b)

    # -- the measurement ----------------------------------------------------------------------

    def measure(
        self,
        image_a: np.ndarray,
        image_b: np.ndarray,
        *,
        counts_a: int,
        counts_b: int,
        speed_mm_s: float | None = None,
        calibrator: SelfCalibrator | None = None,
    ) -> Measurement:
        """Measure one pair.

        Parameters
        ----------
        image_a, image_b : ndarray, shape (height, width)
            Grayscale images lit by light A and light B, B taken after A.
        counts_a, counts_b : int
            Encoder counts latched at the two triggers.
        speed_mm_s : float, optional
            Feed speed at capture, mm/s (for motion deblurring).
        calibrator : vision.selfcal.SelfCalibrator, optional
            The board's calibrator (kept by the caller per board): this pair's estimate is
            folded in and the smoothed calibration applied.  Without it, this pair's own
            estimate is used.  Ignored without ``radius_mm``.

        Returns
        -------
        Measurement

        Raises
        ------
        ValueError, MeasurementError, RegistrationError
            Bad images or counts, a pair that cannot be registered, too few marks.
        """
        a = np.asarray(image_a)
        b = np.asarray(image_b)
        if a.shape != b.shape:
            raise ValueError(f"image_a and image_b differ in size: {a.shape} vs {b.shape}")
        enc = self.rig.encoder
        d_enc = encoder_shift_px(
            counts_a, counts_b, px_per_count=enc.px_per_count, counter_bits=enc.counter_bits
        )
        if abs(d_enc) > self.width - self.min_overlap_px:
            raise MeasurementError(
                f"encoder counts give a shift of {d_enc:.1f} px, larger than the image allows "
                f"({self.width} px wide, {self.min_overlap_px} px of overlap needed)"
            )
        if speed_mm_s is not None:
            speed_mm_s = float(speed_mm_s)
            if not math.isfinite(speed_mm_s):
                raise ValueError(f"speed_mm_s must be finite, got {speed_mm_s!r}")
        rows_a, prof_a = self._rows_and_profile(a, "image_a")
        rows_b, prof_b = self._rows_and_profile(b, "image_b")

        rows_a_raw, rows_b_raw, prof_a_raw, prof_b_raw = rows_a, rows_b, prof_a, prof_b
        orient = self.orientation(rows_a, rows_b)
        roll = orient.roll_deg if orient.confidence >= self.min_roll_confidence else (
            self.rig.camera.roll_deg)
        cos_roll = math.cos(math.radians(roll))
        margin = self.shearer.margin_px(roll)
        if margin:
            rows_a, _ = self.shearer(rows_a, roll)
            rows_b, _ = self.shearer(rows_b, roll)
            prof_a, prof_b = column_profile(rows_a), column_profile(rows_b)
        d_enc_sheared = d_enc / cos_roll

        if self.register:
            # Texture in rows along the feed (fibres and motion along the rows), profiles
            # along the marks.
            rot_a = self.rotator(rows_a_raw, roll, normalise=True)
            rot_b = self.rotator(rows_b_raw, roll, normalise=True)
            pick = self._texture_rows[self._texture_rows < rot_a.shape[0]]
            tex_a = shading_free_texture(rot_a[pick], column_profile(rot_a)
                                         if rot_a is not rows_a_raw else prof_a_raw)
            tex_b = shading_free_texture(rot_b[pick], column_profile(rot_b)
                                         if rot_b is not rows_b_raw else prof_b_raw)
            reg = self.registrar(
                tex_a, tex_b, encoder_shift_px=d_enc_sheared, profile_a=prof_a,
                profile_b=prof_b,
            )
        else:
            reg = Registration(shift_px=d_enc_sheared, confidence=math.nan,
                               encoder_shift_px=d_enc_sheared)
        d = reg.shift_px

        if self._flat is not None:
            prof_a, prof_b = flat_field_correct(
                prof_a, prof_b, reference_a=self._flat[0], reference_b=self._flat[1]
            )
        blur = self.blur_px(speed_mm_s)
        if blur > self.deblur_min_px:
            both = self.deblurrer(np.stack([prof_a, prof_b]), blur_px=blur)
            prof_a, prof_b = both[0], both[1]
        else:
            blur = 0.0

        u0, u1 = overlap(self.width, d, columns=(margin, self.width - margin))
        count = u1 - u0
        if count < self.min_overlap_px:
            raise MeasurementError(
                f"registered shift {d:.1f} px leaves only {max(count, 0)} px of overlap"
            )
        ia = prof_a[u0:u1]
        ib = shift_profile(prof_b, shift_px=d, start=u0, count=count)
        if np.any(ia <= 0) or np.any(ib <= 0):
            raise MeasurementError(
                "non-positive intensities in the overlap (dark or clipped images)"
            )
        raw = np.log(ib / ia)
        period = repeat_period_px(self.detrender(raw, start=u0))
        log_ratio = self.detrender(raw, start=u0, period_px=period)
        slope = slope_from_ratio(np.exp(log_ratio), **self._angles)
        if not np.all(np.isfinite(slope)):
            raise MeasurementError("slope is not finite (intensity ratio out of the lights' range)")
        height = self._heights(slope, cos_roll, period)
        cols = self._c0 + u0 + np.arange(count)
        x_mm = (self._cx + (cols - self._cx) * cos_roll) / self.px_per_mm
        marks = find_marks(x_mm, height, slope=slope, min_marks=self.min_marks)
        cal: Calibration | None = None
        kin_depth = raw_depth = math.nan
        if self.radius_mm is not None:
            dx_mm = cos_roll / self.px_per_mm
            model = kinematic_slope(x_mm, marks.cusps_mm, marks.bottoms_mm,
                                    radius_mm=self.radius_mm)
            cal = fit_calibration(slope, model, dx_mm=dx_mm, marks=len(marks.widths_mm))
            if calibrator is not None:
                cal = calibrator.update(cal)
            raw_depth = marks.depth_um
            if cal.trusted:
                slope_raw = slope
                for deblur in (True, False):  # the deconvolution may raise the noise too much
                    s_cal = apply_calibration(slope, cal, dx_mm=dx_mm, pitch_mm=marks.pitch_mm,
                                              deblur=deblur)
                    h_cal = self._heights(s_cal, cos_roll, period)
                    try:
                        # the marks are known to be there: a lower noise floor is safe, and
                        # the calibrated profile must show about as many
                        m_cal = find_marks(x_mm, h_cal, slope=s_cal, min_marks=self.min_marks,
                                           min_snr=2.0)
                    except MeasurementError:
                        continue
                    if abs(len(m_cal.widths_mm) - len(marks.widths_mm)) > max(
                            1, len(marks.widths_mm) // 10):
                        continue
                    slope, height, marks = s_cal, h_cal, m_cal
                    pays = cal.scatter_fraction > 0 and not np.array_equal(
                        s_cal, slope_raw / cal.gain)
                    cal = replace(cal, deblurred=bool(deblur and pays))
                    break
            kin_depth = float(np.mean(kinematic_depths_um(
                marks.cusps_mm, marks.bottoms_mm, radius_mm=self.radius_mm)))
        knife_widths = None
        if self.knives is not None:
            knife_widths = knife_means(marks.widths_mm, knives=self.knives, phase=0)
        return Measurement(
            x_mm=x_mm,
            height_um=height,
            slope=slope,
            pitch_mm=marks.pitch_mm,
            mark_widths_mm=marks.widths_mm,
            mark_depths_um=marks.depths_um,
            cusps_mm=marks.cusps_mm,
            bottoms_mm=marks.bottoms_mm,
            uniformity_cv=marks.uniformity_cv,
            depth_um=marks.depth_um,
            shift_px=d * cos_roll,
            encoder_shift_px=d_enc,
            confidence=reg.confidence,
            blur_px=blur,
            roll_deg=roll,
            roll_confidence=orient.confidence,
            calibration=cal,
            kinematic_depth_um=kin_depth,
            uncalibrated_depth_um=raw_depth,
            knife_widths_mm=knife_widths,
        )


def measure_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    *,
    rig: Rig,
    counts_a: int,
    counts_b: int,
    speed_mm_s: float | None = None,
    flat_field: tuple[np.ndarray, np.ndarray] | None = None,
) -> Measurement:
    """Measure one pair with a one-off :class:`Measurer` (see :meth:`Measurer.measure`)."""
    a = np.asarray(image_a)
    b = np.asarray(image_b)
    if a.shape != b.shape:
        raise ValueError(f"image_a and image_b differ in size: {a.shape} vs {b.shape}")
    check_image("image_a", a)
    measurer = Measurer(rig, a.shape, flat_field=flat_field)  # type: ignore[arg-type]
    return measurer.measure(a, b, counts_a=counts_a, counts_b=counts_b, speed_mm_s=speed_mm_s)
