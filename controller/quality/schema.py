"""The quality record and its table: fields, checks, the quality class, columns per schema version.

Pure (no database): :mod:`controller.quality.log` (the log), its two stores
(:mod:`controller.quality.store_sqlite`, :mod:`controller.quality.store_postgres`) and the journal
all take the record, its checks and the table layout from here. Field meanings and units:
``docs/quality_log.md``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import operator
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone
from typing import Any

from config.heads import DEFAULT_HEAD, HEAD_NAME
from config.loading import Section
from controller.quality.defect_fields import check_defect_fields
from core.checks import check_finite, check_int, check_positive
from core.errors import PlanerError

#: Version of the table layout this code writes; logs with a higher version are refused.
SCHEMA_VERSION = 8
#: SQLite ``application_id`` marking a file as a planer quality log ("PLQL").
APPLICATION_ID = 0x504C514C
#: Longest machine id (``[machine] id``), characters.
MACHINE_ID_MAX = 64
#: Longest head name, characters (a name is ``config.heads.HEAD_NAME``; ``DEFAULT_HEAD`` is the
#: head of a single-head planer and of every record written before schema version 8).
HEAD_MAX = 32


class QualityLogError(PlanerError, ValueError):
    """The file is not a readable quality log (corrupt, foreign or from a newer version)."""


class RecordRefusedError(PlanerError, ValueError):
    """A record holds a value the log's schema cannot store; ``field`` names it.

    Raised by :meth:`QualityLog.append` before anything is written (e.g. a ``board_id`` beyond
    SQLite's 64-bit integers). :func:`storable` turns such a record into a failed one that
    the log takes.
    """

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


#: Largest integer an SQLite INTEGER column holds (``seq``, ``board_id``).
SQLITE_INT_MAX = 2**63 - 1


# --------------------------------------------------------------------------------------------
# time stamps


def utc_iso(epoch_s: float) -> str:
    """ISO-8601 UTC time stamp of a POSIX time, e.g. ``2026-05-09T07:35:25.123456+00:00``.

    Parameters
    ----------
    epoch_s : float
        Seconds since 1970-01-01 UTC (``time.time()`` of the injected wall clock).
    """
    v = check_finite("epoch_s", epoch_s)
    return datetime.fromtimestamp(v, tz=timezone.utc).isoformat(timespec="microseconds")


def _check_wall_time(value: str) -> str:
    if not isinstance(value, str):
        raise ValueError(f"wall_time must be an ISO-8601 UTC string, got {value!r}")
    text = value[:-1] + "+00:00" if value.endswith("Z") else value
    try:
        stamp = datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"wall_time is not an ISO-8601 time stamp: {value!r}") from None
    if stamp.utcoffset() is None or stamp.utcoffset().total_seconds() != 0:
        raise ValueError(f"wall_time must be in UTC (offset +00:00 or Z), got {value!r}")
    return value


# --------------------------------------------------------------------------------------------
# the record


def _opt_float(name: str, value: Any) -> float | None:
    """``None`` or a finite float; NaN means "not measured" and becomes ``None``."""
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or None, got {value!r}") from None
    if math.isnan(v):
        return None
    return check_finite(name, v)


def _float_tuple(name: str, values: Any) -> tuple[float, ...]:
    """A tuple of floats; NaN elements are kept (a knife whose mark was not found)."""
    if values is None:
        return ()
    if isinstance(values, (str, bytes)) or not hasattr(values, "__iter__"):
        raise ValueError(f"{name} must be a sequence of numbers, got {values!r}")
    out = []
    for i, x in enumerate(values):
        try:
            v = float(x)
        except (TypeError, ValueError):
            raise ValueError(f"{name}[{i}] must be a number, got {x!r}") from None
        if math.isinf(v):
            raise ValueError(f"{name}[{i}] must be finite or NaN, got {x!r}")
        out.append(v)
    return tuple(out)


def _opt_bool(name: str, value: Any) -> bool | None:
    """``None`` or a bool; numpy booleans are accepted, numbers and strings are not."""
    if value is None or isinstance(value, bool):
        return value
    if type(value).__name__ in ("bool_", "bool") and hasattr(value, "item"):
        return bool(value)
    raise ValueError(f"{name} must be true, false or None, got {value!r}")


@dataclass(frozen=True, kw_only=True)
class QualityRecord:
    """One measurement as the quality log stores it (all keyword arguments).

    Scalar metrics are ``None`` when not measured; NaN given for one is stored as ``None``.
    A failed measurement (``ok=False``) carries an ``error`` and no pitch, widths, uniformity,
    depth or pass/fail; it may carry the registration's ``shift_px`` and ``confidence``.
    Sequences are stored as tuples of floats.

    Attributes
    ----------
    t_s : float
        Machine time of the measurement (trigger A), seconds.
    wall_time : str
        Wall-clock time, ISO-8601 in UTC (see :func:`utc_iso`).
    seq : int
        Sequence number of the image pair, >= 0.
    board_id : int
        Board under the camera (0 when none), >= 0.
    board_position_mm : float
        Position of the imaged patch (image A's centre) from the board's leading end, mm.
    ok : bool
        Whether the measurement succeeded.
    error : str or None
        Why it failed (e.g. ``"registration failed: confidence 0.21"``); ``None`` when ok.
        The text before the first colon is the reason the report counts.
    pitch_mm : float or None
        Measured mark pitch (feed per knife), mm.
    mark_widths_mm : tuple of float, shape (Z,)
        Measured mark width per knife, mm (index = knife number; NaN = not found).
    uniformity_cv : float or None
        Coefficient of variation of the mark widths (std / mean), dimensionless.
    depth_um : float or None
        Mark depth (waviness), micrometres.
    shift_px : float or None
        Registration shift of image B against A, pixels.
    confidence : float or None
        Registration confidence, 0..1.
    feed_setpoint_mm_s : float or None
        Feed-rate setpoint in force at the measurement, mm/s.
    piezo_offsets_um : tuple of float, shape (Z,)
        Piezo offset setpoint per knife in force at the measurement, micrometres
        (> 0 lifts the cutterhead while that knife cuts).
    target_pitch_mm : float or None
        Target pitch of the quality class, mm.
    passed : bool or None
        Pass/fail against the quality class (:func:`judge`); ``None`` when not judged.
    true_pitch_mm, true_uniformity_cv : float or None
        Simulator only: the true pitch (mm) and uniformity (CV) of the imaged patch.
    extra : dict
        Free JSON-serialisable data, e.g. ``extra["profile"] = {"x_mm": [...],
        "height_um": [...]}``.
    machine_id : str or None
        The machine that measured (``[machine] id``); ``None`` = the log's own machine id is
        stamped on append (records read back from logs before schema version 3 hold ``None``).
    roll_deg : float or None
        Direction of the marks' normal (the feed) in the image: the camera's roll, degrees.
    roll_confidence : float or None
        Confidence of the per-pair roll estimate, 0..1 (below the vision's threshold the rig
        file's roll was used).
    calibration_state : {"off", "applied", "untrusted"} or None
        The self-calibration from the knife kinematics: ``off`` (no cutting radius),
        ``applied`` (the values below corrected the profile), ``untrusted`` (estimated, not
        applied: confidence too low); ``None`` = not known (records before schema version 4,
        pairs the vision could not measure).
    calibration_gain : float or None
        Photometric gain (measured slope / kinematic slope), dimensionless.
    calibration_gain_confidence : float or None
        Its confidence, 0..1 (smoothed over the board's pairs).
    calibration_scatter_mm : float or None
        Subsurface scattering length along the fibres, mm.
    calibration_scatter_fraction : float or None
        Fraction of the light scattered, 0..1.
    calibration_scatter_confidence : float or None
        Confidence of the scattering estimate, 0..1.
    kinematic_depth_um : float or None
        Mark depth from the marks' cusps and lowest points with the cutting radius, um: beside
        ``depth_um`` (photometric), a difference shows spring-back, tear-out or chatter.
    uncalibrated_depth_um : float or None
        ``depth_um`` before the self-calibration, um.
    flag_reason : str or None
        Why a measured pair was flagged and kept out of the control loops: the vision's own
        checks disagreed (``Measurement.flag_reason``) or the pitch disagrees with the feed
        and spindle the PLC reports beyond slip and ripple. A flagged record is a failed one
        (``ok=False``; ``error`` says ``flagged: ...``); ``None`` = not flagged (records
        before schema version 5 hold ``None``).
    board_travel_m : float or None
        Board travelled under the cutter since the service started, m (the knife condition's
        abscissa); ``None`` before the first table was applied and before schema version 6.
    knife_drift_um_per_m : tuple of float, shape (Z,)
        Each knife's wear: the fitted drift of its piezo offset per metre of board, um/m
        (negative: the knife wears back; NaN before enough board was fitted; empty when not
        known). Schema version 6, as the fields below.
    knife_reserve_um : tuple of float, shape (Z,)
        Each knife's offset-table reserve: the stroke left in the direction it drifts, um.
    jointing_state : {"fitting", "not_due", "due"} or None
        The jointing forecast (:class:`controller.laws.knife_condition.JointingState`):
        still fitting the wear, not due within its horizon, or due after the figures below.
    jointing_due_m, jointing_due_boards, jointing_due_h : float or None
        When the finish leaves its quality class at the present wear: in m of board, boards
        of ``[quality] board_length_mm`` and hours at the feed then (0: now); ``None`` unless
        ``jointing_state`` is ``due``.
    jointing_knife : int or None
        The knife whose reserve runs out first (0-based, as the offset table).
    defects : tuple of dict or None
        The pair's planing defects (schema version 7), the contract's objects (``kind``,
        ``x_mm``, ``y_mm``, ``length_mm``, ``width_mm``, ``depth_um`` or ``None``,
        ``confidence``; :mod:`controller.quality.defect_fields`); ``()`` none found, ``None``
        not looked for (``[quality] defects = false``, a pair the vision could not measure).
    grade : int or None
        The pair's ASTM D1666 grade, 1 (defect-free) ... 5 (very poor); with ``defects``.
    grade_reason : str or None
        Why (the worst defect, the rule's steps); with ``defects``.
    board_grade : int or None
        The grade of the board (``board_id``) over its pairs up to this one: the board's last
        record holds the whole board's grade.
    board_grade_reason : str or None
        Why (the worst pair, widespread defects).
    board_defect_counts : dict or None
        Defects per kind on the board's pairs up to this one: a count for every kind.
    head : str
        The cutterhead that cut the measured surface (schema version 8): a moulder's head name
        (``[a-z][a-z0-9_]*``, e.g. ``"bottom"``); ``"main"`` for a single-head planer and for
        every record written before version 8.
    """

    t_s: float
    wall_time: str
    seq: int
    board_id: int
    board_position_mm: float
    ok: bool
    error: str | None = None
    pitch_mm: float | None = None
    mark_widths_mm: tuple[float, ...] = ()
    uniformity_cv: float | None = None
    depth_um: float | None = None
    shift_px: float | None = None
    confidence: float | None = None
    feed_setpoint_mm_s: float | None = None
    piezo_offsets_um: tuple[float, ...] = ()
    target_pitch_mm: float | None = None
    passed: bool | None = None
    true_pitch_mm: float | None = None
    true_uniformity_cv: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    machine_id: str | None = None
    roll_deg: float | None = None
    roll_confidence: float | None = None
    calibration_state: str | None = None
    calibration_gain: float | None = None
    calibration_gain_confidence: float | None = None
    calibration_scatter_mm: float | None = None
    calibration_scatter_fraction: float | None = None
    calibration_scatter_confidence: float | None = None
    kinematic_depth_um: float | None = None
    uncalibrated_depth_um: float | None = None
    flag_reason: str | None = None
    board_travel_m: float | None = None
    knife_drift_um_per_m: tuple[float, ...] = ()
    knife_reserve_um: tuple[float, ...] = ()
    jointing_state: str | None = None
    jointing_due_m: float | None = None
    jointing_due_boards: float | None = None
    jointing_due_h: float | None = None
    jointing_knife: int | None = None
    defects: tuple[dict[str, Any], ...] | None = None
    grade: int | None = None
    grade_reason: str | None = None
    board_grade: int | None = None
    board_grade_reason: str | None = None
    board_defect_counts: dict[str, int] | None = None
    head: str = DEFAULT_HEAD

    def __post_init__(self) -> None:
        # the checks and conversions field by field (tests pin them to that form), in order,
        # with a fast path for the values the service gives (exact floats, ints, bools)
        d = self.__dict__  # a frozen dataclass's fields (object.__setattr__'s effect)
        v = d["t_s"]
        if v.__class__ is not float or v - v != 0.0:  # v - v: NaN for NaN and infinities
            d["t_s"] = check_finite("t_s", v)
        d["wall_time"] = _check_wall_time(d["wall_time"])
        for name in _INT_FIELDS:
            v = d[name]
            if v.__class__ is not int or v < 0:
                d[name] = check_int(name, v, lo=0)
        v = d["board_position_mm"]
        if v.__class__ is not float or v - v != 0.0:
            d["board_position_mm"] = check_finite("board_position_mm", v)
        ok = d["ok"]
        if ok.__class__ is not bool:
            ok = _opt_bool("ok", ok)
            if ok is None:
                raise ValueError("ok must be true or false, got None")
            d["ok"] = ok
        for name in _OPT_FLOATS:
            v = d[name]
            if v is not None and (v.__class__ is not float or v - v != 0.0):
                d[name] = _opt_float(name, v)  # NaN -> None; others converted or refused
        for name in _TUPLES:
            v = d[name]
            if v.__class__ is not tuple or not _plain_floats(v):
                d[name] = _float_tuple(name, v)
        v = d["passed"]
        if v is not None and v.__class__ is not bool:
            d["passed"] = _opt_bool("passed", v)
        if d["machine_id"] is not None:
            d["machine_id"] = _check_machine_id("machine_id", d["machine_id"])
        d["head"] = check_head("head", d["head"])
        self._check_rest(d)

    def _check_rest(self, d: dict[str, Any]) -> None:
        """The checks after the fields' own: the fields taken together (``d``: the fields)."""
        if self.error is not None and not isinstance(self.error, str):
            raise ValueError(f"error must be a string or None, got {self.error!r}")
        if self.flag_reason is not None:
            if not isinstance(self.flag_reason, str) or not self.flag_reason:
                raise ValueError(f"flag_reason must be a non-empty string or None, got "
                                 f"{self.flag_reason!r:.80}")
            d["flag_reason"] = str(self.flag_reason)
            if self.ok:
                raise ValueError("a flagged pair (flag_reason set) is not a successful "
                                 "measurement: ok must be false")
        if self.jointing_state not in _QUIET_JOINTING or self.jointing_knife is not None \
                or self.jointing_due_m is not None or self.jointing_due_boards is not None \
                or self.jointing_due_h is not None:
            _check_jointing(self)
        if self.defects is not None or self.grade is not None or self.board_grade is not None \
                or self.board_defect_counts is not None or self.grade_reason is not None \
                or self.board_grade_reason is not None:
            d.update(check_defect_fields(self))  # schema version 7 (all None: nothing to do)
        state = self.calibration_state
        if state not in _CALIBRATION_OR_NONE:
            raise ValueError(f"calibration_state must be one of {', '.join(CALIBRATION_STATES)} "
                             f"or None, got {state!r:.80}")
        if state is None or state == "off":
            given = [n for n in CALIBRATION_FIELDS if d[n] is not None]
            if given:
                raise ValueError(f"{given[0]} needs calibration_state applied or untrusted, "
                                 f"got {state!r}")
        extra = self.extra
        if not isinstance(extra, Mapping) or not all(isinstance(k, str) for k in extra):
            raise ValueError(f"extra must be a dict with string keys, got {extra!r:.80}")
        d["extra"] = dict(extra)
        if self.ok:
            if self.error is not None:
                raise ValueError(f"error must be None for a successful measurement, got "
                                 f"{self.error!r}")
        else:
            if not self.error:
                raise ValueError("error must say why the measurement failed (ok=False)")
            carried = [n for n in ("pitch_mm", "uniformity_cv", "depth_um", "passed",
                                   "kinematic_depth_um", "uncalibrated_depth_um")
                       if d[n] is not None]
            if self.mark_widths_mm:
                carried.append("mark_widths_mm")
            if carried:
                raise ValueError(f"a failed measurement carries no metrics, got {carried[0]}")


def _plain_floats(values: tuple[Any, ...]) -> bool:
    """Whether a tuple holds only exact floats, finite or NaN (kept as it is)."""
    for x in values:
        if x.__class__ is not float or (x - x != 0.0 and x == x):  # an infinity
            return False
    return True


def _check_jointing(rec: QualityRecord) -> None:
    """The knife condition's fields of a record: the state known, its figures only when due."""
    if rec.jointing_state not in (None, *JOINTING_STATES):
        raise ValueError(f"jointing_state must be one of {', '.join(JOINTING_STATES)} or None, "
                         f"got {rec.jointing_state!r:.80}")
    if rec.jointing_knife is not None:
        object.__setattr__(rec, "jointing_knife",
                           check_int("jointing_knife", rec.jointing_knife, lo=0, hi=7))
    if rec.jointing_state != "due":
        given = [n for n in JOINTING_FIELDS if getattr(rec, n) is not None]
        if given:
            raise ValueError(f"{given[0]} needs jointing_state due, got "
                             f"{rec.jointing_state!r}")
    for name in ("jointing_due_m", "jointing_due_boards", "jointing_due_h"):
        v = getattr(rec, name)
        if v is not None and v < 0:
            raise ValueError(f"{name} must be >= 0, got {v!r}")


#: The jointing forecast's states (``jointing_state``; the values of
#: :class:`controller.laws.knife_condition.JointingState`).
JOINTING_STATES = ("fitting", "not_due", "due")
#: The forecast's figures, set only with state ``due``.
JOINTING_FIELDS = ("jointing_due_m", "jointing_due_boards", "jointing_due_h", "jointing_knife")

#: The self-calibration's states (``calibration_state``).
CALIBRATION_STATES = ("off", "applied", "untrusted")
_CALIBRATION_OR_NONE = (None, *CALIBRATION_STATES)
_QUIET_JOINTING = (None, "fitting", "not_due")
"""Jointing states that need no figures: a record with none skips :func:`_check_jointing`."""
#: The self-calibration's values, set only with state ``applied`` or ``untrusted``.
CALIBRATION_FIELDS = (
    "calibration_gain", "calibration_gain_confidence", "calibration_scatter_mm",
    "calibration_scatter_fraction", "calibration_scatter_confidence",
)
_OPT_FLOATS = (
    "pitch_mm", "uniformity_cv", "depth_um", "shift_px", "confidence", "feed_setpoint_mm_s",
    "target_pitch_mm", "true_pitch_mm", "true_uniformity_cv", "roll_deg", "roll_confidence",
    *CALIBRATION_FIELDS, "kinematic_depth_um", "uncalibrated_depth_um", "board_travel_m",
    "jointing_due_m", "jointing_due_boards", "jointing_due_h",
)
_TUPLES = ("mark_widths_mm", "piezo_offsets_um", "knife_drift_um_per_m", "knife_reserve_um")
#: Tuples stored in columns added later (NULL in older records reads back as empty).
_LATE_TUPLES = ("knife_drift_um_per_m", "knife_reserve_um")
_FIELD_NAMES = tuple(f.name for f in fields(QualityRecord))
_INT_FIELDS = ("seq", "board_id")
_TEXT_FIELDS = ("wall_time", "error", "flag_reason", "grade_reason", "board_grade_reason")
#: Fields stored as JSON text (schema version 7; NULL = ``None``).
_JSON_FIELDS = ("defects", "board_defect_counts")
#: The board's grade fields (schema version 7; set together, only on a board).
_BOARD_GRADE_FIELDS = ("board_grade", "board_grade_reason", "board_defect_counts")
#: The planing defects' record fields (schema version 7), kept on a refused record.
DEFECT_FIELDS = ("defects", "grade", "grade_reason", *_BOARD_GRADE_FIELDS)
#: The knife condition's record fields (schema version 6), as :func:`knife_condition_fields`.
KNIFE_CONDITION_FIELDS = ("board_travel_m", "knife_drift_um_per_m", "knife_reserve_um",
                          "jointing_state", *JOINTING_FIELDS)


def _finite(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def vision_fields(measurement: Any, *, ok: bool) -> dict[str, Any]:
    """The record fields of a vision measurement's orientation and self-calibration.

    Parameters
    ----------
    measurement : object
        A ``vision.pipeline.Measurement`` (or anything with some of its attributes:
        ``roll_deg``, ``roll_confidence``, ``calibration``, ``kinematic_depth_um``,
        ``uncalibrated_depth_um``); missing attributes give no field.
    ok : bool
        Whether the record is a successful one: only then the depths (metrics) are given.

    Returns
    -------
    dict
        ``roll_deg``, ``roll_confidence``, ``calibration_state`` (``off`` when the
        measurement has ``calibration = None``, ``applied`` / ``untrusted`` by its
        ``trusted``) and the ``calibration_*`` values, ``kinematic_depth_um``,
        ``uncalibrated_depth_um``; non-finite values as ``None``.
    """
    out: dict[str, Any] = {}
    for name in ("roll_deg", "roll_confidence"):
        if hasattr(measurement, name):
            out[name] = _finite(getattr(measurement, name))
    if hasattr(measurement, "calibration"):
        cal = measurement.calibration
        if cal is None:
            out["calibration_state"] = "off"
        else:
            trusted = bool(getattr(cal, "trusted", False))
            out["calibration_state"] = "applied" if trusted else "untrusted"
            for name in CALIBRATION_FIELDS:
                attr = name.removeprefix("calibration_")
                out[name] = _finite(getattr(cal, attr, None))
    if ok:
        for name in ("kinematic_depth_um", "uncalibrated_depth_um"):
            if hasattr(measurement, name):
                out[name] = _finite(getattr(measurement, name))
    return out


def knife_condition_fields(condition: Mapping[str, Any] | None) -> dict[str, Any]:
    """The record fields of the service's knife condition (schema version 6).

    Parameters
    ----------
    condition : mapping or None
        ``controller.service.loops.KnifeConditionWatch.describe()``: ``board_travel_m``,
        ``knives`` (each with ``drift_um_per_m``, ``reserve_um``), ``state``, ``due_in_m``,
        ``due_in_boards``, ``due_in_h``, ``knife``; ``None`` (no table applied yet) gives no
        field.

    Returns
    -------
    dict
        ``board_travel_m``, ``knife_drift_um_per_m``, ``knife_reserve_um`` (per knife, NaN for
        a drift not fitted yet), ``jointing_state`` and, when due, ``jointing_due_m``,
        ``jointing_due_boards``, ``jointing_due_h``, ``jointing_knife``.
    """
    if not condition:
        return {}
    knives = list(condition.get("knives") or ())

    def per_knife(key: str) -> tuple[float, ...]:
        return tuple(math.nan if _finite(k.get(key)) is None else float(k[key]) for k in knives)

    state = condition.get("state")
    out: dict[str, Any] = {
        "board_travel_m": _finite(condition.get("board_travel_m")),
        "knife_drift_um_per_m": per_knife("drift_um_per_m"),
        "knife_reserve_um": per_knife("reserve_um"),
        "jointing_state": state if state in JOINTING_STATES else None,
    }
    if out["jointing_state"] == "due":
        out["jointing_due_m"] = _finite(condition.get("due_in_m"))
        out["jointing_due_boards"] = _finite(condition.get("due_in_boards"))
        out["jointing_due_h"] = _finite(condition.get("due_in_h"))
        knife = condition.get("knife")
        out["jointing_knife"] = knife if isinstance(knife, int) else None
    return out


def check_storable(record: QualityRecord, *, extra_json: str | None = None) -> str:
    """Raise :class:`RecordRefusedError` naming the first field the log cannot store.

    A valid :class:`QualityRecord` may still hold values the SQLite schema refuses: integers
    beyond 64 bits (``seq``, ``board_id``), text that is not valid Unicode (lone surrogates) or
    an ``extra`` that is not JSON serialisable.

    Parameters
    ----------
    record : QualityRecord
        The record.
    extra_json : str, keyword-only, optional
        ``extra``'s text as an earlier call on this record returned it: not encoded again.

    Returns
    -------
    str
        ``extra`` as the log stores it (JSON text; the row's ``extra_json``).
    """
    for name in _INT_FIELDS:
        v = getattr(record, name)
        if not 0 <= v <= SQLITE_INT_MAX:
            raise RecordRefusedError(
                name, f"{name} {v} is out of the log's range 0..{SQLITE_INT_MAX}")
    for name in _TEXT_FIELDS:
        v = getattr(record, name)
        if v is not None:
            try:
                v.encode("utf-8")
            except UnicodeEncodeError:
                raise RecordRefusedError(
                    name, f"{name} is not valid Unicode text: {v!r:.80}") from None
    if extra_json is not None:
        return extra_json
    try:
        return _EXTRA_ENCODER.encode(record.extra)  # json.dumps(extra, default=_json_default)
    except (TypeError, ValueError, RecursionError) as exc:
        raise RecordRefusedError("extra", f"extra is not JSON serialisable: {exc}") from None


def storable(record: QualityRecord) -> tuple[QualityRecord, str]:
    """``record`` itself when the log can store it, else a failed record naming the fields.

    Each refused value is replaced (an integer by 0, text by its escaped form, ``extra`` by
    its ``repr`` texts) and kept as text in ``extra["refused"]``; ``error`` reads
    ``record refused: <field> ...`` (after the original error of a failed measurement). The
    setpoints, registration diagnostics and truth are kept; the metrics of a successful
    measurement go (a failed record carries none).

    Returns
    -------
    (QualityRecord, str)
        A record :meth:`QualityLog.append` accepts, and its ``extra`` as the log stores it
        (:func:`check_storable`'s text: encoded once for the journal and the log).
    """
    reasons: list[str] = []
    refused: dict[str, str] = {}
    changes: dict[str, Any] = {}
    current = record
    text = ""
    for _ in range(len(_INT_FIELDS) + len(_TEXT_FIELDS) + 1):
        try:
            text = check_storable(current)
            break
        except RecordRefusedError as exc:
            name = exc.field
            reasons.append(str(exc))
            value = getattr(current, name)
            if name in _INT_FIELDS:
                refused[name] = str(value)
                changes[name] = 0
                if name == "board_id":  # no board: no board grade either
                    changes.update(dict.fromkeys(_BOARD_GRADE_FIELDS))
            elif name in _TEXT_FIELDS:
                refused[name] = value.encode("utf-8", "backslashreplace").decode("utf-8")
                changes[name] = (utc_iso(0.0) if name == "wall_time" else refused[name])
            else:
                refused[name] = repr(value)[:2000]
                changes[name] = {}
            current = dataclasses.replace(current, **changes)
    if not reasons:
        return record, text
    base = current
    error = "record refused: " + "; ".join(reasons)
    if not base.ok and base.error:
        error = f"{base.error} ({error})"
    extra = dict(base.extra) if "extra" not in refused else {}
    extra["refused"] = refused
    kept = {n: getattr(base, n) for n in (
        "t_s", "wall_time", "seq", "board_id", "board_position_mm", "shift_px", "confidence",
        "feed_setpoint_mm_s", "piezo_offsets_um", "target_pitch_mm", "true_pitch_mm",
        "true_uniformity_cv", "roll_deg", "roll_confidence", "calibration_state",
        *CALIBRATION_FIELDS, "flag_reason", *KNIFE_CONDITION_FIELDS, *DEFECT_FIELDS, "head")}
    out = QualityRecord(**kept, ok=False, error=error, extra=extra)
    return out, check_storable(out)


# --------------------------------------------------------------------------------------------
# quality class and pass/fail


@dataclass(frozen=True)
class QualityClass:
    """Limits a measurement must meet to pass.

    Parameters
    ----------
    name : str
        Name of the class (e.g. ``"furniture-1.5"``).
    target_pitch_mm : float
        Target mark pitch, mm (> 0).
    pitch_tolerance : float
        Allowed relative pitch deviation, fraction of the target (0.02 = +-2 %), in [0, 1).
    uniformity_max_cv : float or None
        Largest allowed CV of the mark widths; ``None`` = not checked.
    depth_max_um : float or None
        Largest allowed mark depth, micrometres; ``None`` = not checked.
    """

    name: str
    target_pitch_mm: float
    pitch_tolerance: float
    uniformity_max_cv: float | None = None
    depth_max_um: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty string, got {self.name!r}")
        object.__setattr__(self, "target_pitch_mm",
                           check_positive("target_pitch_mm", self.target_pitch_mm))
        tol = check_positive("pitch_tolerance", self.pitch_tolerance, allow_zero=True)
        if tol >= 1:
            raise ValueError(f"pitch_tolerance is a fraction and must be < 1, got {tol!r}")
        object.__setattr__(self, "pitch_tolerance", tol)
        for name in ("uniformity_max_cv", "depth_max_um"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, check_positive(name, v, allow_zero=True))

    def to_dict(self) -> dict[str, Any]:
        """The class as a JSON-ready dict (the keys of the constructor)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> QualityClass:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown quality class key {unknown[0]!r}")
        return cls(**dict(data))


def quality_class_from_section(section: Section) -> QualityClass:
    """Read a quality class from a config table (keys as :class:`QualityClass`; errors name them).

    ``name``, ``target_pitch_mm`` and ``pitch_tolerance`` are required; ``uniformity_max_cv``
    and ``depth_max_um`` are optional (absent = not checked).
    """
    return QualityClass(
        name=section.string("name"),
        target_pitch_mm=section.number("target_pitch_mm", lo=0.0, lo_open=True),
        pitch_tolerance=section.number("pitch_tolerance", lo=0.0, hi=0.999),
        uniformity_max_cv=(section.number("uniformity_max_cv", lo=0.0)
                           if section.has("uniformity_max_cv") else None),
        depth_max_um=(section.number("depth_max_um", lo=0.0)
                      if section.has("depth_max_um") else None),
    )


def _metric(metrics: Any, name: str) -> Any:
    if isinstance(metrics, Mapping):
        return metrics.get(name)
    return getattr(metrics, name, None)


def judge(metrics: Any, quality_class: QualityClass) -> bool:
    """Whether a measurement meets a quality class (all limits inclusive).

    Parameters
    ----------
    metrics : QualityRecord, mapping or object
        Anything with ``pitch_mm``, ``uniformity_cv`` and ``depth_um`` (attributes or keys).
    quality_class : QualityClass
        The limits. Uniformity and depth are checked only when the class sets a limit.

    Returns
    -------
    bool
        ``|pitch_mm / target_pitch_mm - 1| <= pitch_tolerance`` and
        ``uniformity_cv <= uniformity_max_cv`` and ``depth_um <= depth_max_um``.

    Raises
    ------
    ValueError
        When a metric the class checks is missing or not finite (judge only successful
        measurements; a failed one has ``passed=None``).
    """
    qc = quality_class
    if not isinstance(qc, QualityClass):
        raise ValueError(f"quality_class must be a QualityClass, got {type(qc).__name__}")
    pitch = check_positive("pitch_mm", _required(metrics, "pitch_mm"))
    ok = abs(pitch / qc.target_pitch_mm - 1.0) <= qc.pitch_tolerance + 1e-9
    if qc.uniformity_max_cv is not None:
        cv = check_positive("uniformity_cv", _required(metrics, "uniformity_cv"), allow_zero=True)
        ok = ok and cv <= qc.uniformity_max_cv
    if qc.depth_max_um is not None:
        depth = check_finite("depth_um", _required(metrics, "depth_um"))
        ok = ok and depth <= qc.depth_max_um
    return bool(ok)


def _required(metrics: Any, name: str) -> Any:
    v = _metric(metrics, name)
    if v is None:
        raise ValueError(f"{name} is missing: judge only successful measurements")
    return v


# --------------------------------------------------------------------------------------------
# the table layout (shared by the stores: the same columns in SQLite and PostgreSQL)

_STATE_CHECK = ("TEXT CHECK (calibration_state IN ("
                + ", ".join(f"'{v}'" for v in CALIBRATION_STATES) + "))")
_JOINTING_CHECK = ("TEXT CHECK (jointing_state IN ("
                   + ", ".join(f"'{v}'" for v in JOINTING_STATES) + "))")
#: Columns in record-field order: (field, SQLite type, PostgreSQL type).
_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("t_s", "REAL NOT NULL", "DOUBLE PRECISION NOT NULL"),
    ("wall_time", "TEXT NOT NULL", "TEXT NOT NULL"),
    ("seq", "INTEGER NOT NULL", "BIGINT NOT NULL"),
    ("board_id", "INTEGER NOT NULL", "BIGINT NOT NULL"),
    ("board_position_mm", "REAL NOT NULL", "DOUBLE PRECISION NOT NULL"),
    ("ok", "INTEGER NOT NULL CHECK (ok IN (0, 1))", "BOOLEAN NOT NULL"),
    ("error", "TEXT", "TEXT"),
    ("pitch_mm", "REAL", "DOUBLE PRECISION"),
    ("mark_widths_mm", "TEXT NOT NULL", "TEXT NOT NULL"),
    ("uniformity_cv", "REAL", "DOUBLE PRECISION"),
    ("depth_um", "REAL", "DOUBLE PRECISION"),
    ("shift_px", "REAL", "DOUBLE PRECISION"),
    ("confidence", "REAL", "DOUBLE PRECISION"),
    ("feed_setpoint_mm_s", "REAL", "DOUBLE PRECISION"),
    ("piezo_offsets_um", "TEXT NOT NULL", "TEXT NOT NULL"),
    ("target_pitch_mm", "REAL", "DOUBLE PRECISION"),
    ("passed", "INTEGER CHECK (passed IN (0, 1))", "BOOLEAN"),
    ("true_pitch_mm", "REAL", "DOUBLE PRECISION"),
    ("true_uniformity_cv", "REAL", "DOUBLE PRECISION"),
    ("extra", "TEXT NOT NULL", "TEXT NOT NULL"),
    ("machine_id", "TEXT", "TEXT"),
    ("roll_deg", "REAL", "DOUBLE PRECISION"),
    ("roll_confidence", "REAL", "DOUBLE PRECISION"),
    ("calibration_state", _STATE_CHECK, _STATE_CHECK),
    ("calibration_gain", "REAL", "DOUBLE PRECISION"),
    ("calibration_gain_confidence", "REAL", "DOUBLE PRECISION"),
    ("calibration_scatter_mm", "REAL", "DOUBLE PRECISION"),
    ("calibration_scatter_fraction", "REAL", "DOUBLE PRECISION"),
    ("calibration_scatter_confidence", "REAL", "DOUBLE PRECISION"),
    ("kinematic_depth_um", "REAL", "DOUBLE PRECISION"),
    ("uncalibrated_depth_um", "REAL", "DOUBLE PRECISION"),
    ("flag_reason", "TEXT", "TEXT"),
    ("board_travel_m", "REAL", "DOUBLE PRECISION"),
    ("knife_drift_um_per_m", "TEXT", "TEXT"),
    ("knife_reserve_um", "TEXT", "TEXT"),
    ("jointing_state", _JOINTING_CHECK, _JOINTING_CHECK),
    ("jointing_due_m", "REAL", "DOUBLE PRECISION"),
    ("jointing_due_boards", "REAL", "DOUBLE PRECISION"),
    ("jointing_due_h", "REAL", "DOUBLE PRECISION"),
    ("jointing_knife", "INTEGER CHECK (jointing_knife BETWEEN 0 AND 7)",
     "INTEGER CHECK (jointing_knife BETWEEN 0 AND 7)"),
    ("defects", "TEXT", "TEXT"),
    ("grade", "INTEGER CHECK (grade BETWEEN 1 AND 5)", "INTEGER CHECK (grade BETWEEN 1 AND 5)"),
    ("grade_reason", "TEXT", "TEXT"),
    ("board_grade", "INTEGER CHECK (board_grade BETWEEN 1 AND 5)",
     "INTEGER CHECK (board_grade BETWEEN 1 AND 5)"),
    ("board_grade_reason", "TEXT", "TEXT"),
    ("board_defect_counts", "TEXT", "TEXT"),
    ("head", f"TEXT NOT NULL DEFAULT '{DEFAULT_HEAD}'", f"TEXT NOT NULL DEFAULT '{DEFAULT_HEAD}'"),
)
assert tuple(c for c, _, _ in _COLUMNS) == _FIELD_NAMES, "schema and record differ"

#: The table's column of each record field: the CSV header's names (one set, with units).
_COLUMN_OF = {"wall_time": "wall_time_utc", "extra": "extra_json"}
_V3 = _FIELD_NAMES[:_FIELD_NAMES.index("machine_id") + 1]
_V1 = tuple(n for n in _V3 if n != "machine_id")
_V4 = _FIELD_NAMES[:_FIELD_NAMES.index("uncalibrated_depth_um") + 1]
_V5 = _FIELD_NAMES[:_FIELD_NAMES.index("flag_reason") + 1]
_V6 = _FIELD_NAMES[:_FIELD_NAMES.index("jointing_knife") + 1]
_V7 = _FIELD_NAMES[:_FIELD_NAMES.index("board_defect_counts") + 1]
#: Column names by schema version: (id column, record columns in field order). Version 1
#: used the field names; version 2 the CSV header's (``record_id``, ``wall_time_utc``,
#: ``extra_json``); version 3 added ``machine_id``; version 4 the orientation, the
#: self-calibration and the kinematic depth (``roll_deg`` ... ``uncalibrated_depth_um``);
#: version 5 ``flag_reason``; version 6 the knife condition (``board_travel_m`` ...
#: ``jointing_knife``); version 7 the planing defects and grades (``defects`` ...
#: ``board_defect_counts``); version 8 the cutterhead (``head``).
_NAMES = {
    1: ("id", _V1),
    2: ("record_id", tuple(_COLUMN_OF.get(n, n) for n in _V1)),
    3: ("record_id", tuple(_COLUMN_OF.get(n, n) for n in _V3)),
    4: ("record_id", tuple(_COLUMN_OF.get(n, n) for n in _V4)),
    5: ("record_id", tuple(_COLUMN_OF.get(n, n) for n in _V5)),
    6: ("record_id", tuple(_COLUMN_OF.get(n, n) for n in _V6)),
    7: ("record_id", tuple(_COLUMN_OF.get(n, n) for n in _V7)),
    8: ("record_id", tuple(_COLUMN_OF.get(n, n) for n in _FIELD_NAMES)),
}
assert SCHEMA_VERSION == max(_NAMES)


#: The columns version 4 added: (name, SQLite type, PostgreSQL type), for the migrations.
ADDED_IN_V4: tuple[tuple[str, str, str], ...] = tuple(
    c for c in _COLUMNS if c[0] not in _V3 and c[0] in _V4)
#: The columns version 5 added (``flag_reason``), for the migrations.
ADDED_IN_V5: tuple[tuple[str, str, str], ...] = tuple(
    c for c in _COLUMNS if c[0] not in _V4 and c[0] in _V5)
#: The columns version 6 added (the knife condition), for the migrations.
ADDED_IN_V6: tuple[tuple[str, str, str], ...] = tuple(
    c for c in _COLUMNS if c[0] not in _V5 and c[0] in _V6)
#: The columns version 7 added (the planing defects and grades), for the migrations.
ADDED_IN_V7: tuple[tuple[str, str, str], ...] = tuple(
    c for c in _COLUMNS if c[0] not in _V6 and c[0] in _V7)
#: The column version 8 added (``head``, ``'main'`` in the rows before it), for the migrations.
ADDED_IN_V8: tuple[tuple[str, str, str], ...] = tuple(c for c in _COLUMNS if c[0] not in _V7)
_ADDED_IN = {4: ADDED_IN_V4, 5: ADDED_IN_V5, 6: ADDED_IN_V6, 7: ADDED_IN_V7, 8: ADDED_IN_V8}
assert max(_ADDED_IN) == SCHEMA_VERSION


def columns_added_since(version: int) -> tuple[tuple[str, str, str], ...]:
    """The columns the versions after ``version`` (3 or later) added, in order.

    ``(name, SQLite type, PostgreSQL type)`` each: what a writer adds to bring a log of
    ``version`` to :data:`SCHEMA_VERSION`.
    """
    if not 3 <= version <= SCHEMA_VERSION:
        raise ValueError(f"version must be in 3..{SCHEMA_VERSION}, got {version!r}")
    return tuple(c for v in range(version + 1, SCHEMA_VERSION + 1) for c in _ADDED_IN[v])


def column_names(version: int) -> tuple[str, tuple[str, ...]]:
    """``(id column, record columns in field order)`` of a schema version's ``records`` table."""
    return _NAMES[version]


def create_statements(dialect: str) -> tuple[str, ...]:
    """The statements creating an empty log's tables (``dialect``: "sqlite" or "postgresql").

    Both create ``schema_version``, ``meta``, ``records`` (columns :data:`CSV_COLUMNS`),
    ``record_uids`` (the journal's record identities, unique) and the same indexes.
    """
    if dialect not in ("sqlite", "postgresql"):
        raise ValueError(f"dialect must be 'sqlite' or 'postgresql', got {dialect!r}")
    pg = dialect == "postgresql"
    rid = ("record_id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY" if pg
           else "record_id INTEGER PRIMARY KEY AUTOINCREMENT")
    cols = ", ".join(f"{_COLUMN_OF.get(c, c)} {p if pg else s}" for c, s, p in _COLUMNS)
    return (
        "CREATE TABLE schema_version (version INTEGER NOT NULL)",
        "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
        f"CREATE TABLE records ({rid}, {cols})",
        "CREATE INDEX records_board ON records (board_id)",
        "CREATE INDEX records_seq ON records (seq)",
        "CREATE INDEX records_machine_time ON records (machine_id, wall_time_utc)",
        "CREATE TABLE record_uids (uid TEXT PRIMARY KEY, record_id "
        + ("BIGINT NOT NULL REFERENCES records (record_id))" if pg else "INTEGER NOT NULL)"),
    )


@dataclass(frozen=True)
class Selection:
    """Which records to read (all filters optional, combined with AND); see ``records``."""

    board_id: int | None = None
    since_seq: int | None = None
    after_id: int | None = None
    machine_id: str | None = None
    head: str | None = None

    def fit(self, columns: Sequence[str]) -> Selection | None:
        """The selection on a layout with ``columns``; ``None`` when no row can match.

        A layout before ``head`` (schema version 8) holds only head ``"main"``'s records.
        """
        if self.head is None or "head" in columns:
            return self
        return dataclasses.replace(self, head=None) if self.head == DEFAULT_HEAD else None

    def where(self, id_column: str, mark: str) -> tuple[list[str], list[Any]]:
        """SQL conditions (placeholder ``mark``: ``?`` or ``%s``) and their parameters."""
        where: list[str] = []
        params: list[Any] = []
        for column, value in (("board_id", self.board_id), ("seq", self.since_seq),
                              (id_column, self.after_id), ("machine_id", self.machine_id),
                              ("head", self.head)):
            if value is not None:
                op = ">=" if column == "seq" else ">" if column == id_column else "="
                where.append(f"{column} {op} {mark}")
                params.append(value)
        return where, params


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):  # numpy arrays and scalars
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


_EXTRA_ENCODER = json.JSONEncoder(default=_json_default)
"""``json.dumps(extra, default=_json_default)``'s encoder, made once (no state per call)."""
_LINE_ENCODER = json.JSONEncoder(allow_nan=False, separators=(",", ":"))
"""``json.dumps(fields, allow_nan=False, separators=(",", ":"))``'s encoder, made once."""


def _list_from_json(text: str) -> tuple[float, ...]:
    return tuple(math.nan if v is None else float(v) for v in json.loads(text))


def _finite_json(value: Any) -> Any:
    """``value`` with non-finite floats as ``None`` and numpy values as Python ones."""
    if isinstance(value, Mapping):
        return {str(k): _finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_json(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return _finite_json(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def record_to_dict(record: QualityRecord) -> dict[str, Any]:
    """One record as a JSON-ready dict (fields by name; NaN as ``None``, also inside ``extra``)."""
    out = _plain_fields(record)
    out["extra"] = _finite_json(record.extra)
    return {name: out[name] for name in _FIELD_NAMES}


_GET_FIELDS = operator.attrgetter(*_FIELD_NAMES)
"""A record's fields in field order, in one call."""
_TUPLE_AT = tuple(_FIELD_NAMES.index(n) for n in _TUPLES)
_EXTRA_AT = _FIELD_NAMES.index("extra")
_MACHINE_AT = _FIELD_NAMES.index("machine_id")
_DEFECTS_AT = _FIELD_NAMES.index("defects")
_JSON_AT = tuple(_FIELD_NAMES.index(n) for n in _JSON_FIELDS)
_PLAIN_AT = tuple(i for i, n in enumerate(_FIELD_NAMES)
                  if n not in _TUPLES and n not in _JSON_FIELDS and n != "extra")
"""Where a row holds a tuple (JSON list), JSON text, ``extra``, ``machine_id``; the rest."""


def _plain_fields(record: QualityRecord) -> dict[str, Any]:
    """The JSON-ready fields of a record but ``extra`` (NaN in a list as ``None``)."""
    out = dict(zip(_FIELD_NAMES, _GET_FIELDS(record), strict=True))
    del out["extra"]
    for name in _TUPLES:
        out[name] = [None if x != x else x for x in out[name]]  # x != x: NaN
    for name in _JSON_FIELDS:
        v = out[name]
        if v is not None:
            out[name] = list(v) if name == "defects" else dict(v)
    return out


def record_json(record: QualityRecord, *, extra_json: str | None = None) -> str:
    """One record as compact strict JSON (``record_to_dict``'s object; the journal's lines).

    ``extra_json``: ``extra``'s text as :func:`check_storable` gave it, reused when it holds
    no ``NaN`` or ``Infinity`` (else ``extra`` is encoded again with them as ``null``): a
    record is encoded once for the journal and the log. ``extra`` is the object's last key.

    Raises
    ------
    ValueError, TypeError
        A field that is not JSON (the caller records why instead).
    """
    body = _LINE_ENCODER.encode(_plain_fields(record))
    if extra_json is None or "NaN" in extra_json or "Infinity" in extra_json:
        extra_json = _LINE_ENCODER.encode(_finite_json(record.extra))
    return f'{body[:-1]},"extra":{extra_json}}}'


def record_to_json(record: QualityRecord) -> str:
    """One record as a line of JSON (fields by name; NaN as ``null``), e.g. for a fallback file."""
    return json.dumps(record_to_dict(record), default=_json_default, allow_nan=False)


def record_from_dict(data: Mapping[str, Any]) -> QualityRecord:
    """Inverse of :func:`record_to_dict` (``null`` in a list reads back as NaN).

    Raises
    ------
    ValueError
        Not a record: unknown or missing fields, or invalid values (the message names them).
    """
    if not isinstance(data, Mapping):
        raise ValueError(f"a record must be a JSON object, got {type(data).__name__}")
    unknown = sorted(set(data) - set(_FIELD_NAMES))
    if unknown:
        raise ValueError(f"unknown record field {unknown[0]!r}")
    kw = dict(data)
    for name in _TUPLES:
        if name in kw:
            vals = kw[name]
            if not isinstance(vals, list):
                raise ValueError(f"{name} must be a list, got {vals!r:.80}")
            kw[name] = tuple(math.nan if v is None else v for v in vals)
    try:
        return QualityRecord(**kw)
    except TypeError as exc:
        raise ValueError(f"not a quality record: {exc}") from None


def _to_row(rec: QualityRecord, *, extra_json: str | None = None,
            machine_id: str | None = None) -> tuple[Any, ...]:
    """The row of a record (field order).

    ``extra_json`` (:func:`check_storable`'s text) is not encoded again; ``machine_id`` is
    stored when the record names none. Tuples are JSON lists (``null`` for NaN), ``defects``
    and ``board_defect_counts`` JSON text, booleans 0/1.
    """
    row = list(_GET_FIELDS(rec))
    for i in _PLAIN_AT:
        if row[i].__class__ is bool:
            row[i] = int(row[i])
    for i in _TUPLE_AT:  # json.dumps's text: floats by repr, NaN as null
        text = "[" + ", ".join(["null" if x != x else repr(x) for x in row[i]]) + "]"
        if "inf" in text:  # an infinity (never in a checked record): json.dumps's spelling
            text = json.dumps([None if x != x else x for x in row[i]])
        row[i] = text
    for i in _JSON_AT:
        v = row[i]
        if v is not None:
            row[i] = json.dumps(list(v) if i == _DEFECTS_AT else v)
    if extra_json is not None:
        row[_EXTRA_AT] = extra_json
    else:
        try:
            row[_EXTRA_AT] = _EXTRA_ENCODER.encode(row[_EXTRA_AT])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"extra is not JSON serialisable: {exc}") from None
    if row[_MACHINE_AT] is None:
        row[_MACHINE_AT] = machine_id
    return tuple(row)


def _from_row(row: Sequence[Any]) -> QualityRecord:
    rid, *vals = row
    try:
        kw = dict(zip(_FIELD_NAMES, vals, strict=True))
        for name in _TUPLES:
            kw[name] = (() if kw[name] is None and name in _LATE_TUPLES
                        else _list_from_json(kw[name]))
        kw["extra"] = json.loads(kw["extra"])
        for name in _JSON_FIELDS:
            kw[name] = None if kw[name] is None else json.loads(kw[name])
        kw["ok"] = bool(kw["ok"])
        kw["passed"] = None if kw["passed"] is None else bool(kw["passed"])
        if kw["head"] is None:  # a layout before schema version 8: the single head
            kw["head"] = DEFAULT_HEAD
        return QualityRecord(**kw)
    except (TypeError, ValueError, KeyError) as exc:
        raise QualityLogError(f"record {rid} of the quality log is unreadable: {exc}") from None


def _check_machine_id(name: str, value: Any) -> str | None:
    if value is None:
        return None
    if (not isinstance(value, str) or not value or not value.isprintable()
            or len(value) > MACHINE_ID_MAX or value != value.strip()):
        raise ValueError(f"{name} must be a printable string of 1..{MACHINE_ID_MAX} characters "
                         f"without surrounding spaces, got {value!r:.80}")
    return value


def check_head(name: str, value: Any) -> str:
    """A head name (``[a-z][a-z0-9_]*``, at most :data:`HEAD_MAX` characters); else ValueError."""
    if not isinstance(value, str) or len(value) > HEAD_MAX or not HEAD_NAME.fullmatch(value):
        raise ValueError(f"{name} must be a head name ([a-z][a-z0-9_]*, at most {HEAD_MAX} "
                         f"characters), got {value!r:.80}")
    return value
