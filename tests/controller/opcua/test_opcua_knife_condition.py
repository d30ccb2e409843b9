"""OPC UA: the knife condition and the chipped knives in ``ManufacturerSpecific``, read by a client.

A real asyncua server (127.0.0.1, ephemeral port) fed service snapshots and events, read by a
real asyncua client: before any offset table there is no forecast (state "", knife -1, NaN);
with one, the wear and reserve per knife, the forecast's state, line and figures; a chipped
or nicked knife is counted and named, and its event arrives as an ALARM.
"""

from __future__ import annotations

import math

import pytest

asyncua = pytest.importorskip("asyncua", reason="asyncua is not installed")


from controller.opcua.view import MANUFACTURER_NAMES, MachineView, WwEventCategory  # noqa: E402
from controller.service.events import EventKind, ServiceEvent  # noqa: E402
from controller.service.status import ServiceStatus  # noqa: E402
from tests.controller.opcua.test_opcua_server import (  # noqa: E402, F401
    feed_and_wait,
    read_manufacturer,
    served,
)

NAMES = ("BoardTravelM", "KnifeWearUmPerM", "KnifeReserveUm", "JointingState",
         "JointingForecast", "JointingDueM", "JointingDueBoards", "JointingDueH",
         "JointingKnife", "KnifeChips", "LastChippedKnife", "LastChipRunoutStepUm",
         "LastChipCause")
KC = {"board_travel_m": 21.25,
      "knives": [{"knife": k, "offset_um": o, "drift_um_per_m": d, "reserve_um": r}
                 for k, o, d, r in ((0, -4.1, -0.21, 1.9), (1, 1.3, 0.07, 4.7),
                                    (2, 1.4, 0.07, 4.6), (3, 1.4, None, 4.6))],
      "due_in_m": 50.0, "due_in_boards": 12.5, "due_in_h": 0.0231, "knife": 0,
      "text": "jointing due in 12 boards / 0.02 h at this feed (knife 0)", "state": "due",
      "t_s": 35.2}
CHIP = {"knife": 1, "cause": "runout_step", "runout_step_um": 6.02, "width_change_mm": 0.031,
        "seq": 41, "t_s": 4.1}


def _status(t_s, *, kc=None, chip=None, chips=0) -> ServiceStatus:
    return ServiceStatus(
        t_s=t_s, state="run", safe_reason=None, missing=(), feed_setpoint_mm_s=600.0,
        feed_actual_mm_s=600.0, offsets_um=(-4.1, 1.3, 1.4, 1.4), amplifier_enabled=True,
        last_measurement=None, counters=ServiceStatus.freeze({"knife_chips": chips}),
        alerts={"target_unreachable": None, "measurements_failing": None,
                "knife_chipped": chip},
        knife_condition=kc)


def _read_all(srv) -> dict:
    return read_manufacturer(srv, NAMES)


def test_the_names_are_served_with_their_types():
    assert set(NAMES) <= set(MANUFACTURER_NAMES)
    assert MANUFACTURER_NAMES["KnifeReserveUm"] == "Double[]"
    assert MANUFACTURER_NAMES["JointingKnife"] == "Int64"


def test_a_client_reads_the_knife_condition_and_the_chipped_knife(served):  # noqa: F811
    srv = served.srv
    before = _read_all(srv)  # the module's server may have had other statuses: none has a kc
    assert before["JointingState"] == "" and before["JointingKnife"] == -1
    assert math.isnan(before["JointingDueM"]) and before["LastChippedKnife"] == -1

    feed_and_wait(served, lambda: srv.update(_status(200.0, kc=KC)))
    v = _read_all(srv)
    assert v["BoardTravelM"] == 21.25
    assert v["KnifeWearUmPerM"][:3] == [-0.21, 0.07, 0.07] and math.isnan(v["KnifeWearUmPerM"][3])
    assert v["KnifeReserveUm"] == [1.9, 4.7, 4.6, 4.6]
    assert v["JointingState"] == "due" and v["JointingForecast"] == KC["text"]
    assert (v["JointingDueM"], v["JointingDueBoards"], v["JointingDueH"]) == (50.0, 12.5, 0.0231)
    assert v["JointingKnife"] == 0 and v["KnifeChips"] == 0

    feed_and_wait(served, lambda: srv.update(_status(201.0, kc=KC, chip=CHIP, chips=1)))
    v = _read_all(srv)
    assert v["KnifeChips"] == 1 and v["LastChippedKnife"] == 1
    assert v["LastChipRunoutStepUm"] == pytest.approx(6.02)
    assert v["LastChipCause"] == "runout_step"

    nick = {"knife": None, "cause": "nick", "y_mm": 0.49, "ridge_um": 12.8,
            "runout_step_um": None, "width_change_mm": None, "seq": 68, "t_s": 8.3}
    feed_and_wait(served, lambda: srv.update(_status(202.0, kc=KC, chip=nick, chips=2)))
    v = _read_all(srv)
    assert v["KnifeChips"] == 2 and v["LastChipCause"] == "nick"
    assert v["LastChippedKnife"] == -1 and math.isnan(v["LastChipRunoutStepUm"])


def test_a_chipped_knife_is_an_alarm_and_jointing_due_a_warning():
    view = MachineView()
    chipped = view.event(ServiceEvent(4.1, EventKind.KNIFE_CHIPPED, "knife 1 chipped", data=CHIP))
    due = view.event(ServiceEvent(5.0, EventKind.JOINTING_DUE, KC["text"]))
    assert chipped.category is WwEventCategory.ALARM and chipped.message_id == "knife_chipped"
    assert due.category is WwEventCategory.WARNING
