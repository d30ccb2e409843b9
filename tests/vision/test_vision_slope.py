"""Seed Eq. 4 with general azimuths, the sign of the misprinted Eq. 3b, and real DiLiGenT data."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from vision.marks import corr2
from vision.slope import lambert_intensity, slope_eq4, slope_from_ratio

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "diligent_ball"


def test_light_at_180_gives_plus_p_sin_sigma():
    # Seed Eq. 3b misprints the sign: with tau = 180 deg, I ~ cos(s) + p sin(s).
    s, p = 82.0, np.array([-0.03, -0.01, 0.0, 0.01, 0.03])
    i_a = lambert_intensity(p, slant_deg=s, azimuth_deg=0.0)
    i_b = lambert_intensity(p, slant_deg=s, azimuth_deg=180.0)
    sig = math.radians(s)
    norm = np.sqrt(1 + p * p)
    np.testing.assert_allclose(i_b, (math.cos(sig) + p * math.sin(sig)) / norm, rtol=1e-12)
    np.testing.assert_allclose(i_a, (math.cos(sig) - p * math.sin(sig)) / norm, rtol=1e-12)
    # a surface rising toward +x faces away from the +x light: darker in A, brighter in B
    assert np.all(np.diff(i_a) < 0) and np.all(np.diff(i_b) > 0)
    # ... so Eq. 4 with A = light at 0 deg returns +p, not -p
    np.testing.assert_allclose(slope_eq4(i_a, i_b, slant_deg=s), p, atol=1e-12)


@pytest.mark.parametrize(
    "slant, tau_a, tau_b",
    [(82.0, 0.0, 180.0), (60.0, 0.0, 180.0), (37.0, -4.0, -177.0), (80.0, 0.0, 90.0),
     (45.0, 20.0, 150.0), (85.0, 180.0, 0.0)],
)
def test_eq4_inverts_lambert_for_general_azimuths(slant, tau_a, tau_b):
    p = np.linspace(-0.08, 0.08, 41)
    albedo = np.random.default_rng(1).uniform(0.2, 0.9, p.size)  # cancels in the ratio
    i_a = lambert_intensity(p, slant_deg=slant, azimuth_deg=tau_a, albedo=albedo)
    i_b = lambert_intensity(p, slant_deg=slant, azimuth_deg=tau_b, albedo=1.07 * albedo)
    got = slope_eq4(i_a, i_b / 1.07, slant_deg=slant, azimuth_a_deg=tau_a, azimuth_b_deg=tau_b)
    np.testing.assert_allclose(got, p, atol=1e-12)
    via_ratio = slope_from_ratio(
        i_b / 1.07 / i_a, slant_deg=slant, azimuth_a_deg=tau_a, azimuth_b_deg=tau_b
    )
    np.testing.assert_allclose(via_ratio, p, atol=1e-12)


def test_eq4_opposed_lights_formula():
    i_a = np.array([0.9, 1.0, 1.3])
    i_b = np.array([1.1, 1.0, 0.7])
    expect = (i_b - i_a) / (i_b + i_a) / math.tan(math.radians(70.0))
    np.testing.assert_allclose(slope_eq4(i_a, i_b, slant_deg=70.0), expect)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"slant_deg": 0.0}, "slant_deg"),
        ({"slant_deg": 95.0}, "slant_deg"),
        ({"slant_deg": float("nan")}, "slant_deg"),
        ({"slant_deg": 80.0, "azimuth_a_deg": 30.0, "azimuth_b_deg": -30.0}, "same cosine"),
        ({"slant_deg": 80.0, "azimuth_b_deg": float("inf")}, "azimuth_b_deg"),
    ],
)
def test_eq4_rejects_bad_geometry(kwargs, match):
    with pytest.raises(ValueError, match=match):
        slope_eq4(np.ones(3), np.ones(3), **kwargs)


def test_eq4_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="shape"):
        slope_eq4(np.ones(3), np.ones(4), slant_deg=80.0)


def _diligent_gray(index: int, intensities: np.ndarray) -> np.ndarray:
    cv2 = pytest.importorskip("cv2")
    img = cv2.imread(str(DATA / f"{index:03d}.png"), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.dtype == np.uint16 and img.shape[2] == 3
    rgb = img[:, :, ::-1].astype(np.float64)  # OpenCV loads BGR
    return (rgb / intensities[index - 1][None, None, :]).mean(axis=2)


@pytest.mark.skipif(not DATA.is_dir(), reason="shared DiLiGenT data absent")
@pytest.mark.parametrize("pair, minimum", [((92, 44), 0.98), ((68, 20), 0.975)])
def test_diligent_ball_eq4_slope_matches_true_slope(pair, minimum):
    scipy_io = pytest.importorskip("scipy.io")
    lights = np.loadtxt(DATA / "light_directions.txt")
    strengths = np.loadtxt(DATA / "light_intensities.txt")
    normals = scipy_io.loadmat(str(DATA / "Normal_gt.mat"))["Normal_gt"]
    cv2 = pytest.importorskip("cv2")
    mask = cv2.imread(str(DATA / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    a, b = pair
    la, lb = lights[a - 1], lights[b - 1]
    slant = math.degrees(0.5 * (math.acos(la[2]) + math.acos(lb[2])))
    tau_a = math.degrees(math.atan2(la[1], la[0]))
    tau_b = math.degrees(math.atan2(lb[1], lb[0]))
    assert abs(tau_a) < 15 and abs(abs(tau_b) - 180) < 15  # light A stands on the +x side
    with np.errstate(divide="ignore", invalid="ignore"):
        true_p = -normals[:, :, 0] / normals[:, :, 2]
    i_a, i_b = _diligent_gray(a, strengths), _diligent_gray(b, strengths)
    p = slope_eq4(i_a, i_b, slant_deg=slant, azimuth_a_deg=tau_a, azimuth_b_deg=tau_b)
    lit = mask & (normals[:, :, 2] > 0.5) & np.isfinite(p)
    assert lit.sum() > 5000
    r = corr2(p[lit], true_p[lit])
    assert r >= minimum
    # the sign convention is pinned: swapping the lights flips the slope
    swapped = slope_eq4(i_b, i_a, slant_deg=slant, azimuth_a_deg=tau_a, azimuth_b_deg=tau_b)
    assert corr2(swapped[lit], true_p[lit]) <= -minimum
    # and the scale is absolute to within the lights' calibration
    assert 0.85 < float(np.median(p[lit] / true_p[lit])) < 1.2
