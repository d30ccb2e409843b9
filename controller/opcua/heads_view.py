"""What a moulder (several heads, one feed) shows over OPC UA (pure, no I/O, no asyncua).

Each head is a unit of the machine as OPC 40550 models it: ``State/SubUnits/<head>``
(``IWwSubUnitsType``; each ``<SubUnit>`` implements ``IWwBaseStateType``: ``Overview``,
``Flags``, ``Values``), with the head's own ``ManufacturerSpecific`` folder beside them. Each
head's values come from a :class:`~controller.opcua.view.MachineView` of its own service;
``State/Machine`` is the whole machine, combined from the heads (:meth:`MoulderView.flags`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

from controller.opcua.view import (
    MANUFACTURER_NAMES,
    MachineView,
    UnitMode,
    UnitState,
    WwEvent,
    as_number,
)
from controller.quality.schema import QualityClass
from controller.service.events import ServiceEvent
from controller.service.frame_result import FrameResult
from controller.service.status import ServiceStatus

__all__ = [
    "HEAD_EXTRA_NAMES",
    "HEAD_MANUFACTURER_NAMES",
    "MOULDER_MANUFACTURER_NAMES",
    "SUBUNITS",
    "MoulderView",
    "head_path",
]

SUBUNITS = "State/SubUnits"
"""Where the heads are, below the machine."""

HEAD_EXTRA_NAMES: Mapping[str, str] = {
    "Face": "String", "Knives": "Int64", "TargetPitchMm": "Double", "SpindleRpm": "Double",
    "SpindleRpmMin": "Double", "SpindleRpmMax": "Double", "SpindleSetpointRpm": "Double",
    "SafeState": "Boolean", "LimitsFeed": "Boolean",
}
"""A head's variables beyond a single machine's ``ManufacturerSpecific`` set: its face, knives
(the PLC's, else the configured), target pitch, measured spindle speed (rpm; the configured
before the PLC's first read) and its range, the coordinator's speed setpoint (variable heads),
whether its service is in its safe state and whether it sets the feed now."""

HEAD_MANUFACTURER_NAMES: Mapping[str, str] = {**MANUFACTURER_NAMES, **HEAD_EXTRA_NAMES}
"""``State/SubUnits/<head>/ManufacturerSpecific`` variables and their data types."""

MOULDER_MANUFACTURER_NAMES: Mapping[str, str] = {"Heads": "String[]", "LimitingHeads": "String[]"}
"""Added to the machine's ``ManufacturerSpecific`` in a moulder: the heads in order and the
heads that set the feed now."""

_STATE_RANK = (UnitState.ERROR, UnitState.STANDBY, UnitState.WORKING, UnitState.READY)
_ALL_FLAGS = ("MachineOn", "PowerPresent", "MachineInitialized", "Calibrated", "RecipeInRun")
"""Flags the machine has when every head has them; the others when any head has."""


def head_path(head: str, rest: str) -> str:
    """The path below the machine of a head's variable (``State/SubUnits/top/Flags/Error``)."""
    return f"{SUBUNITS}/{head}/{rest}"


class MoulderView:
    """The OPC UA picture of a moulder, updated head by head.

    Parameters
    ----------
    heads : sequence of mapping
        The heads in order (:func:`controller.edge.feed.head_configs_json`: ``name``, ``face``,
        ``knives``, ``rpm``, ``rpm_min``, ``rpm_max``, ``target_pitch_mm``).
    quality_class : QualityClass or None
        Each head's class until its service tells its own.
    calibrated : bool
        ``Flags/Calibrated`` of every head.
    """

    def __init__(self, heads: Sequence[Mapping[str, Any]], *,
                 quality_class: QualityClass | None = None, calibrated: bool = True) -> None:
        if not heads:
            raise ValueError("heads must name at least one head")
        self.configs: dict[str, dict[str, Any]] = {str(h["name"]): dict(h) for h in heads}
        if len(self.configs) != len(heads):
            raise ValueError(f"heads must have unique names, got {[h['name'] for h in heads]}")
        self.views = {name: MachineView(quality_class=quality_class, calibrated=calibrated)
                      for name in self.configs}
        self._plc: dict[str, dict[str, Any]] = {name: {} for name in self.configs}
        self._machine: dict[str, Any] = {}
        self._paths: dict[tuple[str | None, str], dict[str, str]] = {}
        """Each variable's path by (head, part) and name, made at its first update."""

    @property
    def names(self) -> list[str]:
        """The heads in order."""
        return list(self.configs)

    def view(self, head: str) -> MachineView:
        """The head's own view (``ValueError`` naming an unknown head)."""
        try:
            return self.views[head]
        except KeyError:
            raise ValueError(f"head must be one of {self.names}, got {head!r}") from None

    # --- inputs -------------------------------------------------------------------------------

    def set_quality_class(self, head: str, qc: QualityClass | None) -> None:
        """The class the head's measurements are judged against (its service's)."""
        if qc is not None:
            self.view(head).quality_class = qc

    def update(self, head: str, status: ServiceStatus) -> None:
        """A head's status snapshot."""
        self.view(head).update(status)

    def result(self, head: str, r: FrameResult) -> None:
        """A head's pair result."""
        self.view(head).result(r)

    def event(self, head: str, e: ServiceEvent) -> WwEvent:
        """The Woodworking event of a head's service event (``PathParts`` names the head)."""
        ev = self.view(head).event(e)
        return dataclasses.replace(ev, message=f"{head}: {ev.message}",
                                   path_parts=("SubUnits", head))

    def take_plc(self, head: str, facts: Mapping[str, Any]) -> None:
        """The head's measured ``spindle_rpm`` and ``knives`` (``None``: not read yet)."""
        self.view(head)
        self._plc[head] = dict(facts)

    def take_machine(self, d: Mapping[str, Any]) -> None:
        """The feed coordinator's last decision (``feed_mm_s``, ``limiting``, setpoints)."""
        self._machine = dict(d)

    # --- outputs ------------------------------------------------------------------------------

    @property
    def current_state(self) -> UnitState:
        """The machine's state: the worst of its heads' (ERROR, STANDBY, WORKING, READY)."""
        return _machine_state([v.current_state for v in self.views.values()])

    @property
    def current_mode(self) -> UnitMode:
        """``AUTOMATIC`` when every head is, ``OTHER`` when none is known, else SEMIAUTOMATIC."""
        return _machine_mode([v.current_mode for v in self.views.values()])

    def flags(self) -> dict[str, bool]:
        """The machine's flags: the heads' all-of (:data:`_ALL_FLAGS`), else any-of."""
        return _machine_flags([v.flags() for v in self.views.values()])

    def values(self) -> dict[str, float | int]:
        """The machine's values (feed, length and pieces in: the first head's).

        Pieces out are the last head's, runs summed over the heads.
        """
        return _machine_values([v.values() for v in self.views.values()])

    def head_manufacturer(self, head: str) -> dict[str, Any]:
        """The head's ``ManufacturerSpecific`` (:data:`HEAD_MANUFACTURER_NAMES`)."""
        view, cfg, plc = self.view(head), self.configs[head], self._plc[head]
        status = view.status
        rpm = plc.get("spindle_rpm")
        knives = plc.get("knives")
        knives = knives if knives is not None else cfg.get("knives")
        setpoints = self._machine.get("spindle_setpoints_rpm") or {}
        return {
            **view.manufacturer(),
            "Face": str(cfg.get("face") or ""),
            "Knives": int(knives) if knives is not None and math.isfinite(knives) else 0,
            "TargetPitchMm": as_number(cfg.get("target_pitch_mm")),
            "SpindleRpm": as_number(rpm if rpm is not None else cfg.get("rpm")),
            "SpindleRpmMin": as_number(cfg.get("rpm_min")),
            "SpindleRpmMax": as_number(cfg.get("rpm_max")),
            "SpindleSetpointRpm": as_number(setpoints.get(head)),
            "SafeState": bool(status is not None and status.state == "safe"),
            "LimitsFeed": head in (self._machine.get("limiting") or ()),
        }

    def all_values(self) -> dict[str, Any]:
        """Every value by its path below the machine.

        ``State/Machine/...``, the machine's ``ManufacturerSpecific/FeedSetpointMmS``,
        ``Heads``, ``LimitingHeads`` and each head's
        ``State/SubUnits/<head>/{Overview, Flags, Values, ManufacturerSpecific}/...``.
        """
        # each head's state, mode, flags and values once; the machine's are made of them
        heads = {head: (view.current_state, view.current_mode, view.flags(), view.values())
                 for head, view in self.views.items()}
        parts = list(zip(*heads.values(), strict=True))
        out: dict[str, Any] = {
            "State/Machine/Overview/CurrentState": int(_machine_state(parts[0])),
            "State/Machine/Overview/CurrentMode": int(_machine_mode(parts[1])),
        }
        out.update(self._at(None, "Flags", _machine_flags(parts[2])))
        out.update(self._at(None, "Values", _machine_values(parts[3])))
        out["ManufacturerSpecific/FeedSetpointMmS"] = as_number(self._machine.get("feed_mm_s"))
        out["ManufacturerSpecific/Heads"] = self.names
        out["ManufacturerSpecific/LimitingHeads"] = [
            str(h) for h in self._machine.get("limiting") or ()]
        for head, (state, mode, flags, values) in heads.items():
            out.update(self._at(head, "Overview", {"CurrentState": int(state),
                                                   "CurrentMode": int(mode)}))
            out.update(self._at(head, "Flags", flags))
            out.update(self._at(head, "Values", values))
            out.update(self._at(head, "ManufacturerSpecific", self.head_manufacturer(head)))
        return out

    def _at(self, head: str | None, part: str, values: Mapping[str, Any]) -> dict[str, Any]:
        """``values`` by their paths in ``part`` of ``head`` (``None``: the machine's state).

        A variable's path is made once, at its first update (the same few hundred every time).
        """
        paths = self._paths.setdefault((head, part), {})
        out = {}
        for name, value in values.items():
            path = paths.get(name)
            if path is None:
                path = paths[name] = (f"State/Machine/{part}/{name}" if head is None
                                      else head_path(head, f"{part}/{name}"))
            out[path] = value
        return out


def _machine_state(states: Sequence[UnitState]) -> UnitState:
    """The worst of the heads' states (ERROR, STANDBY, WORKING, READY; else OFFLINE)."""
    return next((s for s in _STATE_RANK if s in states), UnitState.OFFLINE)


def _machine_mode(modes: Sequence[UnitMode]) -> UnitMode:
    """The heads' one mode, else ``SEMIAUTOMATIC``."""
    return modes[0] if len(set(modes)) == 1 else UnitMode.SEMIAUTOMATIC


def _machine_flags(per_head: Sequence[Mapping[str, bool]]) -> dict[str, bool]:
    """The heads' all-of (:data:`_ALL_FLAGS`), else any-of."""
    return {name: (all if name in _ALL_FLAGS else any)(f[name] for f in per_head)
            for name in per_head[0]}


def _machine_values(per_head: Sequence[Mapping[str, float | int]]) -> dict[str, float | int]:
    """The first head's values, the last head's pieces out, the runs summed over the heads."""
    out = dict(per_head[0])
    for k in ("AbsolutePiecesOut", "RelativePiecesOut"):
        out[k] = per_head[-1][k]
    for k in ("AbsoluteRunsGood", "RelativeRunsGood", "AbsoluteRunsTotal", "RelativeRunsTotal"):
        out[k] = sum(int(v[k]) for v in per_head)
    return out
