"""Shading of the local wood defects on the renderer's board grid (its helpers, apart).

:func:`shade_patch` replaces, over one board box, the profile's shading by the exact shading
with the defects' slopes along and across the feed and their cast shadows
(:func:`cast_light`); ``self`` is the :class:`plant_sim.rendering.optics.Renderer` (its lights,
grid and scattering).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.ndimage

from plant_sim.rendering.defects import SHADOW_AMBIENT, DefectLayer

__all__ = ["BoardGrid", "cast_light", "shade_patch"]


@dataclass(frozen=True)
class BoardGrid:
    """One frame's board grid along the feed (``Renderer._radiance_grid``).

    ``edges`` the cell edges (columns ``-m .. n + m - 1``), ``z`` the profile's height there,
    um, ``p`` each cell's mean slope, ``k`` the first column's offset, ``n`` the columns,
    ``m`` the scattering kernel's half-width, ``b_u0`` the board point at undistorted column 0.
    """

    edges: np.ndarray
    z: np.ndarray
    p: np.ndarray
    k: int
    n: int
    m: int
    b_u0: float


def shade_patch(
    self: Any, rad: np.ndarray, rho_w: np.ndarray, r_w: np.ndarray, defects: DefectLayer,
    grid: BoardGrid, box: tuple[float, float, float, float], which: int,
) -> None:
    """Add to ``rad`` the shading the local defects change over one board box.

    On the box's grid cells the exact shading with the defects' slopes along and across
    the feed (and their cast shadows toward the light) replaces the profile's; the
    scattering along the fibres spreads the difference as it spreads the profile's.
    """
    dx, dy = self.dx_mm, self.dy_mm
    n, m, k = grid.n, grid.m, grid.k
    x0, x1, y0, y1 = box
    i0 = int(math.floor((x0 - grid.b_u0) / dx)) - k
    i1 = int(math.ceil((x1 - grid.b_u0) / dx)) - k + 1
    o0, o1 = max(0, i0), min(n, i1)
    r0 = max(0, int(math.floor((y0 - self._y0) / dy)))
    r1 = min(rad.shape[0], int(math.ceil((y1 - self._y0) / dy)) + 1)
    if o1 <= o0 or r1 <= r0:
        return
    e0, e1 = max(-m, o0 - m), min(n + m, o1 + m)
    xe = grid.edges[e0 + m: e1 + m + 1]
    xc = 0.5 * (xe[:-1] + xe[1:])
    yr = (self._y0 + np.arange(r0, r1) * dy)[:, None]
    h_e = defects.local_height_um(xe[None, :], yr)
    p_d = np.diff(h_e, axis=1) * (1e-3 / dx)
    q_d = (defects.local_height_um(xc[None, :], yr + 0.5 * dy)
           - defects.local_height_um(xc[None, :], yr - 0.5 * dy)) * (1e-3 / dy)
    p_base = grid.p[e0 + m: e1 + m]
    g_new, c_new = self._shade(p_base[None, :] + p_d, which, q=q_d)
    g_old, c_old = self._shade(p_base, which)
    z_c = 0.5 * (grid.z[e0 + m: e1 + m] + grid.z[e0 + m + 1: e1 + m + 1])[None, :]
    lit = cast_light(self, z_c + 0.5 * (h_e[:, :-1] + h_e[:, 1:]), which)
    dg = g_new * lit - g_old[None, :]
    dc = (c_new * lit - c_old[None, :])[:, o0 - e0: o1 - e0]
    if m:
        a = self._scatter_a
        spread = scipy.ndimage.convolve1d(dg, self._scatter_kernel, axis=1, mode="constant")
        dg = (1.0 - a) * dg + a * spread
    dg = dg[:, o0 - e0: o1 - e0]
    rad[r0:r1, o0:o1] += (rho_w[r0:r1, o0:o1] * dg.astype(np.float32)
                          - r_w[r0:r1, o0:o1] * dc.astype(np.float32))

def cast_light(self: Any, z_um: np.ndarray, which: int) -> np.ndarray:
    """1 where light ``which`` reaches a cell, :data:`SHADOW_AMBIENT` in a cast shadow.

    Shadows are cast along the feed (the lights stand at azimuth 0 and 180 deg): a cell is
    dark when the surface toward its light rises above the light's elevation from it.
    """
    cos_t = self._light[which][2]
    if abs(cos_t) < 0.5:
        return np.ones_like(z_um)
    step = self.dx_mm * 1e3 * self._tan_elevation[which]  # um per grid column
    z = z_um if cos_t > 0 else z_um[:, ::-1]  # toward the light = toward increasing index
    idx = np.arange(z.shape[1]) * step
    lowered = z - idx  # z_j - (j - i) step > z_i: cell i is in cell j's shadow
    ahead = np.maximum.accumulate(lowered[:, ::-1], axis=1)[:, ::-1]
    horizon = np.full_like(z, -np.inf)
    horizon[:, :-1] = ahead[:, 1:] + idx[:-1]
    dark = horizon > z + 1e-6
    lit = np.where(dark, SHADOW_AMBIENT, 1.0)
    return lit if cos_t > 0 else lit[:, ::-1]
