"""The heads of a machine: one cutterhead (a planer) or several (a four-sided moulder).

A moulder has N heads (bottom, right, left, top, ...), each with its own spindle, knives,
camera, piezo amplifier (a CANopen node on the one CAN bus) and finish target, and one feed for
all. A file without ``[[heads]]`` has one head, ``"main"`` (face ``"top"``), built from its
existing tables, so every single-head file means what it meant before.

This module holds the service side's :class:`HeadConfig` (``[[heads]]`` of ``machine.toml``),
the names every head shares (:class:`Face`, :data:`HEAD_NAME`) and the checks of a list of heads
(unique names and node ids). :mod:`config.machine` builds ``MachineConfig.heads`` with it,
:mod:`config.sim` the simulator's heads. Errors are :class:`~core.errors.ConfigError` naming the
key and the bad value (``heads[2].rpm_min must be <= heads[2].rpm (6000.0), got 7000.0``).
"""

from __future__ import annotations

import enum
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from config.loading import Section
from core.errors import ConfigError

__all__ = [
    "DEFAULT_FACE",
    "DEFAULT_HEAD",
    "FACES",
    "HEAD_NAME",
    "Face",
    "HeadConfig",
    "check_head_name",
    "check_unique",
    "find_head",
    "head_identity",
    "head_sections",
    "head_table",
    "heads_from_toml",
    "rpm_range",
]

HEAD_NAME = re.compile(r"[a-z][a-z0-9_]*")
"""A head's name: lower-case letters, digits and ``_``, starting with a letter."""
DEFAULT_HEAD = "main"
"""The name of the one head of a file without ``[[heads]]``."""


class Face(str, enum.Enum):
    """The face of the workpiece a head cuts (the value is the name used in TOML and JSON)."""

    BOTTOM = "bottom"
    RIGHT = "right"
    LEFT = "left"
    TOP = "top"
    PROFILE = "profile"

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


FACES: tuple[str, ...] = tuple(f.value for f in Face)
"""Names of the faces: bottom, right, left, top, profile."""
DEFAULT_FACE = Face.TOP
"""The face of the single default head."""

MAX_KNIVES = 8
"""Most knives on a head (the amplifier's offset frames carry eight)."""


def check_head_name(name: Any, key: str) -> str:
    """``name`` if it is a head name (:data:`HEAD_NAME`); else ConfigError naming ``key``."""
    if not isinstance(name, str) or not HEAD_NAME.fullmatch(name):
        raise ConfigError(f"{key} must be a name of lower-case letters, digits and _ starting "
                          f"with a letter, got {name!r:.80}")
    return name


def rpm_range(rpm: float | None, rpm_min: float | None, rpm_max: float | None,
              key: str) -> tuple[float | None, float | None, float | None]:
    """A head's speeds ``(rpm, rpm_min, rpm_max)`` completed and checked.

    Parameters
    ----------
    rpm, rpm_min, rpm_max : float or None
        As given (``None``: not given).
    key : str
        The head's key in errors (``heads[2]``).

    Returns
    -------
    (rpm, rpm_min, rpm_max)
        A fixed head (``rpm`` alone) gets ``rpm_min == rpm_max == rpm``; a variable head
        (``rpm_min`` and ``rpm_max``) without ``rpm`` runs at ``rpm_max``; nothing given stays
        ``(None, None, None)`` (the PLC's).

    Raises
    ------
    ConfigError
        Only one of ``rpm_min``/``rpm_max``, or not ``rpm_min <= rpm <= rpm_max``.
    """
    if (rpm_min is None) != (rpm_max is None):
        given = "rpm_min" if rpm_min is not None else "rpm_max"
        other = "rpm_max" if rpm_min is not None else "rpm_min"
        raise ConfigError(f"{key}.{given} needs {key}.{other} too (a variable head gives both)")
    if rpm_min is None or rpm_max is None:
        return rpm, rpm, rpm
    if rpm_min > rpm_max:
        raise ConfigError(f"{key}.rpm_min must be <= {key}.rpm_max ({rpm_max!r}), got {rpm_min!r}")
    if rpm is None:
        rpm = rpm_max
    if rpm < rpm_min:
        raise ConfigError(f"{key}.rpm_min must be <= {key}.rpm ({rpm!r}), got {rpm_min!r}")
    if rpm > rpm_max:
        raise ConfigError(f"{key}.rpm_max must be >= {key}.rpm ({rpm!r}), got {rpm_max!r}")
    return rpm, rpm_min, rpm_max


