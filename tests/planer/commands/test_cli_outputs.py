"""Outputs never overwrite inputs, are checked before the work, and name themselves on failure.

``planer report`` reads its log read-only; ``--csv`` or a figure that is the log (same path,
a symlink, a hard link) is refused; ``planer measure --plot`` takes a figure file only.
"""

from __future__ import annotations

import errno
import hashlib
import os

import pytest

from controller.quality.log import QualityLog
from planer.cli import main
from planer.outputs import figure_file, not_an_input, same_file, writing
from tests.controller.quality.test_report import QC, make_run


def _run(argv, capsys):
    try:
        rc = main(argv)
    except SystemExit as exc:
        rc = exc.code
    cap = capsys.readouterr()
    return rc, [ln for ln in cap.err.splitlines() if ln.strip()]


def _digest(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.fixture
def log_file(tmp_path):
    path = tmp_path / "run.sqlite"
    with QualityLog(path) as log:
        log.set_quality_class(QC)
        for r in make_run(3, per_board=5):
            log.append(r)
    return path


def _as_link(kind, log_file, tmp_path):
    if kind == "same":
        return log_file
    link = tmp_path / "other" / "alias.csv"
    link.parent.mkdir()
    if kind == "symlink":
        link.symlink_to(log_file)
    elif kind == "hardlink":
        os.link(log_file, link)
    else:
        link = tmp_path / "other" / ".." / log_file.name  # the same file by another spelling
    return link


@pytest.mark.parametrize("kind", ["same", "symlink", "hardlink", "dotdot"])
def test_report_refuses_a_csv_that_is_the_log(log_file, tmp_path, capsys, kind):
    target = _as_link(kind, log_file, tmp_path)
    before = _digest(log_file)
    rc, err = _run(["report", str(log_file), "--csv", str(target)], capsys)
    assert rc == 2 and len(err) == 1
    assert err[0].startswith(f"planer report: error: --csv {target}: is LOG ")
    assert _digest(log_file) == before


def test_report_refuses_a_csv_that_is_the_journal(log_file, tmp_path, capsys):
    journal = tmp_path / "run.sqlite.journal.jsonl"
    rc, err = _run(["report", str(log_file), "--csv", str(journal)], capsys)
    assert rc == 2 and "record journal" in err[0] and not journal.exists()


@pytest.mark.parametrize("content", [b"", b"garbage, not SQLite\n"])
def test_report_leaves_an_empty_or_foreign_file_as_it_is(tmp_path, capsys, content):
    p = tmp_path / "q.sqlite"
    p.write_bytes(content)
    rc, err = _run(["report", str(p)], capsys)
    assert rc == 2 and len(err) == 1 and str(p) in err[0]
    assert p.read_bytes() == content
    assert sorted(os.listdir(tmp_path)) == ["q.sqlite"]  # no -wal, -shm or figure beside it


def test_report_reads_the_log_without_writing_it(log_file, capsys):
    before = _digest(log_file)
    os.chmod(log_file, 0o444)
    try:
        rc, _ = _run(["report", str(log_file), "--json"], capsys)
    finally:
        os.chmod(log_file, 0o644)
    assert rc == 0 and _digest(log_file) == before


def test_report_names_a_file_a_full_disk_stopped(log_file, tmp_path, capsys, monkeypatch):
    def full(self, path, **kw):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(QualityLog, "export_csv", full)
    csv = tmp_path / "out.csv"
    rc, err = _run(["report", str(log_file), "--csv", str(csv)], capsys)
    assert rc == 2
    assert err == [f"planer report: error: --csv {csv}: cannot write: No space left on device"]


def test_report_says_what_a_url_of_another_database_is(capsys):
    rc, err = _run(["report", "mysql://planer@db:3306/quality"], capsys)
    assert rc == 2 and "mysql:// is not a quality log" in err[0] and "not found" not in err[0]


@pytest.mark.parametrize("plot, words", [("{tmp}", "is a folder"), ("{tmp}/out.txt", ".txt"),
                                         ("{tmp}/profile", "no suffix"),
                                         ("{tmp}/a.png", "is IMAGE_A")])
def test_measure_checks_plot_before_the_work(tmp_path, capsys, plot, words):
    """The rig does not exist: the --plot error comes first, so it was checked before."""
    a = tmp_path / "a.png"
    a.write_bytes(b"not read")
    rc, err = _run(["measure", str(a), str(tmp_path / "b.png"), "--counts-a", "0",
                    "--counts-b", "10", "--rig", str(tmp_path / "nope.toml"),
                    "--plot", plot.format(tmp=tmp_path)], capsys)
    assert rc == 2 and len(err) == 1
    assert err[0].startswith("planer measure: error: --plot ") and words in err[0], err
    assert a.read_bytes() == b"not read"


def test_same_file_by_path_symlink_and_inode(tmp_path):
    a = tmp_path / "a"
    a.write_text("x")
    (tmp_path / "s").symlink_to(a)
    os.link(a, tmp_path / "h")
    assert same_file(a, tmp_path / "s") and same_file(a, tmp_path / "h")
    assert not same_file(a, tmp_path / "b") and same_file(tmp_path / "b", tmp_path / "b")
    with pytest.raises(ValueError, match="--out .*is LOG"):
        not_an_input("--out", tmp_path / "h", {"LOG": a, "URL": None})
    assert figure_file("--plot", "x.PDF") == "x.PDF"
    with pytest.raises(OSError, match=r"^--plot x.png: cannot write: No space left"):
        with writing("--plot", "x.png"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
