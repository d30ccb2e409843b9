"""Ground truth of the defect boards (``tests/support/defect_boards.py``) in the vision's terms.

For each rendered board: its defects as the measurement's contract states them (kind,
``x_mm``/``y_mm`` of the centre in image A's undistorted frame from its top-left corner, x along
the feed; ``length_mm`` along the feed, ``width_mm`` across it; ``depth_um``), whether each is
above the sizes the vision is required to find (``detectable``), and the board's true ASTM
D1666 grade by :func:`vision.defects.grading.grade` applied to the true defects.  Renders are
cached on
disk (keyed by the renderer's source and the board's parameters) so repeated test runs only
measure.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import pickle
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tests.support import defect_boards
from tests.support.defect_boards import DefectBoard, Defects, render_defect_board
from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import Grade, grade_pair

#: kinds whose location is the whole field (matched by kind alone)
FIELD_WIDE = ("raised_grain", "chatter", "snipe")


@dataclass(frozen=True)
class TrueDefect:
    """One true defect in the contract's terms (``detectable``: above the required sizes)."""

    kind: str
    x_mm: float
    y_mm: float
    length_mm: float
    width_mm: float
    depth_um: float | None
    detectable: bool


def _image_xy(board: DefectBoard, xb: float, yb: float) -> tuple[float, float]:
    """Board point (x at shot A, y across) -> A's image frame, mm from the top-left corner."""
    cam = board.rig.camera
    ppm = cam.px_per_mm
    r = math.radians(board.roll_deg)
    xi, eta = xb - cam.cx / ppm, yb
    u = cam.cx + (xi * math.cos(r) - eta * math.sin(r)) * ppm
    v = cam.cy + (xi * math.sin(r) + eta * math.cos(r)) * ppm
    return u / ppm, v / ppm


def snipe_sag_um(board: DefectBoard) -> float:
    """The snipe's height over the field, largest distance above its chord, um."""
    d = board.defects
    if not d.snipe_um:
        return 0.0
    cam = board.rig.camera
    ppm = cam.px_per_mm
    w = board.image_a.shape[1]
    # the renderer's grid starts x0 mm before the field's centre reach (as it computes it)
    rr = math.radians(board.roll_deg)
    cx, cy = cam.cx, cam.cy
    reach = (abs(cx * math.cos(rr)) + abs(cy * math.sin(rr)) + abs(board.shift_px) + 30) / ppm
    x0 = cx / ppm - reach - 1.0
    xs = np.linspace(0.0, w / ppm, 400)
    z = -d.snipe_um * np.exp(-(xs - x0) / d.snipe_mm)
    chord = z[0] + (z[-1] - z[0]) * (xs - xs[0]) / (xs[-1] - xs[0])
    return float((z - chord).max())


def board_truth(board: DefectBoard) -> tuple[TrueDefect, ...]:
    """The board's true defects (see the module's docstring)."""
    cam = board.rig.camera
    ppm = cam.px_per_mm
    h, w = board.image_a.shape
    fx, fy, fl, fw = w / 2 / ppm, h / 2 / ppm, w / ppm, h / ppm
    out: list[TrueDefect] = []
    for p in board.placed:
        x, y = _image_xy(board, p.x_mm, p.y_mm)
        a = math.radians(p.angle_deg)
        length = abs(p.length_mm * math.cos(a)) + abs(p.width_mm * math.sin(a))
        width = abs(p.length_mm * math.sin(a)) + abs(p.width_mm * math.cos(a))
        if p.kind == "torn":
            out.append(TrueDefect("torn_grain", x, y, length, width, p.depth_um,
                                  p.depth_um >= 50.0 and p.length_mm >= 2.0))
        elif p.kind == "fuzzy":
            out.append(TrueDefect("fuzzy_grain", x, y, length, width, None,
                                  board.defects.fuzzy_um >= 10.0))
        elif p.kind == "chip":
            out.append(TrueDefect("chip_mark", x, y, length, width, p.depth_um,
                                  p.depth_um >= 30.0))
        elif p.kind == "nick":
            out.append(TrueDefect("knife_nick", fx, y, fl, width, p.depth_um,
                                  -p.depth_um >= 10.0))
    d = board.defects
    if d.raised_um:
        # along-feed slope of the ridges: none when the rings run along the feed
        out.append(TrueDefect("raised_grain", fx, fy, fl, fw, -d.raised_um,
                              d.raised_um >= 10.0 and abs(math.sin(math.radians(
                                  board.ring_angle_deg))) >= 0.25))
    if d.chatter_um:
        far = min(abs(1.0 / d.chatter_passes - n / board.knives) for n in range(board.knives + 1))
        out.append(TrueDefect("chatter", fx, fy, fl, fw, d.chatter_um,
                              d.chatter_um >= 0.5 and far >= 0.03))
    if d.snipe_um:
        sag = snipe_sag_um(board)
        out.append(TrueDefect("snipe", fl / 8, fy, fl / 4, fw, sag, sag >= 3.0))
    return tuple(out)


