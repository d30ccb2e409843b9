"""Plots of a sweep's outcome over its grid (matplotlib figures, no pyplot state).

One figure per outcome, one panel per varied key: every successful run is a point at its value
of that key; the runs whose other keys all hold their base values (the one-at-a-time line
through the base plant) are filled and joined by their mean, the others (corners, other
combinations) hollow. Failed runs are red crosses on the axis' floor; a run that never settled
(empty distance) is a triangle at the top of the distance panel.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

OUTCOMES = (
    ("final_true_cv", "final true uniformity CV", 1.0, (0.05,)),
    ("final_pitch_error", "final pitch error, %", 100.0, (-2.0, 2.0)),
    ("cv_settled_after_mm", "board to CV <= 0.05 after the loop closed, m", 1e-3, ()),
    ("feed_ratio", "final feed / fastest the class allows", 1.0, (1.0,)),
    ("offset_ratio", "largest piezo offset / stroke", 1.0, (1.0,)),
)
"""(column, axis label, scale, reference lines) of each figure."""
TITLE_CHARS_PER_IN = 14
"""Characters of a 9 pt title per inch of figure width it may fill (its lines are wrapped)."""


def _float(text: str) -> float | None:
    try:
        v = float(text)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def varied_keys(rows: Sequence[Mapping[str, str]], keys: Sequence[str]) -> list[str]:
    """The keys that take more than one value over the rows."""
    return [k for k in keys if len({r.get(k, "") for r in rows}) > 1]


def _order(text: str) -> tuple[Any, ...]:
    """Sort key of a value's text: numbers by value, lists by length then by their spread."""
    v = _float(text)
    if v is not None:
        return (0, v, text)
    items = [_float(x) for x in text.strip("[]").split(",")] if text.startswith("[") else []
    nums = [x for x in items if x is not None]
    if nums and len(nums) == len(items):
        return (1, len(nums), max(nums) - min(nums), text)
    return (2, 0, 0.0, text)


def _positions(values: Sequence[str]) -> tuple[dict[str, float], list[str] | None]:
    """The x of each distinct value: numeric when all are numbers, else 0, 1, ... with labels."""
    distinct = sorted(set(values), key=_order)
    if all(_float(v) is not None for v in distinct):
        return {v: float(_float(v)) for v in distinct}, None  # type: ignore[arg-type]
    return {v: float(i) for i, v in enumerate(distinct)}, distinct


def _on_line(row: Mapping[str, str], key: str, keys: Sequence[str], bases: Mapping[str, str],
             group: frozenset[str]) -> bool:
    """Whether ``row`` lies on ``key``'s one-at-a-time line.

    It differs from the base only in keys varied together with ``key`` (``group``), and in
    ``key`` itself unless it is the base plant.
    """
    diff = {k for k in keys if row.get(k, "") != bases.get(k, "")}
    return diff <= group and (key in diff or not diff)


def outcome_figure(
    rows: Sequence[Mapping[str, str]],
    keys: Sequence[str],
    bases: Mapping[str, str],
    outcome: str,
    *,
    groups: Sequence[Sequence[str]] = (),
) -> Any:
    """One outcome over every varied key (a matplotlib ``Figure``; no pyplot).

    Parameters
    ----------
    rows : sequence of mapping
        ``results.csv`` rows (strings).
    keys : sequence of str
        The input columns.
    bases : mapping
        Base value of each key, as the CSV writes it.
    outcome : str
        One of the columns of ``OUTCOMES``.
    groups : sequence of sequence of str
        Keys a grid varies together (its axes); a key's line also takes the runs that change
        the keys of its smallest group (knives with their runout lists).
    """
    from matplotlib.figure import Figure

    spec = {o[0]: o for o in OUTCOMES}
    if outcome not in spec:
        raise ValueError(f"outcome must be one of {', '.join(spec)}, got {outcome!r}")
    _, ylabel, scale, refs = spec[outcome]
    shown = varied_keys(rows, keys) or list(keys[:1])
    ncol = min(3, max(1, len(shown)))
    nrow = max(1, math.ceil(len(shown) / ncol))
    fig = Figure(figsize=(4.2 * ncol, 3.0 * nrow), layout="constrained")
    ok = [r for r in rows if not r.get("error")]
    vals = [_float(r.get(outcome, "")) for r in ok]
    finite = [v * scale for v in vals if v is not None]
    top = max(finite + [r * 1.0 for r in refs] + [0.0]) if finite or refs else 1.0
    floor = min(finite + [r * 1.0 for r in refs] + [0.0]) if finite or refs else 0.0
    for i, key in enumerate(shown):
        ax = fig.add_subplot(nrow, ncol, i + 1)
        pos, labels = _positions([r.get(key, "") for r in rows])
        mine = [frozenset(g) for g in groups if key in g] or [frozenset([key])]
        group = min(mine, key=len) | {key}
        line: dict[float, list[float]] = {}
        for r in rows:
            x = pos[r.get(key, "")]
            on_line = _on_line(r, key, keys, bases, group)
            if r.get("error"):
                ax.plot([x], [floor], "x", color="tab:red", ms=7)
                continue
            v = _float(r.get(outcome, ""))
            if v is None:
                if outcome.endswith("_after_mm"):
                    ax.plot([x], [top * 1.08 if top > 0 else 1.0], "^", color="tab:orange",
                            ms=6, mfc="tab:orange" if on_line else "none")
                continue
            y = v * scale
            if on_line:
                line.setdefault(x, []).append(y)
            ax.plot([x], [y], "o", color="tab:blue" if on_line else "0.55",
                    mfc="tab:blue" if on_line else "none", ms=5, alpha=0.9)
        if line:
            xs = sorted(line)
            ax.plot(xs, [sum(line[x]) / len(line[x]) for x in xs], "-", color="tab:blue", lw=1)
        for ref in refs:
            ax.axhline(ref, color="tab:green", lw=0.8, ls="--")
        if labels is not None:
            ax.set_xticks(range(len(labels)))
            ax.set_xticklabels(labels, rotation=35, ha="right", fontsize=6)
        base = bases.get(key, "")
        if base in pos:
            ax.axvline(pos[base], color="0.8", lw=0.8, zorder=0)
        ax.set_xlabel(key, fontsize=8)
        ax.set_ylabel(ylabel if i % ncol == 0 else "", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    never = "; triangles: never settled" if outcome.endswith("_after_mm") else ""
    title = (f"{ylabel} over the sweep ({len(ok)} runs, {len(rows) - len(ok)} failed; "
             f"filled: other keys at base{never})")
    # wrapped to the figure's width (9 pt: about 14 characters per inch), never cut off
    fig.suptitle(textwrap.fill(title, width=int(TITLE_CHARS_PER_IN * fig.get_figwidth())),
                 fontsize=9)
    return fig


def save_plots(
    rows: Sequence[Mapping[str, str]],
    keys: Sequence[str],
    bases: Mapping[str, str],
    out_dir: str | Path,
    *,
    stem: str = "sweep",
    groups: Sequence[Sequence[str]] = (),
) -> list[Path]:
    """Write ``out_dir/<stem>_<outcome>.png`` for every outcome; return the paths."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from core.fileio import atomic_writer

    out = Path(out_dir)
    paths = []
    for name, *_ in OUTCOMES:
        fig = outcome_figure(rows, keys, bases, name, groups=groups)
        FigureCanvasAgg(fig)
        path = out / f"{stem}_{name}.png"
        with atomic_writer(path, binary=True) as fh:
            fig.savefig(fh, format="png", dpi=90)
        paths.append(path)
    return paths
