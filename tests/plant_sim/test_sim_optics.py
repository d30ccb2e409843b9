"""Simulated images: Lambert shading, registration truth, encoder, LEDs, distortion, blur."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from config.wood import SPECIES, Wood, species
from core.units import wrap_counter
from plant_sim.model.surface import Cutterhead, passes_steady
from plant_sim.rendering.optics import Optics, PencilLine, Renderer, RigEffects
from plant_sim.rendering.scenarios import (
    board_pair,
    make_rig,
    random_board_pair,
    random_board_params,
)

W, H = 240, 96
PPM = 12.5
FLAT_WOOD = Wood("flat", 0.5, 0, 1, 0, 0, 1, 0, 1, 1, 0, 0, 0, 1, 1)
CLEAN = {"shot_noise": False, "read_noise_dn": 0.0, "quantize": False}


def _renderer(wood=SPECIES["beech"], k1=0.0, exposure_ms=0.0, seed=0, w=W, h=H, **optics):
    rig = make_rig(width=w, height=h, k1=k1, exposure_ms=exposure_ms)
    return rig, Renderer(rig, Optics(width=w, height=h, **optics), wood, seed=seed)


def _marks(pitch=1.5, knives=4, runout=(0.0, 1.0, 2.0, 0.5), x0=-60.0, x1=60.0):
    from plant_sim.model.surface import envelope

    head = Cutterhead(knives, 60.0, runout)
    passes = passes_steady(
        head,
        spindle_rpm=6000.0,
        feed_mm_s=pitch * 100 * knives,
        x_start_mm=x0,
        x_end_mm=x1,
        phase_mm=0.123,
    )
    return envelope(np.linspace(x0, x1, 2001), passes)


def _flat(b):
    return np.zeros_like(b)


@pytest.fixture(scope="module")
def clean_beech():
    return _renderer(**CLEAN)


@pytest.mark.parametrize("oversample", [1, 3])
def test_eq4_ratio_gives_true_slope_and_pins_the_sign(oversample):
    rig, rend = _renderer(oversample=oversample, **CLEAN)
    surf = _marks()
    speed = 10 / PPM / rend.optics.dt_ab_s  # shift of exactly 10 px
    pair = rend.render_pair(surf, board_x_at_centre_mm=3.0, speed_mm_s=speed)
    assert pair.truth.shift_px == pytest.approx(10.0)
    a = pair.image_a[:, :-10].astype(float)
    b = pair.image_b[:, 10:].astype(float)
    p = ((b - a) / (b + a)).mean(axis=0) / math.tan(math.radians(rig.lights.slant_deg))
    true = pair.truth.slope[:-10]
    assert np.abs(true).max() > 0.01
    assert np.max(np.abs(p - true)) < 0.02 * np.abs(true).max()
    assert np.corrcoef(p, true)[0, 1] > 0.999
    # light A stands on +x: where the surface rises toward +x, image A is the darker one
    rising = true > 0.005
    assert a[:, rising].mean() < b[:, rising].mean()
    # the truth slope is the derivative of the truth height
    dz = np.gradient(pair.truth.height_um, pair.truth.x_mm) * 1e-3
    assert np.median(np.abs(dz - pair.truth.slope)) < 0.05 * np.abs(true).max()


def _ssd_shift(a, b, guess):
    """Shift d minimising sum (A[:, u] - B[:, u + d])^2 (linear interpolation of B)."""
    cols = np.arange(a.shape[1], dtype=float)
    u = np.arange(int(abs(guess)) + 15, a.shape[1] - int(abs(guess)) - 15)

    def cost(d):
        bi = np.stack([np.interp(u + d, cols, row) for row in b])
        return float(np.sum((a[:, u] - bi) ** 2))

    return minimize_scalar(
        cost, bounds=(guess - 1.5, guess + 1.5), method="bounded", options={"xatol": 1e-4}
    ).x


@pytest.mark.parametrize("speed", [333.3, 517.0, 741.9])
def test_texture_moves_by_the_true_shift(speed):
    _, rend = _renderer(wood=SPECIES["oak"], **CLEAN)
    pair = rend.render_pair(_flat, board_x_at_centre_mm=21.7, speed_mm_s=speed)
    d = _ssd_shift(pair.image_a.astype(float), pair.image_b.astype(float), pair.truth.shift_px)
    assert pair.truth.shift_px == pytest.approx(speed * rend.optics.dt_ab_s * PPM)
    assert d == pytest.approx(pair.truth.shift_px, abs=0.02)


@pytest.mark.parametrize("bits", [16, 32])
def test_encoder_counts_wrap_around(bits):
    _, rend = _renderer(w=64, h=8, **CLEAN)
    top = 1 << bits
    for counts_a, err_px in [(top - 3, 0.0), (top - 40, 7.3), (5, -12.0), (-7, 0.0)]:
        pair = rend.render_pair(
            _flat,
            board_x_at_centre_mm=0.0,
            speed_mm_s=600.0,
            counts_a=counts_a,
            encoder_error_px=err_px,
            counter_bits=bits,
        )
        assert 0 <= pair.counts_a < top and 0 <= pair.counts_b < top
        assert pair.counts_a == counts_a % top
        moved = round(600.0 * rend.optics.dt_ab_s * 20.0) + round(err_px / rend.px_per_count)
        assert (pair.counts_b - pair.counts_a) % top == moved % top
    assert wrap_counter(top + 5, bits=bits) == 5
    # by default the counter width is the rig's
    rig16 = make_rig(width=64, height=8, counter_bits=16)
    rend16 = Renderer(rig16, Optics(width=64, height=8), FLAT_WOOD, seed=0)
    pair = rend16.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=1.0, counts_a=70000)
    assert pair.counts_a == 70000 % 65536


def test_led_imbalance_and_falloff():
    _, rend = _renderer(wood=FLAT_WOOD, led_imbalance=0.07, **CLEAN)
    pair = rend.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0)
    ratio = pair.image_b / pair.image_a
    assert np.allclose(ratio, 1.07, rtol=1e-5)
    assert pair.image_a.mean() == pytest.approx(0.45 * 255, rel=1e-3)  # Optics.level
    _, rend = _renderer(wood=FLAT_WOOD, falloff=0.1, **CLEAN)
    pair = rend.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0)
    a, b = pair.image_a.mean(axis=0), pair.image_b.mean(axis=0)
    # each LED is brighter on its own side (A's light on +x), by `falloff` across the field
    assert a[-1] / a[0] == pytest.approx(1.05 / 0.95, rel=2e-3)
    assert b[0] / b[-1] == pytest.approx(1.05 / 0.95, rel=2e-3)


@pytest.mark.parametrize("k1", [-0.3, 0.3])
def test_distortion_moves_points_as_project_points_says(k1):
    rig, rend = _renderer(wood=FLAT_WOOD, k1=k1, w=320, h=240, **CLEAN)
    b0 = 9.7  # a bump across the board at b0: its slope changes sign there

    def bump(b):
        return 5.0 * np.exp(-((b - b0) ** 2) / (2 * 0.5**2))

    pair = rend.render_pair(bump, board_x_at_centre_mm=0.0, speed_mm_s=0.0)
    diff = pair.image_b - pair.image_a
    cam = rig.camera
    for row in (0, 60, 120, 239):
        r = diff[row]
        i = np.flatnonzero(np.sign(r[:-1]) != np.sign(r[1:]))
        i = i[np.argmin(np.abs(i - (cam.cx + b0 * PPM)))]
        col = i + r[i] / (r[i] - r[i + 1])
        # the board point (b0, Y) whose projection lands on this row
        y = (row - cam.cy) / PPM
        for _ in range(30):
            obj = np.array([[[b0 * PPM / cam.fx, y * PPM / cam.fy, 1.0]]])
            img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), rend.K, rend.dist)
            y -= (img[0, 0, 1] - row) / PPM
        assert col == pytest.approx(img[0, 0, 0], abs=0.02)
        if row == 0:
            # and the distortion is strong enough to matter
            assert abs(img[0, 0, 0] - (cam.cx + b0 * PPM)) > 0.3


def test_motion_blur_is_the_average_over_the_exposure():
    surf = _marks(pitch=1.0)
    v, t_ms = 900.0, 0.8  # 9 px of blur: exaggerated to see it
    _, blurred = _renderer(exposure_ms=t_ms, **CLEAN)
    _, sharp = _renderer(exposure_ms=0.0, **CLEAN)
    pair = blurred.render_pair(surf, board_x_at_centre_mm=1.0, speed_mm_s=v)
    assert pair.truth.blur_px == pytest.approx(v * t_ms * 1e-3 * PPM)
    ts = (np.arange(64) + 0.5) / 64 - 0.5
    mean = np.mean(
        [
            sharp.render_pair(
                surf, board_x_at_centre_mm=1.0 - v * t * t_ms * 1e-3, speed_mm_s=v
            ).image_a
            for t in ts
        ],
        axis=0,
    )
    one = sharp.render_pair(surf, board_x_at_centre_mm=1.0, speed_mm_s=v).image_a
    err = np.abs(pair.image_a - mean)[:, 10:-10]
    assert err.max() < 0.01 * mean.mean()
    assert np.abs(one - mean)[:, 10:-10].max() > 10 * err.max()


def test_deterministic_for_a_seed_and_noise_is_physical():
    rig1, p1 = board_pair(seed=5, width=W, height=H)
    rig2, p2 = board_pair(seed=5, width=W, height=H)
    assert rig1 == rig2
    assert np.array_equal(p1.image_a, p2.image_a) and np.array_equal(p1.image_b, p2.image_b)
    assert (p1.counts_a, p1.counts_b) == (p2.counts_a, p2.counts_b)
    _, p3 = board_pair(seed=6, width=W, height=H)
    assert not np.array_equal(p1.image_a, p3.image_a)
    # noise: std of (noisy - clean) is sqrt(shot + read^2)
    _, clean = _renderer(**CLEAN)
    _, noisy = _renderer(shot_noise=True, read_noise_dn=0.5, quantize=False)
    surf = _marks()
    a0 = clean.render_pair(surf, board_x_at_centre_mm=0.0, speed_mm_s=500.0).image_a
    a1 = noisy.render_pair(surf, board_x_at_centre_mm=0.0, speed_mm_s=500.0, rng_seed=1).image_a
    o = noisy.optics
    expect = math.sqrt(a0.mean() * o.gain * o.max_dn / o.full_well_e + o.read_noise_dn**2)
    assert np.std(a1 - a0) == pytest.approx(expect, rel=0.05)


def test_quantisation_saturates_and_bit_depth():
    _, rend = _renderer(gain=3.0, shot_noise=False, read_noise_dn=0.0)
    img = rend.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=100.0).image_a
    assert img.dtype == np.uint8 and img.max() == 255
    assert np.mean(img == 255) > 0.5
    _, rend = _renderer(bit_depth=12)
    img = rend.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=100.0).image_a
    assert img.dtype == np.uint16 and 0.3 * 4095 < img.mean() < 0.6 * 4095


def test_truth_profile_and_marks_in_frame_a():
    rig, pair = board_pair(
        seed=3, pitch_mm=1.8, knives=3, runout_um=(0.0, 0.0, 0.0), width=W, height=H
    )
    t = pair.truth
    assert np.allclose(t.x_mm, np.arange(W) / PPM)
    b = t.x_mm + t.board_offset_mm
    assert np.allclose(t.height_um, t.surface.height_at(b))
    m = t.metrics(0.0, W / PPM)
    assert m["n_marks"] >= 8
    assert m["pitch_mm"] == pytest.approx(1.8, rel=1e-6)
    assert m["uniformity_cv"] < 1e-9
    assert all(0.0 <= c <= W / PPM for c in m["cusps_mm"])
    # the cusps are where the true profile peaks
    for c in m["cusps_mm"][1:-1]:
        near = np.abs(t.x_mm - c) < 0.4
        assert abs(t.x_mm[near][np.argmax(t.height_um[near])] - c) <= 1.0 / PPM
    with pytest.raises(ValueError, match="surface"):
        dataclasses.replace(t, surface=None).metrics(0.0, 10.0)


def test_board_pair_speed_pitch_and_rig():
    rig, pair = board_pair(
        seed=1,
        pitch_mm=2.0,
        knives=2,
        speed_mm_s=800.0,
        runout_um=(0, 0),
        width=W,
        height=H,
        k1=-0.2,
        counter_bits=16,
    )
    assert pair.speed_mm_s == 800.0
    assert pair.truth.shift_px == pytest.approx(800.0 * 0.002 * PPM)
    assert pair.truth.metrics(1.0, W / PPM - 1.0)["pitch_mm"] == pytest.approx(2.0, rel=1e-3)
    assert rig.camera.dist == (-0.2, 0.0, 0.0, 0.0, 0.0)
    assert rig.encoder.px_per_count == pytest.approx(rig.camera.px_per_mm / 20.0)
    assert rig.camera.cx == (W - 1) / 2 and rig.camera.cy == (H - 1) / 2
    assert 0 <= pair.counts_a < 1 << 16
    _, pair2 = board_pair(seed=1, pitch_mm=2.0, knives=2, spindle_rpm=9000.0, width=W, height=H)
    assert pair2.speed_mm_s == pytest.approx(2.0 * 9000.0 / 60.0 * 2)


def test_random_boards_cover_the_acceptance_ranges():
    params = [random_board_params(s) for s in range(40)]
    assert {p["species"] for p in params} <= set(SPECIES)
    assert len({p["species"] for p in params}) >= 4
    for p in params:
        assert 1.0 <= p["pitch_mm"] <= 2.5 and 1 <= p["knives"] <= 6
        assert len(p["runout_um"]) == p["knives"]
        assert 0 < p["speed_mm_s"] <= 1000.0
        assert abs(p["imbalance"]) <= 0.1 and abs(p["k1"]) <= 0.3
        assert abs(p["encoder_error_px"]) <= 20.0
    rig, pair = random_board_pair(0)
    assert pair.image_a.shape == (493, 659)
    assert pair.truth.metrics(2.0, 50.0)["n_marks"] > 5


def test_bad_inputs_name_the_parameter():
    for kwargs, name in [
        ({"width": 3}, "width"),
        ({"bit_depth": 4}, "bit_depth"),
        ({"led_imbalance": float("nan")}, "led_imbalance"),
        ({"dt_ab_s": -1.0}, "dt_ab_s"),
        ({"counts_per_mm": 0.0}, "counts_per_mm"),
        ({"oversample": 9}, "oversample"),
        ({"oversample": 2}, "oversample"),
    ]:
        with pytest.raises(ValueError, match=name):
            Optics(**kwargs)
    rig = make_rig(width=64, height=8)
    with pytest.raises(ValueError, match="px_per_count"):
        Renderer(rig, Optics(width=64, height=8, counts_per_mm=10.0), FLAT_WOOD, seed=0)
    with pytest.raises(ValueError, match="dist"):  # barrel model folds over in the corners
        Renderer(make_rig(width=320, height=240, k1=-0.3, fx=150.0), Optics(width=320, height=240),
                 FLAT_WOOD, seed=0)
    rend = Renderer(rig, Optics(width=64, height=8), FLAT_WOOD, seed=0)
    for kwargs, name in [
        ({"counter_bits": 8}, "counter_bits"),
        ({"speed_mm_s": float("nan")}, "speed_mm_s"),
        ({"board_x_at_centre_mm": float("inf")}, "board_x_at_centre_mm"),
        ({"counts_a": 1.5}, "counts_a"),
    ]:
        args = {"board_x_at_centre_mm": 0.0, "speed_mm_s": 10.0} | kwargs
        with pytest.raises(ValueError, match=name):
            rend.render_pair(_flat, **args)
    with pytest.raises(ValueError, match="height"):
        rend.render_pair(42, board_x_at_centre_mm=0.0, speed_mm_s=1.0)
    with pytest.raises(ValueError, match="species"):
        species("balsa")
    with pytest.raises(ValueError, match="albedo"):
        dataclasses.replace(FLAT_WOOD, albedo=2.0)
    with pytest.raises(ValueError, match="pitch_mm"):
        board_pair(pitch_mm=0.0, width=64, height=8)


def test_surface_like_arrays_are_interpolated(clean_beech):
    _, rend = clean_beech
    surf = _marks()

    class Sampled:
        x_mm = np.linspace(-60, 60, 120001)
        height_um = surf.height_at(x_mm)

    a = rend.render_pair(surf, board_x_at_centre_mm=2.0, speed_mm_s=300.0)
    b = rend.render_pair(Sampled(), board_x_at_centre_mm=2.0, speed_mm_s=300.0)
    assert np.allclose(a.image_a, b.image_a, atol=0.05)
    assert b.truth.surface is None


@pytest.mark.parametrize(("speed", "k1"), [(0.0, 0.0), (950.0, -0.3), (400.0, 0.3)])
def test_board_range_covers_every_height_query(speed, k1):
    _, rend = _renderer(k1=k1, exposure_ms=0.1, **CLEAN)
    seen = []

    def spy(b):
        seen.append((b.min(), b.max()))
        return np.zeros_like(b)

    rend.render_pair(spy, board_x_at_centre_mm=12.0, speed_mm_s=speed)
    lo, hi = rend.board_range_mm(board_x_at_centre_mm=12.0, speed_mm_s=speed)
    got_lo, got_hi = min(s[0] for s in seen), max(s[1] for s in seen)
    assert lo <= got_lo and got_hi <= hi
    assert got_lo - lo < 1e-6 or hi - got_hi < 1e-6  # tight on at least one end
    assert hi - lo < (W + 20) / PPM + speed * rend.optics.dt_ab_s


# -- effects of a real rig and real wood ------------------------------------------------------


def _fx_renderer(wood=FLAT_WOOD, w=W, h=H, seed=0, **effects):
    rig = make_rig(width=w, height=h, exposure_ms=0.0)
    rend = Renderer(rig, Optics(width=w, height=h, **CLEAN), wood, seed=seed,
                    effects=RigEffects(**effects))
    return rig, rend


def _plane(slope):
    def height(b):
        return 1e3 * slope * b

    return height


def _fundamental_fit(profile, period_px):
    """Least-squares ``c0 sin + c1 cos + c2`` at ``period_px``; returns (c0, c1)."""
    u = np.arange(profile.size)
    m = np.stack([np.sin(2 * np.pi * u / period_px), np.cos(2 * np.pi * u / period_px),
                  np.ones(u.size)], axis=1)
    c, *_ = np.linalg.lstsq(m, profile, rcond=None)
    return c[0], c[1]


def _fundamental(profile, period_px):
    """Amplitude of a profile's component at ``period_px``."""
    return math.hypot(*_fundamental_fit(profile, period_px))


