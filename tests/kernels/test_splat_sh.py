"""SH colour kernels against the twin (degrees 0-3, forward and backward), the twin's SH gradient against finite
differences, and the camera struct."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from mgso.geometry import se3_exp
from mgso_kernels.reference import splat as ref
from mgso_kernels.splat import make_camera
from mgso_kernels.splat import sh as wsh
from mgso_kernels.splat.common import vec6


def _setup(rng, n, degree, device):
    T = se3_exp(rng.normal(size=6) * 0.5)
    cam = make_camera(100.0, 100.0, 50.0, 40.0, 100, 80, T)
    K = (degree + 1) ** 2
    sh = rng.normal(size=(n, K, 3)) * 1.5  # large enough that some colours clamp at 0
    means = rng.normal(size=(n, 3)) * 2.0
    centre = -T[:3, :3].T @ T[:3, 3]
    return cam, T, sh, means, centre


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_forward_and_backward_match_twin(wp_device, degree):
    rng = np.random.default_rng(degree)
    n = 64
    cam, T, sh, means, centre = _setup(rng, n, degree, wp_device)
    radii = np.ones(n, np.int32)
    radii[::7] = 0  # culled: colour and gradients 0
    depths = rng.uniform(1, 5, n).astype(np.float32)
    d_sh = wp.array(sh.astype(np.float32), device=wp_device)
    d_means = wp.array(means.astype(np.float32), device=wp_device)
    d_radii = wp.array(radii, device=wp_device)
    rgbz = wp.zeros(n, dtype=wp.vec4, device=wp_device)
    wsh.launch_evaluate_sh(d_sh, d_means, (degree + 1) ** 2, cam, d_radii, wp.array(depths, device=wp_device), rgbz,
                           wp_device)
    want = ref.sh_to_rgb(sh, means, centre, degree)
    got = rgbz.numpy()
    vis = radii > 0
    assert np.any(want[vis] == 0.0) and np.any(want[vis] > 0.0)  # both sides of the clamp are exercised
    np.testing.assert_allclose(got[vis, :3], want[vis], atol=2e-6)
    np.testing.assert_array_equal(got[vis, 3], depths[vis])
    assert np.all(got[~vis] == 0)

    v_rgb = rng.normal(size=(n, 3))
    v_sh = wp.zeros_like(d_sh)
    v_means = wp.zeros((n, 3), dtype=wp.float32, device=wp_device)
    v_pose = wp.zeros(n, dtype=vec6, device=wp_device)
    wsh.launch_evaluate_sh_backward(d_sh, d_means, (degree + 1) ** 2, cam, d_radii,
                                    wp.array(v_rgb.astype(np.float32), dtype=wp.vec3, device=wp_device), v_sh,
                                    v_means, v_pose, wp_device)
    r_sh, r_means, r_centre = ref.sh_to_rgb_vjp(sh[vis], means[vis], centre, degree, v_rgb[vis])
    np.testing.assert_allclose(v_sh.numpy()[vis], r_sh, atol=2e-6)
    np.testing.assert_allclose(v_means.numpy()[vis], r_means, atol=2e-5 * max(1.0, np.abs(r_means).max()))
    assert np.all(v_sh.numpy()[~vis] == 0) and np.all(v_means.numpy()[~vis] == 0)
    # the camera centre moves by -R^T v under world_to_cam <- exp(delta) world_to_cam: v_pose[:3] = -R v_centre
    pose = v_pose.numpy().sum(0)
    np.testing.assert_allclose(pose[:3], -T[:3, :3] @ r_centre, atol=1e-4 * max(1.0, np.abs(r_centre).max()))
    assert np.all(pose[3:] == 0)
    if degree == 0:
        assert np.all(v_means.numpy() == 0) and np.all(pose == 0)


def test_lower_sh_degree_uses_leading_coefficients(wp_device):
    rng = np.random.default_rng(7)
    n = 16
    cam, T, sh, means, centre = _setup(rng, n, 3, wp_device)
    d_sh = wp.array(sh.astype(np.float32), device=wp_device)
    d_means = wp.array(means.astype(np.float32), device=wp_device)
    ones = wp.array(np.ones(n, np.int32), device=wp_device)
    rgbz = wp.zeros(n, dtype=wp.vec4, device=wp_device)
    wsh.launch_evaluate_sh(d_sh, d_means, 4, cam, ones, wp.zeros(n, dtype=float, device=wp_device), rgbz, wp_device)
    np.testing.assert_allclose(rgbz.numpy()[:, :3], ref.sh_to_rgb(sh[:, :4], means, centre, 1), atol=2e-6)
    v_sh = wp.zeros_like(d_sh)
    wsh.launch_evaluate_sh_backward(d_sh, d_means, 4, cam, ones, wp.array(np.ones((n, 3), np.float32),
                                    dtype=wp.vec3, device=wp_device), v_sh,
                                    wp.zeros((n, 3), dtype=float, device=wp_device),
                                    wp.zeros(n, dtype=vec6, device=wp_device), wp_device)
    assert np.all(v_sh.numpy()[:, 4:] == 0) and np.any(v_sh.numpy()[:, 1:4] != 0)
    with pytest.raises(TypeError, match="radii: expected a Warp array"):
        wsh.launch_evaluate_sh(d_sh, d_means, 4, cam, np.ones(n, np.int32), wp.zeros(n, dtype=float,
                               device=wp_device), rgbz, wp_device)
    with pytest.raises(ValueError, match=r"rgbz: expected shape \(16,\)"):
        wsh.launch_evaluate_sh(d_sh, d_means, 4, cam, ones, wp.zeros(n, dtype=float, device=wp_device), rgbz[:8],
                               wp_device)
    with pytest.raises(ValueError, match="degree"):
        wsh.launch_evaluate_sh(d_sh, d_means, 5, cam, ones, wp.zeros(n, dtype=float, device=wp_device), rgbz,
                               wp_device)


def _sh_both_ways(sh, means, radii, depths, v_rgb, num_bases, cam):
    """Forward and backward on the CPU with the C++ blocks and with the Warp kernels' code (runtime.use_native off):
    each way's outputs and the blocks' statuses."""
    from mgso_kernels import runtime

    out = []
    for native in (True, False):
        before = runtime.use_native(native)
        try:
            n, K = sh.shape[0], sh.shape[1]
            d_sh, d_means = wp.array(sh, device="cpu"), wp.array(means, device="cpu")
            d_radii = wp.array(radii, device="cpu")
            rgbz = wp.array(np.full((n, 4), 9.0, np.float32), dtype=wp.vec4, device="cpu")   # all overwritten
            st_f = wsh.launch_evaluate_sh(d_sh, d_means, num_bases, cam, d_radii, wp.array(depths, device="cpu"),
                                          rgbz, "cpu")
            v_sh = wp.array(np.full((n, K, 3), 9.0, np.float32), device="cpu")
            v_means = wp.array(np.full((n, 3), 0.25, np.float32), device="cpu")
            v_pose = wp.array(np.full((n, 6), 0.5, np.float32), dtype=vec6, device="cpu")
            st_b = wsh.launch_evaluate_sh_backward(d_sh, d_means, num_bases, cam, d_radii,
                                                   wp.array(v_rgb, dtype=wp.vec3, device="cpu"), v_sh, v_means,
                                                   v_pose, "cpu")
            out.append(([rgbz.numpy(), v_sh.numpy(), v_means.numpy(), v_pose.numpy()],
                        st_f.numpy(), st_b.numpy()))
        finally:
            runtime.use_native(before)
    return out


@pytest.mark.parametrize("K", [1, 4])
def test_sh_degree0_blocks_equal_the_kernels_bit_for_bit(K):
    """The CPU's C++ blocks at degree 0 (num_bases 1; K 4: a map that will raise its degree later) write what the
    Warp kernels write, bit for bit: culled Gaussians, colours clamped at 0 (and one exactly at 0), NaN coefficients,
    a -0 upstream gradient, the trailing coefficients' zeros; a block boundary falls inside the range. The blocks ran
    (status 1); with use_native off they did not (status 0: the control compares two different code paths)."""
    rng = np.random.default_rng(K)
    n = 2 * wsh.SH_BLOCK + 37
    cam, _, sh, means, _ = _setup(rng, n, 0, "cpu")
    sh = np.concatenate([sh, rng.normal(size=(n, K - 1, 3))], axis=1).astype(np.float32)
    sh[::97, 0, 1] = np.nan
    sh[5, 0, 2] = np.float32(-0.5) / np.float32(wsh.SH_C0)    # a colour at (or within a rounding of) 0
    sh[6, 0, :] = -10.0                                         # clamped
    means = means.astype(np.float32)
    radii = (rng.random(n) > 0.3).astype(np.int32)
    depths = rng.uniform(1, 5, n).astype(np.float32)
    v_rgb = rng.normal(size=(n, 3)).astype(np.float32)
    v_rgb[7] = -0.0
    (native, st_f, st_b), (warp_code, st_f0, st_b0) = _sh_both_ways(sh, means, radii, depths, v_rgb, 1, cam)
    assert st_f.min() == 1 and st_b.min() == 1 and st_f0.max() == 0 and st_b0.max() == 0
    for a, b in zip(native, warp_code):
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))
    rgb = native[0][:, :3]
    assert np.any(rgb[radii > 0] == 0) and np.all(rgb[radii == 0] == 0) and np.any(np.isnan(sh[radii > 0, 0]))
    assert np.all(native[1][:, 1:] == 0) and np.any(native[1][:, 0] != 0)
    assert np.all(native[2] == 0.25) and np.all(native[3] == 0.5)     # degree 0 adds nothing there


def test_sh_blocks_decline_above_degree0():
    """At degree 1 the blocks decline (status 0) and the Warp code writes (the test above's outputs for degree 0 are
    the blocks')."""
    rng = np.random.default_rng(3)
    n = 100
    cam, _, sh, means, _ = _setup(rng, n, 1, "cpu")
    (native, st_f, st_b), (warp_code, _, _) = _sh_both_ways(
        sh.astype(np.float32), means.astype(np.float32), np.ones(n, np.int32), np.ones(n, np.float32),
        rng.normal(size=(n, 3)).astype(np.float32), 4, cam)
    assert st_f.max() == 0 and st_b.max() == 0
    for a, b in zip(native, warp_code):
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))


