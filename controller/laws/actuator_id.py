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
margin) so that the loop never divides by nearly nothing nor turns a mode around. Pure; per
measurement a DFT of ``Z`` values in plain numbers (``Z <= 8``: cheaper than numpy's FFT calls)
and ``O(Z)`` updates; the circulant matrix is built once per new estimate.
"""

from __future__ import annotations

import cmath
import math
import operator
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
        z = self.knives
        twiddles = np.exp(-2j * np.pi * np.outer(np.arange(z), np.arange(z)) / z) / math.sqrt(z)
        # exact 0, +-1, +-i where they are (the unit roots' rounding set aside)
        twiddles.real[np.abs(twiddles.real) < 1e-15] = 0.0
        twiddles.imag[np.abs(twiddles.imag) < 1e-15] = 0.0
        self._twiddles = tuple(tuple(complex(v) for v in row) for row in twiddles)
        self.version = 0
        """Counts the changes of the estimate (a new :meth:`matrix` after each)."""
        self._matrix: np.ndarray | None = None
        self.reset()

    def reset(self) -> None:
        """Forget every measurement (back to the prior: every gain 1)."""
        z = self.knives
        self._past: deque[tuple[list[complex], list[complex]]] = deque(maxlen=self.lag)
        self._soo = [0.0] * z  # per mode (plain numbers: updated per measurement)
        self._soy = [0j] * z
        self.samples = 0
        self._set_gains(np.ones(z, complex))

    def _set_gains(self, gains: np.ndarray) -> None:
        self._gains = gains
        self._matrix = None  # built again when asked for
        self.version += 1

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
        z = self.knives
        o_arr = np.asarray(offsets_um, dtype=float)
        y_arr = np.asarray(equivalent_um, dtype=float)
        if o_arr.shape != (z,) or y_arr.shape != (z,):
            raise ValueError(f"offsets_um and equivalent_um must have {z} values")
        o, y = o_arr.tolist(), y_arr.tolist()
        if not all(map(math.isfinite, o + y)):
            raise ValueError("offsets_um and equivalent_um must be finite")
        om = self._dft(o)
        ym = self._dft(y)
        self.samples += 1
        if len(self._past) == self.lag:
            o0, y0 = self._past[0]
            soo, soy = self._soo, self._soy
            any_moved = False
            for m in range(z):  # per mode, in plain complex numbers (Z is small)
                do, dy = om[m] - o0[m], ym[m] - y0[m]
                if abs(do) < self.min_step_um:
                    continue
                ratio = dy / do
                if not (0.5 * self.gain_min <= abs(ratio) <= 1.5 * self.gain_max
                        and abs(cmath.phase(ratio)) <= self.gate_phase):
                    continue
                soo[m] = self.forget * soo[m] + abs(do) ** 2
                soy[m] = self.forget * soy[m] + do.conjugate() * dy
                any_moved = True
            if any_moved:
                self._set_gains(self._fit())
        self._past.append((om, ym))

    def _dft(self, v: list[float]) -> list[complex]:
        """``np.fft.fft(v, norm="ortho")`` with the twiddles set up once."""
        return [sum(map(operator.mul, row, v)) for row in self._twiddles]

    def _fit(self) -> np.ndarray:
        a = (np.array(self._soy) + self.prior_um2) / (np.array(self._soo) + self.prior_um2)
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
        return np.array(self._soo)

    def matrix(self) -> np.ndarray:
        """The estimated effective gain as a real circulant matrix, shape (Z, Z) (a copy)."""
        return self.shared_matrix().copy()

    def shared_matrix(self) -> np.ndarray:
        """:meth:`matrix` built once per estimate (:attr:`version`); not to be changed."""
        if self._matrix is None:
            self._matrix = circulant_from_mode_gains(self._gains)
        return self._matrix
