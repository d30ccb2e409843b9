"""Measurement stage: the vision's Measurer on one pair, and the plausibility of its result.

The measurer is built once per image shape by an injected factory (``factory(shape) ->
measurer`` with ``measurer.measure(image_a, image_b, *, counts_a, counts_b, speed_mm_s)``), so
a measurer in a worker process plugs in as another factory. A factory that says
``takes_facts = True`` (:class:`VisionMeasurers`, the service's default) is called as
``factory(shape, facts)`` with the machine's facts from the PLC's registers
(:class:`MachineFacts`: cutting radius, knives) and rebuilt only when they change; its
measurers get ``calibrator=`` too: one :class:`vision.calibration.selfcal.SelfCalibrator` per
board, reset
when the board changes (the self-calibration from the knife kinematics, ``docs/vision.md``).
In real time the call (and a build) runs in a worker thread (the heartbeats go on meanwhile), or
in worker processes (:meth:`MeasurementStage.use_workers`, :mod:`controller.workers.pool`):
then :meth:`MeasurementStage.start` hands the pair over at once and
:meth:`MeasurementStage.finish` takes the results in sequence order, folding each pair's
calibration estimates into the board's calibrator in that order. Whatever the vision raises
(:data:`VISION_ERRORS`: its ``MeasurementError`` / ``RegistrationError``, ``cv2.error``, numpy's
and Python's numerical errors) is a failed measurement with its reason, never a crash of the
service.

A measured pair is *flagged* (kept out of the loops, logged with its reason: the record's
``flag_reason``) when the vision's own checks disagree (``Measurement.flag_reason``) or when its
pitch per knife pass disagrees with the feed per pass the PLC reports
(:mod:`controller.service.pitch_check`); the error is then a
:class:`~controller.service.pitch_check.Flagged`.

A pair the vision refuses may still show planing defects (a torn board is often refused): with
``defects=True`` the measurer maps it anyway and the refusal carries them
(:func:`vision.defects.refused.surface_of`). Its error is then a
:class:`~controller.service.frame_result.Refused`, a string like
every other pair's error that carries the surface (through a worker process's pipe too), which
the pair's ``FrameResult.surface`` and quality record read.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from config.machine import PlausibilityConfig
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.service.events import exc_name
from controller.service.frame_result import Refused
from controller.service.pitch_check import (
    FIELD_HALF_MM,
    FeedHistory,
    Flagged,
    pitch_disagreement,
)
from core.errors import RegistrationError
from protocol.frames import Frame
from vision.calibration.selfcal import SelfCalibrator
from vision.defects.refused import surface_of

VISION_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,  # MeasurementError, RegistrationError, numpy's LinAlgError, bad inputs
    ArithmeticError,  # FloatingPointError, ZeroDivisionError, OverflowError
    LookupError,  # IndexError, KeyError
    TypeError,
    AttributeError,
    RuntimeError,
    MemoryError,  # a huge image
    cv2.error,
)
"""What a measurement may raise: each is a failed measurement (``measurement failed: ...``)."""


_THREAD = threading.local()  # the nice value a measuring thread was given

INLINE_MAX_S = 0.005
"""In real time a pair is measured on the event loop's own thread (no hand-off to a worker
thread and back: two thread wake-ups, 0.2-0.5 ms on a virtual machine, up to 4-5 ms when the
cores are shared) while the recent measurements (:data:`INLINE_WINDOW`) took at most this much
CPU time, s, but :data:`INLINE_SPARE` of them; the bus cycles then wait about this long at most
for a pair. Slower ones (large images), a measurer not yet built and the first
:data:`INLINE_START` pairs go to the worker thread. CPU time, not wall time: a measurement the
host's other work held up is not slow, and the worker thread would not be faster."""
INLINE_WINDOW = 8
"""Measurements whose CPU times decide whether the next is measured inline."""
INLINE_START = 3
"""Measurements in the worker thread before the first one on the event loop's thread."""
INLINE_SPARE = 1
"""Measurements of the window that may take longer than :data:`INLINE_MAX_S` (a new board's
orientation search, a cold cache) without sending the next pairs to the worker thread: a
single slow pair sent the next eight to the thread, 4-5 ms slower each, three times the
p99 of 300 pairs."""


