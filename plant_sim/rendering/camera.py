"""The camera downstream of the cutter: triggers, latched counts, frame assembly and truth.

Trigger A fires every ``1 / pairs_per_s`` seconds (at ``k / pairs_per_s``) while the whole field
of view lies on a board; trigger B ``dt_ab_s`` later. The encoder counts are latched at both
triggers, and at A the index latch (the count at the spindle index pulse nearest to the moment
the board point now at the image centre was under the cutter). When B has fired the pair is
assembled: the true surface under the camera is the envelope of the knife passes recorded for
that board (:func:`plant_sim.model.surface.envelope`), its marks over image A's field of view are
the
truth, and the images are rendered by the optics :class:`~plant_sim.rendering.optics.Renderer`
(built once).

Wood defects (``[defects]``, :mod:`plant_sim.rendering.defects`) on a board are rendered with
the pair's images (their heights shaded by the renderer) and listed in the frame's truth
(``truth["defects"]``, in image A's frame).

Knots (a fault) darken an elliptical patch of the board and add a rough height profile there;
the optics renderer draws one texture per rig, so the dark patch is applied to the rendered
images per pixel (each pixel's board coordinate is known from the renderer's distortion maps).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.units import counter_difference
from plant_sim.model.surface import Passes, Surface, envelope
from plant_sim.rendering.defects import Defect, DefectLayer, nick_ridge, truth_in_frame
from protocol.frames import Frame

__all__ = ["FrameAssembler", "Knot", "Latch", "RenderJob", "TriggerClock", "render_images"]


class TriggerClock:
    """Trigger-A instants ``k / pairs_per_s``.

    Parameters
    ----------
    pairs_per_s : float
        Pair rate, Hz.
    """

    def __init__(self, pairs_per_s: float) -> None:
        self.period_s = 1.0 / pairs_per_s
        self.k = 1

    def next_time(self) -> float:
        """Time of the next trigger A."""
        return self.k * self.period_s

    def consume(self) -> None:
        """The next trigger has been handled (fired or skipped)."""
        self.k += 1


@dataclass
class Latch:
    """What is latched for one pair (A at once, B later)."""

    seq: int
    t_a: float
    s_a: float
    counts_a: int
    v_a: float
    board_id: int
    x_centre_mm: float
    index_latch: int
    t_b: float
    s_b: float = math.nan
    counts_b: int = 0
    slip_counts: int = 0


@dataclass(frozen=True)
class Knot:
    """A knot: a dark, rough elliptical patch on one board.

    Attributes
    ----------
    board_id : int
        Board that carries it.
    x_mm : float
        Centre, board coordinate (from the trailing end), mm.
    y_mm : float
        Centre across the board, mm from the optical axis.
    length_mm, width_mm : float
        Axes of the ellipse along and across the feed.
    darkness : float
        Fractional darkening at the centre (0..1).
    roughness_um : float
        Rms of the rough height profile added inside the knot.
    seed : int
        Seed of the roughness.
    """

    board_id: int
    x_mm: float
    y_mm: float = 0.0
    length_mm: float = 40.0
    width_mm: float = 30.0
    darkness: float = 0.6
    roughness_um: float = 4.0
    seed: int = 0
    _profile: Any = field(default=None, compare=False, repr=False)

    def weight(self, x_mm: np.ndarray) -> np.ndarray:
        """Smooth 0..1 weight along the board (1 at the centre, 0 beyond the half-length)."""
        r = np.abs(np.asarray(x_mm, dtype=float) - self.x_mm) / (0.5 * self.length_mm)
        return np.where(r < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.minimum(r, 1.0))), 0.0)

    def overlaps(self, x_lo_mm: float, x_hi_mm: float) -> bool:
        """Whether the knot touches ``[x_lo_mm, x_hi_mm]``."""
        h = 0.5 * self.length_mm
        return self.x_mm + h > x_lo_mm and self.x_mm - h < x_hi_mm

    def roughness(self, x_mm: np.ndarray) -> np.ndarray:
        """Rough height profile inside the knot, um (zero outside)."""
        x = np.asarray(x_mm, dtype=float)
        prof = self._profile
        if prof is None:
            rng = np.random.default_rng([self.seed, 0x6B6E6F74])
            dx = 0.02
            n = int(math.ceil(self.length_mm / dx)) + 3
            white = rng.standard_normal(n)
            ker = np.exp(-0.5 * (np.arange(-25, 26) * dx / 0.15) ** 2)
            sm = np.convolve(white, ker / np.sqrt(np.sum(ker**2)), mode="same")
            grid = self.x_mm - 0.5 * self.length_mm + dx * (np.arange(n) - 1)
            prof = (grid, sm)
            object.__setattr__(self, "_profile", prof)
        grid, sm = prof
        return self.roughness_um * self.weight(x) * np.interp(x, grid, sm)

    def albedo_factor(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Multiplicative darkening ``1 - darkness * w`` over an elliptical patch."""
        u = (np.asarray(x_mm) - self.x_mm) / (0.5 * self.length_mm)
        v = (np.asarray(y_mm) - self.y_mm) / (0.5 * self.width_mm)
        r = np.sqrt(u * u + v * v)
        w = np.where(r < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.minimum(r, 1.0))), 0.0)
        return 1.0 - self.darkness * w


