"""Tile-sorted alpha blending, forward (Warp module): the kernels with 1-16 pixels of a tile row per thread.

(The CPU default is :mod:`mgso_kernels.splat.raster_tile`, a thread per tile with the row's pixels in SIMD lanes;
these kernels are the CUDA path, ``pixels_per_thread=1``, and are selectable on the CPU.)

**Work split.** One thread per *tile row*: thread ``i`` shades the 16 pixels of row ``i % 16`` of the tile in slot
``i // 16``, so a contiguous chunk of threads (what :func:`mgso_kernels.runtime.launch_split` gives one CPU core,
``align=16``) is a set of whole tiles. Slots visit tiles in an interleaved order (``tile = slot * stride mod
tiles``, stride coprime, near tiles / golden ratio), so each core gets tiles from all over the image and a scene
that is busy in one half does not leave the other core idle. Per Gaussian of the tile's depth-sorted list the thread
computes the exact span of the row inside the Gaussian's cut-off ellipse (``opacity exp(power) >= 1/255``, one
``sqrt``) and touches only the pixels in that span; along the span ``exp(power)`` follows the recurrence
``E(x+1) = E(x) F(x)``, ``F(x+1) = F(x) exp(-a)`` (the power is quadratic in x; ``exp(-a)`` is precomputed per
Gaussian), so a row costs two ``exp`` per Gaussian instead of one per pixel. Single-threaded on this 2-core CPU
that was 2.2x faster than a thread per pixel testing every list entry (docs/rasteriser.md has the measurements).
The backward pass uses the same spans and recurrence, so both passes make the same skip decisions bit for bit.

**Rules** (3DGS's, per pixel, front to back): ``power = -0.5 (a dx^2 + c dy^2) - b dx dy`` with
``(dx, dy) = (u, v) - mean2d`` (pixel (row v, col u) is sampled at (u, v)); ``alpha = min(0.99, opacity exp(power))``;
skip if ``alpha < 1/255``; if ``T (1 - alpha) < 1e-4`` the pixel stops *without* accumulating; else
``w = alpha T`` is accumulated and ``T *= 1 - alpha``. (3DGS also skips ``power > 0``, which a positive-definite
conic never produces; pixels outside the cut-off ellipse, the only ones the span excludes, have
``alpha < 1/255``.) Outputs: ``rgb = sum w c + T_final background``, ``depth = sum w z`` (camera z, **not**
normalised: divide by ``alpha`` for the depth of the visible surface), ``alpha = 1 - T_final``, and for the
backward pass ``T_final`` and ``n_contrib`` (1 + the position in the tile list of the last accumulated Gaussian; 0
if none).

**Packing.** Before blending, :func:`pack_splats` copies each sorted pair's Gaussian data (mean, conic, opacity,
depth, cut-off radius^2, colour) into contiguous arrays in sorted order, so the blend streams memory instead of
gathering by Gaussian index (measured in docs/rasteriser.md).

Twin: :func:`mgso_kernels.reference.splat.render`.
"""

from __future__ import annotations

import warp as wp

from .camera import TILE_SIZE, Camera
from .common import ALPHA_MAX, ALPHA_MIN, T_MIN, vec8, vec16, vec16i

wp.set_module_options({"enable_backward": False})

__all__ = ["pack_splats", "pack_splats_blocks", "pack_pair", "PACK_BLOCK", "rasterize_forward", "rasterize_alpha",
           "rasterize_alpha_depth", "vec8", "vec16", "vec16i", "row_span", "ALPHA_MIN", "ALPHA_MAX", "T_MIN",
           "SEGMENT_WIDTHS", "segment_threads"]

TS = wp.constant(TILE_SIZE)
SEGMENT_WIDTHS = (1, 2, 4, 8, 16, TILE_SIZE * TILE_SIZE)  # pixels per thread the blend kernels accept; 256 = a
# whole tile per thread, lanes vectorised (mgso_kernels.splat.raster_tile, the CPU default)