@pytest.mark.parametrize("roll_deg", [-3.0, 0.4, 2.0])
def test_roll_leans_the_marks_by_the_roll_angle(roll_deg):
    _, rend = _fx_renderer(h=200, roll_deg=roll_deg)
    pitch = 1.6
    surf = _marks(pitch=pitch, runout=(0.0, 0.0, 0.0, 0.0))
    img = rend.render_pair(surf, board_x_at_centre_mm=0.0, speed_mm_s=0.0).image_a
    r = math.radians(roll_deg)
    period = pitch * PPM / math.cos(r)  # along a row the board advances cos(roll) per column
    rows = np.arange(10, 190)
    # each row's mark phase: cos(2 pi (u - d) / period) has phase 2 pi d / period
    fits = [_fundamental_fit(img[v, 20:220], period) for v in rows]
    phase = np.unwrap([math.atan2(c0, c1) for c0, c1 in fits])
    d = phase * period / (2 * np.pi)
    lean = np.polyfit(rows, d, 1)[0]
    # a mark (constant board x) leans tan(roll) columns per row toward -u (the vision's sign)
    assert math.degrees(math.atan(-lean)) == pytest.approx(roll_deg, abs=0.02)
    # the board frame of every pixel is the camera frame turned by the roll
    xc = (np.arange(W) - rend.rig.camera.cx) / PPM
    yc = (np.arange(200) - rend.rig.camera.cy) / PPM
    assert np.allclose(rend.x_phys_mm, xc[None, :] * math.cos(r) + yc[:, None] * math.sin(r))
    assert np.allclose(rend.y_phys_mm, yc[:, None] * math.cos(r) - xc[None, :] * math.sin(r))


