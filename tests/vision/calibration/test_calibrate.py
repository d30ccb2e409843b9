"""Camera calibration (seed §4.2): corners, intrinsics, and the ``planer calibrate`` command.

Real data: the 18 webcam photographs in ../shared/data/checkerboard_webcam (skipped when absent),
compared with OpenCV's own plain pipeline run here. Synthetic data: boards rendered through a
known camera with known k1, by inverse mapping of every (supersampled) pixel onto the board.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from config.loading import default_path
from config.rig import load_rig
from planer.cli import main
from vision.calibration.camera import (
    CalibrationResult,
    board_points,
    calibrate,
    find_corners,
    parse_pattern,
    subpix_half_window_px,
)

WEBCAM = Path(__file__).resolve().parents[4] / "shared" / "data" / "checkerboard_webcam"
PATTERN = (7, 7)
K1_FLAGS = cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST


def webcam_images() -> list[Path]:
    files = sorted(WEBCAM.glob("left*.jpg")) if WEBCAM.is_dir() else []
    if len(files) < 3:
        pytest.skip(f"webcam checkerboard images not found in {WEBCAM}")
    return files


# --------------------------------------------------------------------------- reference


@pytest.fixture(scope="module")
def opencv_reference() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """OpenCV's plain pipeline (tutorial settings) on the webcam images, for both models."""
    files = webcam_images()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    obj = np.zeros((49, 3), np.float32)
    obj[:, :2] = np.mgrid[0:7, 0:7].T.reshape(-1, 2)
    img_pts = []
    for f in files:
        gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(gray, PATTERN, None)
        assert found, f
        img_pts.append(cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), crit))
    size = gray.shape[::-1]
    out = {}
    for model, flags in (("k1", K1_FLAGS), ("full", 0)):
        _, k_mat, dist, _, _ = cv2.calibrateCamera(
            [obj] * len(img_pts), img_pts, size, None, None, flags=flags
        )
        out[model] = (k_mat, dist.ravel())
    return out


def run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(["calibrate", *args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_agrees(rig_path: Path, k_mat: np.ndarray, dist: np.ndarray, model: str) -> None:
    cam = load_rig(rig_path).camera
    assert cam.fx == pytest.approx(k_mat[0, 0], rel=0.01)
    assert cam.fy == pytest.approx(k_mat[1, 1], rel=0.01)
    if model == "k1":
        assert abs(cam.dist[0] - dist[0]) < 0.01
        assert cam.dist[1:] == (0.0, 0.0, 0.0, 0.0)
        # the principal point is estimated, not put at the image centre (320, 240)
        assert cam.cx == pytest.approx(k_mat[0, 2], abs=3.0)
        assert cam.cy == pytest.approx(k_mat[1, 2], abs=3.0)
        assert abs(cam.cx - 320.0) > 50.0


# --------------------------------------------------------------------------- webcam


@pytest.mark.parametrize("model", ["k1", "full"])
def test_webcam_agrees_with_opencv(model, opencv_reference, tmp_path, capsys):
    files = webcam_images()
    out = tmp_path / "rig.toml"
    code, stdout, err = run_cli(
        [*map(str, files), "--pattern", "7x7", "--model", model, "--out", str(out)], capsys
    )
    assert code == 0, err
    assert err == ""
    assert f"{len(files)} used, 0 skipped" in stdout
    assert_agrees(out, *opencv_reference[model], model)


def test_webcam_with_corrupt_and_blank_files(opencv_reference, tmp_path, capsys):
    files = webcam_images()
    corrupt = tmp_path / "corrupt.jpg"
    corrupt.write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg \x00\x13\x37")
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 200, np.uint8))
    missing = tmp_path / "missing.jpg"
    images = [str(files[0]), str(corrupt), *map(str, files[1:5]), str(blank), str(missing)]
    images += list(map(str, files[5:]))
    out = tmp_path / "rig.toml"
    code, stdout, err = run_cli([*images, "--pattern", "7x7", "--out", str(out)], capsys)
    assert code == 0, err
    lines = err.strip().splitlines()
    assert len(lines) == 3
    for bad, line in zip((corrupt, blank, missing), lines, strict=True):
        assert str(bad) in line and "warning" in line
    assert f"{len(files)} used, 3 skipped" in stdout
    assert_agrees(out, *opencv_reference["k1"], "k1")


