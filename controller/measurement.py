"""Measurement stage: the vision's Measurer on one pair, and the plausibility of its result.

The measurer is built once per image shape by an injected factory (``factory(shape) ->
measurer`` with ``measurer.measure(image_a, image_b, *, counts_a, counts_b, speed_mm_s)``), so
a measurer in a worker process plugs in as another factory. A factory that says
``takes_facts = True`` (:class:`VisionMeasurers`, the service's default) is called as
``factory(shape, facts)`` with the machine's facts from the PLC's registers
(:class:`MachineFacts`: cutting radius, knives) and rebuilt only when they change; its
measurers get ``calibrator=`` too: one :class:`vision.selfcal.SelfCalibrator` per board, reset
when the board changes (the self-calibration from the knife kinematics, ``docs/vision.md``).
In real time the call (and a build) runs in a worker thread (the heartbeats go on meanwhile).
Whatever the vision raises (:data:`VISION_ERRORS`: its ``MeasurementError`` /
``RegistrationError``, ``cv2.error``, numpy's and Python's numerical errors) is a failed
measurement with its reason, never a crash of the service.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from config.machine import PlausibilityConfig
from controller.events import exc_name
from controller.plc_client import PlcSnapshot
from core.errors import RegistrationError
from protocol.frames import Frame
from vision.selfcal import SelfCalibrator

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


def failure_reason(exc: BaseException) -> str:
    """The logged reason of a measurement that raised ``exc``."""
    first = str(exc).splitlines()[0] if str(exc) else ""
    if isinstance(exc, RegistrationError):
        return f"registration failed: {first or exc_name(exc)}"
    if isinstance(exc, ValueError) and first:  # MeasurementError and the vision's checks
        return f"measurement failed: {first}"
    return f"measurement failed: {exc_name(exc)}: {first}"


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
    knives=Z, **options)`` (``facts=None``: without them, the self-calibration off).

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
        self.options = dict(options)

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


class MeasurementStage:
    """Measure pairs and judge the results' plausibility.

    Parameters
    ----------
    plausibility : PlausibilityConfig
        ``min_marks``, ``min_confidence``, ``pitch_ratio_min``, ``pitch_ratio_max``.
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
        self.threaded = threaded
        self._factory = measurer_factory
        self._measurers: dict[tuple[Any, ...], Any] = {}
        self._calibrator: Any = None
        self._calibrated: tuple[int, Any] | None = None  # (board, facts key) it calibrates
        self.calibrator_resets = 0
        """How often a board's calibrator was started afresh (a new board or new facts)."""

    @property
    def takes_facts(self) -> bool:
        """Whether the factory builds measurers with the machine's facts (and a calibrator)."""
        return bool(getattr(self._factory, "takes_facts", False))

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
        m = self._measurers.get(key)
        if m is None and takes and facts is None:
            m = next((v for k, v in self._measurers.items() if k[0] == shape), None)
        if m is None:
            if takes:
                # set-up work once: the measurers of facts no longer in force go
                for old in [k for k in self._measurers if k[0] == shape]:
                    del self._measurers[old]
                m = self._factory(shape, facts)
            else:
                m = self._factory(shape)
            self._measurers[key] = m
        return m

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
        try:
            meas = await call_blocking(self.threaded, self._measure_now, frame, facts, kwargs)
        except VISION_ERRORS as exc:
            return failure_reason(exc), None
        return None, meas

    def _measure_now(self, frame: Frame, facts: MachineFacts | None,
                     kwargs: dict[str, Any]) -> Any:
        """Build (if needed) and run the measurer (in the worker thread in real time)."""
        return self.measurer(tuple(np.shape(frame.image_a)), facts).measure(
            frame.image_a,
            frame.image_b,
            counts_a=frame.counts_a,
            counts_b=frame.counts_b,
            speed_mm_s=frame.speed_mm_s if frame.speed_mm_s > 0 else None,
            **kwargs,
        )

    def implausible(self, meas: Any, frame: Frame, snap: PlcSnapshot) -> str | None:
        """Basic plausibility: a pitch, enough marks, confidence, spindle and feed running.

        Returns ``None`` when plausible, else the reason (``"implausible: ..."``); a result
        without the expected fields is implausible too.
        """
        try:
            return self._implausible(meas, frame, snap)
        except (AttributeError, TypeError, ValueError, ArithmeticError) as exc:
            return f"implausible: {exc_name(exc)}: {exc}"

    def _implausible(self, meas: Any, frame: Frame, snap: PlcSnapshot) -> str | None:
        pl = self.plausibility
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
        """The pitch per knife pass against ``V / (n Z)`` (``None`` if within the ratios)."""
        pl = self.plausibility
        expected = expected_pitch_mm(frame, snap)
        ratio = pitch / expected
        if not pl.pitch_ratio_min <= ratio <= pl.pitch_ratio_max:
            return (
                f"implausible: pitch {pitch:.3f} mm vs {expected:.3f} mm expected from "
                f"V/(nZ) (ratio {ratio:.2f})"
            )
        return None
