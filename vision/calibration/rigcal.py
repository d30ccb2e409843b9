"""Rig calibration from a reference run: camera roll and the two lights' slants.

A reference run is a few image pairs of a planed board of known cutting radius R (a hardwood
board with little subsurface scattering, planed at a steady feed).  Each pair is measured with
the rig file as it stands, the self-calibration off:

- **Roll**: the median of the pairs' confident roll estimates (:mod:`vision.orientation`).
- **Slants**: between the cusps the true slope is the kinematic ``p = (x - b_k) / R``
  (:func:`vision.calibration.selfcal.kinematic_slope`).  With each light's intensity divided by
  its own
  ``cos(sigma)`` (the illumination correction removes such constants), Lambert gives
  ``log(I_B / I_A) = c + log(1 + p t_B) - log(1 - p t_A)
  = c + (t_A + t_B) p + (t_A^2 - t_B^2) p^2 / 2 + O(p^3)`` with ``t = tan(sigma)``.
  The measured log-ratio (recovered from the measured slope with the file's slants) is fitted
  against the kinematic ``p`` and ``p^2`` (one constant per pair, samples next to the cusps
  left out): ``a = t_A + t_B`` and ``b = (t_A^2 - t_B^2) / 2`` give ``t_A - t_B = 2 b / a``.
  The sum is fixed by the marks' contrast (well determined); the difference by the small
  curvature term (a fraction of a degree of spread per pair: use several pairs).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from config.rig import Rig
from core.checks import check_positive
from core.errors import MeasurementError
from vision.calibration.selfcal import kinematic_slope


@dataclass(frozen=True)
class RigEstimate:
    """Camera roll and light slants estimated from a reference run.

    Attributes
    ----------
    roll_deg : float
        Median roll of the pairs, degrees.
    roll_spread_deg : float
        Median absolute deviation of the pairs' rolls, degrees.
    slant_a_deg, slant_b_deg : float
        Slants of light A and light B, degrees.
    slant_sum_deg : float
        Slant giving the fitted mean ``(t_A + t_B) / 2`` (well determined even when the
        difference is not), degrees.
    pairs_used : int
        Pairs that gave marks.
    residual : float
        RMS residual of the log-ratio fit over the RMS log-ratio.
    """

    roll_deg: float
    roll_spread_deg: float
    slant_a_deg: float
    slant_b_deg: float
    slant_sum_deg: float
    pairs_used: int
    residual: float

    def apply(self, rig: Rig, *, width: int | None = None, height: int | None = None) -> Rig:
        """The rig with this estimate's roll and slants (and the image size) written in."""
        cam = replace(rig.camera, roll_deg=round(self.roll_deg, 4))
        if width is not None and height is not None:
            cam = replace(cam, width=int(width), height=int(height))
        lights = replace(rig.lights, slant_deg=round(self.slant_sum_deg, 4),
                         slant_a_deg=round(self.slant_a_deg, 4),
                         slant_b_deg=round(self.slant_b_deg, 4))
        return replace(rig, camera=cam, lights=lights)


def log_ratio_from_slope(slope: np.ndarray, *, slant_a_deg: float,
                         slant_b_deg: float) -> np.ndarray:
    """Invert :func:`vision.slope.slope_from_ratio` (opposed lights): ``log(I_B / I_A)``.

    Parameters
    ----------
    slope : ndarray, shape (n,)
        Slope measured with the given slants.
    slant_a_deg, slant_b_deg : float
        Slants the slope was computed with, degrees.

    Returns
    -------
    ndarray, shape (n,)
        ``log((1 + p t_B) / (1 - p t_A))``.
    """
    ta = math.tan(math.radians(slant_a_deg))
    tb = math.tan(math.radians(slant_b_deg))
    p = np.asarray(slope, dtype=np.float64)
    return np.log1p(p * tb) - np.log1p(-p * ta)


