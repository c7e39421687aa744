"""Inverse-depth residuals of candidate points against the window's keyframes: the per-pair work of point activation
(DSO ``ImmaturePoint::linearizeResidual``, called by ``optimizeImmaturePoint`` when an immature point becomes active).

A **pair** is one candidate point (hosted in keyframe ``h``) and one target keyframe ``t``; pairs of the same
(host, target) keyframes share a **key** holding ``R K^-1``, ``t`` of ``target_from_host`` (current estimates) and the
relative brightness ``(a_rel, b_rel)`` (``I_t ~ a_rel I_h + b_rel``). For each of the 8 pattern pixels
``(u + dx, v + dy)`` of the host: project with the point's inverse depth ``d``, require ``z > 0`` and DSO's margins
``lo < x < w - hi`` (1.1 / 3) and a finite sample of the target's ``(I, gx, gy)``; residual ``r = I_t - (a_rel
I_h + b_rel)``, Huber weight ``hw`` (9), the host's squared gradient weight ``w_h^2`` (DSO's immature points weigh by
the host only), inverse-depth derivative ``J_d = drescale (fx gx (t_x - t_z u_n) + fy gy (t_y - t_z v_n))``.

Per pair (one thread each, no reduction: any split over the CPU cores gives the same bits): ``ok`` (all 8 pixels
good), ``energy = sum w_h^2 hw r^2 (2 - hw)``, ``H_dd = sum hw w_h^2 J_d^2``, ``b_d = sum hw w_h^2 r J_d`` (0 unless
``ok``). The caller (``mgso.tracking.immature_points.optimize_inverse_depths``) sums them per point and runs the
Gauss-Newton iterations.

Two sequential kernels pick which candidates become active (DSO ``activatePointsMT`` with its
``CoarseDistanceMap``): :func:`distance_map` (DSO ``growDistBFS``: breadth-first steps from the active points, at
level 1) and :func:`pick_spaced` (candidates in order, each taken when it is far enough from the points taken before
it, the map then lowered around it by a stamp). Both are one thread, on the CPU: the order is the algorithm. In
NumPy and OpenCV they were 5 % of the odometry's CPU time on KITTI (a dilation an image per step; a Python loop
over the candidates).

Twin: :mod:`mgso_kernels.reference.activation`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from . import runtime
from .photometric import Intrinsics, huber_weight, make_intrinsics, sample_pattern

__all__ = ["DepthParams", "make_depth_params", "DepthPairs", "point_depth_kernel", "point_depth_residuals",
           "DISTANCE_STEPS", "DISTANCE_NONE", "distance_map", "pick_spaced"]

# LLVM's full SLP depth on the CPU (runtime.cpu_flags_full_slp): point_depth_residuals 0.81x the time, the same bits
wp.set_module_options({"enable_backward": False, "cpu_compiler_flags": runtime.cpu_flags_full_slp()})


@wp.struct
class DepthParams:
    cam: Intrinsics  # level-0 intrinsics and image size (every keyframe)
    huber_th: float  # DSO setting_huberTH = 9
    border_lo: float  # projection margins: lo < x < width - hi
    border_hi: float


@wp.kernel
def point_depth_kernel(offset: int,
                       pair_point: wp.array(dtype=wp.int32),  # [M] point index
                       pair_key: wp.array(dtype=wp.int32),  # [M] key index
                       key_target: wp.array(dtype=wp.int32),  # [nk] target slot (index into dI)
                       key_RKi: wp.array(dtype=wp.mat33),  # [nk] R K^-1 of target_from_host
                       key_t: wp.array(dtype=wp.vec3),  # [nk] t of target_from_host
                       key_aff: wp.array(dtype=wp.vec2),  # [nk] (a_rel, b_rel)
                       uv: wp.array(dtype=wp.vec2),  # [n] host pixel (level 0)
                       idepth: wp.array(dtype=float),  # [n] host inverse depth
                       color: wp.array2d(dtype=float),  # [n, 8] host intensity per pattern pixel
                       weight: wp.array2d(dtype=float),  # [n, 8] host gradient weight per pattern pixel
                       dI: wp.array3d(dtype=wp.vec3),  # [slots, H, W] (I, gx, gy) of each keyframe
                       params: DepthParams,
                       out_ok: wp.array(dtype=wp.int32),  # [M] out: 1 when all 8 pixels are good
                       out_energy: wp.array(dtype=float),  # [M] out (0 unless ok)
                       out_hdd: wp.array(dtype=float),  # [M] out: sum hw w^2 J_d^2 (0 unless ok)
                       out_bd: wp.array(dtype=float)):  # [M] out: sum hw w^2 r J_d (0 unless ok)
    j = offset + wp.tid()
    p = pair_point[j]
    k = pair_key[j]
    img = dI[key_target[k]]
    cam = params.cam
    RKi = key_RKi[k]
    t = key_t[k]
    aff = key_aff[k]
    c = uv[p]
    d = idepth[p]
    ok = True
    e = float(0.0)
    h = float(0.0)
    b = float(0.0)
    ps = sample_pattern(c[0], c[1], d, RKi, t, cam, params.border_lo, params.border_hi, img)
    for i in range(8):
        good = ps.good[i] != 0
        if not good:
            ok = False
        r = wp.where(good, ps.intensity[i] - (aff[0] * color[p, i] + aff[1]), 0.0)
        hw = huber_weight(r, params.huber_th)
        wh = weight[p, i]
        gw = wh * wh
        jd = wp.where(good, ps.dr[i] * (ps.gx[i] * cam.fx * (t[0] - t[2] * ps.un[i])
                                        + ps.gy[i] * cam.fy * (t[1] - t[2] * ps.vn[i])), 0.0)
        e += gw * hw * r * r * (2.0 - hw)
        h += hw * gw * jd * jd
        b += hw * gw * r * jd
    out_ok[j] = wp.where(ok, 1, 0)
    out_energy[j] = wp.where(ok, e, 0.0)
    out_hdd[j] = wp.where(ok, h, 0.0)
    out_bd[j] = wp.where(ok, b, 0.0)


def make_depth_params(fx: float, fy: float, cx: float, cy: float, width: int, height: int, *,
                      huber_th: float = 9.0, border_lo: float = 1.1, border_hi: float = 3.0) -> DepthParams:
    """Level-0 intrinsics and DSO's residual constants."""
    if not (fx > 0 and fy > 0) or width < 8 or height < 8:
        raise ValueError(f"bad intrinsics fx={fx} fy={fy} size {width}x{height}")
    p = DepthParams()
    p.cam = make_intrinsics(fx, fy, cx, cy, width, height)
    p.huber_th, p.border_lo, p.border_hi = float(huber_th), float(border_lo), float(border_hi)
    return p


