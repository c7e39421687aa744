"""Tile-sorted alpha blending, hand-written backward (Warp module): the row kernels (1-16 pixels per thread), the
per-Gaussian gather of the per-pair gradients. (The CPU default backward blend is
:func:`mgso_kernels.splat.raster_tile.rasterize_backward_tile`, dispatched by :func:`launch_rasterize_backward`.)

Warp's ``wp.Tape`` is silently wrong for the blending loop (a runtime-bounded loop carrying ``T``), so this adjoint
is written by hand, as 3DGS and gsplat do: per pixel, back to front from the last accumulated Gaussian
(``n_contrib``), rebuilding the transmittance from ``T_final`` (``T_i = T_{i+1} / (1 - alpha_i)``) and keeping the
sum of what lies behind. With ``G = v_rgb``, ``g_i = c_i . G + z_i v_depth`` and ``S_i = sum_{j > i} w_j g_j``:

    v_alpha_i = T_i g_i - (S_i + T_final (background . G) - T_final v_alpha) / (1 - alpha_i)
    v_c_i = w_i G,   v_z_i = w_i v_depth

then through ``alpha = min(0.99, opacity exp(power))`` (zero where the clamp is active) to the opacity, the conic
and the 2D mean. Threads are tile rows as in :mod:`mgso_kernels.splat.raster`, with the same row spans and the same
``exp`` recurrence, so the skip decisions are the forward's bit for bit.

**Accumulation without cross-thread atomics on the CPU.** A row thread sums, over its pixels, the 16-vector ``(v_mx,
v_my, v_a, v_b, v_c, v_opacity, v_r, v_g, v_b, v_z, |v_mx|, |v_my|, w, 0, 0, 0)`` of each Gaussian and adds it once
into that pair's *slot* (one per (tile, Gaussian) pair, see :mod:`mgso_kernels.splat.bin`). All rows of a tile run
on one CPU thread (chunks are whole tiles), so the adds are never concurrent on the CPU; on CUDA ``wp.atomic_add``
is atomic. Then :func:`gather_gaussian_grads` sums each Gaussian's contiguous slot range. The CPU result is bitwise
identical however the launch is split. Components 10-11 are the AbsGS statistic (the sum over pixels of the absolute
per-pixel 2D-mean gradient), 12 the sum of the Gaussian's blending weights ``w = alpha T`` over the pixels that took
it (not a gradient: how much of the view the Gaussian makes, zero for one hidden behind opaque Gaussians in every
pixel; the densification's ``prune_weight_px``); 13-15 are padding (a row of 64 bytes).

Twin: :func:`mgso_kernels.reference.splat.render_vjp`.
"""

from __future__ import annotations

import os
import platform

import warp as wp

from .camera import TILE_SIZE, Camera
from .common import ALPHA_MAX, ALPHA_MIN, vec8, vec16, vec16i
from .raster import row_span, segment_threads, span_exp_start, tile_row

wp.set_module_options({"enable_backward": False})

__all__ = ["GATHER_BLOCK", "gather_gaussian_grads", "gather_gaussian_grads_blocks", "rasterize_backward"]


