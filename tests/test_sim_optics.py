"""Simulated images: Lambert shading, registration truth, encoder, LEDs, distortion, blur."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from config.wood import SPECIES, Wood, species
from plant_sim.optics import Optics, Renderer, wrap_counts
from plant_sim.scenarios import board_pair, make_rig, random_board_pair, random_board_params
from plant_sim.surface import Cutterhead, passes_steady

W, H = 240, 96
PPM = 12.5
FLAT_WOOD = Wood("flat", 0.5, 0, 1, 0, 0, 1, 0, 1, 1, 0, 0, 0, 1, 1)
CLEAN = {"shot_noise": False, "read_noise_dn": 0.0, "quantize": False}


def _renderer(wood=SPECIES["beech"], k1=0.0, exposure_ms=0.0, seed=0, w=W, h=H, **optics):
    rig = make_rig(width=w, height=h, k1=k1, exposure_ms=exposure_ms)
    return rig, Renderer(rig, Optics(width=w, height=h, **optics), wood, seed=seed)


def _marks(pitch=1.5, knives=4, runout=(0.0, 1.0, 2.0, 0.5), x0=-60.0, x1=60.0):
    from plant_sim.surface import envelope

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
    assert wrap_counts(top + 5, bits) == 5
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
