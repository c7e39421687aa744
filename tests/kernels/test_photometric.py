"""The shared photometric residual: Warp vs NumPy twin, and the twin's Jacobians vs central finite differences."""

import cv2
import numpy as np
import pytest
import warp as wp

from mgso.geometry import make_pose, se3_exp, so3_exp
from mgso_kernels import photometric as ph
from mgso_kernels.reference import image as ref_img
from mgso_kernels.reference import photometric as ref

W, H = 160, 120
CAM = dict(fx=150.0, fy=140.0, cx=79.3, cy=60.8)


def texture(h, w, seed=0, sigma=2.0):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
    return (255.0 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)


def analytic_image(x, y):
    """A smooth image with an exact gradient, for finite-difference checks."""
    a = 0.21 * x + 0.10 * y
    b = 0.07 * x - 0.19 * y
    c = 0.13 * x + 0.17 * y + 1.0
    I = 128 + 40 * np.sin(a) + 30 * np.cos(b) + 20 * np.sin(c)
    gx = 40 * 0.21 * np.cos(a) - 30 * 0.07 * np.sin(b) + 20 * 0.13 * np.cos(c)
    gy = 40 * 0.10 * np.cos(a) + 30 * 0.19 * np.sin(b) + 20 * 0.17 * np.cos(c)
    return I, gx, gy