class _KnottedSurface:
    """A surface's exact height plus the roughness of knots (a height source for the renderer)."""

    def __init__(self, surface: Surface, knots: list[Knot]) -> None:
        self.surface = surface
        self.knots = knots

    def height_at(self, x_mm: np.ndarray) -> np.ndarray:
        h = self.surface.height_at(x_mm)
        for k in self.knots:
            h = h + k.roughness(x_mm)
        return h

    def metrics(self, x_lo_mm: float, x_hi_mm: float) -> dict[str, object]:
        return self.surface.metrics(x_lo_mm, x_hi_mm)


@dataclass(frozen=True)
class RenderJob:
    """Everything needed to render one pair's images (picklable, for worker processes).

    Attributes
    ----------
    seq : int
        The frame's sequence number.
    source : Surface or height source
        The true surface near the field of view (with the knots' roughness, if any).
    knots : tuple of Knot
        Knots darkening the images.
    x_centre_mm : float
        Board coordinate on the optical axis at trigger A, mm.
    shift_mm : float
        Board travel from trigger A to B, mm.
    v_a_mm_s : float
        Feed speed at trigger A, mm/s (used when the optics have no A-to-B delay).
    counts_a : int
        Encoder count latched at A.
    counter_bits : int
        Encoder counter width.
    defects : DefectLayer or None
        Wood defects over the pair's board range (``None``: none).
    """

    seq: int
    source: Any
    knots: tuple[Knot, ...]
    x_centre_mm: float
    shift_mm: float
    v_a_mm_s: float
    counts_a: int
    counter_bits: int
    defects: DefectLayer | None = None


