"""The measurement's front end: binning, undistortion, shear and rotation in one table each."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from config.rig import Camera
from vision.calibration.undistort import Undistorter
from vision.front_end import FrontEnd

W, H = 400, 300


def _camera(k1: float, roll_deg: float = 0.0) -> Camera:
    return Camera(fx=800.0, fy=800.0, cx=(W - 1) / 2, cy=(H - 1) / 2,
                  dist=(k1, 0.0, 0.0, 0.0, 0.0), px_per_mm=12.5, roll_deg=roll_deg)


def _stripes(xi: np.ndarray) -> np.ndarray:
    return 120.0 + 50.0 * np.sin(2 * np.pi * xi / 29.0) + 20.0 * np.sin(2 * np.pi * xi / 11.3)


def _image(cam: Camera, roll_deg: float) -> np.ndarray:
    """Distorted image of stripes that run at ``roll_deg`` from the columns (marks)."""
    k = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    cols, rows = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    pts = np.stack([cols.ravel(), rows.ravel()], axis=1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    und = cv2.undistortPoints(pts, k, np.array(cam.dist), None, k, criteria=crit).reshape(H, W, 2)
    r = math.radians(roll_deg)
    xi = (und[..., 0] - cam.cx) * math.cos(r) + (und[..., 1] - cam.cy) * math.sin(r)
    return _stripes(xi).astype(np.float32)


@pytest.mark.parametrize("k1", [0.0, -0.2, 0.15])
def test_unsheared_profile_is_the_mean_of_the_undistorted_image(k1):
    cam = _camera(k1)
    front = FrontEnd(cam, (H, W), max_roll_deg=5.0)
    img = _image(cam, 0.0)
    prof = front.profile(front.bin(img, "image"), 0.0) / front.k0
    c0, c1 = front.columns
    full = Undistorter(cam, (H, W))(img)[40 : H - 40, c0:c1].mean(axis=0)
    inner = slice(5, front.width - 5)
    assert np.abs(prof[inner] - full[inner]).max() < 1.0  # of +-70
    expect = _stripes(np.arange(c0, c1) - cam.cx)
    assert np.abs(prof[inner] - expect[inner]).max() < 2.0


@pytest.mark.parametrize("roll_deg", [-3.0, 1.0, 4.0])
def test_sheared_profile_averages_along_the_marks(roll_deg):
    cam = _camera(-0.1)
    front = FrontEnd(cam, (H, W), max_roll_deg=5.0)
    img = _image(cam, roll_deg)
    binned = front.bin(img, "image")
    margin = front.margin_px(roll_deg)
    assert margin > 0
    prof = front.profile(binned, roll_deg) / front.k0
    c0, _ = front.columns
    # sample u' lies (u' - cx) cos(roll) along the feed from the centre
    xi = (c0 + np.arange(front.width) - cam.cx) * math.cos(math.radians(roll_deg))
    inner = slice(margin + 3, front.width - margin - 3)
    err = np.abs(prof[inner] - _stripes(xi)[inner]).max()
    assert err < 2.5
    # without the shear the marks smear over the rows: far from the stripes
    plain = front.profile(binned, 0.0) / front.k0
    assert np.abs(plain[inner] - _stripes(xi)[inner]).max() > 3 * err


@pytest.mark.parametrize("roll_deg", [0.5, 2.0, 5.0])
def test_profile_bins_keep_the_smear_limits(roll_deg):
    cam = _camera(-0.3)
    front = FrontEnd(cam, (H, W), max_roll_deg=5.0, roll_smear_px=0.5, max_drift_px=0.25)
    m = front.profile_factor(roll_deg, shear=True)
    k = m * front.k0
    assert k * math.tan(math.radians(roll_deg)) <= 0.5 + 1e-9 or m == 1
    assert k * front.undistort.drift_px_per_row <= 0.25 + 1e-9 or m == 1
    assert front.profile_factor(roll_deg, shear=False) >= m


def test_texture_rows_are_made_on_demand_and_agree_with_all_of_them():
    cam = _camera(-0.12)
    front = FrontEnd(cam, (H, W), max_roll_deg=5.0, texture_rows=40)
    rng = np.random.default_rng(3)
    img = (100 + 20 * rng.standard_normal((H, W))).clip(1, 255).astype(np.uint8)
    binned = front.bin(img, "image")
    for roll in (0.0, 2.5):
        prof = front.profile(binned, 0.0)
        tex = front.texture(binned, roll, prof)
        full = np.asarray(tex)
        assert full.shape == tex.shape and full.dtype == np.float32
        if roll == 0.0:
            np.testing.assert_allclose(tex[::3], full[::3], rtol=0, atol=1e-6)
            # shading-free: each column averages to ~0 over the rows
            assert np.abs(full.mean(axis=0)).max() < 0.2
        else:  # rotated rows are divided by their own profile: exactly zero-mean columns
            np.testing.assert_allclose(full.mean(axis=0), 0.0, atol=1e-5)
    with pytest.raises(TypeError):
        front.texture(binned, 0.0, front.profile(binned, 0.0))[3]


def test_group_means_are_undistorted_every_second_column():
    cam = _camera(-0.2)
    front = FrontEnd(cam, (H, W), max_roll_deg=5.0, groups=12)
    img = _image(cam, 0.0)
    groups = front.group_means(front.bin(img, "a"), front.bin(img, "b"))
    step = front.group_step
    assert step == 2 and groups.shape == (2, 12, front.width // step)
    c0, _ = front.columns
    # column p is the mean of undistorted columns c0 + 2p and c0 + 2p + 1
    u = c0 + step * np.arange(groups.shape[2]) + 0.5
    expect = 0.5 * (_stripes(u - 0.5 - cam.cx) + _stripes(u + 0.5 - cam.cx)) * front.k0
    inner = slice(4, groups.shape[2] - 4)
    assert np.abs(groups[0][:, inner] - expect[inner]).max() < 3.0 * front.k0
    np.testing.assert_array_equal(groups[0], groups[1])


def test_black_and_saturated_images_are_judged_from_the_groups():
    front = FrontEnd(_camera(-0.1), (H, W), max_roll_deg=5.0)
    assert front.bin(np.zeros((H, W), np.uint8), "a").level == 0.0
    assert front.bin(np.full((H, W), 255, np.uint8), "a").saturated
    ok = front.bin(np.full((H, W), 128, np.uint8), "a")
    assert ok.level == pytest.approx(128 / 255) and not ok.saturated
    with pytest.raises(ValueError, match="image"):
        front.bin(np.zeros((H, W + 1), np.uint8), "image")
