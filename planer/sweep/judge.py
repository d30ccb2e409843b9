"""What a run's pitch can be judged against: the feed drive's physical ramp and the feed cap.

A run starts at the scenario's initial feed; the drive reaches the feed of the target pitch no
sooner than its acceleration limit and its velocity loop allow (``plant_sim.model.feed_drive``:
``a = clip(2 pi bandwidth (setpoint - v), +-accel_max)``). :func:`drive_ramp_end_mm` is the
board travel at which the drive, given the final setpoint at once, would come within 1 % of it:
the earliest end of the physical ramp. The envelope's criterion for the pitch is "inside
+-2 % within 1.5 m of board after the physical ramp ends" (:data:`PITCH_WITHIN_MM`): a run
shorter than the ramp plus 1.5 m cannot be judged on its pitch (:func:`pitch_verdict` says
``ramp not finished``), and a target pitch beyond the feed cap (``feed.max_mm_s``) is held at
the cap (the HIL's summary then judges the pitch against the reachable one: ``capped``).
"""

from __future__ import annotations

import math

from core.checks import check_positive

PITCH_WITHIN_MM = 1500.0
"""Board travel after the physical ramp's end within which the pitch must be in band, mm."""
RAMP_TOL = 0.01
"""The ramp has ended when the drive is within this fraction of the final feed."""

VERDICTS = ("in band", "late", "off", "ramp not finished")
"""Values of :func:`pitch_verdict` (prefixed ``capped, `` when the target is beyond the cap)."""


def drive_ramp_end_mm(initial_mm_s: float, final_mm_s: float, *, accel_mm_s2: float,
                      bandwidth_hz: float, tol: float = RAMP_TOL) -> float:
    """Board travel until the feed drive can be within ``tol`` of ``final_mm_s``, mm.

    The drive's velocity loop (first order, rate ``k = 2 pi bandwidth_hz``) with its
    acceleration limited to ``accel_mm_s2``, given ``final_mm_s`` at time 0: limited at
    ``accel_mm_s2`` while the error exceeds ``accel / k``, then an exponential tail.

    Parameters
    ----------
    initial_mm_s, final_mm_s : float
        The feed at the start and the feed of the target, mm/s (> 0).
    accel_mm_s2 : float
        The drive's acceleration limit, mm/s^2 (> 0).
    bandwidth_hz : float
        The velocity loop's bandwidth, Hz (> 0).
    tol : float
        Relative distance to ``final_mm_s`` at which the ramp counts as ended.

    Returns
    -------
    float
        Board travel from the start, mm (0 when the start is within ``tol`` already).
    """
    f0 = check_positive("initial_mm_s", initial_mm_s)
    f1 = check_positive("final_mm_s", final_mm_s)
    a = check_positive("accel_mm_s2", accel_mm_s2)
    k = 2.0 * math.pi * check_positive("bandwidth_hz", bandwidth_hz)
    band = check_positive("tol", tol) * f1
    err = abs(f0 - f1)
    if err <= band:
        return 0.0
    sign = 1.0 if f0 > f1 else -1.0  # the error's sign along the ramp: v = f1 + sign * e
    travel = 0.0
    knee = a / k  # below this error the loop's own rate, above it the acceleration limit
    if err > knee:
        e1 = max(knee, band)
        v0, v1 = f1 + sign * err, f1 + sign * e1
        travel += abs(v0 * v0 - v1 * v1) / (2.0 * a)
        err = e1
    if err > band:
        t = math.log(err / band) / k
        travel += f1 * t + sign * err / k * (1.0 - math.exp(-k * t))
    return travel


def pitch_verdict(*, travel_mm: float, ramp_end_mm: float, in_band_from_mm: float | None,
                  final_pitch_error: float | None, capped: bool = False,
                  within_mm: float = PITCH_WITHIN_MM, tol: float = 0.02) -> str:
    """The pitch's verdict of one run (one of :data:`VERDICTS`, ``capped, `` in front if so).

    Parameters
    ----------
    travel_mm : float
        Board the run went, mm.
    ramp_end_mm : float
        :func:`drive_ramp_end_mm` of the run, mm.
    in_band_from_mm : float or None
        Board travel from which every true pitch stayed in band (``None``: never), mm.
    final_pitch_error : float or None
        The final pitch's relative error against what it is judged by.
    capped : bool
        The target pitch is beyond the feed cap (judged against the reachable pitch).
    within_mm : float
        Board after the ramp's end within which the pitch must be in band, mm.
    tol : float
        The band, relative.

    Returns
    -------
    str
        ``ramp not finished`` (the run is shorter than the ramp plus ``within_mm``), ``in
        band`` (in band by ``ramp_end_mm + within_mm`` and to the end), ``late`` (in band to the
        end, from later), ``off`` (not in band at the end).
    """
    if travel_mm < ramp_end_mm + within_mm:
        out = "ramp not finished"
    elif in_band_from_mm is None or final_pitch_error is None or abs(final_pitch_error) > tol:
        out = "off"
    elif in_band_from_mm <= ramp_end_mm + within_mm:
        out = "in band"
    else:
        out = "late"
    return f"capped, {out}" if capped else out