def test_scattering_lowers_mark_contrast_with_its_length():
    wood = dataclasses.replace(FLAT_WOOD, translucency=0.6, scattering_anisotropy=3.0)
    pitch = 1.6  # 20 px: an exact number of periods in the profile below
    surf = _marks(pitch=pitch, runout=(0.0, 0.0, 0.0, 0.0))
    amps = []
    for length in (0.0, 0.1, 0.25, 0.5):
        _, rend = _fx_renderer(wood=wood, scattering_mm=length)
        pair = rend.render_pair(surf, board_x_at_centre_mm=0.0, speed_mm_s=0.0)
        a = pair.image_a[:, 20:220].mean(axis=0)
        amps.append(_fundamental(a, pitch * PPM))
        # the fraction `translucency` is spread by an exponential kernel (transfer 1/(1+k^2 l^2))
        k = 2 * np.pi / pitch
        expect = 0.4 + 0.6 / (1.0 + (k * length) ** 2)
        assert amps[-1] / amps[0] == pytest.approx(expect, rel=0.03)
    assert all(a1 < a0 for a0, a1 in zip(amps, amps[1:], strict=False))
    # an opaque wood does not scatter
    opaque = dataclasses.replace(wood, translucency=0.0)
    _, r0 = _fx_renderer(wood=opaque)
    _, r1 = _fx_renderer(wood=opaque, scattering_mm=0.5)
    i0 = r0.render_pair(surf, board_x_at_centre_mm=0.0, speed_mm_s=0.0).image_a
    i1 = r1.render_pair(surf, board_x_at_centre_mm=0.0, speed_mm_s=0.0).image_a
    assert np.array_equal(i0, i1)


