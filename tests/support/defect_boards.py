"""An independent renderer of boards with wood defects (not plant_sim, not vision).

Shares no code with ``plant_sim/`` or ``vision/``; it takes only the pixel scale and encoder
resolution of ``tests/support/vision_boards.py``.  Unlike that renderer (a 1-D height along the
feed),
the surface here is a 2-D height field ``z(x, y)`` on a board grid of 0.02 mm along the feed and
0.04 mm across it, so that defects whose shading depends on the light are rendered as a camera
sees them:

- **cuttermarks**: the lower envelope of the knife-tip arcs of radius R (per-knife runout),
  optionally with *chatter* (each pass's lowest point modulated by a sinusoid over the passes)
  and *snipe* (the cut deepening exponentially toward one end of the board);
- **torn grain**: pits of 0.05-1 mm depth, 2-15 mm long, along or across the grain, soft walls
  and a rough, fibrous bottom;
- **raised grain**: ridges following the growth rings (the latewood bands, which also set the
  albedo's ring pattern) at any angle to the feed, 10-50 um high;
- **fuzzy grain**: a patch of fibre tufts, 10-30 um rms, elongated along the grain;
- **chip marks**: smooth dents 30-150 um deep, 1-4 mm across;
- **knife nick**: in a band across the feed one knife cuts short by tens of micrometres (a ridge
  along the feed on that knife's marks).

Shading: Lambert (seed Eq. 1) under two lights at azimuth 0 (the +x side) and 180 deg at the
rig's slant, with cast shadows (a point is dark when the surface toward its light rises above the
light's elevation) and a little ambient light; the 2-D surface normal enters through
``1 / sqrt(1 + p^2 + q^2)``.  The cuttermarks' own shading is computed exactly on a fine 1-D
grid (0.002 mm); the defects add, on the 2-D grid, the difference between the shading with and
without them, so a board without defects is rendered as precisely as ``vision_boards`` does.
Pixels average over their footprint (one pixel along and across the feed) and the motion blur;
camera roll; species set the albedo (rings, fibres, pores or rays) and its level; LED imbalance;
read noise; 8-bit rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from config.rig import Camera, Encoder, Lights, Rig
from tests.support.vision_boards import COUNTS_PER_MM, PX_PER_MM

FINE_MM = 0.002  # 1-D grid of the cuttermarks' shading
DX_MM = 0.02  # 2-D board grid along the feed
DY_MM = 0.04  # and across it
AMBIENT = 0.03  # fraction of the direct light reaching shadowed points (interreflections)


@dataclass(frozen=True)
class Species:
    """Appearance of a wood species (albedo only; the defects carry the geometry)."""

    name: str
    level_dn: float  # mean grey level
    ring_mm: tuple[float, float]  # range of the growth rings' spacing
    ring_contrast: float  # latewood darker by this fraction
    fibre: float  # 2-D fibre texture, fraction
    along: float  # along-feed albedo variation, fraction
    pores: int  # dark dots (oak) per image
    rays: int  # short dark flecks across the grain (beech)


SPECIES = {
    "pine": Species("pine", 125.0, (2.5, 6.0), 0.18, 0.03, 0.03, 0, 0),
    "oak": Species("oak", 105.0, (1.5, 4.0), 0.08, 0.04, 0.04, 400, 0),
    "beech": Species("beech", 135.0, (1.5, 3.5), 0.04, 0.025, 0.03, 0, 60),
}


@dataclass(frozen=True)
class Defects:
    """The defects of one board (all off by default: a clean board).

    Lengths in mm, heights in um; angles in degrees from the feed (x) toward +y.
    """

    torn: tuple[tuple[float, float, float, float], ...] = ()  # (depth_mm, length, width, angle)
    raised_um: float = 0.0  # ridge height along the rings
    fuzzy_um: float = 0.0  # rms of the fuzzy patch
    fuzzy_mm: float = 12.0  # patch diameter
    chips_um: tuple[float, ...] = ()  # depth of each chip mark
    nick_um: float = 0.0  # how much shorter the nicked knife cuts in its band
    nick_mm: float = 0.6  # width of the nick's band across the feed
    chatter_um: float = 0.0  # amplitude of the passes' modulation
    chatter_passes: float = 4.7  # its period, knife passes
    snipe_um: float = 0.0  # the cut deeper by this much at the field's -x edge
    snipe_mm: float = 40.0  # decay length of the snipe


@dataclass(frozen=True)
class Placed:
    """One local defect as placed on the board grid (``x`` along the feed at shot A, ``y``
    across it from the board's centre line, mm; ``depth_um`` < 0 for a ridge)."""

    kind: str  # "torn", "fuzzy", "chip" or "nick"
    x_mm: float
    y_mm: float
    length_mm: float  # along its own axis
    width_mm: float
    angle_deg: float  # its axis from the feed toward +y
    depth_um: float


@dataclass(frozen=True)
class DefectBoard:
    """A rendered pair and its truth (profile in A's frame along the feed)."""

    rig: Rig
    image_a: np.ndarray
    image_b: np.ndarray
    counts_a: int
    counts_b: int
    shift_px: float  # true board motion between the shots, px along the feed
    x_mm: np.ndarray  # truth grid: board position along the feed at A
    height_um: np.ndarray  # the cuttermarks' profile (chatter and snipe included, no defects)
    surface_um: np.ndarray  # the whole surface averaged along the marks over the imaged rows
    cusps_mm: np.ndarray  # true cusps of the cuttermarks
    depths_um: np.ndarray  # per complete true mark (mean of its cusps minus its bottom)
    speed_mm_s: float
    radius_mm: float
    knives: int
    spindle_rpm: float
    roll_deg: float
    species: str
    defects: Defects = field(default_factory=Defects)
    placed: tuple[Placed, ...] = ()  # where the local defects were put (board frame)
    ring_angle_deg: float = 10.0  # direction of the growth rings (and raised grain)


def _box(n: int) -> np.ndarray:
    k = np.ones(max(1, int(n)))
    return k / k.sum()


def _filt(values: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    ext = np.pad(values, (kernel.size // 2, (kernel.size - 1) // 2), mode="edge")
    return np.convolve(ext, kernel, "valid")


def _marks(xb: np.ndarray, *, pitch_mm: float, radius_mm: float, runout_um: np.ndarray,
           chatter_um: float, chatter_passes: float, phase: float,
           raise_knife: int | None = None, raise_um: float = 0.0
           ) -> tuple[np.ndarray, np.ndarray]:
    """Lower envelope of the arcs on grid ``xb`` (mm): height (mm) and index of the arc."""
    x0, x1 = float(xb[0]), float(xb[-1])
    centres = np.arange(x0 - 3 * pitch_mm, x1 + 3 * pitch_mm, pitch_mm)
    knives = runout_um.size
    j = np.arange(centres.size)
    lowest_um = -runout_um[j % knives]
    if chatter_um:
        lowest_um = lowest_um + chatter_um * np.sin(2 * np.pi * j / chatter_passes + phase)
    if raise_knife is not None:
        lowest_um = lowest_um + np.where(j % knives == raise_knife, raise_um, 0.0)
    z = np.full(xb.size, np.inf)
    which = np.zeros(xb.size, dtype=int)
    for k, (c, lo) in enumerate(zip(centres, lowest_um * 1e-3, strict=True)):
        sel = slice(max(0, int((c - 2 * pitch_mm - x0) / (xb[1] - xb[0]))),
                    int((c + 2 * pitch_mm - x0) / (xb[1] - xb[0])) + 1)
        arc = lo + (xb[sel] - c) ** 2 / (2.0 * radius_mm)
        better = arc < z[sel]
        z[sel] = np.where(better, arc, z[sel])
        which[sel] = np.where(better, k, which[sel])
    return z, which


def _lambert(p: np.ndarray, q: np.ndarray | float, sign: float, slant: float) -> np.ndarray:
    """Lambert radiance of slope (p, q) under the light at azimuth 0 (sign +1) or 180 (-1)."""
    return np.maximum(0.0, math.cos(slant) - sign * p * math.sin(slant)) / np.sqrt(
        1.0 + p * p + q * q)


def _lit(z_mm: np.ndarray, x_mm: np.ndarray, sign: float, slant: float) -> np.ndarray:
    """1 where the light at azimuth 0 (+1) or 180 (-1) reaches the point, else 0 (rows along x)."""
    c = 1.0 / math.tan(slant)  # the ray climbs c mm per mm toward its light
    if sign > 0:  # light on the +x side: anything further along +x that rises above the ray
        g = z_mm - c * x_mm[None, :]
        ahead = np.maximum.accumulate(g[:, ::-1], axis=1)[:, ::-1]
        ahead = np.concatenate([ahead[:, 1:], np.full((g.shape[0], 1), -np.inf)], axis=1)
    else:
        g = z_mm + c * x_mm[None, :]
        ahead = np.maximum.accumulate(g, axis=1)
        ahead = np.concatenate([np.full((g.shape[0], 1), -np.inf), ahead[:, :-1]], axis=1)
    return (ahead <= g + 1e-6).astype(np.float32)


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sx: float, sy: float
                  ) -> np.ndarray:
    """Unit-rms Gaussian noise smoothed by sigmas ``sx``, ``sy`` (grid samples)."""
    n = rng.standard_normal(shape).astype(np.float32)
    n = cv2.GaussianBlur(n, (0, 0), sigmaX=max(sx, 0.3), sigmaY=max(sy, 0.3))
    return n / max(float(n.std()), 1e-9)


def render_defect_board(
    seed: int,
    *,
    species: str = "pine",
    defects: Defects = Defects(),
    shift_px: float = 20.0,
    slip_px: float = 0.0,
    pitch_mm: float = 2.0,
    radius_mm: float = 60.0,
    runout_um: tuple[float, ...] = (0.0, 2.0, -1.0, 1.0),
    slant_deg: float = 82.0,
    roll_deg: float = 0.0,
    ring_angle_deg: float = 10.0,
    speed_mm_s: float = 200.0,
    exposure_ms: float = 0.1,
    noise_dn: float = 1.5,
    imbalance: float = 0.0,
    width: int = 659,
    height: int = 240,
) -> DefectBoard:
    """Render one pair of a board with defects (B taken after the board moved ``shift_px``).

    Parameters
    ----------
    seed : int
        Seed of everything random (albedo, defect shapes and places, noise).
    species : str
        ``"pine"``, ``"oak"`` or ``"beech"`` (:data:`SPECIES`).
    defects : Defects
        What is wrong with the surface.
    shift_px, slip_px : float
        True motion between the shots, and the encoder's error, pixels.
    ring_angle_deg : float
        Direction of the growth rings (and of the raised grain) from the feed, degrees.

    Returns
    -------
    DefectBoard
    """
    rng = np.random.default_rng(seed)
    sp = SPECIES[species]
    ppm = PX_PER_MM
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    rr = math.radians(roll_deg)
    cr, sr = math.cos(rr), math.sin(rr)
    reach_mm = (abs(cx * cr) + abs(cy * sr) + abs(shift_px) + 30) / ppm
    x0 = cx / ppm - reach_mm - 1.0
    x1 = cx / ppm + reach_mm + 1.0
    half_y = (abs(cx * sr) + abs(cy * cr) + 10) / ppm
    slant = math.radians(slant_deg)
    runout = np.asarray(runout_um, dtype=float)
    knives = runout.size
    phase = float(rng.uniform(0, 2 * np.pi))

    # -- cuttermarks on the fine 1-D grid: exact pixel-averaged shading -----------------------
    xf = np.arange(x0, x1, FINE_MM)
    mk = dict(pitch_mm=pitch_mm, radius_mm=radius_mm, runout_um=runout,
              chatter_um=defects.chatter_um, chatter_passes=defects.chatter_passes, phase=phase)
    zf, which = _marks(xf, **mk)
    marks_only = zf.copy()
    if defects.snipe_um:
        zf = zf - defects.snipe_um * 1e-3 * np.exp(-(xf - x0) / defects.snipe_mm)
    pf = np.gradient(zf, xf)
    cusp_idx = np.flatnonzero(np.diff(which) != 0)
    cusps = xf[cusp_idx] + FINE_MM / 2
    depths = []
    for i in range(cusps.size - 1):
        seg = marks_only[cusp_idx[i] + 1: cusp_idx[i + 1] + 1]
        depths.append(1000 * (0.5 * (marks_only[cusp_idx[i]] + marks_only[cusp_idx[i + 1] + 1])
                              - seg.min()))
    blur_mm = speed_mm_s * exposure_ms / 1000.0
    foot = _box(round(1.0 / ppm / FINE_MM))
    mot = _box(round(blur_mm / FINE_MM)) if blur_mm > FINE_MM else None
    clean = []
    for sign in (1.0, -1.0):
        s = _lambert(pf, 0.0, sign, slant)
        s = _filt(s, foot)
        clean.append(_filt(s, mot) if mot is not None else s)

    # -- the 2-D board grid ---------------------------------------------------------------------
    X = np.arange(x0, x1, DX_MM)
    Y = np.arange(-half_y, half_y, DY_MM)
    ny, nx = Y.size, X.size
    xx = X[None, :]
    yy = Y[:, None]
    dz = np.zeros((ny, nx), dtype=np.float64)  # defects' height, mm
    placed: list[Placed] = []
    # the field's centre region, where defects must lie to be seen by both shots
    fx0, fx1 = cx / ppm - 0.4 * width / ppm, cx / ppm + 0.4 * width / ppm
    ta = math.radians(ring_angle_deg)
    ring_mm = float(rng.uniform(*sp.ring_mm))
    along_ring = xx * math.cos(ta) + yy * math.sin(ta)
    across_ring = -xx * math.sin(ta) + yy * math.cos(ta)
    ring_phase = (across_ring + 0.004 * along_ring**2) / ring_mm + rng.uniform(0, 1)
    latewood = 0.5 * (1.0 + np.tanh((np.cos(2 * np.pi * ring_phase) - 0.5) / 0.15))

    if defects.raised_um:
        ridge = cv2.GaussianBlur(latewood.astype(np.float32), (0, 0),
                                 sigmaX=0.08 / DX_MM, sigmaY=0.08 / DY_MM)
        dz += defects.raised_um * 1e-3 * (ridge - ridge.mean())
    for depth_mm, length, wid, angle in defects.torn:
        a = math.radians(angle)
        tx, ty = rng.uniform(fx0 + length / 2, fx1 - length / 2), rng.uniform(-4.0, 4.0)
        u = (xx - tx) * math.cos(a) + (yy - ty) * math.sin(a)
        v = -(xx - tx) * math.sin(a) + (yy - ty) * math.cos(a)
        r = np.sqrt((2 * u / length) ** 2 + (2 * v / wid) ** 2)
        wobble = 1.0 + 0.15 * _smooth_noise(rng, (ny, nx), 0.6 / DX_MM, 0.3 / DY_MM)
        mask = np.clip((1.0 - r * wobble) / 0.12, 0.0, 1.0).astype(np.float32)
        mask = cv2.GaussianBlur(mask, (0, 0), sigmaX=0.06 / DX_MM, sigmaY=0.06 / DY_MM)
        bottom = 0.75 + 0.25 * _smooth_noise(rng, (ny, nx), 0.25 / DX_MM, 0.05 / DY_MM)
        dz -= depth_mm * mask * np.clip(bottom, 0.3, 1.3)
        placed.append(Placed("torn", tx, ty, length, wid, angle, 1000.0 * depth_mm))
    if defects.fuzzy_um:
        fxc, fyc = rng.uniform(fx0 + 8, fx1 - 8), rng.uniform(-3.0, 3.0)
        r2 = ((xx - fxc) ** 2 + (yy - fyc) ** 2) / (defects.fuzzy_mm / 2) ** 2
        patch = np.clip((1.0 - r2) / 0.3, 0.0, 1.0)
        tufts = _smooth_noise(rng, (ny, nx), 0.2 / DX_MM, 0.06 / DY_MM)
        dz += defects.fuzzy_um * 1e-3 * patch * tufts
        placed.append(Placed("fuzzy", fxc, fyc, defects.fuzzy_mm, defects.fuzzy_mm, 0.0, 0.0))
    for chip_um in defects.chips_um:
        kx, ky = rng.uniform(fx0 + 3, fx1 - 3), rng.uniform(-6.0, 6.0)
        sx, sy = rng.uniform(0.4, 1.2), rng.uniform(0.5, 1.5)
        dz -= chip_um * 1e-3 * np.exp(-0.5 * (((xx - kx) / sx) ** 2 + ((yy - ky) / sy) ** 2))
        placed.append(Placed("chip", kx, ky, 4 * sx, 4 * sy, 0.0, chip_um))  # +-2 sigma
    z_nick_line = None
    if defects.nick_um:
        knife = int(rng.integers(0, knives))
        zn, _ = _marks(xf, raise_knife=knife, raise_um=defects.nick_um, **mk)
        band_y = rng.uniform(-4.0, 4.0)
        band = np.clip((defects.nick_mm / 2 - np.abs(yy - band_y)) / 0.05 + 0.5, 0, 1)
        z_nick_line = np.interp(X, xf, zn - marks_only)
        dz += band * z_nick_line[None, :]
        placed.append(Placed("nick", cx / ppm, band_y, width / ppm, defects.nick_mm, 0.0,
                             -defects.nick_um))

    # -- radiance maps: exact clean shading plus the defects' difference -----------------------
    rho = (1.0 - sp.ring_contrast * latewood).astype(np.float32)
    along = _smooth_noise(rng, (1, nx), 0.3 / DX_MM, 0.1)[0]
    rho *= (1.0 + sp.along * along)[None, :].astype(np.float32)
    rho *= 1.0 + sp.fibre * _smooth_noise(rng, (ny, nx), 1.0 / DX_MM, 0.06 / DY_MM)
    if sp.pores:
        dots = np.zeros((ny, nx), np.float32)
        dots[rng.integers(0, ny, sp.pores), rng.integers(0, nx, sp.pores)] = 1.0
        dots = cv2.GaussianBlur(dots, (0, 0), sigmaX=0.12 / DX_MM, sigmaY=0.05 / DY_MM)
        rho *= 1.0 - 0.5 * dots / max(float(dots.max()), 1e-9)
    if sp.rays:
        flecks = np.zeros((ny, nx), np.float32)
        flecks[rng.integers(0, ny, sp.rays), rng.integers(0, nx, sp.rays)] = 1.0
        flecks = cv2.GaussianBlur(flecks, (0, 0), sigmaX=0.1 / DX_MM, sigmaY=0.6 / DY_MM)
        rho *= 1.0 - 0.3 * flecks / max(float(flecks.max()), 1e-9)

    kx_box = max(1, round((1.0 / ppm + blur_mm) / DX_MM))
    ky_box = max(1, round(1.0 / ppm / DY_MM))
    has_defect = bool(np.any(dz != 0.0))
    maps = []
    for sign, shade in zip((1.0, -1.0), clean, strict=True):
        base = np.interp(X, xf, shade)[None, :]
        if has_defect:
            pm = np.interp(X, xf, pf)[None, :]
            gy, gx = np.gradient(dz, DY_MM, DX_MM)
            p = pm + gx
            full = _lambert(p, gy, sign, slant)
            z2 = np.interp(X, xf, zf)[None, :] + dz
            lit = _lit(z2, X, sign, slant)
            full = full * (AMBIENT + (1.0 - AMBIENT) * lit)
            delta = (full - _lambert(pm, 0.0, sign, slant)).astype(np.float32)
            m = rho * (base + delta)
        else:
            m = rho * base
        maps.append(cv2.blur(m.astype(np.float32), (kx_box, ky_box),
                             borderType=cv2.BORDER_REFLECT))

    # -- the two shots ---------------------------------------------------------------------------
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    xi_mm = ((uu - cx) * cr + (vv - cy) * sr) / ppm
    eta_mm = (-(uu - cx) * sr + (vv - cy) * cr) / ppm
    falloff = 1.0 + 0.04 * (uu - cx) / width
    cos_s = math.cos(slant)

    def shot(offset_mm: float, radiance: np.ndarray, gain: float) -> np.ndarray:
        mx = ((xi_mm + cx / ppm - offset_mm - x0) / DX_MM).astype(np.float32)
        my = ((eta_mm + half_y) / DY_MM).astype(np.float32)
        img = cv2.remap(radiance, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        img = sp.level_dn * gain * falloff * img / cos_s
        img = img + rng.normal(0.0, noise_dn, img.shape)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)

    image_a = shot(0.0, maps[0], 1.0)
    image_b = shot(shift_px / ppm, maps[1], 1.0 + imbalance)
    counts_a = 4_294_967_000
    counts_b = (counts_a + int(round((shift_px + slip_px) * COUNTS_PER_MM / ppm))) % (1 << 32)
    rig = Rig(
        Camera(fx=1400.0, fy=1400.0, cx=cx, cy=cy, dist=(0.0, 0.0, 0.0, 0.0, 0.0),
               px_per_mm=ppm, exposure_ms=exposure_ms),
        Lights(slant_deg=slant_deg),
        Encoder(px_per_count=ppm / COUNTS_PER_MM),
    )
    # truth: the surface averaged along the marks over the rows the camera sees at A
    rows = np.abs(Y) <= abs(cx * sr) / ppm + abs(cy * cr) / ppm
    dz_mean = dz[rows].mean(axis=0) if has_defect else np.zeros(nx)
    x_mm = cx / ppm + np.arange(-cx - 30, cx + 30, 0.25) / ppm
    marks_truth = np.interp(x_mm, xf, zf)
    surface = marks_truth + np.interp(x_mm, X, dz_mean)
    spindle_rpm = speed_mm_s * 60.0 / (pitch_mm * knives)
    return DefectBoard(rig, image_a, image_b, counts_a, counts_b, shift_px, x_mm,
                       marks_truth * 1000.0, surface * 1000.0, cusps, np.asarray(depths),
                       speed_mm_s, radius_mm, knives, spindle_rpm, roll_deg, species, defects,
                       tuple(placed), ring_angle_deg)
