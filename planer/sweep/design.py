"""A sweep file and its grid: which HIL runs a sweep makes (pure; no simulator, no I/O but reading).

The sweep file (``config/sweeps/*.toml``)::

    base = "default"              # scenario of config/hil.toml, or "path.toml[:name]"
    seeds = [0, 1]                # every grid point runs once per seed
    [fixed]                       # optional: values for every run (same keys as the grid)
    distance_m = 5.0
    [grid]                        # every combination of these lists
    target_pitch_mm = [1.0, 1.5]
    "sim.piezo.resonance_hz" = [150.0, 800.0]
    "sim.cutterhead.knives,sim.cutterhead.runout_um" = [[2, [0.0, 3.0]], [4, [0, 4, -2, 2]]]

Keys are scenario keys (``config/hil.toml``: ``distance_m``, ``runout_um``, ``target_pitch_mm``,
``initial_feed_mm_s``, ``max_sim_s``) or dotted keys into the simulator (``sim.TABLE.KEY``,
``config/sim.toml``) and the service's configuration (``machine.TABLE.KEY``,
``config/machine.toml``). A key made of several keys joined by commas varies them together: each
value is a list with one entry per key (knives with runout lists of matching length).

``[[grid]]`` (an array of tables) instead of ``[grid]`` gives several grids whose runs are joined:
one-at-a-time variations around the base (one short grid per key) plus a few corners. A point
that equals an earlier one (same values once the base fills the keys its grid leaves out, same
seed) runs once.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from config.loading import Section, load_toml
from core.errors import ConfigError

SCENARIO_KEYS = ("distance_m", "runout_um", "initial_feed_mm_s", "target_pitch_mm", "max_sim_s")
"""Scenario keys a sweep may set (``seed`` comes from ``seeds``)."""
CONFIG_PREFIXES = ("sim", "machine")
"""Dotted keys start with one of these: the simulator's and the service's configuration."""
MAX_POINTS = 100_000
"""Refuse grids larger than this (a typo in a list would otherwise hang the planner)."""

Axis = tuple[tuple[str, ...], tuple[tuple[Any, ...], ...]]
"""One axis of a grid: the keys varied together and, per entry, one value per key."""


@dataclass(frozen=True)
class Sweep:
    """A parsed sweep file.

    Attributes
    ----------
    base : str
        The base scenario (``load_scenario`` argument).
    seeds : tuple of int
        Seeds; every grid point runs once per seed.
    fixed : mapping
        Key -> value applied to every run.
    grids : tuple of tuple of (tuple of str, tuple)
        Per grid, its axes in file order: the keys varied together and their values (one tuple
        of values per key group entry).
    source : Path or None
        The file it came from.
    """

    base: str
    seeds: tuple[int, ...]
    fixed: Mapping[str, Any] = field(default_factory=dict)
    grids: tuple[tuple[Axis, ...], ...] = ()
    source: Path | None = None

    @property
    def keys(self) -> tuple[str, ...]:
        """Every varied key, in the order of first appearance (the CSV's input columns)."""
        out: list[str] = []
        for grid in self.grids:
            for group, _ in grid:
                out.extend(k for k in group if k not in out)
        return tuple(out)


@dataclass(frozen=True)
class Point:
    """One run of a sweep: its number, its seed and the values of its grid's keys.

    Attributes
    ----------
    index : int
        Position in the sweep (the CSV's ``run`` column), from 0.
    seed : int
        Simulator seed.
    values : mapping
        Key -> value, the fixed ones first, then the point's grid values.
    """

    index: int
    seed: int
    values: Mapping[str, Any]


def check_key(key: str, where: str) -> str:
    """Check that ``key`` is a scenario key or a dotted ``sim.``/``machine.`` key; return it.

    Raises
    ------
    ConfigError
        Naming ``where`` (``sweep.toml: grid."sim.x"``) and the key.
    """
    if key in SCENARIO_KEYS:
        return key
    head, _, rest = key.partition(".")
    parts = rest.split(".") if rest else []
    if head in CONFIG_PREFIXES and parts and all(parts):
        return key
    raise ConfigError(
        f"{where}: unknown key {key!r}: use a scenario key ({', '.join(SCENARIO_KEYS)}) or a "
        f"dotted key sim.TABLE.KEY / machine.TABLE.KEY"
    )


def _axis(key: str, values: Any, where: str) -> Axis:
    group = tuple(k.strip() for k in key.split(","))
    for k in group:
        check_key(k, where)
    if len(set(group)) != len(group):
        raise ConfigError(f"{where}: key {key!r} names a key twice")
    if not isinstance(values, list) or not values:
        raise ConfigError(f"{where}.{json.dumps(key)} must be a non-empty list of values")
    out = []
    for i, v in enumerate(values):
        if len(group) == 1:
            out.append((v,))
            continue
        if not isinstance(v, list) or len(v) != len(group):
            raise ConfigError(
                f"{where}.{json.dumps(key)}[{i}] must be a list of {len(group)} values (one per "
                f"key: {', '.join(group)}), got {v!r}"
            )
        out.append(tuple(v))
    return group, tuple(out)


def _grid(table: Any, where: str) -> tuple[Axis, ...]:
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where} must be a table of key = [values]")
    axes = tuple(_axis(str(k), v, where) for k, v in table.items())
    seen: list[str] = []
    for group, _ in axes:
        for k in group:
            if k in seen:
                raise ConfigError(f"{where}: key {k!r} is varied twice")
            seen.append(k)
    return axes