@dataclass(frozen=True)
class HeadConfig:
    """One head as the service sees it (``[[heads]]`` of ``machine.toml``).

    Attributes
    ----------
    name : str
        Unique name (:data:`HEAD_NAME`), e.g. ``"top"``; ``"main"`` for a single head.
    face : Face
        The face it cuts (a name is looked up).
    position_mm : float
        Its place along the feed, mm from the first head (>= 0).
    knives : int or None
        Knives Z (1..8); ``None``: the PLC's ``knives``.
    radius_mm : float or None
        Tip radius, mm; ``None``: the PLC's ``cutterhead_radius_mm``.
    rpm, rpm_min, rpm_max : float or None
        Spindle speed and the range its setpoint may take (a fixed head: all three equal; see
        :func:`rpm_range`); ``None``: the PLC's.
    node_id : int
        Its piezo amplifier's CANopen node id (1..127), unique on the bus.
    target_pitch_mm : float
        The finish it holds: mm per knife mark.
    quality_class : str or None
        Its quality class name; ``None``: the machine's ``[quality] class_name``.
    uniformity_max_cv : float or None
        Its largest CV of the mark widths; ``None``: the machine's ``[quality]``.
    rig : Path or None
        Its rig file (camera, lights, encoder); ``None``: the shipped ``config/rig.toml``.
    spool_dir : Path or None
        Where its camera's pairs arrive; ``None``: the machine's ``[frames] spool_dir``.
    camera_id : str or None
        Its camera (Aravis device id); ``None``: the machine's ``[frames] camera_id``.

    Raises
    ------
    ConfigError
        A field out of range (the message names the head and the field); a file's errors name
        the key instead (:func:`heads_from_toml`).
    """

    name: str
    face: Face
    node_id: int
    target_pitch_mm: float
    position_mm: float = 0.0
    knives: int | None = None
    radius_mm: float | None = None
    rpm: float | None = None
    rpm_min: float | None = None
    rpm_max: float | None = None
    quality_class: str | None = None
    uniformity_max_cv: float | None = None
    rig: Path | None = None
    spool_dir: Path | None = None
    camera_id: str | None = None

    def __post_init__(self) -> None:
        key = f"head {self.name!s:.40}"
        check_head_name(self.name, f"{key}: name")
        try:
            object.__setattr__(self, "face", Face(self.face))
        except ValueError:
            raise ConfigError(f"{key}: face must be one of {', '.join(FACES)}, "
                              f"got {self.face!r}") from None
        if isinstance(self.node_id, bool) or not isinstance(self.node_id, int) \
                or not 1 <= self.node_id <= 127:
            raise ConfigError(f"{key}: node_id must be an integer in 1..127, got {self.node_id!r}")
        if self.knives is not None and not 1 <= self.knives <= MAX_KNIVES:
            raise ConfigError(f"{key}: knives must be in 1..{MAX_KNIVES}, got {self.knives!r}")
        for name in ("target_pitch_mm", "radius_mm", "uniformity_max_cv"):
            value = getattr(self, name)
            if value is not None and not value > 0.0:
                raise ConfigError(f"{key}: {name} must be > 0, got {value!r}")
        if not self.position_mm >= 0.0:
            raise ConfigError(f"{key}: position_mm must be >= 0, got {self.position_mm!r}")
        speeds = rpm_range(self.rpm, self.rpm_min, self.rpm_max, key)
        object.__setattr__(self, "rpm", speeds[0])
        object.__setattr__(self, "rpm_min", speeds[1])
        object.__setattr__(self, "rpm_max", speeds[2])

    @property
    def variable(self) -> bool:
        """Whether its spindle speed may be set (``rpm_min < rpm_max``)."""
        return (self.rpm_min is not None and self.rpm_max is not None
                and self.rpm_min < self.rpm_max)


def check_unique(values: Iterable[Any], what: str, key: str = "heads") -> None:
    """Raise ConfigError naming ``key[i].what`` for the first value given twice.

    ``values`` are each head's ``what`` in file order (e.g. every ``name`` or ``node_id``).
    """
    seen: dict[Any, int] = {}
    for i, value in enumerate(values):
        if value in seen:
            shown = repr(str(value) if isinstance(value, Path) else value)
            raise ConfigError(f"{key}[{i}].{what} must be unique: {shown} is also "
                              f"{key}[{seen[value]}].{what}")
        seen[value] = i


def find_head(heads: Iterable[Any], name: str) -> Any:
    """The head called ``name`` among ``heads`` (anything with a ``name``).

    Raises
    ------
    ConfigError
        No head of that name; the message lists the names.
    """
    heads = tuple(heads)
    for head in heads:
        if head.name == name:
            return head
    raise ConfigError(f"no head named {name!r}; the heads are "
                      f"{', '.join(h.name for h in heads)}")


_HEAD_KEYS = ("name", "face", "position_mm", "knives", "radius_mm", "rpm", "rpm_min", "rpm_max",
              "node_id", "target_pitch_mm", "quality_class", "uniformity_max_cv", "rig",
              "spool_dir", "camera_id")


