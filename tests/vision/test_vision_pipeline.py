"""The whole measurement on simulated boards: accuracy against the truth, and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.errors import MeasurementError
from plant_sim.rendering import scenarios
from vision.marks import corr2
from vision.pipeline import Measurement, Measurer, measure_pair


def _measure(rig, pair, **kwargs) -> Measurement:
    measurer = Measurer(rig, pair.image_a.shape, **kwargs)
    return measurer.measure(
        pair.image_a, pair.image_b, counts_a=pair.counts_a, counts_b=pair.counts_b,
        speed_mm_s=pair.speed_mm_s,
    )


def _check_against_truth(result: Measurement, pair, *, min_corr: float) -> dict[str, float]:
    truth = pair.truth
    true_h = np.interp(result.x_mm, truth.x_mm, truth.height_um)
    corr = corr2(result.height_um, true_h)
    # the true marks over the same x range as the measured complete marks
    tol = min(0.1, 0.3 * float(np.min(result.mark_widths_mm)))
    true = truth.metrics(result.cusps_mm[0] - tol, result.cusps_mm[-1] + tol)
    report = {
        "corr": corr,
        "shift_err_px": result.shift_px - truth.shift_px,
        "pitch_rel": result.pitch_mm / true["pitch_mm"] - 1.0,
        "cv_err": result.uniformity_cv - true["uniformity_cv"],
        "depth_rel": result.depth_um / true["depth_um"] - 1.0,
    }
    assert true["n_marks"] == len(result.mark_widths_mm), report
    assert corr >= min_corr, report
    assert abs(report["shift_err_px"]) <= 0.5, report
    assert abs(report["pitch_rel"]) <= 0.01, report
    assert abs(report["cv_err"]) <= 0.03, report
    assert abs(report["depth_rel"]) <= 0.15, report
    np.testing.assert_allclose(result.cusps_mm, true["cusps_mm"], atol=0.05)
    return report


CASES = {
    # name: (board_pair keyword arguments, minimum profile correlation)
    "beech-baseline": ({"species": "beech"}, 0.97),
    "oak-2.5mm-1-knife": ({"species": "oak", "pitch_mm": 2.5, "knives": 1}, 0.97),
    "spruce-1mm-6-knives-runout": (
        {"species": "spruce", "pitch_mm": 1.0, "knives": 6, "runout_um": (0, 3, 1, 2, 0.5, 2.5)},
        0.97,
    ),
    "pine-1m/s": ({"species": "pine", "pitch_mm": 2.0, "knives": 3, "speed_mm_s": 1000.0}, 0.95),
    "meranti-led-imbalance-falloff": (
        {"species": "meranti", "imbalance": 0.1, "falloff": 0.1}, 0.97,
    ),
    "ramin-barrel-k1": ({"species": "ramin", "pitch_mm": 1.2, "knives": 2, "k1": -0.3}, 0.97),
    "beech-pincushion-k1": ({"species": "beech", "pitch_mm": 1.8, "k1": 0.3}, 0.97),
    "oak-encoder+20": ({"species": "oak", "encoder_error_px": 20.0}, 0.95),
    "spruce-encoder-20-imbalance": (
        {"species": "spruce", "encoder_error_px": -20.0, "imbalance": -0.08, "falloff": -0.1},
        0.95,
    ),
    "pine-fast-long-exposure": (
        {"species": "pine", "pitch_mm": 1.5, "speed_mm_s": 1000.0, "exposure_ms": 0.4}, 0.95,
    ),
    "meranti-big-runout-16-bit-wrap": (
        {"species": "meranti", "pitch_mm": 2.2, "knives": 5, "runout_um": (6, -4, 0, 9, -7),
         "counter_bits": 16, "counts_a": 65530, "encoder_error_px": 9.0},
        0.97,
    ),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_accuracy_on_simulated_boards(name):
    kwargs, min_corr = CASES[name]
    rig, pair = scenarios.board_pair(seed=11 + sorted(CASES).index(name), **kwargs)
    result = _measure(rig, pair)
    _check_against_truth(result, pair, min_corr=min_corr)
    if kwargs.get("exposure_ms", 0) >= 0.2:
        assert result.blur_px == pytest.approx(pair.truth.blur_px)  # deblurred for its blur


@pytest.mark.parametrize("seed", range(200, 216))
def test_accuracy_on_held_out_random_boards(seed):
    rig, pair = scenarios.random_board_pair(seed)
    result = _measure(rig, pair)
    _check_against_truth(result, pair, min_corr=0.95)


def test_flat_field_reference():
    kw = {"species": "oak", "imbalance": 0.1, "falloff": -0.1, "k1": -0.15}
    rig, pair = scenarios.board_pair(seed=31, **kw)
    _, flat = scenarios.board_pair(seed=32, radius_mm=1e7, **kw)  # a flat board, same lights
    result = _measure(rig, pair, flat_field=(flat.image_a, flat.image_b))
    _check_against_truth(result, pair, min_corr=0.97)


def test_measurer_is_reusable_and_measure_pair_agrees():
    rig, pair = scenarios.board_pair(seed=41, species="beech")
    measurer = Measurer(rig, pair.image_a.shape)
    kw = {"counts_a": pair.counts_a, "counts_b": pair.counts_b, "speed_mm_s": pair.speed_mm_s}
    first = measurer.measure(pair.image_a, pair.image_b, **kw)
    again = measurer.measure(pair.image_a, pair.image_b, **kw)
    np.testing.assert_array_equal(first.height_um, again.height_um)
    one_off = measure_pair(pair.image_a, pair.image_b, rig=rig, **kw)
    np.testing.assert_allclose(one_off.height_um, first.height_um)
    assert one_off.pitch_mm == first.pitch_mm


def test_json_has_the_contract_keys():
    rig, pair = scenarios.board_pair(seed=42, species="ramin")
    data = _measure(rig, pair).to_json()
    for key in ("x_mm", "height_um", "pitch_mm", "mark_widths_mm", "uniformity_cv", "depth_um",
                "shift_px"):
        assert key in data
    assert len(data["x_mm"]) == len(data["height_um"]) > 100
    assert all(isinstance(v, float) for v in data["mark_widths_mm"])
    assert all(math.isfinite(v) for v in (data["pitch_mm"], data["depth_um"], data["shift_px"]))
    assert data["marks"] == len(data["mark_widths_mm"]) == len(data["cusps_mm"]) - 1


# -- bad input ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def good():
    return scenarios.board_pair(seed=43, species="beech")


def test_images_of_different_sizes(good):
    rig, pair = good
    with pytest.raises(ValueError, match="differ in size"):
        measure_pair(pair.image_a, pair.image_b[:, :-3], rig=rig, counts_a=0, counts_b=24)
    measurer = Measurer(rig, pair.image_a.shape)
    with pytest.raises(ValueError, match="set up for"):
        measurer.measure(pair.image_a[:-2], pair.image_b[:-2], counts_a=0, counts_b=24)


def test_black_and_saturated_pairs(good):
    rig, pair = good
    measurer = Measurer(rig, pair.image_a.shape)
    black = np.zeros_like(pair.image_a)
    with pytest.raises(MeasurementError, match="black"):
        measurer.measure(black, black, counts_a=0, counts_b=24)
    full = np.full_like(pair.image_a, 255)
    with pytest.raises(MeasurementError, match="saturated"):
        measurer.measure(full, full, counts_a=0, counts_b=24)
    with pytest.raises(MeasurementError, match="image_b is black"):
        measurer.measure(pair.image_a, black, counts_a=0, counts_b=24)


def test_counts_giving_a_shift_larger_than_the_image(good):
    rig, pair = good
    measurer = Measurer(rig, pair.image_a.shape)
    counts = int(700 / rig.encoder.px_per_count)
    with pytest.raises(MeasurementError, match="larger than the image"):
        measurer.measure(pair.image_a, pair.image_b, counts_a=5, counts_b=5 + counts)
    with pytest.raises(ValueError, match="counts_b"):
        measurer.measure(pair.image_a, pair.image_b, counts_a=5, counts_b=2**40)


def test_a_flat_board_has_no_marks_to_report():
    rig, flat = scenarios.board_pair(seed=44, radius_mm=1e7)
    with pytest.raises(MeasurementError, match="too few cuttermarks"):
        _measure(rig, flat)


def test_swapped_images_do_not_give_a_made_up_profile(good):
    rig, pair = good
    measurer = Measurer(rig, pair.image_a.shape)
    with pytest.raises(MeasurementError):
        measurer.measure(pair.image_b, pair.image_a, counts_a=pair.counts_a,
                         counts_b=pair.counts_b)


def test_sixteen_bit_containers_and_float_images(good):
    rig, pair = good
    measurer = Measurer(rig, pair.image_a.shape)
    kw = {"counts_a": pair.counts_a, "counts_b": pair.counts_b}
    eight = measurer.measure(pair.image_a, pair.image_b, **kw)
    ten_bit = measurer.measure(pair.image_a.astype(np.uint16) * 4,
                               pair.image_b.astype(np.uint16) * 4, **kw)
    unit = measurer.measure(pair.image_a / 255.0, pair.image_b / 255.0, **kw)
    for other in (ten_bit, unit):
        assert other.pitch_mm == pytest.approx(eight.pitch_mm, rel=1e-6)
        np.testing.assert_allclose(other.height_um, eight.height_um, atol=1e-3)
    full_10_bit = np.full(pair.image_a.shape, 1023, np.uint16)
    with pytest.raises(MeasurementError, match="saturated"):
        measurer.measure(full_10_bit, full_10_bit, **kw)
