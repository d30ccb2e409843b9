"""The measurement on boards with the effects of real rigs and real wood.

Boards from the independent renderer ``tests/support/vision_boards.py`` (not ``plant_sim``): camera
roll, anisotropic subsurface scattering, true light slants off the rig file, rough reflectance,
knots, pores, a pencil line, bow and cup, read noise, 1 m/s with slip.  Each effect alone, over
tables of cases; criteria of the issue: profile correlation >= 0.97 (against the truth without
its cubic trend, which the illumination correction removes), pitch within 1 %, uniformity CV
within 0.03, depth within 10 %, registration within 0.5 px, no refusal.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.support.vision_boards import render_board
from vision.marks import corr2
from vision.pipeline import Measurer

RUNOUT = (0.0, 2.0, -1.0, 1.0)

CASES = {
    "plain": {},
    "roll +3 deg": dict(roll_deg=3.0),
    "roll -3 deg": dict(roll_deg=-3.0),
    "roll +1 deg, slip -10 px": dict(roll_deg=1.0, slip_px=-10.0),
    "scattering 0.1 mm": dict(scatter_mm=0.1),
    "scattering 0.3 mm": dict(scatter_mm=0.3),
    "scattering 0.5 mm": dict(scatter_mm=0.5),
    "slants +3/+3 deg": dict(slant_a_error_deg=3.0, slant_b_error_deg=3.0),
    "slants -3/-3 deg": dict(slant_a_error_deg=-3.0, slant_b_error_deg=-3.0),
    "slants +3/-3 deg": dict(slant_a_error_deg=3.0, slant_b_error_deg=-3.0),
    "rough reflectance": dict(roughness_rad=0.5),
    "knots, pores, pencil line": dict(knots=2, pores=150, pencil=True),
    "bow and cup 5 m": dict(bow_m=5.0, cup_m=5.0),
    "noise 10 DN": dict(noise_dn=10.0, seed=5, height=493),
    "noise 20 DN": dict(noise_dn=20.0, seed=4, height=493),
    "noise 20 DN, roll -2 deg, slip 10 px": dict(noise_dn=20.0, seed=1, roll_deg=-2.0,
                                               slip_px=10.0, height=493),
    "1 m/s, 10 px slip": dict(speed_mm_s=1000.0, slip_px=10.0),
    "roll 2 deg, slants +2/-1, 1 m/s, slip": dict(roll_deg=2.0, slant_a_error_deg=2.0,
                                                  slant_b_error_deg=-1.0, speed_mm_s=1000.0,
                                                  slip_px=10.0, roughness_rad=0.3),
}


ALL_TOGETHER = dict(roughness_rad=0.4, knots=1, pores=100, pencil=True, bow_m=5.0, cup_m=5.0,
                    speed_mm_s=1000.0, slip_px=10.0, imbalance=0.05, height=493)

TOGETHER = {
    # everything at once, 1 m/s with 10 px slip; noise and scattering at the range's ends
    "roll -2.5, slants +2/-3, scattering 0.3 mm, 20 DN": dict(
        seed=4, roll_deg=-2.5, slant_a_error_deg=2.0, slant_b_error_deg=-3.0, scatter_mm=0.3,
        noise_dn=20.0),
    "roll +3, slants -3/+3, scattering 0.1 mm, 20 DN": dict(
        seed=5, roll_deg=3.0, slant_a_error_deg=-3.0, slant_b_error_deg=3.0, scatter_mm=0.1,
        noise_dn=20.0),
    "roll +2, slants -2/+3, scattering 0.5 mm, 20 DN": dict(
        seed=4, roll_deg=2.0, slant_a_error_deg=-2.0, slant_b_error_deg=3.0, scatter_mm=0.5,
        noise_dn=20.0),
}


def _truth_metrics(board, m):
    tc = board.cusps_mm
    i0 = int(np.argmin(np.abs(tc - m.cusps_mm[0])))
    i1 = int(np.argmin(np.abs(tc - m.cusps_mm[-1])))
    widths = np.diff(tc[i0 : i1 + 1])
    return widths.mean(), widths.std() / widths.mean(), board.depths_um[i0:i1].mean()


def _measure(board, **options):
    measurer = Measurer(board.rig, board.image_a.shape, **options)
    return measurer.measure(board.image_a, board.image_b, counts_a=board.counts_a,
                            counts_b=board.counts_b, speed_mm_s=board.speed_mm_s)


@pytest.mark.parametrize("name", list(CASES))
def test_effect_alone_is_measured_within_the_issue_criteria(name):
    kw = {"height": 240, **CASES[name]}
    board = render_board(kw.pop("seed", 4), runout_um=RUNOUT, **kw)
    m = _measure(board, radius_mm=board.radius_mm, knives=board.knives)
    assert abs(m.shift_px - board.shift_px) < 0.5
    assert abs(m.roll_deg - board.roll_deg) < 0.1
    truth = np.interp(m.x_mm, board.x_mm, board.height_um)
    truth = truth - np.polyval(np.polyfit(m.x_mm, truth, 3), m.x_mm)
    assert corr2(m.height_um, truth) >= 0.97
    pitch, cv, depth = _truth_metrics(board, m)
    assert m.pitch_mm == pytest.approx(pitch, rel=0.01)
    assert abs(m.uniformity_cv - cv) < 0.03
    assert m.calibration is not None and m.calibration.trusted
    assert m.depth_um == pytest.approx(depth, rel=0.10)
    assert m.kinematic_depth_um == pytest.approx(depth, rel=0.10)
    # the gain found is the one the slant error causes (reflectance/scattering aside)
    if "scatter_mm" not in kw and "roughness_rad" not in kw:
        assert m.calibration.gain == pytest.approx(board.gain, rel=0.06)


@pytest.mark.parametrize("name", list(TOGETHER))
def test_all_effects_together_at_1_m_s_with_slip(name):
    kw = {**ALL_TOGETHER, **TOGETHER[name]}
    board = render_board(kw.pop("seed"), runout_um=RUNOUT, **kw)
    m = _measure(board, radius_mm=board.radius_mm, knives=board.knives)
    assert abs(m.shift_px - board.shift_px) < 0.5
    assert abs(m.roll_deg - board.roll_deg) < 0.1
    truth = np.interp(m.x_mm, board.x_mm, board.height_um)
    truth = truth - np.polyval(np.polyfit(m.x_mm, truth, 3), m.x_mm)
    assert corr2(m.height_um, truth) >= 0.97
    pitch, cv, depth = _truth_metrics(board, m)
    assert m.pitch_mm == pytest.approx(pitch, rel=0.01)
    assert abs(m.uniformity_cv - cv) < 0.03
    assert m.calibration is not None and m.calibration.trusted
    assert m.depth_um == pytest.approx(depth, rel=0.10)


@pytest.mark.parametrize("roll_deg", [-3.0, -1.5, 0.5, 2.0, 3.0])
def test_roll_is_estimated_and_the_marks_averaged_along_it(roll_deg):
    board = render_board(6, roll_deg=roll_deg, runout_um=RUNOUT, height=240)
    m = _measure(board)
    assert m.roll_deg == pytest.approx(roll_deg, abs=0.05)
    assert m.roll_confidence > 0.8
    pitch, _, _ = _truth_metrics(board, m)
    assert m.pitch_mm == pytest.approx(pitch, rel=0.005)
    assert m.to_json()["roll_deg"] == pytest.approx(roll_deg, abs=0.05)


def test_without_radius_the_calibration_is_off_and_depth_is_photometric():
    board = render_board(4, slant_a_error_deg=3.0, slant_b_error_deg=3.0, runout_um=RUNOUT)
    m = _measure(board)
    data = m.to_json()
    assert data["calibration"]["state"] == "off"
    assert data["kinematic_depth_um"] is None
    _, _, depth = _truth_metrics(board, m)
    # uncalibrated, the slant error shows in the depth by the gain it causes
    assert m.depth_um / depth == pytest.approx(board.gain, rel=0.08)


def test_calibration_on_a_board_without_marks_shape_is_not_trusted():
    from vision.calibration.selfcal import fit_calibration

    rng = np.random.default_rng(0)
    x = np.arange(400) * 0.08
    model = ((x % 1.5) - 0.75) / 60.0
    noise = rng.normal(0, 0.01, x.size)  # slope that is all noise
    cal = fit_calibration(noise, model, dx_mm=0.08, marks=20)
    assert not cal.trusted and cal.gain_confidence < 0.2
    good = fit_calibration(1.3 * model + rng.normal(0, 1e-4, x.size), model, dx_mm=0.08,
                           marks=20)
    assert good.trusted and good.gain == pytest.approx(1.3, rel=0.02)
    absurd = fit_calibration(10.0 * model, model, dx_mm=0.08, marks=20)  # no rig is that far off
    assert absurd.gain == pytest.approx(10.0, rel=0.02) and not absurd.trusted


def test_self_calibrator_smooths_over_pairs_and_forgets_on_reset():
    from vision.calibration.selfcal import Calibration, SelfCalibrator

    cal = SelfCalibrator(weight=0.3, min_confidence=0.5)
    out = None
    for g in (1.2, 1.25, 1.15, 1.2):
        out = cal.update(Calibration(gain=g, gain_confidence=0.9, trusted=True))
    assert out is not None and out.trusted and out.gain == pytest.approx(1.2, rel=0.03)
    out = cal.update(Calibration(gain=5.0, gain_confidence=0.0))  # a useless pair: no effect
    assert out.gain == pytest.approx(1.2, rel=0.03) and out.gain_confidence < 0.9
    cal.reset()
    first = cal.update(Calibration(gain=2.0, gain_confidence=0.2))
    assert not first.trusted and first.gain == pytest.approx(2.0)


def test_kinematic_depth_of_equal_marks_is_pitch_squared_over_8r():
    from vision.calibration.selfcal import kinematic_depths_um

    cusps = np.arange(6) * 1.5
    bottoms = cusps[:-1] + 0.75
    d = kinematic_depths_um(cusps, bottoms, radius_mm=60.0)
    assert np.allclose(d, 1000 * 1.5**2 / (8 * 60.0))


def test_noise_lowers_the_confidence_honestly():
    clean = _measure(render_board(5, runout_um=RUNOUT, noise_dn=1.0, height=493))
    noisy = _measure(render_board(5, runout_um=RUNOUT, noise_dn=20.0, height=493))
    assert noisy.confidence < clean.confidence
    assert math.isfinite(noisy.confidence) and noisy.confidence > 0.2


@pytest.mark.parametrize("size", [(986, 1318), (246, 329)])
def test_rig_calibrated_at_another_image_size_is_refused_naming_both(size):
    from dataclasses import replace

    board = render_board(1, height=160)
    with pytest.raises(ValueError, match=rf"{size[1]}x{size[0]}"):
        Measurer(board.rig, size)
    sized = replace(board.rig, camera=replace(board.rig.camera, width=659, height=160))
    with pytest.raises(ValueError, match=r"659x160 pixels, the images are 659x170"):
        Measurer(sized, (170, 659))
    Measurer(sized, (160, 659))  # the right size is fine


@pytest.mark.parametrize(("noise_dn", "roll_deg"), [(1.0, 0.0), (20.0, -1.5)])
def test_images_of_two_different_boards_are_refused_even_with_the_noise_rule(noise_dn, roll_deg):
    from core.errors import RegistrationError

    a = render_board(2, runout_um=RUNOUT, noise_dn=noise_dn, roll_deg=roll_deg, height=320)
    b = render_board(22, runout_um=RUNOUT, noise_dn=noise_dn, roll_deg=roll_deg, height=320)
    measurer = Measurer(a.rig, a.image_a.shape)
    with pytest.raises(RegistrationError):
        measurer.measure(a.image_a, b.image_b, counts_a=a.counts_a, counts_b=a.counts_b)
