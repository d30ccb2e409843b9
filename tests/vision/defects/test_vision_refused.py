"""The defects of a pair whose cuttermark measurement is refused (``vision/defects/refused.py``),
on boards of the independent renderer (``tests/support/defect_boards.py``)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from core.errors import MeasurementError, RegistrationError
from tests.support.defect_truth import board_spec, board_truth, cached_board, matches
from vision.defects.detect import DefectKind, residual
from vision.defects.refused import (
    RefusedSurface,
    attach,
    map_pitch_mm,
    refused_surface,
    surface_of,
)
from vision.pipeline import Measurer, _orient
from vision.registration.registrar import encoder_shift_px

# boards of the tuning split the measurement refuses (docs/vision.md): fuzzy grain whose
# shading outvotes the albedo (encoder 1.6 px and 2.7 px off), a knife nick (3.0 px off)
REFUSED_FUZZY, REFUSED_FUZZY_SLIPPED, REFUSED_NICK = 2, 202, 196


def _measurer(board, defects=True):
    return Measurer(board.rig, board.image_a.shape, knives=4, defects=defects)


def _refusal(board, measurer):
    with pytest.raises(MeasurementError) as info:
        measurer.measure(board.image_a, board.image_b, counts_a=board.counts_a,
                         counts_b=board.counts_b, speed_mm_s=board.speed_mm_s)
    return info.value


def _encoder_px(board):
    enc = board.rig.encoder
    return encoder_shift_px(board.counts_a, board.counts_b, px_per_count=enc.px_per_count,
                            counter_bits=enc.counter_bits)


@pytest.mark.parametrize("index", [REFUSED_FUZZY, REFUSED_NICK])
def test_a_refused_pair_carries_its_defects(index):
    board = cached_board(**board_spec(index))
    exc = _refusal(board, _measurer(board))
    surface = surface_of(exc)
    assert surface is not None, exc
    truth = [t for t in board_truth(board) if t.detectable]
    assert truth
    for t in truth:  # every true defect found, nothing else
        assert any(matches(t, d) for d in surface.defects), (truth, surface.defects)
    assert len(surface.defects) == len(truth), surface.defects
    assert surface.grade >= 2 and surface.grade_reason
    assert surface.encoder_shift_px == pytest.approx(_encoder_px(board))
    # a worker process's refusal reaches the service with its defects
    again = surface_of(pickle.loads(pickle.dumps(exc)))
    assert again == surface
    # the refusal itself stands: the same error the measurement raised without the defects
    plain = _refusal(board, _measurer(board, defects=False))
    assert type(plain) is type(exc) and str(plain) == str(exc)
    assert surface_of(plain) is None


def test_the_shift_is_refined_on_the_map_within_the_slip():
    board = cached_board(**board_spec(REFUSED_FUZZY_SLIPPED))
    m = _measurer(board)
    ba, bb = m._binned(board.image_a, "a"), m._binned(board.image_b, "b")
    _, roll = _orient(m, ba, bb, None)
    enc = _encoder_px(board)
    assert abs(enc - board.shift_px) > 2.5  # the belt slipped
    kept = refused_surface(m.defect_finder, ba.bins, bb.bins, encoder_shift_px=enc,
                           roll_deg=roll, slip_px=0.0)
    assert kept.shift_px == enc
    found = refused_surface(m.defect_finder, ba.bins, bb.bins, encoder_shift_px=enc,
                            roll_deg=roll, slip_px=6.0)
    assert abs(found.shift_px - enc) <= 6.0
    assert abs(found.shift_px - board.shift_px) <= 1.0, (found.shift_px, board.shift_px)
    assert [d.kind for d in found.defects] == [DefectKind.FUZZY_GRAIN]


def test_the_coarse_sources_are_made_once_for_every_shift_tried(monkeypatch):
    board = cached_board(**board_spec(REFUSED_FUZZY_SLIPPED))
    m = _measurer(board)
    ba, bb = m._binned(board.image_a, "a"), m._binned(board.image_b, "b")
    _, roll = _orient(m, ba, bb, None)
    enc = _encoder_px(board)
    mapper = m.defect_finder.mapper
    made, maps = [], []
    coarse, call = mapper._coarse, type(mapper).__call__
    monkeypatch.setattr(mapper, "_coarse", lambda rows: made.append(1) or coarse(rows))
    monkeypatch.setattr(type(mapper), "__call__",
                        lambda self, *a, **kw: maps.append(1) or call(self, *a, **kw))
    found = refused_surface(m.defect_finder, ba.bins, bb.bins, encoder_shift_px=enc,
                            roll_deg=roll, slip_px=6.0)
    assert len(maps) > 5 and len(made) == 2  # ~15 maps of one pair, its two sources once
    # the same surface as with the sources handed in
    given = refused_surface(m.defect_finder, ba.bins, bb.bins, encoder_shift_px=enc,
                            roll_deg=roll, slip_px=6.0,
                            coarse=(coarse(ba.bins), coarse(bb.bins)))
    assert given == found and len(made) == 2


def test_the_pitch_is_read_from_the_maps_marks():
    board = cached_board(**board_spec(REFUSED_NICK))
    m = _measurer(board)
    ba, bb = m._binned(board.image_a, "a"), m._binned(board.image_b, "b")
    smap = m.defect_finder.mapper(ba.bins, bb.bins, shift_px=board.shift_px,
                                  roll_deg=board.roll_deg)
    pitch = map_pitch_mm(residual(smap, m.defect_finder.settings))
    # the renderer's knives cut 2.0 mm marks; the map sees them along the feed (roll +-3 deg)
    assert pitch == pytest.approx(2.0, rel=0.02)


def test_attach_and_surface_of():
    surface = RefusedSurface((), 1, "no defects", 20.0, 21.0, math.nan)
    exc = RegistrationError("cannot register")
    assert surface_of(exc) is None
    attach(exc, surface)
    assert surface_of(exc) is surface
    assert surface.to_json() == {"defects": [], "grade": 1, "grade_reason": "no defects",
                                 "shift_px": 20.0, "encoder_shift_px": 21.0, "pitch_mm": None}
    with pytest.raises(ValueError, match="slip_px"):
        board = cached_board(**board_spec(REFUSED_FUZZY))
        m = _measurer(board)
        ba = m._binned(board.image_a, "a")
        refused_surface(m.defect_finder, ba.bins, ba.bins, encoder_shift_px=1.0,
                        roll_deg=0.0, slip_px=-1.0)


def test_a_pair_that_cannot_be_mapped_is_refused_as_it_is():
    board = cached_board(**board_spec(REFUSED_FUZZY))
    m = _measurer(board)
    dark = np.zeros_like(board.image_a)
    with pytest.raises(MeasurementError) as info:  # too dark: no map either
        m.measure(dark, dark, counts_a=board.counts_a, counts_b=board.counts_b)
    assert surface_of(info.value) is None
    far = (board.counts_a + 10 ** 6) % (1 << 32)  # the encoder's shift leaves no overlap
    with pytest.raises(MeasurementError) as info:
        m.measure(board.image_a, board.image_b, counts_a=board.counts_a, counts_b=far)
    assert surface_of(info.value) is None
