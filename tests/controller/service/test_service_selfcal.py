"""The service measures with the machine's facts and calibrates itself per board.

* :class:`controller.service.measurement.MeasurementStage` builds the vision's measurer with the
PLC's
  cutting radius and knives (again only when they change) and hands one self-calibrator per
  board to it (a fresh one for every new board);
* the records carry the roll, the calibration and the kinematic depth: on the in-process
  simulator with the realistic rig of ``config/sim.toml`` (roll, slants off the rig file,
  translucent spruce, noise) the calibrated depth is right where the uncalibrated one is not;
* ``open_service`` opens the log through ``open_quality_log`` with the configured machine id
  and creates no folder for a database URL.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from config.machine import load_machine
from controller.quality.log import QualityLog
from controller.service.measurement import MachineFacts, MeasurementStage, VisionMeasurers

SHAPE = (6, 8)


class FakeSnap:
    """The registers the facts come from."""

    def __init__(self, radius_mm=60.0, knives=4, spindle_rpm=6000.0):
        self.values = {"cutterhead_radius_mm": radius_mm, "knives": knives,
                       "spindle_rpm": spindle_rpm}

    def __getitem__(self, name):
        return self.values[name]

    @property
    def knives(self):
        return int(self.values["knives"])

    @property
    def spindle_rpm(self):
        return float(self.values["spindle_rpm"])


class FactsFactory:
    """A factory taking the machine's facts; its measurers record what they were given."""

    takes_facts = True

    def __init__(self):
        self.built = []

    def __call__(self, shape, facts=None):
        self.built.append((shape, facts))
        calls = []

        def measure(a, b, **kw):
            calls.append(kw)
            return SimpleNamespace(facts=facts, kw=kw)

        return SimpleNamespace(measure=measure, calls=calls, facts=facts)


def _frame(board_id=1, shape=SHAPE):
    return SimpleNamespace(image_a=np.zeros(shape), image_b=np.zeros(shape), counts_a=1,
                           counts_b=2, speed_mm_s=600.0, board_id=board_id)


def _measure(stage, frame, snap):
    error, meas = asyncio.run(stage.measure(frame, snap))
    assert error is None
    return meas


@pytest.mark.parametrize(
    "change, rebuilt",
    [
        (dict(), False),
        (dict(spindle_rpm=4500.0), False),  # not part of the set-up
        (dict(radius_mm=60.0 + 4e-4), False),  # below 1 um: the same cutterhead
        (dict(radius_mm=62.5), True),
        (dict(knives=6), True),
        (dict(radius_mm=50.0, knives=2), True),
    ],
)
def test_measurer_is_built_with_the_plcs_facts_and_again_only_when_they_change(change, rebuilt):
    factory = FactsFactory()
    stage = MeasurementStage(None, factory, threaded=False)
    first = _measure(stage, _frame(), FakeSnap())
    assert first.facts == MachineFacts(60.0, 4, 6000.0)
    snap = FakeSnap(**{"radius_mm": 60.0, "knives": 4, "spindle_rpm": 6000.0, **change})
    again = _measure(stage, _frame(), snap)
    assert len(factory.built) == (2 if rebuilt else 1)
    if rebuilt:
        assert (again.facts.radius_mm, again.facts.knives) == (snap["cutterhead_radius_mm"],
                                                                snap.knives)
        assert len(stage._measurers) == 1  # the measurer of the old facts went
    _measure(stage, _frame(), snap)  # the same facts once more: nothing built
    assert len(factory.built) == (2 if rebuilt else 1)


def test_one_calibrator_per_board_fresh_for_each_new_board():
    factory = FactsFactory()
    stage = MeasurementStage(None, factory, threaded=False)
    boards = [1, 1, 1, 2, 2, 1, 3]
    given = [_measure(stage, _frame(board_id=b), FakeSnap()).kw["calibrator"] for b in boards]
    assert all(c is given[0] for c in given)  # one object, reset in place
    changes = sum(a != b for a, b in zip(boards, boards[1:], strict=False))
    assert stage.calibrator_resets == 1 + changes
    # the calibrator of a board keeps what it learnt; a new board starts afresh
    from vision.calibration.selfcal import Calibration

    cal = stage.calibrator(3, None)
    est = Calibration(gain=0.8, gain_confidence=0.9, scatter_mm=0.2, scatter_fraction=0.5,
                      scatter_confidence=0.6, trusted=True, deblurred=False)
    cal.update(est)
    assert stage.calibrator(3, None).pairs == 1
    assert stage.calibrator(4, None).pairs == 0
    # new facts on the same board: start afresh too (another cutterhead)
    stage.calibrator(4, None).update(est)
    assert stage.calibrator(4, MachineFacts(55.0, 4, 6000.0)).pairs == 0


