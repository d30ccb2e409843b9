"""The renderer's fast paths equal the reference formulas they replace.

The reference functions below are the renderer's formulas as they were before the speed work
(numpy step by step); the renderer now interpolates the texture with one ``cv2.addWeighted``,
clips with ``cv2.max`` and draws its sensor noise through :func:`standard_normal_f32`. The
images must agree to float32 rounding for any board, speed, position and rig effect, and the
noise must be independent standard normal samples, deterministic for the generator's state.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats

import plant_sim.rendering.optics as optics_mod
from config.wood import SPECIES
from plant_sim.model.surface import Cutterhead, envelope, passes_steady
from plant_sim.rendering.optics import Optics, PencilLine, Renderer, RigEffects, standard_normal_f32
from plant_sim.rendering.scenarios import make_rig

W, H = 96, 40
FX = RigEffects(roll_deg=0.7, slant_offset_deg=(1.5, -1.0), scattering_mm=0.2,
                reflectance_roughness_deg=15.0, bow_mm=3.0, cup_mm=0.5,
                pencil_lines=(PencilLine(y_mm=0.5),))


def _reference_window(tile: np.ndarray, period: int, c0: int, n: int, frac: float) -> np.ndarray:
    """The texture window as the renderer took it before: ``w[j] + f (w[j + 1] - w[j])``."""
    c0 %= period
    if c0 + n + 1 <= tile.shape[1]:
        win = tile[:, c0 : c0 + n + 1]
    else:
        win = tile[:, (c0 + np.arange(n + 1)) % period]
    if frac < 1e-9:
        return win[:, :n].copy()
    f = np.float32(frac)
    out = win[:, 1:] - win[:, :n]
    out *= f
    out += win[:, :n]
    return out


def _reference_grid(rend: Renderer, height, b_at_axis_mm: float, speed_mm_s: float,
                    which: int) -> tuple[np.ndarray, int]:
    """``Renderer._radiance_grid`` step by step, as it was written before the speed work."""
    dx = rend.dx_mm
    blur_cols, _half, k, n = rend._grid_extent(speed_mm_s)
    b_u0 = b_at_axis_mm - rend._cx_mm
    t0 = b_u0 / dx + k
    c0 = math.floor(t0)
    frac = t0 - c0
    m = rend._scatter_kernel.size // 2
    edges = b_u0 + (k - m + np.arange(n + 2 * m + 1) - 0.5) * dx
    z = np.asarray(height(edges), dtype=np.float64)
    p_prof = np.diff(z) * (1e-3 / dx)
    if rend._bow_per_mm != 0.0:
        p_prof += rend._bow_per_mm * (edges[:-1] + 0.5 * dx - rend._bow_mid_mm)
    g, c = rend._shade(p_prof, which)
    if m:
        a = rend._scatter_a
        g = (1.0 - a) * g[m:-m] + a * np.convolve(g, rend._scatter_kernel, mode="valid")
        c = c[m:-m]
    rad = _reference_window(rend._tile_rho, rend._period, c0, n, frac)
    rad *= g.astype(np.float32)[None, :]
    rough = _reference_window(rend._tile_r[which], rend._period, c0, n, frac)
    rough *= c.astype(np.float32)[None, :]
    rad -= rough
    np.maximum(rad, 0.0, out=rad)
    kernel = rend._pixel_kernel
    if blur_cols > 1e-3:
        kernel = np.convolve(kernel, optics_mod._box_kernel(blur_cols)).astype(np.float32)
    if kernel.size > 1:
        rad = cv2.filter2D(rad, -1, kernel[None, :], borderType=cv2.BORDER_REPLICATE)
    return rad, k


def _reference_image(rend: Renderer, height, b_at_axis_mm: float, speed_mm_s: float,
                     which: int, noise: np.ndarray | None) -> np.ndarray:
    """``Renderer._render_one`` before the speed work, with the given standard normal field."""
    rad, k = _reference_grid(rend, height, b_at_axis_mm, speed_mm_s, which)
    img = cv2.remap(rad, rend._col_index - np.float32(k), rend._map_y, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    img *= rend._gain_maps[which]
    o = rend.optics
    if noise is not None:
        if o.shot_noise:
            var = np.maximum(img, 0.0)
            var *= np.float32(rend._dn_per_e)
            var += np.float32(o.read_noise_dn**2)
            sd = np.sqrt(var, out=var)
        else:
            sd = np.float32(o.read_noise_dn)
        img += sd * noise
    if not o.quantize:
        return img
    img += 0.5
    np.clip(img, 0.0, o.max_dn, out=img)
    return img.astype(o.dtype)


def _surface(pitch_mm: float, runout: tuple[float, ...], phase_mm: float):
    head = Cutterhead(len(runout), 60.0, runout)
    passes = passes_steady(head, spindle_rpm=6000.0, feed_mm_s=pitch_mm * 100 * len(runout),
                           x_start_mm=-40.0, x_end_mm=40.0, phase_mm=phase_mm)
    return envelope(np.linspace(-40.0, 40.0, 512), passes)


@pytest.fixture(scope="module")
def renderers() -> dict[str, Renderer]:
    rig = make_rig(width=W, height=H, k1=-0.05, exposure_ms=0.1)
    clean = {"shot_noise": False, "read_noise_dn": 0.0, "quantize": False}
    return {
        "plain": Renderer(rig, Optics(width=W, height=H, **clean), SPECIES["beech"], seed=1),
        "effects": Renderer(rig, Optics(width=W, height=H, oversample=3, **clean),
                            SPECIES["spruce"], seed=2, effects=FX),
    }


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(["plain", "effects"]), which=st.sampled_from([0, 1]),
       centre=st.floats(-10.0, 10.0), speed=st.floats(0.0, 1500.0),
       pitch=st.floats(0.8, 2.5), phase=st.floats(0.0, 2.0))
def test_radiance_and_image_equal_the_reference_formula(renderers, name, which, centre, speed,
                                                        pitch, phase):
    rend = renderers[name]
    surf = _surface(pitch, (0.0, 3.0, -1.0), phase)
    fast, k = rend._radiance_grid(surf.height_at, centre, speed, which)
    ref, k_ref = _reference_grid(rend, surf.height_at, centre, speed, which)
    assert k == k_ref and fast.shape == ref.shape and fast.dtype == ref.dtype
    np.testing.assert_allclose(fast, ref, rtol=2e-6, atol=2e-6 * float(ref.max()))
    img = rend._render_one(surf.height_at, centre, speed, which, np.random.default_rng(0))
    want = _reference_image(rend, surf.height_at, centre, speed, which, None)
    np.testing.assert_allclose(img, want, rtol=2e-6, atol=2e-6 * float(want.max()))


def test_texture_window_view_is_never_written(renderers):
    """A window at a whole column is a view into the tile: rendering must leave the tile as is."""
    rend = renderers["plain"]
    before = (rend._tile_rho.copy(), [t.copy() for t in rend._tile_r])
    dx = rend.dx_mm
    centre = rend._cx_mm + 37 * dx  # b_u0 / dx a whole number: frac == 0
    surf = _surface(1.5, (0.0, 2.0), 0.3)
    for which in (0, 1):
        rend._render_one(surf.height_at, centre, 0.0, which, np.random.default_rng(0))
    assert np.array_equal(before[0], rend._tile_rho)
    assert all(np.array_equal(a, b) for a, b in zip(before[1], rend._tile_r, strict=True))


@pytest.mark.parametrize("shot_noise,read_noise_dn,quantize",
                         [(True, 2.0, True), (True, 0.0, False), (False, 3.0, True)])
def test_noisy_image_is_the_reference_formula_with_the_same_normal_field(
        monkeypatch, shot_noise, read_noise_dn, quantize):
    rig = make_rig(width=W, height=H, exposure_ms=0.1)
    rend = Renderer(rig, Optics(width=W, height=H, shot_noise=shot_noise,
                                read_noise_dn=read_noise_dn, quantize=quantize),
                    SPECIES["spruce"], seed=3, effects=FX)
    field = np.random.default_rng(7).standard_normal((H, W), dtype=np.float32)
    monkeypatch.setattr(optics_mod, "standard_normal_f32", lambda rng, shape: field.copy())
    surf = _surface(1.7, (0.0, 2.0, -1.0, 1.0), 0.2)
    for which in (0, 1):
        got = rend._render_one(surf.height_at, 1.0, 700.0, which, np.random.default_rng(0))
        want = _reference_image(rend, surf.height_at, 1.0, 700.0, which, field)
        assert got.dtype == want.dtype
        if quantize:  # float32 rounding may move a value across a rounding boundary
            diff = np.abs(got.astype(int) - want.astype(int))
            assert diff.max() <= 1 and np.mean(diff) < 1e-3
        else:
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4)


def test_standard_normal_is_deterministic_for_the_generator_state():
    a1, a2 = np.random.default_rng(11), np.random.default_rng(11)
    x = standard_normal_f32(a1, (50, 60))
    y = standard_normal_f32(a2, (50, 60))
    assert x.dtype == np.float32 and x.shape == (50, 60) and np.array_equal(x, y)
    assert not np.array_equal(standard_normal_f32(a1, (50, 60)), x)  # the stream moves on


def test_standard_normal_draws_one_value_from_the_stream():
    rng, twin = np.random.default_rng(5), np.random.default_rng(5)
    standard_normal_f32(rng, (8, 8))
    twin.integers(0, 2**31 - 1)
    assert rng.bit_generator.state == twin.bit_generator.state


def test_standard_normal_is_independent_standard_normal():
    rng = np.random.default_rng(2024)
    fields = [standard_normal_f32(rng, (120, 160)) for _ in range(20)]
    z = np.concatenate([f.ravel() for f in fields]).astype(np.float64)
    assert abs(z.mean()) < 5 * 1 / math.sqrt(z.size)
    assert z.std() == pytest.approx(1.0, abs=5 * math.sqrt(2 / z.size))
    assert stats.kstest(z[::3], "norm").pvalue > 1e-3
    assert abs(stats.skew(z)) < 0.02 and abs(stats.kurtosis(z)) < 0.04
    assert (np.abs(z) > 4).mean() == pytest.approx(2 * stats.norm.sf(4), rel=0.5)
    f = fields[0].astype(np.float64)
    for a, b in ((f[:, :-1], f[:, 1:]), (f[:-1], f[1:]), (fields[0], fields[1])):
        r = np.corrcoef(np.ravel(a), np.ravel(b))[0, 1]
        assert abs(r) < 5 / math.sqrt(np.size(a))


def test_sensor_noise_has_the_configured_std_and_no_pattern_between_images():
    rig = make_rig(width=W, height=H, exposure_ms=0.0)
    rend = Renderer(rig, Optics(width=W, height=H, shot_noise=True, read_noise_dn=2.0,
                                quantize=False), SPECIES["spruce"], seed=4)
    clean = Renderer(rig, Optics(width=W, height=H, shot_noise=False, read_noise_dn=0.0,
                                 quantize=False), SPECIES["spruce"], seed=4)

    def flat(b):
        return np.zeros_like(b)

    ref = clean.render_pair(flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0)
    pair = rend.render_pair(flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0, rng_seed=9)
    na = (pair.image_a - ref.image_a) / np.sqrt(ref.image_a * rend._dn_per_e + 4.0)
    nb = (pair.image_b - ref.image_b) / np.sqrt(ref.image_b * rend._dn_per_e + 4.0)
    assert na.std() == pytest.approx(1.0, abs=0.05) and nb.std() == pytest.approx(1.0, abs=0.05)
    assert abs(np.corrcoef(na.ravel(), nb.ravel())[0, 1]) < 0.05
    again = rend.render_pair(flat, board_x_at_centre_mm=0.0, speed_mm_s=0.0, rng_seed=9)
    assert np.array_equal(again.image_a, pair.image_a)
