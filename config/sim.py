"""The simulator's configuration (``config/sim.toml``) loaded into frozen dataclasses.

Tables: ``[spindle]``, ``[cutterhead]``, ``[piezo]``, ``[feed]``, ``[encoder]``, ``[camera]``
(with ``[camera.optics]``), ``[board]``, ``[plc]``, ``[faults]`` describe the machine model
(:mod:`plant_sim.machine.machine`); ``[modbus]``, ``[can]``, ``[frames]``, ``[run]`` its interfaces
(the Modbus server, the CAN node, the frame spool and the ``planer sim`` runner); ``[defects]``
the wood defects on the boards (:mod:`config.defects`). Every value is
checked on load and an error names its key (``piezo.stroke_um must be > 0.0, got -1``).
A file (:func:`load_sim`) gives only what it changes: its tables are deep-merged over the
shipped ``config/sim.toml`` (:func:`config.loading.over_shipped`), or over the shipped file its
top-level ``base`` names, e.g. ``config/sim_drift.toml`` (``[cutterhead.drift]``: knives that
warm up and wear, docs/drift.md). A document built in code (:func:`sim_from_dict`) takes the
defaults below for what it leaves out; unknown keys are refused (typos).

See ``docs/simulator.md`` for what each parameter means physically.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from config.defects import DefectsConfig, defects_table
from config.faults import FAULT_KINDS as _FAULT_KINDS
from config.faults import check_fault_head, parse_fault
from config.heads import (
    DEFAULT_FACE,
    DEFAULT_HEAD,
    Face,
    check_unique,
    find_head,
    head_identity,
    head_sections,
    rpm_range,
)
from config.loading import (
    LOOPBACK_HOST,
    MODBUS_PORT,
    SPOOL_DIR,
    Section,
    can_bus_keys,
    default_path,
    load_toml,
    modbus_endpoint,
    over_shipped,
)
from config.rig import Rig, load_rig
from core.errors import ConfigError

__all__ = [
    "BoardConfig",
    "CameraConfig",
    "CanConfig",
    "CutterheadConfig",
    "DriftConfig",
    "EncoderConfig",
    "FaultSpec",
    "FeedConfig",
    "FramesConfig",
    "ModbusConfig",
    "OpticsConfig",
    "PencilLineConfig",
    "PiezoConfig",
    "PlcConfig",
    "RunConfig",
    "SimConfig",
    "SimHeadConfig",
    "SpindleConfig",
    "ALL_HEADS_FAULTS",
    "FAULT_KINDS",
    "MACHINE_FAULTS",
    "default_sim",
    "default_sim_head",
    "fault_heads",
    "head_sim_config",
    "load_sim",
    "sim_from_dict",
    "with_base",
]

FAULT_KINDS: tuple[str, ...] = _FAULT_KINDS
"""Fault kinds the machine model understands (the registry :mod:`config.faults`)."""
MACHINE_FAULTS: frozenset[str] = frozenset(
    {"feed_fault", "encoder_fault", "encoder_wrap", "belt_slip", "modbus_restart"})
"""Faults of the one feed, encoder or PLC: without a head they strike the first head's machine
(the owner of the feed and the encoder)."""
ALL_HEADS_FAULTS: frozenset[str] = frozenset({"estop", "reset", "species_change"})
"""Faults of the whole machine: without a head they strike every head."""


@dataclass(frozen=True)
class SpindleConfig:
    """Spindle drive.

    Attributes
    ----------
    rpm : float
        Nominal speed, revolutions per minute.
    ripple_frac : float
        Amplitude of the sinusoidal load ripple of the speed, fraction of ``rpm``.
    ripple_hz : float
        Frequency of that ripple, Hz.
    load_droop_frac : float
        Speed drop while a board is in the cut, fraction of ``rpm`` (first-order, 0.1 s).
    coast_tau_s : float
        Time constant of the coast-down after a ``spindle_stop`` fault, seconds.
    brake_tau_s : float
        Time constant of the braked stop after an e-stop, seconds.
    spinup_tau_s : float
        Time constant of the run-up after a fault reset, seconds.
    rpm_min, rpm_max : float or None
        The range the speed's setpoint may take (a variable spindle, e.g. a moulder's top
        head; ``rpm`` is its start); ``None``: fixed at ``rpm`` (see :attr:`rpm_range`).
    """

    rpm: float = 6000.0
    ripple_frac: float = 0.001
    ripple_hz: float = 2.0
    load_droop_frac: float = 0.002
    coast_tau_s: float = 3.0
    brake_tau_s: float = 0.5
    spinup_tau_s: float = 1.0
    rpm_min: float | None = None
    rpm_max: float | None = None

    @property
    def rpm_range(self) -> tuple[float, float]:
        """``(rpm_min, rpm_max)``; ``(rpm, rpm)`` for a fixed spindle."""
        return (self.rpm if self.rpm_min is None else self.rpm_min,
                self.rpm if self.rpm_max is None else self.rpm_max)

    @property
    def variable(self) -> bool:
        """Whether the speed's setpoint may change (``rpm_min < rpm_max``)."""
        lo, hi = self.rpm_range
        return lo < hi


@dataclass(frozen=True)
class DriftConfig:
    """Runout drift of the knives over machine time (``[cutterhead.drift]``; docs/drift.md).

    Knife k stands out by an extra ``warmup_um[k] (1 - exp(-t / warmup_tau_s[k])) -
    wear_um_per_min[k] t / 60`` um at machine time t (s): a warm-up toward its amplitude plus
    linear wear. Each tuple has one value per knife.

    Attributes
    ----------
    warmup_um : tuple of float
        Warm-up amplitude per knife, um (positive: stands further out when warm).
    warmup_tau_s : tuple of float
        Warm-up time constant per knife, seconds (the file may give one number for all).
    wear_um_per_min : tuple of float
        Wear per knife (the tip recedes), um per minute, >= 0.
    """

    warmup_um: tuple[float, ...]
    warmup_tau_s: tuple[float, ...]
    wear_um_per_min: tuple[float, ...]

    @property
    def active(self) -> bool:
        """Whether any knife drifts."""
        return any(self.warmup_um) or any(self.wear_um_per_min)