def failure_reason(exc: BaseException) -> str:
    """The logged reason of a measurement that raised ``exc``.

    A :class:`Refused` when the refusal carries the pair's defects (the measurer looks for
    them: :func:`vision.defects.refused.surface_of`), a plain string otherwise.
    """
    first = str(exc).splitlines()[0] if str(exc) else ""
    if isinstance(exc, RegistrationError):
        text = f"registration failed: {first or exc_name(exc)}"
    elif isinstance(exc, ValueError) and first:  # MeasurementError and the vision's checks
        text = f"measurement failed: {first}"
    else:
        text = f"measurement failed: {exc_name(exc)}: {first}"
    surface = surface_of(exc)
    return text if surface is None else Refused(text, surface)


async def call_blocking(threaded: bool, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)`` in a worker thread (``threaded``) or inline."""
    if threaded:
        return await asyncio.to_thread(fn, *args, **kwargs)
    return fn(*args, **kwargs)


@dataclass(frozen=True)
class MachineFacts:
    """What the machine tells the measurement (the PLC's registers), for the vision's set-up.

    Attributes
    ----------
    radius_mm : float
        Cutting radius R of the cutterhead (``cutterhead_radius_mm``), mm.
    knives : int
        Number of knives Z (``knives``).
    spindle_rpm : float
        Spindle speed (``spindle_rpm``), rpm; not part of the measurer's set-up.
    """

    radius_mm: float
    knives: int
    spindle_rpm: float

    @classmethod
    def of(cls, snap: PlcSnapshot) -> MachineFacts:
        """The facts of a register read (one :meth:`PlcSnapshot.problem` found sound)."""
        return cls(radius_mm=float(snap["cutterhead_radius_mm"]), knives=int(snap.knives),
                   spindle_rpm=float(snap.spindle_rpm))

    @property
    def key(self) -> tuple[float, int]:
        """What a measurer is built from: ``(radius_mm to 1 um, knives)``."""
        return (round(self.radius_mm, 3), self.knives)


class VisionMeasurers:
    """The service's measurer factory: the vision's ``Measurer`` of one rig, per shape and facts.

    ``factory(shape, facts)`` builds ``vision.pipeline.Measurer(rig, shape, radius_mm=R,
    knives=Z, encoder_fallback=True, **options)`` (``facts=None``: without them, the
    self-calibration off).

    Parameters
    ----------
    rig : config.rig.Rig
        The rig.
    **options
        Further keywords of ``Measurer`` (e.g. ``flat_field``).
    """

    takes_facts = True
    """Called with the machine's facts; its measurers take ``calibrator=``."""

    def __init__(self, rig: Any, **options: Any) -> None:
        from vision.pipeline import Measurer  # imported here: not at the first pair

        self._measurer_class = Measurer
        self.rig = rig
        # A and B are triggered on one board 2 ms apart: the encoder's shift may stand in for
        # a registration the read noise defeats, when the marks confirm it (vision docs).
        self.options = {"encoder_fallback": True, **options}

    def __call__(self, shape: tuple[int, int], facts: MachineFacts | None = None) -> Any:
        """A measurer for images of ``shape`` with the machine's ``facts``."""
        kw: dict[str, Any] = dict(self.options)
        if facts is not None:
            kw.update(radius_mm=facts.radius_mm, knives=facts.knives)
        return self._measurer_class(self.rig, shape, **kw)


def _board_of(frame: Frame) -> int:
    """The pair's board id (-1 when its metadata holds none usable)."""
    try:
        return int(getattr(frame, "board_id", 0))
    except (TypeError, ValueError, OverflowError):
        return -1


def speed_of(frame: Frame, snap: PlcSnapshot) -> float:
    """Board speed of a pair: the encoder's (``frame.speed_mm_s``) or the PLC's actual, mm/s."""
    return frame.speed_mm_s if frame.speed_mm_s > 0 else snap.feed_actual_mm_s


def expected_pitch_mm(frame: Frame, snap: PlcSnapshot) -> float:
    """Board travel per knife pass from the encoder speed and the spindle, ``V / (n Z)``, mm."""
    return speed_of(frame, snap) / (snap.spindle_rpm / 60.0 * snap.knives)


@dataclass
class PendingMeasurement:
    """A pair handed to the measurement (:meth:`MeasurementStage.start`), not yet finished.

    Attributes
    ----------
    frame : Frame
        The pair.
    snap : PlcSnapshot or None
        The registers in force at its arrival.
    future : asyncio.Future or None
        The worker's :class:`~controller.workers.pool.WorkerOutcome` (``None``: measured
        in this process when finished).
    which : tuple or None
        ``(board, facts key)`` of the calibrator it was measured with (worker processes).
    measure_s : float
        Wall time of the vision's own work, s (set when finished).
    worker : int
        The worker process that measured it (-1: this process).
    finished_at : float
        ``time.perf_counter()`` when its result was back on the event loop (0: not yet).
    """

    frame: Frame
    snap: PlcSnapshot | None
    future: Any = None
    which: tuple[Any, ...] | None = None
    measure_s: float = 0.0
    worker: int = -1
    finished_at: float = 0.0


class MeasurementStage:
    """Measure pairs and judge the results' plausibility.

    Parameters
    ----------
    plausibility : PlausibilityConfig
        ``min_marks``, ``min_confidence``, ``pitch_ratio_min``, ``pitch_ratio_max``,
        ``pitch_tolerance``.
    measurer_factory : callable
        ``factory(shape) -> measurer``; called once per image shape ``(height, width)``. With
        ``takes_facts = True`` (:class:`VisionMeasurers`): ``factory(shape, facts)``, once per
        shape and :attr:`MachineFacts.key`, and the measurer gets the board's calibrator.
    threaded : bool
        Measure in a worker thread (real time) or inline (simulated time).
    """

    def __init__(
        self,
        plausibility: PlausibilityConfig,
        measurer_factory: Callable[..., Any],
        *,
        threaded: bool,
    ) -> None:
        self.plausibility = plausibility
        self.feed_history = FeedHistory()
        """The PLC's feed and spindle readings (every PLC cycle), for the pitch check."""
        self.threaded = threaded
        self._factory = measurer_factory
        self._measurers: dict[tuple[Any, ...], Any] = {}
        self._calibrator: Any = None
        self._calibrated: tuple[int, Any] | None = None  # (board, facts key) it calibrates
        self.calibrator_resets = 0
        """How often a board's calibrator was started afresh (a new board or new facts)."""
        self._pool: Any = None
        # worker processes: the board's calibrator per (board, facts key), folded in sequence
        # order at finish; the pairs in flight per key; the key handed out last
        self._masters: dict[tuple[Any, ...], SelfCalibrator] = {}
        self._in_flight: dict[tuple[Any, ...], int] = {}
        self._dispatched: tuple[Any, ...] | None = None
        self._prepared: tuple[Any, ...] | None = None
        self._facts_prepared: tuple[float, int] | None = None
        self._build_lock = threading.Lock()
        self.last_measure_s = 0.0
        """Wall time of the vision's own work on the last pair measured in this process, s."""
        self.thread_nice: int | None = None
        """Nice value of the thread measuring in real time (``None``: as started); a busy host
        then shares its cores with the pairs first
        (:func:`controller.service.latency.prioritize`)."""
        self.inline_max_s: float = INLINE_MAX_S
        """Measure on the event loop's thread while the recent measurements took at most this
        much CPU time (:data:`INLINE_MAX_S`; 0: always in the worker thread), at the loop's own
        priority (real time where granted; bounded by this limit and by the real-time guard,
        :func:`core.realtime.guard_realtime`)."""
        self._recent_s: deque[float] = deque(maxlen=INLINE_WINDOW)  # CPU times, s
        self._last_cpu_s = 0.0
        self.inline_count = 0
        """Pairs measured on the event loop's thread."""

    @property
    def takes_facts(self) -> bool:
        """Whether the factory builds measurers with the machine's facts (and a calibrator)."""
        return bool(getattr(self._factory, "takes_facts", False))

    @property
    def factory(self) -> Callable[..., Any]:
        """The measurer factory (a worker pool is started with it)."""
        return self._factory

    @property
    def workers(self) -> int:
        """Worker processes measuring (0: this process)."""
        return 0 if self._pool is None else int(self._pool.workers)

    @property
    def pool(self) -> Any:
        """The worker processes (``MeasureWorkerPool``), or ``None``."""
        return self._pool

    def use_workers(self, pool: Any) -> None:
        """Measure in worker processes from the next pair on (``None``: in this process again).

        Parameters
        ----------
        pool : MeasureWorkerPool or None
            Started with this stage's factory (the caller owns it and closes it).
        """
        self._pool = pool
        self._prepared = None

    def set_factory(self, measurer_factory: Callable[..., Any]) -> None:
        """Use another measurer factory from the next pair on (the built measurers go)."""
        self._factory = measurer_factory
        self._measurers.clear()
        self._calibrated = None

    def measurer(self, shape: tuple[int, int], facts: MachineFacts | None = None) -> Any:
        """The measurer for images of ``shape`` (built once per shape and facts).

        Without ``facts`` a factory taking them gives the measurer in use for ``shape`` (built
        without facts if there is none yet).
        """
        takes = self.takes_facts
        key = (shape, facts.key if (takes and facts is not None) else None)
        with self._build_lock:  # one set-up at a time (a pair waits for one under way)
            m = self._measurers.get(key)
            if m is None and takes and facts is None:
                m = next((v for k, v in self._measurers.items() if k[0] == shape), None)
            if m is None:
                if takes:
                    m = self._factory(shape, facts)
                    # set-up work once: the measurers of facts no longer in force go
                    for old in [k for k in self._measurers if k[0] == shape]:
                        del self._measurers[old]
                else:
                    m = self._factory(shape)
                self._measurers[key] = m
        return m

    def prepare(self, snap: PlcSnapshot | None) -> None:
        """Set up for the machine's facts of a register read now, not at the next pair.

        Called with every PLC cycle's registers; only a change of the cutting radius or the
        knives does anything: the measurers of the image shapes in use are built for them (in
        a background thread in real time, in the workers with worker processes), so the pair
        after a start or a change does not wait 20-60 ms for the set-up.
        """
        self.feed_history.note(snap)
        if not self.takes_facts or snap is None:
            return
        try:
            facts = MachineFacts.of(snap)
            if facts.key == self._facts_prepared or snap.problem() is not None:
                return
        except (ValueError, TypeError, OverflowError, KeyError):
            return  # registers that make no sense: the cycle reports them
        self._facts_prepared = facts.key
        pool = self._pool
        if pool is not None:
            for shape in {k[0] for k in self._measurers} | ({pool.shape} - {None}):
                self._prepared = (shape, facts.key)
                pool.prepare(shape, facts)
            return
        for shape in {k[0] for k in list(self._measurers)}:
            if self.threaded:
                threading.Thread(target=self.measurer, args=(shape, facts), daemon=True,
                                 name="measurer-set-up").start()
            else:
                self.measurer(shape, facts)

    def calibrator(self, board_id: int, facts: MachineFacts | None) -> Any:
        """The self-calibrator of ``board_id`` (a fresh one for a new board or new facts)."""
        which = (int(board_id), None if facts is None else facts.key)
        if self._calibrator is None or self._calibrated != which:
            if self._calibrator is None:
                self._calibrator = SelfCalibrator()
            else:
                self._calibrator.reset()
            self._calibrated = which
            self.calibrator_resets += 1
        return self._calibrator

    async def measure(
        self, frame: Frame, snap: PlcSnapshot | None = None
    ) -> tuple[str | None, Any]:
        """Measure one pair: ``(None, measurement)`` or ``(reason, None)`` if the vision raised.

        Parameters
        ----------
        frame : Frame
            The pair.
        snap : PlcSnapshot, optional
            The registers in force (sound: :meth:`PlcSnapshot.problem` is ``None``); their
            facts set the measurer up when the factory takes them.
        """
        facts = None
        kwargs: dict[str, Any] = {}
        if self.takes_facts:
            if snap is not None:
                facts = MachineFacts.of(snap)
            kwargs["calibrator"] = self.calibrator(_board_of(frame), facts)
        self.last_measure_s = self._last_cpu_s = 0.0
        try:
            ready = self._inline_measurer(frame, facts) if self.threaded else None
            if ready is not None:
                meas = self._inline(ready, frame, kwargs)
            else:
                meas = await call_blocking(self.threaded, self._timed, frame, facts, kwargs)
        except VISION_ERRORS as exc:
            return failure_reason(exc), None
        finally:
            if self.threaded:
                self._recent_s.append(self._last_cpu_s)
        return None, meas

    def _inline_measurer(self, frame: Frame, facts: MachineFacts | None) -> Any:
        """The measurer to run on the event loop's thread now, or ``None`` (worker thread).

        Only one already built (no set-up under way: the build lock is free), and only once
        :data:`INLINE_START` were measured and while the last :data:`INLINE_WINDOW` took at
        most :attr:`inline_max_s` of CPU time each, but :data:`INLINE_SPARE` of them.
        """
        recent = self._recent_s
        limit = self.inline_max_s
        if (limit <= 0 or len(recent) < INLINE_START
                or sum(1 for t in recent if t > limit) > INLINE_SPARE):
            return None
        if not self._build_lock.acquire(blocking=False):
            return None  # a set-up under way (prepare): never wait for it on the loop
        try:
            shape = tuple(np.shape(frame.image_a))
            key = (shape, facts.key if (self.takes_facts and facts is not None) else None)
            return self._measurers.get(key)
        finally:
            self._build_lock.release()

    def _inline(self, measurer: Any, frame: Frame, kwargs: dict[str, Any]) -> Any:
        self.inline_count += 1
        # at the event loop's own scheduling (real time where granted): the pair's own path,
        # a few ms at most (the rule above); under the fair scheduler a busy host took the core
        # from it mid-measurement (p99 5.96-9.53 ms against 4.73-4.94 kept, load 1.6)
        return self._clocked(self._run_measurer, measurer, frame, kwargs)

    def _timed(self, frame: Frame, facts: MachineFacts | None, kwargs: dict[str, Any]) -> Any:
        nice = self.thread_nice
        if nice is not None and getattr(_THREAD, "nice", None) != nice:
            from core.realtime import lower_priority

            lower_priority(nice)  # this worker thread, once
            _THREAD.nice = nice
        return self._clocked(self.measure_now, frame, facts, kwargs)

    def _clocked(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)``, its wall time in :attr:`last_measure_s`, its CPU time noted."""
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            return fn(*args)
        finally:
            self.last_measure_s = time.perf_counter() - t0
            self._last_cpu_s = time.thread_time() - c0

    def start(self, frame: Frame, snap: PlcSnapshot | None = None) -> PendingMeasurement:
        """Start measuring one pair: handed to a worker process now, or measured at finish.

        Call in sequence order; :meth:`finish` each in the same order. With worker processes
        the pair goes out at once with the board's calibrator as the pairs finished so far
        left it (a copy), and a change of the machine's facts sets every worker up anew.
        """
        pending = PendingMeasurement(frame, snap)
        pool = self._pool
        if pool is None:
            return pending
        facts = None
        calibrator = None
        if self.takes_facts:
            if snap is not None:
                facts = MachineFacts.of(snap)
            which = (_board_of(frame), None if facts is None else facts.key)
            if which != self._dispatched:  # a new board or new facts: a fresh calibrator
                self._dispatched = which
                self._masters[which] = SelfCalibrator()
                self.calibrator_resets += 1
                self._forget_masters()
            pending.which = which
            self._in_flight[which] = self._in_flight.get(which, 0) + 1
            calibrator = self._masters[which]
            shape = tuple(np.shape(frame.image_a))
            key = (shape, None if facts is None else facts.key)
            if facts is not None and key != self._prepared:
                self._prepared = key
                pool.prepare(shape, facts)
        pending.future = pool.submit(frame, facts=facts, calibrator=calibrator)
        return pending

    async def finish(self, pending: PendingMeasurement) -> tuple[str | None, Any]:
        """The measurement of a started pair: ``(None, measurement)`` or ``(reason, None)``.

        Raises
        ------
        MeasurementWorkerError
            A worker's measurement raised what the vision never raises (a bug: the caller's
            supervisor boundary reports it).
        """
        if pending.future is None:
            out = await self.measure(pending.frame, pending.snap)
            pending.measure_s = self.last_measure_s
            return out
        try:
            outcome = await pending.future
        finally:
            which = pending.which
            if which is not None:
                self._in_flight[which] -= 1
        pending.measure_s = outcome.measure_s
        pending.worker = outcome.worker
        master = self._masters.get(which) if which is not None else None
        if master is not None:
            for estimate in outcome.estimates:  # in sequence order: as if measured here
                master.update(estimate)
        self._forget_masters()
        return outcome.error, outcome.measurement

    def _forget_masters(self) -> None:
        """Drop the calibrators of boards no pair in flight or to come will use."""
        for which in [w for w in self._masters if w != self._dispatched]:
            if self._in_flight.get(which, 0) <= 0:
                del self._masters[which]
                self._in_flight.pop(which, None)

    def measure_now(self, frame: Frame, facts: MachineFacts | None,
                    kwargs: dict[str, Any]) -> Any:
        """Build (if needed) and run the measurer (a worker thread or process in real time)."""
        return self._run_measurer(self.measurer(tuple(np.shape(frame.image_a)), facts), frame,
                                  kwargs)

    @staticmethod
    def _run_measurer(measurer: Any, frame: Frame, kwargs: dict[str, Any]) -> Any:
        return measurer.measure(
            frame.image_a,
            frame.image_b,
            counts_a=frame.counts_a,
            counts_b=frame.counts_b,
            speed_mm_s=frame.speed_mm_s if frame.speed_mm_s > 0 else None,
            **kwargs,
        )

    def implausible(self, meas: Any, frame: Frame, snap: PlcSnapshot) -> str | None:
        """Basic plausibility: not flagged, a pitch, enough marks, confidence, machine running.

        Returns ``None`` when plausible, else the reason: a :class:`Flagged` when the vision
        flagged the measurement (its ``flag_reason``), else ``"implausible: ..."``; a result
        without the expected fields is implausible too.
        """
        try:
            return self._implausible(meas, frame, snap)
        except (AttributeError, TypeError, ValueError, ArithmeticError) as exc:
            return f"implausible: {exc_name(exc)}: {exc}"

    def _implausible(self, meas: Any, frame: Frame, snap: PlcSnapshot) -> str | None:
        pl = self.plausibility
        flag = getattr(meas, "flag_reason", None)
        if flag is not None:
            return Flagged(str(flag))
        pitch = float(getattr(meas, "pitch_mm", math.nan))
        widths = np.asarray(getattr(meas, "mark_widths_mm", ()), dtype=float)
        conf = getattr(meas, "confidence", None)
        if not math.isfinite(pitch) or pitch <= 0:
            return f"implausible: pitch {pitch}"
        if widths.size < pl.min_marks:
            return f"implausible: {widths.size} complete marks, need {pl.min_marks}"
        if conf is not None and float(conf) < pl.min_confidence:
            return f"implausible: confidence {float(conf):.2f} < {pl.min_confidence}"
        n_rev_s = snap.spindle_rpm / 60.0
        if n_rev_s <= 0 or speed_of(frame, snap) <= 0:
            return "implausible: spindle or feed stopped"
        return None

    def implausible_pitch(self, pitch: float, frame: Frame, snap: PlcSnapshot) -> str | None:
        """The pitch per knife pass against ``V / (n Z)`` (``None`` if it agrees).

        First the wide ratios (``pitch_ratio_min`` .. ``pitch_ratio_max`` of the encoder's
        speed over the PLC's spindle: ``"implausible: ..."``), then, where the PLC's feed and
        spindle held steady since the pair's marks were cut, ``pitch_tolerance``
        (:func:`controller.service.pitch_check.pitch_disagreement`): a :class:`Flagged`.
        """
        pl = self.plausibility
        expected = expected_pitch_mm(frame, snap)
        ratio = pitch / expected
        if not pl.pitch_ratio_min <= ratio <= pl.pitch_ratio_max:
            return (
                f"implausible: pitch {pitch:.3f} mm vs {expected:.3f} mm expected from "
                f"V/(nZ) (ratio {ratio:.2f})"
            )
        history = self.feed_history
        history.note(snap)  # the pair's own read (the cycle's, or a fresh one)
        t_s = getattr(snap, "t_s", None)
        if t_s is None or not math.isfinite(t_s):
            return None  # no time of the read: the cutting feed is not known
        cutting = history.cutting_feed(t_s, travel_mm=snap.cutter_to_camera_mm + FIELD_HALF_MM)
        why = pitch_disagreement(pitch, cutting, tolerance=pl.pitch_tolerance)
        return None if why is None else Flagged(why)
