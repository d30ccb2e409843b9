"""The service's one lifecycle (:class:`controller.runtime.ServiceRuntime`).

Its frame source (a camera gets a reader of the PLC's latches of its own; a spool none), its
teardown (every step runs, in order, whatever failed), and its start on a real service.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace
from types import SimpleNamespace

import can
import pytest

from config.machine import load_machine
from controller.runtime import RuntimeOptions, ServiceRuntime


def _capture(monkeypatch):
    import controller.runtime as fs

    got = {}

    def fake_open(frames, *, inprocess=None, latch_reader=None):
        got.update(frames=frames, latch_reader=latch_reader)
        return SimpleNamespace(close=lambda: None)

    monkeypatch.setattr(fs, "open_frame_source", fake_open)
    return got


def test_a_camera_source_gets_the_plcs_latches(monkeypatch):
    from controller.frames.camera.latches import ModbusLatchReader

    got = _capture(monkeypatch)
    cfg = load_machine()
    cfg = cfg.with_changes(frames=replace(cfg.frames, source="camera", camera_id="Fake_1"),
                           plc=replace(cfg.plc, host="127.0.0.1", port=1502, unit_id=7))
    rt = ServiceRuntime(cfg)
    rt.open_source()
    reader = rt.latch_reader
    try:
        assert isinstance(reader, ModbusLatchReader) and got["latch_reader"] is reader
        assert got["frames"] is cfg.frames
        assert reader.unit_id == 7
        assert (reader.client.comm_params.host, reader.client.comm_params.port) == (
            "127.0.0.1", 1502)
        assert all(name in reader.map for name in ("trigger_seq", "trigger_a_counts",
                                                   "trigger_b_counts", "index_latch_counts"))
    finally:
        reader.close()


def test_a_spool_source_needs_no_latch_reader(monkeypatch):
    got = _capture(monkeypatch)
    cfg = load_machine()
    assert cfg.frames.source == "spool"
    rt = ServiceRuntime(cfg)
    rt.open_source()
    reader = rt.latch_reader
    assert reader is None and got["latch_reader"] is None


def test_the_latch_reader_is_closed_when_the_camera_does_not_open(monkeypatch):
    import controller.frames.camera.latches as latches
    import controller.runtime as fs

    closed = []

    class Reader:
        def __init__(self, *a, **kw):
            pass

        def close(self):
            closed.append(True)

    def failing(frames, *, inprocess=None, latch_reader=None):
        raise OSError("camera Fake_9 not found")

    monkeypatch.setattr(latches, "ModbusLatchReader", Reader)
    monkeypatch.setattr(fs, "open_frame_source", failing)
    cfg = load_machine()
    cfg = cfg.with_changes(frames=replace(cfg.frames, source="camera", camera_id="Fake_9"))
    with pytest.raises(OSError, match="Fake_9"):
        ServiceRuntime(cfg).open_source()
    assert closed == [True]




def test_the_teardown_runs_every_step_in_order_and_raises_what_failed():
    done = []

    def step(name, fail=False):
        def run():
            done.append(name)
            if fail:
                raise OSError(f"{name} failed")
        return run

    rt = ServiceRuntime(load_machine())
    rt.service = SimpleNamespace(close=step("service", fail=True))
    rt.pool = SimpleNamespace(close=step("pool"))
    rt.attach(SimpleNamespace(close=step("source", fail=True)), then_close=step("latches"))
    with pytest.raises(OSError, match="source failed") as caught:
        rt.close()
    assert "service failed" in str(caught.value.__context__)  # the earlier failure, chained
    assert done == ["service", "pool", "source", "latches"]
    rt.close()  # idempotent: nothing runs twice
    assert done == ["service", "pool", "source", "latches"]


def test_a_bus_handed_in_is_shut_down_when_the_service_cannot_open(tmp_path):
    bus = can.Bus(interface="virtual", channel=f"rt-{id(tmp_path)}")
    cfg = load_machine()
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    rt = ServiceRuntime(cfg, log_path=blocked / "log.sqlite", can_bus=bus)
    with pytest.raises(OSError):
        asyncio.run(rt.open())
    assert rt.service is None
    with pytest.raises(can.CanOperationError):
        bus.send(can.Message(arbitration_id=1, data=b"x"))  # shut down


@pytest.mark.parametrize("bad", [dict(workers=-1), dict(min_workers=-2), dict(workers=1.5)])
def test_bad_options_are_refused_naming_the_option(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        RuntimeOptions(**bad)


def test_a_real_service_opens_runs_and_closes_once(tmp_path):
    """Opened on a virtual bus, no PLC: it runs until stopped and closes its log and bus."""
    bus = can.Bus(interface="virtual", channel=f"rt-real-{id(tmp_path)}")
    cfg = load_machine()
    cfg = cfg.with_changes(plc=replace(cfg.plc, host="127.0.0.1", port=9, timeout_s=0.05))

    async def main():
        async with ServiceRuntime(cfg, log_path=tmp_path / "log.sqlite", can_bus=bus,
                                  options=RuntimeOptions(workers=0, tune=False)) as rt:
            from controller.frames.source import QueueFrameSource

            source = rt.attach(QueueFrameSource(maxsize=2))
            stop = asyncio.Event()
            asyncio.get_running_loop().call_later(0.3, stop.set)
            await rt.run(stop=stop)
            return rt, source

    rt, source = asyncio.run(main())
    assert rt.service.counters["frames"] == 0
    assert (tmp_path / "log.sqlite").exists()
    with pytest.raises(can.CanOperationError):
        bus.send(can.Message(arbitration_id=1, data=b"x"))