def test_twin_sh_gradient_matches_finite_differences():
    rng = np.random.default_rng(3)
    n, degree = 6, 3
    sh = rng.normal(size=(n, 16, 3)) * 0.3
    means = rng.normal(size=(n, 3))
    centre = rng.normal(size=3) * 0.1
    v = rng.normal(size=(n, 3))
    g_sh, g_means, g_centre = ref.sh_to_rgb_vjp(sh, means, centre, degree, v)

    def f(sh_, means_, centre_):
        return np.sum(ref.sh_to_rgb(sh_, means_, centre_, degree) * v)

    eps = 1e-6
    for arr, grad, fn in ((sh, g_sh, lambda a: f(a, means, centre)), (means, g_means, lambda a: f(sh, a, centre)),
                          (centre, g_centre, lambda a: f(sh, means, a))):
        fd = np.zeros_like(arr)
        for idx in np.ndindex(arr.shape):
            hi, lo = arr.copy(), arr.copy()
            hi[idx] += eps
            lo[idx] -= eps
            fd[idx] = (fn(hi) - fn(lo)) / (2 * eps)
        np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-7)


def test_sh_basis_constants_are_the_real_sh_normalisation():
    # degree-l bases are orthonormal over the sphere: check the constants by Monte Carlo-free quadrature
    # (a 200 x 400 grid in (theta, phi) integrates these polynomials to ~1e-4)
    th = (np.arange(200) + 0.5) * np.pi / 200
    ph = (np.arange(400) + 0.5) * 2 * np.pi / 400
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    w = (np.sin(T) * (np.pi / 200) * (2 * np.pi / 400)).ravel()
    B = ref.sh_basis(d, 3)
    gram = (B * w[:, None]).T @ B
    np.testing.assert_allclose(gram, np.eye(16), atol=2e-3)


