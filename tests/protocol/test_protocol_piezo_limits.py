"""PIEZO_LIMITS: the amplifier's limits on the wire -- round trips, layout, ranges, the DBC."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from config.loading import default_path
from controller.laws.limits import AmpLimits
from core.errors import ConfigError
from protocol import piezo_can
from protocol.piezo_can import PiezoCodec

CODEC = PiezoCodec.load()
S_LO, S_HI = CODEC.signal_range(piezo_can.LIMITS, "stroke_um")
O_LO, O_HI = CODEC.signal_range(piezo_can.LIMITS, "offset_min_um")


def test_the_message_is_in_the_dbc_with_its_id_and_ranges():
    assert CODEC.limits_id == CODEC.ids[piezo_can.LIMITS] == 0x281
    assert (S_LO, S_HI) == (0.0, 65.535)
    assert (O_LO, O_HI) == (-32.768, 32.767)
    assert CODEC.signal_range(piezo_can.LIMITS, "setpoint_timeout_ms") == (0.0, 510.0)
    assert piezo_can.LIMITS_PERIOD_S == piezo_can.HEARTBEAT_PERIOD_S


@given(
    st.floats(S_LO, S_HI),
    st.floats(O_LO, O_HI),
    st.floats(O_LO, O_HI),
    st.integers(0, 255),
    st.floats(0.0, 510.0),
)
def test_limits_round_trip_to_the_resolution(stroke, lo, hi, slew, timeout):
    fid, data = CODEC.encode_limits(stroke_um=stroke, offset_min_um=lo, offset_max_um=hi,
                                    slew_max_um_ms=slew, setpoint_timeout_ms=timeout)
    assert fid == CODEC.limits_id and len(data) == 8
    name, sig = CODEC.decode(fid, data)
    assert name == piezo_can.LIMITS
    assert abs(sig["stroke_um"] - stroke) <= 0.0005 + 1e-9
    assert abs(sig["offset_min_um"] - lo) <= 0.0005 + 1e-9
    assert abs(sig["offset_max_um"] - hi) <= 0.0005 + 1e-9
    assert sig["slew_max_um_ms"] == slew
    assert abs(sig["setpoint_timeout_ms"] - timeout) <= 1.0 + 1e-9  # steps of 2 ms
    assert sig["setpoint_timeout_ms"] % 2 == 0
    # little-endian layout: u16 stroke, s16 min, s16 max (1 nm per bit), u8 slew, u8 timeout/2
    raw = struct.unpack("<Hhh2B", data)
    assert abs(raw[0] - stroke * 1000) <= 0.5 + 1e-6
    assert abs(raw[1] - lo * 1000) <= 0.5 + 1e-6 and abs(raw[2] - hi * 1000) <= 0.5 + 1e-6
    assert raw[3] == slew and raw[4] * 2 == sig["setpoint_timeout_ms"]


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"stroke_um": -0.01}, "stroke_um"),
        ({"stroke_um": 65.6}, "stroke_um"),
        ({"offset_min_um": -33.0}, "offset_min_um"),
        ({"offset_max_um": 40.0}, "offset_max_um"),
        ({"slew_max_um_ms": 1.5}, "slew_max_um_ms must be an integer"),
        ({"slew_max_um_ms": 256}, "slew_max_um_ms"),
        ({"setpoint_timeout_ms": 520.0}, "setpoint_timeout_ms"),
        ({"setpoint_timeout_ms": float("nan")}, "setpoint_timeout_ms"),
        ({"setpoint_timeout_ms": "fast"}, "setpoint_timeout_ms must be a number"),
        ({"stroke_um": float("inf")}, "stroke_um must be finite"),
    ],
)
def test_values_the_wire_cannot_carry_are_refused_naming_the_signal(kwargs, needle):
    good = {"stroke_um": 10.0, "offset_min_um": -10.0, "offset_max_um": 10.0,
            "slew_max_um_ms": 0, "setpoint_timeout_ms": 100.0}
    with pytest.raises(ValueError, match=needle):
        CODEC.encode_limits(**{**good, **kwargs})


def test_decoded_limits_become_the_amplifiers_limits():
    frame = CODEC.encode_limits(stroke_um=10.0, offset_min_um=-8.0, offset_max_um=9.5,
                                slew_max_um_ms=40, setpoint_timeout_ms=100.0)
    lim = AmpLimits.from_signals(CODEC.decode(*frame)[1])
    assert lim == AmpLimits(stroke_um=10.0, offset_min_um=-8.0, offset_max_um=9.5,
                            slew_max_um_ms=40.0, setpoint_timeout_s=0.1)
    assert lim.bound_um == 8.0
    with pytest.raises(ValueError, match="lacks signal offset_min_um"):
        AmpLimits.from_signals({"stroke_um": 1.0})
    with pytest.raises(ValueError, match="PIEZO_LIMITS"):
        CODEC.decode(CODEC.limits_id, b"\0" * 7)  # short frame


def test_a_dbc_without_the_limits_message_is_refused(tmp_path):
    text = default_path("piezo.dbc").read_text()
    block = text[text.index("BO_ 641 PIEZO_LIMITS"):text.index("BO_ 1794")]
    p = tmp_path / "x.dbc"
    p.write_text(text.replace(block, "").replace("CM_ BO_ 641", "CM_ BO_ 640")
                 .replace("CM_ SG_ 641 slew_max_um_ms", "CM_ SG_ 640 fault")
                 .replace("CM_ SG_ 641 setpoint_timeout_ms", "CM_ SG_ 640 state"))
    with pytest.raises(ConfigError, match="PIEZO_LIMITS missing"):
        PiezoCodec.load(p)


def test_the_simulated_amplifier_reports_its_own_stroke_with_the_heartbeat():
    """The node sends PIEZO_LIMITS from its amplifier's configuration, at start and every 100 ms."""
    from types import SimpleNamespace

    from plant_sim.interfaces.amp_node import AmpNodeCore
    from plant_sim.model.piezo import PiezoAmplifier

    cfg = SimpleNamespace(stroke_um=7.5, timeout_s=0.1, resonance_hz=800.0, damping=0.2,
                          hysteresis=0.0, input_shaper=False, ambient_c=25.0)
    amp = PiezoAmplifier(cfg, 4, rng=None)

    class Machine:
        def __init__(self):
            self.amp = amp

        def piezo_command(self, **kw):
            pass

        def set_piezo_offsets(self, offs):
            amp.set_offsets(offs)

        def piezo_status(self):
            return SimpleNamespace(displacement_um=0.0, temperature_c=25.0, fault=0, state=0)

    core = AmpNodeCore(Machine(), CODEC, knives=4)
    got = []
    for i in range(31):  # 0.30 s at 10 ms
        for fid, data in core.poll(i * 0.01):
            name, sig = CODEC.decode(fid, data)
            if name == piezo_can.LIMITS:
                got.append((i, sig))
    assert [i for i, _ in got] == [0, 10, 20, 30]  # at start, then with each heartbeat
    sig = got[0][1]
    assert sig["stroke_um"] == 7.5 and (sig["offset_min_um"], sig["offset_max_um"]) == (-7.5, 7.5)
    assert sig["setpoint_timeout_ms"] == 100.0 and sig["slew_max_um_ms"] == 0
    # and refuses a table beyond it (stroke-limit bit), as the limits say
    core.on_message(piezo_can.OFFSETS[0], {f"offset_knife_{k}": v for k, v in
                                          enumerate([8.0, -8.0, 0.0, 0.0])}, 0.31)
    assert core.refused == 1
