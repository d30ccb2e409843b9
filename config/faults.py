"""The fault registry: every fault the simulated planer can suffer, its parameters, who plays it.

One :class:`FaultKind` per fault, each with

* its parameters (:class:`FaultParam`: unit, range, required or with a default);
* whether it is an **interface** fault (the Modbus server or the CAN node misbehave; played by
  whoever drives the interfaces: ``plant_sim.run.runner`` or the in-process HIL plant) or a
  **machine** fault (the :class:`plant_sim.machine.machine.Machine` model applies it);
* the service condition it should trip (``modbus_restart`` -> ``plc``; names of
  ``controller.service.supervisor.SOURCES``), ``None`` when the service should ride it out (a belt
  slip, a
  knot: one odd measurement, no safe state). The HIL summary's fault report judges against it.

Parsing and validation of a fault table (``[faults] inject`` of ``config/sim.toml``,
``faults = [...]`` of a ``config/hil.toml`` scenario) happen here, once: :func:`parse_fault`,
:func:`parse_faults`. Errors are :class:`~core.errors.ConfigError` naming the key
(``faults.inject[0].duration_s is required for can_silence``).
"""

from __future__ import annotations

import enum
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from config.heads import check_head_name
from config.wood import SPECIES as WOOD_SPECIES
from core.errors import ConfigError

__all__ = [
    "AT_S",
    "FAULT_KINDS",
    "INTERFACE_FAULTS",
    "Fault",
    "check_fault_head",
    "FaultKind",
    "FaultParam",
    "parse_fault",
    "parse_faults",
]


@dataclass(frozen=True)
class FaultParam:
    """One parameter of a fault kind.

    Attributes
    ----------
    name : str
        Key in the fault table (unit in the name where it has one).
    unit : str
        Unit (``"s"``, ``"px"``, ``"counts"``, ``"mm"``, ``"um"``, ``""``).
    doc : str
        What it means.
    lo, hi : float
        Allowed range (``lo_open``: ``lo`` itself excluded).
    lo_open : bool
        Whether ``lo`` is excluded.
    integer : bool
        Whether the value must be a whole number.
    default : float or str or None
        Value when not given; ``None`` with ``required`` false: the model picks (see ``doc``).
    required : bool
        Whether the table must give it.
    choices : tuple of str
        For a parameter that is a name, not a number: the names allowed (empty: a number).
    """

    name: str
    unit: str
    doc: str
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    integer: bool = False
    default: float | str | None = None
    required: bool = False
    choices: tuple[str, ...] = ()

    def check(self, value: Any, key: str) -> float | int | str:
        """``value`` in range (a name among ``choices``); :class:`ConfigError` naming ``key``."""
        if self.choices:
            if not isinstance(value, str) or value not in self.choices:
                raise ConfigError(f"{key} must be one of {', '.join(self.choices)}, got {value!r}")
            return value
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ConfigError(f"{key} must be a number, got {value!r}")
        v = float(value)
        if not math.isfinite(v):
            raise ConfigError(f"{key} must be finite, got {value!r}")
        if v < self.lo or (self.lo_open and v == self.lo) or v > self.hi:
            lo = "(" if self.lo_open else "["
            raise ConfigError(
                f"{key} must be in {lo}{self.lo:g}, {self.hi:g}]"
                f"{' ' + self.unit if self.unit else ''}, got {value!r}"
            )
        if self.integer and v != int(v):
            raise ConfigError(f"{key} must be a whole number, got {value!r}")
        return int(v) if self.integer else v


AT_S = FaultParam("at_s", "s", "machine time at which the fault acts (absent: now)", lo=0.0)
"""The parameter every fault has."""

_DURATION = "how long the fault lasts"


@dataclass(frozen=True)
class _Spec:
    params: tuple[FaultParam, ...] = ()
    interface: bool = False
    trips: str | None = None
    doc: str = ""
    exclusive: tuple[str, ...] = ()


