"""The envelope sweep file: every corner it promises, each checked by the project's loaders."""

from __future__ import annotations

import itertools

from config.loading import default_path
from planer.sweep.design import expand, load_sweep
from planer.sweep.point import build_sim_config, prepare

ENVELOPE = default_path("sweeps/envelope.toml")


def test_the_envelope_has_every_piezo_corner_and_each_side_corner_three_seeds():
    sweep = load_sweep(ENVELOPE)
    assert sweep.seeds == (0, 1, 2) and sweep.fixed["distance_m"] == 8.0
    points = expand(sweep)
    piezo = {(p.values["sim.piezo.resonance_hz"], p.values["sim.piezo.hysteresis"],
               p.values["sim.piezo.damping"]) for p in points
              if "sim.piezo.resonance_hz" in p.values}
    assert piezo == set(itertools.product((60.0, 2000.0), (0.0, 0.35), (0.01, 0.95)))
    seen = {k: {p.values[k] for p in points if k in p.values} for k in (
        "sim.feed.accel_max_mm_s2", "sim.feed.bandwidth_hz", "sim.camera.roll_deg",
        "sim.camera.optics.read_noise_dn", "sim.cutterhead.knives", "target_pitch_mm")}
    assert seen == {
        "sim.feed.accel_max_mm_s2": {10.0, 2000.0}, "sim.feed.bandwidth_hz": {0.3, 20.0},
        "sim.camera.roll_deg": {-5.0, 5.0}, "sim.camera.optics.read_noise_dn": {30.0},
        "sim.cutterhead.knives": {2, 8}, "target_pitch_mm": {0.5, 3.0},
    }
    for p in points:
        assert sum(1 for q in points if q.values == p.values) == 3  # three seeds each


def test_every_envelope_point_is_accepted_by_the_loaders():
    """Hysteresis 0.35 is within the simulator's range (its loader allows up to 0.5)."""
    jobs, _ = prepare(load_sweep(ENVELOPE))
    assert len(jobs) == 57  # the base point (feed acceleration 2000) once, not twice
    corner = next(j for j in jobs if j.point.values.get("sim.piezo.hysteresis") == 0.35)
    assert build_sim_config(corner).piezo.hysteresis == 0.35
