"""Wood textures for the image simulator: a species preset turned into sampled periodic fields.

The grain runs along the board (along x, the feed): grain stripes vary across the board (in y)
and wander slowly along x; annual-ring / figure variation is a low-frequency modulation along x;
the fibre texture and the fibre-scale roughness are 2-D random fields elongated along x.

:func:`texture_tiles` turns a :class:`config.wood.Wood` preset into periodic sampled fields.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from config.wood import Wood

__all__ = ["WoodTiles", "texture_tiles"]


@dataclass(frozen=True)
class WoodTiles:
    """Periodic sampled wood fields on a regular board grid (float32, shape (rows, cols)).

    Attributes
    ----------
    albedo : ndarray
        Albedo (0..1) at each grid node.
    slope_x, slope_y : ndarray
        Roughness slopes dz/dx and dz/dy (dimensionless).
    dx_mm, dy_mm : float
        Grid steps along x (period ``cols * dx_mm``) and y.
    """

    albedo: np.ndarray
    slope_x: np.ndarray
    slope_y: np.ndarray
    dx_mm: float
    dy_mm: float


def _spectrum(
    rng: np.random.Generator, shape: tuple[int, int], d: tuple[float, float],
    corr_mm: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-spectrum (rfft2 layout) of a periodic Gaussian field with Gaussian correlation.

    Returns the (unnormalised) spectrum and the angular wavenumbers ``ky`` (column vector) and
    ``kx`` (row vector), rad/mm.
    """
    rows, cols = shape
    ky = (2 * np.pi * sfft.fftfreq(rows, d[0]))[:, None].astype(np.float32)
    kx = (2 * np.pi * sfft.rfftfreq(cols, d[1]))[None, :].astype(np.float32)
    amp = np.exp(-0.25 * ((kx * corr_mm[1]) ** 2 + (ky * corr_mm[0]) ** 2))
    spec = rng.standard_normal(amp.shape, dtype=np.float32) * amp + 1j * (
        rng.standard_normal(amp.shape, dtype=np.float32) * amp
    )
    spec[0, 0] = 0.0
    return spec.astype(np.complex64), ky, kx


def _field(spec: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    return sfft.irfft2(spec, s=shape, workers=1).astype(np.float32, copy=False)


def _periodic_1d(rng: np.random.Generator, n: int, d: float, scale_mm: float) -> np.ndarray:
    """Periodic 1-D Gaussian random signal with correlation length ``scale_mm``; unit rms."""
    k = 2 * np.pi * np.fft.rfftfreq(n, d)
    spec = (rng.standard_normal(k.size) + 1j * rng.standard_normal(k.size)) * np.exp(
        -0.25 * (k * scale_mm) ** 2
    )
    spec[0] = 0.0
    sig = np.fft.irfft(spec, n)
    rms = float(sig.std()) or 1.0
    return sig / rms


def texture_tiles(
    wood: Wood, *, rows: int, cols: int, dx_mm: float, dy_mm: float, seed: int
) -> WoodTiles:
    """Sample a wood's albedo and roughness slopes on a grid periodic along x.

    Parameters
    ----------
    wood : Wood
        Species appearance.
    rows, cols : int
        Grid size; the grid is periodic with period ``cols * dx_mm`` along x.
    dx_mm, dy_mm : float
        Grid steps along x (feed) and y, millimetres.
    seed : int
        Random seed (the same seed gives the same board).
    """
    rng = np.random.default_rng(seed)
    y = np.arange(rows) * dy_mm
    # grain stripes: a random signal across the board, sampled at y + wander(x)
    n_stripe = int(np.ceil((rows * dy_mm + 20.0 * wood.grain_period_mm + 10.0) / 0.01))
    stripe = _periodic_1d(rng, n_stripe, 0.01, 0.25 * wood.grain_period_mm)
    # sharpen into earlywood/latewood bands: a periodic carrier with random phase jitter
    yy = np.arange(n_stripe) * 0.01
    carrier = np.sin(2 * np.pi * yy / wood.grain_period_mm + 2.0 * stripe)
    stripe = 0.6 * carrier + 0.4 * stripe
    stripe /= stripe.std() or 1.0
    wander = wood.grain_wander_mm * _periodic_1d(rng, cols, dx_mm, 10.0)
    pos = (y[:, None] + wander[None, :] + 5.0 * wood.grain_period_mm + 5.0) / 0.01
    grain = np.interp(pos.ravel(), np.arange(n_stripe), stripe).reshape(rows, cols)
    figure = _periodic_1d(rng, cols, dx_mm, 0.3 * wood.figure_period_mm)
    shape = (rows, cols)
    fspec, _, _ = _spectrum(rng, shape, (dy_mm, dx_mm), (wood.fibre_width_mm, wood.fibre_length_mm))
    fibre = _field(fspec, shape)
    rel = fibre * np.float32(wood.fibre_contrast / (float(fibre.std()) or 1.0))
    del fibre
    rel += (wood.grain_contrast * grain + wood.figure_contrast * figure[None, :]).astype(np.float32)
    if wood.pore_density_per_mm2 > 0 and wood.pore_contrast > 0:
        area = rows * dy_mm * cols * dx_mm
        n = rng.poisson(wood.pore_density_per_mm2 * area)
        pores = np.zeros(shape, dtype=np.float32)
        np.add.at(
            pores,
            (rng.integers(0, rows, n), rng.integers(0, cols, n)),
            rng.uniform(0.5, 1.0, n).astype(np.float32),
        )
        # elongated along x: Gaussian blur (sigma 0.25 mm along x, 0.03 mm across), periodic
        ky = (2 * np.pi * sfft.fftfreq(rows, dy_mm))[:, None]
        kx = (2 * np.pi * sfft.rfftfreq(cols, dx_mm))[None, :]
        sx, sy = 0.25, 0.03
        ker = np.exp(-0.5 * ((kx * sx) ** 2 + (ky * sy) ** 2)).astype(np.float32)
        pores = _field(sfft.rfft2(pores, workers=1) * ker, shape)
        peak = dx_mm * dy_mm / (2 * np.pi * sx * sy)
        rel -= np.float32(wood.pore_contrast) * np.minimum(pores * np.float32(1.0 / peak), 1.0)
    albedo = np.clip(np.float32(wood.albedo) * (1.0 + rel), 0.0, 1.0)
    if wood.roughness_um > 0:
        rspec, ky, kx = _spectrum(
            rng, shape, (dy_mm, dx_mm), (wood.roughness_width_mm, wood.roughness_length_mm)
        )
        rms = float(_field(rspec, shape).std()) or 1.0
        rspec *= np.float32(1e-3 * wood.roughness_um / rms)
        gx = _field(rspec * (1j * kx), shape)
        gy = _field(rspec * (1j * ky), shape)
    else:
        gx = np.zeros(shape, dtype=np.float32)
        gy = np.zeros(shape, dtype=np.float32)
    return WoodTiles(
        albedo=albedo.astype(np.float32),
        slope_x=gx.astype(np.float32),
        slope_y=gy.astype(np.float32),
        dx_mm=float(dx_mm),
        dy_mm=float(dy_mm),
    )
