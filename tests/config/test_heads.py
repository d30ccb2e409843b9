"""Heads as configuration, the service side: ``[[heads]]`` of machine.toml, the default head
"main", ``head_config``, and the shipped moulder file."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from config.heads import FACES, Face, HeadConfig, find_head, head_table, heads_from_toml
from config.loading import default_path
from config.machine import default_head, head_config, load_machine, machine_from_dict
from core.errors import ConfigError

MOULDER = default_path("machine_moulder.toml")


def _head(**over):
    """A well-formed [[heads]] table with ``over`` changed."""
    return {"name": "top", "face": "top", "node_id": 3, "target_pitch_mm": 1.0, **over}


def _heads(*tables):
    return {"heads": list(tables)}


# ------------------------------------------------------------------------ the default head "main"
def test_a_file_without_heads_has_one_head_main_from_its_tables():
    cfg = machine_from_dict({})
    (head,) = cfg.heads
    assert head.name == "main" and head.face is Face.TOP and head.position_mm == 0.0
    assert head.node_id == cfg.can.node_id == 2
    assert head.target_pitch_mm == cfg.quality.target_pitch_mm == 1.5
    assert head.spool_dir == cfg.frames.spool_dir and head.rig is None
    assert (head.knives, head.radius_mm, head.rpm, head.rpm_min, head.rpm_max) == (None,) * 5
    assert not head.variable
    assert cfg.declared_heads == ()


def test_the_default_head_follows_the_existing_keys():
    doc = {"rig": "my_rig.toml", "can": {"node_id": 9},
           "quality": {"target_pitch_mm": 2.25, "class_name": "coarse"},
           "frames": {"spool_dir": "spool_a", "camera_id": "Fake_1"}}
    (head,) = machine_from_dict(doc).heads
    assert (head.name, head.node_id, head.target_pitch_mm, head.rig, head.spool_dir,
            head.camera_id) == ("main", 9, 2.25, Path("my_rig.toml"), Path("spool_a"), "Fake_1")


def test_the_default_head_follows_a_changed_table():
    """HIL and the sweep change [quality] in code: the single head is derived, never stale."""
    cfg = load_machine()
    changed = cfg.with_changes(quality=replace(cfg.quality, target_pitch_mm=0.5),
                               can=replace(cfg.can, node_id=11))
    assert (changed.heads[0].target_pitch_mm, changed.heads[0].node_id) == (0.5, 11)
    assert changed.heads[0] == default_head(changed)


@pytest.mark.parametrize("doc", [
    {},
    {"rig": "r.toml", "can": {"node_id": 7}, "quality": {"target_pitch_mm": 0.8,
                                                        "class_name": "x"},
     "frames": {"spool_dir": "elsewhere", "camera_id": "cam"}},
])
def test_head_config_of_main_is_the_config_itself(doc):
    cfg = machine_from_dict(doc)
    assert head_config(cfg, "main") == cfg


def test_head_config_of_main_in_the_shipped_file_is_the_config_itself():
    cfg = load_machine()
    assert head_config(cfg, "main") == cfg
    assert head_config(cfg, "main").heads == cfg.heads


# ---------------------------------------------------------------------------- [[heads]] loading
def test_a_head_takes_what_it_does_not_give_from_the_file():
    doc = {"rig": "shared_rig.toml", "quality": {"target_pitch_mm": 1.75},
           "frames": {"spool_dir": "runs/sp", "camera_id": "Fake_0"},
           **_heads({"name": "a", "face": "left", "node_id": 4},
                    {"name": "b", "face": "right", "node_id": 5, "target_pitch_mm": 2.0,
                     "rig": "b_rig.toml", "spool_dir": "b_spool", "camera_id": "Fake_b",
                     "quality_class": "std", "uniformity_max_cv": 0.04})}
    a, b = machine_from_dict(doc).heads
    assert (a.target_pitch_mm, a.rig, a.spool_dir, a.camera_id, a.quality_class,
            a.uniformity_max_cv) == (1.75, Path("shared_rig.toml"), Path("runs/sp/a"), "Fake_0",
                                     None, None)
    assert (b.target_pitch_mm, b.rig, b.spool_dir, b.camera_id, b.quality_class,
            b.uniformity_max_cv) == (2.0, Path("b_rig.toml"), Path("b_spool"), "Fake_b", "std",
                                     0.04)


@pytest.mark.parametrize("given,expect", [
    ({}, (None, None, None, False)),
    ({"rpm": 9000.0}, (9000.0, 9000.0, 9000.0, False)),
    ({"rpm": 6000, "rpm_min": 4000, "rpm_max": 8000}, (6000.0, 4000.0, 8000.0, True)),
    ({"rpm_min": 4000.0, "rpm_max": 8000.0}, (8000.0, 4000.0, 8000.0, True)),  # starts fastest
    ({"rpm": 5000.0, "rpm_min": 5000.0, "rpm_max": 5000.0}, (5000.0, 5000.0, 5000.0, False)),
])
def test_speeds_of_fixed_and_variable_heads(given, expect):
    (head,) = machine_from_dict(_heads(_head(**given))).heads
    assert (head.rpm, head.rpm_min, head.rpm_max, head.variable) == expect


@pytest.mark.parametrize("heads,key,bad", [
    ([{"face": "top", "node_id": 3}], "missing key heads[0].name", None),
    ([_head(name="Top")], "heads[0].name", "'Top'"),
    ([_head(name="2nd")], "heads[0].name", "'2nd'"),
    ([_head(name=7)], "heads[0].name", "7"),
    ([_head(face="front")], "heads[0].face", "'front'"),
    ([{"name": "a", "node_id": 3}], "missing key heads[0].face", None),
    ([_head(node_id=0)], "heads[0].node_id", "0"),
    ([_head(node_id=128)], "heads[0].node_id", "128"),
    ([{"name": "a", "face": "top"}], "missing key heads[0].node_id", None),
    ([_head(knives=9)], "heads[0].knives", "9"),
    ([_head(knives=0)], "heads[0].knives", "0"),
    ([_head(target_pitch_mm=0.0)], "heads[0].target_pitch_mm", "0.0"),
    ([_head(radius_mm=1.0)], "heads[0].radius_mm", "1.0"),
    ([_head(position_mm=-5.0)], "heads[0].position_mm", "-5.0"),
    ([_head(rpm=50.0)], "heads[0].rpm", "50.0"),
    ([_head(uniformity_max_cv=0.0)], "heads[0].uniformity_max_cv", "0.0"),
    ([_head(rmp=6000.0)], "unknown key heads[0].rmp", None),
    ([_head(spool_dir="")], "heads[0].spool_dir", None),
    ([_head(name="a", node_id=2), _head(name="b", node_id=3),
      _head(name="c", node_id=4, rpm=6000.0, rpm_min=7000.0, rpm_max=8000.0)],
     "heads[2].rpm_min", "7000.0"),
    ([_head(rpm=9000.0, rpm_min=4000.0, rpm_max=8000.0)], "heads[0].rpm_max", "8000.0"),
    ([_head(rpm_min=8000.0, rpm_max=4000.0)], "heads[0].rpm_min", "8000.0"),
    ([_head(rpm_min=4000.0)], "heads[0].rpm_min", None),
    ([_head(rpm_max=4000.0)], "heads[0].rpm_max", None),
    ([_head(name="a", node_id=2), _head(name="a", node_id=3)], "heads[1].name", "'a'"),
    ([_head(name="a", node_id=2), _head(name="b", node_id=2)], "heads[1].node_id", "2"),
    ([_head(name="a", node_id=2, spool_dir="s"), _head(name="b", node_id=3, spool_dir="s")],
     "heads[1].spool_dir", "'s'"),
])
def test_bad_heads_name_their_key_and_value(heads, key, bad):
    with pytest.raises(ConfigError) as err:
        machine_from_dict({"heads": heads})
    msg = str(err.value)
    assert key in msg
    if bad is not None:
        assert bad in msg
    assert "\n" not in msg  # one line


@pytest.mark.parametrize("raw", [[], {"name": "a"}, "top"])
def test_heads_must_be_a_non_empty_array_of_tables(raw):
    with pytest.raises(ConfigError, match=r"^heads must be a non-empty array of tables"):
        machine_from_dict({"heads": raw})


def test_a_bad_head_in_a_file_names_the_file(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text('[[heads]]\nname = "a"\nface = "top"\nnode_id = 2\n'
                 '[[heads]]\nname = "b"\nface = "up"\nnode_id = 3\n')
    with pytest.raises(ConfigError, match=r"m\.toml: heads\[1\]\.face .*'up'"):
        load_machine(p)


def test_heads_table_round_trips():
    heads = load_machine(MOULDER).heads
    again = heads_from_toml([dict(head_table(h)) for h in heads], rig=None,
                            spool_dir=Path("elsewhere"), camera_id="x", target_pitch_mm=9.0)
    assert again == heads


# ------------------------------------------------------------------------- HeadConfig in code
@pytest.mark.parametrize("over,field,bad", [
    ({"name": "Main"}, "name", "'Main'"),
    ({"face": "front"}, "face", "'front'"),
    ({"node_id": 0}, "node_id", "0"),
    ({"node_id": True}, "node_id", "True"),
    ({"knives": 9}, "knives", "9"),
    ({"target_pitch_mm": -1.0}, "target_pitch_mm", "-1.0"),
    ({"position_mm": -1.0}, "position_mm", "-1.0"),
    ({"rpm": 5000.0, "rpm_min": 6000.0, "rpm_max": 7000.0}, "rpm_min", "6000.0"),
])
def test_head_config_built_in_code_is_checked(over, field, bad):
    kw = {"name": "top", "face": "top", "node_id": 2, "target_pitch_mm": 1.0, **over}
    with pytest.raises(ConfigError) as err:
        HeadConfig(**kw)
    assert field in str(err.value) and bad in str(err.value)


def test_head_config_in_code_looks_up_its_face_and_completes_a_fixed_speed():
    head = HeadConfig(name="right", face="right", node_id=3, target_pitch_mm=2.0, rpm=9000.0)
    assert head.face is Face.RIGHT and f"{head.face}" == "right"
    assert (head.rpm_min, head.rpm_max, head.variable) == (9000.0, 9000.0, False)


def test_find_head_lists_the_names_when_there_is_none():
    heads = load_machine(MOULDER).heads
    assert find_head(heads, "left").node_id == 4
    with pytest.raises(ConfigError, match="no head named 'middle'; the heads are bottom, right, "
                                          "left, top"):
        find_head(heads, "middle")


def test_faces_are_the_design_names():
    assert FACES == ("bottom", "right", "left", "top", "profile")


# ---------------------------------------------------------------------- the shipped moulder file
MOULDER_HEADS = [  # name, face, position, knives, rpm, rpm_min, rpm_max, node, target
    ("bottom", "bottom", 0.0, 4, 6000.0, 6000.0, 6000.0, 2, 1.5),
    ("right", "right", 400.0, 2, 9000.0, 9000.0, 9000.0, 3, 2.0),
    ("left", "left", 700.0, 2, 9000.0, 9000.0, 9000.0, 4, 2.0),
    ("top", "top", 1100.0, 6, 6000.0, 4000.0, 8000.0, 5, 1.0),
]


def test_the_moulder_file_has_the_design_heads():
    cfg = load_machine(MOULDER)
    got = [(h.name, h.face.value, h.position_mm, h.knives, h.rpm, h.rpm_min, h.rpm_max,
            h.node_id, h.target_pitch_mm) for h in cfg.heads]
    assert got == MOULDER_HEADS
    assert [h.variable for h in cfg.heads] == [False, False, False, True]
    shipped = load_machine()  # every other table is the shipped file's
    assert (cfg.plc, cfg.can, cfg.safety, cfg.log) == (shipped.plc, shipped.can, shipped.safety,
                                                       shipped.log)


def test_the_moulder_targets_meet_at_600_mm_s():
    """The design's fastest common feed: every fixed head meets its target at 600 mm/s; the
    variable top head meets its own there at 6000 rpm, inside its range."""
    heads = load_machine(MOULDER).heads
    fixed = [h.target_pitch_mm * h.rpm / 60.0 * h.knives for h in heads if not h.variable]
    assert min(fixed) == pytest.approx(600.0)
    (top,) = [h for h in heads if h.variable]
    rpm = 600.0 * 60.0 / (top.knives * top.target_pitch_mm)
    assert rpm == pytest.approx(6000.0) and top.rpm_min <= rpm <= top.rpm_max


@pytest.mark.parametrize("name,node,target,cls,spool", [
    ("bottom", 2, 1.5, "fine-1.5", "runs/spool/bottom"),
    ("right", 3, 2.0, "standard-2.0", "runs/spool/right"),
    ("left", 4, 2.0, "standard-2.0", "runs/spool/left"),
    ("top", 5, 1.0, "fine-1.0", "runs/spool/top"),
])
def test_head_config_gives_each_head_its_own_service_config(name, node, target, cls, spool):
    cfg = load_machine(MOULDER)
    one = head_config(cfg, name)
    assert one.heads == (find_head(cfg.heads, name),)
    assert (one.can.node_id, one.quality.target_pitch_mm, one.quality.class_name,
            one.frames.spool_dir) == (node, target, cls, Path(spool))
    # the rest is the machine's: the bus, the PLC, the log, the loops, the safety
    assert replace(one.can, node_id=cfg.can.node_id) == cfg.can
    assert replace(one.quality, target_pitch_mm=cfg.quality.target_pitch_mm,
                   class_name=cfg.quality.class_name) == cfg.quality
    assert (one.plc, one.log, one.safety, one.feed_loop, one.rig) == (
        cfg.plc, cfg.log, cfg.safety, cfg.feed_loop, cfg.rig)
    assert head_config(one, name) == one  # a head's config is its own single head


def test_head_config_takes_the_heads_cv_limit_and_camera():
    doc = {"frames": {"camera_id": "Fake_shared"}, "quality": {"uniformity_max_cv": 0.05},
           **_heads(_head(uniformity_max_cv=0.03, camera_id="Fake_top"),
                    _head(name="low", node_id=4))}
    cfg = machine_from_dict(doc)
    top, low = head_config(cfg, "top"), head_config(cfg, "low")
    assert (top.quality.uniformity_max_cv, top.frames.camera_id) == (0.03, "Fake_top")
    assert (low.quality.uniformity_max_cv, low.frames.camera_id) == (0.05, "Fake_shared")


def test_head_config_of_an_unknown_head_is_an_error():
    with pytest.raises(ConfigError, match="no head named 'top'; the heads are main"):
        head_config(load_machine(), "top")


def test_a_moulder_reading_cameras_directly_is_refused_in_one_line(tmp_path):
    """Each camera's pairs need its own head's trigger latches: not read yet, so refused."""
    p = tmp_path / "m.toml"
    p.write_text('base = "machine_moulder.toml"\n[frames]\nsource = "camera"\n'
                 'camera_id = "Fake_1"\n')
    with pytest.raises(ConfigError, match=r"frames\.source = 'camera' with 4 \[\[heads\]\]") as e:
        load_machine(p)
    assert "\n" not in str(e.value)