def test_scattering_is_stronger_along_the_fibres_than_across():
    wood = dataclasses.replace(FLAT_WOOD, translucency=0.8, scattering_anisotropy=4.0)
    length = 0.3
    _, rend = _fx_renderer(wood=wood, scattering_mm=length)
    rows, cols = 256, 2048  # a texture tile: periodic along x (and here along y)
    y = np.arange(rows)[:, None] * rend.dy_mm
    x = np.arange(cols)[None, :] * rend.dx_mm
    # whole periods of about 1.3 mm along x and along y
    k_along = 2 * np.pi * 125 / (cols * rend.dx_mm)
    k_across = 2 * np.pi * 16 / (rows * rend.dy_mm)
    along = np.broadcast_to(np.sin(k_along * x), (rows, cols)).astype(np.float32)
    across = np.broadcast_to(np.sin(k_across * y), (rows, cols)).astype(np.float32)
    got_along = float(np.ptp(rend._scatter_tile(along, length, 4.0))) / float(np.ptp(along))
    got_across = float(np.ptp(rend._scatter_tile(across, length, 4.0))) / float(np.ptp(across))
    assert got_along == pytest.approx(0.2 + 0.8 / (1 + (k_along * length) ** 2), rel=1e-3)
    assert got_across == pytest.approx(0.2 + 0.8 / (1 + (k_across * length / 4) ** 2), rel=1e-3)
    assert got_along < got_across < 1.0