def test_a_factory_without_facts_gets_no_facts_and_no_calibrator():
    built = []

    class Plain:
        def measure(self, a, b, *, counts_a, counts_b, speed_mm_s=None):  # the old signature
            return SimpleNamespace(speed=speed_mm_s)

    stage = MeasurementStage(None, lambda shape: built.append(shape) or Plain(),
                             threaded=False)
    assert not stage.takes_facts
    for snap in (FakeSnap(), FakeSnap(radius_mm=40.0), None):
        assert _measure(stage, _frame(), snap).speed == 600.0
    assert built == [SHAPE]


def test_vision_factory_builds_the_measurer_with_radius_and_knives():
    from config.loading import default_path
    from config.rig import load_rig

    rig = load_rig(default_path("rig.toml"))
    factory = VisionMeasurers(rig)
    shape = (rig.camera.height or 493, rig.camera.width or 659)
    m = factory(shape, MachineFacts(62.0, 3, 5000.0))
    assert m.radius_mm == 62.0 and m.knives == 3
    off = factory(shape)
    assert off.radius_mm is None and off.knives is None


# --------------------------------------------------------------------------------------------
# the whole service on the realistic simulated rig


def test_records_carry_roll_calibration_and_kinematic_depth_on_the_realistic_rig(tmp_path):
    from planer.hil import InProcessPlant, Scenario, sim_config_for
    from tests.support.plant_support import run_for

    cfg = load_machine()
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    sim_cfg = sim_config_for(Scenario())
    cam = sim_cfg.camera
    assert cam.roll_deg != 0 and cam.slant_offset_deg != (0.0, 0.0)  # the realistic rig

    async def main():
        plant = InProcessPlant(cfg, sim_cfg, plc_transport="direct")  # default: the vision
        await plant.start()
        res = await run_for(plant, 2.5)
        status = plant.service.status()
        await plant.close()
        return res, status

    res, status = asyncio.run(main())
    with QualityLog(tmp_path / "q.sqlite", create=False) as log:
        recs = log.records()
    assert len(recs) == len(res) >= 12
    ok = [(r, fr) for r, fr in zip(recs, res, strict=True) if r.ok]
    assert len(ok) >= len(recs) - 1
    for r, _ in ok:
        assert abs(r.roll_deg - cam.roll_deg) < 0.1 and r.roll_confidence > 0.5
        assert r.calibration_state in ("applied", "untrusted")
        assert r.kinematic_depth_um is not None and r.uncalibrated_depth_um is not None
    late = ok[len(ok) // 2:]  # the board's calibration has settled
    assert all(r.calibration_state == "applied" for r, _ in late)
    true = np.array([fr.truth["depth_um"] for _, fr in late])
    depth = np.array([r.depth_um for r, _ in late])
    raw = np.array([r.uncalibrated_depth_um for r, _ in late])
    kin = np.array([r.kinematic_depth_um for r, _ in late])
    err, raw_err = np.abs(depth / true - 1), np.abs(raw / true - 1)
    assert err.max() < 0.10 and np.abs(kin / true - 1).max() < 0.05
    assert raw_err.mean() > 2 * err.mean()  # the self-calibration corrected the depth
    gains = np.array([r.calibration_gain for r, _ in late])
    assert np.all(np.abs(gains - 1) > 0.03)  # the rig is off, and the log says by how much
    # the status (OPC UA, web, serve) shows the last pair's the same way
    last = status.last_measurement
    assert last.seq == recs[-1].seq and last.calibration_state == recs[-1].calibration_state
    for name in ("roll_deg", "calibration_gain", "depth_um", "kinematic_depth_um"):
        assert getattr(last, name) == pytest.approx(getattr(recs[-1], name), rel=1e-12)
        assert status.to_dict()["last_measurement"][name] == getattr(last, name)


# --------------------------------------------------------------------------------------------
# opening the log


def _open(cfg, **kw):
    import can

    from controller.service.service import open_service

    bus = can.Bus(interface="virtual", channel=f"selfcal-{id(cfg)}")
    try:
        return open_service(cfg, can_bus=bus, threaded=False, **kw)
    except BaseException:
        bus.shutdown()
        raise


def test_open_service_stamps_the_configured_machine_id(tmp_path):
    cfg = load_machine()
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "sub" / "q.sqlite",
                                       machine_id="planer-9"))
    svc = _open(cfg)
    try:
        assert svc.log.machine_id == "planer-9" and (tmp_path / "sub").is_dir()
    finally:
        svc.close()


