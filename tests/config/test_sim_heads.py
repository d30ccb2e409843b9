"""Heads as configuration, the simulator side: ``[[heads]]`` of sim.toml over the shared tables,
``head_sim_config``, a variable spindle, faults naming a head, the shipped moulder file."""

from __future__ import annotations

import dataclasses

import pytest

from config.faults import Fault, FaultKind, parse_fault, parse_faults
from config.heads import Face
from config.loading import default_path
from config.machine import load_machine
from config.sim import (
    SpindleConfig,
    default_sim_head,
    head_sim_config,
    load_sim,
    sim_from_dict,
)
from core.errors import ConfigError

MOULDER = default_path("sim_moulder.toml")


def _head(**over):
    return {"name": "right", "face": "right", "node_id": 3, **over}


# ------------------------------------------------------------------------ the default head "main"
@pytest.mark.parametrize("name", ["sim.toml", "sim_drift.toml", "sim_wear.toml", "sim_nick.toml",
                                  "sim_defects.toml"])
def test_shipped_single_head_files_have_one_head_main_equal_to_their_tables(name):
    cfg = load_sim(default_path(name))
    (head,) = cfg.heads
    assert (head.name, head.face, head.position_mm, head.node_id) == ("main", Face.TOP, 0.0,
                                                                      cfg.can.node_id)
    assert (head.cutterhead, head.spindle, head.camera, head.piezo) == (
        cfg.cutterhead, cfg.spindle, cfg.camera, cfg.piezo)
    assert head_sim_config(cfg, "main") == cfg


def test_the_default_head_follows_a_changed_table():
    cfg = load_sim()
    flat = dataclasses.replace(cfg, cutterhead=dataclasses.replace(cfg.cutterhead,
                                                                   runout_um=(0.0,) * 4))
    assert flat.heads[0].cutterhead.runout_um == (0.0,) * 4
    assert flat.heads[0] == default_sim_head(flat)


# ---------------------------------------------------------------------------- [[heads]] loading
def test_a_head_with_the_shared_knife_count_keeps_the_shared_runout_and_drift():
    base = load_sim(default_path("sim_drift.toml"))
    cfg = sim_from_dict({"base": "sim_drift.toml", "heads": [_head(rpm=9000.0)]})
    (head,) = cfg.heads
    assert head.cutterhead == base.cutterhead and head.cutterhead.drift is not None
    assert head.spindle == dataclasses.replace(base.spindle, rpm=9000.0)
    assert not head.spindle.variable
    assert (head.camera, head.piezo) == (base.camera, base.piezo)


def test_a_head_with_another_knife_count_starts_without_runout_or_drift():
    cfg = sim_from_dict({"base": "sim_drift.toml", "heads": [_head(knives=2)]})
    ch = cfg.heads[0].cutterhead
    assert (ch.knives, ch.runout_um, ch.drift) == (2, (0.0, 0.0), None)
    assert ch.radius_mm == cfg.cutterhead.radius_mm


def test_a_heads_own_tables_override_the_shared_ones():
    cfg = sim_from_dict({"heads": [_head(
        knives=2, radius_mm=50.0, runout_um=[1.0, -1.0], eccentricity_um=0.0,
        drift={"warmup_um": [1.0, 2.0], "warmup_tau_s": 10.0, "wear_um_per_min": [0.0, 0.5]},
        rpm=6000.0, rpm_min=4000.0, rpm_max=8000.0, cutter_to_camera_mm=250.0, roll_deg=-0.2,
        species="oak", read_noise_dn=1.0, stroke_um=15.0, position_mm=400.0)]})
    h = cfg.heads[0]
    assert (h.cutterhead.knives, h.cutterhead.radius_mm, h.cutterhead.runout_um,
            h.cutterhead.eccentricity_um) == (2, 50.0, (1.0, -1.0), 0.0)
    assert h.cutterhead.drift.warmup_tau_s == (10.0, 10.0)
    assert h.cutterhead.drift.wear_um_per_min == (0.0, 0.5)
    assert (h.spindle.rpm, h.spindle.rpm_range, h.spindle.variable) == (6000.0, (4000.0, 8000.0),
                                                                      True)
    assert h.spindle.ripple_frac == cfg.spindle.ripple_frac  # the rest is the shared [spindle]
    assert (h.camera.cutter_to_camera_mm, h.camera.roll_deg, h.camera.species,
            h.camera.optics.noise) == (250.0, -0.2, "oak", 1.0)
    assert h.camera.rig == cfg.camera.rig and h.camera.pairs_per_s == cfg.camera.pairs_per_s
    assert h.piezo == dataclasses.replace(cfg.piezo, stroke_um=15.0)
    assert (h.position_mm, h.node_id, h.face) == (400.0, 3, Face.RIGHT)


