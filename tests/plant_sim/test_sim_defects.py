"""Wood defects in the simulator: each kind's height, its rendering, its truth, its placement.

For each kind the truth (``truth_in_frame``: centre in image A's undistorted frame, size, depth)
must match what is rendered: the height map image A shows is lower by the depth under a pit,
higher by it on a ridge, and the images change where the truth says and nowhere else.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from config.defects import DEFECT_KINDS, defects_table
from config.loading import Section, default_path
from config.sim import load_sim, sim_from_dict
from config.wood import species
from core.errors import ConfigError
from plant_sim.machine.machine import Machine
from plant_sim.model.surface import Cutterhead, passes_steady
from plant_sim.rendering import scenarios as sc
from plant_sim.rendering.defects import (
    Defect,
    DefectKind,
    DefectLayer,
    board_defects,
    nick_ridge,
    truth_in_frame,
)
from plant_sim.rendering.optics import Optics, RigEffects

W, H = 320, 240
BC = 500.0  # board coordinate on the optical axis at trigger A
SPEED = 600.0
HEAD = Cutterhead(4, 60.0, (0.0, 4.0, -2.0, 2.0))


def _renderer(roll_deg: float = 0.0, wood: str = "spruce"):
    rig = sc.make_rig(width=W, height=H)
    optics = Optics(width=W, height=H, read_noise_dn=0.0, shot_noise=False, quantize=False,
                    counts_per_mm=20.0)
    fx = RigEffects(roll_deg=roll_deg, scattering_mm=0.2, reflectance_roughness_deg=15.0)
    return sc.renderer(rig, optics, species(wood), 1, fx)


def _surface(rend):
    lo, hi = rend.board_range_mm(board_x_at_centre_mm=BC, speed_mm_s=SPEED)
    return sc.board_surface(HEAD, spindle_rpm=6000.0, feed_mm_s=SPEED, x_start_mm=lo - 25,
                            x_end_mm=hi + 25)


def _truth(rend, item):
    cam = rend.rig.camera
    return truth_in_frame(item, x_centre_mm=BC, cx=cam.cx, cy=cam.cy, px_per_mm=rend.px_per_mm,
                          px_per_mm_y=rend.px_per_mm_y, roll_deg=rend.effects.roll_deg,
                          frame_height_mm=H / rend.px_per_mm_y)


def _pixel(rend, truth):
    """The undistorted pixel ``(row, col)`` of a truth's centre (no distortion here)."""
    return (int(round(truth["y_mm"] * rend.px_per_mm_y)),
            int(round(truth["x_mm"] * rend.px_per_mm)))


def _added_height(rend, surf, layer):
    with_ = rend.height_map(surf, board_x_at_centre_mm=BC, defects=layer)
    return with_ - rend.height_map(surf, board_x_at_centre_mm=BC)


def _images(rend, surf, layer):
    pair = rend.render_pair(surf, board_x_at_centre_mm=BC, speed_mm_s=SPEED, rng_seed=3,
                            defects=layer)
    return pair.image_a


def _box_px(rend, truth, margin_px):
    """Rows and columns of image A within ``margin_px`` of the truth's box."""
    r, c = _pixel(rend, truth)
    half_l = 0.5 * truth["length_mm"] * rend.px_per_mm + margin_px
    half_w = 0.5 * truth["width_mm"] * rend.px_per_mm_y + margin_px
    rows, cols = np.mgrid[0:H, 0:W]
    return (np.abs(rows - r) <= half_w) & (np.abs(cols - c) <= half_l)


LOCAL = [
    Defect(DefectKind.TORN_GRAIN, 2, BC - 3.0, 2.0, 8.0, 3.0, 400.0, seed=1),
    Defect(DefectKind.TORN_GRAIN, 2, BC + 2.0, -1.0, 1.5, 6.0, 80.0, seed=2),  # across
    Defect(DefectKind.CHIP_MARK, 2, BC + 4.0, 3.0, 3.0, 2.0, 120.0, seed=3),
    Defect(DefectKind.RAISED_GRAIN, 2, BC, 0.0, 14.0, 10.0, 40.0, angle_deg=35.0,
           period_mm=3.0, seed=4),
    Defect(DefectKind.FUZZY_GRAIN, 2, BC - 2.0, 1.0, 12.0, 8.0, 20.0, seed=5),
]


