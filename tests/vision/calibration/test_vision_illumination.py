"""Illumination correction: flat field, detrended log-ratio, LED imbalance and fall-off."""

from __future__ import annotations

import numpy as np
import pytest

from vision.calibration.illumination import (
    Detrender,
    corrected_log_ratio,
    flat_field_correct,
    running_mean,
)
from vision.integrate import integrate_slope
from vision.marks import corr2
from vision.slope import lambert_intensity, slope_eq4, slope_from_ratio

SLANT = 82.0


def _marks_slope(n: int = 640, pitch_px: float = 18.7, phase: float = 5.0) -> np.ndarray:
    """Pixel-mean slope of a chain of arcs (R = 60 mm at 12.5 px/mm)."""

    def height_px(x: np.ndarray) -> np.ndarray:
        local = (x % pitch_px) - pitch_px / 2
        return local**2 / (2 * 60.0 * 12.5)

    x = np.arange(n) + phase
    return height_px(x + 0.5) - height_px(x - 0.5)


def _lit(slope: np.ndarray, *, imbalance: float, falloff: float) -> tuple[np.ndarray, np.ndarray]:
    n = slope.size
    u = np.linspace(-0.5, 0.5, n)
    albedo = 0.5 * (1 + 0.03 * np.sin(np.arange(n) / 7.0))
    i_a = lambert_intensity(slope, slant_deg=SLANT, azimuth_deg=0.0, albedo=albedo)
    i_b = lambert_intensity(slope, slant_deg=SLANT, azimuth_deg=180.0, albedo=albedo)
    i_a = i_a * (1 + falloff * u)  # each LED brighter on its own side
    i_b = i_b * (1 + imbalance) * (1 - falloff * u)
    return i_a, i_b


@pytest.mark.parametrize("imbalance, falloff", [(0.05, 0.0), (0.1, 0.0), (0.0, 0.1),
                                                (-0.07, 0.08), (0.1, -0.1)])
def test_detrended_log_ratio_survives_imbalance_and_falloff(imbalance, falloff):
    p = _marks_slope()
    i_a, i_b = _lit(p, imbalance=imbalance, falloff=falloff)
    true_h = integrate_slope(p, dx_mm=0.08)
    plain = slope_eq4(i_a, i_b, slant_deg=SLANT)
    corrected = slope_from_ratio(
        np.exp(corrected_log_ratio(i_a, i_b, period_px=18.7)), slant_deg=SLANT
    )
    # the profile (integrated slope) is what the imbalance wrecks
    assert corr2(integrate_slope(corrected, dx_mm=0.08), true_h) >= 0.97
    assert corr2(integrate_slope(plain, dx_mm=0.08), true_h) < 0.9
    assert np.abs(corrected - p).max() < 0.1 * np.abs(p).max()


def test_plain_eq4_is_wrecked_by_a_ten_percent_imbalance():
    p = _marks_slope()
    i_a, i_b = _lit(p, imbalance=0.1, falloff=0.1)
    plain = slope_eq4(i_a, i_b, slant_deg=SLANT)
    assert np.abs(plain - p).mean() > np.abs(p).mean()
    true_h = integrate_slope(p, dx_mm=0.08)
    assert corr2(integrate_slope(plain, dx_mm=0.08), true_h) < 0.5


def test_flat_field_reference_removes_the_lights_exactly():
    p = _marks_slope()
    i_a, i_b = _lit(p, imbalance=0.08, falloff=0.1)
    flat_a, flat_b = _lit(np.zeros_like(p), imbalance=0.08, falloff=0.1)
    flat_a /= 0.5 * (1 + 0.03 * np.sin(np.arange(p.size) / 7.0))  # a flat board of even albedo
    flat_b /= 0.5 * (1 + 0.03 * np.sin(np.arange(p.size) / 7.0))
    a, b = flat_field_correct(i_a, i_b, reference_a=flat_a, reference_b=flat_b)
    np.testing.assert_allclose(slope_eq4(a, b, slant_deg=SLANT), p, atol=1e-12)
    with pytest.raises(ValueError, match="reference"):
        flat_field_correct(i_a, i_b, reference_a=np.zeros_like(i_a), reference_b=flat_b)
    with pytest.raises(ValueError, match="length"):
        flat_field_correct(i_a, i_b, reference_a=flat_a[1:], reference_b=flat_b)


def test_detrender_removes_polynomials_and_keeps_the_marks():
    n = 600
    u = np.linspace(-1, 1, n)
    poly = 0.3 - 0.2 * u + 0.05 * u**2 + 0.04 * u**3
    marks = np.sin(np.arange(n) * 2 * np.pi / 23.4)
    det = Detrender(n, degree=3)
    np.testing.assert_allclose(det(poly), 0.0, atol=1e-12)
    # with the marks' period the fit ignores the partial periods at the ends
    with_period = det(poly + marks, period_px=23.4)
    without = det(poly + marks)
    assert np.abs(with_period - marks).max() < 0.02
    assert np.abs(with_period - marks).max() < np.abs(without - marks).max()
    # sub-ranges of the column axis
    part = det(poly[100:400], start=100, period_px=23.4)
    np.testing.assert_allclose(part, 0.0, atol=1e-9)


def test_running_mean_annihilates_its_period():
    x = np.arange(500)
    periodic = np.sin(2 * np.pi * x / 17.3) + 0.5 * np.cos(4 * np.pi * x / 17.3)
    assert np.abs(running_mean(periodic, 17.3)).max() < 0.02
    line = 2.0 + 0.01 * x
    rm = running_mean(line, 17.3)
    m0 = (line.size - rm.size) // 2
    np.testing.assert_allclose(rm, line[m0 : m0 + rm.size], atol=1e-9)
    with pytest.raises(ValueError, match="length"):
        running_mean(line, 0.5)
