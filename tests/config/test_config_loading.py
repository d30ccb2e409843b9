"""Config loading: typed access naming keys, the rig file contract, shared entry checks."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import tomllib

from config import Section, default_path, load_toml
from config.rig import load_rig, rig_from_dict, rig_to_toml
from core import checks
from core.errors import ConfigError

GOOD = {
    "camera": {"fx": 1000.0, "fy": 1001.0, "cx": 320.0, "cy": 240.0,
               "dist": [-0.1, 0.0, 0.0, 0.0, 0.0], "px_per_mm": 12.5, "exposure_ms": 0.1},
    "lights": {"slant_deg": 80.0},
    "encoder": {"px_per_count": 0.25},
}


def _with(path, value):
    import copy

    d = copy.deepcopy(GOOD)
    table, key = path.split(".")
    if value is None:
        del d[table][key]
    else:
        d[table][key] = value
    return d


def test_shipped_rig_loads_and_round_trips():
    rig = load_rig(default_path("rig.toml"))
    assert rig.lights.azimuth_a_deg == 0.0 and rig.lights.azimuth_b_deg == 180.0
    assert rig_from_dict(tomllib.loads(rig_to_toml(rig))) == rig


def test_rig_defaults():
    rig = rig_from_dict(GOOD)
    assert rig.lights.azimuth_b_deg == 180.0
    assert rig.encoder.counter_bits == 32
    assert rig.camera.dist == (-0.1, 0.0, 0.0, 0.0, 0.0)


def test_seed_one_coefficient_dist_is_expanded():
    rig = rig_from_dict(_with("camera.dist", [-0.2]))
    assert rig.camera.dist == (-0.2, 0.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("path", "value", "named"),
    [
        ("camera.fx", None, "camera.fx"),
        ("camera.fx", -5.0, "camera.fx"),
        ("camera.fx", "big", "camera.fx"),
        ("camera.px_per_mm", 0.0, "camera.px_per_mm"),
        ("camera.dist", [0.1, 0.2], "camera.dist"),
        ("camera.dist", [0.1, "x", 0, 0, 0], "camera.dist[1]"),
        ("camera.exposure_ms", -1.0, "camera.exposure_ms"),
        ("lights.slant_deg", 95.0, "lights.slant_deg"),
        ("lights.slant_deg", math.nan, "lights.slant_deg"),
        ("encoder.px_per_count", None, "encoder.px_per_count"),
        ("encoder.counter_bits", 24, "encoder.counter_bits"),
        ("encoder.counter_bits", True, "encoder.counter_bits"),
    ],
)
def test_bad_rig_values_name_the_key(path, value, named):
    with pytest.raises(ConfigError, match=re_escape(named)):
        rig_from_dict(_with(path, value))


def re_escape(s):
    import re

    return re.escape(s)


def test_load_errors_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_toml(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera\nfx = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_toml(bad)
    with pytest.raises(ConfigError, match="directory"):
        load_toml(tmp_path)
    bad_value = tmp_path / "rig.toml"
    bad_value.write_text("[camera]\nfx = -1.0\n")
    with pytest.raises(ConfigError, match="rig.toml: camera.fx must be > 0"):
        load_rig(bad_value)


def test_section_rejects_unknown_keys_and_wrong_types():
    s = Section({"a": 1, "typo": 2}, "t")
    assert s.integer("a") == 1
    with pytest.raises(ConfigError, match="unknown key t.typo"):
        s.reject_unknown()
    with pytest.raises(ConfigError, match="t.a must be a string"):
        Section({"a": 1}, "t").string("a")
    with pytest.raises(ConfigError, match="t.m must be one of"):
        Section({"m": "x"}, "t").string("m", choices=("hold", "ramp_down"))
    with pytest.raises(ConfigError, match="must be a table"):
        Section([1, 2], "t")


@pytest.mark.parametrize(
    ("fn", "args", "ok"),
    [
        (checks.check_positive, ("v", 1.0), True),
        (checks.check_positive, ("v", 0.0), False),
        (checks.check_positive, ("v", float("inf")), False),
        (checks.check_range, ("v", 5, 0, 10), True),
        (checks.check_range, ("v", 11, 0, 10), False),
        (checks.check_int, ("v", 3), True),
        (checks.check_int, ("v", 3.0), False),
        (checks.check_int, ("v", True), False),
        (checks.check_finite, ("v", "abc"), False),
    ],
)
def test_checks_table(fn, args, ok):
    if ok:
        fn(*args)
    else:
        with pytest.raises(ValueError, match="^v "):
            fn(*args)


def test_check_image_and_shapes():
    img = np.zeros((10, 20), np.uint8)
    assert checks.check_image("image_a", img) is not None
    with pytest.raises(ValueError, match="image_a must be a 2-D"):
        checks.check_image("image_a", np.zeros((4, 20, 3)))
    with pytest.raises(ValueError, match="NaN"):
        checks.check_image("image_a", np.full((10, 20), np.nan))
    with pytest.raises(ValueError, match="image_a and image_b differ in shape"):
        checks.check_same_shape(("image_a", "image_b"), img, np.zeros((10, 21)))


@pytest.mark.parametrize(
    ("key", "shown"),
    [("gain", "feed_loop.gain"), ("a b", 'feed_loop."a b"'), ("x\ny", 'feed_loop."x\\ny"'),
     ("k-1_A", "feed_loop.k-1_A"), ("", 'feed_loop.""')],
)
def test_keys_that_are_not_bare_are_quoted_so_messages_stay_one_line(key, shown):
    s = Section({key: 1}, "feed_loop")
    with pytest.raises(ConfigError) as err:
        s.reject_unknown()
    assert str(err.value) == f"unknown key {shown}" and "\n" not in str(err.value)


def test_a_file_that_is_not_utf8_is_a_config_error_naming_it(tmp_path):
    p = tmp_path / "latin1.toml"
    p.write_bytes('name = "Säge"\n'.encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin1\.toml: not valid TOML: not UTF-8"):
        load_toml(p)


def test_sim_defaults_are_written_once_in_the_dataclasses():
    """An empty sim file gives every table's dataclass defaults (the loader repeats none)."""
    import dataclasses

    import config.sim as sim

    rig_path = default_path("rig.toml")
    expected = {}
    for f in dataclasses.fields(sim.SimConfig):
        if f.name == "camera":  # the only table with required fields: the shipped rig
            expected[f.name] = sim.CameraConfig(rig_path=rig_path, rig=load_rig(rig_path))
        elif f.name in ("faults", "declared_heads"):  # no [[heads]]: the one head "main"
            expected[f.name] = ()
        elif f.name != "source":
            name = f.type if isinstance(f.type, str) else f.type.__name__
            expected[f.name] = getattr(sim, name)()
    assert sim.sim_from_dict({}) == sim.SimConfig(**expected)


def test_simulator_and_service_meet_at_the_same_default_endpoints():
    from config.machine import machine_from_dict
    from config.sim import sim_from_dict

    s, m = sim_from_dict({}), machine_from_dict({})
    assert (s.modbus.host, s.modbus.port) == (m.plc.host, m.plc.port)
    assert Path(s.frames.spool_dir) == Path(m.frames.spool_dir)