def _cache_dir() -> Path:
    root = Path(os.environ.get("PLANER_DEFECT_CACHE", tempfile.gettempdir()))
    path = root / "planer_defect_boards"
    path.mkdir(parents=True, exist_ok=True)
    return path


_SOURCE = hashlib.sha1(Path(defect_boards.__file__).read_bytes()).hexdigest()[:12]
_MEMO: dict[str, DefectBoard] = {}


def cached_board(**spec: Any) -> DefectBoard:
    """:func:`render_defect_board` with ``spec``, cached in memory and on disk."""
    key = hashlib.sha1((_SOURCE + repr(sorted(spec.items()))).encode()).hexdigest()[:20]
    board = _MEMO.get(key)
    if board is None:
        f = _cache_dir() / f"{key}.pkl"
        if f.exists():
            try:
                board = pickle.loads(f.read_bytes())
            except Exception:  # a torn write: render again
                board = None
        if board is None:
            board = render_defect_board(**spec)
            tmp = f.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(pickle.dumps(board))
            tmp.replace(f)
        _MEMO[key] = board
    return board


KINDS = ("torn_grain", "raised_grain", "fuzzy_grain", "chip_mark", "knife_nick", "chatter",
         "snipe", "clean")
SPECIES = ("pine", "oak", "beech")


def board_spec(i: int, kind: str | None = None) -> dict[str, Any]:
    """The i-th acceptance board: its kind in turn (or ``kind``), the rest drawn from seed i.

    Sizes over item 2's ranges; species in turn; speed 50 mm/s-2 m/s (log-uniform); roll
    +-3 deg; read noise 1.5-20 DN; LED imbalance +-5 %; true shift 12-36 px, encoder slip
    +-4 px.
    """
    rng = np.random.default_rng(5000 + i)
    kind = KINDS[i % len(KINDS)] if kind is None else kind
    if kind == "torn_grain":
        across = bool(rng.integers(0, 2))
        torn = (float(rng.uniform(0.05, 1.0)), float(rng.uniform(2, 15)),
                float(rng.uniform(1.5, 4.0)), float((90 if across else 0) + rng.uniform(-10, 10)))
        defects = Defects(torn=(torn,))
    elif kind == "raised_grain":
        defects = Defects(raised_um=float(rng.uniform(10, 50)))
    elif kind == "fuzzy_grain":
        defects = Defects(fuzzy_um=float(rng.uniform(10, 30)))
    elif kind == "chip_mark":
        defects = Defects(chips_um=tuple(float(v) for v in rng.uniform(30, 150,
                                                                       int(rng.integers(1, 3)))))
    elif kind == "knife_nick":
        defects = Defects(nick_um=float(rng.uniform(10, 40)), nick_mm=float(rng.uniform(0.3, 1.0)))
    elif kind == "chatter":
        defects = Defects(chatter_um=float(rng.uniform(0.5, 2.5)),
                          chatter_passes=float(rng.uniform(3.3, 7.7)))
    elif kind == "snipe":
        defects = Defects(snipe_um=float(rng.uniform(50, 200)), snipe_mm=float(rng.uniform(20, 60)))
    else:
        defects = Defects()
    ring = float(rng.uniform(15, 90) if kind == "raised_grain" else rng.uniform(-20, 20))
    return dict(
        seed=7000 + i, species=SPECIES[i % 3], defects=defects, ring_angle_deg=ring,
        speed_mm_s=float(np.exp(rng.uniform(math.log(50), math.log(2000)))),
        roll_deg=float(rng.uniform(-3, 3)), shift_px=float(rng.uniform(12, 36)),
        slip_px=float(rng.uniform(-4, 4)), imbalance=float(rng.uniform(-0.05, 0.05)),
        noise_dn=float(rng.uniform(1.5, 20.0)),
    )


