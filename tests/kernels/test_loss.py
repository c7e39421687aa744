"""L1 + D-SSIM: Warp kernels against the NumPy twin (forward and backward), and the twin against finite differences."""

import numpy as np
import pytest

from mgso_kernels import loss as wl
from mgso_kernels.reference import loss as rl


def _pair(rng, h, w):
    target = rng.random((h, w, 3)).astype(np.float32)
    rendered = np.clip(target + 0.15 * rng.standard_normal((h, w, 3)), 0, 1).astype(np.float32)
    return rendered, target


def test_window_is_the_3dgs_window():
    g = wl.gaussian_window()
    assert g.shape == (11,) and abs(g.sum() - 1) < 1e-6
    # exp(-(x^2)/(2*1.5^2)) normalised: the ratio of neighbours is fixed by sigma alone
    assert np.isclose(g[6] / g[5], np.exp(-1 / 4.5), rtol=1e-6)
    assert np.allclose(g, g[::-1])
    # the chunk kernels have it built in
    from mgso_kernels.loss_chunks import WINDOW
    assert np.array_equal(WINDOW, g)


def test_twin_ssim_is_the_zero_padded_windowed_formula(rng):
    """The twin's SSIM map at a few pixels equals the textbook formula evaluated with explicit 11x11 loops."""
    x = rng.random((14, 17, 3))
    y = rng.random((14, 17, 3))
    g = rl.gaussian_window()
    S = rl.ssim_map(x, y, g)
    for (py, px) in [(0, 0), (3, 8), (13, 16), (7, 2)]:
        for c in range(3):
            m = np.zeros(5)
            for dy in range(-5, 6):
                for dx in range(-5, 6):
                    yy, xx = py + dy, px + dx
                    if 0 <= yy < 14 and 0 <= xx < 17:   # zero padding: outside pixels contribute nothing
                        wgt = g[dy + 5] * g[dx + 5]
                        a, b = x[yy, xx, c], y[yy, xx, c]
                        m += wgt * np.array([a, b, a * a, b * b, a * b])
            mx, my, exx, eyy, exy = m
            sx, sy, sxy = exx - mx ** 2, eyy - my ** 2, exy - mx * my
            ref = ((2 * mx * my + 1e-4) * (2 * sxy + 9e-4)) / ((mx ** 2 + my ** 2 + 1e-4) * (sx + sy + 9e-4))
            assert np.isclose(S[py, px, c], ref, rtol=1e-10)


@pytest.mark.parametrize("use_mask,exposure", [(False, None), (True, (0.3, -0.05))])
@pytest.mark.parametrize("h,w", [(96, 131), (64, 96)])
def test_forward_and_backward_match_twin(wp_device, rng, use_mask, exposure, h, w):
    # 96 x 131: > 4096 pixels, the launches are split over the cores; odd sizes exercise the borders, and rows of
    # 3 x 131 floats are not whole 16-float chunks (staged). 64 x 96: rows are whole chunks (read in place).
    rendered, target = _pair(rng, h, w)
    mask = None
    if use_mask:
        mask = (rng.random((h, w)) > 0.2).astype(np.float32) * rng.uniform(0.5, 1.5, (h, w)).astype(np.float32)
        mask[:, :12] = 0.0   # an invalid border, as after undistortion
    fn = wl.L1SSIMLoss(h, w, wp_device)
    res = fn(rendered, target, mask=mask, exposure=exposure)
    ref = rl.l1_dssim_loss(rendered, target, mask=mask, exposure=exposure)
    assert np.isclose(res.weight_sum, ref["weight_sum"], rtol=1e-6)
    assert np.isclose(res.l1, ref["l1"], rtol=1e-5, atol=1e-7)
    assert np.isclose(res.ssim, ref["ssim"], rtol=1e-5, atol=1e-6)
    assert np.isclose(res.loss, ref["loss"], rtol=1e-5, atol=1e-7)
    g = res.v_rendered.numpy()
    scale = np.abs(ref["v_rendered"]).max()
    assert g.shape == (h, w, 3)
    np.testing.assert_allclose(g, ref["v_rendered"], atol=2e-5 * scale, rtol=0)
    np.testing.assert_allclose(res.v_exposure, ref["v_exposure"], rtol=2e-5, atol=1e-7)
    if use_mask:
        # weight-0 pixels farther than the window radius (5 px) from any weighted pixel get exactly no gradient;
        # nearer ones still get the SSIM gradient of their valid neighbours' windows
        assert not np.any(g[:, :7]) and np.abs(g[:, 7:12]).max() > 0