_SPECS: dict[str, _Spec] = {
    "belt_slip": _Spec(
        (FaultParam("px", "px", "encoder lie between triggers A and B of the next pair "
                    "(default 12 px)", default=12.0),
         FaultParam("counts", "counts", "the same lie in encoder counts (instead of px)",
                    integer=True)),
        doc="the feed belt slips: the encoder gains counts the board did not travel",
        exclusive=("px", "counts"),
    ),
    "encoder_wrap": _Spec(
        (FaultParam("counts_before_wrap", "counts", "counts from now until the 32-bit counter "
                    "wraps", lo=1.0, hi=float(2**32 - 1), integer=True, default=2000.0),),
        doc="the encoder counter is preset to wrap soon",
    ),
    "encoder_fault": _Spec(doc="the encoder counter stops (PLC faults bit 2) until a reset"),
    "knot": _Spec(
        (FaultParam("board_id", "", "board (default the next one)", lo=1.0, integer=True),
         FaultParam("at_mm", "mm", "from the board's leading end", lo=0.0, default=1000.0),
         FaultParam("length_mm", "mm", "along the board", lo=0.0, lo_open=True, default=40.0),
         FaultParam("width_mm", "mm", "across the board", lo=0.0, lo_open=True, default=30.0),
         FaultParam("y_mm", "mm", "across, from the centre line", default=0.0),
         FaultParam("darkness", "", "0 none .. 1 black", lo=0.0, hi=1.0, default=0.6),
         FaultParam("roughness_um", "µm", "surface roughness", lo=0.0, default=4.0)),
        doc="a dark, rough patch on a board",
    ),
    "spindle_stop": _Spec(trips="machine", doc="the spindle drive trips and coasts down"),
    "estop": _Spec(trips="machine", doc="e-stop: spindle braked, feed stopped, amplifier off"),
    "feed_fault": _Spec(doc="the feed drive trips (PLC faults bit 0) and stops"),
    "piezo_fault": _Spec(
        (FaultParam("bit", "", "amplifier fault bit (3 overcurrent)", lo=0.0, hi=7.0,
                    integer=True, default=3.0),),
        trips="amplifier", doc="the piezo amplifier faults (state 3, output zero)",
    ),
    "can_drop": _Spec(
        (FaultParam("duration_s", "s", _DURATION, lo=0.0, lo_open=True, required=True),
         FaultParam("fraction", "", "share of the frames to the amplifier lost", lo=0.0,
                    lo_open=True, hi=1.0, default=1.0)),
        interface=True, doc="frames to the piezo amplifier are lost on the bus",
    ),
    "modbus_restart": _Spec(
        (FaultParam("duration_s", "s", "how long the server stays closed", lo=0.0,
                    required=True),),
        interface=True, trips="plc",
        doc="the PLC's Modbus server closes (every client dropped), then listens again",
    ),
    "can_silence": _Spec(
        (FaultParam("duration_s", "s", _DURATION, lo=0.0, lo_open=True, required=True),),
        interface=True, trips="can", doc="the piezo amplifier sends nothing",
    ),
    "reset": _Spec(doc="fault reset: clears the e-stop and the drive faults"),
    "knife_chip": _Spec(
        (FaultParam("knife", "", "the knife that chips (0 = the index knife)", lo=0.0, hi=7.0,
                    integer=True, default=0.0),
         FaultParam("step_um", "µm", "its runout steps by this much (> 0: it stands further "
                    "out and cuts deeper, as a knife that moved; < 0: a chip takes material "
                    "off its edge)", lo=-50.0, hi=50.0, default=6.0),
         FaultParam("at_travel_mm", "mm", "the table's travel at which it happens (instead of "
                    "at_s)", lo=0.0)),
        doc="a knife chips or moves: a step of its runout, at a time or a distance",
    ),
    "species_change": _Spec(
        (FaultParam("species", "", "the wood of the boards from then on", required=True,
                    choices=tuple(sorted(WOOD_SPECIES))),
         FaultParam("board_id", "", "the first board of the new wood (default the next one)",
                    lo=1.0, integer=True)),
        doc="the wood changes between two boards (its texture, albedo, translucency)",
    ),
    "camera_silent": _Spec(
        (FaultParam("duration_s", "s", _DURATION, lo=0.0, lo_open=True, required=True),),
        trips="measurement",
        doc="the camera sends no pair at all (a moulder: one head's camera; the service's "
            "measurement timeout while a board passes)",
    ),
    "measurement_dropout": _Spec(
        (FaultParam("duration_s", "s", _DURATION, lo=0.0, lo_open=True, required=True),
         FaultParam("fraction", "", "share of the pairs hit", lo=0.0, lo_open=True, hi=1.0,
                    default=0.5),
         FaultParam("spoil", "", "0: the pairs hit are lost (never delivered); 1: they arrive "
                    "spoiled (light B did not fire)", lo=0.0, hi=1.0, integer=True,
                    default=0.0)),
        doc="a share of the image pairs is lost or spoiled for a while (camera or lights)",
    ),
}


