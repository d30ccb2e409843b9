"""The one stand-in for the simulated machine in tests: the Machine API with trivial dynamics.

It has the interface of :class:`plant_sim.machine.machine.Machine` that the PLC server, the CAN
node, the runner and the in-process register bus use (``tests/plant_sim/
test_fake_machine_contract.py`` holds it against the real machine), and none of its physics: a
frame every ``1 / pairs_per_s`` seconds with its sequence number in its pixels, the feed setpoint
as written, the offsets ramping to zero after a command time-out.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from protocol.frames import Frame
from protocol.registers import RegisterMap

RMAP = RegisterMap.load()


class FakeMachine:
    """The Machine API of docs/architecture.md, with trivial dynamics."""

    def __init__(
        self,
        *,
        knives: int = 4,
        pairs_per_s: float = 10.0,
        stroke_um: float = 20.0,
        timeout_s: float = 0.1,
        ramp_um_s: float = 50.0,
        feed_setpoint: float = 800.0,
        **values: float | int,
    ) -> None:
        self.t_s = 0.0
        self.knives = knives
        self.period_s = 1.0 / pairs_per_s
        self.stroke_um = stroke_um
        self.timeout_s = timeout_s
        self.ramp_um_s = ramp_um_s
        self.seq = 0
        self.next_frame_s = self.period_s
        self.heartbeat_plc = 0
        self.heartbeat_service: int | None = None
        self.feed_setpoint = float(feed_setpoint)
        self.offsets_um = np.zeros(knives)
        self.enable = False
        self.last_cmd_s: float | None = None
        self.alive_counters: list[int] = []
        self.injected: list[tuple[str, dict]] = []
        self.values = {r.name: 0 for r in RMAP}
        self.values.update(
            feed_min_mm_s=50.0,
            feed_max_mm_s=1000.0,
            feed_accel_max_mm_s2=2000.0,
            spindle_rpm=6000.0,
            knives=knives,
            cutter_to_camera_mm=300.0,
            counts_per_mm=20.0,
            watchdog_ms=1000,
            cutterhead_radius_mm=60.0,
            encoder_counts=4_000_000_000,
            index_latch_counts=123_456,
        )
        unknown = set(values) - set(self.values)
        if unknown:
            raise ValueError(f"not registers of the map: {sorted(unknown)}")
        self.values.update(values)

    # the Machine API -------------------------------------------------------------------------
    def advance(self, dt_s: float) -> list[Frame]:
        self.t_s += dt_s
        self.heartbeat_plc = (self.heartbeat_plc + 1) & 0xFFFF
        if self.last_cmd_s is not None and self.t_s - self.last_cmd_s > self.timeout_s:
            step = self.ramp_um_s * dt_s
            self.offsets_um = np.sign(self.offsets_um) * np.maximum(
                np.abs(self.offsets_um) - step, 0.0
            )
        out = []
        while self.t_s >= self.next_frame_s - 1e-12:
            self.seq += 1
            img = np.full((8, 16), self.seq % 256, np.uint8)
            out.append(
                Frame(
                    seq=self.seq,
                    t_s=self.next_frame_s,
                    image_a=img,
                    image_b=img + 1,
                    counts_a=self.seq * 100,
                    counts_b=self.seq * 100 + 40,
                    speed_mm_s=self.feed_setpoint,
                )
            )
            self.next_frame_s += self.period_s
        return out

    def register_values(self) -> dict[str, float | int]:
        v = dict(self.values)
        v["heartbeat_plc"] = self.heartbeat_plc
        v["feed_setpoint_mm_s"] = self.feed_setpoint
        v["feed_actual_mm_s"] = self.feed_setpoint
        v["heartbeat_service"] = self.heartbeat_service or 0
        v["trigger_seq"] = self.seq & 0xFFFF
        return v

    def set_feed_setpoint(self, feed_mm_s: float) -> None:
        if not self.values["feed_min_mm_s"] <= feed_mm_s <= self.values["feed_max_mm_s"]:
            raise ValueError(f"feed_mm_s out of range: {feed_mm_s}")
        self.feed_setpoint = feed_mm_s

    def set_service_heartbeat(self, value: int) -> None:
        self.heartbeat_service = value

    def piezo_command(self, *, enable: bool, alive_counter: int, knives: int | None = None) -> None:
        if knives is not None and knives != self.knives:
            raise ValueError(f"knives {knives} is not the machine's {self.knives}")
        self.enable = enable
        self.last_cmd_s = self.t_s
        self.alive_counters.append(alive_counter)

    def set_piezo_offsets(self, offsets_um) -> None:
        arr = np.asarray(offsets_um, float)
        if arr.shape != (self.knives,):
            raise ValueError(f"offsets_um must have {self.knives} values")
        if np.any(np.abs(arr) > self.stroke_um):
            raise ValueError("offsets_um beyond the stroke")
        self.offsets_um = arr

    def timed_out(self) -> bool:
        return self.last_cmd_s is not None and self.t_s - self.last_cmd_s > self.timeout_s

    def piezo_status(self):
        ramping = self.timed_out() and np.any(self.offsets_um != 0)
        return SimpleNamespace(
            displacement_um=float(np.max(np.abs(self.offsets_um))),
            temperature_c=25.0,
            fault=4 if self.timed_out() else 0,
            state=2 if ramping else (1 if self.enable else 0),
        )

    def inject(self, fault: str, **params) -> None:
        self.injected.append((fault, params))

    def take_interface_events(self) -> list[dict]:
        """Like the real machine: interface faults that came due, handed to the runner."""
        due = [
            {"kind": f, "t_s": self.t_s, **{k: v for k, v in p.items() if k != "at_s"}}
            for f, p in self.injected
            if f in ("modbus_restart", "can_silence") and p.get("at_s", 0.0) <= self.t_s + 1e-9
        ]
        self.injected = [
            (f, p)
            for f, p in self.injected
            if not (
                f in ("modbus_restart", "can_silence") and p.get("at_s", 0.0) <= self.t_s + 1e-9
            )
        ]
        return due


# ------------------------------------------------------------------------------ the server