DRIFT_WARMUP_MAX_UM = 50.0
"""Largest warm-up amplitude of a knife, um."""
DRIFT_TAU_DEFAULT_S = 120.0
"""Warm-up time constant when ``[cutterhead.drift]`` gives none, seconds."""
DRIFT_WEAR_MAX_UM_PER_MIN = 10.0
"""Largest wear rate of a knife, um per minute."""


@dataclass(frozen=True)
class CutterheadConfig:
    """Cutterhead geometry: Z knives at tip radius R with per-knife runout and eccentricity.

    Attributes
    ----------
    knives : int
        Number of knives Z (1..8, the CAN offset frames carry eight).
    radius_mm : float
        Tip radius R, millimetres.
    runout_um : tuple of float
        Radial runout of each knife, micrometres (positive: stands out, cuts deeper).
    eccentricity_um : float
        Eccentricity of the head on its spindle: knife k stands out by an extra
        ``eccentricity_um * cos(2 pi k / Z)`` micrometres.
    drift : DriftConfig or None
        Warm-up and wear of the knives (``[cutterhead.drift]``); ``None``: no such table.
    """

    knives: int = 4
    radius_mm: float = 60.0
    runout_um: tuple[float, ...] = (0.0, 4.0, -2.0, 2.0)
    eccentricity_um: float = 0.5
    drift: DriftConfig | None = None


@dataclass(frozen=True)
class PiezoConfig:
    """Piezo actuator (vertical cutterhead motion) and its amplifier.

    Attributes
    ----------
    stroke_um : float
        Offsets are limited to ``[-stroke_um, +stroke_um]``.
    resonance_hz : float
        First resonance of the actuator and spindle, Hz (undamped natural frequency).
    damping : float
        Damping ratio of that resonance.
    hysteresis : float
        Hysteresis loop width over the peak-to-peak excursion of a small cycle (the loop of a
        full-stroke cycle is about 0.76 times as wide, relatively).
    input_shaper : bool
        The amplifier splits each setpoint step into two (zero-vibration shaper tuned to the
        nominal resonance) so that the resonance is not excited.
    lead_fraction : float
        The setpoint switches to knife k's offset this fraction of a knife period before
        knife k reaches bottom dead centre.
    timeout_s : float
        Setpoint timeout: with no new command (RPDO3) for longer, the offsets ramp to zero.
    ramp_um_s : float
        Rate of that ramp, micrometres per second.
    sensor_noise_um : float
        Rms noise of the eddy-current sensor on the spindle's vertical displacement.
    ambient_c, thermal_tau_s, heating_c_per_um_s, max_temperature_c : float
        Actuator temperature: first-order towards ``ambient_c + heating_c_per_um_s * slew``
        (slew: mean absolute setpoint rate, um/s) with ``thermal_tau_s``; over
        ``max_temperature_c`` the amplifier faults (over-temperature).
    """

    stroke_um: float = 20.0
    resonance_hz: float = 800.0
    damping: float = 0.2
    hysteresis: float = 0.03
    input_shaper: bool = True
    lead_fraction: float = 0.75
    timeout_s: float = 0.1
    ramp_um_s: float = 50.0
    sensor_noise_um: float = 0.05
    ambient_c: float = 25.0
    thermal_tau_s: float = 60.0
    heating_c_per_um_s: float = 0.005
    max_temperature_c: float = 70.0


@dataclass(frozen=True)
class FeedConfig:
    """Feed drive (lead-screw table with a velocity loop).

    Attributes
    ----------
    min_mm_s, max_mm_s : float
        Accepted setpoint range; a setpoint outside raises ``ValueError`` (never clamped).
    accel_max_mm_s2 : float
        Acceleration limit.
    bandwidth_hz : float
        Bandwidth of the velocity loop (first order).
    initial_mm_s : float
        Setpoint (and speed) at start.
    """

    min_mm_s: float = 50.0
    max_mm_s: float = 1000.0
    accel_max_mm_s2: float = 2000.0
    bandwidth_hz: float = 8.0
    initial_mm_s: float = 800.0


@dataclass(frozen=True)
class EncoderConfig:
    """Feed encoder counter.

    Attributes
    ----------
    counts_per_mm : float
        Resolution, counts per millimetre of feed.
    counter_bits : int
        Counter width (16 or 32); the counter wraps at ``2**counter_bits``.
    start_counts : int
        Counter value at start (set close to ``2**counter_bits`` to exercise the wrap).
    """

    counts_per_mm: float = 20.0
    counter_bits: int = 32
    start_counts: int = 0


@dataclass(frozen=True)
class OpticsConfig:
    """Image rendering knobs passed to :class:`plant_sim.rendering.optics.Optics`.

    Attributes
    ----------
    imbalance : float
        LED B brightness over LED A, minus one.
    falloff : float
        Fractional intensity change of each LED across the field.
    noise : float
        Read noise, digital numbers rms (shot noise is always on); the file's key is
        ``read_noise_dn`` (or its older name ``noise``).
    width, height : int
        Image size, pixels.
    """

    imbalance: float = 0.05
    falloff: float = 0.1
    noise: float = 0.5
    width: int = 659
    height: int = 493

    @property
    def read_noise_dn(self) -> float:
        """Read noise, DN rms (the same as ``noise``)."""
        return self.noise


