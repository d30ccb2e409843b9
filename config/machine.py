"""The service's configuration (``config/machine.toml``) as frozen, validated dataclasses.

One file says where the PLC and the piezo amplifier are, where the image pairs come from, which
quality class to hold and how to behave when something is gone. The same service runs against
the simulator and against the real machine by changing this file only (e.g. ``can.interface =
"socketcan"``, ``can.channel = "can0"``, ``plc.host`` = the PLC's address).

A file (:func:`load_machine`) gives only what it changes: its tables are deep-merged over the
shipped ``config/machine.toml`` (:func:`config.loading.over_shipped`). Every wrong value raises
:class:`core.errors.ConfigError` naming the key (``"safety.plc_timeout_s must be > 0"``);
unknown keys are rejected (typos).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from config.heads import DEFAULT_FACE, DEFAULT_HEAD, HeadConfig, find_head, heads_from_toml
from config.loading import (
    LOOPBACK_HOST,
    MODBUS_PORT,
    SPOOL_DIR,
    Section,
    can_bus_keys,
    default_path,
    load_toml,
    modbus_endpoint,
    naming_file,
    over_shipped,
)
from core.errors import ConfigError

FRAME_SOURCES = ("spool", "inprocess", "camera")
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

    host: str = LOOPBACK_HOST
    port: int = MODBUS_PORT
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
        Period of the amplifier's command (RPDO3: enable, knives, alive counter), seconds.
    offsets_period_s : float
        The offset table (RPDO1/2) is sent on change and at least this often, seconds.
    node_id : int
        The piezo amplifier's CANopen node id (1..127).
    eds : Path or None
        The amplifier's EDS file; ``None`` means the shipped ``config/piezo_amp.eds``.
    """

    interface: str = "virtual"
    channel: str = "planer"
    options: Mapping[str, Any] = field(default_factory=_frozen)
    command_period_s: float = 0.02
    offsets_period_s: float = 0.2
    node_id: int = 2
    eds: Path | None = None


