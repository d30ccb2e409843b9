"""The uniformity loop in closed loop with the transport delay: board travel to CV <= 0.03.

A board plant on simulated time: the camera sees board cut ``L / V`` seconds earlier, a table
sent at ``t`` cuts from ``t + settle``, the actuator is a circulant map of the table (ideal, a
slow piezo, a hysteretic one), the widths are the linear model's with measurement noise. The
HIL runs of the same targets are in docs/control_design.md (section 7).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.laws.design import uniformity_closed_loop_radius, uniformity_loop_model
from controller.laws.offset_qp import best_offsets_um
from controller.laws.uniformity_loop import (
    UniformityLoop,
    UniformityLoopConfig,
    linear_widths_mm,
    second_difference,
    width_cv,
)

R_MM, PITCH_MM, TS_S, WINDOW_MM = 60.0, 1.5, 0.1, 40.0
RUNOUT = np.array([0.5, 4.0, -2.0, 2.0])  # the default plant (eccentricity in knife 0)
# a 150 Hz piezo at 400 Hz knife frequency, measured in plant_sim.model.piezo at the knives' BDC
SLOW = np.array([[[0.355, 0.105, -0.23, -0.23][(i - j) % 4] for j in range(4)]
                 for i in range(4)])


def run(*, camera_mm=300.0, feed_mm_s=600.0, actuator=None, runout=RUNOUT, travel_mm=3000.0,
        noise_mm=0.005, seed=0, cfg=None):
    """Closed loop on board travel; returns (travel after the first pair mm, true CV), loop."""
    runout = np.asarray(runout, dtype=float)
    z = runout.size
    a = np.eye(z) if actuator is None else np.asarray(actuator)
    cfg = cfg or UniformityLoopConfig(knives=z)
    loop = UniformityLoop(cfg)
    rng = np.random.default_rng(seed)
    sent = [(-math.inf, np.zeros(z))]
    delay_s = camera_mm / feed_mm_s
    half_s = 0.5 * WINDOW_MM / feed_mm_s
    out = []
    t = delay_s
    while (t - delay_s) * feed_mm_s <= travel_mm:
        cut = t - delay_s
        in_force = [o for ts, o in sent if ts + cfg.settle_s <= cut][-1]
        w = linear_widths_mm(a @ in_force - runout, pitch_mm=PITCH_MM, radius_mm=R_MM)
        out.append(((t - delay_s) * feed_mm_s, width_cv(np.maximum(w, 0.0))))
        meas = w + noise_mm * rng.standard_normal(z)
        offs = loop.update(knife_widths_mm=np.where(meas > 0, meas, np.nan), pitch_mm=PITCH_MM,
                           now_s=t, cut_at_s=cut - half_s, cut_until_s=cut + half_s)
        sent.append((t, offs))
        t += TS_S
    return out, loop


def settled_after_mm(out, max_cv=0.03):
    bad = [d for d, cv in out if cv > max_cv]
    return 0.0 if not bad else bad[-1] + TS_S


@pytest.mark.parametrize("camera", [300.0, 1000.0, 2000.0])
@pytest.mark.parametrize("feed", [100.0, 600.0, 1000.0])
def test_cv_within_about_one_transport_delay_of_board(camera, feed):
    out, _ = run(camera_mm=camera, feed_mm_s=feed, travel_mm=camera + 1500.0)
    assert out[0][1] >= 0.1
    # the first pair's table shows after L (+ settle and one pair): the loop's targets are
    # 1 m at 300 mm, 2 m at 1000 mm, 4 m at 2000 mm
    assert settled_after_mm(out) <= 1.1 * camera + feed * (TS_S + 0.05) + 20.0
    assert np.mean([cv for _, cv in out[-10:]]) < 0.01


@pytest.mark.parametrize(
    ("name", "actuator"),
    [("150 Hz piezo", SLOW), ("hysteresis 0.30", 0.18 * np.eye(4))],
)
def test_weak_actuators_are_identified_and_compensated_within_3_m(name, actuator):
    out, loop = run(actuator=actuator, travel_mm=3500.0)
    assert settled_after_mm(out) <= 3000.0, name
    assert np.mean([cv for _, cv in out[-10:]]) < 0.01, name
    truth = np.fft.fft(actuator[:, 0])
    assert np.all(np.abs(loop.mode_gains[1:] - truth[1:]) < 0.15), (name, loop.mode_gains)


def test_without_identification_a_weak_actuator_is_slow():
    cfg = UniformityLoopConfig(identify=False)
    slow, _ = run(actuator=0.18 * np.eye(4), travel_mm=3000.0, cfg=cfg)
    fast, _ = run(actuator=0.18 * np.eye(4), travel_mm=3000.0)
    assert settled_after_mm(fast) < 0.6 * settled_after_mm(slow)


def test_saturated_plant_ends_at_the_constrained_optimum():
    runout = np.array([0.5, 15.0, -8.5, 5.0])
    cfg = UniformityLoopConfig(stroke_um=10.0)
    out, loop = run(runout=runout, cfg=cfg, noise_mm=0.0, travel_mm=3000.0)
    a = loop.mode_gains  # the ideal actuator, as identified
    assert np.allclose(a, 1.0, atol=0.05)
    best = best_offsets_um(runout, width_operator=second_difference(4), actuator=np.eye(4),
                           bound_um=cfg.offset_limit_um)
    w = linear_widths_mm(best - runout, pitch_mm=PITCH_MM, radius_mm=R_MM)
    assert out[-1][1] == pytest.approx(width_cv(w), rel=0.01)


@pytest.mark.parametrize("alpha", [0.5, 1.5, 2.0])
def test_the_decay_follows_the_designed_closed_loop_pole(alpha):
    """An actuator stronger or weaker than modelled (no identification): the error decays at
    the rate of the design model's dominant closed-loop pole (controller.laws.design)."""
    cfg = UniformityLoopConfig(identify=False, guard=False)  # the law alone
    feed, camera = 600.0, 300.0
    out, _ = run(actuator=alpha * np.eye(4), feed_mm_s=feed, camera_mm=camera, noise_mm=0.0,
                 travel_mm=4000.0, cfg=cfg)
    mdl = uniformity_loop_model(cfg, feed, cutter_to_camera_mm=camera, latency_samples=0)
    radius = uniformity_closed_loop_radius(mdl, alpha)
    assert radius < 1.0
    cvs = np.array([cv for _, cv in out])
    # envelope decay per pair over the tail, once the first transient has passed
    tail = cvs[20:60]
    peaks = [max(tail[i:i + 8]) for i in range(0, len(tail) - 8, 8)]
    rate = (peaks[-1] / peaks[0]) ** (1.0 / (8 * (len(peaks) - 1)))
    assert rate == pytest.approx(radius, abs=0.03)
