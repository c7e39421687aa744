"""The tile-per-thread blending kernels (mgso_kernels.splat.raster_tile, the CPU default): their vectorisable exp, and
agreement with the 16-pixel row kernels on a scene dense enough to stop pixels early, colour and opacity gradients
against central differences of the Warp forward (tile and per-pixel paths, both absgrad variants). Parity with the
NumPy twin,
split-equals-single and the densification statistics are tested for the default path in test_splat_forward.py and
test_splat_backward.py."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from mgso.geometry import se3_exp
from mgso_kernels.reference import splat as ref
from mgso_kernels.splat import Rasterizer, make_camera
from mgso_kernels.splat import raster_tile

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


@wp.kernel
def _exp_kernel(x: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = raster_tile.exp_lane(x[i])


def test_exp_lane_matches_exp(wp_device):
    rng = np.random.default_rng(0)
    x = np.concatenate([np.linspace(-87.0, 0.0, 100001), -np.abs(rng.normal(0.0, 3.0, 20000)),
                        [0.0, -1e-30, -0.5 * np.log(2.0), -np.log(2.0)]]).astype(np.float32)
    out = wp.zeros(len(x), dtype=float, device=wp_device)
    wp.launch(_exp_kernel, dim=len(x), inputs=[wp.array(x, device=wp_device), out], device=wp_device)
    got = out.numpy().astype(np.float64)
    want = np.exp(x.astype(np.float64))
    rel = np.abs(got - want) / want
    assert rel.max() < 2e-7  # expf's own accuracy is ~1 ulp (6e-8); measured 9.3e-8
    # far below the range it flushes to the value at -87 instead of going negative or NaN
    wp.launch(_exp_kernel, dim=3, inputs=[wp.array(np.float32([-100.0, -1e4, -np.inf]), device=wp_device), out],
              device=wp_device)
    tail = out.numpy()[:3]
    assert np.all(np.isfinite(tail)) and np.all(tail >= 0) and np.all(tail < 2e-38)


def _scene(seed, n, width, height):
    rng = np.random.default_rng(seed)
    T = se3_exp(rng.normal(size=6) * 0.2)
    cam = ref.RefCamera(fx=70.0, fy=72.0, cx=width / 2 - 0.3, cy=height / 2 + 0.6, width=width, height=height,
                        world_to_cam=T)
    scene = ref.random_scene(rng, n, cam, 1)
    wcam = make_camera(cam.fx, cam.fy, cam.cx, cam.cy, width, height, T, near=cam.near, far=cam.far)
    return rng, scene, wcam


@pytest.mark.parametrize("size", [(96, 80), (53, 35)])
def test_tile_kernels_agree_with_row_kernels(wp_device, size):
    rng, scene, cam = _scene(3, 500, *size)
    v_rgb = rng.normal(size=(size[1], size[0], 3)).astype(np.float32)
    v_depth = rng.normal(size=(size[1], size[0])).astype(np.float32)
    v_alpha = rng.normal(size=(size[1], size[0])).astype(np.float32)
    res = {}
    for seg in (16, raster_tile.TILE_PIXELS):
        rast = Rasterizer(wp_device, pixels_per_thread=seg)
        out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3))
        r = {k: getattr(out, k).numpy().copy() for k in ("rgb", "depth", "alpha", "T_final", "n_contrib")}
        r["coverage"] = rast.render_alpha(*(scene[k] for k in PARAMS[:4]), cam).alpha.numpy().copy()
        out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3))
        g = rast.backward(out, v_rgb, v_depth, v_alpha)
        for name in ("v_means", "v_log_scales", "v_quats", "v_opacity_logits", "v_sh", "v_pose", "v_means2d",
                     "absgrad", "weights"):
            r[name] = getattr(g, name).numpy().copy()
        res[seg] = r
    a, b = res[16], res[raster_tile.TILE_PIXELS]
    # the scene is dense: many pixels stop early (n_contrib below their tile's list length)
    assert (a["alpha"] > 0.999).mean() > 0.2
    # the row kernels step exp(power) along the row by a recurrence, the tile kernels evaluate it per pixel: the
    # images agree to float rounding, and the stop decisions everywhere but where T lands within rounding of 1e-4
    for key in ("rgb", "alpha", "T_final", "coverage"):
        # CUDA: a pixel whose transmittance lands at the 1e-4 stop can take one more Gaussian in one variant (fused
        # multiply-adds in another order); seen once at 3.9e-5 in alpha on an H100
        tol = 2e-5 if wp.get_device(wp_device).is_cpu else 1e-4
        np.testing.assert_allclose(b[key], a[key], atol=tol, rtol=0, err_msg=key)
    # depth likewise: on CUDA one pixel that stops at the 1e-4 transmittance in one variant was 1.5e-4 apart (H200)
    dtol = 2e-5 if wp.get_device(wp_device).is_cpu else 2e-4
    np.testing.assert_allclose(b["depth"], a["depth"], atol=dtol * np.abs(a["depth"]).max(), rtol=0)
    assert (b["n_contrib"] != a["n_contrib"]).mean() < 1e-3  # measured: none differ
    for name in ("v_means", "v_log_scales", "v_quats", "v_opacity_logits", "v_sh", "v_pose", "v_means2d",
                 "absgrad", "weights"):
        scale = np.abs(a[name]).max()
        assert scale > 0, name
        np.testing.assert_allclose(b[name], a[name], atol=2e-5 * scale, rtol=0, err_msg=name)  # measured <= 4e-6


def test_backward_without_absgrad_changes_nothing_else(wp_device):
    rng, scene, cam = _scene(4, 300, 64, 48)
    v_rgb = rng.normal(size=(48, 64, 3)).astype(np.float32)
    rast = Rasterizer(wp_device)
    res = []
    for absgrad in (True, False):
        out = rast.forward(*(scene[k] for k in PARAMS), cam)
        g = rast.backward(out, v_rgb, absgrad=absgrad)
        res.append({f: getattr(g, f).numpy().copy() for f in ("v_means", "v_log_scales", "v_quats",
                                                              "v_opacity_logits", "v_sh", "v_pose", "v_means2d",
                                                              "absgrad", "weights")})
    assert res[0]["absgrad"].max() > 0 and not res[1]["absgrad"].any()
    for name in res[0]:
        if name != "absgrad":
            if wp.get_device(wp_device).is_cpu:  # CPU: bitwise; CUDA atomics add in a varying order
                assert np.array_equal(res[0][name], res[1][name]), name
            else:
                np.testing.assert_allclose(res[0][name], res[1][name], rtol=1e-4,
                                           atol=1e-6 * np.abs(res[1][name]).max(), err_msg=name)


@pytest.mark.parametrize("seg,absgrad", [(raster_tile.TILE_PIXELS, True), (raster_tile.TILE_PIXELS, False),
                                         (1, True), (1, False)])
def test_colour_and_opacity_gradients_match_finite_differences_of_warp(wp_device, seg, absgrad):
    # The Warp backward against central differences of the Warp forward itself (not via the twin), for the tile
    # kernels (CPU default) and the per-pixel kernels (CUDA default). Colours and opacities do not move the cut-off
    # ellipses, so a small step changes no tile list and, with colours away from the 0 clamp (SH degree 0, no hard
    # cases), the image is smooth in them; an opacity step could still cross the 1/255 skip or the early stop, which
    # a step of 3e-4 does not on this scene (1e-3 does). Measured max errors / max |fd|: sh 2.3e-5, opacity 6.1e-3
    # (float32 rounding of the forward over the step). Geometry gradients jump where cut-offs move in float32; they are checked
    # against the twin's analytic gradients (test_splat_backward.py), which are checked against central differences.
    rng = np.random.default_rng(44)
    cam = ref.RefCamera(fx=40.0, fy=38.0, cx=20.3, cy=17.4, width=40, height=36, world_to_cam=se3_exp(
        rng.normal(size=6) * 0.2))
    scene = ref.random_scene(rng, 30, cam, 0, hard_cases=False)
    wcam = make_camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.world_to_cam, near=cam.near,
                       far=cam.far)
    ups = [rng.normal(size=s).astype(np.float32) for s in ((36, 40, 3), (36, 40), (36, 40))]
    rast = Rasterizer(wp_device, pixels_per_thread=seg)

    def loss(sc):
        o = rast.forward(*(sc[k].astype(np.float32) for k in PARAMS), wcam)
        return sum(float(np.sum(getattr(o, k).numpy().astype(np.float64) * u))
                   for k, u in zip(("rgb", "depth", "alpha"), ups))

    out = rast.forward(*(scene[k].astype(np.float32) for k in PARAMS), wcam)
    g = rast.backward(out, *ups, absgrad=absgrad)
    grads = {"sh": g.v_sh.numpy().astype(np.float64).copy(),
             "opacity_logits": g.v_opacity_logits.numpy().astype(np.float64).copy()}
    for name, eps, tol in (("sh", 1e-2, 1e-4), ("opacity_logits", 3e-4, 2e-2)):
        x = scene[name]
        fd = np.zeros_like(x)
        for idx in np.ndindex(x.shape):
            hi, lo = dict(scene), dict(scene)
            hi[name], lo[name] = x.copy(), x.copy()
            hi[name][idx] += eps
            lo[name][idx] -= eps
            fd[idx] = (loss(hi) - loss(lo)) / (2 * eps)
        assert np.abs(fd).max() > 0.1, name
        np.testing.assert_allclose(grads[name], fd, rtol=0, atol=tol * np.abs(fd).max(), err_msg=name)


def _render_both_ways(device, scene, cam, ups, absgrad):
    """Forward and backward of the tile kernels with their C++ snippets and with their own Warp code, and the status
    flags each path left (1 where the snippet did a tile)."""
    return _render(device, scene, cam, ups, absgrad, True), _render(device, scene, cam, ups, absgrad, False)


def _render(device, scene, cam, ups, absgrad, native: bool) -> dict:
    """Images, coverage and gradients of the tile kernels, with their C++ snippets or their own Warp code, and the
    status flags each launch left."""
    before = raster_tile.use_native(native)
    try:
        rast = Rasterizer(device)
        out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3))
        r = {k: getattr(out, k).numpy().copy() for k in ("rgb", "depth", "alpha", "T_final", "n_contrib")}
        dim = cam.tiles_x * cam.tiles_y
        r["status_forward"] = raster_tile.status_buffer(dim, device).numpy().copy()
        for t_stop in (0.0, 0.01):   # the coverage kernel, with and without the depth (the seeding's)
            a = rast.render_alpha(*(scene[k] for k in PARAMS[:4]), cam, t_stop=t_stop)
            r[f"coverage_{t_stop}"] = a.alpha.numpy().copy()
            r[f"status_coverage_{t_stop}"] = raster_tile.status_buffer(dim, device).numpy().copy()
            a = rast.render_alpha(*(scene[k] for k in PARAMS[:4]), cam, with_depth=True, t_stop=t_stop)
            r[f"coverage_depth_{t_stop}"] = np.stack([a.alpha.numpy(), a.depth.numpy()])
            r[f"status_coverage_depth_{t_stop}"] = raster_tile.status_buffer(dim, device).numpy().copy()
        out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3))
        rast.backward(out, *ups, absgrad=absgrad)
        # the tile snippet stores into the pairs (no add): NaN left in the pairs' buffer by anything before must not
        # reach the gradients
        rast.pair_grads_.full.fill_(wp.types.vector(16, wp.float32)(*([float("nan")] * 16)))
        g = rast.backward(out, *ups, absgrad=absgrad)
        r["status_backward"] = raster_tile.status_buffer(dim, device).numpy().copy()
        for name in ("v_means", "v_log_scales", "v_quats", "v_opacity_logits", "v_sh", "v_pose", "v_means2d",
                     "absgrad", "weights"):
            r[name] = getattr(g, name).numpy().copy()
    finally:
        raster_tile.use_native(before)
    return r


@pytest.mark.parametrize("size,n,absgrad", [((53, 35), 400, True), ((96, 80), 900, False), ((16, 16), 60, True)])
def test_cpp_tile_blend_equals_the_warp_kernels_to_rounding(wp_device, size, n, absgrad):
    # The C++ snippets (raster_tile_cpp) do the Warp kernels' arithmetic in another order of work and with FMAs (the
    # exp polynomial in Estrin's form): the same images, coverage (with and without depth, with and without the
    # coverage stop) and gradients to float rounding, and the same stop decisions (n_contrib), on tiles cut by the
    # image border, with the twin's hard cases (behind the camera, off-screen, thin, large, on tile borders, below
    # 1/255) and a dense scene where pixels stop early. Measured: at most 1.9e-6 of each array's largest value apart,
    # n_contrib equal everywhere. On the CPU the snippets must have done every tile (status 1; 0 would mean a silent
    # fallback), and switched off (the control) none; on CUDA they decline (status 0) and the Warp code runs.
    rng, scene, cam = _scene(11, n, *size)
    w, h = size
    ups = [rng.normal(size=s).astype(np.float32) for s in ((h, w, 3), (h, w), (h, w))]
    cpp, warp_code = _render_both_ways(wp_device, scene, cam, ups, absgrad)
    cpu = wp.get_device(wp_device).is_cpu
    for key in [k for k in cpp if k.startswith("status")]:
        assert (cpp[key] == (1 if cpu else 0)).all(), key
        assert not warp_code[key].any(), key
    assert (cpp["alpha"] > 0.999).mean() > 0.1 and (cpp["n_contrib"] > 0).mean() > 0.5
    assert np.array_equal(cpp["n_contrib"], warp_code["n_contrib"])
    for key, value in cpp.items():
        if key.startswith("status"):
            continue
        if key != "absgrad" or absgrad:
            assert np.abs(value).max() > 0, key
        if cpu:
            np.testing.assert_allclose(value, warp_code[key], rtol=0, atol=5e-6 * np.abs(value).max(), err_msg=key)
        else:  # the same Warp code twice; its float atomics add in a varying order
            np.testing.assert_allclose(value, warp_code[key], rtol=1e-4, atol=1e-6 * np.abs(value).max(), err_msg=key)


def test_the_tile_backward_stores_each_pair_whatever_its_buffer_held(wp_device):
    """The tile backward's snippet stores each pair's sums (a store, not an add) into the pairs the launcher zeroed;
    a pair it visits without a pixel to take it, and those past every pixel's last contributor, stay zero. One 16x16
    tile: three opaque bars a row stop the top half's pixels, a translucent bar behind them in the top half (listed,
    visited, no live pixel), and translucent bars over the bottom half, some behind it; the pairs' buffer holds NaN
    before the backward (_render). The C++ snippet and the kernel's own Warp code give the same finite gradients, the
    hidden bar's zero."""
    f, z0 = 20.0, np.array([1.0, 1.01, 1.02])
    rows = []   # (row centre, sigma_y px, opacity logit, z)
    for r in range(8):
        rows += [(float(r), 0.5, 10.0, z) for z in z0]
    hidden = len(rows)
    rows.append((3.0, 0.5, 0.0, 3.0))
    rows += [(11.5, 4.0, -0.85, z) for z in np.linspace(1.5, 5.5, 8)]
    n = len(rows)
    c, sy, logit, z = (np.array(v, np.float64) for v in zip(*rows))
    scene = {"means": np.stack([np.zeros(n), (c - 7.5) * z / f, z], 1).astype(np.float32),
             "log_scales": np.log(np.stack([30.0 * z / f, sy * z / f, np.full(n, 1e-3)], 1)).astype(np.float32),
             "quats": np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
             "opacity_logits": logit.astype(np.float32),
             "sh": np.random.default_rng(2).normal(size=(n, 1, 3)).astype(np.float32)}
    cam = make_camera(f, f, 7.5, 7.5, 16, 16, np.eye(4))
    rng = np.random.default_rng(5)
    ups = [rng.normal(size=s).astype(np.float32) for s in ((16, 16, 3), (16, 16), (16, 16))]
    cpp, warp_code = _render_both_ways(wp_device, scene, cam, ups, True)
    assert (cpp["n_contrib"][:8] <= 3 * 8).all() and (cpp["n_contrib"][8:] > hidden).any()   # top stopped early
    for key, value in cpp.items():
        if key.startswith("status"):
            continue
        assert np.isfinite(value).all(), key
        np.testing.assert_allclose(value, warp_code[key], rtol=0, atol=5e-6 * np.abs(value).max(), err_msg=key)
    assert cpp["v_opacity_logits"][hidden] == 0 and np.abs(cpp["v_opacity_logits"][hidden + 1:]).max() > 0
    assert cpp["weights"][hidden] == 0 and cpp["weights"][hidden + 1:].max() > 0   # its blending weight too


