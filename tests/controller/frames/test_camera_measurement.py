"""A pair through the camera path and the same pair through the spool give the same measurement.

The simulator renders one board pair; the camera path gets it as two camera buffers plus the
PLC's latch record (``PairAssembler``), the spool path as files written by ``SpoolWriter`` and
read back by ``SpoolReader``. Both frames are measured by the vision; every output agrees.
"""

from __future__ import annotations

import numpy as np
import pytest

from controller.frames.camera.pairing import CameraImage, PairAssembler, TriggerLatch
from protocol.frames import Frame
from protocol.spool import SpoolReader, SpoolWriter


@pytest.fixture(scope="module")
def board():
    from plant_sim.rendering import scenarios

    return scenarios.board_pair(seed=3)


def _camera_frame(pair, seq):
    asm = PairAssembler(frame_id_bits=16, frame_id_skips_zero=True, counts_per_mm=20.0,
                        ab_tolerance_s=1.0)
    asm.sync(frame_id=65535, seq=seq)  # the frame id wraps inside the pair
    asm.add_latch(TriggerLatch(seq=seq, counts_a=pair.counts_a, counts_b=pair.counts_b,
                               speed_mm_s=pair.speed_mm_s, board_id=7, t_s=1.5))
    asm.add_image(CameraImage(65535, 1_000_000, pair.image_a))
    asm.add_image(CameraImage(1, 3_000_000, pair.image_b))
    (frame,) = asm.take()
    return frame


def _spool_frame(pair, seq, tmp_path):
    SpoolWriter(tmp_path, keep=4, fsync=False).write(Frame(
        seq=seq, t_s=1.5, image_a=pair.image_a, image_b=pair.image_b, counts_a=pair.counts_a,
        counts_b=pair.counts_b, speed_mm_s=pair.speed_mm_s, board_id=7))
    return SpoolReader(tmp_path, start="all").poll()


def test_camera_and_spool_paths_measure_the_same(board, tmp_path):
    from vision.pipeline import measure_pair

    rig, pair = board
    cam = _camera_frame(pair, 65535)
    spool = _spool_frame(pair, 65535, tmp_path)
    assert cam.error is None and spool.error is None
    for name in ("seq", "counts_a", "counts_b", "speed_mm_s", "board_id"):
        assert getattr(cam, name) == getattr(spool, name), name
    np.testing.assert_array_equal(cam.image_a, spool.image_a)
    np.testing.assert_array_equal(cam.image_b, spool.image_b)
    results = [measure_pair(f.image_a, f.image_b, rig=rig, counts_a=f.counts_a,
                            counts_b=f.counts_b, speed_mm_s=f.speed_mm_s) for f in (cam, spool)]
    a, b = results
    assert a.pitch_mm == b.pitch_mm and a.shift_px == b.shift_px
    np.testing.assert_array_equal(a.mark_widths_mm, b.mark_widths_mm)
    np.testing.assert_array_equal(a.height_um, b.height_um)
    assert abs(a.shift_px - pair.truth.shift_px) < 1.0  # a real measurement, not noise
