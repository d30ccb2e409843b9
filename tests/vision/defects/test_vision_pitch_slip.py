"""A pair registered one marks' pitch off: the defect map made a pitch nearer the encoder.

The marks repeat every pitch, so a registration can lock one pitch off (the simulator's torn
pits 0.4-1 mm deep did it within the measurer's slip). The marks' profile stays right, but
B's wood lies a pitch off A's: bands of the field stand out as false chip marks, raised grain
or snipe. :meth:`vision.defects.detect.DefectFinder.registered` maps the pair one pitch
nearer the encoder's shift where many cells are marked, and keeps that map where its
cells' median falls below 0.3 and its marked cells below half of the registered map's.
Boards of the independent renderer (``tests/support/defect_boards.py``; 2.0 mm marks at
12.5 px/mm: a 25 px pitch).
"""

from __future__ import annotations

import pytest

from tests.support.defect_truth import board_spec, cached_board
from vision.defects.detect import DefectSettings
from vision.pipeline import Measurer, _orient

PITCH_MM = 2.0
"""The renderer's marks."""


def _pair(index: int):
    board = cached_board(**board_spec(index))
    m = Measurer(board.rig, board.image_a.shape, knives=4, defects=True)
    ba, bb = m._binned(board.image_a, "a"), m._binned(board.image_b, "b")
    _, roll = _orient(m, ba, bb, None)
    return board, m.defect_finder, ba.bins, bb.bins, roll


@pytest.mark.parametrize("index", [16, 11, 0])  # torn grain, two chip marks, a knife nick
def test_a_pair_registered_a_pitch_off_is_mapped_where_the_encoder_puts_it(index):
    board, finder, a, b, roll = _pair(index)
    step = PITCH_MM * board.rig.camera.px_per_mm
    right = finder(a, b, shift_px=board.shift_px, roll_deg=roll, pitch_mm=PITCH_MM)
    assert right
    for off in (-step, step):
        wrong = board.shift_px + off
        # without the encoder the map a pitch off is all there is: other defects (false
        # ones, or the true ones misplaced and mismeasured)
        alone = finder(a, b, shift_px=wrong, roll_deg=roll, pitch_mm=PITCH_MM)
        assert alone != right, off
        # the encoder's shift within the renderer's slip of the true one
        enc = board.shift_px + 3.0
        found = finder(a, b, shift_px=wrong, roll_deg=roll, pitch_mm=PITCH_MM,
                       encoder_shift_px=enc)
        assert found == right, (off, found)


def test_a_pitch_away_from_the_encoder_is_not_looked_at():
    """Registered right, the encoder a little off: the map at the registration's shift."""
    board, finder, a, b, roll = _pair(16)
    right = finder(a, b, shift_px=board.shift_px, roll_deg=roll, pitch_mm=PITCH_MM)
    for enc in (board.shift_px - 4.0, board.shift_px + 4.0, board.shift_px):
        assert finder(a, b, shift_px=board.shift_px, roll_deg=roll, pitch_mm=PITCH_MM,
                      encoder_shift_px=enc) == right


def test_a_clean_pair_is_mapped_once():
    """Few cells marked: no map a pitch off (a clean pair pays nothing more)."""
    board, finder, a, b, roll = _pair(7)  # clean
    step = PITCH_MM * board.rig.camera.px_per_mm
    calls = []
    mapper = finder.mapper

    class Counting:
        def __call__(self, *args, **kw):
            calls.append(kw["shift_px"])
            return mapper(*args, **kw)

        def coarse_source(self, rows):  # made once per pair, not a map
            return mapper.coarse_source(rows)

    finder.mapper = Counting()
    try:
        found = finder(a, b, shift_px=board.shift_px, roll_deg=roll, pitch_mm=PITCH_MM,
                       encoder_shift_px=board.shift_px + step)
    finally:
        finder.mapper = mapper
    assert found == () and calls == [board.shift_px]


@pytest.mark.parametrize("index", [65, 89, 113, 1057, 1073])
def test_a_defect_over_the_field_keeps_its_registration(index):
    """Raised grain's ridges give these maps a pitch off a cells' median 0.35-0.45 of the
    right one's, with fewer cells marked (at a median ratio of 0.5 each would move): the
    encoder pointing there does not move a right registration."""
    board, finder, a, b, roll = _pair(index)
    step = PITCH_MM * board.rig.camera.px_per_mm
    right = finder(a, b, shift_px=board.shift_px, roll_deg=roll, pitch_mm=PITCH_MM)
    assert [d.kind.value for d in right] == ["raised_grain"]
    for enc in (board.shift_px - step, board.shift_px + step):
        assert finder(a, b, shift_px=board.shift_px, roll_deg=roll, pitch_mm=PITCH_MM,
                      encoder_shift_px=enc) == right


def test_the_settings_are_checked():
    with pytest.raises(ValueError, match="slip_median"):
        DefectSettings(slip_median=0.0)
    with pytest.raises(ValueError, match="slip_cells"):
        DefectSettings(slip_cells=0.0)
    with pytest.raises(ValueError, match="slip_marked"):
        DefectSettings(slip_marked=-0.1)
    s = DefectSettings()
    assert (s.slip_marked, s.slip_median, s.slip_cells) == (0.05, 0.3, 0.5)
