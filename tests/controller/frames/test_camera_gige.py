"""The camera path over the real GigE Vision protocol: ``arv-fake-gv-camera-0.8`` on 127.0.0.1.

The fake GigE camera listens on the loopback address only; no traffic leaves this machine.
Skips with the reason when Aravis or the ``aravis-tools`` program is missing.
"""

from __future__ import annotations

import shutil
import subprocess
import time

import numpy as np
import pytest

from controller.frames.camera.device import aravis_unavailable

WHY = aravis_unavailable()
TOOL = shutil.which("arv-fake-gv-camera-0.8")
pytestmark = [
    pytest.mark.skipif(WHY is not None, reason=f"camera tests need Aravis: {WHY}"),
    pytest.mark.skipif(TOOL is None, reason="arv-fake-gv-camera-0.8 not found "
                       "(Debian package aravis-tools)"),
]

W, H = 659, 493


@pytest.fixture
def gige_camera(request):
    """A fake GigE Vision camera on 127.0.0.1 (extra options by parametrize), stopped after."""
    proc = subprocess.Popen([TOOL, "-i", "127.0.0.1", "-s", "PLANERTEST",
                             *getattr(request, "param", ())],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        yield "127.0.0.1", proc
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _open(address, proc, settings):
    """Open the camera; the server may need a moment to listen (bounded retries)."""
    from controller.frames.camera.device import AravisCamera, CameraError

    last = None
    for _ in range(50):
        if proc.poll() is not None:
            pytest.fail(f"arv-fake-gv-camera-0.8 exited: {proc.stderr.read().decode()[-300:]}")
        try:
            return AravisCamera(address, settings)
        except CameraError as exc:
            last = exc
            time.sleep(0.1)  # the server process starting: not a measurement wait
    raise last


def test_gige_vision_acquisition_over_loopback(gige_camera):
    from controller.frames.camera.device import CameraSettings
    from controller.frames.camera.source import CameraFrameSource

    address, proc = gige_camera
    cam = _open(address, proc, CameraSettings(width=W, height=H, exposure_us=10_000.0,
                                              gain_db=0.0, trigger_source="Software",
                                              pairs_per_s=50.0))
    assert cam.camera.is_gv_device()
    assert (cam.info["width"], cam.info["height"], cam.info["pixel_format"]) == (W, H, "Mono8")
    assert cam.info["packet_size"] > 0
    src = CameraFrameSource(cam)
    frames = []
    try:
        end = time.monotonic() + 20.0
        while len(frames) < 8 and time.monotonic() < end:
            f = src.poll()
            if f is None:
                time.sleep(0.005)
            else:
                frames.append(f)
        counters = src.counters
    finally:
        src.close()
    good = [f for f in frames if f.error is None]
    assert len(frames) == 8 and len(good) >= 6
    for f in good:
        assert f.image_a.shape == (H, W) and f.image_a.dtype == np.uint8
        # the fake draws frame_id % 255 at (0, 0): B is the frame right after A
        assert (int(f.image_b[0, 0]) - int(f.image_a[0, 0])) % 255 == 1
    assert counters["images"] >= 16 and counters["aravis_completed"] >= 16


@pytest.mark.parametrize("gige_camera", [("--gvsp-lost-ratio", "20")], indirect=True)
def test_gige_packet_loss_gives_failed_pairs_never_wrong_ones(gige_camera):
    """2 % of the stream packets lost: incomplete buffers fail their pairs, with the reason."""
    from controller.frames.camera.device import CameraSettings
    from controller.frames.camera.source import CameraFrameSource

    address, proc = gige_camera
    cam = _open(address, proc, CameraSettings(width=W, height=H, exposure_us=10_000.0,
                                              gain_db=0.0, trigger_source="Software",
                                              pairs_per_s=50.0))
    src = CameraFrameSource(cam)
    frames = []
    try:
        end = time.monotonic() + 20.0
        while len(frames) < 8 and time.monotonic() < end:
            f = src.poll()
            if f is None:
                time.sleep(0.005)
            else:
                frames.append(f)
        counters = src.counters
    finally:
        src.close()
    assert len(frames) == 8
    assert [f.seq for f in frames] == list(range(frames[0].seq, frames[0].seq + 8))
    assert counters["aravis_failures"] > 0 and counters["restarts"] == 0
    for f in frames:
        if f.error is None:  # a buffer that made it whole: still the right two frames
            assert (int(f.image_b[0, 0]) - int(f.image_a[0, 0])) % 255 == 1
        else:
            assert "incomplete: missing packets" in f.error and f.image_a is None
    assert any(f.error for f in frames)
