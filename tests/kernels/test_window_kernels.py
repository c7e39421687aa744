"""Window kernels (mgso_kernels.window): Warp vs the NumPy twin, the twin's Jacobians vs central finite differences
(pair parameters and absolute frame parameters through the adjoints), and the Schur complement vs a dense one."""

import cv2
import numpy as np
import pytest
import warp as wp

from mgso.geometry import make_pose, se3_adjoint, se3_exp, se3_inverse, so3_exp
from mgso_kernels import window as kw
from mgso_kernels.reference import image as ref_img
from mgso_kernels.reference import window as ref
from mgso_kernels.reference.photometric import Cam

W, H = 120, 96
CAM = Cam(fx=110.0, fy=105.0, cx=59.3, cy=47.8, width=W, height=H)


def texture(seed, sigma=1.6):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), sigma)
    return (255.0 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)


def analytic_image(x, y):
    a = 0.21 * x + 0.10 * y
    b = 0.07 * x - 0.19 * y
    I = 128 + 40 * np.sin(a) + 30 * np.cos(b)
    gx = 40 * 0.21 * np.cos(a) - 30 * 0.07 * np.sin(b)
    gy = 40 * 0.10 * np.cos(a) + 30 * 0.19 * np.sin(b)
    return I, gx, gy


def make_window(rng, nkf=3, npts=30):
    """Keyframe poses (world_to_cam current and at the linearisation point), affine, points, pairs to every other
    keyframe."""
    w2c = [np.eye(4)]
    for i in range(1, nkf):
        w2c.append(make_pose(so3_exp(rng.normal(0, 0.01, 3)), [0.04 * i, -0.01 * i, 0.01]))
    w2c0 = [se3_exp(rng.normal(0, 0.002, 6)) @ T for T in w2c]
    aff = [(rng.normal(0, 0.05), rng.normal(0, 3)) for _ in range(nkf)]
    host = np.repeat(np.arange(nkf), npts)
    n = len(host)
    uv = np.stack([rng.uniform(14, W - 15, n), rng.uniform(12, H - 13, n)], axis=1).astype(np.float32)
    idepth = rng.uniform(0.3, 1.2, n).astype(np.float32)
    color = rng.uniform(20, 230, (n, 8)).astype(np.float32)
    weight = rng.uniform(0.3, 1.0, (n, 8)).astype(np.float32)
    keylist = [(h, t) for h in range(nkf) for t in range(nkf) if h != t]
    kid = {ht: i for i, ht in enumerate(keylist)}
    pp, pk = [], []
    for p in range(n):
        for t in range(nkf):
            if t != host[p]:
                pp.append(p)
                pk.append(kid[(host[p], t)])
    keys = keys_of(keylist, w2c, w2c0, aff, th=1e9)
    return dict(w2c=w2c, w2c0=w2c0, aff=aff, host=host, uv=uv, idepth=idepth, color=color, weight=weight,
                keylist=keylist, keys=keys, pp=np.array(pp, np.int32), pk=np.array(pk, np.int32), nkf=nkf)


def keys_of(keylist, w2c, w2c0, aff, th=1e9):
    nk = len(keylist)
    R, t, R0, t0 = np.zeros((nk, 3, 3)), np.zeros((nk, 3)), np.zeros((nk, 3, 3)), np.zeros((nk, 3))
    A, adj = np.zeros((nk, 3)), np.zeros((nk, 6, 6))
    for i, (h, g) in enumerate(keylist):
        T = w2c[g] @ se3_inverse(w2c[h])
        T0 = w2c0[g] @ se3_inverse(w2c0[h])
        R[i], t[i], R0[i], t0[i] = T[:3, :3], T[:3, 3], T0[:3, :3], T0[:3, 3]
        a_rel = np.exp(aff[g][0] - aff[h][0])
        A[i] = (a_rel, aff[h][1], aff[g][1])
        adj[i] = se3_adjoint(T0)
    return kw.WindowKeys(np.array([k[0] for k in keylist], np.int32), np.array([k[1] for k in keylist], np.int32),
                         R, t, R0, t0, A, np.full(nk, th), adj)


