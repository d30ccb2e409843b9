"""Surface slope p = dz/dx from two intensity profiles (seed Eq. 4, general azimuths).

With q = 0 the Lambertian model (seed Eq. 1) gives for a light at slant sigma and azimuth tau

    I = I0 * rho * (cos(sigma) - p * cos(tau) * sin(sigma)) / sqrt(1 + p^2).

For tau_A = 0 and tau_B = 180 deg this is ``I_A ~ cos(sigma) - p sin(sigma)`` and
``I_B ~ cos(sigma) + p sin(sigma)``: the light at 180 deg gives **+p sin(sigma)** (the seed's
Eq. 3b misprints the sign).  Eliminating ``I0 * rho / sqrt(1 + p^2)`` between the two lights gives
seed Eq. 4 with light 1 = A and light 2 = B:

    p = (I_B - I_A) / (I_B cos(tau_A) - I_A cos(tau_B)) / tan(sigma),

which is ``(I_B - I_A) / (I_B + I_A) / tan(sigma)`` for opposed lights.  It needs
``cos(tau_A) != cos(tau_B)``.
"""

from __future__ import annotations

import math

import numpy as np

from core.checks import check_finite, check_range
from vision import kernels


def _angles(slant_deg: float, azimuth_a_deg: float, azimuth_b_deg: float) -> tuple[float, ...]:
    s = check_range("slant_deg", slant_deg, 0.0, 89.9)
    if s <= 0.0:
        raise ValueError(f"slant_deg must be > 0, got {slant_deg!r}")
    ca = math.cos(math.radians(check_finite("azimuth_a_deg", azimuth_a_deg)))
    cb = math.cos(math.radians(check_finite("azimuth_b_deg", azimuth_b_deg)))
    if abs(ca - cb) < 1e-3:
        raise ValueError(
            f"azimuth_a_deg={azimuth_a_deg} and azimuth_b_deg={azimuth_b_deg} have the same "
            "cosine: the two lights cannot separate the slope along x"
        )
    return math.tan(math.radians(s)), ca, cb


def slope_eq4(
    intensity_a: np.ndarray,
    intensity_b: np.ndarray,
    *,
    slant_deg: float,
    azimuth_a_deg: float = 0.0,
    azimuth_b_deg: float = 180.0,
) -> np.ndarray:
    """Slope from two intensities by seed Eq. 4.

    Parameters
    ----------
    intensity_a, intensity_b : array_like, same shape
        Intensities of the same surface points lit by light A and light B (any units, equal
        light strengths assumed; see :mod:`vision.calibration.illumination` otherwise).
    slant_deg : float
        Slant (zenith) angle of both lights from the camera axis, degrees.
    azimuth_a_deg, azimuth_b_deg : float, optional
        Azimuths of lights A and B from +x, degrees.

    Returns
    -------
    ndarray, same shape
        Slope ``p = dz/dx`` (dimensionless); NaN where the denominator vanishes.
    """
    tan_s, ca, cb = _angles(slant_deg, azimuth_a_deg, azimuth_b_deg)
    ia = np.asarray(intensity_a, dtype=np.float64)
    ib = np.asarray(intensity_b, dtype=np.float64)
    if ia.shape != ib.shape:
        raise ValueError(f"intensity_a and intensity_b differ in shape: {ia.shape} vs {ib.shape}")
    den = (ib * ca - ia * cb) * tan_s
    with np.errstate(divide="ignore", invalid="ignore"):
        p = (ib - ia) / den
    return np.where(den != 0, p, np.nan)