def segment_threads(cam: Camera, seg: int) -> tuple[int, int]:
    """(threads of a blend launch, threads per tile) for segments of ``seg`` pixels."""
    if seg not in SEGMENT_WIDTHS:
        raise ValueError(f"pixels per thread must be one of {SEGMENT_WIDTHS}, got {seg}")
    if seg == TILE_SIZE * TILE_SIZE:
        return cam.tiles_x * cam.tiles_y, 1
    per_tile = TILE_SIZE * (TILE_SIZE // seg)
    return cam.tiles_x * cam.tiles_y * per_tile, per_tile


@wp.func
def tile_row(i: int, cam: Camera, seg: int) -> wp.vec4i:
    """Thread index -> (tile, first column, row y, number of columns of the segment inside the image; 0: none).

    A thread shades ``seg`` consecutive pixels of one tile row (16: the whole row). Consecutive groups of
    ``16 * 16 / seg`` threads are whole tiles, visited in the interleaved order of ``cam.tile_stride``.
    """
    nseg = TS // seg
    per_tile = TS * nseg
    slot = i // per_tile
    rem = i - slot * per_tile
    r = rem // nseg
    sg = rem - r * nseg
    tile = (slot * cam.tile_stride) % (cam.tiles_x * cam.tiles_y)
    ty = tile // cam.tiles_x
    tx = tile - ty * cam.tiles_x
    y = ty * TS + r
    x0 = tx * TS + sg * seg
    nx = wp.min(seg, cam.width - x0)
    if y >= cam.height:
        nx = 0
    return wp.vec4i(tile, x0, y, nx)


@wp.func
def row_span(s: vec8, dy: float, x0: int, nx: int) -> wp.vec2i:
    """Columns [lo, hi] of the row (relative to x0, clipped to [0, nx)) inside the cut-off ellipse; lo > hi: none.

    ``s`` = (mx, my, a, b, c, opacity, exp(-a), r2); the ellipse is a dx^2 + 2 b dx dy + c dy^2 <= r2.
    """
    a = s[2]
    b = s[3]
    disc = a * s[7] - (a * s[4] - b * b) * dy * dy
    if disc < 0.0:
        return wp.vec2i(1, 0)
    half = wp.sqrt(disc) / a
    xc = s[0] - b * dy / a
    lo = wp.max(int(wp.ceil(xc - half)) - x0, 0)
    hi = wp.min(int(wp.floor(xc + half)) - x0, nx - 1)
    return wp.vec2i(lo, hi)


@wp.func
def span_exp_start(s: vec8, dx: float, dy: float) -> wp.vec2:
    """(E, F) at the first pixel of a span: E = exp(power), F = exp(power(x+1) - power(x)); then per pixel
    E *= F, F *= exp(-a) (= s[6])."""
    a = s[2]
    b = s[3]
    power = -0.5 * (a * dx * dx + s[4] * dy * dy) - b * dx * dy
    step = -(a * dx + b * dy) - 0.5 * a
    return wp.vec2(wp.exp(power), wp.exp(step))


@wp.func
def pack_pair(j: int, slots: wp.array(dtype=wp.int32), pair_gauss: wp.array(dtype=wp.int32),
              splat_g: wp.array(dtype=vec8), rgbz_g: wp.array(dtype=wp.vec4), depths_g: wp.array(dtype=float),
              with_color: int, splats: wp.array(dtype=vec8), splat_rgbz: wp.array(dtype=wp.vec4)):
    """Sorted pair ``j`` gets its Gaussian's data (see :func:`pack_splats`)."""
    g = pair_gauss[slots[j]]
    splats[j] = splat_g[g]
    if with_color == 1:
        splat_rgbz[j] = rgbz_g[g]
    elif with_color == 2:
        splat_rgbz[j] = wp.vec4(0.0, 0.0, 0.0, depths_g[g])


# The CPU's pack in C++ (a native snippet): a block of 32 pairs looks up its Gaussians first, then copies their data,
# so the block's dependent loads (slot -> Gaussian -> data, each a cache miss on a large map) overlap instead of
# waiting one pair at a time; the copy is the same bytes. 1.65 against 3.44 ms for 245k pairs and 11.0 against 52.0
# ms for 972k (50k and 200k Gaussians, one Zen 3 thread; docs/rasteriser.md). Returns 0 (nothing written) where the
# arrays are not contiguous, and on CUDA, where :func:`pack_splats` runs a thread per pair.
_PACK_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
if (slots.strides[0] != 4 || pair_gauss.strides[0] != 4 || splat_g.strides[0] != 32 || rgbz_g.strides[0] != 16
    || depths_g.strides[0] != 4 || splats.strides[0] != 32 || splat_rgbz.strides[0] != 16) return 0;
const int* sl = (const int*)slots.data;
const int* pg = (const int*)pair_gauss.data;
const float* sg = (const float*)splat_g.data;
const float* cg = (const float*)rgbz_g.data;
const float* dg = (const float*)depths_g.data;
float* so = (float*)splats.data;
float* co = (float*)splat_rgbz.data;
int g[32];
for (int j0 = lo; j0 < hi; j0 += 32) {
    const int m = hi - j0 < 32 ? hi - j0 : 32;
    for (int k = 0; k < m; ++k) g[k] = pg[sl[j0 + k]];
    for (int k = 0; k < m; ++k) {
        __builtin_memcpy(so + 8L * (j0 + k), sg + 8L * g[k], 32);
        if (with_color == 1) {
            __builtin_memcpy(co + 4L * (j0 + k), cg + 4L * g[k], 16);
        } else if (with_color == 2) {
            float* c = co + 4L * (j0 + k);
            c[0] = 0.0f; c[1] = 0.0f; c[2] = 0.0f; c[3] = dg[g[k]];
        }
    }
}
return 1;
#else
return 0;
#endif
"""


@wp.func_native(_PACK_CPP)
def pack_splats_cpp(lo: int, hi: int, slots: wp.array(dtype=wp.int32), pair_gauss: wp.array(dtype=wp.int32),
                    splat_g: wp.array(dtype=vec8), rgbz_g: wp.array(dtype=wp.vec4), depths_g: wp.array(dtype=float),
                    with_color: int, splats: wp.array(dtype=vec8), splat_rgbz: wp.array(dtype=wp.vec4)) -> int:
    """:func:`pack_splats` for the pairs ``[lo, hi)`` in C++ (above): the same bytes. Returns 1, or 0 where it does
    not apply (nothing written)."""
    ...


@wp.kernel
def pack_splats_blocks(
    offset: int,
    block: int,  # pairs a thread
    n_pairs: int,
    slots: wp.array(dtype=wp.int32),
    pair_gauss: wp.array(dtype=wp.int32),
    splat_g: wp.array(dtype=vec8),
    rgbz_g: wp.array(dtype=wp.vec4),
    depths_g: wp.array(dtype=float),
    with_color: int,
    splats: wp.array(dtype=vec8),
    splat_rgbz: wp.array(dtype=wp.vec4),
    native: int,  # 1: the C++ block where it applies; 0: this kernel's loop (raster_tile.use_native)
    status: wp.array(dtype=wp.int32),  # [threads] out: 1 where the C++ block did the pairs
):
    """:func:`pack_splats` with ``block`` pairs a thread, for the CPU: the C++ block first, this loop where it
    declines."""
    c = offset + wp.tid()
    lo = c * block
    hi = wp.min(lo + block, n_pairs)
    done = int(0)
    if native != 0:
        done = pack_splats_cpp(lo, hi, slots, pair_gauss, splat_g, rgbz_g, depths_g, with_color, splats,
                               splat_rgbz)
    status[c] = done
    if done == 0:
        for j in range(lo, hi):
            pack_pair(j, slots, pair_gauss, splat_g, rgbz_g, depths_g, with_color, splats, splat_rgbz)


@wp.kernel
def pack_splats(
    offset: int,
    slots: wp.array(dtype=wp.int32),  # [M] sorted pair slots
    pair_gauss: wp.array(dtype=wp.int32),  # [M] Gaussian of each slot
    splat_g: wp.array(dtype=vec8),  # [N] per Gaussian (projection's)
    rgbz_g: wp.array(dtype=wp.vec4),  # [N] per Gaussian colour + depth (read when with_color == 1)
    depths_g: wp.array(dtype=float),  # [N] per Gaussian depth (read when with_color == 2)
    with_color: int,  # 0: splats only; 1: colour and depth from rgbz_g; 2: depth only, from depths_g
    splats: wp.array(dtype=vec8),  # [M] out, in sorted order
    splat_rgbz: wp.array(dtype=wp.vec4),  # [M] out: r, g, b, depth
):
    pack_pair(offset + wp.tid(), slots, pair_gauss, splat_g, rgbz_g, depths_g, with_color, splats, splat_rgbz)


@wp.kernel
def rasterize_forward(
    offset: int,
    cam: Camera,
    seg: int,  # pixels per thread (1, 2, 4, 8, 16): 16 = a tile row (CPU), 1 = a pixel (GPU)
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2] [start, end) into the sorted pairs
    splats: wp.array(dtype=vec8),  # [M] packed, sorted
    splat_rgbz: wp.array(dtype=wp.vec4),  # [M] packed, sorted: r, g, b, depth
    background: wp.vec3,  # RGB
    rgb: wp.array3d(dtype=float),  # [H, W, 3] out
    depth: wp.array2d(dtype=float),  # [H, W] out, sum w z (unnormalised)
    alpha: wp.array2d(dtype=float),  # [H, W] out, 1 - T_final
    T_final: wp.array2d(dtype=float),  # [H, W] out
    n_contrib: wp.array2d(dtype=wp.int32),  # [H, W] out, tile-list count up to the last accumulated Gaussian
):
    tr = tile_row(offset + wp.tid(), cam, seg)
    tile = tr[0]
    x0 = tr[1]
    y = tr[2]
    nx = tr[3]
    if nx <= 0:
        return
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    fy = float(y)
    T = vec16(1.0)
    Cr = vec16(0.0)
    Cg = vec16(0.0)
    Cb = vec16(0.0)
    D = vec16(0.0)
    last = vec16i(0)
    done = int(0)  # bit k: pixel x0 + k has stopped
    full = (1 << nx) - 1
    for j in range(start, end):
        s = splats[j]
        dy = fy - s[1]
        span = row_span(s, dy, x0, nx)
        if span[0] > span[1]:
            continue
        bits = ((1 << (span[1] - span[0] + 1)) - 1) << span[0]
        if done & bits == bits:  # every pixel of the span has stopped
            continue
        e = span_exp_start(s, float(x0 + span[0]) - s[0], dy)
        E = e[0]
        F = e[1]
        col = splat_rgbz[j]
        for k in range(span[0], span[1] + 1):
            if (done >> k) & 1 == 0:
                a = wp.min(ALPHA_MAX, s[5] * E)
                if a >= ALPHA_MIN:
                    Tk = T[k]
                    Tn = Tk * (1.0 - a)
                    if Tn < T_MIN:
                        done = done | (1 << k)
                    else:
                        w = a * Tk
                        Cr[k] = Cr[k] + w * col[0]
                        Cg[k] = Cg[k] + w * col[1]
                        Cb[k] = Cb[k] + w * col[2]
                        D[k] = D[k] + w * col[3]
                        T[k] = Tn
                        last[k] = j - start + 1
            E = E * F
            F = F * s[6]
        if done == full:
            break
    for k in range(nx):
        x = x0 + k
        Tk = T[k]
        rgb[y, x, 0] = Cr[k] + Tk * background[0]
        rgb[y, x, 1] = Cg[k] + Tk * background[1]
        rgb[y, x, 2] = Cb[k] + Tk * background[2]
        depth[y, x] = D[k]
        alpha[y, x] = 1.0 - Tk
        T_final[y, x] = Tk
        n_contrib[y, x] = last[k]


def _alpha_kernel(with_depth: bool):
    """The coverage kernel of 1-16 pixels a thread, with or without the accumulated depth (two compiled variants):
    the rules of :func:`mgso_kernels.splat.raster_tile._alpha_tile_kernel` (3DGS's blend for the transmittance,
    plus a pixel's stop once an accumulated Gaussian took its transmittance below ``t_stop``)."""

    @wp.kernel
    def rasterize_alpha(
        offset: int,
        cam: Camera,
        seg: int,  # pixels per thread
        ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
        splats: wp.array(dtype=vec8),  # [M] packed, sorted
        splat_rgbz: wp.array(dtype=wp.vec4),  # [M] packed, sorted: depth in [3] (read only with depth)
        t_stop: float,  # the coverage stop; <= T_MIN: the full render's rule only
        alpha: wp.array2d(dtype=float),  # [H, W] out, accumulated alpha = 1 - T_final
        depth: wp.array2d(dtype=float),  # [H, W] out with depth, sum w z (unnormalised); else not written
    ):
        tr = tile_row(offset + wp.tid(), cam, seg)
        tile = tr[0]
        x0 = tr[1]
        y = tr[2]
        nx = tr[3]
        if nx <= 0:
            return
        fy = float(y)
        T = vec16(1.0)
        D = vec16(0.0)
        done = int(0)
        full = (1 << nx) - 1
        for j in range(ranges[tile, 0], ranges[tile, 1]):
            s = splats[j]
            dy = fy - s[1]
            span = row_span(s, dy, x0, nx)
            if span[0] > span[1]:
                continue
            bits = ((1 << (span[1] - span[0] + 1)) - 1) << span[0]
            if done & bits == bits:
                continue
            e = span_exp_start(s, float(x0 + span[0]) - s[0], dy)
            E = e[0]
            F = e[1]
            z = float(0.0)
            if wp.static(with_depth):
                z = splat_rgbz[j][3]
            for k in range(span[0], span[1] + 1):
                if (done >> k) & 1 == 0:
                    a = wp.min(ALPHA_MAX, s[5] * E)
                    if a >= ALPHA_MIN:
                        Tk = T[k]
                        Tn = Tk * (1.0 - a)
                        if Tn < T_MIN:
                            done = done | (1 << k)
                        else:
                            if wp.static(with_depth):
                                D[k] = D[k] + a * Tk * z
                            T[k] = Tn
                            if Tn < t_stop:
                                done = done | (1 << k)
                E = E * F
                F = F * s[6]
            if done == full:
                break
        for k in range(nx):
            alpha[y, x0 + k] = 1.0 - T[k]
            if wp.static(with_depth):
                depth[y, x0 + k] = D[k]

    return rasterize_alpha


rasterize_alpha = _alpha_kernel(False)
rasterize_alpha_depth = _alpha_kernel(True)   # the coverage alpha and the accumulated depth


# ------------------------------------------------------------------------------------------------- launchers
def launch_pack_splats(slots, pair_gauss, splat_g, rgbz_g, n_pairs: int, splats, splat_rgbz, device: str,
                       threads: int | None = None, min_chunk: int = 4096, depths_g=None):
    """Copy the sorted pairs' Gaussian data into contiguous arrays: with ``rgbz_g`` their colour and depth too;
    without it but with ``depths_g`` (N,) their depth only (``splat_rgbz[:, 3]``, for the coverage depth); with
    neither the blending data only (alpha-only). On the CPU returns the call's own per-block status (a Warp int32
    array, 1 where the C++ block did the block's pairs; renders may pack on two threads at once), else None."""
    from ..runtime import launch_blocks, launch_split, placeholder

    if splats.shape[0] < n_pairs or splat_rgbz.shape[0] < n_pairs:
        raise ValueError(f"pack_splats: splat buffers hold {splats.shape[0]}, need {n_pairs}")
    if n_pairs == 0:
        return None
    with_color = 1 if rgbz_g is not None else (2 if depths_g is not None else 0)
    rgbz_g = rgbz_g if rgbz_g is not None else placeholder(wp.vec4, 1, device)
    depths_g = depths_g if depths_g is not None else placeholder(wp.float32, 1, device)
    if str(device).startswith("cpu"):
        from .raster_tile import native_flag

        # blocks of PACK_BLOCK pairs, a thread each (the C++ block; launch_blocks spreads the blocks over the cores)
        return launch_blocks(pack_splats_blocks, n_pairs, PACK_BLOCK, [slots, pair_gauss, splat_g, rgbz_g, depths_g,
                                                                       with_color, splats, splat_rgbz],
                             native_flag(), device, threads=threads, min_chunk=min_chunk)
    launch_split(pack_splats, n_pairs, [slots, pair_gauss, splat_g, rgbz_g, depths_g, with_color, splats,
                                        splat_rgbz], device, threads=threads, min_chunk=min_chunk)
    return None


#: Pairs a thread of the CPU's pack (:func:`pack_splats_blocks`).
PACK_BLOCK = 1024


def launch_rasterize_forward(cam: Camera, ranges, splats, splat_rgbz, background, rgb, depth, alpha, T_final,
                             n_contrib, device: str, threads: int | None = None, min_chunk: int = 4096,
                             seg: int = TILE_SIZE, only_rgb: bool = False) -> None:
    """Blend every pixel; outputs (H, W[, 3]) are fully overwritten. ``seg``: pixels per thread; ``min_chunk``:
    fewest pixels per CPU chunk. ``only_rgb`` (a whole tile a thread only): the colour alone, ``depth``, ``alpha``,
    ``T_final`` and ``n_contrib`` may be None and are not written (renders without a gradient: on the CPU the blend
    then keeps neither the depth nor the last list position, a little cheaper; the same colours bit for bit)."""
    from ..runtime import launch_split, placeholder
    from ._checks import check_array

    H, W = cam.height, cam.width
    check_array(rgb, "rgb", wp.float32, (H, W, 3), device)
    if only_rgb and seg != TILE_SIZE * TILE_SIZE:
        raise ValueError(f"rasterize_forward: only_rgb needs a whole tile a thread (seg={TILE_SIZE * TILE_SIZE}), "
                         f"got seg={seg}")
    if only_rgb:
        f32, i32 = placeholder(wp.float32, 2, device), placeholder(wp.int32, 2, device)
        depth, alpha, T_final, n_contrib = f32, f32, f32, i32
    else:
        for name, a in (("depth", depth), ("alpha", alpha), ("T_final", T_final)):
            check_array(a, name, wp.float32, (H, W), device)
        check_array(n_contrib, "n_contrib", wp.int32, (H, W), device)
    if ranges.shape[0] < cam.tiles_x * cam.tiles_y:
        raise ValueError("rasterize_forward: ranges has fewer rows than the camera has tiles")
    dim, per_tile = segment_threads(cam, seg)
    if seg == TILE_SIZE * TILE_SIZE:
        from . import raster_tile as rt

        rt.launch_tiles(rt.rasterize_forward_tile, rt.rasterize_forward_tile_dynamic, dim,
                        [cam, ranges, splats, splat_rgbz, wp.vec3(*background), rgb, depth, alpha, T_final, n_contrib,
                         int(bool(only_rgb))],
                        device, threads=threads, min_chunk=max(1, min_chunk // seg))
        return
    launch_split(rasterize_forward, dim, [cam, seg, ranges, splats, splat_rgbz, wp.vec3(*background), rgb, depth,
                                          alpha, T_final, n_contrib],
                 device, threads=threads, min_chunk=max(1, min_chunk // seg), align=per_tile)


def launch_rasterize_alpha(cam: Camera, ranges, splats, alpha, device: str, threads: int | None = None,
                           min_chunk: int = 4096, seg: int = TILE_SIZE, splat_rgbz=None, depth=None,
                           t_stop: float = 0.0) -> None:
    """Accumulated alpha (H, W), and with ``depth`` (H, W) the accumulated depth ``sum w z`` (``splat_rgbz``
    packed with the depths): the cheap path for coverage tests. ``t_stop``: a pixel also stops once an accumulated
    Gaussian took its transmittance below this (0: the full render's alpha and depth)."""
    from ..runtime import launch_split, placeholder
    from ._checks import check_array

    check_array(alpha, "alpha", wp.float32, (cam.height, cam.width), device)
    with_depth = depth is not None
    if with_depth:
        check_array(depth, "depth", wp.float32, (cam.height, cam.width), device)
        if splat_rgbz is None:
            raise ValueError("rasterize_alpha: the depth needs splat_rgbz packed with the depths")
    else:
        splat_rgbz, depth = placeholder(wp.vec4, 1, device), placeholder(wp.float32, 2, device)
    dim, per_tile = segment_threads(cam, seg)
    if seg == TILE_SIZE * TILE_SIZE:
        from . import raster_tile as rt

        rt.launch_tiles(rt.rasterize_alpha_depth_tile if with_depth else rt.rasterize_alpha_tile,
                        rt.rasterize_alpha_depth_tile_dynamic if with_depth else rt.rasterize_alpha_tile_dynamic, dim,
                        [cam, ranges, splats, splat_rgbz, float(t_stop), alpha, depth], device, threads=threads,
                        min_chunk=max(1, min_chunk // seg))
        return
    launch_split(rasterize_alpha_depth if with_depth else rasterize_alpha, dim,
                 [cam, seg, ranges, splats, splat_rgbz, float(t_stop), alpha, depth], device, threads=threads,
                 min_chunk=max(1, min_chunk // seg), align=per_tile)
