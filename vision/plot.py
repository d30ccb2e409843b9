"""Figure of a measured profile with its cuttermarks (as the seed's Figs. 5-6), Agg backend.

Pure figure building: :func:`profile_figure` returns a :class:`matplotlib.figure.Figure` bound to
an Agg canvas (no pyplot, no display); the caller saves it.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def profile_figure(
    measurement: Any,
    *,
    reference: tuple[np.ndarray, np.ndarray] | None = None,
    title: str | None = None,
    width_in: float = 11.0,
    height_in: float = 5.5,
) -> Any:
    """Plot a profile, its cusps, lowest points and mark widths.

    Parameters
    ----------
    measurement : vision.pipeline.Measurement
        Anything with ``x_mm``, ``height_um``, ``cusps_mm``, ``bottoms_mm``,
        ``mark_widths_mm``, ``mark_depths_um``, ``pitch_mm``, ``uniformity_cv``, ``depth_um``
        and ``shift_px``.
    reference : tuple of ndarray, optional
        ``(x_mm, height_um)`` of a reference profile drawn beside it (e.g. the truth).
    title : str, optional
        Figure title.
    width_in, height_in : float, optional
        Figure size, inches.

    Returns
    -------
    matplotlib.figure.Figure
        Two panels: the profile (top) and the width and depth of every mark (bottom).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    m = measurement
    x = np.asarray(m.x_mm, dtype=float)
    h = np.asarray(m.height_um, dtype=float)
    cusps = np.asarray(m.cusps_mm, dtype=float)
    bottoms = np.asarray(m.bottoms_mm, dtype=float)
    widths = np.asarray(m.mark_widths_mm, dtype=float)
    depths = np.asarray(m.mark_depths_um, dtype=float)

    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    ax, ax2 = fig.subplots(2, 1, height_ratios=(2.2, 1.0), sharex=True)
    if reference is not None:
        rx, rh = (np.asarray(v, dtype=float) for v in reference)
        inside = (rx >= x[0]) & (rx <= x[-1])
        rx, rh = rx[inside], rh[inside]
        if rx.size:
            ax.plot(rx, rh - rh.mean() + h.mean(), color="0.6", lw=1.0, label="reference")
    ax.plot(x, h, color="C0", lw=1.2, label="measured profile")
    ax.plot(cusps, np.interp(cusps, x, h), "v", color="C3", ms=5, label="cusps")
    ax.plot(bottoms, np.interp(bottoms, x, h), "o", color="C2", ms=3.5, label="lowest points")
    for c in cusps:
        ax.axvline(c, color="C3", lw=0.4, alpha=0.5)
    if widths.size <= 40:
        top = float(np.max(h)) if h.size else 0.0
        for left, w in zip(cusps[:-1], widths, strict=True):
            ax.text(left + w / 2, top, f"{w:.2f}", ha="center", va="bottom", fontsize=6.5)
    ax.set_ylabel("height (µm)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8, borderaxespad=0.0)
    summary = (
        f"pitch {m.pitch_mm:.3f} mm, uniformity CV {m.uniformity_cv:.3f}, "
        f"depth {m.depth_um:.2f} µm, {widths.size} marks, shift {m.shift_px:.2f} px"
    )
    ax.set_title(summary if title is None else f"{title}\n{summary}", fontsize=10)

    mids = 0.5 * (cusps[:-1] + cusps[1:])
    ax2.bar(mids, widths, width=0.8 * widths, color="C0", alpha=0.6, label="width (mm)")
    ax2.axhline(m.pitch_mm, color="C0", lw=0.8, ls="--")
    ax2.set_ylabel("width (mm)")
    ax3 = ax2.twinx()
    ax3.plot(mids, depths, "s-", color="C1", ms=3, lw=0.8, label="depth (µm)")
    ax3.set_ylabel("depth (µm)")
    ax2.set_xlabel("x along the feed (mm)")
    return fig