@pytest.mark.parametrize(("off_a", "off_b"), [(0.0, 0.0), (1.5, -1.0), (-2.0, 0.5), (3.0, 3.0)])
@pytest.mark.parametrize("slope", [-0.012, 0.02])
def test_slant_offset_changes_the_ab_ratio_as_lambert_with_the_true_slant(off_a, off_b, slope):
    rig, rend = _fx_renderer(slant_offset_deg=(off_a, off_b))
    assert rig.lights.slant_deg == 82.0  # the rig file keeps the nominal slant
    assert rend.true_slant_deg == pytest.approx((82.0 + off_a, 82.0 + off_b))
    pair = rend.render_pair(_plane(slope), board_x_at_centre_mm=0.0, speed_mm_s=0.0)
    ratio = float(np.mean(pair.image_a / pair.image_b))
    sa, sb = (math.radians(82.0 + off_a), math.radians(82.0 + off_b))
    # each LED gives the same brightness on a flat board; its slope sensitivity is tan(true slant)
    expect = (1.0 - slope * math.tan(sa)) / (1.0 + slope * math.tan(sb))
    assert ratio == pytest.approx(expect, rel=1e-5)
    flat = rend.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0)
    assert flat.image_a.mean() == pytest.approx(0.45 * 255, rel=1e-4)
    assert flat.image_b.mean() == pytest.approx(0.45 * 255, rel=1e-4)


def _oren_nayar(p, slant_deg, azimuth_deg, sigma_deg):
    """Independent Oren-Nayar radiance of a plane of slope p seen from straight above."""
    n = np.array([-p, 0.0, 1.0]) / math.sqrt(1 + p * p)
    s, t = math.radians(slant_deg), math.radians(azimuth_deg)
    light = np.array([math.sin(s) * math.cos(t), math.sin(s) * math.sin(t), math.cos(s)])
    view = np.array([0.0, 0.0, 1.0])
    ti, tr = math.acos(light @ n), math.acos(view @ n)
    lt, vt = light - (light @ n) * n, view - (view @ n) * n
    nv = np.linalg.norm(vt)
    cos_dphi = 0.0 if nv < 1e-12 else lt @ vt / np.linalg.norm(lt) / nv
    sg = math.radians(sigma_deg) ** 2
    a, b = 1 - 0.5 * sg / (sg + 0.33), 0.45 * sg / (sg + 0.09)
    back = math.sin(max(ti, tr)) * math.tan(min(ti, tr))
    return math.cos(ti) * (a + b * max(0.0, cos_dphi) * back)


@pytest.mark.parametrize("sigma_deg", [20.0, 45.0])
def test_rough_wood_reflectance_is_oren_nayar(sigma_deg):
    _, lam = _fx_renderer()
    _, rough = _fx_renderer(reflectance_roughness_deg=sigma_deg)
    for slope in (-0.03, -0.01, 0.01, 0.03):
        pr = rough.render_pair(_plane(slope), board_x_at_centre_mm=0.0, speed_mm_s=0.0)
        pl = lam.render_pair(_plane(slope), board_x_at_centre_mm=0.0, speed_mm_s=0.0)
        for img, az in ((pr.image_a, 0.0), (pr.image_b, 180.0)):
            expect = _oren_nayar(slope, 82.0, az, sigma_deg) / _oren_nayar(0.0, 82.0, az, sigma_deg)
            assert img.mean() / (0.45 * 255) == pytest.approx(expect, rel=1e-4)
        # rough wood shows the slopes with less contrast than Lambert
        c_rough = (pr.image_b - pr.image_a).mean() / (pr.image_b + pr.image_a).mean()
        c_lam = (pl.image_b - pl.image_a).mean() / (pl.image_b + pl.image_a).mean()
        assert abs(c_rough) < abs(c_lam)


