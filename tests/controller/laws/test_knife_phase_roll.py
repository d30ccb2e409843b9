"""Knife attribution with a rolled camera, across the plant envelope (property tests).

A mark bottom at feed distance ``s`` from the optical axis crosses the centre row of a camera
rolled by ``r`` at column ``u = cx + s ppm / cos r``. The vision reports it in the board frame,
``x = (cx + (u - cx) cos r) / ppm = cx / ppm + s`` (:mod:`vision.pipeline`); a bottom left in
the image's own frame (``u / ppm``) is off by ``s (1 / cos r - 1)``, up to 0.1 mm at 5 deg at
the field's edge. Either way :func:`attribute_marks` gives every mark its knife: the travel
per pass is fitted to the bottoms (it absorbs the scale), the phase is their circular mean.
2-8 knives, pitch 0.5-3 mm, roll up to +-5 deg, the bottoms' noise up to 0.25 px.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.knife_phase import attribute_marks, wrapped_difference

WRAP = 1 << 32
PPM = 12.5  # the shipped rig: px/mm, optical axis column, image width
CX = 329.0
WIDTH_PX = 659
CPM = 20.0
L_MM = 300.0


def rolled_bottoms(*, knives, pitch_mm, roll_deg, index, lead_counts, noise_px, seed,
                   board_frame=True):
    """The mark bottoms a vision reports with a rolled camera, and each mark's knife."""
    counts_a = (index + round(L_MM * CPM) + lead_counts) % WRAP
    base = wrapped_difference(counts_a, index)
    j = np.arange(-200, 201)
    s = (base - j * pitch_mm * CPM) / CPM - L_MM  # feed distance from the axis, mm
    cos_r = math.cos(math.radians(roll_deg))
    u = CX + s * PPM / cos_r  # column where the mark crosses the centre row
    inside = (u >= 2) & (u <= WIDTH_PX - 3)
    u = u[inside] + np.random.default_rng(seed).uniform(-noise_px, noise_px, inside.sum())
    x = (CX + (u - CX) * cos_r) / PPM if board_frame else u / PPM
    order = np.argsort(x)
    return x[order], np.mod(j[inside], knives)[order], counts_a


@settings(max_examples=200, deadline=None)
@given(
    knives=st.integers(2, 8),
    pitch_mm=st.floats(0.5, 3.0),
    roll_deg=st.floats(-5.0, 5.0),
    index=st.integers(0, WRAP - 1),
    lead=st.floats(0.0, 1.0),
    noise_px=st.floats(0.0, 0.25),
    guide=st.floats(0.9, 1.1),
    board_frame=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_rolled_bottoms_get_their_knives(knives, pitch_mm, roll_deg, index, lead, noise_px,
                                         guide, board_frame, seed):
    x, knife, counts_a = rolled_bottoms(
        knives=knives, pitch_mm=pitch_mm, roll_deg=roll_deg, index=index,
        lead_counts=round(lead * pitch_mm * CPM * 0.4), noise_px=noise_px, seed=seed,
        board_frame=board_frame)
    pa = attribute_marks(x, None, counts_a=counts_a, index_latch_counts=index,
                         cutter_to_camera_mm=L_MM, counts_per_mm=CPM, px_per_mm=PPM, cx_px=CX,
                         pass_guide_mm=pitch_mm * guide, knives=knives)
    assert np.array_equal(pa.knife, knife)
    assert pa.missing == 0
    assert pa.spread < 0.15
    scale = 1.0 if board_frame else 1.0 / math.cos(math.radians(roll_deg))
    assert pa.pass_mm == pytest.approx(pitch_mm * scale, rel=2e-3)


@pytest.mark.parametrize("roll_deg", [-5.0, -3.0, 3.0, 5.0])
def test_a_rolled_field_does_not_put_two_bottoms_on_one_pass(roll_deg):
    """At the shipped plant (4 knives, 1.5 mm) no two bottoms land on one pass at any roll."""
    x, knife, counts_a = rolled_bottoms(knives=4, pitch_mm=1.5, roll_deg=roll_deg,
                                        index=123_456, lead_counts=7, noise_px=0.2, seed=1)
    pa = attribute_marks(x, None, counts_a=counts_a, index_latch_counts=123_456,
                         cutter_to_camera_mm=L_MM, counts_per_mm=CPM, px_per_mm=PPM, cx_px=CX,
                         pass_guide_mm=1.5, knives=4)
    assert np.array_equal(pa.knife, knife)
    assert np.all(np.diff(x) > 1.4)  # the gaps are a pitch, not 0.63 mm


@pytest.mark.parametrize("n, offset", [(2, -0.1), (13, 0.3333), (26, -0.1), (30, 0.3333)])
def test_spread_of_exact_pass_numbers_is_zero_not_nan(n, offset):
    """Their mean resultant rounds to just above 1: the spread is 0 (NaN refused the pair)."""
    from controller.laws.knife_phase import phase_spread

    assert phase_spread(np.arange(n) + offset) == pytest.approx(0.0, abs=1e-6)
