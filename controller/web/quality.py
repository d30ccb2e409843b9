"""The quality staff page's data: boards of a quality log, their records, figures and CSV.

:class:`QualityBrowser` opens a quality log read-only (an SQLite file or a PostgreSQL URL,
:func:`controller.quality.log.open_quality_log`), reads new records incrementally (``after_id``)
and answers the page: the board list, one board's records, its figures as PNG
(:func:`controller.quality.report.build_figures`) and CSV
(:data:`~controller.quality.log.CSV_COLUMNS`).
Thread-safe (the server calls it from its worker threads).
"""

from __future__ import annotations

import csv
import io
import math
import threading
from pathlib import Path
from typing import Any

from controller.quality.log import (
    CSV_COLUMNS,
    QualityClass,
    QualityLog,
    QualityRecord,
    csv_row,
    open_quality_log,
)

__all__ = ["FIGURE_NAMES", "QualityBrowser"]

FIGURE_NAMES = ("pitch_uniformity", "setpoints", "profile", "defect_map")
"""Figures a board may have (``controller.quality.report.build_figures``; ``defect_map`` when
its records carry planing defects)."""


def _mean(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return sum(vals) / len(vals) if vals else None


def _round(v: float | None, digits: int) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), digits)


def _board_grade(recs: list[QualityRecord]) -> dict[str, Any]:
    """A board's grade and defects from its last record that carries them."""
    last = next((r for r in reversed(recs) if r.board_grade is not None), None)
    counts = None if last is None else dict(last.board_defect_counts or {})
    return {"grade": None if last is None else last.board_grade,
            "defects": None if counts is None else sum(counts.values()),
            "defect_counts": counts}


