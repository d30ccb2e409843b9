"""One-call simulated boards for the vision tests: a rig and a rendered image pair with truth.

:func:`board_pair` plans a board with a cutterhead at constant speed (:func:`passes_steady`),
takes the exact lower envelope of the knife circles (:func:`envelope`) and renders the two
grazing-light images (:class:`plant_sim.rendering.optics.Renderer`). :func:`random_board_pair`
draws every
parameter from the ranges of the vision's acceptance criteria, for held-out testing.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from config import wood as wood_presets
from config.rig import Camera, Encoder, Lights, Rig
from config.wood import SPECIES, Wood
from core.checks import check_finite, check_int, check_positive, check_range
from plant_sim.model.surface import Cutterhead, Surface, envelope, passes_steady
from plant_sim.rendering.camera import Knot
from plant_sim.rendering.optics import ImagePair, Optics, PencilLine, Renderer, RigEffects

__all__ = [
    "DEFAULT_RUNOUT_UM",
    "board_pair",
    "board_surface",
    "make_rig",
    "random_board_pair",
    "random_board_params",
    "renderer",
]

DEFAULT_RUNOUT_UM = (0.0, 2.0, 0.5, 1.5, 1.0, 2.5)
"""Runout of knives 0..5 used when ``runout_um`` is not given (micrometres)."""

PX_PER_MM = 12.5
COUNTS_PER_MM = 20.0


def make_rig(
    *,
    width: int = 659,
    height: int = 493,
    k1: float = 0.0,
    exposure_ms: float | None = 0.05,
    counter_bits: int = 32,
    px_per_mm: float = PX_PER_MM,
    counts_per_mm: float = COUNTS_PER_MM,
    slant_deg: float = 82.0,
    fx: float = 1400.0,
) -> Rig:
    """A consistent simulated rig: K centred, ``dist = (k1, 0, 0, 0, 0)``, encoder to match."""
    cam = Camera(
        fx=fx,
        fy=fx,
        cx=(width - 1) / 2.0,
        cy=(height - 1) / 2.0,
        dist=(float(k1), 0.0, 0.0, 0.0, 0.0),
        px_per_mm=px_per_mm,
        exposure_ms=exposure_ms,
    )
    return Rig(
        camera=cam,
        lights=Lights(slant_deg=slant_deg, azimuth_a_deg=0.0, azimuth_b_deg=180.0),
        encoder=Encoder(px_per_count=px_per_mm / counts_per_mm, counter_bits=counter_bits),
    )


@lru_cache(maxsize=4)
def renderer(
    rig: Rig, optics: Optics, wood: Wood, seed: int, effects: RigEffects | None = None
) -> Renderer:
    """A cached :class:`Renderer` (building one draws the wood texture; about 0.1-0.5 s)."""
    return Renderer(rig, optics, wood, seed=seed, effects=effects)


def board_surface(
    head: Cutterhead,
    *,
    spindle_rpm: float,
    feed_mm_s: float,
    x_start_mm: float,
    x_end_mm: float,
    phase_mm: float = 0.0,
    offsets_um: Sequence[float] | None = None,
    step_mm: float = 0.02,
) -> Surface:
    """The planed surface over ``[x_start_mm, x_end_mm]``, sampled every ``step_mm``."""
    passes = passes_steady(
        head,
        spindle_rpm=spindle_rpm,
        feed_mm_s=feed_mm_s,
        x_start_mm=x_start_mm,
        x_end_mm=x_end_mm,
        offsets_um=offsets_um,
        phase_mm=phase_mm,
    )
    n = int(math.ceil((x_end_mm - x_start_mm) / step_mm)) + 1
    return envelope(np.linspace(x_start_mm, x_end_mm, n), passes)


@dataclass(frozen=True)
class BoardScene:
    """What :func:`board_pair` renders: the board, the cutterhead, the rig and its effects.

    Attributes
    ----------
    seed : int
        Seeds the wood texture, the knife phase, the board position, ``counts_a`` (when not
        given) and the sensor noise. Same arguments, same pair.
    species : str
        Wood preset name (see :data:`config.wood.SPECIES`).
    pitch_mm : float
        Feed per knife, millimetres (the ideal mark width).
    knives : int
        Knife count Z.
    runout_um : sequence of float, optional
        Runout per knife, um; ``None`` takes the first ``knives`` of :data:`DEFAULT_RUNOUT_UM`.
    radius_mm : float
        Tip radius, millimetres.
    spindle_rpm : float
        Spindle speed; when ``speed_mm_s`` is given too, the spindle speed follows from the pitch.
    speed_mm_s : float, optional
        Feed speed; ``None`` gives ``pitch_mm * spindle_rpm / 60 * knives``.
    imbalance, falloff : float
        LED B/A brightness ratio minus one; fractional change of each LED across the field.
    k1 : float
        Radial distortion coefficient, ``dist = (k1, 0, 0, 0, 0)``.
    encoder_error_px : float
        Error of the counted shift, pixels.
    exposure_ms : float or None
        Exposure time (also written into the rig).
    width, height : int
        Image size.
    noise : bool
        Sensor noise (read and shot) on or off.
    dt_ab_s : float
        Time between triggers A and B.
    counter_bits : int
        Encoder counter width (16 or 32).
    counts_a : int, optional
        Count latched at trigger A; random when ``None``.
    offsets_um, eccentricity_um, slant_deg, gain, quantize, board_x_at_centre_mm
        Further options: piezo offsets per knife, cutterhead eccentricity, light slant, sensor
        gain, integer images, board position on the axis at trigger A (random when ``None``).
    flat : bool
        Render a flat board (height 0 everywhere, same wood, LEDs and camera): the flat-field
        reference of the vision's illumination correction. Its truth has no surface.
    roll_deg, slant_offset_deg, scattering_mm, reflectance_roughness_deg, bow_mm, cup_mm,
    pencil_lines, board_length_mm
        Effects of a real rig and real wood (:class:`plant_sim.rendering.optics.RigEffects`):
        camera roll,
        true slant minus the rig file's per light (the rig keeps ``slant_deg``), scattering
        length along the fibres (the species' ``translucency`` sets how much), Oren-Nayar
        roughness, bow and cup sagitta, pencil lines along the feed. All off by default.
    read_noise_dn : float, optional
        Sensor read noise, DN rms; ``None`` gives 0.5 with ``noise`` and 0 without (shot noise
        follows ``noise``).
    knots : sequence of plant_sim.rendering.camera.Knot
        Knots (dark rough patches; ``x_mm`` in board coordinates, so give
        ``board_x_at_centre_mm`` to place them in view): their roughness is in the height (and
        the truth profile), their darkness in the images, not in the true marks.
    pore_density_per_mm2 : float, optional
        Pores per mm^2, replacing the species' (``None``: the species' own); a species without
        pores gets them with a contrast of 0.3.

    """

    seed: int = 0
    species: str = "beech"
    pitch_mm: float = 1.5
    knives: int = 4
    runout_um: Sequence[float] | None = None
    radius_mm: float = 60.0
    spindle_rpm: float = 6000.0
    speed_mm_s: float | None = None
    imbalance: float = 0.0
    falloff: float = 0.0
    k1: float = 0.0
    encoder_error_px: float = 0.0
    exposure_ms: float | None = 0.05
    width: int = 659
    height: int = 493
    noise: bool = True
    dt_ab_s: float = 0.002
    counter_bits: int = 32
    counts_a: int | None = None
    offsets_um: Sequence[float] | None = None
    eccentricity_um: float = 0.0
    slant_deg: float = 82.0
    gain: float = 1.0
    quantize: bool = True
    board_x_at_centre_mm: float | None = None
    flat: bool = False
    roll_deg: float = 0.0
    slant_offset_deg: tuple[float, float] = (0.0, 0.0)
    scattering_mm: float = 0.0
    reflectance_roughness_deg: float = 0.0
    bow_mm: float = 0.0
    cup_mm: float = 0.0
    pencil_lines: Sequence[PencilLine] = ()
    read_noise_dn: float | None = None
    board_length_mm: float = 4000.0
    knots: Sequence[Knot] = ()
    pore_density_per_mm2: float | None = None


def board_pair(scene: BoardScene | None = None, /, **changes: Any) -> tuple[Rig, ImagePair]:
    """A simulated rig and one rendered image pair of a freshly planed board.

    Parameters
    ----------
    scene : BoardScene, optional
        What to render (default: :class:`BoardScene`'s defaults).
    **changes
        Fields of the scene to change (``board_pair(roll_deg=3.0, knives=8)``).

    Returns
    -------
    rig : config.rig.Rig
        ``px_per_mm = 12.5``, K centred with ``fx = fy = 1400``, 20 counts per mm.
    pair : plant_sim.rendering.optics.ImagePair
        Images, counts and truth (``pair.truth.metrics(x_lo, x_hi)`` gives the true marks).

    Raises
    ------
    ValueError
        A field that :class:`BoardScene` does not have, or a value out of its range (naming it).
    """
    unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(BoardScene)})
    if unknown:
        raise ValueError(f"board_pair has no option {', '.join(unknown)}")
    sc = dataclasses.replace(scene if scene is not None else BoardScene(), **changes)
    return _render_scene(sc)


def _render_scene(sc: BoardScene) -> tuple[Rig, ImagePair]:
    """Render one scene (checked here, field by field)."""
    check_int("seed", sc.seed, lo=0)
    pitch = check_positive("pitch_mm", sc.pitch_mm)
    z = check_int("knives", sc.knives, lo=1, hi=64)
    rpm = check_positive("spindle_rpm", sc.spindle_rpm)
    if sc.speed_mm_s is None:
        speed = pitch * rpm / 60.0 * z
    else:
        speed = check_positive("speed_mm_s", sc.speed_mm_s)
        rpm = speed * 60.0 / (pitch * z)
    if sc.runout_um is None:
        runout = tuple(DEFAULT_RUNOUT_UM[k % len(DEFAULT_RUNOUT_UM)] for k in range(z))
    else:
        runout = tuple(sc.runout_um)
    check_range("k1", sc.k1, -1.0, 1.0)
    wood = wood_presets.species(sc.species)
    if sc.pore_density_per_mm2 is not None:
        check_positive("pore_density_per_mm2", sc.pore_density_per_mm2, allow_zero=True)
        wood = dataclasses.replace(wood, pore_density_per_mm2=float(sc.pore_density_per_mm2))
        if wood.pore_contrast == 0.0 and wood.pore_density_per_mm2 > 0:
            wood = dataclasses.replace(wood, pore_contrast=0.3)
    knots = tuple(sc.knots)
    for kn in knots:
        if not isinstance(kn, Knot):
            raise ValueError(f"knots must hold plant_sim.rendering.camera.Knot objects, got {kn!r}")
    head = Cutterhead(z, sc.radius_mm, runout, sc.eccentricity_um)
    rng = np.random.default_rng([sc.seed, 0xB0A2D])
    rig = make_rig(
        width=sc.width, height=sc.height, k1=sc.k1, exposure_ms=sc.exposure_ms,
        counter_bits=sc.counter_bits, slant_deg=sc.slant_deg,
    )
    read_noise_dn = sc.read_noise_dn
    if read_noise_dn is None:
        read_noise_dn = 0.5 if sc.noise else 0.0
    effects = RigEffects(
        roll_deg=sc.roll_deg,
        slant_offset_deg=tuple(sc.slant_offset_deg),
        scattering_mm=sc.scattering_mm,
        reflectance_roughness_deg=sc.reflectance_roughness_deg,
        bow_mm=sc.bow_mm,
        cup_mm=sc.cup_mm,
        board_length_mm=sc.board_length_mm,
        pencil_lines=tuple(sc.pencil_lines),
    )
    optics = Optics(
        width=sc.width,
        height=sc.height,
        read_noise_dn=read_noise_dn,
        shot_noise=bool(sc.noise),
        led_imbalance=sc.imbalance,
        falloff=sc.falloff,
        exposure_ms=sc.exposure_ms,
        dt_ab_s=sc.dt_ab_s,
        counts_per_mm=COUNTS_PER_MM,
        gain=sc.gain,
        quantize=sc.quantize,
    )
    rend = renderer(rig, optics, wood, sc.seed, None if effects == RigEffects() else effects)
    if sc.board_x_at_centre_mm is None:
        bc = float(rng.uniform(100.0, 1000.0))
    else:
        bc = check_finite("board_x_at_centre_mm", sc.board_x_at_centre_mm)
    lo, hi = rend.board_range_mm(board_x_at_centre_mm=bc, speed_mm_s=speed)
    x0, x1 = lo - 1.0, hi + 1.0
    phase = float(rng.uniform(0.0, pitch * z))
    surface = board_surface(
        head, spindle_rpm=rpm, feed_mm_s=speed, x_start_mm=x0, x_end_mm=x1, phase_mm=phase,
        offsets_um=sc.offsets_um,
    )
    if sc.counts_a is None:
        ca = int(rng.integers(0, 1 << sc.counter_bits))
    else:
        ca = check_int("counts_a", sc.counts_a)
    source: Any = _flat_board if sc.flat else surface
    if knots:
        source = _Knotted(source, knots)
    pair = rend.render_pair(
        source,
        board_x_at_centre_mm=bc,
        speed_mm_s=speed,
        counts_a=ca,
        encoder_error_px=sc.encoder_error_px,
        counter_bits=sc.counter_bits,
        rng_seed=int(rng.integers(0, 2**63 - 1)),
        albedo_factor=_knot_darkness(knots) if knots else None,
    )
    return rig, pair


class _Knotted:
    """A height source plus the roughness of knots (marks and metrics from the surface)."""

    def __init__(self, source: Any, knots: tuple[Knot, ...]) -> None:
        self._height = source.height_at if hasattr(source, "height_at") else source
        self._source = source
        self._knots = knots
        if hasattr(source, "metrics"):
            self.metrics = source.metrics

    def height_at(self, x_mm: np.ndarray) -> np.ndarray:
        h = np.asarray(self._height(x_mm), dtype=float)
        for k in self._knots:
            h = h + k.roughness(x_mm)
        return h


def _knot_darkness(knots: tuple[Knot, ...]) -> Any:
    def factor(x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        f = np.ones(np.shape(x_mm))
        for k in knots:
            f = f * k.albedo_factor(x_mm, y_mm)
        return f

    return factor


def _flat_board(b_mm: np.ndarray) -> np.ndarray:
    return np.zeros_like(b_mm)


def random_board_params(seed: int) -> dict[str, Any]:
    """Keyword arguments of :func:`board_pair` drawn from the vision's acceptance ranges.

    Species from the presets; pitch 1-2.5 mm; 1-6 knives with runout (up to 0.12
    ``pitch^2 / R``, so every knife still leaves a mark at least half a pitch wide); feed up to
    1 m/s with the spindle at 1500-24000 rpm; LED imbalance and fall-off up to 10 %; ``|k1|``
    up to 0.3; encoder error up to +-20 px; 16- or 32-bit counter; exposure 0.02-0.1 ms.
    """
    seed = check_int("seed", seed, lo=0)
    rng = np.random.default_rng([seed, 0x4A2D])
    names = sorted(SPECIES)
    radius = 60.0
    while True:
        pitch = float(rng.uniform(1.0, 2.5))
        z = int(rng.integers(1, 7))
        speed = float(rng.uniform(30.0, 1000.0))
        rpm = speed * 60.0 / (pitch * z)
        if 1500.0 <= rpm <= 24000.0:
            break
    max_runout = 0.12 * pitch**2 / radius * 1e3
    runout = tuple(float(v) for v in rng.uniform(-max_runout, max_runout, z))
    return {
        "seed": seed,
        "species": names[int(rng.integers(0, len(names)))],
        "pitch_mm": pitch,
        "knives": z,
        "runout_um": runout,
        "radius_mm": radius,
        "speed_mm_s": speed,
        "imbalance": float(rng.uniform(-0.1, 0.1)),
        "falloff": float(rng.uniform(-0.1, 0.1)),
        "k1": float(rng.uniform(-0.3, 0.3)),
        "encoder_error_px": float(rng.uniform(-20.0, 20.0)),
        "exposure_ms": float(rng.uniform(0.02, 0.1)),
        "counter_bits": int(rng.choice([16, 32])),
    }


def random_board_pair(seed: int) -> tuple[Rig, ImagePair]:
    """:func:`board_pair` with :func:`random_board_params` (held-out simulated boards)."""
    return board_pair(**random_board_params(seed))
