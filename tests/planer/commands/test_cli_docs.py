"""docs/cli.md says what ``planer COMMAND --help`` says: every option of every command, and
the scenarios of config/hil.toml."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from config.loading import default_path, load_toml
from planer.cli import COMMANDS, build_parser

CLI_MD = Path(__file__).parents[3] / "docs" / "cli.md"


def _section(command: str) -> str:
    text = CLI_MD.read_text(encoding="utf-8")
    m = re.search(rf"^### `planer {re.escape(command)}\b.*?$(.*?)(?=^##)", text, re.S | re.M)
    assert m, f"docs/cli.md has no section for planer {command}"
    return m.group(1)


def _documented_options(section: str) -> set[str]:
    """The options named in the first column of the section's option table."""
    rows = [ln for ln in section.splitlines() if ln.startswith("| `")]
    return {opt for row in rows for opt in re.findall(r"`(--[a-z][a-z0-9-]*)", row.split("|")[1])}


def _parser_options(command: str) -> set[str]:
    parser = build_parser([command])
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {opt for action in sub.choices[command]._actions for opt in action.option_strings
            if opt.startswith("--") and opt != "--help"}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_option_of_every_command_is_documented_and_no_other(command):
    assert _documented_options(_section(command)) == _parser_options(command)


def test_the_hil_scenarios_documented_are_those_of_config_hil_toml():
    section = _section("hil")
    table = section[section.index("| scenario |"):]
    documented = re.findall(r"^\| `([a-z_]+)` \|", table, re.M)
    assert documented == list(load_toml(default_path("hil.toml")))  # in the file's order