@pytest.mark.parametrize("defect", LOCAL, ids=lambda d: f"{d.kind.value}-{d.seed}")
def test_local_defect_height_and_images_match_its_truth(defect):
    rend = _renderer()
    surf = _surface(rend)
    layer = DefectLayer([defect])
    truth = _truth(rend, defect)
    assert truth["kind"] == defect.kind.value and truth["depth_um"] == defect.depth_um
    added = _added_height(rend, surf, layer)
    inside = _box_px(rend, truth, 0)
    r, c = _pixel(rend, truth)
    kind = defect.kind
    if kind in (DefectKind.TORN_GRAIN, DefectKind.CHIP_MARK):
        # lower by the depth at the centre (torn grain: its fibrous bottom, +-5 %)
        assert added[r, c] == pytest.approx(-defect.depth_um, rel=0.12)
        assert added.min() >= -1.15 * defect.depth_um and added.max() <= 0.0
    elif kind is DefectKind.RAISED_GRAIN:
        assert added[inside].max() == pytest.approx(defect.depth_um, rel=0.02)
        assert added.min() >= 0.0
        # the ridges follow the rings: constant along (cos a, sin a) in the board frame
        a = math.radians(defect.angle_deg)
        bx = np.array([BC, BC + 1.0 * math.cos(a)])
        by = np.array([0.3, 0.3 + 1.0 * math.sin(a)])
        h = defect.height_um(bx, by)
        assert h[0] == pytest.approx(h[1], abs=1e-9)
    else:  # fuzzy grain: the rms over its inner part
        core = _box_px(rend, {**truth, "length_mm": truth["length_mm"] - 3,
                              "width_mm": truth["width_mm"] - 3}, 0)
        rms = float(np.sqrt(np.mean(added[core] ** 2)))
        assert rms == pytest.approx(defect.depth_um, rel=0.3)
    # nothing outside its box
    assert np.all(added[~_box_px(rend, truth, 1)] == 0.0)
    # the image changes inside the box and not away from it (its shadow falls along the feed)
    diff = np.abs(_images(rend, surf, layer) - _images(rend, surf, None))
    reach_px = defect.shadow_reach_mm(1.0 / math.tan(math.radians(82.0))) * rend.px_per_mm
    assert diff[inside].max() > 5.0
    far = ~_box_px(rend, truth, reach_px + 3)
    assert diff[far].max() < 1e-3


def test_truth_position_is_where_the_image_changes_with_roll():
    rend = _renderer(roll_deg=2.0)
    surf = _surface(rend)
    chip = Defect(DefectKind.CHIP_MARK, 2, BC + 6.0, 5.0, 2.0, 2.0, 100.0)
    truth = _truth(rend, chip)
    diff = np.abs(_images(rend, surf, DefectLayer([chip])) - _images(rend, surf, None))
    rows, cols = np.nonzero(diff > 0.2 * diff.max())
    w = diff[rows, cols]
    centroid = (float(np.average(rows, weights=w)), float(np.average(cols, weights=w)))
    expect = (truth["y_mm"] * rend.px_per_mm_y, truth["x_mm"] * rend.px_per_mm)
    assert centroid == pytest.approx(expect, abs=2.0)
    # the roll moved it off the unrolled position by y sin(r) along x
    assert abs(truth["y_mm"] - (rend.rig.camera.cy / rend.px_per_mm_y + 5.0)) > 0.1


