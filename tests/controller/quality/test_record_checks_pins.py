"""A record's checks, pinned to their field-by-field form.

``QualityRecord.__post_init__`` takes the values the service gives (exact floats, ints, bools,
tuples of floats, no defects, a quiet jointing state) by a fast path and everything else
through the field-by-field checks (:func:`_post_init_reference` below, its earlier form).
Random field values, good and bad (NaN, infinities, numpy scalars, ints for floats, lists and
arrays for tuples, strings, negative and boolean integers, defects and grades,
jointing figures, calibration values without a state, failed records with metrics) must give
the same fields, or the same error, both ways.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import MISSING, fields
from typing import Any

import numpy as np
import pytest

from controller.quality.log import QualityRecord, utc_iso
from controller.quality.schema import (
    _FIELD_NAMES,
    _OPT_FLOATS,
    _TUPLES,
    CALIBRATION_FIELDS,
    CALIBRATION_STATES,
    _check_jointing,
    _check_machine_id,
    _check_wall_time,
    _float_tuple,
    _opt_bool,
    _opt_float,
    check_defect_fields,
    check_finite,
    check_head,
    check_int,
)
from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import grade_pair


def _post_init_reference(rec: QualityRecord) -> None:
    """:meth:`QualityRecord.__post_init__` field by field (its earlier form)."""

    def put(name: str, value: Any) -> None:
        object.__setattr__(rec, name, value)

    put("t_s", check_finite("t_s", rec.t_s))
    put("wall_time", _check_wall_time(rec.wall_time))
    put("seq", check_int("seq", rec.seq, lo=0))
    put("board_id", check_int("board_id", rec.board_id, lo=0))
    put("board_position_mm", check_finite("board_position_mm", rec.board_position_mm))
    ok = _opt_bool("ok", rec.ok)
    if ok is None:
        raise ValueError("ok must be true or false, got None")
    put("ok", ok)
    for name in _OPT_FLOATS:
        put(name, _opt_float(name, getattr(rec, name)))
    for name in _TUPLES:
        put(name, _float_tuple(name, getattr(rec, name)))
    put("passed", _opt_bool("passed", rec.passed))
    put("machine_id", _check_machine_id("machine_id", rec.machine_id))
    put("head", check_head("head", rec.head))
    if rec.error is not None and not isinstance(rec.error, str):
        raise ValueError(f"error must be a string or None, got {rec.error!r}")
    if rec.flag_reason is not None:
        if not isinstance(rec.flag_reason, str) or not rec.flag_reason:
            raise ValueError(f"flag_reason must be a non-empty string or None, got "
                             f"{rec.flag_reason!r:.80}")
        put("flag_reason", str(rec.flag_reason))
        if rec.ok:
            raise ValueError("a flagged pair (flag_reason set) is not a successful "
                             "measurement: ok must be false")
    _check_jointing(rec)
    for name, value in check_defect_fields(rec).items():  # schema version 7
        put(name, value)
    if rec.calibration_state not in (None, *CALIBRATION_STATES):
        raise ValueError(f"calibration_state must be one of {', '.join(CALIBRATION_STATES)} "
                         f"or None, got {rec.calibration_state!r:.80}")
    if rec.calibration_state in (None, "off"):
        given = [n for n in CALIBRATION_FIELDS if getattr(rec, n) is not None]
        if given:
            raise ValueError(f"{given[0]} needs calibration_state applied or untrusted, "
                             f"got {rec.calibration_state!r}")
    if not isinstance(rec.extra, Mapping) or not all(isinstance(k, str) for k in rec.extra):
        raise ValueError(f"extra must be a dict with string keys, got {rec.extra!r:.80}")
    put("extra", dict(rec.extra))
    if rec.ok:
        if rec.error is not None:
            raise ValueError(f"error must be None for a successful measurement, got "
                             f"{rec.error!r}")
    else:
        if not rec.error:
            raise ValueError("error must say why the measurement failed (ok=False)")
        carried = [n for n in ("pitch_mm", "uniformity_cv", "depth_um", "passed",
                               "kinematic_depth_um", "uncalibrated_depth_um")
                   if getattr(rec, n) is not None]
        if rec.mark_widths_mm:
            carried.append("mark_widths_mm")
        if carried:
            raise ValueError(f"a failed measurement carries no metrics, got {carried[0]}")


def _number(rng: np.random.Generator, bad: float) -> Any:
    x = float(rng.standard_normal() * 10.0 ** rng.integers(-3, 4))
    if rng.random() < bad:
        return [math.inf, -math.inf, True, "1.5", [1.0]][int(rng.integers(0, 5))]
    return [x, x, x, x, math.nan, -0.0, np.float64(x), np.float32(x), int(x), None][
        int(rng.integers(0, 10))]


def _sequence(rng: np.random.Generator, bad: float) -> Any:
    vals = [float(v) for v in rng.standard_normal(int(rng.integers(1, 5)))]
    if rng.random() < bad:
        return [(*vals[:-1], math.inf), "1;2", (*vals[:-1], "x"), 3.0][int(rng.integers(0, 4))]
    k = int(rng.integers(0, 7))
    if k == 0:
        vals[0] = math.nan
    return [tuple(vals), tuple(vals), tuple(vals), list(vals), np.asarray(vals),
            (*vals[:-1], 3), None][k]


def _pick(rng: np.random.Generator, bad: float, good: Any, wrong: list[Any]) -> Any:
    return wrong[int(rng.integers(0, len(wrong)))] if rng.random() < bad else good


def _kwargs(rng: np.random.Generator, i: int) -> dict[str, Any]:
    bad = 0.0 if i % 2 else 0.04  # half the records clean, half with a few odd values
    ok = bool(rng.random() < 0.7)
    kw: dict[str, Any] = dict(
        t_s=_pick(rng, bad, float(rng.random() * 1e4), [math.nan, math.inf, "1", None]),
        wall_time=_pick(rng, bad, utc_iso(1.7e9 + i), ["yesterday", "2026-01-01T00:00:00"]),
        seq=_pick(rng, bad, [int(rng.integers(0, 1000)), np.int64(5)][i % 3 // 2],
                  [-1, True, 2.0]),
        board_id=_pick(rng, bad, int(rng.integers(0, 50)), [-3, False, "1"]),
        board_position_mm=_pick(rng, bad, float(rng.random() * 400), [math.inf, None]),
        ok=_pick(rng, bad, [ok, np.bool_(ok)][i % 5 // 4], [None, 1]),
        error=None if ok else "registration failed: low",
        head=_pick(rng, bad, ("main", "bottom", "top")[i % 3], ["Top!", ""]),
        machine_id=_pick(rng, bad, (None, "m1")[i % 2], [" m", ""]),
        extra=_pick(rng, bad, {"state": "run", "w": [1.0, math.nan]}, [{1: "x"}, [1]]),
    )
    carried = ("pitch_mm", "uniformity_cv", "depth_um", "kinematic_depth_um",
               "uncalibrated_depth_um")
    for name in _OPT_FLOATS:
        if rng.random() < 0.5 and (ok or name not in carried or rng.random() < bad):
            kw[name] = _number(rng, bad)
    for name in CALIBRATION_FIELDS:
        kw.pop(name, None)
    if rng.random() < 0.5:
        kw["calibration_state"] = _pick(rng, bad, ("applied", "untrusted", "off", None)[i % 4],
                                        ["bad"])
        if kw["calibration_state"] in ("applied", "untrusted") or rng.random() < bad:
            for name in CALIBRATION_FIELDS:
                kw[name] = _number(rng, bad)
    for name in _TUPLES:
        if rng.random() < 0.6 and (ok or name != "mark_widths_mm" or rng.random() < bad):
            kw[name] = _sequence(rng, bad)
    if ok and rng.random() < 0.5:
        kw["passed"] = _pick(rng, bad, [True, False, None, np.bool_(True)][i % 4], [1])
    for name in ("jointing_due_m", "jointing_due_boards", "jointing_due_h"):
        kw.pop(name, None)
    if rng.random() < 0.5:
        state = _pick(rng, bad, ("fitting", "not_due", "due")[i % 3], ["soon"])
        kw["jointing_state"] = state
        if state == "due" or rng.random() < bad:
            kw.update(jointing_due_m=_pick(rng, bad, float(rng.random() * 100), [-1.0]),
                      jointing_knife=_pick(rng, bad, int(rng.integers(0, 8)), [9, -1]))
    if not ok and rng.random() < 0.3:
        kw["flag_reason"] = _pick(rng, bad, "pitch off", ["", 3])
    if rng.random() < 0.3:
        found = [Defect(DefectKind.TORN_GRAIN, 12.0, 8.5, 12.5, 3.0, 180.0, 0.9)][
            :int(rng.integers(0, 2))]
        g = grade_pair(found)
        kw.update(defects=tuple(d.to_json() for d in found), grade=g.grade,
                  grade_reason=_pick(rng, bad, g.reason, [None]))
    if rng.random() < bad:
        kw["board_grade"] = 2
    return kw


def _outcome(make: Any) -> tuple[str, Any]:
    try:
        rec = make()
    except (ValueError, TypeError) as exc:
        return type(exc).__name__, str(exc)
    return "ok", [(n, _same(getattr(rec, n))) for n in _FIELD_NAMES]


def _same(v: Any) -> Any:
    """A value compared with its type (NaN as a marker: NaN != NaN)."""
    if isinstance(v, float) and math.isnan(v):
        return ("nan", type(v))
    if isinstance(v, tuple):
        return tuple(_same(x) for x in v)
    return (v, type(v))


def _reference(kw: dict[str, Any]) -> QualityRecord:
    rec = object.__new__(QualityRecord)
    for f in fields(QualityRecord):
        if f.name in kw:
            value = kw[f.name]
        elif f.default is not MISSING:
            value = f.default
        else:
            value = f.default_factory()
        object.__setattr__(rec, f.name, value)
    _post_init_reference(rec)
    return rec


@pytest.mark.parametrize("seed", range(6))
def test_the_checks_are_the_field_by_field_checks(seed):
    rng = np.random.default_rng(1000 + seed)
    outcomes = set()
    for i in range(400):
        kw = _kwargs(rng, i)
        new = _outcome(lambda kw=kw: QualityRecord(**kw))
        old = _outcome(lambda kw=kw: _reference(kw))
        assert new == old, kw
        outcomes.add(new[0])
    assert outcomes == {"ok", "ValueError"}  # both kinds seen in every series


def test_the_services_values_take_the_fast_path_unchanged():
    """Exact floats and tuples are kept as given; NaN metrics read None, NaN widths stay."""
    widths = (1.5, math.nan, 1.4, 1.6)
    rec = QualityRecord(t_s=1.0, wall_time=utc_iso(1.7e9), seq=3, board_id=1,
                        board_position_mm=2.5, ok=True, pitch_mm=1.49, depth_um=math.nan,
                        mark_widths_mm=widths, passed=True, extra={"a": 1})
    assert rec.mark_widths_mm is widths and rec.pitch_mm == 1.49 and rec.depth_um is None
    with pytest.raises(ValueError, match=r"mark_widths_mm\[1\] must be finite or NaN"):
        QualityRecord(t_s=1.0, wall_time=utc_iso(1.7e9), seq=3, board_id=1,
                      board_position_mm=2.5, ok=True, mark_widths_mm=(1.0, math.inf))
