"""Rig calibration from a reference run: vision.calibration.rigcal and the command."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from config.rig import load_rig, rig_to_toml
from planer.cli import main
from tests.support.vision_boards import render_board
from vision.calibration.rigcal import estimate_rig, fit_slants, log_ratio_from_slope

RUNOUT = (0.0, 2.0, -1.0, 1.0)


def _run(errors, roll_deg, n=4, **kw):
    boards = [render_board(s, slant_a_error_deg=errors[0], slant_b_error_deg=errors[1],
                           roll_deg=roll_deg, runout_um=RUNOUT, noise_dn=2.0, height=240, **kw)
              for s in range(n)]
    return boards


def test_slant_fit_recovers_both_tangents_from_exact_lambert_ratios():
    rng = np.random.default_rng(0)
    ta, tb = math.tan(math.radians(84.0)), math.tan(math.radians(80.5))
    ratios, slopes = [], []
    for _ in range(3):
        p = rng.uniform(-0.0125, 0.0125, 300)
        ratios.append(np.log1p(p * tb) - np.log1p(-p * ta) + rng.normal(0, 1e-3))
        slopes.append(p)
    fa, fb, resid = fit_slants(ratios, slopes)
    assert math.degrees(math.atan(fa)) == pytest.approx(84.0, abs=0.05)
    assert math.degrees(math.atan(fb)) == pytest.approx(80.5, abs=0.05)
    assert resid < 0.01


def test_log_ratio_inverts_the_slope_formula():
    from vision.slope import slope_from_ratio

    p = np.linspace(-0.01, 0.01, 11)
    lr = log_ratio_from_slope(p, slant_a_deg=83.0, slant_b_deg=80.0)
    back = slope_from_ratio(np.exp(lr), slant_deg=83.0, slant_b_deg=80.0)
    assert np.allclose(back, p, atol=1e-12)


@pytest.mark.parametrize(("errors", "roll_deg"), [((2.0, -1.0), 1.5), ((-2.5, 1.5), -0.8),
                                                  ((3.0, 3.0), 2.0)])
def test_reference_run_gives_roll_and_each_slant(errors, roll_deg):
    boards = _run(errors, roll_deg)
    pairs = [(b.image_a, b.image_b, b.counts_a, b.counts_b) for b in boards]
    est = estimate_rig(pairs, boards[0].rig, radius_mm=60.0, speed_mm_s=boards[0].speed_mm_s)
    assert est.roll_deg == pytest.approx(roll_deg, abs=0.05)
    # the mean slant is fixed by the marks' contrast, the difference by a small curvature term
    t_mean = 0.5 * sum(math.tan(math.radians(82.0 + e)) for e in errors)
    assert est.slant_sum_deg == pytest.approx(math.degrees(math.atan(t_mean)), abs=0.1)
    assert est.slant_a_deg == pytest.approx(82.0 + errors[0], abs=0.5)
    assert est.slant_b_deg == pytest.approx(82.0 + errors[1], abs=0.5)
    assert est.pairs_used == len(pairs)


def test_command_writes_the_rig_and_the_calibrated_rig_measures_without_self_calibration(
        tmp_path, capsys):
    errors, roll = (2.5, -1.5), 1.2
    boards = _run(errors, roll, n=5)
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(boards[0].rig))
    argv = ["calibrate-rig"]
    for k, b in enumerate(boards):
        for tag, img in (("a", b.image_a), ("b", b.image_b)):
            path = tmp_path / f"{k}{tag}.png"
            assert cv2.imwrite(str(path), img)
            argv.append(str(path))
    for b in boards:
        argv += ["--counts", f"{b.counts_a},{b.counts_b}"]
    out = tmp_path / "calibrated.toml"
    speed = boards[0].speed_mm_s
    argv += ["--radius-mm", "60", "--feed-mm-s", str(speed), "--rpm",
             str(boards[0].spindle_rpm), "--knives", "4", "--rig", str(rig_file), "--out",
             str(out)]
    assert main(argv) == 0
    report = json.loads(capsys.readouterr()[0])
    assert report["roll_deg"] == pytest.approx(roll, abs=0.05)
    assert report["px_per_mm_factor"] == pytest.approx(1.0, abs=0.01)
    rig = load_rig(out)
    assert rig.camera.roll_deg == pytest.approx(roll, abs=0.05)
    assert (rig.camera.width, rig.camera.height) == (659, 240)
    assert rig.lights.slants_deg[0] == pytest.approx(82.0 + errors[0], abs=0.5)
    assert rig.lights.slants_deg[1] == pytest.approx(82.0 + errors[1], abs=0.5)
    # a new board measured with the calibrated rig alone (no radius): depth right
    from vision.pipeline import Measurer

    board = render_board(9, slant_a_error_deg=errors[0], slant_b_error_deg=errors[1],
                         roll_deg=roll, runout_um=RUNOUT, height=240)
    m = Measurer(rig, board.image_a.shape).measure(
        board.image_a, board.image_b, counts_a=board.counts_a, counts_b=board.counts_b,
        speed_mm_s=board.speed_mm_s)
    i0 = int(np.argmin(np.abs(board.cusps_mm - m.cusps_mm[0])))
    i1 = int(np.argmin(np.abs(board.cusps_mm - m.cusps_mm[-1])))
    assert m.depth_um == pytest.approx(board.depths_um[i0:i1].mean(), rel=0.06)


@pytest.mark.parametrize(("extra", "needle"), [
    (["--counts", "1,2"], "pairs"),
    ([], "no image pairs"),
])
def test_command_errors_are_one_line(tmp_path, capsys, extra, needle):
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(render_board(1, height=40).rig))
    a = tmp_path / "a.png"
    cv2.imwrite(str(a), np.full((40, 659), 100, np.uint8))
    files = [str(a)] if extra else []
    rc = main(["calibrate-rig", *files, *extra, "--radius-mm", "60", "--rig", str(rig_file),
               "--out", str(tmp_path / "o.toml")])
    err = capsys.readouterr()[1]
    assert rc == 2 and err.count("\n") == 1 and needle in err
