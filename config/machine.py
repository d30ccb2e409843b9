"""The service's configuration (``config/machine.toml``) as frozen, validated dataclasses.

One file says where the PLC and the piezo amplifier are, where the image pairs come from, which
quality class to hold and how to behave when something is gone. The same service runs against
the simulator and against the real machine by changing this file only (e.g. ``can.interface =
"socketcan"``, ``can.channel = "can0"``, ``plc.host`` = the PLC's address).

Every wrong or missing value raises :class:`core.errors.ConfigError` naming the key
(``"safety.plc_timeout_s must be > 0"``); unknown keys are rejected (typos).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from config.loading import Section, can_bus_keys, default_path, load_toml, modbus_endpoint
from core.errors import ConfigError

FRAME_SOURCES = ("spool", "inprocess")
SAFE_STATES = ("hold", "ramp_down")


def _frozen(mapping: Mapping[str, Any] | None = None) -> Mapping[str, Any]:
    return MappingProxyType(dict(mapping or {}))


@dataclass(frozen=True)
class PlcConfig:
    """Where the PLC's Modbus TCP server is and how patiently to talk to it.

    Attributes
    ----------
    host, port, unit_id
        Modbus TCP endpoint and unit (device) id.
    timeout_s : float
        Time limit of one request, seconds.
    backoff_initial_s, backoff_max_s : float
        Reconnect back-off: first wait, doubled after each failed attempt up to the cap.
    registers : Path or None
        Register map file; ``None`` means the shipped ``config/registers.toml``.
    """

    host: str = "127.0.0.1"
    port: int = 5020
    unit_id: int = 1
    timeout_s: float = 0.25
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 2.0
    registers: Path | None = None


@dataclass(frozen=True)
class CanConfig:
    """The CAN bus to the piezo amplifier (python-can) and the send periods.

    Attributes
    ----------
    interface, channel
        python-can interface name and channel (``virtual``/any name, ``udp_multicast``/IPv4 group,
        ``socketcan``/``can0``, ``remote``/``ws://...``).
    options : mapping
        Extra keyword arguments for ``can.Bus``.
    command_period_s : float
        Period of ``PIEZO_COMMAND`` (enable, knives, alive counter), seconds.
    offsets_period_s : float
        ``PIEZO_OFFSETS_*`` are sent on change and at least this often, seconds.
    dbc : Path or None
        DBC file; ``None`` means the shipped ``config/piezo.dbc``.
    """

    interface: str = "virtual"
    channel: str = "planer"
    options: Mapping[str, Any] = field(default_factory=_frozen)
    command_period_s: float = 0.02
    offsets_period_s: float = 0.2
    dbc: Path | None = None


@dataclass(frozen=True)
class FramesConfig:
    """Where image pairs come from: a spool directory (camera process) or in-process.

    ``pairs_per_s`` is the camera's nominal rate (the control loops' sample time);
    ``image_width`` x ``image_height`` the camera's image size, pixels, so the measurement is
    set up before the first pair arrives (0: on the first pair).
    """

    source: str = "spool"
    spool_dir: Path = Path("runs/spool")
    poll_s: float = 0.002
    pairs_per_s: float = 10.0
    image_width: int = 0
    image_height: int = 0


@dataclass(frozen=True)
class QualityConfig:
    """The quality class the service holds and judges every measurement against.

    ``tolerance`` is relative (0.02 = +-2 % of ``target_pitch_mm``).
    """

    class_name: str = "fine-1.5"
    target_pitch_mm: float = 1.5
    tolerance: float = 0.02
    uniformity_max_cv: float = 0.05
    depth_max_um: float = 20.0


@dataclass(frozen=True)
class PlausibilityConfig:
    """A measurement is used for control only when it passes these checks.

    Attributes
    ----------
    pitch_ratio_min, pitch_ratio_max : float
        Bounds of measured pitch / kinematic pitch ``V_f / (n Z)``.
    min_marks : int
        Fewest complete marks in the profile.
    min_confidence : float
        Lowest registration confidence.
    """

    pitch_ratio_min: float = 0.5
    pitch_ratio_max: float = 2.0
    min_marks: int = 6
    min_confidence: float = 0.3


@dataclass(frozen=True)
class SafetyConfig:
    """Timeouts and the safe-state action of :mod:`controller.safety` (seconds, mm/s)."""

    cycle_s: float = 0.02
    plc_timeout_s: float = 0.5
    can_timeout_s: float = 0.3
    measurement_timeout_s: float = 2.0
    recovery_s: float = 0.3
    safe_state: str = "ramp_down"
    safe_feed_mm_s: float = 400.0
    ramp_mm_s2: float = 500.0


@dataclass(frozen=True)
class LogConfig:
    """Quality log location and how often ``planer serve`` prints a progress line."""

    path: Path = Path("runs/quality.sqlite")
    print_every: int = 20


@dataclass(frozen=True)
class MachineConfig:
    """The whole ``machine.toml``.

    ``feed_loop`` and ``uniformity_loop`` hold the raw (validated numeric) keys of those tables;
    :mod:`controller.service` passes them to the control laws' own configuration classes, whose
    defaults apply to missing keys.
    """

    plc: PlcConfig = PlcConfig()
    can: CanConfig = CanConfig()
    frames: FramesConfig = FramesConfig()
    rig: Path | None = None
    quality: QualityConfig = QualityConfig()
    stroke_um: float = 20.0
    feed_loop: Mapping[str, Any] = field(default_factory=_frozen)
    uniformity_loop: Mapping[str, Any] = field(default_factory=_frozen)
    plausibility: PlausibilityConfig = PlausibilityConfig()
    safety: SafetyConfig = SafetyConfig()
    log: LogConfig = LogConfig()

    def with_changes(self, **tables: Any) -> MachineConfig:
        """A copy with whole tables replaced, e.g. ``cfg.with_changes(plc=new_plc)``."""
        return replace(self, **tables)


def _path_or_none(sec: Section, name: str, base: Path | None) -> Path | None:
    raw = sec.string(name, "")
    if raw == "":
        return None
    return Path(raw).expanduser()


def _loop_table(sec: Section) -> Mapping[str, Any]:
    out: dict[str, Any] = {}
    for name in list(sec._data):  # noqa: SLF001 - Section has no key iterator
        val = sec.raw(name)
        if isinstance(val, bool):
            out[name] = val
        elif isinstance(val, (int, float)):
            out[name] = sec.number(name) if isinstance(val, float) else val
        elif isinstance(val, list):
            out[name] = sec.numbers(name)
        elif isinstance(val, str):
            out[name] = val
        else:
            raise ConfigError(f"{sec.key(name)} must be a number, boolean, string or list")
    return _frozen(out)


def machine_from_dict(data: Mapping[str, Any], *, base: Path | None = None) -> MachineConfig:
    """Build and check a :class:`MachineConfig` from a parsed TOML document.

    Parameters
    ----------
    data : mapping
        The parsed document.
    base : Path, optional
        Unused for now (paths are relative to the working directory); kept for loaders that
        resolve paths against the file's folder.

    Raises
    ------
    ConfigError
        A value is missing, of the wrong type or out of range; the message names the key.
    """
    root = Section(data, "")

    plc = root.section("plc", required=False)
    host, port, unit_id = modbus_endpoint(plc, host="127.0.0.1", port=5020, unit_id=1, unit_hi=247)
    plc_cfg = PlcConfig(
        host=host,
        port=port,
        unit_id=unit_id,
        timeout_s=plc.number("timeout_s", 0.25, lo=0.0, lo_open=True, hi=60.0),
        backoff_initial_s=plc.number("backoff_initial_s", 0.05, lo=0.0, lo_open=True),
        backoff_max_s=plc.number("backoff_max_s", 2.0, lo=0.0, lo_open=True),
        registers=_path_or_none(plc, "registers", base),
    )
    if plc_cfg.backoff_max_s < plc_cfg.backoff_initial_s:
        raise ConfigError("plc.backoff_max_s must be >= plc.backoff_initial_s")
    plc.reject_unknown()

    can = root.section("can", required=False)
    interface, channel, options = can_bus_keys(can, interface="virtual", channel="planer")
    can_cfg = CanConfig(
        interface=interface,
        channel=channel,
        options=_frozen(options),
        command_period_s=can.number("command_period_s", 0.02, lo=0.0, lo_open=True, hi=0.05),
        offsets_period_s=can.number("offsets_period_s", 0.2, lo=0.0, lo_open=True, hi=10.0),
        dbc=_path_or_none(can, "dbc", base),
    )
    can.reject_unknown()

    fr = root.section("frames", required=False)
    frames_cfg = FramesConfig(
        source=fr.string("source", "spool", choices=FRAME_SOURCES),
        spool_dir=Path(fr.string("spool_dir", "runs/spool")),
        poll_s=fr.number("poll_s", 0.002, lo=0.0, lo_open=True, hi=1.0),
        pairs_per_s=fr.number("pairs_per_s", 10.0, lo=0.0, lo_open=True, hi=1000.0),
        image_width=fr.integer("image_width", 0, lo=0, hi=100_000),
        image_height=fr.integer("image_height", 0, lo=0, hi=100_000),
    )
    fr.reject_unknown()

    rig = None if root.string("rig", "") == "" else Path(root.string("rig"))

    q = root.section("quality", required=False)
    quality_cfg = QualityConfig(
        class_name=q.string("class_name", "fine-1.5"),
        target_pitch_mm=q.number("target_pitch_mm", 1.5, lo=0.0, lo_open=True, hi=20.0),
        tolerance=q.number("tolerance", 0.02, lo=0.0, lo_open=True, hi=1.0),
        uniformity_max_cv=q.number("uniformity_max_cv", 0.05, lo=0.0, lo_open=True),
        depth_max_um=q.number("depth_max_um", 20.0, lo=0.0, lo_open=True),
    )
    q.reject_unknown()

    pz = root.section("piezo", required=False)
    stroke_um = pz.number("stroke_um", 20.0, lo=0.0, lo_open=True, hi=32.767)
    pz.reject_unknown()

    feed_loop = _loop_table(root.section("feed_loop", required=False))
    uniformity_loop = _loop_table(root.section("uniformity_loop", required=False))

    pl = root.section("plausibility", required=False)
    plaus_cfg = PlausibilityConfig(
        pitch_ratio_min=pl.number("pitch_ratio_min", 0.5, lo=0.0, lo_open=True, hi=1.0),
        pitch_ratio_max=pl.number("pitch_ratio_max", 2.0, lo=1.0),
        min_marks=pl.integer("min_marks", 6, lo=2),
        min_confidence=pl.number("min_confidence", 0.3, lo=0.0, hi=1.0),
    )
    pl.reject_unknown()

    sf = root.section("safety", required=False)
    safety_cfg = SafetyConfig(
        cycle_s=sf.number("cycle_s", 0.02, lo=0.0, lo_open=True, hi=0.05),
        plc_timeout_s=sf.number("plc_timeout_s", 0.5, lo=0.0, lo_open=True),
        can_timeout_s=sf.number("can_timeout_s", 0.3, lo=0.0, lo_open=True),
        measurement_timeout_s=sf.number("measurement_timeout_s", 2.0, lo=0.0, lo_open=True),
        recovery_s=sf.number("recovery_s", 0.3, lo=0.0),
        safe_state=sf.string("safe_state", "ramp_down", choices=SAFE_STATES),
        safe_feed_mm_s=sf.number("safe_feed_mm_s", 400.0, lo=0.0),
        ramp_mm_s2=sf.number("ramp_mm_s2", 500.0, lo=0.0, lo_open=True),
    )
    for name in ("plc_timeout_s", "can_timeout_s"):
        if getattr(safety_cfg, name) <= safety_cfg.cycle_s:
            raise ConfigError(f"safety.{name} must be longer than safety.cycle_s")
    sf.reject_unknown()

    lg = root.section("log", required=False)
    log_cfg = LogConfig(
        path=Path(lg.string("path", "runs/quality.sqlite")),
        print_every=lg.integer("print_every", 20, lo=1),
    )
    lg.reject_unknown()

    root.reject_unknown()
    return MachineConfig(
        plc=plc_cfg,
        can=can_cfg,
        frames=frames_cfg,
        rig=rig,
        quality=quality_cfg,
        stroke_um=stroke_um,
        feed_loop=feed_loop,
        uniformity_loop=uniformity_loop,
        plausibility=plaus_cfg,
        safety=safety_cfg,
        log=log_cfg,
    )


def load_machine(path: str | Path | None = None) -> MachineConfig:
    """Load and check ``machine.toml`` (default: the shipped one); errors name file and key."""
    p = default_path("machine.toml") if path is None else Path(path)
    data = load_toml(p)
    try:
        return machine_from_dict(data, base=p.parent)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None


def registers_path(cfg: MachineConfig) -> Path:
    """The register map file this configuration uses."""
    return cfg.plc.registers or default_path("registers.toml")


def dbc_path(cfg: MachineConfig) -> Path:
    """The DBC file this configuration uses."""
    return cfg.can.dbc or default_path("piezo.dbc")


def rig_path(cfg: MachineConfig) -> Path:
    """The rig file this configuration uses."""
    return cfg.rig or default_path("rig.toml")