def test_too_few_images_fails_with_one_line(tmp_path, capsys):
    files = webcam_images()
    corrupt = tmp_path / "corrupt.jpg"
    corrupt.write_bytes(b"garbage")
    out = tmp_path / "rig.toml"
    out.write_text("previous contents\n")
    code, _, err = run_cli(
        [str(files[0]), str(files[1]), str(corrupt), "--pattern", "7x7", "--out", str(out)],
        capsys,
    )
    assert code != 0
    error_lines = [ln for ln in err.splitlines() if "warning" not in ln]
    assert len(error_lines) == 1
    assert "error" in error_lines[0] and "2 of 3" in error_lines[0]
    assert out.read_text() == "previous contents\n"  # nothing half-written


def test_wrong_pattern_finds_no_board(tmp_path, capsys):
    files = webcam_images()[:3]
    code, _, err = run_cli(
        [*map(str, files), "--pattern", "9x6", "--out", str(tmp_path / "r.toml")], capsys
    )
    assert code == 2
    assert err.count("no 9x6 checkerboard") == 3
    assert not (tmp_path / "r.toml").exists()


def test_find_corners_matches_reference_corners():
    """The adaptive sub-pixel window changes the tutorial's corners by well under a pixel."""
    files = webcam_images()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    for f in files[:4]:
        gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ours = find_corners(gray, pattern=PATTERN)
        _, c = cv2.findChessboardCorners(gray, PATTERN, None)
        ref = cv2.cornerSubPix(gray, c, (11, 11), (-1, -1), crit).reshape(-1, 2)
        assert ours is not None and ours.shape == (49, 2) and ours.dtype == np.float32
        assert np.abs(ours - ref).max() < 0.5
        colour = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
        np.testing.assert_allclose(find_corners(colour, pattern=PATTERN), ours, atol=1e-4)


# --------------------------------------------------------------------------- synthetic

TRUE_K = np.array([[820.0, 0.0, 290.0], [0.0, 815.0, 250.0], [0.0, 0.0, 1.0]])
TRUE_K1 = -0.22
SIZE = (640, 480)
SQUARE_MM = 4.0


