"""The operator page of a moulder in headless Chromium: a row and a tab per head, each tab
showing that head's pitch, state, target, board strip; two real heads' services behind
``serving`` (the servers' own process), the top head in its safe state. Skips as
test_web_browser.py does when Chromium or its driver is missing.
``PLANER_WEB_HEADS_SCREENSHOT=PATH`` saves the page (docs/web_heads.png is taken this way)."""

from __future__ import annotations

import asyncio
import os
import queue
import threading

import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the web extra (uvicorn) is not installed")
pytest.importorskip("selenium", reason="selenium is not installed")

from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

from tests.controller.edge.two_heads import two_heads  # noqa: E402
from tests.controller.web.test_web_browser import (  # noqa: E402, F401
    TIMEOUT_S,
    _number,
    _text,
    chrome,
)


class _ServedHeads:
    """Two heads' composition served (``serving``) from a loop on a thread of its own."""

    def __init__(self, tmp_path) -> None:
        self.tmp_path = tmp_path
        self.ready: queue.Queue = queue.Queue()
        self.done = threading.Event()
        self.thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)

    async def _run(self) -> None:
        from controller.edge.compose import serving

        try:
            heads = await two_heads(self.tmp_path)
            cfg = heads.plants["bottom"].cfg
            async with serving(cfg, lambda: heads, http="127.0.0.1:0") as srv:
                self.heads = heads
                self.ready.put(srv)
                await asyncio.to_thread(self.done.wait)
            await heads.close()
        except Exception as exc:  # noqa: BLE001 - handed to the test thread, which re-raises
            self.ready.put(exc)

    def __enter__(self):
        self.thread.start()
        got = self.ready.get(timeout=TIMEOUT_S)
        if isinstance(got, BaseException):
            raise got
        return got

    def __exit__(self, *exc: object) -> None:
        self.done.set()
        self.thread.join(TIMEOUT_S)
        assert not self.thread.is_alive(), "the servers did not stop"


_ROWS = """
return Array.from(document.querySelectorAll('#heads-table tbody tr')).map((tr) => ({
  head: tr.dataset.head, selected: tr.classList.contains('selected'),
  cells: Object.fromEntries(Array.from(tr.cells).map((td) => [td.className, td.textContent])),
}));
"""


def test_a_row_and_a_tab_per_head_each_tab_shows_its_head(chrome, tmp_path):  # noqa: F811
    wait = WebDriverWait(chrome, TIMEOUT_S, poll_frequency=0.2)
    served = _ServedHeads(tmp_path)
    with served as srv:
        heads = served.heads
        last = {n: next(r for r in reversed(s.results) if r.ok) for n, s in heads.heads.items()}
        chrome.get(srv.url)
        wait.until(lambda d: len(d.execute_script(_ROWS)) == 2)
        wait.until(lambda d: all(r["cells"]["pitch"] != "-" for r in d.execute_script(_ROWS)))
        rows = {r["head"]: r for r in chrome.execute_script(_ROWS)}
        assert list(rows) == ["bottom", "top"]
        for name, target in (("bottom", "1.50"), ("top", "1.00")):
            cells = rows[name]["cells"]
            assert cells["pitch"] == f"{last[name].reported_pitch_mm:.3f}"
            assert cells["cv"] == f"{last[name].reported_uniformity_cv:.3f}"
            assert cells["target"] == target and cells["face"] == name
            assert cells["knives"] == "4"
            assert cells["rpm"] == f"{float(heads.heads[name].plc.last.spindle_rpm):.0f}"
        assert rows["bottom"]["cells"]["state"] == "RUN"
        assert rows["top"]["cells"]["state"].startswith("SAFE")
        assert rows["bottom"]["selected"] and not rows["top"]["selected"]
        assert rows["top"]["cells"]["offsets"] == "0.0 0.0 0.0 0.0"
        # the first head's panels; then the top head's tab shows the top head's
        assert chrome.find_element(By.TAG_NAME, "body").get_attribute("data-head") == "bottom"
        wait.until(lambda d: _text(d, "state") == "RUN")
        assert _number(_text(chrome, "pitch")) == round(last["bottom"].reported_pitch_mm, 3)
        assert "target 1.5 mm" in _text(chrome, "pitch-target")
        chrome.find_element(By.CSS_SELECTOR, "#head-tabs button[data-head='top']").click()
        wait.until(lambda d: d.find_element(By.TAG_NAME, "body").get_attribute(
            "data-head") == "top")
        wait.until(lambda d: _text(d, "state") == "SAFE STATE")
        assert _number(_text(chrome, "pitch")) == round(last["top"].reported_pitch_mm, 3)
        assert "target 1 mm" in _text(chrome, "pitch-target")
        assert _text(chrome, "seq") == f"#{heads.heads['top'].results[-1].seq}"
        assert chrome.execute_script(
            "return document.querySelectorAll('#pitch-chart circle').length;") >= 5
        assert chrome.find_element(By.ID, "board-strip")  # the selected head's board strip
        # the events name their head
        texts = [e.get_attribute("textContent")
                 for e in chrome.find_elements(By.CSS_SELECTOR, "#events li")]
        assert any(" s  top: " in t for t in texts), texts
        assert any(" s  bottom: " in t for t in texts), texts
        shot = os.environ.get("PLANER_WEB_HEADS_SCREENSHOT")
        if shot:  # for the docs (docs/web_heads.png)
            chrome.save_screenshot(shot)
    severe = [e["message"] for e in chrome.get_log("browser") if e["level"] == "SEVERE"]
    assert not severe, severe
