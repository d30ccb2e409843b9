"""Closing several things so that one failing never leaves the others open."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any


def close_all(steps: Sequence[Callable[[], Any]]) -> None:
    """Call every step in order, each even when one before it raised.

    The last error raised propagates, the earlier ones chained as its ``__context__`` (nothing
    is swallowed: no catch-all handler).
    """
    if not steps:
        return
    try:
        steps[0]()
    finally:  # an error in a later step carries this one as its context
        close_all(steps[1:])
