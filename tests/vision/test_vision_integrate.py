"""Frequency-domain integration of slope to height (non-periodic ends, absolute micrometres)."""

from __future__ import annotations

import numpy as np
import pytest

from vision.integrate import Integrator, integrate_slope

DX_MM = 0.08  # 12.5 px/mm


def _centre(h: np.ndarray) -> np.ndarray:
    return h - h.mean()


@pytest.mark.parametrize(
    "height_mm",
    [
        lambda x: 0.002 * x,  # a pure tilt: the worst case for a plain FFT (jump at the wrap)
        lambda x: 1e-4 * (x - 10.0) ** 2,  # a bow
        lambda x: 0.004 * np.sin(2 * np.pi * x / 3.7 + 0.4),  # non-integer number of periods
        lambda x: 0.003 * np.sin(x / 4.0) + 0.0005 * x,
    ],
)
def test_integrates_smooth_non_periodic_profiles(height_mm):
    n = 613
    x = np.arange(n) * DX_MM
    h = height_mm(x)
    p = np.gradient(h, DX_MM, edge_order=2)
    got = integrate_slope(p, dx_mm=DX_MM)
    expect = _centre(h) * 1000.0
    scale = np.ptp(expect)
    err = np.abs(got - expect)
    assert err.max() < 0.01 * scale  # no end artefacts
    assert np.sqrt(np.mean(err**2)) < 0.002 * scale


def test_heights_are_absolute_micrometres():
    # slope 0.001 over 10 mm rises 10 um
    n = 126
    p = np.full(n, 0.001)
    h = integrate_slope(p, dx_mm=DX_MM)
    assert h[-1] - h[0] == pytest.approx(0.001 * (n - 1) * DX_MM * 1000.0, rel=0.02)
    assert abs(h.mean()) < 1e-9


def test_cuttermark_arcs_round_trip():
    # a chain of arcs of radius 60 mm: slope sawtooth with jumps at the cusps; a camera pixel
    # measures the mean slope over its width (the height difference across it)
    radius, pitch = 60.0, 1.5

    def arcs(x):
        local = (x % pitch) - pitch / 2
        return local**2 / (2 * radius)

    x = np.arange(640) * DX_MM + 0.37
    h_mm = arcs(x)
    p = (arcs(x + DX_MM / 2) - arcs(x - DX_MM / 2)) / DX_MM
    got = integrate_slope(p, dx_mm=DX_MM)
    expect = _centre(h_mm) * 1000.0
    assert np.corrcoef(got, expect)[0, 1] > 0.999
    err = got - expect
    assert np.abs(err).max() < 0.06 * np.ptp(expect)  # a little ringing at the sharpest cusps
    assert np.sqrt(np.mean(err**2)) < 0.015 * np.ptp(expect)
    depth = pitch**2 / (8 * radius) * 1000.0
    assert np.ptp(got) == pytest.approx(depth, rel=0.1)  # cusps fall between samples


def test_integrator_set_up_once_serves_shorter_profiles():
    integ = Integrator(700, dx_mm=DX_MM)
    assert integ.nfft >= 700
    x = np.arange(500) * DX_MM
    p = 0.01 * np.cos(x)
    h = integ(p)
    expect = _centre(0.01 * np.sin(x)) * 1000.0
    assert np.abs(h - expect).max() < 0.01 * np.ptp(expect)
    with pytest.raises(ValueError, match="slope"):
        integ(np.zeros(701))
    with pytest.raises(ValueError, match="dx_mm"):
        Integrator(10, dx_mm=0.0)


def test_linear_in_the_slope():
    rng = np.random.default_rng(0)
    p1, p2 = rng.standard_normal(300), rng.standard_normal(300)
    integ = Integrator(300, dx_mm=DX_MM)
    np.testing.assert_allclose(integ(2 * p1 - p2), 2 * integ(p1) - integ(p2), atol=1e-9)
