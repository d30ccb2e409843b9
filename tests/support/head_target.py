"""A small PLC target with several heads: what the PLC server and bus need of a ``Moulder``.

``register_values()`` gives the single map (the first head's fields at their legacy addresses,
the common values); ``head_register_values(i)`` head ``i``'s block; ``set_spindle_setpoint(i,
rpm)`` refuses a value outside the head's ``spindle_rpm_min..spindle_rpm_max`` as a drive would.
"""

from __future__ import annotations

from protocol.registers import HeadFault, RegisterMap

RMAP = RegisterMap.load()

# (knives, rpm, rpm_min, rpm_max, cutter_to_camera_mm): the shipped moulder's heads
HEADS = (
    (4, 6000.0, 6000.0, 6000.0, 300.0),
    (2, 9000.0, 9000.0, 9000.0, 320.0),
    (2, 9000.0, 9000.0, 9000.0, 340.0),
    (6, 6000.0, 4000.0, 8000.0, 360.0),
)


class HeadTarget:
    """Heads with distinct values (head ``i``'s ``trigger_seq`` is ``100 + i``, ...)."""

    def __init__(self, heads: int = len(HEADS)) -> None:
        self.head_count = heads
        self.setpoints: list[tuple[int, float]] = []
        self.feed_setpoint = 300.0
        self.heartbeat_service = 0
        self.heads = [self._head(i) for i in range(heads)]
        self.common: dict[str, float | int] = {r.name: 0 for r in RMAP}
        self.common.update(feed_min_mm_s=50.0, feed_max_mm_s=1000.0, feed_setpoint_mm_s=300.0,
                           feed_actual_mm_s=300.0, counts_per_mm=20.0, watchdog_ms=1000,
                           encoder_counts=123_456_789, heartbeat_plc=11)

    @staticmethod
    def _head(i: int) -> dict[str, float | int]:
        knives, rpm, lo, hi, dist = HEADS[i % len(HEADS)]
        return {
            "spindle_rpm": rpm + i, "spindle_setpoint_rpm": rpm, "spindle_rpm_min": lo,
            "spindle_rpm_max": hi, "knives": knives, "cutterhead_radius_mm": 60.0 + i,
            "cutter_to_camera_mm": dist, "trigger_a_counts": 1000 * i + 1,
            "trigger_b_counts": 1000 * i + 2, "trigger_seq": 100 + i,
            "index_latch_counts": 0xFFFF_0000 + i,
            "head_faults": int(HeadFault.CAMERA_SILENT) if i == 2 else 0,
        }

    def _fill(self, i: int, values: dict[str, float | int]) -> dict[str, float | int]:
        """Block registers beyond the design's (what the head's camera sees): the common value."""
        assert RMAP.heads is not None
        for name in RMAP.heads.names:
            values.setdefault(name, self.common.get(name, 0))
        return values

    def register_values(self) -> dict[str, float | int]:
        out = dict(self.common)
        out.update({k: v for k, v in self.heads[0].items() if k in out})
        out["heartbeat_service"] = self.heartbeat_service
        out["feed_setpoint_mm_s"] = self.feed_setpoint
        return out

    def head_register_values(self, i: int) -> dict[str, float | int]:
        if not 0 <= i < self.head_count:
            raise ValueError(f"head {i} outside 0..{self.head_count - 1}")
        return self._fill(i, dict(self.heads[i]))

    def set_spindle_setpoint(self, i: int, rpm: float) -> None:
        h = self.heads[i]
        if not h["spindle_rpm_min"] <= rpm <= h["spindle_rpm_max"]:
            raise ValueError(f"rpm {rpm} outside the drive's range")
        h["spindle_setpoint_rpm"] = rpm
        self.setpoints.append((i, rpm))

    def set_feed_setpoint(self, feed_mm_s: float) -> None:
        self.feed_setpoint = feed_mm_s

    def set_service_heartbeat(self, value: int) -> None:
        self.heartbeat_service = value
