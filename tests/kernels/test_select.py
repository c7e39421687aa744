"""Pixel-selection kernel (mgso_kernels.select) vs its NumPy twin (the vectorised cells), single vs split launches,
and input checks. (tests/tracking/test_pixel_selector.py checks both against DSO's nested loops.)"""

import cv2
import numpy as np
import pytest

from mgso.tracking.pixel_selector import block_thresholds
from mgso_kernels import runtime
from mgso_kernels import select as ks
from mgso_kernels.reference import image as ref_img
from mgso_kernels.reference import select as ref


def scene(h, w, seed):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.8)
    img = (255.0 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)
    img[h // 3: h // 2, w // 4: w // 2] = 100.0  # a flat patch: coarser levels fill those cells
    lv = [dI for _, dI, _ in ref_img.build_pyramid(img, 3)]
    g = [d[..., 1] ** 2 + d[..., 2] ** 2 for d in lv]
    return lv[0][..., 1:3], g, block_thresholds(g[0]), rng


@pytest.mark.parametrize("pot, th_factor, use_dirs", [(3, 1.0, True), (2, 2.0, True), (4, 1.0, False),
                                                     (1, 1.0, True), (7, 5.0, True)])
def test_kernel_equals_twin(wp_device, pot, th_factor, use_dirs):
    h, w = 250, 333  # not multiples of the cells or of 32
    dxy, g, ths, rng = scene(h, w, pot)
    dirs = [rng.integers(0, 16, (-(-h // c), -(-w // c))) for c in (pot, 2 * pot, 4 * pot)]
    got = ks.select_map(dxy, g, ths, pot, *dirs, th_factor=th_factor, use_directions=use_dirs, device=wp_device)
    want = ref.select_map(dxy, g, ths, pot, *dirs, th_factor=th_factor, use_directions=use_dirs)
    np.testing.assert_array_equal(got, want)
    assert np.count_nonzero(got == 1) > 20
    # the pyramid's (I, dx, dy) read in place gives the same map
    dI0 = np.concatenate([rng.uniform(0, 255, (h, w, 1)).astype(np.float32), dxy], axis=2)
    np.testing.assert_array_equal(ks.select_map(dI0, g, ths, pot, *dirs, th_factor=th_factor,
                                                use_directions=use_dirs, device=wp_device), want)
    if th_factor > 1.5:
        assert np.count_nonzero(got >= 2) > 0


def test_split_equals_single(wp_device):
    h, w = 480, 640
    dxy, g, ths, rng = scene(h, w, 9)
    dirs = [rng.integers(0, 16, (-(-h // c), -(-w // c))) for c in (1, 2, 4)]
    runtime.set_cpu_threads(1)
    try:
        a = ks.select_map(dxy, g, ths, 1, *dirs, device=wp_device)
    finally:
        runtime.set_cpu_threads(0)
    b = ks.select_map(dxy, g, ths, 1, *dirs, device=wp_device)
    np.testing.assert_array_equal(a, b)


def test_checks_inputs(wp_device):
    dxy, g, ths, rng = scene(96, 128, 1)
    dirs = [rng.integers(0, 16, (-(-96 // c), -(-128 // c))) for c in (3, 6, 12)]
    with pytest.raises(ValueError, match="dir3"):
        ks.select_map(dxy, g, ths, 3, dirs[0], dirs[2], dirs[2], device=wp_device)
    with pytest.raises(ValueError, match="dxy0"):
        ks.select_map(dxy[:, :, :1], g, ths, 3, *dirs, device=wp_device)
    with pytest.raises(ValueError, match="pot"):
        ks.select_map(dxy, g, ths, 0, *dirs, device=wp_device)