def fit_slants(log_ratios: Sequence[np.ndarray], slopes: Sequence[np.ndarray]
               ) -> tuple[float, float, float]:
    """Least-squares ``t_A``, ``t_B`` from log-ratios against kinematic slopes.

    Parameters
    ----------
    log_ratios : sequence of ndarray, each shape (n_i,)
        Measured ``log(I_B / I_A)`` per pair (finite samples only are used).
    slopes : sequence of ndarray, each shape (n_i,)
        Kinematic slopes of the same samples (NaN: left out).

    Returns
    -------
    t_a, t_b : float
        Tangents of the two slants.
    residual : float
        RMS residual over the RMS of the fitted log-ratio (after the constants).
    """
    cols: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    n_pairs = len(log_ratios)
    for i, (lr, p) in enumerate(zip(log_ratios, slopes, strict=True)):
        ok = np.isfinite(lr) & np.isfinite(p)
        if np.count_nonzero(ok) < 8:
            continue
        q = p[ok]
        block = np.zeros((q.size, 2 + n_pairs))
        block[:, 0] = q
        block[:, 1] = q * q
        block[:, 2 + i] = 1.0
        cols.append(block)
        ys.append(lr[ok])
    if not cols:
        raise MeasurementError("no pair of the reference run gave usable marks")
    design = np.concatenate(cols)
    y = np.concatenate(ys)
    keep = np.any(design[:, 2:] != 0, axis=0)
    design = np.concatenate([design[:, :2], design[:, 2:][:, keep]], axis=1)
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    a, b = float(coef[0]), float(coef[1])
    if not a > 0:
        raise MeasurementError("the reference run's marks have no usable contrast")
    resid = y - design @ coef
    centred = y - design[:, 2:] @ coef[2:]
    rel = float(np.sqrt(np.mean(resid**2)) / max(np.sqrt(np.mean(centred**2)), 1e-300))
    diff = 2.0 * b / a
    return 0.5 * (a + diff), 0.5 * (a - diff), rel


def estimate_rig(
    pairs: Sequence[tuple[np.ndarray, np.ndarray, int, int]],
    rig: Rig,
    *,
    radius_mm: float,
    speed_mm_s: float | None = None,
    guard_px: float = 2.5,
    min_roll_confidence: float = 0.5,
) -> RigEstimate:
    """Roll and slants from the pairs of a reference run.

    Parameters
    ----------
    pairs : sequence of (image_a, image_b, counts_a, counts_b)
        The reference run's pairs (one image shape).
    rig : config.rig.Rig
        The rig file as it stands (its slants are the starting point).
    radius_mm : float
        Cutting radius, mm.
    speed_mm_s : float, optional
        Feed speed, mm/s (motion deblurring).
    guard_px : float, optional
        Samples this close to a cusp are left out of the slant fit, pixels.
    min_roll_confidence : float, optional
        Pairs with a less confident roll do not vote for it.

    Returns
    -------
    RigEstimate

    Raises
    ------
    MeasurementError
        No pair could be measured.
    """
    from vision.pipeline import Measurer  # the pipeline imports this package's neighbours

    r = check_positive("radius_mm", radius_mm)
    if not pairs:
        raise ValueError("pairs must hold at least one image pair")
    shape = np.asarray(pairs[0][0]).shape
    measurer = Measurer(rig, shape)  # type: ignore[arg-type]
    slant_a, slant_b = rig.lights.slants_deg
    rolls: list[float] = []
    ratios: list[np.ndarray] = []
    kin: list[np.ndarray] = []
    errors: list[str] = []
    for k, (a, b, ca, cb) in enumerate(pairs):
        try:
            m = measurer.measure(a, b, counts_a=ca, counts_b=cb, speed_mm_s=speed_mm_s)
        except (MeasurementError, ValueError) as exc:
            errors.append(f"pair {k + 1}: {exc}")
            continue
        if m.roll_confidence >= min_roll_confidence:
            rolls.append(m.roll_deg)
        p_kin = kinematic_slope(m.x_mm, m.cusps_mm, m.bottoms_mm, radius_mm=r)
        dx = float(m.x_mm[1] - m.x_mm[0])
        near = np.min(np.abs(m.x_mm[:, None] - m.cusps_mm[None, :]), axis=1) < guard_px * dx
        p_kin[near] = np.nan
        ratios.append(log_ratio_from_slope(m.slope, slant_a_deg=slant_a, slant_b_deg=slant_b))
        kin.append(p_kin)
    if not ratios:
        raise MeasurementError("no pair of the reference run could be measured: "
                               + "; ".join(errors[:3]))
    ta, tb, resid = fit_slants(ratios, kin)
    if not (ta > 0 and tb > 0):
        raise MeasurementError(
            f"the reference run gives implausible slants (tan {ta:.2f}, {tb:.2f}): "
            "use more pairs or a board with less subsurface scattering"
        )
    roll = float(np.median(rolls)) if rolls else rig.camera.roll_deg
    spread = float(np.median(np.abs(np.asarray(rolls) - roll))) if rolls else math.nan
    mean_deg = math.degrees(math.atan(0.5 * (ta + tb)))
    return RigEstimate(
        roll_deg=roll, roll_spread_deg=spread, slant_a_deg=math.degrees(math.atan(ta)),
        slant_b_deg=math.degrees(math.atan(tb)), slant_sum_deg=mean_deg,
        pairs_used=len(ratios), residual=resid,
    )
