"""The simulated planer seen through the vision pipeline.

Every check here measures RENDERED images of the machine model (`plant_sim.machine.machine.Machine`,
frames from `Machine.advance`) with the vision pipeline (`vision.pipeline.Measurer`) and compares
the measurement with the kinematics (feed per knife pass ``V / (n Z)``, mark depth ``p^2 / (8 R)``,
the one-knife-finish threshold) and with each frame's truth:

1. piezo off: measured pitch = feed per knife, measured depth = kinematic depth;
2. one knife standing out beyond the threshold: measured pitch = Z times the feed per knife;
3. per-knife piezo offsets equal to the knives' stand-out: measured marks uniform.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from config.loading import default_path
from config.rig import load_rig
from config.sim import SimConfig, load_sim
from plant_sim.machine.machine import Machine
from plant_sim.model.surface import Cutterhead, envelope, passes_steady
from plant_sim.rendering.optics import RigEffects, effects_from_config
from vision.pipeline import Measurement, Measurer

STEP_S = 0.02  # piezo commands every 20 ms of simulated time (the timeout is 100 ms)
SETTLE_S = 0.02  # piezo table switch plus shaped step, generously


def ideal(cfg: SimConfig) -> SimConfig:
    """``cfg`` with the real-rig effects off: the rig exactly as its file says, opaque wood."""
    return variant(
        cfg,
        camera={"roll_deg": 0.0, "slant_offset_deg": (0.0, 0.0),
                "optics": dataclasses.replace(cfg.camera.optics, noise=0.5)},
        board={"scattering_mm": 0.0, "reflectance_roughness_deg": 0.0, "bow_mm": 0.0,
               "cup_mm": 0.0, "pencil_lines": ()},
    )


@pytest.fixture(scope="module")
def cfg() -> SimConfig:
    """The shipped configuration on an ideal rig (the kinematics checks below are exact)."""
    return ideal(load_sim())


@pytest.fixture(scope="module")
def measurer(cfg: SimConfig) -> Measurer:
    """The pipeline, set up once for the rig the machine renders with."""
    rig = load_rig(cfg.camera.rig_path)
    assert rig == cfg.camera.rig
    o = cfg.camera.optics
    return Measurer(rig, (o.height, o.width))


def variant(cfg: SimConfig, **tables: dict) -> SimConfig:
    """``cfg`` with some fields of some tables replaced: variant(cfg, feed={...})."""
    out = {name: dataclasses.replace(getattr(cfg, name), **f) for name, f in tables.items()}
    return dataclasses.replace(cfg, **out)


class Piezo:
    """Plays the service's side of the amplifier: a NEW alive counter every step."""

    def __init__(self, m: Machine, *, enable: bool) -> None:
        self.m = m
        self.enable = enable
        self.counter = 0

    def advance(self, dt_s: float) -> list:
        if self.enable:
            self.counter += 1
            self.m.piezo_command(enable=True, alive_counter=self.counter % 256)
        return self.m.advance(dt_s)


def collect(piezo: Piezo, n: int, *, after_s: float = -math.inf, max_s: float = 6.0) -> list:
    """Advance until ``n`` frames triggered at or after ``after_s`` have come."""
    m = piezo.m
    t_end = m.t_s + max_s
    frames: list = []
    while len(frames) < n:
        assert m.t_s < t_end, f"only {len(frames)} frames by t = {m.t_s:.2f} s"
        frames += [f for f in piezo.advance(STEP_S) if f.t_s >= after_s]
    assert m.frames_dropped == 0
    return frames


def measure(measurer: Measurer, frames: list) -> list[Measurement]:
    out = []
    for f in frames:
        assert f.image_a is not None and f.image_b is not None
        out.append(measurer.measure(f.image_a, f.image_b, counts_a=f.counts_a,
                                    counts_b=f.counts_b, speed_mm_s=f.speed_mm_s))
    return out


def mean(values) -> float:
    return float(np.mean(list(values)))


# ---------------------------------------------------------------- 1. piezo off: kinematics


