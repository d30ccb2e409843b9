"""The simulated four-sided moulder: several heads, each its own machine, on one feed.

A moulder has N heads (bottom, right, left, top, ...; ``[[heads]]`` of the simulator's
configuration, :attr:`config.sim.SimConfig.heads`), each with its own spindle, knives, piezo
amplifier and camera, and ONE feed for all. :class:`Moulder` builds one
:class:`plant_sim.machine.machine.Machine` per head from :func:`config.sim.head_sim_config`, each
with seeds of its own (wood texture, image and sensor noise), all sharing the first head's
:class:`~plant_sim.model.feed_drive.FeedDrive`, :class:`~plant_sim.model.feed_drive.Encoder` and
stream of boards. Head ``h`` sees the boards from its place along the feed
(:class:`~plant_sim.model.feed_drive.BoardView`, ``position_mm`` from the first head): a board
reaches its cutter ``position_mm`` of feed travel after it reached the first head's, and its
camera ``cutter_to_camera_mm`` (the head's own) after that.

Time moves through :meth:`Moulder.advance`, which steps the heads cycle by cycle in lock-step
(:func:`plant_sim.machine.machine.advance_together`): the feed runs only while every head's
interlock permits it (a tripped spindle on one head stops the feed under all).

Faults (:meth:`Moulder.inject`, or ``[faults] inject`` with ``head = "..."``) strike a head by
name; without one, the machine-wide kinds (the feed's, the encoder's, the PLC's Modbus side) go
to the first head, which owns the feed and the encoder, and ``estop``, ``reset`` and
``species_change`` to every head; a kind that strikes one head (a knife, a spindle, an
amplifier, a camera) needs its head unless the moulder has only one. One rule for both, written
once: :func:`config.sim.fault_heads` (:func:`config.sim.head_sim_config` gives each head's
machine its configured faults by it).

The PLC's view (:mod:`plant_sim.interfaces.register_bus`, :mod:`plant_sim.interfaces.plc_server`):
:meth:`Moulder.register_values` is the legacy single map (the first head's values; ``faults`` and
``machine_state`` of the whole machine), :meth:`Moulder.head_register_values` a head's block.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from config.sim import (
    ALL_HEADS_FAULTS,
    MACHINE_FAULTS,
    SimConfig,
    SimHeadConfig,
    fault_heads,
    head_sim_config,
)
from core.checks import check_int
from plant_sim.machine.machine import Machine, advance_together, start_feed
from plant_sim.model.feed_drive import BoardView
from protocol.frames import Frame
from protocol.registers import MachineState

__all__ = ["ALL_HEADS_FAULTS", "MACHINE_FAULTS", "Moulder", "head_seed"]

# ALL_HEADS_FAULTS, MACHINE_FAULTS: the one rule of where a fault strikes (config.sim.fault_heads)
_RUNNING = int(MachineState.RUNNING)
_SPINDLE_RUNNING = int(MachineState.SPINDLE_RUNNING)
_ESTOP = int(MachineState.ESTOP)


def head_seed(seed: int, index: int) -> int:
    """The seed of head ``index``'s machine: ``seed`` itself for the first, drawn for the rest."""
    if index == 0:
        return seed
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


