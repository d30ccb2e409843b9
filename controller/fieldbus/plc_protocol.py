"""The PLC's requests and answers without I/O: the decoded snapshot, the request codec, back-off.

* :class:`PlcSnapshot` — all registers of one read, decoded and checked;
* :class:`PlcProtocol` — which words to read (the whole span of ``config/registers.toml`` in one
  request; over a head's view of the map, ``RegisterMap.for_head(i)``, the common span and then
  the head's block), how to decode them, which words to write for the feed setpoint (``f32``,
  two registers, function 16), the heartbeat (``u16``, function 6) and a head's spindle
  setpoint (``f32`` in the head's block);
* :class:`Backoff` — the reconnect policy: capped exponential back-off on an injected clock.

Pure: no asyncio, no pymodbus; :mod:`controller.fieldbus.plc_client` puts them on the bus.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from core.checks import check_finite, check_positive
from core.errors import FieldbusError
from protocol.registers import MachineState, ModbusException, PlcFault, RegisterMap

MODBUS_EXCEPTIONS = {int(code): code.text for code in ModbusException}
"""Exception code to the spec's name, for messages (``protocol.registers.ModbusException``)."""


@dataclass(frozen=True)
class PlcSnapshot:
    """All registers of one read, decoded; the fields the service uses are typed attributes.

    Attributes
    ----------
    values : mapping
        Every register by name (``config/registers.toml``).
    t_s : float
        Time of the answer on the client's clock, seconds.
    """

    values: Mapping[str, float | int]
    t_s: float

    def __getitem__(self, name: str) -> float | int:
        return self.values[name]

    @property
    def spindle_rpm(self) -> float:
        """Measured spindle speed, rpm."""
        return float(self.values["spindle_rpm"])

    @property
    def knives(self) -> int:
        """Number of knives Z."""
        return int(self.values["knives"])

    @property
    def feed_min_mm_s(self) -> float:
        """Lowest accepted feed setpoint, mm/s."""
        return float(self.values["feed_min_mm_s"])

    @property
    def feed_max_mm_s(self) -> float:
        """Highest accepted feed setpoint, mm/s."""
        return float(self.values["feed_max_mm_s"])

    @property
    def feed_setpoint_mm_s(self) -> float:
        """Feed setpoint the PLC holds now, mm/s."""
        return float(self.values["feed_setpoint_mm_s"])

    @property
    def feed_actual_mm_s(self) -> float:
        """Measured feed speed, mm/s."""
        return float(self.values["feed_actual_mm_s"])

    @property
    def cutter_to_camera_mm(self) -> float:
        """Distance L from the cutterhead axis to the camera axis, mm."""
        return float(self.values["cutter_to_camera_mm"])

    @property
    def counts_per_mm(self) -> float:
        """Feed encoder resolution, counts/mm."""
        return float(self.values["counts_per_mm"])

    @property
    def index_latch_counts(self) -> int:
        """Encoder counts at the spindle index pulse of the last pair."""
        return int(self.values["index_latch_counts"])

    @property
    def trigger_seq(self) -> int:
        """Sequence number of the last image pair (mod 2**16)."""
        return int(self.values["trigger_seq"])

    @property
    def machine_state(self) -> MachineState:
        """Machine state bits (running, board present, e-stop, spindle running, feed enabled)."""
        return MachineState(int(self.values["machine_state"]))

    @property
    def faults(self) -> PlcFault:
        """Fault bits (feed drive, spindle stopped, encoder, heartbeat lost, piezo amplifier)."""
        return PlcFault(int(self.values["faults"]))

    @property
    def board_present(self) -> bool:
        """Whether a board is under the camera."""
        return MachineState.BOARD_PRESENT in self.machine_state

    @property
    def estop(self) -> bool:
        """Whether the e-stop is active."""
        return MachineState.ESTOP in self.machine_state

    @property
    def spindle_running(self) -> bool:
        """Whether the spindle runs."""
        return MachineState.SPINDLE_RUNNING in self.machine_state

    def problem(self) -> str | None:
        """Why these registers cannot be trusted for control, or ``None`` when they can.

        A PLC that answers nonsense (NaN or infinite floats, no knives, a zero encoder scale,
        inverted feed limits...) must not drive the loops: the service
        treats such an answer like a machine that is not fit to run (safe state, no feed write).

        Returns
        -------
        str or None
            The first problem found, naming the register(s).
        """
        v = self.values
        try:
            knives = int(v["knives"])
            if not 1 <= knives <= MAX_KNIVES:
                return f"knives = {knives} (must be 1..{MAX_KNIVES})"
            for name in _POSITIVE:
                x = float(v[name])
                if not (math.isfinite(x) and x > 0):
                    return f"{name} = {x!r} (must be finite and > 0)"
            for name in _NON_NEGATIVE:
                x = float(v[name])
                if not (math.isfinite(x) and x >= 0):
                    return f"{name} = {x!r} (must be finite and >= 0)"
            if not math.isfinite(self.feed_actual_mm_s):
                return f"feed_actual_mm_s = {self.feed_actual_mm_s!r} (must be finite)"
            lo, hi = self.feed_min_mm_s, self.feed_max_mm_s
            if not lo < hi:
                return f"feed_min_mm_s {lo!r} >= feed_max_mm_s {hi!r}"
            if not math.isfinite(self.feed_setpoint_mm_s):
                return f"feed_setpoint_mm_s = {self.feed_setpoint_mm_s!r} (must be finite)"
        except KeyError as exc:
            return f"register {exc} missing"
        except (TypeError, ValueError) as exc:
            return f"unreadable value: {exc}"
        return None


