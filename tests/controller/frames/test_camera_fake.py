"""The camera path with Aravis' in-process fake camera (``Fake_1``).

The fake camera draws a diagonal ramp whose value at pixel (0, 0) is ``frame_id % 255`` (gain
0 dB, exposure 10 ms), so every pair shows which two frames it was made of: image B must be
the frame right after image A. Skips with the reason when PyGObject or Aravis is missing.
"""

from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import pytest

from controller.frames.camera.device import aravis_unavailable

WHY = aravis_unavailable()
pytestmark = pytest.mark.skipif(WHY is not None, reason=f"camera tests need Aravis: {WHY}")

W, H = 659, 493


def _settings(**kw):
    from controller.frames.camera.device import CameraSettings

    base = {"width": W, "height": H, "exposure_us": 10_000.0, "gain_db": 0.0,
            "trigger_source": "Software", "pairs_per_s": 200.0}
    base.update(kw)
    return CameraSettings(**base)


def _grab(source, n, *, timeout_s=10.0):
    """Up to ``n`` frames from a source (polled; bounded by a generous time limit)."""
    out = []
    end = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < end:
        f = source.poll()
        if f is None:
            time.sleep(0.002)
        else:
            out.append(f)
    return out


def _frame_id(image):
    return int(image[0, 0])


def test_setup_reads_back_the_rigs_size_and_format():
    from controller.frames.camera.device import AravisCamera

    cam = AravisCamera("Fake_1", _settings())
    try:
        assert (cam.info["width"], cam.info["height"]) == (W, H)
        assert cam.info["pixel_format"] == "Mono8"
        assert cam.info["trigger_source"] == "Software"
        assert cam.info["exposure_us"] == pytest.approx(10_000.0)
    finally:
        cam.close()


@pytest.mark.parametrize(("kw", "gives"), [({"width": 4000}, "at most 2048x2048"),
                                           ({"height": 3000}, "at most 2048x2048")])
def test_camera_that_cannot_give_the_rig_size_is_one_clear_error(kw, gives):
    from controller.frames.camera.device import AravisCamera, CameraError

    s = _settings(**kw)
    with pytest.raises(CameraError) as err:
        AravisCamera("Fake_1", s)
    text = str(err.value)
    assert gives in text and f"{s.width}x{s.height} Mono8" in text and "Fake_1" in text


def test_unknown_camera_is_an_os_error_naming_it():
    from controller.frames.camera.device import AravisCamera

    with pytest.raises(OSError, match="No_such_camera"):
        AravisCamera("No_such_camera", _settings())


def test_source_pairs_consecutive_frames_without_plc():
    from controller.frames.camera.device import AravisCamera
    from controller.frames.camera.source import CameraFrameSource

    src = CameraFrameSource(AravisCamera("Fake_1", _settings()))
    try:
        frames = _grab(src, 12)
    finally:
        src.close()
    assert len(frames) == 12
    assert [f.seq for f in frames] == list(range(frames[0].seq, frames[0].seq + 12))
    for f in frames:
        assert f.error is None and f.image_a.shape == (H, W) and f.image_a.dtype == np.uint8
        assert (_frame_id(f.image_b) - _frame_id(f.image_a)) % 255 == 1  # B right after A
        assert f.counts_a == 0 == f.counts_b
    ids = [_frame_id(f.image_a) for f in frames]
    # no pair skipped: A of the next pair is two frames later
    assert all((b - a) % 255 == 2 for a, b in zip(ids[:-1], ids[1:], strict=True))


def test_plc_gone_gives_failed_pairs_never_good_ones():
    from controller.frames.camera.device import AravisCamera
    from controller.frames.camera.source import CameraFrameSource

    src = CameraFrameSource(AravisCamera("Fake_1", _settings()), latch_reader=lambda: None)
    try:
        frames = _grab(src, 6)
    finally:
        src.close()
    assert len(frames) == 6
    assert all(f.error and "no trigger latch" in f.error and f.image_a is None for f in frames)


def test_restart_keeps_pairs_right():
    from controller.frames.camera.device import AravisCamera
    from controller.frames.camera.source import CameraFrameSource

    src = CameraFrameSource(AravisCamera("Fake_1", _settings()))
    try:
        before = _grab(src, 5)
        src.restart()
        after = _grab(src, 30)
        counters = src.counters
    finally:
        src.close()
    assert counters["restarts"] == 1
    good = [f for f in before + after if f.error is None]
    assert len(good) >= 30
    for f in good:
        assert (_frame_id(f.image_b) - _frame_id(f.image_a)) % 255 == 1


def test_open_frame_source_dispatches_camera():
    from config.machine import FramesConfig
    from controller.frames.camera.source import CameraFrameSource
    from controller.frames.source import open_frame_source

    cfg = FramesConfig(source="camera", camera_id="Fake_1", image_width=W, image_height=H,
                       trigger_source="Software", pairs_per_s=100.0)
    src = open_frame_source(cfg)
    try:
        assert isinstance(src, CameraFrameSource)
        frame = asyncio.run(src.next(10.0))
        assert frame is not None and frame.error is None and frame.image_a.shape == (H, W)
        assert src.take_skips() == []
    finally:
        src.close()


def test_acquire_writes_committed_pairs_of_the_rigs_size(tmp_path, capsys):
    from planer.cli import main
    from protocol.spool import SpoolReader

    spool = tmp_path / "spool"
    assert main(["acquire", "--camera", "Fake_1", "--pairs", "20", "--spool", str(spool)]) == 0
    reader = SpoolReader(spool, start="all")
    frames = []
    for _ in range(100):
        f = reader.poll()
        if f is None:
            break
        frames.append(f)
    assert len(frames) == 20 and reader.take_skips() == []
    assert all(f.error is None and f.image_a.shape == (H, W) for f in frames)
    assert [f.seq for f in frames] == list(range(20))
    meta = json.loads((spool / "acquire.json").read_text())
    assert meta["counts"].startswith("not latched") and meta["pairs_written"] == 20
    assert "wrote 20 pairs" in capsys.readouterr().out


@pytest.mark.parametrize("fmt", ["png", "npy"])
def test_acquire_writes_the_spool_images_in_the_format_asked(tmp_path, fmt):
    from planer.cli import main
    from protocol.spool import SpoolReader

    spool = tmp_path / "spool"
    argv = ["acquire", "--camera", "Fake_1", "--pairs", "3", "--spool", str(spool),
            "--image-format", fmt]
    assert main(argv) == 0
    images = sorted(p.suffix for p in spool.iterdir() if p.name.startswith("pair-")
                    and p.suffix != ".json")
    assert images == ["." + fmt] * 6
    reader = SpoolReader(spool, start="all")
    frames = [reader.poll() for _ in range(3)]
    assert all(f is not None and f.error is None and f.image_a.shape == (H, W) for f in frames)