@dataclass(frozen=True)
class CameraConfig:
    """The camera downstream of the cutter.

    Attributes
    ----------
    rig_path : Path
        Rig file (camera, lights, encoder scale); default the shipped ``config/rig.toml``.
    rig : config.rig.Rig
        The loaded rig.
    cutter_to_camera_mm : float
        Distance L from the cutterhead axis to the optical axis along the feed.
    pairs_per_s : float
        Trigger rate of image pairs while a board is under the camera.
    dt_ab_s : float
        Time from trigger A to trigger B.
    species : str
        Wood species of the boards (a key of :data:`config.wood.SPECIES`).
    optics : OpticsConfig
        Rendering knobs.
    roll_deg : float
        The camera's true roll about its optical axis, degrees (the rig file knows nothing of
        it): the marks lean by this angle in the images.
    slant_offset_deg : tuple of float
        True slant of lights A and B minus the rig file's ``slant_deg`` (keys
        ``slant_offset_a_deg``, ``slant_offset_b_deg``); the renderer uses the true slants.
    """

    rig_path: Path
    rig: Rig
    cutter_to_camera_mm: float = 300.0
    pairs_per_s: float = 10.0
    dt_ab_s: float = 0.002
    species: str = "spruce"
    optics: OpticsConfig = field(default_factory=OpticsConfig)
    roll_deg: float = 0.0
    slant_offset_deg: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class PencilLineConfig:
    """A pencil line along the feed: position across the board, width, relative darkening."""

    y_mm: float = 0.0
    width_mm: float = 0.6
    darkness: float = 0.5


@dataclass(frozen=True)
class BoardConfig:
    """The stream of boards through the machine.

    Attributes
    ----------
    length_mm : float
        Length of every board.
    gap_mm : float
        Gap between consecutive boards.
    first_at_mm : float
        Distance of the first board's leading end before the cutter axis at time 0.
    count : int
        Number of boards (0: endless).
    width_mm : float
        Width of the boards (for ``cup_mm``).
    scattering_mm : float
        Subsurface scattering length along the fibres, mm (0: none); the species'
        translucency sets how much light scatters and its anisotropy the length across.
    reflectance_roughness_deg : float
        Oren-Nayar roughness of the wood's reflectance, degrees (0: Lambert).
    bow_mm, cup_mm : float
        Sagitta of every board along its length and across its width (ends / edges higher).
    pencil_lines : tuple of PencilLineConfig
        Pencil lines along the feed on every board (``[[board.pencil_lines]]`` with ``y_mm``,
        ``width_mm``, ``darkness``).
    """

    length_mm: float = 4000.0
    gap_mm: float = 500.0
    first_at_mm: float = 100.0
    count: int = 0
    width_mm: float = 150.0
    scattering_mm: float = 0.0
    reflectance_roughness_deg: float = 0.0
    bow_mm: float = 0.0
    cup_mm: float = 0.0
    pencil_lines: tuple[PencilLineConfig, ...] = ()


@dataclass(frozen=True)
class PlcConfig:
    """The PLC's cycle and watchdog.

    Attributes
    ----------
    cycle_s : float
        PLC cycle: the feed and spindle drives are updated and ``heartbeat_plc`` incremented
        once per cycle.
    watchdog_ms : int
        Fault bit 3 (service heartbeat lost) when ``heartbeat_service`` does not change for
        longer than this.
    """

    cycle_s: float = 0.002
    watchdog_ms: int = 1000


@dataclass(frozen=True)
class FaultSpec:
    """A fault injected by the configuration: ``kind`` and its parameters (``at_s`` etc.).

    ``head``: the head it strikes (a name of ``[[heads]]``); ``None``: not one head.
    """

    kind: str
    params: Mapping[str, Any] = field(default_factory=dict)
    head: str | None = None


@dataclass(frozen=True)
class ModbusConfig:
    """The PLC's Modbus TCP server."""

    host: str = LOOPBACK_HOST
    port: int = MODBUS_PORT
    unit_id: int = 1


@dataclass(frozen=True)
class CanConfig:
    """The piezo amplifier's CAN bus and the amplifier on it.

    python-can ``interface``, ``channel``, extra ``options``; the amplifier's CANopen
    ``node_id`` and its ``eds`` file (``None``: the shipped ``config/piezo_amp.eds``).
    """

    interface: str = "virtual"
    channel: str = "planer-piezo"
    options: Mapping[str, Any] = field(default_factory=dict)
    node_id: int = 2
    eds: Path | None = None


@dataclass(frozen=True)
class FramesConfig:
    """Frame hand-off: spool directory and how many pairs it keeps."""

    spool_dir: str = SPOOL_DIR
    keep: int = 50


@dataclass(frozen=True)
class RunConfig:
    """The ``planer sim`` runner: simulated seconds per wall second and its step."""

    time_scale: float = 1.0
    step_s: float = 0.001


@dataclass(frozen=True)
class SimConfig:
    """The whole simulator configuration."""

    spindle: SpindleConfig
    cutterhead: CutterheadConfig
    piezo: PiezoConfig
    feed: FeedConfig
    encoder: EncoderConfig
    camera: CameraConfig
    board: BoardConfig
    plc: PlcConfig
    faults: tuple[FaultSpec, ...]
    modbus: ModbusConfig
    can: CanConfig
    frames: FramesConfig
    run: RunConfig
    source: Path | None = None
    defects: DefectsConfig = DefectsConfig()
    """``[defects]``: wood defects on the boards (:mod:`config.defects`; none by default)."""
    declared_heads: tuple[SimHeadConfig, ...] = ()
    """``[[heads]]`` as the file gives them; ``()`` for a single-head file (see :attr:`heads`)."""

    @property
    def heads(self) -> tuple[SimHeadConfig, ...]:
        """The machine's heads in file order: ``[[heads]]``, else the one head ``"main"``.

        The single head of a file without ``[[heads]]`` is :func:`default_sim_head` of this
        configuration's own tables (so it follows every change of them).
        """
        return self.declared_heads or (default_sim_head(self),)