def render_board(rvec, tvec, *, ss=2, blur_px=0.6, noise=2.0, seed=0) -> np.ndarray:
    """Image of a 7x7-corner board (8x8 squares) through TRUE_K with radial k1 = TRUE_K1.

    Inverse mapping: each sub-pixel is undistorted (fixed-point inversion of
    r_d = r_u (1 + k1 r_u^2)), its ray is cut with the board plane, and the square it hits gives
    its grey level; ss x ss sub-pixels are averaged per pixel.
    """
    w, h = SIZE
    fx, fy, cx, cy = TRUE_K[0, 0], TRUE_K[1, 1], TRUE_K[0, 2], TRUE_K[1, 2]
    off = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(w)[:, None] + off).ravel()
    v = (np.arange(h)[:, None] + off).ravel()
    xd, yd = np.meshgrid((u - cx) / fx, (v - cy) / fy)
    xu, yu = xd.copy(), yd.copy()
    for _ in range(25):
        f = 1.0 + TRUE_K1 * (xu * xu + yu * yu)
        xu, yu = xd / f, yd / f
    rot, _ = cv2.Rodrigues(np.asarray(rvec, float))
    t = np.asarray(tvec, float)
    n = rot[:, 2]
    s = (n @ t) / (n[0] * xu + n[1] * yu + n[2])
    pts = np.stack([s * xu - t[0], s * yu - t[1], s - t[2]], axis=-1)
    i = np.floor(pts @ rot[:, 0] / SQUARE_MM)
    j = np.floor(pts @ rot[:, 1] / SQUARE_MM)
    on_board = (i >= -1) & (i <= 6) & (j >= -1) & (j <= 6) & (s > 0)
    dark = on_board & ((i + j) % 2 == 0)
    img = np.where(dark, 35.0, 215.0).reshape(h, ss, w, ss).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img += np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def board_poses() -> list[tuple[np.ndarray, np.ndarray]]:
    """Tilted views spread over the field (corners of the image carry the distortion)."""
    centre = np.array([3.0, 3.0, 0.0]) * SQUARE_MM
    poses = []
    for k, (ax, ay, ox, oy, z) in enumerate(
        [
            (0.0, 0.0, 0.0, 0.0, 170.0),
            (0.45, 0.0, -0.12, -0.08, 150.0),
            (-0.4, 0.2, 0.13, 0.09, 160.0),
            (0.1, 0.5, -0.1, 0.1, 150.0),
            (-0.2, -0.45, 0.12, -0.1, 155.0),
            (0.35, 0.35, 0.0, 0.11, 175.0),
            (-0.3, -0.3, -0.14, 0.0, 165.0),
            (0.2, -0.3, 0.15, 0.0, 150.0),
        ]
    ):
        rvec = np.array([ax, ay, 0.3 * (k % 3 - 1)])
        rot, _ = cv2.Rodrigues(rvec)
        tvec = -rot @ centre + np.array([ox * z, oy * z, z])
        poses.append((rvec, tvec))
    return poses


def true_corners(rvec, tvec) -> np.ndarray:
    dist = np.array([TRUE_K1, 0.0, 0.0, 0.0, 0.0])
    pts, _ = cv2.projectPoints(board_points(PATTERN, SQUARE_MM), rvec, tvec, TRUE_K, dist)
    return pts.reshape(-1, 2)


@pytest.fixture(scope="module")
def synthetic_views() -> list[tuple[np.ndarray, np.ndarray]]:
    """(image, true corners) of each pose."""
    views = []
    for k, (rvec, tvec) in enumerate(board_poses()):
        truth = true_corners(rvec, tvec)
        assert truth.min() > 10 and truth[:, 0].max() < SIZE[0] - 10
        assert truth[:, 1].max() < SIZE[1] - 10
        views.append((render_board(rvec, tvec, seed=k), truth))
    return views


def test_synthetic_corners_are_subpixel(synthetic_views):
    for image, truth in synthetic_views:
        found = find_corners(image, pattern=PATTERN)
        assert found is not None
        # same grid up to the board's symmetry: match each true corner to its nearest
        d = np.linalg.norm(found[None, :, :] - truth[:, None, :], axis=2).min(axis=1)
        assert d.max() < 0.5
        assert d.mean() < 0.2
    # over all views (the renderer's 2x2 supersampling leaves a few hundredths of aliasing)
    all_d = [np.linalg.norm(find_corners(i, pattern=PATTERN)[None] - t[:, None], axis=2).min(1)
             for i, t in synthetic_views]
    assert np.mean(np.concatenate(all_d)) < 0.1


