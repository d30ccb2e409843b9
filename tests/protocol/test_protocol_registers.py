"""The register map codec: word order, round trips, limits, write checks, config validation."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from config.loading import default_path, load_toml
from core.errors import ConfigError
from protocol.registers import (
    BIT_FLAGS,
    WRITE_DISPATCH,
    MachineState,
    PlcFault,
    RegisterAccessError,
    RegisterMap,
    RegisterRangeError,
    apply_writes,
    flag_names,
)

RMAP = RegisterMap.load()
TOML = load_toml(default_path("registers.toml"))


def _names(rtype: str) -> list[str]:
    return [r.name for r in RMAP if r.type == rtype]


def test_loads_every_register_of_the_toml():
    assert set(RMAP.registers) == {e["name"] for e in TOML["register"]}
    for e in TOML["register"]:
        reg = RMAP[e["name"]]
        assert (reg.address, reg.type, reg.access) == (e["address"], e["type"], e["access"])
        assert reg.count == (1 if e["type"] == "u16" else 2)
    first, count = RMAP.span()
    assert first == min(e["address"] for e in TOML["register"])
    assert first + count - 1 == max(RMAP[e["name"]].last_address for e in TOML["register"])
    assert RMAP.unit_id == TOML["map"]["unit_id"]


def test_no_two_registers_share_an_address():
    seen: set[int] = set()
    for reg in RMAP:
        words = set(range(reg.address, reg.address + reg.count))
        assert not words & seen
        seen |= words


@given(st.floats(width=32, allow_nan=False, allow_infinity=False))
def test_f32_big_endian_word_order_and_round_trip(x):
    name = _names("f32")[0]
    words = RMAP.encode(name, x)
    # ABCD: high word first; bytes of the IEEE-754 big-endian representation
    assert struct.pack(">HH", *words) == struct.pack(">f", x)
    assert RMAP.decode(name, words) == x


@given(st.integers(0, 2**32 - 1))
def test_u32_high_word_first(x):
    name = _names("u32")[0]
    words = RMAP.encode(name, x)
    assert words == [x >> 16, x & 0xFFFF]
    assert RMAP.decode(name, words) == x


@given(st.integers(-(2**31), 2**31 - 1))
def test_i32_twos_complement_round_trip(x):
    # the shipped map has no i32 register: build a one-register map
    from protocol.registers import Register

    m = RegisterMap([Register("pos", 10, "i32", "rw", 2)])
    words = m.encode("pos", x)
    assert struct.pack(">HH", *words) == struct.pack(">i", x)
    assert m.decode("pos", words) == x


def test_little_word_order_swaps_words():
    from protocol.registers import Register

    regs = [Register("v", 0, "u32", "ro", 2)]
    big = RegisterMap(regs, word_order="big").encode("v", 0x12345678)
    little = RegisterMap(regs, word_order="little").encode("v", 0x12345678)
    assert big == [0x1234, 0x5678] and little == [0x5678, 0x1234]


@pytest.mark.parametrize(
    ("rtype", "bad"),
    [
        ("u16", -1),
        ("u16", 65536),
        ("u16", 1.5),
        ("u32", 2**32),
        ("u32", -1),
        ("f32", float("nan")),
        ("f32", float("inf")),
        ("f32", 1e39),
        ("f32", "fast"),
        ("u16", True),
    ],
)
def test_encode_rejects_values_that_do_not_fit_naming_the_register(rtype, bad):
    name = _names(rtype)[0]
    with pytest.raises(ValueError, match=name):
        RMAP.encode(name, bad)


def test_decode_checks_word_count_and_range():
    name = _names("f32")[0]
    with pytest.raises(ValueError, match=name):
        RMAP.decode(name, [1])
    with pytest.raises(ValueError, match=name):
        RMAP.decode(name, [1, 70000])


values_strategy = st.fixed_dictionaries(
    {
        r.name: (
            st.integers(0, 0xFFFF)
            if r.type == "u16"
            else st.integers(0, 2**32 - 1)
            if r.type == "u32"
            else st.floats(width=32, allow_nan=False, allow_infinity=False)
        )
        for r in RMAP
    }
)


@given(values_strategy)
def test_block_round_trip(values):
    words = RMAP.encode_block(values)
    assert len(words) == RMAP.span()[1]
    assert RMAP.decode_block(words) == values


def test_block_missing_is_zero_and_partial_blocks_decode_whole_registers_only():
    words = RMAP.encode_block({"feed_setpoint_mm_s": 12.5})
    assert RMAP.decode_block(words)["feed_min_mm_s"] == 0.0
    reg = RMAP["feed_setpoint_mm_s"]
    part = RMAP.decode_block(words[reg.address : reg.address + 3], start=reg.address)
    assert part == {"feed_setpoint_mm_s": 12.5}  # the next f32 is cut in half: left out
    with pytest.raises(ValueError, match="nope"):
        RMAP.encode_block({"nope": 1})


CURRENT = {"feed_min_mm_s": 5.0, "feed_max_mm_s": 120.0}


def test_limits_resolve_register_names():
    assert RMAP.limits("feed_setpoint_mm_s", CURRENT) == (5.0, 120.0)
    assert RMAP.limits("heartbeat_service", {}) == (0, 65535)
    with pytest.raises(ValueError, match="feed_min_mm_s"):
        RMAP.limits("feed_setpoint_mm_s", {})


@pytest.mark.parametrize("value", [5.0, 60.0, 120.0])
def test_check_write_accepts_inside_limits(value):
    assert RMAP.check_write("feed_setpoint_mm_s", value, CURRENT) == value


@pytest.mark.parametrize("value", [4.99, 120.01, -1.0, float("nan"), 1e39])
def test_check_write_refuses_outside_limits(value):
    with pytest.raises(RegisterRangeError, match="feed_setpoint_mm_s"):
        RMAP.check_write("feed_setpoint_mm_s", value, CURRENT)


def test_check_write_accepts_a_limit_read_back_from_its_f32_register():
    cur = {"feed_min_mm_s": 0.1, "feed_max_mm_s": 0.3}  # not exact in float32
    hi = RMAP.decode("feed_max_mm_s", RMAP.encode("feed_max_mm_s", 0.3))
    assert hi > 0.3
    assert RMAP.check_write("feed_setpoint_mm_s", hi, cur) == hi


@pytest.mark.parametrize("name", [r.name for r in RMAP if r.access == "ro"])
def test_check_write_refuses_read_only(name):
    with pytest.raises(RegisterAccessError, match=name):
        RMAP.check_write(name, 0, CURRENT)


def test_parse_write_rules():
    sp = RMAP["feed_setpoint_mm_s"]
    words = RMAP.encode("feed_setpoint_mm_s", 42.0)
    assert RMAP.parse_write(sp.address, words, CURRENT) == {"feed_setpoint_mm_s": 42.0}
    with pytest.raises(RegisterAccessError, match="all 2 words"):
        RMAP.parse_write(sp.address, words[:1], CURRENT)
    with pytest.raises(RegisterAccessError, match="all 2 words"):
        RMAP.parse_write(sp.address + 1, words[1:], CURRENT)
    with pytest.raises(RegisterRangeError):
        RMAP.parse_write(sp.address, RMAP.encode("feed_setpoint_mm_s", 500.0), CURRENT)
    # a multi-register write spanning a read-only register is refused as a whole
    block = RMAP.encode_block({"heartbeat_service": 3})
    with pytest.raises(RegisterAccessError, match="heartbeat_plc"):
        RMAP.parse_write(0, block[:2], CURRENT)
    assert RMAP.parse_write(0, [7], CURRENT) == {"heartbeat_service": 7}
    gaps = [a for a in range(*RMAP.span()) if RMAP.at(a) is None]
    for a in gaps:
        with pytest.raises(RegisterAccessError, match=str(a)):
            RMAP.parse_write(a, [0], CURRENT)
    first, count = RMAP.span()
    with pytest.raises(RegisterAccessError):
        RMAP.parse_write(first + count, [0], CURRENT)


def _write_map(tmp_path: Path, body: str) -> Path:
    p = tmp_path / "r.toml"
    p.write_text(body)
    return p


GOOD = """
[map]
unit_id = 1
word_order = "big"
[[register]]
name = "a"
address = 0
type = "f32"
access = "rw"
min = 0.0
max = "b"
[[register]]
name = "b"
address = 2
type = "f32"
access = "ro"
"""


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (lambda s: s.replace('name = "b"\naddress = 2', 'name = "b"\naddress = 1'), "overlaps"),
        (lambda s: s.replace('type = "f32"\naccess = "ro"', 'type = "f64"\naccess = "ro"'), "b"),
        (lambda s: s.replace('access = "ro"', 'access = "wo"'), "register b"),
        (lambda s: s.replace('max = "b"', 'max = "c"'), "register a"),
        (lambda s: s.replace('max = "b"', 'max = "a"'), "register a"),
        (lambda s: s.replace("min = 0.0", "min = 0.0\nscale = 2"), "register a.scale"),
        (lambda s: s.replace('word_order = "big"', 'word_order = "middle"'), "word_order"),
        (lambda s: s.replace("unit_id = 1", "unit_id = 1\nfoo = 2"), "map.foo"),
        (lambda s: s.replace('name = "b"', 'name = "a"'), "duplicate"),
        (lambda s: s.replace("min = 0.0", "min = 5.0\nmax = 1.0").replace('max = "b"', ""), "a"),
    ],
)
def test_load_rejects_bad_maps_naming_the_register(tmp_path, edit, needle):
    assert RegisterMap.load(_write_map(tmp_path, GOOD)).span() == (0, 4)
    path = _write_map(tmp_path, edit(GOOD))
    with pytest.raises(ConfigError, match=needle) as err:
        RegisterMap.load(path)
    assert str(err.value).startswith(f"{path}: ")  # every error names the file too


# ------------------------------------------------------------------ flag bits, write dispatch
def test_flag_enums_are_the_bits_the_toml_declares():
    # a block entry naming a [[register]] has no bits of its own: the [[register]] entry's count
    by_name = {e["name"]: e for e in [*TOML["heads"]["register"], *TOML["register"]]}
    head = RMAP.for_head(0)
    for name, flags in BIT_FLAGS.items():
        declared = by_name[name]["bits"]
        assert head[name].bits == tuple(declared) == flag_names(flags)
        for i, bit in enumerate(declared):  # bit i of the TOML is the member of value 1 << i
            assert flags[bit.upper()].value == 1 << i
    assert MachineState.BOARD_PRESENT == 2 and PlcFault.HEARTBEAT_LOST == 8  # the documented bits


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (lambda b: b[::-1], "bits must be"),
        (lambda b: b[:-1], "bits must be"),
        (lambda b: [*b, "extra"], "bits must be"),
        (lambda b: None, "bits must be"),
    ],
)
def test_load_refuses_flag_bits_that_differ_from_the_enums(tmp_path, edit, needle):
    text = default_path("registers.toml").read_text()
    line = "bits = [" + ", ".join(f'"{b}"' for b in flag_names(PlcFault)) + "]"
    assert line in text
    bits = edit(list(flag_names(PlcFault)))
    new = "" if bits is None else "bits = [" + ", ".join(f'"{b}"' for b in bits) + "]"
    path = _write_map(tmp_path, text.replace(line, new))
    with pytest.raises(ConfigError, match=needle) as err:
        RegisterMap.load(path)
    assert str(path) in str(err.value) and "register faults" in str(err.value)


@pytest.mark.parametrize(
    ("bits", "needle"),
    [('"x"', "list of bit names"), ("[1, 2]", "list of bit names"), ('["a b"]', "identifier"),
     ('["a", "a"]', "duplicate"), ("[" + ", ".join(f'"b{i}"' for i in range(33)) + "]", "33")],
)
def test_load_refuses_malformed_bits(tmp_path, bits, needle):
    body = GOOD.replace('"f32"\naccess = "ro"', f'"u32"\naccess = "ro"\nbits = {bits}')
    with pytest.raises(ConfigError, match=needle):
        RegisterMap.load(_write_map(tmp_path, body))


def test_bits_only_on_integer_registers(tmp_path):
    body = GOOD.replace('access = "ro"', 'access = "ro"\nbits = ["x"]')
    with pytest.raises(ConfigError, match="register b: bits only on u16 or u32"):
        RegisterMap.load(_write_map(tmp_path, body))


def test_every_writable_register_has_one_write_action():
    assert set(WRITE_DISPATCH) == {r.name for r in RMAP if r.writable}


class _Target:
    def __init__(self, refuse_feed: bool = False) -> None:
        self.calls: list[tuple[str, object]] = []
        self.refuse_feed = refuse_feed

    def set_feed_setpoint(self, feed_mm_s: float) -> None:
        if self.refuse_feed:
            raise ValueError("feed drive says no")
        self.calls.append(("feed", feed_mm_s))

    def set_service_heartbeat(self, value: int) -> None:
        self.calls.append(("hb", value))


CURRENT_VALUES = {"feed_min_mm_s": 100.0, "feed_max_mm_s": 900.0}


def test_apply_writes_dispatches_by_register_name_with_the_register_type():
    t = _Target()
    apply_writes(t, RMAP.parse_write(0, [7], CURRENT_VALUES))
    apply_writes(t, RMAP.parse_write(2, RMAP.encode("feed_setpoint_mm_s", 600.0), CURRENT_VALUES))
    assert t.calls == [("hb", 7), ("feed", 600.0)]
    assert type(t.calls[0][1]) is int and type(t.calls[1][1]) is float


def test_apply_writes_refusals_carry_the_modbus_code_and_the_register():
    with pytest.raises(RegisterRangeError, match="register feed_setpoint_mm_s: feed drive says"):
        apply_writes(_Target(refuse_feed=True), {"feed_setpoint_mm_s": 500.0})
    t = _Target()
    with pytest.raises(RegisterAccessError, match="register knives"):
        apply_writes(t, {"heartbeat_service": 1, "knives": 4})
    assert t.calls == []  # nothing applied when one register has no action


def test_numpy_scalars_accepted():
    assert RMAP.encode("encoder_counts", np.uint32(7)) == [0, 7]
    assert RMAP.decode("feed_min_mm_s", RMAP.encode("feed_min_mm_s", np.float32(2.5))) == 2.5


def test_docs_table_matches_the_toml():
    doc = (Path(__file__).resolve().parents[2] / "docs" / "register_map.md").read_text()
    begin, end = "<!-- BEGIN register table -->\n", "<!-- END register table -->"
    assert begin in doc and end in doc
    table = doc.split(begin, 1)[1].split(end, 1)[0]
    assert table == RMAP.markdown_table()
    first, count = RMAP.span()
    assert f"addresses {first}..{first + count - 1} ({count} registers)" in doc


def test_function_codes_and_exception_codes_come_from_the_map_module(tmp_path):
    from protocol.registers import HOLDING_FUNCTION_CODES, ModbusException

    assert RMAP.function_codes == frozenset(TOML["map"]["function_codes"]) == {3, 6, 16, 23}
    assert RegisterAccessError.exception_code == ModbusException.ILLEGAL_DATA_ADDRESS == 2
    assert RegisterRangeError.exception_code == ModbusException.ILLEGAL_DATA_VALUE == 3
    assert ModbusException(1).text == "ILLEGAL FUNCTION"
    only_reads = RegisterMap.load(_write_map(tmp_path, GOOD.replace(
        'word_order = "big"', 'word_order = "big"\nfunction_codes = [3]')))
    assert only_reads.function_codes == {3} and set(HOLDING_FUNCTION_CODES) >= {3}
    for bad in ("[4]", "[6, 16]", "[]", '["3"]', "3"):
        body = GOOD.replace('word_order = "big"', f'word_order = "big"\nfunction_codes = {bad}')
        with pytest.raises(ConfigError, match="map.function_codes"):
            RegisterMap.load(_write_map(tmp_path, body))
