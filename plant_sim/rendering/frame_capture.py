"""Frame capture: the camera's triggers, their latches, and the assembly of each image pair.

Trigger A fires on the trigger clock (``[camera] pairs_per_s``) whenever the whole field of view
lies on a board (5 mm clear of its ends); it latches the encoder count, the index latch (the
count at the index pulse nearest to the moment the board point at the image centre was under
the cutter, from :class:`plant_sim.model.cut_record.CutRecord`) and the board position. Trigger B
fires ``dt_ab_s`` later and latches the count again; then the frame is assembled
(:class:`plant_sim.rendering.camera.FrameAssembler`, images by the optics renderer built once
here). A
pending belt slip (the ``belt_slip`` fault) is applied to the counter between A and B.
"""

from __future__ import annotations

import math
from typing import Any

from config.sim import SimConfig
from plant_sim.model.cut_record import CutRecord, PassLog
from plant_sim.model.feed_drive import BoardStream, Encoder, FeedDrive
from plant_sim.model.surface import Passes
from plant_sim.rendering.camera import FrameAssembler, Knot, Latch, TriggerClock
from protocol.frames import Frame

__all__ = ["BoardDefects", "FrameCapture", "build_renderer"]

_FIELD_MARGIN_MM = 5.0  # the field of view must be this far inside the board's ends


def build_renderer(cfg: SimConfig, *, seed: int) -> Any:
    """The optics renderer of ``cfg``'s camera (rig, species, ``[camera.optics]``, rig effects).

    Parameters
    ----------
    cfg : config.sim.SimConfig
        The simulator configuration.
    seed : int
        Seed of the wood texture and the image noise.

    Returns
    -------
    plant_sim.rendering.optics.Renderer
        Built once; renders each pair's two images.
    """
    from config.wood import SPECIES
    from plant_sim.rendering.optics import Optics, Renderer, effects_from_config

    cam = cfg.camera
    o = cam.optics
    optics = Optics(
        width=o.width,
        height=o.height,
        led_imbalance=o.imbalance,
        falloff=o.falloff,
        read_noise_dn=o.noise,
        dt_ab_s=cam.dt_ab_s,
        counts_per_mm=cfg.encoder.counts_per_mm,
    )
    return Renderer(cam.rig, optics, SPECIES[cam.species], seed=seed,
                    effects=effects_from_config(cfg))


class BoardDefects:
    """The defects of each board (``[defects]``), drawn once per board and kept.

    Callable: ``defects(board_id) -> tuple of Defect`` (empty for the boards without).

    Parameters
    ----------
    cfg : config.sim.SimConfig
        ``[defects]``, the boards' size and the knives.
    """

    def __init__(self, cfg: SimConfig) -> None:
        self.cfg = cfg.defects
        self.length_mm = cfg.board.length_mm
        self.width_mm = cfg.board.width_mm
        self.knives = cfg.cutterhead.knives
        self._boards: dict[int, tuple[Any, ...]] = {}

    def __call__(self, board_id: int) -> tuple[Any, ...]:
        """The defects of ``board_id`` (the same tuple every time it is asked)."""
        got = self._boards.get(board_id)
        if got is None:
            got = ()
            if self.cfg.on_board(board_id):
                from plant_sim.rendering.defects import board_defects

                got = board_defects(self.cfg.place, board_id=board_id,
                                    board_length_mm=self.length_mm,
                                    board_width_mm=self.width_mm, knives=self.knives,
                                    seed=self.cfg.seed)
            if len(self._boards) > 64:
                self._boards.pop(next(iter(self._boards)))
            self._boards[board_id] = got
        return got