def test_synthetic_calibration_recovers_camera(synthetic_views):
    corners = [find_corners(img, pattern=PATTERN) for img, _ in synthetic_views]
    res = calibrate(corners, SIZE, pattern=PATTERN, square_mm=SQUARE_MM, model="k1")
    assert isinstance(res, CalibrationResult)
    assert res.n_images == len(synthetic_views) == len(res.per_image_error_px)
    assert res.fx == pytest.approx(TRUE_K[0, 0], rel=0.005)
    assert res.fy == pytest.approx(TRUE_K[1, 1], rel=0.005)
    # the principal point is the weakest parameter of 8 views: a few pixels
    assert res.cx == pytest.approx(TRUE_K[0, 2], abs=8.0)
    assert res.cy == pytest.approx(TRUE_K[1, 2], abs=8.0)
    assert res.k1 == pytest.approx(TRUE_K1, abs=0.01)
    assert res.dist[1:] == (0.0, 0.0, 0.0, 0.0)
    assert res.rms_px < 0.2
    # rms over all corners is the quadratic mean of the per-image errors (same corner count)
    assert res.rms_px == pytest.approx(np.sqrt(np.mean(np.square(res.per_image_error_px))), 1e-4)
    np.testing.assert_allclose(res.camera_matrix(), [[res.fx, 0, res.cx], [0, res.fy, res.cy],
                                                     [0, 0, 1]])
    # exact corners give the exact camera
    exact = calibrate([t for _, t in synthetic_views], SIZE, pattern=PATTERN,
                      square_mm=SQUARE_MM, model="full")
    assert exact.fx == pytest.approx(TRUE_K[0, 0], rel=1e-4)
    assert exact.k1 == pytest.approx(TRUE_K1, abs=1e-3)
    assert exact.rms_px < 1e-3


