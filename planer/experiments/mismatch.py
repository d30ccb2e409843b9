"""The seed's mismatch experiment (its Figs. 8-9), with and without image-based refinement.

Profile correlation (seed Eq. 8) against the profile of the correctly registered pair when the
encoder's shift is wrong by 0, 4, 8, 12, 15 and 20 px, on several simulated boards. Run::

    python -m planer.experiments.mismatch --out docs

to regenerate ``docs/vision_mismatch.json`` and ``docs/vision_mismatch.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ERRORS_PX = (0, 4, 8, 12, 15, 20)
SEED_PAPER = {8: 0.87, 15: 0.56}
BOARDS = (
    {"species": "beech", "pitch_mm": 2.0, "knives": 4},
    {"species": "oak", "pitch_mm": 2.0, "knives": 1},
    {"species": "spruce", "pitch_mm": 1.5, "knives": 3},
    {"species": "ramin", "pitch_mm": 2.5, "knives": 2},
    {"species": "meranti", "pitch_mm": 2.5, "knives": 6},
    {"species": "pine", "pitch_mm": 1.5, "knives": 4},
)


def run_experiment(
    boards: Sequence[dict] = BOARDS, errors_px: Sequence[float] = ERRORS_PX, *, seed: int = 300
) -> dict[str, dict[str, list[float]]]:
    """Correlations per encoder error: ``{"encoder_only": ..., "refined": ...}``.

    Returns
    -------
    dict
        ``result[mode][str(error_px)]`` is the list of correlations (one per board) of the
        profile measured with that encoder error against the correctly registered profile.
    """
    from plant_sim.rendering.scenarios import board_pair
    from vision.marks import corr2
    from vision.pipeline import Measurer

    out: dict[str, dict[str, list[float]]] = {"encoder_only": {}, "refined": {}}
    for i, kw in enumerate(boards):
        ref_x = ref_h = None
        for err in errors_px:
            rig, pair = board_pair(seed=seed + i, encoder_error_px=float(err), **kw)
            for mode, register in (("encoder_only", False), ("refined", True)):
                m = Measurer(rig, pair.image_a.shape, register=register).measure(
                    pair.image_a,
                    pair.image_b,
                    counts_a=pair.counts_a,
                    counts_b=pair.counts_b,
                    speed_mm_s=pair.speed_mm_s,
                )
                if ref_x is None:  # error 0, encoder only: the correctly registered profile
                    ref_x, ref_h = m.x_mm, m.height_um
                sel = (m.x_mm >= ref_x[0]) & (m.x_mm <= ref_x[-1])
                r = corr2(m.height_um[sel], np.interp(m.x_mm[sel], ref_x, ref_h))
                out[mode].setdefault(str(err), []).append(float(r))
    return out


def plot(result: dict[str, dict[str, list[float]]], path: Path) -> None:
    """Draw mean (and worst) correlation against the registration error, beside the seed's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.8), dpi=110)
    for mode, colour, label in (
        ("encoder_only", "tab:red", "encoder shift only (seed's method)"),
        ("refined", "tab:blue", "with image-based refinement"),
    ):
        errs = sorted(result[mode], key=float)
        x = [float(e) for e in errs]
        ax.plot(x, [np.mean(result[mode][e]) for e in errs], "o-", color=colour, label=label)
        ax.plot(x, [np.min(result[mode][e]) for e in errs], "--", color=colour, lw=0.8,
                label=f"{label.split(' (')[0]}: worst board")
    seed_label = "seed paper (8 px: 87 %, 15 px: 56 %)"
    ax.plot(list(SEED_PAPER), list(SEED_PAPER.values()), "ks", label=seed_label)
    ax.set_xlabel("registration error of the encoder shift (px)")
    ax.set_ylabel("profile correlation with the matched profile")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the experiment and write its JSON and PNG into ``--out``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    n = f"{len(BOARDS)} boards x {len(ERRORS_PX)} errors"
    print(f"mismatch experiment: {n} ...", file=sys.stderr)
    result = run_experiment()
    (args.out / "vision_mismatch.json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, args.out / "vision_mismatch.png")
    for mode, rows in result.items():
        cells = "  ".join(f"{e:>3} px {np.mean(v):.3f}" for e, v in rows.items())
        print(f"{mode:>12}: {cells}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
