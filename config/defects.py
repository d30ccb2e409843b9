"""The simulator's wood defects: the kinds, their physical ranges and the ``[defects]`` table.

``[defects]`` in a simulator file (``config/sim.py`` loads it into :class:`DefectsConfig`)::

    [defects]
    every_nth_board = 2          # boards 2, 4, 6, ... carry defects (0: none)
    seed = 0                     # the draw's own seed (added to the simulator's)

    [[defects.place]]
    kind = "torn_grain"          # one of DEFECT_KINDS
    per_board = 8.0              # how many on each such board (the fraction: drawn)
    depth_um = [100.0, 600.0]    # optional: ranges to draw from, within the kind's
    length_mm = [3.0, 12.0]
    along_fraction = 0.5         # torn grain: the share along the grain (else across)

Every range must lie within the kind's physical one (:data:`DEFECT_KINDS`); an error names
the key and the bad value. What each kind looks like: :mod:`plant_sim.rendering.defects`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from config.loading import Section
from core.errors import ConfigError

__all__ = ["DEFECT_KINDS", "DefectPlaceConfig", "DefectRange", "DefectsConfig", "defects_table"]


@dataclass(frozen=True)
class DefectRange:
    """The physical ranges of one kind: ``(lo, hi)``, or ``None`` where it has no such size.

    ``length_mm`` / ``width_mm`` along / across the feed (torn grain: the longer side, along or
    across the grain; a knife nick runs the board's length, chatter and snipe its width).
    """

    depth_um: tuple[float, float]
    length_mm: tuple[float, float] | None
    width_mm: tuple[float, float] | None = None
    period_mm: tuple[float, float] | None = None


DEFECT_KINDS: Mapping[str, DefectRange] = {
    "torn_grain": DefectRange((50.0, 1000.0), (2.0, 15.0)),
    "raised_grain": DefectRange((10.0, 50.0), (10.0, 60.0), (10.0, 40.0), (1.5, 8.0)),
    "fuzzy_grain": DefectRange((10.0, 30.0), (5.0, 40.0), (3.0, 30.0)),
    "chip_mark": DefectRange((30.0, 150.0), (1.0, 4.0), (1.0, 4.0)),
    "knife_nick": DefectRange((10.0, 100.0), None, (0.3, 2.0)),
    "chatter": DefectRange((1.0, 10.0), (100.0, 2000.0), None, (3.0, 20.0)),
    "snipe": DefectRange((20.0, 300.0), (50.0, 150.0)),
}
"""Each kind's physical ranges: torn grain 0.05-1 mm deep, 2-15 mm (the other side 20-50 % of
it); raised grain 10-50 um high, rings 1.5-8 mm apart; fuzzy grain 10-30 um rms; chip marks
30-150 um deep, 1-4 mm; a knife nick's notch 10-100 um over 0.3-2 mm; chatter 1-10 um at a
period of 3-20 mm (never the pitch: at most 2.5 mm); snipe 20-300 um over the first or last
50-150 mm of a board."""


@dataclass(frozen=True)
class DefectPlaceConfig:
    """One ``[[defects.place]]`` entry: a kind, how many per board, the ranges drawn from."""

    kind: str
    per_board: float
    depth_um: tuple[float, float]
    length_mm: tuple[float, float] | None
    width_mm: tuple[float, float] | None
    period_mm: tuple[float, float] | None
    along_fraction: float = 0.5


@dataclass(frozen=True)
class DefectsConfig:
    """``[defects]``: which boards carry defects and which (none by default)."""

    every_nth_board: int = 0
    seed: int = 0
    place: tuple[DefectPlaceConfig, ...] = ()

    @property
    def active(self) -> bool:
        """Whether any board carries a defect."""
        return self.every_nth_board > 0 and any(p.per_board > 0 for p in self.place)

    def on_board(self, board_id: int) -> bool:
        """Whether ``board_id`` is one of the boards that carry defects."""
        n = self.every_nth_board
        return n > 0 and board_id > 0 and board_id % n == 0


def _range(t: Section, name: str, allowed: tuple[float, float] | None
           ) -> tuple[float, float] | None:
    if allowed is None:
        if t.has(name):
            raise ConfigError(f"{t.key(name)}: this kind has no {name} (got {t.raw(name)!r})")
        return None
    if not t.has(name):
        return allowed
    lo, hi = t.numbers(name, length=2)
    if not allowed[0] <= lo <= hi <= allowed[1]:
        raise ConfigError(f"{t.key(name)} must be [lo, hi] with {allowed[0]:g} <= lo <= hi <= "
                          f"{allowed[1]:g}, got {[lo, hi]!r}")
    return lo, hi


def defects_table(s: Section) -> DefectsConfig:
    """Load and check ``[defects]`` (missing: none); errors name the key and the value."""
    d = DefectsConfig()
    every = s.integer("every_nth_board", d.every_nth_board, lo=0, hi=1_000_000)
    seed = s.integer("seed", d.seed, lo=0)
    items = s.raw("place", [])
    if not isinstance(items, list):
        raise ConfigError(f"{s.key('place')} must be a list of tables, got {items!r}")
    place = []
    for i, item in enumerate(items):
        t = Section(item, f"{s.key('place')}[{i}]")
        kind = t.string("kind", choices=tuple(DEFECT_KINDS))
        r = DEFECT_KINDS[kind]
        place.append(DefectPlaceConfig(
            kind=kind,
            per_board=t.number("per_board", lo=0.0, hi=10_000.0),
            depth_um=_range(t, "depth_um", r.depth_um),  # type: ignore[arg-type]
            length_mm=_range(t, "length_mm", r.length_mm),
            width_mm=_range(t, "width_mm", r.width_mm),
            period_mm=_range(t, "period_mm", r.period_mm),
            along_fraction=(t.number("along_fraction", 0.5, lo=0.0, hi=1.0)
                            if kind == "torn_grain" else 0.5),
        ))
        t.reject_unknown()
    s.reject_unknown()
    return DefectsConfig(every_nth_board=every, seed=seed, place=tuple(place))