@dataclass(frozen=True)
class SimHeadConfig:
    """One simulated head (``[[heads]]`` of ``sim.toml``): the tables of its own ``Machine``.

    Attributes
    ----------
    name : str
        Unique name (:data:`config.heads.HEAD_NAME`); ``"main"`` for a single head.
    face : config.heads.Face
        The face it cuts.
    position_mm : float
        Its place along the feed, mm from the first head.
    cutterhead, spindle, camera, piezo
        Its tables: the shared ``[cutterhead]``, ``[spindle]``, ``[camera]``, ``[piezo]`` with
        the head's keys over them (knives, radius_mm, runout_um, eccentricity_um, drift; rpm,
        rpm_min, rpm_max; cutter_to_camera_mm, roll_deg, species, read_noise_dn; stroke_um).
    node_id : int
        Its amplifier's CANopen node id (1..127) on the one CAN bus.
    """

    name: str
    face: Face
    position_mm: float
    cutterhead: CutterheadConfig
    spindle: SpindleConfig
    camera: CameraConfig
    piezo: PiezoConfig
    node_id: int


def default_sim_head(cfg: SimConfig) -> SimHeadConfig:
    """The one head ``"main"`` (face ``"top"``) of a configuration without ``[[heads]]``."""
    return SimHeadConfig(name=DEFAULT_HEAD, face=DEFAULT_FACE, position_mm=0.0,
                         cutterhead=cfg.cutterhead, spindle=cfg.spindle, camera=cfg.camera,
                         piezo=cfg.piezo, node_id=cfg.can.node_id)


def fault_heads(kind: str, head: str | None, names: Sequence[str]) -> tuple[str, ...]:
    """The heads a fault strikes: the one rule of a moulder's faults (one head's too).

    Parameters
    ----------
    kind : str
        The fault's kind.
    head : str or None
        The head it names (``None``: none).
    names : sequence of str
        The machine's heads in order (the first owns the feed and the encoder).

    Returns
    -------
    tuple of str
        The head it names; else every head for :data:`ALL_HEADS_FAULTS`, the first for
        :data:`MACHINE_FAULTS` or a machine of one head.

    Raises
    ------
    ConfigError
        ``head`` is none of ``names``, or a kind that strikes one head (a knife, a spindle, an
        amplifier, a camera) names none in a machine of several.
    """
    names = tuple(names)
    if head is not None:
        if head not in names:
            raise ConfigError(f"head must be one of {', '.join(names)}, got {head!r}")
        return (head,)
    if kind in ALL_HEADS_FAULTS:
        return names
    if kind in MACHINE_FAULTS or len(names) == 1:
        return names[:1]
    raise ConfigError(f"fault {kind} strikes one head: give head= (one of {', '.join(names)})")


def head_sim_config(cfg: SimConfig, name: str) -> SimConfig:
    """The whole configuration of the ``Machine`` of the head called ``name``.

    Parameters
    ----------
    cfg : SimConfig
        The machine's configuration.
    name : str
        One of ``cfg.heads``' names.

    Returns
    -------
    SimConfig
        ``cfg`` with the head's ``cutterhead``, ``spindle``, ``camera``, ``piezo`` and
        ``can.node_id``, ``heads == (head,)`` and the faults that strike it
        (:func:`fault_heads`); the feed, encoder, board, PLC and interfaces shared. For a
        single-head file ``head_sim_config(cfg, "main") == cfg``.

    Raises
    ------
    ConfigError
        No head of that name.
    """
    head: SimHeadConfig = find_head(cfg.heads, name)
    names = tuple(h.name for h in cfg.heads)
    return dataclasses.replace(
        cfg, cutterhead=head.cutterhead, spindle=head.spindle, camera=head.camera,
        piezo=head.piezo, can=dataclasses.replace(cfg.can, node_id=head.node_id),
        faults=tuple(f for f in cfg.faults if name in fault_heads(f.kind, f.head, names)),
        declared_heads=(head,) if cfg.declared_heads else ())


def _spindle(s: Section) -> SpindleConfig:
    """``[spindle]`` (or a head's): a variable spindle without ``rpm`` starts at ``rpm_max``."""
    d = SpindleConfig()
    ranged = s.has("rpm_min") or s.has("rpm_max")
    rpm, lo, hi = rpm_range(*(s.number(k, lo=100.0, hi=30000.0) if s.has(k) else None
                              for k in ("rpm", "rpm_min", "rpm_max")), s.prefix)
    out = SpindleConfig(
        rpm=d.rpm if rpm is None else rpm,
        ripple_frac=s.number("ripple_frac", d.ripple_frac, lo=0.0, hi=0.05),
        ripple_hz=s.number("ripple_hz", d.ripple_hz, lo=0.0, hi=100.0),
        load_droop_frac=s.number("load_droop_frac", d.load_droop_frac, lo=0.0, hi=0.2),
        coast_tau_s=s.number("coast_tau_s", d.coast_tau_s, lo=0.0, lo_open=True, hi=600.0),
        brake_tau_s=s.number("brake_tau_s", d.brake_tau_s, lo=0.0, lo_open=True, hi=60.0),
        spinup_tau_s=s.number("spinup_tau_s", d.spinup_tau_s, lo=0.0, lo_open=True, hi=600.0),
        rpm_min=lo if ranged else None,  # a fixed spindle keeps None (SpindleConfig.rpm_range)
        rpm_max=hi if ranged else None,
    )
    s.reject_unknown()
    return out


