"""The asyncua script of docs/opcua.md runs as written, as a script, against a live server."""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("asyncua")

from controller.opcua.server import OpcUaServer  # noqa: E402
from controller.service.status import ServiceStatus  # noqa: E402

DOC = Path(__file__).parents[3] / "docs" / "opcua.md"


def _script() -> str:
    blocks = re.findall(r"^```python\n(.*?)^```", DOC.read_text(encoding="utf-8"), re.S | re.M)
    assert len(blocks) == 1, "docs/opcua.md should hold one python block: the script"
    return blocks[0]


def _status(state: str) -> ServiceStatus:
    return ServiceStatus(t_s=5.0, state=state, safe_reason=None if state == "run" else "test",
                         missing=(), feed_setpoint_mm_s=300.0, feed_actual_mm_s=300.0,
                         offsets_um=(0.0,) * 4, amplifier_enabled=state == "run",
                         last_measurement=None, counters=ServiceStatus.freeze({}))


def test_the_docs_script_prints_the_machines_state(tmp_path):
    script = tmp_path / "read_state.py"
    script.write_text(_script(), encoding="utf-8")
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    srv = OpcUaServer("opc.tcp://127.0.0.1:0", knives=4)
    seen = {}
    try:
        asyncio.run_coroutine_threadsafe(srv.start(), loop).result(timeout=120)
        for state in ("run", "safe"):
            before = srv.published
            srv.update(_status(state))
            deadline = time.monotonic() + 30
            while srv.published == before:  # the server's own publishing, not a fixed wait
                assert time.monotonic() < deadline, "the server never published the update"
                time.sleep(0.002)
            proc = subprocess.run([sys.executable, str(script), srv.endpoint], cwd=tmp_path,
                                  capture_output=True, text=True, timeout=120)
            assert proc.returncode == 0, proc.stderr[-2000:]
            seen[state] = proc.stdout.strip().splitlines()[-1]
    finally:
        asyncio.run_coroutine_threadsafe(srv.stop(), loop).result(timeout=60)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=60)
    assert seen["run"] == "3"  # WORKING
    assert seen["safe"] != "3" and seen["safe"].isdigit(), seen
