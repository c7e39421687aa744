"""Epipolar search of immature points in a new frame: DSO's ``ImmaturePoint::traceOn`` for many points at once.

One thread per immature point (outputs do not overlap, so CPU launches split over the cores). For a point with host
pixel ``(u, v)`` (level 0), inverse-depth interval ``[idepth_min, idepth_max]`` (``idepth_max`` NaN/inf when
unknown) and its host pattern (``color``, ``weight``, ``grad_h``; :func:`mgso_kernels.photometric.extract_patterns`),
given the host->target ``KRKi = K R K^-1``, ``Kt = K t`` and affine ``(a, b)`` with ``I_t ~ a I_h + b``:

1. project the interval ends; either outside ``(4, w-5) x (4, h-5)`` -> **OOB**; an unknown ``idepth_max`` searches
   ``max_pix_search`` pixels (DSO ``setting_maxPixSearch * (w + h)``) from the ``idepth_min`` end; the projected
   depth ratio at ``idepth_min`` outside ``(0.75, 1.5)`` -> **OOB**;
2. ends closer than ``slack_interval`` (1.5 px) -> **SKIPPED** (nothing to gain);
3. the expected error along the line ``0.2 + 0.2 (a + b)/a`` from the pattern's gradient matrix (``a`` along, ``b``
   across the line); if twice it exceeds the segment -> **BADCONDITION** (gradient perpendicular to the line);
4. discrete search in ``step_size`` (1 px) steps, at most 99 steps (DSO ``errors[100]``), pattern rotated by the
   homography's 2x2 part, Huber energy; best and second best outside ``+-min_test_radius`` steps (quality =
   second / best, kept when lower than the stored quality or when more than 10 steps were taken);
5. up to ``gn_iterations`` Gauss-Newton steps along the line (each clamped to +-0.5 px, halved back when the energy
   grows, stop below ``gn_threshold``), energy weighted by the host pattern weights squared;
6. energy not below ``energy_th * extra_slack_on_th`` -> **OUTLIER** (a second outlier in a row -> **OOB**);
7. otherwise **GOOD**: the new interval is the inverse depth at ``best +- errorInPixel`` along the line.

A point whose last status is OOB is not traced again. Statuses are DSO's ``ImmaturePointStatus`` values.

One deviation: DSO offsets the first search step by the fractional part of ``uMin * 1000`` (a cheap pseudo-random
sub-step shift); here it is an integer hash of the host pixel and a per-call ``seed``, so that the NumPy twin
reproduces it exactly.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
import warp as wp

from . import runtime
from .image import bilinear_inside, finite, sample_intensity
from .photometric import PATTERN, huber_weight, sample8, vec8f

__all__ = [
    "TraceStatus", "TraceParams", "make_trace_params", "trace_points_kernel", "trace_points",
    "host_target_projection", "hash_unit", "MAX_TRACE_STEPS",
]

wp.set_module_options({"enable_backward": False})

MAX_TRACE_STEPS = 100  # DSO: float errors[100]; numSteps capped at 99
vec100f = wp.types.vector(length=MAX_TRACE_STEPS, dtype=wp.float32)


class TraceStatus(IntEnum):
    """DSO ``ImmaturePointStatus``."""

    GOOD = 0  # traced well
    OOB = 1  # out of bounds (or an outlier twice): end tracking and drop/marginalise
    OUTLIER = 2  # energy too high
    SKIPPED = 3  # interval already shorter than slack_interval pixels: not traced
    BADCONDITION = 4  # gradient (nearly) perpendicular to the epipolar line: not traced
    UNINITIALIZED = 5  # never traced


ST_GOOD = wp.constant(0)
ST_OOB = wp.constant(1)
ST_OUTLIER = wp.constant(2)
ST_SKIPPED = wp.constant(3)
ST_BADCONDITION = wp.constant(4)


@wp.struct
class TraceParams:
    huber_th: float  # DSO setting_huberTH = 9
    step_size: float  # setting_trace_stepsize = 1 px
    max_pix_search: float  # pixels: setting_maxPixSearch (0.027) * (w + h)
    min_test_radius: int  # setting_minTraceTestRadius = 2 steps around the best excluded from the second best
    gn_iterations: int  # setting_trace_GNIterations = 3
    gn_threshold: float  # setting_trace_GNThreshold = 0.1 px
    extra_slack_on_th: float  # setting_trace_extraSlackOnTH = 1.2
    slack_interval: float  # setting_trace_slackInterval = 1.5 px
    min_improvement_factor: float  # setting_trace_minImprovementFactor = 2
    energy_th: float  # patternNum * setting_outlierTH * setting_overallEnergyTHWeight^2 = 8 * 144
    border_lo: float  # interval ends must be > 4 px from the left/top ...
    border_hi: float  # ... and < size - 5
    seed: int  # sub-step shift of the first search step (hash of host pixel and seed)


@wp.func
def hash_unit(a: int, b: int, c: int) -> float:
    """A float in [0, 1) from three ints (lowbias32 integer hash); exact in the NumPy twin."""
    x = wp.uint32(a) * wp.uint32(73856093) ^ wp.uint32(b) * wp.uint32(19349663) ^ wp.uint32(c) * wp.uint32(83492791)
    x = x ^ (x >> wp.uint32(16))
    x = x * wp.uint32(0x7FEB352D)
    x = x ^ (x >> wp.uint32(15))
    # 0x846CA68B from two halves: Warp would type the literal int32, which it overflows (clang warned at every
    # compile; the wrapped value was the same)
    x = x * ((wp.uint32(0x846C) << wp.uint32(16)) | wp.uint32(0xA68B))
    x = x ^ (x >> wp.uint32(16))
    return float(x >> wp.uint32(8)) * (1.0 / 16777216.0)


@wp.func
def _inside(x: float, y: float, w: int, h: int, lo: float, hi: float) -> bool:
    return x > lo and y > lo and x < float(w) - hi and y < float(h) - hi


@wp.func
def pattern_at(cx: float, cy: float, r00: float, r01: float, r10: float, r11: float):
    """The 8 pattern pixels around ``(cx, cy)`` under the 2x2 map ``((r00, r01), (r10, r11))``: ``(xs, ys)``,
    computed before they are sampled (the samples' loads then issue together, as ``photometric.sample_pattern``)."""
    xs = vec8f()
    ys = vec8f()
    for k in range(8):
        px = PATTERN[k, 0]
        py = PATTERN[k, 1]
        xs[k] = cx + r00 * px + r01 * py
        ys[k] = cy + r10 * px + r11 * py
    return xs, ys


@wp.kernel
def trace_points_kernel(offset: int,
                        dI_t: wp.array2d(dtype=wp.vec3),  # [H, W] target level 0 (I, dx, dy)
                        host_uv: wp.array(dtype=wp.vec2),  # [N] host pixel (level 0)
                        host_index: wp.array(dtype=wp.int32),  # [N] index into the per-host arrays
                        color: wp.array2d(dtype=float),  # [N, 8] host pattern intensity
                        weight: wp.array2d(dtype=float),  # [N, 8] host pattern gradient weight
                        grad_h: wp.array(dtype=wp.vec3),  # [N] pattern (sum gx^2, sum gx gy, sum gy^2)
                        KRKi: wp.array(dtype=wp.mat33),  # [F] K R K^-1 host -> target
                        Kt: wp.array(dtype=wp.vec3),  # [F] K t host -> target
                        affine: wp.array(dtype=wp.vec2),  # [F] (a, b): I_t ~ a I_h + b
                        params: TraceParams,
                        idepth_min: wp.array(dtype=float),  # [N] in/out
                        idepth_max: wp.array(dtype=float),  # [N] in/out (NaN/inf = unknown)
                        quality: wp.array(dtype=float),  # [N] in/out (DSO starts at 10000)
                        status: wp.array(dtype=wp.int32),  # [N] in: last status, out: new status
                        trace_uv: wp.array(dtype=wp.vec2),  # [N] out: best match (-1, -1 if none)
                        pixel_interval: wp.array(dtype=float),  # [N] out: DSO lastTracePixelInterval
                        energy_out: wp.array(dtype=float)):  # [N] out: final GN energy (NaN if not searched)
    i = offset + wp.tid()
    last = status[i]
    nan = wp.nan
    energy_out[i] = nan
    f = host_index[i]
    if last == ST_OOB or f < 0 or f >= KRKi.shape[0]:  # a bad host index (checked on the CPU) ends the point too
        status[i] = ST_OOB
        trace_uv[i] = wp.vec2(-1.0, -1.0)
        pixel_interval[i] = 0.0
        return
    w = dI_t.shape[1]
    h = dI_t.shape[0]
    M = KRKi[f]
    kt = Kt[f]
    aff = affine[f]
    c = host_uv[i]
    pr = M * wp.vec3(c[0], c[1], 1.0)
    id_min = idepth_min[i]
    id_max = idepth_max[i]
    p_min = pr + kt * id_min
    u_min = p_min[0] / p_min[2]
    v_min = p_min[1] / p_min[2]
    if not _inside(u_min, v_min, w, h, params.border_lo, params.border_hi):
        trace_uv[i] = wp.vec2(-1.0, -1.0)
        pixel_interval[i] = 0.0
        status[i] = ST_OOB
        return
    dist = float(0.0)
    u_max = float(0.0)
    v_max = float(0.0)
    max_known = finite(id_max)
    if max_known:
        p_max = pr + kt * id_max
        u_max = p_max[0] / p_max[2]
        v_max = p_max[1] / p_max[2]
        if not _inside(u_max, v_max, w, h, params.border_lo, params.border_hi):
            trace_uv[i] = wp.vec2(-1.0, -1.0)
            pixel_interval[i] = 0.0
            status[i] = ST_OOB
            return
        dist = wp.sqrt((u_min - u_max) * (u_min - u_max) + (v_min - v_max) * (v_min - v_max))
        if dist < params.slack_interval:
            trace_uv[i] = wp.vec2(0.5 * (u_max + u_min), 0.5 * (v_max + v_min))
            pixel_interval[i] = dist
            status[i] = ST_SKIPPED
            return
    else:
        dist = params.max_pix_search
        p_max = pr + kt * 0.01  # any depth gives the direction
        ddx = p_max[0] / p_max[2] - u_min
        ddy = p_max[1] / p_max[2] - v_min
        d = 1.0 / wp.sqrt(ddx * ddx + ddy * ddy)
        u_max = u_min + dist * ddx * d
        v_max = v_min + dist * ddy * d
        if not _inside(u_max, v_max, w, h, params.border_lo, params.border_hi):
            trace_uv[i] = wp.vec2(-1.0, -1.0)
            pixel_interval[i] = 0.0
            status[i] = ST_OOB
            return
    # scale change too big
    if not (id_min < 0.0 or (p_min[2] > 0.75 and p_min[2] < 1.5)):
        trace_uv[i] = wp.vec2(-1.0, -1.0)
        pixel_interval[i] = 0.0
        status[i] = ST_OOB
        return
    # error bound in pixels from the pattern's gradient structure along / across the line
    dx = params.step_size * (u_max - u_min)
    dy = params.step_size * (v_max - v_min)
    gh = grad_h[i]
    a = dx * dx * gh[0] + 2.0 * dx * dy * gh[1] + dy * dy * gh[2]
    b = dy * dy * gh[0] - 2.0 * dx * dy * gh[1] + dx * dx * gh[2]
    error_px = 0.2 + 0.2 * (a + b) / a
    if error_px * params.min_improvement_factor > dist and max_known:
        trace_uv[i] = wp.vec2(0.5 * (u_max + u_min), 0.5 * (v_max + v_min))
        pixel_interval[i] = dist
        status[i] = ST_BADCONDITION
        return
    if error_px > 10.0:
        error_px = 10.0
    dx = dx / dist
    dy = dy / dist
    if dist > params.max_pix_search:
        u_max = u_min + params.max_pix_search * dx
        v_max = v_min + params.max_pix_search * dy
        dist = params.max_pix_search
    if not (finite(dx) and finite(dy)):
        trace_uv[i] = wp.vec2(-1.0, -1.0)
        pixel_interval[i] = 0.0
        status[i] = ST_OOB
        return
    num_steps = int(1.9999 + dist / params.step_size)
    if num_steps >= MAX_TRACE_STEPS:
        num_steps = MAX_TRACE_STEPS - 1
    shift = hash_unit(int(c[0] + 0.5), int(c[1] + 0.5), params.seed)
    ptx = u_min - shift * dx
    pty = v_min - shift * dy
    r00 = M[0, 0]
    r01 = M[0, 1]
    r10 = M[1, 0]
    r11 = M[1, 1]
    errors = vec100f()
    best_u = float(0.0)
    best_v = float(0.0)
    best_e = float(1e10)
    best_idx = int(-1)
    for s in range(num_steps):
        # the step's 8 samples first (clamped: memory-safe when outside), then its energy: the loads issue
        # together instead of one pixel's at a time behind its branches (as photometric.sample_pattern)
        xs, ys = pattern_at(ptx, pty, r00, r01, r10, r11)
        hits = vec8f()
        for k in range(8):
            hits[k] = sample_intensity(dI_t, xs[k], ys[k])
        e = float(0.0)
        for k in range(8):
            if bilinear_inside(xs[k], ys[k], w, h):
                hit = hits[k]
                if finite(hit):
                    r = hit - (aff[0] * color[i, k] + aff[1])
                    hw = huber_weight(r, params.huber_th)
                    e += hw * r * r * (2.0 - hw)
                else:
                    e += 1e5
            else:
                e += 1e5
        errors[s] = e
        if e < best_e:
            best_u = ptx
            best_v = pty
            best_e = e
            best_idx = s
        ptx += dx
        pty += dy
    second = float(1e10)
    for s in range(num_steps):
        if (s < best_idx - params.min_test_radius or s > best_idx + params.min_test_radius) and errors[s] < second:
            second = errors[s]
    new_quality = second / best_e
    if new_quality < quality[i] or num_steps > 10:
        quality[i] = new_quality
    # Gauss-Newton along the line
    u_bak = best_u
    v_bak = best_v
    step_back = float(0.0)
    if params.gn_iterations > 0:
        best_e = 1e5
    for it in range(params.gn_iterations):
        H = float(1.0)
        bb = float(0.0)
        e = float(0.0)
        xs, ys = pattern_at(best_u, best_v, r00, r01, r10, r11)
        gI, gX, gY = sample8(dI_t, xs, ys)  # the 8 samples first, as in the search
        for k in range(8):
            if bilinear_inside(xs[k], ys[k], w, h):
                hit3 = wp.vec3(gI[k], gX[k], gY[k])
                if finite(hit3[0]):
                    r = hit3[0] - (aff[0] * color[i, k] + aff[1])
                    dres = dx * hit3[1] + dy * hit3[2]
                    hw = huber_weight(r, params.huber_th)
                    H += hw * dres * dres
                    bb += hw * r * dres
                    wk = weight[i, k]
                    e += wk * wk * hw * r * r * (2.0 - hw)
                else:
                    e += 1e5
            else:
                e += 1e5
        if e > best_e:
            step_back = 0.5 * step_back
            best_u = u_bak + step_back * dx
            best_v = v_bak + step_back * dy
        else:
            step = -bb / H
            step = wp.clamp(step, -0.5, 0.5)
            if not finite(step):
                step = 0.0
            u_bak = best_u
            v_bak = best_v
            step_back = step
            best_u += step * dx
            best_v += step * dy
            best_e = e
        if wp.abs(step_back) < params.gn_threshold:
            break
    energy_out[i] = best_e
    if not (best_e < params.energy_th * params.extra_slack_on_th):
        trace_uv[i] = wp.vec2(-1.0, -1.0)
        pixel_interval[i] = 0.0
        if last == ST_OUTLIER:
            status[i] = ST_OOB
        else:
            status[i] = ST_OUTLIER
        return
    # new interval: the inverse depths at best +- error_px along the line
    lo = float(0.0)
    hi = float(0.0)
    if dx * dx > dy * dy:
        xa = best_u - error_px * dx
        xb = best_u + error_px * dx
        lo = (pr[2] * xa - pr[0]) / (kt[0] - kt[2] * xa)
        hi = (pr[2] * xb - pr[0]) / (kt[0] - kt[2] * xb)
    else:
        ya = best_v - error_px * dy
        yb = best_v + error_px * dy
        lo = (pr[2] * ya - pr[1]) / (kt[1] - kt[2] * ya)
        hi = (pr[2] * yb - pr[1]) / (kt[1] - kt[2] * yb)
    if lo > hi:
        tmp = lo
        lo = hi
        hi = tmp
    idepth_min[i] = lo  # DSO stores them before checking (a bad interval makes the next trace OOB)
    idepth_max[i] = hi
    if not (finite(lo) and finite(hi)) or hi < 0.0:
        trace_uv[i] = wp.vec2(-1.0, -1.0)
        pixel_interval[i] = 0.0
        status[i] = ST_OUTLIER
        return
    trace_uv[i] = wp.vec2(best_u, best_v)
    pixel_interval[i] = 2.0 * error_px
    status[i] = ST_GOOD


# ---------------------------------------------------------------------------------------------- launchers
def make_trace_params(width: int, height: int, *, huber_th: float = 9.0, step_size: float = 1.0,
                      max_pix_search: float = 0.027, min_test_radius: int = 2, gn_iterations: int = 3,
                      gn_threshold: float = 0.1, extra_slack_on_th: float = 1.2, slack_interval: float = 1.5,
                      min_improvement_factor: float = 2.0, outlier_th: float = 144.0,
                      overall_energy_th_weight: float = 1.0, seed: int = 0) -> TraceParams:
    """Trace parameters with DSO's defaults (``settings.cpp``). ``width, height``: level-0 image size;
    ``max_pix_search`` is relative to ``width + height`` as in DSO; ``outlier_th`` is per pattern pixel."""
    if width < 16 or height < 16:
        raise ValueError(f"image {width}x{height} too small to trace in")
    if not step_size > 0:
        raise ValueError(f"step_size must be > 0, got {step_size}")
    p = TraceParams()
    p.huber_th = float(huber_th)
    p.step_size = float(step_size)
    p.max_pix_search = float(max_pix_search * (width + height))
    p.min_test_radius = int(min_test_radius)
    p.gn_iterations = int(gn_iterations)
    p.gn_threshold = float(gn_threshold)
    p.extra_slack_on_th = float(extra_slack_on_th)
    p.slack_interval = float(slack_interval)
    p.min_improvement_factor = float(min_improvement_factor)
    p.energy_th = float(8 * outlier_th * overall_energy_th_weight ** 2)
    p.border_lo = 4.0
    p.border_hi = 5.0
    p.seed = int(seed)
    return p


def host_target_projection(K: np.ndarray, target_from_host: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(KRKi [F, 3, 3], Kt [F, 3])`` float32 for ``target_from_host [F, 4, 4]`` (or one ``[4, 4]``) and a level-0
    camera matrix ``K`` shared by host and target (DSO ``traceNewCoarse``)."""
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(target_from_host, dtype=np.float64).reshape(-1, 4, 4)
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got {K.shape}")
    KRKi = K[None] @ T[:, :3, :3] @ np.linalg.inv(K)[None]
    Kt = (K[None] @ T[:, :3, 3:4])[..., 0]
    return KRKi.astype(np.float32), Kt.astype(np.float32)


def _check(name: str, a, dtype, shape) -> None:
    if not isinstance(a, wp.array) or a.dtype != dtype:
        raise TypeError(f"{name}: expected a wp.array of {getattr(dtype, '__name__', dtype)}, got "
                        f"{type(a).__name__} {getattr(getattr(a, 'dtype', None), '__name__', None)}")
    if tuple(a.shape) != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got {tuple(a.shape)}")


def trace_points(dI_t: wp.array, host_uv: wp.array, host_index: wp.array, color: wp.array, weight: wp.array,
                 grad_h: wp.array, KRKi: wp.array, Kt: wp.array, affine: wp.array, params: TraceParams,
                 idepth_min: wp.array, idepth_max: wp.array, quality: wp.array, status: wp.array,
                 trace_uv: wp.array, pixel_interval: wp.array, energy: wp.array,
                 device: str | None = None, split: bool = True) -> None:
    """Trace ``N`` immature points (of ``F`` host keyframes) in a new frame; updates the state arrays in place.

    ``dI_t [H, W] vec3`` the new frame's level 0; per point ``host_uv [N] vec2``, ``host_index [N] int32``,
    ``color, weight [N, 8]``, ``grad_h [N] vec3``; per host ``KRKi [F] mat33``, ``Kt [F] vec3``, ``affine [F]
    vec2`` (:func:`host_target_projection`, ``photometric.affine_from_to``); in/out ``idepth_min, idepth_max,
    quality [N] float32``, ``status [N] int32`` (:class:`TraceStatus`); out ``trace_uv [N] vec2``,
    ``pixel_interval, energy [N] float32``.
    """
    device = device or str(dI_t.device)
    if not isinstance(dI_t, wp.array) or dI_t.ndim != 2 or dI_t.dtype != wp.vec3:
        raise TypeError("dI_t must be a 2-D wp.array of vec3 (I, dx, dy)")
    n = host_uv.shape[0] if isinstance(host_uv, wp.array) else -1
    _check("host_uv", host_uv, wp.vec2, (n,))
    _check("host_index", host_index, wp.int32, (n,))
    _check("color", color, wp.float32, (n, 8))
    _check("weight", weight, wp.float32, (n, 8))
    _check("grad_h", grad_h, wp.vec3, (n,))
    nf = KRKi.shape[0] if isinstance(KRKi, wp.array) else -1
    _check("KRKi", KRKi, wp.mat33, (nf,))
    _check("Kt", Kt, wp.vec3, (nf,))
    _check("affine", affine, wp.vec2, (nf,))
    for name, a in (("idepth_min", idepth_min), ("idepth_max", idepth_max), ("quality", quality),
                    ("pixel_interval", pixel_interval), ("energy", energy)):
        _check(name, a, wp.float32, (n,))
    _check("status", status, wp.int32, (n,))
    _check("trace_uv", trace_uv, wp.vec2, (n,))
    if n and nf <= 0:
        raise ValueError("no host frames given (KRKi is empty)")
    if n and wp.get_device(device).is_cpu:  # a free view on the CPU: check the indices the kernel will follow
        # (on a GPU the copy back would cost a synchronisation: the kernel ends such points as OOB instead)
        hi = host_index.numpy()
        if hi.min() < 0 or hi.max() >= nf:
            raise ValueError(f"host_index must lie in [0, {nf}), got [{hi.min()}, {hi.max()}]")
    if n:
        runtime.launch_split(trace_points_kernel, n,
                             [dI_t, host_uv, host_index, color, weight, grad_h, KRKi, Kt, affine, params,
                              idepth_min, idepth_max, quality, status, trace_uv, pixel_interval, energy],
                             device, min_chunk=64, threads=None if split else 1)

