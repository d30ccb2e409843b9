"""Illumination correction for the two-light slope: LED imbalance and fall-off.

Seed Eq. 4 assumes both lights equally strong and uniform over the field.  Real LEDs differ by
several per cent and fall off across the field; since the grazing-light shading of a cuttermark is
itself only a few per cent of the intensity, plain Eq. 4 then returns mostly illumination.

With lights ``L_A(u)``, ``L_B(u)`` (camera frame) the registered profiles are
``I_A(u) = L_A(u) a(u) f_A(p(u))`` and ``I_B(u + d) = L_B(u + d) a(u) f_B(p(u))``, so the
log-ratio is

    log(I_B / I_A) = log(L_B(u + d) / L_A(u)) + log(f_B(p) / f_A(p)).

Two corrections:

* **Flat-field reference** (optional): the column profiles of a pair taken on a flat, planed board
  measure ``L_A`` and ``L_B`` (times a constant); :func:`flat_field_correct` divides each profile by
  its own reference, in the camera frame, before B is shifted.
* **Detrending** (always; the only correction without a reference): the first term is smooth over
  the field, while the cuttermark term oscillates with the pitch.  A least-squares polynomial of
  low degree (default 3) in ``u`` fitted to the log-ratio and removed takes the illumination out.
  *Assumption:* the true slope has no component that is a low-degree polynomial over the field —
  the board is flat over the camera's field (no bow, cup or tilt to measure) and the field holds
  many marks (at least about 8), so that the marks' own slope averages to zero over it.  A tilt or
  bow of the board is removed together with the illumination; cuttermarks are not.
"""

from __future__ import annotations

import math

import numpy as np

from core.checks import check_1d, check_int
from vision import kernels


