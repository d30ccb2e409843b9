"""One merge rule for every configuration file: a partial file keeps every shipped value.

For every shipped file (``config/sim.toml``, ``config/machine.toml``, ``config/rig.toml``) and
every key in it: a file with only that key (its value changed) loads as the shipped file with
that one value changed, or fails with the same error the whole file so changed gives.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterator
from typing import Any

import pytest
import tomli_w

from config.loading import default_path, load_toml, merged, over_shipped
from config.machine import load_machine
from config.rig import load_rig
from config.sim import load_sim
from core.errors import ConfigError

LOADERS = {"sim.toml": load_sim, "machine.toml": load_machine, "rig.toml": load_rig}


def _leaves(doc: dict, path: tuple = ()) -> Iterator[tuple[tuple, Any]]:
    for key, value in doc.items():
        if isinstance(value, dict) and value:
            yield from _leaves(value, (*path, key))
        else:
            yield (*path, key), value


def _changed(value: Any) -> Any:
    """Another value of the same type (the same one where no generic change makes sense)."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    if isinstance(value, float):
        return value * 1.1 if value else 0.1
    if isinstance(value, list) and value and isinstance(value[0], (int, float)):
        return [_changed(value[0]), *value[1:]]
    return value  # strings, tables of lists: the same value, a file naming it is still partial


def _nested(path: tuple, value: Any) -> dict:
    out: dict = {path[-1]: value}
    for key in reversed(path[:-1]):
        out = {key: out}
    return out


def _load(kind: str, path):
    try:
        cfg = LOADERS[kind](path)
    except ConfigError as exc:
        return "error: " + str(exc).split(": ", 1)[1]  # without the file's name
    return dataclasses.replace(cfg, source=None) if hasattr(cfg, "source") else cfg


def _cases():
    for kind in LOADERS:
        for path, value in _leaves(load_toml(default_path(kind))):
            yield pytest.param(kind, path, value, id=f"{kind}:{'.'.join(path)}")


@pytest.mark.parametrize("kind, path, value", list(_cases()))
def test_a_file_with_one_key_is_the_shipped_file_with_that_value(tmp_path, kind, path, value):
    new = _changed(value)
    whole = copy.deepcopy(load_toml(default_path(kind)))
    node = whole
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = new
    (tmp_path / "whole.toml").write_text(tomli_w.dumps(whole))
    (tmp_path / "one_key.toml").write_text(tomli_w.dumps(_nested(path, new)))
    expected = _load(kind, tmp_path / "whole.toml")
    got = _load(kind, tmp_path / "one_key.toml")
    assert got == expected
    if new != value and not isinstance(expected, str):  # the one value did change
        assert got != _load(kind, default_path(kind)), path


def test_the_readme_sim_file_is_the_shipped_machine_on_another_can_bus(tmp_path):
    """README: ``sim_udp.toml`` with only ``[can]`` simulates the machine ``planer hil`` does."""
    p = tmp_path / "sim_udp.toml"
    p.write_text('[can]\ninterface = "udp_multicast"\nchannel = "239.74.163.2"\n')
    shipped, got = load_sim(), load_sim(p)
    assert got.camera.roll_deg == shipped.camera.roll_deg != 0.0  # roll, slants, noise kept
    assert dataclasses.replace(got, can=shipped.can, source=None) == dataclasses.replace(
        shipped, source=None)
    assert (got.can.interface, got.can.channel) == ("udp_multicast", "239.74.163.2")


def test_a_machine_file_with_only_the_exposure_keeps_the_image_size(tmp_path):
    p = tmp_path / "machine.toml"
    p.write_text("[frames]\nexposure_us = 800.0\n")
    cfg, shipped = load_machine(p), load_machine()
    assert cfg.frames.exposure_us == 800.0
    assert (cfg.frames.image_width, cfg.frames.image_height) == (
        shipped.frames.image_width, shipped.frames.image_height) != (0, 0)


def test_a_base_names_the_ground_and_that_ground_stands_on_the_shipped_file(tmp_path):
    p = tmp_path / "drift_fast.toml"
    p.write_text('base = "sim_drift.toml"\n[cutterhead.drift]\nwarmup_tau_s = 5.0\n')
    cfg, drift = load_sim(p), load_sim(default_path("sim_drift.toml"))
    assert cfg.cutterhead.drift.warmup_tau_s == (5.0,) * 4
    assert cfg.cutterhead.drift.warmup_um == drift.cutterhead.drift.warmup_um
    assert cfg.camera.roll_deg == load_sim().camera.roll_deg


@pytest.mark.parametrize("base, words", [
    ("nope.toml", "no such file"), ("../sim.toml", "base must name"), (3, "base must name")])
def test_a_bad_base_is_named(base, words):
    with pytest.raises(ConfigError, match=words):
        over_shipped({"base": base}, "sim.toml")


def test_merge_is_deep_and_replaces_lists_and_values():
    below = {"a": {"x": 1, "y": [1, 2], "t": {"u": 1}}, "b": 2}
    above = {"a": {"y": [3], "t": {"v": 2}}, "c": 3}
    assert merged(below, above) == {"a": {"x": 1, "y": [3], "t": {"u": 1, "v": 2}},
                                    "b": 2, "c": 3}
    assert below == {"a": {"x": 1, "y": [1, 2], "t": {"u": 1}}, "b": 2}  # unchanged