@pytest.mark.parametrize("with_color", [0, 1, 2])
def test_the_cpus_blocked_pack_copies_the_bytes_of_the_pair_kernel(wp_device, with_color):
    """launch_pack_splats on the CPU runs blocks of PACK_BLOCK pairs in C++ (the Gaussians of a block looked up before
    their data is copied); on CUDA the thread-per-pair kernel. Both give each sorted pair its Gaussian's data, bit for
    bit: checked against the pair kernel and NumPy on 5,000 pairs in a random order (4 blocks and a part), for the
    colour, the depth-only and the splats-only variants; on the CPU every block's status is 1, and with the C++
    switched off (the control, raster_tile.use_native(False)) the kernel's own loop writes the same bytes (status 0)."""
    from mgso_kernels.splat import raster

    rng = np.random.default_rng(3)
    n_g, m = 700, 5000
    gauss = rng.integers(0, n_g, m).astype(np.int32)
    slots = rng.permutation(m).astype(np.int32)
    sg = rng.random((n_g, 8), dtype=np.float32)
    cg = rng.random((n_g, 4), dtype=np.float32)
    dg = rng.random(n_g, dtype=np.float32)
    arr = lambda a, t: wp.array(a, dtype=t, device=wp_device)  # noqa: E731
    args = [arr(slots, wp.int32), arr(gauss, wp.int32), arr(sg, raster.vec8)]
    rgbz = arr(cg, wp.vec4) if with_color == 1 else None
    depths = arr(dg, wp.float32) if with_color == 2 else None
    want_s = sg[gauss[slots]]
    want_c = {0: None, 1: cg[gauss[slots]],
              2: np.concatenate([np.zeros((m, 3), np.float32), dg[gauss[slots]][:, None]], axis=1)}[with_color]

    status = []

    def pack(block_kernel: bool):
        out_s = wp.zeros(m, dtype=raster.vec8, device=wp_device)
        out_c = wp.zeros(m, dtype=wp.vec4, device=wp_device)
        if block_kernel:
            st = raster.launch_pack_splats(*args, rgbz, m, out_s, out_c, wp_device, depths_g=depths)
            status.append(None if st is None else st.numpy())
        else:   # the thread-per-pair kernel (CUDA's)
            flag = 1 if rgbz is not None else (2 if depths is not None else 0)
            wp.launch(raster.pack_splats, dim=m, inputs=[0, *args, rgbz if rgbz is not None else arr(cg[:1], wp.vec4),
                                                         depths if depths is not None else arr(dg[:1], wp.float32),
                                                         flag, out_s, out_c], device=wp_device)
        return out_s.numpy(), out_c.numpy()

    got_s, got_c = pack(True)
    ref_s, ref_c = pack(False)
    np.testing.assert_array_equal(got_s, want_s)
    np.testing.assert_array_equal(got_s, ref_s)
    np.testing.assert_array_equal(got_c, ref_c)
    if want_c is not None:
        np.testing.assert_array_equal(got_c, want_c)
    if str(wp_device).startswith("cpu"):
        assert (status[-1] == 1).all() and len(status[-1]) == 5
        before = raster_tile.use_native(False)
        try:
            off_s, off_c = pack(True)
            assert (status[-1] == 0).all() and len(status[-1]) == 5
        finally:
            raster_tile.use_native(before)
        np.testing.assert_array_equal(off_s, got_s)
        np.testing.assert_array_equal(off_c, got_c)


