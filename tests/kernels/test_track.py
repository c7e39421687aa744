"""Coarse-tracking residuals and the 8x8 reduction: kernel vs twin, exact float64 reduction, split launches."""

import cv2
import numpy as np
import pytest
import warp as wp

from mgso.geometry import make_pose, se3_exp, so3_exp
from mgso_kernels import photometric as ph
from mgso_kernels import track as tk
from mgso_kernels.reference import image as ref_img
from mgso_kernels.reference import photometric as ref_ph
from mgso_kernels.reference import track as ref

W, H = 160, 120
CAM = dict(fx=150.0, fy=150.0, cx=79.5, cy=59.5)


def texture(h, w, seed=0, sigma=2.5):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
    return (255.0 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)


def shifted(img, dx, dy=0.0):
    M = np.array([[1, 0, dx], [0, 1, dy]], dtype=np.float64)
    return cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


@pytest.fixture(scope="module")
def setup():
    img_h = texture(H, W, seed=21)
    img_t = shifted(img_h, 1.5, -0.7) + np.random.default_rng(3).normal(0, 3, (H, W)).astype(np.float32)
    img_t[40:60, 60:90] = 255.0  # an occluder: saturated residuals
    dI_h, _ = ref_img.gradients(img_h)
    dI_t, _ = ref_img.gradients(img_t.astype(np.float32))
    rng = np.random.default_rng(5)
    n = 2000
    uv = np.stack([rng.integers(0, W, n), rng.integers(0, H, n)], axis=1).astype(np.float32)
    idepth = rng.uniform(0.5, 1.5, n).astype(np.float32)
    return img_h, dI_h, dI_t, uv, idepth


def ref_colors(dI_h, uv, pattern):
    if pattern == 1:
        return ref_img.sample_dI(dI_h, uv[:, 0], uv[:, 1])[:, 0:1].astype(np.float32)
    x = uv[:, None, 0] + ph.PATTERN_NP[None, :, 0]
    y = uv[:, None, 1] + ph.PATTERN_NP[None, :, 1]
    return ref_img.sample_dI(dI_h, x, y)[..., 0].astype(np.float32)


@pytest.mark.parametrize("pattern", [1, 8])
def test_system_matches_twin(wp_device, setup, pattern):
    _, dI_h, dI_t, uv, idepth = setup
    col = ref_colors(dI_h, uv, pattern)
    T = make_pose(so3_exp([0.004, -0.006, 0.002]), [0.01, -0.004, 0.02])
    pair = ph.make_frame_pair(T, 0.05, 2.0, 0.1, -3.0)
    cam = ph.make_intrinsics(**CAM, width=W, height=H)
    ws = tk.TrackWorkspace(len(uv), pattern, wp_device)
    dI_tw = wp.array(dI_t, dtype=wp.vec3, device=wp_device)
    got = tk.track_system(uv, idepth, col, pair, cam, dI_tw, ws, flow_stride=7)
    want = ref.track_system(uv, idepth, col, ref_ph.Pair.from_pose(T, 0.05, 2.0, 0.1, -3.0),
                            ref_ph.Cam(**CAM, width=W, height=H), ref_ph.dI_sampler(dI_t), flow_stride=7)
    # a residual may flip across the image margin or the cutoff between fp32 and fp64: allow a couple
    st = ws.state.numpy()
    flips = int((st != want["state"]).sum())
    assert flips <= 2
    assert got.num_terms > 0.8 * pattern * len(uv) and got.num_saturated > 20 and want["num_saturated"] > 20
    assert abs(got.num_terms - want["num_terms"]) <= flips and abs(got.num_inliers - want["num_inliers"]) <= flips
    tol = 1e-4 + 2e-3 * flips
    assert np.abs(got.H - want["H"]).max() <= tol * np.abs(want["H"]).max()
    assert np.abs(got.b - want["b"]).max() <= tol * np.abs(want["b"]).max()
    assert got.energy == pytest.approx(want["energy"], rel=tol)
    assert got.flow_count == want["flow_count"] == 2 * len(range(0, len(uv), 7))
    assert got.flow_t_sum == pytest.approx(want["flow_t_sum"], rel=1e-4)
    assert got.flow_rt_sum == pytest.approx(want["flow_rt_sum"], rel=1e-4)
    same = st == want["state"]
    np.testing.assert_allclose(ws.residual.numpy()[same], want["residual"][same], atol=2e-3)
    np.testing.assert_allclose(ws.weight.numpy()[same], want["weight"][same], rtol=1e-4, atol=1e-6)
    assert np.allclose(got.H, got.H.T)
    assert got.saturated_ratio == pytest.approx(got.num_saturated / got.num_terms)


