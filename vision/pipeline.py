"""The whole measurement of one image pair: images in, profile and cuttermark metrics out.

Steps (all set-up done once per rig and image shape in :class:`Measurer`):

1. bin both images' rows once, estimate the marks' direction from a few row groups, and
   resample only what is needed -- the profile's bins undistorted and sheared along the marks,
   the texture rows undistorted (rotated to the feed), each in one remap
   (:mod:`vision.front_end`, :mod:`vision.orientation`);
2. column profiles (:mod:`vision.profile`) and shading-free textures (made on demand);
3. registration: encoder shift (seed Eq. 5-6), refined from the images -- coarse on the albedo
   (2-D texture, or the 1-D column profiles), fine on the column profiles
   (:mod:`vision.registration.registrar`);
4. optional flat-field correction of each profile in the camera frame, then Wiener deblurring along
   the feed when the motion blur is sizeable (:mod:`vision.deblur`);
5. B resampled onto A's columns over the overlap; log-ratio detrended against LED imbalance and
   fall-off (:mod:`vision.calibration.illumination`); slope by seed Eq. 4 (:mod:`vision.slope`);
6. frequency-domain integration to height in micrometres (:mod:`vision.integrate`);
7. cusps, widths, depths, pitch, uniformity (:mod:`vision.marks`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.fft

from config.rig import Rig
from core.checks import check_image, check_int, check_positive, check_range
from core.errors import MeasurementError, RegistrationError
from vision import ffts, kernels
from vision.calibration.illumination import Detrender, flat_field_correct, running_mean
from vision.calibration.selfcal import (
    Calibration,
    SelfCalibrator,
    apply_calibration,
    deblurs,
    fit_calibration,
    kinematic_depths_um,
    kinematic_slope,
)
from vision.deblur import Deblurrer, blur_length_px
from vision.defects.detect import Defect, DefectFinder
from vision.defects.grading import pair_grade
from vision.defects.refused import attach, refused_pair
from vision.front_end import Binned, FrontEnd, mean_profile
from vision.integrate import Integrator
from vision.marks import (
    Marks,
    find_marks,
    knife_means,
    repeat_period_px,
)
from vision.orientation import Orientation, RollEstimator
from vision.profile import overlap, shift_profile
from vision.registration.checks import checked
from vision.registration.consistency import (
    RegisteredProfile,
    honest_confidence,
    marks_shading_agreement,
)
from vision.registration.defect_rows import (
    clean_columns,
    masked_pair,
    row_checks,
    weighted_profile,
)
from vision.registration.encoder_fallback import encoder_registration
from vision.registration.registrar import Registrar, Registration, encoder_shift_px
from vision.slope import RatioSlope


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
    calibration : vision.calibration.selfcal.Calibration or None
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
    flag_reason : str or None
        Why the measurement's own checks disagree (``None``: they agree); a flagged measurement
        reports a ``confidence`` of at most the measurer's ``flagged_confidence`` (0.3).
    marks_agreement : float
        How well the marks found explain each image's own column profile
        (:func:`vision.registration.consistency.marks_shading_agreement`, the worse of A and B;
        0.76-0.92 on
        good pairs, <= 0.68 on misregistered ones).
    registration_source : str
        The coarse registration used: ``"texture"``, ``"profile"``, ``"shading"`` (or
        ``"encoder"`` when not registered).
    defects : tuple of vision.defects.detect.Defect, or None
        Planing defects found on the pair's 2-D surface map (``None``: not looked for, the
        measurer's ``defects=False``).
    grade, grade_reason : int or None, str or None
        ASTM D1666 grade of the pair (1 defect-free ... 5 very poor, :mod:`vision.defects.grading`)
        and why (``None`` when the defects were not looked for); snipe is left to the board
        (:func:`vision.defects.grading.pair_grade`: ``defects`` keep the raw bend).
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
    flag_reason: str | None = None
    marks_agreement: float = math.nan
    registration_source: str = "texture"
    defects: tuple[Defect, ...] | None = None
    grade: int | None = None
    grade_reason: str | None = None

    @property
    def flagged(self) -> bool:
        """Whether one of the measurement's own checks failed (``flag_reason`` says which)."""
        return self.flag_reason is not None

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
            "flag_reason": self.flag_reason,
            "marks_agreement": _finite_or_none(self.marks_agreement, 3),
            "registration_source": self.registration_source,
            "defects": (None if self.defects is None else [d.to_json() for d in self.defects]),
            "grade": self.grade,
            "grade_reason": self.grade_reason,
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
    # h less slow at m0 .., less slow[0] before and slow[-1] after: one compiled pass
    out = np.empty(n)
    kernels.less_running(np.ascontiguousarray(h), slow, m0, out)
    out -= out.sum() / n
    return out


