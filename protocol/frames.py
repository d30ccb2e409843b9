"""Frames handed from the camera to the service: one encoder-registered image pair.

:class:`Frame` is the pair; :class:`protocol.frame_queue.InProcessSource` hands frames over inside
one process. The
hand-off between processes, a spool folder of atomically written pairs, is
:mod:`protocol.spool` (writer and reader) over :mod:`protocol.spool_files` (the files' names,
metadata, checks and decoding); see ``docs/frames.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One image pair as the camera hands it over.

    Attributes
    ----------
    seq : int
        Sequence number of the pair (matches the PLC's ``trigger_seq``, modulo 2**16).
    t_s : float
        Machine time at trigger A, seconds.
    image_a, image_b : ndarray, shape (H, W)
        Grayscale images lit by light A (azimuth 0 deg) and light B, B taken after A.
    counts_a, counts_b : int
        Feed encoder counts latched at the two triggers (wrapped counter values).
    speed_mm_s : float
        Feed speed at capture, mm/s (for motion deblurring).
    index_latch_counts : int
        Encoder counts at the spindle index pulse belonging to the imaged board patch
        (see ``docs/architecture.md``, mark-to-knife phase).
    board_id : int
        Board under the camera (0 when none).
    board_position_mm : float
        Position of image A's centre from the board's leading end, mm.
    truth : dict or None
        Simulator only: the true ``pitch_mm``, ``uniformity_cv``, ``mark_widths_mm``,
        ``depth_um``, ``shift_px`` of the imaged patch, and ``defects`` (when the board
        carries wood defects in view): a list of dicts with the keys a defect detector reports,
        ``kind`` (``torn_grain``, ``raised_grain``, ``fuzzy_grain``, ``chip_mark``,
        ``knife_nick``, ``chatter``, ``snipe``), ``x_mm``, ``y_mm`` (centre in image A's
        undistorted frame from its top-left corner, x along the feed), ``length_mm`` (along
        the feed), ``width_mm``, ``depth_um`` (depth of a pit, height of a ridge, rms of
        fuzz, amplitude of chatter; positive), plus ``angle_deg``, ``period_mm``, ``knife``,
        ``notch_um``, ``board_x_mm``, ``board_y_mm`` where they apply
        (:mod:`plant_sim.rendering.defects`). ``None`` on a real machine.
    error : str or None
        Why the pair cannot be measured although its metadata arrived (an image file that is
        missing or unreadable); the images are then ``None``. The service logs such a pair as a
        failed measurement instead of losing it.
    """

    seq: int
    t_s: float
    image_a: np.ndarray
    image_b: np.ndarray
    counts_a: int
    counts_b: int
    speed_mm_s: float
    index_latch_counts: int = 0
    board_id: int = 0
    board_position_mm: float = 0.0
    truth: dict[str, Any] | None = field(default=None)
    error: str | None = None