def _cutterhead(s: Section) -> CutterheadConfig:
    d = CutterheadConfig()
    knives = s.integer("knives", d.knives, lo=1, hi=8)
    if s.has("runout_um"):
        runout = s.numbers("runout_um", length=knives)
    elif knives == len(d.runout_um):
        runout = d.runout_um
    else:
        runout = (0.0,) * knives
    for i, r in enumerate(runout):
        if abs(r) > 100.0:
            raise ConfigError(f"{s.key('runout_um')}[{i}] must be within +-100 µm, got {r!r}")
    out = CutterheadConfig(
        knives=knives,
        radius_mm=s.number("radius_mm", d.radius_mm, lo=5.0, hi=500.0),
        runout_um=runout,
        eccentricity_um=s.number("eccentricity_um", d.eccentricity_um, lo=-100.0, hi=100.0),
        drift=_drift(s.section("drift"), knives) if s.has("drift") else None,
    )
    s.reject_unknown()
    return out


def _drift(s: Section, knives: int) -> DriftConfig:
    """``[cutterhead.drift]``: per-knife lists (``warmup_tau_s`` may be one number)."""
    zeros = (0.0,) * knives
    warmup = s.numbers("warmup_um", zeros, length=knives)
    for i, v in enumerate(warmup):
        if abs(v) > DRIFT_WARMUP_MAX_UM:
            raise ConfigError(f"{s.key('warmup_um')}[{i}] must be within "
                              f"+-{DRIFT_WARMUP_MAX_UM:g} µm, got {v!r}")
    raw_tau = s.raw("warmup_tau_s", DRIFT_TAU_DEFAULT_S)
    if isinstance(raw_tau, (list, tuple)):
        tau = s.numbers("warmup_tau_s", length=knives)
    else:
        tau = (s.number("warmup_tau_s", DRIFT_TAU_DEFAULT_S, lo=0.0, lo_open=True,
                        hi=86400.0),) * knives
    for i, v in enumerate(tau):
        if not 0.0 < v <= 86400.0:
            raise ConfigError(f"{s.key('warmup_tau_s')}[{i}] must be > 0 and <= 86400 s, "
                              f"got {v!r}")
    wear = s.numbers("wear_um_per_min", zeros, length=knives)
    for i, v in enumerate(wear):
        if not 0.0 <= v <= DRIFT_WEAR_MAX_UM_PER_MIN:
            raise ConfigError(f"{s.key('wear_um_per_min')}[{i}] must be within 0.."
                              f"{DRIFT_WEAR_MAX_UM_PER_MIN:g} µm/min, got {v!r}")
    s.reject_unknown()
    return DriftConfig(warmup_um=warmup, warmup_tau_s=tau, wear_um_per_min=wear)


def _piezo(s: Section) -> PiezoConfig:
    d = PiezoConfig()
    out = PiezoConfig(
        stroke_um=s.number("stroke_um", d.stroke_um, lo=0.0, lo_open=True, hi=1000.0),
        resonance_hz=s.number("resonance_hz", d.resonance_hz, lo=10.0, hi=100000.0),
        damping=s.number("damping", d.damping, lo=0.01, hi=0.95),
        hysteresis=s.number("hysteresis", d.hysteresis, lo=0.0, hi=0.5),  # the model's range
        input_shaper=s.boolean("input_shaper", d.input_shaper),
        lead_fraction=s.number("lead_fraction", d.lead_fraction, lo=0.05, hi=0.95),
        timeout_s=s.number("timeout_s", d.timeout_s, lo=0.0, lo_open=True, hi=60.0),
        ramp_um_s=s.number("ramp_um_s", d.ramp_um_s, lo=0.0, lo_open=True),
        sensor_noise_um=s.number("sensor_noise_um", d.sensor_noise_um, lo=0.0, hi=10.0),
        ambient_c=s.number("ambient_c", d.ambient_c, lo=-40.0, hi=80.0),
        thermal_tau_s=s.number("thermal_tau_s", d.thermal_tau_s, lo=0.0, lo_open=True),
        heating_c_per_um_s=s.number("heating_c_per_um_s", d.heating_c_per_um_s, lo=0.0),
        max_temperature_c=s.number("max_temperature_c", d.max_temperature_c, lo=0.0, hi=300.0),
    )
    s.reject_unknown()
    if out.max_temperature_c <= out.ambient_c:
        raise ConfigError(f"{s.key('max_temperature_c')} must exceed ambient_c")
    return out


def _feed(s: Section) -> FeedConfig:
    d = FeedConfig()
    lo = s.number("min_mm_s", d.min_mm_s, lo=0.0, lo_open=True)
    hi = s.number("max_mm_s", d.max_mm_s, lo=0.0, lo_open=True, hi=10000.0)
    if hi <= lo:
        raise ConfigError(f"{s.key('max_mm_s')} must exceed min_mm_s ({lo}), got {hi!r}")
    out = FeedConfig(
        min_mm_s=lo,
        max_mm_s=hi,
        accel_max_mm_s2=s.number("accel_max_mm_s2", d.accel_max_mm_s2, lo=0.0, lo_open=True),
        bandwidth_hz=s.number("bandwidth_hz", d.bandwidth_hz, lo=0.1, hi=100.0),
        initial_mm_s=s.number("initial_mm_s", d.initial_mm_s, lo=lo, hi=hi),
    )
    s.reject_unknown()
    return out


def _encoder(s: Section) -> EncoderConfig:
    d = EncoderConfig()
    bits = s.integer("counter_bits", d.counter_bits)
    if bits not in (16, 32):
        raise ConfigError(f"{s.key('counter_bits')} must be 16 or 32, got {bits}")
    out = EncoderConfig(
        counts_per_mm=s.number("counts_per_mm", d.counts_per_mm, lo=0.0, lo_open=True, hi=1e6),
        counter_bits=bits,
        start_counts=s.integer("start_counts", d.start_counts, lo=0, hi=(1 << bits) - 1),
    )
    s.reject_unknown()
    return out


def _optics(s: Section) -> OpticsConfig:
    d = OpticsConfig()
    out = OpticsConfig(
        imbalance=s.number("imbalance", d.imbalance, lo=-0.9, hi=10.0),
        falloff=s.number("falloff", d.falloff, lo=-1.0, hi=1.0),
        noise=_read_noise(s, d.noise),
        width=s.integer("width", d.width, lo=16, hi=16384),
        height=s.integer("height", d.height, lo=4, hi=16384),
    )
    s.reject_unknown()
    return out


