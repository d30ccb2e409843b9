"""The seed's mismatch experiment: refinement removes the encoder's registration error."""

from __future__ import annotations

import numpy as np

from planer.experiments.mismatch import run_experiment


def test_refinement_restores_the_profile_that_encoder_errors_destroy():
    res = run_experiment(boards=({"species": "beech", "pitch_mm": 2.0, "knives": 4},),
                         errors_px=(0, 8, 15))
    enc, ref = res["encoder_only"], res["refined"]
    assert enc["0"][0] > 0.999  # the reference against itself
    # the seed's observation: a mismatch of a fraction of a mark degrades the profile
    assert enc["8"][0] < 0.9 and enc["15"][0] < 0.9
    # with the image-based refinement every error is registered away
    assert min(min(v) for v in ref.values()) > 0.99
    assert np.mean(ref["8"]) > np.mean(enc["8"]) + 0.1
