"""The record of the cut: every knife pass over each board, and the spindle's index pulses.

At every knife's bottom dead centre (BDC) the machine model
(:class:`plant_sim.machine.machine.Machine`)
calls :meth:`CutRecord.bdc`: the pass is recorded for the board under the cutter (5 mm clear
of its ends) as the board coordinate of the cutter axis, the cut bottom
``-standout_k(t) + x_piezo`` (um; the stand-out drifts with machine time when the head has a
:class:`plant_sim.model.surface.RunoutDrift`) and the knife. Knife 0 at BDC is also the index
pulse: the
encoder's raw count there goes into a ring of the last :data:`INDEX_RING` pulses, from which the
camera's index latch is taken (:meth:`CutRecord.index_latch`). Only the last few boards are kept.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from core.checks import check_int
from plant_sim.model.feed_drive import BoardStream, Encoder
from plant_sim.model.surface import Passes, RunoutDrift

__all__ = ["INDEX_RING", "CutRecord", "PassLog"]

INDEX_RING = 4096
"""Index pulses remembered (the camera's index latch looks back at most this far)."""

_CUT_MARGIN_MM = 5.0  # no pass recorded this close to a board's ends
_BOARDS_KEPT = 3  # boards older than the newest minus this are forgotten


class PassLog:
    """Growing arrays of the knife passes over one board.

    Parameters
    ----------
    radius_mm : float
        Cutting radius of the head, mm (carried into :class:`plant_sim.model.surface.Passes`).
    """

    def __init__(self, radius_mm: float) -> None:
        self.radius_mm = radius_mm
        self.n = 0
        self.x = np.empty(1024)
        self.bottom = np.empty(1024)
        self.knife = np.empty(1024, dtype=np.int64)

    def append(self, x_mm: float, bottom_um: float, knife: int) -> None:
        """Add one pass: board coordinate of the cutter axis (mm), cut bottom (um), knife."""
        if self.n == self.x.size:
            self.x = np.concatenate([self.x, np.empty(self.n)])
            self.bottom = np.concatenate([self.bottom, np.empty(self.n)])
            self.knife = np.concatenate([self.knife, np.empty(self.n, dtype=np.int64)])
        i = self.n
        self.x[i] = x_mm
        self.bottom[i] = bottom_um
        self.knife[i] = knife
        self.n = i + 1

    def passes(self) -> Passes:
        """A copy of the passes so far (shape ``(n,)`` each)."""
        n = self.n
        return Passes(self.x[:n].copy(), self.bottom[:n].copy(), self.knife[:n].copy(),
                      self.radius_mm)


class CutRecord:
    """Knife passes per board and the index pulses, as the machine cuts.

    Parameters
    ----------
    standout_um : sequence of float
        True radial stand-out of each knife, um (shape ``(Z,)``).
    radius_mm : float
        Cutting radius, mm.
    boards : plant_sim.model.feed_drive.BoardStream
        Where the boards are.
    encoder : plant_sim.model.feed_drive.Encoder
        The feed encoder (raw counts at the index pulses).
    drift : plant_sim.model.surface.RunoutDrift, optional
        Warm-up and wear added to the stand-out at each pass's machine time.
    """

    def __init__(self, standout_um: Sequence[float], radius_mm: float, *,
                 boards: BoardStream, encoder: Encoder,
                 drift: RunoutDrift | None = None) -> None:
        self._standout = [float(v) for v in standout_um]
        if drift is not None and drift.knives != len(self._standout):
            raise ValueError(f"drift must have one value per knife ({len(self._standout)}), "
                             f"got {drift.knives}")
        self.drift = drift if drift is not None and drift.active else None
        self.radius_mm = radius_mm
        self.boards = boards
        self.encoder = encoder
        self.logs: dict[int, PassLog] = {}
        self._idx_s = np.full(INDEX_RING, np.nan)
        self._idx_raw = np.zeros(INDEX_RING, dtype=np.int64)
        self._idx_n = 0

    def standout_um(self, knife: int, t_s: float) -> float:
        """Stand-out of knife ``knife`` at machine time ``t_s`` (runout, eccentricity, drift)."""
        base = self._standout[knife]
        return base if self.drift is None else base + self.drift.knife_um(knife, t_s)

    def step_standout(self, knife: int, step_um: float) -> None:
        """Knife ``knife`` stands out ``step_um`` more from now on (a chipped or moved knife)."""
        k = check_int("knife", knife, lo=0, hi=len(self._standout) - 1)
        self._standout[k] += float(step_um)

    def bdc(self, knife: int, s_mm: float, piezo_um: float, *, t_s: float = 0.0) -> None:
        """Knife ``knife`` at BDC at time ``t_s``: table at ``s_mm``, head at ``piezo_um``."""
        if knife == 0:
            i = self._idx_n % INDEX_RING
            self._idx_s[i] = s_mm
            self._idx_raw[i] = self.encoder.raw(s_mm)
            self._idx_n += 1
        bid, x = self.boards.at(s_mm, 0.0, margin_mm=_CUT_MARGIN_MM)
        if bid == 0:
            return
        log = self.logs.get(bid)
        if log is None:
            log = self.logs[bid] = PassLog(self.radius_mm)
            for old in [k for k in self.logs if k < bid - _BOARDS_KEPT]:
                del self.logs[old]
        log.append(x, piezo_um - self.standout_um(knife, t_s), knife)

    def index_latch(self, s_cut_mm: float) -> int:
        """Counter value (wrapped) at the index pulse nearest to table position ``s_cut_mm``."""
        n = min(self._idx_n, INDEX_RING)
        if n == 0:
            return self.encoder.wrap(0)
        d = np.abs(self._idx_s[:n] - s_cut_mm)
        i = int(np.nanargmin(d))
        return self.encoder.wrap(int(self._idx_raw[i]))

    def passes(self, board_id: int) -> Passes:
        """Every knife pass recorded over board ``board_id`` (recent boards only).

        Raises
        ------
        ValueError
            ``board_id`` not a positive integer, or no passes recorded over it.
        """
        log = self.logs.get(check_int("board_id", board_id, lo=1))
        if log is None:
            raise ValueError(f"board_id {board_id}: no passes recorded (not cut yet or too old)")
        return log.passes()

    def latest_board(self) -> int:
        """Id of the newest board with passes; ``ValueError`` if none has been cut yet."""
        if not self.logs:
            raise ValueError("no board has been cut yet")
        return max(self.logs)