def render_images(renderer: Any, job: RenderJob, *,
                  rng_seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render a job's images A and B, shape ``(height, width)``, with its knots darkened.

    Parameters
    ----------
    renderer : plant_sim.rendering.optics.Renderer
        The renderer (built once per rig and optics).
    job : RenderJob
        What to render.
    rng_seed : int, optional
        Seed of this pair's sensor noise; ``None`` draws from the renderer's own stream.
    """
    dt = renderer.optics.dt_ab_s
    speed = job.shift_mm / dt if dt > 0 else job.v_a_mm_s
    pair = renderer.render_pair(
        job.source,
        board_x_at_centre_mm=job.x_centre_mm,
        speed_mm_s=speed,
        counts_a=job.counts_a,
        counter_bits=job.counter_bits,
        rng_seed=rng_seed,
        defects=job.defects,
    )
    image_a, image_b = pair.image_a, pair.image_b
    if job.knots:
        image_a = _darken(renderer, image_a, job.knots, job.x_centre_mm)
        image_b = _darken(renderer, image_b, job.knots, job.x_centre_mm - job.shift_mm)
    return image_a, image_b


def _darken(renderer: Any, image: np.ndarray, knots: Sequence[Knot],
            x_axis_mm: float) -> np.ndarray:
    bx = renderer.x_phys_mm + x_axis_mm
    by = renderer.y_phys_mm
    f = np.ones(image.shape, dtype=np.float32)
    for k in knots:
        f *= k.albedo_factor(bx, by).astype(np.float32)
    out = image.astype(np.float32) * f
    if np.issubdtype(image.dtype, np.integer):
        return np.clip(out + 0.5, 0, np.iinfo(image.dtype).max).astype(image.dtype)
    return out


class FrameAssembler:
    """Turns completed latches into :class:`~protocol.frames.Frame` objects.

    Parameters
    ----------
    rig : config.rig.Rig
        Camera geometry (``cx``, ``px_per_mm``) and encoder scale.
    width : int
        Image width, pixels (image A's field of view is undistorted columns ``0..width-1``).
    counter_bits : int
        Encoder counter width.
    renderer : plant_sim.rendering.optics.Renderer or None
        Renders the images; ``None`` gives frames without images (truth and counts only).
    height : int
        Image height, pixels (the field across the feed, for the defects' truth).
    roll_deg : float
        The camera's true roll (the defects' truth in image A's frame).
    defects : callable, optional
        ``defects(board_id) -> tuple of Defect`` on that board (``None``: no defects).
    """

    MARGIN_MM = 20.0

    def __init__(self, rig, *, width: int, counter_bits: int, renderer=None, height: int = 0,
                 roll_deg: float = 0.0, defects=None) -> None:
        cam = rig.camera
        self.px_per_mm = float(cam.px_per_mm)
        self.px_per_mm_y = self.px_per_mm * float(cam.fy) / float(cam.fx)
        self.cx = float(cam.cx)
        self.cy = float(cam.cy)
        self.height_px = int(height) if height else int(round(2 * self.cy + 1))
        self.roll_deg = float(roll_deg)
        self.defects = defects
        self.px_per_count = float(rig.encoder.px_per_count)
        self.x_lo_mm = -self.cx / self.px_per_mm  # FOV relative to the optical axis
        self.x_hi_mm = (width - 1 - self.cx) / self.px_per_mm
        self.counter_bits = counter_bits
        self.renderer = renderer
        self.cols_mm = np.arange(width) / self.px_per_mm
        self.jobs: dict[int, RenderJob] | None = None

    def defer_rendering(self) -> None:
        """Keep a :class:`RenderJob` per frame (see :meth:`take_job`) instead of rendering.

        For a machine built without a renderer whose images are rendered elsewhere (worker
        processes, :mod:`plant_sim.run.render_worker`).
        """
        if self.jobs is None:
            self.jobs = {}

    def take_job(self, seq: int) -> RenderJob | None:
        """The render job of frame ``seq`` (removed), or ``None``."""
        return self.jobs.pop(seq, None) if self.jobs is not None else None

    def field_mm(self, x_centre_mm: float) -> tuple[float, float]:
        """Board range of image A's (undistorted) field for a centre at ``x_centre_mm``."""
        return x_centre_mm + self.x_lo_mm, x_centre_mm + self.x_hi_mm

    def surface(self, passes: Passes, x_lo_mm: float, x_hi_mm: float) -> Surface:
        """True surface over ``[x_lo_mm, x_hi_mm]`` from the board's passes."""
        sel = passes.slice(x_lo_mm, x_hi_mm, margin_mm=self.MARGIN_MM)
        if len(sel) == 0:
            raise ValueError("no knife passes recorded there")
        xs = np.linspace(x_lo_mm, x_hi_mm, 128)
        return envelope(xs, sel)

    def truth(
        self, surface: Surface, x_centre_mm: float, shift_px: float, passes: Passes | None = None
    ) -> dict[str, Any]:
        """Truth of image A's field: the surface's marks in A's frame (``x_mm = u / px_per_mm``).

        Besides :meth:`plant_sim.model.surface.Surface.metrics` (``pitch_mm`` = mean width of the
        complete marks, ``uniformity_cv``, ``depth_um``, ``mark_widths_mm``, ``knife``, ...):
        ``bottoms_mm`` (each mark's BDC in A's frame), ``shift_px`` (true A-to-B shift),
        ``board_x_mm`` (board coordinate at the optical axis), ``board_offset_mm`` (board
        coordinate minus A-frame ``x_mm``) and ``feed_per_knife_mm`` (mean spacing of all knife
        passes over the field: the kinematic pitch, unbiased by an incomplete revolution).
        """
        lo, hi = self.field_mm(x_centre_mm)
        m = surface.metrics(lo, hi)
        if passes is not None:
            xs = np.sort(passes.slice(lo, hi).x_mm)
            m["feed_per_knife_mm"] = (
                float((xs[-1] - xs[0]) / (xs.size - 1)) if xs.size > 1 else math.nan
            )
        offset = x_centre_mm - self.cx / self.px_per_mm  # board x = x_mm + offset
        sel = surface.marks_between(lo, hi)
        m["cusps_mm"] = [c - offset for c in m["cusps_mm"]]
        m["bottoms_mm"] = [float(b - offset) for b in surface.bottoms_mm[sel]]
        m["shift_px"] = float(shift_px)
        m["board_x_mm"] = float(x_centre_mm)
        m["board_offset_mm"] = float(offset)
        return m

    def _defects_in_view(self, latch: Latch, near: Passes, lo: float, hi: float,
                         shift_mm: float) -> DefectLayer | None:
        """The board's defects near image A's and B's fields (``None``: none there)."""
        if self.defects is None:
            return None
        on_board = self.defects(latch.board_id)
        if not on_board:
            return None
        x_lo, x_hi = lo - abs(shift_mm) - 15.0, hi + abs(shift_mm) + 15.0  # shadows, blur
        items: list[Any] = []
        for d in on_board:
            b = d.bbox()
            if b[1] < x_lo or b[0] > x_hi:
                continue
            if d.kind.value == "knife_nick":
                items.append(nick_ridge(d, near, x_lo, x_hi))
            else:
                items.append(d)
        return DefectLayer(items) if items else None

    def _in_field(self, item: Any, lo: float, hi: float) -> bool:
        """Whether a defect touches image A's field (board range ``[lo, hi]``, its rows)."""
        d: Defect = getattr(item, "defect", item)
        x0, x1, y0, y1 = d.bbox()
        if d.kind.profile or d.kind.value == "knife_nick":
            y0, y1 = -math.inf, math.inf
            if d.kind.value == "knife_nick":
                y0, y1 = d.y_mm - 0.5 * d.width_mm, d.y_mm + 0.5 * d.width_mm
        top = -self.cy / self.px_per_mm_y
        bottom = (self.height_px - 1 - self.cy) / self.px_per_mm_y
        return x1 >= lo and x0 <= hi and y1 >= top and y0 <= bottom

    def _defect_truth(self, item: Any, x_centre_mm: float) -> dict[str, Any]:
        return truth_in_frame(item, x_centre_mm=x_centre_mm, cx=self.cx, cy=self.cy,
                              px_per_mm=self.px_per_mm, px_per_mm_y=self.px_per_mm_y,
                              roll_deg=self.roll_deg,
                              frame_height_mm=self.height_px / self.px_per_mm_y)

    def assemble(
        self, latch: Latch, passes: Passes, knots: list[Knot], *, board_length_mm: float
    ) -> Frame:
        """Build the frame of a completed latch."""
        shift_mm = latch.s_b - latch.s_a
        shift_px = shift_mm * self.px_per_mm
        lo, hi = self.field_mm(latch.x_centre_mm)
        near = passes.slice(lo, hi, margin_mm=self.MARGIN_MM)
        surf = self.surface(near, lo - 5.0, hi + 5.0)
        truth = self.truth(surf, latch.x_centre_mm, shift_px, near)
        counted_px = counter_difference(latch.counts_b, latch.counts_a, bits=self.counter_bits)
        truth["encoder_error_px"] = counted_px * self.px_per_count - shift_px
        mine = [k for k in knots if k.board_id == latch.board_id and k.overlaps(lo - 5, hi + 5)]
        truth["knot"] = bool(mine)
        layer = self._defects_in_view(latch, near, lo, hi, shift_mm)
        if layer is not None:
            truth["defects"] = [self._defect_truth(item, latch.x_centre_mm)
                                for item in layer.items if self._in_field(item, lo, hi)]
        image_a = image_b = None
        if self.renderer is not None or self.jobs is not None:
            job = RenderJob(
                seq=latch.seq,
                source=_KnottedSurface(surf, mine) if mine else surf,
                knots=tuple(mine),
                x_centre_mm=latch.x_centre_mm,
                shift_mm=shift_mm,
                v_a_mm_s=latch.v_a,
                counts_a=latch.counts_a,
                counter_bits=self.counter_bits,
                defects=layer,
            )
            if self.renderer is not None:
                image_a, image_b = render_images(self.renderer, job)
            else:
                self.jobs[latch.seq] = job  # type: ignore[index]
        return Frame(
            seq=latch.seq,
            t_s=latch.t_a,
            image_a=image_a,
            image_b=image_b,
            counts_a=latch.counts_a,
            counts_b=latch.counts_b,
            speed_mm_s=latch.v_a,
            index_latch_counts=latch.index_latch,
            board_id=latch.board_id,
            board_position_mm=board_length_mm - latch.x_centre_mm,
            truth=truth,
        )
