"""Measurement stage: the vision's Measurer on one pair, and the plausibility of its result.

The measurer is built once per image shape by an injected factory (``factory(shape) ->
measurer`` with ``measurer.measure(image_a, image_b, *, counts_a, counts_b, speed_mm_s)``), so
a measurer in a worker process plugs in as another factory. In real time the call runs in a
worker thread (the heartbeats go on meanwhile). Whatever the vision raises
(:data:`VISION_ERRORS`: its ``MeasurementError``/``RegistrationError``, ``cv2.error``, numpy's
and Python's numerical errors) is a failed measurement with its reason, never a crash of the
service.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from config.machine import PlausibilityConfig
from controller.events import exc_name
from controller.plc_client import PlcSnapshot
from core.errors import RegistrationError
from protocol.frames import Frame

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
        ``factory(shape) -> measurer``; called once per image shape ``(height, width)``.
    threaded : bool
        Measure in a worker thread (real time) or inline (simulated time).
    """

    def __init__(
        self,
        plausibility: PlausibilityConfig,
        measurer_factory: Callable[[tuple[int, int]], Any],
        *,
        threaded: bool,
    ) -> None:
        self.plausibility = plausibility
        self.threaded = threaded
        self._factory = measurer_factory
        self._measurers: dict[tuple[int, int], Any] = {}

    def set_factory(self, measurer_factory: Callable[[tuple[int, int]], Any]) -> None:
        """Use another measurer factory from the next pair on (the built measurers go)."""
        self._factory = measurer_factory
        self._measurers.clear()

    def measurer(self, shape: tuple[int, int]) -> Any:
        """The measurer for images of ``shape`` (built once per shape)."""
        m = self._measurers.get(shape)
        if m is None:
            m = self._factory(shape)
            self._measurers[shape] = m
        return m

    async def measure(self, frame: Frame) -> tuple[str | None, Any]:
        """Measure one pair: ``(None, measurement)`` or ``(reason, None)`` if the vision raised."""
        try:
            meas = await call_blocking(
                self.threaded,
                self.measurer(tuple(np.shape(frame.image_a))).measure,
                frame.image_a,
                frame.image_b,
                counts_a=frame.counts_a,
                counts_b=frame.counts_b,
                speed_mm_s=frame.speed_mm_s if frame.speed_mm_s > 0 else None,
            )
        except VISION_ERRORS as exc:
            return failure_reason(exc), None
        return None, meas

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
