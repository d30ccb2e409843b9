"""Image formation for dynamic photometric stereo: two grazing-light images of a moving board.

Geometry (docs/architecture.md)
-------------------------------
- Board coordinate ``b`` (mm) is fixed to the board. At trigger A the board point ``b`` is at
  physical position ``X = b - board_x_at_centre_mm`` (mm from the optical axis along the feed);
  the board moves toward +x, so at trigger B (``dt_ab_s`` later) it is at
  ``X + speed_mm_s * dt_ab_s``. The trigger instant is the middle of the exposure.
- The undistorted image uses the camera matrix K of the distorted one: undistorted column ``u`` is
  at ``X = (u - cx) / px_per_mm``, undistorted row ``v`` at ``Y = (v - cy) / px_per_mm_y`` with
  ``px_per_mm_y = px_per_mm * fy / fx``. Each distorted pixel shows the board at the undistorted
  position that :func:`cv2.undistortPoints` (``P = K``) gives for it, so that
  :func:`cv2.projectPoints` maps a board point back to the pixel that shows it.
- Radiance by the seed's Eq. 1 (Lambert): ``I = I0 rho (-p cos(tau) sin(s) - q sin(tau) sin(s) +
  cos(s)) / sqrt(1 + p^2 + q^2)`` with ``p = dz/dx`` (kinematic profile plus fibre roughness) and
  ``q = dz/dy`` (roughness). The light at azimuth 0 deg stands on the +x side, so a surface
  rising toward +x is darker in image A.

Effects of a real rig and real wood (:class:`RigEffects`, all off by default)
-----------------------------------------------------------------------------
- Camera roll about the optical axis (the convention of :mod:`vision.orientation` and
  ``docs/architecture.md``): the pixel at camera-frame offset ``(Xc, Yc)`` (mm from the axis,
  undistorted) shows the board point ``X = Xc cos(r) + Yc sin(r)``, ``Y = -Xc sin(r) +
  Yc cos(r)``; a mark (constant ``X``) runs down the image leaning ``tan(r)`` columns per row
  toward -u, and the feed runs along ``(cos r, sin r)`` in ``(u, v)``, so the measured
  ``roll_deg`` equals the simulated one. ``x_phys_mm`` /
  ``y_phys_mm`` are board-frame positions; the lights (azimuths, fall-off) are fixed to the
  machine, i.e. to the board frame.
- True light slant: light i shines at the rig file's slant (``Lights.slants_deg``) plus
  ``slant_offset_deg[i]`` while the rig file
  keeps the nominal slant. Each LED's power is set so that a flat board shows ``Optics.level``
  (its slope sensitivity ``tan(s_i)`` changes, its flat brightness does not).
- Rough-wood reflectance (Oren-Nayar, roughness ``reflectance_roughness_deg``): the profile's
  shading is ``A cos(ti) + B cos(ti) sin(alpha) tan(beta) max(0, cos(phi_i - phi_r))`` with the
  camera looking straight down; ``A = 1`` and ``B = 0`` is Lambert.
- Subsurface scattering: a fraction ``Wood.translucency`` of the reflected light leaves the wood
  spread by an exponential kernel of length ``scattering_mm`` along the fibres (x) and
  ``scattering_mm / Wood.scattering_anisotropy`` across them; it lowers the contrast of the marks
  and of the fibre-scale roughness.
- Bow and cup of the board (sagitta over its length / width, ends and edges higher for positive
  values) tilt the surface: bow adds the slope ``8 bow (b - L/2) / L^2`` to the profile, cup the
  slope ``8 cup y / W^2`` across it. Neither is part of the truth profile (the marks).
- Pencil lines along the feed (across the marks) darken the albedo.
The static parts (roll, scattering of the roughness, cup, pencil lines) are built into the maps
and textures once per renderer; per frame only 1-D work along x is added.

Rendering is done on a regular board grid (one column per undistorted pixel along x, or finer
with ``Optics.oversample``; one row per pixel along y), blurred along the feed by the exposure
(exact box average of the radiance), then resampled at the precomputed positions of the distorted
pixels with :func:`cv2.remap`; illumination (LED imbalance, fall-off) is applied per pixel, then
shot and read noise, then quantisation with saturation.

Cost: per image the work is a fixed number of passes over the board grid and the
image, in float32, with no per-pixel Python; the texture window is interpolated in one
``cv2.addWeighted`` and the sensor noise drawn by OpenCV's generator seeded from the
renderer's stream (:func:`standard_normal_f32`); ``tests/plant_sim/test_sim_speed_optics.py`` holds
the step-by-step reference formulas the images must equal.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import scipy.fft as sfft

from config.rig import Rig
from config.wood import Wood
from core.checks import check_finite, check_int, check_positive, check_range
from core.units import wrap_counter
from plant_sim.rendering.defect_shading import BoardGrid, shade_patch
from plant_sim.rendering.defects import DefectLayer
from plant_sim.rendering.wood import texture_tiles

__all__ = [
    "ImagePair",
    "Optics",
    "PencilLine",
    "Renderer",
    "RigEffects",
    "Truth",
    "effects_from_config",
]

HeightSource = Any  # callable height_um(b_mm), a Surface, or an object with x_mm, height_um
AlbedoFactor = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (board x, board y) -> factor


@dataclass(frozen=True)
class Optics:
    """Camera sensor, exposure, LED and encoder parameters of the simulated rig.

    Attributes
    ----------
    width, height : int
        Image size in pixels (659 x 493 by default).
    bit_depth : int
        Bits per pixel (8 gives uint8 images, 9..16 give uint16); full scale ``2**bit_depth - 1``.
    level : float
        Mean brightness of a flat board of the species' mean albedo, lit by light A at the field
        centre, as a fraction of full scale (before ``gain``).
    gain : float
        Analogue gain (multiplies signal and shot noise; > 1 drives towards saturation).
    read_noise_dn : float
        Read noise, digital numbers rms.
    full_well_e : float
        Full-well capacity at unit gain, electrons; sets the shot noise.
    shot_noise : bool
        Whether to add shot noise.
    led_imbalance : float
        Brightness of LED B over LED A minus one (0.07: B is 7 % brighter).
    falloff : float
        Fractional intensity change of each LED across the field width; each LED is brighter on
        its own side (the light at azimuth 0 deg on +x).
    exposure_ms : float or None
        Exposure time, milliseconds; ``None`` takes the rig's (0 if the rig has none).
    dt_ab_s : float
        Time between triggers A and B, seconds.
    counts_per_mm : float
        Feed encoder resolution, counts per mm; the rig's ``px_per_count`` must equal
        ``px_per_mm / counts_per_mm``.
    quantize : bool
        Quantise to integers (``False`` returns float32 images without clipping, for tests).
    oversample : int
        Board-grid columns per undistorted pixel along x (odd: 1, 3, 5, 7, so that cell edges
        fall on pixel edges); the radiance is computed per column and averaged over each pixel's
        footprint (finer pixel integration, slower).
    """

    width: int = 659
    height: int = 493
    bit_depth: int = 8
    level: float = 0.45
    gain: float = 1.0
    read_noise_dn: float = 0.5
    full_well_e: float = 10000.0
    shot_noise: bool = True
    led_imbalance: float = 0.0
    falloff: float = 0.0
    exposure_ms: float | None = None
    dt_ab_s: float = 0.002
    counts_per_mm: float = 20.0
    quantize: bool = True
    oversample: int = 1

    def __post_init__(self) -> None:
        check_int("width", self.width, lo=16, hi=16384)
        check_int("height", self.height, lo=4, hi=16384)
        check_int("bit_depth", self.bit_depth, lo=8, hi=16)
        check_range("level", self.level, 0.0, 1.0)
        check_positive("gain", self.gain)
        check_positive("read_noise_dn", self.read_noise_dn, allow_zero=True)
        check_positive("full_well_e", self.full_well_e)
        check_range("led_imbalance", self.led_imbalance, -0.9, 10.0)
        check_range("falloff", self.falloff, -1.0, 1.0)
        if self.exposure_ms is not None:
            check_positive("exposure_ms", self.exposure_ms, allow_zero=True)
        check_positive("dt_ab_s", self.dt_ab_s, allow_zero=True)
        check_positive("counts_per_mm", self.counts_per_mm)
        if check_int("oversample", self.oversample, lo=1, hi=7) % 2 == 0:
            raise ValueError(f"oversample must be odd (1, 3, 5, 7), got {self.oversample}")

    @property
    def max_dn(self) -> int:
        """Full-scale value, ``2**bit_depth - 1``."""
        return (1 << self.bit_depth) - 1

    @property
    def dtype(self) -> type:
        """Output pixel type: uint8 up to 8 bits, uint16 above."""
        return np.uint8 if self.bit_depth <= 8 else np.uint16


@dataclass(frozen=True)
class PencilLine:
    """A pencil line drawn on the board along the feed (so across the marks).

    Attributes
    ----------
    y_mm : float
        Position across the board, millimetres from the optical axis (board frame).
    width_mm : float
        Full width of the line, millimetres.
    darkness : float
        Relative darkening of the albedo at the line's centre (0..1).
    """

    y_mm: float = 0.0
    width_mm: float = 0.6
    darkness: float = 0.5

    def __post_init__(self) -> None:
        check_finite("y_mm", self.y_mm)
        check_range("width_mm", self.width_mm, 0.01, 50.0)
        check_range("darkness", self.darkness, 0.0, 1.0)


@dataclass(frozen=True)
class RigEffects:
    """Effects of a real rig and real wood that the rig file does not describe.

    The defaults (all off) render exactly what the rig file says.

    Attributes
    ----------
    roll_deg : float
        Roll of the camera about its optical axis, degrees (within +-10).
    slant_offset_deg : tuple of float
        True slant minus the rig file's slant, lights A and B, degrees (within +-10 each).
    scattering_mm : float
        Subsurface scattering length along the fibres, millimetres (0: none; up to 2). How much
        light scatters is the wood's ``translucency``; across the fibres the length is divided
        by its ``scattering_anisotropy``.
    reflectance_roughness_deg : float
        Oren-Nayar roughness sigma of the wood's reflectance, degrees (0: Lambert; up to 60).
    bow_mm, cup_mm : float
        Sagitta of the board along its length and across its width, millimetres (positive: the
        ends / edges stand higher than the middle).
    board_length_mm, board_width_mm : float
        Board size for bow and cup; board coordinate 0 is the board's trailing end.
    pencil_lines : tuple of PencilLine
        Pencil lines along the feed.
    """

    roll_deg: float = 0.0
    slant_offset_deg: tuple[float, float] = (0.0, 0.0)
    scattering_mm: float = 0.0
    reflectance_roughness_deg: float = 0.0
    bow_mm: float = 0.0
    cup_mm: float = 0.0
    board_length_mm: float = 4000.0
    board_width_mm: float = 150.0
    pencil_lines: tuple[PencilLine, ...] = ()

    def __post_init__(self) -> None:
        check_range("roll_deg", self.roll_deg, -10.0, 10.0)
        offsets = tuple(float(v) for v in self.slant_offset_deg)
        if len(offsets) != 2:
            raise ValueError(f"slant_offset_deg must hold 2 values (A, B), got {offsets!r}")
        for v in offsets:
            check_range("slant_offset_deg", v, -10.0, 10.0)
        object.__setattr__(self, "slant_offset_deg", offsets)
        check_range("scattering_mm", self.scattering_mm, 0.0, 2.0)
        check_range("reflectance_roughness_deg", self.reflectance_roughness_deg, 0.0, 60.0)
        check_range("bow_mm", self.bow_mm, -100.0, 100.0)
        check_range("cup_mm", self.cup_mm, -20.0, 20.0)
        check_range("board_length_mm", self.board_length_mm, 100.0, 100000.0)
        check_range("board_width_mm", self.board_width_mm, 10.0, 2000.0)
        lines = tuple(self.pencil_lines)
        for line in lines:
            if not isinstance(line, PencilLine):
                raise ValueError(f"pencil_lines must hold PencilLine objects, got {line!r}")
        object.__setattr__(self, "pencil_lines", lines)


def effects_from_config(cfg: Any) -> RigEffects:
    """The :class:`RigEffects` of a simulator configuration (``config.sim.SimConfig``).

    ``[camera] roll_deg``, ``slant_offset_a_deg``, ``slant_offset_b_deg`` and ``[board]``
    ``scattering_mm``, ``reflectance_roughness_deg``, ``bow_mm``, ``cup_mm``, ``length_mm``,
    ``width_mm``, ``pencil_lines``.
    """
    cam, board = cfg.camera, cfg.board
    return RigEffects(
        roll_deg=cam.roll_deg,
        slant_offset_deg=tuple(cam.slant_offset_deg),
        scattering_mm=board.scattering_mm,
        reflectance_roughness_deg=board.reflectance_roughness_deg,
        bow_mm=board.bow_mm,
        cup_mm=board.cup_mm,
        board_length_mm=board.length_mm,
        board_width_mm=board.width_mm,
        pencil_lines=tuple(
            PencilLine(y_mm=p.y_mm, width_mm=p.width_mm, darkness=p.darkness)
            for p in board.pencil_lines
        ),
    )


@dataclass(frozen=True)
class Truth:
    """Ground truth of a rendered pair, in image A's frame.

    Attributes
    ----------
    x_mm : ndarray, shape (W,)
        ``u / px_per_mm`` for every undistorted column ``u`` of image A.
    height_um : ndarray, shape (W,)
        True (kinematic) height of the board point seen at that column on the centre row, um
        (board point ``x_mm + board_offset_mm`` along the feed through the optical axis; with
        camera roll, along the feed rather than along the image row); the bow is not in it.
    shift_px : float
        True shift from A to B in undistorted pixels, ``speed * dt_ab * px_per_mm``.
    surface : Surface or None
        The surface rendered, when it carries marks (see :mod:`plant_sim.model.surface`).
    board_offset_mm : float
        Board coordinate minus ``x_mm``: board point ``b`` is at ``x_mm = b - board_offset_mm``.
    slope : ndarray, shape (W,)
        True kinematic slope dz/dx (dimensionless) at those columns (mean over each pixel).
    blur_px : float
        Motion blur length (speed x exposure) in pixels.
    """

    x_mm: np.ndarray
    height_um: np.ndarray
    shift_px: float
    surface: Any = None
    board_offset_mm: float = 0.0
    slope: np.ndarray = field(default_factory=lambda: np.zeros(0))
    blur_px: float = 0.0

    def metrics(self, x_lo_mm: float, x_hi_mm: float) -> dict[str, object]:
        """True cuttermark metrics of the complete marks between two A-frame positions.

        Returns
        -------
        dict
            As :meth:`plant_sim.model.surface.Surface.metrics` (``pitch_mm``, ``uniformity_cv``,
            ``depth_um``, ``mark_widths_mm``, ...) with ``cusps_mm`` in A's frame.

        Raises
        ------
        ValueError
            The pair was rendered from a plain height function (no marks known).
        """
        if self.surface is None or not hasattr(self.surface, "metrics"):
            raise ValueError("surface: the pair was rendered without a Surface; no true marks")
        lo = check_finite("x_lo_mm", x_lo_mm)
        hi = check_finite("x_hi_mm", x_hi_mm)
        out = self.surface.metrics(lo + self.board_offset_mm, hi + self.board_offset_mm)
        out["cusps_mm"] = [c - self.board_offset_mm for c in out["cusps_mm"]]
        return out


@dataclass(frozen=True)
class ImagePair:
    """Two rendered images, the latched encoder counts and the ground truth.

    Attributes
    ----------
    image_a, image_b : ndarray, shape (height, width)
        uint8 / uint16 (float32 when ``Optics.quantize`` is off).
    counts_a, counts_b : int
        Encoder counts latched at triggers A and B (wrapped to the counter width).
    speed_mm_s : float
        Feed speed at capture, mm/s.
    truth : Truth
        Ground truth.
    """

    image_a: np.ndarray
    image_b: np.ndarray
    counts_a: int
    counts_b: int
    speed_mm_s: float
    truth: Truth


def _height_function(source: HeightSource) -> Callable[[np.ndarray], np.ndarray]:
    if hasattr(source, "height_at"):
        return source.height_at
    if callable(source):
        return source
    if hasattr(source, "x_mm") and hasattr(source, "height_um"):
        xs = np.asarray(source.x_mm, dtype=float)
        hs = np.asarray(source.height_um, dtype=float)
        order = np.argsort(xs)
        xs, hs = xs[order], hs[order]

        def interp(b: np.ndarray) -> np.ndarray:
            return np.interp(b, xs, hs)

        return interp
    raise ValueError(
        "height must be a callable height_um(b_mm) or a Surface-like object with x_mm, height_um"
    )


def pixel_map(cam: Any, w: int, h: int, *, px_per_mm: float, px_per_mm_y: float,
              roll_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The board-frame position every distorted pixel shows, through the lens model.

    Returns
    -------
    K : ndarray, shape (3, 3)
        The camera matrix.
    dist : ndarray
        The distortion coefficients.
    x_phys_mm, y_phys_mm : ndarray, shape (h, w)
        Along and across the feed, mm, from the optical centre (the camera rolled by
        ``roll_deg``).

    Raises
    ------
    ValueError
        The lens model cannot be inverted over the image (it folds over).
    """
    ppm = px_per_mm
    K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
    dist = np.asarray(cam.dist, dtype=float)
    # undistorted position of every distorted pixel
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([cols.ravel(), rows.ravel()], axis=1).reshape(-1, 1, 2)
    if np.any(dist != 0):
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
        und = cv2.undistortPoints(pts, K, dist, None, K, criteria=crit)
        # check the inversion: projecting back must land on the pixel
        obj = np.empty((und.shape[0], 1, 3))
        obj[:, 0, 0] = (und[:, 0, 0] - cam.cx) / cam.fx
        obj[:, 0, 1] = (und[:, 0, 1] - cam.cy) / cam.fy
        obj[:, 0, 2] = 1.0
        back, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, dist)
        err = float(np.max(np.abs(back - pts)))
        if not err < 1e-3:
            raise ValueError(
                f"dist {tuple(cam.dist)} cannot be inverted over a {w}x{h} image (the lens "
                f"model folds over; round-trip error {err:.3g} px)"
            )
        und = und.reshape(h, w, 2)
    else:
        und = pts.reshape(h, w, 2)
    xc = (und[..., 0] - cam.cx) / ppm
    yc = (und[..., 1] - cam.cy) / px_per_mm_y
    roll = math.radians(roll_deg)
    cr, sr = math.cos(roll), math.sin(roll)
    # board-frame position shown by each pixel (the camera rolled by `roll`)
    x_phys_mm = (xc * cr + yc * sr).astype(np.float64)
    y_phys_mm = (yc * cr - xc * sr).astype(np.float64)
    del xc, yc
    return K, dist, x_phys_mm, y_phys_mm