def scene(rng, n, T):
    uv = np.stack([rng.uniform(3, W - 4, n), rng.uniform(3, H - 4, n)], axis=1).astype(np.float32)
    idepth = rng.uniform(0.2, 2.0, n).astype(np.float32)
    color = rng.uniform(0, 255, (n, 8)).astype(np.float32)
    weight = rng.uniform(0.2, 1.0, (n, 8)).astype(np.float32)
    weight[: n // 4] = -1.0  # target weight only
    return uv, idepth, color, weight


def warp_and_ref_pairs(T, a_h=0.1, b_h=3.0, a_t=-0.2, b_t=-5.0, e_h=10.0, e_t=12.0):
    return (ph.make_frame_pair(T, a_h, b_h, a_t, b_t, e_h, e_t), ref.Pair.from_pose(T, a_h, b_h, a_t, b_t, e_h, e_t))


def test_pattern_is_dso_pattern_8():
    # DSO settings.cpp staticPattern[8], "8 for SSE efficiency"
    assert ph.PATTERN_NP.tolist() == [[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]]
    assert np.abs(ph.PATTERN_NP).max() == ph.PATTERN_PADDING


@pytest.mark.parametrize("grad_c2, forward", [(2500.0, 0.0), (0.0, 0.0), (2500.0, -0.8)])
def test_residuals_and_jacobians_match_twin(wp_device, grad_c2, forward):
    rng = np.random.default_rng(7)
    n = 300
    T = make_pose(so3_exp([0.02, -0.03, 0.01]), [0.05, -0.02, forward])
    uv, idepth, color, weight = scene(rng, n, T)
    img = texture(H, W, seed=4)
    dI, _ = ref_img.gradients(img)
    dI_w = wp.array(dI, dtype=wp.vec3, device=wp_device)
    cam_w = ph.make_intrinsics(**CAM, width=W, height=H)
    cam_r = ref.Cam(**CAM, width=W, height=H)
    pair_w, pair_r = warp_and_ref_pairs(T)
    params = ph.make_photometric_params(grad_c2=grad_c2)
    got = ph.evaluate_patches(uv, idepth, color, weight, pair_w, cam_w, cam_w, dI_w, params)
    u = uv[:, None, 0] + ref.PATTERN[None, :, 0]
    v = uv[:, None, 1] + ref.PATTERN[None, :, 1]
    want = ref.photometric_residual(u, v, idepth[:, None], color, weight, pair_r, cam_r, cam_r, ref.dI_sampler(dI),
                                    grad_c2=grad_c2)
    kx, ky = want["target_xy"][..., 0], want["target_xy"][..., 1]
    near_border = ((np.abs(kx - 1.1) < 1e-3) | (np.abs(kx - (W - 3)) < 1e-3)
                   | (np.abs(ky - 1.1) < 1e-3) | (np.abs(ky - (H - 3)) < 1e-3))
    same = (got.status == want["status"]) | near_border
    assert same.all()
    counts = np.bincount(want["status"].ravel(), minlength=3)
    assert counts[0] > (0.5 if forward == 0 else 0.1) * n * 8 and counts[1] > 0  # many in view, some out
    if forward < 0:
        assert counts[2] > 0  # the camera moved past some points
    ok = (got.status == 0) & (want["status"] == 0)
    for key in ("residual", "huber_weight", "grad_weight", "energy", "J_idepth"):
        scale = np.abs(want[key][ok]).max() + 1e-9
        np.testing.assert_allclose(getattr(got, key)[ok], want[key][ok], rtol=2e-4, atol=2e-5 * scale, err_msg=key)
    for key in ("target_xy", "J_pose", "J_aff", "J_calib"):
        a, b = getattr(got, key)[ok], want[key][ok]
        scale = np.abs(b).max(axis=0) + 1e-9  # per component
        err = np.abs(a - b) / (2e-4 * np.abs(b) + 1e-4 * scale)
        assert err.max() <= 1.0, (key, err.max())
    assert np.all(got.residual[got.status != 0] == 0) and np.all(got.J_pose[got.status != 0] == 0)
    if grad_c2 == 0:
        assert np.all(got.grad_weight[ok] == 1.0)
    # Huber: |r| >= 9 gets weight 9/|r| and the energy 9 (2|r| - 9) of the Huber norm (times the gradient weight)
    big = ok & (np.abs(got.residual) >= 9.5)
    assert big.sum() > 10
    np.testing.assert_allclose(got.huber_weight[big], 9.0 / np.abs(got.residual[big]), rtol=1e-5)
    np.testing.assert_allclose(got.energy[big], got.grad_weight[big] * 9.0 * (2 * np.abs(got.residual[big]) - 9.0),
                               rtol=1e-4)


def _fd_setup():
    rng = np.random.default_rng(11)
    n = 40
    uv = np.stack([rng.uniform(30, W - 30, n), rng.uniform(30, H - 30, n)], axis=1)
    u = uv[:, None, 0] + ref.PATTERN[None, :, 0]
    v = uv[:, None, 1] + ref.PATTERN[None, :, 1]
    idepth = np.repeat(rng.uniform(0.3, 1.5, n)[:, None], 8, axis=1)
    color = rng.uniform(20, 230, (n, 8))
    T = make_pose(so3_exp([0.03, -0.02, 0.015]), [0.04, -0.03, 0.05])
    return u, v, idepth, color, T


def _res(u, v, idepth, color, T, aff=(0.1, 3.0, -0.2, -5.0), cam=None):
    cam = cam or ref.Cam(**CAM, width=W, height=H)
    pair = ref.Pair.from_pose(T, *aff, 10.0, 12.0)
    return ref.photometric_residual(u, v, idepth, color, 0.5, pair, cam, cam, analytic_image)


def test_jacobians_match_central_differences():
    u, v, idepth, color, T = _fd_setup()
    base = _res(u, v, idepth, color, T)
    assert np.all(base["status"] == 0)
    eps = 1e-6

    def check(name, J, f_plus, f_minus):
        fd = (f_plus["residual"] - f_minus["residual"]) / (2 * eps)
        np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-6 * (np.abs(fd).max() + 1), err_msg=name)

    for k in range(6):  # left perturbation of target_from_host, translation first
        d = np.zeros(6)
        d[k] = eps
        check(f"pose[{k}]", base["J_pose"][..., k], _res(u, v, idepth, color, se3_exp(d) @ T),
              _res(u, v, idepth, color, se3_exp(-d) @ T))
    check("idepth", base["J_idepth"], _res(u, v, idepth + eps, color, T), _res(u, v, idepth - eps, color, T))
    aff = np.array([0.1, 3.0, -0.2, -5.0])  # (a_h, b_h, a_t, b_t) in the constructor's order
    order = {0: 2, 1: 3, 2: 0, 3: 1}  # J_aff is (a_t, b_t, a_h, b_h)
    for k in range(4):
        d = np.zeros(4)
        d[order[k]] = eps
        check(f"aff[{k}]", base["J_aff"][..., k], _res(u, v, idepth, color, T, tuple(aff + d)),
              _res(u, v, idepth, color, T, tuple(aff - d)))
    for k, name in enumerate(["fx", "fy", "cx", "cy"]):
        cp = dict(CAM)
        cm = dict(CAM)
        cp[name] += eps
        cm[name] -= eps
        check(name, base["J_calib"][..., k], _res(u, v, idepth, color, T, cam=ref.Cam(**cp, width=W, height=H)),
              _res(u, v, idepth, color, T, cam=ref.Cam(**cm, width=W, height=H)))


