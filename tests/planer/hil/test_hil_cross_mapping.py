"""Machine time onto service time in the cross-process HIL: offset and rate.

The simulated clock slows itself on a loaded host; a fault's timing must still be judged
against the service's clock at the moment it happened. Synthetic results, no processes.
"""

from __future__ import annotations

import socket

import numpy as np
import pytest

from controller.service.frame_result import FrameResult
from planer.hil.cross_process import free_port, time_factor
from planer.hil.summary import _local_offset
from plant_sim.run.runner import CLOCK_KEY


def _results(rate: float, *, offset: float, delays, stamped: bool, n: int = 60,
             period: float = 0.1) -> list[FrameResult]:
    """Pairs every ``period`` machine s; the machine runs ``rate`` machine s per service s."""
    out = []
    for i, d in zip(range(n), delays, strict=False):
        ft = (i + 1) * period
        taken = offset + ft / rate  # service (host) clock at capture
        truth = {"pitch_mm": 1.5, **({CLOCK_KEY: taken} if stamped else {})}
        out.append(FrameResult(seq=i + 1, ok=True, error=None, measurement=None,
                               knife_widths_mm=(), applied=True, feed_setpoint_mm_s=600.0,
                               offsets_um=(0.0,) * 4, state="run", t_s=taken + d,
                               latency_s=0.01, truth=truth, frame_t_s=ft))
    return out


@pytest.mark.parametrize("rate", [1.0, 0.8, 0.6])
def test_time_factor_is_the_machine_rate_whatever_the_arrival_jitter(rate):
    rng = np.random.default_rng(1)
    res = _results(rate, offset=100.0, delays=rng.uniform(0.02, 0.2, 60), stamped=False)
    assert time_factor(res) == pytest.approx(rate, rel=0.03)
    assert time_factor(res[:1]) is None and time_factor([]) is None


@pytest.mark.parametrize("rate", [1.0, 0.75, 0.5])
def test_stamped_pairs_map_a_fault_exactly_despite_delays_and_a_slow_clock(rate):
    """With the simulator's stamps the offset at the fault is exact (the service's clock at
    machine time at_s), however the arrivals lag; without, it can be off by the slow-down."""
    rng = np.random.default_rng(2)
    delays = rng.uniform(0.05, 0.6, 60)  # a busy service: arrivals lag and jitter
    at_s = 3.55  # between two pairs
    exact = 100.0 + at_s / rate - at_s
    stamped = _results(rate, offset=100.0, delays=delays, stamped=True)
    assert _local_offset(stamped, at_s, 0.0) == pytest.approx(exact, abs=1e-9)
    bare = _results(rate, offset=100.0, delays=delays, stamped=False)
    est = _local_offset(bare, at_s, 0.0)
    assert est >= 100.0 + min(delays)  # a lower bound no better than the smallest delay
    if rate < 1.0:  # without stamps the slow-down over the window shows as an error
        assert abs(est - exact) > 0.05


def test_stamps_on_another_clock_are_not_used():
    """A stamp later than the pair's arrival is not on the service's clock: ignored."""
    res = _results(1.0, offset=100.0, delays=[0.1] * 60, stamped=True)
    for r in res:
        r.truth[CLOCK_KEY] += 50.0
    assert _local_offset(res, 3.0, 0.0) == pytest.approx(100.1, abs=1e-9)


def test_free_port_is_free_to_listen_on():
    port = free_port()
    assert 1024 <= port <= 65535
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", port))


def test_gap_and_latency_statistics():
    from planer.hil.cross_process import _command_gaps, gap_stats_ms, latency_stats_ms

    times = [0.0, 0.02, 0.04, 0.16, 0.18]  # one gap of 120 ms
    g = gap_stats_ms(times)
    assert g["n"] == 4 and g["max"] == pytest.approx(120.0) and g["over_100"] == 1
    assert g["p50"] == pytest.approx(20.0) and gap_stats_ms([1.0]) is None
    lat = latency_stats_ms([0.001] * 99 + [0.05])
    assert lat["p50"] == 1.0 and lat["max"] == 50.0 and lat["n"] == 100
    assert latency_stats_ms([]) is None
    lines = ["t=1.00 s  rtf=1.00  can rx=5 tx=9 dropped=0  command gap max=22 ms",
             "ready", "t=2.00 s  ...  command gap max=130 ms", "command gap max=?? ms"]
    assert _command_gaps(lines) == {"max": 130.0, "over_100": 1, "lines": 2}
    assert _command_gaps(["ready"]) is None
