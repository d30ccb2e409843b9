"""Wood defects a planed board carries, their heights, and their ground truth.

A :class:`Defect` lies on one board, in board coordinates (``x_mm`` from the board's trailing
end as the knots' and the capture's, ``y_mm`` across the board from the camera's optical axis).
Its height (um, added to the planed profile; negative = below it):

- ``torn_grain``: a pit ``depth_um`` deep (0.05-1 mm), ``length_mm`` x ``width_mm`` (2-15 mm
  along or across the grain), soft walls over a quarter of its half-axes and a fibrous bottom
  (+-5 % of the depth, stretched along the grain);
- ``raised_grain``: ridges ``depth_um`` high (10-50 um) along the growth rings, spaced
  ``period_mm`` and at ``angle_deg`` to the feed, over a ``length_mm`` x ``width_mm`` patch;
- ``fuzzy_grain``: fibre tufts of ``depth_um`` rms (10-30 um), elongated along the grain;
- ``chip_mark``: a smooth dent ``depth_um`` deep (30-150 um), ``length_mm`` x ``width_mm``;
- ``knife_nick``: knife ``knife`` is notched ``notch_um`` over ``width_mm`` at ``y_mm``: on its
  marks the cut leaves a ridge along the whole board (its height is the kinematics', at most
  ``notch_um``: :func:`nick_ridge`);
- ``chatter``: a waviness of amplitude ``depth_um`` and period ``period_mm`` (never the pitch:
  3-20 mm, the pitch is at most 2.5 mm) along ``length_mm`` of board, across its width;
- ``snipe``: the first or last ``length_mm`` (50-150 mm) of the board cut ``depth_um`` deeper,
  the depth fading out over the inner 40 % of that length.

Chatter and snipe are 1-D (along the feed: :meth:`DefectLayer.profile_um`); the others are local
2-D fields (:meth:`DefectLayer.local_height_um`) that the renderer shades on patches of its
board grid (:meth:`plant_sim.rendering.optics.Renderer.render_pair`, ``defects=``). The truth
of a defect in a pair (:func:`truth_in_frame`) is the same keys a defect detector reports:
``kind``, ``x_mm``, ``y_mm`` (its centre in image A's undistorted frame from the top-left
corner, ``u / px_per_mm`` and ``v / px_per_mm_y``; x along the feed), ``length_mm`` (along the
feed), ``width_mm`` (across), ``depth_um`` (depth of a pit or dent, height of a ridge, rms of
fuzz, amplitude of chatter; positive), plus ``angle_deg`` and ``period_mm`` where they apply and
``board_x_mm``, ``board_y_mm`` (its board coordinates).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from config.defects import DEFECT_KINDS
from core.checks import check_finite, check_int, check_range

__all__ = [
    "KIND_RANGES",
    "Defect",
    "DefectKind",
    "DefectLayer",
    "NickRidge",
    "board_defects",
    "nick_ridge",
    "truth_in_frame",
]


class DefectKind(enum.Enum):
    """The kinds of wood defect the simulator renders."""

    TORN_GRAIN = "torn_grain"
    RAISED_GRAIN = "raised_grain"
    FUZZY_GRAIN = "fuzzy_grain"
    CHIP_MARK = "chip_mark"
    KNIFE_NICK = "knife_nick"
    CHATTER = "chatter"
    SNIPE = "snipe"

    @property
    def profile(self) -> bool:
        """Whether it is 1-D along the feed (across the whole board width)."""
        return self in (DefectKind.CHATTER, DefectKind.SNIPE)


KIND_RANGES = {DefectKind(name): r for name, r in DEFECT_KINDS.items()}
"""Each kind's physical ranges (:data:`config.defects.DEFECT_KINDS`)."""

