"""Activation kernel (mgso_kernels.activation): Warp vs the NumPy twin, its inverse-depth derivative vs central finite
differences of the energy, bitwise equality single vs split over the CPU cores, and input checks."""

import cv2
import numpy as np
import pytest
import warp as wp

from mgso.geometry import make_pose, se3_inverse, so3_exp
from mgso_kernels import activation as ka
from mgso_kernels import runtime
from mgso_kernels.reference import activation as ref
from mgso_kernels.reference import image as ref_img
from mgso_kernels.reference.photometric import dI_sampler

W, H = 120, 96
CAM = dict(fx=110.0, fy=105.0, cx=59.3, cy=47.8, width=W, height=H)


def images(seed, n, sigma):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        t = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), sigma)
        t = (255.0 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)
        out.append(ref_img.gradients(t)[0].astype(np.float32))
    return out


def problem(rng, nkf=3, npts=40):
    w2c = [np.eye(4)] + [make_pose(so3_exp(rng.normal(0, 0.01, 3)), [0.05 * i, -0.02 * i, 0.01]) for i in range(1, nkf)]
    host = np.repeat(np.arange(nkf), npts)
    n = len(host)
    uv = np.stack([rng.uniform(10, W - 11, n), rng.uniform(8, H - 9, n)], axis=1).astype(np.float32)
    idepth = rng.uniform(0.3, 1.5, n).astype(np.float32)
    color = rng.uniform(20, 230, (n, 8)).astype(np.float32)
    weight = rng.uniform(0.3, 1.0, (n, 8)).astype(np.float32)
    keylist = [(h, t) for h in range(nkf) for t in range(nkf) if h != t]
    R = np.stack([(w2c[t] @ se3_inverse(w2c[h]))[:3, :3] for h, t in keylist])
    tt = np.stack([(w2c[t] @ se3_inverse(w2c[h]))[:3, 3] for h, t in keylist])
    aff = np.array([(np.exp(rng.normal(0, 0.05)), rng.normal(0, 3)) for _ in keylist])
    kid = {k: i for i, k in enumerate(keylist)}
    pp = np.array([p for p in range(n) for t in range(nkf) if t != host[p]], np.int32)
    pk = np.array([kid[(host[p], t)] for p in range(n) for t in range(nkf) if t != host[p]], np.int32)
    return dict(key_target=np.array([t for _, t in keylist], np.int32), R=R, t=tt, aff=aff, pp=pp, pk=pk, uv=uv,
                idepth=idepth, color=color, weight=weight)


def run(pr, dIs, device, idepth=None):
    stack = wp.array(np.stack(dIs), dtype=wp.vec3, device=device)
    params = ka.make_depth_params(CAM["fx"], CAM["fy"], CAM["cx"], CAM["cy"], W, H)
    return ka.point_depth_residuals(params, pr["key_target"], pr["R"], pr["t"], pr["aff"], pr["pp"], pr["pk"],
                                    pr["uv"], pr["idepth"] if idepth is None else idepth, pr["color"],
                                    pr["weight"], stack, device=device)


def analytic_image(x, y):
    x = np.float64(x)
    y = np.float64(y)
    a = 0.21 * x + 0.10 * y
    b = 0.07 * x - 0.19 * y
    return (128 + 40 * np.sin(a) + 30 * np.cos(b), 40 * 0.21 * np.cos(a) - 30 * 0.07 * np.sin(b),
            40 * 0.10 * np.cos(a) + 30 * 0.19 * np.sin(b))


def run_ref(pr, dIs, idepth=None, samplers=None):
    return ref.point_depth_residuals(CAM, pr["key_target"], pr["R"], pr["t"], pr["aff"], pr["pp"], pr["pk"],
                                     pr["uv"], pr["idepth"] if idepth is None else idepth, pr["color"],
                                     pr["weight"], samplers or {i: dI_sampler(d) for i, d in enumerate(dIs)})


