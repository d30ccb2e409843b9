"""The measurement's own checks on its registration, and the search when they fail.

:func:`checked` runs after the pair has been measured at its registered shift: the marks found
must explain each image's own shading
(:func:`vision.registration.consistency.marks_shading_agreement`) and
the shift must lie within the slip bound of the encoder's.  When the texture registered the
pair and the marks disagree, the column profiles register it a second time
(:meth:`vision.registration.registrar.Registrar.without_texture`).  When that does not satisfy the
checks
either -- a defect's shading outvoted the albedo in the texture *and* the profiles, or the
registration is half a mark off -- or the registered shift lies beyond the slip bound of the
encoder's (a pit's texture pulled it a whole mark off: its marks agree, its profile does not),
:func:`rescued` searches the shifts a defect can fool the
registration into: the shifts found, each half a mark to either side (the fine fit's alias),
and a grid over the slip bound around the encoder's, each refined by the fine fit, and keeps
the one whose marks explain the images best (of those within a few hundredths of the best,
the one nearest the encoder's: a whole mark's alias explains them as well).  Such a
registration reports ``source == "marks"`` and a confidence of at most ``RESCUED_CONFIDENCE``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from core.errors import MeasurementError, RegistrationError
from vision.registration.consistency import RegisteredProfile, ShiftChecker
from vision.registration.registrar import Registration
from vision.registration.shift_estimators import log_difference, mark_period_px

RESCUED_CONFIDENCE = 0.5
"""The most a registration chosen by the marks check alone reports."""

_TIE = 0.03  # agreements this close explain the images equally well


def rescued(measurer: ShiftChecker, raw: tuple[np.ndarray, np.ndarray],
            prepared: Callable[..., Any], seeds: list[float], encoder_px: float,
            margin: int, cos_roll: float,
            ) -> tuple[Registration, RegisteredProfile] | None:
    """The shift, among a defect's aliases, whose marks explain the images best.

    Parameters
    ----------
    measurer : ShiftChecker (a vision.pipeline.Measurer)
        The measurer (its registrar, thresholds and profile).
    raw : tuple of ndarray
        A's and B's column profiles as registered (camera frame).
    prepared : callable
        ``prepared(d)``: the profiles the measurement uses at shift ``d``.
    seeds : list of float
        Shifts found so far, pixels.
    encoder_px : float
        The encoder's shift, pixels.
    margin : int
        Columns left out at either end.
    cos_roll : float
        Cosine of the roll.

    Returns
    -------
    tuple or None
        The registration (``source == "marks"``) and its profile; ``None`` when no candidate
        within the slip bound gives marks that explain the images at ``min_agreement``.
    """
    reg = measurer.registrar
    pa, pb = raw
    slip = measurer.max_slip_px
    period = mark_period_px(pa)
    step = 2.0 * reg.fine_px
    reach = int(slip // step)
    cands = [encoder_px + k * step for k in range(-reach, reach + 1)]
    if math.isfinite(period) and period > 2 * step:
        for s in seeds:
            if math.isfinite(s):
                cands.extend(s + k * 0.5 * period for k in (-2, -1, 1, 2))
    tried: list[float] = []
    found: list[tuple[float, float, Any]] = []
    for c in cands:
        if abs(c - encoder_px) > slip + reg.fine_px:
            continue
        try:
            shift, score = _refined(reg, pa, pb, prepared(c), c)
        except RegistrationError:
            continue
        if score < reg.min_fine_score:
            shift = c
        if (not math.isfinite(shift) or abs(shift - encoder_px) > slip
                or any(abs(shift - t) < 0.5 for t in tried)):
            continue
        tried.append(shift)
        try:
            # judged without removing the shading's slow part: that removal may keep a right
            # shift (0.5 mm marks), never choose another one (an alias two marks off scored
            # above the right shift with it on a clean board)
            profile = measurer._registered_profile(*prepared(shift), shift, margin, cos_roll,
                                                   slow_removed=False)
        except MeasurementError:
            continue
        if math.isfinite(profile.agreement.score):
            found.append((profile.agreement.score, shift, profile))
    if not found:
        return None
    best = max(f[0] for f in found)
    if best < measurer.min_agreement:
        return None
    score, shift, profile = min((f for f in found if f[0] >= best - _TIE),
                                key=lambda f: abs(f[1] - encoder_px))
    return Registration(shift_px=shift, confidence=min(RESCUED_CONFIDENCE, score),
                        encoder_shift_px=encoder_px, source="marks"), profile


def _refined(reg: Any, pa: np.ndarray, pb: np.ndarray, prep: tuple, guess: float
             ) -> tuple[float, float]:
    """The fine fit near ``guess``, a defect's rows and columns left out.

    With a defect found, the fit runs on the profiles without its rows (and, when it covers
    most rows of its columns, without those columns), B there already registered onto A at
    ``guess``: it finds the residual.  Without one, on the plain profiles.
    """
    qa, qb, registered, columns = prep
    if not registered:
        return reg.fine(pa, pb, guess_px=guess)
    la, lb = log_difference(qa), log_difference(qb)
    if columns is not None:  # a defect over most rows of its columns: only the clean stretch
        keep = np.zeros(la.size, dtype=bool)
        keep[columns[0]: max(columns[0], columns[1] - 1)] = True
        la[~keep] = 0.0
        lb[~keep] = 0.0
    residual, score = reg.fine_fit(la, lb, 0.0)
    return guess + residual, score


def checked(measurer: ShiftChecker, raw: tuple[np.ndarray, np.ndarray],
            prepared: Callable[..., Any], reg: Registration, profile: RegisteredProfile,
            margin: int, cos_roll: float,
            ) -> tuple[Registration, RegisteredProfile, str | None]:
    """The measurement's own checks; a second registration, then a search, when they fail.

    Returns the registration and profile kept and the reason the checks still fail
    (``None``: they pass).  When the marks found do not explain the images' own shading and
    the registration came from the texture, the pair is registered again from the column
    profiles alone (the texture is what light-dependent defects fool); the one whose marks
    explain the images better is kept.  When the marks still do not explain the images, or
    the shift lies beyond the slip bound, :func:`rescued` searches within the slip bound; what
    it does not find stays flagged.
    """
    m = measurer
    if not m.register:
        return reg, profile, None
    score = profile.agreement.score
    reasons: list[str] = []
    second: Registration | None = None
    if not score >= m.min_agreement and reg.source == "texture":
        try:
            second = m.registrar.without_texture(*raw, encoder_shift_px=reg.encoder_shift_px)
        except RegistrationError as exc:
            reasons.append(f"no second registration ({exc})")
        if second is not None and abs(second.shift_px - reg.shift_px) > 0.5:
            try:
                other = m._registered_profile(*prepared(second.shift_px), second.shift_px,
                                              margin, cos_roll)
            except MeasurementError as exc:
                reasons.append(f"the column profiles' registration gives no marks ({exc})")
            else:
                if other.agreement.score > score or not math.isfinite(score):
                    reasons.append(
                        f"texture registration {reg.shift_px:.1f} px rejected: its marks "
                        f"explain the images at {score:.2f}, the column profiles' "
                        f"({second.shift_px:.1f} px) at {other.agreement.score:.2f}")
                    reg, profile, score = second, other, other.agreement.score
                else:
                    reasons.append(
                        f"texture ({reg.shift_px:.1f} px) and column profiles "
                        f"({second.shift_px:.1f} px) disagree")
    slipped = abs(reg.shift_px - reg.encoder_shift_px) > m.max_slip_px
    if not score >= m.min_agreement or slipped:
        seeds = [reg.shift_px] + ([second.shift_px] if second is not None else [])
        found = rescued(m, raw, prepared, seeds, reg.encoder_shift_px, margin, cos_roll)
        # a shift beyond the slip bound whose marks agree is replaced only by one that
        # explains the images clearly better (a whole mark's alias explains them as well: the
        # belt may have slipped that far, and the pair stays flagged)
        if found is not None and (not score >= m.min_agreement
                                  or found[1].agreement.score > score + _TIE):
            return found[0], found[1], None
    failed: list[str] = []
    if not score >= m.min_agreement:
        failed.append(f"the marks found explain the images' own shading at {score:.2f} < "
                      f"{m.min_agreement:.2f} (misregistered pair or no knife marks)")
        failed.extend(reasons)
    if slipped:
        failed.append(f"registered shift {reg.shift_px:.1f} px is more than the slip bound "
                      f"{m.max_slip_px:.1f} px from the encoder's "
                      f"{reg.encoder_shift_px:.1f} px")
    return reg, profile, "; ".join(failed) if failed else None
