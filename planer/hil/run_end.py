"""How a HIL run ended: its distance run, or cut short by a limit (a check of the summary).

A run that stops before the board travel it was asked for did not show what it was run for:
``planer hil --distance-m 60`` with the scenario's ``max_sim_s = 60`` stops near 35 m. The
summary says why the run ended (``run_end``) and its ``done`` table gets ``distance_reached``,
so such a run never passes.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, MutableMapping
from typing import Any

__all__ = ["RunEnd", "note_run_end", "run_end_text"]


class RunEnd(enum.Enum):
    """Why a HIL run ended (its value is the summary's ``run_end.reason``)."""

    DISTANCE = "distance"
    """The board travel asked for was run."""
    TIME_LIMIT = "max_sim_s"
    """The scenario's time limit (``max_sim_s`` of machine time) cut the run."""
    STOPPED = "stopped"
    """The run ended before its distance for another reason (the simulator ended)."""


def judge_run_end(*, distance_m: float, travelled_m: float, time_limit_hit: bool) -> RunEnd:
    """Why a run that travelled ``travelled_m`` of its ``distance_m`` ended."""
    if travelled_m >= distance_m:
        return RunEnd.DISTANCE
    return RunEnd.TIME_LIMIT if time_limit_hit else RunEnd.STOPPED


def run_end_text(run_end: MutableMapping[str, Any] | dict[str, Any]) -> str:
    """One sentence: how the run ended (the summary's ``run_end``)."""
    got, asked = run_end["board_travel_m"], run_end["distance_m"]
    if run_end["reason"] == RunEnd.DISTANCE.value:
        return f"The run went its {asked:g} m of board ({got:.2f} m)."
    if run_end["reason"] == RunEnd.TIME_LIMIT.value:
        return (f"The time limit cut the run: max_sim_s {run_end['max_sim_s']:g} s of machine "
                f"time ran out at {got:.2f} m of the {asked:g} m asked (raise max_sim_s in a "
                "scenario file, or ask for less).")
    return f"The run ended at {got:.2f} m of the {asked:g} m asked."


def note_run_end(
    summary: dict[str, Any],
    *,
    distance_m: float,
    travelled_m: float,
    max_sim_s: float,
    time_limit_hit: bool,
    say: Callable[[str], None] | None = None,
) -> RunEnd:
    """Add how the run ended to ``summary``; a run cut short fails.

    Parameters
    ----------
    summary : dict
        The run's summary (``done``, ``checks``, ``passed``); changed in place.
    distance_m : float
        Board travel asked for, m.
    travelled_m : float
        Board travel run, m (the measure the run stops on).
    max_sim_s : float
        The scenario's time limit, machine seconds.
    time_limit_hit : bool
        Whether the time limit stopped the run.
    say : callable, optional
        Receives the sentence when the run was cut short.

    Returns
    -------
    RunEnd
        Also ``summary["run_end"]["reason"]`` (its value); ``summary["done"]
        ["distance_reached"]`` is whether it is :attr:`RunEnd.DISTANCE`.
    """
    end = judge_run_end(distance_m=distance_m, travelled_m=travelled_m,
                        time_limit_hit=time_limit_hit)
    run_end = {"reason": end.value, "distance_m": float(distance_m),
               "board_travel_m": round(float(travelled_m), 3), "max_sim_s": float(max_sim_s)}
    summary["run_end"] = run_end
    ok = end is RunEnd.DISTANCE
    summary["done"]["distance_reached"] = ok
    summary.setdefault("checks", {})["distance_reached"] = {"ok": ok,
                                                           "text": run_end_text(run_end)}
    summary["passed"] = all(summary["done"].values())
    if not ok and say is not None:
        text = run_end_text(run_end)
        say(f"planer hil: {text[0].lower()}{text[1:]}")
    return end
