"""The pitch's judgement: the drive's physical ramp and the verdicts."""

from __future__ import annotations

import types

import pytest

from planer.sweep.judge import PITCH_WITHIN_MM, drive_ramp_end_mm, pitch_verdict
from plant_sim.model.feed_drive import FeedDrive


def _simulated_ramp_end_mm(f0: float, f1: float, accel: float, bw: float, dt: float = 0.002):
    """Travel at which the simulated drive, set to ``f1`` at once, stays within 1 % of it."""
    cfg = types.SimpleNamespace(initial_mm_s=f0, accel_max_mm_s2=accel, bandwidth_hz=bw,
                                min_mm_s=1.0, max_mm_s=5000.0)
    drive = FeedDrive(cfg)
    drive.set_setpoint(f1)
    t = 0.0
    while abs(drive.v_mm_s / f1 - 1.0) > 0.01:
        drive.start_cycle(t, dt)
        drive.end_cycle(dt)
        t += dt
    return drive.s_mm


@pytest.mark.parametrize(("f0", "f1", "accel", "bw"), [
    (800.0, 600.0, 10.0, 8.0),     # the envelope's slow PLC: acceleration-limited throughout
    (800.0, 600.0, 2000.0, 0.3),   # a slow velocity loop: its exponential only
    (800.0, 600.0, 2000.0, 20.0),
    (700.0, 600.0, 25.0, 8.0),
    (400.0, 1200.0, 50.0, 2.0),    # up, both phases
])
def test_the_ramp_end_is_where_the_simulated_drive_gets_within_one_percent(f0, f1, accel, bw):
    want = _simulated_ramp_end_mm(f0, f1, accel, bw)
    got = drive_ramp_end_mm(f0, f1, accel_mm_s2=accel, bandwidth_hz=bw)
    assert got == pytest.approx(want, rel=0.01, abs=5.0)


def test_the_slow_plc_of_the_envelope_cannot_finish_its_ramp_in_8_m():
    """10 mm/s^2 from 800 to 600 mm/s: 19.4 s to within 1 % (606 mm/s), 13.6 m of board."""
    end = drive_ramp_end_mm(800.0, 600.0, accel_mm_s2=10.0, bandwidth_hz=8.0)
    assert end == pytest.approx((800.0**2 - 606.0**2) / 20.0, rel=1e-6)
    assert pitch_verdict(travel_mm=8000.0, ramp_end_mm=end, in_band_from_mm=None,
                         final_pitch_error=0.169) == "ramp not finished"
    assert drive_ramp_end_mm(600.0, 600.0, accel_mm_s2=10.0, bandwidth_hz=8.0) == 0.0


def test_the_verdicts():
    kw = {"travel_mm": 8000.0, "ramp_end_mm": 1000.0}
    assert pitch_verdict(**kw, in_band_from_mm=2400.0, final_pitch_error=0.001) == "in band"
    assert pitch_verdict(**kw, in_band_from_mm=1000.0 + PITCH_WITHIN_MM + 1.0,
                         final_pitch_error=0.001) == "late"
    assert pitch_verdict(**kw, in_band_from_mm=None, final_pitch_error=0.05) == "off"
    assert pitch_verdict(**kw, in_band_from_mm=2000.0, final_pitch_error=0.03) == "off"
    assert pitch_verdict(**kw, in_band_from_mm=2000.0, final_pitch_error=0.0,
                         capped=True) == "capped, in band"
    with pytest.raises(ValueError, match="accel_mm_s2"):
        drive_ramp_end_mm(800.0, 600.0, accel_mm_s2=0.0, bandwidth_hz=8.0)