@wp.kernel
def rasterize_backward(
    offset: int,
    cam: Camera,
    seg: int,  # pixels per thread, as the forward
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
    splats: wp.array(dtype=vec8),  # [M] packed, sorted (forward's)
    splat_rgbz: wp.array(dtype=wp.vec4),  # [M] r, g, b, depth
    slots: wp.array(dtype=wp.int32),  # [M] sorted pair slots
    background: wp.vec3,
    T_final: wp.array2d(dtype=float),  # [H, W] forward's
    n_contrib: wp.array2d(dtype=wp.int32),  # [H, W] forward's
    v_rgb: wp.array3d(dtype=float),  # [H, W, 3] upstream
    v_depth: wp.array2d(dtype=float),  # [H, W] upstream
    v_alpha: wp.array2d(dtype=float),  # [H, W] upstream
    use_depth: int,  # 0: v_depth ignored (may be a dummy)
    use_alpha: int,  # 0: v_alpha ignored
    pair_grads: wp.array(dtype=vec16),  # [M] in/out (zeroed by the caller), indexed by slot
):
    tr = tile_row(offset + wp.tid(), cam, seg)
    tile = tr[0]
    x0 = tr[1]
    y = tr[2]
    nx = tr[3]
    if nx <= 0:
        return
    start = ranges[tile, 0]
    fy = float(y)
    T = vec16(0.0)
    S = vec16(0.0)  # sum over the Gaussians behind of w g, plus the background's and alpha's share
    Gr = vec16(0.0)
    Gg = vec16(0.0)
    Gb = vec16(0.0)
    VD = vec16(0.0)
    nc = vec16i(0)
    n_max = int(0)
    for k in range(nx):
        x = x0 + k
        Tf = T_final[y, x]
        T[k] = Tf
        Gr[k] = v_rgb[y, x, 0]
        Gg[k] = v_rgb[y, x, 1]
        Gb[k] = v_rgb[y, x, 2]
        vA = float(0.0)
        if use_depth != 0:
            VD[k] = v_depth[y, x]
        if use_alpha != 0:
            vA = v_alpha[y, x]
        # the background's and alpha's share of d loss / d alpha_i, times (1 - alpha_i)
        S[k] = Tf * (background[0] * Gr[k] + background[1] * Gg[k] + background[2] * Gb[k] - vA)
        nc[k] = n_contrib[y, x]
        n_max = wp.max(n_max, nc[k])
    # pixels in decreasing n_contrib order, so the set of pixels a list position can reach (n_contrib > i) grows
    # by a pointer as i goes down
    order = vec16i(0)
    for k in range(nx):
        order[k] = k
    for k in range(1, nx):
        kk = order[k]
        q = k
        while q > 0 and nc[order[q - 1]] < nc[kk]:
            order[q] = order[q - 1]
            q -= 1
        order[q] = kk
    active = int(0)
    ptr = int(0)
    for jj in range(n_max):
        i = n_max - 1 - jj  # position in the tile list, back to front
        while ptr < nx and nc[order[ptr]] > i:
            active = active | (1 << order[ptr])
            ptr += 1
        j = start + i
        s = splats[j]
        dy = fy - s[1]
        span = row_span(s, dy, x0, nx)
        if span[0] > span[1]:
            continue
        if active & (((1 << (span[1] - span[0] + 1)) - 1) << span[0]) == 0:
            continue
        e = span_exp_start(s, float(x0 + span[0]) - s[0], dy)
        E = e[0]
        F = e[1]
        col = splat_rgbz[j]
        # per-span sums; dy is constant along the row and dx steps by 1, so the conic and mean gradients factor:
        # sum_px (a dx + b dy) v_pow = a P1 + b dy P0, sum_px -0.5 dx^2 v_pow = -0.5 P2, ...
        P0 = float(0.0)  # sum v_pow
        P1 = float(0.0)  # sum dx v_pow
        P2 = float(0.0)  # sum dx^2 v_pow
        v_op = float(0.0)
        v_cr = float(0.0)
        v_cg = float(0.0)
        v_cb = float(0.0)
        v_z = float(0.0)
        abs_x = float(0.0)
        abs_y = float(0.0)
        v_w = float(0.0)  # sum of the blending weights w
        hit = int(0)
        dx = float(x0 + span[0]) - s[0]
        for k in range(span[0], span[1] + 1):
            if (active >> k) & 1 != 0:
                r = s[5] * E
                a = wp.min(ALPHA_MAX, r)
                if a >= ALPHA_MIN:
                    hit = 1
                    inv = 1.0 / (1.0 - a)
                    Tk = T[k] * inv  # transmittance in front of this Gaussian
                    T[k] = Tk
                    w = a * Tk
                    gi = col[0] * Gr[k] + col[1] * Gg[k] + col[2] * Gb[k] + col[3] * VD[k]
                    v_a = Tk * gi - S[k] * inv
                    S[k] = S[k] + w * gi
                    v_r = float(0.0)
                    if r <= ALPHA_MAX:  # no gradient through the 0.99 clamp
                        v_r = v_a
                    v_pow = v_r * r
                    P0 += v_pow
                    P1 += dx * v_pow
                    P2 += dx * dx * v_pow
                    m = wp.abs(v_pow)
                    abs_x += wp.abs(s[2] * dx + s[3] * dy) * m
                    abs_y += wp.abs(s[3] * dx + s[4] * dy) * m
                    v_op += v_r * E
                    v_cr += w * Gr[k]
                    v_cg += w * Gg[k]
                    v_cb += w * Gb[k]
                    v_z += w * VD[k]
                    v_w += w
            E = E * F
            F = F * s[6]
            dx = dx + 1.0
        acc = vec16(s[2] * P1 + s[3] * dy * P0, s[3] * P1 + s[4] * dy * P0, -0.5 * P2, -dy * P1, -0.5 * dy * dy * P0,
                    v_op, v_cr, v_cg, v_cb, v_z, abs_x, abs_y, v_w, 0.0, 0.0, 0.0)
        if hit != 0:
            wp.atomic_add(pair_grads, slots[j], acc)


