"""The 2-D surface map: slope along the feed by seed Eq. 4 at every pixel, albedo, frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from config.rig import Camera, Lights
from vision.defects.surface_map import SurfaceMapper, surface_map

PPM = 12.5
SLANT = 82.0


def _camera(w: int = 400, h: int = 120) -> Camera:
    return Camera(fx=1400.0, fy=1400.0, cx=(w - 1) / 2, cy=(h - 1) / 2,
                  dist=(0.0, 0.0, 0.0, 0.0, 0.0), px_per_mm=PPM)


def _pair(shift_px: int, *, bump: bool = True, gain_b: float = 1.0):
    """A Lambert pair of a 2-D height field (marks + a dent) with albedo, B shifted."""
    h, w = 120, 400
    n = w + shift_px + 2
    x = np.arange(n) / PPM
    y = np.arange(h)[:, None] / PPM
    z = 0.004 * np.cos(2 * np.pi * x / 2.0)[None, :] * np.ones((h, 1))  # mm
    if bump:
        z = z - 0.03 * np.exp(-((x[None, :] - 12.0) ** 2 + (y - 4.8) ** 2) / (2 * 0.8 ** 2))
    p = np.gradient(z, 1 / PPM, axis=1)
    q = np.gradient(z, 1 / PPM, axis=0)
    rng = np.random.default_rng(0)
    rho = 1.0 + 0.1 * np.sin(2 * np.pi * x / 3.1)[None, :] + 0.05 * rng.standard_normal((h, n))
    s = math.radians(SLANT)
    la = rho * np.maximum(0, math.cos(s) - p * math.sin(s)) / np.sqrt(1 + p * p + q * q)
    lb = rho * np.maximum(0, math.cos(s) + p * math.sin(s)) / np.sqrt(1 + p * p + q * q)
    # A's column u sees the board at u + shift, B's at u: B shows A's point u at u + shift
    sl = slice(shift_px, shift_px + w)
    a = 600.0 * la[:, sl]
    b = 600.0 * gain_b * lb[:, :w]
    return a.astype(np.float32), b.astype(np.float32), p[:, sl], rho[:, sl]


def test_slope_along_feed_and_albedo_at_every_pixel():
    a, b, p, rho = _pair(17, gain_b=1.07)
    m = surface_map(a, b, camera=_camera(), lights=Lights(slant_deg=SLANT), shift_px=17.0)
    assert m.shape == a.shape
    ok = m.valid
    assert ok[:, : 400 - 18].all() and not ok[:, -1].any()  # B does not see the last columns
    est, true = m.slope_along_feed[ok], p[ok]
    assert np.corrcoef(est, true)[0, 1] > 0.99
    assert np.std(est - true) < 0.05 * np.std(true) + 1e-4  # the imbalance removed, no scale
    alb = m.albedo[ok] / np.mean(rho[ok])
    assert np.corrcoef(alb, rho[ok])[0, 1] > 0.98


def test_a_wrong_shift_breaks_the_slope():
    """Registration matters: one pixel off and the albedo leaks into the slope."""
    a, b, p, _ = _pair(17)
    good = surface_map(a, b, camera=_camera(), lights=Lights(slant_deg=SLANT), shift_px=17.0)
    bad = surface_map(a, b, camera=_camera(), lights=Lights(slant_deg=SLANT), shift_px=18.0)
    ok = good.valid & bad.valid
    err = [np.std(m.slope_along_feed[ok] - p[ok]) for m in (good, bad)]
    assert err[1] > 3 * err[0]


def test_heights_integrate_the_slope_per_row():
    a, b, _, _ = _pair(12, bump=True)
    m = surface_map(a, b, camera=_camera(), lights=Lights(slant_deg=SLANT), shift_px=12.0)
    h = m.heights_um()
    row = int(round(4.8 * PPM))
    far = 5
    # the 30 um dent at x = 12 mm shows in its row and not in a far one
    col = int(12 * PPM) - 12
    dip = h[row, col] - np.median(h[row, 50:350])
    assert dip < -20
    assert h[far, col] - np.median(h[far, 50:350]) > -5


def test_frames_roll_and_binned_rows():
    cam = _camera()
    mapper = SurfaceMapper(cam, Lights(slant_deg=SLANT), (120, 400), bin_rows=4)
    rows = np.full((30, 400), 400.0, np.float32)
    m = mapper(rows, rows, shift_px=0.0, roll_deg=0.0)
    assert m.shape == (30, 400)
    x, y = m.image_xy_mm(np.array([0.0, 399.0]), np.array([0.0, 29.0]))
    assert x == pytest.approx([0.0, 399.0 / PPM])
    assert y == pytest.approx([1.5 / PPM, (1.5 + 4 * 29) / PPM])
    assert np.allclose(m.slope_along_feed[m.valid], 0.0, atol=1e-6)
    rolled = mapper(rows, rows, shift_px=0.0, roll_deg=3.0)
    assert rolled.valid.mean() < m.valid.mean()  # the turned grid leaves the image at corners
    xr, yr = rolled.image_xy_mm(np.array([399.0]), np.array([15.0]))
    assert yr[0] > y.mean()  # the feed turns +x toward +v


@pytest.mark.parametrize("kwargs, word", [
    ({"bin_rows": 0}, "bin_rows"),
    ({"columns": (10, 5)}, "columns"),
])
def test_bad_set_up_is_refused(kwargs, word):
    with pytest.raises(ValueError, match=word):
        SurfaceMapper(_camera(), Lights(slant_deg=SLANT), (120, 400), **kwargs)


def test_bad_inputs_are_refused():
    mapper = SurfaceMapper(_camera(), Lights(slant_deg=SLANT), (120, 400))
    img = np.ones((120, 400), np.float32)
    with pytest.raises(ValueError, match="rows_a"):
        mapper(img[:10], img, shift_px=0.0)
    with pytest.raises(ValueError, match="shift_px"):
        mapper(img, img, shift_px=float("nan"))
    with pytest.raises(ValueError, match="opposite"):
        SurfaceMapper(_camera(), Lights(slant_deg=SLANT, azimuth_b_deg=0.0), (120, 400))


def test_a_coarse_map_is_the_fine_map_averaged_in_blocks():
    """Columns and rows averaged before the remap: the same slope on ~0.16 x 0.4 mm samples."""
    a, b, p, _ = _pair(17)
    mapper = SurfaceMapper(_camera(), Lights(slant_deg=SLANT), a.shape, bin_rows=1,
                           merge_rows=5, bin_cols=2)
    m = mapper(a, b, shift_px=17.0)
    assert m.shape == (120 // 5, 400 // 2)
    assert m.col_step_px == 2.0 and m.row_step_px == 5.0 and m.cols_per_mm == PPM / 2
    # the true slope averaged over the same blocks (centres at 2 j + 0.5, 5 i + 2)
    true = p.reshape(24, 5, 200, 2).mean(axis=(1, 3))
    ok = m.valid
    assert ok[:, : (400 - 18) // 2].all()
    assert np.corrcoef(m.slope_along_feed[ok], true[ok])[0, 1] > 0.98
    assert m.feed_mm(0) == pytest.approx((0.5 - 199.5) / PPM)
    x, y = m.image_xy_mm(10, 3)
    assert (x, y) == (pytest.approx(20.5 / PPM), pytest.approx(17.0 / PPM))
    with pytest.raises(ValueError, match="merge_rows"):
        SurfaceMapper(_camera(), Lights(slant_deg=SLANT), a.shape, merge_rows=100)


def test_the_middle_row_of_each_block_keeps_the_maps_geometry():
    """``middle_row``: one source row of each odd block, the map's samples where they were."""
    a, b, _, _ = _pair(17)
    lights = Lights(slant_deg=SLANT)
    full = SurfaceMapper(_camera(), lights, a.shape, merge_rows=5, bin_cols=2)
    thin = SurfaceMapper(_camera(), lights, a.shape, merge_rows=5, bin_cols=2, middle_row=True)
    # rows alike within each block of 5: averaging them or taking the middle one agree
    a5, b5 = (np.repeat(x[2::5], 5, axis=0) for x in (a, b))
    m_full, m_thin = full(a5, b5, shift_px=17.0), thin(a5, b5, shift_px=17.0)
    assert (m_thin.row0_px, m_thin.row_step_px) == (m_full.row0_px, m_full.row_step_px)
    assert np.array_equal(m_thin.valid, m_full.valid)
    np.testing.assert_allclose(m_thin.slope_along_feed, m_full.slope_along_feed, atol=1e-5)
    # on the real pair it reads only the middle rows: what a mapper of those rows alone gives
    m = thin(a, b, shift_px=17.0)
    ref = full(a5, b5, shift_px=17.0)
    np.testing.assert_allclose(m.slope_along_feed, ref.slope_along_feed, atol=1e-5)
    with pytest.raises(ValueError, match="middle_row"):
        SurfaceMapper(_camera(), lights, a.shape, merge_rows=4, middle_row=True)


