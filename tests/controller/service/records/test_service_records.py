"""What the service puts into the quality log besides the metrics, and what its loops remember.

* a decimated surface profile every ``PROFILE_EVERY``-th successful measurement and on the first
  of each board (small: at most ``PROFILE_MAX_POINTS`` points, rounded), which ``planer report``
  draws;
* the supervisor's state and the reason of a safe state in every record;
* a feed setpoint the PLC refused never enters the feed loop's setpoint history.

Simulated time, the in-process plant of ``tests/controller/service/test_service_loop.py``.
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import replace

import numpy as np
import pytest

from controller.quality.log import QualityLog, record_to_json
from controller.quality.report import last_profile
from controller.service.events import EventKind
from controller.service.records import (
    PROFILE_EVERY,
    PROFILE_MAX_POINTS,
    decimated_profile,
    rounded,
)
from controller.service.supervisor import SafetyState
from protocol.register_bus import BusRefused
from tests.controller.service.test_service_loop import TruthMeasurer, make_plant
from tests.support.plant_support import run_for

N_COLUMNS = 659


def _profile(seq: int) -> tuple[np.ndarray, np.ndarray]:
    x = np.arange(N_COLUMNS) / 12.5 + 1e-7 * seq  # mm, with digits beyond the rounding
    h = 3.0 * np.sin(2 * np.pi * x / 1.5) + 0.123456 * (seq % 7)
    return x, h


class ProfileMeasurer(TruthMeasurer):
    """The truth measurer, plus a full-resolution profile per pair (as the vision gives)."""

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None):
        m = super().measure(image_a, image_b, counts_a=counts_a, counts_b=counts_b,
                            speed_mm_s=speed_mm_s)
        seq = self.frames[(counts_a, counts_b)].seq
        m.x_mm, m.height_um = _profile(seq)
        return m


def _plant(tmp_path, **kw):
    plant, measurer = make_plant(tmp_path, **kw)
    prof = ProfileMeasurer(measurer.frames)
    plant.service.measurement.set_factory(lambda shape: prof)
    return plant, prof


@pytest.mark.parametrize("n", [2, 399, 400, 401, 659, 5000])
def test_decimated_profile_is_small_rounded_and_keeps_the_ends(n):
    x = np.linspace(-3.0, 50.0, n) + 1.234e-5
    h = 5.0 * np.cos(x * 4.1) + 0.0449
    out = decimated_profile(x, h)
    xs, hs = np.asarray(out["x_mm"]), np.asarray(out["height_um"])
    assert xs.size == hs.size == min(n, PROFILE_MAX_POINTS)
    assert xs[0] == pytest.approx(x[0], abs=5e-4) and xs[-1] == pytest.approx(x[-1], abs=5e-4)
    assert np.all(np.diff(xs) > 0)
    assert np.allclose(xs * 1000, np.round(xs * 1000), atol=1e-6)  # 0.001 mm
    assert np.allclose(hs * 10, np.round(hs * 10), atol=1e-6)  # 0.1 um
    # every kept point is a sample of the profile (no smoothing of the marks' cusps)
    idx = np.searchsorted(x, xs - 1e-3)
    assert np.all(np.abs(h[idx] - hs) <= 0.05 + 1e-9)
    json.dumps(out)


@pytest.mark.parametrize("seed", range(12))
def test_rounded_gives_pythons_round_bit_for_bit(seed):
    """The profile's rounding in numpy (``rounded``) is the comprehension it replaced: the same
    floats (bits, signs of zero), also for values whose scaled product lands on a half."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3000))
    values = np.concatenate([
        rng.normal(0.0, 10.0 ** rng.uniform(-4, 6), n),
        (rng.integers(-10**7, 10**7, n) + 0.5) / 1000.0,  # halves of the 3rd digit
        (rng.integers(-10**6, 10**6, n) + 0.5) / 10.0,  # halves of the 1st
        rng.uniform(-1e-3, 1e-3, n),  # rounds to +-0.0
        np.array([0.0, -0.0, 2.0**40 + 0.5, -(2.0**33), 1e15 / 7]),
    ])
    for digits in (1, 3):
        new = rounded(values, digits)
        old = [round(float(v), digits) for v in values]
        assert [v.hex() for v in new] == [v.hex() for v in old]
        assert all(type(v) is float for v in new)


def test_decimated_profile_keeps_the_records_floats():
    """The record's profile is what the per-value ``round`` gave (pinned on a real-size one)."""
    x = np.arange(N_COLUMNS) / 12.5 + 1.234567e-5
    h = 3.0 * np.sin(2 * np.pi * x / 1.5) + 0.04449
    out = decimated_profile(x, h)
    idx = np.unique(np.round(np.linspace(0, x.size - 1, PROFILE_MAX_POINTS)).astype(int))
    assert out == {"x_mm": [round(float(v), 3) for v in x[idx]],
                   "height_um": [round(float(v), 1) for v in h[idx]]}