def test_reduction_is_exact_float64_sum_of_the_kernels_terms(wp_device, setup):
    _, dI_h, dI_t, uv, idepth = setup
    col = ref_colors(dI_h, uv, 8)
    T = make_pose(so3_exp([0.003, 0.002, -0.004]), [0.012, 0.0, -0.01])
    pair = ph.make_frame_pair(T)
    cam = ph.make_intrinsics(**CAM, width=W, height=H)
    ws = tk.TrackWorkspace(len(uv), 8, wp_device, store_jacobians=True)
    dI_tw = wp.array(dI_t, dtype=wp.vec3, device=wp_device)
    got = tk.track_system(uv, idepth, col, pair, cam, dI_tw, ws)
    J = ws.jacobian.numpy().astype(np.float64).reshape(-1, 8)
    Wt = ws.weight.numpy().astype(np.float64).ravel()
    r = ws.residual.numpy().astype(np.float64).ravel()
    inl = ws.state.numpy().ravel() == tk.TrackState.IN
    H64 = np.einsum("k,ki,kj->ij", Wt[inl], J[inl], J[inl])
    b64 = np.einsum("k,ki,k->i", Wt[inl], J[inl], r[inl])
    np.testing.assert_allclose(got.H, H64, rtol=1e-10, atol=1e-12 * np.abs(H64).max())
    np.testing.assert_allclose(got.b, b64, rtol=1e-10, atol=1e-12 * np.abs(b64).max())
    assert got.num_inliers == inl.sum() > 10000


@pytest.mark.parametrize("simd", [False, True])
def test_the_system_is_the_float64_sum_of_the_residuals_terms(wp_device, setup, simd):
    """The scalar kernel accumulates only the upper triangle of ``H`` (element by element); the system must be the
    float64 sum of the per-residual terms that a workspace storing Jacobians reports, symmetric, and the per-residual
    outputs must not depend on whether Jacobians are stored. The CPU's 8-point path (``simd``, DSO's tracker: one
    residual a point) forms each term in float32 and sums it in float64 lanes: the same system to float32 rounding
    of the products."""
    _, dI_h, dI_t, uv, idepth = setup
    uv, idepth = uv[:1995], idepth[:1995]  # the last block ends part-way (and so does its last 8-point group)
    col = ref_colors(dI_h, uv, 1)
    T = make_pose(so3_exp([0.003, 0.002, -0.004]), [0.012, 0.0, -0.01])
    pair = ph.make_frame_pair(T, 0.05, 2.0, 0.1, -3.0)
    cam = ph.make_intrinsics(**CAM, width=W, height=H)
    dI_tw = wp.array(dI_t, dtype=wp.vec3, device=wp_device)
    plain = tk.TrackWorkspace(len(uv), 1, wp_device, simd=simd)
    scalar = tk.TrackWorkspace(len(uv), 1, wp_device, store_jacobians=True)
    got = tk.track_system(uv, idepth, col, pair, cam, dI_tw, plain, flow_stride=7)
    ref_s = tk.track_system(uv, idepth, col, pair, cam, dI_tw, scalar, flow_stride=7)
    np.testing.assert_array_equal(plain.state.numpy(), scalar.state.numpy())
    for name in ("residual", "weight"):
        if simd:  # the same float32 arithmetic, vectorised: allow the compiler's contractions
            np.testing.assert_allclose(getattr(plain, name).numpy(), getattr(scalar, name).numpy(), rtol=1e-6,
                                       atol=1e-5, err_msg=name)
        else:
            np.testing.assert_array_equal(getattr(plain, name).numpy(), getattr(scalar, name).numpy(), err_msg=name)
    J = scalar.jacobian.numpy().astype(np.float64).reshape(-1, 8)
    Wt = scalar.weight.numpy().astype(np.float64).ravel()
    r = scalar.residual.numpy().astype(np.float64).ravel()
    inl = scalar.state.numpy().ravel() == tk.TrackState.IN
    assert 1000 < inl.sum() < len(uv)  # some residuals out of the system: they must add nothing
    H64 = np.einsum("k,ki,kj->ij", Wt[inl], J[inl], J[inl])
    b64 = np.einsum("k,ki,k->i", Wt[inl], J[inl], r[inl])
    # scalar: exact float64 sums. simd, measured on the 2-core x86-64 machine (2026-12-04): H 2.5e-9 of its largest
    # entry and 3.3e-8 of each entry, b 1.1e-9 and 3.4e-9
    (rh, sh), (rb, sb) = ((1e-10, 1e-12), (1e-10, 1e-12)) if not simd else ((1e-7, 7.5e-9), (1e-8, 3.5e-9))
    np.testing.assert_allclose(got.H, H64, rtol=rh, atol=sh * np.abs(H64).max())
    np.testing.assert_allclose(got.b, b64, rtol=rb, atol=sb * np.abs(b64).max())
    assert np.array_equal(got.H, got.H.T)
    assert (got.energy == pytest.approx(ref_s.energy, rel=1e-12)
            and got.num_terms == ref_s.num_terms and got.num_inliers == ref_s.num_inliers
            and got.num_saturated == ref_s.num_saturated)
    assert got.flow_count == ref_s.flow_count == 2 * len(range(0, len(uv), 7))
    assert got.flow_t_sum == pytest.approx(ref_s.flow_t_sum, rel=1e-12)
    assert got.flow_rt_sum == pytest.approx(ref_s.flow_rt_sum, rel=1e-12)


