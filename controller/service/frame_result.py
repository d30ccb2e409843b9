"""What the service did with one image pair (:class:`FrameResult`, handed to ``on_result``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from vision.defects.refused import RefusedSurface


class Refused(str):
    """The error of a pair the vision refused, with the planing defects it found all the same.

    The text is the refusal's (:func:`controller.service.measurement.failure_reason`);
    :attr:`surface` the refused pair's defects, grade and the shift its map was registered at
    (:class:`vision.defects.refused.RefusedSurface`). Pickles with its surface (a worker
    process's reply).
    """

    surface: RefusedSurface | None

    def __new__(cls, reason: str, surface: RefusedSurface | None = None) -> Refused:  # noqa: D102
        obj = super().__new__(cls, reason)
        obj.surface = surface
        return obj


def refused_surface_of(error: object) -> RefusedSurface | None:
    """The defects a pair's error carries (``None``: not a refusal with defects)."""
    return error.surface if isinstance(error, Refused) else None


@dataclass(frozen=True)
class FrameResult:
    """What the service did with one image pair.

    Attributes
    ----------
    seq : int
        The pair's sequence number.
    ok : bool
        Whether the measurement succeeded and passed the plausibility checks.
    error : str or None
        Why not (``"registration failed: ..."``, ``"implausible: ..."``); a refusal that
        carries the pair's planing defects is a
        :class:`Refused` (:attr:`surface`).
    measurement : object or None
        The vision result (``x_mm``, ``pitch_mm``, ``mark_widths_mm``, ...).
    knife_widths_mm : tuple of float
        Mark width per knife and pass, mm: 0 for a knife that left no mark in the field (a
        vanished knife), NaN for a knife without a pass there.
    applied : bool
        Whether setpoints were updated from it (``ok`` and state ``RUN``).
    feed_setpoint_mm_s : float or None
        Feed setpoint in force after the pair, mm/s.
    offsets_um : tuple of float
        Piezo offsets in force after the pair, um.
    state : str
        Supervisor state after the pair (``"run"`` / ``"safe"``).
    t_s : float
        Service time when the pair arrived, s.
    latency_s : float
        Wall-clock seconds from the pair's arrival (the call of :meth:`Service.handle_frame`)
        to its setpoints on the wire (or to the decision not to send any).
    truth : dict or None
        The simulator's truth of the imaged patch (``Frame.truth``).
    counts_a : int
        Encoder counts at trigger A (board travel).
    frame_t_s : float
        Machine time of the pair (trigger A), s.
    record_id : int or None
        Id of the quality record (``None`` while it waits in the journal).
    extra : dict
        ``timing_ms`` (``plc_read_ms``, ``measure_ms``, ``control_ms``), ``safe_reason``,
        ``passes`` (the attribution's summary, :meth:`controller.service.attribution.Attributed.
        to_json`: ``vanished_knives``, ``kinematic_cv``, ``pitch_mm``, ``uniformity_cv``, ...),
        ``profile`` (a decimated profile, some pairs),
        ``plc_feed_setpoint_mm_s`` (the PLC's setpoint in force, for the record while the
        service has written none), ``board_id`` and ``board_position_mm`` (the frame's board
        and place on it: the page's board strip, OPC UA's board grade), ``frame_centre_x_mm``
        (the optical axis in image A along the feed, the rig's ``cx / px_per_mm``).
    """

    seq: int
    ok: bool
    error: str | None
    measurement: Any
    knife_widths_mm: tuple[float, ...]
    applied: bool
    feed_setpoint_mm_s: float | None
    offsets_um: tuple[float, ...]
    state: str
    t_s: float
    latency_s: float
    truth: dict[str, Any] | None = None
    counts_a: int = 0
    frame_t_s: float = 0.0
    record_id: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def refused_surface(self) -> Any:
        """The planing defects of a pair the vision refused (``None``: measured, or not looked for).

        A :class:`vision.defects.refused.RefusedSurface` (``defects``, ``grade``,
        ``grade_reason``, ``shift_px``).
        """
        return refused_surface_of(self.error)

    @property
    def surface(self) -> Any:
        """What the pair's planing defects are read from (``None``: neither).

        The measurement, or the refused pair's surface (:attr:`refused_surface`): both have
        ``defects``, ``grade``, ``grade_reason``, as
        :func:`controller.quality.defect_fields.pair_fields` reads them.
        """
        return self.measurement if self.measurement is not None else self.refused_surface

    @property
    def passes(self) -> dict[str, Any]:
        """The attribution's summary ``extra["passes"]`` (empty: marks not attributed)."""
        got = self.extra.get("passes")
        return got if isinstance(got, dict) else {}

    @property
    def vanished_knives(self) -> tuple[int, ...]:
        """Knives that left no mark in the field (another knife's cut removed it)."""
        return tuple(int(k) for k in self.passes.get("vanished_knives") or ())

    @property
    def reported_pitch_mm(self) -> float | None:
        """The pair's pitch for the record and displays, mm (``None`` unless ``ok``).

        The measured pitch (mean mark width); the board travel per knife pass when passes
        left no mark (a vanished knife: the mean of the marks found is a multiple of it).
        """
        return self._reported("pitch_mm")

    @property
    def reported_uniformity_cv(self) -> float | None:
        """The pair's uniformity for the record and displays (``None`` unless ``ok``).

        The measured CV of the marks; the kinematic CV (widths per knife and pass, a vanished
        knife counted 0) when passes left no mark.
        """
        return self._reported("uniformity_cv")

    def _reported(self, name: str) -> float | None:
        if not self.ok:
            return None
        value = self.passes.get(name)
        if value is None:
            value = getattr(self.measurement, name, None)
        try:
            return None if value is None else float(value)
        except (TypeError, ValueError):
            return None