def test_linearize_and_schur_match_twin(wp_device):
    rng = np.random.default_rng(3)
    win = make_window(rng, nkf=3, npts=25)
    imgs = [texture(10 + i) for i in range(win["nkf"])]
    dIs = [ref_img.gradients(im)[0] for im in imgs]
    params = kw.make_window_params(CAM.fx, CAM.fy, CAM.cx, CAM.cy, W, H)
    keys = win["keys"]
    keys.energy_th[:] = 8 * 20.0 ** 2  # some pairs become outliers
    images = {i: wp.array(dIs[i], dtype=wp.vec3, device=wp_device) for i in range(win["nkf"])}
    lin = kw.linearize_window(params, keys, win["pp"], win["pk"], win["uv"], win["idepth"], win["color"],
                              win["weight"], images, pairs_per_block=4, device=wp_device)
    lr = ref.linearize_window(dict(cam=CAM), keys, win["pp"], win["pk"], win["uv"], win["idepth"], win["color"],
                              win["weight"], {i: ref.dI_sampler(dIs[i]) for i in range(win["nkf"])})
    states = lr["state"]
    assert {1, 3} <= set(states.tolist())  # IN and OUTLIER both exercised
    agree = lin.state == states
    assert agree.mean() > 0.97  # float32 vs float64 at the threshold / margins may flip a rare pair
    both_in = agree & (states == 1)
    np.testing.assert_allclose(lin.energy[agree], lr["energy"][agree], rtol=2e-4, atol=1e-2)
    np.testing.assert_allclose(lin.hcd[both_in], lr["hcd"][both_in], rtol=2e-3, atol=1e-2 * np.abs(lr["hcd"]).max())
    np.testing.assert_allclose(lin.hdd[both_in], lr["hdd"][both_in], rtol=2e-3, atol=1e-6 * lr["hdd"].max())
    if agree.all():
        scale = np.abs(lr["key_H"]).max()
        np.testing.assert_allclose(lin.key_H, lr["key_H"], rtol=2e-3, atol=1e-5 * scale)
        np.testing.assert_allclose(lin.key_b, lr["key_b"], rtol=2e-3, atol=1e-5 * np.abs(lr["key_b"]).max())
    # Schur over the same linearisation (kernel's numbers into both)
    n = len(win["host"])
    point_start = np.searchsorted(win["pp"], np.arange(n + 1)).astype(np.int32)
    extra = rng.uniform(0, 5, n)
    sc = kw.schur_points(lin, keys, win["pk"], point_start, win["nkf"], extra_h=extra, extra_b=-extra, device=wp_device)
    lind = dict(state=lin.state, hcd=lin.hcd, hdd=lin.hdd, bd=lin.bd)
    sr = ref.schur_points(lind, keys, win["pk"], point_start, win["nkf"], extra_h=extra, extra_b=-extra)
    np.testing.assert_allclose(sc.hdd, sr["hdd"], rtol=1e-12)
    np.testing.assert_allclose(sc.w, sr["w"], rtol=1e-10, atol=1e-10 * np.abs(sr["w"]).max())
    np.testing.assert_allclose(sc.H_sc, sr["H_sc"], rtol=1e-10, atol=1e-10 * np.abs(sr["H_sc"]).max())
    np.testing.assert_allclose(sc.b_sc, sr["b_sc"], rtol=1e-10, atol=1e-10 * np.abs(sr["b_sc"]).max())


