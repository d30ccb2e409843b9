"""The operator and quality pages in a real browser (headless Chromium) during
``planer hil --in-process --http 127.0.0.1:0``; and the same composition in this process.

Checks that the values appear and change, that the page's scripts raise no error (a CSP
violation would be one) and that every request the page makes goes to 127.0.0.1. Skips with the
reason when Chromium, chromedriver or the packages are missing. ``PLANER_WEB_SCREENSHOT=PATH``
saves a screenshot of the operator page (docs/web_operator.png is taken this way).
"""

from __future__ import annotations

import asyncio
import json
import os
import queue
import re
import shutil
import signal
import subprocess
import threading
import time
from dataclasses import replace
from pathlib import Path
from urllib.parse import urlsplit

import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the web extra (uvicorn) is not installed")
pytest.importorskip("selenium", reason="selenium is not installed")

from selenium import webdriver  # noqa: E402
from selenium.common.exceptions import WebDriverException  # noqa: E402
from selenium.webdriver.chrome.service import Service as ChromeService  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

from tests.support.interrupt import ended_or_stacks, planer_argv  # noqa: E402

CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
BROWSERS = ("/usr/lib/chromium/chromium", "/usr/bin/chromium", "/usr/bin/chromium-browser")
BROWSER = next((b for b in BROWSERS if Path(b).exists()), None)
ROOT = Path(__file__).resolve().parents[3]
TIMEOUT_S = 120.0  # generous: the machine is shared and loaded



class _HilWithPages:
    """An in-process HIL run on a thread of its own, with the web pages served during it."""

    def __init__(self, log_path: Path, *, distance_m: float = 200.0) -> None:
        from planer.hil import load_scenario

        self.scenario = replace(load_scenario("default"), distance_m=distance_m)
        self.log_path = log_path
        self.done = threading.Event()
        self.ready: queue.Queue = queue.Queue()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._main, name="hil-with-pages", daemon=True)

    def _main(self) -> None:
        try:
            asyncio.run(self._run())
        except Exception as exc:  # noqa: BLE001 - handed to the test thread, which re-raises
            self.error = exc
            self.ready.put(exc)

    async def _run(self) -> None:
        from controller.edge.compose import serving
        from planer.hil import InProcessHil, machine_config_for

        cfg = machine_config_for(self.scenario, log_path=self.log_path)
        runner = InProcessHil(self.scenario, log_path=self.log_path, plc_transport="direct")
        async with serving(cfg, lambda: getattr(runner, "service", None),
                           http="127.0.0.1:0") as srv:
            self.ready.put(srv)
            run = asyncio.create_task(runner.run())
            wait = asyncio.create_task(asyncio.to_thread(self.done.wait))
            await asyncio.wait({run, wait}, return_when=asyncio.FIRST_COMPLETED)
            run.cancel()
            await asyncio.gather(run, return_exceptions=True)
            self.done.set()
            await wait

    def __enter__(self):
        self.thread.start()
        got = self.ready.get(timeout=TIMEOUT_S)
        if isinstance(got, BaseException):
            raise got
        return got

    def __exit__(self, *exc: object) -> None:
        self.done.set()
        self.thread.join(TIMEOUT_S)
        assert not self.thread.is_alive(), "the HIL run did not stop"


@pytest.fixture()
def chrome(tmp_path, monkeypatch):
    if BROWSER is None or not Path(CHROMEDRIVER).exists():
        pytest.skip("headless Chromium needs the Debian packages chromium and chromium-driver")
    monkeypatch.setenv("SE_OFFLINE", "true")  # Selenium Manager downloads nothing
    opts = webdriver.ChromeOptions()
    opts.binary_location = BROWSER
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic",
                "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
                "--window-size=1500,1250", f"--user-data-dir={tmp_path / 'chrome-profile'}"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    try:
        driver = webdriver.Chrome(options=opts, service=ChromeService(CHROMEDRIVER))
    except WebDriverException as exc:
        pytest.skip(f"headless Chromium does not start here: {exc.msg}")
    driver.set_page_load_timeout(TIMEOUT_S)
    try:
        yield driver
    finally:
        driver.quit()


