"""A nicked knife in closed loop: told within 0.5 m of board of the camera first seeing it.

The ``knife_nick`` scenario (config/hil.toml, config/sim_nick.toml): board 1 is clean, board 2
is cut by a knife notched over 1-2 mm of its edge, its marks leaving a ridge along the board.
The service looks for planing defects on every pair (``defects = true``) and tells the nick as
``KNIFE_CHIPPED`` (``cause`` "nick"); the distance is measured from the first pair whose
rendered board carries the nick (the simulator's truth) to the pair it was told on. In-process
HIL, real vision on rendered images, simulated time.
"""

from __future__ import annotations

import asyncio

from controller.service.events import EventKind
from planer.hil import load_scenario
from planer.hil.in_process import InProcessHil

HALF_METRE_MM = 500.0


def _nicked(r) -> bool:
    return any(d.get("kind") == "knife_nick" for d in (r.truth or {}).get("defects", ()))


def test_a_nicked_knife_is_told_within_half_a_metre_of_the_camera_seeing_it(tmp_path):
    sc = load_scenario("knife_nick")
    assert sc.defects is True
    hil = InProcessHil(sc, log_path=tmp_path / "hil.sqlite")
    summary = asyncio.run(hil.run())
    service = hil.service
    travel = {m["seq"]: m["board_travel_mm"] for m in summary["measurements"]}

    told = [e for e in service.events if e.kind is EventKind.KNIFE_CHIPPED]
    assert len(told) == 1, [e.text for e in told]  # one nick, told once
    nick = told[0].data
    assert nick["cause"] == "nick" and nick["knife"] is None and nick["ridge_um"] > 0
    first = next(r for r in service.results if _nicked(r))  # the camera sees it first
    assert not any(_nicked(r) for r in service.results if r.seq < first.seq)
    assert nick["seq"] >= first.seq  # never before the board that carries it
    distance_mm = travel[nick["seq"]] - travel[first.seq]
    assert 0.0 <= distance_mm <= HALF_METRE_MM, distance_mm
    # counted in the summary, shown in the status (the page and OPC UA read it)
    assert summary["alerts"]["knife_chipped"] == 1
    assert summary["alerts"]["chips"][0]["cause"] == "nick"
    assert service.status().alerts["knife_chipped"]["y_mm"] == nick["y_mm"]
    assert service.counters["knife_chips"] == 1
    assert summary["passed"], summary["checks"]
    print(f"knife nick told {distance_mm:.0f} mm of board after the camera first saw it "
          f"(pair {first.seq} -> {nick['seq']})")
