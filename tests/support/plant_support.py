"""Helpers shared by the tests that drive the service against the in-process plant."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np


def record_frames(plant, frames: dict | None = None) -> dict:
    """Make ``plant.machine.advance`` file every frame under ``(counts_a, counts_b)``.

    Fills ``frames`` (a new dictionary when None) and returns it, for fake measurers that look
    the true marks up.
    """
    frames = {} if frames is None else frames
    advance = plant.machine.advance

    def recording_advance(dt_s):
        out = advance(dt_s)
        for f in out:
            frames[(f.counts_a, f.counts_b)] = f
        return out

    plant.machine.advance = recording_advance
    return frames


async def run_for(plant, seconds):
    """Step the plant and its service for ``seconds`` of simulated time; all frame results."""
    results = []
    end = plant.clock() + seconds
    while plant.clock() < end - 1e-9:
        results += await plant.step()
    return results


def truth_measurer(frames: dict):
    """A measurer that reports each pair's true marks (looked up in ``frames``, see
    :func:`record_frames`): the service's control without the vision's cost or noise."""

    class Truth:
        def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None):
            tr = frames[(counts_a, counts_b)].truth
            return SimpleNamespace(
                pitch_mm=float(tr["pitch_mm"]),
                mark_widths_mm=np.asarray(tr["mark_widths_mm"], float),
                bottoms_mm=np.asarray(tr["bottoms_mm"], float),
                uniformity_cv=float(tr["uniformity_cv"]), depth_um=float(tr["depth_um"]),
                shift_px=float(tr["shift_px"]), confidence=1.0)

    return Truth()