@pytest.mark.parametrize("n_tiles", [2, 1200, 70000])
def test_the_cpus_radix_sort_gives_warps_order(wp_device, n_tiles):
    """bin.sort_pairs sorts (tile << 32 | depth bits, slot) pairs stably by the key's low tile_key_bits; on the CPU in
    C++ (11-bit digits: 3, 4 and 5 passes for these tile counts, so the result ends in either half), elsewhere with
    wp.utils.radix_sort_pairs. The same keys and slots bit for bit on 30,000 pairs with repeated depths (ties keep
    the slot order), and the C++ sort ran on the CPU (returned 1); the control with the C++ switched off returns 0
    and the same order."""
    from mgso_kernels.splat import bin as binning

    rng = np.random.default_rng(5)
    m = 30000
    tile = rng.integers(0, n_tiles, m).astype(np.int64)
    depth = rng.choice(np.float32([0.5, 1.0, 2.5, 7.25]), m) if n_tiles == 2 else rng.random(m, dtype=np.float32) + 0.1
    keys = (tile << 32) | depth.view(np.uint32).astype(np.int64)
    slots = np.arange(m, dtype=np.int32)

    def run(native):
        k = wp.array(np.concatenate([keys, keys]), dtype=wp.int64, device=wp_device)
        v = wp.array(np.concatenate([slots, slots]), dtype=wp.int32, device=wp_device)
        if native is None:
            wp.utils.radix_sort_pairs(k, v, m, begin_bit=0, end_bit=binning.tile_key_bits(n_tiles))
            return k.numpy()[:m], v.numpy()[:m], None
        before = raster_tile.use_native(native)
        try:
            ran = binning.sort_pairs(k, v, m, n_tiles)
        finally:
            raster_tile.use_native(before)
        return k.numpy()[:m], v.numpy()[:m], ran

    want_k, want_v, _ = run(None)
    order = np.lexsort((slots, keys))                      # stable by key: NumPy's own
    np.testing.assert_array_equal(want_v, order)
    for native in (True, False):
        got_k, got_v, ran = run(native)
        np.testing.assert_array_equal(got_k, want_k)
        np.testing.assert_array_equal(got_v, want_v)
        assert ran == (1 if native and str(wp_device).startswith("cpu") else 0)


