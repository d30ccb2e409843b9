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
    RegisterAccessError,
    RegisterMap,
    RegisterRangeError,
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
    with pytest.raises(ConfigError, match=needle):
        RegisterMap.load(_write_map(tmp_path, edit(GOOD)))


def test_numpy_scalars_accepted():
    assert RMAP.encode("encoder_counts", np.uint32(7)) == [0, 7]
    assert RMAP.decode("feed_min_mm_s", RMAP.encode("feed_min_mm_s", np.float32(2.5))) == 2.5


def test_docs_table_matches_the_toml():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "register_map.md").read_text()
    begin, end = "<!-- BEGIN register table -->\n", "<!-- END register table -->"
    assert begin in doc and end in doc
    table = doc.split(begin, 1)[1].split(end, 1)[0]
    assert table == RMAP.markdown_table()
    first, count = RMAP.span()
    assert f"addresses {first}..{first + count - 1} ({count} registers)" in doc
