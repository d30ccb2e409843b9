"""Helpers shared by the tests that drive the service against the in-process plant."""

from __future__ import annotations


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
