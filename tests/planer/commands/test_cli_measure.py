"""``planer measure`` end to end: PNG files in, one JSON object out; one-line errors."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from config.rig import rig_to_toml
from planer.cli import main
from plant_sim.rendering import scenarios


@pytest.fixture(scope="module")
def board():
    return scenarios.board_pair(seed=7, species="oak", k1=-0.15, encoder_error_px=6.0,
                                imbalance=0.06)


@pytest.fixture()
def files(tmp_path, board):
    rig, pair = board
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    assert cv2.imwrite(str(a), pair.image_a) and cv2.imwrite(str(b), pair.image_b)
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(rig))
    return {"a": a, "b": b, "rig": rig_file, "tmp": tmp_path, "pair": pair}


def _args(f, *, a=None, b=None, counts=None, extra=()):
    pair = f["pair"]
    ca, cb = counts if counts is not None else (pair.counts_a, pair.counts_b)
    return ["measure", str(a or f["a"]), str(b or f["b"]), "--counts-a", str(ca),
            "--counts-b", str(cb), "--rig", str(f["rig"]), *extra]


def test_good_pair_prints_one_json_object(files, capsys):
    pair = files["pair"]
    plot = files["tmp"] / "profile.png"
    rc = main(_args(files, extra=("--speed-mm-s", str(pair.speed_mm_s), "--plot", str(plot))))
    out, err = capsys.readouterr()
    assert rc == 0 and err == ""
    assert out.count("\n") == 1
    data = json.loads(out)
    for key in ("x_mm", "height_um", "pitch_mm", "mark_widths_mm", "uniformity_cv", "depth_um",
                "shift_px"):
        assert key in data
    truth = pair.truth
    assert abs(data["shift_px"] - truth.shift_px) < 0.5
    true = truth.metrics(data["cusps_mm"][0] - 0.1, data["cusps_mm"][-1] + 0.1)
    assert data["pitch_mm"] == pytest.approx(true["pitch_mm"], rel=0.01)
    h_true = np.interp(data["x_mm"], truth.x_mm, truth.height_um)
    assert np.corrcoef(data["height_um"], h_true)[0, 1] > 0.97
    img = cv2.imread(str(plot))
    assert img is not None and img.shape[0] > 200 and img.shape[1] > 400


def test_flat_field_option(files, capsys):
    _, flat = scenarios.board_pair(seed=8, species="oak", k1=-0.15, imbalance=0.06,
                                   radius_mm=1e7)
    fa, fb = files["tmp"] / "fa.png", files["tmp"] / "fb.png"
    cv2.imwrite(str(fa), flat.image_a)
    cv2.imwrite(str(fb), flat.image_b)
    rc = main(_args(files, extra=("--flat-a", str(fa), "--flat-b", str(fb))))
    out, err = capsys.readouterr()
    assert rc == 0 and err == ""
    assert json.loads(out)["pitch_mm"] > 0


def _fails(capsys, argv, *words):
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc != 0
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("planer measure: error:")
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def test_missing_file(files, capsys):
    _fails(capsys, _args(files, a=files["tmp"] / "nope.png"), "nope.png", "not found")


def test_corrupt_file(files, capsys):
    bad = files["tmp"] / "bad.png"
    data = files["b"].read_bytes()
    bad.write_bytes(data[: len(data) // 3])
    _fails(capsys, _args(files, b=bad), "bad.png")
    junk = files["tmp"] / "junk.png"
    junk.write_bytes(b"this is not a png" * 50)
    _fails(capsys, _args(files, a=junk), "junk.png")


def test_images_of_different_sizes(files, capsys):
    small = files["tmp"] / "small.png"
    cv2.imwrite(str(small), files["pair"].image_b[:, :600])
    _fails(capsys, _args(files, b=small), "differ in size")


def test_all_black_pair(files, capsys):
    black = files["tmp"] / "black.png"
    cv2.imwrite(str(black), np.zeros_like(files["pair"].image_a))
    _fails(capsys, _args(files, a=black, b=black), "black")


def test_saturated_pair(files, capsys):
    white = files["tmp"] / "white.png"
    cv2.imwrite(str(white), np.full_like(files["pair"].image_a, 255))
    _fails(capsys, _args(files, a=white, b=white), "saturated")


def test_counts_giving_a_shift_larger_than_the_image(files, capsys):
    _fails(capsys, _args(files, counts=(1000, 1000 + 2000)), "larger than the image")


@pytest.mark.parametrize(
    "old, new, key",
    [
        ("slant_deg = 82.0", "slant_deg = 95.0", "lights.slant_deg"),
        ("px_per_count = 0.625", "px_per_count = -1.0", "encoder.px_per_count"),
        ("fx = 1400.0", 'fx = "wide"', "camera.fx"),
        ("px_per_mm = 12.5\n", "px_per_mm = 0.0\n", "camera.px_per_mm"),
    ],
)
def test_bad_rig_value(files, capsys, old, new, key):
    text = files["rig"].read_text()
    assert old in text
    files["rig"].write_text(text.replace(old, new))
    _fails(capsys, _args(files), key)


def test_flat_options_go_together(files, capsys):
    _fails(capsys, _args(files, extra=("--flat-a", str(files["a"]))), "--flat-a")


@pytest.mark.parametrize("speed", ["-800", "1e9"])
def test_implausible_speed_is_refused_in_one_line(files, capsys, speed):
    rc = main(_args(files, extra=("--speed-mm-s", speed)))
    _, err = capsys.readouterr()
    assert rc == 2 and err.count("\n") == 1 and "--speed-mm-s" in err and f"{float(speed):g}" in err


def test_new_keys_and_machine_facts(files, capsys):
    pair = files["pair"]
    rc = main(_args(files, extra=("--speed-mm-s", str(pair.speed_mm_s))))
    off = json.loads(capsys.readouterr()[0])
    assert rc == 0 and off["calibration"]["state"] == "off"
    assert off["kinematic_depth_um"] is None and "roll_deg" in off
    rc = main(_args(files, extra=("--speed-mm-s", str(pair.speed_mm_s), "--radius-mm", "60",
                                  "--knives", "4", "--rpm", "6000")))
    on = json.loads(capsys.readouterr()[0])
    assert rc == 0 and on["calibration"]["state"] in ("applied", "untrusted")
    assert on["kinematic_depth_um"] > 0 and len(on["knife_widths_mm"]) == 4
    assert on["feed_per_pass_mm"] == pytest.approx(pair.speed_mm_s * 60 / (6000 * 4), rel=1e-4)
    for key in off:
        assert key in on


def test_defects_and_grade_in_the_json_contract(tmp_path, capsys):
    """``defects`` (objects with the contract's keys), ``grade`` and ``grade_reason``."""
    from tests.support.defect_boards import Defects, render_defect_board

    board = render_defect_board(11, defects=Defects(chips_um=(120.0,)), noise_dn=3.0)
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    assert cv2.imwrite(str(a), board.image_a) and cv2.imwrite(str(b), board.image_b)
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(board.rig))
    rc = main(["measure", str(a), str(b), "--counts-a", str(board.counts_a), "--counts-b",
               str(board.counts_b), "--rig", str(rig_file)])
    out, err = capsys.readouterr()
    assert rc == 0 and err == ""
    data = json.loads(out)
    assert isinstance(data["grade"], int) and 1 <= data["grade"] <= 5
    assert isinstance(data["grade_reason"], str) and data["grade_reason"]
    assert data["defects"], "a 120 um chip mark must be found"
    kinds = {"torn_grain", "raised_grain", "fuzzy_grain", "chip_mark", "knife_nick", "chatter",
             "snipe"}
    for d in data["defects"]:
        assert set(d) == {"kind", "x_mm", "y_mm", "length_mm", "width_mm", "depth_um",
                          "confidence"}
        assert d["kind"] in kinds and 0.0 <= d["confidence"] <= 1.0
        assert d["depth_um"] is None or isinstance(d["depth_um"], float)
    chip = board.placed[0]
    ppm = board.rig.camera.px_per_mm
    true_x, true_y = chip.x_mm, board.rig.camera.cy / ppm + chip.y_mm  # roll 0
    assert any(d["kind"] == "chip_mark" and math.hypot(d["x_mm"] - true_x, d["y_mm"] - true_y)
               <= 2.0 for d in data["defects"])
    assert data["grade"] >= 2
