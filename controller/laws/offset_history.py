"""Which offset table cut which board: the history of the tables in force (pass-to-board map).

The camera sees board that was cut ``L / V`` seconds earlier (``L`` cutter to camera, ``V`` the
feed): 0.3-40 s on the machines it serves. The uniformity loop learns on every image pair, so it
must know the table the measured board was cut with, not the one in force now. The feed loop
gives the cut times of a measurement's window
(:meth:`controller.laws.feed_loop.FeedLoop.cut_interval_s`,
its own setpoint history integrated back over ``L``); :class:`OffsetHistory` gives the table in
force over that interval (time-weighted mean when it changed inside the window). A table sent at
``t`` is in force at the cutter from ``t + settle_s`` (CAN, the amplifier's next switch, the
shaper): the caller subtracts ``settle_s`` from the cut times. Pure and clock-injected.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import numpy as np

from core.checks import check_finite, check_positive


class OffsetHistory:
    """Offset tables with the time each took effect; table ``i`` holds on ``[t_i, t_{i+1})``.

    Parameters
    ----------
    knives : int
        Table length ``Z``.
    horizon_s : float
        Tables that ended more than this before the newest entry are dropped, seconds.
    """

    def __init__(self, knives: int, *, horizon_s: float) -> None:
        self.knives = int(knives)
        self.horizon_s = check_positive("horizon_s", horizon_s)
        self._t: list[float] = []
        self._v: list[tuple[float, ...]] = []  # the tables, plain floats

    def restart(self, offsets_um: Sequence[float], at_s: float = -math.inf) -> None:
        """Forget everything: ``offsets_um`` in force from ``at_s`` (-inf: always were)."""
        self._t = [float(at_s)]
        self._v = [_table(offsets_um)]

    @property
    def start_s(self) -> float:
        """Time from which the history knows the table (-inf: always), seconds."""
        return self._t[0] if self._t else math.inf

    @property
    def last_change_s(self) -> float:
        """Time of the newest entry, seconds."""
        return self._t[-1] if self._t else -math.inf

    def __len__(self) -> int:
        return len(self._t)

    def append(self, offsets_um: Sequence[float], at_s: float) -> np.ndarray | None:
        """``offsets_um`` in force from ``at_s`` (not earlier than the newest entry).

        Returns
        -------
        ndarray or None
            The table it replaced when ``at_s`` is the newest entry's time (the newer table
            replaces the older one), else ``None``.
        """
        t = check_finite("at_s", at_s)
        v = _table(offsets_um)
        if self._t and t < self._t[-1]:
            raise ValueError(f"at_s must not go back: {t!r} < {self._t[-1]!r}")
        if self._t and t == self._t[-1]:
            replaced = np.array(self._v[-1])
            self._v[-1] = v  # same instant: the newer table replaces the older
            return replaced
        else:
            self._t.append(t)
            self._v.append(v)
        k = bisect.bisect_right(self._t, t - self.horizon_s) - 1
        if k > 0:  # keep the entry in force at the horizon
            del self._t[:k], self._v[:k]
        return None

    def pop(self, replaced: np.ndarray | None = None) -> None:
        """Take back the newest entry (it never reached the machine).

        ``replaced``: what :meth:`append` returned for it; that table is put back in its place.
        Otherwise the entry goes (the oldest one always stays).
        """
        if replaced is not None:
            self._v[-1] = _table(replaced)
        elif len(self._t) > 1:
            self._t.pop()
            self._v.pop()

    def latest(self) -> np.ndarray:
        """The table in force now (a copy)."""
        return np.array(self._v[-1])

    def mean_over(self, t0_s: float, t1_s: float) -> np.ndarray | None:
        """Time-weighted mean of the tables in force over ``[t0_s, t1_s]``.

        Returns
        -------
        ndarray, shape (Z,), or None
            ``None`` when ``t0_s`` is before the history's start (the table is unknown).
        """
        t0, t1 = sorted((float(t0_s), float(t1_s)))
        if not self._t or t0 < self._t[0]:
            return None
        i0 = bisect.bisect_right(self._t, t0) - 1
        i1 = bisect.bisect_right(self._t, t1) - 1
        if i0 == i1 or t1 <= t0:
            return np.array(self._v[i0])
        # plain floats, the same products and sums as ``acc += v_i * max(b - a, 0)`` in numpy;
        # table i holds on [t_i, t_{i+1}), clipped to [t0, t1] only at both ends (t_{i0} <= t0
        # < t_{i0+1}, t_{i1} <= t1)
        ts, vl = self._t, self._v
        w = max(ts[i0 + 1] - t0, 0.0)
        acc = [v * w for v in vl[i0]]  # (0 + x is x)
        for i in range(i0 + 1, i1):
            w = ts[i + 1] - ts[i]
            acc = [s + v * w for s, v in zip(acc, vl[i], strict=True)]
        w = max(t1 - ts[i1], 0.0)
        span = t1 - t0
        return np.array([(s + v * w) / span for s, v in zip(acc, vl[i1], strict=True)])


def _table(offsets_um: Sequence[float]) -> tuple[float, ...]:
    """An offset table as plain floats (what the history keeps)."""
    return tuple(np.asarray(offsets_um, dtype=float).tolist())
