"""The operator page's data: service snapshots, events and pair results as plain JSON.

Pure functions (:func:`result_json`, :func:`event_json`, :func:`status_json`,
:func:`mark_knives`) turn what the service reports into JSON without NaN, and :class:`LiveView`
keeps the latest of each plus a short history, thread-safely. In ``planer serve`` and
``planer hil`` the servers' process holds it, fed the JSON (``take_status``, ``take_result``,
``take_event``) that :mod:`controller.edge.feed` computes beside the service;
:meth:`LiveView.follow` feeds it from a service in the same process (tests, tools).
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from controller.quality.schema import QualityClass
from controller.service.events import ServiceEvent
from controller.service.frame_result import FrameResult
from controller.service.status import ServiceStatus
from controller.web.board_strip import defect_fields_json
from controller.web.head_live import HeadLive

__all__ = [
    "PROFILE_MAX_POINTS",
    "LiveView",
    "event_json",
    "knife_match_margin",
    "mark_knives",
    "result_json",
    "status_json",
]

_log = logging.getLogger(__name__)

PROFILE_MAX_POINTS = 600
"""Most profile samples sent to the page per pair (samples, not averages: cusps stay sharp)."""


def _num(v: Any, digits: int | None = None) -> float | None:
    """A finite float (rounded to ``digits``) or ``None``."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    if not math.isfinite(f):
        return None
    return round(f, digits) if digits is not None else f


def _nums(values: Any, digits: int | None = None) -> list[float | None]:
    if values is None:
        return []
    return [_num(v, digits) for v in np.asarray(values, dtype=float).ravel()]


def _alignment_errors(w: np.ndarray, kw: np.ndarray) -> np.ndarray:
    """Squared width mismatch for each cyclic phase ``k0`` (inf where nothing compares)."""
    z = kw.size
    i = np.arange(w.size)
    errs = np.full(z, math.inf)
    for k0 in range(z):
        ref = kw[(k0 - i) % z]
        ok = np.isfinite(ref) & np.isfinite(w)
        if ok.any():
            errs[k0] = float(np.sum((w[ok] - ref[ok]) ** 2))
    return errs


def mark_knives(widths_mm: Sequence[float], knife_widths_mm: Sequence[float]) -> list[int]:
    """Which knife cut each mark, from the widths: the best cyclic alignment.

    Marks along the image (increasing ``x``) were cut by knives in reverse turn (a later pass
    lies further upstream), so mark ``i`` has knife ``(k0 - i) mod Z``; ``k0`` is chosen so the
    marks' widths best match the service's per-knife widths (least squares, NaN knives
    ignored; the lowest ``k0`` on a tie). Once the loop has made the widths equal, the match
    is ambiguous (see :func:`knife_match_margin`).

    Parameters
    ----------
    widths_mm : sequence of float, shape (m,)
        Width of each complete mark in image order, mm.
    knife_widths_mm : sequence of float, shape (Z,)
        Mean width per knife (the service's attribution), mm; NaN for a knife without marks.

    Returns
    -------
    list of int, length m
        Knife of each mark (empty when ``Z`` or ``m`` is 0).
    """
    w = np.asarray(widths_mm, dtype=float).ravel()
    kw = np.asarray(knife_widths_mm, dtype=float).ravel()
    if kw.size == 0 or w.size == 0:
        return []
    k0 = int(np.argmin(_alignment_errors(w, kw)))
    return [int(k) for k in (k0 - np.arange(w.size)) % kw.size]


def knife_match_margin(widths_mm: Sequence[float], knife_widths_mm: Sequence[float]) -> float:
    """How clearly :func:`mark_knives` found its phase: second-best over best mismatch.

    Returns
    -------
    float
        >= 1; large when one phase fits far better than every other, near 1 when the knives'
        widths are too alike to tell them apart (inf for an exact unique fit, 1 with one knife).
    """
    w = np.asarray(widths_mm, dtype=float).ravel()
    kw = np.asarray(knife_widths_mm, dtype=float).ravel()
    if kw.size < 2 or w.size == 0:
        return 1.0
    errs = np.sort(_alignment_errors(w, kw))
    if not math.isfinite(errs[1]):
        return 1.0
    return math.inf if errs[0] == 0 else float(errs[1] / errs[0])


UNAMBIGUOUS_MARGIN = 4.0
"""A width match whose :func:`knife_match_margin` is below this is reported as ambiguous."""


