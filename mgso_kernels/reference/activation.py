"""NumPy twin of :mod:`mgso_kernels.activation`: each pair's inverse-depth residual sums, one pair and one pattern
pixel at a time in float64, DSO's breadth-first distance map and the spaced pick as their loops (slow and
obvious)."""

from __future__ import annotations

from collections import deque

import numpy as np

from .photometric import PATTERN

__all__ = ["point_depth_residuals", "distance_map", "pick_spaced"]


def point_depth_residuals(cam: dict, key_target, key_R, key_t, key_aff, pair_point, pair_key, uv, idepth, color,
                          weight, samplers: dict, huber_th: float = 9.0, border_lo: float = 1.1,
                          border_hi: float = 3.0) -> dict:
    """``{ok, energy, hdd, bd}`` per pair; ``cam``: fx, fy, cx, cy, width, height; ``samplers``: slot ->
    ``sampler(x, y) -> (I, gx, gy)`` (:func:`mgso_kernels.reference.photometric.dI_sampler` of a level-0 image for
    parity, an analytic image for finite differences)."""
    fx, fy, cx, cy, W, H = (cam[k] for k in ("fx", "fy", "cx", "cy", "width", "height"))
    M = len(pair_point)
    out = {"ok": np.zeros(M, bool), "energy": np.zeros(M), "hdd": np.zeros(M), "bd": np.zeros(M)}
    for j in range(M):
        p, k = int(pair_point[j]), int(pair_key[j])
        R = np.asarray(key_R[k], np.float64)
        t = np.asarray(key_t[k], np.float64)
        a_rel, b_rel = float(key_aff[k][0]), float(key_aff[k][1])
        sample = samplers[int(key_target[k])]
        ok, e, h, b = True, 0.0, 0.0, 0.0
        for i in range(8):
            u = float(uv[p][0]) + PATTERN[i, 0]
            v = float(uv[p][1]) + PATTERN[i, 1]
            P = R @ np.array([(u - cx) / fx, (v - cy) / fy, 1.0]) + t * float(idepth[p])
            if not P[2] > 0:
                ok = False
                continue
            un, vn, dres = P[0] / P[2], P[1] / P[2], 1.0 / P[2]
            ku, kv = fx * un + cx, fy * vn + cy
            if not (border_lo < ku < W - border_hi and border_lo < kv < H - border_hi):
                ok = False
                continue
            s = np.array([float(x) for x in sample(ku, kv)])
            if not np.all(np.isfinite(s)):
                ok = False
                continue
            r = s[0] - (a_rel * float(color[p][i]) + b_rel)
            hw = 1.0 if abs(r) < huber_th else huber_th / abs(r)
            gw = float(weight[p][i]) ** 2
            jd = dres * (s[1] * fx * (t[0] - t[2] * un) + s[2] * fy * (t[1] - t[2] * vn))
            e += gw * hw * r * r * (2.0 - hw)
            h += hw * gw * jd * jd
            b += hw * gw * r * jd
        if ok:
            out["ok"][j] = True
            out["energy"][j], out["hdd"][j], out["bd"][j] = e, h, b
    return out


def distance_map(seeds, shape, steps: int = 40) -> np.ndarray:
    """DSO ``growDistBFS`` written as its loops (odd steps 8-neighbours, even steps 4-neighbours; border pixels do
    not grow; 1000 where no step reached)."""
    h, w = shape
    d = np.full((h, w), 1000.0, np.float32)
    q = deque()
    for x, y in np.asarray(seeds).reshape(-1, 2).tolist():
        d[y, x] = 0
        q.append((x, y))
    for k in range(1, steps):
        nq = deque()
        nb = [(1, 0), (-1, 0), (0, 1), (0, -1)]
        if k % 2 == 1:
            nb += [(1, 1), (-1, 1), (-1, -1), (1, -1)]
        for x, y in q:
            if x == 0 or y == 0 or x == w - 1 or y == h - 1:
                continue
            for dx, dy in nb:
                if d[y + dy, x + dx] > k:
                    d[y + dy, x + dx] = k
                    nq.append((x + dx, y + dy))
        q = nq
    return d


def pick_spaced(u, v, jitter, need, stamp, dist) -> np.ndarray:
    """Each candidate in order: taken when ``dist[v, u] + jitter >= need``, then ``dist`` lowered to the stamp around
    it (in place). Candidates outside ``dist`` are skipped."""
    h, w = dist.shape
    r = stamp.shape[0] // 2
    picked = np.zeros(len(u), bool)
    for j in range(len(u)):
        uj, vj = int(u[j]), int(v[j])
        if not (0 <= uj < w and 0 <= vj < h):
            continue
        if float(dist[vj, uj]) + float(jitter[j]) >= float(need[j]):
            picked[j] = True
            for y in range(max(vj - r, 0), min(vj + r + 1, h)):
                for x in range(max(uj - r, 0), min(uj + r + 1, w)):
                    dist[y, x] = min(dist[y, x], stamp[y - vj + r, x - uj + r])
    return picked