def test_valid_rows_and_columns_are_the_maps_and_read_only():
    a, b, _, _ = _pair(17)
    m = SurfaceMapper(_camera(), Lights(slant_deg=SLANT), a.shape, bin_rows=1, merge_rows=5,
                      bin_cols=2)(a, b, shift_px=17.0)
    assert np.array_equal(m.valid_cols, np.flatnonzero(m.valid.any(axis=0)))
    assert np.array_equal(m.valid_rows, np.flatnonzero(m.valid.any(axis=1)))
    assert m.valid_cols.size < m.shape[1]  # B's shift leaves the last columns unseen
    assert m.valid_cols is m.valid_cols  # found once
    with pytest.raises(ValueError):
        m.valid_cols[0] = 5


def test_uint16_row_bins_give_the_same_map_as_float_ones():
    """The fast coarse paths of ``uint16`` bins (pairs of columns, wider blocks of the middle
    bin): the map of the same sums given as float64 (OpenCV's area resize) is the same."""
    a, b, _, _ = _pair(17)
    bins_a = a.reshape(40, 3, -1).sum(axis=1).astype(np.uint16)
    bins_b = b.reshape(40, 3, -1).sum(axis=1).astype(np.uint16)
    for merge, cols, middle in ((1, 2, False), (3, 6, True), (1, 4, False)):
        mapper = SurfaceMapper(_camera(), Lights(slant_deg=SLANT), a.shape, bin_rows=3,
                               merge_rows=merge, bin_cols=cols, middle_row=middle)
        fast = mapper(bins_a, bins_b, shift_px=17.0)
        ref = mapper(bins_a.astype(np.float64), bins_b.astype(np.float64), shift_px=17.0)
        assert np.array_equal(fast.valid, ref.valid)
        # the fast paths round the block means to integers (as OpenCV does for uint16: half a
        # DN of ~250, a slope error below 1e-3 against marks of +-0.013)
        np.testing.assert_allclose(fast.slope_along_feed, ref.slope_along_feed, atol=1e-3)
        assert np.abs(fast.slope_along_feed - ref.slope_along_feed).max() > 0


