"""The operator page's knife condition card in a real browser (headless Chromium).

The page is served from a :class:`LiveView` holding a service snapshot with a knife condition
(wear, reserve and offset per knife, the jointing forecast) and the last chipped or nicked
knife; the card must show them, mark the knife that runs out first, and turn the forecast red
once jointing is due within the service's warning. Skips with the reason when Chromium or the
packages are missing (the ``chrome`` fixture of ``test_web_browser.py``).
"""

from __future__ import annotations

import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")
pytest.importorskip("selenium", reason="selenium is not installed")

from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

from controller.service.loops import JOINTING_WARN_BOARDS  # noqa: E402
from controller.service.status import ServiceStatus  # noqa: E402
from controller.web.app import make_app  # noqa: E402
from controller.web.live import LiveView  # noqa: E402
from controller.web.server import WebServer  # noqa: E402
from tests.controller.web.test_web_browser import TIMEOUT_S, chrome  # noqa: E402, F401

KNIVES = [
    {"knife": 0, "offset_um": -4.1, "drift_um_per_m": -0.212, "reserve_um": 1.9},
    {"knife": 1, "offset_um": 1.3, "drift_um_per_m": 0.07, "reserve_um": 4.7},
    {"knife": 2, "offset_um": 1.4, "drift_um_per_m": 0.071, "reserve_um": 4.6},
    {"knife": 3, "offset_um": 1.4, "drift_um_per_m": 0.071, "reserve_um": 4.6},
]


def _status(boards: float, chip: dict | None = None) -> ServiceStatus:
    kc = {"board_travel_m": 21.25, "knives": KNIVES, "due_in_m": boards * 4.0,
          "due_in_boards": boards, "due_in_h": boards * 4.0 / 0.6 / 3600, "knife": 0,
          "text": f"jointing due in {boards:.0f} boards / 0.05 h at this feed (knife 0)",
          "state": "due", "t_s": 35.2}
    return ServiceStatus(
        t_s=35.3, state="run", safe_reason=None, missing=(), feed_setpoint_mm_s=600.0,
        feed_actual_mm_s=600.0, offsets_um=tuple(k["offset_um"] for k in KNIVES),
        amplifier_enabled=True, last_measurement=None, counters=ServiceStatus.freeze({}),
        alerts={"target_unreachable": None, "measurements_failing": None,
                "knife_chipped": chip},
        knife_condition=kc)


def _card(driver) -> dict:
    return driver.execute_script("""
        const rows = Array.from(document.querySelectorAll('#kc-table tbody tr'));
        return {
          forecast: document.getElementById('kc-forecast').textContent,
          forecast_class: document.getElementById('kc-forecast').className,
          chip: document.getElementById('kc-chip').textContent,
          travel: document.getElementById('kc-travel').textContent,
          rows: rows.map((r) => Array.from(r.cells).map((c) => c.textContent)),
          selected: rows.filter((r) => r.className === 'selected')
            .map((r) => r.cells[0].textContent),
          bars: document.querySelectorAll('#reserve-chart rect.bar').length,
          version: document.body.dataset.version || '',
        };""")


def test_the_card_shows_wear_reserve_forecast_and_a_chipped_knife(chrome):  # noqa: F811
    live = LiveView()
    live.update(_status(boards=60.0))
    server = WebServer(make_app(live, None), "127.0.0.1:0")
    server.start()
    try:
        chrome.get(server.url)
        wait = WebDriverWait(chrome, TIMEOUT_S)
        wait.until(lambda d: "jointing due in 60 boards" in _card(d)["forecast"])
        card = _card(chrome)
        assert card["rows"][0] == ["knife 0", "-0.212", "1.90", "-4.10"]
        assert [r[0] for r in card["rows"]] == ["knife 0", "knife 1", "knife 2", "knife 3"]
        assert card["selected"] == ["knife 0"]  # the one whose reserve runs out first
        assert card["bars"] == 4 and card["travel"] == "(21.3 m of board)"
        assert "soon" not in card["forecast_class"].split() and card["chip"] == ""
        assert chrome.find_element(By.ID, "kc-chip").is_displayed() is False  # nothing to say

        chip = {"knife": 1, "runout_step_um": 6.02, "width_change_mm": 0.031, "seq": 41,
                "t_s": 4.1}
        live.update(_status(boards=JOINTING_WARN_BOARDS - 8.0, chip=chip))
        wait.until(lambda d: _card(d)["chip"] != "")
        card = _card(chrome)
        assert card["chip"] == ("knife 1 chipped or moved at t=4.1 s: runout +6.0 µm, "
                                "marks +0.031 mm")
        assert card["forecast"].startswith("jointing due in 12 boards")
        assert {"due", "soon"} <= set(card["forecast_class"].split())

        nick = {"knife": None, "cause": "nick", "y_mm": 0.49, "ridge_um": 12.8,
                "runout_step_um": None, "width_change_mm": None, "seq": 68, "t_s": 8.3}
        live.update(_status(boards=JOINTING_WARN_BOARDS - 8.0, chip=nick))
        wait.until(lambda d: "nicked" in _card(d)["chip"])
        assert _card(chrome)["chip"] == ("a knife is nicked (t=8.3 s): a ridge along the board "
                                         "at 0.5 mm across the field, 13 µm high")
        errors = [e for e in chrome.get_log("browser") if e["level"] == "SEVERE"]
        assert errors == []
    finally:
        server.stop()