@dataclass
class DepthPairs:
    """Per pair results of :func:`point_depth_residuals` (NumPy)."""

    ok: np.ndarray  # [M] bool
    energy: np.ndarray  # [M] float32
    hdd: np.ndarray  # [M] float32
    bd: np.ndarray  # [M] float32


def point_depth_residuals(params: DepthParams, key_target: np.ndarray, key_R: np.ndarray, key_t: np.ndarray,
                          key_aff: np.ndarray, pair_point: np.ndarray, pair_key: np.ndarray, uv, idepth: np.ndarray,
                          color, weight, images: wp.array, *, device: str | None = None) -> DepthPairs:
    """Residual sums of ``M`` pairs at the points' ``idepth [n]`` (see the module text).

    ``key_target [nk]`` slot of each key's target in ``images`` (``wp.array3d(vec3) [slots, H, W]``, level-0
    ``(I, gx, gy)``, e.g. the window's ``dI0_``); ``key_R [nk, 3, 3]``, ``key_t [nk, 3]`` ``target_from_host``;
    ``key_aff [nk, 2]`` ``(a_rel, b_rel)``; ``pair_point [M]`` index into ``uv [n, 2]`` (pixels), ``idepth``,
    ``color/weight [n, 8]``; ``pair_key [M]`` index into the keys. ``uv``, ``color``, ``weight`` may be wp.arrays on
    ``device`` already (kept across the iterations of one activation: no copies).
    """
    device = device or runtime.device_of(images)
    kt = np.ascontiguousarray(key_target, dtype=np.int32)
    nk = len(kt)
    pp = np.ascontiguousarray(pair_point, dtype=np.int32)
    pk = np.ascontiguousarray(pair_key, dtype=np.int32)
    M = len(pp)
    n = int(uv.shape[0])
    if pk.shape != (M,):
        raise ValueError(f"pair_key must be [{M}], got {pk.shape}")
    if M and (pp.min() < 0 or pp.max() >= n or pk.min() < 0 or pk.max() >= nk):
        raise ValueError("point_depth_residuals: pair_point / pair_key out of range")
    if not isinstance(images, wp.array) or images.dtype != wp.vec3 or images.ndim != 3:
        raise TypeError("images must be a 3-D wp.array of vec3 [slots, H, W] (I, gx, gy)")
    if (images.shape[2], images.shape[1]) != (params.cam.width, params.cam.height):
        raise ValueError(f"images are {images.shape[2]}x{images.shape[1]}, params say "
                         f"{params.cam.width}x{params.cam.height}")
    if nk and (kt.min() < 0 or kt.max() >= images.shape[0]):
        raise ValueError(f"key_target must be slots of the {images.shape[0]} images")
    R = np.asarray(key_R, dtype=np.float64).reshape(nk, 3, 3)
    cam = params.cam
    Ki = np.array([[1.0 / cam.fx, 0.0, -cam.cx / cam.fx], [0.0, 1.0 / cam.fy, -cam.cy / cam.fy], [0.0, 0.0, 1.0]])

    def arr(a, dt, shape_tail):
        if isinstance(a, wp.array):
            return a
        a = np.ascontiguousarray(a, dtype=np.float32)
        if a.shape[1:] != shape_tail or a.shape[0] != n:
            raise ValueError(f"expected [{n}, {', '.join(map(str, shape_tail))}], got {a.shape}")
        return wp.array(a, dtype=dt, device=device, copy=not is_cpu)

    # the launch only reads these: views of the NumPy arrays on the CPU (no copies), copies on a GPU
    is_cpu = wp.get_device(device).is_cpu
    f = lambda a, dt: wp.array(np.ascontiguousarray(a), dtype=dt, device=device, copy=not is_cpu)  # noqa: E731
    out_ok = wp.zeros(M, dtype=wp.int32, device=device)
    out_e = wp.zeros(M, dtype=float, device=device)
    out_h = wp.zeros(M, dtype=float, device=device)
    out_b = wp.zeros(M, dtype=float, device=device)
    if M:
        runtime.launch_split(point_depth_kernel, M,
                             [f(pp, wp.int32), f(pk, wp.int32), f(kt, wp.int32),
                              f((R @ Ki).astype(np.float32), wp.mat33),
                              f(np.asarray(key_t, np.float32).reshape(nk, 3), wp.vec3),
                              f(np.asarray(key_aff, np.float32).reshape(nk, 2), wp.vec2),
                              arr(uv, wp.vec2, (2,)), f(np.asarray(idepth, np.float32).reshape(n), wp.float32),
                              arr(color, wp.float32, (8,)), arr(weight, wp.float32, (8,)), images, params,
                              out_ok, out_e, out_h, out_b], device, min_chunk=2048)
    return DepthPairs(out_ok.numpy().astype(bool), out_e.numpy(), out_h.numpy(), out_b.numpy())