class Renderer:
    """Renders image pairs of a board for one rig, optics and wood; set up once.

    Parameters
    ----------
    rig : config.rig.Rig
        Camera (K, distortion, ``px_per_mm``, exposure), lights (slant, azimuths), encoder.
    optics : Optics
        Sensor, LEDs, timing and encoder resolution.
    wood : config.wood.Wood
        Species appearance (the board's texture is drawn from ``seed``).
    seed : int
        Seed of the board texture and of the default noise stream.
    effects : RigEffects, optional
        Roll, true light slants, scattering, reflectance, bow, cup, pencil lines (default: none).

    Raises
    ------
    ValueError
        The rig's ``px_per_count`` does not match ``px_per_mm / counts_per_mm``.
    """

    def __init__(
        self, rig: Rig, optics: Optics, wood: Wood, *, seed: int,
        effects: RigEffects | None = None,
    ) -> None:
        self.rig = rig
        self.optics = optics
        self.wood = wood
        self.seed = check_int("seed", seed, lo=0)
        if effects is None:
            effects = RigEffects()
        elif not isinstance(effects, RigEffects):
            raise ValueError(f"effects must be a RigEffects, got {type(effects).__name__}")
        self.effects = fx = effects
        cam = rig.camera
        ppm = float(cam.px_per_mm)
        expect = ppm / optics.counts_per_mm
        if not math.isclose(rig.encoder.px_per_count, expect, rel_tol=1e-6):
            raise ValueError(
                f"px_per_count of the rig ({rig.encoder.px_per_count}) must equal px_per_mm / "
                f"counts_per_mm = {expect}"
            )
        self.px_per_mm = ppm
        self.px_per_mm_y = ppm * cam.fy / cam.fx
        self.px_per_count = float(rig.encoder.px_per_count)
        exp = optics.exposure_ms if optics.exposure_ms is not None else (cam.exposure_ms or 0.0)
        self.exposure_s = float(exp) * 1e-3
        w, h = optics.width, optics.height
        self.K, self.dist, self.x_phys_mm, self.y_phys_mm = pixel_map(
            cam, w, h, px_per_mm=self.px_per_mm, px_per_mm_y=self.px_per_mm_y,
            roll_deg=fx.roll_deg)
        self._x_lo = float(self.x_phys_mm.min())
        self._x_hi = float(self.x_phys_mm.max())
        self.field_width_mm = self._x_hi - self._x_lo
        n_rows, span_cols = self._board_grid(cam, optics)
        tiles = texture_tiles(
            wood, rows=n_rows, cols=self._period, dx_mm=self.dx_mm, dy_mm=self.dy_mm,
            seed=self.seed
        )
        self._set_lights(rig, fx)
        self._set_reflectance(tiles, fx, wood, n_rows=n_rows, span_cols=span_cols)
        self._set_gains(optics, wood)
        self._noise_rng = np.random.default_rng([self.seed, 0x5EED])
        self._undistorted_cols = np.arange(w, dtype=np.float64)

    def _board_grid(self, cam: Any, optics: Optics) -> tuple[int, int]:
        """The fine board grid the texture is sampled on; its rows and its span in columns."""
        ppm = self.px_per_mm
        x_lo, x_hi = self._x_lo, self._x_hi
        y_lo, y_hi = float(self.y_phys_mm.min()), float(self.y_phys_mm.max())
        # board grid
        self.dx_mm = 1.0 / (ppm * optics.oversample)
        self.dy_mm = 1.0 / self.px_per_mm_y
        cy_mm = cam.cy / self.px_per_mm_y
        # first grid row, on an undistorted pixel row
        self._y0 = (math.floor((y_lo + cy_mm) / self.dy_mm) - 2) * self.dy_mm - cy_mm
        n_rows = int(math.ceil((y_hi - y_lo) / self.dy_mm)) + 5
        self._map_y = ((self.y_phys_mm - self._y0) / self.dy_mm).astype(np.float32)
        self._cx_mm = cam.cx / ppm
        self._pixel_kernel = _pixel_kernel(optics.oversample)
        # grid column (relative to undistorted column 0) shown by each distorted pixel
        self._col_index = ((self.x_phys_mm + self._cx_mm) / self.dx_mm).astype(np.float32)
        span_cols = int(math.ceil((x_hi - x_lo) / self.dx_mm)) + 8
        period = max(2048, sfft.next_fast_len(span_cols + 64, real=True))
        self._period = period
        return n_rows, span_cols

    def _set_lights(self, rig: Rig, fx: RigEffects) -> None:
        """Each light's azimuth and true slant (the rig file's plus the effect's offset)."""
        # lights: the true slant of each (the rig file's plus the effect's offset)
        lit = rig.lights
        self._tau = (math.radians(lit.azimuth_a_deg), math.radians(lit.azimuth_b_deg))
        nominal = getattr(lit, "slants_deg", (lit.slant_deg, lit.slant_deg))
        self.true_slant_deg = tuple(
            float(n) + d for n, d in zip(nominal, fx.slant_offset_deg, strict=True)
        )
        for sl in self.true_slant_deg:
            if not 0.0 < sl < 90.0:
                raise ValueError(f"slant_offset_deg gives a true slant of {sl} deg (0..90)")
        self._tan_elevation = tuple(1.0 / math.tan(math.radians(sl))
                                    for sl in self.true_slant_deg)
        sig = math.radians(fx.reflectance_roughness_deg)
        self._on_a = 1.0 - 0.5 * sig * sig / (sig * sig + 0.33)
        self._on_b = 0.45 * sig * sig / (sig * sig + 0.09)
        self._light = tuple(
            (math.sin(math.radians(sl)), math.cos(math.radians(sl)), math.cos(t), math.sin(t))
            for sl, t in zip(self.true_slant_deg, self._tau, strict=True)
        )

    def _set_reflectance(self, tiles: Any, fx: RigEffects, wood: Wood, *, n_rows: int,
                         span_cols: int) -> None:
        """Bow, scattering and the roughness tiles of each light (scattered once, here)."""
        # bow: slope 8 bow (b - L/2) / L^2 added to the profile's
        self._bow_per_mm = 8.0 * fx.bow_mm / fx.board_length_mm**2
        self._bow_mid_mm = 0.5 * fx.board_length_mm
        # subsurface scattering: the fraction `a` leaves through an exponential kernel
        self._scatter_a = float(wood.translucency) if fx.scattering_mm > 0 else 0.0
        if self._scatter_a > 0:
            self._scatter_kernel = _exp_kernel(fx.scattering_mm / self.dx_mm)
        else:
            self._scatter_kernel = np.ones(1)
        # Shading (seed Eq. 1, or Oren-Nayar) with p = p_profile + p_rough, q = q_rough + q_cup:
        #   rho * shade = rho * g(p_profile) - R * c(p_profile),
        #   g = the profile's exact shading (per grid column, per frame),
        #   R = rho * (p_rough cos(tau) + q sin(tau)), c = A sin(s) / sqrt(1 + p^2 + <rough^2>);
        # the roughness enters linearly and the normalisation by its mean square (the cross term
        # is below 1e-5 relative). R is scattered once here; g per frame along x.
        pad = span_cols + 512
        self._pad = pad
        rho = tiles.albedo
        y_rows = self._y0 + np.arange(n_rows) * self.dy_mm
        if fx.pencil_lines:
            rho = rho * _pencil_factor(y_rows, fx.pencil_lines)[:, None]
        q_cup = (8.0 * fx.cup_mm / fx.board_width_mm**2 * y_rows).astype(np.float32)
        self._tile_r = []
        for tau in self._tau:
            rough = np.float32(math.cos(tau)) * tiles.slope_x
            if math.sin(tau) != 0.0:
                rough += np.float32(math.sin(tau)) * (tiles.slope_y + q_cup[:, None])
            if self._scatter_a > 0:
                rough = self._scatter_tile(rough, fx.scattering_mm, wood.scattering_anisotropy)
            r = rho * rough
            self._tile_r.append(np.ascontiguousarray(np.concatenate([r, r[:, :pad]], axis=1)))
        self._tile_rho = np.ascontiguousarray(np.concatenate([rho, rho[:, :pad]], axis=1))
        self._rough_ms = float(np.mean(tiles.slope_x**2) + np.mean(tiles.slope_y**2))
        del tiles, rho, rough, r

    def _set_gains(self, optics: Optics, wood: Wood) -> None:
        """Each LED's gain map over the field (level, fall-off, imbalance)."""
        gains = []
        for i, tau in enumerate(self._tau):
            # each LED's power gives `level` on a flat board of mean albedo
            flat = self._on_a * self._light[i][1]
            scale = optics.level * optics.max_dn / (wood.albedo * flat) * optics.gain
            proj = self.x_phys_mm * math.cos(tau) + self.y_phys_mm * math.sin(tau)
            g = scale * (1.0 + optics.falloff * proj / self.field_width_mm)
            if i == 1:
                g = g * (1.0 + optics.led_imbalance)
            gains.append(g.astype(np.float32))
        self._gain_maps = tuple(gains)
        self._dn_per_e = optics.gain * optics.max_dn / optics.full_well_e

    # -- rendering -------------------------------------------------------------------------

    def _tile_window(self, tile: np.ndarray, c0: int, n: int, frac: float) -> np.ndarray:
        """Columns ``c0 + frac .. c0 + frac + n - 1`` of a padded periodic tile (linear in x).

        Shape ``(rows, n)``, float32; when ``frac`` is 0 a view into the tile (never write to it).
        """
        c0 %= self._period
        if c0 + n + 1 <= tile.shape[1]:
            win = tile[:, c0 : c0 + n + 1]
        else:  # a window longer than the padding (extreme motion blur)
            win = tile[:, (c0 + np.arange(n + 1)) % self._period]
        if frac < 1e-9:
            return win[:, :n]  # a view: the caller must not write into it
        # (1 - f) w[j] + f w[j + 1] in one pass (equal to w[j] + f (w[j + 1] - w[j]) within
        # float32 rounding; tests/plant_sim/test_sim_speed_optics.py)
        return cv2.addWeighted(win[:, :n], 1.0 - frac, win[:, 1:], frac, 0.0)

    def _scatter_tile(self, field_: np.ndarray, length_mm: float, anisotropy: float) -> np.ndarray:
        """``(1 - a) f + a K * f`` of a tile (periodic along x), K the scattering kernel."""
        a = np.float32(self._scatter_a)
        rows, cols = field_.shape
        kx = 2 * np.pi * sfft.rfftfreq(cols, self.dx_mm)
        ky = 2 * np.pi * sfft.fftfreq(rows, self.dy_mm)
        ly = length_mm / anisotropy
        h = 1.0 / ((1.0 + (kx[None, :] * length_mm) ** 2) * (1.0 + (ky[:, None] * ly) ** 2))
        spec = sfft.rfft2(field_, workers=1)
        spec *= ((1.0 - a) + a * h).astype(np.complex64)
        return sfft.irfft2(spec, s=field_.shape, workers=1).astype(np.float32, copy=False)

    def _shade(self, p: np.ndarray, which: int,
               q: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Profile shading ``g`` and roughness coefficient ``c`` per grid column (float64).

        ``q`` (a defect's slope across the feed, same shape as ``p``): the normal's tilt across
        enters the incidence and the normalisation; the Oren-Nayar term keeps its projection
        along the feed.
        """
        sin_s, cos_s, cos_t, sin_t = self._light[which]
        if q is None:
            pq2 = p * p
            lit = cos_s - p * (cos_t * sin_s)
        else:
            pq2 = p * p + q * q
            lit = cos_s - p * (cos_t * sin_s) - q * (sin_t * sin_s)
        norm = 1.0 / np.sqrt(1.0 + pq2 + self._rough_ms)
        cos_i = lit * norm
        g = self._on_a * cos_i
        if self._on_b > 0:
            inv = 1.0 / np.sqrt(1.0 + pq2)
            cos_i0 = lit * inv
            # light and view projected on the tangent plane (normal (-p, 0, 1) inv, view +z)
            lx = sin_s * cos_t + cos_i0 * inv * p
            ly = sin_s * sin_t
            lz = cos_s - cos_i0 * inv
            vx, vz = p * inv * inv, 1.0 - inv * inv
            num = lx * vx + lz * vz
            den = np.sqrt(lx * lx + ly * ly + lz * lz) * np.sqrt(vx * vx + vz * vz)
            cos_dphi = np.divide(num, den, out=np.zeros_like(num), where=den > 1e-15)
            th_i = np.arccos(np.clip(cos_i0, -1.0, 1.0))
            th_r = np.arctan(np.abs(p))
            back = np.sin(np.maximum(th_i, th_r)) * np.tan(np.minimum(th_i, th_r))
            g = g + self._on_b * np.maximum(cos_i, 0.0) * back * np.maximum(cos_dphi, 0.0)
        return g, (self._on_a * sin_s) * norm

    def _grid_extent(self, speed_mm_s: float) -> tuple[float, int, int, int]:
        """Blur length (grid columns), blur half-width, first grid column and column count."""
        dx = self.dx_mm
        blur_cols = abs(speed_mm_s) * self.exposure_s / dx
        half = int(math.ceil(0.5 * blur_cols)) + 1 if blur_cols > 1e-3 else 0
        half += self._pixel_kernel.size // 2
        k = int(math.floor((self._x_lo + self._cx_mm) / dx)) - 2 - half
        n = int(math.ceil((self._x_hi - self._x_lo) / dx)) + 5 + 2 * half
        return blur_cols, half, k, n

    def board_range_mm(
        self, *, board_x_at_centre_mm: float, speed_mm_s: float
    ) -> tuple[float, float]:
        """Board coordinates at which :meth:`render_pair` evaluates the height function.

        A surface passed to :meth:`render_pair` with the same arguments must cover this range
        (e.g. passes from :func:`plant_sim.model.surface.passes_steady` over it).

        Returns
        -------
        (lo_mm, hi_mm) : tuple of float
        """
        bc = check_finite("board_x_at_centre_mm", board_x_at_centre_mm)
        v = check_finite("speed_mm_s", speed_mm_s)
        _, _, k, n = self._grid_extent(v)
        dx = self.dx_mm
        shift = v * self.optics.dt_ab_s
        m = self._scatter_kernel.size // 2
        lo_grid = (k - m - 0.5) * dx - self._cx_mm
        hi_grid = (k + n + m - 0.5) * dx - self._cx_mm
        lo_truth = -self._cx_mm - 0.5 / self.px_per_mm
        hi_truth = (self.optics.width - 0.5) / self.px_per_mm - self._cx_mm
        lo = bc + min(lo_grid, lo_truth) + min(0.0, -shift)
        hi = bc + max(hi_grid, hi_truth) + max(0.0, -shift)
        return lo - 1e-9, hi + 1e-9

    def _radiance_grid(
        self, height: Callable[[np.ndarray], np.ndarray], b_at_axis_mm: float,
        speed_mm_s: float, which: int, defects: DefectLayer | None = None,
    ) -> tuple[np.ndarray, int]:
        """Blurred radiance on a board grid whose nodes fall on undistorted pixel columns.

        Node ``i`` is at board coordinate ``b_u0 + (k + i) dx`` with ``b_u0`` the board point at
        undistorted column 0; returns the grid (rows, n), float32, and ``k``.
        """
        dx = self.dx_mm
        blur_cols, half, k, n = self._grid_extent(speed_mm_s)
        b_u0 = b_at_axis_mm - self._cx_mm
        t0 = b_u0 / dx + k  # tile column of node 0
        c0 = math.floor(t0)
        frac = t0 - c0
        m = self._scatter_kernel.size // 2
        edges = b_u0 + (k - m + np.arange(n + 2 * m + 1) - 0.5) * dx
        z = np.asarray(height(edges), dtype=np.float64)
        if z.shape != edges.shape or not np.all(np.isfinite(z)):
            raise ValueError("height returned non-finite values or a wrong shape")
        if defects is not None and defects.profiles:
            z = z + defects.profile_um(edges)  # chatter, snipe: along the feed
        p_prof = np.diff(z) * (1e-3 / dx)  # mean slope over each grid cell
        if self._bow_per_mm != 0.0:
            p_prof += self._bow_per_mm * (edges[:-1] + 0.5 * dx - self._bow_mid_mm)
        g, c = self._shade(p_prof, which)
        if m:
            a = self._scatter_a
            g = (1.0 - a) * g[m:-m] + a * np.convolve(g, self._scatter_kernel, mode="valid")
            c = c[m:-m]
        rho_w = self._tile_window(self._tile_rho, c0, n, frac)
        r_w = self._tile_window(self._tile_r[which], c0, n, frac)
        rad = np.multiply(rho_w, g.astype(np.float32)[None, :])
        rad -= np.multiply(r_w, c.astype(np.float32)[None, :])
        if defects is not None and defects.local:
            grid = BoardGrid(edges=edges, z=z, p=p_prof, k=k, n=n, m=m, b_u0=b_u0)
            for box, covered in defects.patches(self._tan_elevation[which]):
                shade_patch(self, rad, rho_w, r_w, covered, grid, box, which)
        cv2.max(rad, 0.0, dst=rad)  # np.maximum's NaN handling costs 3x; rad has no NaN
        kernel = self._pixel_kernel
        if blur_cols > 1e-3:
            kernel = np.convolve(kernel, _box_kernel(blur_cols)).astype(np.float32)
        if kernel.size > 1:
            rad = cv2.filter2D(rad, -1, kernel[None, :], borderType=cv2.BORDER_REPLICATE)
        return rad, k

    def _render_one(
        self, height: Callable[[np.ndarray], np.ndarray], b_at_axis_mm: float,
        speed_mm_s: float, which: int, rng: np.random.Generator,
        albedo_factor: AlbedoFactor | None = None, defects: DefectLayer | None = None,
    ) -> np.ndarray:
        rad, k = self._radiance_grid(height, b_at_axis_mm, speed_mm_s, which, defects)
        map_x = self._col_index - np.float32(k)
        img = cv2.remap(rad, map_x, self._map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        img *= self._gain_maps[which]
        if albedo_factor is not None:
            f = albedo_factor(self.x_phys_mm + b_at_axis_mm, self.y_phys_mm)
            f = np.asarray(f, dtype=np.float32)
            if f.shape != img.shape or not np.all(np.isfinite(f)) or np.any(f < 0):
                raise ValueError("albedo_factor must return finite factors >= 0, one per pixel")
            img *= f
        o = self.optics
        if o.shot_noise or o.read_noise_dn > 0:
            noise = standard_normal_f32(rng, img.shape)
            if o.shot_noise:
                var = cv2.max(img, 0.0)
                var *= np.float32(self._dn_per_e)
                var += np.float32(o.read_noise_dn**2)
                noise *= cv2.sqrt(var, dst=var)
            else:
                noise *= np.float32(o.read_noise_dn)
            img += noise
        if not o.quantize:
            return img
        img += 0.5
        np.clip(img, 0.0, o.max_dn, out=img)
        return img.astype(o.dtype)

    def render_pair(
        self,
        height: HeightSource,
        *,
        board_x_at_centre_mm: float,
        speed_mm_s: float,
        counts_a: int = 0,
        encoder_error_px: float = 0.0,
        counter_bits: int | None = None,
        rng_seed: int | None = None,
        albedo_factor: AlbedoFactor | None = None,
        defects: DefectLayer | None = None,
    ) -> ImagePair:
        """Render the images A and B of a moving board and the encoder counts at both triggers.

        Parameters
        ----------
        height : callable or Surface-like
            ``height_um(b_mm)`` of the board (vectorised), or an object with ``height_at`` (a
            :class:`plant_sim.model.surface.Surface`, evaluated exactly), or one with arrays
            ``x_mm``
            and ``height_um`` (linearly interpolated).
        board_x_at_centre_mm : float
            Board coordinate on the optical axis at trigger A, millimetres.
        speed_mm_s : float
            Feed speed (toward +x), mm/s; sets the shift A to B and the motion blur.
        counts_a : int
            Encoder count latched at trigger A (wrapped to ``counter_bits``).
        encoder_error_px : float
            Error of the counted shift (slip, bad count), pixels; ``counts_b`` is off by
            ``round(encoder_error_px / px_per_count)`` counts.
        counter_bits : int, optional
            Encoder counter width, 16 or 32; ``None`` takes the rig's ``encoder.counter_bits``.
        rng_seed : int, optional
            Seed of the sensor noise; ``None`` draws from the renderer's own stream.
        albedo_factor : callable, optional
            ``factor(board_x_mm, board_y_mm)`` (arrays of the image's shape) multiplying the
            reflected light per pixel before the sensor noise: knots, stains.
        defects : DefectLayer, optional
            Wood defects over the pair's board range (:mod:`plant_sim.rendering.defects`):
            their heights are added to the profile and shaded (``None`` or empty: the same
            images, at the same cost, as without).

        Returns
        -------
        ImagePair
            Images ``(optics.height, optics.width)``, counts, speed and the ground truth.
        """
        bc = check_finite("board_x_at_centre_mm", board_x_at_centre_mm)
        v = check_finite("speed_mm_s", speed_mm_s)
        ca = check_int("counts_a", counts_a)
        err = check_finite("encoder_error_px", encoder_error_px)
        if counter_bits is None:
            counter_bits = self.rig.encoder.counter_bits
        bits = check_int("counter_bits", counter_bits)
        if bits not in (16, 32):
            raise ValueError(f"counter_bits must be 16 or 32, got {bits}")
        fn = _height_function(height)
        rng = self._noise_rng if rng_seed is None else np.random.default_rng(rng_seed)
        o = self.optics
        shift_mm = v * o.dt_ab_s
        # at trigger A board point b is at X = b - bc; at B at X + shift -> b = X + bc - shift
        if defects is not None and not defects:
            defects = None
        img_a = self._render_one(fn, bc, v, 0, rng, albedo_factor, defects)
        img_b = self._render_one(fn, bc - shift_mm, v, 1, rng, albedo_factor, defects)
        ppm = self.px_per_mm
        cam = self.rig.camera
        counts_a_w = wrap_counter(ca, bits=bits)
        counts_b = (
            ca + int(round(shift_mm * o.counts_per_mm)) + int(round(err / self.px_per_count))
        )
        u = self._undistorted_cols
        offset = bc - cam.cx / ppm
        x_mm = u / ppm
        b = x_mm + offset
        h_true = np.asarray(fn(b), dtype=float)
        half = 0.5 / ppm
        slope = (np.asarray(fn(b + half), dtype=float) - np.asarray(fn(b - half), dtype=float)) * (
            1e-3 * ppm
        )
        truth = Truth(
            x_mm=x_mm,
            height_um=h_true,
            shift_px=shift_mm * ppm,
            surface=height if hasattr(height, "metrics") else None,
            board_offset_mm=offset,
            slope=slope,
            blur_px=abs(v) * self.exposure_s * ppm,
        )
        return ImagePair(
            image_a=img_a,
            image_b=img_b,
            counts_a=counts_a_w,
            counts_b=wrap_counter(counts_b, bits=bits),
            speed_mm_s=v,
            truth=truth,
        )


    def height_map(self, height: HeightSource, *, board_x_at_centre_mm: float,
                   defects: DefectLayer | None = None) -> np.ndarray:
        """The height image A shows at each pixel: the profile plus the defects, um.

        Parameters
        ----------
        height : callable or Surface-like
            As :meth:`render_pair`'s.
        board_x_at_centre_mm : float
            Board coordinate on the optical axis at trigger A, mm.
        defects : DefectLayer, optional
            As :meth:`render_pair`'s.

        Returns
        -------
        ndarray, shape (height, width)
            Height of the board point each (distorted) pixel of image A shows, um; the bow is
            not in it.
        """
        bc = check_finite("board_x_at_centre_mm", board_x_at_centre_mm)
        bx = self.x_phys_mm + bc
        out = np.asarray(_height_function(height)(bx.ravel()), dtype=float).reshape(bx.shape)
        if defects is not None and defects:
            out = out + defects.height_um(bx, self.y_phys_mm)
        return out

def standard_normal_f32(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Independent standard normal samples, float32, drawn for one image from ``rng``'s stream.

    One integer drawn from ``rng`` seeds OpenCV's generator (thread-local), which fills the
    array: the same distribution as ``rng.standard_normal(shape, dtype=np.float32)`` (i.i.d.
    N(0, 1); tests/plant_sim/test_sim_speed_optics.py checks it) and deterministic for ``rng``'s
    state,
    at a fifth of the cost (the ziggurat of numpy's generator took 60 % of a rendered pair).

    Parameters
    ----------
    rng : numpy.random.Generator
        The noise stream (advanced by one draw).
    shape : tuple of int
        Shape of the result.

    Returns
    -------
    ndarray, float32, shape ``shape``
    """
    out = np.empty(shape, dtype=np.float32)
    cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
    cv2.randn(out, 0.0, 1.0)
    return out


def _exp_kernel(length_cols: float) -> np.ndarray:
    """Taps of the two-sided exponential ``exp(-|j| / length)`` over +-5 lengths, sum one.

    Shape (2J + 1,), float64.
    """
    j_max = max(1, int(math.ceil(5.0 * length_cols)))
    j = np.arange(-j_max, j_max + 1, dtype=np.float64)
    w = np.exp(-np.abs(j) / length_cols)
    return w / w.sum()


def _pencil_factor(y_mm: np.ndarray, lines: tuple[PencilLine, ...]) -> np.ndarray:
    """Albedo factor per board row: ``prod(1 - darkness * raised cosine)``; float32."""
    f = np.ones(y_mm.shape, dtype=np.float64)
    for line in lines:
        r = np.abs(y_mm - line.y_mm) / (0.5 * line.width_mm)
        w = np.where(r < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.minimum(r, 1.0))), 0.0)
        f *= 1.0 - line.darkness * w
    return f.astype(np.float32)


def _pixel_kernel(m: int) -> np.ndarray:
    """Weights averaging the ``m`` (odd) grid cells of width 1/m px that make up one pixel.

    Shape (m,), float32, all ``1/m``; ``[1]`` for ``m = 1``.
    """
    return np.full(m, 1.0 / m, dtype=np.float32)


def _box_kernel(width_cols: float) -> np.ndarray:
    """Taps of the motion-blur box filter on the board grid.

    ``sum_j w_j f[i + j]`` is the mean of the linear interpolant of ``f`` over
    ``[i - width/2, i + width/2]``; shape (2J + 1,), float32, sums to one.
    """
    half = 0.5 * width_cols
    j_max = int(math.ceil(half)) + 1
    j = np.arange(-j_max, j_max + 1, dtype=np.float64)

    def hat_integral(x: np.ndarray) -> np.ndarray:
        # integral of the unit hat function (support [-1, 1]) from -inf to x
        x = np.clip(x, -1.0, 1.0)
        return np.where(x <= 0.0, 0.5 * (x + 1.0) ** 2, 1.0 - 0.5 * (1.0 - x) ** 2)

    w = (hat_integral(half - j) - hat_integral(-half - j)) / width_cols
    return (w / w.sum()).astype(np.float32)