class QualityBrowser:
    """Read-only access to a quality log for the quality page.

    Parameters
    ----------
    target : str or Path
        The log: an SQLite file or ``postgresql://...``. It must exist (nothing is created).

    Raises
    ------
    OSError, ValueError
        The log cannot be opened (missing file, unreachable database, not a quality log),
        raised by the first call that needs it (:meth:`refresh`).
    """

    def __init__(self, target: str | Path) -> None:
        if not isinstance(target, (str, Path)) or str(target) == "":
            raise ValueError(f"quality log must be a file or a postgresql:// URL, got {target!r}")
        self.target = target
        self._lock = threading.Lock()
        self._log: QualityLog | None = None
        self._entries: list[tuple[int, QualityRecord]] = []
        self._last_id = 0
        self._qc: QualityClass | None = None
        self._figure_lock = threading.Lock()  # matplotlib is not thread-safe: one at a time
        self._figures: dict[tuple[int, int], dict[str, bytes]] = {}

    def _open(self) -> QualityLog:
        if self._log is None:
            self._log = open_quality_log(self.target, create=False)
        return self._log

    def refresh(self) -> int:
        """Read the records appended since the last call; return how many there are in all."""
        with self._lock:
            log = self._open()
            new = log.entries(after_id=self._last_id)
            if new:
                self._entries.extend(new)
                self._last_id = new[-1][0]
            self._qc = log.quality_class()
            return len(self._entries)

    @property
    def quality_class(self) -> QualityClass | None:
        """The class the log's writer stored (after :meth:`refresh`)."""
        return self._qc

    def _board_entries(self, board_id: int) -> list[tuple[int, QualityRecord]]:
        self.refresh()
        with self._lock:
            return [(i, r) for i, r in self._entries if r.board_id == board_id]

    def boards(self) -> list[dict[str, Any]]:
        """One summary per board, in the order the boards first appear.

        Returns
        -------
        list of dict
            ``board_id``, ``machine_id``, ``records``, ``ok`` (measured), ``passed``,
            ``judged``, ``first_time`` / ``last_time`` (UTC text), ``length_mm`` (span of
            board positions), ``mean_pitch_mm``, ``mean_uniformity_cv``, ``mean_depth_um``,
            ``grade`` (the board's D1666 grade: its last record's ``board_grade``; ``None``
            without defects looked for), ``defects`` (their number) and ``defect_counts``.
        """
        self.refresh()
        with self._lock:
            entries = list(self._entries)
        groups: dict[int, list[QualityRecord]] = {}
        for _, r in entries:
            groups.setdefault(r.board_id, []).append(r)
        out = []
        for bid, recs in groups.items():
            ok = [r for r in recs if r.ok]
            judged = [r for r in recs if r.passed is not None]
            pos = [r.board_position_mm for r in recs]
            out.append({
                "board_id": bid,
                "machine_id": recs[0].machine_id,
                "records": len(recs),
                "ok": len(ok),
                "judged": len(judged),
                "passed": sum(1 for r in judged if r.passed),
                "first_time": recs[0].wall_time,
                "last_time": recs[-1].wall_time,
                "length_mm": _round(max(pos) - min(pos), 1),
                "mean_pitch_mm": _round(_mean([r.pitch_mm for r in ok]), 4),
                "mean_uniformity_cv": _round(_mean([r.uniformity_cv for r in ok]), 4),
                "mean_depth_um": _round(_mean([r.depth_um for r in ok]), 2),
                **_board_grade(recs),
            })
        return out

    def board(self, board_id: int) -> dict[str, Any]:
        """One board's records for the page's table, and the figures it has.

        Raises
        ------
        KeyError
            No record of that board.
        """
        entries = self._board_entries(board_id)
        if not entries:
            raise KeyError(board_id)
        rows = [{
            "id": rid,
            "seq": r.seq,
            "wall_time": r.wall_time,
            "board_position_mm": _round(r.board_position_mm, 2),
            "ok": r.ok,
            "error": r.error,
            "pitch_mm": _round(r.pitch_mm, 4),
            "uniformity_cv": _round(r.uniformity_cv, 4),
            "depth_um": _round(r.depth_um, 2),
            "confidence": _round(r.confidence, 3),
            "feed_setpoint_mm_s": _round(r.feed_setpoint_mm_s, 1),
            "passed": r.passed,
            "state": (r.extra or {}).get("state"),
            "grade": r.grade,
            "defects": None if r.defects is None else [d["kind"] for d in r.defects],
        } for rid, r in entries]
        qc = self._qc
        has_profile = any(isinstance((r.extra or {}).get("profile"), dict) for _, r in entries)
        has_defects = any(r.defects is not None for _, r in entries)
        figures = [n for n in FIGURE_NAMES if (n != "profile" or has_profile)
                   and (n != "defect_map" or has_defects)]
        return {"board_id": board_id, "records": rows, "figures": figures,
                "quality_class": None if qc is None else qc.to_dict()}

    def figure_png(self, board_id: int, name: str, *, dpi: int = 80) -> bytes:
        """One of the board's figures (:data:`FIGURE_NAMES`) as PNG bytes.

        The board's figures are drawn together, one board at a time, and kept until the
        board has new records (the page asks for all of them at once).

        Raises
        ------
        KeyError
            No record of that board, or the board has no such figure (e.g. no profile).
        """
        from controller.quality.report import build_figures

        if name not in FIGURE_NAMES:
            raise KeyError(name)
        entries = self._board_entries(board_id)
        if not entries:
            raise KeyError(board_id)
        key = (board_id, entries[-1][0])
        with self._figure_lock:
            pngs = self._figures.get(key)
            if pngs is None:
                figures = build_figures([r for _, r in entries], quality_class=self._qc)
                pngs = {}
                for fig_name, fig in figures.items():
                    buf = io.BytesIO()
                    fig.savefig(buf, format="png", dpi=dpi)
                    pngs[fig_name] = buf.getvalue()
                if len(self._figures) >= 8:  # a few boards' figures at most
                    self._figures.pop(next(iter(self._figures)))
                self._figures[key] = pngs
        if name not in pngs:
            raise KeyError(name)
        return pngs[name]

    def csv_text(self, board_id: int | None = None) -> str:
        """The records (of one board, or all) as CSV text, columns ``CSV_COLUMNS``.

        Raises
        ------
        KeyError
            ``board_id`` given and no record of that board.
        """
        if board_id is None:
            self.refresh()
            with self._lock:
                entries = list(self._entries)
        else:
            entries = self._board_entries(board_id)
            if not entries:
                raise KeyError(board_id)
        buf = io.StringIO(newline="")
        w = csv.writer(buf)
        w.writerow(CSV_COLUMNS)
        for rid, rec in entries:
            w.writerow(csv_row(rid, rec))
        return buf.getvalue()

    def close(self) -> None:
        """Close the log (idempotent)."""
        with self._lock:
            if self._log is not None:
                self._log.close()
                self._log = None
