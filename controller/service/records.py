"""Quality records stage: one record per pair, durable, whatever happens to the log.

:class:`QualityRecords` turns each :class:`~controller.service.frame_result.FrameResult` into a
:class:`~controller.quality.log.QualityRecord` (failed pairs included, with their reason and the
setpoints in force; every ``PROFILE_EVERY``-th successful one and the first of each board with a
decimated profile) and hands it to a :class:`~controller.quality.journal.RecordSink`: the record
is in the log, or in the local journal beside it when the log cannot take it (disk full, file
locked, a value the schema refuses), and the journal is written to the log as soon as it takes
records again. Log trouble is reported once (``LOG_FAILED`` ... ``LOG_RECOVERED``) and fails the
supervisor's ``log`` condition while it lasts (no control without a record of it).

In real time (``threaded``) the record is made after the pair's setpoints went out, off the
control path, by a :class:`~controller.quality.write_ahead.WriteAheadSink`:
:meth:`QualityRecords.append` only queues it; the journal thread makes the records and appends
what queued up meanwhile to the journal with one fsync (durable: :attr:`on_stored`), and the
database thread writes them to the log, in batches, whatever time the log takes.

A pair is **handled** once its record is durable (fsync'ed to the journal, or in the log):
only then does :attr:`QualityRecords.on_handled` hear of it (the pipeline then counts it,
shows it as the last measurement and calls ``on_result``). So a pair anyone was told of has
a record that survives a SIGKILL; the setpoints never wait for the disk (they went out
before the record was made). Inline (not ``threaded``) a record is durable when
:meth:`~QualityRecords.append` returns. Nothing the
event loop does waits for the database: the log's state is read from the sink's published
snapshot. At most :data:`MAX_QUEUED` records wait for the *journal* (local disk slower than the
camera); beyond that the next pair waits for it. A log that is locked or does not answer only
holds records back in the journal (``LOG_FAILED`` is said); a log that refuses them (disk
full, a damaged file) or a journal that cannot be written fails the ``log`` condition.
"""

from __future__ import annotations

import asyncio
import math
import sqlite3
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from config.machine import MachineConfig
from controller.quality.defect_fields import BoardGrades, frame_centre_mm, pair_fields
from controller.quality.defect_report import FRAME_CENTRE_KEY
from controller.quality.journal import RecordSink, default_journal_path
from controller.quality.log import QualityClass, QualityRecord, judge, utc_iso, vision_fields
from controller.quality.schema import DEFAULT_HEAD, check_head, knife_condition_fields
from controller.quality.write_ahead import CLOSE_TIMEOUT_S, WriteAheadSink
from controller.service.events import EventKind, EventLog
from controller.service.frame_result import FrameResult
from controller.service.intake import finite_or_none, frame_metadata, int_or
from controller.service.pitch_check import flag_reason_of
from protocol.frames import Frame

PROFILE_EVERY = 10
"""Every this many successful measurements (and the first of each board) a record carries the
surface profile (``extra["profile"]``, drawn by ``planer report``)."""
PROFILE_MAX_POINTS = 800
"""Most points of a stored profile (about 6 kB of JSON)."""
MAX_QUEUED = 200
"""Records waiting for the journal thread (real time: local disk) before the next pair waits for
it (2 s of pairs at 100 pairs/s). The database never makes a pair wait."""


def decimated_profile(
    x_mm: Any, height_um: Any, *, max_points: int = PROFILE_MAX_POINTS
) -> dict[str, list[float]] | None:
    """A profile small enough for every tenth quality record: samples, rounded.

    Parameters
    ----------
    x_mm, height_um : array_like, shape (n,)
        Positions along the feed (mm) and heights (um) of the measured profile.
    max_points : int
        Most samples kept (evenly spaced in index, the first and last always; samples, not
        averages, so the marks' cusps stay sharp).

    Returns
    -------
    dict or None
        ``{"x_mm": [...], "height_um": [...]}`` rounded to 0.001 mm and 0.1 um, or ``None``
        when fewer than two finite samples of equal-length 1-D arrays are given.
    """
    try:
        x = np.asarray(x_mm, dtype=float)
        h = np.asarray(height_um, dtype=float)
    except (TypeError, ValueError):
        return None
    if x.ndim != 1 or x.shape != h.shape:
        return None
    good = np.isfinite(x) & np.isfinite(h)
    x, h = x[good], h[good]
    if x.size < 2:
        return None
    if x.size > max_points:
        idx = np.unique(np.round(np.linspace(0, x.size - 1, max_points)).astype(int))
        x, h = x[idx], h[idx]
    return {"x_mm": rounded(x, 3), "height_um": rounded(h, 1)}