@pytest.mark.parametrize("read_noise_dn", [2.0, 7.0, 20.0])
def test_read_noise_gives_the_configured_std_in_a_flat_region(read_noise_dn):
    rig = make_rig(width=W, height=H, exposure_ms=0.0)
    optics = Optics(width=W, height=H, shot_noise=False, read_noise_dn=read_noise_dn,
                    quantize=False)
    rend = Renderer(rig, optics, SPECIES["spruce"], seed=0)
    a = rend.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0, rng_seed=1).image_a
    b = rend.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0, rng_seed=2).image_a
    region = (a - b)[10:-10, 20:-20]  # the same board twice: only the noise differs
    assert np.std(region) / math.sqrt(2) == pytest.approx(read_noise_dn, rel=0.03)
    # board_pair passes it on (8-bit images add the quantisation's 1/12 DN^2)
    kw = {"seed": 4, "width": W, "height": H, "noise": False, "flat": True,
          "read_noise_dn": read_noise_dn, "board_x_at_centre_mm": 50.0, "counts_a": 0}
    _, p1 = board_pair(**kw)
    clean = board_pair(**(kw | {"read_noise_dn": 0.0, "quantize": False}))[1].image_a
    diff = (p1.image_a.astype(float) - clean)[10:-10, 20:-20]
    expect = math.sqrt(read_noise_dn**2 + 1 / 12)
    assert np.std(diff) == pytest.approx(expect, rel=0.05)


def test_bow_tilts_the_board_and_stays_out_of_the_truth():
    bow, length = 20.0, 4000.0
    _, rend = _fx_renderer(bow_mm=bow, board_length_mm=length)
    for bc in (300.0, 2000.0, 3500.0):
        pair = rend.render_pair(_flat, board_x_at_centre_mm=bc, speed_mm_s=0.0)
        a, b = pair.image_a.astype(float), pair.image_b.astype(float)
        p = float(np.mean((b - a) / (b + a))) / math.tan(math.radians(82.0))
        assert p == pytest.approx(8 * bow * (bc - length / 2) / length**2, abs=2e-5)
        assert np.all(pair.truth.slope == 0.0) and np.all(pair.truth.height_um == 0.0)


def test_cup_tilts_the_board_across():
    from config.rig import Lights

    cup, width = 2.0, 100.0
    rig = make_rig(width=W, height=H, exposure_ms=0.0)
    rig = dataclasses.replace(rig, lights=Lights(slant_deg=82.0, azimuth_a_deg=90.0,
                                                 azimuth_b_deg=270.0))
    rends = [Renderer(rig, Optics(width=W, height=H, **CLEAN), FLAT_WOOD, seed=0,
                      effects=RigEffects(cup_mm=c, board_width_mm=width)) for c in (0.0, cup)]
    imgs = [r.render_pair(_flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0).image_a for r in rends]
    y = (np.arange(H) - rig.camera.cy) / PPM
    q = 8 * cup * y / width**2  # dz/dy of the cupped board (edges up)
    # light A at azimuth 90 deg (+y): I ~ cos(s) - q sin(s)
    ratio = imgs[1].mean(axis=1) / imgs[0].mean(axis=1)
    assert np.allclose(ratio, 1.0 - q * math.tan(math.radians(82.0)), atol=2e-3)
    assert np.ptp(ratio) > 0.05


def test_pencil_line_darkens_its_rows_only():
    line = PencilLine(y_mm=1.0, width_mm=0.6, darkness=0.4)
    _, plain = _fx_renderer()
    rig, lined = _fx_renderer(pencil_lines=(line,))
    surf = _marks()
    a0 = plain.render_pair(surf, board_x_at_centre_mm=0.0, speed_mm_s=0.0).image_a
    a1 = lined.render_pair(surf, board_x_at_centre_mm=0.0, speed_mm_s=0.0).image_a
    ratio = (a1 / a0).mean(axis=1)
    y = (np.arange(H) - rig.camera.cy) / PPM
    inside = np.abs(y - 1.0) < 0.3
    assert ratio.min() == pytest.approx(0.6, abs=0.01)
    assert abs(y[np.argmin(ratio)] - 1.0) <= 0.5 / PPM
    assert np.allclose(ratio[~inside], 1.0, atol=1e-6) and np.all(ratio[inside] < 1.0)
    # across the marks: every column of the line's row is darkened alike
    row = int(np.argmin(ratio))
    assert np.allclose(a1[row] / a0[row], ratio[row], rtol=1e-4)