def revolution_px(slope: np.ndarray, period_px: float, knives: int | None) -> float:
    """The window of :func:`remove_slow`: one cutterhead revolution, samples.

    The repeat period (:func:`vision.marks.repeat_period_px`) is one pitch when the knives'
    runout pattern is weak; a running mean over one pitch then follows the knife-to-knife
    height differences and removes them (a true CV of 0.005-0.012 measured as half of it).
    With ``knives`` known, the repeat period of ``k`` pitches (``k`` from the slope's dominant
    period, the pitch) is widened to ``knives`` pitches when ``k`` divides ``knives`` and the
    profile holds two of them; else (and without ``knives``) the repeat period as it is.
    """
    if knives is None or not math.isfinite(period_px) or period_px <= 0:
        return period_px
    pitch = _pitch_px(slope)
    if not math.isfinite(pitch) or pitch <= 0:
        return period_px
    k = max(1, round(period_px / pitch))
    window = period_px * (int(knives) // k)
    return window if int(knives) % k == 0 and window <= slope.size / 2 else period_px


_PITCH_WINDOWS: dict[int, np.ndarray] = {}


def _pitch_px(slope: np.ndarray) -> float:
    """The slope's dominant period at its periodogram's own resolution, samples (NaN: none).

    :func:`vision.marks.dominant_period_px` (Hann window, parabolic peak, at least two periods
    of at least 4 samples) without its 4x zero-padding, a quarter of the FFT: the window of
    :func:`revolution_px` needs only the whole number of pitches in the repeat period, which
    the peak's fraction of a bin does not move.
    """
    s = np.asarray(slope, dtype=np.float64)
    n = s.size
    if n < 8:
        return math.nan
    window = _PITCH_WINDOWS.get(n)
    if window is None:
        if len(_PITCH_WINDOWS) > 64:
            _PITCH_WINDOWS.clear()
        window = _PITCH_WINDOWS[n] = np.hanning(n)
    nfft = scipy.fft.next_fast_len(n, real=True)
    spec = ffts.rfft((s - s.sum() / n) * window, nfft)
    k_lo = max(1, int(math.ceil(2.0 * nfft / n)))
    k_hi = min(spec.size - 2, int(nfft / 4.0))
    if k_hi <= k_lo:
        return math.nan
    return nfft / kernels.spectrum_peak(spec, k_lo, k_hi)


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
    texture_width_px : int, optional
        Images at least twice this wide register their texture on windows this many columns
        wide (A's centred, B's ``round(encoder shift)`` columns further, so the windows hold
        the same wood; at 1920 px a third of the cost); the fine fit still uses the whole
        profiles.  0: always the whole width.
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
        (:mod:`vision.calibration.selfcal`) and gives the kinematic depth.
    knives : int, optional
        Number of knives: per-knife mean widths (relative phase).
    min_agreement : float, optional
        The marks found must explain each image's own column profile at least this well
        (:func:`vision.registration.consistency.marks_shading_agreement`); below it the pair is
        registered
        once more without its texture (the column profiles alone), and when that does not
        explain the images either, the measurement is flagged.
    max_slip_px : float, optional
        Largest difference between the registered and the encoder's shift the belt allows,
        pixels (default ``search_px``); beyond it the measurement is flagged.
    flagged_confidence : float, optional
        The most confidence a flagged measurement reports.
    remove_slow : bool, optional
        Subtract from the height its running mean over one cutterhead revolution (the marks'
        repeat period, which the mean annihilates): what varies more slowly is the integrated
        low-frequency noise and residual illumination, not measurable anyway (see
        :func:`remove_slow`).
    defects : bool, optional
        Also map the pair's along-feed slope and albedo in 2-D and find planing defects on it
        with their D1666 grade (:mod:`vision.defects.detect`, :mod:`vision.defects.grading`;
        ``Measurement.defects``, ``grade``); off by default (it costs CPU).
    encoder_fallback : bool, optional
        When the images do not register the pair (the albedo drowned in read noise), measure
        at the encoder's shift if the marks found there explain both images and no other
        shift within the slip bound explains them about as well
        (:mod:`vision.registration.encoder_fallback`; ``registration_source == "encoder"``,
        confidence at
        most 0.5).  Off by default: the marks cannot tell two boards whose marks happen to
        line up from one board, so it is for pairs known to show one board (the service's
        hardware-triggered pairs, 2 ms apart).
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
        texture_width_px: int = 640,
        register: bool = True,
        max_roll_deg: float = 5.0,
        roll_smear_px: float = 0.5,
        min_roll_confidence: float = 0.3,
        radius_mm: float | None = None,
        knives: int | None = None,
        remove_slow: bool = True,
        min_agreement: float = 0.7,
        max_slip_px: float | None = None,
        flagged_confidence: float = 0.3,
        defects: bool = False,
        encoder_fallback: bool = False,
    ) -> None:
        self.rig = rig
        self.encoder_fallback = bool(encoder_fallback)
        check_rig_size(rig, shape)
        self.max_roll_deg = check_positive("max_roll_deg", max_roll_deg, allow_zero=True)
        self.min_roll_confidence = float(min_roll_confidence)
        self.radius_mm = None if radius_mm is None else check_positive("radius_mm", radius_mm)
        self.knives = None if knives is None else check_int("knives", knives, lo=1)
        self.remove_slow = bool(remove_slow)
        self.min_agreement = check_range("min_agreement", min_agreement, -1.0, 1.0)
        self.flagged_confidence = check_range("flagged_confidence", flagged_confidence, 0.0, 1.0)
        self.max_slip_px = float(search_px) if max_slip_px is None else check_positive(
            "max_slip_px", max_slip_px, allow_zero=True)
        self.front = FrontEnd(rig.camera, shape, max_roll_deg=self.max_roll_deg,
                              roll_smear_px=check_positive("roll_smear_px", roll_smear_px),
                              texture_rows=texture_rows)
        self.undistort = self.front.undistort
        self.shape = self.front.shape
        c0, _ = self.front.columns
        self._c0 = c0
        self.width = self.front.width
        self.px_per_mm = rig.camera.px_per_mm
        self.min_marks = check_int("min_marks", min_marks, lo=1)
        self.register = bool(register)
        if not 0.0 < min_overlap < 1.0:
            raise ValueError(f"min_overlap must be in (0, 1), got {min_overlap!r}")
        self.min_overlap_px = max(32, int(round(min_overlap * self.width)))
        self.deblur_min_px = check_positive("deblur_min_px", deblur_min_px, allow_zero=True)
        self.texture_width_px = check_int("texture_width_px", texture_width_px, lo=0)
        self.registrar = Registrar(
            self.width, search_px=search_px, min_overlap_px=min(self.min_overlap_px, self.width - 1)
        )
        row_v = self.front.row_v_px
        self._cx = rig.camera.cx
        step = self.front.group_step  # the groups come every step-th column: scale to them
        self.roll_estimator = (
            RollEstimator(row_v / step, self.width // step, cy=rig.camera.cy / step,
                          centre_deg=rig.camera.roll_deg, max_roll_deg=self.max_roll_deg,
                          highpass_px=int(round(41 / step)), max_frequency=0.25 * step)
            if self.max_roll_deg > 0 and row_v.size >= 2 else None
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
        self._slope = RatioSlope(**self._angles)  # validates the light geometry once
        self.defect_finder = (DefectFinder(
            rig.camera, rig.lights, self.shape, bin_rows=self.front.k0,
            first_row_px=self.front.undistort.first_row_px, columns=self.front.columns,
            source_rows=self.front.undistort.bins, knives=self.knives) if defects else None)
        self._flat: tuple[np.ndarray, np.ndarray] | None = None
        if flat_field is not None:
            if len(flat_field) != 2:
                raise ValueError("flat_field must be a pair of images (A, B)")
            ref_a = self.front.profile(self._binned(flat_field[0], "flat_a"), 0.0)
            ref_b = self.front.profile(self._binned(flat_field[1], "flat_b"), 0.0)
            if np.any(ref_a <= 0) or np.any(ref_b <= 0):
                raise MeasurementError("flat-field images have dark columns")
            self._flat = (ref_a, ref_b)

    # -- pieces -------------------------------------------------------------------------------

    def _binned(self, image: np.ndarray, name: str) -> Binned:
        binned = self.front.bin(image, name)
        if binned.level < 0.01:
            raise MeasurementError(
                f"{name} is black (mean level {100 * binned.level:.2f} % of full scale)"
            )
        if binned.saturated:
            raise MeasurementError(f"{name} is saturated (most pixels at full scale)")
        return binned

    def _texture_windows(self, shift_px: float) -> tuple[slice | None, slice | None, int]:
        """Texture columns of A and B and B's offset (``None, None, 0``: the whole width).

        Windows ``texture_width_px`` wide, A's as central as the shift allows, B's
        ``round(shift_px)`` columns further: the same wood in both, the residual shift small.
        """
        tw, w = self.texture_width_px, self.width
        s = int(round(shift_px))
        reg = self.registrar
        lags = 2 * (math.ceil(reg.search_px + reg.margin_px) + 1)
        if not 0 < 2 * tw <= w or abs(s) > w - tw or tw - lags < reg.min_overlap_px:
            return None, None, 0
        lo, hi = max(0, -s), min(w - tw, w - tw - s)
        ca = min(hi, max(lo, (w - tw - s) // 2))
        return slice(ca, ca + tw), slice(ca + s, ca + s + tw), s

    def blur_px(self, speed_mm_s: float | None) -> float:
        """Motion blur length for a feed speed (0 when the speed or exposure is unknown)."""
        exposure = self.rig.camera.exposure_ms
        if speed_mm_s is None or exposure is None:
            return 0.0
        return blur_length_px(abs(speed_mm_s), exposure_ms=exposure, px_per_mm=self.px_per_mm)

    def _heights(self, slope: np.ndarray, cos_roll: float, period_px: float) -> np.ndarray:
        height = self.integrator(slope) * cos_roll
        if not self.remove_slow:
            return height
        return remove_slow(height, revolution_px(slope, period_px, self.knives))

    def orientation(self, binned_a: Binned, binned_b: Binned) -> Orientation:
        """Direction of the marks from both images' row groups (the rig's roll when off)."""
        if self.roll_estimator is None:
            return Orientation(self.rig.camera.roll_deg, math.nan)
        return self.roll_estimator.estimate(self.front.group_means(binned_a, binned_b))

    def _self_calibrated(
        self, slope: np.ndarray, height: np.ndarray, marks: Marks, x_mm: np.ndarray,
        cos_roll: float, period: float, calibrator: SelfCalibrator | None,
    ) -> tuple[Calibration, np.ndarray, np.ndarray, Marks, float]:
        """The self-calibration from the kinematics and the profile it calibrates.

        Returns the calibration (smoothed by ``calibrator`` when given), the slope, height and
        marks (calibrated when the calibration is trusted) and the uncalibrated depth, um.
        """
        assert self.radius_mm is not None
        dx_mm = cos_roll / self.px_per_mm
        model = kinematic_slope(x_mm, marks.cusps_mm, marks.bottoms_mm, radius_mm=self.radius_mm)
        cal = fit_calibration(slope, model, dx_mm=dx_mm, marks=len(marks.widths_mm))
        if calibrator is not None:
            cal = calibrator.update(cal)
        raw_depth = marks.depth_um
        if not cal.trusted:
            return cal, slope, height, marks, raw_depth
        if not deblurs(cal, pitch_mm=marks.pitch_mm):
            # The gain alone: integration, slow-part removal and the marks' depths are linear
            # in the slope and the cusps do not move, so all of it scales.
            marks = replace(marks, depths_um=marks.depths_um / cal.gain,
                            cusp_heights_um=marks.cusp_heights_um / cal.gain,
                            depth_um=marks.depth_um / cal.gain)
            return (replace(cal, deblurred=False), slope / cal.gain, height / cal.gain, marks,
                    raw_depth)
        slope_raw = slope
        for deblur in (True, False):  # the deconvolution may raise the noise too much
            s_cal = apply_calibration(slope, cal, dx_mm=dx_mm, pitch_mm=marks.pitch_mm,
                                      deblur=deblur)
            h_cal = self._heights(s_cal, cos_roll, period)
            try:
                # the marks are known to be there: a lower noise floor is safe, and the
                # calibrated profile must show about as many or more (the deconvolution
                # resolves narrow marks the blur merged: a knife 0.4 mm wide beside a vanished
                # one at 0.5 mm pitch, 12.5 px/mm)
                m_cal = find_marks(x_mm, h_cal, slope=s_cal, min_marks=self.min_marks,
                                   min_snr=2.0)
            except MeasurementError:
                continue
            if len(marks.widths_mm) - len(m_cal.widths_mm) > max(
                    1, len(marks.widths_mm) // 10):
                continue
            pays = deblur and cal.scatter_fraction > 0 and not np.array_equal(
                s_cal, slope_raw / cal.gain)
            return replace(cal, deblurred=bool(pays)), s_cal, h_cal, m_cal, raw_depth
        return cal, slope, height, marks, raw_depth

    def _registered_profile(self, prof_a: np.ndarray, prof_b: np.ndarray, registered: bool,
                            columns: tuple[int, int] | None, d: float, margin: int,
                            cos_roll: float, *, slow_removed: bool = True) -> RegisteredProfile:
        """Slope, height and marks of the pair registered at ``d`` px, and their agreement.

        ``registered``: ``prof_b`` is already B at ``u + d`` in A's columns; ``columns``: only
        A's columns ``c0 .. c1 - 1`` of the overlap are used (``None``: all of it).
        """
        u0, u1 = overlap(self.width, d, columns=(margin, self.width - margin))
        if columns is not None:
            u0, u1 = max(u0, columns[0]), min(u1, columns[1])
        count = u1 - u0
        if count < self.min_overlap_px:
            raise MeasurementError(
                f"registered shift {d:.1f} px leaves only {max(count, 0)} px of overlap"
            )
        ia = prof_a[u0:u1]
        ib = (prof_b[u0:u1] if registered else
              shift_profile(prof_b, shift_px=d, start=u0, count=count))
        if kernels.any_nonpositive(np.ascontiguousarray(ia, dtype=np.float64),
                                   np.ascontiguousarray(ib, dtype=np.float64)):
            raise MeasurementError(
                "non-positive intensities in the overlap (dark or clipped images)"
            )
        log_a, log_b = np.log(ia), np.log(ib)
        raw = log_b - log_a
        period = repeat_period_px(self.detrender(raw, start=u0))
        log_ratio = self.detrender(raw, start=u0, period_px=period)
        slope, finite = self._slope.finite(np.exp(log_ratio))
        if not finite:
            raise MeasurementError("slope is not finite (intensity ratio out of the lights' range)")
        height = self._heights(slope, cos_roll, period)
        # (cx + (cols - cx) cos_roll) / px_per_mm of the columns c0 + u0 ..., one compiled pass
        x_mm = np.empty(count)
        kernels.feed_positions(int(self._c0 + u0), float(self._cx), float(cos_roll),
                               float(self.px_per_mm), x_mm)
        marks = find_marks(x_mm, height, slope=slope, min_marks=self.min_marks)
        agreement = marks_shading_agreement(log_a, log_b, x_mm, marks.cusps_mm, marks.bottoms_mm,
                                            slow_removed=slow_removed)
        return RegisteredProfile(slope, height, marks, x_mm, period, agreement)

    def _register(self, binned_a: Binned, binned_b: Binned, roll: float, prof_a: np.ndarray,
                  prof_b: np.ndarray, d_enc: float) -> Registration:
        """The registrar on the pair: texture rows along the feed, profiles along the marks."""
        cols_a, cols_b, offset = self._texture_windows(d_enc)
        whole = (self.front.texture(binned_a, roll, prof_a),
                 self.front.texture(binned_b, roll, prof_b))  # resampled only if used
        if cols_a is None:
            return self.registrar(*whole, encoder_shift_px=d_enc, profile_a=prof_a,
                                  profile_b=prof_b)
        return self.registrar(
            self.front.texture(binned_a, roll, prof_a, columns=cols_a),
            self.front.texture(binned_b, roll, prof_b, columns=cols_b),
            encoder_shift_px=d_enc, profile_a=prof_a, profile_b=prof_b,
            texture_offset_px=offset, whole_textures=whole,
        )

    # -- the measurement ----------------------------------------------------------------------

    def measure(self, image_a: np.ndarray, image_b: np.ndarray, *, counts_a: int,
                counts_b: int, speed_mm_s: float | None = None,
                calibrator: SelfCalibrator | None = None) -> Measurement:
        """Measure one pair (:meth:`measured`: parameters, result, refusals).

        With ``defects=True`` a refusal carries the pair's defects all the same, found at the
        encoder's shift refined on the map (:func:`vision.defects.refused.surface_of`).
        """
        try:
            return self.measured(image_a, image_b, counts_a=counts_a, counts_b=counts_b,
                                 speed_mm_s=speed_mm_s, calibrator=calibrator)
        except MeasurementError as exc:
            surface = refused_pair(self, image_a, image_b, counts_a=counts_a,
                                   counts_b=counts_b) if self.defect_finder else None
            if surface is not None:
                attach(exc, surface)
            raise

    def measured(
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
        calibrator : vision.calibration.selfcal.SelfCalibrator, optional
            The board's calibrator (kept by the caller per board): this pair's estimate is
            folded in and the smoothed calibration applied (without ``radius_mm``, not); and
            the board's roll, searched for only every ``calibrator.roll_every`` pairs, the last
            confident estimate used in between.  Without it, this pair's own estimates.

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
        binned_a = self._binned(a, "image_a")
        binned_b = self._binned(b, "image_b")

        orient, roll = _orient(self, binned_a, binned_b, calibrator)
        cos_roll = math.cos(math.radians(roll))
        margin = self.front.margin_px(roll)
        rows_a, factor = self.front.profile_rows(binned_a, roll)
        rows_b, _ = self.front.profile_rows(binned_b, roll)
        prof_a, prof_b = mean_profile(rows_a, factor), mean_profile(rows_b, factor)
        d_enc_sheared = d_enc / cos_roll

        raw_profiles = (prof_a, prof_b)  # as registered: the second opinion sees the same
        reg = Registration(shift_px=d_enc_sheared, confidence=math.nan,
                           encoder_shift_px=d_enc_sheared, source="encoder")
        unregistered: RegistrationError | None = None
        if self.register:
            try:
                reg = self._register(binned_a, binned_b, roll, prof_a, prof_b, d_enc_sheared)
            except RegistrationError as exc:  # the encoder's shift, if the marks confirm it
                if not self.encoder_fallback:
                    raise
                unregistered = exc
        blur = self.blur_px(speed_mm_s)
        if not blur > self.deblur_min_px:
            blur = 0.0

        prepared = functools.partial(_prepared, self, rows=(rows_a, rows_b),
                                     profiles=(prof_a, prof_b), factor=factor, margin=margin,
                                     blur=blur)

        if unregistered is not None:
            reg, profile = encoder_registration(self, prepared, d_enc_sheared, margin, cos_roll,
                                                unregistered)
        else:
            profile = self._registered_profile(*prepared(reg.shift_px), reg.shift_px, margin,
                                               cos_roll)
        reg, profile, reason = checked(self, raw_profiles, prepared, reg, profile,
                                       margin, cos_roll)
        confidence, reason = honest_confidence(
            reg.confidence, [reason] if reason else [],
            flagged_confidence=self.flagged_confidence)
        return _result(self, profile, reg, confidence=confidence, reason=reason, d_enc=d_enc,
                            blur=blur, roll=roll, orient=orient, cos_roll=cos_roll,
                            calibrator=calibrator, binned=(binned_a, binned_b))


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


def _orient(m: Measurer, binned_a: Any, binned_b: Any,
            calibrator: Any) -> tuple[Orientation, float]:
    """The marks' orientation (the board's, once known) and the roll the pair is read at."""
    known = None
    if calibrator is not None and m.roll_estimator is not None:
        known = calibrator.known_roll()  # the board's roll, searched for a few pairs ago
    if known is not None:
        orient = Orientation(*known)
    else:
        orient = m.orientation(binned_a, binned_b)
        if calibrator is not None and m.roll_estimator is not None:
            calibrator.note_roll(orient.roll_deg, orient.confidence,
                                 min_confidence=m.min_roll_confidence)
    roll = orient.roll_deg if orient.confidence >= m.min_roll_confidence else (
        m.rig.camera.roll_deg)
    return orient, roll


def _prepared(m: Measurer, d: float, *, rows: tuple[np.ndarray, np.ndarray],
              profiles: tuple[np.ndarray, np.ndarray], factor: Any, margin: int,
              blur: float) -> tuple[np.ndarray, np.ndarray, bool, tuple[int, int] | None]:
    """The profiles at shift ``d`` and the columns to use.

    A defect's rows left out (B then registered onto A), its columns too when it covers
    most of their rows; the bins' ends tapered when they disagree (raised grain).
    """
    rows_a, rows_b = rows
    pa, pb = profiles
    registered, columns = False, None
    mask = weights = None
    if m.register:
        mask, weights = row_checks(m.width, rows_a, rows_b, d, margin)
    if weights is not None and mask is None:  # the bins' ends tapered (raised grain)
        pa, pb = (weighted_profile(rows_a, factor, weights),
                  weighted_profile(rows_b, factor, weights))
    if mask is not None:
        columns = clean_columns(mask, min_width=m.min_overlap_px)
        ra, rb = rows_a, rows_b
        if m._flat is not None:  # the references in the camera's columns
            ones = np.ones(m.width)
            fa, fb = flat_field_correct(ones, ones, reference_a=m._flat[0],
                                        reference_b=m._flat[1])
            ra, rb = ra * fa[None, :], rb * fb[None, :]
        pa, pb = masked_pair(ra, rb, factor, mask, weights=weights)
        registered = True
    elif m._flat is not None:
        pa, pb = flat_field_correct(pa, pb, reference_a=m._flat[0],
                                    reference_b=m._flat[1])
    if blur > 0:
        both = m.deblurrer(np.stack([pa, pb]), blur_px=blur)
        pa, pb = both[0], both[1]
    return pa, pb, registered, columns


def _result(m: Measurer, profile: Any, reg: Any, *, confidence: float, reason: str | None,
            d_enc: float, blur: float, roll: float, orient: Orientation, cos_roll: float,
            calibrator: Any, binned: tuple[Any, Any]) -> Measurement:
    """The measurement of a registered profile: self-calibrated, per knife, its defects."""
    binned_a, binned_b = binned
    slope, height, marks, x_mm, period = (profile.slope, profile.height, profile.marks,
                                          profile.x_mm, profile.period)
    d = reg.shift_px
    cal: Calibration | None = None
    kin_depth = raw_depth = math.nan
    if m.radius_mm is not None:
        cal, slope, height, marks, raw_depth = m._self_calibrated(
            slope, height, marks, x_mm, cos_roll, period, calibrator)
        kin = kinematic_depths_um(marks.cusps_mm, marks.bottoms_mm, radius_mm=m.radius_mm)
        kin_depth = float(kin.sum() / kin.size)  # np.mean's operations, without its overhead
    knife_widths = None
    if m.knives is not None:
        knife_widths = knife_means(marks.widths_mm, knives=m.knives, phase=0)
    found = grade = None
    if m.defect_finder is not None:
        found = m.defect_finder(binned_a.bins, binned_b.bins, shift_px=d * cos_roll,
                                   roll_deg=roll, bottoms_mm=marks.bottoms_mm,
                                   pitch_mm=marks.pitch_mm, encoder_shift_px=d_enc)
        grade = pair_grade(found)
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
        confidence=confidence,
        blur_px=blur,
        roll_deg=roll,
        roll_confidence=orient.confidence,
        calibration=cal,
        kinematic_depth_um=kin_depth,
        uncalibrated_depth_um=raw_depth,
        knife_widths_mm=knife_widths,
        flag_reason=reason,
        marks_agreement=profile.agreement.score,
        registration_source=reg.source,
        defects=found,
        grade=None if grade is None else grade.grade,
        grade_reason=None if grade is None else grade.reason,
    )