def flat_field_correct(
    profile_a: np.ndarray,
    profile_b: np.ndarray,
    *,
    reference_a: np.ndarray,
    reference_b: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Divide each light's column profile by its flat-board reference.

    Both are divided by the same scale (the mean of the two references), so the LED imbalance
    the references hold is removed too, while the flat board's own albedo cancels in B / A.

    Parameters
    ----------
    profile_a, profile_b : ndarray, shape (width,)
        Column profiles of A and B in the camera frame (before B is shifted).
    reference_a, reference_b : ndarray, shape (width,)
        Column profiles of a flat board under light A and light B, same columns.

    Returns
    -------
    tuple of ndarray, shape (width,)
        Corrected ``(profile_a, profile_b)``.
    """
    pa = check_1d("profile_a", profile_a)
    pb = check_1d("profile_b", profile_b)
    ra = check_1d("reference_a", reference_a)
    rb = check_1d("reference_b", reference_b)
    if not pa.shape == pb.shape == ra.shape == rb.shape:
        raise ValueError(
            f"profiles and references differ in length: {pa.size}, {pb.size}, {ra.size}, {rb.size}"
        )
    if np.any(ra <= 0) or np.any(rb <= 0):
        raise ValueError("reference (flat field) profiles must be positive everywhere")
    scale = 0.5 * (ra.mean() + rb.mean())
    return pa * (scale / ra), pb * (scale / rb)


class Detrender:
    """Removes a least-squares Legendre polynomial from sub-ranges of a fixed column axis.

    Parameters
    ----------
    width : int
        Length of the full column axis, pixels.
    degree : int, optional
        Polynomial degree (0 removes the mean only).
    """

    def __init__(self, width: int, *, degree: int = 3) -> None:
        self.width = check_int("width", width, lo=2)
        self.degree = check_int("degree", degree, lo=0, hi=8)
        x = np.linspace(-1.0, 1.0, self.width)
        self._basis = np.ascontiguousarray(np.polynomial.legendre.legvander(x, self.degree))
        self._plain: dict[tuple[int, int], np.ndarray] = {}  # (start, n) -> (B'B)^-1 B'

    def trend(
        self, values: np.ndarray, *, start: int = 0, period_px: float | None = None
    ) -> np.ndarray:
        """The fitted polynomial over columns ``start .. start + len(values)``.

        A profile holds a non-whole number of marks, so a plain least-squares polynomial also
        picks up part of the marks' own slope.  With ``period_px`` (the marks' period) the
        polynomial is fitted to the running mean over one period instead, which annihilates
        anything with that period while a polynomial stays a polynomial; the same running mean
        is applied to the basis, so the fit stays exact for a pure polynomial.

        Parameters
        ----------
        values : ndarray, shape (n,)
            Samples at columns ``start + i``.
        start : int, optional
            Column of the first sample.
        period_px : float, optional
            Period of the marks, samples (ignored unless it leaves enough samples to fit).

        Returns
        -------
        ndarray, shape (n,)
        """
        v = np.asarray(values, dtype=np.float64)
        n = v.size
        if start < 0 or start + n > self.width:
            raise ValueError(f"columns {start}..{start + n} lie outside 0..{self.width}")
        if n <= self.degree:
            raise ValueError(f"need more than {self.degree} samples to detrend, got {n}")
        basis = self._basis[start : start + n]
        if period_px is not None and math.isfinite(period_px) and period_px >= 2.0:
            if n - period_px >= 4 * (self.degree + 1):
                # the running means of values and basis, the normal equations and the
                # polynomial in one compiled call
                ok, trend = kernels.smooth_trend(np.ascontiguousarray(v), basis,
                                                 float(period_px))
                if not ok:
                    raise np.linalg.LinAlgError("Singular matrix")
                return trend
        # The plain fit's pseudo-inverse depends on the columns only: set up once per range.
        pinv = self._plain.get((start, n))
        if pinv is None:
            if len(self._plain) > 64:
                self._plain.clear()
            pinv = self._plain[(start, n)] = np.linalg.solve(basis.T @ basis, basis.T)
        return basis @ (pinv @ v)

    def __call__(
        self, values: np.ndarray, *, start: int = 0, period_px: float | None = None
    ) -> np.ndarray:
        """``values`` minus :meth:`trend`."""
        v = np.asarray(values, dtype=np.float64)
        return v - self.trend(v, start=start, period_px=period_px)


def running_mean(values: np.ndarray, length: float) -> np.ndarray:
    """Mean over a window of ``length`` samples (fractional lengths allowed), valid part only.

    The samples are taken as a piecewise-constant signal (sample ``i`` covers ``[i - 1/2,
    i + 1/2]``); the window centred on ``x`` averages it over ``[x - length/2, x + length/2]``,
    for every sample ``x`` whose window lies inside the signal.

    Parameters
    ----------
    values : ndarray, shape (n,) or (n, k)
        Signal(s) along axis 0.
    length : float
        Window length, samples, ``1 <= length <= n``.

    Returns
    -------
    ndarray, shape (m,) or (m, k)
        One value per centre ``x = ceil((length - 1) / 2) .. n - 1 - ceil((length - 1) / 2)``.
    """
    v = np.asarray(values, dtype=np.float64)
    n = v.shape[0]
    if not 1.0 <= length <= n:
        raise ValueError(f"length must be in [1, {n}], got {length!r}")
    if v.ndim == 1:  # the compiled loop: the same sums and interpolation, one call
        return kernels.running_mean_1d(np.ascontiguousarray(v), float(length))
    half = 0.5 * length
    m0 = math.ceil(half - 0.5)
    centres = np.arange(m0, n - m0, dtype=np.float64)
    knots = np.arange(n + 1, dtype=np.float64) - 0.5
    cum = np.zeros((n + 1,) + v.shape[1:])
    np.cumsum(v, axis=0, out=cum[1:])
    hi = _interp_knots(centres + half, knots, cum)
    hi -= _interp_knots(centres - half, knots, cum)
    hi /= length
    return hi


def _interp_run(x: np.ndarray, knots: np.ndarray, values: np.ndarray) -> np.ndarray | None:
    """:func:`_interp_knots` for ``x`` one knot apart each (one knot interval per sample).

    The samples then fall into consecutive intervals: slices instead of gathers.  ``None``
    when they do not (the caller gathers).
    """
    last = knots.size - 1
    m = x.size
    j0 = int(np.searchsorted(knots, x[0], side="right")) - 1
    if j0 < 0 or j0 + m > last or knots[j0 + m - 1] > x[-1] or x[-1] >= knots[j0 + m]:
        return None
    base = values[j0 : j0 + m]
    slope = values[j0 + 1 : j0 + m + 1] - base
    t = x - knots[j0 : j0 + m]
    out = slope * (t if values.ndim == 1 else t[:, None])
    out += base
    return out


def _interp_knots(x: np.ndarray, knots: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``np.interp(x, knots, values)`` along axis 0 of ``values`` (1-D or 2-D), same arithmetic.

    ``knots`` evenly spaced by exactly 1 and ``x`` inside them.
    """
    if x.size > 1:
        run = _interp_run(x, knots, values)
        if run is not None:
            return run
    j = np.searchsorted(knots, x, side="right") - 1
    last = knots.size - 1
    np.minimum(j, last - 1, out=j)
    slope = values[j + 1] - values[j]  # / (knots[j + 1] - knots[j]) == / 1.0
    t = x - knots[j]
    out = slope * (t if values.ndim == 1 else t[:, None]) + values[j]
    at_end = x == knots[last]
    if np.any(at_end):
        out[at_end] = values[last]
    return out


def corrected_log_ratio(
    intensity_a: np.ndarray,
    intensity_b: np.ndarray,
    *,
    degree: int = 3,
    period_px: float | None = None,
) -> np.ndarray:
    """``log(I_B / I_A)`` with a smooth polynomial (the illumination) removed.

    Parameters
    ----------
    intensity_a, intensity_b : ndarray, shape (n,)
        Registered, positive column profiles of A and B.
    degree : int, optional
        Degree of the removed polynomial.
    period_px : float, optional
        Period of the marks, samples (see :meth:`Detrender.trend`).

    Returns
    -------
    ndarray, shape (n,)
        Detrended log-ratio; ``exp`` of it is the corrected ``I_B / I_A``.
    """
    a = check_1d("intensity_a", intensity_a)
    b = check_1d("intensity_b", intensity_b)
    if a.shape != b.shape:
        raise ValueError(f"intensity_a and intensity_b differ in length: {a.size} vs {b.size}")
    if np.any(a <= 0) or np.any(b <= 0):
        raise ValueError("intensities must be positive for the log-ratio")
    r = np.log(b / a)
    return Detrender(r.size, degree=degree)(r, period_px=period_px)