def test_effects_reject_bad_values_naming_them():
    for kwargs, name in [
        ({"roll_deg": 12.0}, "roll_deg"),
        ({"slant_offset_deg": (1.0,)}, "slant_offset_deg"),
        ({"slant_offset_deg": (0.0, 11.0)}, "slant_offset_deg"),
        ({"scattering_mm": -0.1}, "scattering_mm"),
        ({"reflectance_roughness_deg": 90.0}, "reflectance_roughness_deg"),
        ({"bow_mm": float("nan")}, "bow_mm"),
        ({"pencil_lines": ({"y_mm": 1.0},)}, "pencil_lines"),
    ]:
        with pytest.raises(ValueError, match=name):
            RigEffects(**kwargs)
    with pytest.raises(ValueError, match="darkness"):
        PencilLine(darkness=1.5)
    with pytest.raises(ValueError, match="translucency"):
        dataclasses.replace(FLAT_WOOD, translucency=1.2)
    with pytest.raises(ValueError, match="effects"):
        Renderer(make_rig(width=64, height=8), Optics(width=64, height=8), FLAT_WOOD, seed=0,
                 effects={"roll_deg": 1.0})
    rig = make_rig(width=64, height=8, slant_deg=85.0)
    with pytest.raises(ValueError, match="slant_offset_deg"):
        Renderer(rig, Optics(width=64, height=8), FLAT_WOOD, seed=0,
                 effects=RigEffects(slant_offset_deg=(6.0, 0.0)))


def test_softwoods_are_the_translucent_species():
    soft = {SPECIES[n].translucency for n in ("spruce", "pine")}
    hard = {SPECIES[n].translucency for n in ("beech", "oak", "ramin", "meranti")}
    assert min(soft) > max(hard) > 0.0
    assert all(w.scattering_anisotropy > 1.0 for w in SPECIES.values())


def test_board_pair_passes_the_effects_and_keeps_the_rig_nominal():
    kw = {"seed": 2, "width": W, "height": H, "species": "spruce"}
    rig0, p0 = board_pair(**kw)
    rig1, p1 = board_pair(roll_deg=0.5, slant_offset_deg=(1.5, -1.0), scattering_mm=0.2,
                          reflectance_roughness_deg=15.0, bow_mm=3.0, cup_mm=0.5,
                          pencil_lines=(PencilLine(y_mm=1.0),), read_noise_dn=2.0, **kw)
    assert rig0 == rig1  # the rig file knows nothing of the effects
    assert p0.counts_a == p1.counts_a and p0.truth.shift_px == p1.truth.shift_px
    assert np.array_equal(p0.truth.height_um, p1.truth.height_um)
    assert not np.array_equal(p0.image_a, p1.image_a)
    # no effects: the same renderer (and images) as before the effects existed
    _, p2 = board_pair(roll_deg=0.0, **kw)
    assert np.array_equal(p0.image_a, p2.image_a)


def test_sim_config_effects_defaults_and_errors(tmp_path):
    from config.sim import default_sim, load_sim, sim_from_dict
    from core.errors import ConfigError
    from plant_sim.rendering.optics import effects_from_config

    # a document built without the new keys renders the ideal rig, as before they existed
    assert effects_from_config(default_sim()) == RigEffects()
    # a file keeps the shipped rig's effects; the older name noise replaces read_noise_dn
    old = tmp_path / "old.toml"
    old.write_text('[camera]\nspecies = "spruce"\n[camera.optics]\nnoise = 0.5\n')
    assert effects_from_config(load_sim(old)) == effects_from_config(load_sim())
    assert load_sim(old).camera.optics.read_noise_dn == 0.5
    # the shipped config/sim.toml is a realistic rig: what a real machine has, its rig file not
    shipped = load_sim()
    fx = effects_from_config(shipped)
    assert 0.0 < abs(fx.roll_deg) < 1.0  # a fraction of a degree
    assert all(1.0 <= abs(d) <= 2.0 for d in fx.slant_offset_deg)
    assert SPECIES[shipped.camera.species].translucency >= 0.5 and fx.scattering_mm > 0
    assert fx.reflectance_roughness_deg > 0 and fx.bow_mm != 0 and fx.cup_mm != 0
    assert fx.pencil_lines  # the wood effects of [board]
    assert shipped.camera.optics.read_noise_dn > default_sim().camera.optics.read_noise_dn
    cfg = sim_from_dict({
        "camera": {"roll_deg": -0.7, "slant_offset_a_deg": 2.0, "optics": {"read_noise_dn": 7}},
        "board": {"scattering_mm": 0.3, "bow_mm": 2.0, "length_mm": 3000.0,
                  "pencil_lines": [{"y_mm": 4.0, "darkness": 0.3}]},
    })
    fx = effects_from_config(cfg)
    assert fx.roll_deg == -0.7 and fx.slant_offset_deg == (2.0, 0.0)
    assert fx.scattering_mm == 0.3 and fx.bow_mm == 2.0 and fx.board_length_mm == 3000.0
    assert fx.pencil_lines == (PencilLine(y_mm=4.0, width_mm=0.6, darkness=0.3),)
    assert cfg.camera.optics.read_noise_dn == 7.0
    for data, key in [
        ({"camera": {"roll_deg": 11.0}}, "camera.roll_deg"),
        ({"camera": {"slant_offset_b_deg": "x"}}, "camera.slant_offset_b_deg"),
        ({"camera": {"slant_offset_a_deg": 9.5}}, "camera.slant_offset_a_deg"),
        ({"camera": {"optics": {"read_noise_dn": -1.0}}}, "camera.optics.read_noise_dn"),
        ({"camera": {"optics": {"read_noise_dn": 1.0, "noise": 1.0}}}, "read_noise_dn"),
        ({"board": {"scattering_mm": 3.0}}, "board.scattering_mm"),
        ({"board": {"reflectance_roughness_deg": -1.0}}, "board.reflectance_roughness_deg"),
        ({"board": {"cup_mm": 50.0}}, "board.cup_mm"),
        ({"board": {"pencil_lines": {"y_mm": 1.0}}}, "board.pencil_lines"),
        ({"board": {"pencil_lines": [{"y_mm": 1.0, "dark": 0.2}]}}, r"board.pencil_lines\[0\]"),
        ({"board": {"pencil_lines": [{"darkness": 2.0}]}}, r"board.pencil_lines\[0\].darkness"),
    ]:
        with pytest.raises(ConfigError, match=key):
            sim_from_dict(data)
    bad = tmp_path / "sim.toml"
    bad.write_text("[camera]\nroll_deg = 45.0\n")
    with pytest.raises(ConfigError, match="camera.roll_deg"):
        load_sim(bad)


