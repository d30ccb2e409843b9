"""The amplifier's limits in its object dictionary (0x2200), read by SDO at start."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from controller.laws.limits import AmpLimits
from plant_sim.interfaces.amp_node import AmpNodeCore
from plant_sim.model.piezo import PiezoAmplifier
from protocol.piezo_canopen import LIMITS, load_od, sdo_upload_request, sdo_upload_value
from tests.support import canopen_frames as cf


def test_the_limits_record_is_in_the_eds_with_its_types_and_defaults():
    od = load_od(2)
    rec = od[LIMITS]
    assert [rec[s].name for s in range(1, 6)] == [
        "Stroke", "Offset minimum", "Offset maximum", "Slew maximum", "Setpoint timeout"]
    assert [rec[s].data_type for s in range(1, 6)] == [0x6, 0x3, 0x3, 0x6, 0x6]  # U16/I16
    assert all(rec[s].readable and not rec[s].writable for s in range(1, 6))
    assert (rec[1].default, rec[2].default, rec[3].default) == (20000, -20000, 20000)


def test_read_limits_become_the_amplifiers_limits():
    lim = AmpLimits.from_signals({"stroke_um": 10.0, "offset_min_um": -8.0,
                                  "offset_max_um": 9.5, "slew_max_um_ms": 40,
                                  "setpoint_timeout_ms": 100})
    assert lim == AmpLimits(stroke_um=10.0, offset_min_um=-8.0, offset_max_um=9.5,
                            slew_max_um_ms=40.0, setpoint_timeout_s=0.1)
    assert lim.bound_um == 8.0
    with pytest.raises(ValueError, match="lacks signal offset_min_um"):
        AmpLimits.from_signals({"stroke_um": 1.0})


def test_the_simulated_amplifier_answers_with_its_own_stroke():
    """The node reads its limits live from its amplifier model (sim.toml [piezo])."""
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

    core = AmpNodeCore(Machine(), knives=4)
    core.poll(0.0)
    got = {}
    for sub in range(1, 6):
        core.on_frame(0x602, sdo_upload_request(LIMITS, sub), 0.0)
        (answer,) = [d for fid, d in core.poll(0.0) if fid == 0x582]
        got[sub] = core.node.od[LIMITS][sub].decode_raw(sdo_upload_value(answer, LIMITS, sub))
    assert got == {1: 7500, 2: -7500, 3: 7500, 4: 0, 5: 100}
    # and refuses a table beyond it (stroke-limit bit), as the limits say
    core.on_frame(*cf.start(), 0.0)
    for fid, data in cf.offsets([8.0, -8.0, 0.0, 0.0]):
        core.on_frame(fid, data, 0.0)
    assert core.refused == 1
