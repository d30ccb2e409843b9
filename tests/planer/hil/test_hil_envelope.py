"""The closed loop's measurement across the plant envelope (in process, simulated time).

Each run is the shipped plant at production feed (4 knives, 1.5 mm, 600 mm/s) with one key of
the simulator changed (a ``sim_config`` of ``base = "sim.toml"`` and that key): at least 90 %
of the pairs give a measurement with knife attribution, and the measured CV follows the true
one within 0.005 or 20 %, whichever is larger. Camera rolled 5 deg (the roll the rig file does
not know): the bottoms reach the attribution in the board's frame. Cutter-to-camera 3 m: the
first 1.3 m of board the camera sees (true CV 0.22-0.36, the loop's dead time 5 s). The small
CVs (0.002-0.02) the vision under-reported are tested on single pairs in
``tests/vision/test_vision_revolution_window.py``.
"""

from __future__ import annotations

import asyncio

import pytest

from planer.hil import InProcessHil
from planer.hil.scenario import Scenario

pytestmark = pytest.mark.slow


def _run(tmp_path, sim_toml: str, distance_m: float) -> list[dict]:
    sim = tmp_path / "sim_one_key.toml"
    sim.write_text('base = "sim.toml"\n' + sim_toml)
    sc = Scenario(name="envelope", distance_m=distance_m, runout_um=(0.0, 4.0, -2.0, 2.0),
                  initial_feed_mm_s=600.0, target_pitch_mm=1.5, sim_config=sim)
    hil = InProcessHil(sc, log_path=tmp_path / "hil.sqlite")
    summary = asyncio.run(hil.run())
    assert summary["board_travel_m"] >= distance_m
    return summary["measurements"]


def _cv_follows(m: dict) -> bool:
    true = m["true_uniformity_cv"]
    return abs(m["uniformity_cv"] - true) <= max(0.005, 0.2 * true)


def test_camera_rolled_5_deg(tmp_path):
    ms = _run(tmp_path, "[camera]\nroll_deg = 5.0\n", 3.0)
    ok = [m for m in ms if m["ok"]]
    assert len(ms) >= 25
    assert len(ok) >= 0.9 * len(ms), [m["error"] for m in ms if not m["ok"]]
    assert sum(map(_cv_follows, ok)) >= 0.9 * len(ok)


def test_camera_3_m_behind_the_cutter(tmp_path):
    ms = _run(tmp_path, "[camera]\ncutter_to_camera_mm = 3000.0\n", 4.5)
    ok = [m for m in ms if m["ok"]]
    assert len(ms) >= 10
    assert len(ok) >= 0.9 * len(ms), [m["error"] for m in ms if not m["ok"]]
    assert sum(map(_cv_follows, ok)) >= 0.9 * len(ok)