MAX_KNIVES = 8
"""Most knives the piezo frames carry."""
MAX_READ_WORDS = 125
"""Most registers one Modbus read (function 3 or 23) returns."""
MAX_PLANS = 64
"""Sequences of heads whose block reads a protocol keeps planned (a moulder asks for one)."""
_INT_ONLY = frozenset({int})
BlocksReads = tuple[tuple[int, int, tuple[int, ...]], ...]
"""Reads of head blocks: ``(address, words, heads)`` each (:meth:`PlcProtocol.blocks_reads`)."""
_POSITIVE = (
    "feed_min_mm_s",
    "feed_max_mm_s",
    "counts_per_mm",
    "cutter_to_camera_mm",
    "cutterhead_radius_mm",
)
_NON_NEGATIVE = ("spindle_rpm", "feed_accel_max_mm_s2")


def int_words(words: Sequence[int]) -> list[int]:
    """``[int(w) for w in words]``: a new list of the words as plain ints.

    Words that are plain ints already (what a bus answers) are copied as they are, without a
    conversion each; any other word (a numpy integer, a float, a bool) is converted, and a word
    ``int`` refuses raises as ``int`` does.
    """
    ws = list(words)
    if set(map(type, ws)) <= _INT_ONLY:
        return ws
    return [int(w) for w in ws]


