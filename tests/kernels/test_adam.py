"""Fused Adam, gather and densification statistics: Warp kernels against the NumPy twin."""

import numpy as np
import pytest
import warp as wp

from mgso_kernels import adam as wa
from mgso_kernels import runtime
from mgso_kernels.reference import adam as ra

RATES = dict(means=1.6e-4, log_scales=5e-3, quats=1e-3, opacity_logits=2.5e-2, sh_dc=2.5e-3, sh_rest=2.5e-3 / 20)


def _rand_group(rng, n, k, scale=1.0):
    return {"means": scale * rng.standard_normal((n, 3)), "log_scales": scale * rng.standard_normal((n, 3)),
            "quats": scale * rng.standard_normal((n, 4)), "opacity_logits": scale * rng.standard_normal(n),
            "sh": scale * rng.standard_normal((n, k, 3))}


def _to_wp(group, device):
    s = wa.GaussianParams()
    s.means = wp.array(group["means"].astype(np.float32), dtype=wp.vec3, device=device)
    s.log_scales = wp.array(group["log_scales"].astype(np.float32), dtype=wp.vec3, device=device)
    s.quats = wp.array(group["quats"].astype(np.float32), dtype=wp.vec4, device=device)
    s.opacity_logits = wp.array(group["opacity_logits"].astype(np.float32), dtype=wp.float32, device=device)
    s.sh = wp.array(group["sh"].astype(np.float32), dtype=wp.vec3, device=device)
    return s


def _from_wp(s):
    return {k: getattr(s, k).numpy().astype(np.float64) for k in ra.GROUPS}


@pytest.mark.parametrize("bias,sparse,use_visible", [
    (wa.BIAS_GLOBAL, False, False),       # torch.optim.Adam, as 3DGS
    (wa.BIAS_PER_GAUSSIAN, False, False),
    (wa.BIAS_GLOBAL, True, True),         # 3DGS SparseGaussianAdam / gsplat visible_adam
    (wa.BIAS_PER_GAUSSIAN, True, False),  # sparse by non-zero gradient
    (wa.BIAS_NONE, True, True),           # gsplat's fused kernel
])
def test_adam_matches_twin_over_steps(wp_device, rng, bias, sparse, use_visible):
    n, k = 257, 4
    p0 = _rand_group(rng, n, k)
    params, m, v = _to_wp(p0, wp_device), _to_wp(_rand_group(rng, n, k, 0.0), wp_device), \
        _to_wp(_rand_group(rng, n, k, 0.0), wp_device)
    steps0 = rng.integers(0, 5, n).astype(np.int32)   # rows added at different times
    steps = wp.array(steps0, dtype=wp.int32, device=wp_device)
    P = {kk: vv.astype(np.float32).astype(np.float64) for kk, vv in p0.items()}
    M = {kk: np.zeros_like(vv) for kk, vv in P.items()}
    V = {kk: np.zeros_like(vv) for kk, vv in P.items()}
    S = steps0.astype(np.int64)
    for it in range(1, 6):
        g = _rand_group(rng, n, k, 0.1)
        vis = rng.random(n) > 0.4
        if sparse and not use_visible:
            for kk in g:
                g[kk][~vis] = 0.0
        g32 = {kk: vv.astype(np.float32) for kk, vv in g.items()}
        grads = _to_wp(g32, wp_device)
        hp = wa.make_hyper(wa.AdamRates(**RATES), bias_correction=bias, global_step=it + 10, sparse=sparse,
                           use_visible=use_visible)
        wa.adam_step(params, grads, m, v, steps, hp,
                     visible=wp.array(vis.astype(np.uint8), dtype=wp.uint8, device=wp_device), device=wp_device)
        P, M, V, S = ra.adam_step_gaussians(P, g32, M, V, S, RATES, bias_correction=bias, global_step=it + 10,
                                            sparse=sparse, visible=vis if use_visible else None)
    got = _from_wp(params)
    for kk in ra.GROUPS:
        # float32 parameters round every update to their ulp: allow a few ulps per step plus 1e-4 of the total move
        moved = np.abs(P[kk] - p0[kk].astype(np.float32))
        tol = 5 * 2 * np.spacing(np.abs(P[kk]).astype(np.float32)) + 1e-4 * moved
        assert np.all(np.abs(got[kk] - P[kk]) <= tol), (kk, np.max(np.abs(got[kk] - P[kk]) - tol))
        assert np.any(moved > 0)
        np.testing.assert_allclose(_from_wp(m)[kk], M[kk], rtol=1e-5, atol=2e-8, err_msg=kk)  # float32 of g ~ 0.1
        np.testing.assert_allclose(_from_wp(v)[kk], V[kk], rtol=3e-5, atol=1e-12, err_msg=kk)  # 1 - 0.999 in float32: 1.3e-5
    assert np.array_equal(steps.numpy(), S)
    if sparse:
        assert np.any(S == steps0) and np.any(S > steps0)   # some rows were skipped, some updated


