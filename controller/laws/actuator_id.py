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
``min_step_um`` (the learning transients; a slow drift of the runout, which the loop follows
with equally slow moves of the table, would otherwise pass for a gain near zero: in closed loop
``y`` stays near zero while ``o`` tracks ``s``) and whose ratio ``dY_m / dO_m`` has a magnitude
within ``[gain_min / 4, 1.5 gain_max]`` (a step of the runout itself, a knife changed or a
misattributed pair, passes for a wild gain; a difference across a table change inside the
measured window, for nearly none). Large moves (``4 min_step_um``) that moved nothing, ``2
lag_pairs`` in a row, are themselves the finding: that pattern has no authority. Once a mode is
confident, a difference must also agree with its estimate
(:meth:`ActuatorIdentifier._consistent`); ``3 lag_pairs`` disagreeing in a row
and the mode is learnt afresh (the actuator changed), as is a mode that was confident and lost
all its confidence to disagreeing differences. A jump of the width errors while the
table stood still is a step of the runout: the differences start again after it. The gain may
lie anywhere on the phase circle: a resonance below the knife passing frequency turns a mode by
60-180 degrees (at 100 Hz and 400 knife passes per second the alternating mode's gain is about
-0.2), and a hysteretic stack shrinks small cycles to a few per cent.

Beside each mode's gain the accepted differences give its dependence on the amplitude
``|O_m|`` they were taken at (:meth:`ActuatorIdentifier.amplitude_slope`: the slope of an affine
describing function ``a_m(A)``, counted only beyond three standard errors and when the gain
at the largest amplitude seen is twice the one at the smallest), which a hysteretic
stack shows and a linear actuator does not; :meth:`ActuatorIdentifier.gains_at` gives the gains
at given amplitudes, within the amplitudes seen.