class PlcProtocol:
    """Sans-I/O Modbus requests and answers over a :class:`RegisterMap` (built once).

    Parameters
    ----------
    regmap : RegisterMap
        The register map.
    """

    def __init__(self, regmap: RegisterMap) -> None:
        self.regmap = regmap
        self.ranges = regmap.read_ranges()
        """The ``(address, words)`` ranges one sample reads, in order."""
        self.read_address, self.read_count = self.ranges[0]
        self.block: tuple[int, int] | None = self.ranges[1] if len(self.ranges) > 1 else None
        """The head's block ``(address, words)`` over a head's view; ``None`` otherwise."""
        self._feed = regmap["feed_setpoint_mm_s"]
        self._hb = regmap["heartbeat_service"]
        self._spindle = regmap.registers.get("spindle_setpoint_rpm")
        self._blocks_reads: dict[tuple[int, ...], BlocksReads] = {}

    def blocks_reads(self, heads: Sequence[int]) -> BlocksReads:
        """The reads that fetch the blocks of ``heads``: ``(address, words, heads)`` each.

        One read per block, or, where the map's ``[heads] read_across`` lets a read run across
        blocks, one per run of consecutive heads (at most :data:`MAX_READ_WORDS` words: the
        last block's used words, the others' whole stride with their reserved words).
        ``ValueError`` naming a head outside the map's blocks (or a map without blocks).
        Planned once per sequence of heads given as plain ints (a moulder's coordinator asks
        for the same heads every PLC cycle); any other kind of index is checked each time.
        """
        key = tuple(heads)
        if all(type(h) is int for h in key):  # bools and other numbers take the long way
            plan = self._blocks_reads.get(key)
            if plan is None:
                if len(self._blocks_reads) >= MAX_PLANS:  # a caller asking ever new sets
                    self._blocks_reads.clear()
                plan = self._blocks_reads[key] = self._plan_blocks_reads(key)
            return plan
        return self._plan_blocks_reads(key)

    def _plan_blocks_reads(self, heads: Sequence[int]) -> BlocksReads:
        """:meth:`blocks_reads` worked out (every head checked)."""
        block = self.regmap.heads
        if block is None:
            raise ValueError("heads: the register map has no [heads] blocks")
        for h in heads:
            block.address(h)  # ValueError naming a bad head
        order = sorted({int(h) for h in heads})
        out: list[tuple[int, int, tuple[int, ...]]] = []
        run: list[int] = []
        used = block.used
        for h in order:
            fits = (block.read_across and run and h == run[-1] + 1
                    and (h - run[0]) * block.stride + used <= MAX_READ_WORDS)
            if run and not fits:
                out.append(self._blocks_read(run))
                run = []
            run.append(h)
        if run:
            out.append(self._blocks_read(run))
        return tuple(out)

    def _blocks_read(self, run: Sequence[int]) -> tuple[int, int, tuple[int, ...]]:
        block = self.regmap.heads
        assert block is not None
        first = block.address(run[0])
        return first, (len(run) - 1) * block.stride + block.used, tuple(run)

    def split_blocks(self, read: tuple[int, int, tuple[int, ...]],
                     words: Sequence[int]) -> dict[int, list[int]]:
        """The words of each head's block (its used words) in the answer to one read.

        ``read`` is one of :meth:`blocks_reads`; ``FieldbusError`` when the answer has another
        length.
        """
        _, count, heads = read
        if len(words) != count:
            raise FieldbusError(f"PLC answered {len(words)} registers, expected {count}")
        block = self.regmap.heads
        assert block is not None
        stride, used, h0 = block.stride, block.used, heads[0]
        return {h: int_words(words[(h - h0) * stride:][:used]) for h in heads}

    def decode_read(self, words: Sequence[int]) -> dict[str, float | int]:
        """Decode the words of one whole-span read into every register's value."""
        return self.decode_range(0, words)

    def decode_range(self, index: int, words: Sequence[int]) -> dict[str, float | int]:
        """Decode the words read from ``ranges[index]`` into its registers' values."""
        address, count = self.ranges[index]
        if len(words) != count:
            raise FieldbusError(f"PLC answered {len(words)} registers, expected {count}")
        return self.regmap.decode_block(words, address)

    def spindle_request(
        self, rpm: float, current: Mapping[str, float | int] | None = None
    ) -> tuple[int, list[int]]:
        """Address and words writing the head's spindle setpoint (a head's view only).

        Checked against ``spindle_rpm_min..spindle_rpm_max`` of ``current`` when given
        (``ValueError`` naming the register).
        """
        if self._spindle is None:
            raise ValueError(
                "spindle_setpoint_rpm: the client's register map is no head's view "
                "(RegisterMap.for_head(i))"
            )
        v = check_finite("rpm", rpm)
        if current is not None:
            self.regmap.check_write(self._spindle.name, v, current)
        return self._spindle.address, self.regmap.encode(self._spindle.name, v)

    def feed_request(
        self, feed_mm_s: float, current: Mapping[str, float | int] | None = None
    ) -> tuple[int, list[int]]:
        """Address and words writing the feed setpoint (checked against the limits if known)."""
        v = check_finite("feed_mm_s", feed_mm_s)
        if current is not None:
            self.regmap.check_write(self._feed.name, v, current)
        return self._feed.address, self.regmap.encode(self._feed.name, v)

    def heartbeat_request(self, value: int) -> tuple[int, list[int]]:
        """Address and word writing the service heartbeat (wrapped to 16 bits)."""
        return self._hb.address, self.regmap.encode(self._hb.name, int(value) & 0xFFFF)

    def names_at(self, address: int, count: int) -> str:
        """Names of the registers in ``[address, address + count)`` for error messages."""
        names: list[str] = []
        for a in range(address, address + count):
            reg = self.regmap.at(a)
            if reg is not None and reg.name not in names:
                names.append(reg.name)
        if not names:
            return f"address {address}"
        if len(names) > 3:
            return f"{names[0]}..{names[-1]} ({address}..{address + count - 1})"
        return ", ".join(names)


class Backoff:
    """Capped exponential back-off for reconnect attempts (pure; time passed in).

    Parameters
    ----------
    initial_s : float
        Wait after the first failure, seconds.
    max_s : float
        Cap of the wait, seconds.
    factor : float
        Growth per consecutive failure.
    """

    def __init__(self, initial_s: float, max_s: float, *, factor: float = 2.0) -> None:
        self.initial_s = check_positive("initial_s", initial_s)
        self.max_s = check_positive("max_s", max_s)
        if self.max_s < self.initial_s:
            raise ValueError(f"max_s {max_s} < initial_s {initial_s}")
        self.factor = check_positive("factor", factor)
        self.failures = 0
        self.next_attempt_s = float("-inf")

    def delay_s(self) -> float:
        """Wait after the current number of consecutive failures."""
        if self.failures == 0:
            return 0.0
        return min(self.max_s, self.initial_s * self.factor ** (self.failures - 1))

    def failed(self, now_s: float) -> float:
        """Record a failed attempt at ``now_s``; return the time of the next allowed attempt."""
        self.failures += 1
        self.next_attempt_s = check_finite("now_s", now_s) + self.delay_s()
        return self.next_attempt_s

    def succeeded(self) -> None:
        """Record a success: the next failure starts from ``initial_s`` again."""
        self.failures = 0
        self.next_attempt_s = float("-inf")

    def may_attempt(self, now_s: float) -> bool:
        """Whether an attempt is allowed at ``now_s``."""
        return now_s >= self.next_attempt_s