def test_pose_jacobian_is_dso_formula_at_identity():
    # At T = identity the target pixel is the host pixel; DSO's d_xi_x = fx * (id, 0, -id u, -u v, 1 + u^2, -v).
    cam = ref.Cam(**CAM, width=W, height=H)
    u, v = np.array([50.0]), np.array([70.0])
    out = ref.photometric_residual(u, v, np.array([0.5]), 100.0, -1, ref.Pair.from_pose(np.eye(4)), cam, cam,
                                   analytic_image)
    un, vn = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    _, gx, gy = analytic_image(u, v)
    dku = cam.fx * np.array([0.5, 0, -0.5 * un[0], -un[0] * vn[0], 1 + un[0] ** 2, -vn[0]])
    dkv = cam.fy * np.array([0, 0.5, -0.5 * vn[0], -(1 + vn[0] ** 2), un[0] * vn[0], un[0]])
    np.testing.assert_allclose(out["J_pose"][0], gx[0] * dku + gy[0] * dkv, rtol=1e-12)


def test_extract_patterns_matches_twin(wp_device, rng):
    img = texture(H, W, seed=5)
    dI, _ = ref_img.gradients(img)
    dI_w = wp.array(dI, dtype=wp.vec3, device=wp_device)
    uv = np.concatenate([rng.integers(3, 150, (50, 2)).astype(np.float32), [[1, 1], [158, 60], [20.5, 30.25]]])
    uv = uv.astype(np.float32)
    got = ph.extract_patterns(dI_w, uv)
    want = ref.extract_patterns(dI, uv)
    assert np.array_equal(got.valid, want["valid"])
    assert not got.valid[-3] and not got.valid[-2] and got.valid[-1]
    np.testing.assert_allclose(got.color, want["color"], atol=1e-3)
    np.testing.assert_allclose(got.weight, want["weight"], rtol=1e-5)
    np.testing.assert_allclose(got.grad_h, want["grad_h"], rtol=1e-4, atol=1e-2)
    # integer centre: colour is the pixel, weight uses DSO's forward-difference (BiLin) gradient
    x, y = int(uv[0, 0]), int(uv[0, 1])
    assert got.color[0, 4] == pytest.approx(img[y, x], abs=1e-3)
    g2 = (img[y, x + 1] - img[y, x]) ** 2 + (img[y + 1, x] - img[y, x]) ** 2
    assert got.weight[0, 4] == pytest.approx(np.sqrt(2500 / (2500 + g2)), rel=1e-5)


def test_affine_model_is_dso_from_to():
    a, b = ph.affine_from_to(0.1, 3.0, -0.2, -5.0, 10.0, 12.0)
    assert a == pytest.approx(np.exp(-0.3) * 1.2) and b == pytest.approx(-5.0 - a * 3.0)
    assert ph.affine_from_to(0.1, 3.0, -0.2, -5.0, 0.0, 12.0)[0] == pytest.approx(np.exp(-0.3))  # unknown exposure
    # a diverged window's affine (a real-time run's lost segment reached float32's overflow): a ratio that fits
    # float32, not an OverflowError (math.exp(800) raises); the twin agrees; within the limit nothing changes
    for d in (800.0, -800.0, 90.0):
        a, b = ph.affine_from_to(0.0, 1.0, d, 0.0)
        assert np.isfinite(np.float32(a)) and np.isfinite(np.float32(b))
        assert a == pytest.approx(np.exp(np.sign(d) * 80.0)) and a == pytest.approx(ref.affine_from_to(0, 1, d, 0)[0])
    assert ph.affine_from_to(0.0, 0.0, 79.0, 0.0)[0] == pytest.approx(np.exp(79.0))
    with pytest.raises(ValueError, match="4x4"):
        ph.make_frame_pair(np.eye(3))
    with pytest.raises(ValueError, match="focal"):
        ph.make_intrinsics(0, 1, 0, 0, 10, 10)