def _read_noise(s: Section, default: float, *, alias: bool = True) -> float:
    """``read_noise_dn`` (``[camera.optics]`` also takes its old name ``noise``: ``alias``)."""
    if alias and s.has("read_noise_dn") and s.has("noise"):
        raise ConfigError(f"{s.key('read_noise_dn')}: give read_noise_dn or noise, not both")
    name = "noise" if alias and s.has("noise") else "read_noise_dn"
    return s.number(name, default, lo=0.0, hi=100.0)


def _camera_place(s: Section, d: Any) -> dict[str, Any]:
    """The camera's keys a head may give its own (``d``: their defaults), checked.

    ``cutter_to_camera_mm``, ``roll_deg`` and ``species`` (one of
    :data:`config.wood.SPECIES`, case and spaces ignored): ``[camera]``'s and each head's.
    """
    species = s.string("species", d.species).strip().lower()
    from config.wood import SPECIES  # the known species (a data table, no I/O)

    if species not in SPECIES:
        raise ConfigError(
            f"{s.key('species')} must be one of {', '.join(sorted(SPECIES))}; got {species!r}"
        )
    return {
        "cutter_to_camera_mm": s.number("cutter_to_camera_mm", d.cutter_to_camera_mm, lo=1.0,
                                        hi=10000.0),
        "roll_deg": s.number("roll_deg", d.roll_deg, lo=-10.0, hi=10.0),
        "species": species,
    }


def _camera(s: Section, base: Path | None) -> CameraConfig:
    d = CameraConfig
    rig_raw = s.string("rig", "")
    if rig_raw:
        rig_path = Path(rig_raw)
        if not rig_path.is_absolute() and base is not None:
            rig_path = base / rig_path
    else:
        rig_path = default_path("rig.toml")
    try:
        rig = load_rig(rig_path)
    except ConfigError as exc:
        raise ConfigError(f"{s.key('rig')}: {exc}") from None
    out = CameraConfig(
        rig_path=rig_path,
        rig=rig,
        **_camera_place(s, d),
        pairs_per_s=s.number("pairs_per_s", d.pairs_per_s, lo=0.0, lo_open=True, hi=1000.0),
        dt_ab_s=s.number("dt_ab_s", d.dt_ab_s, lo=0.0, lo_open=True, hi=0.1),
        optics=_optics(s.section("optics", required=False)),
        slant_offset_deg=(
            s.number("slant_offset_a_deg", d.slant_offset_deg[0], lo=-10.0, hi=10.0),
            s.number("slant_offset_b_deg", d.slant_offset_deg[1], lo=-10.0, hi=10.0),
        ),
    )
    s.reject_unknown()
    lit = rig.lights
    nominal = getattr(lit, "slants_deg", (lit.slant_deg, lit.slant_deg))
    for name, off, nom in zip(("slant_offset_a_deg", "slant_offset_b_deg"),
                              out.slant_offset_deg, nominal, strict=True):
        if not 0.0 < nom + off < 90.0:
            raise ConfigError(
                f"{s.key(name)} gives a true slant of {nom + off} deg with the rig's "
                f"{nom}; must stay within (0, 90)"
            )
    if out.dt_ab_s * out.pairs_per_s >= 1.0:
        raise ConfigError(f"{s.key('dt_ab_s')} must be shorter than the trigger period")
    return out


def _board(s: Section) -> BoardConfig:
    d = BoardConfig()
    out = BoardConfig(
        length_mm=s.number("length_mm", d.length_mm, lo=100.0, hi=100000.0),
        gap_mm=s.number("gap_mm", d.gap_mm, lo=0.0, hi=100000.0),
        first_at_mm=s.number("first_at_mm", d.first_at_mm, lo=0.0, hi=100000.0),
        count=s.integer("count", d.count, lo=0),
        width_mm=s.number("width_mm", d.width_mm, lo=10.0, hi=2000.0),
        scattering_mm=s.number("scattering_mm", d.scattering_mm, lo=0.0, hi=2.0),
        reflectance_roughness_deg=s.number(
            "reflectance_roughness_deg", d.reflectance_roughness_deg, lo=0.0, hi=60.0
        ),
        bow_mm=s.number("bow_mm", d.bow_mm, lo=-100.0, hi=100.0),
        cup_mm=s.number("cup_mm", d.cup_mm, lo=-20.0, hi=20.0),
        pencil_lines=_pencil_lines(s),
    )
    s.reject_unknown()
    return out


def _pencil_lines(s: Section) -> tuple[PencilLineConfig, ...]:
    items = s.raw("pencil_lines", [])
    if not isinstance(items, list):
        raise ConfigError(f"{s.key('pencil_lines')} must be a list of tables, got {items!r}")
    d = PencilLineConfig()
    out = []
    for i, item in enumerate(items):
        t = Section(item, f"{s.key('pencil_lines')}[{i}]")
        out.append(PencilLineConfig(
            y_mm=t.number("y_mm", d.y_mm, lo=-1000.0, hi=1000.0),
            width_mm=t.number("width_mm", d.width_mm, lo=0.01, hi=50.0),
            darkness=t.number("darkness", d.darkness, lo=0.0, hi=1.0),
        ))
        t.reject_unknown()
    return tuple(out)


def _plc(s: Section) -> PlcConfig:
    d = PlcConfig()
    out = PlcConfig(
        cycle_s=s.number("cycle_s", d.cycle_s, lo=1e-4, hi=0.1),
        watchdog_ms=s.integer("watchdog_ms", d.watchdog_ms, lo=1, hi=65535),
    )
    s.reject_unknown()
    return out