@pytest.mark.parametrize("n_tiles", [3, 1200, 70000])
def test_the_cpus_sort_from_the_gaussians_gives_the_radix_sorts_order_and_ranges(n_tiles):
    """bin.sort_pairs_and_ranges on the rasteriser's layout (Gaussian g's pairs at its slots, all with g's depth bits,
    one a tile): on the CPU it sorts the Gaussians by depth and places their slots tile by tile, the keys left as
    they were (returns 2); the slots and tile ranges are the twin's (reference.splat.sorted_pairs: NumPy's stable
    sort of the keys) bit for bit (ties in depth keep the slot order; Gaussians without pairs; tiles without pairs
    stay [0, 0)). The control with the C++ switched off takes the radix sort and tile_ranges (returns 1 or 0): the
    same slots and ranges, and the keys sorted. A key whose tile is outside [0, n_tiles), Gaussians whose slots are
    not one after the other, or a scratch too short make the C++ decline with nothing written."""
    from mgso_kernels.splat import bin as binning

    rng = np.random.default_rng(n_tiles)
    n = 4000
    touched = np.minimum(rng.integers(0, 9, n), n_tiles).astype(np.int32)   # a pair a tile
    touched[rng.random(n) < 0.2] = 0
    offsets = np.concatenate([[0], np.cumsum(touched)[:-1]]).astype(np.int32)
    m = int(touched.sum())
    depth = (rng.choice(np.float32([0.5, 1.0, 2.5]), n) if n_tiles == 3 else
             rng.random(n, dtype=np.float32) * 5 + 0.1).astype(np.float32)
    depth_bits = depth.view(np.uint32).astype(np.int64)
    keys = np.concatenate([(np.sort(rng.choice(n_tiles, touched[g], replace=False)).astype(np.int64) << 32)
                           | depth_bits[g] for g in range(n)])
    assert len(keys) == m
    slots = np.arange(m, dtype=np.int32)
    want_v, want_r = ref.sorted_pairs(keys, n_tiles)

    def arrays(k0):
        return (wp.array(np.concatenate([k0, k0]), dtype=wp.int64, device="cpu"),
                wp.array(np.concatenate([slots, slots]), dtype=wp.int32, device="cpu"),
                wp.array(np.full((n_tiles, 2), -7, np.int32), device="cpu"))

    def run(native):
        k, v, r = arrays(keys)
        before = raster_tile.use_native(native)
        try:
            ran = binning.sort_pairs_and_ranges(k, v, m, n_tiles, wp.array(offsets, device="cpu"),
                                                wp.array(touched, device="cpu"), r)
        finally:
            raster_tile.use_native(before)
        return k.numpy()[:m], v.numpy()[:m], r.numpy(), ran

    got_k, got_v, got_r, ran = run(True)
    assert ran == 2 and np.array_equal(got_k, keys)
    np.testing.assert_array_equal(got_v, want_v)
    np.testing.assert_array_equal(got_r, want_r)
    off_k, off_v, off_r, off_ran = run(False)
    assert off_ran in (0, 1)
    np.testing.assert_array_equal(off_k, keys[want_v])
    np.testing.assert_array_equal(off_v, want_v)
    np.testing.assert_array_equal(off_r, want_r)
    scratch = wp.empty(binning.sort_by_gaussian_scratch(n, n_tiles), dtype=wp.int32, device="cpu")
    status = wp.zeros(1, dtype=wp.int32, device="cpu")
    bad = keys.copy()
    bad[m // 2] = (np.int64(n_tiles) << 32) | (bad[m // 2] & 0xFFFFFFFF)
    off_bad = offsets.copy()
    off_bad[np.flatnonzero(touched)[1]] += 1
    # a tile outside the view; slots not one after the other; a scratch one int short
    for k0, off, scr in ((bad, offsets, scratch), (keys, off_bad, scratch), (keys, offsets, scratch[:-1])):
        k, v, r = arrays(k0)
        wp.launch(binning.sort_by_gaussian_cpu, dim=1, inputs=[n, m, n_tiles, wp.array(off, device="cpu"),
                                                               wp.array(touched, device="cpu"), k, v, r, scr, 1,
                                                               status], device="cpu")
        assert status.numpy()[0] == 0 and np.array_equal(k.numpy()[:m], k0)
        assert np.array_equal(v.numpy()[:m], slots) and np.all(r.numpy() == -7)


def _random_splats(rng, n, width, height, big=False):
    """Projected Gaussians as the projection writes them (mean, conic, opacity, exp(-a), cut-off r2), a few culled:
    means inside the image, on its borders and off it; ``big``: ellipses many tile rows tall."""
    means = np.stack([rng.uniform(-40, width + 40, n), rng.uniform(-40, height + 40, n)], 1)
    means[: n // 10, 0] = rng.choice([0.0, width - 1.0, -0.5, width - 0.5], n // 10)
    means[n // 10: n // 5, 1] = rng.choice([0.0, height - 1.0, 15.0, 16.0, 31.5], n // 10)
    sig = np.exp(rng.uniform(0.0, 5.5 if big else 3.5, (n, 2)))
    th = rng.uniform(0, np.pi, n)
    c, s_ = np.cos(th), np.sin(th)
    cxx = (c * sig[:, 0]) ** 2 + (s_ * sig[:, 1]) ** 2 + 0.3
    cyy = (s_ * sig[:, 0]) ** 2 + (c * sig[:, 1]) ** 2 + 0.3
    cxy = c * s_ * (sig[:, 0] ** 2 - sig[:, 1] ** 2)
    det = cxx * cyy - cxy * cxy
    a, b, cc = cyy / det, -cxy / det, cxx / det
    op = rng.uniform(0.004, 0.99, n)
    r2 = 2.0 * np.log(255.0 * op) * 1.001 + 0.01
    splats = np.stack([means[:, 0], means[:, 1], a, b, cc, op, np.exp(-a), r2], 1).astype(np.float32)
    radii = np.where(rng.random(n) < 0.05, 0, 1 + rng.integers(0, 50, n)).astype(np.int32)
    radii[16:40] = 0                    # a whole group of 16 culled (the C++ blocks pass over it) and part of one
    depths = rng.uniform(0.1, 30.0, n).astype(np.float32)
    return splats, radii, depths


@pytest.mark.parametrize("size,n,big", [((640, 480), 3000, False), ((53, 35), 700, False), ((16, 4000), 600, True),
                                        ((40, 16400), 300, True)])
def test_the_cpus_binning_blocks_list_the_kernels_pairs(wp_device, size, n, big):
    """On the CPU the binning (count_tiles, emit_pairs) runs in C++ blocks of BIN_BLOCK Gaussians whose row and column
    ranges are computed 16 at a time: the same tiles_touched, keys, slots and pair_gauss bit for bit as the Warp
    kernels (CUDA's path) on Gaussians inside, across and off the image borders, culled ones (a whole group of 16
    among them, which the blocks pass over), several blocks, and tall images whose ellipses reach hundreds of tile
    rows (a block's items flushed more than once); every block's status is 1, except beyond 1024 tile rows (16,400
    px), where the block declines (status 0) and the kernels' own loop gives the same pairs; with the C++ switched
    off (the control) status 0 and the same pairs."""
    from mgso_kernels.splat import bin as binning
    from mgso_kernels.splat import raster

    rng = np.random.default_rng(size[0] + n)
    splats, radii, depths = _random_splats(rng, n, *size, big=big)
    cam = make_camera(100.0, 100.0, size[0] / 2, size[1] / 2, size[0], size[1], np.eye(4))
    arr = lambda a, t: wp.array(a, dtype=t, device=wp_device)  # noqa: E731
    sp, rd, dp = arr(splats, raster.vec8), arr(radii, wp.int32), arr(depths, wp.float32)

    cache = wp.full(4 * n, 12345, dtype=wp.int32, device=wp_device)    # stale values the count must overwrite

    def run(kind):
        touched = wp.zeros(n + 1, dtype=wp.int32, device=wp_device)
        kept = {"cache": cache} if kind == "cache" else {}
        if kind == "kernel":
            wp.launch(binning.count_tiles, dim=n, inputs=[0, sp, rd, cam, touched[:n]], device=wp_device)
            st_count = None
        else:
            before = raster_tile.use_native(kind != "off")
            try:
                st_count = binning.launch_count_tiles(sp, rd, cam, touched[:n], wp_device, **kept)
            finally:
                raster_tile.use_native(before)
        t = touched.numpy()
        offsets = np.concatenate([[0], np.cumsum(t[:n])]).astype(np.int32)
        m = int(offsets[-1])
        keys = wp.zeros(2 * m, dtype=wp.int64, device=wp_device)
        slots = wp.zeros(2 * m, dtype=wp.int32, device=wp_device)
        gauss = wp.zeros(max(m, 1), dtype=wp.int32, device=wp_device)
        off = arr(offsets[:n], wp.int32)
        if kind == "kernel":
            wp.launch(binning.emit_pairs, dim=n, inputs=[0, sp, dp, rd, off, cam, keys, slots, gauss],
                      device=wp_device)
            st_emit = None
        else:
            before = raster_tile.use_native(kind != "off")
            try:
                st_emit = binning.launch_emit_pairs(sp, dp, rd, off, cam, keys, slots, gauss, m, wp_device, **kept)
            finally:
                raster_tile.use_native(before)
        out = (t[:n], keys.numpy()[:m], slots.numpy()[:m], gauss.numpy()[:m])
        status = [None if x is None else x.numpy() for x in (st_count, st_emit)]
        return out, status

    want, _ = run("kernel")
    assert want[1].size > (5 if big else 1) * n      # pairs listed, many rows a Gaussian for the big ones
    got, status = run("native")
    for w, g in zip(want, got):
        np.testing.assert_array_equal(g, w)
    if not str(wp_device).startswith("cpu"):
        return
    blocks = -(-n // binning.BIN_BLOCK)
    tall = size[1] > 16 * 1024
    for st in status:
        assert len(st) == blocks and (st == (0 if tall else 1)).all()
    off, status = run("off")
    for w, g in zip(want, off):
        np.testing.assert_array_equal(g, w)
    for st in status:
        assert (st == 0).all()
    # the count keeps the ranges of the Gaussians of up to 3 tile rows for the emit: the same pairs
    got, status = run("cache")
    for w, g in zip(want, got):
        np.testing.assert_array_equal(g, w)
    c = cache.numpy().reshape(n, 4)
    if tall:        # the blocks declined: the kernels' loop marked every Gaussian as not kept
        assert (c[:, 0] == -1).all()
        return
    rows = c[:, 0] >> 16
    # measured: 58 % kept (1,404 of 3,000 with rows), 100 % (478 of 700), 26 % (107 of 600) for the big ones
    assert (c[:, 0] >= 0).mean() > 0.15 and (rows > 0).sum() > n // 8 and (c[:, 0] != 12345).all()
    if big:
        assert (c[:, 0] == -1).any()                       # more than 3 tile rows: computed again by the emit
    # the emit reads them (the control): a kept range moved down a tile row moves that Gaussian's pairs
    g = int(np.flatnonzero((rows > 0) & (want[0] > 0))[0])
    c[g, 0] += 1
    cache.assign(c.reshape(-1))
    offsets = np.concatenate([[0], np.cumsum(want[0])]).astype(np.int32)
    keys = wp.zeros(2 * len(want[1]), dtype=wp.int64, device=wp_device)
    slots = wp.zeros(2 * len(want[1]), dtype=wp.int32, device=wp_device)
    gauss = wp.zeros(len(want[1]), dtype=wp.int32, device=wp_device)
    binning.launch_emit_pairs(sp, dp, rd, arr(offsets[:n], wp.int32), cam, keys, slots, gauss, len(want[1]),
                              wp_device, cache=cache)
    assert not np.array_equal(keys.numpy()[:len(want[1])], want[1])


@pytest.mark.parametrize("n,antialiased", [(1000, False), (5003, False), (700, True)])
def test_the_cpus_projection_blocks_compute_the_kernels_values(wp_device, n, antialiased):
    """On the CPU the projection and its backward run in C++ blocks of PROJECT_BLOCK Gaussians, 16 a vector: the same
    means2d, conics, depths, opacities, radii and blend records, and the same gradients (means, log-scales,
    quaternions, opacity logits, pose terms), bit for bit, as the thread-per-Gaussian Warp kernels (CUDA's path), on
    Gaussians behind the camera and beyond the far plane, off the image, faint (culled by opacity), with zero
    quaternions, and culled ones in the backward (whole groups of 16 off the image among them, which the blocks pass
    over: the forward by a bound on the screen extent, the backward by the radii); every block's status is 1. The
    antialiased mode is not in C++: its blocks decline (status 0) and give the kernels' values. The control (C++
    switched off): status 0, the same values."""
    from mgso_kernels.splat import project as proj
    from mgso_kernels.splat.common import vec6, vec8

    rng = np.random.default_rng(n)
    cam = make_camera(300.0, 310.0, 160.3, 119.6, 320, 240, se3_exp(rng.normal(size=6) * 0.3), near=0.05, far=50.0)
    means = (rng.normal(size=(n, 3)) * 2).astype(np.float32)
    means[:50] *= 30                                                    # beyond far, behind, far off the image
    ls = rng.normal(-2, 1.5, (n, 3)).astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    quats[:7] = 0.0
    ls[n - n // 10:] = rng.uniform(-8.0, -5.0, (n // 10, 1))           # tiny, round: the radius's floor
    logits = rng.normal(0, 4, n).astype(np.float32)                     # some below 1/255
    up = [rng.normal(size=(n, 2)).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32),
          rng.normal(size=n).astype(np.float32), rng.normal(size=n).astype(np.float32)]
    arr = lambda a, t=wp.float32: wp.array(a, dtype=t, device=wp_device)  # noqa: E731
    params = [arr(means), arr(ls), arr(quats), arr(logits), cam, 0.3, antialiased]

    def run(kind):
        fwd = [wp.zeros(n, dtype=wp.vec2, device=wp_device), wp.zeros(n, dtype=wp.vec3, device=wp_device),
               wp.zeros(n, dtype=float, device=wp_device), wp.zeros(n, dtype=float, device=wp_device),
               wp.zeros(n, dtype=wp.int32, device=wp_device), wp.zeros(n, dtype=vec8, device=wp_device)]
        bwd = [wp.zeros((n, 3), dtype=float, device=wp_device), wp.zeros((n, 3), dtype=float, device=wp_device),
               wp.zeros((n, 4), dtype=float, device=wp_device), wp.zeros(n, dtype=float, device=wp_device),
               wp.zeros(n, dtype=vec6, device=wp_device)]
        ups = [arr(up[0], wp.vec2), arr(up[1], wp.vec3), arr(up[2]), arr(up[3])]
        status = []
        if kind == "kernel":
            wp.launch(proj.project_gaussians, dim=n, inputs=[0, *params, *fwd], device=wp_device)
            wp.launch(proj.project_gaussians_backward, dim=n, inputs=[0, *params, fwd[4], *ups, *bwd],
                      device=wp_device)
        else:
            before = raster_tile.use_native(kind == "native")
            try:
                status.append(proj.launch_project(*params, *fwd, wp_device))
                status.append(proj.launch_project_backward(*params, fwd[4], *ups, *bwd, wp_device))
            finally:
                raster_tile.use_native(before)
        out = [a.numpy() for a in fwd + bwd]
        out[5] = out[5][out[4] > 0]                # the blend records are written for the visible only
        return out, [None if st is None else st.numpy() for st in status]

    want, _ = run("kernel")
    visible = int((want[4] > 0).sum())
    assert 0.1 * n < visible < 0.9 * n                                   # culls and visible ones both
    assert np.abs(want[6]).max() > 0 and np.isfinite(want[6]).all()
    got, status = run("native")
    for k, (w, g) in enumerate(zip(want, got)):
        np.testing.assert_array_equal(g, w, err_msg=str(k))
    if not str(wp_device).startswith("cpu"):
        return
    blocks = -(-n // proj.PROJECT_BLOCK)
    for st in status:
        assert len(st) == blocks and (st == (0 if antialiased else 1)).all()
    off, status = run("off")
    for k, (w, g) in enumerate(zip(want, off)):
        np.testing.assert_array_equal(g, w, err_msg=str(k))
    for st in status:
        assert (st == 0).all()


_LANE_CASES = [((53, 35), 400, True), ((96, 80), 900, False), ((16, 16), 60, True), ((70, 41), 1500, False)]


def _snippet_outputs(device, narrow_pixels: int = 0) -> dict:
    """Everything the C++ snippets compute on the lane cases' scenes (images, coverage, gradients), by name; the
    backward at the CPU's lanes whatever the image's size (``raster_bwd.NARROW_BACKWARD_PIXELS`` 0), or with
    ``narrow_pixels`` as that rule (above every case's size: the 8-lane backward)."""
    from mgso_kernels.splat import raster_bwd

    before = raster_bwd.NARROW_BACKWARD_PIXELS
    raster_bwd.NARROW_BACKWARD_PIXELS = narrow_pixels
    try:
        out = {}
        for c, (size, n, absgrad) in enumerate(_LANE_CASES):
            rng, scene, cam = _scene(20 + c, n, *size)
            w, h = size
            ups = [rng.normal(size=s).astype(np.float32) for s in ((h, w, 3), (h, w), (h, w))]
            cpp = _render(device, scene, cam, ups, absgrad, True)
            out.update({f"{c}_{k}": v for k, v in cpp.items()})
        return out
    finally:
        raster_bwd.NARROW_BACKWARD_PIXELS = before


@pytest.mark.parametrize("masks", ["1", "0"])
def test_the_snippets_16_lanes_equal_their_8_lanes_bit_for_bit(wp_device, tmp_path, masks):
    # Where the CPU has AVX-512 the snippets blend a whole tile row (16 pixels) a vector instead of half of one:
    # each pixel's arithmetic and the order of every lane's sums are those of the 8 lanes, so the images, coverage,
    # n_contrib and gradients are equal bit for bit. The 8 lanes run in a second process (MGSO_TILE_LANES=8 is read
    # at import); both processes report the width they compiled at, so the comparison is between two code paths.
    # The lanes' decisions (which pixels take a Gaussian, which stop) are AVX-512 mask registers here and, with
    # MGSO_TILE_MASKS=0 in the second process, 0/1 float lanes as on a CPU without AVX-512: the same bits again (each
    # process reports which it compiled).
    import os
    import subprocess
    import sys

    if not wp.get_device(wp_device).is_cpu:
        pytest.skip("the C++ snippets run on the CPU only")
    lanes = raster_tile.native_lanes(wp_device)
    if lanes != 16:
        pytest.skip(f"this CPU compiles the snippets at {lanes} lanes only (no AVX-512)")
    dump = tmp_path / "lanes8.npz"
    env = dict(os.environ, MGSO_TILE_LANES="8", MGSO_TILE_MASKS=masks)
    proc = subprocess.run([sys.executable, __file__, str(dump)], env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    narrow = dict(np.load(dump))
    assert int(narrow.pop("lanes")) == 8
    assert raster_tile.native_masks(wp_device)
    assert bool(narrow.pop("masks")) == (masks == "1")
    wide = _snippet_outputs(wp_device)
    assert sorted(wide) == sorted(narrow)
    for key, value in wide.items():
        if key.split("_", 1)[1].startswith("status"):
            assert (value == 1).all() and (narrow[key] == 1).all(), key
        else:
            assert np.array_equal(value, narrow[key]), key


def test_small_images_take_the_8_lane_backward_with_the_same_gradients(wp_device, monkeypatch):
    """On the CPU an image of at most ``NARROW_BACKWARD_PIXELS`` takes the backward tile snippet at 8 lanes (faster
    there: docs/rasteriser.md), compiled beside the 16-lane one in this process: the same gradients bit for bit on
    the lane cases, every tile done by the snippet; the rule picks the narrow kernel at the threshold and the wide
    one a pixel above it (the control)."""
    from mgso_kernels.splat import raster_bwd

    if not wp.get_device(wp_device).is_cpu:
        pytest.skip("the C++ snippets run on the CPU only")
    wide = _snippet_outputs(wp_device, narrow_pixels=0)
    narrow = _snippet_outputs(wp_device, narrow_pixels=10**9)
    for key, value in wide.items():
        if key.split("_", 1)[1].startswith("status"):
            assert (value == 1).all() and (narrow[key] == 1).all(), key
        else:
            assert np.array_equal(value, narrow[key]), key
    # the rule: which kernel launch_rasterize_backward hands to launch_split
    from mgso_kernels import runtime

    taken = []
    real = runtime.launch_split
    monkeypatch.setattr(runtime, "launch_split", lambda kernel, *a, **k: taken.append(kernel) or real(kernel, *a, **k))
    rng, scene, cam = _scene(30, 200, 53, 35)
    ups = [rng.normal(size=s).astype(np.float32) for s in ((35, 53, 3), (35, 53), (35, 53))]
    rast = Rasterizer(wp_device)
    for limit in (53 * 35, 53 * 35 - 1):
        monkeypatch.setattr(raster_bwd, "NARROW_BACKWARD_PIXELS", limit)
        for absgrad in (True, False):
            taken.clear()
            rast.backward(rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3)), *ups, absgrad=absgrad)
            tiles = [k for k in taken if k.key.endswith("rasterize_backward_tile")]
            small = limit == 53 * 35
            want = ((raster_tile.rasterize_backward_tile_narrow if small else raster_tile.rasterize_backward_tile)
                    if absgrad else (raster_tile.rasterize_backward_tile_noabs_narrow if small
                                     else raster_tile.rasterize_backward_tile_noabs))
            assert tiles == [want], (limit, absgrad, [k.key for k in tiles])


def test_the_8_lane_backward_threshold_by_maker_and_environment(monkeypatch):
    """NARROW_BACKWARD_PIXELS: ``$MGSO_NARROW_BACKWARD_PIXELS`` where set (0 allowed: never 8 lanes), a clear error for
    a value that is not a number of pixels, else 0 on AMD and 40,000 elsewhere (as measured: docs/rasteriser.md)."""
    from mgso_kernels.splat import raster_bwd

    monkeypatch.setenv("MGSO_NARROW_BACKWARD_PIXELS", "1234")
    assert raster_bwd._narrow_backward_pixels() == 1234
    monkeypatch.setenv("MGSO_NARROW_BACKWARD_PIXELS", "0")
    assert raster_bwd._narrow_backward_pixels() == 0
    for bad in ("many", "-5"):
        monkeypatch.setenv("MGSO_NARROW_BACKWARD_PIXELS", bad)
        with pytest.raises(ValueError, match="MGSO_NARROW_BACKWARD_PIXELS"):
            raster_bwd._narrow_backward_pixels()
    monkeypatch.delenv("MGSO_NARROW_BACKWARD_PIXELS")
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            amd = any(line.startswith("vendor_id") and "AMD" in line for line in f)
    except OSError:
        pytest.skip("no /proc/cpuinfo to say the CPU's maker")
    assert raster_bwd._narrow_backward_pixels() == (0 if amd else 40_000)


def test_the_forward_snippet_declines_images_that_are_not_contiguous(wp_device):
    """The forward snippet writes its outputs through plain pointers, so images that are views of wider ones (rows
    not one after the other) make it decline (status 0) and the Warp code write them: the same images as the Warp
    code into contiguous ones, bit for bit. The control: into contiguous images the snippet does every tile."""
    from mgso_kernels.splat import raster as _raster

    _, scene, cam = _scene(5, 300, 53, 35)
    h, w = 35, 53
    dim = cam.tiles_x * cam.tiles_y

    def blend(native: bool, pad: int):
        before = raster_tile.use_native(native)
        try:
            rast = Rasterizer(wp_device)
            out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3))
            wide = [wp.zeros((h, w + pad, 3), dtype=wp.float32, device=wp_device)]
            wide += [wp.zeros((h, w + pad), dtype=wp.float32, device=wp_device) for _ in range(3)]
            wide += [wp.zeros((h, w + pad), dtype=wp.int32, device=wp_device)]
            views = [a[:, :w] for a in wide]
            _raster.launch_rasterize_forward(cam, rast.ranges_.full, rast.splats_.full, rast.splat_rgbz_.full,
                                             (0.1, 0.2, 0.3), *views, wp_device, seg=rast.pixels_per_thread)
            status = raster_tile.status_buffer(dim, wp_device).numpy().copy()
            images = [a.numpy()[:, :w].copy() for a in wide]
            reference = [getattr(out, k).numpy().copy() for k in ("rgb", "depth", "alpha", "T_final", "n_contrib")]
        finally:
            raster_tile.use_native(before)
        return status, images, reference

    status, images, _ = blend(True, 7)
    assert not status.any()
    _, _, warp_code = blend(False, 0)
    for got, want in zip(images, warp_code):
        assert np.abs(want).max() > 0
        np.testing.assert_array_equal(got, want)
    status, images, cpp = blend(True, 0)
    assert (status == (1 if wp.get_device(wp_device).is_cpu else 0)).all()
    for got, want in zip(images, cpp):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("native", [True, False])
def test_a_colour_only_render_gives_the_full_renders_colours(wp_device, native):
    """``forward(..., rgb_only=True)`` (the evaluation's and the viewer's renders) blends without the depth and the
    last list position: the same colours bit for bit as the full forward, with the C++ snippet (every tile done by it
    on the CPU) and with the Warp code (the control, native off); no depth, alpha, T_final or n_contrib where a whole
    tile is a thread, and a backward of it is refused with a clear error."""
    _, scene, cam = _scene(7, 400, 53, 35)
    dim = cam.tiles_x * cam.tiles_y
    before = raster_tile.use_native(native)
    try:
        rast = Rasterizer(wp_device)
        full = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3)).rgb.numpy().copy()
        out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3), rgb_only=True)
        status = raster_tile.status_buffer(dim, wp_device).numpy().copy()
        rgb = out.rgb.numpy().copy()
    finally:
        raster_tile.use_native(before)
    assert np.abs(full - (0.1, 0.2, 0.3)).max() > 0.1
    np.testing.assert_array_equal(rgb, full)
    if rast.pixels_per_thread == 256:
        assert (status == (1 if native and wp.get_device(wp_device).is_cpu else 0)).all()
        assert out.depth is None and out.alpha is None and out.T_final is None and out.n_contrib is None
        with pytest.raises(ValueError, match="rgb_only"):
            rast.backward(out, np.zeros((35, 53, 3), np.float32))


if __name__ == "__main__":   # the 8-lane half of test_the_snippets_16_lanes_equal_their_8_lanes_bit_for_bit
    import sys

    from mgso_kernels import runtime

    device = runtime.init("cpu")
    np.savez(sys.argv[1], lanes=raster_tile.native_lanes(device), masks=raster_tile.native_masks(device),
             **_snippet_outputs(device))
