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
from dataclasses import dataclass
from typing import Any

import numpy as np

from config.rig import Rig
from core.checks import check_image, check_int, check_positive
from core.errors import MeasurementError
from vision.deblur import Deblurrer, blur_length_px
from vision.illumination import Detrender, flat_field_correct
from vision.integrate import Integrator
from vision.marks import find_marks, repeat_period_px
from vision.profile import column_profile, overlap, shift_profile
from vision.registration import (
    Registrar,
    Registration,
    encoder_shift_px,
    shading_free_texture,
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
        texture_rows: int = 32,
        register: bool = True,
    ) -> None:
        self.rig = rig
        self.undistort = Undistorter(rig.camera, shape)
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
        self._texture_rows = np.unique(
            np.linspace(0, n_rows - 1, min(n_rows, texture_rows)).round().astype(int)
        )
        if detrend_degree is None:
            detrend_degree = 1 if flat_field is not None else 3
        self.detrender = Detrender(self.width, degree=detrend_degree)
        self.integrator = Integrator(self.width, dx_mm=1.0 / self.px_per_mm)
        self.deblurrer = Deblurrer(self.width, regularisation=regularisation)
        lights = rig.lights
        self._angles = {
            "slant_deg": lights.slant_deg,
            "azimuth_a_deg": lights.azimuth_a_deg,
            "azimuth_b_deg": lights.azimuth_b_deg,
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

    # -- the measurement ----------------------------------------------------------------------

    def measure(
        self,
        image_a: np.ndarray,
        image_b: np.ndarray,
        *,
        counts_a: int,
        counts_b: int,
        speed_mm_s: float | None = None,
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

        if self.register:
            tex_a = shading_free_texture(rows_a[self._texture_rows], prof_a)
            tex_b = shading_free_texture(rows_b[self._texture_rows], prof_b)
            reg = self.registrar(
                tex_a, tex_b, encoder_shift_px=d_enc, profile_a=prof_a, profile_b=prof_b
            )
        else:
            reg = Registration(shift_px=d_enc, confidence=math.nan, encoder_shift_px=d_enc)
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

        u0, u1 = overlap(self.width, d)
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
        height = self.integrator(slope)
        x_mm = (self._c0 + u0 + np.arange(count)) / self.px_per_mm
        marks = find_marks(x_mm, height, slope=slope, min_marks=self.min_marks)
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
            shift_px=d,
            encoder_shift_px=reg.encoder_shift_px,
            confidence=reg.confidence,
            blur_px=blur,
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
