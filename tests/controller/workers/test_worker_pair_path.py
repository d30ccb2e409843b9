"""The worker's per-pair path in its leaner forms, pinned to the forms they replace.

Each pair's reply arrays go straight into the pair's slot (:func:`_pack_into_slot`: no
concatenated copy first), the messages are framed from the C pickler's bytes
(:func:`_framed`), the calibrator's and the measurement's class tests are made once per class:
each must give what the two steps, ``ForkingPickler`` and the per-pair tests gave, on random
inputs.
"""

from __future__ import annotations

import dataclasses
import pickle
import struct
from dataclasses import dataclass
from multiprocessing.reduction import ForkingPickler
from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.service.measurement import MachineFacts
from controller.workers.process import (
    RollChain,
    _cal_state,
    _framed,
    _pack,
    _pack_into_slot,
    _Packed,
)
from tests.support.worker_forms import _blob_into_slot
from vision.calibration.selfcal import Calibration, SelfCalibrator


@dataclass(frozen=True)
class _Meas:
    x_mm: np.ndarray
    pitch_mm: float
    widths_mm: np.ndarray
    counts: np.ndarray  # not float64: stays as it is
    note: str = "m"
    knife_mm: np.ndarray | None = None
    calibration: Calibration | None = None


_floats = st.lists(st.floats(allow_nan=True, width=64), max_size=40).map(
    lambda v: np.asarray(v, dtype=np.float64))


def _meas_strategy() -> st.SearchStrategy:
    return st.builds(
        _Meas, x_mm=_floats, pitch_mm=st.floats(), widths_mm=_floats,
        counts=st.lists(st.integers(-5, 5), max_size=4).map(lambda v: np.asarray(v, np.int32)),
        knife_mm=st.none() | _floats | st.lists(st.floats(-1e6, 1e6), max_size=9).map(
            lambda v: np.asarray(v, dtype=np.float32)),
        calibration=st.none() | st.builds(Calibration, gain=st.floats(0.1, 3.0)))


def _same_packed(a, b) -> None:
    assert type(a) is type(b)
    if type(a) is not _Packed:
        assert a is b
        return
    assert a.cls is b.cls and a.names == b.names and a.lengths == b.lengths
    assert list(a.state) == list(b.state)
    for k, v in a.state.items():
        w = b.state[k]
        if isinstance(v, np.ndarray):
            assert w.dtype == v.dtype and w.tobytes() == v.tobytes()
        else:
            assert pickle.dumps(w) == pickle.dumps(v)  # NaN for NaN
    assert (a.blob is None) == (b.blob is None)
    if a.blob is not None:
        assert a.blob.tobytes() == b.blob.tobytes()


@settings(max_examples=120, deadline=None)
@given(meas=_meas_strategy(), offset=st.integers(0, 64).map(lambda n: 8 * n),
       room=st.integers(0, 1200))
def test_arrays_straight_into_the_slot_are_the_two_steps(meas, offset, room):
    old_buf, new_buf = bytearray(b"\xa5" * 2048), bytearray(b"\xa5" * 2048)
    room = min(room, len(old_buf) - offset)
    old = _blob_into_slot(_pack(meas), old_buf, offset, room)
    new = _pack_into_slot(meas, new_buf, offset, room)
    _same_packed(old, new)
    assert old_buf == new_buf  # the slot's bytes too, beyond the arrays untouched
    if type(new) is _Packed and new.blob is None:
        n = sum(new.lengths)
        blob = np.ndarray((n,), np.float64, buffer=new_buf, offset=offset).copy()
        back, ref = new.unpack(blob), old._replace(blob=blob).unpack()
        assert list(vars(back)) == list(vars(ref))
        for k, v in vars(ref).items():
            got = getattr(back, k)
            if isinstance(v, np.ndarray):
                assert got.dtype == v.dtype and got.tobytes() == v.tobytes()
            else:
                assert pickle.dumps(got) == pickle.dumps(v)


def test_what_is_not_a_plain_dataclass_goes_as_it_is_into_no_slot():
    buf = bytearray(4096)
    for meas in (SimpleNamespace(x_mm=np.zeros(3), slope=np.zeros(3)), ("a", "tuple"), None,
                 _Meas(np.zeros(3), 1.0, np.zeros(2, np.float32), np.zeros(1, int))):
        assert _pack_into_slot(meas, buf, 0, 4096) is meas
    assert buf == bytearray(4096)