def _faults(raw: Any) -> tuple[FaultSpec, ...]:
    """``[faults] inject = [{kind = ..., ...}]`` or an array of tables ``[[faults]]``."""
    if raw is None:
        return ()
    if isinstance(raw, Mapping):
        s = Section(raw, "faults")
        items = s.raw("inject", [])
        s.reject_unknown()
        prefix = "faults.inject"
    else:
        items = raw
        prefix = "faults"
    if not isinstance(items, list):
        raise ConfigError(f"{prefix} must be a list of tables, got {items!r}")
    out = []
    for i, item in enumerate(items):
        fault = parse_fault(item, f"{prefix}[{i}]")  # the registry checks kind and parameters
        out.append(FaultSpec(kind=fault.kind.value, params={
            k: v for k, v in fault.table().items() if k not in ("kind", "head")},
            head=fault.head))
    return tuple(out)


def _modbus(s: Section) -> ModbusConfig:
    d = ModbusConfig()
    host, port, unit_id = modbus_endpoint(
        s, host=d.host, port=d.port, unit_id=d.unit_id, port_lo=0
    )
    s.reject_unknown()
    return ModbusConfig(host=host, port=port, unit_id=unit_id)


def _can(s: Section, base: Path | None) -> CanConfig:
    d = CanConfig()
    interface, channel, options = can_bus_keys(s, interface=d.interface, channel=d.channel)
    node_id = s.integer("node_id", d.node_id, lo=1, hi=127)
    eds = s.string("eds", "")
    s.reject_unknown()
    eds_path = Path(eds).expanduser() if eds else None
    if eds_path is not None and not eds_path.is_absolute() and base is not None:
        eds_path = base / eds_path
    return CanConfig(interface=interface, channel=channel, options=options, node_id=node_id,
                     eds=eds_path)


def _frames(s: Section) -> FramesConfig:
    d = FramesConfig()
    out = FramesConfig(
        spool_dir=s.string("spool_dir", d.spool_dir),
        keep=s.integer("keep", d.keep, lo=1, hi=1_000_000),
    )
    s.reject_unknown()
    if not out.spool_dir:
        raise ConfigError(f"{s.key('spool_dir')} must not be empty")
    return out


def _run(s: Section) -> RunConfig:
    d = RunConfig()
    out = RunConfig(
        time_scale=s.number("time_scale", d.time_scale, lo=0.0, lo_open=True, hi=1000.0),
        step_s=s.number("step_s", d.step_s, lo=1e-5, hi=1.0),
    )
    s.reject_unknown()
    return out


_HEAD_CUTTER_KEYS = ("knives", "radius_mm", "runout_um", "eccentricity_um", "drift")
_HEAD_SPINDLE_KEYS = ("rpm", "rpm_min", "rpm_max")


def _head_cutterhead(t: Section, shared: CutterheadConfig) -> CutterheadConfig:
    """A head's cutterhead: its keys over the shared ``[cutterhead]`` (errors name the head).

    Runout and drift are per knife: a head with another knife count than the shared table
    takes no runout (zeros) and no drift unless it gives its own.
    """
    raw = {k: t.raw(k) for k in _HEAD_CUTTER_KEYS if t.has(k)}
    raw.setdefault("knives", shared.knives)
    raw.setdefault("radius_mm", shared.radius_mm)
    raw.setdefault("eccentricity_um", shared.eccentricity_um)
    if raw["knives"] == shared.knives:
        raw.setdefault("runout_um", list(shared.runout_um))
        if shared.drift is not None:
            raw.setdefault("drift", {"warmup_um": list(shared.drift.warmup_um),
                                     "warmup_tau_s": list(shared.drift.warmup_tau_s),
                                     "wear_um_per_min": list(shared.drift.wear_um_per_min)})
    return _cutterhead(Section(raw, t.prefix))


def _head_spindle(t: Section, shared: SpindleConfig) -> SpindleConfig:
    """A head's spindle: its ``rpm`` (fixed) or ``rpm_min``/``rpm_max`` over ``[spindle]``.

    The head's own speeds replace all three of the shared table's (a range without ``rpm``
    starts at its ``rpm_max``, as :func:`config.heads.rpm_range` completes it).
    """
    raw = {k: v for k, v in dataclasses.asdict(shared).items() if v is not None}
    given = {k: t.raw(k) for k in _HEAD_SPINDLE_KEYS if t.has(k)}
    if given:
        for k in _HEAD_SPINDLE_KEYS:
            raw.pop(k, None)
    raw.update(given)
    return _spindle(Section(raw, t.prefix))


def _head_camera(t: Section, shared: CameraConfig) -> CameraConfig:
    """A head's camera: ``cutter_to_camera_mm``, ``roll_deg``, ``species``, ``read_noise_dn``."""
    return dataclasses.replace(
        shared, **_camera_place(t, shared),
        optics=dataclasses.replace(shared.optics,
                                   noise=_read_noise(t, shared.optics.noise, alias=False)))


def _sim_heads(raw: Any, cfg: SimConfig) -> tuple[SimHeadConfig, ...]:
    """``[[heads]]`` of ``sim.toml``: each head's keys over the shared tables, checked."""
    heads = []
    for t in head_sections(raw):
        name, face, position_mm, node_id = head_identity(t)
        head = SimHeadConfig(
            name=name,
            face=face,
            position_mm=position_mm,
            cutterhead=_head_cutterhead(t, cfg.cutterhead),
            spindle=_head_spindle(t, cfg.spindle),
            camera=_head_camera(t, cfg.camera),
            piezo=dataclasses.replace(
                cfg.piezo, stroke_um=t.number("stroke_um", cfg.piezo.stroke_um, lo=0.0,
                                              lo_open=True, hi=1000.0)),
            node_id=node_id,
        )
        t.reject_unknown()
        heads.append(head)
    out = tuple(heads)
    check_unique((h.name for h in out), "name")
    check_unique((h.node_id for h in out), "node_id")
    return out