def sweep_from_dict(data: Mapping[str, Any], *, source: Path | None = None) -> Sweep:
    """Build and check a :class:`Sweep` from a parsed sweep file (errors name the key).

    Raises
    ------
    ConfigError
        Missing ``base``/``seeds``/``grid``, a bad key, an empty list, a group value of the
        wrong length, a grid of more than ``MAX_POINTS`` runs.
    """
    s = Section(data, "")
    base = s.string("base")
    if not base:
        raise ConfigError("base must name a scenario")
    raw_seeds = s.raw("seeds", [0])
    if not isinstance(raw_seeds, list) or not raw_seeds:
        raise ConfigError(f"seeds must be a non-empty list of integers, got {raw_seeds!r}")
    for i, sd in enumerate(raw_seeds):
        if isinstance(sd, bool) or not isinstance(sd, int) or sd < 0:
            raise ConfigError(f"seeds[{i}] must be an integer >= 0, got {sd!r}")
    if len(set(raw_seeds)) != len(raw_seeds):
        raise ConfigError("seeds: a seed is listed twice")
    fixed_raw = s.raw("fixed", {})
    if not isinstance(fixed_raw, Mapping):
        raise ConfigError("fixed must be a table of key = value")
    fixed = {check_key(str(k), "fixed"): v for k, v in fixed_raw.items()}
    raw_grid = s.raw("grid")
    if isinstance(raw_grid, list):
        if not raw_grid:
            raise ConfigError("grid must hold at least one table")
        grids = tuple(_grid(g, f"grid[{i}]") for i, g in enumerate(raw_grid))
    else:
        grids = (_grid(raw_grid, "grid"),)
    for grid in grids:
        for group, _ in grid:
            both = [k for k in group if k in fixed]
            if both:
                raise ConfigError(f"grid: key {both[0]!r} is both fixed and varied")
    s.reject_unknown()
    total = sum(math.prod(len(v) for _, v in g) for g in grids) * len(raw_seeds)
    if total > MAX_POINTS:
        raise ConfigError(f"grid: {total} runs is more than {MAX_POINTS}")
    return Sweep(base=base, seeds=tuple(raw_seeds), fixed=fixed, grids=grids, source=source)


def load_sweep(path: str | Path) -> Sweep:
    """Load a sweep file; errors name the file and the key.

    A relative ``base`` path (``"my.toml:name"``) is resolved from the sweep file's folder when
    it exists there.
    """
    p = Path(path)
    data = load_toml(p)
    try:
        sw = sweep_from_dict(data, source=p)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None
    file_part, sep, rest = sw.base.partition(".toml")
    if sep:
        given = Path(file_part + sep)
        if not given.is_absolute() and (p.parent / given).is_file():
            sw = replace(sw, base=f"{p.parent / given}{rest}")
    return sw


def grid_combinations(
    grid: Sequence[tuple[tuple[str, ...], Sequence[tuple[Any, ...]]]],
) -> list[dict[str, Any]]:
    """Every combination of one grid's axes, the first axis varying slowest.

    Parameters
    ----------
    grid : sequence of (keys, values)
        Axes: the keys varied together and, per entry, one value per key.

    Returns
    -------
    list of dict
        ``prod(len(values))`` dicts key -> value, in ``itertools.product`` order.
    """
    out = []
    for combo in itertools.product(*(values for _, values in grid)):
        point: dict[str, Any] = {}
        for (group, _), entry in zip(grid, combo, strict=True):
            point.update(zip(group, entry, strict=True))
        out.append(point)
    return out


def canonical(value: Any) -> str:
    """A value as the CSV shows it: JSON for lists, ``repr``-short numbers, strings as they are.

    Integers and integral floats differ (``4`` vs ``4.0``) only in type, not in the text
    compared: both read ``4``, so the same plant written two ways counts once.
    """
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        return str(int(value))
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(canonical(v) for v in value) + "]"
    return str(value)


def expand(sweep: Sweep, base_values: Mapping[str, Any] | None = None) -> list[Point]:
    """Every run of a sweep: each grid's combinations, each once per seed, duplicates dropped.

    Parameters
    ----------
    sweep : Sweep
        The sweep.
    base_values : mapping, optional
        Key -> the base's value for keys a grid leaves out (for dropping duplicates across
        grids); keys without a base value count as "not set".

    Returns
    -------
    list of Point
        Numbered from 0: for each grid, for each combination, for each seed.
    """
    base = dict(base_values or {})
    keys = sweep.keys
    seen: set[tuple[str, ...]] = set()
    points: list[Point] = []
    for grid in sweep.grids:
        for combo in grid_combinations(grid):
            for seed in sweep.seeds:
                full = {k: combo.get(k, base.get(k)) for k in keys}
                ident = (str(seed),
                         *("" if full[k] is None else canonical(full[k]) for k in keys))
                if ident in seen:
                    continue
                seen.add(ident)
                points.append(Point(index=len(points), seed=seed,
                                    values={**sweep.fixed, **combo}))
    return points
