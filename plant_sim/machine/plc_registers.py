"""The PLC's own logic and its register view: fault bits, e-stop, heartbeats, watchdog, interlock.

What the Modbus server (:mod:`plant_sim.interfaces.plc_server`) exposes comes from here:
:meth:`PlcRegisters.values` gives every register of ``config/registers.toml`` from the drives'
state, the last camera pair's latches and the PLC's flags. Per PLC cycle
(:meth:`PlcRegisters.start_cycle`) the PLC increments its heartbeat and checks the service's
(no new ``heartbeat_service`` value for ``[plc] watchdog_ms``: faults bit 3, flagged only); the
feed interlock (:meth:`PlcRegisters.feed_permitted`) lets the feed run only while the spindle
runs, no e-stop and no feed-drive fault.
"""

from __future__ import annotations

from pathlib import Path

from config.sim import SimConfig
from core.checks import check_int
from plant_sim.model.feed_drive import BoardStream, Encoder, FeedDrive
from plant_sim.model.spindle import Spindle
from plant_sim.rendering.frame_capture import FrameCapture
from protocol.registers import HeadFault, MachineState, PlcFault, RegisterMap

_HEARTBEAT_LOST = int(PlcFault.HEARTBEAT_LOST)
_FEED_DRIVE = int(PlcFault.FEED_DRIVE)
# machine_state bits as plain ints: building an IntFlag per read cost more than the rest of it
_RUNNING = int(MachineState.RUNNING)
_BOARD_PRESENT = int(MachineState.BOARD_PRESENT)
_ESTOP = int(MachineState.ESTOP)
_SPINDLE_RUNNING = int(MachineState.SPINDLE_RUNNING)
_FEED_ENABLED = int(MachineState.FEED_ENABLED)
_PIEZO_AMPLIFIER = int(PlcFault.PIEZO_AMPLIFIER)
_SPINDLE_STOPPED = int(PlcFault.SPINDLE_STOPPED)

_HEAD_AMPLIFIER = int(HeadFault.AMPLIFIER)
_HEAD_SPINDLE = int(HeadFault.SPINDLE)
_HEAD_CAMERA_SILENT = int(HeadFault.CAMERA_SILENT)
__all__ = ["PlcRegisters", "register_names"]


def register_names(path: str | Path | None = None) -> list[str]:
    """Names of every register in the register map (``config/registers.toml`` by default)."""
    return [reg.name for reg in RegisterMap.load(path)]


