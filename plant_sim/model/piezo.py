"""The piezo actuator that moves the cutterhead vertically, and its amplifier's logic.

Actuator (:class:`PiezoActuator`)
---------------------------------
The amplifier's output ``u`` (micrometres of commanded displacement) passes a rate-independent
hysteresis, then a second-order resonance:

- hysteresis, a first-order Bouc-Wen operator integrated in closed form over every step of
  ``u``: ``dh/du = (sign(du) H - h) / u_h``, level ``y = u - h``. ``h`` saturates at ``+-H``, so a
  large cycle has a loop of width about ``2 H``; ``u_h = stroke / 2`` and ``H`` are chosen so that
  a full-stroke cycle's loop is ``hysteresis`` times its peak-to-peak excursion (small cycles have
  relatively narrower loops, as real stacks do);
- linear dynamics ``x'' + 2 zeta wn x' + wn^2 x = wn^2 y`` (``wn = 2 pi resonance_hz``), exact
  for piecewise-constant ``y``: the state is propagated with the closed-form matrix exponential,
  so a second of simulation costs one evaluation per setpoint step, not one per microsecond.

Amplifier (:class:`PiezoAmplifier`)
-----------------------------------
Plays the per-knife offset table in step with the spindle: the machine calls :meth:`switch`
when the spindle reaches ``lead_fraction`` of a knife period before knife k's bottom dead centre,
and the output steps to knife k's offset. With ``input_shaper`` every step is split into two
(zero-vibration shaper: ``1/(1+K)`` now and ``K/(1+K)`` half a damped period later,
``K = exp(-zeta pi / sqrt(1 - zeta^2))``), which cancels the resonance's ringing, so the
displacement has settled when the knife cuts. States (CANopen status ``0x2100`` sub 4): 0 disabled,
1 enabled and tracking, 2 ramping to zero after a setpoint timeout, 3 fault. Fault bits: 0
over-temperature, 1 stroke limit reached, 2 setpoint timeout, 3 overcurrent. Its limits
(:meth:`PiezoAmplifier.limits`, CANopen ``0x2200``) come from its own configuration: the stroke,
the offsets it accepts (``+-stroke``), no slew limit (0) and its setpoint timeout.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from core.checks import check_finite, check_int, check_positive, check_range

__all__ = [
    "DISABLED",
    "ENABLED",
    "FAULT",
    "RAMPING",
    "PiezoActuator",
    "PiezoAmplifier",
    "PiezoLimits",
    "PiezoStatus",
]

DISABLED, ENABLED, RAMPING, FAULT = 0, 1, 2, 3
FAULT_OVERTEMP, FAULT_STROKE, FAULT_TIMEOUT, FAULT_OVERCURRENT = 1, 2, 4, 8


@dataclass(frozen=True)
class PiezoStatus:
    """What the amplifier reports (its CANopen status, TPDO1).

    Attributes
    ----------
    displacement_um : float
        Vertical displacement of the spindle measured by the eddy-current sensor, um.
    temperature_c : float
        Actuator temperature, degrees Celsius.
    fault : int
        Bit 0 over-temperature, bit 1 stroke limit, bit 2 setpoint timeout, bit 3 overcurrent.
    state : int
        0 disabled, 1 enabled, 2 ramping to zero, 3 fault.
    alive_counter : int
        The amplifier's own counter, incremented every 10 ms (mod 256).
    """

    displacement_um: float
    temperature_c: float
    fault: int
    state: int
    alive_counter: int


@dataclass(frozen=True)
class PiezoLimits:
    """The limits the amplifier enforces and reports (CANopen ``0x2200``).

    Attributes
    ----------
    stroke_um : float
        The actuator's stroke, um.
    offset_min_um, offset_max_um : float
        The offsets it accepts in a table, um; a table with one outside is refused.
    slew_max_um_ms : float
        Largest output slew rate, um/ms; 0: not limited (the simulated amplifier steps).
    setpoint_timeout_ms : float
        Without a new command (RPDO3) for this long it ramps to zero, ms.
    """

    stroke_um: float
    offset_min_um: float
    offset_max_um: float
    slew_max_um_ms: float
    setpoint_timeout_ms: float


class PiezoActuator:
    """Hysteresis followed by a second-order resonance, integrated exactly between steps.

    Parameters
    ----------
    resonance_hz : float
        Undamped natural frequency, Hz.
    damping : float
        Damping ratio (0 < damping < 1).
    hysteresis : float
        Loop width of a full-stroke cycle over its peak-to-peak excursion (0 disables).
    stroke_um : float
        Stroke, micrometres (sets the hysteresis scale).

    Attributes
    ----------
    t_s : float
        Time of the state, seconds.
    u_um, x_um, v_um_s : float
        Drive level, displacement and velocity.
    """

    def __init__(
        self, *, resonance_hz: float, damping: float, hysteresis: float, stroke_um: float
    ) -> None:
        f = check_positive("resonance_hz", resonance_hz)
        z = check_range("damping", damping, 1e-3, 0.999)
        hy = check_range("hysteresis", hysteresis, 0.0, 0.5)
        stroke = check_positive("stroke_um", stroke_um)
        self.wn = 2.0 * math.pi * f
        self.zeta = z
        self.wd = self.wn * math.sqrt(1.0 - z * z)
        self.sigma = z * self.wn
        # Bouc-Wen scale: a full-stroke cycle (a = stroke / u_h = 2) has relative loop width
        # (H / u_h) (1 - (1 + tanh a) e^-a) / a
        self.u_h = 0.5 * stroke
        a = stroke / self.u_h
        rel = (1.0 - (1.0 + math.tanh(a)) * math.exp(-a)) / a
        self.h_sat = hy * self.u_h / rel if hy > 0 else 0.0
        self.t_s = 0.0
        self.u_um = 0.0
        self.h_um = 0.0
        self.level_um = 0.0
        self.x_um = 0.0
        self.v_um_s = 0.0

    def drive(self, u_um: float) -> None:
        """Step the drive level to ``u_um`` now (hysteresis applied to the step)."""
        du = u_um - self.u_um
        if du == 0.0:
            return
        if self.h_sat > 0.0:
            s = self.h_sat if du > 0 else -self.h_sat
            self.h_um = s + (self.h_um - s) * math.exp(-abs(du) / self.u_h)
        self.u_um = u_um
        self.level_um = u_um - self.h_um

    def _transition(self, tau: float) -> tuple[float, float, float, float]:
        ex = math.exp(-self.sigma * tau)
        c = math.cos(self.wd * tau)
        s = math.sin(self.wd * tau)
        k = self.sigma / self.wd
        return (
            ex * (c + k * s),
            ex * s / self.wd,
            -ex * s * self.wn * self.wn / self.wd,
            ex * (c - k * s),
        )

    def propagate_to(self, t_s: float) -> None:
        """Advance the state to time ``t_s`` with the drive level held."""
        tau = t_s - self.t_s
        if tau <= 0.0:
            return
        # _transition(tau) inlined, the same expressions bit for bit (runs ~2000 times per
        # simulated second; tests/plant_sim/test_sim_speed_model.py compares the two)
        ex = math.exp(-self.sigma * tau)
        wd, wn = self.wd, self.wn
        c = math.cos(wd * tau)
        s = math.sin(wd * tau)
        k = self.sigma / wd
        e = self.x_um - self.level_um
        v = self.v_um_s
        self.x_um = self.level_um + ex * (c + k * s) * e + ex * s / wd * v
        self.v_um_s = -ex * s * wn * wn / wd * e + ex * (c - k * s) * v
        self.t_s = t_s

    def displacement_at(self, t_s: np.ndarray) -> np.ndarray:
        """Displacement at times ``t_s >= self.t_s`` with the drive held (state unchanged), um."""
        tau = np.asarray(t_s, dtype=float) - self.t_s
        ex = np.exp(-self.sigma * tau)
        c = np.cos(self.wd * tau)
        s = np.sin(self.wd * tau)
        e = self.x_um - self.level_um
        return self.level_um + ex * (e * (c + self.sigma / self.wd * s) + self.v_um_s / self.wd * s)


class PiezoAmplifier:
    """The amplifier: enable, setpoint timeout, offset table played per knife, shaping, status.

    Parameters
    ----------
    cfg : config.sim.PiezoConfig
        Actuator and amplifier parameters.
    knives : int
        Number of knives Z (size of the offset table).
    rng : numpy.random.Generator
        Noise of the eddy-current sensor.
    """

    def __init__(self, cfg, knives: int, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.knives = check_int("knives", knives, lo=1, hi=8)
        self.rng = rng
        self.actuator = PiezoActuator(
            resonance_hz=cfg.resonance_hz,
            damping=cfg.damping,
            hysteresis=cfg.hysteresis,
            stroke_um=cfg.stroke_um,
        )
        act = self.actuator
        if cfg.input_shaper:
            k = math.exp(-act.zeta * math.pi / math.sqrt(1.0 - act.zeta**2))
            self.shaper_a1 = 1.0 / (1.0 + k)
            self.shaper_delay_s = math.pi / act.wd
        else:
            self.shaper_a1 = 1.0
            self.shaper_delay_s = 0.0
        self.offsets_um = [0.0] * self.knives
        self.state = DISABLED
        self.fault_bits = 0
        self.knife = 0  # knife whose offset is being played
        self.target_um = 0.0  # unshaped output (the staircase)
        self.output_um = 0.0  # shaped output = actuator drive level
        self._pending: deque[tuple[float, float]] = deque()
        self.last_command_s = -math.inf
        self.last_alive: int | None = None
        self.ramp_start_s = 0.0
        self.ramp_from_um = [0.0] * self.knives
        self.temperature_c = cfg.ambient_c
        self._slew_um = 0.0  # sum of |target steps| since the last cycle update
        self._stroke_hit = False
        self.forced_off = False  # e-stop: power removed
        self.commands = 0

    # -- commands (CAN side) -------------------------------------------------------------

    def command(self, t_s: float, *, enable: bool, alive_counter: int) -> None:
        """A command (RPDO3); a new alive counter restarts the setpoint timeout."""
        alive = check_int("alive_counter", alive_counter, lo=0, hi=255)
        self.commands += 1
        if alive == self.last_alive and enable:
            return  # a stale frame (the sender is hung): neither refreshes nor enables
        self.last_command_s = t_s
        self.last_alive = alive
        if self.state == FAULT:
            if not enable:  # a disable clears a fault whose cause is gone
                if self.temperature_c < self.cfg.max_temperature_c - 5.0:
                    self.fault_bits &= ~(FAULT_OVERTEMP | FAULT_OVERCURRENT)
                    self.state = DISABLED
            return
        if self.forced_off:
            self.state = DISABLED
            return
        if enable:
            if self.state != ENABLED:
                self.state = ENABLED
            self.fault_bits &= ~FAULT_TIMEOUT
        else:
            self.state = DISABLED
            self.fault_bits &= ~FAULT_TIMEOUT
            self.set_target(t_s, 0.0)

    def set_offsets(self, offsets_um: Sequence[float]) -> None:
        """Store the per-knife offset table (played from the next knife switch)."""
        self.offsets_um = self.check_offsets(offsets_um)

    def check_offsets(self, offsets_um: Sequence[float]) -> list[float]:
        """The table for the head's knives; ``ValueError`` beyond the stroke or too short."""
        vals = list(offsets_um)
        if not self.knives <= len(vals) <= 8:
            raise ValueError(
                f"offsets_um must hold one value per knife ({self.knives}, at most 8), "
                f"got {len(vals)}"
            )
        stroke = self.cfg.stroke_um
        out = []
        for i, v in enumerate(vals):
            f = check_finite(f"offsets_um[{i}]", v)
            if abs(f) > stroke:
                raise ValueError(f"offsets_um[{i}] must be within +-{stroke} µm, got {v!r}")
            out.append(f)
        return out[: self.knives]

    def limits(self) -> PiezoLimits:
        """What the amplifier reports of its limits: from its own configuration."""
        stroke = float(self.cfg.stroke_um)
        return PiezoLimits(
            stroke_um=stroke,
            offset_min_um=-stroke,
            offset_max_um=stroke,
            slew_max_um_ms=0.0,
            setpoint_timeout_ms=float(self.cfg.timeout_s) * 1e3,
        )

    def inject_fault(self, t_s: float, bits: int) -> None:
        """Amplifier fault (e.g. overcurrent): output to zero, state 3."""
        self.fault_bits |= bits
        self.state = FAULT
        self.set_target(t_s, 0.0)

    def power_off(self, t_s: float, off: bool) -> None:
        """E-stop removes (``off``) or restores the amplifier's power stage."""
        self.forced_off = off
        if off and self.state in (ENABLED, RAMPING):
            self.state = DISABLED
            self.set_target(t_s, 0.0)

    # -- playing the table ----------------------------------------------------------------

    def setpoint_um(self, knife: int, t_s: float) -> float:
        """Unshaped output for ``knife`` at time ``t_s`` in the current state."""
        if self.state == ENABLED:
            return self.offsets_um[knife]
        if self.state == RAMPING:
            dec = self.cfg.ramp_um_s * (t_s - self.ramp_start_s)
            o = self.ramp_from_um[knife]
            return math.copysign(max(abs(o) - dec, 0.0), o)
        return 0.0

    def set_target(self, t_s: float, value_um: float) -> None:
        """Step the unshaped output; the shaper schedules the second half of the step."""
        delta = value_um - self.target_um
        if delta == 0.0:
            return
        self.advance_to(t_s)
        self.target_um = value_um
        self._slew_um += abs(delta)
        first = self.shaper_a1 * delta
        self.output_um += first
        self.actuator.drive(self.output_um)
        if self.shaper_delay_s > 0.0:
            self._pending.append((t_s + self.shaper_delay_s, delta - first))

    def switch(self, knife: int, t_s: float) -> None:
        """The spindle reached the switch point of ``knife``: play its offset."""
        self.knife = knife
        self.set_target(t_s, self.setpoint_um(knife, t_s))

    def advance_to(self, t_s: float) -> None:
        """Propagate the actuator to ``t_s``, applying the shaper's delayed half-steps."""
        act = self.actuator
        pend = self._pending
        while pend and pend[0][0] <= t_s:
            tp, d = pend.popleft()
            act.propagate_to(tp)
            self.output_um = self.output_um + d if pend else self.target_um
            act.drive(self.output_um)
            self._check_stroke()
        act.propagate_to(t_s)
        self._check_stroke()

    def _check_stroke(self) -> None:
        if abs(self.actuator.x_um) >= self.cfg.stroke_um:
            self._stroke_hit = True

    def cycle(self, t_s: float, dt_s: float, *, spindle_turning: bool) -> None:
        """Once per PLC cycle: setpoint timeout, ramp, temperature, stroke flag."""
        cfg = self.cfg
        if self.state == ENABLED and t_s - self.last_command_s > cfg.timeout_s:
            self.state = RAMPING
            self.fault_bits |= FAULT_TIMEOUT
            self.ramp_start_s = t_s
            self.ramp_from_um = [self.setpoint_um_enabled(k) for k in range(self.knives)]
        if self.state != ENABLED or not spindle_turning:
            self.set_target(t_s, self.setpoint_um(self.knife, t_s))
        # temperature: first order towards ambient + heating * mean slew rate
        slew = self._slew_um / dt_s if dt_s > 0 else 0.0
        self._slew_um = 0.0
        goal = cfg.ambient_c + cfg.heating_c_per_um_s * slew
        gain = 1.0 - math.exp(-dt_s / cfg.thermal_tau_s)
        self.temperature_c += (goal - self.temperature_c) * gain
        if self.temperature_c > cfg.max_temperature_c and self.state != FAULT:
            self.inject_fault(t_s, FAULT_OVERTEMP)
        if self._stroke_hit:
            self.fault_bits |= FAULT_STROKE
        else:
            self.fault_bits &= ~FAULT_STROKE
        self._stroke_hit = False

    def setpoint_um_enabled(self, knife: int) -> float:
        """The table's offset for ``knife``."""
        return self.offsets_um[knife]

    def sensor_um(self) -> float:
        """Eddy-current sensor reading of the spindle's vertical displacement, um."""
        return self.actuator.x_um + self.cfg.sensor_noise_um * float(self.rng.standard_normal())

    def status(self, t_s: float) -> PiezoStatus:
        """The amplifier's status as of ``t_s`` (the actuator must be advanced to ``t_s``)."""
        return PiezoStatus(
            displacement_um=self.sensor_um(),
            temperature_c=self.temperature_c,
            fault=self.fault_bits,
            state=self.state,
            alive_counter=int(t_s / 0.01) % 256,
        )