def test_knife_nick_leaves_a_ridge_on_its_knifes_marks_along_the_feed():
    rend = _renderer()
    lo, hi = rend.board_range_mm(board_x_at_centre_mm=BC, speed_mm_s=SPEED)
    passes = passes_steady(HEAD, spindle_rpm=6000.0, feed_mm_s=SPEED, x_start_mm=lo - 25,
                           x_end_mm=hi + 25)
    nick = Defect(DefectKind.KNIFE_NICK, 2, 2000.0, -2.0, 4000.0, 1.0, 30.0, knife=1)
    ridge = nick_ridge(nick, passes, lo - 5, hi + 5)
    truth = _truth(rend, ridge)
    assert truth["kind"] == "knife_nick" and truth["knife"] == 1 and truth["notch_um"] == 30.0
    assert 0.0 < truth["depth_um"] <= 30.0  # the kinematics cap the ridge at the notch
    xs = np.linspace(lo, hi, 4001)
    r = ridge.ridge_um(xs)
    assert r.max() == pytest.approx(truth["depth_um"], rel=0.01)
    # raised only where knife 1's passes would have cut: under no other knife's marks
    plain = ridge.plain
    owner_knife = plain.passes.knife[np.searchsorted(plain.cusps_mm, xs)]
    assert np.all(r[owner_knife != 1] < 1e-6) and r[owner_knife == 1].max() > 1.0
    # across the feed only inside its band; along the feed the band runs the whole field
    layer = DefectLayer([ridge])
    y_in = ridge.height_um(xs, np.full_like(xs, nick.y_mm))
    y_out = ridge.height_um(xs, np.full_like(xs, nick.y_mm + 0.6))
    assert np.array_equal(y_in, r) and np.all(y_out == 0.0)
    surf = _surface(rend)
    row = int(round(truth["y_mm"] * rend.px_per_mm_y))
    added = _added_height(rend, surf, layer)
    assert added[row].max() == pytest.approx(truth["depth_um"], rel=0.05)
    assert np.all(added[row + 10] == 0.0)


def test_chatter_waviness_has_its_period_not_the_pitch():
    rend = _renderer()
    surf = _surface(rend)
    chatter = Defect(DefectKind.CHATTER, 2, BC, 0.0, 400.0, 150.0, 5.0, period_mm=7.3, seed=9)
    truth = _truth(rend, chatter)
    assert truth["period_mm"] == 7.3 and truth["width_mm"] == pytest.approx(H / 12.5)
    xs = BC + np.arange(-100.0, 100.0, 0.05)
    z = chatter.profile_um(xs)
    assert np.max(np.abs(z)) == pytest.approx(5.0, rel=1e-3)
    spec = np.abs(np.fft.rfft(z))
    f = np.fft.rfftfreq(z.size, 0.05)
    assert 1.0 / f[np.argmax(spec)] == pytest.approx(7.3, rel=0.05)
    pitch = 600.0 / (6000.0 / 60.0 * 4)
    assert abs(1.0 / f[np.argmax(spec)] / pitch - 1) > 0.5
    added = _added_height(rend, surf, DefectLayer([chatter]))
    assert np.allclose(added[0], added[-1], atol=0.5)  # across the whole width (roll 0)


@pytest.mark.parametrize("trailing", [True, False])
def test_snipe_cuts_the_board_end_deeper(trailing):
    length = 4000.0
    snipe = Defect(DefectKind.SNIPE, 2, 50.0 if trailing else length - 50.0, 0.0, 100.0,
                   150.0, 120.0, seed=0 if trailing else 1)
    end, inside = (0.0, 200.0) if trailing else (length, length - 200.0)
    z = snipe.profile_um(np.array([end, inside]))
    assert z[0] == pytest.approx(-120.0) and z[1] == 0.0
    ramp_start = 100.0 - 40.0  # full depth over the outer 60 %, then a fade
    near = snipe.profile_um(np.array([ramp_start - 1.0 if trailing else length - ramp_start + 1]))
    assert near[0] == pytest.approx(-120.0)


def test_no_defect_renders_the_same_images():
    rend = _renderer()
    surf = _surface(rend)
    plain = _images(rend, surf, None)
    assert np.array_equal(plain, _images(rend, surf, DefectLayer([])))
    far = Defect(DefectKind.TORN_GRAIN, 2, BC + 300.0, 0.0, 5.0, 2.0, 500.0)
    assert np.array_equal(plain, _images(rend, surf, DefectLayer([far])))


@pytest.mark.parametrize("wood", ["spruce", "beech", "oak"])
def test_every_species_renders_a_defect(wood):
    rend = _renderer(wood=wood)
    surf = _surface(rend)
    torn = LOCAL[0]
    diff = np.abs(_images(rend, surf, DefectLayer([torn])) - _images(rend, surf, None))
    assert diff[_box_px(rend, _truth(rend, torn), 0)].max() > 5.0


