"""The per-head register blocks: head views, their addresses and names, bad blocks refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from config.loading import default_path
from core.errors import ConfigError
from protocol.registers import (
    HEAD_WRITE_DISPATCH,
    HeadFault,
    RegisterAccessError,
    RegisterMap,
    RegisterRangeError,
    apply_head_writes,
)

RMAP = RegisterMap.load()
HEAD_FIELDS = (
    "spindle_rpm", "spindle_setpoint_rpm", "spindle_rpm_min", "spindle_rpm_max", "knives",
    "cutterhead_radius_mm", "cutter_to_camera_mm", "trigger_a_counts", "trigger_b_counts",
    "trigger_seq", "index_latch_counts", "head_faults",
)
"""The design's head fields (a block may hold more: what a head's camera sees of the board)."""
COMMON = (
    "heartbeat_service", "heartbeat_plc", "feed_setpoint_mm_s", "feed_min_mm_s", "feed_max_mm_s",
    "feed_accel_max_mm_s2", "feed_actual_mm_s", "encoder_counts", "faults", "counts_per_mm",
    "watchdog_ms",
)
"""Machine-wide registers: never in a head block."""
assert RMAP.heads is not None
BLOCK = set(RMAP.heads.names)
USED = RMAP.heads.used

# (head, name, address): the shipped block, base 1000, stride 32
TABLE = [
    (0, "spindle_rpm", 1000), (0, "spindle_setpoint_rpm", 1002), (0, "spindle_rpm_min", 1004),
    (0, "spindle_rpm_max", 1006), (0, "knives", 1008), (0, "head_faults", 1009),
    (0, "cutterhead_radius_mm", 1010), (0, "cutter_to_camera_mm", 1012),
    (0, "trigger_a_counts", 1014), (0, "trigger_b_counts", 1016), (0, "trigger_seq", 1018),
    (0, "index_latch_counts", 1019),
    (1, "spindle_rpm", 1032), (1, "knives", 1040), (1, "index_latch_counts", 1051),
    (3, "spindle_setpoint_rpm", 1098), (3, "head_faults", 1105),
    (7, "spindle_rpm", 1224), (7, "index_latch_counts", 1243),
]


def test_the_shipped_map_has_eight_blocks_and_the_single_map_unchanged():
    assert RMAP.head_count == 8 and RMAP.head is None
    assert RMAP.span() == RMAP.common_span() == (0, 38)
    assert RMAP["spindle_rpm"].address == 12 and RMAP["knives"].address == 25
    assert "spindle_setpoint_rpm" not in RMAP and "head_faults" not in RMAP
    assert RMAP.read_ranges() == ((0, 38),)
    assert RMAP.heads is not None and RMAP.heads.names[:12] == (
        "spindle_rpm", "spindle_setpoint_rpm", "spindle_rpm_min", "spindle_rpm_max", "knives",
        "head_faults", "cutterhead_radius_mm", "cutter_to_camera_mm", "trigger_a_counts",
        "trigger_b_counts", "trigger_seq", "index_latch_counts")
    assert set(HEAD_FIELDS) <= BLOCK and not set(COMMON) & BLOCK
    assert 21 <= USED <= 32


@pytest.mark.parametrize(("head", "name", "address"), TABLE)
def test_head_view_addresses(head, name, address):
    view = RMAP.for_head(head)
    assert view.head == head
    assert view[name].address == address
    assert view.at(address) is view[name]


@pytest.mark.parametrize("head", range(8))
def test_head_view_names_common_unchanged_and_ranges(head):
    view = RMAP.for_head(head)
    assert set(view.registers) == BLOCK | set(RMAP.registers)
    for name in set(RMAP.registers) - BLOCK:
        assert view[name] == RMAP[name]
    for name in BLOCK & set(RMAP.registers):  # same facts, other address
        assert view[name].type == RMAP[name].type and view[name].unit == RMAP[name].unit
        assert view.at(RMAP[name].address) is None  # the legacy word is a gap of the view
    base = 1000 + 32 * head
    assert view.read_ranges() == ((0, 38), (base, USED))
    assert view.head_span() == (base, USED) and RMAP.head_span(head) == (base, USED)
    assert RMAP.for_head(head) is view and view.for_head(head) is view
    assert view.for_head((head + 1) % 8) is RMAP.for_head((head + 1) % 8)


def test_a_view_encodes_decodes_and_checks_writes_like_the_map():
    view = RMAP.for_head(3)
    values = {"spindle_rpm": 6123.5, "knives": 6, "head_faults": int(HeadFault.SPINDLE),
              "heartbeat_service": 7, "index_latch_counts": 0xDEADBEEF}
    words = view.encode_block(values)
    first = view.span()[0]
    assert words[1096 - first : 1098 - first] == view.encode("spindle_rpm", 6123.5)
    assert words[1104 - first] == 6 and words[1105 - first] == 2
    decoded = view.decode_block(words[1096 - first : 1096 - first + USED], 1096)
    assert decoded["spindle_rpm"] == 6123.5 and decoded["index_latch_counts"] == 0xDEADBEEF
    assert "heartbeat_service" not in decoded
    limits = {"spindle_rpm_min": 4000.0, "spindle_rpm_max": 8000.0}
    assert view.limits("spindle_setpoint_rpm", limits) == (4000.0, 8000.0)
    assert view.check_write("spindle_setpoint_rpm", 6000, limits) == 6000.0
    for bad in (3999.0, 8000.5):
        with pytest.raises(RegisterRangeError, match="spindle_setpoint_rpm"):
            view.check_write("spindle_setpoint_rpm", bad, limits)
    accepted = view.parse_write(1098, view.encode("spindle_setpoint_rpm", 4500.0), limits)
    assert accepted == {"spindle_setpoint_rpm": 4500.0}
    with pytest.raises(RegisterAccessError, match="knives"):
        view.parse_write(1104, [4], limits)
    with pytest.raises(RegisterAccessError, match=f"address {1096 + USED}"):  # a reserved word
        view.parse_write(1096 + USED, [0], limits)


def test_fixed_speed_head_accepts_only_its_rpm():
    view = RMAP.for_head(0)
    fixed = {"spindle_rpm_min": 6000.0, "spindle_rpm_max": 6000.0}
    assert view.check_write("spindle_setpoint_rpm", 6000.0, fixed) == 6000.0
    with pytest.raises(RegisterRangeError):
        view.check_write("spindle_setpoint_rpm", 6001.0, fixed)


@pytest.mark.parametrize("bad", [-1, 8, 1.5, True, "0"])
def test_for_head_refuses_a_bad_index_naming_it(bad):
    with pytest.raises(ValueError, match="head"):
        RMAP.for_head(bad)


def test_a_map_without_heads_has_no_views(tmp_path):
    single = RegisterMap.load(_without_heads(tmp_path))
    assert single.head_count == 0 and single.heads is None
    assert single.markdown_table() == RMAP.markdown_table().split("\n\nHead block")[0] + "\n"
    with pytest.raises(ValueError, match="no \\[heads\\]"):
        single.for_head(0)


def _without_heads(tmp_path: Path) -> Path:
    text = default_path("registers.toml").read_text()
    p = tmp_path / "single.toml"
    p.write_text(text.split("\n[heads]\n", 1)[0])
    return p


class _Heads:
    def __init__(self) -> None:
        self.setpoints: list[tuple[int, float]] = []

    def set_spindle_setpoint(self, head: int, rpm: float) -> None:
        if rpm > 9000:
            raise ValueError(f"rpm {rpm} beyond the drive")
        self.setpoints.append((head, rpm))


def test_every_writable_block_register_has_one_head_write_action():
    assert RMAP.heads is not None
    assert set(HEAD_WRITE_DISPATCH) == {r.name for r in RMAP.heads.registers if r.writable}
    target = _Heads()
    apply_head_writes(target, 5, {"spindle_setpoint_rpm": 7000.0})
    assert target.setpoints == [(5, 7000.0)]
    with pytest.raises(RegisterRangeError, match="spindle_setpoint_rpm of head 2"):
        apply_head_writes(target, 2, {"spindle_setpoint_rpm": 9500.0})
    with pytest.raises(RegisterAccessError, match="knives of head 1"):
        apply_head_writes(target, 1, {"knives": 4})
    assert target.setpoints == [(5, 7000.0)]


# ------------------------------------------------------------------ bad blocks
SHIPPED = default_path("registers.toml").read_text()


def _edit(old: str, new: str):
    def f(text: str) -> str:
        assert old in text, old
        return text.replace(old, new, 1)
    return f


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (_edit("base = 1000", "base = 30"), "overlap register board_id"),
        (_edit("base = 1000", "base = 65500"), "past address 65535"),
        (_edit("stride = 32", "stride = 20"), "exceeds the stride 20"),
        (_edit("count = 8", "count = 0"), "heads.count"),
        (_edit('name = "knives"\noffset = 8', 'name = "knives"\noffset = 7'), "overlaps"),
        (_edit('name = "knives"\noffset = 8', 'name = "knives"\noffset = 8\ntype = "u16"'),
         "heads.register knives: type is given by the \\[\\[register\\]\\] entry"),
        (_edit('name = "trigger_seq"\noffset = 18', 'name = "knives"\noffset = 18'),
         "heads.register knives: duplicate"),
        (_edit('min = "spindle_rpm_min"', 'min = "spindle_rpm_lo"'),
         "spindle_setpoint_rpm: min names unknown register 'spindle_rpm_lo'"),
        (_edit('"amplifier", "spindle", "camera_silent"', '"spindle", "amplifier"'),
         "register head_faults: bits must be"),
        (_edit("stride = 32\n", "stride = 32\nwidth = 3\n"), "heads.width"),
        (_edit('offset = 4\ntype = "f32"', 'offset = 4\ntype = "f64"'),
         "heads.register spindle_rpm_min.type"),
        (_edit('name = "spindle_rpm_max"\noffset = 6\ntype = "f32"\naccess = "ro"',
               'name = "spindle_rpm_max"\noffset = 6\ntype = "f32"\naccess = "ro"\nmax = 3.0'),
         "min/max only make sense on rw"),
    ],
)
def test_bad_blocks_refused_with_a_clear_config_error(tmp_path, edit, needle):
    path = tmp_path / "registers.toml"
    path.write_text(edit(SHIPPED))
    with pytest.raises(ConfigError, match=needle) as err:
        RegisterMap.load(path)
    assert str(err.value).startswith(f"{path}: ")
