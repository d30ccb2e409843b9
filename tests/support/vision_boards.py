"""An independent renderer of image pairs with real-rig and real-wood effects (not plant_sim).

Shares no code with the simulator or with ``vision/``.  A board is a chain of knife-tip arcs of
radius R (one per knife pass, per-knife runout), optionally bowed along the feed and cupped across;
it is seen by a camera rolled by ``roll_deg`` about its axis and lit by two grazing lights whose
*true* slants ``slant_a_deg`` / ``slant_b_deg`` may differ from the rig file's ``slant_deg``.

Effects (each optional):

- roll: pixel ``(u, v)`` sees the board point ``xi = (u - cx) cos(roll) + (v - cy) sin(roll)``
  (px, along the feed) and ``eta = -(u - cx) sin(roll) + (v - cy) cos(roll)`` (across);
- anisotropic subsurface scattering: a fraction ``scatter_fraction`` of the irradiance re-emerges
  spread along the fibres (the feed) by a two-sided exponential of length ``scatter_mm`` (across
  the fibres it spreads ``scatter_mm / 4``: invisible, the shading varies along the feed only);
- rough reflectance (Oren-Nayar, roughness ``roughness_rad``, view along the camera axis);
- albedo: along-feed grain, a 2-D fibre texture elongated along the feed, knots (dark ellipses),
  pores (small dark dots), a pencil line drawn across the marks (along the feed);
- motion blur over the exposure, LED imbalance, grain stripes fixed to the camera;
- sensor read noise (``noise_dn``, 8-bit) and rounding; an encoder error (``slip_px``).

Pixels average the shading over their footprint along the feed (box of one pixel plus the motion
blur, pre-filtered on a fine 1-D grid); the albedo is sampled bilinearly from a 0.04 mm map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from config.rig import Camera, Encoder, Lights, Rig

PX_PER_MM = 12.5
COUNTS_PER_MM = 20.0
STEP_MM = 0.002  # fine 1-D grid along the feed
ALBEDO_MM = 0.04  # albedo map grid


@dataclass(frozen=True)
class Board:
    """A rendered pair and its truth (profile in A's frame along the feed)."""

    rig: Rig
    image_a: np.ndarray
    image_b: np.ndarray
    counts_a: int
    counts_b: int
    shift_px: float  # true board motion between the shots, px along the feed
    x_mm: np.ndarray  # true profile, board position along the feed at A (image centre row)
    height_um: np.ndarray
    cusps_mm: np.ndarray
    depths_um: np.ndarray  # per complete true mark (mean of its cusps minus its bottom)
    speed_mm_s: float
    radius_mm: float
    knives: int
    spindle_rpm: float
    roll_deg: float
    gain: float  # the photometric gain the effects cause (slant error; reflectance ~1)


def _oren_nayar(p: np.ndarray, *, azimuth_sign: float, slant_rad: float,
                roughness_rad: float) -> np.ndarray:
    """Radiance of a surface of slope p (q = 0) under a light in the x-z plane, view along z."""
    n = np.stack([-p, np.zeros_like(p), np.ones_like(p)]) / np.sqrt(1.0 + p * p)
    light = np.array([azimuth_sign * math.sin(slant_rad), 0.0, math.cos(slant_rad)])
    cos_i = np.clip(np.tensordot(light, n, axes=1), 0.0, None)
    if roughness_rad <= 0:
        return cos_i
    s2 = roughness_rad**2
    a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b = 0.45 * s2 / (s2 + 0.09)
    cos_r = n[2]
    theta_i = np.arccos(np.clip(cos_i, -1, 1))
    theta_r = np.arccos(np.clip(cos_r, -1, 1))
    alpha = np.maximum(theta_i, theta_r)
    beta = np.minimum(theta_i, theta_r)
    # azimuths of light and view projected on the tangent plane: both in the x-z plane
    lt = light[:, None] - cos_i[None, :] * n
    vt = np.array([0.0, 0.0, 1.0])[:, None] - cos_r[None, :] * n
    norm = np.linalg.norm(lt, axis=0) * np.linalg.norm(vt, axis=0)
    cos_phi = np.where(norm > 1e-12, np.sum(lt * vt, axis=0) / np.maximum(norm, 1e-12), 0.0)
    return cos_i * (a + b * np.maximum(0.0, cos_phi) * np.sin(alpha) * np.tan(beta))


def render_board(
    seed: int,
    *,
    shift_px: float = 18.3,
    slip_px: float = 0.0,
    pitch_mm: float = 1.5,
    radius_mm: float = 60.0,
    runout_um: tuple[float, ...] = (0.0,),
    slant_deg: float = 82.0,
    slant_a_error_deg: float = 0.0,
    slant_b_error_deg: float = 0.0,
    roll_deg: float = 0.0,
    scatter_mm: float = 0.0,
    scatter_fraction: float = 0.5,
    roughness_rad: float = 0.0,
    albedo: float = 0.04,
    fibre: float = 0.03,
    knots: int = 0,
    pores: int = 0,
    pencil: bool = False,
    bow_m: float = 0.0,
    cup_m: float = 0.0,
    noise_dn: float = 1.0,
    imbalance: float = 0.0,
    grain: float = 0.05,
    speed_mm_s: float = 200.0,
    exposure_ms: float = 0.1,
    level_dn: float = 110.0,
    width: int = 659,
    height: int = 320,
    rig_roll_deg: float | None = None,
) -> Board:
    """Render one pair (image B taken after the board moved ``shift_px`` along the feed)."""
    rng = np.random.default_rng(seed)
    ppm = PX_PER_MM
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    rr = math.radians(roll_deg)
    cr, sr = math.cos(rr), math.sin(rr)
    reach_mm = (abs(cx * cr) + abs(cy * sr) + shift_px + 40) / ppm
    # board coordinate along the feed: x_b = xi_mm + cx / ppm at A
    x0 = cx / ppm - reach_mm - 2.0
    x1 = cx / ppm + reach_mm + 2.0
    xb = np.arange(x0, x1, STEP_MM)
    knives = len(runout_um)
    centres = np.arange(x0 - 3 * pitch_mm, x1 + 3 * pitch_mm, pitch_mm)
    lowest = -np.asarray(runout_um, float)[np.arange(centres.size) % knives] * 1e-3
    z = np.full(xb.size, np.inf)
    which = np.zeros(xb.size, dtype=int)
    for k, (c, lo) in enumerate(zip(centres, lowest, strict=True)):
        arc = lo + (xb - c) ** 2 / (2.0 * radius_mm)
        better = arc < z
        z[better] = arc[better]
        which[better] = k
    marks_z = z.copy()
    if bow_m:
        xm = xb - cx / ppm
        z = z + xm * xm / (2.0 * bow_m * 1000.0)
    p = np.gradient(z, xb)
    cusp_idx = np.flatnonzero(np.diff(which) != 0)
    cusps = xb[cusp_idx] + STEP_MM / 2
    # true depth per complete mark
    depths = []
    for i in range(cusps.size - 1):
        seg = marks_z[cusp_idx[i] + 1: cusp_idx[i + 1] + 1]
        depths.append(1000 * (0.5 * (marks_z[cusp_idx[i]] + marks_z[cusp_idx[i + 1] + 1])
                              - seg.min()))
    depths_um = np.asarray(depths)

    sa = math.radians(slant_deg + slant_a_error_deg)
    sb = math.radians(slant_deg + slant_b_error_deg)
    shade_a = _oren_nayar(p, azimuth_sign=+1.0, slant_rad=sa, roughness_rad=roughness_rad)
    shade_b = _oren_nayar(p, azimuth_sign=-1.0, slant_rad=sb, roughness_rad=roughness_rad)

    def filt(values: np.ndarray, kernel: np.ndarray) -> np.ndarray:
        ext = np.pad(values, (kernel.size // 2, (kernel.size - 1) // 2), mode="edge")
        return np.convolve(ext, kernel, "valid")

    if scatter_mm > 0:
        t = np.arange(-int(5 * scatter_mm / STEP_MM), int(5 * scatter_mm / STEP_MM) + 1) * STEP_MM
        ker = np.exp(-np.abs(t) / scatter_mm)
        ker /= ker.sum()
        shade_a = (1 - scatter_fraction) * shade_a + scatter_fraction * filt(shade_a, ker)
        shade_b = (1 - scatter_fraction) * shade_b + scatter_fraction * filt(shade_b, ker)
    # pixel footprint along the feed plus motion blur over the exposure
    blur_mm = speed_mm_s * exposure_ms / 1000.0
    box = np.ones(max(1, int(round((1.0 / ppm) / STEP_MM))))
    box /= box.sum()
    shade_a, shade_b = filt(shade_a, box), filt(shade_b, box)
    if blur_mm > STEP_MM:
        mot = np.ones(max(1, int(round(blur_mm / STEP_MM))))
        mot /= mot.sum()
        shade_a, shade_b = filt(shade_a, mot), filt(shade_b, mot)

    # albedo map on the board: x along the feed, y across
    ny = int((height + 60) / ppm / ALBEDO_MM)
    nx = int((x1 - x0) / ALBEDO_MM)
    y0 = -(ny * ALBEDO_MM) / 2
    along = rng.standard_normal(nx).astype(np.float32)
    along = cv2.GaussianBlur(along[None, :], (0, 0), sigmaX=0.3 / ALBEDO_MM)[0]
    along /= max(float(along.std()), 1e-9)
    fib = rng.standard_normal((ny, nx)).astype(np.float32)
    fib = cv2.GaussianBlur(fib, (0, 0), sigmaX=1.0 / ALBEDO_MM, sigmaY=0.06 / ALBEDO_MM)
    fib /= max(float(fib.std()), 1e-9)
    rho = 1.0 + albedo * along[None, :] + fibre * fib
    gy, gx = np.mgrid[0:ny, 0:nx].astype(np.float32)
    gxm, gym = x0 + gx * ALBEDO_MM, y0 + gy * ALBEDO_MM
    for _ in range(knots):
        kx, ky = rng.uniform(x0 + 5, x1 - 5), rng.uniform(y0 / 2, -y0 / 2)
        ax, ay = rng.uniform(1.5, 4.0), rng.uniform(1.0, 2.5)
        r2 = ((gxm - kx) / ax) ** 2 + ((gym - ky) / ay) ** 2
        rho *= 1.0 - 0.45 * np.exp(-r2 * r2)
    if pores:
        dots = np.zeros((ny, nx), np.float32)
        dots[rng.integers(0, ny, pores), rng.integers(0, nx, pores)] = 1.0
        dots = cv2.GaussianBlur(dots, (0, 0), sigmaX=0.1 / ALBEDO_MM, sigmaY=0.05 / ALBEDO_MM)
        rho *= 1.0 - 0.5 * dots / max(float(dots.max()), 1e-9)
    if pencil:
        ly = rng.uniform(y0 / 3, -y0 / 3)
        rho *= 1.0 - 0.5 * np.exp(-(((gym - ly) / 0.25) ** 2))
    rho = rho.astype(np.float32)

    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    xi_mm = ((uu - cx) * cr + (vv - cy) * sr) / ppm
    eta_mm = (-(uu - cx) * sr + (vv - cy) * cr) / ppm
    cup = 1.0
    if cup_m:
        q = eta_mm / (cup_m * 1000.0)
        cup = 1.0 / np.sqrt(1.0 + q * q)
    stripes = 1.0 + grain * np.sin(2 * np.pi * np.arange(height) / 37.0 + rng.uniform(0, 6))
    falloff = 1.0 + 0.05 * (uu - cx) / width
    shift_mm = shift_px / ppm

    def shot(offset_mm: float, shade: np.ndarray, gain: float, cos_s: float) -> np.ndarray:
        xbp = xi_mm + cx / ppm - offset_mm  # board coordinate seen by each pixel
        s_img = np.interp(xbp, xb, shade)
        mx = ((xbp - x0) / ALBEDO_MM).astype(np.float32)
        my = ((eta_mm - y0) / ALBEDO_MM).astype(np.float32)
        r_img = cv2.remap(rho, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        img = level_dn * gain * stripes[:, None] * falloff * cup * r_img * s_img / cos_s
        img = img + rng.normal(0.0, noise_dn, img.shape)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)

    cos_ref = math.cos(math.radians(slant_deg))
    image_a = shot(0.0, shade_a, 1.0, cos_ref)
    image_b = shot(shift_mm, shade_b, 1.0 + imbalance, cos_ref)
    counts_a = 4_294_967_000
    counts_b = (counts_a + int(round((shift_px + slip_px) * COUNTS_PER_MM / ppm))) % (1 << 32)
    rig = Rig(
        Camera(fx=1400.0, fy=1400.0, cx=cx, cy=cy, dist=(0.0, 0.0, 0.0, 0.0, 0.0),
               px_per_mm=ppm, exposure_ms=exposure_ms),
        Lights(slant_deg=slant_deg),
        Encoder(px_per_count=ppm / COUNTS_PER_MM),
    )
    if rig_roll_deg is not None:
        rig = _with_roll(rig, rig_roll_deg)
    x_mm = cx / ppm + np.arange(-cx - 40, cx + 40, 0.25) / ppm
    gain = 0.5 * (math.tan(sa) + math.tan(sb)) / math.tan(math.radians(slant_deg))
    spindle_rpm = speed_mm_s * 60.0 / (pitch_mm * knives)  # feed per knife pass = pitch
    return Board(rig, image_a, image_b, counts_a, counts_b, shift_px, x_mm,
                 np.interp(x_mm, xb, z) * 1000.0, cusps, depths_um, speed_mm_s, radius_mm, knives,
                 spindle_rpm, roll_deg, gain)


def _with_roll(rig: Rig, roll_deg: float) -> Rig:
    from dataclasses import replace

    return replace(rig, camera=replace(rig.camera, roll_deg=roll_deg))
