"""The tests' stand-in machine keeps the real machine's interface (one contract for both).

Every method of the Machine API that the PLC server, the CAN node, the runner and the in-process
register bus call exists on both with the same parameters; both expose the same registers; both
refuse a feed setpoint outside the PLC's limits and offsets beyond the stroke; both hand out
frames from ``advance``.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from config.sim import default_sim
from plant_sim.machine.machine import Machine
from protocol.frames import Frame
from protocol.registers import RegisterMap
from tests.support.fake_machine import FakeMachine

API = ("advance", "register_values", "set_feed_setpoint", "set_service_heartbeat",
       "piezo_command", "set_piezo_offsets", "piezo_status", "inject", "take_interface_events")


@pytest.fixture(scope="module")
def machines():
    return Machine(default_sim(), seed=0, render_images=False), FakeMachine()


@pytest.mark.parametrize("name", API)
def test_the_fake_has_each_method_of_the_real_one_with_its_parameters(machines, name):
    real, fake = machines
    assert callable(getattr(real, name)) and callable(getattr(fake, name))
    got = list(inspect.signature(getattr(fake, name)).parameters)
    want = list(inspect.signature(getattr(real, name)).parameters)
    assert got == want, (name, got, want)


def test_both_expose_every_register_of_the_map(machines):
    names = {r.name for r in RegisterMap.load()}
    for m in machines:
        assert names <= set(m.register_values()), type(m).__name__


@pytest.mark.parametrize("feed", [0.0, -5.0, 1e6])
def test_both_refuse_a_feed_outside_the_limits(machines, feed):
    for m in machines:
        with pytest.raises(ValueError):
            m.set_feed_setpoint(feed)


def test_both_refuse_offsets_beyond_the_stroke(machines):
    for m in machines:
        with pytest.raises(ValueError):
            m.set_piezo_offsets(np.full(m.knives, 1e3))


def test_both_hand_out_frames_as_time_goes_on(machines):
    for m in machines:
        frames = [f for _ in range(100) for f in m.advance(0.01)]
        assert frames and all(isinstance(f, Frame) for f in frames), type(m).__name__
