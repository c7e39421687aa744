"""NumPy twin of :mod:`mgso_kernels.trace`: DSO's ``ImmaturePoint::traceOn``, one point at a time, plainly.

Arithmetic in float32 like the kernel (the search takes discrete decisions, so the twin follows the kernel's
precision); images are sampled with the twin bilinear sampler.
"""

from __future__ import annotations

import numpy as np

from .image import bilinear_inside, sample_dI

__all__ = ["hash_unit", "trace_point", "trace_points", "GOOD", "OOB", "OUTLIER", "SKIPPED", "BADCONDITION"]

GOOD, OOB, OUTLIER, SKIPPED, BADCONDITION, UNINITIALIZED = range(6)
PATTERN = np.array([[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]], dtype=np.float32)
f32 = np.float32


def hash_unit(a: int, b: int, c: int) -> np.float32:
    m = 0xFFFFFFFF
    x = ((a & m) * 73856093 & m) ^ ((b & m) * 19349663 & m) ^ ((c & m) * 83492791 & m)
    x ^= x >> 16
    x = (x * 0x7FEB352D) & m
    x ^= x >> 15
    x = (x * 0x846CA68B) & m
    x ^= x >> 16
    return f32((x >> 8) / 16777216.0)


def _huber(r, th):
    a = np.abs(r)
    return np.where(a < th, f32(1), f32(th) / np.maximum(a, f32(1e-30))).astype(np.float32)


