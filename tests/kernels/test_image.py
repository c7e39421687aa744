"""Pyramid geometry, pyramid + gradient kernels and bilinear sampling against their NumPy twin."""

import cv2
import numpy as np
import pytest
import warp as wp

from mgso_kernels import image as kimg
from mgso_kernels.reference import image as ref


def texture(h, w, seed=0, sigma=2.0):
    """Smooth random texture in 0-255 (blurred noise)."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
    t = (t - t.min()) / (t.max() - t.min())
    return (255.0 * t).astype(np.float32)


# ------------------------------------------------------------------------------------------------ geometry
def test_level_count_follows_dso_rule():
    # DSO setGlobalCalib halves while w*h > 5000: 640x480 -> levels 0 to 3, coarsest 80 x 60.
    assert kimg.pyramid_levels_for(640, 480) == 4
    assert kimg.pyramid_levels_for(1241, 376) == 5  # 1241x376 -> ... -> 77x23
    assert kimg.pyramid_levels_for(752, 480) == 5  # EuRoC: 94x60 still has 5640 > 5000 px, coarsest 47x30
    assert kimg.pyramid_levels_for(640, 480, min_area=1200) == 5  # coarsest 40x30
    assert kimg.pyramid_levels_for(2560, 1920) == 6  # capped at PYR_LEVELS = 6
    assert kimg.pyramid_levels_for(64, 48) == 1
    with pytest.raises(ValueError, match="positive"):
        kimg.pyramid_levels_for(0, 10)


def test_plan_pyramid_crops_kitti_centrally_and_shifts_principal_point():
    cam = kimg.Pinhole(718.856, 718.856, 607.1928, 185.2157)
    g = kimg.plan_pyramid(1241, 376, cam)
    assert (g.levels, g.width, g.height) == (5, 1232, 368)
    assert (g.offset_x, g.offset_y) == (4, 4)
    assert g.camera.cx == pytest.approx(607.1928 - 4) and g.camera.cy == pytest.approx(185.2157 - 4)
    assert g.camera.fx == cam.fx
    assert g.level_size(4) == (77, 23)
    img = np.arange(376 * 1241, dtype=np.float32).reshape(376, 1241)
    out = g.adjust(img)
    assert out.shape == (368, 1232) and out[0, 0] == img[4, 4] and out[-1, -1] == img[371, 1235]
    # a pixel keeps its ray: input pixel (x, y) and cropped pixel (x - 4, y - 4) see the same direction
    x_in = 700.0
    assert (x_in - cam.cx) / cam.fx == pytest.approx(((x_in - g.offset_x) - g.camera.cx) / g.camera.fx)

    gp = kimg.plan_pyramid(1241, 376, cam, mode="pad")
    assert (gp.width, gp.height) == (1248, 384)
    assert gp.camera.cx == pytest.approx(607.1928 - gp.offset_x) and gp.offset_x < 0
    padded = gp.adjust(img)
    assert padded.shape == (384, 1248)
    assert padded[-gp.offset_y, -gp.offset_x] == img[0, 0]

    g640 = kimg.plan_pyramid(640, 480, cam)
    assert (g640.width, g640.height, g640.offset_x, g640.offset_y) == (640, 480, 0, 0)
    with pytest.raises(ValueError, match="too small"):
        kimg.plan_pyramid(20, 20, levels=4)
    with pytest.raises(ValueError, match="crop' or 'pad"):
        kimg.plan_pyramid(640, 480, mode="stretch")
    with pytest.raises(ValueError, match="expects 1241x376"):
        g.adjust(np.zeros((10, 10)))


def test_level_intrinsics_match_the_2x2_average_pyramid():
    # On a linear ramp the averaged level-l pixel x_l holds the level-0 value at (x_l + 0.5) * 2^l - 0.5, which
    # is exactly the mapping cx_l = (cx + 0.5) / 2^l - 0.5, fx_l = fx / 2^l encodes.
    h, w, levels = 32, 64, 4
    ramp = (0.25 * np.arange(w)[None, :] + 0.5 * np.arange(h)[:, None]).astype(np.float64)
    pyr = ref.build_pyramid(ramp, levels, dtype=np.float64)
    cam = kimg.Pinhole(100.0, 110.0, 31.3, 15.7)
    X = np.array([0.07, -0.03, 1.0])
    x0 = cam.fx * X[0] / X[2] + cam.cx
    y0 = cam.fy * X[1] / X[2] + cam.cy
    for lvl in range(1, levels):
        c = cam.at_level(lvl)
        xl = c.fx * X[0] / X[2] + c.cx
        yl = c.fy * X[1] / X[2] + c.cy
        assert xl == pytest.approx((x0 + 0.5) / 2 ** lvl - 0.5)
        assert yl == pytest.approx((y0 + 0.5) / 2 ** lvl - 0.5)
        I = pyr[lvl][0]
        yy, xx = np.mgrid[0:I.shape[0], 0:I.shape[1]]
        s = 2 ** lvl
        assert np.allclose(I, 0.25 * ((xx + 0.5) * s - 0.5) + 0.5 * ((yy + 0.5) * s - 0.5))


# ------------------------------------------------------------------------------------------------- kernels
def test_pyramid_and_gradients_match_twin(wp_device):
    img = texture(96, 128, seed=1)
    geom = kimg.plan_pyramid(128, 96, levels=4)
    pyr = kimg.ImagePyramid(geom, wp_device).build(img)
    twin = ref.build_pyramid(img, 4)
    for lvl in range(4):
        I, dI, g2 = twin[lvl]
        assert pyr.intensity[lvl].shape == I.shape
        np.testing.assert_allclose(pyr.intensity[lvl].numpy(), I, rtol=0, atol=1e-4)
        np.testing.assert_allclose(pyr.dI[lvl].numpy(), dI, rtol=0, atol=1e-4)
        np.testing.assert_allclose(pyr.grad_sq[lvl].numpy(), g2, rtol=1e-5, atol=1e-3)
    # central differences in the interior, clamped one-sided halves at the border
    dI0 = pyr.dI[0].numpy()
    nan_img = img.copy()
    nan_img[50, 60] = np.nan
    dI_nan = kimg.ImagePyramid(kimg.plan_pyramid(128, 96, levels=1), wp_device).build(nan_img).dI[0].numpy()
    assert dI_nan[50, 59, 1] == 0 and dI_nan[49, 60, 2] == 0 and dI_nan[50, 61, 1] == 0  # non-finite -> 0 (DSO)
    assert dI_nan[50, 58, 1] == pytest.approx(dI0[50, 58, 1])
    assert dI0[10, 20, 1] == pytest.approx(0.5 * (img[10, 21] - img[10, 19]), abs=1e-4)
    assert dI0[10, 0, 1] == pytest.approx(0.5 * (img[10, 1] - img[10, 0]), abs=1e-4)
    assert dI0[95, 7, 2] == pytest.approx(0.5 * (img[95, 7] - img[94, 7]), abs=1e-4)


@pytest.mark.parametrize("w, h", [(2, 2), (3, 5), (33, 7), (65, 3), (640, 4)])
def test_pyramid_rows_are_the_float32_arithmetic_bit_for_bit(wp_device, w, h):
    """The gradients and the 2x2 mean against the same float32 operations in NumPy (central differences clamped at
    the border, non-finite -> 0, ``dx*dx + dy*dy`` without FMA; ``0.25 * (((a + b) + c) + d)``): on the CPU the
    native row loops (mgso_kernels.image_simd), and the Warp loops where a row is not contiguous (a strided view of a
    wider image), give these bits; on a GPU (FMA contraction) to float32 rounding. Sizes cover a first and a last
    column in one span, spans that start past the border, and images narrower than 3 pixels."""
    rng = np.random.default_rng(w * 100 + h)
    img = (rng.random((h, w)) * 255).astype(np.float32)
    img[h // 2, w // 2] = np.nan
    img[0, w - 1] = np.inf
    xm = np.clip(np.arange(w) - 1, 0, w - 1)
    xp = np.clip(np.arange(w) + 1, 0, w - 1)
    ym = np.clip(np.arange(h) - 1, 0, h - 1)
    yp = np.clip(np.arange(h) + 1, 0, h - 1)
    with np.errstate(invalid="ignore"):
        dx = np.float32(0.5) * (img[:, xp] - img[:, xm])
        dy = np.float32(0.5) * (img[yp, :] - img[ym, :])
        dx = np.where(dx - dx == 0, dx, np.float32(0)).astype(np.float32)
        dy = np.where(dy - dy == 0, dy, np.float32(0)).astype(np.float32)
    g2 = (dx * dx) + (dy * dy)
    want_dI = np.stack([img, dx, dy], axis=-1)
    big = (rng.random((2 * h, 2 * w)) * 255).astype(np.float32)
    want_half = np.float32(0.25) * (((big[0::2, 0::2] + big[0::2, 1::2]) + big[1::2, 0::2]) + big[1::2, 1::2])
    exact = wp.get_device(wp_device).is_cpu
    wide = np.zeros((h, 2 * w), np.float32)
    wide[:, ::2] = img  # its even columns: a view whose rows are not contiguous
    for name, src in (("contiguous", wp.array(img, device=wp_device)),
                      ("strided", wp.array(wide, device=wp_device)[:, ::2])):
        assert (src.strides[1] == 4) == (name == "contiguous")
        dI = wp.zeros((h, w), dtype=wp.vec3, device=wp_device)
        gs = wp.zeros((h, w), dtype=wp.float32, device=wp_device)
        kimg.gradients(src, dI, gs, split=False)
        if exact:
            np.testing.assert_array_equal(dI.numpy(), want_dI, err_msg=name)
            np.testing.assert_array_equal(gs.numpy(), g2, err_msg=name)
        else:
            np.testing.assert_allclose(gs.numpy(), g2, rtol=1e-6, err_msg=name)
    dst = wp.zeros((h, w), dtype=wp.float32, device=wp_device)
    kimg.downsample(wp.array(big, device=wp_device), dst, split=False)
    np.testing.assert_array_equal(dst.numpy(), want_half)


def test_split_launch_is_identical_and_uint8_input_works(wp_device):
    img = (texture(128, 160, seed=2)).astype(np.uint8)
    geom = kimg.plan_pyramid(160, 128, levels=3)
    a = kimg.ImagePyramid(geom, wp_device)
    b = kimg.ImagePyramid(geom, wp_device)
    kimg.build_pyramid(img, a, split=False)
    from mgso_kernels import runtime
    old = runtime.cpu_threads()
    runtime.set_cpu_threads(2)
    try:
        n = runtime.launch_split(kimg.compute_gradients, kimg.span_threads(128, 160),
                                 [a.intensity[0], b.dI[0], b.grad_sq[0]], wp_device, min_chunk=100)
        kimg.build_pyramid(img, b, split=True)
    finally:
        runtime.set_cpu_threads(old)
    if wp.get_device(wp_device).is_cpu:
        assert n == 2
    for lvl in range(3):
        assert np.array_equal(a.dI[lvl].numpy(), b.dI[lvl].numpy())
    with pytest.raises(ValueError, match="expects 160x128"):
        a.build(np.zeros((10, 10), np.float32))
    with pytest.raises(ValueError, match="gray"):
        a.build(np.zeros((128, 160, 3), np.float32))


def test_bilinear_sampling_matches_twin_and_checks_bounds(wp_device, rng):
    img = texture(40, 50, seed=3)
    dI, _ = ref.gradients(img)
    dI_w = wp.array(dI, dtype=wp.vec3, device=wp_device)
    xy = np.concatenate([rng.uniform(-2, 51, (300, 2)),
                         [[0, 0], [49, 39], [49.0, 10.5], [49.01, 10], [-0.01, 3], [np.nan, 3], [12, 7]]]
                        ).astype(np.float32)
    for bilin in (False, True):
        val, ok = kimg.sample_points(dI_w, xy, bilin_derivative=bilin)
        ok_ref = ref.bilinear_inside(xy[:, 0], xy[:, 1], 50, 40)
        assert np.array_equal(ok, ok_ref)
        f = ref.sample_dI_bilin_derivative if bilin else ref.sample_dI
        want = f(dI, xy[ok, 0], xy[ok, 1])
        np.testing.assert_allclose(val[ok], want, rtol=1e-5, atol=1e-3)
        assert np.all(val[~ok] == 0)
    # at an integer pixel the sample is the pixel; the BiLin gradient there is the forward difference
    val, _ = kimg.sample_points(dI_w, np.array([[12, 7]], np.float32))
    assert np.allclose(val[0], dI[7, 12], atol=1e-4)
    val, _ = kimg.sample_points(dI_w, np.array([[12, 7]], np.float32), bilin_derivative=True)
    assert np.allclose(val[0], [img[7, 12], img[7, 13] - img[7, 12], img[8, 12] - img[7, 12]], atol=1e-3)


@wp.kernel
def _finite_kernel(x: wp.array(dtype=float), v: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.int32),
                   out3: wp.array(dtype=wp.int32)):
    i = wp.tid()
    out[i] = wp.where(kimg.finite(x[i]), 1, 0)
    out3[i] = wp.where(kimg.finite3(v[i]), 1, 0)


def test_inline_finite_is_isfinite(wp_device):
    """``finite`` / ``finite3`` (``x - x == 0``, inlined; ``wp.isfinite`` is a call on the CPU) agree with
    ``np.isfinite`` on NaN, +-inf, the largest and smallest floats, denormals and signed zeros."""
    f32 = np.finfo(np.float32)
    vals = np.array([0.0, -0.0, 1.0, -3.5, f32.max, -f32.max, f32.tiny, f32.tiny / 8, np.nan, np.inf, -np.inf],
                    dtype=np.float32)
    vecs = np.stack([np.roll(np.array([vals[i], 1.0, 2.0], np.float32), k)
                     for i in range(len(vals)) for k in range(3)])
    x = wp.array(np.repeat(vals, 3), dtype=float, device=wp_device)
    v = wp.array(vecs, dtype=wp.vec3, device=wp_device)
    out = wp.zeros(len(vecs), dtype=wp.int32, device=wp_device)
    out3 = wp.zeros(len(vecs), dtype=wp.int32, device=wp_device)
    wp.launch(_finite_kernel, dim=len(vecs), inputs=[x, v, out, out3], device=wp_device)
    np.testing.assert_array_equal(out.numpy(), np.isfinite(np.repeat(vals, 3)).astype(np.int32))
    np.testing.assert_array_equal(out3.numpy(), np.isfinite(vecs).all(axis=1).astype(np.int32))
    assert out.numpy().sum() == 3 * 8 and out3.numpy().sum() == 3 * 8     # 8 finite values, 3 non-finite
