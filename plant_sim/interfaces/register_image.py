"""The words a PLC serves: the single map's span and one block per head (sans-I/O).

The PLC server (:mod:`plant_sim.interfaces.plc_server`), its process
(:mod:`plant_sim.interfaces.plc_process`) and the in-process bus
(:mod:`plant_sim.interfaces.register_bus`) all answer from a :class:`RegisterImage`:

* reads lie wholly in the single map's span (``RegisterMap.common_span``, the legacy registers:
  the first head's fields at their old addresses) or wholly in one served head's block
  (``RegisterMap.head_span``; the block's reserved words read 0), or, where the map's
  ``[heads] read_across`` says so, wholly in the served blocks (one read over several heads'
  consecutive blocks); anything else is refused
  (:class:`~protocol.registers.RegisterAccessError`, exception 02);
* a write in the single span is checked by the whole map, one in block ``i`` by head ``i``'s
  view (``RegisterMap.for_head``), its limits resolved against that head's values
  (``spindle_setpoint_rpm`` within ``spindle_rpm_min..spindle_rpm_max``);
* :func:`apply` hands accepted writes to the machine: the single map's through
  :func:`~protocol.registers.apply_writes`, a block's through
  :func:`~protocol.registers.apply_head_writes` (``set_spindle_setpoint(i, rpm)``).

How many heads a machine serves: :func:`heads_served` (``head_count`` of a machine with
``head_register_values``, 1 when it has no ``head_count``; 0 without ``head_register_values``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from protocol.registers import (
    RegisterAccessError,
    RegisterMap,
    apply_head_writes,
    apply_writes,
)

__all__ = ["HeadWrite", "RegisterImage", "apply", "heads_served"]

Values = Mapping[str, float | int]
HeadWrite = tuple[int | None, dict[str, float | int]]
"""An accepted write: the head whose block it went to (``None``: the single map) and values."""


def heads_served(machine: Any, regmap: RegisterMap) -> int:
    """Head blocks a PLC over ``machine`` serves (at most the map's ``head_count``)."""
    if regmap.heads is None or not hasattr(machine, "head_register_values"):
        return 0
    return max(0, min(int(getattr(machine, "head_count", 1)), regmap.head_count))


def head_values(machine: Any, count: int) -> list[dict[str, float | int]]:
    """``machine.head_register_values(i)`` for the first ``count`` heads."""
    return [dict(machine.head_register_values(i)) for i in range(count)]


def apply(machine: Any, write: HeadWrite) -> None:
    """Apply one accepted write to the machine (``ValueError`` subclasses when it refuses)."""
    head, accepted = write
    if head is None:
        apply_writes(machine, accepted)
    else:
        apply_head_writes(machine, head, accepted)


class RegisterImage:
    """Encoded words of the single map's span and of ``heads`` head blocks.

    Parameters
    ----------
    regmap : RegisterMap
        The map (a view is taken as its whole map).
    heads : int
        Head blocks served, ``0 <= heads <= regmap.head_count``.
    """

    def __init__(self, regmap: RegisterMap, heads: int = 0) -> None:
        self.rmap = regmap.whole
        if not 0 <= heads <= self.rmap.head_count:
            raise ValueError(f"heads must be 0..{self.rmap.head_count}, got {heads!r}")
        self.heads = int(heads)
        self.first, self.count = self.rmap.common_span()
        block = self.rmap.heads
        self.stride = block.stride if block is not None else 0
        self.views = [self.rmap.for_head(i) for i in range(self.heads)]
        # the block's layout, the same in every block: found once, not per cycle
        self._slots: dict[str, tuple[int, int]] = (
            {} if block is None else {r.name: (r.address, r.count) for r in block.registers})
        """Each block register's offset and words."""
        self._bases = [block.address(i) for i in range(self.heads)] if block is not None else []
        """Each served block's first address."""
        self._used = block.used if block is not None else 0
        self._across = block is not None and block.read_across
        """Reads may run across the served blocks (``[heads] read_across``)."""
        self._values: dict[str, float | int] | None = {}
        self._head_values: list[dict[str, float | int]] | None = [{} for _ in range(self.heads)]
        self.words: list[int] = [0] * self.count
        self.head_words: list[list[int]] = [[0] * self.stride for _ in range(self.heads)]

    @property
    def values(self) -> dict[str, float | int]:
        """The single map's values (decoded from the words when they were loaded as words)."""
        if self._values is None:
            self._values = self.rmap.decode_block(self.words, self.first)
        return self._values

    @property
    def head_values(self) -> list[dict[str, float | int]]:
        """Each served head's block values (decoded likewise)."""
        if self._head_values is None:
            heads = []
            for i, view in enumerate(self.views):
                decoded = view.decode_block(self.head_words[i][: self._used], self._bases[i])
                heads.append({k: v for k, v in decoded.items() if k in self._slots})
            self._head_values = heads
        return self._head_values

    @property
    def size(self) -> int:
        """Words of the whole image (the single span, then every served block)."""
        return self.count + self.heads * self.stride

    def load(self, values: Values, heads: Sequence[Values] = ()) -> None:
        """Encode the single map's ``values`` and each served head's values."""
        if len(heads) != self.heads:
            raise ValueError(f"expected values of {self.heads} heads, got {len(heads)}")
        self._values = dict(values)
        self.words = self.rmap.encode_block(self._values)
        self._head_values = [dict(h) for h in heads]
        self.head_words = [self._encode_head(i) for i in range(self.heads)]

    def _encode_head(self, i: int) -> list[int]:
        view = self.views[i]
        out = [0] * self.stride
        for name, value in self.head_values[i].items():
            slot = self._slots.get(name)
            if slot is None:
                raise ValueError(f"head {i}: {name!r} is no register of the head block")
            off, n = slot
            out[off : off + n] = view.encode(name, value)
        return out

    def flat(self) -> list[int]:
        """All words: the single span, then the blocks (the shared block's layout)."""
        out = list(self.words)
        for block in self.head_words:
            out += block
        return out

    def load_flat(self, words: Sequence[int]) -> None:
        """Load words laid out as :meth:`flat` gives them.

        The words are served as they are (a block's reserved words read 0); the values are
        decoded from them when first asked for (:attr:`values`, :attr:`head_values`: a write's
        check), not per load.
        """
        ws = [int(w) for w in words]
        if len(ws) != self.size:
            raise ValueError(f"expected {self.size} words, got {len(ws)}")
        self.words = ws[: self.count]
        used, stride = self._used, self.stride
        self.head_words = [
            ws[start : start + used] + [0] * (stride - used)
            for start in range(self.count, self.size, stride)]
        self._values = None
        self._head_values = None

    def _head_of(self, address: int) -> int | None:
        """The served head whose block covers ``address`` (``None``: no served block)."""
        if self.rmap.heads is None:
            return None
        i = self.rmap.heads.head_at(address)
        return i if i is not None and i < self.heads else None

    def read(self, address: int, count: int) -> list[int]:
        """Words ``[address, address + count)``; refused unless wholly in one range.

        One range: the single span, one served block, or (``[heads] read_across``) the
        served blocks together.

        Raises
        ------
        RegisterAccessError
            The range leaves the single span and every served block (exception 02).
        """
        a, n = int(address), int(count)
        if self.first <= a and a + n <= self.first + self.count:
            return self.words[a - self.first : a - self.first + n]
        i = self._head_of(a)
        if i is not None:
            off = a - self._bases[i]
            if off + n <= self.stride:
                return self.head_words[i][off : off + n]
            if self._across and off + n <= (self.heads - i) * self.stride:
                last = i + (off + n - 1) // self.stride
                words = [w for block in self.head_words[i : last + 1] for w in block]
                return words[off : off + n]
        raise RegisterAccessError(f"read of {n} registers at {a} outside the served map")

    def parse_write(self, address: int, words: Sequence[int]) -> HeadWrite:
        """Check a write against the map or the head's view (``parse_write`` rules).

        Raises
        ------
        RegisterAccessError, RegisterRangeError
            As :meth:`RegisterMap.parse_write` (exceptions 02 / 03).
        """
        i = self._head_of(address)
        if i is None:
            return None, self.rmap.parse_write(address, words, self.values)
        current = {**self.values, **self.head_values[i]}
        return i, self.views[i].parse_write(address, words, current)

    def store(self, write: HeadWrite) -> None:
        """Serve the written values from now on."""
        head, accepted = write
        for name, value in accepted.items():
            if head is None:
                reg = self.rmap[name]
                i = reg.address - self.first
                self.words[i : i + reg.count] = self.rmap.encode(name, value)
                self.values[name] = value
            else:
                off, n = self._slots[name]
                self.head_words[head][off : off + n] = self.views[head].encode(name, value)
                self.head_values[head][name] = value

    def overlay(self, writes: Sequence[HeadWrite]) -> None:
        """Re-encode with written values laid over the loaded ones (writes not yet applied)."""
        for write in writes:
            self.store(write)