@pytest.mark.parametrize("window_size,sigma", [(7, 1.0), (13, 2.0)])
def test_other_windows_match_twin(wp_device, rng, window_size, sigma):
    """Windows other than 3DGS's 11 x 11, sigma 1.5 run the per-pixel kernels."""
    h, w = 40, 48
    rendered, target = _pair(rng, h, w)
    fn = wl.L1SSIMLoss(h, w, wp_device, window_size=window_size, sigma=sigma)
    assert not fn.chunked and wl.L1SSIMLoss(h, w, wp_device).chunked
    res = fn(rendered, target, exposure=(0.1, 0.02))
    ref = rl.l1_dssim_loss(rendered, target, exposure=(0.1, 0.02), window_size=window_size, sigma=sigma)
    assert np.isclose(res.loss, ref["loss"], rtol=1e-5, atol=1e-7)
    assert np.isclose(res.ssim, ref["ssim"], rtol=1e-5, atol=1e-6)
    scale = np.abs(ref["v_rendered"]).max()
    np.testing.assert_allclose(res.v_rendered.numpy(), ref["v_rendered"], atol=2e-5 * scale, rtol=0)
    np.testing.assert_allclose(res.v_exposure, ref["v_exposure"], rtol=2e-5, atol=1e-7)


def test_warp_accepts_warp_arrays_and_is_deterministic(wp_device, rng):
    import warp as wp
    h, w = 40, 50
    rendered, target = _pair(rng, h, w)
    fn = wl.L1SSIMLoss(h, w, wp_device)
    a = fn(rendered, target)
    g1 = a.v_rendered.numpy().copy()
    b = fn(wp.array(rendered, dtype=wp.float32, device=wp_device), wp.array(target, dtype=wp.vec3, device=wp_device))
    assert a.loss == b.loss and np.array_equal(g1, b.v_rendered.numpy())


def test_identical_images_and_empty_mask(wp_device, rng):
    h, w = 20, 24
    _, target = _pair(rng, h, w)
    fn = wl.L1SSIMLoss(h, w, wp_device)
    res = fn(target, target)
    assert res.l1 == 0.0 and abs(res.ssim - 1.0) < 1e-5 and abs(res.loss) < 1e-5
    assert np.abs(res.v_rendered.numpy()).max() < 1e-4
    res0 = fn(target * 0.5, target, mask=np.zeros((h, w), np.float32))
    assert res0.weight_sum == 0.0 and res0.loss == 0.0 and not np.any(res0.v_rendered.numpy())


def test_bad_inputs_are_named(wp_device):
    fn = wl.L1SSIMLoss(10, 12, wp_device)
    img = np.zeros((10, 12, 3), np.float32)
    with pytest.raises(ValueError, match="rendered.*12x10|built for"):
        fn(np.zeros((11, 12, 3), np.float32), img)
    with pytest.raises(ValueError, match="target.*uint8|divide"):
        fn(img, np.zeros((10, 12, 3), np.uint8))
    with pytest.raises(ValueError, match="mask"):
        fn(img, img, mask=np.ones((10, 11), np.float32))


def test_twin_gradient_matches_finite_differences(rng):
    h, w = 9, 13
    x = rng.random((h, w, 3))
    y = np.clip(x + 0.2 * rng.standard_normal((h, w, 3)), 0, 1)
    mask = rng.uniform(0.0, 1.0, (h, w))
    expo = (0.2, 0.03)
    ref = rl.l1_dssim_loss(x, y, mask=mask, exposure=expo)
    eps = 1e-6

    def f(xx, e):
        return rl.l1_dssim_loss(xx, y, mask=mask, exposure=e)["loss"]

    for _ in range(25):
        i, j, c = rng.integers(h), rng.integers(w), rng.integers(3)
        xp, xm = x.copy(), x.copy()
        xp[i, j, c] += eps
        xm[i, j, c] -= eps
        fd = (f(xp, expo) - f(xm, expo)) / (2 * eps)
        assert np.isclose(ref["v_rendered"][i, j, c], fd, rtol=1e-5, atol=1e-9), (i, j, c)
    for k in range(2):
        ep, em = list(expo), list(expo)
        ep[k] += eps
        em[k] -= eps
        fd = (f(x, tuple(ep)) - f(x, tuple(em))) / (2 * eps)
        assert np.isclose(ref["v_exposure"][k], fd, rtol=1e-5, atol=1e-9)


