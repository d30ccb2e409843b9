"""``planer calibrate-rig --spool``: a folder that is missing, a file or without pairs is named."""

from __future__ import annotations

from pathlib import Path

import pytest

from planer.cli import main

RIG = Path(__file__).parents[3] / "config" / "rig.toml"


def _run(argv, capsys):
    rc = main(argv)
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("kind", ["missing", "file", "empty"])
def test_a_spool_without_pairs_is_named(tmp_path, capsys, kind):
    spool = tmp_path / "spool"
    if kind == "file":
        spool.write_text("not a folder\n")
    elif kind == "empty":
        spool.mkdir()
        (spool / "notes.txt").write_text("x\n")
    rc, err = _run(["calibrate-rig", "--spool", str(spool), "--radius-mm", "60",
                    "--rig", str(RIG), "--out", str(tmp_path / "rig.toml")], capsys)
    assert rc == 2
    expected = {"missing": f"--spool {spool}: no such folder",
                "file": f"--spool {spool}: is a file, expected a spool folder",
                "empty": f"--spool {spool}: no good image pairs in the folder"}[kind]
    assert err.startswith(f"planer calibrate-rig: error: {expected}"), err
    assert "no image pairs given" not in err
    assert not (tmp_path / "rig.toml").exists()
