"""A pair the cuttermark measurement refuses keeps the planing defects found on it.

Board 56 of the defect acceptance set (``tests/support/defect_truth.py``: torn grain, rendered
by the independent renderer of ``tests/support/defect_boards.py``) is refused by the vision
("too few cuttermarks"), and the refusal carries its defects
(:func:`vision.defects.refused.surface_of`). In the service (the in-process plant, simulated
time, pairs measured by the simulator's truth with no defects) two pairs of board 1 are that
refusal, as a worker process hands it back (pickled): their ``FrameResult`` and quality
records carry the torn grain and its grade, and the board's grade and counts include it.
"""

from __future__ import annotations

import asyncio
import pickle
from dataclasses import replace

import pytest

from controller.opcua.view import MachineView
from controller.quality.log import QualityLog
from controller.service.events import EventKind
from controller.service.frame_result import Refused, refused_surface_of
from controller.service.measurement import failure_reason
from controller.web.board_strip import defect_fields_json
from core.errors import MeasurementError
from tests.controller.service.test_service_loop import TruthMeasurer, make_plant
from tests.support.defect_truth import board_spec, cached_board
from tests.support.plant_support import run_for
from vision.defects.refused import surface_of
from vision.pipeline import Measurer

TORN_REFUSED = 56  # torn grain: no complete cuttermark left to measure
REFUSED_CALLS = (12, 13)  # the measurer's calls (pairs) that are the refusal


def _refusal(defects: bool) -> MeasurementError:
    board = cached_board(**board_spec(TORN_REFUSED))
    m = Measurer(board.rig, board.image_a.shape, knives=4, defects=defects)
    with pytest.raises(MeasurementError) as info:
        m.measure(board.image_a, board.image_b, counts_a=board.counts_a,
                  counts_b=board.counts_b, speed_mm_s=board.speed_mm_s)
    return info.value


@pytest.fixture(scope="module")
def refusal() -> MeasurementError:
    return _refusal(True)


def test_the_refusal_carries_the_torn_grain_into_the_pairs_error(refusal):
    surface = surface_of(refusal)
    assert surface is not None and [d.kind.value for d in surface.defects] == ["torn_grain"]
    assert surface.grade >= 3
    reason = failure_reason(refusal)
    plain = failure_reason(_refusal(False))  # the measurer not looking: the same refusal
    assert type(plain) is str and isinstance(reason, Refused)
    assert reason == plain and reason.startswith("measurement failed: too few cuttermarks")
    assert refused_surface_of(reason) == surface and refused_surface_of(plain) is None
    back = pickle.loads(pickle.dumps(reason))  # a worker process's reply
    assert back == reason and refused_surface_of(back) == surface
    assert failure_reason(ValueError("no surface")) == "measurement failed: no surface"


class _Looking(TruthMeasurer):
    """The truth, looked at for defects (none), but the pairs of ``REFUSED_CALLS`` refused."""

    def __init__(self, frames, refusal):
        super().__init__(frames)
        self._refusal = pickle.dumps(refusal)

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None):
        m = super().measure(image_a, image_b, counts_a=counts_a, counts_b=counts_b,
                            speed_mm_s=speed_mm_s)
        if self.calls in REFUSED_CALLS:
            raise pickle.loads(self._refusal)
        m.defects, m.grade, m.grade_reason = (), 1, "defect-free"
        return m


def test_refused_pairs_keep_their_defects_in_the_result_the_record_and_the_board(
        tmp_path, refusal):
    surface = surface_of(refusal)

    async def main():
        plant, measurer = make_plant(tmp_path)
        looking = _Looking(measurer.frames, refusal)
        plant.service.measurement.set_factory(lambda shape: looking)
        await plant.start()
        svc = plant.service
        handle = svc.handle_frame

        async def on_board_1(frame, **kw):
            return await handle(replace(frame, board_id=1), **kw)

        svc.handle_frame = on_board_1
        try:
            return await run_for(plant, 3.0)
        finally:
            await plant.close()

    results = asyncio.run(main())
    refused = [r for r in results if r.refused_surface is not None]
    assert len(refused) == len(REFUSED_CALLS)
    for r in refused:
        assert not r.ok and r.measurement is None and r.surface == surface
        assert r.error.startswith("measurement failed: too few cuttermarks")
        page = defect_fields_json(r)  # the operator page's board strip
        assert [d["kind"] for d in page["defects"]] == ["torn_grain"]
        assert page["grade"] == surface.grade
    view = MachineView()  # OPC UA's BoardGrade: the board so far
    for r in results:
        view.result(r)
    assert view.manufacturer()["BoardGrade"] == surface.grade
    with QualityLog(tmp_path / "q.sqlite", create=False) as log:
        recs = log.records()
    by_seq = {r.seq: r for r in recs}
    for r in refused:
        rec = by_seq[r.seq]
        assert not rec.ok and rec.error == r.error
        assert [d["kind"] for d in rec.defects] == ["torn_grain"]
        assert (rec.grade, rec.grade_reason) == (surface.grade, surface.grade_reason)
    first = min(r.seq for r in refused)
    graded = [rec for rec in recs if rec.board_grade is not None]
    assert len(graded) > 20  # every pair was looked at
    before = [rec for rec in graded if rec.seq < first]
    after = [rec for rec in graded if rec.seq >= first]
    assert before and all(rec.board_grade == 1 for rec in before)
    assert after and all(rec.board_grade == surface.grade for rec in after)
    assert after[-1].board_defect_counts["torn_grain"] == len(refused)


def _nick_refusal(refusal: MeasurementError) -> MeasurementError:
    """The same refusal, its surface a knife nick at y = 20 mm (a nicked knife's ridge)."""
    from vision.defects.detect import Defect, DefectKind
    from vision.defects.refused import _ATTRIBUTE

    nick = Defect(DefectKind("knife_nick"), x_mm=30.0, y_mm=20.0, length_mm=60.0, width_mm=0.6,
                  depth_um=8.0, confidence=0.9)
    surface = replace(surface_of(refusal), defects=(nick,), grade=3,
                      grade_reason="knife nick")
    exc = MeasurementError(str(refusal))
    setattr(exc, _ATTRIBUTE, surface)
    return exc


def test_a_nick_seen_only_on_refused_pairs_is_told(tmp_path, refusal):
    """The nick monitor hears refused pairs too: two in a row with the same ridge tell it."""
    nicked = _nick_refusal(refusal)
    assert [d.kind.value for d in surface_of(nicked).defects] == ["knife_nick"]

    async def main():
        plant, measurer = make_plant(tmp_path)
        looking = _Looking(measurer.frames, nicked)
        plant.service.measurement.set_factory(lambda shape: looking)
        await plant.start()
        try:
            await run_for(plant, 3.0)
            return plant.service.events
        finally:
            await plant.close()

    events = asyncio.run(main())
    chipped = [e for e in events if e.kind is EventKind.KNIFE_CHIPPED]
    assert chipped, [e.text for e in events]
    assert "nick" in chipped[0].text