def test_the_cpu_8_point_path_handles_every_kind_of_point_as_the_scalar_loop(wp_device, setup):
    """The CPU's 8-point path against the scalar loop on points that are behind the camera, outside the image, at a
    NaN or infinite inverse depth, or far outside (a cell index that would overflow): the same states, residuals and
    weights, the same system to float32 rounding, and nothing non-finite in it (a masked lane adds 0, not 0 * inf).
    The GPU has only the scalar loop, where this is the identity."""
    _, dI_h, dI_t, uv, idepth = setup
    n = 803  # 25 blocks of 32 and 3 points: every block, and the last 8-point group, ends part-way
    uv, idepth = uv[:n].copy(), idepth[:n].copy()
    idepth[5::41] = -idepth[5::41]  # behind the camera once moved
    idepth[7::53] = np.nan
    idepth[9::59] = np.inf
    uv[11::61] = [1e9, -1e9]  # projects to a huge pixel: the cell must be clamped before int()
    col = ref_colors(dI_h, np.clip(uv, 0, [W - 1, H - 1]), 1)
    T = make_pose(so3_exp([0.01, 0.02, -0.004]), [0.3, 0.0, -0.2])
    pair = ph.make_frame_pair(T, 0.05, 2.0, 0.1, -3.0)
    cam = ph.make_intrinsics(**CAM, width=W, height=H)
    dI_tw = wp.array(dI_t, dtype=wp.vec3, device=wp_device)
    out = {}
    for simd in (False, True):
        ws = tk.TrackWorkspace(n, 1, wp_device, simd=simd, points_per_block=32)
        out[simd] = (tk.track_system(uv, idepth, col, pair, cam, dI_tw, ws, flow_stride=5),
                     ws.state.numpy().copy(), ws.residual.numpy().copy(), ws.weight.numpy().copy())
    (a, st_a, r_a, w_a), (b, st_b, r_b, w_b) = out[False], out[True]
    for kind in (tk.TrackState.IN, tk.TrackState.OOB, tk.TrackState.BEHIND, tk.TrackState.SATURATED):
        assert (st_a == kind).sum() > 5, kind
    np.testing.assert_array_equal(st_b, st_a)
    np.testing.assert_allclose(r_b, r_a, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(w_b, w_a, rtol=1e-6, atol=1e-7)
    for sys_ in (a, b):
        assert np.all(np.isfinite(sys_.H)) and np.all(np.isfinite(sys_.b)) and np.isfinite(sys_.energy)
    # measured (2026-12-04): H 6.6e-9 of its largest entry, 1.2e-6 of one; b 6.4e-8 and 1.4e-7; energy equal
    np.testing.assert_allclose(b.H, a.H, rtol=3.5e-6, atol=2e-8 * np.abs(a.H).max())
    np.testing.assert_allclose(b.b, a.b, rtol=4.5e-7, atol=2e-7 * np.abs(a.b).max())
    assert b.energy == pytest.approx(a.energy, rel=1e-12)
    assert (b.num_terms, b.num_inliers, b.num_saturated, b.flow_count) == (
        a.num_terms, a.num_inliers, a.num_saturated, a.flow_count)
    assert b.flow_t_sum == pytest.approx(a.flow_t_sum, rel=1e-6, nan_ok=True)
    assert b.flow_rt_sum == pytest.approx(a.flow_rt_sum, rel=1e-6, nan_ok=True)


def test_split_equals_single_and_energy_only_mode(wp_device, setup):
    _, dI_h, dI_t, uv, idepth = setup
    # enough points that a launch splits (chunks of at least tk.SPLIT_MIN_POINTS residuals)
    reps = -(-3 * tk.SPLIT_MIN_POINTS // len(uv))
    uv = np.tile(uv, (reps, 1))
    idepth = np.tile(idepth, reps)
    col = ref_colors(dI_h, uv, 1)
    pair = ph.make_frame_pair(make_pose(np.eye(3), [0.01, 0.0, 0.0]))
    cam = ph.make_intrinsics(**CAM, width=W, height=H)
    dI_tw = wp.array(dI_t, dtype=wp.vec3, device=wp_device)
    ws = tk.TrackWorkspace(len(uv), 1, wp_device)
    a = tk.track_system(uv, idepth, col, pair, cam, dI_tw, ws, split=False)
    b = tk.track_system(uv, idepth, col, pair, cam, dI_tw, ws, threads=2)
    assert np.array_equal(a.H, b.H) and np.array_equal(a.b, b.b) and a.energy == b.energy
    c = tk.track_system(uv, idepth, col, pair, cam, dI_tw, ws, with_system=False)
    assert np.all(c.H == 0) and c.energy == a.energy and c.num_inliers == a.num_inliers
    # the same with the inputs kept as Warp arrays across calls (as the tracker does): the launches recorded for one
    # variant of the kernel must not serve the other (they share Warp's kernel key)
    uvw = wp.array(uv.astype(np.float32), dtype=wp.vec2, device=wp_device)
    idw = wp.array(idepth.astype(np.float32), device=wp_device)
    colw = wp.array(col.astype(np.float32), device=wp_device)
    for with_system in (True, False, True):
        e = tk.track_system(uvw, idw, colw, pair, cam, dI_tw, ws, threads=2, with_system=with_system)
        assert np.array_equal(e.H, b.H) if with_system else np.all(e.H == 0)
        assert e.energy == a.energy
    # a tighter cutoff saturates more residuals at the constant energy 2*9*cutoff - 81
    d = tk.track_system(uv, idepth, col, pair, cam, dI_tw, ws, cutoff_th=10.0)
    assert d.num_saturated > a.num_saturated and d.num_terms == a.num_terms
    with pytest.raises(ValueError, match="capacity"):
        m = len(uv) + 1
        tk.track_system(np.zeros((m, 2)), np.ones(m), np.ones((m, 1)), pair, cam, dI_tw, ws)
    with pytest.raises(ValueError, match="ref_color"):
        tk.track_system(uv, idepth, np.ones((len(uv), 8)), pair, cam, dI_tw, ws)


def test_gauss_newton_on_the_system_recovers_a_known_shift(wp_device):
    # Target = reference shifted by (+1.5, -0.7) px; all points on a fronto-parallel plane at inverse depth 1.
    # A few Gauss-Newton steps T <- exp(dx) T, a_t += ..., b_t += ... must move the image centre by the shift:
    # this checks the Jacobian signs against the left-perturbation convention.
    img_h = texture(H, W, seed=8, sigma=3.0)
    img_t = shifted(img_h, 1.5, -0.7) * 1.1 + 4.0  # and a brightness change: a_t = log(1.1), b_t = 4
    dI_h, _ = ref_img.gradients(img_h)
    dI_t = wp.array(ref_img.gradients(img_t.astype(np.float32))[0], dtype=wp.vec3, device=wp_device)
    yy, xx = np.mgrid[6:H - 6:2, 6:W - 6:2]
    uv = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float32)
    idepth = np.ones(len(uv), np.float32)
    col = ref_colors(dI_h, uv, 1)
    cam = ph.make_intrinsics(**CAM, width=W, height=H)
    ws = tk.TrackWorkspace(len(uv), 1, wp_device)
    T, a_t, b_t = np.eye(4), 0.0, 0.0
    energies = []
    for _ in range(6):
        s = tk.track_system(uv, idepth, col, ph.make_frame_pair(T, a_t=a_t, b_t=b_t), cam, dI_t, ws, cutoff_th=60)
        energies.append(s.mean_energy)
        Hd = s.H + 1e-6 * np.diag(np.diag(s.H))
        inc = np.linalg.solve(Hd, -s.b)
        T = se3_exp(inc[:6]) @ T
        a_t += inc[6]
        b_t += inc[7]
    assert energies[-1] < 0.2 * energies[0]
    c = np.array([CAM["cx"], CAM["cy"]])
    h = np.array([0.0, 0.0, 1.0])
    P = T[:3, :3] @ h + T[:3, 3]
    moved = np.array([CAM["fx"] * P[0] / P[2], CAM["fy"] * P[1] / P[2]]) + c
    np.testing.assert_allclose(moved - c, [1.5, -0.7], atol=0.05)
    assert np.exp(a_t) == pytest.approx(1.1, abs=0.01) and b_t == pytest.approx(4.0, abs=1.5)


def test_a_reused_workspace_and_pair_give_a_fresh_ones_results(wp_device, setup):
    """The tracker reuses one workspace a level and refills its own ``FramePair`` (``TrackWorkspace.frame_pair``);
    ``track_system`` skips the checks of the arrays it saw last and the recorded launch sets only what changed. Two
    references of different sizes and two poses, alternated on one workspace, give bitwise what a new workspace and a
    new ``make_frame_pair`` give each time; the refilled struct equals ``make_frame_pair``'s field by field."""
    _, dI_h, dI_t, uv, idepth = setup
    cam = ph.make_intrinsics(**CAM, width=W, height=H)
    dI = wp.array(dI_t, dtype=wp.vec3, device=wp_device)
    refs = []
    for n in (2000, 700):  # two references: the second smaller, so a stale point count would show
        refs.append((wp.array(uv[:n], dtype=wp.vec2, device=wp_device),
                     wp.array(idepth[:n], dtype=wp.float32, device=wp_device),
                     wp.array(ref_colors(dI_h, uv[:n], 1), dtype=wp.float32, device=wp_device)))
    poses = [make_pose(so3_exp([0.004, -0.006, 0.002]), [0.01, -0.004, 0.02]),
             se3_exp([0.02, 0.0, -0.01, 0.0, 0.003, 0.0])]
    ws = tk.TrackWorkspace(len(uv), 1, wp_device)
    for step in range(6):
        r, T = refs[step % 2], poses[(step // 2) % 2]
        pair = ws.frame_pair(T, 0.05, 2.0, 0.1, -3.0, 1.0, 2.0)
        fresh_pair = ph.make_frame_pair(T, 0.05, 2.0, 0.1, -3.0, 1.0, 2.0)
        assert np.array_equal(np.asarray(pair.R), np.asarray(fresh_pair.R)) and np.array_equal(
            np.asarray(pair.t), np.asarray(fresh_pair.t))
        assert (pair.a_rel, pair.b_h, pair.b_t) == (fresh_pair.a_rel, fresh_pair.b_h, fresh_pair.b_t)
        got = tk.track_system(*r, pair, cam, dI, ws)
        want = tk.track_system(*r, fresh_pair, cam, dI, tk.TrackWorkspace(len(uv), 1, wp_device))
        assert ws.n == r[0].shape[0]
        assert np.array_equal(got.H, want.H) and np.array_equal(got.b, want.b), step
        assert (got.energy, got.num_terms, got.num_inliers, got.flow_count) == (
            want.energy, want.num_terms, want.num_inliers, want.flow_count), step
    with pytest.raises(ValueError, match="finite 4x4"):
        ws.frame_pair(np.full((4, 4), np.nan))