def _old_framed(obj) -> bytes:
    body = ForkingPickler.dumps(obj)
    if len(body) > 0x7FFFFFFF:
        return struct.pack("!i", -1) + struct.pack("!Q", len(body)) + bytes(body)
    return struct.pack("!i", len(body)) + bytes(body)


_plain = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12)
    | st.binary(max_size=40),
    lambda inner: st.tuples(inner, inner) | st.lists(inner, max_size=4).map(tuple),
    max_leaves=12)


@settings(max_examples=150, deadline=None)
@given(ticket=st.integers(1, 2**40), counts=st.integers(0, 2**31), speed=st.floats(),
       radius=st.floats(5, 500), knives=st.integers(1, 8), rest=_plain,
       roll=st.none() | st.just(()) | st.tuples(st.floats(), st.floats())
       | st.builds(RollChain, st.integers(1, 99), st.booleans()),
       image=st.none() | _floats)
def test_messages_are_framed_as_connection_send_frames_them(ticket, counts, speed, radius,
                                                            knives, rest, roll, image):
    cal = SelfCalibrator()
    where = (("shm", "psm_0123abcd", 649774 * 3, (493, 659), "|u1") if image is None
             else ("pickled", image, image))
    job = ("job", ticket, where, counts, counts + 7, speed,
           MachineFacts(radius_mm=radius, knives=knives, spindle_rpm=6000.0),
           *_cal_state(cal), roll, 2)
    for msg in (job, ("slotted", (ticket, ticket + 1)), ("fault", ticket, "ValueError: x"),
                ("done", ticket, None, rest, (Calibration(gain=1.5),), 0.002, None), rest):
        assert _framed(msg) == _old_framed(msg)


def _old_cal_state(cal):
    cls = type(cal)
    state = getattr(cal, "__dict__", None)
    if (state is None or hasattr(cls, "__setstate__") or hasattr(cls, "__slots__")
            or cls.__reduce_ex__ is not object.__reduce_ex__
            or cls.__reduce__ is not object.__reduce__):
        return cal, None
    values = []
    arrays = []
    for v in state.values():
        t = type(v)
        if t is np.ndarray and v.ndim == 1 and v.dtype == np.float64:
            arrays.append(len(values))
            v = tuple(v.tolist())
        elif not (t in (float, int, bool, str, type(None))
                  or (t is tuple and all(type(x) in (float, int, bool, str, type(None))
                                         for x in v))):
            return cal, None
        values.append(v)
    return pickle.dumps((cls, tuple(state), tuple(arrays))), tuple(values)


class _Slotted:
    __slots__ = ("a",)

    def __init__(self) -> None:
        self.a = 1.0


@dataclass
class _WithState:
    a: float = 1.0

    def __setstate__(self, state):  # pragma: no cover - never unpickled here
        self.__dict__.update(state)


@settings(max_examples=80, deadline=None)
@given(estimates=st.lists(st.builds(Calibration, gain=st.floats(0.05, 20.0),
                                    gain_confidence=st.floats(0.0, 1.0)), max_size=6),
       extra=st.none() | _floats | st.just([1.0]) | st.just(np.zeros((2, 2))))
def test_the_calibrators_values_are_as_before(estimates, extra):
    cal = SelfCalibrator()
    for est in estimates:
        cal.update(est)
    if extra is not None:
        cal.extra = extra  # an array sent as a tuple, a list or a 2-D array: as it is
    for obj in (cal, _Slotted(), _WithState(), SimpleNamespace(a=1.0), 3.0):
        old, new = _old_cal_state(obj), _cal_state(obj)
        assert pickle.dumps(old[1]) == pickle.dumps(new[1])  # NaN for NaN
        if old[1] is None:
            assert new[0] is obj
        else:
            assert pickle.loads(old[0]) == pickle.loads(new[0])
    assert dataclasses.is_dataclass(_WithState)


@settings(max_examples=80, deadline=None)
@given(meas=_meas_strategy(), in_slot=st.booleans())
def test_a_packed_reply_pickled_as_names_once_and_values_is_the_same_packed(meas, in_slot):
    packed = _pack(meas)
    if type(packed) is not _Packed:
        return
    if in_slot:
        packed = packed._replace(blob=None)
    first, second = (pickle.loads(pickle.dumps(packed)) for _ in range(2))
    _same_packed(packed, first)
    _same_packed(packed, second)
    assert first.state is not second.state  # each reply its own fields
    # the names go once, as one bytes object: the same bytes for every reply of the class
    assert pickle.dumps(packed).count(b"widths_mm") == 1
