"""The measurement's own checks, and the confidence they leave it.

A pair can go wrong without any single step noticing: a defect whose shading depends on the
light (a pit lit from the left is not a pit lit from the right) can pull the texture
registration onto a wrong shift at high confidence, after which the slope shows *half-marks*
and the pitch comes out halved.  The checks here compare what independent parts of the
measurement say; a measurement whose checks disagree is never reported at high confidence.

- **Marks against each image** (:func:`marks_shading_agreement`).  Inside a knife mark the slope
  grows linearly, ``p = (x - b_k) / R``, and resets at every cusp; each image's log-intensity
  follows it with the light's sign (``log I_A ~ -tan(sigma) p``, ``log I_B ~ +tan(sigma) p``).
  The marks found from the registered pair therefore predict each image's own column profile up
  to a scale: A's alone (registration-free: are these the marks the camera sees?) and B's as
  registered (is B where the registration put it?).  Half-marks from a misregistered pair
  explain about a quarter of the sawtooth; true marks most of it.
- **Shift against the encoder** (:func:`shift_within_slip`): the registered shift may differ
  from the encoder's by at most the slip the belt is known to allow.
- **Two shift estimates** (:func:`shifts_agree`): when the registration had two coarse
  estimates, they must agree.

:func:`honest_confidence` folds the checks into the confidence reported and names the first
that failed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from core.checks import check_finite, check_positive, check_range
from vision import check_kernels, kernels

if TYPE_CHECKING:  # types only: marks and registrar do not import this module
    from vision.marks import Marks
    from vision.registration.registrar import Registrar


@dataclass(frozen=True)
class Agreement:
    """How well the marks found explain each image's own column profile.

    Attributes
    ----------
    score_a, score_b : float
        Correlation in [-1, 1] of A's (with sign -1) and registered B's (sign +1) log-profile
        with the marks' kinematic slope, a cubic removed from both (NaN: too few samples).
    """

    score_a: float
    score_b: float

    @property
    def score(self) -> float:
        """The worse of the two (NaN when either is)."""
        if not (math.isfinite(self.score_a) and math.isfinite(self.score_b)):
            return math.nan
        return min(self.score_a, self.score_b)


@dataclass(frozen=True)
class RegisteredProfile:
    """The pair registered at one shift: slope, height, marks and the marks' agreement."""

    slope: np.ndarray
    height: np.ndarray
    marks: Marks
    x_mm: np.ndarray
    period: float
    agreement: Agreement


class ShiftChecker(Protocol):
    """What the measurement's checks need of the measurer (:class:`vision.pipeline.Measurer`)."""

    registrar: Registrar
    register: bool
    min_agreement: float
    max_slip_px: float

    def _registered_profile(self, prof_a: np.ndarray, prof_b: np.ndarray, registered: bool,
                            columns: tuple[int, int] | None, d: float, margin: int,
                            cos_roll: float, *, slow_removed: bool = True
                            ) -> RegisteredProfile: ...


def marks_shading_agreement(
    log_a: np.ndarray,
    log_b: np.ndarray,
    x_mm: np.ndarray,
    cusps_mm: np.ndarray,
    bottoms_mm: np.ndarray,
    *,
    max_samples: int = 700,
    slow_removed: bool = True,
) -> Agreement:
    """Correlation of each image's log-profile with the slope the found marks predict.

    Parameters
    ----------
    log_a, log_b : ndarray, shape (n,)
        Log column profiles of A and of B resampled onto A's columns (registered), over the
        samples ``x_mm``.
    x_mm : ndarray, shape (n,)
        Positions of the samples, mm (increasing).
    cusps_mm : ndarray, shape (m + 1,)
        Cusps bounding the ``m >= 1`` complete marks found, mm.
    bottoms_mm : ndarray, shape (m,)
        Lowest point of each mark, mm.
    max_samples : int, optional
        Longer profiles are judged on every k-th sample inside the marks (at most this many).
    slow_removed : bool, optional
        Remove the log-profiles' running mean over 8 marks first (default). The search of
        other shifts (:func:`vision.registration.checks.rescued`) judges without it: with it,
        a shift two marks off on a clean 1.5 mm board explained the images better (0.71)
        than the right one (0.61), and only the right one may be kept there.

    Returns
    -------
    Agreement
        ``-corr(log_a, p)`` and ``+corr(log_b, p)`` over the samples inside the marks, with a
        cubic in ``x`` removed from each (illumination, board shape) and from the
        log-profiles first their running mean over 8 marks (the albedo's slow part: grain,
        colour); ``p = x - b_k`` in mark ``k`` (the kinematic slope up to the scale
        ``1 / R``, which the correlation ignores).
    """
    la = np.asarray(log_a, dtype=np.float64)
    lb = np.asarray(log_b, dtype=np.float64)
    x = np.asarray(x_mm, dtype=np.float64)
    if la.ndim != 1 or la.shape != lb.shape or la.shape != x.shape:
        raise ValueError(f"log_a, log_b and x_mm must be 1-D of one length, got {la.shape}, "
                         f"{lb.shape}, {x.shape}")
    c = np.asarray(cusps_mm, dtype=np.float64)
    b = np.asarray(bottoms_mm, dtype=np.float64)
    if c.ndim != 1 or b.ndim != 1 or c.size != b.size + 1:
        raise ValueError(f"cusps_mm must hold one more value than bottoms_mm, got {c.shape} "
                         f"and {b.shape}")
    if b.size < 1:
        return Agreement(math.nan, math.nan)
    # one compiled call (vision.check_kernels): the marks' shading, not the wood's -- the
    # log-profiles lose their running mean over 8 marks (the albedo's slow part, which a cubic
    # leaves; 0.5 mm marks: 0.44-0.91 -> 0.76-0.9; check_kernels.without_slow, the values of
    # _without_slow) --, then the samples inside the marks, every k-th of them, the cubic by
    # its normal equations (t in [-1, 1]: well posed), the correlations
    agreement = (check_kernels.marks_agreement_slow_removed if slow_removed
                 else check_kernels.marks_agreement)
    score_a, score_b = agreement(
        np.ascontiguousarray(la), np.ascontiguousarray(lb), np.ascontiguousarray(x),
        np.ascontiguousarray(c), np.ascontiguousarray(b), int(max_samples))
    return Agreement(float(score_a), float(score_b))