@pytest.mark.parametrize(
    ("feed_mm_s", "runout_free", "piezo"),
    [
        (800.0, False, "disabled"),
        (800.0, True, "zero_offsets"),
        (600.0, False, "zero_offsets"),
        (600.0, True, "disabled"),
    ],
)
def test_piezo_off_measured_pitch_and_depth_follow_the_kinematics(
    cfg, measurer, feed_mm_s, runout_free, piezo
):
    tables: dict = {"feed": {"initial_mm_s": feed_mm_s}}
    if runout_free:
        tables["cutterhead"] = {"runout_um": (0.0,) * cfg.cutterhead.knives,
                                "eccentricity_um": 0.0}
    c = variant(cfg, **tables)
    m = Machine(c, seed=11)
    drive = Piezo(m, enable=piezo == "zero_offsets")
    if drive.enable:
        m.set_piezo_offsets([0.0] * c.cutterhead.knives)
    frames = collect(drive, 3)
    got = measure(measurer, frames)
    assert m.piezo_status().state == (1 if drive.enable else 0)

    z, r_mm = c.cutterhead.knives, c.cutterhead.radius_mm
    pitch_kin = mean(f.speed_mm_s / (c.spindle.rpm / 60.0 * z) for f in frames)  # V / (n Z)
    pitch_truth = mean(f.truth["feed_per_knife_mm"] for f in frames)
    pitch = mean(g.pitch_mm for g in got)
    assert pitch == pytest.approx(pitch_kin, rel=0.01)
    assert pitch == pytest.approx(pitch_truth, rel=0.01)
    # every knife leaves marks: one complete mark per feed per knife over the measured span
    for g in got:
        span_mm = float(g.x_mm[-1] - g.x_mm[0])
        assert span_mm / pitch_kin - 3 <= len(g.mark_widths_mm) <= span_mm / pitch_kin

    depth = mean(g.depth_um for g in got)
    assert depth == pytest.approx(mean(f.truth["depth_um"] for f in frames), rel=0.15)
    if runout_free:
        assert depth == pytest.approx(1e3 * pitch_kin**2 / (8.0 * r_mm), rel=0.15)
        assert mean(g.uniformity_cv for g in got) < 0.03
    else:  # the shipped runout: uneven marks, seen as such
        cv_truth = mean(f.truth["uniformity_cv"] for f in frames)
        assert cv_truth >= 0.10
        assert mean(g.uniformity_cv for g in got) == pytest.approx(cv_truth, abs=0.02)


# ---------------------------------------------------------------- 2. one-knife finish


def one_knife_threshold_um(*, knives: int, radius_mm: float, pitch_mm: float) -> float:
    """Smallest stand-out of one knife (others level) that erases every other knife's marks.

    Found by bisection on the exact envelope of :mod:`plant_sim.model.surface`.
    """
    span = 12 * knives * pitch_mm
    xs = np.linspace(0.0, span, 64)

    def one_knife(delta_um: float) -> bool:
        head = Cutterhead(knives, radius_mm, (delta_um,) + (0.0,) * (knives - 1))
        passes = passes_steady(head, spindle_rpm=6000.0, feed_mm_s=pitch_mm * 100.0 * knives,
                               x_start_mm=0.0, x_end_mm=span)
        return set(envelope(xs, passes).knife.tolist()) == {0}

    lo, hi = 0.0, 1e3 * radius_mm * 0.01
    assert one_knife(hi) and not one_knife(lo)
    while hi - lo > 1e-3:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if one_knife(mid) else (mid, hi)
    return hi


def test_one_knife_finish_measured_pitch_is_z_times_feed_per_knife(cfg, measurer):
    z, r_mm = cfg.cutterhead.knives, cfg.cutterhead.radius_mm
    p_mm = 0.5  # feed per knife: 200 mm/s at 6000 rpm, 4 knives
    threshold = one_knife_threshold_um(knives=z, radius_mm=r_mm, pitch_mm=p_mm)
    # the real threshold: the knife half a revolution away from the standing-out one must fall
    # under the cusp of two of its marks Z p apart, Z^2 p^2 / (8 R); the p^2 / (2 R) is
    # the two-knife case and far too low for four knives
    assert threshold == pytest.approx(1e3 * z**2 * p_mm**2 / (8 * r_mm), rel=1e-3)
    assert threshold > 3.9 * 1e3 * p_mm**2 / (2 * r_mm)
    runout = 3.0 * threshold  # well above
    c = variant(
        cfg,
        cutterhead={"runout_um": (runout,) + (0.0,) * (z - 1), "eccentricity_um": 0.0},
        feed={"initial_mm_s": p_mm * cfg.spindle.rpm / 60.0 * z},
    )
    m = Machine(c, seed=12)
    frames = collect(Piezo(m, enable=False), 3)
    got = measure(measurer, frames)

    per_knife = mean(f.truth["feed_per_knife_mm"] for f in frames)
    assert per_knife == pytest.approx(p_mm, rel=0.01)
    for f in frames:  # the truth: only the standing-out knife leaves marks
        assert set(f.truth["knife"]) == {0}
        assert f.truth["pitch_mm"] == pytest.approx(z * f.truth["feed_per_knife_mm"], rel=0.01)
    pitch = mean(g.pitch_mm for g in got)
    assert pitch == pytest.approx(z * per_knife, rel=0.01)
    assert pitch == pytest.approx(mean(f.truth["pitch_mm"] for f in frames), rel=0.01)
    depth = mean(g.depth_um for g in got)
    assert depth == pytest.approx(1e3 * (z * per_knife) ** 2 / (8 * r_mm), rel=0.15)
    assert depth == pytest.approx(mean(f.truth["depth_um"] for f in frames), rel=0.15)