@pytest.mark.parametrize(
    "x,h",
    [([], []), ([1.0], [2.0]), ([1.0, 2.0], [1.0]), ([[1.0, 2.0]], [[1.0, 2.0]]),
     ([np.nan, np.nan, 1.0], [1.0, 2.0, 3.0])],
)
def test_decimated_profile_of_nothing_usable_is_none(x, h):
    assert decimated_profile(np.asarray(x), np.asarray(h)) is None


def test_profiles_every_nth_and_first_of_each_board_and_the_report_finds_them(tmp_path):
    async def main():
        plant, _ = _plant(tmp_path)
        await plant.start()
        svc = plant.service
        handle = svc.handle_frame
        board_len = 7  # a new board every 7 pairs

        async def boards(frame, **kw):
            return await handle(replace(frame, board_id=1 + frame.seq // board_len), **kw)

        svc.handle_frame = boards
        res = await run_for(plant, 5.0)
        await plant.close()
        assert len(res) > 3 * PROFILE_EVERY
        with QualityLog(tmp_path / "q.sqlite", create=False) as log:
            recs = log.records()
        ok = [r for r in recs if r.ok]
        expected = set()
        last_board = None
        for i, r in enumerate(ok):
            if i % PROFILE_EVERY == 0 or r.board_id != last_board:
                expected.add(r.seq)
            last_board = r.board_id
        got = {r.seq for r in recs if "profile" in r.extra}
        assert got == expected
        for r in recs:
            if "profile" not in r.extra:
                continue
            p = r.extra["profile"]
            assert len(p["x_mm"]) == len(p["height_um"]) <= PROFILE_MAX_POINTS
            x, h = _profile(r.seq)
            assert p["x_mm"][0] == pytest.approx(x[0], abs=5e-4)
            assert p["x_mm"][-1] == pytest.approx(x[-1], abs=5e-4)
            assert len(record_to_json(r)) < 16000  # records stay small
        newest = max(got)
        found = last_profile(recs)
        assert found is not None and found[0].seq == newest

    asyncio.run(main())


def test_every_record_says_run_or_safe_and_why(tmp_path):
    async def main():
        plant, _ = _plant(tmp_path)
        await plant.start()
        await run_for(plant, 2.5)
        t_down = plant.clock()
        await plant.plc_down(1.0)
        await run_for(plant, 3.0)
        await plant.close()
        with QualityLog(tmp_path / "q.sqlite", create=False) as log:
            recs = log.records()
        assert {r.extra["state"] for r in recs} == {"run", "safe"}
        for r in recs:
            reason = r.extra["safe_reason"]
            if r.extra["state"] == "run":
                assert reason is None
            else:
                assert isinstance(reason, str) and reason
        down = [r for r in recs if r.extra["state"] == "safe" and r.t_s > t_down]
        assert down and any("plc gone" in r.extra["safe_reason"] for r in down)

    asyncio.run(main())


def test_refused_feed_writes_never_enter_the_feed_loop_history(tmp_path):
    """The PLC refuses every feed change for a while: the loop keeps the feed really in force."""

    async def main():
        plant, _ = _plant(tmp_path)
        await plant.start()
        svc = plant.service
        bus = plant.direct_bus
        feed_addr = plant.regmap["feed_setpoint_mm_s"].address
        write = bus.write

        async def refusing(address, words):
            if address == feed_addr:
                raise BusRefused(4, "server device failure")
            await write(address, words)

        bus.write = refusing
        await run_for(plant, 1.0)
        assert svc.state is SafetyState.RUN
        plc_feed = plant.machine.register_values()["feed_setpoint_mm_s"]
        checked = 0
        for _ in range(100):  # the loop wants 600 mm/s; the PLC stays at 800
            res = await plant.step()
            assert svc.feed_loop.feed_mm_s == pytest.approx(plc_feed)
            assert svc.feed_setpoint_mm_s == pytest.approx(plc_feed)
            checked += sum(r.ok for r in res)
        assert checked > 5 and svc.counters["setpoint_refused"] > 10
        # reported once, not once per attempt
        assert len([e for e in svc.events if e.kind is EventKind.FEED_REFUSED]) == 1
        hist_v = np.asarray(svc.feed_loop._hist_v)
        assert np.allclose(hist_v, plc_feed)
        bus.write = write  # the PLC takes setpoints again: the loop moves the feed
        await run_for(plant, 3.0)
        feed = plant.machine.register_values()["feed_setpoint_mm_s"]
        assert feed < plc_feed - 100 and svc.feed_loop.feed_mm_s == pytest.approx(feed)
        await plant.close()

    asyncio.run(main())