def test_schur_twin_equals_dense_schur():
    """The twin's Schur terms equal the dense complement of the full (frames + depths) system."""
    rng = np.random.default_rng(5)
    win = make_window(rng, nkf=3, npts=6)
    keys = win["keys"]
    lr = ref.linearize_window(dict(cam=CAM), keys, win["pp"], win["pk"], win["uv"], win["idepth"], win["color"],
                              win["weight"], {i: analytic_image for i in range(win["nkf"])})
    n, nf = len(win["host"]), 8 * win["nkf"]
    # full Hessian from per-pair Jacobians in absolute parameters
    Hfull = np.zeros((nf + n, nf + n))
    bfull = np.zeros(nf + n)
    for j, (p, k) in enumerate(zip(win["pp"], win["pk"])):
        st, e, r, Wt, Jc, Jd = ref.linearize_pair(keys.R[k], keys.t[k], keys.R0[k], keys.t0[k], keys.aff[k], 1e9, CAM,
                                                  float(win["uv"][p, 0]), float(win["uv"][p, 1]),
                                                  float(win["idepth"][p]), win["color"][p], win["weight"][p],
                                                  analytic_image)
        if st != 1:
            continue
        J = np.zeros((8, nf + n))
        J[:, :nf] = Jc @ ref.pair_to_frames(keys, k, win["nkf"])
        J[:, nf + p] = Jd
        Hfull += (J * Wt[:, None]).T @ J
        bfull += (Wt * r) @ J
    point_start = np.searchsorted(win["pp"], np.arange(n + 1))
    sr = ref.schur_points(lr, keys, win["pk"], point_start, win["nkf"])
    Hcc, Hcd, Hdd = Hfull[:nf, :nf], Hfull[:nf, nf:], np.diag(Hfull[nf:, nf:])
    np.testing.assert_allclose(np.diag(Hfull[nf:, nf:]), sr["hdd"], rtol=1e-10)
    assert np.allclose(Hfull[nf:, nf:], np.diag(Hdd))  # points are independent given the frames
    np.testing.assert_allclose(sr["H_sc"], (Hcd / Hdd) @ Hcd.T, rtol=1e-9, atol=1e-9 * np.abs(Hcc).max())
    np.testing.assert_allclose(sr["b_sc"], (Hcd / Hdd) @ bfull[nf:], rtol=1e-9, atol=1e-9 * np.abs(bfull).max())
    # the key blocks mapped to frames are H_cc
    Htop = sum(ref.pair_to_frames(keys, k, win["nkf"]).T @ lr["key_H"][k] @ ref.pair_to_frames(keys, k, win["nkf"])
               for k in range(len(keys.host)))
    np.testing.assert_allclose(Htop, Hcc, rtol=1e-9, atol=1e-9 * np.abs(Hcc).max())


def _centre_residual(win, k, p, w2c, aff, idepth):
    """Residual of the pattern centre (pixel 4) of point p in key k with the given absolute states."""
    h, g = win["keylist"][k]
    T = w2c[g] @ se3_inverse(w2c[h])
    a_rel = np.exp(aff[g][0] - aff[h][0])
    u, v = float(win["uv"][p, 0]), float(win["uv"][p, 1])
    x, y, _, _, _ = ref._project(T[:3, :3], T[:3, 3], CAM, u, v, idepth)
    I, _, _ = analytic_image(np.array([x]), np.array([y]))
    return float(I[0]) - aff[g][1] - a_rel * (float(win["color"][p, 4]) - aff[h][1])


def test_jacobians_match_finite_differences():
    """Centre pixel (where the geometric Jacobian is exact) at the linearisation point: the pair Jacobian mapped to
    absolute frame parameters (left perturbation of world_to_cam, a, b) and the inverse-depth Jacobian vs central
    differences of the residual."""
    rng = np.random.default_rng(11)
    win = make_window(rng, nkf=3, npts=4)
    win["w2c0"] = [T.copy() for T in win["w2c"]]  # evaluate at the linearisation point
    keys = keys_of(win["keylist"], win["w2c"], win["w2c0"], win["aff"])
    eps = 1e-6
    checked = 0
    for j in range(0, len(win["pp"]), 3):
        p, k = int(win["pp"][j]), int(win["pk"][j])
        st, e, r, Wt, Jc, Jd = ref.linearize_pair(keys.R[k], keys.t[k], keys.R0[k], keys.t0[k], keys.aff[k], 1e9, CAM,
                                                  float(win["uv"][p, 0]), float(win["uv"][p, 1]),
                                                  float(win["idepth"][p]), win["color"][p], win["weight"][p],
                                                  analytic_image)
        if st != 1:
            continue
        Jabs = Jc[4] @ ref.pair_to_frames(keys, k, win["nkf"])
        num = np.zeros(8 * win["nkf"])
        for s in range(win["nkf"]):
            for a in range(8):
                vals = []
                for sg in (1, -1):
                    w2c = [T.copy() for T in win["w2c"]]
                    aff = [list(x) for x in win["aff"]]
                    if a < 6:
                        d = np.zeros(6)
                        d[a] = sg * eps
                        w2c[s] = se3_exp(d) @ w2c[s]
                    else:
                        aff[s][a - 6] += sg * eps
                    vals.append(_centre_residual(win, k, p, w2c, aff, float(win["idepth"][p])))
                num[8 * s + a] = (vals[0] - vals[1]) / (2 * eps)
        np.testing.assert_allclose(Jabs, num, rtol=1e-4, atol=1e-4 * np.abs(num).max())
        d0 = float(win["idepth"][p])
        numd = (_centre_residual(win, k, p, win["w2c"], win["aff"], d0 + eps)
                - _centre_residual(win, k, p, win["w2c"], win["aff"], d0 - eps)) / (2 * eps)
        np.testing.assert_allclose(Jd[4], numd, rtol=1e-4, atol=1e-6)
        checked += 1
    assert checked >= 5


