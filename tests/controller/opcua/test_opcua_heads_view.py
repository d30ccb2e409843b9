"""The moulder's OPC UA picture (pure): the machine's state, flags and values made of its heads'."""

from __future__ import annotations

import pytest

from controller.opcua.heads_view import MoulderView, head_path
from controller.opcua.view import MachineView, UnitMode, UnitState
from controller.service.status import ServiceStatus

HEADS = [{"name": n, "face": n, "knives": 4, "rpm": 6000.0, "target_pitch_mm": 1.5}
         for n in ("bottom", "right", "left", "top")]


def _status(state: str, *, feed: float = 600.0, missing: tuple[str, ...] = ()) -> ServiceStatus:
    return ServiceStatus(t_s=1.0, state=state, safe_reason=None if state == "run" else "x",
                         missing=missing, feed_setpoint_mm_s=feed, feed_actual_mm_s=feed,
                         offsets_um=(0.0,) * 4, amplifier_enabled=True, last_measurement=None,
                         counters={})


def _moulder() -> MoulderView:
    view = MoulderView(HEADS)
    for i, name in enumerate(view.names):  # each head its own counts
        view.update(name, _status("safe", missing=("camera",)) if name == "left"
                    else _status("run"))
        v = view.view(name)
        v._pieces_in, v._pieces_out, v._runs_total, v._runs_good = 10 + i, 5 + i, 7 * i, 3 * i
    return view


def test_the_machine_is_made_of_its_heads_values_as_served():
    view = _moulder()
    got = view.all_values()
    assert got["State/Machine/Overview/CurrentState"] == int(UnitState.ERROR)  # left's
    assert got["State/Machine/Overview/CurrentMode"] == int(UnitMode.SEMIAUTOMATIC)
    assert got["State/Machine/Flags/Error"] is True and got["State/Machine/Flags/RecipeInRun"] \
        is False  # any-of / all-of
    assert got["State/Machine/Values/AbsolutePiecesIn"] == 10  # the first head's
    assert got["State/Machine/Values/AbsolutePiecesOut"] == 8  # the last head's
    assert got["State/Machine/Values/AbsoluteRunsTotal"] == 0 + 7 + 14 + 21
    assert got["State/Machine/Values/RelativeRunsGood"] == 0 + 3 + 6 + 9
    assert got[head_path("left", "Overview/CurrentState")] == int(UnitState.ERROR)
    assert got[head_path("top", "Overview/CurrentState")] == int(UnitState.WORKING)
    assert got[head_path("right", "Values/AbsoluteRunsTotal")] == 7
    # the machine's properties say what all_values serves
    assert (view.current_state, view.current_mode) == (UnitState.ERROR, UnitMode.SEMIAUTOMATIC)
    assert {f"State/Machine/Flags/{k}": v for k, v in view.flags().items()}.items() \
        <= got.items()
    assert {f"State/Machine/Values/{k}": v for k, v in view.values().items()}.items() \
        <= got.items()


def test_all_values_asks_each_head_once_for_its_values_and_flags(monkeypatch):
    view = _moulder()
    calls = {"values": 0, "flags": 0}
    for name in calls:
        real = getattr(MachineView, name)

        def counted(self, real=real, name=name):
            calls[name] += 1
            return real(self)

        monkeypatch.setattr(MachineView, name, counted)
    first = view.all_values()
    assert calls == {"values": 4, "flags": 4}
    # every variable's path is made at its first update, not at every update
    from controller.opcua import heads_view

    made = []
    real_path = heads_view.head_path
    monkeypatch.setattr(heads_view, "head_path", lambda *a: made.append(a) or real_path(*a))
    assert view.all_values() == first and made == []


@pytest.mark.parametrize("n", [1, 2])
def test_one_or_two_heads_alike(n):
    view = MoulderView(HEADS[:n])
    got = view.all_values()
    assert got["State/Machine/Overview/CurrentState"] == int(UnitState.OFFLINE)
    assert got["State/Machine/Overview/CurrentMode"] == int(UnitMode.OTHER)
    assert got["ManufacturerSpecific/Heads"] == [h["name"] for h in HEADS[:n]]