@dataclass(frozen=True)
class FramesConfig:
    """Where image pairs come from: a spool directory (camera process) or in-process.

    ``pairs_per_s`` is the camera's nominal rate (the control loops' sample time);
    ``image_width`` x ``image_height`` the camera's image size, pixels, so the measurement is
    set up before the first pair arrives (0: on the first pair).
    """

    source: str = "spool"
    spool_dir: Path = Path(SPOOL_DIR)
    poll_s: float = 0.002
    pairs_per_s: float = 10.0
    image_width: int = 0
    image_height: int = 0
    # source = "camera" (docs/camera.md): Aravis device id and GenICam settings
    camera_id: str = ""
    exposure_us: float = 0.0  # 0: the rig's exposure_ms, else the camera's
    fake_exposure_us: float = 0.0  # Aravis' fake cameras (Fake_*) when exposure_us is 0
    gain_db: float = 0.0
    trigger_source: str = "Line1"  # PLC trigger line; "Software" for tests
    packet_size: int = 0  # GigE Vision packet size, bytes; 0: negotiated

    @property
    def image_shape(self) -> tuple[int, int] | None:
        """``(image_height, image_width)``, pixels, when both are set; else ``None``."""
        if self.image_width > 0 and self.image_height > 0:
            return (self.image_height, self.image_width)
        return None


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
    board_length_mm: float = 4000.0
    """A typical board, mm: the knife condition's forecast in boards."""
    defects: bool = False
    """Look for planing defects on every pair (the vision's defect detector: a nicked knife
    is told at once, ``KNIFE_CHIPPED``); costs CPU per pair (docs/vision.md)."""


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
    pitch_tolerance : float
        Largest relative difference between the measured pitch per knife pass and the feed
        per pass the PLC reports, ``V / (n Z)`` (feed and spindle steady since the cut);
        beyond it the pair is flagged and kept out of the loops. The default 0.01 is the
        budget of what the two legitimately differ by: the spindle's load ripple (0.1 %) and
        droop (0.2 %) between the cut and the PLC's reading, the feed encoder's slip against
        the board (belt-driven table, 0.5 %) and the measured pitch's own error (0.2 %).
    pass_tolerance : float
        Relative margin around the range of the feed per pass when the marks were cut
        (:mod:`controller.service.cut_feed`) within which the knife-phase fit's travel per pass
        must lie, else the pair's attribution is refused. The default 0.03 is 2.5 times the
        budget of what the two legitimately differ by (the speed read per pair 0.2 %, spindle
        ripple and droop 0.3 %, encoder slip 0.5 %, the fit's own error 0.2 %); at most
        :data:`MAX_PASS_TOLERANCE`, half the nearest miscounted fit, ``Z / (Z + 1)`` of the
        true travel at 8 knives (11 % off).
    """

    pitch_ratio_min: float = 0.5
    pitch_ratio_max: float = 2.0
    min_marks: int = 6
    min_confidence: float = 0.3
    pitch_tolerance: float = 0.01
    pass_tolerance: float = 0.03


MAX_PASS_TOLERANCE = 0.055
"""Largest ``[plausibility] pass_tolerance``: under half the gap to a fit that counted one
pass too many per revolution, ``1 - Z / (Z + 1)`` = 11.1 % at the most knives (8)."""


@dataclass(frozen=True)
class SafetyConfig:
    """Timeouts and the safe-state action of the supervisor (seconds, mm/s).

    See :mod:`controller.service.supervisor`.
    """

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
    machine_id: str = ""
    """``[machine] id``: names this machine's records in a shared quality log ("" = host name)."""


@dataclass(frozen=True)
class ServiceConfig:
    """``[service]``: how the service runs (``docs/service.md``, "Workers").

    ``workers``: measure in this many worker processes (0: in the service's own process, a
    worker thread); more than the cores available is a warning and one process per core.
    ``cpu_latency_us``: while ``planer serve`` runs, no core takes longer than this to wake
    (PM QoS, :func:`core.realtime.cpu_wakeup_latency`; 0: idle cores poll; -1: as the system
    has it). Needs root; otherwise the service says so and runs as the system has it.
    """

    workers: int = 0
    cpu_latency_us: int = 0


@dataclass(frozen=True)
class OpcUaConfig:
    """``[opcua]``: the OPC UA server (``docs/opcua.md``); off while ``endpoint`` is empty.

    ``certificate`` / ``private_key`` (Basic256Sha256 SignAndEncrypt) and ``users_file`` (user
    names and password hashes) are required to bind anything but a loopback address.
    """

    endpoint: str = ""
    certificate: Path | None = None
    private_key: Path | None = None
    users_file: Path | None = None


@dataclass(frozen=True)
class HttpConfig:
    """``[http]``: the operator and quality web pages (``docs/web.md``).

    Off while ``listen`` is empty; e.g. ``listen = "127.0.0.1:8080"``.
    """

    listen: str = ""


IDENTIFICATION_KEYS = (
    "Manufacturer", "Model", "SerialNumber", "ProductInstanceUri", "DeviceClass",
    "YearOfConstruction", "MonthOfConstruction", "ManufacturerUri", "ProductCode",
    "HardwareRevision", "SoftwareRevision", "AssetId", "ComponentName", "Location",
)
"""``[identification]`` keys (OPC UA Machinery ``Identification``; the years/months integers)."""


def _opcua_tables(root: Section) -> tuple[OpcUaConfig, Mapping[str, Any]]:
    op = root.section("opcua", required=False)
    endpoint = op.string("endpoint", "")
    if endpoint and not endpoint.startswith("opc.tcp://"):
        raise ConfigError(f"{op.key('endpoint')} must look like opc.tcp://127.0.0.1:4840")
    opcua = OpcUaConfig(endpoint=endpoint, certificate=_path_or_none(op, "certificate", None),
                        private_key=_path_or_none(op, "private_key", None),
                        users_file=_path_or_none(op, "users_file", None))
    op.reject_unknown()
    idn = root.section("identification", required=False)
    ident: dict[str, Any] = {}
    for key in IDENTIFICATION_KEYS:
        if idn.raw(key, None) is None:
            continue
        if key in ("YearOfConstruction", "MonthOfConstruction"):
            ident[key] = idn.integer(key, lo=1, hi=12 if key == "MonthOfConstruction" else 65535)
        else:
            ident[key] = idn.string(key)
    idn.reject_unknown()
    return opcua, _frozen(ident)


@dataclass(frozen=True)
class MachineConfig:
    """The whole ``machine.toml``.

    ``feed_loop`` and ``uniformity_loop`` hold the raw (validated numeric) keys of those tables;
    :mod:`controller.service.service` passes them to the control laws' own configuration classes,
    whose
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
    opcua: OpcUaConfig = OpcUaConfig()
    http: HttpConfig = HttpConfig()
    identification: Mapping[str, Any] = field(default_factory=_frozen)
    service: ServiceConfig = ServiceConfig()
    declared_heads: tuple[HeadConfig, ...] = ()
    """``[[heads]]`` as the file gives them; ``()`` for a single-head file (see :attr:`heads`)."""
    source: Path | None = field(default=None, compare=False)
    """The file this configuration was loaded from (``None``: built in code). Code that checks
    the raw ``feed_loop`` / ``uniformity_loop`` tables later names it with
    ``with config.loading.naming_file(cfg.source): ...``."""

    @property
    def heads(self) -> tuple[HeadConfig, ...]:
        """The machine's heads in file order: ``[[heads]]``, else the one head ``"main"``.

        The single head of a file without ``[[heads]]`` is :func:`default_head` of this
        configuration's own tables, so it follows every change of them.
        """
        return self.declared_heads or (default_head(self),)

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


def _plc_table(root: Section, d: MachineConfig, base: Path | None) -> PlcConfig:
    """``[plc]``, checked (defaults: the dataclass fields)."""
    plc = root.section("plc", required=False)
    dp = d.plc
    host, port, unit_id = modbus_endpoint(
        plc, host=dp.host, port=dp.port, unit_id=dp.unit_id, unit_hi=247
    )
    plc_cfg = PlcConfig(
        host=host,
        port=port,
        unit_id=unit_id,
        timeout_s=plc.number("timeout_s", dp.timeout_s, lo=0.0, lo_open=True, hi=60.0),
        backoff_initial_s=plc.number(
            "backoff_initial_s", dp.backoff_initial_s, lo=0.0, lo_open=True
        ),
        backoff_max_s=plc.number("backoff_max_s", dp.backoff_max_s, lo=0.0, lo_open=True),
        registers=_path_or_none(plc, "registers", base),
    )
    if plc_cfg.backoff_max_s < plc_cfg.backoff_initial_s:
        raise ConfigError("plc.backoff_max_s must be >= plc.backoff_initial_s")
    plc.reject_unknown()

    return plc_cfg


def _can_table(root: Section, d: MachineConfig, base: Path | None) -> CanConfig:
    """``[can]``, checked (defaults: the dataclass fields)."""
    can = root.section("can", required=False)
    dc = d.can
    interface, channel, options = can_bus_keys(can, interface=dc.interface, channel=dc.channel)
    can_cfg = CanConfig(
        interface=interface,
        channel=channel,
        options=_frozen(options),
        command_period_s=can.number(
            "command_period_s", dc.command_period_s, lo=0.0, lo_open=True, hi=0.05
        ),
        offsets_period_s=can.number(
            "offsets_period_s", dc.offsets_period_s, lo=0.0, lo_open=True, hi=10.0
        ),
        node_id=can.integer("node_id", dc.node_id, lo=1, hi=127),
        eds=_path_or_none(can, "eds", base),
    )
    if _path_or_none(can, "dbc", base) is not None:  # "" (as once shipped) is let through
        raise ConfigError(f"{can.key('dbc')}: the amplifier is a CANopen node described by its "
                          f"EDS file: set {can.key('eds')} (\"\" = config/piezo_amp.eds)")
    can.reject_unknown()

    return can_cfg


def _frames_table(root: Section, d: MachineConfig) -> FramesConfig:
    """``[frames]``, checked (defaults: the dataclass fields)."""
    fr = root.section("frames", required=False)
    df = d.frames
    frames_cfg = FramesConfig(
        source=fr.string("source", df.source, choices=FRAME_SOURCES),
        spool_dir=Path(fr.string("spool_dir", str(df.spool_dir))),
        poll_s=fr.number("poll_s", df.poll_s, lo=0.0, lo_open=True, hi=1.0),
        pairs_per_s=fr.number("pairs_per_s", df.pairs_per_s, lo=0.0, lo_open=True, hi=1000.0),
        image_width=fr.integer("image_width", df.image_width, lo=0, hi=100_000),
        image_height=fr.integer("image_height", df.image_height, lo=0, hi=100_000),
        camera_id=fr.string("camera_id", df.camera_id),
        exposure_us=fr.number("exposure_us", df.exposure_us, lo=0.0, hi=1e7),
        fake_exposure_us=fr.number("fake_exposure_us", df.fake_exposure_us, lo=0.0, hi=1e7),
        gain_db=fr.number("gain_db", df.gain_db, lo=0.0, hi=100.0),
        trigger_source=fr.string("trigger_source", df.trigger_source),
        packet_size=fr.integer("packet_size", df.packet_size, lo=0, hi=16_384),
    )
    fr.reject_unknown()

    return frames_cfg


def _quality_table(root: Section, d: MachineConfig) -> QualityConfig:
    """``[quality]``, checked (defaults: the dataclass fields)."""
    q = root.section("quality", required=False)
    dq = d.quality
    quality_cfg = QualityConfig(
        class_name=q.string("class_name", dq.class_name),
        target_pitch_mm=q.number(
            "target_pitch_mm", dq.target_pitch_mm, lo=0.0, lo_open=True, hi=20.0
        ),
        tolerance=q.number("tolerance", dq.tolerance, lo=0.0, lo_open=True, hi=1.0),
        uniformity_max_cv=q.number(
            "uniformity_max_cv", dq.uniformity_max_cv, lo=0.0, lo_open=True
        ),
        depth_max_um=q.number("depth_max_um", dq.depth_max_um, lo=0.0, lo_open=True),
        board_length_mm=q.number("board_length_mm", dq.board_length_mm, lo=0.0, lo_open=True,
                                 hi=100_000.0),
        defects=q.boolean("defects", dq.defects),
    )
    q.reject_unknown()

    return quality_cfg


def _plausibility_table(root: Section, d: MachineConfig) -> PlausibilityConfig:
    """``[plausibility]``, checked (defaults: the dataclass fields)."""
    pl = root.section("plausibility", required=False)
    dl = d.plausibility
    plaus_cfg = PlausibilityConfig(
        pitch_ratio_min=pl.number(
            "pitch_ratio_min", dl.pitch_ratio_min, lo=0.0, lo_open=True, hi=1.0
        ),
        pitch_ratio_max=pl.number("pitch_ratio_max", dl.pitch_ratio_max, lo=1.0),
        min_marks=pl.integer("min_marks", dl.min_marks, lo=2),
        min_confidence=pl.number("min_confidence", dl.min_confidence, lo=0.0, hi=1.0),
        pitch_tolerance=pl.number("pitch_tolerance", dl.pitch_tolerance, lo=0.0, lo_open=True,
                                  hi=0.5),
        pass_tolerance=pl.number("pass_tolerance", dl.pass_tolerance, lo=0.0, lo_open=True,
                                 hi=MAX_PASS_TOLERANCE),
    )
    pl.reject_unknown()

    return plaus_cfg


def _safety_table(root: Section, d: MachineConfig) -> SafetyConfig:
    """``[safety]``, checked (defaults: the dataclass fields)."""
    sf = root.section("safety", required=False)
    ds = d.safety
    safety_cfg = SafetyConfig(
        cycle_s=sf.number("cycle_s", ds.cycle_s, lo=0.0, lo_open=True, hi=0.05),
        plc_timeout_s=sf.number("plc_timeout_s", ds.plc_timeout_s, lo=0.0, lo_open=True),
        can_timeout_s=sf.number("can_timeout_s", ds.can_timeout_s, lo=0.0, lo_open=True),
        measurement_timeout_s=sf.number(
            "measurement_timeout_s", ds.measurement_timeout_s, lo=0.0, lo_open=True
        ),
        recovery_s=sf.number("recovery_s", ds.recovery_s, lo=0.0),
        safe_state=sf.string("safe_state", ds.safe_state, choices=SAFE_STATES),
        safe_feed_mm_s=sf.number("safe_feed_mm_s", ds.safe_feed_mm_s, lo=0.0),
        ramp_mm_s2=sf.number("ramp_mm_s2", ds.ramp_mm_s2, lo=0.0, lo_open=True),
    )
    for name in ("plc_timeout_s", "can_timeout_s"):
        if getattr(safety_cfg, name) <= safety_cfg.cycle_s:
            raise ConfigError(f"safety.{name} must be longer than safety.cycle_s")
    sf.reject_unknown()

    return safety_cfg


def _log_table(root: Section, d: MachineConfig) -> LogConfig:
    """``[log]`` and ``[machine]``, checked (defaults: the dataclass fields)."""
    lg = root.section("log", required=False)
    log_cfg = LogConfig(
        path=Path(lg.string("path", str(d.log.path))),
        print_every=lg.integer("print_every", d.log.print_every, lo=1),
    )
    lg.reject_unknown()
    mc = root.section("machine", required=False)  # [machine] id: stamped on quality records
    mid = mc.string("id", d.log.machine_id)
    if mid and (len(mid) > 64 or not mid.isprintable() or mid != mid.strip()):
        raise ConfigError(f"{mc.key('id')} must be 1..64 printable characters, got {mid!r:.80}")
    log_cfg = replace(log_cfg, machine_id=mid)
    mc.reject_unknown()
    return log_cfg


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
    # every default is the dataclass field's own (written once, in the classes above)
    d = MachineConfig()

    plc_cfg = _plc_table(root, d, base)
    can_cfg = _can_table(root, d, base)
    frames_cfg = _frames_table(root, d)
    rig = None if root.string("rig", "") == "" else Path(root.string("rig"))

    quality_cfg = _quality_table(root, d)
    pz = root.section("piezo", required=False)
    stroke_um = pz.number("stroke_um", d.stroke_um, lo=0.0, lo_open=True, hi=32.767)
    pz.reject_unknown()

    feed_loop = _loop_table(root.section("feed_loop", required=False))
    uniformity_loop = _loop_table(root.section("uniformity_loop", required=False))

    plaus_cfg = _plausibility_table(root, d)
    safety_cfg = _safety_table(root, d)
    log_cfg = _log_table(root, d)
    opcua_cfg, identification = _opcua_tables(root)
    ht = root.section("http", required=False)
    listen = ht.string("listen", "")
    if listen and not re.fullmatch(r"(\[[0-9A-Fa-f:.]+\]|[^\s:\[\]]+):[0-9]{1,5}", listen):
        raise ConfigError(f"{ht.key('listen')} must look like 127.0.0.1:8080, got {listen!r:.80}")
    ht.reject_unknown()
    sv = root.section("service", required=False)
    service_cfg = ServiceConfig(
        workers=sv.integer("workers", d.service.workers, lo=0, hi=256),
        cpu_latency_us=sv.integer("cpu_latency_us", d.service.cpu_latency_us, lo=-1,
                                  hi=1_000_000))
    sv.reject_unknown()

    heads = () if root.raw("heads", None) is None else heads_from_toml(
        root.raw("heads"), rig=rig, spool_dir=frames_cfg.spool_dir,
        camera_id=frames_cfg.camera_id, target_pitch_mm=quality_cfg.target_pitch_mm)
    if len(heads) > 1 and frames_cfg.source == "camera":
        # each camera's pairs need its own head's trigger latches, which the camera source
        # does not read yet: the heads' pairs come through their spools
        raise ConfigError(
            f"frames.source = 'camera' with {len(heads)} [[heads]]: a moulder's heads "
            "read their pairs from their spools (heads[i].spool_dir); cameras read directly "
            "per head are not supported yet")

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
        opcua=opcua_cfg,
        http=HttpConfig(listen=listen),
        identification=identification,
        service=service_cfg,
        declared_heads=heads,
    )


def default_head(cfg: MachineConfig) -> HeadConfig:
    """The one head ``"main"`` (face ``"top"``) of a configuration without ``[[heads]]``.

    Built from the existing keys: ``[quality] target_pitch_mm``, ``[can] node_id``, ``rig``,
    ``[frames] spool_dir`` and ``camera_id``; knives, radius and speeds are the PLC's.
    """
    return HeadConfig(name=DEFAULT_HEAD, face=DEFAULT_FACE, node_id=cfg.can.node_id,
                      target_pitch_mm=cfg.quality.target_pitch_mm, rig=cfg.rig,
                      spool_dir=cfg.frames.spool_dir, camera_id=cfg.frames.camera_id)


def head_config(cfg: MachineConfig, name: str) -> MachineConfig:
    """A single-head configuration for the head called ``name`` (its own ``Service``).

    Parameters
    ----------
    cfg : MachineConfig
        The machine's configuration.
    name : str
        One of ``cfg.heads``' names.

    Returns
    -------
    MachineConfig
        ``cfg`` with ``heads == (head,)`` and the head's target pitch, quality class and
        uniformity limit (``[quality]``), amplifier node id (``[can] node_id``), rig and
        ``[frames] spool_dir`` / ``camera_id``; every other table (the log too) unchanged.
        For a single-head file ``head_config(cfg, "main") == cfg``.

    Raises
    ------
    ConfigError
        No head of that name.
    """
    head: HeadConfig = find_head(cfg.heads, name)
    q = cfg.quality
    quality = replace(
        q, target_pitch_mm=head.target_pitch_mm,
        class_name=q.class_name if head.quality_class is None else head.quality_class,
        uniformity_max_cv=(q.uniformity_max_cv if head.uniformity_max_cv is None
                           else head.uniformity_max_cv))
    frames = replace(
        cfg.frames,
        spool_dir=cfg.frames.spool_dir if head.spool_dir is None else head.spool_dir,
        camera_id=cfg.frames.camera_id if head.camera_id is None else head.camera_id)
    return replace(cfg, quality=quality, can=replace(cfg.can, node_id=head.node_id),
                   rig=head.rig, frames=frames,
                   declared_heads=(head,) if cfg.declared_heads else ())


def load_machine(path: str | Path | None = None) -> MachineConfig:
    """Load and check ``machine.toml`` (default: the shipped one); errors name file and key."""
    p = default_path("machine.toml") if path is None else Path(path)
    data = load_toml(p)
    with naming_file(p):  # over the shipped machine.toml: a file gives only what it changes
        data = over_shipped(data, "machine.toml")
        return replace(machine_from_dict(data, base=p.parent), source=p)


def registers_path(cfg: MachineConfig) -> Path:
    """The register map file this configuration uses."""
    return cfg.plc.registers or default_path("registers.toml")


def eds_path(cfg: MachineConfig) -> Path:
    """The amplifier's EDS file this configuration uses."""
    return cfg.can.eds or default_path("piezo_amp.eds")


def rig_path(cfg: MachineConfig) -> Path:
    """The rig file this configuration uses."""
    return cfg.rig or default_path("rig.toml")