def _text(driver, element_id: str) -> str:
    return driver.find_element(By.ID, element_id).text


def _number(text: str) -> float | None:
    m = re.fullmatch(r"[-+]?\d+(\.\d+)?", text.strip())
    return float(text) if m else None


_DRAWN = """
const all = (s) => Array.from(document.querySelectorAll(s));
const path = document.querySelector('#profile path.line');
return {
  profile_d: path ? path.getAttribute('d').length : 0,
  labels: all('#profile text.mark-label').map((e) => e.textContent),
  width_bars: all('#widths-chart rect.bar').length,
  offset_labels: all('#offsets-chart text').length,
  pitch_band: all('#pitch-chart rect.band').length,
};
"""


def _requested_urls(driver) -> list[str]:
    urls = []
    for entry in driver.get_log("performance"):
        msg = json.loads(entry["message"])["message"]
        if msg.get("method") == "Network.requestWillBeSent":
            urls.append(msg["params"]["request"]["url"])
    return urls


class _PlanerHilHttp:
    """``planer hil --in-process --http 127.0.0.1:0`` as a process; the URL from its stderr."""

    def __init__(self, log_path: Path, *, distance_m: float = 200.0) -> None:
        # SIGINT as from a terminal, whatever the test runner inherited (the Ctrl-C at the end)
        self.argv = planer_argv("hil", "--in-process", "--plc", "direct",
                                "--distance-m", str(distance_m), "--log", str(log_path),
                                "--http", "127.0.0.1:0", sigint="default")
        self.lines: queue.Queue = queue.Queue()
        self.stderr: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.stderr.append(line)
            self.lines.put(line)
        self.lines.put(None)

    def _said(self) -> str:
        """Its stderr: all of it once the process has ended (the reader meets the pipe's end)."""
        if self.proc.poll() is not None:
            self.reader.join(TIMEOUT_S)
        return "".join(self.stderr)

    def __enter__(self) -> str:
        self.proc = subprocess.Popen(self.argv, cwd=ROOT, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)
        self.reader.start()
        while True:
            line = self.lines.get(timeout=TIMEOUT_S)
            if line is None:
                raise AssertionError("planer hil ended before serving: " + "".join(self.stderr))
            m = re.match(r"http: (http://127\.0\.0\.1:\d+/) ", line)
            if m:
                return m.group(1)

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)  # Ctrl-C: the run stops and cleans up
        try:
            _, said = ended_or_stacks(self.proc, "planer hil --http after Ctrl-C",
                                      stderr=self._said)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
        if exc_type is None:  # mid-run: interrupted (130); after it: the summary's code
            assert self.proc.returncode in (0, 1, 130), said
            last = said.strip().splitlines()[-1:]
            assert last in (["planer hil: interrupted"], ["planer hil: stopped serving"]), said


