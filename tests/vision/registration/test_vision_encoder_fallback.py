"""The encoder's shift when read noise drowns the albedo, and marks a few pixels wide.

``vision.registration.encoder_fallback``: at 30 DN the images no longer register the pair; with
``Measurer(encoder_fallback=True)`` the encoder's shift is used when the marks found there
explain both images and no other shift within the slip bound explains them clearly better --
never when the belt slipped.  ``vision.marks.periodic_noise``: marks of 6 px whose cusps are
rounded fill the slope's sample-to-sample differences themselves; one revolution apart they
cancel, and the noise floor comes from there.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.errors import MeasurementError, RegistrationError
from plant_sim.rendering.scenarios import board_pair
from vision import kernels
from vision.marks import find_marks, periodic_noise
from vision.pipeline import Measurer
from vision.registration.encoder_fallback import ENCODER_CONFIDENCE


def _tolerance(true_cv: float) -> float:
    return max(0.005, 0.2 * true_cv)


def _measure(pair, rig, **options):
    options = {"knives": 4, **options}
    m = Measurer(rig, pair.image_a.shape, radius_mm=60.0, **options)
    return m.measure(pair.image_a, pair.image_b, counts_a=pair.counts_a, counts_b=pair.counts_b)


@pytest.mark.parametrize("seed", [0, 2])
def test_noisy_pair_is_measured_at_the_encoders_shift_and_says_so(seed):
    rig, pair = board_pair(seed=seed, species="spruce", read_noise_dn=30.0)
    with pytest.raises(RegistrationError, match="cannot register"):
        _measure(pair, rig)  # the images alone: the albedo is gone
    r = _measure(pair, rig, encoder_fallback=True)
    assert r.registration_source == "encoder"
    assert r.shift_px == pytest.approx(r.encoder_shift_px)
    assert 0.0 < r.confidence <= ENCODER_CONFIDENCE
    assert r.marks_agreement >= 0.7 and r.flag_reason is None
    true = pair.truth.metrics(r.x_mm[0], r.x_mm[-1])
    assert abs(r.uniformity_cv - true["uniformity_cv"]) <= _tolerance(true["uniformity_cv"])
    assert r.pitch_mm == pytest.approx(true["pitch_mm"], rel=0.01)


@pytest.mark.parametrize(("slip_px", "why"), [
    (6.0, "not confirmed either"),      # the marks at the encoder's shift are half-marks
    (18.75, "belt slip"),               # a whole mark: the true shift explains them better
    (-18.75, "belt slip"),
])
def test_a_slipped_encoder_is_never_used(slip_px, why):
    rig, pair = board_pair(seed=0, species="spruce", read_noise_dn=30.0,
                           encoder_error_px=slip_px)
    with pytest.raises(RegistrationError, match=why):
        _measure(pair, rig, encoder_fallback=True)


def _fine_marks(seed: int, noise: float, runout_um=(0.0, 0.2, -0.1, 0.1)):
    """Slope and height of 0.5 mm marks at 12.5 px/mm, cusps rounded by 0.2 mm scattering."""
    rng = np.random.default_rng(seed)
    dx, pitch, radius = 0.08, 0.5, 60.0
    x = np.arange(640) * dx
    centres = np.arange(-2, 110) * pitch
    tips = np.array([runout_um[k % 4] for k in range(centres.size)]) * 1e-3
    z = np.min((x[None, :] - centres[:, None]) ** 2 / (2 * radius) - tips[:, None], axis=0)
    slope = np.gradient(z, dx)
    k = np.exp(-np.abs(np.arange(-15, 16)) * dx / 0.2)
    blurred = np.convolve(slope, k / k.sum(), mode="same")[20:-20]
    blurred = 0.3 * blurred + rng.normal(0.0, noise, blurred.size)  # weak, scattered shading
    height = np.cumsum(blurred) * dx * 1000.0
    return x[20:-20], height - height.mean(), blurred, z[20:-20]


def test_fine_marks_whose_cusps_fill_the_differences_are_found():
    x, h, p, z = _fine_marks(1, 2e-5)
    _, _, _, noise1, typical, _ = kernels.cusp_candidates(np.ascontiguousarray(p))
    assert typical < 5.0 * noise1  # the sample-to-sample noise floor alone refuses them
    assert periodic_noise(p) < typical / 5.0
    marks = find_marks(x, h, slope=p)
    sharp = find_marks(x, (z - z.mean()) * 1000.0, slope=np.gradient(z, 0.08))  # the truth
    assert marks.pitch_mm == pytest.approx(0.5, rel=0.01)
    assert marks.widths_mm.size >= sharp.widths_mm.size - 2


def test_half_millimetre_marks_on_scattering_spruce_are_measured():
    # the shipped simulator's rig and wood effects; before the periodic floor: no marks at all
    rig, pair = board_pair(seed=0, species="spruce", pitch_mm=0.5, knives=2, runout_um=[0, 0.05],
                           scattering_mm=0.2, read_noise_dn=2.0, imbalance=0.05, falloff=0.1,
                           roll_deg=0.4, slant_offset_deg=(1.5, -1.0), bow_mm=3.0, cup_mm=0.5,
                           reflectance_roughness_deg=15.0)
    r = _measure(pair, rig, register=False, knives=2)  # the encoder's exact shift: the marks alone
    true = pair.truth.metrics(r.x_mm[0], r.x_mm[-1])
    assert len(r.mark_widths_mm) >= true["n_marks"] - 3
    assert r.pitch_mm == pytest.approx(0.5, rel=0.01)
    assert abs(r.uniformity_cv - true["uniformity_cv"]) <= _tolerance(true["uniformity_cv"])


def test_the_periodic_noise_floor_still_refuses_a_flat_board():
    rng = np.random.default_rng(3)
    p = rng.normal(0.0, 1e-3, 640)
    assert periodic_noise(p) == pytest.approx(1e-3, rel=0.25) or math.isinf(periodic_noise(p))
    x = np.arange(640) * 0.08
    with pytest.raises(MeasurementError, match="too few cuttermarks"):
        find_marks(x, np.cumsum(p) * 80.0, slope=p)
