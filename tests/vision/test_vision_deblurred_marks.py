"""The self-calibrated (deblurred) profile keeps the narrow marks the blurred one merged."""

from __future__ import annotations

import numpy as np

from plant_sim.rendering.scenarios import board_pair
from vision.pipeline import Measurer


def test_narrow_marks_beside_a_vanished_knife_survive_the_calibration():
    """0.5 mm pitch, 4 knives, knife 2 vanished, knife 0's marks 0.39 mm (5 px at 12.5 px/mm),
    0.05 mm of scattering: the blurred profile shows 64 of the 75 marks (knife 0's merged into
    its neighbours), the deblurred one all of them, and the measurement takes those."""
    rig, pair = board_pair(seed=4, pitch_mm=0.5, knives=4, runout_um=(0.0, 0.5, -2.0, 0.4),
                           scattering_mm=0.05)
    m = Measurer(rig, pair.image_a.shape, radius_mm=60.0, knives=4)
    result = m.measure(pair.image_a, pair.image_b, counts_a=pair.counts_a,
                       counts_b=pair.counts_b, speed_mm_s=pair.speed_mm_s)
    cusps = np.asarray(result.cusps_mm)
    truth = pair.truth.metrics(cusps[0], cusps[-1])
    true_widths = np.asarray(truth["mark_widths_mm"])
    seen = int(np.count_nonzero(true_widths >= 0.15))  # the vanished knife's slivers merge
    assert seen == 75
    assert abs(len(result.mark_widths_mm) - seen) <= 1
    # every cusp of a mark of at least 0.15 mm found within a sample (0.08 mm)
    true_cusps = np.asarray(truth["cusps_mm"])
    bounding = [i for i in range(true_cusps.size)
                if (i > 0 and true_widths[i - 1] >= 0.15)
                or (i < true_widths.size and true_widths[i] >= 0.15)]
    off = [abs(float(np.min(np.abs(cusps - true_cusps[i])))) for i in bounding]
    assert np.percentile(off, 95) < 0.08
