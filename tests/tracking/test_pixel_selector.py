"""DSO pixel selection: the vectorised cells equal DSO's nested loops; count, spread and gradients on a texture."""

import cv2
import numpy as np
import pytest

from mgso.tracking import pixel_selector as ps
from mgso_kernels.reference import image as ref_img


def textured(h, w, seed=0, sigma=1.5):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
    return (255.0 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)


def levels_of(img):
    return [dI for _, dI, _ in ref_img.build_pyramid(img, 3)]


def loop_select(dxy0, g, ths, pot, dir2, dir3, dir4, th_factor=1.0, dw1=0.75):
    """DSO PixelSelector::select written as its nested loops (with the direction index per cell given)."""
    h, w = g[0].shape
    out = np.zeros((h, w), np.int8)
    h32, w32 = ths.shape
    for y4 in range(0, h, 4 * pot):
        for x4 in range(0, w, 4 * pot):
            best4, val4 = -1, 0.0
            d4 = ps.DIRECTIONS[dir4[y4 // (4 * pot), x4 // (4 * pot)]]
            for y3 in range(0, min(4 * pot, h - y4), 2 * pot):
                for x3 in range(0, min(4 * pot, w - x4), 2 * pot):
                    x34, y34 = x3 + x4, y3 + y4
                    best3, val3 = -1, 0.0
                    d3 = ps.DIRECTIONS[dir3[y34 // (2 * pot), x34 // (2 * pot)]]
                    for y2 in range(0, min(2 * pot, h - y34), pot):
                        for x2 in range(0, min(2 * pot, w - x34), pot):
                            x234, y234 = x2 + x34, y2 + y34
                            best2, val2 = -1, 0.0
                            d2 = ps.DIRECTIONS[dir2[y234 // pot, x234 // pot]]
                            for y1 in range(min(pot, h - y234)):
                                for x1 in range(min(pot, w - x234)):
                                    xf, yf = x1 + x234, y1 + y234
                                    if xf < 4 or xf >= w - 5 or yf < 4 or yf >= h - 4:
                                        continue
                                    t0 = ths[min(yf >> 5, h32 - 1), min(xf >> 5, w32 - 1)]
                                    t1 = t0 * dw1
                                    t2 = t1 * dw1 * dw1
                                    gd = dxy0[yf, xf]
                                    if g[0][yf, xf] > t0 * th_factor:
                                        dn = abs(gd @ d2)
                                        if dn > val2:
                                            val2, best2, best3, best4 = dn, (yf, xf), -2, -2
                                    if best3 == -2:
                                        continue
                                    if g[1][yf >> 1, xf >> 1] > t1 * th_factor:
                                        dn = abs(gd @ d3)
                                        if dn > val3:
                                            val3, best3, best4 = dn, (yf, xf), -2
                                    if best4 == -2:
                                        continue
                                    if g[2][yf >> 2, xf >> 2] > t2 * th_factor:
                                        dn = abs(gd @ d4)
                                        if dn > val4:
                                            val4, best4 = dn, (yf, xf)
                            if best2 != -1:
                                out[best2] = 1
                                val3 = 1e10
                    if best3 not in (-1, -2):
                        out[best3] = 2
                        val4 = 1e10
            if best4 not in (-1, -2):
                out[best4] = 4
    return out


@pytest.mark.parametrize("pot, th_factor", [(1, 1.0), (2, 1.0), (3, 1.0), (3, 3.0), (5, 8.0)])
def test_vectorised_cells_equal_dso_loops(pot, th_factor):
    img = textured(72, 100, seed=pot, sigma=2.0)
    img[30:50, 40:70] = 128.0  # a flat patch: level-1/2 choices and empty cells
    lv = levels_of(img)
    g = [d[..., 1] ** 2 + d[..., 2] ** 2 for d in lv]
    ths = ps.block_thresholds(g[0])
    rng = np.random.default_rng(pot)
    dirs = [rng.integers(0, 16, (-(-72 // c), -(-100 // c))) for c in (pot, 2 * pot, 4 * pot)]
    got = ps.select_map(lv[0][..., 1:3], g, ths, pot, *dirs, th_factor=th_factor)
    want = loop_select(lv[0][..., 1:3], g, ths, pot, *dirs, th_factor=th_factor)
    assert np.array_equal(got, want)
    assert np.count_nonzero(got) > 10
    if th_factor > 2:
        assert len(set(np.unique(got).tolist()) & {2, 4}) >= 1  # coarser levels fill cells without level-0 pixels


def test_block_thresholds_are_median_plus_seven_smoothed():
    # constant gradient magnitude 10 everywhere inside: median bin 10, +7, squared
    img = np.tile(np.arange(96, dtype=np.float32) * 10.0, (64, 1))
    dI, g2 = ref_img.gradients(img)
    ths = ps.block_thresholds(g2)
    assert ths.shape == (2, 3)
    np.testing.assert_allclose(ths, 17.0 ** 2)
    with pytest.raises(ValueError, match="smaller than one 32x32"):
        ps.block_thresholds(np.zeros((20, 100)))


@pytest.mark.parametrize("density", [1500, 2000])
def test_selection_hits_the_density_and_is_spread_on_high_gradients(density):
    img = textured(480, 640, seed=3)
    lv = levels_of(img)
    sel = ps.PixelSelector(640, 480, seed=1)
    out = sel.select(lv, density)
    n = len(out)
    assert 0.75 * density <= n <= 1.1 * density, (n, out.potential, out.num_candidates)
    x, y = out.xy[:, 0], out.xy[:, 1]
    assert x.min() >= 4 and x.max() < 640 - 5 and y.min() >= 4 and y.max() < 480 - 4
    quads = np.bincount((x >= 320).astype(int) + 2 * (y >= 240).astype(int), minlength=4)
    assert quads.min() > 0.15 * n, quads
    g = np.sqrt(lv[0][..., 1] ** 2 + lv[0][..., 2] ** 2)
    assert g[y, x].mean() > 2.0 * g.mean()
    assert np.mean(out.level == 0) > 0.5
    assert np.all(np.diff(y * 640 + x) > 0)  # raster order, no duplicates
    assert set(out.dso_type.tolist()) <= {1, 2, 4}
    # the same seed gives the same selection; the potential carries over to the next keyframe
    again = ps.PixelSelector(640, 480, seed=1).select(lv, density)
    assert np.array_equal(again.xy, out.xy)
    second = sel.select(lv, density)
    assert 0.75 * density <= len(second) <= 1.1 * density


def test_selector_recurses_towards_the_density():
    img = textured(240, 320, seed=4)
    lv = levels_of(img)
    few = ps.PixelSelector(320, 240, initial_potential=12).select(lv, 2000)  # far too coarse at first
    assert few.potential < 12 and len(few) > 0.5 * 2000
    many = ps.PixelSelector(320, 240, initial_potential=1).select(lv, 100)  # far too fine at first
    assert many.potential > 1 and len(many) <= 1.1 * 100
    with pytest.raises(ValueError, match="levels 0-2"):
        ps.PixelSelector(320, 240).select(lv[:2], 100)
    with pytest.raises(ValueError, match="expected \\(240, 320, 3\\)"):
        ps.PixelSelector(320, 240).select([lv[1], lv[1], lv[2]], 100)
