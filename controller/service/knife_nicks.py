"""A knife nick, from the ridge the defect detector finds on the pairs: told at once.

A nick (a notch in one knife's edge: a stone, a nail) leaves that knife's marks uncut across a
narrow band of the board: a ridge along the feed that stays at the same place across the feed
on every pair from then on. The vision's defect detector
(:func:`vision.defects.detect.knife_nicks`, with ``Measurer(defects=True)``) reports it per pair
as a ``knife_nick`` defect (its position ``y_mm`` across the feed, its height). The mark widths
hardly move (the band is 0.3-2 mm of a field tens of mm wide, and the measurement leaves a
defect's rows out of its profiles), so :class:`~controller.service.alerts.KnifeChipMonitor`
does not see it; :class:`KnifeNickMonitor` does: a nick at the same place (within
:data:`NICK_Y_TOL_MM`) on :data:`NICK_CONFIRM` of the last :data:`NICK_WINDOW` pairs that were
looked at is told as ``KNIFE_CHIPPED`` (the one event kind of a knife that chipped or nicked;
``data["cause"] = "nick"``), once per nick: within 2-3 pairs (0.12-0.18 m of board at
600 mm/s) of the first pair that shows it.

Pure apart from the event log it reports to; times are passed in.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from typing import Any

from controller.service.events import EventKind, EventLog

__all__ = ["NICK_CONFIRM", "NICK_FORGET_PAIRS", "NICK_WINDOW", "NICK_Y_TOL_MM",
           "KnifeNickMonitor"]

NICK_CONFIRM = 2
"""Pairs (of the last :data:`NICK_WINDOW` looked at) that must show a nick at one place."""
NICK_WINDOW = 3
"""Pairs over which a nick is confirmed (one pair may miss it: the detector's recall)."""
NICK_Y_TOL_MM = 2.0
"""Nicks this close across the feed are one, mm (the detector's position scatters ~0.5 mm)."""
NICK_FORGET_PAIRS = 50
"""A nick told is forgotten after this many pairs looked at without it (3 m of board at
0.06 m per pair): one seen again later (a new board, a new knife set) is told again."""
NICK_MIN_CONFIDENCE = 0.3
"""Detections below this confidence do not count (as in the D1666 grade)."""


def nick_positions(defects: Iterable[Any] | None) -> list[tuple[float, float | None]] | None:
    """``(y_mm, height_um)`` of the knife nicks among a pair's defects.

    ``None``: the pair was not looked at (no defect list: the measurer does not look for
    defects, or the pair failed before).
    """
    if defects is None:
        return None
    out = []
    for d in defects:
        kind = getattr(getattr(d, "kind", None), "value", getattr(d, "kind", None))
        if kind != "knife_nick" or float(getattr(d, "confidence", 1.0)) < NICK_MIN_CONFIDENCE:
            continue
        depth = getattr(d, "depth_um", None)
        out.append((float(d.y_mm), None if depth is None else abs(float(depth))))
    return out


class KnifeNickMonitor:
    """Knife nicks confirmed on consecutive pairs, told once each (see the module docstring).

    Parameters
    ----------
    report : EventLog
        Where ``KNIFE_CHIPPED`` goes (and the ``knife_chips`` counter).
    """

    def __init__(self, report: EventLog) -> None:
        self._report = report
        self._recent: deque[list[tuple[float, float | None]]] = deque(maxlen=NICK_WINDOW)
        self._known: list[list[float]] = []  # [y_mm, pairs since last seen] of nicks told
        self.last: dict[str, Any] | None = None
        """The last nick told (``None``: none)."""
        self.nicks = 0

    def reset(self) -> None:
        """Forget the pairs seen (the knives were changed): a nick seen again is told again."""
        self._recent.clear()
        self._known.clear()

    def pair(self, t: float, defects: Iterable[Any] | None, *, seq: int | None = None) -> bool:
        """One pair's defects (``Measurement.defects``); whether a nick was told on it."""
        found = nick_positions(defects)
        if found is None:
            return False
        for known in self._known:
            known[1] = 0 if any(abs(y - known[0]) <= NICK_Y_TOL_MM for y, _ in found) \
                else known[1] + 1
        self._known = [k for k in self._known if k[1] < NICK_FORGET_PAIRS]
        self._recent.append(found)
        told = False
        for y, height in found:
            if any(abs(y - k[0]) <= NICK_Y_TOL_MM for k in self._known):
                continue  # told already
            seen = sum(any(abs(y - y2) <= NICK_Y_TOL_MM for y2, _ in pair)
                       for pair in self._recent)
            if seen < NICK_CONFIRM:
                continue
            self._known.append([y, 0])
            self._tell(t, y, height, seq)
            told = True
        return told

    def _tell(self, t: float, y_mm: float, height_um: float | None, seq: int | None) -> None:
        self.nicks += 1
        self.last = {"knife": None, "cause": "nick", "y_mm": round(y_mm, 2),
                     "ridge_um": None if height_um is None else round(height_um, 1),
                     "runout_step_um": None, "width_change_mm": None, "seq": seq, "t_s": t}
        self._report.count("knife_chips")
        ridge = "" if height_um is None else f", a ridge {height_um:.0f} µm high"
        self._report.emit(
            t, EventKind.KNIFE_CHIPPED,
            f"a knife is nicked: its marks leave a ridge along the board at {y_mm:.1f} mm "
            f"across the camera's field{ridge}", data=self.last)