def test_a_variable_head_without_rpm_starts_at_its_fastest():
    (h,) = sim_from_dict({"heads": [_head(rpm_min=4000.0, rpm_max=8000.0)]}).heads
    assert (h.spindle.rpm, h.spindle.rpm_range) == (8000.0, (4000.0, 8000.0))


def test_a_variable_spindle_table_without_rpm_starts_at_its_fastest_as_a_head_does():
    # [spindle] and a head complete their speeds by the one rule (config.heads.rpm_range)
    cfg = sim_from_dict({"spindle": {"rpm_min": 7000.0, "rpm_max": 9000.0}})
    assert (cfg.spindle.rpm, cfg.spindle.rpm_range) == (9000.0, (7000.0, 9000.0))
    fixed = sim_from_dict({"spindle": {"rpm": 5000.0}}).spindle
    assert (fixed.rpm, fixed.rpm_min, fixed.rpm_max, fixed.variable) == (5000.0, None, None, False)
    with pytest.raises(ConfigError, match=r"spindle\.rpm_min must be <= spindle\.rpm"):
        sim_from_dict({"spindle": {"rpm": 6000.0, "rpm_min": 7000.0, "rpm_max": 9000.0}})
    with pytest.raises(ConfigError, match=r"spindle\.rpm_max needs spindle\.rpm_min"):
        sim_from_dict({"spindle": {"rpm_max": 9000.0}})


def test_the_heads_toml_shape_with_a_drift_sub_table_loads(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[[heads]]\nname = "a"\nface = "bottom"\nnode_id = 2\n'
                 '[heads.drift]\nwarmup_um = [1.0, 2.0, 3.0, 4.0]\n'
                 '[[heads]]\nname = "b"\nface = "top"\nnode_id = 3\nknives = 2\n')
    a, b = load_sim(p).heads
    assert a.cutterhead.drift.warmup_um == (1.0, 2.0, 3.0, 4.0)
    assert b.cutterhead.drift is None and b.cutterhead.knives == 2


