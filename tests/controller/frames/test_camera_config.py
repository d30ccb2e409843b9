"""Camera settings from the machine file, and their checks (no camera needed)."""

from __future__ import annotations

import pytest

from config.machine import machine_from_dict
from controller.frames.camera.device import CameraSettings
from controller.frames.camera.latches import parse_host_port
from controller.frames.camera.source import settings_from_config
from core.errors import ConfigError


def test_frames_camera_keys_load():
    cfg = machine_from_dict({"frames": {
        "source": "camera", "camera_id": "Fake_1", "exposure_us": 250.0, "gain_db": 3.0,
        "trigger_source": "Software", "packet_size": 8192, "image_width": 659,
        "image_height": 493}})
    f = cfg.frames
    assert (f.source, f.camera_id, f.exposure_us, f.gain_db, f.trigger_source,
            f.packet_size) == ("camera", "Fake_1", 250.0, 3.0, "Software", 8192)
    s = settings_from_config(f)
    assert (s.width, s.height, s.exposure_us, s.gain_db, s.packet_size) == (659, 493, 250.0,
                                                                            3.0, 8192)


@pytest.mark.parametrize(("table", "key"), [({"packet_size": -1}, "frames.packet_size"),
                                            ({"gain_db": -2.0}, "frames.gain_db"),
                                            ({"camera_id": 5}, "frames.camera_id"),
                                            ({"source": "usb"}, "frames.source")])
def test_bad_camera_keys_name_the_key(table, key):
    with pytest.raises(ConfigError, match=key):
        machine_from_dict({"frames": table})


class _RigCamera:
    width, height, exposure_ms = 640, 480, 0.2


def test_rig_size_and_exposure_win():
    f = machine_from_dict({"frames": {"image_width": 659, "image_height": 493}}).frames
    s = settings_from_config(f, rig_camera=_RigCamera())
    assert (s.width, s.height) == (640, 480) and s.exposure_us == pytest.approx(200.0)


def test_no_size_is_an_error_naming_the_keys():
    f = machine_from_dict({"frames": {"image_width": 0, "image_height": 0}}).frames
    with pytest.raises(ValueError, match="image_width"):
        settings_from_config(f)


@pytest.mark.parametrize(("kw", "name"), [({"width": 0}, "width"),
                                          ({"pixel_format": "Mono16"}, "pixel_format"),
                                          ({"trigger_source": "Line9"}, "trigger_source"),
                                          ({"trigger_activation": "Both"}, "trigger_activation"),
                                          ({"exposure_us": -1.0}, "exposure_us"),
                                          ({"packet_size": 100_000}, "packet_size"),
                                          ({"buffers": 1}, "buffers")])
def test_camera_settings_checks_name_the_field(kw, name):
    base = {"width": 659, "height": 493}
    base.update(kw)
    with pytest.raises(ValueError, match=name):
        CameraSettings(**base)


@pytest.mark.parametrize(("text", "want"), [("127.0.0.1:5020", ("127.0.0.1", 5020)),
                                            ("plc.local", ("plc.local", 502)),
                                            ("[::1]:502", ("[::1]", 502))])
def test_parse_host_port(text, want):
    assert parse_host_port(text) == want


@pytest.mark.parametrize("text", ["host:0", "host:x", ":502", "host:70000"])
def test_parse_host_port_refuses(text):
    with pytest.raises(ValueError, match="--plc"):
        parse_host_port(text)


class _Reply:
    def __init__(self, registers):
        self.registers = registers

    def isError(self):  # noqa: N802 - pymodbus' name
        return False


def test_latch_reader_decodes_the_latch_block(monkeypatch):
    from controller.frames.camera.latches import ModbusLatchReader
    from protocol.registers import RegisterMap

    values = {"trigger_a_counts": 2**32 - 5, "trigger_b_counts": 27, "trigger_seq": 65535,
              "index_latch_counts": 123456, "board_id": 9, "board_position_mm": 250.5,
              "feed_actual_mm_s": 800.0, "counts_per_mm": 20.0}
    words = RegisterMap.load().encode_block(values)
    reader = ModbusLatchReader("127.0.0.1", 1, clock=lambda: 42.0)
    first, count = reader._first, reader._count
    reader.client.connect = lambda: True
    monkeypatch.setattr(type(reader.client), "connected", property(lambda self: True))
    reader.client.read_holding_registers = lambda a, count, device_id: _Reply(
        words[a:a + count])
    latch = reader()
    assert (first, count) == (10, 24)
    assert (latch.seq, latch.counts_a, latch.counts_b, latch.index_latch_counts,
            latch.board_id, latch.board_position_mm, latch.speed_mm_s, latch.counts_per_mm,
            latch.t_s) == (65535, 2**32 - 5, 27, 123456, 9, 250.5, 800.0, 20.0, 42.0)


def test_latch_reader_without_plc_gives_none():
    from controller.frames.camera.latches import ModbusLatchReader

    reader = ModbusLatchReader("127.0.0.1", 1, timeout_s=0.2)  # nothing listens on port 1
    try:
        assert reader() is None and reader.errors == 1
    finally:
        reader.close()