def rounded(values: np.ndarray, digits: int) -> list[float]:
    """``[round(float(v), digits) for v in values]``, the same floats, for a finite float array.

    numpy's ``np.round`` (``rint(v * 10**digits) / 10**digits``) gives Python's correctly
    rounded value wherever ``v * 10**digits`` did not round onto or across a half: there both
    round the same integer and divide it alike. The few values whose scaled product lies within
    a hair of a half (or is too large for the test) are rounded by Python, so the result is
    Python's bit for bit at a numpy call's cost (800 samples: ~0.4 ms as a comprehension).

    Parameters
    ----------
    values : ndarray, shape (n,)
        Finite floats.
    digits : int
        Decimal places, >= 0.

    Returns
    -------
    list of float
    """
    scale = 10.0**digits
    y = values * scale
    k = np.rint(y)
    out = (k / scale).tolist()
    near = (np.abs(np.abs(y - k) - 0.5) <= _HALF_MARGIN) | ~(np.abs(y) < _EXACT_BELOW)
    if near.any():
        for i in np.flatnonzero(near).tolist():
            out[i] = round(float(values[i]), digits)
    return out


_HALF_MARGIN = 1e-6
"""How near a half the scaled value must lie (in units of the last digit kept) to be rounded
by Python: well above the product's rounding error (half an ulp of a value below
:data:`_EXACT_BELOW`, 1.2e-7)."""
_EXACT_BELOW = 2.0**30
"""Scaled values at or above this (or not finite) are rounded by Python."""


def quality_class_of(cfg: MachineConfig) -> QualityClass:
    """The quality class ``[quality]`` describes."""
    q = cfg.quality
    return QualityClass(
        name=q.class_name,
        target_pitch_mm=q.target_pitch_mm,
        pitch_tolerance=q.tolerance,
        uniformity_max_cv=q.uniformity_max_cv,
        depth_max_um=q.depth_max_um,
    )


class _Queued:
    """A pair waiting for its record to be durable (real time): with the write-ahead sink."""

    __slots__ = ("answered", "frame", "result", "t")

    def __init__(self, result: FrameResult, frame: Frame | None, t: float) -> None:
        self.result = result
        self.frame = frame  # dropped once the record is made (its images are not kept)
        self.t = t
        self.answered = False  # the journal's first answer taken (health, counters)