@pytest.mark.parametrize("where", ["config", "option"])
def test_a_database_url_creates_no_local_folder(tmp_path, monkeypatch, where):
    from tests.support.pg_support import _free_port

    monkeypatch.chdir(tmp_path)
    url = f"postgresql://planer@127.0.0.1:{_free_port()}/fleet"  # nothing listens there
    cfg = load_machine()
    kw = {}
    if where == "config":
        cfg = cfg.with_changes(log=replace(cfg.log, path=url))
    else:
        kw["log_path"] = url
    pytest.importorskip("psycopg")
    with pytest.raises(OSError, match="127.0.0.1"):
        _open(cfg, **kw)
    assert list(tmp_path.iterdir()) == []  # no stray "postgresql:" folder


# --------------------------------------------------------------------------------------------
# planer bench: the cost of the new steps


def test_vision_bench_times_orientation_and_self_calibration_as_the_service_runs_them(
        monkeypatch):
    from planer.benchmarks import vision as bench
    from vision.pipeline import Measurer

    seen = []
    users: dict[int, set[int]] = {}  # calibrator: the measurers it calibrated
    real = Measurer.measure

    def spy(self, a, b, **kw):
        seen.append((self.max_roll_deg, self.radius_mm, self.knives, kw.get("calibrator")))
        if kw.get("calibrator") is not None:
            users.setdefault(id(kw["calibrator"]), set()).add(id(self))
        return real(self, a, b, **kw)

    monkeypatch.setattr(Measurer, "measure", spy)
    monkeypatch.setattr(bench, "SIZES", ((400, 300),))
    monkeypatch.setattr(bench, "_rate", lambda fn, t, n, **kw: (fn(), 100.0)[1])
    (row,) = bench.run(quick=True)
    assert {"width", "height", "pairs_per_s", "copy_pairs_per_s", "no_roll_pairs_per_s",
            "selfcal_pairs_per_s", "remap_pairs_per_s", "cpu_ms", "selfcal_cpu_ms",
            "remap_cpu_ms", "orientation_ms", "selfcal_ms"} <= set(row)
    assert row["cpu_ms"] > 0 and row["selfcal_cpu_ms"] > 0 and row["remap_cpu_ms"] >= 0
    assert row["selfcal_ms"] == pytest.approx(row["selfcal_cpu_ms"] - row["cpu_ms"], abs=0.011)
    assert all(np.isfinite(row[k]) for k in ("cpu_ms", "orientation_ms", "selfcal_ms"))
    variants = {(roll, radius, knives, cal is not None) for roll, radius, knives, cal in seen}
    assert variants == {(5.0, None, None, False), (0.0, None, None, False),
                        (5.0, bench.SELFCAL_RADIUS_MM, bench.SELFCAL_KNIVES, True)}
    # one board: one calibrator over each variant's timed pairs (the self-calibration's, the
    # service's measurement without and with the defects)
    assert len(users) == 3 and all(len(u) == 1 for u in users.values())


def test_the_measurer_in_use_is_what_the_service_shows():
    factory = FactsFactory()
    stage = MeasurementStage(None, factory, threaded=False)
    pre = stage.measurer(SHAPE)  # set-up before the first pair: no facts yet
    assert pre.facts is None and stage.measurer(SHAPE) is pre
    used = _measure(stage, _frame(), FakeSnap()).facts
    current = stage.measurer(SHAPE)
    assert current.facts == used and current is not pre and len(factory.built) == 2
