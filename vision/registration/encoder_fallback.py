"""The encoder's shift as the registration of last resort, accepted only when the marks confirm it.

At high read noise (25-30 DN on the shipped rig) the wood's albedo drowns: the texture and
column-profile correlations fall to the level of two unrelated boards (0.03-0.15) and
:class:`vision.registration.registrar.Registrar` refuses the pair.  The knife marks are still
plain in the
column profiles (400 rows averaged), and the encoder's shift is good to its count (0.625 px at
12.5 px/mm and 20 counts/mm) unless the belt slipped.  A slipping belt makes the encoder's
shift wrong, so it is used only when the marks found at that shift explain both images
(:func:`vision.registration.consistency.marks_shading_agreement`) *and* no other shift within the
slip bound
explains them clearly better:

- the agreement at the encoder's shift must reach the measurer's ``min_agreement``;
- no shift of a grid over ``encoder +- max_slip_px`` farther than ``NEAR_PX`` from it may
  explain the images more than ``TIE`` better.  On the simulated spruce boards at 30 DN
  (``board_pair``, 1.5 mm, runout 0/2/0.5/1.5 um) the agreement peaks at 0.92-0.95 at the true
  shift, falls to 0.79-0.85 at 1.25 px and below 0.74 at 2.5 px, and reaches 0.75-0.83 a whole
  mark away (where the runout pattern vanishes from the widths: CV 0.08 measured as 0.01): a
  belt that slipped by 2.5 px or more, up to the slip bound, leaves the encoder's shift below
  ``min_agreement`` or a clearly better shift in the grid, and the pair is refused.  When the
  marks are all alike (the loop has evened the knives) a whole mark's alias explains the
  images as well as the true shift; the encoder's is then kept, as
  :func:`vision.registration.checks.rescued` keeps the candidate nearest it, and an alias of alike
  marks
  measures alike widths.

A registration accepted here reports ``source == "encoder"`` and a confidence of at most
``ENCODER_CONFIDENCE``.  What cannot be told apart: a slip beyond the slip bound that lands on a
whole mark's alias (the grid does not reach the true shift); the slip bound is the rig's word on
how far the belt may slip between the two triggers.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from core.errors import MeasurementError, RegistrationError
from vision.registration.consistency import RegisteredProfile, ShiftChecker
from vision.registration.registrar import Registration

ENCODER_CONFIDENCE = 0.5
"""The most a registration taken from the encoder alone reports."""

NEAR_PX = 2.5
"""Shifts this close to the encoder's belong to its own agreement peak (count, quantisation)."""

TIE = 0.03
"""Agreements this close explain the images equally well (as :mod:`vision.registration.checks`)."""

STEP_PX = 1.25
"""Grid step of the search for a better shift, pixels (the peak is ~2.5 px wide at 0.7)."""


def _agreement(measurer: ShiftChecker, prepared: Callable[..., Any], shift: float, margin: int,
               cos_roll: float) -> tuple[float, RegisteredProfile | None]:
    """The marks' agreement at ``shift`` and its profile (``-inf, None``: no marks there)."""
    try:
        profile = measurer._registered_profile(*prepared(shift), shift, margin, cos_roll)
    except MeasurementError:
        return -math.inf, None
    score = profile.agreement.score
    return (score, profile) if math.isfinite(score) else (-math.inf, None)


def encoder_registration(measurer: ShiftChecker, prepared: Callable[..., Any], encoder_px: float,
                         margin: int, cos_roll: float, failure: RegistrationError,
                         ) -> tuple[Registration, RegisteredProfile]:
    """The pair registered at the encoder's shift, when the marks confirm that shift.

    Parameters
    ----------
    measurer : ShiftChecker (a vision.pipeline.Measurer)
        The measurer (``min_agreement``, ``max_slip_px`` and its profile).
    prepared : callable
        ``prepared(d)``: the profiles the measurement uses at shift ``d``.
    encoder_px : float
        The encoder's shift in the profiles' (sheared) columns, pixels.
    margin : int
        Columns left out at either end.
    cos_roll : float
        Cosine of the roll.
    failure : RegistrationError
        Why the images did not register the pair (kept in the refusal's message).

    Returns
    -------
    registration : vision.registration.registrar.Registration
        ``source == "encoder"``, the encoder's shift, confidence ``min(ENCODER_CONFIDENCE,
        agreement)``.
    profile : vision.pipeline.RegisteredProfile
        The pair's profile at that shift.

    Raises
    ------
    RegistrationError
        The marks at the encoder's shift do not explain the images at ``min_agreement``, or a
        shift farther than ``NEAR_PX`` within the slip bound explains them more than ``TIE``
        better (the belt may have slipped); the message starts with ``failure``'s.
    """
    score, profile = _agreement(measurer, prepared, encoder_px, margin, cos_roll)
    if profile is None or not score >= measurer.min_agreement:
        shown = "no marks" if profile is None else f"{score:.2f}"
        raise RegistrationError(
            f"{failure}; the encoder's shift {encoder_px:.1f} px is not confirmed either: the "
            f"marks found there explain the images at {shown} < {measurer.min_agreement:.2f}")
    slip = measurer.max_slip_px
    reach = int(slip // STEP_PX)
    best, best_at = -math.inf, math.nan
    for k in range(-reach, reach + 1):
        offset = k * STEP_PX
        if abs(offset) <= NEAR_PX:
            continue
        other, _ = _agreement(measurer, prepared, encoder_px + offset, margin, cos_roll)
        if other > best:
            best, best_at = other, encoder_px + offset
    if best > score + TIE:
        raise RegistrationError(
            f"{failure}; the encoder's shift {encoder_px:.1f} px is not confirmed: its marks "
            f"explain the images at {score:.2f}, those at {best_at:.1f} px at {best:.2f} "
            f"(belt slip?)")
    assert profile is not None
    reg = Registration(shift_px=encoder_px, confidence=float(np.clip(
        min(ENCODER_CONFIDENCE, score), 0.0, 1.0)), encoder_shift_px=encoder_px,
        source="encoder")
    return reg, profile