The fit is exponentially weighted least squares over the accepted differences (forgetting only
when something new is learnt, so a settled loop keeps its estimate) with a prior ``a_m = 1``
of weight ``prior_um2``. Beside the estimate it keeps what the fit knows: the weighted number
of differences and their residual, so each mode has an uncertainty ``sigma_m`` (the fit's
standard error and the prior's pull) and a confidence ``1 - 2 sigma_m / |a_m|`` (clipped to
[0, 1]): the fraction of the loop's robust-stability disc (``|a_true / a_hat - 1| < 1``,
``controller.laws.design``) left after two standard errors. :meth:`mode_states` sorts the modes
into ``usable`` (confident, ``|a_m| >= gain_min``), ``no_authority`` (``|a_m| + 2 sigma_m <
gain_min`` after ``min_samples`` differences: the actuator cannot move that knife pattern),
``unidentifiable`` (many differences, still no confidence) and ``unknown`` (not enough seen
yet). :attr:`mode_gains`, the gains the loop plans with, bound ``|a_m|`` to ``[gain_min,
gain_max]`` (``unconfirmed_gain_min`` below while the mode is not confident; the phase kept) so
that the loop never divides by nearly nothing. Pure; per measurement a DFT of ``Z`` values in
plain numbers (``Z <= 8``: cheaper than numpy's FFT calls) and ``O(Z)`` updates; the circulant
matrix is built once per new estimate.
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


#: Values of :meth:`ActuatorIdentifier.mode_states`, one per mode.
MODE_STATES = ("usable", "unknown", "no_authority", "unidentifiable")


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
        Bounds on the planning gain ``|a_m|``; a mode confidently below ``gain_min`` has no
        authority.
    phase_max_deg : float
        Bound on ``|arg a_m|`` of the planning gain, degrees (180: the whole circle).
    gate_phase_deg : float
        A difference whose own gain ratio turns further than this is left out, degrees (180:
        none is).
    min_samples : int
        Accepted differences before a mode may count as usable or without authority.
    unidentifiable_samples : int
        Accepted differences after which a mode still without confidence is unidentifiable.
    unconfirmed_gain_min : float
        Smallest planning ``|a_m|`` of a mode not yet confident (a few differences saying
        "small" do not blow the table up).

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
        phase_max_deg: float = 180.0,
        gate_phase_deg: float = 180.0,
        min_samples: int = 3,
        unidentifiable_samples: int = 30,
        unconfirmed_gain_min: float = 0.5,
    ) -> None:
        self.knives = check_int("knives", knives, lo=1)
        self.lag = check_int("lag_pairs", lag_pairs, lo=1)
        self.min_step_um = check_positive("min_step_um", min_step_um)
        check_range("memory", memory, 1.0, 1e9)
        self.forget = 1.0 - 1.0 / float(memory)
        self.prior_um2 = check_positive("prior_um2", prior_um2)
        self.gain_min = check_range("gain_min", gain_min, 1e-3, 1.0)
        self.gain_max = check_range("gain_max", gain_max, 1.0, 100.0)
        self.phase_max = math.radians(check_range("phase_max_deg", phase_max_deg, 0.0, 180.0))
        self.gate_phase = math.radians(check_range("gate_phase_deg", gate_phase_deg, 0.0, 180.0))
        self.min_samples = check_int("min_samples", min_samples, lo=1)
        self.jump_um = 4.0 * self.min_step_um
        """A move of the width errors (um of offset, per mode) with the table steady that counts
        as a step of the runout."""
        self.still_samples = 2 * self.lag
        """Large moves (``4 min_step_um``) in a row whose response is below the ratio gate
        (``gain_min / 4``) after which a mode has no authority even without a fit."""
        self.reject_reset = 3 * self.lag
        """Consecutive outliers after which a mode is learnt afresh (the actuator changed)."""
        self.unconfirmed_gain_min = check_range("unconfirmed_gain_min", unconfirmed_gain_min,
                                                0.0, 1.0)
        self.unidentifiable_samples = check_int(
            "unidentifiable_samples", unidentifiable_samples, lo=self.min_samples)
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
        self._syy = [0.0] * z  # weighted sum of |dY|^2 (the fit's residual)
        self._n = [0.0] * z  # weighted number of accepted differences
        # the same sums weighted by the difference's amplitude (mean |O_m| of its two ends):
        # the gain's dependence on the amplitude (a hysteretic stack)
        self._sao = [0.0] * z  # sum A |dO|^2
        self._saao = [0.0] * z  # sum A^2 |dO|^2
        self._saoy = [0j] * z  # sum A conj(dO) dY
        self._amp_lo = [math.inf] * z  # the amplitudes the accepted differences reached, um
        self._amp_hi = [0.0] * z
        self._rejected = [0] * z  # consecutive differences left out as outliers
        self._confident = [False] * z  # confident once since learnt (afresh)
        self._still = [0] * z  # large moves in a row that moved nothing (ratio ~ 0)
        self.samples = 0
        self._prior = np.ones(z, complex)
        self._raw = np.ones(z, complex)
        self._set_gains(np.ones(z, complex))

    def start_from(self, mode_gains: Sequence[complex]) -> None:
        """Forget every measurement and start from a known actuator (e.g. one learnt before).

        ``mode_gains`` (shape (Z,), ``a_{Z-m} = conj(a_m)``; ``a_0`` ignored) becomes the prior
        the fit is drawn to and the estimate until the data say otherwise.
        """
        g = np.asarray(mode_gains, dtype=complex)
        z = self.knives
        if g.shape != (z,) or not np.all(np.isfinite(g)):
            raise ValueError(f"mode_gains must be {z} finite complex values, got {mode_gains!r}")
        self.reset()
        g = g.copy()
        g[0] = 1.0
        for m in range(1, (z + 1) // 2):
            g[z - m] = np.conj(g[m])
        if z % 2 == 0:
            g[z // 2] = g[z // 2].real
        self._prior = g
        self._raw = g.copy()
        mag = np.clip(np.abs(g), self.gain_min, self.gain_max)
        a = mag * np.exp(1j * np.clip(np.angle(g), -self.phase_max, self.phase_max))
        a[0] = 1.0
        if z % 2 == 0:
            a[z // 2] = a[z // 2].real
        self._set_gains(a)

    def _set_gains(self, gains: np.ndarray) -> None:
        self._gains = gains
        self._matrix = None  # built again when asked for
        self.version += 1
        self._changed()

    def _changed(self) -> None:
        """The fit's sums, counts or estimate changed: the judgements made of them are stale.

        Every change of what :meth:`mode_states` and :meth:`amplitude_dependent` read (the
        sums, ``_n``, ``_still``, ``_raw``, the prior) comes through here (:meth:`add`,
        :meth:`_forget_mode`, :meth:`_set_gains` after each fit, reset or start): both are then
        computed again when next asked, and kept while nothing changes (a pair whose table
        did not move, most of a run once learnt).
        """
        self._states: tuple[str, ...] | None = None
        self._amp_dependent: bool | None = None

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
        if self._past and self._jumped(om, ym):
            self._past.clear()  # no difference straddles a step of the runout
        if len(self._past) == self.lag:
            o0, y0 = self._past[0]
            soo, soy, syy, n = self._soo, self._soy, self._syy, self._n
            lam = self.forget
            any_moved = False
            for m in range(1, z // 2 + 1):  # per mode pair, in plain complex numbers
                do, dy = om[m] - o0[m], ym[m] - y0[m]
                if abs(do) < self.min_step_um:
                    continue
                amp = 0.5 * (abs(om[m]) + abs(o0[m]))
                ratio = dy / do
                if abs(ratio) < 0.25 * self.gain_min and abs(do) >= 4.0 * self.min_step_um:
                    self._still[m] += 1  # a large move that moved nothing
                    self._changed()
                    continue
                if (not 0.25 * self.gain_min <= abs(ratio) <= 1.5 * self.gain_max
                        or abs(cmath.phase(ratio)) > self.gate_phase):
                    continue
                self._still[m] = 0
                self._changed()  # (an accepted difference or an outlier: the sums may move)
                if not self._consistent(m, do, dy, amp):
                    self._rejected[m] += 1
                    if self._rejected[m] >= self.reject_reset:  # the actuator changed: relearn
                        self._forget_mode(m)
                    continue
                self._rejected[m] = 0
                soo[m] = lam * soo[m] + abs(do) ** 2
                soy[m] = lam * soy[m] + do.conjugate() * dy
                syy[m] = lam * syy[m] + abs(dy) ** 2
                n[m] = lam * n[m] + 1.0
                w2 = abs(do) ** 2
                self._sao[m] = lam * self._sao[m] + amp * w2
                self._saao[m] = lam * self._saao[m] + amp * amp * w2
                self._saoy[m] = lam * self._saoy[m] + amp * do.conjugate() * dy
                self._amp_lo[m] = min(self._amp_lo[m], abs(om[m]), abs(o0[m]))
                self._amp_hi[m] = max(self._amp_hi[m], abs(om[m]), abs(o0[m]))
                any_moved = True
            for m in range(z // 2 + 1, z):  # mode Z - m: the conjugate of mode m
                c = z - m
                soo[m], soy[m], syy[m], n[m] = soo[c], soy[c].conjugate(), syy[c], n[c]
                self._sao[m], self._saao[m] = self._sao[c], self._saao[c]
                self._saoy[m] = self._saoy[c].conjugate()
                self._amp_lo[m], self._amp_hi[m] = self._amp_lo[c], self._amp_hi[c]
                self._rejected[m] = self._rejected[c]
                self._still[m] = self._still[c]
            if any_moved:
                self._set_gains(self._fit())
                self._relearn_lost()
        self._past.append((om, ym))

    def interrupt(self) -> None:
        """A measurement that does not enter (a mark vanished): no difference reaches across."""
        self._past.clear()

    def _jumped(self, om: list[complex], ym: list[complex]) -> bool:
        """Whether the width errors jumped since the last measurement with the table steady.

        With the table unchanged (every mode within ``min_step_um / 2``) a move of ``Y`` by
        more than ``jump_um`` beyond what the estimate explains is the runout's (a knife
        changed, a misattributed pair): differences across it would read it as the actuator's.
        """
        o1, y1 = self._past[-1]
        z = self.knives
        if max(abs(om[m] - o1[m]) for m in range(1, z)) >= 0.5 * self.min_step_um:
            return False
        return any(abs((ym[m] - y1[m]) - complex(self._gains[m]) * (om[m] - o1[m])) > self.jump_um
                   for m in range(1, z))

    def _consistent(self, m: int, do: complex, dy: complex, amp: float) -> bool:
        """Whether a difference agrees with a confident estimate of mode ``m`` (else an outlier).

        Before the mode is confident every difference counts (the first learning steps are what
        identify a turned or weak actuator). After, ``|dY - a dO|`` must stay within half the
        predicted move (three uncertainties of the gain, when larger) plus three residual
        standard deviations: a step of the runout
        (``dS``, a knife changed) is left out whatever its phase. A gain that depends on the
        amplitude (:meth:`amplitude_slope`) is judged at the difference's amplitude ``amp``.
        """
        n = self._n[m]
        if n < self.min_samples - 1e-9:
            return True
        slope, centre = self.amplitude_slope(m)
        a_c = complex(self._raw[m])
        a = a_c + slope * (amp - centre)
        se = self._stderr(m)
        if 2.0 * se >= abs(a_c):
            return True  # not confident: nothing to judge by
        sigma = math.sqrt(self._residual(m) / max(n - 1.0, 1.0))
        return abs(dy - a * do) <= max(0.5 * abs(a), 3.0 * se) * abs(do) + 3.0 * sigma

    def _relearn_lost(self) -> None:
        """A mode that was confident and lost all confidence is learnt afresh (it changed)."""
        conf = self.confidence()
        lost = False
        for m in range(1, self.knives):
            if conf[m] > 0.0:
                self._confident[m] = True
            elif self._confident[m]:
                self._forget_mode(m)
                lost = True
        if lost:
            self._set_gains(self._fit())

    def _forget_mode(self, m: int) -> None:
        """Forget what mode ``m`` (and its conjugate) learnt: back to the prior."""
        self._changed()
        for k in {m, (self.knives - m) % self.knives}:
            self._soo[k], self._soy[k], self._syy[k], self._n[k] = 0.0, 0j, 0.0, 0.0
            self._sao[k], self._saao[k], self._saoy[k] = 0.0, 0.0, 0j
            self._amp_lo[k], self._amp_hi[k] = math.inf, 0.0
            self._rejected[k] = 0
            self._confident[k] = False
            self._still[k] = 0

    def _dft(self, v: list[float]) -> list[complex]:
        """``np.fft.fft(v, norm="ortho")`` with the twiddles set up once."""
        return [sum(map(operator.mul, row, v)) for row in self._twiddles]

    def _fit(self) -> np.ndarray:
        p = self.prior_um2
        a = (np.array(self._soy) + p * self._prior) / (np.array(self._soo) + p)
        z = self.knives
        if z % 2 == 0:
            a[z // 2] = a[z // 2].real  # the alternating mode is real
        a[0] = 1.0
        for m in range(1, (z + 1) // 2):  # a real map: mode Z - m is the conjugate of mode m
            a[z - m] = np.conj(a[m])
        self._raw = a.copy()
        return self._bounded(a)

    def _bounded(self, a: np.ndarray) -> np.ndarray:
        """Raw gains per mode bounded for planning (magnitude, phase), a real map."""
        z = self.knives
        # a gain not yet confirmed is planned with at least ``unconfirmed_gain_min``: a few
        # differences that say "small" must not blow the table up to the stroke
        low = np.where(self.confidence() > 0.0, self.gain_min,
                       max(self.gain_min, self.unconfirmed_gain_min))
        mag = np.clip(np.abs(a), low, self.gain_max)
        phase = np.clip(np.angle(a), -self.phase_max, self.phase_max)
        a = mag * np.exp(1j * phase)
        if z % 2 == 0:
            a[z // 2] = a[z // 2].real  # (a phase of exactly +-pi leaves rounding behind)
        for m in range(1, (z + 1) // 2):
            a[z - m] = np.conj(a[m])
        a[0] = 1.0
        return a

    @property
    def mode_gains(self) -> np.ndarray:
        """The planning gain ``a_m`` per Fourier mode, shape (Z,), complex (``a_0 = 1``)."""
        return self._gains.copy()

    @property
    def raw_gains(self) -> np.ndarray:
        """The least-squares estimate per mode before the bounds, shape (Z,), complex."""
        return self._raw.copy()

    def amplitude_slope(self, m: int) -> tuple[complex, float]:
        """How mode ``m``'s gain changes with its amplitude: ``(slope per um, centre um)``.

        A hysteretic stack moves a small cycle by a few per cent of the table and a large one
        by most of it: the gain of a difference grows with the amplitude ``A`` (``|O_m|``, the
        mean of its two ends) it was taken at. Beside the estimate ``a_m`` (the gain at the
        weighted mean amplitude, the ``centre``) the accepted differences give the slope of
        ``a_m(A) = a_m + slope (A - centre)`` by least squares on the centred amplitudes. The
        slope counts only when it is larger than three of its standard errors (the residual of
        the affine fit over the amplitudes' spread) and the gain at the largest amplitude seen
        is at least twice the one at the smallest: a linear actuator, or one with little
        hysteresis, has slope 0.

        Returns
        -------
        (complex, float)
            The slope, 1/um (0 when not significant), and the centre amplitude, um.
        """
        soo, n = self._soo[m], self._n[m]
        if m == 0 or soo <= 0.0 or n < self.min_samples + 1 - 1e-9:
            return 0j, 0.0
        centre = self._sao[m] / soo
        spread = self._saao[m] - self._sao[m] * centre
        if spread <= 1e-12 * max(self._saao[m], 1.0):
            return 0j, centre
        cov = self._saoy[m] - centre * self._soy[m]
        slope = cov / spread
        res = max(self._residual(m) - abs(cov) ** 2 / spread, 0.0)
        se = math.sqrt(res / max(n - 2.0, 1.0) / spread)
        # it counts when it is beyond three standard errors and the gain at the largest
        # amplitude seen is at least twice the gain at the smallest (the mark of hysteresis:
        # small cycles shrink); a feed transient or a little hysteresis does not plan by it
        a_c = complex(self._raw[m])
        lo = abs(a_c + slope * (self._amp_lo[m] - centre))
        hi = abs(a_c + slope * (self._amp_hi[m] - centre))
        keep = abs(slope) > 3.0 * se and hi >= 2.0 * lo
        return (slope if keep else 0j), centre

    def amplitude_dependent(self) -> bool:
        """Whether some mode's gain depends on its amplitude (:meth:`amplitude_slope`).

        Computed once per change of the fit (:meth:`_changed`).
        """
        if self._amp_dependent is None:
            self._amp_dependent = any(self.amplitude_slope(m)[0] != 0
                                      for m in range(1, self.knives // 2 + 1))
        return self._amp_dependent

    def mode_amplitudes(self, table_um: Sequence[float]) -> np.ndarray:
        """``|O_m|`` of a table per mode (the amplitude :meth:`gains_at` takes), um, shape (Z,)."""
        o = np.asarray(table_um, dtype=float)
        return np.abs(np.fft.fft(o, norm="ortho"))

    def gains_at(self, amplitudes_um: Sequence[float]) -> np.ndarray:
        """The planning gains with each mode's gain taken at its amplitude, shape (Z,).

        ``a_m + slope_m (A_m - centre_m)`` (:meth:`amplitude_slope`), ``A_m`` kept within the
        amplitudes the accepted differences reached (no extrapolation), then bounded as
        :attr:`mode_gains` are. Without an amplitude dependence: :attr:`mode_gains`.
        """
        amps = np.asarray(amplitudes_um, dtype=float)
        z = self.knives
        if amps.shape != (z,) or not np.all(np.isfinite(amps)):
            raise ValueError(f"amplitudes_um must be {z} finite values, got {amplitudes_um!r}")
        a = self._raw.copy()
        changed = False
        for m in range(1, z // 2 + 1):
            slope, centre = self.amplitude_slope(m)
            if slope == 0:
                continue
            amp = min(max(float(amps[m]), self._amp_lo[m]), self._amp_hi[m])
            a[m] = a[m] + slope * (amp - centre)
            if 2 * m == z:
                a[m] = a[m].real
            changed = True
        if not changed:
            return self.mode_gains
        for m in range(1, (z + 1) // 2):
            a[z - m] = np.conj(a[m])
        return self._bounded(a)

    @property
    def excitation_um2(self) -> np.ndarray:
        """Weighted sum of the accepted squared differences per mode (what the fit knows), um^2."""
        return np.array(self._soo)

    @property
    def differences(self) -> np.ndarray:
        """Weighted number of accepted differences per mode, shape (Z,)."""
        return np.array(self._n)

    def gain_stderr(self) -> np.ndarray:
        """Uncertainty of each mode's estimate, shape (Z,) (``inf`` before two differences).

        The standard error of the weighted fit (its residual ``sum |dY - a dO|^2`` over the
        differences less one, divided by the excitation, the prior's included) and the prior's
        pull on the estimate (``prior_um2 |a_prior - a| / (excitation + prior_um2)``) added in
        quadrature: little excitation is little confidence even without noise.
        """
        z = self.knives
        out = np.full(z, math.inf)
        out[0] = 0.0
        for m in range(1, z):
            n = self._n[m]
            if n < 1.5:
                continue
            out[m] = self._stderr(m)
        return out

    def _residual(self, m: int) -> float:
        """``sum |dY - a dO|^2`` of mode ``m``'s accepted differences at its estimate, um^2."""
        a = complex(self._raw[m])
        res = self._syy[m] - 2.0 * (a.conjugate() * self._soy[m]).real + abs(a) ** 2 * self._soo[m]
        return max(res, 0.0)

    def _stderr(self, m: int) -> float:
        a = complex(self._raw[m])
        n = self._n[m]
        res = self._residual(m)
        w = self._soo[m] + self.prior_um2
        fit = max(res, 0.0) / max(n - 1.0, 1.0) / w
        pull = self.prior_um2 * abs(complex(self._prior[m]) - a) / w
        return math.sqrt(fit + pull * pull)

    def confidence(self) -> np.ndarray:
        """Per mode ``1 - 2 sigma_m / |a_m|`` clipped to [0, 1] (0 before ``min_samples``)."""
        se = self.gain_stderr()
        mag = np.maximum(np.abs(self._raw), 1e-12)
        conf = np.clip(1.0 - 2.0 * se / mag, 0.0, 1.0)
        conf[np.array(self._n) < self.min_samples - 1e-9] = 0.0
        conf[0] = 1.0
        return conf

    def mode_states(self) -> tuple[str, ...]:
        """Each mode's state (:data:`MODE_STATES`); mode 0 is always ``usable``.

        Computed once per change of the fit (:meth:`_changed`).
        """
        if self._states is None:
            self._states = _mode_states_now(self)
        return self._states

    def matrix(self) -> np.ndarray:
        """The estimated effective gain as a real circulant matrix, shape (Z, Z) (a copy)."""
        return self.shared_matrix().copy()

    def shared_matrix(self) -> np.ndarray:
        """:meth:`matrix` built once per estimate (:attr:`version`); not to be changed."""
        if self._matrix is None:
            self._matrix = circulant_from_mode_gains(self._gains)
        return self._matrix


def _mode_states_now(ident: ActuatorIdentifier) -> tuple[str, ...]:
    """:meth:`ActuatorIdentifier.mode_states` computed from the fit as it is."""
    # per mode in plain floats: gain_stderr's and confidence's values, bit for bit
    raw = ident._raw.tolist()
    out = ["usable"]
    for m in range(1, ident.knives):
        mag = abs(complex(raw[m]))
        n = ident._n[m]
        se = math.inf if n < 1.5 else ident._stderr(m)
        conf = (0.0 if n < ident.min_samples - 1e-9
                else min(max(1.0 - 2.0 * se / max(mag, 1e-12), 0.0), 1.0))
        if ((n >= ident.min_samples - 1e-9 and mag + 2.0 * se < ident.gain_min)
                or ident._still[m] >= ident.still_samples):
            out.append("no_authority")
        elif conf > 0.0 and mag >= ident.gain_min:
            out.append("usable")
        elif n >= ident.unidentifiable_samples - 1e-9:
            out.append("unidentifiable")
        else:
            out.append("unknown")
    return tuple(out)
