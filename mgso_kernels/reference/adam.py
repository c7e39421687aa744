"""NumPy twin of :mod:`mgso_kernels.adam`: Adam written row by row in float64, the gather, the statistics update."""

from __future__ import annotations

import numpy as np

__all__ = ["GROUPS", "adam_step_gaussians", "adam_step_flat", "gather_rows", "accumulate_densify_stats"]

# group name -> key of the learning rate in `rates`
GROUPS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def _adam(p, g, m, v, lr, b1, b2, eps, t):
    """torch.optim.Adam for one step; t = None means no bias correction."""
    m = b1 * m + (1 - b1) * g
    v = b2 * v + (1 - b2) * g * g
    bc1 = 1.0 if t is None else 1 - b1 ** t
    bc2 = 1.0 if t is None else 1 - b2 ** t
    p = p - lr / bc1 * m / (np.sqrt(v) / np.sqrt(bc2) + eps)
    return p, m, v


def adam_step_gaussians(params: dict, grads: dict, exp_avg: dict, exp_avg_sq: dict, steps: np.ndarray, rates: dict,
                        beta1=0.9, beta2=0.999, eps=1e-15, bias_correction=1, global_step=1, sparse=False,
                        visible=None):
    """Return updated copies (params, exp_avg, exp_avg_sq, steps). Dicts hold float arrays keyed by GROUPS.

    ``rates``: keys means, log_scales, quats, opacity_logits, sh_dc, sh_rest. ``bias_correction``: 0 none,
    1 global step, 2 per-Gaussian step.
    """
    P = {k: np.array(params[k], dtype=np.float64) for k in GROUPS}
    M = {k: np.array(exp_avg[k], dtype=np.float64) for k in GROUPS}
    V = {k: np.array(exp_avg_sq[k], dtype=np.float64) for k in GROUPS}
    S = np.array(steps, dtype=np.int64)
    n = P["means"].shape[0]
    for i in range(n):
        if sparse:
            if visible is not None:
                if not visible[i]:
                    continue
            elif not any(np.any(np.asarray(grads[k][i]) != 0) for k in GROUPS):
                continue
        S[i] += 1
        t = {0: None, 1: global_step, 2: S[i]}[bias_correction]
        for k in GROUPS:
            g = np.asarray(grads[k][i], dtype=np.float64)
            if k == "sh":
                for j in range(P[k].shape[1]):
                    lr = rates["sh_dc"] if j == 0 else rates["sh_rest"]
                    P[k][i, j], M[k][i, j], V[k][i, j] = _adam(P[k][i, j], g[j], M[k][i, j], V[k][i, j], lr, beta1,
                                                               beta2, eps, t)
            else:
                P[k][i], M[k][i], V[k][i] = _adam(P[k][i], g, M[k][i], V[k][i], rates[k], beta1, beta2, eps, t)
    return P, M, V, S


def adam_step_flat(param, grad, exp_avg, exp_avg_sq, lr, step, beta1=0.9, beta2=0.999, eps=1e-15,
                   bias_correction=True):
    return _adam(np.asarray(param, np.float64), np.asarray(grad, np.float64), np.asarray(exp_avg, np.float64),
                 np.asarray(exp_avg_sq, np.float64), lr, beta1, beta2, eps, step if bias_correction else None)


def gather_rows(src: np.ndarray, index: np.ndarray) -> np.ndarray:
    return np.asarray(src)[np.asarray(index)]


def accumulate_densify_stats(stats: dict, v_means2d, radii, width, height, v_means2d_abs=None, weights=None,
                             weight_scale=1.0) -> dict:
    """Return an updated copy of ``stats`` (keys grad2d_sum, absgrad2d_sum, vis_count, max_radius_px, views_seen and,
    weight_max: the largest of weights x weight_scale, or the largest float32 for a view without weights)."""
    out = {k: np.array(v, copy=True) for k, v in stats.items()}
    for i in range(len(radii)):
        if radii[i] <= 0:
            continue
        gx, gy = v_means2d[i]
        out["grad2d_sum"][i] += np.hypot(gx * width / 2.0, gy * height / 2.0)
        if v_means2d_abs is not None:
            ax, ay = v_means2d_abs[i]
            out["absgrad2d_sum"][i] += np.hypot(ax * width / 2.0, ay * height / 2.0)
        out["vis_count"][i] += 1
        out["views_seen"][i] += 1
        out["max_radius_px"][i] = max(out["max_radius_px"][i], radii[i])
        if weights is not None:
            out["weight_max"][i] = max(out["weight_max"][i], weights[i] * weight_scale)
        elif "weight_max" in out:
            out["weight_max"][i] = np.finfo(np.float32).max   # unknown
    return out