def trace_point(dI, uv, color, weight, grad_h, KRKi, Kt, aff, id_min, id_max, quality, last, p) -> dict:
    """One point. ``p``: dict of TraceParams fields. Returns the new state and outputs."""
    out = dict(status=last, idepth_min=f32(id_min), idepth_max=f32(id_max), quality=f32(quality),
               uv=np.array([-1, -1], np.float32), interval=f32(0), energy=f32(np.nan))
    if last == OOB:
        return out
    h, w = dI.shape[:2]
    lo_b, hi_b = p["border_lo"], p["border_hi"]

    def inside(x, y):
        return x > lo_b and y > lo_b and x < w - hi_b and y < h - hi_b

    M = np.asarray(KRKi, np.float32)
    kt = np.asarray(Kt, np.float32)
    pr = M @ np.array([uv[0], uv[1], 1], np.float32)
    p_min = pr + kt * f32(id_min)
    u_min, v_min = p_min[0] / p_min[2], p_min[1] / p_min[2]

    def oob():
        out.update(status=OOB)
        return out

    if not inside(u_min, v_min):
        return oob()
    max_known = np.isfinite(id_max)
    if max_known:
        p_max = pr + kt * f32(id_max)
        u_max, v_max = p_max[0] / p_max[2], p_max[1] / p_max[2]
        if not inside(u_max, v_max):
            return oob()
        dist = np.sqrt((u_min - u_max) ** 2 + (v_min - v_max) ** 2)
        if dist < p["slack_interval"]:
            out.update(status=SKIPPED, uv=np.array([(u_max + u_min) / 2, (v_max + v_min) / 2], np.float32),
                       interval=dist)
            return out
    else:
        dist = f32(p["max_pix_search"])
        p_max = pr + kt * f32(0.01)
        ddx, ddy = p_max[0] / p_max[2] - u_min, p_max[1] / p_max[2] - v_min
        d = f32(1) / np.sqrt(ddx * ddx + ddy * ddy)
        u_max, v_max = u_min + dist * ddx * d, v_min + dist * ddy * d
        if not inside(u_max, v_max):
            return oob()
    if not (id_min < 0 or (0.75 < p_min[2] < 1.5)):
        return oob()
    dx = f32(p["step_size"]) * (u_max - u_min)
    dy = f32(p["step_size"]) * (v_max - v_min)
    g = np.asarray(grad_h, np.float32)
    a = dx * dx * g[0] + 2 * dx * dy * g[1] + dy * dy * g[2]
    b = dy * dy * g[0] - 2 * dx * dy * g[1] + dx * dx * g[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = f32(0.2) + f32(0.2) * (a + b) / a
    if err * p["min_improvement_factor"] > dist and max_known:
        out.update(status=BADCONDITION, uv=np.array([(u_max + u_min) / 2, (v_max + v_min) / 2], np.float32),
                   interval=dist)
        return out
    if err > 10:
        err = f32(10)
    dx, dy = dx / dist, dy / dist
    if dist > p["max_pix_search"]:
        dist = f32(p["max_pix_search"])
    if not (np.isfinite(dx) and np.isfinite(dy)):
        return oob()
    num_steps = min(int(1.9999 + dist / p["step_size"]), 99)
    shift = hash_unit(int(uv[0] + 0.5), int(uv[1] + 0.5), p["seed"])
    ptx, pty = u_min - shift * dx, v_min - shift * dy
    rot = PATTERN @ M[:2, :2].T  # rotated pattern [8, 2]
    target = aff[0] * np.asarray(color, np.float32) + aff[1]

    def pattern_energy(x0, y0, with_grad):
        x, y = x0 + rot[:, 0], y0 + rot[:, 1]
        ok = bilinear_inside(x, y, w, h)
        s = sample_dI(dI, x, y)
        ok &= np.isfinite(s[:, 0])
        r = (s[:, 0] - target).astype(np.float32)
        hw = _huber(r, p["huber_th"])
        return ok, r, hw, s

    errors = np.zeros(num_steps, np.float32)
    best_u = best_v = f32(0)
    best_e, best_idx = f32(1e10), -1
    for s_ in range(num_steps):
        ok, r, hw, _ = pattern_energy(ptx, pty, False)
        e = f32(np.sum(np.where(ok, hw * r * r * (2 - hw), f32(1e5)), dtype=np.float32))
        errors[s_] = e
        if e < best_e:
            best_u, best_v, best_e, best_idx = ptx, pty, e, s_
        ptx, pty = ptx + dx, pty + dy
    rad = p["min_test_radius"]
    far = (np.arange(num_steps) < best_idx - rad) | (np.arange(num_steps) > best_idx + rad)
    second = f32(min(1e10, errors[far].min())) if far.any() else f32(1e10)
    new_q = second / best_e
    if new_q < quality or num_steps > 10:
        out["quality"] = f32(new_q)
    u_bak, v_bak, step_back = best_u, best_v, f32(0)
    if p["gn_iterations"] > 0:
        best_e = f32(1e5)
    wgt = np.asarray(weight, np.float32)
    for _ in range(p["gn_iterations"]):
        ok, r, hw, s = pattern_energy(best_u, best_v, True)
        dres = dx * s[:, 1] + dy * s[:, 2]
        H = f32(1) + np.sum(np.where(ok, hw * dres * dres, 0), dtype=np.float32)
        bb = np.sum(np.where(ok, hw * r * dres, 0), dtype=np.float32)
        e = f32(np.sum(np.where(ok, wgt * wgt * hw * r * r * (2 - hw), f32(1e5)), dtype=np.float32))
        if e > best_e:
            step_back = step_back * f32(0.5)
            best_u, best_v = u_bak + step_back * dx, v_bak + step_back * dy
        else:
            step = f32(np.clip(-bb / H, -0.5, 0.5))
            if not np.isfinite(step):
                step = f32(0)
            u_bak, v_bak, step_back = best_u, best_v, step
            best_u, best_v, best_e = best_u + step * dx, best_v + step * dy, e
        if abs(step_back) < p["gn_threshold"]:
            break
    out["energy"] = f32(best_e)
    if not best_e < p["energy_th"] * p["extra_slack_on_th"]:
        out.update(status=OOB if last == OUTLIER else OUTLIER)
        return out
    with np.errstate(divide="ignore", invalid="ignore"):
        if dx * dx > dy * dy:
            xa, xb = best_u - err * dx, best_u + err * dx
            lo = (pr[2] * xa - pr[0]) / (kt[0] - kt[2] * xa)
            hi = (pr[2] * xb - pr[0]) / (kt[0] - kt[2] * xb)
        else:
            ya, yb = best_v - err * dy, best_v + err * dy
            lo = (pr[2] * ya - pr[1]) / (kt[1] - kt[2] * ya)
            hi = (pr[2] * yb - pr[1]) / (kt[1] - kt[2] * yb)
    lo, hi = min(lo, hi), max(lo, hi)
    out.update(idepth_min=f32(lo), idepth_max=f32(hi))
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi < 0:
        out.update(status=OUTLIER)
        return out
    out.update(status=GOOD, uv=np.array([best_u, best_v], np.float32), interval=f32(2 * err))
    return out


def trace_points(dI, host_uv, host_index, color, weight, grad_h, KRKi, Kt, affine, params, idepth_min, idepth_max,
                 quality, status) -> dict:
    """All points; returns arrays ``status, idepth_min, idepth_max, quality, uv, interval, energy``."""
    res = [trace_point(dI, host_uv[i], color[i], weight[i], grad_h[i], KRKi[host_index[i]], Kt[host_index[i]],
                       affine[host_index[i]], idepth_min[i], idepth_max[i], quality[i], int(status[i]), params)
           for i in range(len(host_uv))]
    keys = ["status", "idepth_min", "idepth_max", "quality", "uv", "interval", "energy"]
    return {k: np.array([r[k] for r in res]) for k in keys}