def test_per_gaussian_bias_correction_gives_a_fresh_start(wp_device, rng):
    """With per-Gaussian steps a late-added row's first move is lr * sign(g) (Adam's first step), whatever the
    global step; with a global step t = 5000 the same row moves lr * (1-b1)/sqrt(1-b2) * sqrt(1-b2^t) = 3.15 lr."""
    n, k = 8, 1
    params = _to_wp(_rand_group(rng, n, k), wp_device)
    before = _from_wp(params)
    zeros = lambda: _to_wp(_rand_group(rng, n, k, 0.0), wp_device)  # noqa: E731
    g = _rand_group(rng, n, k)
    for bias, expected in ((wa.BIAS_PER_GAUSSIAN, 1.0),
                           (wa.BIAS_GLOBAL, 0.1 / np.sqrt(0.001) * np.sqrt(1 - 0.999 ** 5000))):
        p = _to_wp(before, wp_device)
        hp = wa.make_hyper(wa.AdamRates(**RATES), bias_correction=bias, global_step=5000)
        wa.adam_step(p, _to_wp(g, wp_device), zeros(), zeros(), wp.zeros(n, dtype=wp.int32, device=wp_device), hp,
                     device=wp_device)
        moved = (before["means"] - _from_wp(p)["means"]) / (RATES["means"] * np.sign(g["means"]))
        np.testing.assert_allclose(moved, expected, rtol=1e-3)


def test_adam_array_matches_twin(wp_device, rng):
    n = 10
    p, m, v = rng.standard_normal(n).astype(np.float32), np.zeros(n, np.float32), np.zeros(n, np.float32)
    wpp, wm, wv = (wp.array(a, dtype=wp.float32, device=wp_device) for a in (p, m, v))
    P, M, V = p.astype(np.float64), m.astype(np.float64), v.astype(np.float64)
    for step in range(1, 5):
        g = rng.standard_normal(n).astype(np.float32)
        wa.adam_step_array(wpp, wp.array(g, device=wp_device), wm, wv, lr=0.01, step=step, device=wp_device)
        P, M, V = ra.adam_step_flat(P, g, M, V, 0.01, step)
    np.testing.assert_allclose(wpp.numpy(), P, rtol=1e-6, atol=1e-4 * 0.01)  # 1e-4 of the learning rate


def test_gather_matches_twin(wp_device, rng):
    n = 50
    index = rng.integers(0, n, 70).astype(np.int32)
    widx = wp.array(index, dtype=wp.int32, device=wp_device)
    for arr, dt in ((rng.standard_normal((n, 3)).astype(np.float32), wp.vec3),
                    (rng.standard_normal((n, 4)).astype(np.float32), wp.vec4),
                    (rng.integers(0, 100, n).astype(np.int32), wp.int32),
                    (rng.standard_normal(n).astype(np.float32), wp.float32),
                    (rng.standard_normal((n, 5, 3)).astype(np.float32), wp.vec3)):
        src = wp.array(arr, dtype=dt, device=wp_device)
        dst = wp.zeros((80,) + tuple(src.shape[1:]), dtype=dt, device=wp_device)
        wa.gather(src, widx, dst, device=wp_device)
        assert np.array_equal(dst.numpy()[:70], ra.gather_rows(arr, index))
        assert not np.any(dst.numpy()[70:])