def test_launchers_check_inputs(wp_device):
    rng = np.random.default_rng(0)
    win = make_window(rng, nkf=2, npts=3)
    params = kw.make_window_params(CAM.fx, CAM.fy, CAM.cx, CAM.cy, W, H)
    with pytest.raises(ValueError, match="no image for target"):
        kw.linearize_window(params, win["keys"], win["pp"], win["pk"], win["uv"], win["idepth"], win["color"],
                            win["weight"], {}, device=wp_device)
    with pytest.raises(ValueError, match="out of range"):
        kw.linearize_window(params, win["keys"], win["pp"], win["pk"] + 5, win["uv"], win["idepth"], win["color"],
                            win["weight"], {}, device=wp_device)
    with pytest.raises(ValueError, match="uv"):
        kw.linearize_window(params, win["keys"], win["pp"], win["pk"], win["uv"][:, :1], win["idepth"],
                            win["color"], win["weight"], {}, device=wp_device)


def test_linearize_with_a_cache_sees_each_call_s_state():
    """The optimiser passes one cache for all its iterations: the launch is recorded once and its key and inverse-
    depth arrays refilled; each call must give what an uncached call gives at that state (bit for bit), and the
    key sums the same bits as adding each block's partial row in order."""
    rng = np.random.default_rng(5)
    win = make_window(rng, nkf=4, npts=40)
    dIs = [ref_img.gradients(texture(20 + i))[0] for i in range(win["nkf"])]
    params = kw.make_window_params(CAM.fx, CAM.fy, CAM.cx, CAM.cy, W, H)
    images = {i: wp.array(dIs[i], dtype=wp.vec3, device="cpu") for i in range(win["nkf"])}
    args = (win["pp"], win["pk"], win["uv"])
    rest = (win["color"], win["weight"], images)
    cache: dict = {}
    first = kw.linearize_window(params, win["keys"], *args, win["idepth"], *rest, pairs_per_block=3, cache=cache)
    moved = [se3_exp(rng.normal(0, 0.003, 6)) @ T for T in win["w2c"]]
    keys2 = keys_of(win["keylist"], moved, win["w2c0"], win["aff"])
    idepth2 = win["idepth"] * rng.uniform(0.97, 1.03, len(win["idepth"])).astype(np.float32)
    cached = kw.linearize_window(params, keys2, *args, idepth2, *rest, pairs_per_block=3, cache=cache)
    fresh = kw.linearize_window(params, keys2, *args, idepth2, *rest, pairs_per_block=3)
    assert not np.array_equal(first.hcd, fresh.hcd)  # the second state differs
    for name in ("state", "energy", "hcd", "hdd", "bd", "key_H", "key_b"):
        np.testing.assert_array_equal(getattr(cached, name), getattr(fresh, name), err_msg=name)
    assert len(cache["recorded"]) == 1  # one recorded launch, replayed
    # the key sums against np.add.at over the blocks' partial rows, in order
    part = cache["partials"].numpy()[:cache["B"]]
    kH = np.zeros((len(keys2), kw.NUM_KEY_SLOTS))
    np.add.at(kH, cache["bkey"], part)
    np.testing.assert_array_equal(cached.key_H.reshape(len(keys2), -1), kH[:, :100])
    np.testing.assert_array_equal(cached.key_b, kH[:, 100:110])
