"""Wood species presets: the optical and micro-geometric appearance of planed wood, by species.

A data table (no I/O): the simulator's configuration names a species from it, and
:mod:`plant_sim.rendering.wood` turns a preset into sampled texture fields for the renderer.
"""

from __future__ import annotations

from dataclasses import dataclass

from core.checks import check_positive, check_range

__all__ = ["SPECIES", "Wood", "species"]


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
    translucency : float
        Fraction (0..1) of the reflected light that leaves the wood after subsurface scattering
        (spread by the rig's scattering length, see :class:`plant_sim.rendering.optics.RigEffects`)
        instead of at the point where it entered; softwoods (spruce, pine) are the most
        translucent.
    scattering_anisotropy : float
        Ratio (>= 1) of the scattering length along the fibres (x) to the one across them (y).
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
    translucency: float = 0.0
    scattering_anisotropy: float = 1.0

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
        check_range("translucency", self.translucency, 0.0, 1.0)
        check_range("scattering_anisotropy", self.scattering_anisotropy, 1.0, 100.0)


def _preset(name: str, albedo: float, grain: tuple[float, float, float],
            figure: tuple[float, float], fibre: tuple[float, float, float],
            pores: tuple[float, float], rough: tuple[float, float, float],
            scattering: tuple[float, float]) -> Wood:
    return Wood(name, albedo, *grain, *figure, *fibre, *pores, *rough, *scattering)


SPECIES: dict[str, Wood] = {
    w.name: w
    for w in (
        # name, albedo, grain (contrast, period, wander), figure (contrast, period),
        # fibre (contrast, length, width), pores (per mm^2, contrast),
        # roughness (um rms, length, width), subsurface scattering (translucency, anisotropy)
        # diffuse-porous, fine and even: little grain, fine fibres
        _preset("beech", 0.55, (0.05, 1.6, 0.3), (0.04, 25.0), (0.035, 0.6, 0.04),
                (2.0, 0.25), (0.30, 0.8, 0.05), (0.25, 2.0)),
        # ring-porous, strong grain and large pores
        _preset("oak", 0.42, (0.12, 2.5, 0.4), (0.06, 30.0), (0.05, 1.0, 0.06),
                (4.0, 0.45), (0.60, 1.2, 0.08), (0.2, 2.0)),
        # softwood: strong earlywood/latewood stripes, smooth fibres, no pores
        _preset("spruce", 0.65, (0.14, 3.0, 0.5), (0.05, 40.0), (0.03, 1.5, 0.05),
                (0.0, 0.0), (0.40, 1.5, 0.06), (0.6, 3.0)),
        # tropical, very even and pale
        _preset("ramin", 0.62, (0.03, 1.2, 0.2), (0.03, 20.0), (0.03, 0.5, 0.04),
                (3.0, 0.20), (0.25, 0.6, 0.05), (0.3, 2.0)),
        # tropical, reddish, interlocked grain (ribbon stripes), open pores
        _preset("meranti", 0.40, (0.08, 4.0, 0.8), (0.08, 15.0), (0.05, 0.8, 0.06),
                (5.0, 0.40), (0.50, 1.0, 0.07), (0.25, 2.0)),
        # softwood with resinous latewood: high-contrast stripes
        _preset("pine", 0.60, (0.16, 4.0, 0.6), (0.06, 35.0), (0.035, 1.5, 0.05),
                (0.0, 0.0), (0.45, 1.5, 0.06), (0.55, 3.0)),
    )
}


def species(name: str) -> Wood:
    """The preset for ``name`` (case-insensitive); ``ValueError`` names the known species."""
    key = str(name).strip().lower()
    if key not in SPECIES:
        raise ValueError(f"species must be one of {', '.join(sorted(SPECIES))}; got {name!r}")
    return SPECIES[key]
