"""Online identification of the piezo's effective gain per knife mode, from what the cut shows.

The amplifier plays the offset table once per revolution; what the knives cut is the actuator's
response at each knife's bottom dead centre. A slow actuator (resonance near the knife passing
frequency) lets part of one knife's step spill into the next knife's cut, and hysteresis shrinks
small cycles (a Bouc-Wen stack at 0.30 moves the cut by only about 0.2 um per um commanded, and
lags into the following knife). At the time scale of the loop (image pairs, 0.1 s: dozens of
revolutions) both are a fixed linear map of the table, circulant because the table repeats every
revolution: the effective relative depth is ``A o`` with ``A`` circulant, i.e. one complex gain
``a_m`` per Fourier mode ``m`` of the knives (``a_{Z-m} = conj(a_m)``; ``a_0`` does not matter:
a constant offset changes no width).

From every complete measurement the loop knows the effective offsets of the measured board
``o`` (the table in force when it was cut) and the width errors in offset units
``y = D^+ (w - mean(w)) / G = A o - s`` (``s`` the runout). Per mode, ``Y_m = a_m O_m - S_m``.
:class:`ActuatorIdentifier` fits ``a_m`` on differences over ``lag_pairs`` measurements,
``dY_m = a_m dO_m - dS_m``, taking only differences in which the mode moved by at least
``min_step_um`` (the learning transients) and whose ratio ``dY_m / dO_m`` is itself a plausible
gain (magnitude within ``[gain_min / 2, 1.5 gain_max]``, phase within ``+-gate_phase_deg``): a
step of the runout itself (a knife changed, a misattributed pair) passes for a wild gain and is
left out. A slow drift of the runout (``dS``), which the loop
follows with equally slow moves of the table, would otherwise pass for a gain near zero (in
closed loop ``y`` stays near zero while ``o`` tracks ``s``). The fit is exponentially weighted
least squares over the accepted differences (forgetting only when something new is learnt, so a
settled loop keeps its estimate) with a prior ``a_m = 1`` of weight ``prior_um2``, and ``|a_m|``
bounded to ``[gain_min, gain_max]`` and its phase to ``+-phase_max_deg`` (inside the loop's phase
margin) so that the loop never divides by nearly nothing nor turns a mode around. Pure; O(Z)
per measurement.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from core.checks import check_int, check_positive, check_range


def circulant_from_mode_gains(mode_gains: np.ndarray) -> np.ndarray:
    """The real circulant matrix whose Fourier mode ``m`` has gain ``mode_gains[m]``.

    Parameters
    ----------
    mode_gains : ndarray of complex, shape (Z,)
        Gains per mode, ``mode_gains[Z - m] = conj(mode_gains[m])`` (a real map).

    Returns
    -------
    ndarray, shape (Z, Z)
        ``A`` with ``A @ v = ifft(mode_gains * fft(v))``.
    """
    g = np.asarray(mode_gains, dtype=complex)
    z = g.size
    col = np.real(np.fft.ifft(g))  # response to a unit offset on knife 0
    return np.array([[col[(i - j) % z] for j in range(z)] for i in range(z)])


class ActuatorIdentifier:
    """Per-mode complex gain of the actuator from (effective offsets, width errors) pairs.

    Parameters
    ----------
    knives : int
        ``Z``.
    lag_pairs : int
        Measurements between the two ends of a difference.
    min_step_um : float
        A mode's difference counts only when it moved by at least this much, um.
    memory : float
        Time constant of the forgetting, in accepted differences.
    prior_um2 : float
        Weight of the prior ``a_m = 1``, um^2 of offset excitation (the fit follows the data
        once the offsets have moved by a few times ``sqrt(prior_um2)``).
    gain_min, gain_max : float
        Bounds on ``|a_m|``.
    phase_max_deg : float
        Bound on ``|arg a_m|``, degrees.
    gate_phase_deg : float
        A difference whose own gain ratio turns further than this is left out, degrees.

    Attributes
    ----------
    samples : int
        Complete measurements taken in since the last reset.
    """

    def __init__(
        self,
        knives: int,
        *,
        lag_pairs: int = 5,
        min_step_um: float = 0.5,
        memory: float = 200.0,
        prior_um2: float = 1.0,
        gain_min: float = 0.1,
        gain_max: float = 2.0,
        phase_max_deg: float = 60.0,
        gate_phase_deg: float = 75.0,
    ) -> None:
        self.knives = check_int("knives", knives, lo=1)
        self.lag = check_int("lag_pairs", lag_pairs, lo=1)
        self.min_step_um = check_positive("min_step_um", min_step_um)
        check_range("memory", memory, 1.0, 1e9)
        self.forget = 1.0 - 1.0 / float(memory)
        self.prior_um2 = check_positive("prior_um2", prior_um2)
        self.gain_min = check_range("gain_min", gain_min, 1e-3, 1.0)
        self.gain_max = check_range("gain_max", gain_max, 1.0, 100.0)
        self.phase_max = math.radians(check_range("phase_max_deg", phase_max_deg, 0.0, 90.0))
        self.gate_phase = math.radians(check_range("gate_phase_deg", gate_phase_deg, 0.0, 180.0))
        self.reset()

    def reset(self) -> None:
        """Forget every measurement (back to the prior: every gain 1)."""
        z = self.knives
        self._past: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=self.lag)
        self._soo = np.zeros(z)
        self._soy = np.zeros(z, complex)
        self.samples = 0
        self._gains = np.ones(z, complex)

    def add(self, offsets_um: Sequence[float], equivalent_um: Sequence[float]) -> None:
        """Take one complete measurement.

        Parameters
        ----------
        offsets_um : sequence of float, shape (Z,)
            Effective commanded offsets of the measured board (the table in force when it was
            cut), um.
        equivalent_um : sequence of float, shape (Z,)
            ``y = D^+ (w - mean(w)) / G``: the width errors in um of offset.
        """
        o = np.asarray(offsets_um, dtype=float)
        y = np.asarray(equivalent_um, dtype=float)
        if o.shape != (self.knives,) or y.shape != (self.knives,):
            raise ValueError(f"offsets_um and equivalent_um must have {self.knives} values")
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(y))):
            raise ValueError("offsets_um and equivalent_um must be finite")
        om = np.fft.fft(o, norm="ortho")
        ym = np.fft.fft(y, norm="ortho")
        self.samples += 1
        if len(self._past) == self.lag:
            o0, y0 = self._past[0]
            do, dy = om - o0, ym - y0
            moved = np.abs(do) >= self.min_step_um
            ratio = np.where(moved, dy / np.where(moved, do, 1.0), 0.0)
            moved &= (np.abs(ratio) >= 0.5 * self.gain_min) & (np.abs(ratio) <= 1.5 * self.gain_max)
            moved &= np.abs(np.angle(ratio)) <= self.gate_phase
            lam = np.where(moved, self.forget, 1.0)
            self._soo = lam * self._soo + np.where(moved, np.abs(do) ** 2, 0.0)
            self._soy = lam * self._soy + np.where(moved, np.conj(do) * dy, 0.0)
            if np.any(moved):
                self._gains = self._fit()
        self._past.append((om, ym))

    def _fit(self) -> np.ndarray:
        a = (self._soy + self.prior_um2) / (self._soo + self.prior_um2)
        z = self.knives
        if z % 2 == 0:
            a[z // 2] = a[z // 2].real  # the alternating mode is real
        a[0] = 1.0
        mag = np.clip(np.abs(a), self.gain_min, self.gain_max)
        phase = np.clip(np.angle(a), -self.phase_max, self.phase_max)
        a = mag * np.exp(1j * phase)
        # a real map: mode Z - m is the conjugate of mode m
        for m in range(1, (z + 1) // 2):
            a[z - m] = np.conj(a[m])
        return a

    @property
    def mode_gains(self) -> np.ndarray:
        """The estimate ``a_m`` per Fourier mode, shape (Z,), complex (``a_0 = 1``)."""
        return self._gains.copy()

    @property
    def excitation_um2(self) -> np.ndarray:
        """Weighted sum of the accepted squared differences per mode (what the fit knows), um^2."""
        return self._soo.copy()

    def matrix(self) -> np.ndarray:
        """The estimated effective gain as a real circulant matrix, shape (Z, Z)."""
        return circulant_from_mode_gains(self._gains)
