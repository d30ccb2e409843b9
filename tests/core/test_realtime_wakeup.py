"""The CPUs' wake-up latency request (PM QoS) of `planer serve`.

Against a stand-in device file: what is written, that the request is held while the block runs
and let go after it, and that a missing device or a request not asked for never raises.
"""

from __future__ import annotations

import os

import pytest

from config.machine import load_machine, machine_from_dict
from core.errors import ConfigError
from core.realtime import cpu_wakeup_latency


def _open_fds() -> set[str]:
    if not os.path.isdir("/proc/self/fd"):
        pytest.skip("no /proc/self/fd here")
    return set(os.listdir("/proc/self/fd"))


@pytest.mark.parametrize("max_us", [0, 25, 1000])
def test_the_request_is_the_value_as_a_32_bit_integer_held_while_the_block_runs(tmp_path,
                                                                                 max_us):
    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    before = _open_fds()
    with cpu_wakeup_latency(max_us, device=str(device)) as how:
        assert how == f"cores wake within {max_us} us"
        assert device.read_bytes() == max_us.to_bytes(4, "little", signed=True)
        held = _open_fds() - before
    assert len(held) == 1  # the device stays open for the block ...
    assert _open_fds() - before == set()  # ... and is closed after it (the request ends)


@pytest.mark.parametrize("max_us", [None, -1])
def test_not_asked_leaves_the_system_as_it_is(tmp_path, max_us):
    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    with cpu_wakeup_latency(max_us, device=str(device)) as how:
        assert how.startswith("as the system has it (not asked)")
    assert device.read_bytes() == b""


def test_a_device_that_cannot_be_opened_says_why_and_does_not_raise(tmp_path):
    missing = tmp_path / "nowhere" / "cpu_dma_latency"
    with cpu_wakeup_latency(0, device=str(missing)) as how:
        assert how.startswith("as the system has it (") and str(missing) in how


@pytest.mark.parametrize("table, value", [({}, 0), ({"cpu_latency_us": -1}, -1),
                                          ({"cpu_latency_us": 50}, 50)])
def test_the_service_cpu_latency_key_is_read(table, value):
    assert machine_from_dict({"service": table}).service.cpu_latency_us == value


@pytest.mark.parametrize("table, message", [
    ({"cpu_latency_us": -2}, "service.cpu_latency_us must be >= -1"),
    ({"cpu_latency_us": 0.5}, "service.cpu_latency_us must be an integer"),
])
def test_the_service_cpu_latency_key_is_checked_naming_it(table, message):
    with pytest.raises(ConfigError, match=message):
        machine_from_dict({"service": table})


def test_the_shipped_machine_asks_for_polling_cores():
    assert load_machine().service.cpu_latency_us == 0