def test_a_map_without_the_albedo_has_the_same_slope():
    """``albedo=False`` (what the DefectFinder asks): no albedo, the slope and samples as ever."""
    a, b, _, _ = _pair(17, gain_b=1.07)
    mapper = SurfaceMapper(_camera(), Lights(slant_deg=SLANT), a.shape, bin_rows=1,
                           merge_rows=5, bin_cols=2)
    full = mapper(a, b, shift_px=17.0)
    bare = mapper(a, b, shift_px=17.0, albedo=False)
    assert bare.albedo is None and full.albedo is not None
    assert np.array_equal(bare.valid, full.valid)
    assert np.array_equal(bare.slope_along_feed, full.slope_along_feed)


def test_coarse_sources_made_once_give_the_same_map():
    """Where several maps of one pair are made (a pitch off, a refused pair's shifts), the
    coarse sources are made once (``coarse_source``) and handed in: the same map."""
    cam = Camera(fx=1400.0, fy=1400.0, cx=329.0, cy=120.0, dist=(-0.12, 0.0, 0.0, 0.0, 0.0),
                 px_per_mm=12.5)
    rng = np.random.default_rng(5)
    rows_a = (1000 + 200 * rng.random((48, 659))).astype(np.uint16)
    rows_b = (1000 + 200 * rng.random((48, 659))).astype(np.uint16)
    mapper = SurfaceMapper(cam, Lights(slant_deg=SLANT), (240, 659), bin_rows=5, bin_cols=2)
    coarse = (mapper.coarse_source(rows_a), mapper.coarse_source(rows_b))
    assert coarse[0].dtype == np.float32 and coarse[0].flags.c_contiguous
    for shift in (14.6, -3.2):
        want = mapper(rows_a, rows_b, shift_px=shift, roll_deg=0.4, albedo=False)
        got = mapper(rows_a, rows_b, shift_px=shift, roll_deg=0.4, albedo=False, coarse=coarse)
        assert np.array_equal(got.slope_along_feed, want.slope_along_feed)
        assert np.array_equal(got.valid, want.valid)
    # either one left None: made from its rows
    half = mapper(rows_a, rows_b, shift_px=14.6, roll_deg=0.4, albedo=False,
                  coarse=(None, coarse[1]))
    assert np.array_equal(half.slope_along_feed, mapper(rows_a, rows_b, shift_px=14.6,
                                                        roll_deg=0.4).slope_along_feed)
    with pytest.raises(ValueError, match=r"coarse\[0\]"):
        mapper(rows_a, rows_b, shift_px=14.6, coarse=(coarse[0].astype(np.float64), None))
    with pytest.raises(ValueError, match=r"coarse\[1\]"):
        mapper(rows_a, rows_b, shift_px=14.6, coarse=(None, coarse[1][:-1]))
    with pytest.raises(ValueError, match="rows"):
        mapper.coarse_source(rows_a[:-1])
