"""The closed loop at 25 and 30 DN of read noise (in process, simulated time).

The shipped plant at production feed (4 knives, 1.5 mm, 600 mm/s) with ``[camera.optics]
read_noise_dn`` raised: the albedo drowns and the images no longer register the pairs; the
service's measurers then take the encoder's shift where the marks confirm it
(``vision.registration.encoder_fallback``). The noise also makes a fall of two samples' means
pass for a cusp now and then, splitting a mark in two (then "marks do not fit one per knife
pass": 58 % of the pairs measured at 30 DN); the arc model drops such cusps
(``vision.marks.without_false_cusps``). Each mark's width carries ~0.02 mm of noise (a CV of
~0.013 where the knives cut evenly); the pair reports the CV of the widths as the knives cut
them (the knife model's CV of ``controller.service.attribution.attribute``).

Done when (the envelope's item): at least 90 % of the pairs give a measurement with knife
attribution, and the measured CV follows the true one within 0.005 or 20 %, whichever is
larger (measured 42 of 43 pairs and 40 of 42 at both noises; the two others within 0.009).
"""

from __future__ import annotations

import asyncio

import pytest

from planer.hil import InProcessHil
from planer.hil.scenario import Scenario

pytestmark = pytest.mark.slow


def cv_follows(m: dict) -> bool:
    """Whether a measured pair's CV follows the true one within 0.005 or 20 %."""
    true = m["true_uniformity_cv"]
    return abs(m["uniformity_cv"] - true) <= max(0.005, 0.2 * true)


@pytest.mark.parametrize("noise_dn", [25.0, 30.0])
def test_read_noise_is_measured_and_the_cv_followed(tmp_path, noise_dn):
    sim = tmp_path / "sim_noise.toml"
    sim.write_text(f'base = "sim.toml"\n[camera.optics]\nread_noise_dn = {noise_dn}\n')
    sc = Scenario(name="noise", distance_m=3.0, runout_um=(0.0, 4.0, -2.0, 2.0),
                  initial_feed_mm_s=600.0, target_pitch_mm=1.5, sim_config=sim)
    summary = asyncio.run(InProcessHil(sc, log_path=tmp_path / "hil.sqlite").run())
    ms = summary["measurements"]
    ok = [m for m in ms if m["ok"]]
    assert len(ms) >= 40
    assert len(ok) >= 0.9 * len(ms), [m["error"] for m in ms if not m["ok"]]
    assert all(m["knife_widths_mm"] for m in ok)
    follows = [m for m in ok if cv_follows(m)]
    assert len(follows) >= 0.9 * len(ok), [(m["true_uniformity_cv"], m["uniformity_cv"])
                                           for m in ok if not cv_follows(m)]
    # where the runout shows (true CV >= 0.05) the measured CV follows it within 20 %
    large = [m for m in ok if m["true_uniformity_cv"] >= 0.05]
    assert large
    assert all(cv_follows(m) for m in large)
    assert summary["final"]["uniformity_cv"] < 0.03  # the loop has evened the knives