class PlcRegisters:
    """The PLC's state and the values of its registers.

    Parameters
    ----------
    cfg : config.sim.SimConfig
        The configuration (``[plc]``, ``[feed]`` limits, ``[encoder]``, ``[cutterhead]``).
    spindle, feed, encoder, boards : the drives, the counter and the boards
        Read for the register values.
    capture : plant_sim.rendering.frame_capture.FrameCapture
        The camera station (the last pair's latches).
    radius_mm : float
        Cutting radius, mm (a register).

    Attributes
    ----------
    estop : bool
        E-stop pressed.
    fault_bits : protocol.registers.PlcFault
        The ``faults`` register.
    heartbeat_plc, heartbeat_service : int
        The two heartbeats (0..65535).
    """

    def __init__(self, cfg: SimConfig, *, spindle: Spindle, feed: FeedDrive, encoder: Encoder,
                 boards: BoardStream, capture: FrameCapture, radius_mm: float) -> None:
        self.cfg = cfg
        self.spindle = spindle
        self.feed = feed
        self.encoder = encoder
        self.boards = boards
        self.capture = capture
        self.radius_mm = radius_mm
        self.knives = cfg.cutterhead.knives
        self.L_mm = cfg.camera.cutter_to_camera_mm
        self._watchdog_s = cfg.plc.watchdog_ms * 1e-3
        self._names = register_names()
        self._names_checked = False
        self.estop = False
        self._faults = 0  # the register's bits as a plain int: IntFlag arithmetic is slow per cycle
        self.heartbeat_plc = 0
        self.heartbeat_service = 0
        self._hb_changed_s = 0.0

    @property
    def fault_bits(self) -> PlcFault:
        """The ``faults`` register's bits."""
        return PlcFault(self._faults)

    def start_cycle(self, t_s: float) -> None:
        """A PLC cycle begins at ``t_s``: check the service's heartbeat, count the PLC's own."""
        if t_s - self._hb_changed_s > self._watchdog_s:
            self._faults |= _HEARTBEAT_LOST
        else:
            self._faults &= ~_HEARTBEAT_LOST
        self.heartbeat_plc = (self.heartbeat_plc + 1) & 0xFFFF

    def feed_permitted(self) -> bool:
        """The interlock: the feed may run (spindle running, no e-stop, no feed-drive fault)."""
        return (not self.estop and self.spindle.running
                and not (self._faults & _FEED_DRIVE))

    def set_flag(self, bit: PlcFault | int, on: bool) -> None:
        """Set or clear one bit of the ``faults`` register (a ``PlcFault`` or its int value)."""
        b = int(bit)
        if on:
            self._faults |= b
        elif self._faults & b:
            self._faults &= ~b

    def set_service_heartbeat(self, value: int, t_s: float) -> None:
        """The service's heartbeat at ``t_s``; a changed value feeds the watchdog."""
        v = check_int("value", value, lo=0, hi=0xFFFF)
        if v != self.heartbeat_service:
            self._hb_changed_s = t_s
            self._faults &= ~_HEARTBEAT_LOST
        self.heartbeat_service = v

    def machine_state(self, t_s: float) -> MachineState:
        """The ``machine_state`` register's bits at ``t_s``."""
        return MachineState(self._state_bits(self.boards.at(self.feed.position_at(t_s),
                                                            self.L_mm)[0]))

    def _state_bits(self, board_id: int) -> int:
        """``machine_state`` as an int, given the board under the camera (0: none)."""
        running = self.spindle.running
        enabled = self.feed.enabled
        st = _BOARD_PRESENT if board_id else 0
        if running:
            st |= _SPINDLE_RUNNING
        if enabled:
            st |= _FEED_ENABLED
        if self.estop:
            st |= _ESTOP
        elif running and enabled:
            st |= _RUNNING
        return st

    def head_values(self, t_s: float, *, camera_silent: bool = False) -> dict[str, float | int]:
        """The fields of the head's register block at ``t_s`` (``[heads]`` of registers.toml).

        Parameters
        ----------
        t_s : float
            Machine time, s (the board under the camera then; the other head fields are held
            over the cycle).
        camera_silent : bool
            The head's camera sends no frames (``HeadFault.CAMERA_SILENT``).
        """
        last = self.capture.last_pair
        sp = self.spindle
        bid = self.boards.at(self.feed.position_at(t_s), self.L_mm)[0]
        bits = 0
        if self._faults & _PIEZO_AMPLIFIER:
            bits |= _HEAD_AMPLIFIER
        if self._faults & _SPINDLE_STOPPED:
            bits |= _HEAD_SPINDLE
        if camera_silent:
            bits |= _HEAD_CAMERA_SILENT
        return {
            "spindle_rpm": sp.rpm,
            "spindle_setpoint_rpm": sp.setpoint_rpm,
            "spindle_rpm_min": sp.rpm_min,
            "spindle_rpm_max": sp.rpm_max,
            "knives": self.knives,
            "cutterhead_radius_mm": self.radius_mm,
            "cutter_to_camera_mm": self.L_mm,
            "trigger_a_counts": last.counts_a if last else 0,
            "trigger_b_counts": last.counts_b if last else 0,
            "trigger_seq": (last.seq if last else 0) & 0xFFFF,
            "index_latch_counts": last.index_latch if last else 0,
            "head_faults": bits,
            # what this head's camera sees (its boards: a moulder's head further down the feed
            # sees each board later)
            "machine_state": self._state_bits(bid),
            "board_id": bid,
            "board_position_mm": (self.boards.length_mm - last.x_centre_mm) if last else 0.0,
        }

    def values(self, t_s: float) -> dict[str, float | int]:
        """Every register of ``config/registers.toml`` with its value at ``t_s``.

        Raises
        ------
        RuntimeError
            The register map names a register the machine has no value for.
        """
        feed = self.feed
        s = feed.position_at(t_s)
        cfg = self.cfg
        last = self.capture.last_pair
        bid = self.boards.at(s, self.L_mm)[0]
        values: dict[str, float | int] = {
            "heartbeat_service": self.heartbeat_service,
            "heartbeat_plc": self.heartbeat_plc,
            "feed_setpoint_mm_s": feed.setpoint_mm_s,
            "feed_min_mm_s": cfg.feed.min_mm_s,
            "feed_max_mm_s": cfg.feed.max_mm_s,
            "feed_accel_max_mm_s2": cfg.feed.accel_max_mm_s2,
            "feed_actual_mm_s": feed.speed_at(t_s),
            "spindle_rpm": self.spindle.rpm,
            "encoder_counts": self.encoder.read(s),
            "trigger_a_counts": last.counts_a if last else 0,
            "trigger_b_counts": last.counts_b if last else 0,
            "trigger_seq": (last.seq if last else 0) & 0xFFFF,
            "index_latch_counts": last.index_latch if last else 0,
            "machine_state": self._state_bits(bid),
            "faults": self._faults,
            "knives": self.knives,
            "cutter_to_camera_mm": self.L_mm,
            "counts_per_mm": cfg.encoder.counts_per_mm,
            "board_id": bid,
            "board_position_mm": (self.boards.length_mm - last.x_centre_mm) if last else 0.0,
            "watchdog_ms": cfg.plc.watchdog_ms,
            "cutterhead_radius_mm": self.radius_mm,
        }
        if not self._names_checked:  # the keys above are fixed: check them against the map once
            missing = [n for n in self._names if n not in values]
            if missing:
                raise RuntimeError(f"machine has no value for registers {missing}")
            self._names_checked = True
        return values