# ---------------------------------------------------------------------------- configuration
def test_board_defects_are_drawn_within_the_ranges_and_the_same_each_time():
    cfg = defects_table(Section({"every_nth_board": 2, "place": [
        {"kind": "torn_grain", "per_board": 20, "depth_um": [100, 600], "along_fraction": 0.0},
        {"kind": "raised_grain", "per_board": 3.5},
        {"kind": "knife_nick", "per_board": 1},
        {"kind": "snipe", "per_board": 2},
    ]}, "defects"))
    assert cfg.active and cfg.on_board(2) and cfg.on_board(4) and not cfg.on_board(3)
    got = board_defects(cfg.place, board_id=2, board_length_mm=4000.0, board_width_mm=150.0,
                        knives=4, seed=0)
    assert got == board_defects(cfg.place, board_id=2, board_length_mm=4000.0,
                                board_width_mm=150.0, knives=4, seed=0)
    torn = [d for d in got if d.kind is DefectKind.TORN_GRAIN]
    assert len(torn) == 20
    for d in torn:
        assert 100.0 <= d.depth_um <= 600.0
        assert 2.0 <= d.width_mm <= 15.0 and d.length_mm < d.width_mm  # all across the grain
        assert 20.0 <= d.bbox()[0] and d.bbox()[1] <= 3980.0
    assert len([d for d in got if d.kind is DefectKind.RAISED_GRAIN]) in (3, 4)
    for d in got:
        r = DEFECT_KINDS[d.kind.value]
        assert r.depth_um[0] <= d.depth_um <= r.depth_um[1]
    snipes = sorted((d for d in got if d.kind is DefectKind.SNIPE), key=lambda d: d.x_mm)
    assert len(snipes) == 2 and snipes[0].bbox()[0] == 0.0 and snipes[1].bbox()[1] == 4000.0
    assert snipes[0].profile_um(np.array([0.0]))[0] == pytest.approx(-snipes[0].depth_um)
    assert snipes[1].profile_um(np.array([4000.0]))[0] == pytest.approx(-snipes[1].depth_um)


@pytest.mark.parametrize("table, key", [
    ({"every_nth_board": -1}, "defects.every_nth_board"),
    ({"place": [{"kind": "knot", "per_board": 1}]}, r"defects.place\[0\].kind"),
    ({"place": [{"kind": "torn_grain", "per_board": 1, "depth_um": [20, 500]}]},
     r"defects.place\[0\].depth_um"),
    ({"place": [{"kind": "torn_grain", "per_board": 1, "length_mm": [2, 30]}]},
     r"defects.place\[0\].length_mm"),
    ({"place": [{"kind": "raised_grain", "per_board": 1, "depth_um": [40, 20]}]},
     r"defects.place\[0\].depth_um"),
    ({"place": [{"kind": "chip_mark", "per_board": 1, "period_mm": [3, 4]}]},
     r"defects.place\[0\].period_mm"),
    ({"place": [{"kind": "snipe", "per_board": -1}]}, r"defects.place\[0\].per_board"),
    ({"place": [{"kind": "snipe", "per_board": 1, "colour": 2}]}, r"colour"),
    ({"every": 2}, "every"),
])
def test_bad_defect_keys_are_refused_naming_key_and_value(table, key):
    with pytest.raises(ConfigError, match=key):
        sim_from_dict({"defects": table})


def test_shipped_defects_file_and_the_frames_truth():
    sim = load_sim(default_path("sim_defects.toml"))
    assert sim.defects.every_nth_board == 2
    assert {p.kind for p in sim.defects.place} == {"torn_grain", "raised_grain"}
    m = Machine(sim, seed=0, render_images=False)
    seen: dict[int, int] = {}
    while m.t_s < 9.0:
        for f in m.advance(0.01):
            d = f.truth.get("defects", [])
            seen[f.board_id] = seen.get(f.board_id, 0) + len(d)
            for t in d:
                assert t["kind"] in ("torn_grain", "raised_grain")
                assert -t["length_mm"] / 2 <= t["x_mm"] <= W_FULL_MM + t["length_mm"] / 2
                assert -t["width_mm"] / 2 <= t["y_mm"] <= H_FULL_MM + t["width_mm"] / 2
    assert seen.get(1, 0) == 0 and seen.get(2, 0) >= 5


W_FULL_MM = 659 / 12.5
H_FULL_MM = 493 / 12.5