def test_densify_stats_match_twin(wp_device, rng):
    n, W, H = 40, 64, 48
    stats_np = {"grad2d_sum": rng.random(n).astype(np.float32), "absgrad2d_sum": rng.random(n).astype(np.float32),
                "vis_count": rng.integers(0, 3, n).astype(np.int32), "max_radius_px": rng.random(n).astype(np.float32),
                "views_seen": rng.integers(0, 9, n).astype(np.int32),
                "weight_max": rng.random(n).astype(np.float32)}
    s = wa.DensifyStats()
    for kk, vv in stats_np.items():
        setattr(s, kk, wp.array(vv, device=wp_device))
    ref = stats_np
    for it in range(4):
        g = (1e-4 * rng.standard_normal((n, 2))).astype(np.float32)
        ga = np.abs(g) * 2
        radii = np.where(rng.random(n) > 0.3, rng.uniform(0.5, 30, n), 0.0).astype(np.float32)
        # blending weights summed over a view (zero for some rows: hidden), in pixels of a level-1 view
        # (the last view without: its visible rows' weight unknown, the largest float32)
        wsum = (rng.random(n) * 3 * (rng.random(n) > 0.3)).astype(np.float32) if it < 3 else None
        wa.accumulate_stats(s, wp.array(g, dtype=wp.vec2, device=wp_device), wp.array(radii, device=wp_device), W, H,
                            v_means2d_abs=wp.array(ga, dtype=wp.vec2, device=wp_device), device=wp_device,
                            weights=None if wsum is None else wp.array(wsum, device=wp_device), weight_scale=4.0)
        ref = ra.accumulate_densify_stats(ref, g, radii, W, H, ga, wsum, 4.0)
    for kk in ref:
        np.testing.assert_allclose(getattr(s, kk).numpy(), ref[kk], rtol=1e-6, err_msg=kk)


@pytest.mark.parametrize("bias,k,sparse", [(wa.BIAS_PER_GAUSSIAN, 1, False), (wa.BIAS_GLOBAL, 1, False),
                                           (wa.BIAS_NONE, 1, False), (wa.BIAS_PER_GAUSSIAN, 4, False),
                                           (wa.BIAS_PER_GAUSSIAN, 1, True)])
def test_the_cpus_adam_blocks_update_as_the_kernel_does(wp_device, rng, bias, k, sparse):
    """On the CPU the dense Adam of SH degree 0 (MGSO's) runs in C++ blocks of ADAM_BLOCK Gaussians (the bias
    corrections once per step count of a block, in a table of 64 by the count mod 64; each group 16 floats a vector):
    parameters, both moments and the step counts equal the Warp kernel's bit for bit over five steps, with runs of
    equal step counts broken at random rows and counts 64 apart in one slot (so cached corrections must be
    recomputed), three blocks and a part; every block's status is 1. SH above degree 0 and the sparse mode decline
    to the kernel's code (status 0), and the control with the C++ switched off (runtime.use_native(False), the
    switch of every C++ snippet) runs none."""
    n = 3 * wa.ADAM_BLOCK + 37
    p0 = _rand_group(rng, n, k)
    steps0 = np.repeat(rng.integers(0, 9, n // 20 + 1), 20)[:n].astype(np.int32)
    steps0[rng.random(n) < 0.05] += 1
    steps0[rng.random(n) < 0.1] += 64                   # the same slot of the block's table of 64 step counts
    grads = [_rand_group(rng, n, k, 0.1) for _ in range(5)]

    def run(native):
        params, m, v = (_to_wp(p0, wp_device), _to_wp(_rand_group(rng, n, k, 0.0), wp_device),
                        _to_wp(_rand_group(rng, n, k, 0.0), wp_device))
        steps = wp.array(steps0, dtype=wp.int32, device=wp_device)
        status = []
        before = runtime.use_native(native)
        try:
            for it, g in enumerate(grads):
                hp = wa.make_hyper(wa.AdamRates(**RATES), bias_correction=bias, global_step=it + 3, sparse=sparse)
                status.append(wa.adam_step(params, _to_wp(g, wp_device), m, v, steps, hp, device=wp_device))
        finally:
            runtime.use_native(before)
        out = [getattr(s, f).numpy() for s in (params, m, v) for f in ra.GROUPS] + [steps.numpy()]
        return out, status

    want, off = run(False)
    got, status = run(True)
    for w, g in zip(want, got):
        np.testing.assert_array_equal(g, w)
    assert np.any(want[0] != p0["means"].astype(np.float32))
    if str(wp_device).startswith("cpu"):
        blocks = -(-n // wa.ADAM_BLOCK)
        for st in status:
            assert len(st) == blocks and (st.numpy() == (1 if k == 1 and not sparse else 0)).all()
        for st in off:
            assert (st.numpy() == 0).all()