SHADOW_AMBIENT = 0.05
"""Fraction of the direct light a cast shadow still receives (interreflections)."""


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@dataclass(frozen=True)
class Defect:
    """One defect on one board (board coordinates; see the module's description).

    Attributes
    ----------
    kind : DefectKind
    board_id : int
    x_mm, y_mm : float
        Centre: along the board from its trailing end, across it from the optical axis, mm.
    length_mm, width_mm : float
        Extent along and across the feed, mm (chatter and snipe: ``width_mm`` the board's).
    depth_um : float
        See the module's description, um (> 0).
    angle_deg : float
        Raised grain: direction of the rings from the feed, degrees.
    period_mm : float
        Raised grain: ring spacing; chatter: wavelength, mm (0: none).
    knife : int
        Knife nick: the notched knife.
    seed : int
        Seed of its random texture (torn grain's bottom, fuzzy grain, phases).
    """

    kind: DefectKind
    board_id: int
    x_mm: float
    y_mm: float
    length_mm: float
    width_mm: float
    depth_um: float
    angle_deg: float = 0.0
    period_mm: float = 0.0
    knife: int = 0
    seed: int = 0
    _texture: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.kind, DefectKind):
            object.__setattr__(self, "kind", DefectKind(self.kind))
        check_int("board_id", self.board_id, lo=0)
        for name in ("x_mm", "y_mm", "angle_deg", "period_mm"):
            check_finite(name, getattr(self, name))
        check_range("length_mm", self.length_mm, 1e-3, 1e6)
        check_range("width_mm", self.width_mm, 1e-3, 1e4)
        check_range("depth_um", self.depth_um, 1e-3, 5000.0)

    # -- extent -----------------------------------------------------------------------------
    def bbox(self) -> tuple[float, float, float, float]:
        """``(x_lo, x_hi, y_lo, y_hi)`` in board coordinates, mm, outside which it is 0."""
        hx, hy = 0.5 * self.length_mm, 0.5 * self.width_mm
        return self.x_mm - hx, self.x_mm + hx, self.y_mm - hy, self.y_mm + hy

    def shadow_reach_mm(self, tan_elevation: float) -> float:
        """How far beyond its box a cast shadow of it may reach, mm."""
        rise = self.depth_um * (1.0 if self.kind is not DefectKind.FUZZY_GRAIN else 4.0)
        return 1e-3 * rise / max(tan_elevation, 1e-3) + 0.5

    # -- heights ----------------------------------------------------------------------------
    def height_um(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        """Height added at board points ``(bx, by)`` (broadcast), um; 0 outside :meth:`bbox`.

        A knife nick's ridge needs the cut (:class:`NickRidge`); here it is 0.
        """
        bx = np.asarray(bx, dtype=float)
        by = np.asarray(by, dtype=float)
        k = self.kind
        if k is DefectKind.TORN_GRAIN:
            return self._torn(bx, by)
        if k is DefectKind.RAISED_GRAIN:
            return self._raised(bx, by)
        if k is DefectKind.FUZZY_GRAIN:
            return self._fuzzy(bx, by)
        if k is DefectKind.CHIP_MARK:
            u = (bx - self.x_mm) / (0.5 * self.length_mm)
            v = (by - self.y_mm) / (0.5 * self.width_mm)
            r2 = u * u + v * v
            return np.where(r2 < 1.0, -self.depth_um * (1.0 - np.minimum(r2, 1.0)) ** 2, 0.0)
        if k.profile:
            return np.broadcast_to(self.profile_um(bx), np.broadcast(bx, by).shape).copy()
        return np.zeros(np.broadcast(bx, by).shape)

    def profile_um(self, bx: np.ndarray) -> np.ndarray:
        """Chatter's and snipe's height along the board, um (0 for the other kinds)."""
        bx = np.asarray(bx, dtype=float)
        if self.kind is DefectKind.CHATTER:
            s = np.abs(bx - self.x_mm) / (0.5 * self.length_mm)
            env = np.where(s < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.minimum(s, 1.0))), 0.0)
            env = np.minimum(1.0, 4.0 * env)  # flat over most of its length
            phase = 2.0 * np.pi * (self.seed % 997) / 997.0
            return self.depth_um * env * np.sin(2.0 * np.pi * bx / self.period_mm + phase)
        if self.kind is DefectKind.SNIPE:
            # the board end lies at the box's outer edge: fade toward the centre of the board
            lo, hi = self.x_mm - 0.5 * self.length_mm, self.x_mm + 0.5 * self.length_mm
            ramp = 0.4 * self.length_mm
            at_trailing = self.seed % 2 == 0  # which end (chosen when placed)
            inward = (hi - bx) if at_trailing else (bx - lo)
            inside = (bx >= lo) & (bx <= hi)
            return np.where(inside, -self.depth_um * _smoothstep(inward / ramp), 0.0)
        return np.zeros(bx.shape)

    def _torn(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        u = (bx - self.x_mm) / (0.5 * self.length_mm)
        v = (by - self.y_mm) / (0.5 * self.width_mm)
        r = np.sqrt(u * u + v * v)
        wall = _smoothstep((1.0 - r) / 0.25)  # 1 over the bottom, soft walls at the rim
        fib = self._fibres(bx, by, along_mm=1.0, across_mm=0.15)
        return -self.depth_um * wall * (1.0 + 0.05 * fib)

    def _raised(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        a = math.radians(self.angle_deg)
        # distance across the rings (the rings run along (cos a, sin a))
        s = (-(bx - self.x_mm) * math.sin(a) + (by - self.y_mm) * math.cos(a)) / self.period_mm
        phase = (self.seed % 101) / 101.0
        ridge = np.maximum(np.cos(2.0 * np.pi * (s + phase)), 0.0) ** 3
        return self.depth_um * ridge * self._window(bx, by)

    def _fuzzy(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        fib = self._fibres(bx, by, along_mm=0.5, across_mm=0.08)
        return self.depth_um * fib * self._window(bx, by)

    def _window(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        """1 inside the box, 0 outside, a raised cosine over its outer 1 mm."""
        ex = 0.5 * self.length_mm - np.abs(bx - self.x_mm)
        ey = 0.5 * self.width_mm - np.abs(by - self.y_mm)
        return _smoothstep(ex / 1.0) * _smoothstep(ey / 1.0)

    def _fibres(self, bx: np.ndarray, by: np.ndarray, *, along_mm: float,
                across_mm: float) -> np.ndarray:
        """A smooth random field of unit rms over the box (correlation lengths given)."""
        tex = self._texture
        if tex is None:
            rng = np.random.default_rng([self.seed, 0x46494252])
            step_x, step_y = along_mm / 3.0, across_mm / 3.0
            x0, x1, y0, y1 = self.bbox()
            nx = int(math.ceil((x1 - x0) / step_x)) + 4
            ny = int(math.ceil((y1 - y0) / step_y)) + 4
            white = rng.standard_normal((ny, nx))
            spec = np.fft.rfft2(white)
            fy = np.fft.fftfreq(ny)[:, None]
            fx = np.fft.rfftfreq(nx)[None, :]
            spec *= np.exp(-0.5 * ((fx * 3.0 * 2 * np.pi) ** 2 + (fy * 3.0 * 2 * np.pi) ** 2))
            grid = np.fft.irfft2(spec, s=white.shape)
            grid /= max(float(np.std(grid)), 1e-12)
            tex = (x0 - 2 * step_x, y0 - 2 * step_y, step_x, step_y, grid.astype(np.float32))
            object.__setattr__(self, "_texture", tex)
        ox, oy, sx, sy, grid = tex
        fx = np.clip((bx - ox) / sx, 0.0, grid.shape[1] - 1.001)
        fy = np.clip((by - oy) / sy, 0.0, grid.shape[0] - 1.001)
        ix, iy = fx.astype(np.int64), fy.astype(np.int64)
        tx, ty = fx - ix, fy - iy
        g00 = grid[iy, ix]
        g01 = grid[iy, ix + 1]
        g10 = grid[iy + 1, ix]
        g11 = grid[iy + 1, ix + 1]
        return ((1 - ty) * ((1 - tx) * g00 + tx * g01) + ty * ((1 - tx) * g10 + tx * g11))


@dataclass(frozen=True)
class NickRidge:
    """A knife nick's ridge over one pair's board range: the cut with the knife notched.

    Attributes
    ----------
    defect : Defect
        The knife nick (``y_mm``, ``width_mm``; ``depth_um`` the notch).
    notched, plain : Surface
        The cut with the knife's passes raised by the notch, and the cut as it is.
    x_lo_mm, x_hi_mm : float
        The board range it covers (the pair's; beyond it the ridge continues as at its ends).
    """

    defect: Defect
    notched: Any
    plain: Any
    x_lo_mm: float
    x_hi_mm: float

    def ridge_um(self, bx: np.ndarray) -> np.ndarray:
        """The ridge's height along the board (>= 0), um."""
        b = np.clip(np.asarray(bx, dtype=float), self.x_lo_mm, self.x_hi_mm)
        return np.maximum(self.notched.height_at(b) - self.plain.height_at(b), 0.0)

    def height_um(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        """The ridge inside the nick's band (soft edges of 0.1 mm), um."""
        d = self.defect
        e = 0.5 * d.width_mm - np.abs(np.asarray(by, dtype=float) - d.y_mm)
        return self.ridge_um(bx) * _smoothstep(e / 0.1)

    def bbox(self) -> tuple[float, float, float, float]:
        """Board box of the ridge over the cut's range, mm."""
        d = self.defect
        return self.x_lo_mm, self.x_hi_mm, d.y_mm - 0.5 * d.width_mm, d.y_mm + 0.5 * d.width_mm

    def shadow_reach_mm(self, tan_elevation: float) -> float:
        """How far beyond its box a cast shadow of it may reach, mm."""
        return self.defect.shadow_reach_mm(tan_elevation)


def nick_ridge(defect: Defect, passes: Any, x_lo_mm: float, x_hi_mm: float) -> NickRidge:
    """The ridge a knife nick leaves over ``[x_lo_mm, x_hi_mm]`` of a board cut by ``passes``.

    The notched knife's tip stands ``depth_um`` back over the nick, so there its passes are
    that much higher; the surface there is the lower envelope of those passes.
    """
    from plant_sim.model.surface import Passes, envelope

    raised = passes.bottom_um + np.where(passes.knife == defect.knife, defect.depth_um, 0.0)
    xs = np.linspace(x_lo_mm, x_hi_mm, 64)
    notched = envelope(xs, Passes(passes.x_mm, raised, passes.knife, passes.radius_mm))
    plain = envelope(xs, passes)
    return NickRidge(defect, notched, plain, float(x_lo_mm), float(x_hi_mm))


class DefectLayer:
    """The defects over one pair's board range, as the renderer takes them.

    Parameters
    ----------
    items : sequence of Defect or NickRidge
        Local defects (2-D, shaded on patches) and 1-D ones (chatter, snipe).
    """

    def __init__(self, items: Sequence[Any]) -> None:
        self.items = tuple(items)
        self.profiles = tuple(d for d in self.items
                              if isinstance(d, Defect) and d.kind.profile)
        self.local = tuple(d for d in self.items if d not in self.profiles)

    def __bool__(self) -> bool:
        return bool(self.items)

    def profile_um(self, bx: np.ndarray) -> np.ndarray:
        """Chatter and snipe along the board, um."""
        out = np.zeros(np.shape(bx))
        for d in self.profiles:
            out = out + d.profile_um(bx)
        return out

    def local_height_um(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        """The local defects' heights at ``(bx, by)`` (broadcast), um."""
        out = np.zeros(np.broadcast(np.asarray(bx), np.asarray(by)).shape)
        for d in self.local:
            out = out + d.height_um(bx, by)
        return out

    def height_um(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        """Every defect's height at ``(bx, by)``: what the renderer adds to the profile, um."""
        return self.local_height_um(bx, by) + self.profile_um(bx)

    def patches(self, tan_elevation: float) -> list[tuple[tuple[float, float, float, float],
                                                         DefectLayer]]:
        """Board boxes covering the local defects and their shadows, overlapping ones merged.

        Each with the layer of the defects it covers (what the box's shading needs).
        """
        boxes: list[tuple[list[float], list[Any]]] = []
        for d in self.local:
            x0, x1, y0, y1 = d.bbox()
            reach = d.shadow_reach_mm(tan_elevation)
            boxes.append(([x0 - reach, x1 + reach, y0 - 0.2, y1 + 0.2], [d]))
        merged = True
        while merged and len(boxes) > 1:
            merged = False
            for i in range(len(boxes)):
                for j in range(i + 1, len(boxes)):
                    a, b = boxes[i][0], boxes[j][0]
                    if a[0] <= b[1] and b[0] <= a[1] and a[2] <= b[3] and b[2] <= a[3]:
                        box = [min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]),
                               max(a[3], b[3])]
                        boxes[i] = (box, boxes[i][1] + boxes[j][1])
                        del boxes[j]
                        merged = True
                        break
                if merged:
                    break
        return [(tuple(b), DefectLayer(items)) for b, items in boxes]  # type: ignore[misc]


def truth_in_frame(item: Any, *, x_centre_mm: float, cx: float, cy: float, px_per_mm: float,
                   px_per_mm_y: float, roll_deg: float,
                   frame_height_mm: float) -> dict[str, Any]:
    """A defect's truth in image A's undistorted frame (see the module's description).

    Parameters
    ----------
    item : Defect or NickRidge
        The defect.
    x_centre_mm : float
        Board coordinate on the optical axis at trigger A, mm.
    cx, cy : float
        Principal point, pixels.
    px_per_mm, px_per_mm_y : float
        Undistorted scale along and across the feed, pixels per mm.
    roll_deg : float
        The camera's roll (the renderer's convention).
    frame_height_mm : float
        Height of the image across the feed, mm (the width of chatter and snipe as seen).
    """
    d = item.defect if isinstance(item, NickRidge) else item
    r = math.radians(roll_deg)
    if d.kind.profile:
        bx, by = d.x_mm, 0.0
    else:
        bx, by = d.x_mm, d.y_mm
    x_phys, y_phys = bx - x_centre_mm, by
    xc = x_phys * math.cos(r) - y_phys * math.sin(r)
    yc = x_phys * math.sin(r) + y_phys * math.cos(r)
    out: dict[str, Any] = {
        "kind": d.kind.value,
        "x_mm": float((cx + xc * px_per_mm) / px_per_mm),
        "y_mm": float((cy + yc * px_per_mm_y) / px_per_mm_y),
        "length_mm": float(d.length_mm),
        "width_mm": float(frame_height_mm if d.kind.profile else d.width_mm),
        "depth_um": float(d.depth_um),
        "board_x_mm": float(d.x_mm),
        "board_y_mm": float(d.y_mm),
    }
    if d.kind is DefectKind.RAISED_GRAIN:
        out["angle_deg"] = float(d.angle_deg)
    if d.kind in (DefectKind.RAISED_GRAIN, DefectKind.CHATTER):
        out["period_mm"] = float(d.period_mm)
    if d.kind is DefectKind.KNIFE_NICK:
        out["knife"] = int(d.knife)
        out["notch_um"] = float(d.depth_um)
        if isinstance(item, NickRidge):
            xs = np.linspace(item.x_lo_mm, item.x_hi_mm, 2000)
            out["depth_um"] = float(np.max(item.ridge_um(xs)))  # the ridge the cut left
    return out


def board_defects(specs: Sequence[Any], *, board_id: int, board_length_mm: float,
                  board_width_mm: float, knives: int, seed: int) -> tuple[Defect, ...]:
    """The defects configured for one board (``[[defects.place]]``), drawn from ``seed``.

    Parameters
    ----------
    specs : sequence of config.sim.DefectPlaceConfig
        Per kind: ``kind``, ``per_board`` and the ranges ``depth_um``, ``length_mm``,
        ``width_mm``, ``period_mm`` to draw from; ``along_fraction`` (torn grain).
    board_id : int
        The board (its draw is the same whenever it is asked for).
    board_length_mm, board_width_mm : float
        The board's size, mm; defects lie 20 mm clear of its ends (snipe at an end).
    knives : int
        Knives of the cutterhead (the notched one of a nick).
    seed : int
        The simulator's seed.
    """
    out: list[Defect] = []
    half_w = 0.5 * board_width_mm
    for i, spec in enumerate(specs):
        kind = DefectKind(spec.kind)
        rng = np.random.default_rng([seed, board_id, i, 0x44454643])
        n = int(math.floor(spec.per_board))
        if rng.random() < spec.per_board - n:
            n += 1
        for j in range(n):
            depth = float(rng.uniform(*spec.depth_um))
            length = float(rng.uniform(*spec.length_mm)) if spec.length_mm else 0.0
            width = float(rng.uniform(*spec.width_mm)) if spec.width_mm else 0.0
            period = float(rng.uniform(*spec.period_mm)) if spec.period_mm else 0.0
            dseed = int(rng.integers(0, 2**31 - 1))
            angle = 0.0
            knife = 0
            if kind is DefectKind.TORN_GRAIN:
                side = length * float(rng.uniform(0.2, 0.5))
                if rng.random() >= spec.along_fraction:  # across the grain
                    length, width = side, length
                else:
                    width = side
            elif kind is DefectKind.RAISED_GRAIN:
                angle = float(rng.uniform(0.0, 180.0))
            elif kind is DefectKind.KNIFE_NICK:
                length = board_length_mm
                knife = int(rng.integers(0, knives))
            if kind is DefectKind.SNIPE:
                dseed = 2 * (dseed // 2) + (j % 2)  # alternate ends (the seed's parity)
                at_trailing = dseed % 2 == 0
                x = 0.5 * length if at_trailing else board_length_mm - 0.5 * length
                y = 0.0
                width = board_width_mm
            elif kind is DefectKind.CHATTER:
                x = float(rng.uniform(0.5 * length, max(0.5 * length + 1.0,
                                                        board_length_mm - 0.5 * length)))
                y, width = 0.0, board_width_mm
            elif kind is DefectKind.KNIFE_NICK:
                x = 0.5 * board_length_mm
                y = float(rng.uniform(-0.5 * half_w, 0.5 * half_w))
            else:
                margin = 20.0 + 0.5 * length
                x = float(rng.uniform(margin, board_length_mm - margin))
                y = float(rng.uniform(-0.4 * half_w, 0.4 * half_w))
            out.append(Defect(kind=kind, board_id=board_id, x_mm=x, y_mm=y, length_mm=length,
                              width_mm=width, depth_um=depth, angle_deg=angle, period_mm=period,
                              knife=knife, seed=dseed))
    return tuple(out)