def slope_from_ratio(
    ratio_ba: np.ndarray,
    *,
    slant_deg: float,
    azimuth_a_deg: float = 0.0,
    azimuth_b_deg: float = 180.0,
    slant_b_deg: float | None = None,
) -> np.ndarray:
    """Slope from the intensity ratio ``I_B / I_A`` (seed Eq. 4 divided through by ``I_A``).

    Parameters
    ----------
    ratio_ba : array_like
        ``I_B / I_A`` after any illumination correction.
    slant_deg, azimuth_a_deg, azimuth_b_deg : float
        As in :func:`slope_eq4`.
    slant_b_deg : float, optional
        Light B's own slant when it differs from light A's (``slant_deg`` is then light A's).
        Each intensity divided by its own ``cos(sigma)`` (the illumination correction does
        that), ``r = (1 - p cos(tau_B) tan(sigma_B)) / (1 - p cos(tau_A) tan(sigma_A))``.

    Returns
    -------
    ndarray
        Slope ``p = (r - 1) / (r cos(tau_A) tan(sigma_A) - cos(tau_B) tan(sigma_B))``.
    """
    tan_s, ca, cb = _angles(slant_deg, azimuth_a_deg, azimuth_b_deg)
    tan_b = tan_s
    if slant_b_deg is not None:
        tan_b, _, _ = _angles(slant_b_deg, azimuth_a_deg, azimuth_b_deg)
    r = np.asarray(ratio_ba, dtype=np.float64)
    den = r * ca * tan_s - cb * tan_b
    with np.errstate(divide="ignore", invalid="ignore"):
        p = (r - 1.0) / den
    return np.where(den != 0, p, np.nan)


def lambert_intensity(
    slope: np.ndarray, *, slant_deg: float, azimuth_deg: float, albedo: float | np.ndarray = 1.0
) -> np.ndarray:
    """Seed Eq. 2 (q = 0): intensity of a surface of slope ``p`` under one light.

    Parameters
    ----------
    slope : array_like
        ``p = dz/dx``.
    slant_deg, azimuth_deg : float
        The light's slant from the camera axis and azimuth from +x, degrees.
    albedo : float or array_like, optional
        ``I0 * rho``.

    Returns
    -------
    ndarray
        ``albedo * (cos(s) - p cos(t) sin(s)) / sqrt(1 + p^2)``, clipped at 0 (self-shadow).
    """
    p = np.asarray(slope, dtype=np.float64)
    s = math.radians(check_finite("slant_deg", slant_deg))
    t = math.radians(check_finite("azimuth_deg", azimuth_deg))
    val = (math.cos(s) - p * math.cos(t) * math.sin(s)) / np.sqrt(1.0 + p * p)
    return np.asarray(albedo) * np.clip(val, 0.0, None)


class RatioSlope:
    """:func:`slope_from_ratio` of one light geometry (checked and set up once).

    Parameters
    ----------
    slant_deg, azimuth_a_deg, azimuth_b_deg, slant_b_deg : float
        As in :func:`slope_from_ratio`.
    """

    def __init__(self, *, slant_deg: float, azimuth_a_deg: float = 0.0,
                 azimuth_b_deg: float = 180.0, slant_b_deg: float | None = None) -> None:
        tan_s, ca, cb = _angles(slant_deg, azimuth_a_deg, azimuth_b_deg)
        tan_b = tan_s
        if slant_b_deg is not None:
            tan_b, _, _ = _angles(slant_b_deg, azimuth_a_deg, azimuth_b_deg)
        self._ca, self._tan_a = ca, tan_s
        self._b = cb * tan_b

    def __call__(self, ratio_ba: np.ndarray) -> np.ndarray:
        """Slope ``p`` from ``I_B / I_A`` (NaN where the denominator vanishes)."""
        r = np.asarray(ratio_ba, dtype=np.float64)
        out = np.empty(r.shape)  # any shape, a scalar's too: one compiled pass over its values
        kernels.ratio_slope(np.ascontiguousarray(r).reshape(-1), self._ca, self._tan_a, self._b,
                            out.reshape(-1))
        return out

    def finite(self, ratio_ba: np.ndarray) -> tuple[np.ndarray, bool]:
        """The slope of a 1-D ratio (as the call) and whether every sample of it is finite.

        One compiled pass (:func:`vision.kernels.ratio_slope`: the call's operations in its
        order).
        """
        r = np.ascontiguousarray(ratio_ba, dtype=np.float64)
        if r.ndim != 1:
            raise ValueError(f"ratio_ba must be 1-D, got shape {r.shape}")
        out = np.empty(r.size)
        ok = kernels.ratio_slope(r, self._ca, self._tan_a, self._b, out)
        return out, bool(ok)