@pytest.mark.parametrize("heads,key,bad", [
    ([{"face": "top", "node_id": 2}], "missing key heads[0].name", None),
    ([_head(name="Right")], "heads[0].name", "'Right'"),
    ([_head(face="front")], "heads[0].face", "'front'"),
    ([_head(node_id=200)], "heads[0].node_id", "200"),
    ([{"name": "a", "face": "top"}], "missing key heads[0].node_id", None),
    ([_head(knives=9)], "heads[0].knives", "9"),
    ([_head(knives=2, runout_um=[1.0, 2.0, 3.0])], "heads[0].runout_um", "3"),
    ([_head(runout_um=[0.0, 0.0, 0.0, 500.0])], "heads[0].runout_um[3]", "500.0"),
    ([_head(drift={"wear_um_per_min": [0.0, 0.0, 0.0, 99.0]})],
     "heads[0].drift.wear_um_per_min[3]", "99.0"),
    ([_head(drift={"warmup_um": [1.0]})], "heads[0].drift.warmup_um", None),
    ([_head(radius_mm=1.0)], "heads[0].radius_mm", "1.0"),
    ([_head(rpm=50.0)], "heads[0].rpm", "50.0"),
    ([_head(rpm=6000.0, rpm_min=7000.0, rpm_max=8000.0)], "heads[0].rpm_min", "7000.0"),
    ([_head(rpm=9000.0, rpm_min=4000.0, rpm_max=8000.0)], "heads[0].rpm_max", "8000.0"),
    ([_head(rpm_min=4000.0)], "heads[0].rpm_min", None),
    ([_head(rpm_max="fast")], "heads[0].rpm_max", "'fast'"),
    ([_head(species="balsa")], "heads[0].species", "'balsa'"),
    ([_head(roll_deg=20.0)], "heads[0].roll_deg", "20.0"),
    ([_head(cutter_to_camera_mm=0.0)], "heads[0].cutter_to_camera_mm", "0.0"),
    ([_head(read_noise_dn=-1.0)], "heads[0].read_noise_dn", "-1.0"),
    ([_head(stroke_um=0.0)], "heads[0].stroke_um", "0.0"),
    ([_head(position_mm=-1.0)], "heads[0].position_mm", "-1.0"),
    ([_head(spindle_rpm=6000.0)], "unknown key heads[0].spindle_rpm", None),
    ([_head(name="a"), _head(name="a", node_id=4)], "heads[1].name", "'a'"),
    ([_head(name="a"), _head(name="b")], "heads[1].node_id", "3"),
    # 1000 mm/s at 500 rpm with 1 knife: 120 mm per pass, over R/4 = 15 mm
    ([_head(name="a"), _head(name="slow", node_id=4, knives=1, rpm=500.0)],
     "at heads[1].rpm;", None),
    ([_head(rpm_min=500.0, rpm_max=8000.0, knives=1)], "at heads[0].rpm_min;", None),
])
def test_bad_sim_heads_name_their_key_and_value(heads, key, bad):
    with pytest.raises(ConfigError) as err:
        sim_from_dict({"heads": heads})
    msg = str(err.value)
    assert key in msg
    if bad is not None:
        assert bad in msg
    assert "\n" not in msg


@pytest.mark.parametrize("raw", [[], {"name": "a"}])
def test_sim_heads_must_be_a_non_empty_array_of_tables(raw):
    with pytest.raises(ConfigError, match=r"^heads must be a non-empty array of tables"):
        sim_from_dict({"heads": raw})


# ------------------------------------------------------------------------ a variable [spindle]
def test_the_shared_spindle_may_be_variable():
    cfg = sim_from_dict({"spindle": {"rpm": 6000.0, "rpm_min": 4000.0, "rpm_max": 8000.0}})
    assert (cfg.spindle.rpm_range, cfg.spindle.variable) == ((4000.0, 8000.0), True)
    assert cfg.heads[0].spindle == cfg.spindle


def test_a_fixed_spindle_ranges_over_its_rpm_alone():
    assert SpindleConfig(rpm=9000.0).rpm_range == (9000.0, 9000.0)
    assert not SpindleConfig().variable
    assert load_sim().spindle.rpm_range == (6000.0, 6000.0)