# ---------------------------------------------------------------- 3. compensation


def compensation_run(cfg: SimConfig, table: str) -> tuple[list, list, list, list]:
    """Frames (and measurements) before and after the piezo plays a per-knife table.

    ``table`` is ``"standout"`` (offsets = each knife's stand-out) or ``"rolled"`` (the same
    values one knife out of step). Returns ``(frames_before, frames_after, standout_um,
    offsets_um)``; the frames after were all cut with the table in effect.
    """
    m = Machine(cfg, seed=13)
    drive = Piezo(m, enable=True)
    m.set_piezo_offsets([0.0] * m.knives)
    before = collect(drive, 3)
    standout = np.asarray(m.standout_um())
    offsets = standout if table == "standout" else np.roll(standout, 1)
    t_apply = m.t_s
    m.set_piezo_offsets(offsets.tolist())
    # transport delay: the field's downstream edge (cut earliest) must have been cut after the
    # offsets took effect
    v = m.feed_speed_mm_s
    delay_s = (m.L_mm + m.assembler.x_hi_mm + 5.0) / v + SETTLE_S
    after = collect(drive, 3, after_s=t_apply + delay_s)
    assert m.piezo_status().state == 1 and m.piezo_status().fault == 0
    return before, after, standout.tolist(), offsets.tolist()


def test_offsets_equal_to_standout_make_measured_marks_uniform(cfg, measurer):
    before, after, standout, _ = compensation_run(cfg, "standout")
    assert max(standout) - min(standout) > 1.0  # there is runout to compensate
    cv_before = mean(g.uniformity_cv for g in measure(measurer, before))
    cv_after = mean(g.uniformity_cv for g in measure(measurer, after))
    cv_before_true = mean(f.truth["uniformity_cv"] for f in before)
    cv_after_true = mean(f.truth["uniformity_cv"] for f in after)
    assert cv_before_true >= 0.10
    assert cv_before >= 0.10
    assert cv_after < 0.03
    assert cv_after < cv_before / 4.0
    # the pipeline sees what the surface is, both ways
    assert cv_before == pytest.approx(cv_before_true, abs=0.02)
    assert cv_after == pytest.approx(cv_after_true, abs=0.01)


def test_offsets_out_of_step_with_the_knives_do_not_equalise(cfg, measurer):
    """Control: the same table shifted by one knife leaves (or makes) uneven marks."""
    _, after, _, offsets = compensation_run(cfg, "rolled")
    assert max(offsets) - min(offsets) > 1.0
    cv_after = mean(g.uniformity_cv for g in measure(measurer, after))
    assert cv_after >= 0.10
    assert cv_after == pytest.approx(mean(f.truth["uniformity_cv"] for f in after), abs=0.02)


# ---------------------------------------------------------------- 4. a realistic rig


def test_realistic_rig_changes_the_images_not_the_cut(measurer):
    """The shipped config/sim.toml: roll, lights off the file, translucent spruce, sensor noise.

    The machine renders those effects (the images differ from the ideal rig's, the cut and the
    truth do not), and the pipeline still measures the marks' pitch and evenness.
    """
    real = load_sim()
    assert real.camera.rig == load_rig(default_path("rig.toml"))  # the rig file is the shipped one
    m = Machine(real, seed=11)
    assert m.renderer.effects == effects_from_config(real)
    assert m.renderer.effects != RigEffects()
    frames = collect(Piezo(m, enable=False), 3)
    plain = collect(Piezo(Machine(ideal(real), seed=11), enable=False), 3)
    for f, g in zip(frames, plain, strict=True):
        assert f.truth["pitch_mm"] == g.truth["pitch_mm"]
        assert f.truth["mark_widths_mm"] == g.truth["mark_widths_mm"]
        assert (f.counts_a, f.counts_b) == (g.counts_a, g.counts_b)
        assert np.mean(np.abs(f.image_a.astype(float) - g.image_a)) > 1.0
    got = measure(measurer, frames)
    pitch_truth = mean(f.truth["feed_per_knife_mm"] for f in frames)
    assert mean(g.pitch_mm for g in got) == pytest.approx(pitch_truth, rel=0.01)
    cv_truth = mean(f.truth["uniformity_cv"] for f in frames)
    assert cv_truth >= 0.10
    assert mean(g.uniformity_cv for g in got) == pytest.approx(cv_truth, abs=0.03)


@pytest.mark.parametrize("roll_deg", [-2.0, 1.5])
def test_the_measured_roll_is_the_simulated_roll(cfg, measurer, roll_deg):
    """Simulator and vision share one roll convention (docs/architecture.md)."""
    rolled = variant(cfg, camera={"roll_deg": roll_deg})
    frames = collect(Piezo(Machine(rolled, seed=3), enable=False), 2)
    got = measure(measurer, frames)
    for g in got:
        assert g.roll_deg == pytest.approx(roll_deg, abs=0.1)
