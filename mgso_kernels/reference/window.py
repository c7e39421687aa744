"""NumPy twin of :mod:`mgso_kernels.window`: the window's pair residuals, Jacobians, Hessian blocks and the Schur
complement over inverse depths, written out plainly in float64 (one Python loop over pairs; slow on purpose).

The target image is reached through ``samplers[slot](x, y) -> (I, gx, gy)`` so that finite-difference tests can use
an analytic image while parity tests use the bilinear sampler of the pyramid (:func:`dI_sampler`).
"""

from __future__ import annotations

import numpy as np

from .photometric import PATTERN, dI_sampler  # noqa: F401  (dI_sampler re-exported for tests)

__all__ = ["pair_jacobians", "linearize_window", "schur_points", "dI_sampler"]

IN, OOB, OUTLIER = 1, 2, 3


def _project(R, t, cam, u, v, d):
    hx = (u - cam.cx) / cam.fx
    hy = (v - cam.cy) / cam.fy
    P = R @ np.array([hx, hy, 1.0]) + t * d
    dres = 1.0 / P[2]
    un, vn = P[0] * dres, P[1] * dres
    return cam.fx * un + cam.cx, cam.fy * vn + cam.cy, un, vn, dres


def pair_jacobians(R0, t0, cam, u, v, d):
    """DSO ``Jpdxi [2, 6]`` (left perturbation ``(v, w)`` of target_from_host) and ``Jpdd [2]`` of the target pixel
    at the pattern centre, at the linearisation point ``(R0, t0)``."""
    _, _, un, vn, dr = _project(R0, t0, cam, u, v, d)
    nid = d * dr
    fx, fy = cam.fx, cam.fy
    Jx = np.array([[nid * fx, 0.0, -nid * un * fx, -un * vn * fx, (1 + un * un) * fx, -vn * fx],
                   [0.0, nid * fy, -nid * vn * fy, -(1 + vn * vn) * fy, un * vn * fy, un * fy]])
    Jd = np.array([dr * (t0[0] - t0[2] * un) * fx, dr * (t0[1] - t0[2] * vn) * fy])
    return Jx, Jd, dr


def linearize_pair(R, t, R0, t0, aff, th, cam, u, v, d, color, weight, sampler, huber_th=9.0, grad_c2=2500.0,
                   border_lo=1.1, border_hi=3.0, min_wji2=2.0):
    """One pair: ``(state, energy, r [8], W [8], Jc [8, 10], Jd [8])`` (state as the kernel's)."""
    a_rel, b_h, b_t = aff
    Jx, Jdd, dr0 = pair_jacobians(R0, t0, cam, u, v, d)
    ok = dr0 > 0
    r = np.zeros(8)
    W = np.zeros(8)
    Jc = np.zeros((8, 10))
    Jd = np.zeros(8)
    energy = 0.0
    wji2 = 0.0
    for i in range(8):
        x, y, _, _, dres = _project(R, t, cam, u + PATTERN[i, 0], v + PATTERN[i, 1], d)
        inside = (border_lo < x < cam.width - border_hi and border_lo < y < cam.height - border_hi
                  and 0 <= x <= cam.width - 1 and 0 <= y <= cam.height - 1 and dres > 0)
        I, gx, gy = (np.nan, 0.0, 0.0)
        if inside:
            Ii, gxi, gyi = sampler(np.array([x]), np.array([y]))
            I, gx, gy = float(Ii[0]), float(gxi[0]), float(gyi[0])
        good = inside and np.isfinite(I) and np.isfinite(gx) and np.isfinite(gy)
        if not good:
            ok = False
            I, gx, gy = 0.0, 0.0, 0.0
        hc = color[i] - b_h
        ri = (I - b_t) - a_rel * hc if good else 0.0
        g2 = gx * gx + gy * gy
        w = 0.5 * (np.sqrt(grad_c2 / (grad_c2 + g2)) + weight[i])
        hw = 1.0 if abs(ri) < huber_th else huber_th / abs(ri)
        energy += w * w * hw * ri * ri * (2 - hw)
        W[i] = hw * w * w
        wji2 += W[i] ** 2 * g2
        g = np.array([gx, gy])
        Jc[i, :6] = g @ Jx
        Jc[i, 6:] = [-a_rel * hc, -1.0, a_rel * hc, a_rel]
        Jd[i] = g @ Jdd
        r[i] = ri
    state = IN if ok and not (energy > th or wji2 < min_wji2) else (OOB if not ok else OUTLIER)
    return state, (energy if state == IN else th), r, W, Jc, Jd