def _decimate(x: np.ndarray, h: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    if x.size <= max_points:
        return x, h
    idx = np.unique(np.linspace(0, x.size - 1, max_points).round().astype(int))
    return x[idx], h[idx]


def _calibration_json(cal: Any) -> dict[str, Any] | None:
    if cal is None:
        return None
    return {
        "gain": _num(getattr(cal, "gain", None), 4),
        "gain_confidence": _num(getattr(cal, "gain_confidence", None), 3),
        "scatter_mm": _num(getattr(cal, "scatter_mm", None), 4),
        "trusted": bool(getattr(cal, "trusted", False)),
        "deblurred": bool(getattr(cal, "deblurred", False)),
    }


def result_json(r: FrameResult, *, max_points: int = PROFILE_MAX_POINTS) -> dict[str, Any]:
    """One pair's result for the page (plain JSON, no NaN).

    Parameters
    ----------
    r : FrameResult
        What the service did with the pair; its ``measurement`` may be ``None`` (a failed
        pair) or any object with the vision ``Measurement``'s fields.
    max_points : int, keyword-only
        Most profile samples kept.

    Returns
    -------
    dict
        ``seq``, ``t_s`` (s), ``ok``, ``error``, ``state``, ``applied``, ``pitch_mm``,
        ``uniformity_cv``, ``depth_um``, ``confidence``, ``roll_deg``, ``roll_confidence``,
        ``calibration`` (``gain``, ``trusted``, ... or ``None``), ``knife_widths_mm`` (per
        knife, mm), ``offsets_um``, ``feed_setpoint_mm_s``, ``latency_ms``, ``counts_a``,
        ``profile`` (``x_mm``, ``height_um``, at most ``max_points`` samples, or ``None``),
        ``marks`` (each ``{"lo_mm", "hi_mm", "bottom_mm", "width_mm", "depth_um",
        "knife"}``) and ``knife_source`` (``"attribution"`` when the service named the knife of
        each mark, ``"widths"`` when inferred by :func:`mark_knives`, ``"widths-ambiguous"``
        when the knives' widths are too alike for that); the board and the planing defects:
        ``board_id``, ``board_position_mm``, ``defects``, ``grade``, ``grade_reason``,
        ``frame_centre_x_mm`` (:func:`controller.web.board_strip.defect_fields_json`).
    """
    m = r.measurement
    pitch = r.reported_pitch_mm
    out: dict[str, Any] = {
        "seq": int(r.seq),
        "t_s": _num(r.t_s, 4),
        "ok": bool(r.ok),
        "error": r.error,
        "state": r.state,
        "applied": bool(r.applied),
        "pitch_mm": _num(pitch, 5),
        "uniformity_cv": _num(r.reported_uniformity_cv, 5) if r.ok else None,
        "depth_um": _num(getattr(m, "depth_um", None), 3) if r.ok else None,
        "confidence": _num(getattr(m, "confidence", None), 3),
        "roll_deg": _num(getattr(m, "roll_deg", None), 3),
        "roll_confidence": _num(getattr(m, "roll_confidence", None), 3),
        "calibration": _calibration_json(getattr(m, "calibration", None)),
        "knife_widths_mm": _nums(r.knife_widths_mm, 5),
        "offsets_um": _nums(r.offsets_um, 3),
        "feed_setpoint_mm_s": _num(r.feed_setpoint_mm_s, 2),
        "latency_ms": _num(r.latency_s * 1e3, 2),
        "counts_a": int(r.counts_a),
        "profile": None,
        "marks": [],
        "knife_source": None,
        **defect_fields_json(r),
    }
    if m is None:
        return out
    try:
        x = np.asarray(m.x_mm, dtype=float).ravel()
        h = np.asarray(m.height_um, dtype=float).ravel()
        if x.shape == h.shape and x.size >= 2:
            xd, hd = _decimate(x, h, max_points)
            out["profile"] = {"x_mm": _nums(xd, 4), "height_um": _nums(hd, 2)}
    except (AttributeError, TypeError, ValueError):
        pass
    try:
        widths = np.asarray(m.mark_widths_mm, dtype=float).ravel()
        cusps = np.asarray(m.cusps_mm, dtype=float).ravel()
        bottoms = np.asarray(m.bottoms_mm, dtype=float).ravel()
        depths = np.asarray(getattr(m, "mark_depths_um", widths * np.nan), dtype=float).ravel()
    except (AttributeError, TypeError, ValueError):
        return out
    n = widths.size
    if cusps.size != n + 1 or bottoms.size != n:
        return out
    named = r.passes.get("knife")
    if isinstance(named, (list, tuple)) and len(named) == n:
        knives, out["knife_source"] = [int(k) for k in named], "attribution"
    elif len(r.knife_widths_mm):
        knives = mark_knives(widths, r.knife_widths_mm)
        clear = knife_match_margin(widths, r.knife_widths_mm) >= UNAMBIGUOUS_MARGIN
        out["knife_source"] = "widths" if clear else "widths-ambiguous"
    else:
        knives = [None] * n
    out["marks"] = [
        {
            "lo_mm": _num(cusps[i], 4),
            "hi_mm": _num(cusps[i + 1], 4),
            "bottom_mm": _num(bottoms[i], 4),
            "width_mm": _num(widths[i], 5),
            "depth_um": _num(depths[i], 3) if depths.size == n else None,
            "knife": knives[i],
        }
        for i in range(n)
    ]
    return out


def event_json(e: ServiceEvent) -> dict[str, Any]:
    """One service event for the page: ``t_s``, ``kind``, ``text`` (and ``reason``)."""
    d = e.to_dict()
    d["t_s"] = _num(d.get("t_s"), 4)
    return d


def status_json(s: ServiceStatus) -> dict[str, Any]:
    """The service snapshot for the page (:meth:`ServiceStatus.to_dict`, no NaN)."""
    return s.to_dict()


class LiveView:
    """The latest state of the service for the operator page; thread-safe.

    A single machine is one head (``status``, ``last``, ``trace``, ``board`` of the snapshot);
    a moulder (:meth:`set_heads`) adds ``heads``: one :class:`~controller.web.head_live.
    HeadLive` per head, the top-level keys then being the first head's.

    Parameters
    ----------
    quality_class : QualityClass, optional
        The class whose band the page draws (default: the followed service's).
    history : int, keyword-only
        Pairs kept for the along-the-board traces.
    max_events : int, keyword-only
        Events kept (newest last).
    counts_per_mm : float, keyword-only, optional
        Encoder counts per mm of board, to place the pairs along the board (default: the
        followed service's PLC snapshot; without either the traces run over time).
    """

    def __init__(self, quality_class: QualityClass | None = None, *, history: int = 400,
                 max_events: int = 50, counts_per_mm: float | None = None) -> None:
        if history < 1 or max_events < 1:
            raise ValueError("history and max_events must be >= 1")
        self._lock = threading.Lock()
        self._history = history
        self._main = HeadLive(history, quality_class=quality_class, counts_per_mm=counts_per_mm)
        self._heads: dict[str, HeadLive] = {}
        self._machine: dict[str, Any] | None = None
        self._events: deque[dict[str, Any]] = deque(maxlen=max_events)
        self._version = 0
        self.changed = threading.Condition(self._lock)
        """Notified on every change (the server's streams wait on it)."""

    @property
    def _qc(self) -> QualityClass | None:
        return self._main.qc

    @property
    def _counts_per_mm(self) -> float | None:
        return self._main.counts_per_mm

    @property
    def version(self) -> int:
        """Increases with every change."""
        with self._lock:
            return self._version

    def _bump(self) -> None:
        self._version += 1
        self.changed.notify_all()

    def _head(self, head: str | None) -> HeadLive:
        """The head's part (``None``: the single machine's); an unannounced head is added."""
        if head is None or (not self._heads and head == "main"):
            return self._main
        part = self._heads.get(head)
        if part is None:
            part = self._heads[head] = HeadLive(self._history, config={"name": head})
        return part

    def set_heads(self, heads: Sequence[dict[str, Any]]) -> None:
        """A moulder's heads in order: the page shows one tab per head from now on.

        Each a dict: ``name``, ``face``, ``knives``, ``rpm``, ``rpm_min``, ``rpm_max``,
        ``target_pitch_mm`` (:func:`controller.edge.feed.head_configs_json`).
        """
        with self._lock:
            self._heads = {str(h["name"]): HeadLive(self._history, config=dict(h))
                           for h in heads}
            self._machine = None
            self._bump()

    def take_machine(self, d: dict[str, Any]) -> None:
        """The moulder's feed coordinator: ``feed_mm_s``, ``limiting``, speed setpoints."""
        with self._lock:
            if d != self._machine:
                self._machine = dict(d)
                self._bump()

    def take_plc(self, head: str, facts: dict[str, Any]) -> None:
        """A head's measured ``spindle_rpm`` and ``knives``."""
        with self._lock:
            part = self._head(head)
            if facts != part.plc:
                part.plc = dict(facts)
                self._bump()

    def set_quality_class(self, qc: QualityClass | None, head: str | None = None) -> None:
        """Use ``qc`` for the band (``None``: none drawn) of the machine or of ``head``."""
        with self._lock:
            self._head(head).qc = qc
            self._bump()

    def set_counts_per_mm(self, counts_per_mm: float | None, head: str | None = None) -> None:
        """Encoder scale for the along-the-board axis (ignored unless finite and > 0)."""
        with self._lock:
            self._head(head).set_counts_per_mm(counts_per_mm)

    def update(self, status: ServiceStatus) -> None:
        """Take a service snapshot."""
        self.take_status(status_json(status))

    def take_status(self, d: dict[str, Any], head: str | None = None) -> None:
        """Take a service snapshot already as :func:`status_json` (of ``head``'s service)."""
        with self._lock:
            if self._head(head).take_status(d):
                self._bump()

    def result(self, r: FrameResult) -> None:
        """Take one pair's result."""
        self.take_result(result_json(r))

    def take_result(self, d: dict[str, Any]) -> None:
        """Take one pair's result already as :func:`result_json` (``board_m`` is added).

        A result with ``head`` goes to that head's part.
        """
        with self._lock:
            self._head(d.get("head")).take_result(d)
            self._bump()

    def event(self, e: ServiceEvent) -> None:
        """Take one service event."""
        self.take_event(event_json(e))

    def take_event(self, d: dict[str, Any]) -> None:
        """Take one service event already as :func:`event_json` (a head's carries ``head``)."""
        with self._lock:
            self._events.append(d)
            self._bump()

    def snapshot(self) -> dict[str, Any]:
        """Everything the page shows, as plain JSON.

        Returns
        -------
        dict
            ``version``, ``status`` (:func:`status_json` or ``None``), ``last`` (the newest
            :func:`result_json` with ``board_m``, or ``None``), ``trace`` (the recent pairs'
            ``t_s``, ``board_m``, ``pitch_mm``, ``uniformity_cv``, ``depth_um``, ...),
            ``events`` (newest last), ``quality_class`` (band limits or ``None``) and
            ``board`` (the current board's defects and grade so far, the last board's:
            :meth:`controller.web.board_strip.BoardStrip.json`). A moulder's adds ``heads``
            (per head in order: its configuration, ``plc`` and the five keys above) and
            ``machine`` (the feed coordinator's decision); the top-level five are then the
            first head's.
        """
        with self._lock:
            heads = [h.json() for h in self._heads.values()]
            first = heads[0] if heads else self._main.json()
            out = {
                "version": self._version,
                "status": first["status"],
                "last": first["last"],
                "trace": first["trace"],
                "events": list(self._events),
                "quality_class": first["quality_class"],
                "board": first["board"],
            }
            if heads:
                out["heads"] = heads
                out["machine"] = self._machine
            return out

    def wait_changed(self, version: int, timeout_s: float) -> int:
        """Block (at most ``timeout_s``) until the version differs from ``version``; return it."""
        with self._lock:
            self.changed.wait_for(lambda: self._version != version, timeout=timeout_s)
            return self._version

    def follow_once(self, service: Any, seen: dict[str, Any]) -> None:
        """Take what ``service`` has new since the last call (``seen`` keeps the positions)."""
        if seen.get("service") is not service:
            seen.clear()
            seen.update(service=service, events=0, results=0, last=None)
            if self._qc is None:
                self.set_quality_class(getattr(service, "quality_class", None))
        snap = getattr(getattr(service, "plc", None), "last", None)
        if self._counts_per_mm is None and snap is not None:
            try:
                self.set_counts_per_mm(float(snap.counts_per_mm))
            except (AttributeError, KeyError, TypeError, ValueError):
                pass
        events = getattr(service, "events", [])
        for e in events[seen["events"]:]:
            self.event(e)
        seen["events"] = len(events)
        results = getattr(service, "results", None)
        if results is not None and getattr(service, "keep_results", False):
            for r in results[seen["results"]:]:
                self.result(r)
            seen["results"] = len(results)
        else:  # the service keeps no list: its newest result
            last = getattr(getattr(service, "pipeline", None), "last", None)
            if last is not None and last is not seen["last"]:
                self.result(last)
            seen["last"] = last
        self.update(service.status())

    async def follow(self, get_service: Callable[[], Any], *, period_s: float = 0.1) -> None:
        """Follow whatever ``get_service()`` returns (``None`` until there is one).

        Runs until cancelled, every ``period_s`` seconds, on the service's event loop.
        """
        if not period_s > 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        seen: dict[str, Any] = {}
        while True:
            service = get_service()
            if service is not None:
                try:
                    self.follow_once(service, seen)
                except (AttributeError, TypeError, ValueError, KeyError, IndexError):
                    _log.exception("web: following the service failed")  # retry next period
            await asyncio.sleep(period_s)
