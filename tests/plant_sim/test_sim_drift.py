"""Runout drift in the simulator: knives that warm up and wear.

``drift_k(t) = A_k (1 - exp(-t / tau_k)) - W_k t / 60`` um at machine time t: starts at the
base runout, approaches base + amplitude with the time constant, wears linearly; configured in
``[cutterhead.drift]`` (errors name the key) and cut into the board at each pass's time.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from config.loading import default_path
from config.sim import DriftConfig, load_sim, sim_from_dict, with_base
from core.errors import ConfigError
from planer.hil.scenario import load_scenario, sim_config_for
from plant_sim.machine.machine import Machine, runout_drift
from plant_sim.model.surface import Cutterhead, RunoutDrift

RUNOUT = (0.0, 4.0, -2.0, 2.0)


def drift(amp=(2.0, 5.0, 1.0, 3.5), tau=(30.0, 30.0, 60.0, 10.0), wear=(0.5, 1.5, 0.2, 1.0)):
    return RunoutDrift(tuple(amp), tuple(tau), tuple(wear))


# ------------------------------------------------------------------------------ the formula
def test_starts_at_the_base_runout():
    head = Cutterhead(4, 60.0, RUNOUT, 0.5, drift=drift())
    still = Cutterhead(4, 60.0, RUNOUT, 0.5)
    assert np.array_equal(head.standout_um(0.0), still.standout_um())
    assert np.array_equal(head.standout_um(), still.standout_um())
    assert np.all(drift().drift_um(-5.0) == 0.0)  # nothing before the start


def test_warm_up_reaches_one_minus_1_over_e_of_its_amplitude_at_tau():
    d = drift(wear=(0.0,) * 4)
    tau = np.asarray(d.warmup_tau_s)
    for k in range(4):
        got = d.knife_um(k, tau[k])
        assert got == pytest.approx(d.warmup_um[k] * (1 - math.exp(-1)), rel=1e-12)
        assert d.knife_um(k, 20 * tau[k]) == pytest.approx(d.warmup_um[k], rel=1e-8)
    head = Cutterhead(4, 60.0, RUNOUT, 0.0, drift=d)
    late = head.standout_um(1e4)
    assert np.allclose(late, np.asarray(RUNOUT) + np.asarray(d.warmup_um))


def test_wear_is_linear_in_time():
    d = drift(amp=(0.0,) * 4)
    t = np.linspace(0.0, 600.0, 7)
    got = np.array([d.drift_um(v) for v in t])
    assert np.allclose(got, -np.outer(t / 60.0, d.wear_um_per_min), atol=1e-12)
    assert np.allclose(np.diff(got, n=2, axis=0), 0.0, atol=1e-9)  # a straight line


@settings(max_examples=60, deadline=None)
@given(
    amp=st.floats(-50, 50), tau=st.floats(0.1, 1e4), wear=st.floats(0, 10),
    t=st.floats(0, 1e5),
)
def test_warm_up_part_is_an_exponential_approach(amp, tau, wear, t):
    d = RunoutDrift((amp,), (tau,), (wear,))
    warm = d.knife_um(0, t) + wear * t / 60.0
    assert abs(warm) <= abs(amp) + 1e-9 and warm * amp >= -1e-12  # between 0 and amplitude
    assert abs(amp - warm) == pytest.approx(abs(amp) * math.exp(-t / tau), abs=1e-9)
    # the rate at the start: A / tau - W / 60
    h = 1e-6 * tau
    assert (d.knife_um(0, h) / h) == pytest.approx(amp / tau - wear / 60.0, rel=1e-3, abs=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(tau=(30.0, 0.0, 30.0, 30.0)), r"warmup_tau_s\[1\]"),
        (dict(wear=(0.1, 0.1, -0.1, 0.1)), r"wear_um_per_min\[2\]"),
        (dict(amp=(0.0, math.nan, 0.0, 0.0)), r"warmup_um\[1\]"),
        (dict(tau=(30.0, 30.0)), "warmup_tau_s"),
        (dict(amp=()), "warmup_um"),
    ],
)
def test_drift_rejects(kwargs, name):
    with pytest.raises(ValueError, match=name):
        drift(**kwargs)


def test_cutterhead_rejects_a_drift_of_other_knives():
    with pytest.raises(ValueError, match="drift"):
        Cutterhead(3, 60.0, (0.0, 1.0, 2.0), drift=drift())


# ------------------------------------------------------------------------- configuration
def test_drift_table_loads_with_one_time_constant_for_all():
    cfg = sim_from_dict({"cutterhead": {"drift": {
        "warmup_um": [1.0, 2.0, 3.0, 4.0], "warmup_tau_s": 45.0,
        "wear_um_per_min": [0.0, 0.1, 0.2, 0.3]}}})
    d = cfg.cutterhead.drift
    assert d == DriftConfig((1.0, 2.0, 3.0, 4.0), (45.0,) * 4, (0.0, 0.1, 0.2, 0.3))
    assert d.active and runout_drift(d) == RunoutDrift(d.warmup_um, d.warmup_tau_s,
                                                       d.wear_um_per_min)
    assert sim_from_dict({}).cutterhead.drift is None and runout_drift(None) is None
    empty = sim_from_dict({"cutterhead": {"drift": {}}}).cutterhead.drift
    assert not empty.active and empty.warmup_tau_s == (120.0,) * 4


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ({"warmup_um": [1.0, 2.0]}, "cutterhead.drift.warmup_um"),
        ({"warmup_um": [1.0, 2.0, 3.0, 60.0]}, r"cutterhead.drift.warmup_um\[3\]"),
        ({"warmup_tau_s": 0.0}, "cutterhead.drift.warmup_tau_s"),
        ({"warmup_tau_s": [10.0, 10.0, -1.0, 10.0]}, r"cutterhead.drift.warmup_tau_s\[2\]"),
        ({"warmup_tau_s": [10.0, 10.0]}, "cutterhead.drift.warmup_tau_s"),
        ({"warmup_tau_s": "slow"}, "cutterhead.drift.warmup_tau_s"),
        ({"wear_um_per_min": [0.0, -0.5, 0.0, 0.0]}, r"cutterhead.drift.wear_um_per_min\[1\]"),
        ({"wear_um_per_min": [0.0, 0.0, 0.0, 11.0]}, r"cutterhead.drift.wear_um_per_min\[3\]"),
        ({"wear": [0.0] * 4}, "unknown key cutterhead.drift.wear"),
    ],
)
def test_drift_config_errors_name_the_key(table, key):
    with pytest.raises(ConfigError, match=key):
        sim_from_dict({"cutterhead": {"drift": table}})


def test_drift_lists_follow_the_knives():
    with pytest.raises(ConfigError, match="cutterhead.drift.warmup_um must have 2 values"):
        sim_from_dict({"cutterhead": {"knives": 2, "runout_um": [0.0, 1.0],
                                      "drift": {"warmup_um": [1.0, 2.0, 3.0, 4.0]}}})


def test_a_file_based_on_the_shipped_one_changes_only_what_it_gives():
    shipped = load_sim()
    cfg = sim_from_dict({"base": "sim.toml", "piezo": {"stroke_um": 12.0}})
    assert cfg.piezo.stroke_um == 12.0
    assert cfg.piezo.resonance_hz == shipped.piezo.resonance_hz
    assert cfg.camera.roll_deg == shipped.camera.roll_deg != 0.0  # not the dataclass default
    assert cfg.board == shipped.board
    merged = with_base({"base": "sim.toml", "can": {"options": {"port": 1}}})
    assert "base" not in merged and merged["can"]["options"] == {"port": 1}
    assert merged["can"]["channel"] == "planer-piezo"


@pytest.mark.parametrize(
    ("base", "match"),
    [("../sim.toml", "base must name"), ("sim", "base must name"), (3, "base must name"),
     ("nowhere.toml", "no such file")],
)
def test_bad_base_is_refused_naming_the_key(base, match):
    with pytest.raises(ConfigError, match=match):
        sim_from_dict({"base": base})


def test_shipped_drift_file_and_scenario():
    cfg = load_sim(default_path("sim_drift.toml"))
    assert cfg.cutterhead.drift is not None and cfg.cutterhead.drift.active
    assert cfg.camera.roll_deg == load_sim().camera.roll_deg  # the shipped rig otherwise
    sc = load_scenario("drift")
    assert sim_config_for(sc).cutterhead.drift == cfg.cutterhead.drift
    assert sc.distance_m > 1.0  # the target is judged after the first metre


# ------------------------------------------------------------------------- the machine
def test_machine_cuts_with_the_drifted_runout():
    base = sim_from_dict({"base": "sim.toml", "piezo": {"hysteresis": 0.0}})
    d = DriftConfig((3.0, -2.0, 6.0, 1.0), (1.0, 0.5, 2.0, 1.5), (10.0, 0.0, 5.0, 2.0))
    cfg = dataclasses.replace(base, cutterhead=dataclasses.replace(base.cutterhead, drift=d))
    m = Machine(cfg, seed=0, render_images=False)
    still = Machine(base, seed=0, render_images=False)
    assert m.standout_um() == still.standout_um()  # at t = 0
    m.advance(3.0)
    still.advance(3.0)
    head = Cutterhead(4, cfg.cutterhead.radius_mm, cfg.cutterhead.runout_um,
                      cfg.cutterhead.eccentricity_um, drift=runout_drift(d))
    assert np.allclose(m.standout_um(), head.standout_um(3.0))
    # every pass's bottom is lower by that knife's drift at its time (the piezo is off)
    p, q = m.passes(1), still.passes(1)
    assert np.array_equal(p.knife, q.knife) and np.allclose(p.x_mm, q.x_mm)
    shift = q.bottom_um - p.bottom_um
    last = slice(-8, None)  # the last two revolutions (20 ms): the drift of now, to within
    expect = head.standout_um(3.0) - np.asarray(still.standout_um())  # 0.6 um/s * 20 ms
    assert np.allclose(shift[last], expect[p.knife[last]], atol=0.015)
    first = slice(0, 4)  # the board's first passes (0.1-0.2 s): far less drift yet
    assert np.all(np.abs(shift[first]) < 0.5 * np.abs(expect[p.knife[first]]))


def test_zero_drift_table_changes_nothing():
    base = load_sim()
    zero = DriftConfig((0.0,) * 4, (60.0,) * 4, (0.0,) * 4)
    cfg = dataclasses.replace(base, cutterhead=dataclasses.replace(base.cutterhead, drift=zero))
    a, b = Machine(base, seed=2, render_images=False), Machine(cfg, seed=2, render_images=False)
    a.advance(1.2)
    b.advance(1.2)
    assert np.array_equal(a.passes(1).bottom_um, b.passes(1).bottom_um)