def test_camera_struct():
    T = se3_exp(np.array([0.1, -0.2, 0.3, 0.05, 0.1, -0.2]))
    cam = make_camera(500.0, 510.0, 320.0, 240.0, 640, 480, T)
    assert (cam.tiles_x, cam.tiles_y) == (40, 30)
    np.testing.assert_allclose(np.array(cam.centre), -T[:3, :3].T @ T[:3, 3], atol=1e-6)
    # 1.3x the half field of view when the principal point is centred
    assert math.isclose(cam.lim_x_pos, 1.3 * 320.0 / 500.0, rel_tol=1e-6)
    assert math.isclose(cam.lim_y_neg, 1.3 * 240.0 / 510.0, rel_tol=1e-6)
    # the tile visiting order is a permutation of all tiles
    n = cam.tiles_x * cam.tiles_y
    assert math.gcd(cam.tile_stride, n) == 1
    assert len({(s * cam.tile_stride) % n for s in range(n)}) == n
    with pytest.raises(ValueError, match="near < far"):
        make_camera(500.0, 500.0, 320.0, 240.0, 640, 480, T, near=2.0, far=1.0)
    with pytest.raises(ValueError, match="4x4 or 3x4"):
        make_camera(500.0, 500.0, 320.0, 240.0, 640, 480, np.eye(3))