def _check_head(head: SimHeadConfig, cfg: SimConfig, key: str) -> None:
    """A head's geometry against the shared feed: runout within the radius, pitch below R/4."""
    ch = head.cutterhead
    runout = "cutterhead.runout_um" if key == "" else f"{key}.runout_um"
    if max(abs(r) for r in ch.runout_um) + abs(ch.eccentricity_um) > 1e3 * ch.radius_mm:
        raise ConfigError(f"{runout} is larger than the radius")
    rpm = "rpm_min" if head.spindle.variable else "rpm"  # the slowest the head may run
    rpm = f"spindle.{rpm}" if key == "" else f"{key}.{rpm}"
    max_pitch = cfg.feed.max_mm_s / (head.spindle.rpm_range[0] / 60.0 * ch.knives)
    if max_pitch > 0.25 * ch.radius_mm:
        raise ConfigError(
            f"feed.max_mm_s gives {max_pitch:.3g} mm per knife pass at {rpm}; "
            f"must stay below R/4 = {ch.radius_mm / 4:g} mm"
        )


def _merged(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``: tables merge key by key, any other value replaces."""
    out = dict(base)
    for key, value in over.items():
        below = out.get(key)
        if isinstance(value, Mapping) and isinstance(below, Mapping):
            out[key] = _merged(below, value)
        else:
            out[key] = value
    return out


def with_base(data: Mapping[str, Any]) -> dict[str, Any]:
    """The document with the shipped file its top-level ``base`` key names merged under it.

    ``base = "sim.toml"`` starts from the shipped ``config/sim.toml`` and changes only the
    tables and keys this document gives (tables merge key by key; lists and values replace).
    ``base`` names a file of the shipped config folder only, so a copy of the document
    elsewhere (the cross-process HIL writes one to a temporary folder) means the same.

    Raises
    ------
    ConfigError
        ``base`` is not a file name of the shipped config folder, the file is missing or bad,
        or the bases form a circle; the message names the key.
    """
    if "base" not in data:
        return dict(data)
    return over_shipped(data, "sim.toml")


def sim_from_dict(data: Mapping[str, Any], *, base_dir: Path | None = None) -> SimConfig:
    """Build and check a :class:`SimConfig` from a parsed TOML document.

    Parameters
    ----------
    data : mapping
        The parsed document; missing tables and keys take their defaults, or the values of
        the shipped file a top-level ``base`` names (:func:`with_base`).
    base_dir : Path, optional
        Directory that a relative ``camera.rig`` path is relative to.

    Raises
    ------
    ConfigError
        A value is missing, mistyped or out of range, or a key is unknown; the message names
        the key.
    """
    root = Section(with_base(data), "")

    def sec(name: str) -> Section:
        return root.section(name, required=False)

    cfg = SimConfig(
        spindle=_spindle(sec("spindle")),
        cutterhead=_cutterhead(sec("cutterhead")),
        piezo=_piezo(sec("piezo")),
        feed=_feed(sec("feed")),
        encoder=_encoder(sec("encoder")),
        camera=_camera(sec("camera"), base_dir),
        board=_board(sec("board")),
        plc=_plc(sec("plc")),
        faults=_faults(root.raw("faults", None)),
        modbus=_modbus(sec("modbus")),
        can=_can(sec("can"), base_dir),
        frames=_frames(sec("frames")),
        run=_run(sec("run")),
        defects=defects_table(sec("defects")),
    )
    if root.raw("heads", None) is not None:
        cfg = dataclasses.replace(cfg, declared_heads=_sim_heads(root.raw("heads"), cfg))
    root.reject_unknown()
    names = tuple(h.name for h in cfg.heads)
    faults_key = "faults.inject" if isinstance(root.raw("faults", None), Mapping) else "faults"
    for i, fault in enumerate(cfg.faults):
        check_fault_head(fault.head, names, f"{faults_key}[{i}].head")
        try:  # the heads it strikes: a one-head kind names its head in a moulder
            fault_heads(fault.kind, fault.head, names)
        except ConfigError as exc:
            raise ConfigError(f"{faults_key}[{i}]: {exc}") from None
    _check_head(default_sim_head(cfg), cfg, "")
    for i, head in enumerate(cfg.declared_heads):
        _check_head(head, cfg, f"heads[{i}]")
    rig = cfg.camera.rig
    expect = rig.camera.px_per_mm / cfg.encoder.counts_per_mm
    if not math.isclose(rig.encoder.px_per_count, expect, rel_tol=1e-6):
        raise ConfigError(
            f"encoder.counts_per_mm ({cfg.encoder.counts_per_mm}) disagrees with the rig: "
            f"px_per_mm / px_per_count = {rig.camera.px_per_mm / rig.encoder.px_per_count}"
        )
    if cfg.encoder.counter_bits != rig.encoder.counter_bits:
        raise ConfigError(
            f"encoder.counter_bits ({cfg.encoder.counter_bits}) disagrees with the rig's "
            f"({rig.encoder.counter_bits}): the service unwraps the latched counts with the rig's"
        )
    return cfg


def load_sim(path: str | Path | None = None) -> SimConfig:
    """Load and check a simulator configuration (default: the shipped ``config/sim.toml``).

    Raises
    ------
    ConfigError
        The file is missing or malformed, or a value is invalid; the message names the file and
        the key.
    """
    p = Path(path) if path is not None else default_path("sim.toml")
    data = load_toml(p)  # over the shipped sim.toml: a file gives only what it changes
    try:
        data = over_shipped(data, "sim.toml", aliases={"camera.optics.noise": "read_noise_dn"})
        cfg = sim_from_dict(data, base_dir=p.parent)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None
    return dataclasses.replace(cfg, source=p)


def default_sim() -> SimConfig:
    """The defaults of every table (no file read except the shipped rig)."""
    return sim_from_dict({})
