"""The two-head composition, once for the folder's tests (simulated time: a few seconds)."""

from __future__ import annotations

import asyncio

import pytest

from tests.controller.edge.two_heads import two_heads


@pytest.fixture(scope="package")
def moulder(tmp_path_factory):
    loop = asyncio.new_event_loop()
    th = loop.run_until_complete(two_heads(tmp_path_factory.mktemp("two_heads")))
    try:
        yield th
    finally:
        loop.run_until_complete(th.close())
        loop.close()
