"""config/machine.toml: the shipped file loads; bad values raise ConfigError naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from config.loading import load_toml
from config.machine import load_machine, machine_from_dict
from core.errors import ConfigError

SHIPPED = Path(__file__).parents[2] / "config" / "machine.toml"


def test_shipped_file_loads_and_is_frozen():
    cfg = load_machine(SHIPPED)
    assert cfg.plc.host == "127.0.0.1"
    assert cfg.safety.safe_state in ("hold", "ramp_down")
    assert cfg.frames.source in ("spool", "inprocess")
    assert cfg.quality.target_pitch_mm > 0
    with pytest.raises(AttributeError):
        cfg.plc.port = 1  # type: ignore[misc]
    with pytest.raises(TypeError):
        cfg.feed_loop["x"] = 1  # type: ignore[index]


def test_empty_document_gives_defaults():
    cfg = machine_from_dict({})
    assert cfg.plc.port == 5020 and cfg.can.interface == "virtual"
    assert cfg.log.path == Path("runs/quality.sqlite")


@pytest.mark.parametrize(
    "doc,key",
    [
        ({"plc": {"port": 0}}, "plc.port"),
        ({"plc": {"port": "502"}}, "plc.port"),
        ({"plc": {"timeout_s": 0}}, "plc.timeout_s"),
        ({"plc": {"hots": "x"}}, "plc.hots"),
        ({"plc": {"backoff_initial_s": 3.0, "backoff_max_s": 1.0}}, "plc.backoff_max_s"),
        ({"plc": {"host": " "}}, "plc.host"),
        ({"plc": {"unit_id": 248}}, "plc.unit_id"),
        ({"can": {"interface": "pcan"}}, "can.interface"),
        ({"can": {"channel": ""}}, "can.channel"),
        ({"can": {"options": 5}}, "can.options"),
        ({"can": {"command_period_s": 0.5}}, "can.command_period_s"),
        ({"frames": {"source": "usb"}}, "frames.source"),
        ({"quality": {"target_pitch_mm": -1.5}}, "quality.target_pitch_mm"),
        ({"quality": {"tolerance": 0}}, "quality.tolerance"),
        ({"piezo": {"stroke_um": 40.0}}, "piezo.stroke_um"),
        ({"safety": {"safe_state": "stop"}}, "safety.safe_state"),
        ({"safety": {"plc_timeout_s": 0.01}}, "safety.plc_timeout_s"),
        ({"safety": {"ramp_mm_s2": 0.0}}, "safety.ramp_mm_s2"),
        ({"plausibility": {"min_marks": 1}}, "plausibility.min_marks"),
        ({"feed_loop": {"kp": {"a": 1}}}, "feed_loop.kp"),
        ({"log": {"print_every": 0}}, "log.print_every"),
        ({"colour": "red"}, "colour"),
    ],
)
def test_bad_values_name_the_key(doc, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        machine_from_dict(doc)


def test_file_errors_name_the_file(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text("[safety]\nsafe_state = 'stop'\n")
    with pytest.raises(ConfigError, match=r"m\.toml.*safety\.safe_state"):
        load_machine(p)
    with pytest.raises(ConfigError, match="not found"):
        load_machine(tmp_path / "missing.toml")


def test_machine_variant_is_a_config_change():
    doc = load_toml(SHIPPED)
    doc["can"].update(interface="socketcan", channel="can0")
    doc["plc"].update(host="192.168.0.10", port=502)
    cfg = machine_from_dict(doc)
    got = (cfg.can.interface, cfg.can.channel, cfg.plc.host)
    assert got == ("socketcan", "can0", "192.168.0.10")


@pytest.mark.parametrize(
    "table,key",
    [({"feed_loop": {"kii": 0.5}}, "feed_loop.kii"), ({"uniformity_loop": {"gain": 5.0}},
                                                      "uniformity_loop.gain")],
)
def test_bad_loop_keys_fail_when_the_service_is_built(table, key):
    from types import SimpleNamespace

    from controller.service.service import Service

    cfg = machine_from_dict(table)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        Service(cfg, plc=None, piezo=None, measurer_factory=lambda s: None,
                rig=SimpleNamespace(), log=None)


@pytest.mark.parametrize("table", ["feed_loop", "uniformity_loop"])
def test_bad_loop_keys_name_the_file_they_came_from(tmp_path, table):
    """``unknown key feed_loop.gian`` must say which file holds it."""
    from types import SimpleNamespace

    from controller.service.service import Service

    p = tmp_path / "mine.toml"
    p.write_text(f"[{table}]\ngian = 0.5\n")
    cfg = load_machine(p)
    assert cfg.source == p and cfg.with_changes().source == p
    with pytest.raises(ConfigError) as err:
        Service(cfg, plc=None, piezo=None, measurer_factory=lambda s: None,
                rig=SimpleNamespace(), log=None)
    assert str(err.value) == f"{p}: unknown key {table}.gian"


def test_source_does_not_take_part_in_equality(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text("")
    assert load_machine(p) == load_machine() and load_machine(p).source == p
    assert machine_from_dict({}).source is None


def test_naming_file_prefixes_once():
    from config.loading import naming_file

    with pytest.raises(ConfigError, match=r"^a\.toml: bad$"):
        with naming_file("a.toml"):
            with naming_file("a.toml"):
                raise ConfigError("bad")
    with pytest.raises(ConfigError, match=r"^bad$"):
        with naming_file(None):
            raise ConfigError("bad")
    with pytest.raises(ValueError, match=r"^plain$"):  # only ConfigError is about the file
        with naming_file("a.toml"):
            raise ValueError("plain")


def test_missing_keys_take_the_dataclass_defaults():
    """Each default is written once (the field's default): an empty file is ``MachineConfig()``."""
    from config.machine import MachineConfig

    assert machine_from_dict({}) == MachineConfig()
    # and a table with one key set keeps every other field's default
    cfg = machine_from_dict({"safety": {"recovery_s": 1.25}})
    assert cfg.safety == MachineConfig().safety.__class__(recovery_s=1.25)


@pytest.mark.parametrize(("width", "height", "shape"), [
    (659, 493, (493, 659)),  # (rows, columns): numpy's order
    (0, 493, None),  # either unset: the measurement sets up on the first pair
    (659, 0, None),
    (0, 0, None),
])
def test_frames_image_shape_is_height_width_when_both_are_set(width, height, shape):
    cfg = machine_from_dict({"frames": {"image_width": width, "image_height": height}})
    assert cfg.frames.image_shape == shape