# ------------------------------------------------------------------------------------------ spacing of new points
DISTANCE_STEPS = 40  # DSO growDistBFS: k < 40
DISTANCE_NONE = 1000.0  # the distance of a pixel no step reached


@wp.kernel
def distance_map_kernel(seed_x: wp.array(dtype=wp.int32), seed_y: wp.array(dtype=wp.int32), steps: int,
                        queue: wp.array2d(dtype=wp.int32),  # [2, h * w] scratch: this step's and the next's pixels
                        dist: wp.array2d(dtype=float)):  # [h, w] in: DISTANCE_NONE everywhere; out: the steps
    h = dist.shape[0]
    w = dist.shape[1]
    n = int(0)
    for i in range(seed_x.shape[0]):
        if dist[seed_y[i], seed_x[i]] != 0.0:
            dist[seed_y[i], seed_x[i]] = 0.0
            queue[0, n] = seed_y[i] * w + seed_x[i]
            n += 1
    cur = int(0)
    for k in range(1, steps):
        nxt = 1 - cur
        m = int(0)
        kf = float(k)
        for q in range(n):
            y = queue[cur, q] // w
            x = queue[cur, q] - y * w
            if x > 0 and y > 0 and x < w - 1 and y < h - 1:  # border pixels are reached but do not grow
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        # odd steps: the 8 neighbours; even steps: the 4 (an octagonal distance, as DSO)
                        if (dx != 0 or dy != 0) and (k % 2 == 1 or dx == 0 or dy == 0):
                            if dist[y + dy, x + dx] > kf:
                                dist[y + dy, x + dx] = kf
                                queue[nxt, m] = (y + dy) * w + x + dx
                                m += 1
        n = m
        cur = nxt
        if n == 0:
            break


