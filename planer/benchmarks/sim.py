"""``planer bench`` part ``sim``: real-time factor of the machine model (simulated s per wall s).

Two runs of the shipped ``config/sim.toml`` with the service's traffic played in-process (a
PIEZO_COMMAND, the offset table and a heartbeat every 10 ms, as the controller sends them):
the model alone (``render_images=False``: frames carry counts and truth, no images) and with
image rendering at the configured 10 pairs/s. Timing starts once a board is under the camera,
so every pair is assembled (and rendered); set-up (the renderer's maps) is reported apart.
Targets (issue 3): >= 20 without images, >= 1 with.
"""

from __future__ import annotations

import time
from typing import Any

TARGET_MODEL = 20.0
TARGET_IMAGES = 1.0


def _measure(render: bool, sim_s: float) -> dict[str, Any]:
    from config.sim import load_sim
    from plant_sim.machine import Machine

    cfg = load_sim()
    t0 = time.perf_counter()
    m = Machine(cfg, seed=1, render_images=render)
    setup_s = time.perf_counter() - t0
    offsets = [float(v) for v in m.standout_um()]
    step = 0.01

    def play(duration_s: float) -> int:
        frames = 0
        for i in range(int(round(duration_s / step))):
            m.piezo_command(enable=True, alive_counter=i % 256)
            m.set_piezo_offsets(offsets)
            m.set_service_heartbeat(i % 65536)
            m.register_values()
            frames += len(m.advance(step))
        return frames

    play(0.6)  # the first board reaches the camera
    t0 = time.perf_counter()
    pairs = play(sim_s)
    wall = time.perf_counter() - t0
    return {
        "sim_s": sim_s,
        "wall_s": round(wall, 4),
        "real_time_factor": round(sim_s / wall, 2),
        "pairs": pairs,
        "setup_s": round(setup_s, 3),
    }


def run(quick: bool) -> dict[str, Any]:
    """Measure the real-time factors.

    Parameters
    ----------
    quick : bool
        Shorter runs (2 s and 1 s simulated instead of 10 s and 4 s).

    Returns
    -------
    dict
        ``model_only`` and ``with_images`` (each ``sim_s``, ``wall_s``, ``real_time_factor``,
        ``pairs``, ``setup_s``), ``pairs_per_s`` of the camera and the ``targets``.
    """
    from config.sim import load_sim

    model = _measure(False, 2.0 if quick else 10.0)
    images = _measure(True, 1.0 if quick else 4.0)
    return {
        "model_only": model,
        "with_images": images,
        "pairs_per_s": load_sim().camera.pairs_per_s,
        "targets": {"model_only": TARGET_MODEL, "with_images": TARGET_IMAGES},
        "meets_targets": bool(
            model["real_time_factor"] >= TARGET_MODEL
            and images["real_time_factor"] >= TARGET_IMAGES
        ),
    }