@wp.func
def gather_one(g: int, pair_offsets: wp.array(dtype=wp.int32), tiles_touched: wp.array(dtype=wp.int32),
               pair_grads: wp.array(dtype=vec16), v_means2d: wp.array(dtype=wp.vec2), v_conics: wp.array(dtype=wp.vec3),
               v_opacities: wp.array(dtype=float), v_colors: wp.array(dtype=wp.vec3), v_depths: wp.array(dtype=float),
               absgrad: wp.array(dtype=wp.vec2), weights: wp.array(dtype=float)):
    """Gaussian ``g``'s slots summed (see :func:`gather_gaussian_grads`)."""
    acc = vec16(0.0)
    p0 = pair_offsets[g]
    for p in range(p0, p0 + tiles_touched[g]):
        acc += pair_grads[p]
    v_means2d[g] = wp.vec2(acc[0], acc[1])
    v_conics[g] = wp.vec3(acc[2], acc[3], acc[4])
    v_opacities[g] = acc[5]
    v_colors[g] = wp.vec3(acc[6], acc[7], acc[8])
    v_depths[g] = acc[9]
    absgrad[g] = wp.vec2(acc[10], acc[11])
    weights[g] = acc[12]


@wp.kernel
def gather_gaussian_grads(
    offset: int,
    pair_offsets: wp.array(dtype=wp.int32),  # [N] first slot of each Gaussian
    tiles_touched: wp.array(dtype=wp.int32),  # [N] number of slots
    pair_grads: wp.array(dtype=vec16),  # [M] by slot
    v_means2d: wp.array(dtype=wp.vec2),  # [N] out, d/d mean2d (pixels)
    v_conics: wp.array(dtype=wp.vec3),  # [N] out
    v_opacities: wp.array(dtype=float),  # [N] out, d/d opacity (after the sigmoid)
    v_colors: wp.array(dtype=wp.vec3),  # [N] out
    v_depths: wp.array(dtype=float),  # [N] out, through the depth output only
    absgrad: wp.array(dtype=wp.vec2),  # [N] out, sum over pixels of |per-pixel v_mean2d|
    weights: wp.array(dtype=float),  # [N] out, sum over pixels of the blending weight w = alpha T
):
    gather_one(offset + wp.tid(), pair_offsets, tiles_touched, pair_grads, v_means2d, v_conics, v_opacities,
               v_colors, v_depths, absgrad, weights)


