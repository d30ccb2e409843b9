"""The one plant driver: steps the machine with its amplifier node and PLC view, plays faults.

Both ``planer sim`` (:mod:`plant_sim.run.runner`, scaled real time) and the in-process HIL
(``planer.hil.in_process``, simulated time) drive the plant through :class:`PlantDriver`, so the
order of things in a step exists once:

1. interface faults that came due are played (the machine's ``take_interface_events`` and the
   driver's own schedule): ``modbus_restart`` switches the PLC off for ``duration_s`` machine
   seconds, ``can_silence`` / ``can_drop`` go to the amplifier node;
2. the PLC comes back when its down time is over;
3. CAN frames received go to the amplifier (at the current machine time), queued Modbus writes
   to the machine (in the order they were accepted);
4. the machine advances; the frames it captured are returned;
5. the amplifier sends the frames due; the PLC view publishes the new register values.

Everything here runs on the thread that steps the machine; the interfaces themselves may live on
other threads (:mod:`plant_sim.interfaces.thread`).

:class:`MoulderDriver` drives a :class:`plant_sim.machine.moulder.Moulder` the same way: its
heads' amplifiers are the nodes of one :class:`~plant_sim.interfaces.amp_node.AmpNodeCore` (each
its own node id) on one bus, and a fault may name the head it strikes (``head=``): the CAN
faults then strike that head's node only.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from typing import Any, Protocol

from config.faults import INTERFACE_FAULTS, FaultKind
from plant_sim.interfaces.amp_node import CAN_FAULTS
from protocol.frames import Frame

__all__ = ["INTERFACE_FAULTS", "MoulderDriver", "PlantDriver", "PlcSwitch"]
# INTERFACE_FAULTS (the registry config.faults): played by the driver; the rest by the machine


class PlcSwitch(Protocol):
    """Switches the PLC's Modbus side off and on (``ServedPlc``, a direct register bus...)."""

    def set_up(self, up: bool) -> None: ...  # noqa: D102


class PlantDriver:
    """Steps a machine with its amplifier node and PLC view; plays the interface faults.

    Parameters
    ----------
    machine : Machine
        The machine model (``t_s``, ``advance``, ``inject``, ``take_interface_events``).
    amp : AmpNode, optional
        The amplifier node on its bus.
    plc : PlcServer, optional
        The PLC's register view: ``refresh()`` after every step, ``apply_writes()`` before.
    plc_switch : PlcSwitch, optional
        What ``modbus_restart`` switches off and on.
    say : callable, optional
        Receives one line per interface fault played.
    """

    def __init__(
        self,
        machine: Any,
        *,
        amp: Any = None,
        plc: Any = None,
        plc_switch: PlcSwitch | None = None,
        say: Callable[[str], None] | None = None,
    ) -> None:
        self.machine = machine
        self.amp = amp
        self.plc = plc
        self.plc_switch = plc_switch
        self._say = say
        self.faults: list[str] = []
        self._schedule: list[tuple[float, int, str, dict[str, Any]]] = []
        self._tie = itertools.count()
        self._plc_down = False
        self._plc_up_at: float | None = None

    @property
    def t_s(self) -> float:
        """Machine time, s."""
        return float(self.machine.t_s)

    @property
    def plc_down(self) -> bool:
        """Whether the ``modbus_restart`` fault holds the PLC's Modbus side off now."""
        return self._plc_down

    # ------------------------------------------------------------------ faults
    def schedule(self, at_s: float, fault: str, **params: Any) -> None:
        """Play a fault at machine time ``at_s`` (see :meth:`inject`)."""
        heapq.heappush(self._schedule, (float(at_s), next(self._tie), fault, params))

    def inject(self, fault: str, **params: Any) -> None:
        """Inject a fault now.

        Kinds and parameters: :class:`config.faults.FaultKind` (checked here; ``duration_s``
        required for these three). ``modbus_restart`` (the PLC's Modbus side is off, dropping
        every client, for ``duration_s`` machine seconds); ``can_drop`` (``fraction``,
        ``duration_s``: the amplifier node drops that fraction of received frames);
        ``can_silence`` (``duration_s``: the node sends nothing); any other kind goes to
        ``machine.inject``.

        Raises
        ------
        ValueError
            An interface fault without that interface.
        """
        self._inject(fault, params)

    def _inject(self, fault: str, params: dict[str, Any], *, head: str | None = None,
                node_id: int | None = None) -> None:
        """:meth:`inject` of a fault on ``head`` (the machine's) or node ``node_id`` (CAN)."""
        params = FaultKind.parse(fault).check(params)  # the registry: a ConfigError names it
        now = self.t_s
        if fault == "modbus_restart":
            if self.plc_switch is None:
                raise ValueError("modbus_restart: the plant has no Modbus server")
            down = float(params["duration_s"])
            self._plc_up_at = now + max(down, 0.0)
            if not self._plc_down:
                self._plc_down = True
                self.plc_switch.set_up(False)
                self.say(f"fault: modbus server down at t={now:.3f} s")
        elif fault in CAN_FAULTS:
            if self.amp is None:
                raise ValueError(f"{fault}: the plant has no CAN node")
            self.amp.core.play(fault, params, start_s=now, node_id=node_id)
        else:
            self.machine.inject(fault, **params, **({} if head is None else {"head": head}))
            return
        self.faults.append(f"{fault}{'' if node_id is None else f'[{head}]'}@{now:.3f}")

    def say(self, line: str) -> None:
        """Report one line (faults played)."""
        if self._say is not None:
            self._say(line)

    def _play_faults(self) -> None:
        now = self.t_s
        take = getattr(self.machine, "take_interface_events", None)
        for event in take() if take is not None else ():
            ev = dict(event)
            kind = ev.pop("kind")
            ev.pop("t_s", None)
            if kind in INTERFACE_FAULTS:
                self.inject(kind, **ev)
        while self._schedule and self._schedule[0][0] <= now + 1e-12:
            _at, _n, fault, params = heapq.heappop(self._schedule)
            self.inject(fault, **params)
        if self._plc_down and self._plc_up_at is not None and now >= self._plc_up_at - 1e-9:
            self._plc_down = False
            self._plc_up_at = None
            self.plc_switch.set_up(True)  # type: ignore[union-attr]
            self.say(f"fault: modbus server up again at t={now:.3f} s")

    # ------------------------------------------------------------------ stepping
    def step(self, dt_s: float, *, publish: bool = True) -> list[Frame]:
        """Advance the plant by ``dt_s`` machine seconds; returns the frames captured.

        Parameters
        ----------
        dt_s : float
            Step, s.
        publish : bool
            Publish the PLC's registers afterwards (a caller doing many steps at once may
            publish once, with :meth:`publish`).
        """
        self._play_faults()
        t = self.t_s
        if self.amp is not None:
            self.amp.receive(t)
        if self.plc is not None:
            self.plc.apply_writes()
        frames = self.machine.advance(dt_s)
        if self.amp is not None:
            self.amp.transmit(self.t_s)
        if publish:
            self.publish()
        return frames

    def publish(self) -> None:
        """Publish the machine's register values to the PLC view."""
        if self.plc is not None:
            self.plc.refresh()