class FrameCapture:
    """The camera station: trigger clock, latches A/B, knots on the boards, frame assembly.

    Parameters
    ----------
    cfg : config.sim.SimConfig
        The configuration (``[camera]``, ``[encoder]``).
    feed, encoder, boards : plant_sim.model.feed_drive.FeedDrive, Encoder, BoardStream
        The table, its counter and the boards on it.
    cut : plant_sim.model.cut_record.CutRecord
        The passes (for the truth and the images) and the index pulses.
    renderer : plant_sim.rendering.optics.Renderer or None
        Renders the images; ``None``: frames without images.

    Attributes
    ----------
    assembler : plant_sim.rendering.camera.FrameAssembler
        Builds each frame (the runner may defer its rendering).
    knots : list of plant_sim.rendering.camera.Knot
        Knots placed on boards (by the ``knot`` fault).
    last_pair : plant_sim.rendering.camera.Latch or None
        The last completed pair's latches (the trigger registers show them).
    frames_dropped : int
        Pairs that could not be assembled (no passes under the field of view).
    pending_slip : int or None
        Counts a ``belt_slip`` adds between A and B of the next pair.
    """

    def __init__(self, cfg: SimConfig, *, feed: FeedDrive, encoder: Encoder,
                 boards: BoardStream, cut: CutRecord, renderer: Any = None) -> None:
        cam = cfg.camera
        self.L_mm = cam.cutter_to_camera_mm
        self.dt_ab_s = cam.dt_ab_s
        self.feed = feed
        self.encoder = encoder
        self.boards = boards
        self.cut = cut
        self.defects = BoardDefects(cfg) if cfg.defects.active else None
        self.assembler = FrameAssembler(
            cam.rig, width=cam.optics.width, counter_bits=cfg.encoder.counter_bits,
            renderer=renderer, height=cam.optics.height, roll_deg=cam.roll_deg,
            defects=self.defects,
        )
        self._fov_lo, self._fov_hi = self.assembler.x_lo_mm, self.assembler.x_hi_mm
        self.triggers = TriggerClock(cam.pairs_per_s)
        self.latch: Latch | None = None
        self.seq = 0
        self.last_pair: Latch | None = None
        self.knots: list[Knot] = []
        self.frames_dropped = 0
        self.pending_slip: int | None = None
        self._due_s = -math.inf  # the next trigger A or B, once known

    def events_until(self, t1: float, frames: list[Frame]) -> None:
        """Fire every trigger due up to ``t1`` s; completed frames are appended to ``frames``."""
        if t1 < self._due_s:  # runs every PLC cycle: nothing is due before the next trigger
            return
        trig = self.triggers
        while True:
            la = self.latch
            tn = trig.k * trig.period_s  # TriggerClock.next_time(), inlined
            tb = la.t_b if la is not None else math.inf
            if tb <= t1 and tb <= tn:
                self._trigger_b(la, frames)  # type: ignore[arg-type]
            elif tn <= t1:
                trig.consume()
                if la is None:
                    self._trigger_a(tn)
            else:
                self._due_s = min(tn, tb)  # latch and clock change only here
                break

    def shift_latch(self, delta_counts: int) -> None:
        """Shift the counts of a pair in flight (the counter was preset by ``delta_counts``)."""
        la = self.latch
        if la is not None:
            mod = self.encoder.modulus
            la.counts_a = (la.counts_a + delta_counts) % mod
            la.index_latch = (la.index_latch + delta_counts) % mod

    def _trigger_a(self, t: float) -> None:
        s = self.feed.position_at(t)
        bid, x = self.boards.at(s, self.L_mm)
        if bid == 0:
            return
        length = self.boards.length_mm
        if x + self._fov_lo < _FIELD_MARGIN_MM or x + self._fov_hi > length - _FIELD_MARGIN_MM:
            return
        raw = self.encoder.raw(s)
        self.seq += 1
        self.latch = Latch(
            seq=self.seq,
            t_a=t,
            s_a=s,
            counts_a=self.encoder.wrap(raw),
            v_a=self.feed.speed_at(t),
            board_id=bid,
            x_centre_mm=x,
            index_latch=self.cut.index_latch(s - self.L_mm),
            t_b=t + self.dt_ab_s,
        )
        if self.pending_slip is not None:
            self.latch.slip_counts = self.pending_slip
            self.encoder.add_slip(self.pending_slip)
            self.pending_slip = None

    def _trigger_b(self, la: Latch, frames: list[Frame]) -> None:
        self.latch = None
        la.s_b = self.feed.position_at(la.t_b)
        la.counts_b = self.encoder.read(la.s_b)
        self.last_pair = la
        log = self.cut.logs.get(la.board_id)
        if log is None or log.n == 0:
            self.frames_dropped += 1
            return
        try:
            frame = self.assembler.assemble(
                la, self._near_passes(log, la.x_centre_mm), self.knots,
                board_length_mm=self.boards.length_mm,
            )
        except ValueError:
            self.frames_dropped += 1
            return
        frames.append(frame)

    def _near_passes(self, log: PassLog, x_centre_mm: float) -> Passes:
        """The passes of ``log`` the assembler keeps for a field centred at ``x_centre_mm``.

        The same selection as :meth:`plant_sim.rendering.camera.FrameAssembler.assemble` makes first
        (``Passes.slice(lo, hi, margin_mm=MARGIN_MM)``), taken from the log's arrays directly:
        the whole board's passes are not copied and checked for every pair.
        """
        a = self.assembler
        lo, hi = a.field_mm(x_centre_mm)
        n = log.n
        x = log.x[:n]
        sel = (x >= lo - a.MARGIN_MM) & (x <= hi + a.MARGIN_MM)
        return Passes(x[sel], log.bottom[:n][sel], log.knife[:n][sel], log.radius_mm)
