"""What every ``planer`` command shares (planer/cli.py): closed pipes, output folders."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from planer.cli import main

ROOT = Path(__file__).resolve().parents[3]

FAKE = textwrap.dedent(
    """
    import sys, types
    import planer.cli as cli

    mod = types.ModuleType("planer.commands.fake")
    mod.configure = lambda parser: parser.add_argument("what")

    def run(args):
        if args.what == "many":
            for i in range(200_000):
                print(f"line {i}")
        elif args.what == "few":
            print("just one line")
        elif args.what == "socket":  # a broken connection, not the terminal: a real error
            raise BrokenPipeError(32, "Broken pipe")
        return 0

    mod.run = run
    sys.modules["planer.commands.fake"] = mod
    cli.COMMANDS = {**cli.COMMANDS, "fake": "a test command"}
    sys.exit(cli.main(sys.argv[1:]))
    """
)


def _run_into_pipe(argv: list[str], *, read_bytes: int | None) -> tuple[int, str]:
    """Run argv with stdout into a pipe whose reader reads ``read_bytes`` then closes.

    ``read_bytes=None``: the reader is gone before the process starts.
    """
    r, w = os.pipe()
    if read_bytes is None:
        os.close(r)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(argv, stdout=w, stderr=subprocess.PIPE, cwd=ROOT, env=env)
    os.close(w)
    if read_bytes is not None:
        got = os.read(r, read_bytes)
        assert got  # the command did write before its reader went away
        os.close(r)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err.decode()


@pytest.mark.parametrize(
    ("args", "read_bytes"),
    [
        (["many"], 10),  # `planer fake many | head -c 10`: blocked mid-output, then EPIPE
        (["few"], None),  # the reader left before the only line: EPIPE at the last flush
    ],
)
def test_a_closed_stdout_ends_quietly_with_exit_0(args, read_bytes):
    code, err = _run_into_pipe([sys.executable, "-c", FAKE, "fake", *args], read_bytes=read_bytes)
    assert (code, err) == (0, "")


def test_help_into_a_closed_pipe_ends_quietly():
    code, err = _run_into_pipe([sys.executable, "-m", "planer.cli", "--help"], read_bytes=None)
    assert (code, err) == (0, "")


def test_a_broken_pipe_that_is_not_stdout_stays_an_error():
    proc = subprocess.run(
        [sys.executable, "-c", FAKE, "fake", "socket"],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith("planer fake: error:") and "Broken pipe" in proc.stderr


def test_calibrate_creates_the_folder_of_out(tmp_path, monkeypatch, capsys):
    """`--out DIR/rig.toml` with DIR missing: the folder is made (docs/cli.md says so)."""
    import cv2

    import vision.calibration.camera as cal
    from config.rig import load_rig

    images = []
    for k in range(3):
        p = tmp_path / f"b{k}.png"
        cv2.imwrite(str(p), np.full((40, 60), 128, np.uint8))
        images.append(str(p))
    # corner finding and calibration are vision's (tests/vision/calibration/test_calibrate.py);
    # stand-ins here
    monkeypatch.setattr(cal, "find_corners", lambda image, pattern: np.zeros((49, 1, 2)))
    result = cal.CalibrationResult(
        fx=500.0, fy=501.0, cx=30.0, cy=20.0, dist=(-0.1, 0.0, 0.0, 0.0, 0.0),
        rms_px=0.1, n_images=3, per_image_error_px=(0.1, 0.1, 0.1),
    )
    monkeypatch.setattr(cal, "calibrate", lambda *a, **k: result)
    out = tmp_path / "new" / "deeper" / "rig.toml"
    code = main(["calibrate", *images, "--pattern", "7x7", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    rig = load_rig(out)
    assert (rig.camera.fx, rig.camera.dist[0]) == (500.0, -0.1)


def test_calibrate_out_that_is_a_folder_is_refused_before_any_work(tmp_path, capsys):
    code = main(["calibrate", str(tmp_path / "none.png"), "--pattern", "7x7", "--out",
                 str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and "--out" in err and "is a folder" in err