def _without_slow(log_a: np.ndarray, log_b: np.ndarray, x: np.ndarray, cusps: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Both log-profiles less their running mean over 8 marks (held at its ends' values).

    One compiled running mean of the two as columns (:func:`vision.kernels.running_mean_2d`:
    each column's sums as :func:`vision.calibration.illumination.running_mean` of it alone).
    The reference of :func:`vision.check_kernels.without_slow`, which the measurement calls.
    """
    n = log_a.size
    if cusps.size < 2 or n < 2 or not x[-1] > x[0]:
        return log_a, log_b
    length = 8.0 * (cusps[-1] - cusps[0]) / (cusps.size - 1) / ((x[-1] - x[0]) / (n - 1))
    if not 1.0 <= length <= n:
        return log_a, log_b
    both = np.empty((n, 2))
    both[:, 0] = log_a
    both[:, 1] = log_b
    mean = kernels.running_mean_2d(both, float(length))
    if mean.shape[0] < 1:
        return log_a, log_b
    lead = (n - mean.shape[0]) // 2
    full = np.empty_like(both)
    full[:lead] = mean[0]
    full[lead:lead + mean.shape[0]] = mean
    full[lead + mean.shape[0]:] = mean[-1]
    both -= full
    return both[:, 0], both[:, 1]


def shift_within_slip(shift_px: float, encoder_shift_px: float, *, max_slip_px: float) -> bool:
    """Whether the registered shift lies within the slip bound of the encoder's.

    Parameters
    ----------
    shift_px, encoder_shift_px : float
        Registered and encoder shift, pixels.
    max_slip_px : float
        Largest difference the belt's slip and the counts' resolution allow, pixels.
    """
    bound = check_positive("max_slip_px", max_slip_px, allow_zero=True)
    return abs(check_finite("shift_px", shift_px)
               - check_finite("encoder_shift_px", encoder_shift_px)) <= bound


def shifts_agree(first_px: float, second_px: float, *, tolerance_px: float) -> bool:
    """Whether two shift estimates agree within ``tolerance_px`` (NaN: no second estimate)."""
    tol = check_positive("tolerance_px", tolerance_px)
    if not (math.isfinite(first_px) and math.isfinite(second_px)):
        return True
    return abs(first_px - second_px) <= tol


def honest_confidence(confidence: float, failed: list[str], *, flagged_confidence: float = 0.3
                      ) -> tuple[float, str | None]:
    """The confidence a measurement may report, and why it was lowered.

    Parameters
    ----------
    confidence : float
        The registration's confidence (NaN: not registered).
    failed : list of str
        The checks that failed, each as a reason a person can read (empty: all passed).
    flagged_confidence : float, optional
        The most a measurement with a failed check may report, in [0, 1].

    Returns
    -------
    confidence : float
        ``confidence`` when every check passed, else at most ``flagged_confidence``.
    reason : str or None
        The failed checks joined by ``"; "`` (``None``: none failed).
    """
    cap = check_range("flagged_confidence", flagged_confidence, 0.0, 1.0)
    if not failed:
        return confidence, None
    conf = min(confidence, cap) if math.isfinite(confidence) else confidence
    return conf, "; ".join(failed)
