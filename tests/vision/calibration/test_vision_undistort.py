"""Lens correction: full-frame undistortion and the binned fast path."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from config.rig import Camera
from vision.calibration.undistort import Undistorter, bin_factor_for

W, H = 320, 240


def _camera(k1: float) -> Camera:
    return Camera(fx=700.0, fy=700.0, cx=(W - 1) / 2, cy=(H - 1) / 2,
                  dist=(k1, 0.0, 0.0, 0.0, 0.0), px_per_mm=12.5)


def _stripes(u: np.ndarray) -> np.ndarray:
    return 120.0 + 60.0 * np.sin(2 * np.pi * u / 23.0) + 30.0 * np.sin(2 * np.pi * u / 7.3)


def _distorted_stripes(cam: Camera) -> np.ndarray:
    """A distorted image of vertical stripes f(u) drawn in the undistorted frame."""
    k = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    cols, rows = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    pts = np.stack([cols.ravel(), rows.ravel()], axis=1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    und = cv2.undistortPoints(pts, k, np.array(cam.dist), None, k, criteria=crit)
    return _stripes(und.reshape(H, W, 2)[..., 0]).astype(np.float32)


def test_zero_distortion_is_identity_and_bins_are_row_sums():
    cam = _camera(0.0)
    und = Undistorter(cam, (H, W))
    img = np.random.default_rng(0).integers(0, 256, (H, W), dtype=np.uint8)
    np.testing.assert_array_equal(und(img), img)
    k = und.bin_rows
    assert k == 16  # nothing limits the bins
    rows = und.binned_rows(img)
    assert rows.dtype == np.uint16 and rows.shape == (H // k, W)
    r0 = (H - (H // k) * k) // 2
    expect = img[r0 : r0 + (H // k) * k].reshape(H // k, k, W).sum(axis=1)
    np.testing.assert_array_equal(rows, expect)


@pytest.mark.parametrize("k1", [-0.3, -0.12, 0.2])
def test_undistortion_straightens_columns(k1):
    cam = _camera(k1)
    und = Undistorter(cam, (H, W))
    img = _distorted_stripes(cam)
    out = und(img)
    c0, c1 = und.columns
    band = slice(20, H - 20)
    cols = np.arange(c0 + 5, c1 - 5)
    expect = _stripes(cols.astype(float))
    got = out[band][:, cols]
    assert np.abs(got - expect[None, :]).max() < 6.0  # bilinear on a 7.3 px stripe
    # the distorted image itself is far from straight
    assert np.abs(img[band][:, cols] - expect[None, :]).max() > 20.0


@pytest.mark.parametrize("k1", [-0.3, 0.2])
def test_binned_path_matches_full_undistortion(k1):
    cam = _camera(k1)
    und = Undistorter(cam, (H, W))
    assert 1 <= und.bin_rows <= 16
    # the drift across one bin stays under the smear limit
    assert und.drift_px_per_row * und.bin_rows <= 0.25 + 1e-9
    img = _distorted_stripes(cam)
    rows = und.binned_rows(img)[und.row_band] / und.bin_rows
    c0, c1 = und.columns
    cols = np.arange(c0 + 5, c1 - 5)
    expect = _stripes(cols.astype(float))
    assert np.abs(rows[:, cols] - expect[None, :]).max() < 6.0
    # column means agree with those of the fully undistorted image
    full = und(img)[20 : H - 20][:, cols].mean(axis=0)
    assert np.abs(rows[:, cols].mean(axis=0) - full).max() < 1.5


def test_stronger_distortion_bins_fewer_rows():
    weak = Undistorter(_camera(-0.05), (H, W))
    strong = Undistorter(_camera(-0.6), (H, W))
    assert strong.drift_px_per_row > weak.drift_px_per_row
    assert strong.bin_rows <= weak.bin_rows
    assert bin_factor_for(0.0) == 8
    assert bin_factor_for(0.05, max_smear_px=0.25) == 5
    assert bin_factor_for(1.0) == 1


def test_undistorter_checks_shapes():
    und = Undistorter(_camera(-0.1), (H, W))
    with pytest.raises(ValueError, match="shape"):
        und(np.zeros((H, W + 1), np.uint8))
    with pytest.raises(ValueError, match="shape"):
        Undistorter(_camera(-0.1), (H,))  # type: ignore[arg-type]