def test_split_launches_are_bitwise_equal_to_one_thread(wp_device, rng):
    """Per-block float64 partials, no atomics: the result does not depend on how the launches are split."""
    from mgso_kernels import runtime
    h, w = 64, 160
    rendered, target = _pair(rng, h, w)
    fn = wl.L1SSIMLoss(h, w, wp_device)
    old = runtime._threads
    try:
        out = []
        for threads in (1, 3):
            runtime.set_cpu_threads(threads)
            r = fn(rendered, target, exposure=(0.1, 0.02))
            out.append((r.loss, r.v_exposure, r.v_rendered.numpy().copy()))
    finally:
        runtime.set_cpu_threads(old)
    assert out[0][0] == out[1][0] and out[0][1] == out[1][1] and np.array_equal(out[0][2], out[1][2])


def test_gradient_float_view(wp_device, rng):
    rendered, target = _pair(rng, 12, 16)
    res = wl.L1SSIMLoss(12, 16, wp_device)(rendered, target)
    assert res.v_rendered_hw3.shape == (12, 16, 3)
    assert np.array_equal(res.v_rendered_hw3.numpy(), res.v_rendered.numpy())


@pytest.mark.parametrize("use_mask,exposure", [(False, None), (True, (0.3, -0.05))])
@pytest.mark.parametrize("h,w", [(70, 131), (80, 96), (9, 5)])
def test_cpu_row_loops_equal_the_chunk_kernels_bit_for_bit(wp_device, rng, use_mask, exposure, h, w):
    """mgso_kernels.loss_simd (the CPU's path) writes what the chunk kernels write: loss, sums, dL/dI and the
    exposure gradient the same bits, for rows that are whole chunks (96: read in place) and not (131, 5: staged),
    blocks of chunks ending part-way (131 x 3 = 393 floats: 25 chunks, 7 blocks) and images smaller than the
    window (9 x 5); and the row loops did run (the status of every block is 1)."""
    import warp as wp

    if not wp.get_device(wp_device).is_cpu:
        pytest.skip("the row loops are the CPU's path")
    rendered, target = _pair(rng, h, w)
    rendered[3, 2] = 0.0                        # a few exact zeros and ties: the L1 sign's three cases
    target[3, 2] = 0.0
    mask = None
    if use_mask:
        mask = (rng.random((h, w)) > 0.2).astype(np.float32) * rng.uniform(0.5, 1.5, (h, w)).astype(np.float32)
    out = {}
    for simd in (False, True):
        fn = wl.L1SSIMLoss(h, w, wp_device, simd=simd)
        r = fn(rendered, target, mask=mask, exposure=exposure)
        out[simd] = (r.loss, r.l1, r.ssim, r.weight_sum, r.v_exposure, r.v_rendered.numpy().copy())
        if simd:
            assert fn._status.numpy().all(), "a block fell back to the chunk kernels"
        else:
            assert not fn.simd
    a, b = out[False], out[True]
    assert a[:5] == b[:5]
    assert np.array_equal(a[5].view(np.uint32), b[5].view(np.uint32))


@pytest.mark.parametrize("h,w", [(48, 64), (37, 50)])   # rows of whole chunks (in place) and staged rows
def test_a_mask_staged_once_is_reused_only_while_its_weights_are_equal(wp_device, rng, h, w):
    # On the CPU the loss keeps the weights it staged last and skips staging equal ones again (a camera's
    # undistortion mask, the same for every view). Each call must still give what a fresh loss gives with its own
    # mask: a different mask, an equal mask in another array, and the first mask changed in place (the control: a
    # cache keyed on the array object would return the stale result there).
    import warp as wp
    rendered, target = _pair(rng, h, w)
    mask_a = (rng.random((h, w)) > 0.2).astype(np.float32)
    mask_b = np.ones((h, w), np.float32)
    mask_b[: h // 3] = 0.0
    arr_a = wp.array(mask_a, dtype=wp.float32, device=wp_device)

    def fresh(mask):
        r = wl.L1SSIMLoss(h, w, wp_device)(rendered, target, mask=mask.copy(), exposure=(0.1, 0.02))
        return r.loss, r.v_rendered.numpy().copy()

    fn = wl.L1SSIMLoss(h, w, wp_device)
    calls = [(arr_a, mask_a), (mask_b, mask_b), (mask_a.copy(), mask_a), (arr_a, mask_a)]
    for k, (given, values) in enumerate(calls):
        r = fn(rendered, target, mask=given, exposure=(0.1, 0.02))
        want_loss, want_grad = fresh(values)
        assert r.loss == want_loss and np.array_equal(r.v_rendered.numpy(), want_grad), k
    changed = mask_a.copy()
    changed[h // 2:] = 0.0
    arr_a.assign(changed)   # the same array, new weights
    r = fn(rendered, target, mask=arr_a, exposure=(0.1, 0.02))
    want_loss, want_grad = fresh(changed)
    assert r.loss == want_loss and np.array_equal(r.v_rendered.numpy(), want_grad)
    assert r.loss != fresh(mask_a)[0]
