"""The texture registration on windows of wide images (the texture stage's width).

Images at least twice ``texture_width_px`` wide register their texture on windows of that
width, B's ``round(encoder shift)`` columns after A's; a window that is not strongly confident
hands over to the whole width.  The windows must give the measurement the whole width gives.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.support.vision_boards import render_board
from vision.pipeline import Measurer
from vision.registration.registrar import Registrar

WIDE = 1320  # >= 2 x 640: the default windows apply


def _measure(board, **options):
    m = Measurer(board.rig, board.image_a.shape, **options)
    return m.measure(board.image_a, board.image_b, counts_a=board.counts_a,
                     counts_b=board.counts_b, speed_mm_s=board.speed_mm_s)


@pytest.mark.parametrize("shift", [-700.4, -60.0, -3.2, 0.0, 18.3, 250.7, 679.6])
@pytest.mark.parametrize("tw", [640, 500])
def test_windows_hold_the_same_wood_inside_both_images(shift, tw):
    board = render_board(1, width=WIDE, height=80)
    m = Measurer(board.rig, board.image_a.shape, texture_width_px=tw)
    cols_a, cols_b, offset = m._texture_windows(shift)
    if abs(round(shift)) > m.width - tw:
        assert (cols_a, cols_b, offset) == (None, None, 0)
        return
    assert offset == round(shift)
    assert cols_b.start - cols_a.start == offset
    for cols in (cols_a, cols_b):
        assert 0 <= cols.start and cols.stop <= m.width and cols.stop - cols.start == tw


@pytest.mark.parametrize("tw, width", [(0, WIDE), (700, WIDE), (640, 659)])
def test_no_windows_when_off_or_the_image_is_not_twice_as_wide(tw, width):
    board = render_board(1, width=width, height=80)
    m = Measurer(board.rig, board.image_a.shape, texture_width_px=tw)
    assert m._texture_windows(18.3) == (None, None, 0)


def test_no_windows_when_the_search_leaves_them_too_little_overlap():
    board = render_board(1, width=WIDE, height=80)
    m = Measurer(board.rig, board.image_a.shape, search_px=200.0)  # 410 lags leave < 330 px
    assert m._texture_windows(18.3) == (None, None, 0)


def test_coarse_on_windows_with_an_offset_finds_the_whole_width_shift():
    board = render_board(2, width=WIDE, height=160)
    m = Measurer(board.rig, board.image_a.shape, texture_width_px=0, max_roll_deg=0.0)
    ba, bb = m.front.bin(board.image_a, "a"), m.front.bin(board.image_b, "b")
    pa, pb = m.front.profile(ba, 0.0), m.front.profile(bb, 0.0)
    ta, tb = np.asarray(m.front.texture(ba, 0.0, pa)), np.asarray(m.front.texture(bb, 0.0, pb))
    guess = board.shift_px + 4.0  # an encoder error
    reg = Registrar(m.width)
    whole = reg.coarse(ta, tb, encoder_shift_px=guess)
    for a0, off in ((300, 22), (500, 18), (100, 15)):
        win = reg.coarse(ta[:, a0:a0 + 512], tb[:, a0 + off:a0 + off + 512],
                         encoder_shift_px=guess, offset_px=off)
        assert win.encoder_shift_px == guess
        assert abs(win.shift_px - whole.shift_px) < 0.5
        assert abs(win.shift_px - board.shift_px) < 0.5
    with pytest.raises(ValueError, match="textures"):
        reg.coarse(ta[:, :8], tb[:, :8], encoder_shift_px=guess)


CASES = {
    "plain": {},
    "noise 20 DN": dict(noise_dn=20.0, seed=4),
    "noise 20 DN, roll -2 deg, slip 10 px": dict(noise_dn=20.0, seed=1, roll_deg=-2.0,
                                               slip_px=10.0),
    "roll +3 deg, scattering 0.3 mm": dict(roll_deg=3.0, scatter_mm=0.3),
}


@pytest.mark.parametrize("name", list(CASES))
def test_windows_measure_what_the_whole_width_measures(name):
    kw = {"height": 240, **CASES[name]}
    board = render_board(kw.pop("seed", 4), width=WIDE, **kw)
    windowed = _measure(board)
    whole = _measure(board, texture_width_px=0)
    assert abs(windowed.shift_px - board.shift_px) < 0.5
    assert windowed.shift_px == pytest.approx(whole.shift_px, abs=0.01)
    assert windowed.pitch_mm == pytest.approx(whole.pitch_mm, rel=1e-4)
    assert windowed.uniformity_cv == pytest.approx(whole.uniformity_cv, abs=1e-3)
    np.testing.assert_allclose(windowed.height_um, whole.height_um, atol=0.05)



@pytest.mark.parametrize("cols", [slice(None, 10), slice(5, 5), slice(-1, 10), slice(0, 10, 2),
                                  slice(0, WIDE + 1)])
def test_texture_rejects_a_bad_column_window(cols):
    board = render_board(1, width=WIDE, height=80)
    m = Measurer(board.rig, board.image_a.shape)
    binned = m.front.bin(board.image_a, "a")
    with pytest.raises(ValueError, match="columns"):
        m.front.texture(binned, 0.0, m.front.profile(binned, 0.0), columns=cols)


@pytest.mark.parametrize("roll_deg", [0.0, 2.0])  # 2 deg: rows rotated to the feed
def test_texture_window_is_the_same_columns_of_the_whole_texture(roll_deg):
    board = render_board(2, width=WIDE, height=120)
    m = Measurer(board.rig, board.image_a.shape)
    assert m.front.rotates(roll_deg) == (roll_deg != 0)
    binned = m.front.bin(board.image_a, "a")
    prof = m.front.profile(binned, 0.0)
    whole = np.asarray(m.front.texture(binned, roll_deg, prof))
    win = m.front.texture(binned, roll_deg, prof, columns=slice(200, 840))
    assert win.shape == (whole.shape[0], 640)
    np.testing.assert_allclose(win[:], whole[:, 200:840], rtol=0, atol=1e-6)