class MoulderDriver(PlantDriver):
    """:class:`PlantDriver` over a moulder: faults name a head; one bus for every amplifier.

    Parameters
    ----------
    moulder : plant_sim.machine.moulder.Moulder
        The moulder (``node_ids``, ``advance`` giving ``(head, frame)`` pairs, ``inject`` with
        ``head=``).
    amp : AmpNode, optional
        Every head's amplifier node on the one bus (:meth:`amp_core` builds its core).
    plc, plc_switch, say
        As :class:`PlantDriver`.
    """

    @staticmethod
    def amp_core(moulder: Any, *, eds: Any = None, seed: int = 0) -> Any:
        """An :class:`~plant_sim.interfaces.amp_node.AmpNodeCore` with one node per head.

        Each head's amplifier answers as its configured node id (``moulder.node_ids``) with
        its own knives; the first head's is the core's ``node``.
        """
        from plant_sim.interfaces.amp_node import AmpNodeCore

        ids = moulder.node_ids
        machines = list(moulder.heads.items())
        name, first = machines[0]
        core = AmpNodeCore(first, knives=first.knives, node_id=ids[name], eds=eds, seed=seed)
        for name, m in machines[1:]:
            core.add_node(ids[name], m, knives=m.knives, eds=eds)
        return core

    def inject(self, fault: str, *, head: str | None = None, **params: Any) -> None:
        """Inject a fault now, into ``head`` (a name) or where the kind belongs.

        ``can_drop`` / ``can_silence`` strike the head's amplifier node only (every node
        without ``head``); ``modbus_restart`` the one PLC; the rest go to
        ``moulder.inject(fault, head=head, ...)``.

        Raises
        ------
        ValueError
            Unknown head, or what :meth:`PlantDriver.inject` refuses.
        """
        if fault in CAN_FAULTS and head is not None:  # that head's node only
            ids = self.machine.node_ids
            if head not in ids:
                raise ValueError(f"head must be one of {', '.join(ids)}, got {head!r}")
            self._inject(fault, params, head=head, node_id=ids[head])
        else:  # the one PLC's fault takes no head
            self._inject(fault, params, head=None if fault in INTERFACE_FAULTS else head)
