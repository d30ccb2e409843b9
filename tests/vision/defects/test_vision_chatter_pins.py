"""Chatter's fit restructured (set-up hoisted into caches) against its earlier form: old == new."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from vision.defects import detect


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


@pytest.mark.parametrize("knives", [1, 2, 4, 6])
def test_chatter_fit_is_the_inline_fit_bit_for_bit(knives):
    rng = np.random.default_rng(knives)
    for _ in range(40):
        m = int(rng.integers(3 * knives + 2, 90))
        d = rng.standard_normal(m) * rng.uniform(0.1, 5.0)
        if rng.random() < 0.5:  # a chatter wave on top: the fit finds it
            period = rng.uniform(2.3, 15.0)
            d += rng.uniform(0.5, 4.0) * np.sin(2 * np.pi * np.arange(m) / period)
        assert detect._chatter_fit(d, knives) == _old_fit(d, knives)


@pytest.mark.parametrize("n, col0, step, cx, ppm", [(330, 0.5, 2.0, 329.0, 12.5),
                                                    (320, 3.5, 6.0, 959.5, 36.4),
                                                    (17, -2.25, 1.0, 8.0, 7.0)])
def test_feed_positions_are_the_maps_x_mm(n, col0, step, cx, ppm):
    from vision.defects.surface_map import SurfaceMap

    smap = SurfaceMap(slope_along_feed=np.zeros((2, n), np.float32), albedo=None,
                      valid=np.ones((2, n), bool), col0_px=col0, row0_px=0.0, row_step_px=1.0,
                      roll_deg=0.0, cx=cx, cy=0.0, px_per_mm=ppm, col_step_px=step)
    want = smap.feed_mm(np.arange(n)) + smap.cx / smap.px_per_mm
    got = detect._feed_positions(n, col0, step, cx, ppm)
    assert np.array_equal(got, want) and not got.flags.writeable