@pytest.mark.parametrize("spindle,key", [
    ({"rpm_min": 4000.0}, "spindle.rpm_min"),
    ({"rpm": 6000.0, "rpm_min": 7000.0, "rpm_max": 8000.0}, "spindle.rpm_min"),
    ({"rpm": 6000.0, "rpm_min": 1.0, "rpm_max": 8000.0}, "spindle.rpm_min"),
])
def test_a_bad_spindle_range_names_its_key(spindle, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        sim_from_dict({"spindle": spindle})


# -------------------------------------------------------------------------- faults naming a head
def test_a_fault_may_name_a_head_and_keeps_it_apart_from_its_parameters():
    fault = parse_fault({"kind": "knife_chip", "head": "right", "knife": 1, "at_s": 2.0}, "f")
    assert (fault.head, fault.at_s, dict(fault.params)) == ("right", 2.0, {"knife": 1})
    assert fault.table() == {"kind": "knife_chip", "at_s": 2.0, "head": "right", "knife": 1}
    assert parse_fault(fault.table(), "f") == fault
    assert parse_fault({"kind": "reset"}, "f").head is None
    assert "head" not in parse_fault({"kind": "reset"}, "f").table()


@pytest.mark.parametrize("item,heads,key,bad", [
    ({"kind": "knife_chip", "head": "middle"}, ("main",), "f.head", "'middle'"),
    ({"kind": "knife_chip", "head": "Right"}, None, "f.head", "'Right'"),
    ({"kind": "knife_chip", "head": 3}, None, "f.head", "3"),
])
def test_a_bad_fault_head_names_its_key(item, heads, key, bad):
    with pytest.raises(ConfigError) as err:
        parse_fault(item, "f", heads=heads)
    assert key in str(err.value) and bad in str(err.value)


def test_parse_faults_checks_every_head_against_the_machine():
    raw = [{"kind": "reset"}, {"kind": "piezo_fault", "head": "top"},
           {"kind": "piezo_fault", "head": "side"}]
    with pytest.raises(ConfigError, match=r"faults\[2\]\.head must name one of the heads "
                                          r"\(bottom, top\), got 'side'"):
        parse_faults(raw, "faults", heads=("bottom", "top"))
    assert [f.head for f in parse_faults(raw[:2], "faults", heads=("top",))] == [None, "top"]


def test_fault_built_in_code_checks_its_head():
    with pytest.raises(ConfigError, match="reset.head"):
        Fault(FaultKind.RESET, head="Not A Name")


@pytest.mark.parametrize("faults,key", [
    ({"inject": [{"kind": "reset"}, {"kind": "piezo_fault", "head": "right"}]},
     r"faults\.inject\[1\]\.head .*'right'"),
    ([{"kind": "piezo_fault", "head": "right"}], r"faults\[0\]\.head .*'right'"),
])
def test_a_sim_fault_naming_an_unknown_head_is_refused_at_load(faults, key):
    with pytest.raises(ConfigError, match=key):
        sim_from_dict({"faults": faults})  # one head: "main"


def test_a_sim_fault_keeps_its_head_out_of_the_machines_parameters():
    cfg = sim_from_dict({"base": "sim_moulder.toml", "faults": {"inject": [
        {"kind": "knife_chip", "head": "right", "knife": 1}, {"kind": "feed_fault"},
        {"kind": "piezo_fault", "head": "top"}]}})
    chip = cfg.faults[0]
    assert (chip.kind, chip.head, dict(chip.params)) == ("knife_chip", "right", {"knife": 1})
    # the feed's fault strikes the first head (the feed's owner) alone, as the Moulder routes it
    assert [f.kind for f in head_sim_config(cfg, "bottom").faults] == ["feed_fault"]
    assert [f.kind for f in head_sim_config(cfg, "right").faults] == ["knife_chip"]
    assert [f.kind for f in head_sim_config(cfg, "top").faults] == ["piezo_fault"]
    assert [f.kind for f in head_sim_config(cfg, "left").faults] == []


@pytest.mark.parametrize(("kind", "head", "struck"), [
    ("estop", None, ["bottom", "right", "left", "top"]),
    ("species_change", None, ["bottom", "right", "left", "top"]),
    ("feed_fault", None, ["bottom"]),
    ("modbus_restart", None, ["bottom"]),
    ("knife_chip", "left", ["left"]),
    ("estop", "top", ["top"]),
])
def test_head_sim_config_and_the_moulder_route_a_fault_by_one_rule(kind, head, struck):
    from config.sim import fault_heads
    from plant_sim.machine.moulder import Moulder

    fault = {"kind": kind, **({"head": head} if head else {}),
             **({"knife": 0} if kind == "knife_chip" else {}),
             **({"species": "oak"} if kind == "species_change" else {}),
             **({"duration_s": 1.0} if kind == "modbus_restart" else {})}
    cfg = sim_from_dict({"base": "sim_moulder.toml", "faults": {"inject": [fault]}})
    names = [h.name for h in cfg.heads]
    assert list(fault_heads(kind, head, names)) == struck
    assert [n for n in names if head_sim_config(cfg, n).faults] == struck
    if kind in ("modbus_restart",):
        return  # an interface fault: its driver plays it, no machine's schedule holds it
    moulder = Moulder(cfg, seed=0, render_images=False)
    assert [n for n in names if moulder.heads[n].cfg.faults] == struck


def test_a_one_head_fault_without_its_head_is_refused_at_load_in_a_moulder():
    with pytest.raises(ConfigError, match=r"faults\.inject\[0\]: fault knife_chip strikes one "
                                          r"head: give head="):
        sim_from_dict({"base": "sim_moulder.toml",
                       "faults": {"inject": [{"kind": "knife_chip", "knife": 0}]}})
    # one head: it is the head's
    assert sim_from_dict({"faults": {"inject": [{"kind": "knife_chip", "knife": 0}]}}).faults


# ---------------------------------------------------------------------- the shipped moulder file
MOULDER_HEADS = [  # name, face, position, knives, rpm range, start rpm, node id
    ("bottom", "bottom", 0.0, 4, (6000.0, 6000.0), 6000.0, 2),
    ("right", "right", 400.0, 2, (9000.0, 9000.0), 9000.0, 3),
    ("left", "left", 700.0, 2, (9000.0, 9000.0), 9000.0, 4),
    ("top", "top", 1100.0, 6, (4000.0, 8000.0), 6000.0, 5),
]


def test_the_moulder_sim_file_has_the_design_heads():
    cfg = load_sim(MOULDER)
    got = [(h.name, h.face.value, h.position_mm, h.cutterhead.knives, h.spindle.rpm_range,
            h.spindle.rpm, h.node_id) for h in cfg.heads]
    assert got == MOULDER_HEADS
    assert all(len(h.cutterhead.runout_um) == h.cutterhead.knives for h in cfg.heads)
    assert (cfg.feed.min_mm_s, cfg.feed.max_mm_s, cfg.feed.initial_mm_s) == (50.0, 1000.0, 600.0)


def test_the_moulder_sim_and_service_files_describe_the_same_heads():
    sim = load_sim(MOULDER).heads
    svc = load_machine(default_path("machine_moulder.toml")).heads
    assert [(h.name, h.face, h.position_mm, h.cutterhead.knives, h.spindle.rpm_range,
             h.spindle.rpm, h.node_id) for h in sim] == [
        (h.name, h.face, h.position_mm, h.knives, (h.rpm_min, h.rpm_max), h.rpm, h.node_id)
        for h in svc]


@pytest.mark.parametrize("name", ["bottom", "right", "left", "top"])
def test_head_sim_config_is_the_heads_machine_with_the_shared_feed(name):
    cfg = load_sim(MOULDER)
    one = head_sim_config(cfg, name)
    (head,) = one.heads
    assert head.name == name
    assert (one.cutterhead, one.spindle, one.camera, one.piezo, one.can.node_id) == (
        head.cutterhead, head.spindle, head.camera, head.piezo, head.node_id)
    assert (one.feed, one.encoder, one.board, one.plc, one.modbus, one.frames, one.run) == (
        cfg.feed, cfg.encoder, cfg.board, cfg.plc, cfg.modbus, cfg.frames, cfg.run)
    assert dataclasses.replace(one.can, node_id=cfg.can.node_id) == cfg.can
    assert head_sim_config(one, name) == one


def test_head_sim_config_of_an_unknown_head_is_an_error():
    with pytest.raises(ConfigError, match="no head named 'main'; the heads are bottom"):
        head_sim_config(load_sim(MOULDER), "main")
