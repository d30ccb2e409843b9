"""The spindle: speed with load ripple and droop, angle, knife timing, coast-down and braking.

A variable-speed spindle (``rpm_min < rpm_max``, a moulder's variable head) follows a setpoint
(:meth:`Spindle.set_setpoint`) within ``[rpm_min, rpm_max]`` on the run-up's first-order ramp
(``spinup_tau_s``); a fixed head (``rpm_min == rpm_max == rpm``) refuses any other speed.

The spindle angle is kept in revolutions (``rev``). Knife ``k`` of ``Z`` is at bottom dead centre
(BDC) when ``Z * rev`` is an integer ``n`` with ``n mod Z == k``; the index pulse is knife 0 at
BDC. The speed is held constant over each PLC cycle (updated by :meth:`Spindle.start_cycle`), so
the angle is linear in time within a cycle and event times are exact.
"""

from __future__ import annotations

import math

from core.checks import check_finite

__all__ = ["BRAKE", "COAST", "RUN", "Spindle"]

RUN, COAST, BRAKE = "run", "coast", "brake"


class Spindle:
    """Spindle drive and rotation.

    Parameters
    ----------
    cfg : config.sim.SpindleConfig
        Speed, ripple, droop and stop time constants.
    ripple_phase_rad : float
        Phase of the load ripple (drawn from the machine's seed).

    The speed range is the configuration's ``rpm_range`` (``rpm_min`` .. ``rpm_max``; both
    ``rpm`` for a fixed head).

    Attributes
    ----------
    rev : float
        Angle at the start of the current cycle, revolutions (unbounded).
    rev_s : float
        Speed over the current cycle, revolutions per second.
    mode : str
        ``"run"``, ``"coast"`` (drive tripped) or ``"brake"`` (e-stop).
    setpoint_rpm : float
        The speed the drive runs to (the ``spindle_setpoint_rpm`` register), rpm.
    rpm_min, rpm_max : float
        The range of the setpoint, rpm (equal for a fixed head).
    """

    def __init__(self, cfg, *, ripple_phase_rad: float = 0.0) -> None:
        self.cfg = cfg
        self.nominal_rev_s = cfg.rpm / 60.0
        self.drive_rev_s = self.nominal_rev_s
        self.ripple_phase = float(ripple_phase_rad)
        self.load = 0.0
        self.rev = 0.0
        self.rev_s = self.nominal_rev_s
        self.t_c = 0.0
        self.mode = RUN
        # set up once (the same expressions as per cycle, so the results are bit-identical)
        self._goal = {RUN: self.nominal_rev_s, COAST: 0.0, BRAKE: 0.0}
        self._tau = {RUN: cfg.spinup_tau_s, COAST: cfg.coast_tau_s, BRAKE: cfg.brake_tau_s}
        self._ripple_frac = cfg.ripple_frac
        self._ripple_w = 2.0 * math.pi * cfg.ripple_hz
        self._droop = cfg.load_droop_frac
        self.rpm_min, self.rpm_max = (float(v) for v in cfg.rpm_range)
        if not self.rpm_min <= cfg.rpm <= self.rpm_max:
            raise ValueError(f"spindle rpm must be in [rpm_min, rpm_max] = [{self.rpm_min}, "
                             f"{self.rpm_max}], got {cfg.rpm!r}")
        self.setpoint_rpm = float(cfg.rpm)
        self._stop_below = 0.005 * self.nominal_rev_s
        # running: within 10 % of the slowest speed it may be set to (a fixed head: of its rpm)
        self._running_from = 0.9 * (self.rpm_min / 60.0 if self.variable else self.nominal_rev_s)
        self._gains_dt: float | None = None
        self._gain: dict[str, float] = {}
        self._load_gain = 0.0

    @property
    def variable(self) -> bool:
        """Whether the speed can be set (``rpm_min < rpm_max``)."""
        return self.rpm_min < self.rpm_max

    def set_setpoint(self, rpm: float) -> None:
        """Run to ``rpm`` from now on (the run-up's ramp); a fault's stop still wins.

        Raises
        ------
        ValueError
            ``rpm`` not finite or outside ``[rpm_min, rpm_max]`` (never clamped).
        """
        v = check_finite("rpm", rpm)
        if not self.rpm_min <= v <= self.rpm_max:
            raise ValueError(f"rpm must be in [{self.rpm_min}, {self.rpm_max}], got {rpm!r}")
        if v == self.setpoint_rpm:
            return
        self.setpoint_rpm = v
        self.nominal_rev_s = v / 60.0
        self._goal[RUN] = self.nominal_rev_s

    def _set_gains(self, dt_s: float) -> None:
        """First-order gains ``1 - exp(-dt / tau)`` of a cycle of ``dt_s`` (once per step size)."""
        self._gain = {m: 1.0 - math.exp(-dt_s / tau) for m, tau in self._tau.items()}
        self._load_gain = 1.0 - math.exp(-dt_s / 0.1)
        self._gains_dt = dt_s

    def start_cycle(self, t_s: float, dt_s: float, *, cutting: bool) -> None:
        """Set the speed for the cycle ``[t_s, t_s + dt_s)``."""
        self.t_c = t_s
        if dt_s != self._gains_dt:
            self._set_gains(dt_s)
        mode = self.mode
        goal = self._goal[mode]
        drive = self.drive_rev_s + (goal - self.drive_rev_s) * self._gain[mode]
        if goal == 0.0 and drive < self._stop_below:
            drive = 0.0
        self.drive_rev_s = drive
        self.load += ((1.0 if cutting else 0.0) - self.load) * self._load_gain
        ripple = self._ripple_frac * math.sin(self._ripple_w * t_s + self.ripple_phase)
        self.rev_s = drive * (1.0 + ripple - self._droop * self.load)

    def end_cycle(self, dt_s: float) -> None:
        """Advance the angle over the whole cycle."""
        self.rev += self.rev_s * dt_s
        self.t_c += dt_s

    def rev_at(self, t_s: float) -> float:
        """Angle at time ``t_s`` within the current cycle, revolutions."""
        return self.rev + self.rev_s * (t_s - self.t_c)

    def time_of_rev(self, rev: float) -> float:
        """Time within the current cycle at which the angle reaches ``rev`` (speed > 0)."""
        return self.t_c + (rev - self.rev) / self.rev_s

    @property
    def rpm(self) -> float:
        """Speed over the current cycle, rpm."""
        return self.rev_s * 60.0

    @property
    def running(self) -> bool:
        """Drive on and within 10 % of the nominal speed (a variable head's slowest)."""
        return self.mode == RUN and self.drive_rev_s >= self._running_from

    @property
    def turning(self) -> bool:
        """Whether the spindle turns at all."""
        return self.rev_s > 0.0
