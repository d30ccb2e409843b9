"""The log's row and the journal's fields of a record, pinned to their field-by-field forms.

``_to_row`` and ``_plain_fields`` take every field in one call and encode the tuples by hand;
the reference functions below are their earlier forms (a loop over the fields, ``json.dumps``
per tuple). Random records (NaN and -0.0 in the tuples, booleans, defects, a machine id or
none, ``extra`` given as text or encoded) must give the same row and the same JSON line.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest

from controller.quality.log import QualityRecord, utc_iso
from controller.quality.schema import (
    _FIELD_NAMES,
    _JSON_FIELDS,
    _TUPLES,
    _finite_json,
    _json_default,
    _plain_fields,
    _to_row,
    check_storable,
    record_json,
)
from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import grade_pair


def _old_list_to_json(values: tuple[float, ...]) -> str:
    return json.dumps([None if math.isnan(v) else v for v in values])


def _old_to_row(rec: QualityRecord, *, extra_json: str | None = None,
                machine_id: str | None = None) -> tuple[Any, ...]:
    row: list[Any] = []
    for name in _FIELD_NAMES:
        v = getattr(rec, name)
        if name in _TUPLES:
            v = _old_list_to_json(v)
        elif name in _JSON_FIELDS:
            v = None if v is None else json.dumps(list(v) if name == "defects" else v)
        elif name == "extra":
            if extra_json is not None:
                v = extra_json
            else:
                try:
                    v = json.dumps(v, default=_json_default)
                except (TypeError, ValueError) as exc:
                    raise ValueError(f"extra is not JSON serialisable: {exc}") from None
        elif name == "machine_id" and v is None:
            v = machine_id
        elif isinstance(v, bool):
            v = int(v)
        row.append(v)
    return tuple(row)


def _old_plain_fields(record: QualityRecord) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in _FIELD_NAMES:
        if name == "extra":
            continue
        v = getattr(record, name)
        if name in _TUPLES:
            v = [None if math.isnan(x) else x for x in v]
        elif name in _JSON_FIELDS and v is not None:
            v = list(v) if name == "defects" else dict(v)
        out[name] = v
    return out


def _floats(rng: np.random.Generator, n: int) -> list[float]:
    pick = rng.integers(0, 6, n)
    raw = rng.standard_normal(n) * 10.0 ** rng.integers(-8, 12, n)
    return [math.nan if p == 0 else -0.0 if p == 1 else 0.1 if p == 2 else float(r)
            for p, r in zip(pick, raw, strict=True)]


def _random_record(rng: np.random.Generator, i: int) -> QualityRecord:
    ok = bool(rng.random() < 0.7)
    kw: dict[str, Any] = dict(
        t_s=float(rng.random() * 1e4), wall_time=utc_iso(1.7e9 + i),
        seq=int(rng.integers(0, 2**62)),
        board_id=int(rng.integers(0, 1000)), board_position_mm=float(rng.standard_normal()),
        ok=ok, piezo_offsets_um=_floats(rng, int(rng.integers(0, 6))),
        knife_drift_um_per_m=_floats(rng, int(rng.integers(0, 5))),
        knife_reserve_um=_floats(rng, int(rng.integers(0, 5))),
        feed_setpoint_mm_s=None if rng.random() < 0.3 else float(rng.random() * 600),
        machine_id=None if rng.random() < 0.5 else f"m{i % 7}",
        head=("main", "bottom", "top")[i % 3],
        extra={"i": i, "w": _floats(rng, 3), "v": np.float32(rng.random()),
               "nested": {"a": [1, 2, None], "b": "text \u00e9"}},
    )
    if ok:
        kw.update(pitch_mm=float(rng.random() + 1), mark_widths_mm=_floats(rng, 4),
                  uniformity_cv=float(rng.random()), passed=bool(rng.random() < 0.5))
    else:
        kw["error"] = "registration failed: low"
    if rng.random() < 0.5:
        found = [Defect(DefectKind.TORN_GRAIN, 12.0, 8.5, 12.5, 3.0, 180.0, 0.9),
                 Defect(DefectKind.CHATTER, 16.0, 10.0, 32.0, 20.0, None, 0.5)][
            :int(rng.integers(0, 3))]
        g = grade_pair(found)
        kw.update(defects=tuple(d.to_json() for d in found), grade=g.grade,
                  grade_reason=g.reason)
    return QualityRecord(**kw)


@pytest.mark.parametrize("seed", range(4))
def test_the_row_is_the_field_by_field_row(seed):
    rng = np.random.default_rng(seed)
    for i in range(150):
        rec = _random_record(rng, i)
        text = check_storable(rec)
        for mid in (None, "log-machine"):
            assert _to_row(rec, extra_json=text, machine_id=mid) == _old_to_row(
                rec, extra_json=text, machine_id=mid)
            assert _to_row(rec, machine_id=mid) == _old_to_row(rec, machine_id=mid)


def _old_record_json(record: QualityRecord, *, extra_json: str | None = None) -> str:
    body = json.dumps(_old_plain_fields(record), allow_nan=False, separators=(",", ":"))
    if extra_json is None or "NaN" in extra_json or "Infinity" in extra_json:
        extra_json = json.dumps(_finite_json(record.extra), allow_nan=False,
                                separators=(",", ":"))
    return f'{body[:-1]},"extra":{extra_json}}}'


@pytest.mark.parametrize("seed", range(4))
def test_the_journal_line_and_extras_text_are_json_dumps(seed):
    rng = np.random.default_rng(200 + seed)
    for i in range(150):
        rec = _random_record(rng, i)
        text = check_storable(rec)
        assert text == json.dumps(rec.extra, default=_json_default)
        assert record_json(rec) == _old_record_json(rec)
        assert record_json(rec, extra_json=text) == _old_record_json(rec, extra_json=text)


@pytest.mark.parametrize("seed", range(4))
def test_the_journal_fields_are_the_field_by_field_ones(seed):
    rng = np.random.default_rng(100 + seed)
    for i in range(150):
        rec = _random_record(rng, i)
        new, old = _plain_fields(rec), _old_plain_fields(rec)
        assert list(new) == list(old)  # the same keys in the same order ...
        assert json.dumps(new) == json.dumps(old)  # ... and values (NaN as null)
        head = json.dumps(old, allow_nan=False, separators=(",", ":"))
        assert record_json(rec).startswith(head[:-1] + ',"extra":')


def test_an_infinity_in_a_tuple_is_spelled_as_json_dumps_does():
    rec = QualityRecord(t_s=0.0, wall_time=utc_iso(0.0), seq=1, board_id=1,
                        board_position_mm=0.0, ok=True, piezo_offsets_um=(1.0, 2.0))
    object.__setattr__(rec, "piezo_offsets_um", (math.inf, -math.inf, math.nan, 1.5))
    assert _to_row(rec) == _old_to_row(rec)
