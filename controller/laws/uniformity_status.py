"""What the uniformity loop says of itself: its status in plain JSON and its notices.

:func:`describe_loop` is the status snapshot's ``uniformity`` entry (``controller.service.status``:
OPC UA and the operator page show it): what the loop does, the actuator's identified gain per
knife pattern with its confidence and state, the held patterns, the best table measured.
:func:`authority_notice` is what the loop tells once when the actuator cannot help (a knife
pattern it cannot move, or the loop holding its best table): the service turns it into the
``uniformity_no_authority`` event. Pure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

HOLD_REASONS = ("made_worse", "no_authority")
"""Why the loop holds its best table (:attr:`UniformityLoop.hold_reason`)."""


@dataclass(frozen=True)
class AuthorityNotice:
    """The loop's word, once, that the actuator cannot do what it should.

    Attributes
    ----------
    t_s : float
        When, seconds.
    text : str
        One line for people.
    data : dict
        ``hold_reason`` (``None``, ``made_worse``, ``no_authority``), ``held_modes`` (knife
        patterns held), ``mode_gains`` (``[magnitude, phase_deg]`` per mode 1..Z/2),
        ``mode_states``, ``confidence``, ``table_um`` (the table in force),
        ``best_score_um`` and ``undos``.
    """

    t_s: float
    text: str
    data: dict[str, Any] = field(default_factory=dict)


def _f(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def describe_loop(loop: Any) -> dict[str, Any]:
    """Plain JSON of a :class:`controller.laws.uniformity_loop.UniformityLoop`.

    Keys ``status``, ``hold_reason``, ``held_modes``, ``modes`` (per mode 1..Z/2: ``mode``,
    ``gain`` (magnitude), ``phase_deg``, ``confidence``, ``state``), ``offsets_um``,
    ``best_table_um``, ``best_score_um``, ``undos`` (every undo since the loop started).
    """
    ident = loop.identifier
    raw = ident.raw_gains
    conf = ident.confidence()
    states = ident.mode_states()
    z = loop.cfg.knives
    modes = [
        {"mode": m, "gain": _f(abs(complex(raw[m]))),
         "phase_deg": _f(math.degrees(np.angle(raw[m]))), "confidence": _f(conf[m]),
         "state": states[m]}
        for m in range(1, z // 2 + 1)
    ]
    guard = loop.guard
    best = guard.best_table_um
    return {
        "status": loop.status,
        "hold_reason": loop.hold_reason,
        "held_modes": sorted(m for m in loop.held_modes if m <= z // 2),
        "modes": modes,
        "offsets_um": [float(v) for v in loop.offsets_um],
        "best_table_um": None if best is None else [float(v) for v in best],
        "best_score_um": _f(guard.best_score_um),
        "undos": int(guard.total_undos),
    }


def authority_notice(loop: Any, t_s: float) -> AuthorityNotice:
    """The notice for the loop's present hold or held patterns."""
    d = describe_loop(loop)
    reason = d["hold_reason"]
    gains = ", ".join(f"{m['mode']}: {m['gain']:.2f} at {m['phase_deg']:+.0f} deg"
                      for m in d["modes"] if m["gain"] is not None)
    table = " ".join(f"{v:+.2f}" for v in d["offsets_um"])
    if reason == "made_worse":
        text = (f"uniformity: the learning made the board worse {d['undos']} times: holding the "
                f"best table measured [{table}] µm (actuator gains per knife pattern {gains})")
    elif reason == "no_authority":
        text = (f"uniformity: the actuator cannot move any knife pattern (gains {gains}): "
                f"holding [{table}] µm")
    else:
        text = (f"uniformity: the actuator cannot move knife pattern(s) "
                f"{', '.join(str(m) for m in d['held_modes'])} (gains {gains}): those held, "
                f"the others learnt")
    data = {
        "hold_reason": reason,
        "held_modes": d["held_modes"],
        "mode_gains": [[m["gain"], m["phase_deg"]] for m in d["modes"]],
        "mode_states": [m["state"] for m in d["modes"]],
        "confidence": [m["confidence"] for m in d["modes"]],
        "table_um": d["offsets_um"],
        "best_score_um": d["best_score_um"],
        "undos": d["undos"],
    }
    return AuthorityNotice(float(t_s), text, data)
