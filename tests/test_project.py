"""The project's own promises: quick start, CI script, command line shell."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from planer import cli

ROOT = Path(__file__).resolve().parents[1]


def _first_shell_block() -> list[str]:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"```(?:sh|bash|shell)\n(.*?)```", text, re.S)
    assert m, "README has no shell code block"
    return [ln for ln in m.group(1).splitlines() if ln.strip()]


def test_readme_quick_start_has_exactly_two_commands():
    lines = _first_shell_block()
    assert len(lines) == 2
    assert "planer hil" in lines[0] and lines[0].startswith("pip install")
    assert "pytest" in lines[1] and "[test]" in lines[1]


def test_ci_runs_the_readme_test_command_in_a_fresh_venv():
    ci = (ROOT / ".ci" / "run").read_text()
    assert _first_shell_block()[1] in ci.splitlines()
    assert "python3 -m venv" in ci


def test_every_command_is_registered_with_help():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(sub.choices) == set(cli.COMMANDS)
    for name in cli.COMMANDS:
        assert "not built" not in sub.choices[name].description, name


def test_value_errors_become_one_line_and_exit_2(capsys, monkeypatch):
    def boom(args):
        raise ValueError("bad thing: value 7\nsecond line")

    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda *_: parser)
    parser._subparsers._group_actions[0].choices["bench"].set_defaults(_run=boom)
    assert cli.main(["bench"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["planer bench: error: bad thing: value 7"]


@pytest.mark.parametrize("argv", [[], ["nonsense"]])
def test_usage_errors_exit_nonzero(argv):
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code != 0