def head_sections(raw: Any, key: str = "heads") -> list[Section]:
    """``[[heads]]`` as one :class:`~config.loading.Section` a head (``key[i]``), checked.

    Raises
    ------
    ConfigError
        Not a non-empty array of tables.
    """
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{key} must be a non-empty array of tables ([[{key}]]), "
                          f"got {raw!r:.80}")
    return [Section(item, f"{key}[{i}]") for i, item in enumerate(raw)]


def head_identity(t: Section) -> tuple[str, Face, float, int]:
    """The keys every head's table has, in ``machine.toml`` and ``sim.toml`` alike.

    ``(name, face, position_mm, node_id)``: its name (:data:`HEAD_NAME`), the face it cuts,
    its place along the feed (mm, default 0) and its amplifier's node id (1..127); errors name
    ``heads[i].key``.
    """
    name = check_head_name(t.raw("name"), t.key("name"))
    face = Face(t.string("face", choices=FACES))
    position_mm = t.number("position_mm", 0.0, lo=0.0, hi=100_000.0)
    return name, face, position_mm, t.integer("node_id", lo=1, hi=127)


def _head(t: Section, *, rig: Path | None, spool_dir: Path, camera_id: str,
          target_pitch_mm: float) -> HeadConfig:
    name, face, position_mm, node_id = head_identity(t)

    def opt_number(k: str, **bounds: Any) -> float | None:
        return t.number(k, **bounds) if t.has(k) else None

    rpm, rpm_min, rpm_max = rpm_range(
        opt_number("rpm", lo=100.0, hi=30000.0), opt_number("rpm_min", lo=100.0, hi=30000.0),
        opt_number("rpm_max", lo=100.0, hi=30000.0), t.prefix)
    rig_raw = t.string("rig", "")
    head = HeadConfig(
        name=name,
        face=face,
        position_mm=position_mm,
        knives=t.integer("knives", lo=1, hi=MAX_KNIVES) if t.has("knives") else None,
        radius_mm=opt_number("radius_mm", lo=5.0, hi=500.0),
        rpm=rpm, rpm_min=rpm_min, rpm_max=rpm_max,
        node_id=node_id,
        target_pitch_mm=t.number("target_pitch_mm", target_pitch_mm, lo=0.0, lo_open=True,
                                 hi=20.0),
        quality_class=t.string("quality_class") if t.has("quality_class") else None,
        uniformity_max_cv=opt_number("uniformity_max_cv", lo=0.0, lo_open=True),
        rig=Path(rig_raw).expanduser() if rig_raw else rig,
        spool_dir=Path(t.string("spool_dir", str(spool_dir / name))),
        camera_id=t.string("camera_id", camera_id),
    )
    if head.spool_dir == Path(""):
        raise ConfigError(f"{t.key('spool_dir')} must not be empty")
    t.reject_unknown()
    return head


def heads_from_toml(raw: Any, *, rig: Path | None, spool_dir: Path, camera_id: str,
                    target_pitch_mm: float, key: str = "heads") -> tuple[HeadConfig, ...]:
    """``[[heads]]`` of ``machine.toml``, checked (at least one head).

    Parameters
    ----------
    raw : list of tables
        The parsed array of tables.
    rig, camera_id, target_pitch_mm
        What a head that does not give its own takes (the file's ``rig``, ``[frames]
        camera_id``, ``[quality] target_pitch_mm``).
    spool_dir : Path
        The file's ``[frames] spool_dir``: a head without its own takes its subfolder named
        after the head (``runs/spool/top``), so two heads never share a spool.
    key : str
        The array's name in errors.

    Raises
    ------
    ConfigError
        Not a non-empty list of tables, a key missing, mistyped or out of range, unknown, or a
        name or node id given twice; the message names ``heads[i].key`` and the bad value.
    """
    out = tuple(_head(t, rig=rig, spool_dir=spool_dir, camera_id=camera_id,
                      target_pitch_mm=target_pitch_mm) for t in head_sections(raw, key))
    check_unique((h.name for h in out), "name", key)
    check_unique((h.node_id for h in out), "node_id", key)
    check_unique((h.spool_dir for h in out), "spool_dir", key)
    return out


def head_table(head: HeadConfig) -> Mapping[str, Any]:
    """``head`` as a ``[[heads]]`` table (the keys :func:`heads_from_toml` reads back)."""
    out: dict[str, Any] = {}
    for k in _HEAD_KEYS:
        v = getattr(head, k)
        if v is None:
            continue
        out[k] = v.value if isinstance(v, Face) else str(v) if isinstance(v, Path) else v
    return out