def test_operator_and_quality_pages_live_during_planer_hil_http(chrome, tmp_path):
    wait = WebDriverWait(chrome, TIMEOUT_S, poll_frequency=0.2)
    with _PlanerHilHttp(tmp_path / "hil.sqlite") as url:
        origin = url.rstrip("/")
        chrome.get(url)
        # the machine state appears, then measurements
        wait.until(lambda d: _text(d, "state") in ("RUN", "SAFE STATE"))
        wait.until(lambda d: _number(_text(d, "pitch")) is not None)
        seq0, pitch0 = _text(chrome, "seq"), _number(_text(chrome, "pitch"))
        assert 0.5 < pitch0 < 5.0
        # and they change as the run goes on
        wait.until(lambda d: _text(d, "seq") != seq0)
        wait.until(lambda d: _text(d, "state") == "RUN")
        wait.until(lambda d: d.execute_script(
            "return document.querySelectorAll('#pitch-chart circle').length;") >= 5)
        assert _number(_text(chrome, "feed-set")) > 0
        assert chrome.execute_script("return document.getElementById('heads').hidden;")
        assert _number(_text(chrome, "feed-act")) > 0
        assert _number(_text(chrome, "confidence")) is not None
        assert _number(_text(chrome, "roll")) is not None
        # the profile with its marks, each labelled with its knife; per-knife bars; the band
        # (read in one script: the charts are redrawn on every update)
        # (a pair whose marks could not be attributed shows "?": wait for one that could)
        wait.until(lambda d: (lambda x: len(x["labels"]) >= 2
                              and all(t.isdigit() for t in x["labels"]))(d.execute_script(_DRAWN)))
        drawn = chrome.execute_script(_DRAWN)
        assert drawn["profile_d"] > 100
        assert drawn["width_bars"] >= 2 and drawn["offset_labels"] >= 2
        assert drawn["pitch_band"] == 1
        # events as they happen: the service starts in SAFE and recovers
        wait.until(lambda d: d.execute_script(
            "return document.querySelectorAll('#events li.recovered').length;") > 0)
        version = "return Number(document.body.dataset.version);"
        v0 = chrome.execute_script(version)
        wait.until(lambda d: d.execute_script(version) > v0 + 3)
        shot = os.environ.get("PLANER_WEB_SCREENSHOT")
        if shot:  # for the docs: a few metres into the run, the loops converged
            wait.until(lambda d: d.execute_script(
                "return document.querySelectorAll('#pitch-chart circle').length;") >= 60)
            chrome.save_screenshot(shot)

        # the quality page: boards of this run's log, a figure, the CSV link
        chrome.get(url + "quality")
        wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, "#boards tbody tr"))
        wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, "#records tbody tr"))
        wait.until(lambda d: d.execute_script(
            "const i = document.querySelector('#figures img');"
            "return i !== null && i.complete && i.naturalWidth > 0;"))
        href = chrome.find_element(By.ID, "board-csv").get_attribute("href")
        assert href.startswith(origin + "/api/quality/boards/") and href.endswith(".csv")

        urls = _requested_urls(chrome)
    # no request left the machine: every URL the page asked for is this server's
    assert urls, "the performance log recorded no requests"
    # (chrome:// are the browser's own built-in pages, e.g. the first empty tab: no network)
    network = [u for u in urls if urlsplit(u).scheme not in ("chrome", "data", "about", "blob")]
    foreign = [u for u in network if not u.startswith(origin + "/")]
    assert not foreign, foreign
    assert {urlsplit(u).path for u in urls} >= {"/", "/static/plot.js", "/static/operator.js",
                                                "/api/live/stream", "/quality"}
    # the page's scripts ran without an error (a blocked asset or script error shows here)
    severe = [e["message"] for e in chrome.get_log("browser") if e["level"] == "SEVERE"]
    assert not severe, severe


def test_hil_composition_serves_only_local_clients_and_stops_with_the_run(tmp_path):
    # the composition in this process (no browser): the server answers while the run goes,
    # records who asked, and is gone when the run ends
    import httpx

    with _HilWithPages(tmp_path / "hil.sqlite") as server:
        deadline = time.monotonic() + TIMEOUT_S
        seqs: set = set()
        while len(seqs) < 3 and time.monotonic() < deadline:
            last = httpx.get(server.url + "api/live", timeout=30.0).json()["last"]
            if last is not None:
                seqs.add(last["seq"])
            time.sleep(0.1)  # polling the run's progress, not waiting for time to pass
        assert len(seqs) >= 3
        served = server.wait_stats(lambda s: bool(s.get("http", {}).get("requests")),
                                   TIMEOUT_S)["http"]["requests"]
        assert served and all(r["client"] == "127.0.0.1" and r["method"] == "GET"
                              for r in served)
    with pytest.raises(httpx.ConnectError):
        httpx.get(server.url, timeout=5.0)
