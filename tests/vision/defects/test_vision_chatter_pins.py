"""Chatter restructured against its earlier forms.

The fit's set-up hoisted into caches (bit for bit), then the whole detector -- the profile's
heights at the marks' lowest points, their differences and the fit -- one compiled call
(:func:`vision.defects.kernels.chatter_fit`): the differences bit for bit, the fit's sums in
order where numpy's matrix products sum in BLAS's order (the same numbers to 1e-12 relative,
the same period and the same decisions).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from vision.defects import detect, kernels
from vision.defects.detect import DefectKind, DefectSettings, Residual, residual
from vision.defects.surface_map import SurfaceMap


@functools.lru_cache(maxsize=32)
def _old_basis(m: int, knives: int) -> tuple[np.ndarray, ...] | None:
    j = np.arange(m)
    knife = j % knives
    onehot = (knife[None, :] == np.arange(knives)[:, None]).astype(np.float64)
    per_knife = onehot / onehot.sum(axis=1, keepdims=True)
    trend = (j - 0.5 * (m - 1)) / m
    trend = trend - (per_knife @ trend)[knife]
    tt = float(trend @ trend)
    f = 1.0 / np.linspace(2.2, 16.0, 139)
    near = np.min(np.abs(f[:, None] - np.arange(knives + 1)[None, :] / knives), axis=1)
    f = f[(near >= 0.6 / m) & (f >= 2.5 / m)]
    if f.size == 0:
        return None
    ph = 2 * np.pi * f[:, None] * (j[None, :] + 0.5)
    sn, cs = np.sin(ph), np.cos(ph)
    for b in (sn, cs):
        b -= (b @ per_knife.T)[:, knife]
        b -= np.outer(b @ trend, trend) / tt
    return (knife, per_knife, trend, f, sn, cs, (sn * sn).sum(1), (sn * cs).sum(1),
            (cs * cs).sum(1))


def _old_fit(d: np.ndarray, knives: int) -> tuple[float, float, float, float] | None:
    """The fit as :func:`vision.defects.detect.chatter` computed it inline before."""
    m = d.size
    basis = _old_basis(m, knives)
    if basis is None:
        return None
    knife, per_knife, trend, f, sn, cs, gss, gsc, gcc = basis
    e = d - (per_knife @ d)[knife]
    e = e - trend * float(trend @ e) / float(trend @ trend)
    bs, bc = sn @ e, cs @ e
    det = np.maximum(gss * gcc - gsc * gsc, 1e-18)
    a_s, a_c = (gcc * bs - gsc * bc) / det, (gss * bc - gsc * bs) / det
    fitted = a_s * bs + a_c * bc
    ee = max(float(e @ e), 1e-18)
    k = int(np.argmax(fitted))
    explained = float(fitted[k]) / ee
    amp_d = float(np.hypot(a_s[k], a_c[k]))
    noise = math.sqrt(max(ee - float(fitted[k]), 0.0) / m) * math.sqrt(2.0 / m)
    amp = amp_d / (2.0 * math.sin(math.pi * float(f[k])))
    return explained, amp_d, noise, amp


def _old_chatter(res: Residual, bottoms_mm: np.ndarray | None, knives: int | None,
                 settings: DefectSettings) -> list[detect.Defect]:
    """:func:`vision.defects.detect.chatter` as numpy calls (before its compiled fit)."""
    if bottoms_mm is None or knives is None or len(bottoms_mm) < 3 * knives + 3:
        return []
    smap = res.smap
    prof = res.profile
    h = np.cumsum(prof) * 1000.0 / smap.cols_per_mm
    xs = smap.feed_mm(np.arange(prof.size)) + smap.cx / smap.px_per_mm
    d = np.diff(np.interp(np.asarray(bottoms_mm, dtype=np.float64), xs, h))
    fit = _old_fit(d, knives)
    if fit is None:
        return []
    explained, amp_d, noise, amp = fit
    if amp < settings.chatter_um or explained < 0.5 or amp_d < 4.5 * noise:
        return []
    cols = smap.valid_cols
    rows = smap.valid_rows
    conf = min(1.0, explained) * min(1.0, amp / (2 * settings.chatter_um))
    return [detect._defect(res, DefectKind.CHATTER, (int(cols[0]), int(cols[-1]) + 1),
                           (int(rows[0]), int(rows[-1]) + 1), amp, conf)]


def _wavy_case(rng: np.random.Generator) -> tuple[Residual, np.ndarray, int]:
    """A residual whose marks' lowest points carry runout, maybe chatter, and noise."""
    knives = int(rng.choice([1, 2, 3, 4, 6]))
    ppm, pitch = float(rng.uniform(6.0, 14.0)), float(rng.uniform(1.0, 2.5))
    cols, rows = int(rng.integers(200, 480)), int(rng.integers(16, 40))
    x = np.arange(cols) / ppm
    j = np.floor(x / pitch)
    h_um = rng.uniform(-2.0, 2.0, knives)[(j % knives).astype(int)]
    if rng.random() < 0.6:  # chatter: off the revolution's period, or on it
        h_um = h_um + rng.uniform(0.2, 3.0) * np.sin(2 * np.pi * (x / pitch)
                                                    / rng.uniform(2.3, 12.0))
    marks = ((x % pitch) - pitch / 2) / 60.0
    slope = marks + np.gradient(h_um / 1000, 1 / ppm)
    p = (slope[None, :] + rng.uniform(0.0005, 0.004) * rng.standard_normal((rows, cols)))
    smap = SurfaceMap(p.astype(np.float32), None, np.ones(p.shape, bool),
                      col0_px=float(rng.uniform(-3, 3)), row0_px=2.0, row_step_px=5.0,
                      roll_deg=0.0, cx=cols / 2, cy=50.0, px_per_mm=ppm,
                      shadow_slope=1 / math.tan(math.radians(82)),
                      col_step_px=float(rng.choice([1.0, 2.0])))
    span = x[-1] * smap.col_step_px
    bottoms = (np.arange(1, int(span / pitch)) + rng.uniform(0.3, 0.7)) * pitch
    return residual(smap, DefectSettings()), bottoms, knives


