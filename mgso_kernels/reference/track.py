"""NumPy twin of :mod:`mgso_kernels.track`: DSO coarse-tracking residuals and the 8x8 system, float64."""

from __future__ import annotations

import numpy as np

from .photometric import PATTERN, Cam, Pair, photometric_residual

__all__ = ["track_system"]


def track_system(host_uv, idepth, ref_color, pair: Pair, cam: Cam, sampler, cutoff_th=20.0, huber_th=9.0,
                 grad_c2=0.0, border_lo=2.0, border_hi=3.0, flow_stride=32) -> dict:
    """Same sums as the kernel: ``H, b, energy, num_terms, num_inliers, num_saturated, flow_t_sum,
    flow_rt_sum, flow_count`` plus per-residual ``residual, weight, state`` ``[N, P]``."""
    uv = np.asarray(host_uv, dtype=np.float64)
    idepth = np.asarray(idepth, dtype=np.float64)
    col = np.asarray(ref_color, dtype=np.float64)
    n, p = col.shape
    off = PATTERN if p == 8 else np.zeros((1, 2))
    u = uv[:, None, 0] + off[None, :, 0]
    v = uv[:, None, 1] + off[None, :, 1]
    res = photometric_residual(u, v, np.repeat(idepth[:, None], p, axis=1), col, -1.0, pair, cam, cam, sampler,
                               huber_th, grad_c2, border_lo, border_hi)
    inb = res["status"] == 0
    r = res["residual"]
    sat = inb & (np.abs(r) > cutoff_th)
    inl = inb & ~sat
    max_energy = 2 * huber_th * cutoff_th - huber_th ** 2
    W = np.where(inl, res["huber_weight"] * res["grad_weight"], 0.0)
    J = np.concatenate([res["J_pose"], res["J_aff"][..., :2]], axis=-1)  # [N, P, 8]
    Jf, Wf, rf = J[inl], W[inl], r[inl]
    H = np.einsum("k,ki,kj->ij", Wf, Jf, Jf)
    b = np.einsum("k,ki,k->i", Wf, Jf, rf)
    energy = res["energy"][inl].sum() + max_energy * sat.sum()
    state = np.where(inb, np.where(sat, 3, 0), res["status"])
    # flow indicators of the point centres
    ft = frt = 0.0
    cnt = 0
    if flow_stride > 0:
        idx = np.arange(0, n, flow_stride)
        c = uv[idx]
        hp = np.stack([(c[:, 0] - cam.cx) / cam.fx, (c[:, 1] - cam.cy) / cam.fy, np.ones(len(idx))], axis=1)
        rh = hp @ pair.R.T
        tt = idepth[idx, None] * pair.t[None, :]

        def shift(P):
            dx = cam.fx * P[:, 0] / P[:, 2] + cam.cx - c[:, 0]
            dy = cam.fy * P[:, 1] / P[:, 2] + cam.cy - c[:, 1]
            return dx ** 2 + dy ** 2

        ft = float((shift(hp + tt) + shift(hp - tt)).sum())
        frt = float((shift(rh + tt) + shift(rh - tt)).sum())
        cnt = 2 * len(idx)
    return dict(H=H, b=b, energy=float(energy), num_terms=int(inb.sum()), num_inliers=int(inl.sum()),
                num_saturated=int(sat.sum()), flow_t_sum=ft, flow_rt_sum=frt, flow_count=cnt,
                residual=np.where(inb, r, 0.0), weight=W, state=state)
