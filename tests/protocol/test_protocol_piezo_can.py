"""The piezo CAN codec: round trips, scaling and rounding, ranges, errors naming the knife."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from core.errors import ConfigError
from protocol import piezo_can
from protocol.piezo_can import PiezoCodec

CODEC = PiezoCodec.load()
LO, HI = CODEC.signal_range("PIEZO_OFFSETS_0_3", "offset_knife_0")


def test_ids_match_the_dbc():
    assert CODEC.command_id == 0x200
    assert CODEC.offset_ids == (0x210, 0x211)
    assert CODEC.status_id == 0x280
    assert CODEC.heartbeat_id == 0x702
    assert (LO, HI) == (-32.768, 32.767)


@given(st.booleans(), st.integers(1, 8), st.integers(0, 255))
def test_command_round_trip(enable, knives, alive):
    fid, data = CODEC.encode_command(enable=enable, knives=knives, alive_counter=alive)
    assert fid == CODEC.command_id and len(data) == 4
    # little-endian bit layout: enable bit 0, knives bits 8..11, alive byte 2
    assert data[0] & 1 == int(enable) and data[1] & 0xF == knives and data[2] == alive
    name, sig = CODEC.decode(fid, data)
    assert name == "PIEZO_COMMAND"
    assert sig == {"enable": int(enable), "knives": knives, "alive_counter": alive}


offsets = st.lists(st.floats(min_value=LO, max_value=HI, allow_nan=False), min_size=1, max_size=8)


@given(offsets)
def test_offsets_round_trip_to_the_resolution(offs):
    frames = CODEC.encode_offsets(offs)
    assert len(frames) == (1 if len(offs) <= 4 else 2)
    got: dict[int, float] = {}
    for fid, data in frames:
        assert fid in CODEC.offset_ids and len(data) == 8
        name, sig = CODEC.decode(fid, data)
        got.update(CODEC.offsets_from(name, sig))
    for k, v in enumerate(offs):
        assert abs(got[k] - v) <= 0.0005 + 1e-9
        # raw little-endian int16 at 1 nm per bit
        raw = struct.unpack("<4h", frames[k // 4][1])[k % 4]
        assert abs(raw - v * 1000) <= 0.5 + 1e-6
    for k in range(len(offs), 4 * len(frames)):
        assert got[k] == 0.0


@pytest.mark.parametrize("bad_knife", [0, 3, 5, 7])
def test_offset_out_of_range_names_the_knife(bad_knife):
    offs = [1.0] * 8
    offs[bad_knife] = HI + 0.01
    with pytest.raises(ValueError, match=f"knife {bad_knife}"):
        CODEC.encode_offsets(offs)
    offs[bad_knife] = float("nan")
    with pytest.raises(ValueError, match=f"knife {bad_knife}"):
        CODEC.encode_offsets(offs)


@pytest.mark.parametrize("n", [0, 9])
def test_offsets_count_checked(n):
    with pytest.raises(ValueError, match="offsets_um"):
        CODEC.encode_offsets([0.0] * n)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"enable": True, "knives": 0, "alive_counter": 0},
        {"enable": True, "knives": 9, "alive_counter": 0},
        {"enable": True, "knives": 4, "alive_counter": 256},
        {"enable": True, "knives": 4, "alive_counter": 1.5},
    ],
)
def test_command_out_of_range(kwargs):
    with pytest.raises(ValueError, match="PIEZO_COMMAND"):
        CODEC.encode_command(**kwargs)


@given(
    st.floats(-40.0, 40.0),
    st.floats(-50.0, 200.0),
    st.integers(0, 15),
    st.integers(0, 3),
    st.integers(0, 255),
)
def test_status_round_trip(disp, temp, fault, state, alive):
    fid, data = CODEC.encode_status(
        displacement_um=disp, temperature_c=temp, fault=fault, state=state, alive_counter=alive
    )
    name, sig = CODEC.decode(fid, data)
    assert name == "PIEZO_STATUS"
    assert abs(sig["displacement_um"] - min(max(disp, LO), HI)) <= 0.0005 + 1e-9
    assert abs(sig["temperature_c"] - temp) <= 0.05 + 1e-9
    assert (sig["fault"], sig["state"], sig["alive_counter"]) == (fault, state, alive)


def test_heartbeat_and_errors():
    fid, data = CODEC.encode_heartbeat()
    assert CODEC.decode(fid, data) == ("AMP_HEARTBEAT", {"nmt_state": piezo_can.NMT_OPERATIONAL})
    with pytest.raises(ValueError, match="0x123"):
        CODEC.decode(0x123, b"\0" * 8)
    with pytest.raises(ValueError, match="PIEZO_STATUS"):
        CODEC.decode(CODEC.status_id, b"\0" * 3)
    with pytest.raises(ValueError, match="state"):
        CODEC.encode_status(
            displacement_um=0.0, temperature_c=20.0, fault=0, state=4, alive_counter=0
        )


def test_bad_dbc_is_a_config_error(tmp_path):
    p = tmp_path / "x.dbc"
    p.write_text('VERSION ""\n\nBU_: A\n\nBO_ 1 OTHER: 1 A\n SG_ s : 0|8@1+ (1,0) [0|255] "" A\n')
    with pytest.raises(ConfigError, match="PIEZO_COMMAND"):
        PiezoCodec.load(p)
    with pytest.raises(ConfigError, match="not found"):
        PiezoCodec.load(tmp_path / "missing.dbc")


def test_dbc_errors_name_the_file(tmp_path):
    p = tmp_path / "x.dbc"
    p.write_text('VERSION ""\n\nBU_: A\n\nBO_ 1 OTHER: 1 A\n SG_ s : 0|8@1+ (1,0) [0|255] "" A\n')
    with pytest.raises(ConfigError, match=r"x\.dbc: piezo DBC: message PIEZO_COMMAND missing"):
        PiezoCodec.load(p)
    p.write_text("this is not a DBC file {{{")
    with pytest.raises(ConfigError, match=r"x\.dbc: not a valid DBC file"):
        PiezoCodec.load(p)
    with pytest.raises(ConfigError, match="cannot read DBC file"):
        PiezoCodec.load(tmp_path)  # a folder


@pytest.mark.parametrize(
    ("fid", "data", "needle"),
    [
        (0x200, [1, 4, 7, 0], "data must be bytes"),
        (0x200, 4, "data must be bytes"),
        (0x200, "abcd", "data must be bytes"),
        ("0x200", b"\x01\x04\x07\x00", "must be an integer"),
        (512.0, b"\x01\x04\x07\x00", "must be an integer"),
        (True, b"\x01\x04\x07\x00", "must be an integer"),
        (0x7FF, b"", "unknown CAN arbitration id 0x7FF"),
    ],
)
def test_decode_refuses_what_is_not_a_frame_with_a_value_error(fid, data, needle):
    with pytest.raises(ValueError, match=needle):
        CODEC.decode(fid, data)


def test_decode_takes_numpy_ids_and_bytes_like_data():
    import numpy as np

    fid, data = CODEC.encode_command(enable=True, knives=4, alive_counter=7)
    expected = CODEC.decode(fid, data)
    assert CODEC.decode(np.uint32(fid), bytearray(data)) == expected
    assert CODEC.decode(fid, memoryview(data)) == expected


def test_values_within_half_a_step_of_the_range_encode_as_its_end():
    """32.7675 um is half a step above the top: it is the top (32.767), not an overflow."""
    for v in (HI + 0.0005, HI + 0.0004, HI):
        ((_, data),) = CODEC.encode_offsets([v])
        assert CODEC.offsets_from(*CODEC.decode(CODEC.offset_ids[0], data))[0] == HI
    ((_, data),) = CODEC.encode_offsets([LO - 0.0005])
    assert CODEC.offsets_from(*CODEC.decode(CODEC.offset_ids[0], data))[0] == LO
    with pytest.raises(ValueError, match="knife 0"):
        CODEC.encode_offsets([HI + 0.0011])
    fid, data = CODEC.encode_status(displacement_um=0.0, temperature_c=3276.75, fault=0, state=0,
                                    alive_counter=0)
    assert CODEC.decode(fid, data)[1]["temperature_c"] == 3276.7


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ("(1,0) [1|8]", "(0,0) [1|8]", "PIEZO_COMMAND.knives: scale 0"),
        ("(1,0) [1|8]", "(1,0) [0|0]", "PIEZO_COMMAND.knives: needs a range"),
        ("(1,0) [1|8]", "(1,0) [1|1000]", "PIEZO_COMMAND.knives: range .* 4-bit unsigned"),
        ("(1,0) [1|8]", "(1,0) [8|1]", "min <= max"),
        ("(0.1,0) [-3276.8|3276.7]", "(0.1,0) [-3276.8|3276.8]", "temperature_c.*16-bit signed"),
    ],
)
def test_dbc_signals_the_codec_cannot_carry_are_refused_naming_file_and_signal(
    tmp_path, old, new, needle
):
    from config.loading import default_path

    text = default_path("piezo.dbc").read_text()
    assert old in text
    p = tmp_path / "x.dbc"
    p.write_text(text.replace(old, new, 1))
    with pytest.raises(ConfigError, match=needle) as err:
        PiezoCodec.load(p)
    assert str(err.value).startswith(f"{p}: ")