def linearize_window(params: dict, keys, pair_point, pair_key, uv, idepth, color, weight, samplers: dict):
    """Twin of :func:`mgso_kernels.window.linearize_window`. ``params``: ``cam`` (with fx, fy, cx, cy, width,
    height) and the residual constants as keywords of :func:`linearize_pair`. Returns a dict of the same fields."""
    cam = params["cam"]
    kw = {k: v for k, v in params.items() if k != "cam"}
    M = len(pair_point)
    nk = len(keys.host)
    out = dict(state=np.zeros(M, np.int32), energy=np.zeros(M), hcd=np.zeros((M, 10)), hdd=np.zeros(M),
               bd=np.zeros(M), key_H=np.zeros((nk, 10, 10)), key_b=np.zeros((nk, 10)))
    for j in range(M):
        p, k = int(pair_point[j]), int(pair_key[j])
        st, e, r, W, Jc, Jd = linearize_pair(keys.R[k], keys.t[k], keys.R0[k], keys.t0[k], keys.aff[k],
                                             keys.energy_th[k], cam, float(uv[p, 0]), float(uv[p, 1]),
                                             float(idepth[p]), color[p], weight[p], samplers[int(keys.target[k])],
                                             **kw)
        out["state"][j] = st
        out["energy"][j] = e
        if st == IN:
            out["hcd"][j] = (W * Jd) @ Jc
            out["hdd"][j] = np.sum(W * Jd * Jd)
            out["bd"][j] = np.sum(W * Jd * r)
            out["key_H"][k] += (Jc * W[:, None]).T @ Jc
            out["key_b"][k] += (W * r) @ Jc
    return out


def pair_to_frames(keys, k: int, num_slots: int) -> np.ndarray:
    """``[10, 8 K]`` map from absolute frame parameters to the pair parameters of key ``k``: ``xi_rel = xi_t -
    Ad xi_h``, affine ``(a_t, b_t, a_h, b_h)`` copied."""
    A = np.zeros((10, 8 * num_slots))
    h, t = int(keys.host[k]), int(keys.target[k])
    A[:6, 8 * t:8 * t + 6] = np.eye(6)
    A[:6, 8 * h:8 * h + 6] -= keys.adj[k]
    A[6, 8 * t + 6] = A[7, 8 * t + 7] = 1.0
    A[8, 8 * h + 6] = A[9, 8 * h + 7] = 1.0
    return A


def schur_points(lin: dict, keys, pair_key, point_start, num_slots, extra_h=None, extra_b=None):
    """Twin of :func:`mgso_kernels.window.schur_points` (dict of ``hdd, bd, w, H_sc, b_sc``)."""
    n = len(point_start) - 1
    nf = 8 * num_slots
    eh = np.zeros(n) if extra_h is None else np.asarray(extra_h, float)
    eb = np.zeros(n) if extra_b is None else np.asarray(extra_b, float)
    hdd = eh.copy()
    bd = eb.copy()
    w = np.zeros((n, nf))
    for p in range(n):
        for j in range(point_start[p], point_start[p + 1]):
            if lin["state"][j] != IN:
                continue
            k = int(pair_key[j])
            w[p] += lin["hcd"][j] @ pair_to_frames(keys, k, num_slots)
            hdd[p] += lin["hdd"][j]
            bd[p] += lin["bd"][j]
    hdd = np.maximum(hdd, 1e-10)
    H_sc = (w / hdd[:, None]).T @ w
    b_sc = (w / hdd[:, None]).T @ bd
    return dict(hdd=hdd, bd=bd, w=w, H_sc=H_sc, b_sc=b_sc)