def _fit(d, knives):
    """The fit :func:`chatter` runs on the marks' differences ``d`` (over the cached basis)."""
    basis = detect._chatter_basis(d.size, knives)
    if basis is None:
        return None
    return kernels.sinusoid_fit(np.ascontiguousarray(d, dtype=np.float64), knives, *basis)


@pytest.mark.parametrize("knives", [1, 2, 4, 6])
def test_chatter_fit_is_the_inline_fit(knives):
    rng = np.random.default_rng(knives)
    for _ in range(40):
        m = int(rng.integers(3 * knives + 2, 90))
        d = rng.standard_normal(m) * rng.uniform(0.1, 5.0)
        if rng.random() < 0.5:  # a chatter wave on top: the fit finds it
            period = rng.uniform(2.3, 15.0)
            d += rng.uniform(0.5, 4.0) * np.sin(2 * np.pi * np.arange(m) / period)
        got, want = _fit(d, knives), _old_fit(d, knives)
        # its sums in order, numpy's in BLAS's: the same best period, numbers to 1e-12
        assert got == pytest.approx(want, rel=1e-12, abs=0.0)


def test_the_mark_differences_are_numpys_bit_for_bit():
    rng = np.random.default_rng(7)
    for _ in range(60):
        n = int(rng.integers(2, 400))
        prof = rng.standard_normal(n) * 0.01
        cpm = float(rng.uniform(3.0, 15.0))
        xs = np.sort(rng.uniform(-5.0, 60.0, n))
        b = np.sort(rng.uniform(-10.0, 70.0, int(rng.integers(2, 50))))  # some outside
        b[::5] = xs[rng.integers(0, n, b[::5].size)]  # some exactly on a column
        want = np.diff(np.interp(b, xs, np.cumsum(prof) * 1000.0 / cpm))
        got = np.empty(b.size - 1)
        kernels._mark_differences(prof, cpm, xs, b, got)
        assert np.array_equal(got, want, equal_nan=True)


def test_chatter_is_its_numpy_form():
    """The same defects (place, size bit for bit; depth and confidence to 1e-12)."""
    rng = np.random.default_rng(2024)
    settings = DefectSettings()
    found = 0
    for _ in range(80):
        res, bottoms, knives = _wavy_case(rng)
        got = detect.chatter(res, bottoms, knives, settings)
        want = _old_chatter(res, bottoms, knives, settings)
        assert len(got) == len(want)
        for g, w in zip(got, want, strict=True):
            assert (g.kind, g.x_mm, g.y_mm, g.length_mm, g.width_mm) == (
                w.kind, w.x_mm, w.y_mm, w.length_mm, w.width_mm)
            assert g.depth_um == pytest.approx(w.depth_um, rel=1e-12, abs=0.0)
            assert g.confidence == pytest.approx(w.confidence, rel=1e-12, abs=0.0)
        found += len(got)
    assert 15 <= found <= 65  # both decisions met often


@pytest.mark.parametrize("n, col0, step, cx, ppm", [(330, 0.5, 2.0, 329.0, 12.5),
                                                    (320, 3.5, 6.0, 959.5, 36.4),
                                                    (17, -2.25, 1.0, 8.0, 7.0)])
def test_feed_positions_are_the_maps_x_mm(n, col0, step, cx, ppm):
    smap = SurfaceMap(slope_along_feed=np.zeros((2, n), np.float32), albedo=None,
                      valid=np.ones((2, n), bool), col0_px=col0, row0_px=0.0, row_step_px=1.0,
                      roll_deg=0.0, cx=cx, cy=0.0, px_per_mm=ppm, col_step_px=step)
    want = smap.feed_mm(np.arange(n)) + smap.cx / smap.px_per_mm
    got = detect._feed_positions(n, col0, step, cx, ppm)
    assert np.array_equal(got, want) and not got.flags.writeable
