"""The fault registry (config/faults.py): one place for kinds, parameters and their checks."""

from __future__ import annotations

import math

import pytest

from config.faults import (
    FAULT_KINDS,
    INTERFACE_FAULTS,
    Fault,
    FaultKind,
    parse_fault,
    parse_faults,
)
from config.sim import load_sim, sim_from_dict
from core.errors import ConfigError
from planer.hil import load_scenario, sim_config_for


def _valid(kind: FaultKind) -> dict[str, float | str]:
    """A value inside the range of every required parameter."""
    out = {}
    for p in kind.params:
        if p.required and p.choices:
            out[p.name] = p.choices[0]
        elif p.required:
            lo = p.lo if math.isfinite(p.lo) else 0.0
            out[p.name] = lo + 1.0 if p.lo_open or p.integer else lo + 0.5
    return out


@pytest.fixture(scope="module")
def sim_cfg():
    return load_sim()


def test_registry_is_the_one_list_of_kinds():
    import config.sim
    from controller.service.supervisor import SOURCES

    assert FAULT_KINDS == tuple(k.value for k in FaultKind) == config.sim.FAULT_KINDS
    assert set(INTERFACE_FAULTS) == {"modbus_restart", "can_silence", "can_drop"}
    for kind in FaultKind:
        assert kind == kind.value and f"{kind}" == kind.value  # a str enum, formats as its name
        assert kind.trips is None or kind.trips in SOURCES, kind
        assert len(set(kind.param_names)) == len(kind.param_names)
        for p in kind.params:
            assert p.lo <= p.hi and (p.default is None or p.lo <= p.default <= p.hi), p
            assert not (p.required and p.default is not None), p
        # an interface fault lasts a while: it always says how long
        if kind.interface:
            assert kind.lasts and "duration_s" in kind.required
    assert FaultKind.MODBUS_RESTART.trips == "plc" and FaultKind.CAN_SILENCE.trips == "can"


@pytest.mark.parametrize("kind", list(FaultKind), ids=str)
def test_every_kind_and_parameter_is_understood_by_the_machine(kind, sim_cfg):
    """What the registry accepts the machine model takes (scheduled, so nothing acts yet)."""
    from plant_sim.machine.machine import Machine

    m = Machine(sim_cfg, seed=0, render_images=False)
    params = _valid(kind)
    m.inject(kind.value, at_s=50.0, **params)
    for p in kind.params:  # each optional parameter alone, at its default or inside its range
        if p.required or p.name == "counts":
            continue
        v = p.default if p.default is not None else (p.lo if math.isfinite(p.lo) else 0.0) + 1
        m.inject(kind.value, at_s=50.0, **{**params, p.name: v})


@pytest.mark.parametrize("kind", [k for k in FaultKind if k.required], ids=str)
def test_a_missing_required_parameter_is_an_error_everywhere(kind, sim_cfg, tmp_path):
    """A fault without ``duration_s`` was once taken as 0 s: now every entry point refuses it."""
    from plant_sim.machine.machine import Machine

    (name,) = kind.required
    with pytest.raises(ConfigError, match=rf"faults\.inject\[0\]\.{name} is required for {kind}"):
        sim_from_dict({"faults": {"inject": [{"kind": kind.value, "at_s": 1.0}]}})
    p = tmp_path / "s.toml"
    p.write_text(f"[a]\nfaults = [{{ kind = '{kind}', at_s = 2.0 }}]\n")
    with pytest.raises(ConfigError, match=rf"s\.toml: a\.faults\[0\]\.{name} is required"):
        load_scenario(str(p))
    with pytest.raises(ValueError, match=rf"{kind}\.{name} is required"):
        Machine(sim_cfg, seed=0, render_images=False).inject(kind.value, at_s=1.0)
    with pytest.raises(ConfigError, match=name):
        Fault(kind, 1.0)


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ({"kind": "gremlin"}, r"f\.kind must be one of belt_slip, .*; got 'gremlin'"),
        ({"at_s": 1.0}, r"f\.kind is required"),
        ({"kind": "estop", "px": 1.0}, r"f\.px: unknown parameter of estop \(allowed: at_s\)"),
        ({"kind": "belt_slip", "px": 1.0, "counts": 2}, r"give one of px, counts"),
        ({"kind": "belt_slip", "px": float("nan")}, r"f\.px must be finite"),
        ({"kind": "belt_slip", "px": True}, r"f\.px must be a number"),
        ({"kind": "belt_slip", "px": "12"}, r"f\.px must be a number"),
        ({"kind": "knot", "darkness": 2.0}, r"f\.darkness must be in \[0, 1\]"),
        ({"kind": "knot", "length_mm": 0.0}, r"f\.length_mm must be in \(0, inf\] mm"),
        ({"kind": "piezo_fault", "bit": 2.5}, r"f\.bit must be a whole number"),
        ({"kind": "can_drop", "duration_s": 1.0, "fraction": 1.5}, r"f\.fraction must be in"),
        ({"kind": "can_silence", "duration_s": 0.0}, r"f\.duration_s must be in \(0, inf\] s"),
        ({"kind": "modbus_restart", "duration_s": -1.0}, r"f\.duration_s must be in \[0"),
        ({"kind": "reset", "at_s": -1.0}, r"f\.at_s must be in \[0"),
        ("estop", r"f must be a table"),
    ],
)
def test_bad_fault_tables_name_the_key(table, match):
    with pytest.raises(ConfigError, match=match):
        parse_fault(table, "f")


def test_fault_tables_round_trip_and_defaults():
    raw = [{"kind": "modbus_restart", "at_s": 3.5, "duration_s": 1.5},
           {"kind": "knot", "board_id": 2, "at_mm": 500.0},
           {"kind": "estop"}]
    faults = parse_faults(raw, "faults", default_at_s=0.0)
    assert [f.table() for f in faults] == [raw[0], {**raw[1], "at_s": 0.0},
                                            {"kind": "estop", "at_s": 0.0}]
    assert [f.duration_s for f in faults] == [1.5, 0.0, 0.0]
    assert isinstance(faults[1].params["board_id"], int)  # whole numbers stay integers
    assert parse_faults(raw[2:], "faults")[0].at_s is None  # no default: acts at once
    assert FaultKind.KNOT.value_of(faults[1].params, "darkness") == 0.6
    assert FaultKind.KNOT.value_of(faults[1].params, "at_mm") == 500.0
    with pytest.raises(ConfigError, match=r"faults must be a list"):
        parse_faults({"kind": "estop"}, "faults")


def test_scenario_machine_faults_reach_the_simulator_interface_faults_do_not():
    from planer.hil import FaultEvent, Scenario

    sc = Scenario(faults=(FaultEvent("modbus_restart", 1.0, {"duration_s": 1.0}),
                          FaultEvent("knot", 2.0, {"at_mm": 100.0}),
                          FaultEvent("can_drop", 3.0, {"duration_s": 0.5})))
    cfg = sim_config_for(sc)
    assert [(f.kind, f.params) for f in cfg.faults] == [("knot", {"at_s": 2.0, "at_mm": 100.0})]
