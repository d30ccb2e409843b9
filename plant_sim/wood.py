"""Wood appearance presets for the image simulator: albedo, grain, figure, fibre texture, roughness.

The grain runs along the board (along x, the feed): grain stripes vary across the board (in y)
and wander slowly along x; annual-ring / figure variation is a low-frequency modulation along x;
the fibre texture and the fibre-scale roughness are 2-D random fields elongated along x.

:func:`texture_tiles` turns a :class:`Wood` into periodic sampled fields for the renderer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from planer.checks import check_positive, check_range

__all__ = ["SPECIES", "Wood", "WoodTiles", "species", "texture_tiles"]


@dataclass(frozen=True)
class Wood:
    """Optical and micro-geometric appearance of a planed wood species (under red light).

    Attributes
    ----------
    name : str
        Species name.
    albedo : float
        Mean albedo (0..1).
    grain_contrast : float
        Relative rms of the grain stripes (earlywood/latewood), fraction of the albedo.
    grain_period_mm : float
        Mean spacing of the grain stripes across the board (in y), millimetres.
    grain_wander_mm : float
        Rms lateral wander of the stripes along the board, millimetres.
    figure_contrast : float
        Relative rms of the low-frequency annual-ring / figure variation along x.
    figure_period_mm : float
        Typical length scale of that variation along x, millimetres.
    fibre_contrast : float
        Relative rms of the fibre texture (2-D), fraction of the albedo.
    fibre_length_mm, fibre_width_mm : float
        Correlation lengths of the fibre texture along x and y, millimetres.
    pore_density_per_mm2 : float
        Density of dark elongated pores (ring-porous and diffuse-porous hardwoods), per mm^2.
    pore_contrast : float
        Relative darkening at a pore's centre.
    roughness_um : float
        Rms height of the fibre-scale roughness, micrometres.
    roughness_length_mm, roughness_width_mm : float
        Correlation lengths of the roughness along x and y, millimetres.
    """

    name: str
    albedo: float
    grain_contrast: float
    grain_period_mm: float
    grain_wander_mm: float
    figure_contrast: float
    figure_period_mm: float
    fibre_contrast: float
    fibre_length_mm: float
    fibre_width_mm: float
    pore_density_per_mm2: float
    pore_contrast: float
    roughness_um: float
    roughness_length_mm: float
    roughness_width_mm: float

    def __post_init__(self) -> None:
        check_range("albedo", self.albedo, 0.01, 1.0)
        for name in ("grain_contrast", "figure_contrast", "fibre_contrast", "pore_contrast"):
            check_range(name, getattr(self, name), 0.0, 0.9)
        for name in (
            "grain_period_mm",
            "figure_period_mm",
            "fibre_length_mm",
            "fibre_width_mm",
            "roughness_length_mm",
            "roughness_width_mm",
        ):
            check_positive(name, getattr(self, name))
        for name in ("grain_wander_mm", "pore_density_per_mm2", "roughness_um"):
            check_positive(name, getattr(self, name), allow_zero=True)


def _preset(name: str, albedo: float, grain: tuple[float, float, float],
            figure: tuple[float, float], fibre: tuple[float, float, float],
            pores: tuple[float, float], rough: tuple[float, float, float]) -> Wood:
    return Wood(name, albedo, *grain, *figure, *fibre, *pores, *rough)


SPECIES: dict[str, Wood] = {
    w.name: w
    for w in (
        # name, albedo, grain (contrast, period, wander), figure (contrast, period),
        # fibre (contrast, length, width), pores (per mm^2, contrast),
        # roughness (um rms, length, width)
        # diffuse-porous, fine and even: little grain, fine fibres
        _preset("beech", 0.55, (0.05, 1.6, 0.3), (0.04, 25.0), (0.035, 0.6, 0.04),
                (2.0, 0.25), (0.30, 0.8, 0.05)),
        # ring-porous, strong grain and large pores
        _preset("oak", 0.42, (0.12, 2.5, 0.4), (0.06, 30.0), (0.05, 1.0, 0.06),
                (4.0, 0.45), (0.60, 1.2, 0.08)),
        # softwood: strong earlywood/latewood stripes, smooth fibres, no pores
        _preset("spruce", 0.65, (0.14, 3.0, 0.5), (0.05, 40.0), (0.03, 1.5, 0.05),
                (0.0, 0.0), (0.40, 1.5, 0.06)),
        # tropical, very even and pale
        _preset("ramin", 0.62, (0.03, 1.2, 0.2), (0.03, 20.0), (0.03, 0.5, 0.04),
                (3.0, 0.20), (0.25, 0.6, 0.05)),
        # tropical, reddish, interlocked grain (ribbon stripes), open pores
        _preset("meranti", 0.40, (0.08, 4.0, 0.8), (0.08, 15.0), (0.05, 0.8, 0.06),
                (5.0, 0.40), (0.50, 1.0, 0.07)),
        # softwood with resinous latewood: high-contrast stripes
        _preset("pine", 0.60, (0.16, 4.0, 0.6), (0.06, 35.0), (0.035, 1.5, 0.05),
                (0.0, 0.0), (0.45, 1.5, 0.06)),
    )
}


def species(name: str) -> Wood:
    """The preset for ``name`` (case-insensitive); ``ValueError`` names the known species."""
    key = str(name).strip().lower()
    if key not in SPECIES:
        raise ValueError(f"species must be one of {', '.join(sorted(SPECIES))}; got {name!r}")
    return SPECIES[key]


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
