"""NumPy twin of :mod:`mgso_kernels.initializer`: DSO ``CoarseInitializer::calcResAndGS`` vectorised over points.

This was the initialiser's own implementation before the kernel (float32 per pixel as DSO, float64 sums); the
kernel keeps its numbers. Plain function of arrays: the per-point outputs are written into the arrays passed in.
"""

from __future__ import annotations

import math

import numpy as np

from .image import sample_dI

__all__ = ["PATTERN", "init_system", "smooth_idepths"]

PATTERN = np.array([[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]], dtype=np.float32)


def init_system(uv, ref_color, dI_t, first_to_new, affine, fx, fy, cx, cy, *, idepth, is_good, energy, iR,
                energy_new, is_good_new, jb_new, maxstep, last_hessian_new, huber_th=9.0, max_energy=8 * 144.0 * 20,
                alpha_opt=0.0, coupling_weight=1.0) -> dict:
    """Same contract as :func:`mgso_kernels.initializer.init_system` with ``dI_t [h, w, 3]`` NumPy and the pose /
    affine / intrinsics given directly. Returns ``dict(H, b, Hsc, bsc, energy, num_good)``."""
    f32 = np.float32
    uv = np.asarray(uv, dtype=f32)
    u, v = uv[:, 0], uv[:, 1]
    T = np.asarray(first_to_new, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    a_exp, b0 = math.exp(affine[0]), affine[1]
    hl, wl = dI_t.shape[:2]
    maxstep[:] = 1e10
    gi = np.flatnonzero(is_good)
    px = u[gi, None] + PATTERN[None, :, 0]
    py = v[gi, None] + PATTERN[None, :, 1]
    hx = (px - f32(cx)) * f32(1.0 / fx)
    hy = (py - f32(cy)) * f32(1.0 / fy)
    idn = idepth[gi, None]
    Rf, tf = R.astype(f32), t.astype(f32)
    P0 = Rf[0, 0] * hx + Rf[0, 1] * hy + Rf[0, 2] + tf[0] * idn
    P1 = Rf[1, 0] * hx + Rf[1, 1] * hy + Rf[1, 2] + tf[1] * idn
    P2 = Rf[2, 0] * hx + Rf[2, 1] * hy + Rf[2, 2] + tf[2] * idn
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        iz = f32(1.0) / P2
        uu = P0 * iz
        vv = P1 * iz
        new_id = idn * iz
        ku = f32(fx) * uu + f32(cx)
        kv = f32(fy) * vv + f32(cy)
        okp = (ku > 1.0) & (kv > 1.0) & (ku < wl - 2.0) & (kv < hl - 2.0) & (new_id > 0)
    hit = sample_dI(dI_t, np.where(okp, ku, 0), np.where(okp, kv, 0))
    rl = ref_color[gi]
    okp &= np.isfinite(hit[..., 0]) & np.isfinite(rl)
    ok_pt = okp.all(axis=1)
    zero = f32(0.0)
    hit = np.where(okp[..., None], hit, zero)
    rl = np.where(okp, rl, zero)
    uu = np.where(okp, uu, zero)  # invalid pixels: everything 0 below (no NaN/inf enters the sums)
    vv = np.where(okp, vv, zero)
    new_id = np.where(okp, new_id, zero)
    iz = np.where(okp, iz, zero)
    res = hit[..., 0] - f32(a_exp) * rl - f32(b0)
    ar = np.abs(res)
    hth = f32(huber_th)
    hw = np.where(ar < hth, f32(1.0), hth / np.maximum(ar, f32(1e-12)))
    e_pt = np.sum(hw * res * res * (f32(2.0) - hw), axis=1)
    dxdd = (tf[0] - tf[2] * uu) * iz
    dydd = (tf[1] - tf[2] * vv) * iz
    hws = np.where(hw < 1.0, np.sqrt(hw), hw)
    m = okp.astype(f32)
    dxi = hws * hit[..., 1] * f32(fx) * m
    dyi = hws * hit[..., 2] * f32(fy) * m
    J = np.empty(dxi.shape + (8,), f32)  # [g, 8 pattern, 8 parameters]
    J[..., 0] = new_id * dxi
    J[..., 1] = new_id * dyi
    J[..., 2] = -new_id * (uu * dxi + vv * dyi)
    J[..., 3] = -uu * vv * dxi - (1 + vv * vv) * dyi
    J[..., 4] = (1 + uu * uu) * dxi + uu * vv * dyi
    J[..., 5] = -vv * dxi + uu * dyi
    J[..., 6] = -hws * f32(a_exp) * rl * m
    J[..., 7] = -hws * m
    dd = (dxi * dxdd + dyi * dydd) * m
    rr = hws * res * m
    with np.errstate(divide="ignore", invalid="ignore"):
        ms = np.where(okp, f32(1.0) / np.hypot(dxdd * f32(fx), dydd * f32(fy)), np.inf)
    if len(gi):
        maxstep[gi] = np.minimum(1e10, np.min(ms, axis=1))
    jb = np.zeros((len(gi), 10))
    jb[:, :8] = np.matmul(dd[:, None, :], J)[:, 0, :]
    jb[:, 8] = np.sum(rr * dd, axis=1)
    jb[:, 9] = np.sum(dd * dd, axis=1)
    good_new_g = ok_pt & (e_pt <= max_energy) & np.isfinite(e_pt)
    is_good_new[:] = False
    is_good_new[gi[good_new_g]] = True
    energy_new[:] = energy
    energy_new[gi[good_new_g], 0] = e_pt[good_new_g]
    jb_new[:] = 0.0
    jb_new[gi] = jb
    E_sum = float(np.sum(energy[~is_good_new, 0].astype(np.float64)) + np.sum(e_pt[good_new_g].astype(np.float64)))
    Jg = J[good_new_g].reshape(-1, 8).astype(np.float64)
    H = Jg.T @ Jg
    b = Jg.T @ rr[good_new_g].reshape(-1).astype(np.float64)
    # DSO's regularisation of the inverse-depth terms of the points that stay good
    gn = np.flatnonzero(is_good_new)
    energy_new[gn, 1] = (idepth[gn] - 1.0) ** 2
    jbn = jb_new[gn]
    last_hessian_new[gn] = jbn[:, 9]
    jbn[:, 8] += alpha_opt * (idepth[gn] - 1.0)
    jbn[:, 9] += alpha_opt
    if alpha_opt == 0:
        jbn[:, 8] += coupling_weight * (idepth[gn] - iR[gn])
        jbn[:, 9] += coupling_weight
    jbn[:, 9] = 1.0 / (1.0 + jbn[:, 9])
    jb_new[gn] = jbn
    Hsc = (jbn[:, :8] * jbn[:, 9:10]).T @ jbn[:, :8]
    bsc = (jbn[:, :8] * jbn[:, 9:10]).T @ jbn[:, 8]
    return dict(H=H, b=b, Hsc=Hsc, bsc=bsc, energy=E_sum, num_good=len(gn))


def smooth_idepths(neighbours, is_good, iR, idepth, reg_weight) -> np.ndarray:
    """DSO ``optReg`` for all points at once from the previous values (the initialiser's former NumPy code).
    Returns the new ``iR``."""
    nn = neighbours.shape[1]
    valid = neighbours >= 0
    nbc = np.where(valid, neighbours, 0)
    nb_good = valid & is_good[nbc]
    vals = np.where(nb_good, iR[nbc], np.nan)
    cnt = nb_good.sum(axis=1)
    srt = np.sort(vals, axis=1)
    med = np.take_along_axis(srt, np.minimum(cnt // 2, nn - 1)[:, None], axis=1)[:, 0]
    upd = is_good & (cnt > 2)
    out = iR.copy()
    out[upd] = (1.0 - reg_weight) * idepth[upd] + reg_weight * med[upd]
    return out