def test_board_pair_knots_and_pores():
    from plant_sim.rendering.camera import Knot

    bc = 500.0
    kw = {"seed": 6, "width": W, "height": H, "noise": False, "quantize": False,
          "board_x_at_centre_mm": bc, "exposure_ms": 0.0}
    knot = Knot(board_id=1, x_mm=bc + 3.0, y_mm=0.5, length_mm=6.0, width_mm=4.0, darkness=0.6,
                roughness_um=0.0)
    _, plain = board_pair(**kw)
    _, knotted = board_pair(knots=(knot,), **kw)
    ratio = knotted.image_a / plain.image_a
    col = int(round(3.0 * PPM + (W - 1) / 2))
    row = int(round((H - 1) / 2 + 0.5 * PPM))
    assert ratio[row, col] == pytest.approx(0.4, abs=0.02)  # dark at its centre
    assert np.allclose(ratio[:, : col - 50], 1.0)  # and nowhere else
    # image B sees it where the board has moved to
    shift = int(round(knotted.truth.shift_px))
    assert knotted.image_b[row, col + shift] / plain.image_b[row, col + shift] == pytest.approx(
        0.4, abs=0.03)
    assert knotted.truth.metrics(1.0, W / PPM - 1) == plain.truth.metrics(1.0, W / PPM - 1)
    rough = dataclasses.replace(knot, roughness_um=3.0)
    _, bumpy = board_pair(knots=(rough,), **kw)
    assert not np.allclose(bumpy.truth.height_um, plain.truth.height_um)
    # pores: small dark spots in a species that has none
    _, clean = board_pair(species="spruce", flat=True, **kw)
    _, pored = board_pair(species="spruce", flat=True, pore_density_per_mm2=5.0, **kw)
    assert pored.image_a.mean() < clean.image_a.mean()
    assert np.percentile(pored.image_a, 1) < np.percentile(clean.image_a, 1) - 2.0
    with pytest.raises(ValueError, match="knots"):
        board_pair(knots=({"x_mm": 1.0},), **kw)
    with pytest.raises(ValueError, match="pore_density_per_mm2"):
        board_pair(pore_density_per_mm2=-1.0, **kw)


@pytest.mark.parametrize("roll_deg", [-2.0, 3.0])
def test_with_roll_the_texture_moves_along_the_rolled_feed(roll_deg):
    rig = make_rig(width=W, height=H, exposure_ms=0.0)
    # no roughness (A and B alike but for the shift), no sub-pixel texture (clean interpolation)
    smooth = dataclasses.replace(SPECIES["oak"], roughness_um=0.0, fibre_width_mm=0.4,
                                 fibre_length_mm=0.6, pore_density_per_mm2=0.0)
    rend = Renderer(rig, Optics(width=W, height=H, **CLEAN), smooth, seed=2,
                    effects=RigEffects(roll_deg=roll_deg))
    d = 12.0
    pair = rend.render_pair(_flat, board_x_at_centre_mm=5.0, speed_mm_s=d / PPM / 0.002)
    r = math.radians(roll_deg)
    du, dv = d * math.cos(r), d * math.sin(r)  # the feed in the image: (cos r, sin r)
    cols, rows = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    b_at = cv2.remap(pair.image_b, cols + np.float32(du), rows + np.float32(dv), cv2.INTER_CUBIC)
    a, b = pair.image_a, b_at
    inner = (slice(8, -8), slice(20, -20))
    err = np.std((a - b)[inner]) / a.mean()
    b_wrong = cv2.remap(pair.image_b, cols + np.float32(d), rows, cv2.INTER_CUBIC)
    assert err < 0.002
    assert err < 0.1 * np.std((a - b_wrong)[inner]) / a.mean()


def test_board_range_covers_the_height_queries_with_roll_and_scattering():
    wood = dataclasses.replace(FLAT_WOOD, translucency=0.5)
    rig = make_rig(width=W, height=H, exposure_ms=0.1)
    rend = Renderer(rig, Optics(width=W, height=H, **CLEAN), wood, seed=0,
                    effects=RigEffects(roll_deg=-4.0, scattering_mm=0.5))
    plain = Renderer(rig, Optics(width=W, height=H, **CLEAN), wood, seed=0)
    seen = []

    def spy(b):
        seen.append((b.min(), b.max()))
        return np.zeros_like(b)

    rend.render_pair(spy, board_x_at_centre_mm=12.0, speed_mm_s=700.0)
    lo, hi = rend.board_range_mm(board_x_at_centre_mm=12.0, speed_mm_s=700.0)
    assert lo <= min(s[0] for s in seen) and max(s[1] for s in seen) <= hi
    # wider than the ideal rig's by the scattering kernel and the rolled field
    lo0, hi0 = plain.board_range_mm(board_x_at_centre_mm=12.0, speed_mm_s=700.0)
    assert lo < lo0 - 2.0 and hi > hi0 + 2.0
