"""The uniformity loop's watch over its own effect: the best table seen, undo of a worse step.

The loop's model (the identified actuator, the runout estimate) can be wrong: a resonance below
the knife passing frequency turns a knife pattern around, a hysteretic stack barely moves small
cycles. Whatever the model says, :class:`TableGuard` judges the tables by what the camera
measured of the board they cut. Its score is the spread of the mark widths in um of relative
depth, ``rms(w - mean(w)) / G`` (``G = R / f * 1e-3``, ``controller.laws.uniformity_loop``): the
measured CV times ``f / G``, the same at every pitch, so a feed change is not taken for the
loop's doing.

Per complete pair the guard takes the table the measured board was cut with and the score; over
a window of ``window`` pairs it keeps the mean score and the mean table. The lowest mean seen is
the best table (the very first pair, the starting table's, counts alone: the loop's first table
goes out with it). Only pairs on which every knife left a mark the measurement could see
(``comparable``) choose the best: a vanished mark's width is clipped at 0, so the score of a
table under which a knife vanished under-states its spread and is not comparable with one
under which every knife cuts (at pitch 0.5 mm a table leaving one knife vanished scored below
the tables that brought it back). Such pairs still count against the best (a score that is
too low already and still worse is worse); before a comparable window there is no best and
nothing is undone. When the mean rises above ``best (1 + rel_tol) + abs_tol_um`` for ``patience``
pairs in a row, the learning made the board worse: :meth:`TableGuard.observe` says
:attr:`Verdict.UNDO` and the loop goes back to the best table. The first window of boards cut
with it again re-measures the best (:meth:`TableGuard.reverted`): about as good as before, the
undo was right and counts; much worse, the world changed (a knife, the wood) and the undo does
not count: the best is re-based on what was measured. After ``max_undos`` counted undos without
a better table in between the model cannot be trusted on this plant: :attr:`Verdict.HOLD`, the
loop keeps the best table. The starting table's boards are the first window: the loop is never
held worse than doing nothing for longer than the transport delay and ``window + patience``
pairs. Pure; a few plain floats per pair.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from core.checks import check_int, check_positive


class Verdict(enum.Enum):
    """What the guard says of the learning after a pair."""

    KEEP = "keep"
    """Go on learning."""
    UNDO = "undo"
    """The board got worse: go back to :attr:`TableGuard.best_table_um`."""
    HOLD = "hold"
    """Undone too often: keep :attr:`TableGuard.best_table_um` and stop learning."""


class TableGuard:
    """The best offset table by measured score, and when learning made the board worse.

    Parameters
    ----------
    knives : int
        Table length ``Z``.
    window : int
        Pairs averaged into one score.
    rel_tol, abs_tol_um : float
        A mean score above ``best (1 + rel_tol) + abs_tol_um`` is worse, um.
    patience : int
        Pairs in a row worse before an undo.
    max_undos : int
        Undos that count (the re-measured best held) before the guard holds.
    """

    def __init__(
        self,
        knives: int,
        *,
        window: int = 3,
        rel_tol: float = 0.2,
        abs_tol_um: float = 0.3,
        patience: int = 3,
        max_undos: int = 3,
    ) -> None:
        self.knives = check_int("knives", knives, lo=1)
        self.window = check_int("window", window, lo=1)
        self.rel_tol = check_positive("rel_tol", rel_tol, allow_zero=True)
        self.abs_tol_um = check_positive("abs_tol_um", abs_tol_um, allow_zero=True)
        self.patience = check_int("patience", patience, lo=1)
        self.max_undos = check_int("max_undos", max_undos, lo=1)
        self.reset(forget=True)

    def reset(self, *, forget: bool = False) -> None:
        """Start a new window (the table changed outside the loop); ``forget``: the best too."""
        self._pairs: deque[tuple[tuple[float, ...], float, bool]] = deque(maxlen=self.window)
        self._strikes = 0
        self._verifying = False
        if forget:
            self._best: tuple[tuple[float, ...], float] | None = None
            self.undos = 0
            """Counted undos since the last better table."""
            self.holding = False
            """Whether the guard said :attr:`Verdict.HOLD` (until ``reset(forget=True)``)."""
            self.total_undos = 0
            """Every undo since the last ``reset(forget=True)``."""

    @property
    def best_table_um(self) -> np.ndarray | None:
        """The table with the lowest mean score seen, um (``None`` before a full window)."""
        return None if self._best is None else np.array(self._best[0])

    @property
    def best_score_um(self) -> float | None:
        """Its mean score, um of relative depth (``None`` before a full window)."""
        return None if self._best is None else self._best[1]

    @property
    def recent_score_um(self) -> float | None:
        """The mean score of the last full window (``None`` before one, or just after a reset)."""
        if len(self._pairs) < self.window:
            return None
        return sum(p[1] for p in self._pairs) / len(self._pairs)

    def worse_than_best(self) -> bool:
        """Whether the last full window scored worse than the best (held: always)."""
        if self.holding:
            return True
        recent = self.recent_score_um
        return recent is not None and recent > self.threshold_um()

    def threshold_um(self) -> float:
        """The mean score above which the board counts as worse, um (inf before a best)."""
        if self._best is None:
            return math.inf
        return self._best[1] * (1.0 + self.rel_tol) + self.abs_tol_um

    def observe(self, table_um: Sequence[float], score_um: float, *,
                comparable: bool = True) -> Verdict:
        """One complete pair: the table its board was cut with and its score.

        Parameters
        ----------
        table_um : sequence of float, shape (Z,)
            The table in force when the measured board was cut, um.
        score_um : float
            ``rms(w - mean(w)) / G`` of the pair, um (>= 0).
        comparable : bool
            Whether every knife left a mark the measurement could see (else the score
            under-states the spread: it counts against the best but never sets it).

        Returns
        -------
        Verdict
        """
        t = tuple(float(v) for v in np.asarray(table_um, dtype=float).tolist())
        if len(t) != self.knives or not all(map(math.isfinite, t)):
            raise ValueError(f"table_um must be {self.knives} finite values, got {table_um!r}")
        s = check_positive("score_um", score_um, allow_zero=True)
        if self.holding:
            return Verdict.HOLD
        self._pairs.append((t, s, bool(comparable)))
        if self._best is None and not self._verifying and comparable:
            self._best = (t, s)  # the starting table: one pair is enough to be judged against
        if len(self._pairs) < self.window:
            return Verdict.KEEP
        mean_s = sum(p[1] for p in self._pairs) / len(self._pairs)
        mean_t = tuple(sum(p[0][k] for p in self._pairs) / len(self._pairs)
                       for k in range(self.knives))
        seen = all(p[2] for p in self._pairs)
        if self._verifying:  # the first window cut with the best table again
            self._verifying = False
            old = self._best
            assert old is not None
            if mean_s <= old[1] * (1.0 + self.rel_tol) + self.abs_tol_um:
                self.undos += 1  # the undo was right
            else:
                self.undos = 0  # the world changed: the best is what it is now
            if seen:
                self._best = (old[0], mean_s)
            if self.undos >= self.max_undos:
                self.holding = True
                return Verdict.HOLD
            return Verdict.KEEP
        if seen and (self._best is None or mean_s < self._best[1]):
            if self._best is not None and mean_s < self._best[1] / (1.0 + self.rel_tol):
                self.undos = 0  # clearly better than before: the learning works again
            self._best = (mean_t, mean_s)
        if mean_s > self.threshold_um():
            self._strikes += 1
        else:
            self._strikes = 0
        if self._strikes >= self.patience:
            return Verdict.UNDO
        return Verdict.KEEP

    def reverted(self) -> None:
        """The loop went back to the best table: the next window re-measures it."""
        self.total_undos += 1
        self._pairs.clear()
        self._strikes = 0
        self._verifying = True