def true_defects(board: DefectBoard) -> tuple[Defect, ...]:
    """The board's true defects as :class:`vision.defects.detect.Defect` (confidence 1)."""
    return tuple(Defect(DefectKind(t.kind), t.x_mm, t.y_mm, t.length_mm, t.width_mm,
                        t.depth_um, 1.0) for t in board_truth(board))


def true_grade(board: DefectBoard) -> Grade:
    """The board's true D1666 grade (:func:`vision.defects.grading.grade_pair` of its defects)."""
    return grade_pair(true_defects(board))


# -- scoring: the acceptance's criteria, shared by the test and the command line -----------------

#: the tuning split (the boards the detectors' thresholds were looked at on) and a held-out
#: split of other seeds (board indices; :func:`board_spec`)
TUNING = range(0, 240)
HELD_OUT = range(1000, 1240)


def board_grade(found: tuple[Defect, ...] | None) -> int | None:
    """The D1666 grade of a rendered board from its one pair's defects, raw snipe counted.

    A pair's own grade leaves snipe to its board (:func:`vision.defects.grading.pair_grade`):
    one pair cannot tell snipe from the rig's bow. Each rendered board is one pair whose
    lights do not fall off (no bow), so its bend is its snipe and the rule is applied to its
    defects as reported (:func:`vision.defects.grading.grade_pair`, as a board's grade counts
    an unplaced pair's raw snipe), as to its true defects (:func:`true_grade`).
    """
    return None if found is None else grade_pair(found).grade


@dataclass(frozen=True)
class Outcome:
    """One board's measurement: its truth, what was found (``None``: no defects reported).

    ``refused``: the cuttermark measurement refused the pair (its defects, if any, came with
    the refusal: :func:`vision.defects.refused.surface_of`).
    """

    index: int
    kind: str  # the board's kind (:data:`KINDS`)
    truth: tuple[TrueDefect, ...]
    found: tuple[Defect, ...] | None
    true_grade: int
    grade: int | None  # the board's (:func:`board_grade`)
    refused: bool = False


def matches(t: TrueDefect, d: Defect) -> bool:
    """Whether a found defect is the true one: same kind, centre within 2 mm (a knife nick's
    band within 2 mm across the feed; raised grain, chatter and snipe by kind alone)."""
    if d.kind.value != t.kind:
        return False
    if t.kind in FIELD_WIDE:
        return True
    if t.kind == "knife_nick":
        return abs(d.y_mm - t.y_mm) <= 2.0
    return math.hypot(d.x_mm - t.x_mm, d.y_mm - t.y_mm) <= 2.0


def measure_boards(indices: Any, kind: str | None = None) -> list[Outcome]:
    """Measure the boards ``indices`` (:func:`board_spec`; every one of ``kind`` when given)
    with ``Measurer(defects=True)``."""
    from core.errors import MeasurementError
    from vision.defects.refused import surface_of
    from vision.pipeline import Measurer

    measurers: dict[tuple[int, ...], Measurer] = {}
    out = []
    for i in indices:
        b = cached_board(**board_spec(i, kind))
        m = measurers.get(b.image_a.shape)
        if m is None:
            m = measurers[b.image_a.shape] = Measurer(b.rig, b.image_a.shape, knives=4,
                                                      defects=True)
        refused = False
        try:
            r = m.measure(b.image_a, b.image_b, counts_a=b.counts_a, counts_b=b.counts_b,
                          speed_mm_s=b.speed_mm_s)
            found = r.defects
        except MeasurementError as exc:  # the measurement itself refused the pair
            refused = True
            surface = surface_of(exc)  # its defects all the same, where a map was made
            found = None if surface is None else surface.defects
        out.append(Outcome(i, kind or KINDS[i % len(KINDS)], board_truth(b), found,
                           true_grade(b).grade, board_grade(found), refused))
    return out