def test_cli_keeps_base_rig_values(synthetic_views, tmp_path, capsys, monkeypatch):
    paths = []
    for k, (image, _) in enumerate(synthetic_views[:5]):
        p = tmp_path / f"board{k}.png"
        cv2.imwrite(str(p), image)
        paths.append(str(p))
    base = tmp_path / "base.toml"
    base.write_text(
        "[camera]\nfx = 1.0\nfy = 1.0\ncx = 0.0\ncy = 0.0\ndist = [0.3, 0.1, 0.0, 0.0, 0.0]\n"
        "px_per_mm = 17.5\nexposure_ms = 0.25\n[lights]\nslant_deg = 80.0\n"
        "azimuth_a_deg = 5.0\nazimuth_b_deg = 185.0\n[encoder]\npx_per_count = 0.4\n"
        "counter_bits = 16\n"
    )
    out = tmp_path / "new.toml"
    code, stdout, err = run_cli(
        [*paths, "--pattern", "7x7", "--square-mm", "4", "--rig", str(base), "--out", str(out)],
        capsys,
    )
    assert code == 0, err
    rig, old = load_rig(out), load_rig(base)
    assert rig.lights == old.lights and rig.encoder == old.encoder
    assert rig.camera.px_per_mm == 17.5 and rig.camera.exposure_ms == 0.25
    assert rig.camera.fx == pytest.approx(TRUE_K[0, 0], rel=0.01)
    assert rig.camera.dist[0] == pytest.approx(TRUE_K1, abs=0.02)
    assert rig.camera.dist[1:] == (0.0, 0.0, 0.0, 0.0)
    assert "5 used, 0 skipped" in stdout and f"{rig.camera.fx:.2f}" in stdout

    # without --rig: the shipped defaults for everything but the intrinsics; --px-per-mm wins
    out2 = tmp_path / "new2.toml"
    code, _, err = run_cli(
        [*paths, "--pattern", "7x7", "--px-per-mm", "9.5", "--out", str(out2)], capsys
    )
    assert code == 0, err
    rig2, default = load_rig(out2), load_rig(default_path("rig.toml"))
    assert rig2.lights == default.lights and rig2.encoder == default.encoder
    assert rig2.camera.exposure_ms == default.camera.exposure_ms
    assert rig2.camera.px_per_mm == 9.5
    assert rig2.camera.fx == pytest.approx(rig.camera.fx, rel=1e-9)  # square size is irrelevant
    assert list(tmp_path.glob(".*.tmp")) == []

    # the disk fails while the rig file is written: the old file stays whole, no leftovers
    import core.fileio

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    before = out2.read_bytes()
    monkeypatch.setattr(core.fileio.os, "fsync", disk_full)
    code, _, err = run_cli([*paths, "--pattern", "7x7", "--out", str(out2)], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "No space left" in err
    assert out2.read_bytes() == before
    assert list(tmp_path.glob(".*.tmp")) == []


@pytest.mark.parametrize(
    "args, words",
    [
        (["--pattern", "7by7"], "--pattern"),
        (["--pattern", "7x7", "--square-mm", "0"], "--square-mm"),
        (["--pattern", "7x7", "--px-per-mm", "-2"], "--px-per-mm"),
        (["--pattern", "7x7", "--rig", "/nonexistent/rig.toml"], "rig.toml"),
    ],
)
def test_cli_bad_options_fail_with_one_line(args, words, tmp_path, capsys):
    img = tmp_path / "a.png"
    cv2.imwrite(str(img), np.zeros((40, 40), np.uint8))
    code, _, err = run_cli([str(img), *args, "--out", str(tmp_path / "o.toml")], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and words in err
    assert not (tmp_path / "o.toml").exists()


# --------------------------------------------------------------------------- pure helpers


@pytest.mark.parametrize(
    "text, expected",
    [("7x7", (7, 7)), ("9x6", (9, 6)), (" 10X4 ", (10, 4)), ("2x2", (2, 2)), ("7×5", (7, 5))],
)
def test_parse_pattern_good(text, expected):
    assert parse_pattern(text) == expected


@pytest.mark.parametrize("text", ["", "7", "7x", "x7", "7x7x7", "7,7", "1x7", "7x0", "-7x7",
                                  "7.5x7", "seven"])
def test_parse_pattern_bad(text):
    with pytest.raises(ValueError, match="--pattern"):
        parse_pattern(text)


def test_board_points_layout():
    pts = board_points((4, 3), 2.5)
    assert pts.shape == (12, 3)
    np.testing.assert_array_equal(pts[:, 2], 0.0)
    np.testing.assert_allclose(pts[1] - pts[0], [2.5, 0.0, 0.0])  # x runs fastest
    np.testing.assert_allclose(pts[4] - pts[0], [0.0, 2.5, 0.0])
    np.testing.assert_allclose(pts[-1], [7.5, 5.0, 0.0])
    with pytest.raises(ValueError, match="square_mm"):
        board_points((4, 3), 0.0)
    with pytest.raises(ValueError, match="pattern"):
        board_points((1, 3), 1.0)


def test_find_corners_without_board_is_none():
    rng = np.random.default_rng(1)
    assert find_corners(np.full((120, 160), 90, np.uint8)) is None
    assert find_corners(rng.integers(0, 256, (120, 160), dtype=np.uint8)) is None
    with pytest.raises(ValueError, match="image"):
        find_corners(np.zeros((4, 5, 6, 7)))


def test_subpix_window_stays_inside_the_squares():
    for spacing, expected in [(40.0, 11), (18.0, 10), (12.0, 7), (5.0, 3), (2.0, 2)]:
        grid = np.stack(np.meshgrid(np.arange(7.0), np.arange(7.0)), -1).reshape(-1, 2)
        half = subpix_half_window_px(grid * spacing, PATTERN)
        assert half == expected
        assert half < spacing or half == 2


def test_calibrate_argument_checks():
    truth = [true_corners(r, t) for r, t in board_poses()[:3]]
    with pytest.raises(ValueError, match="2 usable"):
        calibrate([truth[0], None, truth[1]], SIZE, pattern=PATTERN)
    with pytest.raises(ValueError, match="model"):
        calibrate(truth, SIZE, pattern=PATTERN, model="k2")
    with pytest.raises(ValueError, match=r"corner_sets\[1\]"):
        calibrate([truth[0], truth[1][:-1], truth[2]], SIZE, pattern=PATTERN)
    with pytest.raises(ValueError, match="image_size"):
        calibrate(truth, (640,), pattern=PATTERN)
    with pytest.raises(ValueError, match="square_mm"):
        calibrate(truth, SIZE, pattern=PATTERN, square_mm=-1.0)
    bad = truth[2].copy()
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        calibrate([truth[0], truth[1], bad], SIZE, pattern=PATTERN)
