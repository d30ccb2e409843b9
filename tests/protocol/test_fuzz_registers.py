"""Fuzz of the register map codec: arbitrary register blocks and writes.

Whatever words a PLC (or a client) sends, decoding gives every register lying wholly inside the
block a value of its type, and refusals are ``ValueError`` (``RegisterAccessError`` -> Modbus
exception 02, ``RegisterRangeError`` -> 03) naming the register or the address -- never another
exception type. Example counts are bounded (a few seconds in CI).
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controller.fieldbus.plc_protocol import PlcProtocol, PlcSnapshot
from core.errors import FieldbusError
from protocol.registers import (
    MachineState,
    PlcFault,
    Register,
    RegisterAccessError,
    RegisterMap,
    RegisterRangeError,
)

RMAP = RegisterMap.load()
FIRST, COUNT = RMAP.span()
NAMES = [r.name for r in RMAP]
SCALE = float(os.environ.get("PLANER_FUZZ_SCALE", "1"))
"""Multiplies the example counts: ``PLANER_FUZZ_SCALE=20`` for a deep local run."""
FUZZ = settings(
    max_examples=round(100 * SCALE),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)

words16 = st.integers(0, 0xFFFF)
any_word = st.one_of(words16, st.integers(-(2**20), 2**20))  # also what no register holds
starts = st.one_of(st.integers(FIRST - 4, FIRST + COUNT + 4), st.integers(-(2**31), 2**31))


def _type_ok(name: str, value: object) -> bool:
    reg = RMAP[name]
    if reg.type == "f32":
        return isinstance(value, float)  # NaN and inf included: the decoder reports, not judges
    lo, hi = {"u16": (0, 0xFFFF), "u32": (0, 2**32 - 1), "i32": (-(2**31), 2**31 - 1)}[reg.type]
    return isinstance(value, int) and lo <= value <= hi


@FUZZ
@given(st.lists(words16, max_size=COUNT + 8), starts)
def test_decode_block_of_valid_words_decodes_exactly_the_covered_registers(words, start):
    out = RMAP.decode_block(words, start)
    covered = [r.name for r in RMAP if r.address >= start and r.last_address < start + len(words)]
    assert list(out) == covered  # in address order, nothing partial
    for name, value in out.items():
        assert _type_ok(name, value), (name, value)
        reg = RMAP[name]
        i = reg.address - start
        if reg.type == "f32" and not math.isfinite(value):
            continue
        assert RMAP.encode(name, value) == list(words[i : i + reg.count])  # lossless


@FUZZ
@given(st.lists(any_word, max_size=COUNT + 8), starts)
def test_decode_block_of_any_words_is_a_value_or_a_value_error(words, start):
    try:
        out = RMAP.decode_block(words, start)
    except ValueError as exc:
        assert "register" in str(exc) and "0..65535" in str(exc)
        assert any(not 0 <= w <= 0xFFFF for w in words)
        return
    assert all(_type_ok(n, v) for n, v in out.items())


@FUZZ
@given(st.sampled_from(NAMES), st.lists(any_word, max_size=4))
def test_decode_one_register_refuses_with_its_name(name, words):
    reg = RMAP[name]
    ok = len(words) == reg.count and all(0 <= w <= 0xFFFF for w in words)
    if ok:
        assert _type_ok(name, RMAP.decode(name, words))
    else:
        with pytest.raises(ValueError, match=f"register {name}"):
            RMAP.decode(name, words)


@FUZZ
@given(st.lists(words16, min_size=COUNT, max_size=COUNT))
def test_a_whole_span_read_of_any_words_gives_a_snapshot_that_judges_itself(words):
    """The service's read path: decode, then ``problem()`` says whether it can be trusted."""
    proto = PlcProtocol(RMAP)
    snap = PlcSnapshot(values=proto.decode_read(words), t_s=0.0)
    problem = snap.problem()
    assert problem is None or isinstance(problem, str)
    if problem is None:  # trusted registers are finite and consistent
        assert snap.feed_min_mm_s < snap.feed_max_mm_s
        assert math.isfinite(snap.feed_setpoint_mm_s) and 1 <= snap.knives <= 8
    assert isinstance(snap.machine_state, MachineState) and isinstance(snap.faults, PlcFault)
    assert int(snap.machine_state) == words[RMAP["machine_state"].address - FIRST]