@dataclass(frozen=True)
class Score:
    """Per kind: true positives, misses (of the detectable defects), false positives; clean
    boards and how many gave no defect; graded boards and how many within one step; pairs
    whose cuttermark measurement was refused (``refused``) and of those, the ones whose
    defects came with the refusal (``refused_mapped``, judged with the others); boards of
    each kind judged (``judged``)."""

    tp: dict[str, int]
    fn: dict[str, int]
    fp: dict[str, int]
    clean: int
    clean_ok: int
    graded: int
    grade_ok: int
    refused: int
    boards: int
    judged: dict[str, int] = dataclasses.field(default_factory=dict)
    refused_mapped: int = 0

    def recall(self, kind: str) -> float:
        """Found / (found + missed detectable), 1 without any."""
        n = self.tp.get(kind, 0) + self.fn.get(kind, 0)
        return self.tp.get(kind, 0) / n if n else 1.0

    def precision(self, kind: str) -> float:
        """Right / reported, 1 without any reported."""
        n = self.tp.get(kind, 0) + self.fp.get(kind, 0)
        return self.tp.get(kind, 0) / n if n else 1.0

    def table(self) -> str:
        """The Markdown table of docs/vision.md."""
        lines = ["| kind | boards judged | recall | precision |", "|---|---|---|---|"]
        for k in KINDS[:-1]:
            tp, fn, fp = self.tp.get(k, 0), self.fn.get(k, 0), self.fp.get(k, 0)
            lines.append(f"| {k} | {self.judged.get(k, 0)} | {tp}/{tp + fn} = "
                         f"{self.recall(k):.2f} | {tp}/{tp + fp} = {self.precision(k):.2f} |")
        lines.append(f"| clean: no defect | {self.clean} | {self.clean_ok}/{self.clean} | |")
        lines.append(f"| D1666 grade within one step | {self.graded} | {self.grade_ok}/"
                     f"{self.graded} = {self.grade_ok / max(self.graded, 1):.3f} | |")
        lines.append(f"| refused by the measurement (defects reported) | | {self.refused}/"
                     f"{self.boards} ({self.refused_mapped}) | |")
        return "\n".join(lines)


def score(outcomes: list[Outcome]) -> Score:
    """The acceptance's counts over measured boards (refused pairs are counted apart)."""
    tp: dict[str, int] = {}
    fn: dict[str, int] = {}
    fp: dict[str, int] = {}
    judged: dict[str, int] = {}
    clean = clean_ok = graded = grade_ok = refused = mapped = 0
    for o in outcomes:
        refused += o.refused or o.found is None
        if o.found is None:
            continue
        mapped += o.refused
        judged[o.kind] = judged.get(o.kind, 0) + 1
        if o.kind == "clean":
            clean += 1
            clean_ok += len(o.found) == 0
        graded += 1
        grade_ok += o.grade is not None and abs(o.grade - o.true_grade) <= 1
        used: set[int] = set()
        for t in o.truth:
            hit = next((j for j, d in enumerate(o.found) if j not in used and matches(t, d)),
                       None)
            if hit is not None:
                used.add(hit)
                tp[t.kind] = tp.get(t.kind, 0) + 1
            elif t.detectable:
                fn[t.kind] = fn.get(t.kind, 0) + 1
        for j, d in enumerate(o.found):
            if j not in used:
                fp[d.kind.value] = fp.get(d.kind.value, 0) + 1
    return Score(tp, fn, fp, clean, clean_ok, graded, grade_ok, refused, len(outcomes), judged,
                 mapped)


def main(argv: list[str] | None = None) -> int:
    """``python -m tests.support.defect_truth [--kind KIND] [tuning|held-out|LO:HI ...]``."""
    import argparse

    ap = argparse.ArgumentParser(
        prog="python -m tests.support.defect_truth",
        description="Render (cached in $TMPDIR/planer_defect_boards), measure and score the "
                    "independent renderer's defect boards: the tables of docs/vision.md.")
    ap.add_argument("splits", nargs="*", default=["tuning", "held-out"],
                    help="'tuning' (boards 0:240), 'held-out' (1000:1240) or a board range "
                         "LO:HI (the fresh split: 5000:5240); default: tuning held-out")
    ap.add_argument("--kind", choices=KINDS, default=None,
                    help="every board of this kind (the others drawn as ever from the "
                         "board's seed) instead of the kinds in turn")
    args = ap.parse_args(argv)
    for name in args.splits:
        if name == "tuning":
            idx: Any = TUNING
        elif name == "held-out":
            idx = HELD_OUT
        else:
            try:
                lo, hi = (int(v) for v in name.split(":"))
            except ValueError:
                ap.error(f"split must be tuning, held-out or LO:HI, got {name!r}")
            idx = range(lo, hi)
        what = f", every one {args.kind}" if args.kind else ""
        print(f"## {name} (boards {idx.start}..{idx.stop - 1}{what})")
        print(score(measure_boards(idx, args.kind)).table())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
