"""Backward pass: the twin's analytic gradients against central differences (cut-offs off), and the Warp backward
against the twin's analytic gradients under random upstream gradients (cut-offs on, gsplat's test_basic habit)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from mgso.geometry import se3_exp
from mgso_kernels import adam as kadam
from mgso_kernels.reference import splat as ref
from mgso_kernels.splat import Rasterizer, make_camera

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")
GRAD_OF = {"means": "v_means", "log_scales": "v_log_scales", "quats": "v_quats",
           "opacity_logits": "v_opacity_logits", "sh": "v_sh"}


def _camera(rng, width, height, f=40.0):
    return ref.RefCamera(fx=f, fy=f * 0.95, cx=width / 2 + 0.3, cy=height / 2 - 0.6, width=width, height=height,
                         world_to_cam=se3_exp(rng.normal(size=6) * 0.2))


def _wcam(c):
    return make_camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.world_to_cam, near=c.near, far=c.far)


def _upstream(rng, cam, which):
    H, W = cam.height, cam.width
    v_rgb = rng.normal(size=(H, W, 3)) if "rgb" in which else np.zeros((H, W, 3))
    v_depth = rng.normal(size=(H, W)) if "depth" in which else None
    v_alpha = rng.normal(size=(H, W)) if "alpha" in which else None
    return v_rgb, v_depth, v_alpha


def _loss(scene, cam, bg, ups, degree, antialiased=False):
    out = ref.render(*(scene[k] for k in PARAMS), cam, bg, degree, cutoffs=False, antialiased=antialiased)
    v_rgb, v_depth, v_alpha = ups
    total = np.sum(out["rgb"] * v_rgb)
    if v_depth is not None:
        total += np.sum(out["depth"] * v_depth)
    if v_alpha is not None:
        total += np.sum(out["alpha"] * v_alpha)
    return total


@pytest.mark.parametrize("degree,seed,aa", [(0, 0, False), (1, 1, False), (3, 2, False), (1, 5, True)])
def test_twin_gradients_match_finite_differences(degree, seed, aa):
    rng = np.random.default_rng(seed)
    cam = _camera(rng, 20, 16)
    scene = ref.random_scene(rng, 8, cam, degree, px_range=(1.0, 4.0))
    bg = np.array([0.3, 0.1, 0.6])
    ups = _upstream(rng, cam, ("rgb", "depth", "alpha"))
    g = ref.render_vjp(*(scene[k] for k in PARAMS), cam, bg, *ups, sh_degree=degree, cutoffs=False, antialiased=aa)
    eps = 1e-6
    for name in PARAMS:
        x = scene[name]
        fd = np.zeros_like(x)
        for idx in np.ndindex(x.shape):
            hi, lo = dict(scene), dict(scene)
            hi[name] = x.copy()
            hi[name][idx] += eps
            lo[name] = x.copy()
            lo[name][idx] -= eps
            fd[idx] = (_loss(hi, cam, bg, ups, degree, aa) - _loss(lo, cam, bg, ups, degree, aa)) / (2 * eps)
        an = g[GRAD_OF[name]]
        assert np.abs(fd).max() > 1e-3, name  # something depends on it
        np.testing.assert_allclose(an, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max(), err_msg=name)
    # pose: world_to_cam <- exp(delta) world_to_cam, delta = (v, w)
    fd = np.zeros(6)
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        hi = dataclasses.replace(cam, world_to_cam=se3_exp(d) @ cam.world_to_cam)
        lo = dataclasses.replace(cam, world_to_cam=se3_exp(-d) @ cam.world_to_cam)
        fd[k] = (_loss(scene, hi, bg, ups, degree, aa) - _loss(scene, lo, bg, ups, degree, aa)) / (2 * eps)
    np.testing.assert_allclose(g["v_pose"], fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_twin_gradients_with_cutoffs_match_finite_differences():
    # with the cut-offs on the image jumps where a Gaussian crosses 1/255 or a pixel's early stop moves; a tiny
    # step (1e-7, float64) crosses none of those here, so this checks how the analytic backward treats the 0.99
    # clamp, the skips and the early stop (the scene must exercise them)
    rng = np.random.default_rng(4)
    cam = _camera(rng, 16, 12)
    scene = ref.random_scene(rng, 14, cam, 0, px_range=(1.5, 4.0), hard_cases=False)
    scene["opacity_logits"][:7] = 6.0  # opacity 0.9975: alpha clamps at 0.99 near the centres
    bg = np.array([0.3, 0.1, 0.6])
    ups = _upstream(rng, cam, ("rgb", "depth", "alpha"))
    fw = ref.render(*(scene[k] for k in PARAMS), cam, bg, 0)
    assert (~fw["unclamped"]).any()  # clamped somewhere
    assert (fw["T_final"] < 1e-3).any()  # some pixels stopped early
    g = ref.render_vjp(*(scene[k] for k in PARAMS), cam, bg, *ups, sh_degree=0)

    def loss(sc):
        out = ref.render(*(sc[k] for k in PARAMS), cam, bg, 0)
        return np.sum(out["rgb"] * ups[0]) + np.sum(out["depth"] * ups[1]) + np.sum(out["alpha"] * ups[2])

    eps = 1e-7
    for name in PARAMS:
        x = scene[name]
        fd = np.zeros_like(x)
        for idx in np.ndindex(x.shape):
            hi, lo = dict(scene), dict(scene)
            hi[name], lo[name] = x.copy(), x.copy()
            hi[name][idx] += eps
            lo[name][idx] -= eps
            fd[idx] = (loss(hi) - loss(lo)) / (2 * eps)
        np.testing.assert_allclose(g[GRAD_OF[name]], fd, rtol=1e-4, atol=1e-5 * np.abs(fd).max(), err_msg=name)


def test_twin_cutoffs_switch_changes_the_image():
    # the switch must really remove the cut-offs (else the FD test above would test the jumpy function)
    rng = np.random.default_rng(9)
    cam = _camera(rng, 24, 20)
    scene = ref.random_scene(rng, 30, cam, 0)
    on = ref.render(*(scene[k] for k in PARAMS), cam, (0, 0, 0), cutoffs=True)
    off = ref.render(*(scene[k] for k in PARAMS), cam, (0, 0, 0), cutoffs=False)
    assert np.abs(on["rgb"] - off["rgb"]).max() > 1e-3


def _close(a, b, name, tol=5e-3):
    scale = max(np.abs(b).max(), 1e-8)
    np.testing.assert_allclose(a, b, rtol=tol, atol=tol * scale, err_msg=name)


@pytest.mark.parametrize("which,degree,seed", [(("rgb",), 0, 10), (("depth",), 0, 11), (("alpha",), 0, 12),
                                               (("rgb", "depth", "alpha"), 1, 13), (("rgb",), 3, 14)])
def test_warp_backward_matches_twin(wp_device, which, degree, seed):
    rng = np.random.default_rng(seed)
    cam = _camera(rng, 48, 40)
    scene = ref.random_scene(rng, 45, cam, degree)
    bg = (0.2, 0.5, 0.1)
    v_rgb, v_depth, v_alpha = _upstream(rng, cam, which)
    rast = Rasterizer(wp_device)
    out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam), bg)
    grads = rast.backward(out, v_rgb.astype(np.float32),
                          None if v_depth is None else v_depth.astype(np.float32),
                          None if v_alpha is None else v_alpha.astype(np.float32))
    r = ref.render_vjp(*(scene[k] for k in PARAMS), cam, bg, v_rgb, v_depth, v_alpha, sh_degree=degree)
    for name in ("v_means", "v_log_scales", "v_quats", "v_opacity_logits", "v_sh", "v_pose", "v_means2d", "absgrad",
                 "weights"):
        a = getattr(grads, name).numpy()
        assert a.shape == r[name].shape, name
        assert np.abs(r[name]).max() > 0 or name == "v_sh" and "rgb" not in which, name
        _close(a, r[name], name)


def test_warp_antialiased_matches_twin(wp_device):
    rng = np.random.default_rng(15)
    cam = _camera(rng, 48, 40)
    scene = ref.random_scene(rng, 45, cam, 1)
    bg = (0.2, 0.5, 0.1)
    v_rgb, v_depth, v_alpha = _upstream(rng, cam, ("rgb", "depth", "alpha"))
    rast = Rasterizer(wp_device, antialiased=True)
    out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam), bg)
    r = ref.render_vjp(*(scene[k] for k in PARAMS), cam, bg, v_rgb, v_depth, v_alpha, antialiased=True)
    plain = ref.render(*(scene[k] for k in PARAMS), cam, bg)
    assert np.abs(plain["rgb"] - r["forward"]["rgb"]).max() > 1e-2  # the compensation changes the image
    for key in ("rgb", "depth", "alpha"):
        _close(getattr(out, key).numpy(), r["forward"][key], key, tol=1e-4)
    grads = rast.backward(out, v_rgb.astype(np.float32), v_depth.astype(np.float32), v_alpha.astype(np.float32))
    for name in ("v_means", "v_log_scales", "v_quats", "v_opacity_logits", "v_sh", "v_pose", "v_means2d"):
        _close(getattr(grads, name).numpy(), r[name], name)


@pytest.mark.parametrize("seg", [1, 2, 8, 16, 256])
def test_pixels_per_thread_variants_match_twin(wp_device, seg):
    # a tile per thread (256) is the CPU default; 1 is the CUDA default; 16 was the CPU row kernel: same rules, same
    # results; absgrad=False (the tile path's second compiled kernel) changes nothing but the AbsGS sums (zero)
    rng = np.random.default_rng(20 + seg)
    cam = _camera(rng, 40, 36)
    scene = ref.random_scene(rng, 40, cam, 1)
    bg = (0.3, 0.3, 0.3)
    v_rgb, v_depth, v_alpha = _upstream(rng, cam, ("rgb", "depth", "alpha"))
    rast = Rasterizer(wp_device, pixels_per_thread=seg, threads=3, min_chunk=64)
    out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam), bg)
    r = ref.render_vjp(*(scene[k] for k in PARAMS), cam, bg, v_rgb, v_depth, v_alpha)
    for key in ("rgb", "depth", "alpha"):
        _close(getattr(out, key).numpy(), r["forward"][key], key, tol=1e-4)
    alpha_only = rast.render_alpha(*(scene[k] for k in PARAMS[:4]), _wcam(cam)).alpha.numpy().copy()
    out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam), bg)  # render_alpha invalidated the first one
    assert np.array_equal(alpha_only, out.alpha.numpy())
    grads = rast.backward(out, v_rgb.astype(np.float32), v_depth.astype(np.float32), v_alpha.astype(np.float32))
    for name in ("v_means", "v_log_scales", "v_quats", "v_opacity_logits", "v_sh", "v_pose", "v_means2d", "absgrad",
                 "weights"):
        _close(getattr(grads, name).numpy(), r[name], name)
    assert np.abs(r["absgrad"]).max() > 0 and r["weights"].max() > 0
    out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam), bg)
    grads = rast.backward(out, v_rgb.astype(np.float32), v_depth.astype(np.float32), v_alpha.astype(np.float32),
                          absgrad=False)
    for name in ("v_means", "v_log_scales", "v_quats", "v_opacity_logits", "v_sh", "v_pose", "v_means2d"):
        _close(getattr(grads, name).numpy(), r[name], name)
    assert not grads.absgrad.numpy().any()
    with pytest.raises(ValueError, match="pixels_per_thread"):
        Rasterizer(wp_device, pixels_per_thread=3)


def test_split_backward_is_bitwise_identical(wp_device):
    if not wp.get_device(wp_device).is_cpu:
        pytest.skip("splitting only applies to CPU launches")
    rng = np.random.default_rng(21)
    cam = _camera(rng, 80, 56)
    scene = ref.random_scene(rng, 300, cam, 1)
    ups = [u.astype(np.float32) for u in _upstream(rng, cam, ("rgb", "depth", "alpha"))]
    res = []
    for kw in ({"threads": 1}, {"threads": 3, "min_chunk": 16}):
        rast = Rasterizer(wp_device, **kw)
        out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam))
        g = rast.backward(out, *ups)
        res.append({f.name: getattr(g, f.name).numpy().copy() for f in dataclasses.fields(g)})
    for name, a in res[0].items():
        assert np.array_equal(a, res[1][name]), name


def _layered_scene(front_layers: int):
    """A small Gaussian behind ``front_layers`` large opaque ones (each covering the 32x32 view), and a small one
    in front of them, all centred on the view's axis (world = camera frame). Rows: the hidden one, the front one,
    then the layers."""
    z = [3.0, 0.5] + [1.0 + 0.1 * k for k in range(front_layers)]
    scale = [0.01, 0.005] + [5.0] * front_layers
    logit = [2.0, 2.0] + [np.log(19.0)] * front_layers      # opacity 0.95
    n = len(z)
    return {"means": np.array([[0.0, 0.0, zz] for zz in z]), "log_scales": np.log(np.repeat(np.array(scale)[:, None],
                                                                                             3, 1)),
            "quats": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), "opacity_logits": np.array(logit),
            "sh": np.full((n, 1, 3), 0.4)}


@pytest.mark.parametrize("layers", [4, 0])
def test_a_gaussian_hidden_in_every_pixel_has_no_blending_weight(wp_device, layers):
    # behind four layers of opacity 0.95 (the transmittance 0.05^3 after three, the fourth's 6e-6 below 1e-4, where a
    # pixel's blend stops) the small
    # Gaussian is in view (its radius > 0) but takes part in no pixel: its blending weight is exactly zero, and the
    # stats keep a zero weight for it (the control without the layers blends it: the twin's weight)
    cam = ref.RefCamera(fx=30.0, fy=30.0, cx=16.0, cy=16.0, width=32, height=32, world_to_cam=np.eye(4))
    scene = _layered_scene(layers)
    n = len(scene["means"])
    rast = Rasterizer(wp_device)
    out = rast.forward(*(np.asarray(scene[k], np.float32) for k in PARAMS), _wcam(cam))
    v_rgb = np.random.default_rng(3).normal(size=(32, 32, 3)).astype(np.float32)
    g = rast.backward(out, v_rgb)
    w = g.weights.numpy()
    r = ref.render_vjp(*(scene[k] for k in PARAMS), cam, (0, 0, 0), v_rgb)
    _close(w, r["weights"], "weights")
    assert np.all(out.radii.numpy() > 0)
    assert w[1] > 0.5                               # the one in front: about its area in pixels x its opacity
    assert (w[0] == 0.0) == (layers > 0)
    stats = kadam.DensifyStats()
    for name, dt in (("grad2d_sum", wp.float32), ("absgrad2d_sum", wp.float32), ("vis_count", wp.int32),
                     ("max_radius_px", wp.float32), ("views_seen", wp.int32), ("weight_max", wp.float32)):
        setattr(stats, name, wp.zeros(n, dtype=dt, device=wp_device))
    kadam.accumulate_stats(stats, g.v_means2d.view(wp.vec2), g.radii, 32, 32, device=wp_device, weights=g.weights,
                           weight_scale=4.0)
    assert list(stats.vis_count.numpy()[:2]) == [1, 1]
    np.testing.assert_array_equal(stats.weight_max.numpy(), 4.0 * w)


def test_densify_stats_accumulate_over_views(wp_device):
    # the one statistics mechanism: the backward's v_means2d / absgrad / radii into the map's DensifyStats
    # (mgso_kernels.adam.accumulate_stats, what GaussianMap.accumulate_stats runs), in 3DGS's NDC units
    rng = np.random.default_rng(31)
    cams = [_camera(rng, 48, 32) for _ in range(2)]
    scene = ref.random_scene(rng, 60, cams[0], 0)
    n = 60
    rast = Rasterizer(wp_device)
    stats = kadam.DensifyStats()
    for name, dt in (("grad2d_sum", wp.float32), ("absgrad2d_sum", wp.float32), ("vis_count", wp.int32),
                     ("max_radius_px", wp.float32), ("views_seen", wp.int32), ("weight_max", wp.float32)):
        setattr(stats, name, wp.zeros(n, dtype=dt, device=wp_device))
    want_grad, want_abs, want_count = np.zeros(n), np.zeros(n), np.zeros(n, int)
    want_rad, want_weight = np.zeros(n), np.zeros(n)
    for cam in cams:
        v_rgb = rng.normal(size=(cam.height, cam.width, 3))
        out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam))
        g = rast.backward(out, v_rgb.astype(np.float32))
        kadam.accumulate_stats(stats, g.v_means2d.view(wp.vec2), g.radii, cam.width, cam.height,
                               g.absgrad.view(wp.vec2), device=wp_device, weights=g.weights, weight_scale=4.0)
        r = ref.render_vjp(*(scene[k] for k in PARAMS), cam, (0, 0, 0), v_rgb)
        radii = out.radii.numpy()
        vis = radii > 0
        s = np.array([cam.width / 2, cam.height / 2])
        want_grad += np.where(vis, np.linalg.norm(r["v_means2d"] * s, axis=1), 0)
        want_abs += np.where(vis, np.linalg.norm(r["absgrad"] * s, axis=1), 0)
        want_count += vis
        want_rad = np.maximum(want_rad, radii)
        want_weight = np.maximum(want_weight, np.where(vis, 4.0 * r["weights"], 0))
    assert want_count.max() == 2 and want_count.min() == 0
    np.testing.assert_array_equal(stats.vis_count.numpy(), want_count)
    np.testing.assert_array_equal(stats.views_seen.numpy(), want_count)
    np.testing.assert_array_equal(stats.max_radius_px.numpy(), want_rad)
    _close(stats.grad2d_sum.numpy(), want_grad, "grad2d")
    _close(stats.absgrad2d_sum.numpy(), want_abs, "absgrad2d")
    _close(stats.weight_max.numpy(), want_weight, "weight_max")
    assert np.all(stats.absgrad2d_sum.numpy() >= stats.grad2d_sum.numpy() - 1e-4)


def test_backward_into_given_arrays_is_identical(wp_device):
    # into=: the parameter gradients land in the caller's buffers (a Gaussian map's), bit for bit the same
    rng = np.random.default_rng(41)
    cam = _camera(rng, 40, 32)
    scene = ref.random_scene(rng, 50, cam, 1)
    v_rgb = rng.normal(size=(cam.height, cam.width, 3)).astype(np.float32)
    rast = Rasterizer(wp_device)
    out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam))
    g = rast.backward(out, v_rgb)
    want = {k: getattr(g, "v_" + k).numpy().copy() for k in PARAMS}
    n, k = scene["sh"].shape[:2]

    class Into:
        means = wp.full((n, 3), 7.0, dtype=wp.float32, device=wp_device)   # overwritten, not added to
        log_scales = wp.zeros((n, 3), dtype=wp.float32, device=wp_device)
        quats = wp.zeros((n, 4), dtype=wp.float32, device=wp_device)
        opacity_logits = wp.zeros(n, dtype=wp.float32, device=wp_device)
        sh = wp.zeros((n, k, 3), dtype=wp.float32, device=wp_device)

    out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam))
    g2 = rast.backward(out, v_rgb, into=Into)
    for name in PARAMS:
        got = getattr(Into, name).numpy()
        if wp.get_device(wp_device).is_cpu:      # CPU sums run in a fixed order: bitwise the same
            assert np.array_equal(got, want[name]), name
        else:                                    # CUDA atomics add in a varying order: equal to round-off
            np.testing.assert_allclose(got, want[name], rtol=1e-4, atol=1e-6 * np.abs(want[name]).max(), err_msg=name)
        assert getattr(g2, "v_" + name).ptr == getattr(Into, name).ptr
    Into.quats = wp.zeros((n, 3), dtype=wp.float32, device=wp_device)
    out = rast.forward(*(scene[k] for k in PARAMS), _wcam(cam))
    with pytest.raises(ValueError, match="into.quats"):
        rast.backward(out, v_rgb, into=Into)


def test_gather_blocks_equal_the_kernel_bit_for_bit():
    """The CPU's gather in C++ blocks sums each Gaussian's slots as the kernel does, bit for bit: Gaussians with no
    slot (culled), one slot, many; -0, NaN and inf among the pairs' gradients; a block boundary inside the range. The
    blocks ran (status 1); with use_native off the kernel's loop did (status 0: two different code paths compared)."""
    from mgso_kernels import runtime
    from mgso_kernels.splat import raster_bwd
    from mgso_kernels.splat.common import vec16

    rng = np.random.default_rng(4)
    n = 2 * raster_bwd.GATHER_BLOCK + 77
    touched = rng.integers(0, 9, n).astype(np.int32)
    touched[::5] = 0
    offsets = (np.cumsum(touched) - touched).astype(np.int32)
    m = int(touched.sum())
    grads = (rng.normal(size=(m, 16)) * 1e3 ** rng.integers(-2, 3, (m, 16))).astype(np.float32)
    grads[::37, 3] = -0.0
    grads[11, 5] = np.nan
    grads[12, 6] = np.inf
    out = []
    for native in (True, False):
        before = runtime.use_native(native)
        try:
            arrays = [wp.array(np.full((n, 2), 9.0, np.float32), dtype=wp.vec2, device="cpu"),
                      wp.array(np.full((n, 3), 9.0, np.float32), dtype=wp.vec3, device="cpu"),
                      wp.array(np.full(n, 9.0, np.float32), device="cpu"),
                      wp.array(np.full((n, 3), 9.0, np.float32), dtype=wp.vec3, device="cpu"),
                      wp.array(np.full(n, 9.0, np.float32), device="cpu"),
                      wp.array(np.full((n, 2), 9.0, np.float32), dtype=wp.vec2, device="cpu"),
                      wp.array(np.full(n, 9.0, np.float32), device="cpu")]
            status = raster_bwd.launch_gather_gaussian_grads(
                wp.array(offsets, device="cpu"), wp.array(touched, device="cpu"),
                wp.array(grads, dtype=vec16, device="cpu"), *arrays, "cpu")
            out.append(([a.numpy().reshape(n, -1) for a in arrays], status.numpy()))
        finally:
            runtime.use_native(before)
    (got, st), (want, st0) = out
    assert st.min() == 1 and st0.max() == 0
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))
    # and against NumPy: each Gaussian's slots summed in order
    k = int(np.argmax(touched > 3))
    acc = np.zeros(16, np.float32)
    for row in grads[offsets[k]:offsets[k] + touched[k]]:
        acc = acc + row
    np.testing.assert_array_equal(np.concatenate([a[k] for a in got]), acc[:13])
    assert np.all(np.concatenate([a[touched == 0] for a in got], axis=1) == 0)