@wp.kernel
def pick_spaced_kernel(u: wp.array(dtype=wp.int32), v: wp.array(dtype=wp.int32),
                       jitter: wp.array(dtype=wp.float64), need: wp.array(dtype=wp.float64),
                       stamp: wp.array2d(dtype=float),  # [2r+1, 2r+1] the distances from its centre
                       dist: wp.array2d(dtype=float),  # [h, w] in/out: lowered around each point taken
                       picked: wp.array(dtype=wp.int32)):  # [n] out: 1 where taken
    h = dist.shape[0]
    w = dist.shape[1]
    r = stamp.shape[0] // 2
    for j in range(u.shape[0]):
        uj = u[j]
        vj = v[j]
        if uj >= 0 and vj >= 0 and uj < w and vj < h:
            if wp.float64(dist[vj, uj]) + jitter[j] >= need[j]:
                picked[j] = 1
                for y in range(wp.max(vj - r, 0), wp.min(vj + r + 1, h)):
                    sy = y - vj + r
                    for x in range(wp.max(uj - r, 0), wp.min(uj + r + 1, w)):
                        # branch-free, stored either way: the same values as a conditional store, half its time
                        d = dist[y, x]
                        s = stamp[sy, x - uj + r]
                        dist[y, x] = wp.where(s < d, s, d)


def distance_map(seeds: np.ndarray, shape: tuple[int, int], steps: int = DISTANCE_STEPS) -> np.ndarray:
    """DSO ``CoarseDistanceMap::makeDistanceMap``: ``[h, w]`` float32 breadth-first steps to the nearest seed (``seeds
    [N, 2]`` integer ``(x, y)`` inside the image). Only the pixels reached in the previous step grow, by their 8
    neighbours on odd steps and their 4 on even ones; pixels on the image border are reached but do not grow;
    :data:`DISTANCE_NONE` beyond ``steps - 1`` steps. One thread on the CPU (1.3-1.7 ms at KITTI's level 1, 616x184,
    with 200-2,000 seeds; 2026-12-02)."""
    h, w = int(shape[0]), int(shape[1])
    seeds = np.asarray(seeds, dtype=np.int64).reshape(-1, 2)
    if len(seeds) and (seeds.min() < 0 or np.any(seeds[:, 0] >= w) or np.any(seeds[:, 1] >= h)):
        raise ValueError(f"distance_map: seeds outside the {w}x{h} image")
    out = np.full((h, w), DISTANCE_NONE, np.float32)
    if not len(seeds) or h < 1 or w < 1:
        return out
    dist = wp.array(out, dtype=float, device="cpu", copy=False)
    wp.launch(distance_map_kernel, dim=1, device="cpu",
              inputs=[wp.array(np.ascontiguousarray(seeds[:, 0], np.int32), dtype=wp.int32, device="cpu"),
                      wp.array(np.ascontiguousarray(seeds[:, 1], np.int32), dtype=wp.int32, device="cpu"),
                      int(steps), wp.empty((2, h * w), dtype=wp.int32, device="cpu"), dist])
    return out


def pick_spaced(u: np.ndarray, v: np.ndarray, jitter: np.ndarray, need: np.ndarray, stamp: np.ndarray,
                dist: np.ndarray) -> np.ndarray:
    """Candidates in order (``u, v [n]`` integer pixels of ``dist``, those outside it skipped): candidate ``j`` is
    taken when ``dist[v, u] + jitter[j] >= need[j]`` (float64), and then ``dist = min(dist, stamp)`` on the stamp's
    square around it, so later candidates see it. ``dist [h, w]`` float32 (C-contiguous) is updated in place.
    Returns the taken ones ``[n]`` bool. One thread on the CPU."""
    n = len(u)
    if not (len(v) == len(jitter) == len(need) == n):
        raise ValueError("pick_spaced: u, v, jitter and need must have one entry a candidate")
    if dist.dtype != np.float32 or not dist.flags.c_contiguous or dist.ndim != 2:
        raise ValueError("pick_spaced: dist must be a C-contiguous [h, w] float32 array")
    if not n:
        return np.zeros(0, bool)
    picked = wp.zeros(n, dtype=wp.int32, device="cpu")
    f = lambda a, dt, nt: wp.array(np.ascontiguousarray(a, nt), dtype=dt, device="cpu")  # noqa: E731
    wp.launch(pick_spaced_kernel, dim=1, device="cpu",
              inputs=[f(u, wp.int32, np.int32), f(v, wp.int32, np.int32), f(jitter, wp.float64, np.float64),
                      f(need, wp.float64, np.float64), f(stamp, float, np.float32),
                      wp.array(dist, dtype=float, device="cpu", copy=False), picked])
    return picked.numpy().astype(bool)
