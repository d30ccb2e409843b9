"""The vision benchmark's synthetic pair and result format (no timing assertions)."""

from __future__ import annotations

import pytest

from planer.benchmarks import vision as bench
from vision.pipeline import Measurer


def test_synthetic_pair_is_measurable_and_wraps_the_counter():
    rig, a, b, ca, cb = bench.synthetic_pair(659, 493, shift_px=18.0)
    assert a.shape == b.shape == (493, 659) and a.dtype.name == "uint8"
    assert cb < ca  # the 32-bit counter wrapped between the shots
    result = Measurer(rig, a.shape).measure(a, b, counts_a=ca, counts_b=cb, speed_mm_s=500.0)
    assert result.shift_px == pytest.approx(18.0, abs=0.3)
    assert result.pitch_mm == pytest.approx(1.5, rel=0.01)
    assert result.depth_um == pytest.approx(1.5**2 / (8 * 60.0) * 1000.0, rel=0.1)


def test_run_reports_every_size(monkeypatch):
    monkeypatch.setattr(bench, "SIZES", ((400, 300),))
    monkeypatch.setattr(bench, "_rate", lambda fn, t, n, **kw: (fn(), 123.0)[1])
    out = bench.run(quick=True)
    keys = ("width", "height", "pairs_per_s", "copy_pairs_per_s")  # more may follow
    assert [{k: row[k] for k in keys} for row in out] == [
        {"width": 400, "height": 300, "pairs_per_s": 123.0, "copy_pairs_per_s": 123.0}]
    # the defects' added CPU per pair: the defects' time less the plain one's (its overhead)
    row = out[0]
    plain_ms = row["defects_ms"] / row["defects_overhead"]
    assert row["defects_ms"] > 0
    assert row["defects_cpu_ms"] == pytest.approx(plain_ms + row["defects_ms"], abs=0.02)
    # and on the service's measurement (radius, knives, a SelfCalibrator): it costs more too
    assert row["service_defects_ms"] > 0 and row["service_defects_overhead"] > 0
    service_ms = row["service_defects_ms"] / row["service_defects_overhead"]
    assert service_ms > 0


def test_service_defects_are_timed_on_the_service_measurement(monkeypatch):
    """The service's variants: radius and knives given, a calibrator each, defects or not."""
    rig, a, b, ca, cb = bench.synthetic_pair(400, 300)
    built = []

    class Recording(Measurer):
        def __init__(self, *args, **kw):
            super().__init__(*args, **kw)
            built.append(kw)

    monkeypatch.setattr("vision.pipeline.Measurer", Recording)
    monkeypatch.setattr(bench, "_rate", lambda fn, t, n, **kw: (fn(), 50.0)[1])
    cpu = bench._service_defects_cpu(rig, a, b, ca, cb, 0.01)
    assert set(cpu) == {"service", "defects"} and cpu["defects"] > 0
    assert [(kw["radius_mm"], kw["knives"], kw["defects"]) for kw in built] == [
        (bench.SELFCAL_RADIUS_MM, bench.SELFCAL_KNIVES, False),
        (bench.SELFCAL_RADIUS_MM, bench.SELFCAL_KNIVES, True)]


def test_floor_ratios_compare_cpu_times_with_the_target():
    cpu = {"pairs_per_s": 0.5, "selfcal_pairs_per_s": 0.8, "rolled_pairs_per_s": 2.0,
           "remap_pairs_per_s": 1.0}
    out = bench._floor_ratios(cpu, 1.0)
    assert out["remap_ratio"] == pytest.approx(2.0)
    assert out["selfcal_remap_ratio"] == pytest.approx(1.25)
    assert out["rolled_remap_ratio"] == pytest.approx(0.5)
    assert out["target_remap_ratio"] == 1.0 and out["meets_target"] is True
    assert bench._floor_ratios(cpu, 4.0)["meets_target"] is False


def test_rolled_synthetic_pair_is_found_rolled():
    rig, a, b, ca, cb = bench.synthetic_pair(400, 300, roll_deg=1.0)
    assert rig.camera.roll_deg == 0.0
    result = Measurer(rig, a.shape).measure(a, b, counts_a=ca, counts_b=cb)
    assert result.roll_deg == pytest.approx(1.0, abs=0.05)
    assert result.shift_px == pytest.approx(18.0, abs=0.3)
