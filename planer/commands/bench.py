"""``planer bench``: not built yet."""

from __future__ import annotations

import argparse

HELP = "bench (not built yet)"


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    raise NotImplementedError("planer bench is not built yet")
