"""``planer acquire`` with Aravis' fake camera: usable images with the shipped config, and a
warning for dark or saturated ones (skips without PyGObject or Aravis)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from controller.frames.camera.device import aravis_unavailable
from planer.cli import main

WHY = aravis_unavailable()
pytestmark = pytest.mark.skipif(WHY is not None, reason=f"camera tests need Aravis: {WHY}")


def _acquire(tmp_path, capsys, *extra: str, table: str | None = None):
    spool = tmp_path / "spool"
    argv = ["acquire", "--camera", "Fake_1", "--pairs", "3", "--spool", str(spool), *extra]
    if table is not None:
        cfg = tmp_path / "machine.toml"
        cfg.write_text(f"[frames]\n{table}\n")
        argv += ["--config", str(cfg)]
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err, spool


def _images(spool):
    from protocol.spool import SpoolReader

    reader = SpoolReader(spool, start="all")
    frames = [reader.poll() for _ in range(3)]
    assert all(f is not None and f.error is None for f in frames)
    return [img for f in frames for img in (f.image_a, f.image_b)]


def test_the_shipped_config_gives_the_fake_camera_images_to_see(tmp_path, capsys):
    rc, out, err, spool = _acquire(tmp_path, capsys)
    assert rc == 0
    assert "exposure 10000 µs" in err and "warning" not in err + out, err
    assert out.strip().endswith("wrote 3 pairs to " + str(spool) + " (0 failed, 0 dropped)")
    for img in _images(spool):  # the ramp, not black
        assert np.percentile(img, 99) > 200 and np.percentile(img, 1) < 10
    meta = json.loads((spool / "acquire.json").read_text())
    assert meta["image_problems"] == {"pairs": {}, "first": {}}
    assert meta["camera"]["exposure_us"] == pytest.approx(10_000.0)


def test_black_images_at_a_real_cameras_exposure_are_warned_about(tmp_path, capsys):
    """Without the fake's exposure it gets the rig's 0.1 ms: black, said once and counted."""
    rc, out, err, spool = _acquire(tmp_path, capsys, table="fake_exposure_us = 0.0")
    assert rc == 0  # the pairs are written: a warning, not a failure
    warnings = [ln for ln in err.splitlines() if ln.startswith("planer acquire: warning:")]
    assert len(warnings) == 1, err
    assert warnings[0].startswith("planer acquire: warning: pair 0 is dark (image A: grey "
                                  "levels 0..0") and "exposure 100 µs" in warnings[0]
    assert "raise [frames] exposure_us or gain_db" in warnings[0]
    assert out.strip().endswith("; warning: 3 of 3 pairs dark (see the warnings above)")
    assert all(img.max() == 0 for img in _images(spool))
    meta = json.loads((spool / "acquire.json").read_text())
    assert meta["image_problems"]["pairs"] == {"dark": 3}


def test_saturated_images_are_warned_about(tmp_path, capsys):
    rc, out, err, _ = _acquire(tmp_path, capsys, table="gain_db = 3.0")
    assert rc == 0
    assert "is saturated (image A:" in err and "lower [frames] exposure_us or gain_db" in err
    assert out.strip().endswith("; warning: 3 of 3 pairs saturated (see the warnings above)")


def test_a_plc_that_does_not_answer_is_one_line_of_ours_not_pymodbus_lines(tmp_path):
    import subprocess
    import sys

    from planer.hil.cross_process import free_port

    port = free_port()  # nothing listens there
    out = subprocess.run(
        [sys.executable, "-m", "planer.cli", "acquire", "--camera", "Fake_1", "--pairs", "2",
         "--spool", str(tmp_path / "spool"), "--plc", f"127.0.0.1:{port}", "--timeout", "1"],
        capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert out.returncode == 2, out.stderr
    lines = [ln.strip() for ln in out.stderr.replace("\r", "\n").splitlines() if ln.strip()]
    ours = [ln for ln in lines if not ln.startswith("[")]  # without the progress bar
    assert ours[0].startswith("camera: Aravis Fake Fake_1")
    assert ours[1:] == [
        f"planer acquire: warning: the PLC at 127.0.0.1:{port} does not answer: no trigger "
        "latches, the pairs fail until it answers",
        ours[2]]
    assert ours[2].startswith("planer acquire: error: no good pair from camera 'Fake_1' for 1 s")
    assert "no trigger latch from the PLC" in ours[2]