# The CPU's gather in C++ blocks (a native snippet): a Gaussian's slots summed 16 floats a vector in slot order, the
# same additions as the kernel's vec16 sum (the same bits, tested with runtime.use_native off), where Warp's code
# indexed each slot's floats one at a time (the gather was 2 % of a 160x120 training step on one Zen 4 thread).
# Returns 0 where the arrays are not contiguous (nothing written), and the kernel's loop runs.
_GATHER_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
{
#pragma clang fp contract(off)
if (pair_offsets.strides[0] != 4 || tiles_touched.strides[0] != 4 || pair_grads.strides[0] != 64
    || v_means2d.strides[0] != 8 || v_conics.strides[0] != 12 || v_opacities.strides[0] != 4
    || v_colors.strides[0] != 12 || v_depths.strides[0] != 4 || absgrad.strides[0] != 8
    || weights.strides[0] != 4) return 0;
typedef float v16f_ __attribute__((ext_vector_type(16)));
const int* PO = (const int*)pair_offsets.data;
const int* TT = (const int*)tiles_touched.data;
const float* PG = (const float*)pair_grads.data;
float* M2 = (float*)v_means2d.data;
float* CO = (float*)v_conics.data;
float* OP = (float*)v_opacities.data;
float* CL = (float*)v_colors.data;
float* DZ = (float*)v_depths.data;
float* AB = (float*)absgrad.data;
float* WS = (float*)weights.data;
for (int g = lo; g < hi; ++g) {
    v16f_ acc = 0.0f;
    const int t = TT[g];
    const float* p = PG + 16L * (t > 0 ? PO[g] : 0);
    for (int k = 0; k < t; ++k) {
        v16f_ x;
        __builtin_memcpy(&x, p + 16L * k, sizeof x);
        acc = acc + x;
    }
    M2[2L * g] = acc[0]; M2[2L * g + 1] = acc[1];
    CO[3L * g] = acc[2]; CO[3L * g + 1] = acc[3]; CO[3L * g + 2] = acc[4];
    OP[g] = acc[5];
    CL[3L * g] = acc[6]; CL[3L * g + 1] = acc[7]; CL[3L * g + 2] = acc[8];
    DZ[g] = acc[9];
    AB[2L * g] = acc[10]; AB[2L * g + 1] = acc[11];
    WS[g] = acc[12];
}
return 1;
}
#else
return 0;
#endif
"""


@wp.func_native(_GATHER_CPP)
def gather_cpp(lo: int, hi: int, pair_offsets: wp.array(dtype=wp.int32), tiles_touched: wp.array(dtype=wp.int32),
               pair_grads: wp.array(dtype=vec16), v_means2d: wp.array(dtype=wp.vec2),
               v_conics: wp.array(dtype=wp.vec3), v_opacities: wp.array(dtype=float),
               v_colors: wp.array(dtype=wp.vec3), v_depths: wp.array(dtype=float), absgrad: wp.array(dtype=wp.vec2),
               weights: wp.array(dtype=float)) -> int:
    """:func:`gather_gaussian_grads` for the Gaussians ``[lo, hi)`` in C++ (above). Returns 1, or 0 where it does
    not apply (nothing written)."""
    ...


@wp.kernel
def gather_gaussian_grads_blocks(offset: int, block: int, n: int, pair_offsets: wp.array(dtype=wp.int32),
                                 tiles_touched: wp.array(dtype=wp.int32), pair_grads: wp.array(dtype=vec16),
                                 v_means2d: wp.array(dtype=wp.vec2), v_conics: wp.array(dtype=wp.vec3),
                                 v_opacities: wp.array(dtype=float), v_colors: wp.array(dtype=wp.vec3),
                                 v_depths: wp.array(dtype=float), absgrad: wp.array(dtype=wp.vec2),
                                 weights: wp.array(dtype=float), native: int, status: wp.array(dtype=wp.int32)):
    """:func:`gather_gaussian_grads` with ``block`` Gaussians a thread, for the CPU: the C++ block, this loop where
    it declines; ``status`` 1 where the C++ block ran."""
    c = offset + wp.tid()
    lo = c * block
    hi = wp.min(lo + block, n)
    done = int(0)
    if native != 0:
        done = gather_cpp(lo, hi, pair_offsets, tiles_touched, pair_grads, v_means2d, v_conics, v_opacities,
                          v_colors, v_depths, absgrad, weights)
    status[c] = done
    if done == 0:
        for g in range(lo, hi):
            gather_one(g, pair_offsets, tiles_touched, pair_grads, v_means2d, v_conics, v_opacities, v_colors,
                       v_depths, absgrad, weights)


#: Gaussians a thread of the CPU's gather (:func:`gather_gaussian_grads_blocks`).
GATHER_BLOCK = 1024


# ------------------------------------------------------------------------------------------------- launchers
def _narrow_backward_pixels() -> int:
    """:data:`NARROW_BACKWARD_PIXELS`' value: ``$MGSO_NARROW_BACKWARD_PIXELS`` where set, else by the CPU's maker, as
    measured (the same gradients either way, bit for bit: ``tests/kernels/test_splat_tile.py``):

    - Intel (a 2-core Xeon with AVX-512, 2026-12-07, before the 16-lane listing by compress and the mask registers;
      backward blend, one thread, 16 -> 8 lanes, real maps, ``profiles/splat_raster.py --run DIR --downscale N``):
      7-Scenes 160x120 19.2 -> 15.4 ms, 213x160 24.4 -> 22.6, 320x240 36.5 -> 40.2 (slower), KITTI 310x94 23.0 ->
      17.6, 620x188 42.5 -> 42.8: 8 lanes up to 40,000 pixels;
    - AMD (a 2-core EPYC, Zen 4, 2026-12-08, with them; three rounds alternated): 7-Scenes 160x120 8 -> 16 lanes
      11.3-13.1 -> 9.5-11.7 ms, KITTI 310x94 12.1-15.3 -> 11.5-13.0 ms; the deterministic KITTI run 163.1 / 170.0 s
      against 176.0 s between them, 7-Scenes 146.0 against 148.4 s, the same maps: 16 lanes at every size (0).

    Where the CPU has no AVX-512 both are 8 lanes. Read once, at import (docs/rasteriser.md)."""
    env = os.environ.get("MGSO_NARROW_BACKWARD_PIXELS")
    if env is not None:
        try:
            value = int(env)
        except ValueError:
            raise ValueError(f"MGSO_NARROW_BACKWARD_PIXELS={env!r}: a number of pixels (0: never 8 lanes)") from None
        if value < 0:
            raise ValueError(f"MGSO_NARROW_BACKWARD_PIXELS={env!r}: a number of pixels (0: never 8 lanes)")
        return value
    vendor = ""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("vendor_id"):
                    vendor = line
                    break
    except OSError:
        vendor = platform.processor()
    return 0 if "AMD" in vendor else 40_000


#: On the CPU, images of at most this many pixels take the backward tile snippet at 8 lanes (half a tile row a vector)
#: where the CPU has 16: the same gradients bit for bit, and where most Gaussians reach a few pixels of a tile row the
#: 16-lane vector mostly blends empty lanes. Which is faster depends on the CPU (:func:`_narrow_backward_pixels`).
NARROW_BACKWARD_PIXELS = _narrow_backward_pixels()


def launch_rasterize_backward(cam: Camera, ranges, splats, splat_rgbz, slots, background, T_final, n_contrib, v_rgb,
                              v_depth, v_alpha, pair_grads, n_pairs: int, device: str,
                              threads: int | None = None, min_chunk: int = 4096, seg: int = TILE_SIZE,
                              absgrad: bool = True) -> None:
    """Per-pair gradients (zeroed here, then accumulated) from the upstream image gradients.

    ``v_depth`` / ``v_alpha`` may be ``None`` (no gradient through that output). ``absgrad=False`` lets the tile
    kernel (``seg`` 256) skip the AbsGS sums (components 10, 11 stay 0); the row kernels compute them anyway
    (``Rasterizer.backward`` zeroes them after the gather, so that the result is the same on every path).
    """
    from ..runtime import _is_cpu, launch_split
    from ._checks import check_array
    H, W = cam.height, cam.width
    check_array(v_rgb, "v_rgb", wp.float32, (H, W, 3), device)
    use_depth = 0 if v_depth is None else 1
    use_alpha = 0 if v_alpha is None else 1
    if v_depth is not None:
        check_array(v_depth, "v_depth", wp.float32, (H, W), device)
    else:
        v_depth = T_final  # never read
    if v_alpha is not None:
        check_array(v_alpha, "v_alpha", wp.float32, (H, W), device)
    else:
        v_alpha = T_final
    if pair_grads.shape[0] < n_pairs:
        raise ValueError(f"rasterize_backward: pair_grads holds {pair_grads.shape[0]}, need {n_pairs}")
    pair_grads[:n_pairs].zero_()
    dim, per_tile = segment_threads(cam, seg)
    if seg == TILE_SIZE * TILE_SIZE:
        from . import raster_tile as rt

        narrow = W * H <= NARROW_BACKWARD_PIXELS and _is_cpu(device)
        if absgrad:
            kernels = ((rt.rasterize_backward_tile_narrow, rt.rasterize_backward_tile_narrow_dynamic) if narrow
                       else (rt.rasterize_backward_tile, rt.rasterize_backward_tile_dynamic))
        else:
            kernels = ((rt.rasterize_backward_tile_noabs_narrow, rt.rasterize_backward_tile_noabs_narrow_dynamic)
                       if narrow else (rt.rasterize_backward_tile_noabs, rt.rasterize_backward_tile_noabs_dynamic))
        rt.launch_tiles(*kernels, dim,
                        [cam, ranges, splats, splat_rgbz, slots, wp.vec3(*background), T_final, n_contrib, v_rgb,
                         v_depth, v_alpha, use_depth, use_alpha, rt.BWD_ACC_ROWS, pair_grads], device,
                        threads=threads, min_chunk=max(1, min_chunk // seg))
        return
    launch_split(rasterize_backward, dim,
                 [cam, seg, ranges, splats, splat_rgbz, slots, wp.vec3(*background), T_final, n_contrib, v_rgb,
                  v_depth, v_alpha, use_depth, use_alpha, pair_grads], device,
                 threads=threads, min_chunk=max(1, min_chunk // seg), align=per_tile)


def launch_gather_gaussian_grads(pair_offsets, tiles_touched, pair_grads, v_means2d, v_conics, v_opacities, v_colors,
                                 v_depths, absgrad, weights, device: str, threads: int | None = None,
                                 min_chunk: int = 4096):
    """Sum each Gaussian's slot range into per-Gaussian screen-space gradients and blending weights (all outputs
    overwritten). On the CPU returns the call's per-block status (1 where the C++ block ran), else None."""
    from ..runtime import launch_blocks, launch_split, native_flag

    n = v_means2d.shape[0]
    inputs = [pair_offsets, tiles_touched, pair_grads, v_means2d, v_conics, v_opacities, v_colors, v_depths, absgrad,
              weights]
    if str(device).startswith("cpu"):
        return launch_blocks(gather_gaussian_grads_blocks, n, GATHER_BLOCK, inputs, native_flag(), device,
                             threads=threads, min_chunk=min_chunk)
    launch_split(gather_gaussian_grads, n, inputs, device, threads=threads, min_chunk=min_chunk)
    return None