class QualityRecords:
    """Records of every pair, through a journal-backed sink into the quality log.

    Parameters
    ----------
    cfg : MachineConfig
        ``[quality]`` (target, class) and ``[log] path`` (the journal's place when ``log`` has
        no ``path``).
    log : QualityLog or None
        The quality log (``None``: nothing is recorded). Closed by :meth:`close`.
    report : EventLog
        Events and counters (``log_errors``).
    on_health : callable
        ``on_health(ok)`` when the log starts or stops failing (the supervisor's ``log``).
    threaded : bool
        Real time: records are journalled and then logged by two threads after the setpoints,
        in batches (:class:`~controller.quality.write_ahead.WriteAheadSink`); ``False``:
        written at once, in the caller's thread (:class:`RecordSink`).
    journal_path : Path, optional
        The journal; default beside the log (``<log>.journal.jsonl``; a moulder's head other
        than ``"main"``: ``<log>.<head>.journal.jsonl``).
    head : str, keyword-only
        The cutterhead whose pairs these are (a moulder's head name): on every record
        (``head``, schema version 8). Default ``"main"``, the single head.
    """

    def __init__(
        self,
        cfg: MachineConfig,
        log: Any,
        report: EventLog,
        *,
        on_health: Callable[[bool], None],
        threaded: bool,
        journal_path: Path | None = None,
        head: str = DEFAULT_HEAD,
    ) -> None:
        self.head = check_head("head", head)
        self.cfg = cfg
        self.log = log
        self.quality_class = quality_class_of(cfg)
        self._report = report
        self._on_health = on_health
        self.threaded = threaded
        self._ok_count = 0  # successful measurements so far (profile every PROFILE_EVERY-th)
        self._profile_board: int | None = None
        self._board_grades = BoardGrades()  # records are made in pair order (one thread)
        self._failing = False  # LOG_FAILED said, LOG_RECOVERED not yet
        self._unhealthy = False  # the supervisor's log condition failed by this stage
        self._rewritten = 0
        self.sink: RecordSink | None = None
        self.writer: WriteAheadSink | None = None
        if log is not None:
            if journal_path is None:
                journal_path = default_journal_path(getattr(log, "path", None) or cfg.log.path,
                                                    head=self.head)
            if threaded:
                self.writer = WriteAheadSink(log, journal_path=Path(journal_path),
                                             make=self._make, on_durable=self._durable)
                self.writer.thread_setup = self._thread_setup
            else:
                self.sink = RecordSink(log, journal_path=Path(journal_path))
        # real time: the journal thread's answers, and who waits for room
        self._answers: deque[tuple[_Queued, bool, float]] = deque()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._room: asyncio.Event | None = None
        self._unanswered = 0  # queued pairs the journal has not answered yet
        self._answered_all: asyncio.Event | None = None  # set while none is unanswered
        self.writer_nice: int | None = None
        """Nice value of the writer thread (``None``: as started)."""
        self.on_stored: Callable[[Any, float], None] | None = None
        """Called on the event loop with ``(seq, monotonic time)`` when a pair's record is
        durable (real time; for benchmarks and tests)."""
        self.on_handled: Callable[[FrameResult], None] | None = None
        """Real time: called on the event loop with a pair's result once its record is
        durable (after :attr:`on_stored`), exactly once per pair; never for a pair whose
        record was nowhere durable at :meth:`close`."""

    @property
    def defers_handling(self) -> bool:
        """Whether a pair is handled later than :meth:`append` returns (:attr:`on_handled`)."""
        return self.writer is not None

    @property
    def problem(self) -> str | None:
        """The log's trouble in one line (``None`` when healthy or not logging).

        In real time the writer's published snapshot: no lock, no I/O.
        """
        if self.writer is not None:
            return self.writer.state.problem
        return None if self.sink is None else self.sink.problem

    @property
    def pending(self) -> int:
        """Records not yet in the log (queued, in the journal, or in memory)."""
        if self.writer is not None:
            return self.writer.state.pending
        return 0 if self.sink is None else self.sink.pending

    @property
    def queued(self) -> int:
        """Records queued for the journal thread, not yet durable (real time)."""
        return 0 if self.writer is None else self.writer.queued

    @property
    def batches(self) -> int:
        """Database transactions of the writer (real time; 0 inline)."""
        return 0 if self.writer is None else int(self.writer.state.counters.get("db_batches", 0))

    def _thread_setup(self) -> None:
        """On each writer thread as it starts: the nice value asked for (``writer_nice``)."""
        if self.writer_nice is not None:
            from core.realtime import lower_priority

            lower_priority(self.writer_nice)

    def profile_of(self, meas: Any, frame: Frame) -> dict[str, list[float]] | None:
        """The decimated profile of a successful measurement if this one carries it.

        The first successful measurement of each board and every ``PROFILE_EVERY``-th one
        (counted over the run) do; ``None`` for the others or without a usable profile.
        """
        self._ok_count += 1
        board = int_or(getattr(frame, "board_id", 0), 0)
        first_of_board = board != self._profile_board
        self._profile_board = board
        if not (first_of_board or (self._ok_count - 1) % PROFILE_EVERY == 0):
            return None
        try:
            return decimated_profile(meas.x_mm, meas.height_um)
        except (AttributeError, TypeError, ValueError):
            return None

    def record_of(self, r: FrameResult, frame: Frame) -> QualityRecord:
        """The quality record of a result (never raises: odd metadata is noted, not fatal)."""
        m = r.measurement
        truth = frame.truth or {}
        meta, odd = frame_metadata(frame)
        # like with like: a pair that reports the kinematic numbers (a knife left no mark) is
        # recorded beside the truth's kinematic numbers, not the marks the truth has
        true_keys = (("pass_pitch_mm", "kinematic_cv") if r.vanished_knives
                     and "kinematic_cv" in truth else ("pitch_mm", "uniformity_cv"))
        feed = finite_or_none(r.feed_setpoint_mm_s)
        if feed is None:  # the service wrote none yet: the setpoint the PLC reported in force
            feed = finite_or_none(r.extra.get("plc_feed_setpoint_mm_s"))
        fields: dict[str, Any] = {
            **meta,
            "wall_time": utc_iso(time.time()),
            "head": self.head,
            "ok": r.ok,
            "error": r.error,
            "flag_reason": flag_reason_of(r.error),  # a flagged pair: why (schema version 5)
            "feed_setpoint_mm_s": feed,
            "piezo_offsets_um": tuple(r.offsets_um),
            "target_pitch_mm": self.cfg.quality.target_pitch_mm,
            "true_pitch_mm": finite_or_none(truth.get(true_keys[0])),
            "true_uniformity_cv": finite_or_none(truth.get(true_keys[1])),
            **knife_condition_fields(r.extra.get("knife_condition")),  # schema version 6
            "extra": {
                "state": r.state,
                "safe_reason": r.extra.get("safe_reason"),
                "applied": r.applied,
                "latency_ms": r.latency_s * 1e3,
                "timing_ms": r.extra.get("timing_ms", {}),
                "knife_widths_mm": [None if not math.isfinite(w) else w
                                    for w in r.knife_widths_mm],
                **({"frame_metadata_invalid": odd} if odd else {}),
                **({"passes": r.extra["passes"]} if "passes" in r.extra else {}),
                **({"profile": r.extra["profile"]} if "profile" in r.extra else {}),
                **({"piezo": r.extra["piezo"]} if "piezo" in r.extra else {}),
            },
        }
        if m is not None:
            fields["shift_px"] = finite_or_none(getattr(m, "shift_px", None))
            fields["confidence"] = finite_or_none(getattr(m, "confidence", None))
            # orientation and self-calibration (also on implausible pairs: diagnostics); the
            # kinematic and uncalibrated depths on successful ones
            fields.update(vision_fields(m, ok=r.ok))
            cal = getattr(m, "calibration", None)
            if cal is not None and getattr(cal, "deblurred", False):
                fields["extra"]["calibration_deblurred"] = True
        # planing defects, the pair's grade and its board's so far (schema version 7): of a
        # measured pair (flagged ones too: a defect is often why the vision's checks disagreed)
        # or of a refused one, whose defects were found all the same (FrameResult.surface)
        surface = r.surface
        if surface is not None:
            defect = pair_fields(surface)
            fields.update(defect)
            # where image A's centre is: the report places the defects on the board
            centre = r.extra.get(FRAME_CENTRE_KEY) or (frame_centre_mm(m) if m is not None
                                                       else None)
            if defect and centre is not None:
                fields["extra"][FRAME_CENTRE_KEY] = centre
            fields.update(self._board_grades.add(int_or(fields.get("board_id"), 0),
                                                 defect.get("defects"),
                                                 finite_or_none(fields.get("board_position_mm"))))
        if r.ok:
            fields.update(
                # a vanished knife: the kinematic pitch and CV, not the marks found's
                pitch_mm=finite_or_none(r.reported_pitch_mm),
                mark_widths_mm=tuple(float(w) for w in r.knife_widths_mm),
                uniformity_cv=finite_or_none(r.reported_uniformity_cv),
                depth_um=finite_or_none(getattr(m, "depth_um", None)),
            )
            try:
                fields["extra"]["marks_mm"] = [float(w) for w in m.mark_widths_mm]
                fields["passed"] = judge(fields, self.quality_class)
            except (TypeError, ValueError):
                fields["passed"] = None
        try:
            return QualityRecord(**fields)
        except (TypeError, ValueError) as exc:  # keep the pair: a record that says why
            return QualityRecord(
                **meta,
                wall_time=fields["wall_time"],
                head=self.head,
                ok=False,
                error=f"record invalid: {exc}" if r.ok else f"{r.error} (record invalid: {exc})",
                feed_setpoint_mm_s=feed,
                extra={"state": r.state, "safe_reason": r.extra.get("safe_reason"),
                       "applied": r.applied},
            )


    async def append(self, r: FrameResult, frame: Frame, t: float) -> int | None:
        """Store the pair's record durably; its id in the log, or ``None`` (journal, no log).

        In real time (``threaded``) the record is only queued for the journal thread
        (``None``; it is durable once its batch is fsync'ed to the journal, :attr:`on_stored`,
        and goes to the log after); the caller waits for nothing unless :data:`MAX_QUEUED`
        records wait for the journal already. A log that fails is reported once
        (``LOG_FAILED``; the supervisor's ``log`` condition fails when records are not durable
        or the log refuses them) and counted per record answered meanwhile (``log_errors``);
        held records go to the log, in order, as soon as it takes them again
        (``LOG_RECOVERED``).
        """
        if self.writer is not None:
            await self._enqueue(r, frame, t)
            return None
        sink = self.sink
        if sink is None:
            return None
        rec = self.record_of(r, frame)
        logged, rid = self._store(sink, rec)
        self._answered(t, r.seq, logged)
        return rid

    def _answered(self, t: float, seq: Any, logged: bool) -> None:
        self._health(t, seq)
        if not logged:
            self._report.count("log_errors")

    # ------------------------------------------------------------------ real time
    async def _enqueue(self, r: FrameResult, frame: Frame, t: float) -> None:
        """Queue a record for the journal (after the setpoints); wait only for local disk."""
        writer = self.writer
        assert writer is not None
        loop = asyncio.get_running_loop()
        if self._loop is not loop:
            self._loop, self._room = loop, asyncio.Event()
            self._answered_all = asyncio.Event()
        self._unanswered += 1
        assert self._answered_all is not None
        self._answered_all.clear()
        writer.put(_Queued(r, frame, t))
        while writer.queued > MAX_QUEUED:
            assert self._room is not None
            self._room.clear()
            await self._room.wait()  # the local disk is slower than the camera: pairs wait

    def _make(self, item: _Queued) -> QualityRecord:
        """On the journal thread: the record of a queued pair."""
        frame, item.frame = item.frame, None
        assert frame is not None
        return self.record_of(item.result, frame)

    def _durable(self, items: list[_Queued], durable: bool) -> None:
        """On a writer thread: a batch is on disk (or, ``durable`` False, only in memory).

        Items first answered ``False`` come again with ``True`` once durable after all.
        """
        now = time.monotonic()
        self._answers.extend((item, durable, now) for item in items)
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._take_answers)
            except RuntimeError:  # the loop closed meanwhile: close() takes them
                pass

    def _take_answers(self) -> None:
        """On the event loop: the journal's answers (health, counters, room for more)."""
        writer = self.writer
        while self._answers:
            item, durable, at = self._answers.popleft()
            seq = item.result.seq
            if item.answered:  # durable at last: health only (counted when first answered)
                self._health(item.t, seq)
            else:
                item.answered = True
                self._unanswered -= 1
                logged = durable and writer is not None and writer.state.problem is None
                self._answered(item.t, seq, logged)
            if durable:
                if self.on_stored is not None:
                    self.on_stored(seq, at)
                if self.on_handled is not None:
                    self.on_handled(item.result)
        if self._room is not None and (writer is None or writer.queued <= MAX_QUEUED):
            self._room.set()
        if self._answered_all is not None and self._unanswered <= 0:
            self._answered_all.set()

    async def settle(self, timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
        """Wait until the journal answered every queued pair, at most ``timeout_s`` (real time).

        For the end of a run (never the control loop): the last pairs are handled (their
        records fsync'ed to the journal, milliseconds) before the run's counts are read.
        Returns whether every queued pair was answered (inline: at once, ``True``).
        """
        done = self._answered_all
        if self.writer is None or done is None or self._unanswered <= 0:
            return True
        try:
            await asyncio.wait_for(done.wait(), timeout_s)
        except asyncio.TimeoutError:
            return False
        return True

    def flush(self, timeout_s: float = 60.0) -> bool:
        """Block until every queued record is in the log, at most ``timeout_s`` (tests, tools).

        Returns whether everything is logged; never call it from the control loop.
        """
        ok = True
        if self.writer is not None:
            ok = self.writer.wait_logged(timeout_s)
        self._take_answers()
        return ok

    def _store(self, sink: RecordSink, rec: QualityRecord) -> tuple[bool, int | None]:
        """Append (after the held ones): whether it is in the log, and its id there if known."""
        if sink.pending:
            sink.retry()  # the held ones first, in order
        sink.append(rec)
        if sink.pending:
            return False, None  # in the journal
        try:  # the log's newest id is this record's: one appender (this stage)
            last = self.log.last_id
        except (AttributeError, OSError, ValueError, sqlite3.Error):
            return True, None
        return True, (last if isinstance(last, int) else None)

    def _health(self, t: float, seq: Any) -> None:
        """The log's trouble as events and the supervisor's ``log`` condition (no I/O)."""
        if self.writer is not None:
            st = self.writer.state
            rewritten, problem, failing = st.counters.get("rewritten", 0), st.problem, st.failing
        else:
            sink = self.sink
            assert sink is not None
            rewritten, problem, failing = (sink.counters.get("rewritten", 0), sink.problem,
                                           sink.failing)
        if rewritten != self._rewritten:
            self._rewritten = rewritten
            self._report.emit(t, EventKind.LOG_REFUSED_RECORD,
                              f"quality record of pair {seq} refused by the log: logged as a "
                              "failed record naming the value")
        if problem is not None and not self._failing:
            self._failing = True
            self._report.emit(t, EventKind.LOG_FAILED,
                              f"quality log failing, records held in the journal: {problem}")
        elif problem is None and self._failing:
            self._failing = False
            self._report.emit(t, EventKind.LOG_RECOVERED,
                              "quality log writable again: held records written")
        if failing != self._unhealthy:
            self._unhealthy = failing
            self._on_health(not failing)

    def close(self, t: float, *, timeout_s: float = CLOSE_TIMEOUT_S) -> Path | None:
        """Write what the log takes, close it; the journal left behind (reported) or ``None``.

        In real time the log gets at most ``timeout_s`` (a database that does not answer);
        what it did not take stays in the journal, named in the ``RECORDS_SAVED`` event.
        """
        if self.writer is not None:
            writer = self.writer
            left = writer.close(timeout_s)
            self._take_answers()
            hung = writer.database_busy
            if left is not None:
                n = writer.state.pending
                self._report.emit(t, EventKind.RECORDS_SAVED,
                                  f"{n} quality records NOT in the quality log: kept in {left} "
                                  "(written to the log when a service opens it again)"
                                  + ("; the log did not answer within "
                                     f"{timeout_s:g} s" if hung else ""))
            if not hung:  # a call that never returns holds the log: leave it to the exit
                self.log.close()
            return left
        sink = self.sink
        if sink is None:
            return None
        left = sink.close()
        if left is not None:
            n = sink.pending
            self._report.emit(t, EventKind.RECORDS_SAVED,
                              f"{n} quality records NOT in the quality log: kept in {left} "
                              "(written to the log when a service opens it again)")
        self.log.close()
        return left