def test_matches_twin(wp_device):
    rng = np.random.default_rng(3)
    pr = problem(rng)
    dIs = images(1, 3, 1.6)
    got = run(pr, dIs, wp_device)
    want = run_ref(pr, dIs)
    assert 0.3 < want["ok"].mean() < 1.0  # some pairs leave the image
    agree = got.ok == want["ok"]
    assert agree.mean() > 0.98  # float32 vs float64 exactly at a margin may flip a rare pair
    both = agree & want["ok"]
    np.testing.assert_allclose(got.energy[both], want["energy"][both], rtol=2e-3, atol=1e-2)
    np.testing.assert_allclose(got.hdd[both], want["hdd"][both], rtol=2e-3, atol=1e-3 * want["hdd"].max())
    np.testing.assert_allclose(got.bd[both], want["bd"][both], rtol=2e-3, atol=1e-3 * np.abs(want["bd"]).max())
    assert np.all(got.energy[~got.ok] == 0) and np.all(got.hdd[~got.ok] == 0)


def test_split_is_bitwise_single(wp_device):
    rng = np.random.default_rng(4)
    pr = problem(rng, npts=800)
    dIs = images(2, 3, 1.6)
    runtime.set_cpu_threads(1)
    try:
        a = run(pr, dIs, wp_device)
    finally:
        runtime.set_cpu_threads(0)
    b = run(pr, dIs, wp_device)
    for f in ("ok", "energy", "hdd", "bd"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_depth_derivative_matches_finite_differences():
    """``b_d = 1/2 dE/dd`` (DSO's Huber energy ``hw r^2 (2 - hw)`` has the derivative ``2 hw r dr/dd`` on both sides of
    the threshold) on an analytic image whose gradient is exact, for the twin in float64 (the kernel agrees with the
    twin above)."""
    rng = np.random.default_rng(7)
    pr = problem(rng, npts=15)
    samplers = {i: analytic_image for i in range(3)}
    ip = pr["idepth"].astype(np.float64)
    base = run_ref(pr, None, idepth=ip, samplers=samplers)
    eps = 1e-6
    checked = 0
    for j in np.flatnonzero(base["ok"])[:40]:
        p = pr["pp"][j]
        one = dict(pr, pp=np.array([p], np.int32), pk=pr["pk"][[j]])
        e = []
        for s in (+1, -1):
            d = ip.copy()
            d[p] += s * eps
            e.append(run_ref(one, None, idepth=d, samplers=samplers)["energy"][0])
        dE = (e[0] - e[1]) / (2 * eps)
        assert dE / 2 == pytest.approx(base["bd"][j], rel=1e-3, abs=1e-3 * np.sqrt(base["hdd"][j]))
        checked += 1
    assert checked >= 20


def test_checks_inputs(wp_device):
    rng = np.random.default_rng(5)
    pr = problem(rng, npts=3)
    dIs = images(1, 3, 1.6)
    stack = wp.array(np.stack(dIs), dtype=wp.vec3, device=wp_device)
    params = ka.make_depth_params(CAM["fx"], CAM["fy"], CAM["cx"], CAM["cy"], W, H)
    with pytest.raises(ValueError, match="out of range"):
        ka.point_depth_residuals(params, pr["key_target"], pr["R"], pr["t"], pr["aff"], pr["pp"], pr["pk"] + 50,
                                 pr["uv"], pr["idepth"], pr["color"], pr["weight"], stack, device=wp_device)
    with pytest.raises(ValueError, match="slots"):
        ka.point_depth_residuals(params, pr["key_target"] + 3, pr["R"], pr["t"], pr["aff"], pr["pp"], pr["pk"],
                                 pr["uv"], pr["idepth"], pr["color"], pr["weight"], stack, device=wp_device)
    with pytest.raises(TypeError, match="3-D"):
        ka.point_depth_residuals(params, pr["key_target"], pr["R"], pr["t"], pr["aff"], pr["pp"], pr["pk"],
                                 pr["uv"], pr["idepth"], pr["color"], pr["weight"], stack[0], device=wp_device)
    with pytest.raises(ValueError, match="bad intrinsics"):
        ka.make_depth_params(-1.0, 1.0, 0.0, 0.0, W, H)