@FUZZ
@given(st.lists(words16, max_size=2 * COUNT).filter(lambda w: len(w) != COUNT))
def test_a_read_of_the_wrong_length_is_a_fieldbus_error(words):
    with pytest.raises(FieldbusError, match=f"expected {COUNT}"):
        PlcProtocol(RMAP).decode_read(words)


CURRENT = RMAP.decode_block(RMAP.encode_block({"feed_min_mm_s": 50.0, "feed_max_mm_s": 1000.0}))


@FUZZ
@given(starts, st.lists(any_word, max_size=8))
def test_parse_write_accepts_only_whole_writable_registers_in_range(address, words):
    try:
        accepted = RMAP.parse_write(address, words, CURRENT)
    except (RegisterAccessError, RegisterRangeError) as exc:
        assert exc.exception_code in (2, 3)
        text = str(exc)
        assert "register" in text or "address" in text or "empty" in text
        return
    except ValueError as exc:  # a word outside 0..65535 (a server never passes one)
        assert any(not 0 <= w <= 0xFFFF for w in words), exc
        return
    assert accepted and all(RMAP[n].writable for n in accepted)
    covered = sum(RMAP[n].count for n in accepted)
    assert covered == len(words)  # the write covered exactly those registers
    for name, value in accepted.items():
        lo, hi = RMAP.limits(name, CURRENT)
        if RMAP[name].type == "f32":  # limits are compared as stored (float32)
            lo, hi = float(np.float32(lo)), float(np.float32(hi))
        assert lo <= value <= hi


# ------------------------------------------------------------ maps other than the shipped one
reg_names = st.sampled_from(["a", "b", "c", "d", "machine_state", "faults"])
limits = st.one_of(st.none(), reg_names, st.integers(-(2**33), 2**33),
                   st.floats(allow_nan=True, allow_infinity=True))


@st.composite
def registers(draw: st.DrawFn) -> Register:
    rtype = draw(st.sampled_from(["u16", "u32", "i32", "f32"]))
    access = draw(st.sampled_from(["ro", "rw"]))
    lo, hi = (draw(limits), draw(limits)) if access == "rw" else (None, None)
    bits = tuple(draw(st.lists(st.sampled_from(["x", "y", "running", "estop"]), max_size=3,
                               unique=True)))
    return Register(
        name=draw(reg_names), address=draw(st.integers(0, 40)), type=rtype, access=access,
        count=2 if rtype != "u16" else 1, min=lo, max=hi, bits=bits,
    )


@FUZZ
@given(st.lists(registers(), min_size=1, max_size=6), st.lists(any_word, max_size=50),
       st.integers(-2, 45), st.lists(words16, min_size=1, max_size=4))
def test_any_map_is_refused_with_a_config_error_or_works_with_value_errors_only(
    regs, words, address, write
):
    from core.errors import ConfigError

    try:
        rmap = RegisterMap(regs)
    except ConfigError as exc:
        assert "register" in str(exc), str(exc)
        return
    values: dict[str, float | int] = {}
    try:
        values = rmap.decode_block(words, address)
    except ValueError:
        pass
    current = rmap.decode_block(rmap.encode_block({}))  # every register 0
    try:
        accepted = rmap.parse_write(address, write, {**current, **values})
    except (RegisterAccessError, RegisterRangeError):
        return
    assert all(rmap[n].writable for n in accepted)
    assert rmap.markdown_table().count("\n") == len(rmap.registers) + 2