class FaultKind(str, enum.Enum):
    """The kinds of faults (the value is the name used in TOML tables and JSON).

    A ``str`` enum: ``FaultKind.CAN_SILENCE == "can_silence"``, and it formats as its name.
    """

    BELT_SLIP = "belt_slip"
    ENCODER_WRAP = "encoder_wrap"
    ENCODER_FAULT = "encoder_fault"
    KNOT = "knot"
    SPINDLE_STOP = "spindle_stop"
    ESTOP = "estop"
    FEED_FAULT = "feed_fault"
    PIEZO_FAULT = "piezo_fault"
    CAN_DROP = "can_drop"
    MODBUS_RESTART = "modbus_restart"
    CAN_SILENCE = "can_silence"
    RESET = "reset"
    KNIFE_CHIP = "knife_chip"
    SPECIES_CHANGE = "species_change"
    MEASUREMENT_DROPOUT = "measurement_dropout"
    CAMERA_SILENT = "camera_silent"

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)

    @property
    def params(self) -> tuple[FaultParam, ...]:
        """The kind's parameters (``at_s`` not included: every kind has it)."""
        return _SPECS[self.value].params

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of :attr:`params`."""
        return tuple(p.name for p in self.params)

    @property
    def required(self) -> tuple[str, ...]:
        """Names of the parameters a table must give."""
        return tuple(p.name for p in self.params if p.required)

    @property
    def interface(self) -> bool:
        """Whether the Modbus server or the CAN node plays it (not the machine model)."""
        return _SPECS[self.value].interface

    @property
    def trips(self) -> str | None:
        """The service condition it should trip (``"plc"``, ``"can"``, ...), or ``None``."""
        return _SPECS[self.value].trips

    @property
    def lasts(self) -> bool:
        """Whether it has a ``duration_s`` (ends by itself)."""
        return "duration_s" in self.param_names

    @property
    def doc(self) -> str:
        """What it does, one line."""
        return _SPECS[self.value].doc

    @classmethod
    def parse(cls, name: Any, *, key: str = "kind") -> FaultKind:
        """The kind called ``name``; :class:`ConfigError` naming ``key`` and the kinds if none."""
        try:
            return cls(name)
        except ValueError:
            raise ConfigError(
                f"{key} must be one of {', '.join(FAULT_KINDS)}; got {name!r}"
            ) from None

    def check(self, params: Mapping[str, Any], *, key: str | None = None) -> dict[str, Any]:
        """The parameters checked (``at_s`` allowed, defaults not filled in).

        Parameters
        ----------
        params : mapping
            Parameter name to value.
        key : str, optional
            Prefix of the names in errors (default the kind's name).

        Raises
        ------
        ConfigError
            An unknown parameter, a required one missing, a value not a finite number, out of
            its range or not whole, two exclusive ones together.
        """
        prefix = key if key is not None else self.value
        spec = _SPECS[self.value]
        by_name = {p.name: p for p in spec.params}
        out: dict[str, float] = {}
        for name, value in params.items():
            p = AT_S if name == "at_s" else by_name.get(name)
            if p is None:
                raise ConfigError(
                    f"{prefix}.{name}: unknown parameter of {self.value} (allowed: "
                    f"{', '.join(('at_s', *self.param_names))})"
                )
            out[name] = p.check(value, f"{prefix}.{name}")
        for name in self.required:
            if name not in out:
                what = next(p for p in spec.params if p.name == name)
                raise ConfigError(
                    f"{prefix}.{name} is required for {self.value} ({what.doc}, "
                    f"{what.unit or 'number'})"
                )
        given = [n for n in spec.exclusive if n in out]
        if len(given) > 1:
            raise ConfigError(f"{prefix}: give one of {', '.join(spec.exclusive)}, not both")
        return out

    def value_of(self, params: Mapping[str, Any], name: str) -> float | str | None:
        """A parameter's value: given, else its default (``None`` if it has none)."""
        if name in params:
            v = params[name]
            return v if isinstance(v, str) else float(v)
        p = next((p for p in self.params if p.name == name), None)
        if p is None:
            raise KeyError(f"{self.value} has no parameter {name!r}")
        return p.default


FAULT_KINDS: tuple[str, ...] = tuple(k.value for k in FaultKind)
"""Names of every fault kind."""
INTERFACE_FAULTS: tuple[str, ...] = tuple(k.value for k in FaultKind if k.interface)
"""Names of the faults the interfaces play (Modbus server, CAN node)."""


@dataclass(frozen=True)
class Fault:
    """One fault to inject: its kind, when (machine time), its parameters (checked).

    Parameters
    ----------
    kind : FaultKind or str
        The kind (a name is looked up).
    at_s : float or None
        Machine time, s (``None``: now).
    params : mapping
        The kind's parameters (not ``at_s``).
    head : str or None
        The head it strikes on a machine of several heads (a name of ``[[heads]]``, e.g.
        ``"right"``); ``None``: not one head (the machine, or its one head).

    Raises
    ------
    ConfigError
        Unknown kind, bad or missing parameter, a head that is not a head's name.
    """

    kind: FaultKind
    at_s: float | None = None
    params: Mapping[str, Any] = field(default_factory=dict)
    head: str | None = None

    def __post_init__(self) -> None:
        kind = FaultKind.parse(self.kind)
        object.__setattr__(self, "kind", kind)
        if "at_s" in self.params:
            raise ConfigError(f"{kind.value}: give at_s as the fault's time, not a parameter")
        object.__setattr__(self, "params", kind.check(dict(self.params)))
        if self.at_s is not None:
            object.__setattr__(self, "at_s", AT_S.check(self.at_s, f"{kind.value}.at_s"))
        if self.head is not None:
            check_head_name(self.head, f"{kind.value}.head")

    @property
    def duration_s(self) -> float:
        """How long it lasts, s (0 for a fault without ``duration_s``: it acts once)."""
        return float(self.params.get("duration_s", 0.0))

    def table(self) -> dict[str, Any]:
        """The TOML/JSON table: ``{"kind": ..., "at_s": ..., **params}`` (``at_s`` if set)."""
        out: dict[str, Any] = {"kind": self.kind.value}
        if self.at_s is not None:
            out["at_s"] = self.at_s
        if self.head is not None:
            out["head"] = self.head
        out.update(self.params)
        return out


def parse_fault(item: Any, key: str, *, default_at_s: float | None = None,
                heads: tuple[str, ...] | None = None) -> Fault:
    """One fault table (``{kind = ..., at_s = ..., head = ..., ...}``); errors name ``key``.

    Parameters
    ----------
    item : mapping
        The table.
    key : str
        Its name in errors (``faults.inject[0]``).
    default_at_s : float, optional
        ``at_s`` when the table has none (``None``: the fault acts at once).
    heads : tuple of str, optional
        The machine's head names: a ``head`` not among them is an error (``None``: any
        well-formed name, checked later against the machine).
    """
    if not isinstance(item, Mapping):
        raise ConfigError(f"{key} must be a table with a kind, got {item!r}")
    if "kind" not in item:
        raise ConfigError(f"{key}.kind is required (one of {', '.join(FAULT_KINDS)})")
    kind = FaultKind.parse(item["kind"], key=f"{key}.kind")
    params = kind.check({k: v for k, v in item.items() if k not in ("kind", "head")}, key=key)
    at_s = params.pop("at_s", default_at_s)
    head = item.get("head")
    if head is not None:
        check_head_name(head, f"{key}.head")
        check_fault_head(head, heads, f"{key}.head")
    return Fault(kind, at_s, params, head)


def check_fault_head(head: str | None, heads: tuple[str, ...] | None, key: str) -> None:
    """ConfigError naming ``key`` when ``head`` is not one of ``heads`` (``None``: no check)."""
    if head is None or heads is None or head in heads:
        return
    raise ConfigError(f"{key} must name one of the heads ({', '.join(heads)}), got {head!r}")


def parse_faults(raw: Any, key: str, *, default_at_s: float | None = None,
                 heads: tuple[str, ...] | None = None) -> tuple[Fault, ...]:
    """A list of fault tables (see :func:`parse_fault`); errors name ``key[i]``."""
    if not isinstance(raw, list):
        raise ConfigError(f"{key} must be a list of tables, got {raw!r}")
    return tuple(parse_fault(item, f"{key}[{i}]", default_at_s=default_at_s, heads=heads)
                 for i, item in enumerate(raw))