class Moulder:
    """The simulated moulder: one :class:`Machine` per head on one feed.

    Parameters
    ----------
    sim_cfg : config.sim.SimConfig
        The machine's configuration; its ``heads`` (one head ``"main"`` without ``[[heads]]``).
    seed : int
        Seed of everything random; head ``i`` runs on :func:`head_seed` ``(seed, i)``.
    render_images : bool
        Render the cameras' images (``False``: frames with counts and truth only).

    Attributes
    ----------
    cfg : SimConfig
        The configuration.
    heads : dict of str to Machine
        The heads' machines by name, in configuration order; the first owns the feed.
    head_configs : tuple of config.sim.SimHeadConfig
        The heads as configured (name, face, position, node id, tables).
    last_truth : dict of str to dict
        Per head the truth of its latest frame (``pitch_mm``, ``uniformity_cv``, ...; empty
        before its first).

    Raises
    ------
    ValueError
        A configured fault that strikes one head names none in a moulder of several.
    """

    def __init__(self, sim_cfg: SimConfig, *, seed: int = 0, render_images: bool = True) -> None:
        self.cfg = sim_cfg
        self.seed = check_int("seed", seed, lo=0)
        self.head_configs: tuple[SimHeadConfig, ...] = tuple(sim_cfg.heads)
        self.names: tuple[str, ...] = tuple(h.name for h in self.head_configs)
        for spec in sim_cfg.faults:  # a one-head fault without its head: refused here
            fault_heads(spec.kind, spec.head, self.names)
        self.heads: dict[str, Machine] = {}
        owner: Machine | None = None
        x0 = self.head_configs[0].position_mm
        for i, h in enumerate(self.head_configs):
            cfg = head_sim_config(sim_cfg, h.name)
            if owner is None:  # its feed starts once, with every head's interlock (below)
                m = owner = Machine(cfg, seed=head_seed(self.seed, i),
                                    render_images=render_images, feed_shared=True)
            else:
                m = Machine(cfg, seed=head_seed(self.seed, i), render_images=render_images,
                            feed=owner.feed, encoder=owner.encoder,
                            boards=BoardView(owner.boards, h.position_mm - x0))
            self.heads[h.name] = m
        assert owner is not None
        self.owner = owner
        """The first head's machine: it owns the feed, the encoder and the boards."""
        self._machines: tuple[Machine, ...] = tuple(self.heads.values())
        # every head shares the encoder's origin: a preset moves the latches in flight of all
        owner.faults.other_captures = [m.capture for m in self._machines[1:]]
        start_feed(self._machines)  # the feed's interlock with every head (a fault at t = 0)
        self.last_truth: dict[str, dict[str, Any]] = {n: {} for n in self.names}

    # ------------------------------------------------------------------ heads
    @property
    def head_count(self) -> int:
        """Number of heads (the PLC's register blocks)."""
        return len(self._machines)

    @property
    def node_ids(self) -> dict[str, int]:
        """Each head's amplifier node id on the CAN bus, by name."""
        return {h.name: h.node_id for h in self.head_configs}

    @property
    def positions_mm(self) -> dict[str, float]:
        """Each head's place along the feed, mm from the first head's, by name."""
        x0 = self.head_configs[0].position_mm
        return {h.name: h.position_mm - x0 for h in self.head_configs}

    def head(self, which: int | str) -> Machine:
        """A head's machine by index (config order) or name.

        Raises
        ------
        ValueError
            No such head.
        """
        if isinstance(which, str):
            if which not in self.heads:
                raise ValueError(f"head must be one of {', '.join(self.names)}, got {which!r}")
            return self.heads[which]
        return self._machines[check_int("i", which, lo=0, hi=len(self._machines) - 1)]

    # ------------------------------------------------------------------ time
    @property
    def t_s(self) -> float:
        """Simulated time, s."""
        return self.owner.t_s

    def advance(self, dt_s: float) -> list[tuple[str, Frame]]:
        """Step every head by ``dt_s`` seconds; the frames completed, ``(head, frame)``.

        In the order they were taken (frame time; heads in configuration order at one time).

        Raises
        ------
        ValueError
            ``dt_s`` negative or not finite.
        """
        per_head = advance_together(self._machines, dt_s)
        out = [(name, fr) for name, frames in zip(self.names, per_head, strict=True)
               for fr in frames]
        out.sort(key=lambda item: item[1].t_s)
        for name, fr in out:
            if fr.truth:
                self.last_truth[name] = fr.truth
        return out

    # ------------------------------------------------------------------ PLC side
    def register_values(self) -> dict[str, float | int]:
        """The legacy single map: the first head's values, ``faults`` and state of all heads."""
        values = self.owner.register_values()
        if len(self._machines) > 1:
            values["faults"] = int(self.fault_bits)
            values["machine_state"] = self._state_bits(int(values["machine_state"]))
        return values

    def head_register_values(self, i: int) -> dict[str, float | int]:
        """The head fields of head ``i``'s register block (``Machine.head_register_values``)."""
        return self.head(i).head_register_values(0)

    def machine_state(self) -> MachineState:
        """The ``machine_state`` register's bits (every spindle running: ``spindle_running``)."""
        return MachineState(self._state_bits(int(self.owner.machine_state())))

    def _state_bits(self, first: int) -> int:
        st = first
        if not all(m.spindle.running for m in self._machines):
            st &= ~(_SPINDLE_RUNNING | _RUNNING)
        if self.estop:
            st = (st | _ESTOP) & ~_RUNNING
        return st

    @property
    def fault_bits(self) -> Any:
        """The ``faults`` register: every head's PLC fault bits together."""
        bits = self.owner.fault_bits
        for m in self._machines[1:]:
            bits |= m.fault_bits
        return bits

    @property
    def estop(self) -> bool:
        """E-stop pressed (on any head's PLC)."""
        return any(m.estop for m in self._machines)

    @property
    def heartbeat_plc(self) -> int:
        """The PLC's heartbeat (the first head's PLC cycle count)."""
        return self.owner.heartbeat_plc

    @property
    def heartbeat_service(self) -> int:
        """The service's heartbeat as last written."""
        return self.owner.heartbeat_service

    def set_feed_setpoint(self, feed_mm_s: float) -> None:
        """The one feed's setpoint; ``ValueError`` outside its limits (never clamped)."""
        self.owner.set_feed_setpoint(feed_mm_s)

    def set_spindle_setpoint(self, i: int, rpm: float) -> None:
        """Head ``i``'s spindle setpoint, rpm (``ValueError`` outside its range)."""
        self.head(i).set_spindle_setpoint(0, rpm)

    def set_service_heartbeat(self, value: int) -> None:
        """The service's heartbeat (every head's PLC watchdog sees it)."""
        for m in self._machines:
            m.set_service_heartbeat(value)

    # ------------------------------------------------------------------ faults
    def inject(self, fault: str, *, head: str | None = None, **params: Any) -> None:
        """Inject a fault into a head (``head``) or where the kind belongs (module docstring).

        Kinds and parameters: :mod:`plant_sim.machine.fault_injection`.

        Raises
        ------
        ValueError
            Unknown head, a one-head kind without ``head`` in a moulder of several, or what
            :meth:`Machine.inject` refuses.
        """
        for name in fault_heads(fault, head, self.names):
            self.heads[name].inject(fault, **params)

    def reset_faults(self) -> None:
        """Acknowledge on every head."""
        for m in self._machines:
            m.reset_faults()

    def take_interface_events(self) -> list[dict[str, Any]]:
        """Interface faults that came due, each naming its ``head``; cleared on read."""
        out = []
        for name, m in self.heads.items():
            out.extend({**ev, "head": name} for ev in m.take_interface_events())
        return out

    # ------------------------------------------------------------------ truth
    @property
    def feed_position_mm(self) -> float:
        """True table travel since time 0, mm."""
        return self.owner.feed_position_mm

    @property
    def feed_speed_mm_s(self) -> float:
        """True feed speed now, mm/s (the same under every head)."""
        return self.owner.feed_speed_mm_s

    def pitch_mm(self, head: str) -> float:
        """Head ``head``'s true pitch from the current speeds, ``V / (n Z)``, mm."""
        return self.head(head).pitch_mm()

    def truth(self) -> dict[str, dict[str, Any]]:
        """Per head what is true now and what its latest frame showed.

        Returns
        -------
        dict of str to dict
            By name: ``face``, ``position_mm``, ``node_id``, ``knives``, ``rpm`` (now),
            ``spindle_setpoint_rpm``, ``pitch_mm`` (``V / (n Z)`` now), ``standout_um``,
            ``last_pitch_mm`` and ``last_uniformity_cv`` (its latest frame's truth, ``None``
            before one), ``frames_dropped``.
        """
        out = {}
        for h, m in zip(self.head_configs, self._machines, strict=True):
            last = self.last_truth[h.name]
            out[h.name] = {
                "face": str(h.face),
                "position_mm": self.positions_mm[h.name],
                "node_id": h.node_id,
                "knives": m.knives,
                "rpm": m.spindle_rpm,
                "spindle_setpoint_rpm": m.spindle.setpoint_rpm,
                "pitch_mm": m.pitch_mm(),
                "standout_um": m.standout_um(),
                "last_pitch_mm": last.get("pitch_mm"),
                "last_uniformity_cv": last.get("uniformity_cv"),
                "frames_dropped": m.frames_dropped,
            }
        return out
