"""The profile figure (seed Figs. 5-6): pure figure building on the Agg canvas."""

from __future__ import annotations

import numpy as np

from vision.marks import find_marks
from vision.pipeline import Measurement
from vision.plot import profile_figure


def _measurement() -> Measurement:
    x = np.arange(500) * 0.08
    local = (x % 1.5) - 0.75
    h = local**2 / 120.0 * 1000.0
    p = local / 60.0
    m = find_marks(x, h, slope=p)
    return Measurement(
        x_mm=x, height_um=h - h.mean(), slope=p, pitch_mm=m.pitch_mm,
        mark_widths_mm=m.widths_mm, mark_depths_um=m.depths_um, cusps_mm=m.cusps_mm,
        bottoms_mm=m.bottoms_mm, uniformity_cv=m.uniformity_cv, depth_um=m.depth_um,
        shift_px=15.0, encoder_shift_px=14.0, confidence=0.9,
    )


def test_figure_shows_profile_cusps_and_widths(tmp_path):
    meas = _measurement()
    fig = profile_figure(meas, reference=(meas.x_mm, meas.height_um), title="test")
    ax = fig.axes[0]
    lines = ax.get_lines()
    profile = [ln for ln in lines if ln.get_label() == "measured profile"]
    assert len(profile) == 1
    np.testing.assert_allclose(profile[0].get_xdata(), meas.x_mm)
    cusps = [ln for ln in lines if ln.get_label() == "cusps"][0]
    np.testing.assert_allclose(cusps.get_xdata(), meas.cusps_mm)
    texts = [t.get_text() for t in ax.texts]
    assert len(texts) == len(meas.mark_widths_mm)
    assert "pitch 1.500 mm" in ax.get_title()
    out = tmp_path / "fig.png"
    fig.savefig(out, dpi=60)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_figure_needs_no_pyplot():
    # run in a fresh interpreter: other tests in this process may have imported pyplot
    import subprocess
    import sys

    code = (
        "import sys, tests.vision.test_vision_plot as t\n"
        "t.profile_figure(t._measurement())\n"
        "assert 'matplotlib.pyplot' not in sys.modules, 'pyplot was imported'\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=str(__import__("pathlib").Path(__file__).parents[2]), check=False)
    assert proc.returncode == 0, proc.stderr
