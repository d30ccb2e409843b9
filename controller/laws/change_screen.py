"""Pairs whose width pattern moved more than the table's change can explain (kept out of the loop).

Pure. At fine pitch a knife's mark can vanish or be merged with its neighbour's by the
measurement, and such a pair reads a width pattern far from the last one although the table
hardly moved (docs/control_design.md, section 3, "Vanished marks"). :class:`ChangeScreen`
compares each pair with the last one taken and keeps out those the table's change cannot
explain; after ``patience`` of them in a row the next one is taken, so a real change (a knife
chipped, another wood) costs at most ``patience`` pairs.
"""

from __future__ import annotations

import math

__all__ = ["CHANGE_PITCH_TOL", "ChangeScreen"]

CHANGE_PITCH_TOL = 0.05
"""Pitch change (relative) beyond which a pair is not compared with the last one taken (the
check of unexplained width changes starts again from it)."""


class ChangeScreen:
    """Whether each pair's width pattern moved more than the table's change can explain.

    Parameters
    ----------
    gain_max : float
        Largest actuator gain the loop allows (``[uniformity_loop] gain_max``): a table move of
        ``|do|`` um changes a knife's relative depth by at most ``4 gain_max |do|`` um.
    tol_frac : float
        Allowance beyond that, in pitches (``change_tol_frac``; 0 turns the screen off).
    patience : int
        Pairs kept out in a row before the next one is taken (``change_patience``).
    """

    def __init__(self, *, gain_max: float, tol_frac: float, patience: int) -> None:
        self.gain_max, self.tol_frac, self.patience = gain_max, tol_frac, patience
        self.reset()

    def reset(self) -> None:
        """Forget the reference pair and the count (:attr:`unexplained`)."""
        self._seen: tuple[list[float], list[float], float] | None = None  # o_cut, dev, pitch
        self._run = 0
        self.unexplained = 0
        """Pairs kept out as unexplained since the last reset."""

    def unexplained_pair(self, o_cut: list[float], dev_um: list[float], pitch_mm: float,
                         tol_um: float) -> bool:
        """Whether a pair's width pattern moved more than the table's change can explain.

        ``o_cut``: the table the pair was cut with, um; ``dev_um``: the widths' deviations from
        their mean over ``G`` (um of relative depth); ``tol_um``: ``tol_frac`` pitches in um.
        Against the last pair taken, when at the same pitch (within :data:`CHANGE_PITCH_TOL`:
        a vanished mark's clipped deviation, and its neighbours', scale with ``f / G``):
        ``|dev - dev_prev|`` beyond ``4 gain_max |o - o_prev| + tol_um`` on any knife. After
        ``patience`` such pairs in a row the next one is taken; a pair taken becomes the
        reference.
        """
        ref = self._seen
        if ref is not None and self.tol_frac > 0.0:
            o0, d0, f0 = ref
            moved = math.sqrt(sum((a - b) ** 2 for a, b in zip(o_cut, o0, strict=True)))
            bound = 4.0 * self.gain_max * moved + tol_um
            if (abs(pitch_mm / f0 - 1.0) <= CHANGE_PITCH_TOL
                    and any(abs(a - b) > bound for a, b in zip(dev_um, d0, strict=True))
                    and self._run < self.patience):
                self._run += 1
                self.unexplained += 1
                return True
        self._run = 0
        self._seen = (list(o_cut), list(dev_um), pitch_mm)
        return False
