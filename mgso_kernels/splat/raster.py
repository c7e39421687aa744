"""Tile-sorted alpha blending, forward (Warp module).

Pixel-parallel over a tile-major pixel order: thread ``i`` handles pixel ``i % 256`` (row-major inside the 16x16
tile) of tile ``i // 256`` (row-major over tiles), so a contiguous chunk of threads (what
:func:`mgso_kernels.runtime.launch_split` gives one CPU core, ``align=256``) is a set of whole tiles. Threads of
border tiles that fall outside the image return at once.

Per pixel, front to back over its tile's depth-sorted list (3DGS's rules, exactly):
``power = -0.5 (a dx^2 + c dy^2) - b dx dy`` with ``(dx, dy) = (u, v) - mean2d`` (pixel (row v, col u) is
sampled at (u, v)); skip if ``power > 0``; ``alpha = min(0.99, opacity * exp(power))``; skip if
``alpha < 1/255``; if ``T * (1 - alpha) < 1e-4`` stop *without* accumulating; else accumulate
``w = alpha * T`` and set ``T *= 1 - alpha``. Outputs ``rgb = sum w c + T_final * background``,
``depth = sum w z`` (expected camera z, **not** normalised: divide by ``alpha`` for the depth of the visible
surface), ``alpha = 1 - T_final``, and for the backward pass ``T_final`` and ``n_contrib`` (1 + the position in
the tile list of the last accumulated Gaussian; 0 if none).

Before blending, :func:`pack_splats` copies each sorted pair's Gaussian data (mean, conic, opacity, depth, a
precomputed skip threshold, colour) into contiguous arrays in sorted order, so the inner loop streams memory
instead of gathering by Gaussian index (measured in docs/rasteriser.md). The threshold lets a pixel skip a Gaussian
without an ``exp`` when ``power < log(1 / (255 opacity)) - 1e-3``, where the 1/255 test would skip it anyway.

Twin: :func:`mgso_kernels.reference.splat.render`.
"""

from __future__ import annotations

import warp as wp

from .camera import TILE_SIZE, Camera

wp.set_module_options({"enable_backward": False})

__all__ = ["pack_splats", "rasterize_forward", "rasterize_alpha", "vec8", "splat_alpha", "tile_pixel",
           "ALPHA_MIN", "ALPHA_MAX", "T_MIN"]

vec8 = wp.types.vector(length=8, dtype=wp.float32)

ALPHA_MIN = wp.constant(1.0 / 255.0)
ALPHA_MAX = wp.constant(0.99)
T_MIN = wp.constant(1.0e-4)
SKIP_MARGIN = wp.constant(1.0e-3)
TS = wp.constant(TILE_SIZE)
TILE_PIXELS = wp.constant(TILE_SIZE * TILE_SIZE)


@wp.func
def tile_pixel(i: int, cam: Camera) -> wp.vec3i:
    """Tile-major thread index -> (tile, column, row)."""
    tile = i // TILE_PIXELS
    local = i - tile * TILE_PIXELS
    ty = tile // cam.tiles_x
    tx = tile - ty * cam.tiles_x
    return wp.vec3i(tile, tx * TS + local % TS, ty * TS + local // TS)


@wp.func
def splat_power(s: vec8, px: float, py: float) -> float:
    dx = px - s[0]
    dy = py - s[1]
    return -0.5 * (s[2] * dx * dx + s[4] * dy * dy) - s[3] * dx * dy


@wp.func
def splat_alpha(s: vec8, power: float) -> float:
    """Clamped alpha, or 0 when the Gaussian is skipped at this pixel (power > 0 or alpha < 1/255)."""
    if power > 0.0 or power < s[7]:
        return 0.0
    alpha = wp.min(ALPHA_MAX, s[5] * wp.exp(power))
    if alpha < ALPHA_MIN:
        return 0.0
    return alpha


@wp.kernel
def pack_splats(
    offset: int,
    slots: wp.array(dtype=wp.int32),  # [M] sorted pair slots
    pair_gauss: wp.array(dtype=wp.int32),  # [M] Gaussian of each slot
    means2d: wp.array(dtype=wp.vec2),  # [N]
    conics: wp.array(dtype=wp.vec3),  # [N]
    opacities: wp.array(dtype=float),  # [N]
    depths: wp.array(dtype=float),  # [N]
    colors: wp.array(dtype=wp.vec3),  # [N] (ignored when with_color == 0)
    with_color: int,
    splats: wp.array(dtype=vec8),  # [M] out: mx, my, a, b, c, opacity, depth, skip threshold
    splat_rgb: wp.array(dtype=wp.vec3),  # [M] out
):
    j = offset + wp.tid()
    g = pair_gauss[slots[j]]
    m = means2d[g]
    q = conics[g]
    op = opacities[g]
    thr = -wp.log(255.0 * op) - SKIP_MARGIN
    splats[j] = vec8(m[0], m[1], q[0], q[1], q[2], op, depths[g], thr)
    if with_color != 0:
        splat_rgb[j] = colors[g]


@wp.kernel
def rasterize_forward(
    offset: int,
    cam: Camera,
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2] [start, end) into the sorted pairs
    splats: wp.array(dtype=vec8),  # [M] packed, sorted
    splat_rgb: wp.array(dtype=wp.vec3),  # [M] packed, sorted
    background: wp.vec3,  # RGB
    rgb: wp.array3d(dtype=float),  # [H, W, 3] out
    depth: wp.array2d(dtype=float),  # [H, W] out, sum w z (unnormalised)
    alpha: wp.array2d(dtype=float),  # [H, W] out, 1 - T_final
    T_final: wp.array2d(dtype=float),  # [H, W] out
    n_contrib: wp.array2d(dtype=wp.int32),  # [H, W] out, tile-list count up to the last accumulated Gaussian
):
    tp = tile_pixel(offset + wp.tid(), cam)
    px = tp[1]
    py = tp[2]
    if px >= cam.width or py >= cam.height:
        return
    start = ranges[tp[0], 0]
    end = ranges[tp[0], 1]
    fx = float(px)
    fy = float(py)
    T = float(1.0)
    C = wp.vec3(0.0)
    D = float(0.0)
    last = int(0)
    for j in range(start, end):
        s = splats[j]
        a = splat_alpha(s, splat_power(s, fx, fy))
        if a == 0.0:
            continue
        Tn = T * (1.0 - a)
        if Tn < T_MIN:
            break
        w = a * T
        C += w * splat_rgb[j]
        D += w * s[6]
        T = Tn
        last = j - start + 1
    out = C + T * background
    rgb[py, px, 0] = out[0]
    rgb[py, px, 1] = out[1]
    rgb[py, px, 2] = out[2]
    depth[py, px] = D
    alpha[py, px] = 1.0 - T
    T_final[py, px] = T
    n_contrib[py, px] = last


@wp.kernel
def rasterize_alpha(
    offset: int,
    cam: Camera,
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
    splats: wp.array(dtype=vec8),  # [M] packed, sorted
    alpha: wp.array2d(dtype=float),  # [H, W] out, accumulated alpha = 1 - T_final
):
    tp = tile_pixel(offset + wp.tid(), cam)
    px = tp[1]
    py = tp[2]
    if px >= cam.width or py >= cam.height:
        return
    fx = float(px)
    fy = float(py)
    T = float(1.0)
    for j in range(ranges[tp[0], 0], ranges[tp[0], 1]):
        s = splats[j]
        a = splat_alpha(s, splat_power(s, fx, fy))
        if a == 0.0:
            continue
        Tn = T * (1.0 - a)
        if Tn < T_MIN:
            break
        T = Tn
    alpha[py, px] = 1.0 - T


# ------------------------------------------------------------------------------------------------- launchers
def _pixel_threads(cam: Camera) -> int:
    return cam.tiles_x * cam.tiles_y * TILE_SIZE * TILE_SIZE


def launch_pack_splats(slots, pair_gauss, means2d, conics, opacities, depths, colors, n_pairs: int, splats,
                       splat_rgb, device: str, threads: int | None = None, min_chunk: int = 4096) -> None:
    """Copy the sorted pairs' Gaussian data into contiguous arrays (``colors=None``: alpha-only)."""
    from ..runtime import launch_split

    if splats.shape[0] < n_pairs or splat_rgb.shape[0] < n_pairs:
        raise ValueError(f"pack_splats: splat buffers hold {splats.shape[0]}, need {n_pairs}")
    if n_pairs == 0:
        return
    with_color = 0 if colors is None else 1
    colors = colors if colors is not None else _dummy_vec3(device)
    launch_split(pack_splats, n_pairs, [slots, pair_gauss, means2d, conics, opacities, depths, colors, with_color,
                                        splats, splat_rgb], device, threads=threads, min_chunk=min_chunk)


_dummies: dict = {}


def _dummy_vec3(device):
    key = ("vec3", str(device))
    if key not in _dummies:
        _dummies[key] = wp.zeros(1, dtype=wp.vec3, device=device)
    return _dummies[key]


def launch_rasterize_forward(cam: Camera, ranges, splats, splat_rgb, background, rgb, depth, alpha, T_final,
                             n_contrib, device: str, threads: int | None = None, min_chunk: int = 4096) -> None:
    """Blend every pixel; outputs (H, W[, 3]) are fully overwritten."""
    from ..runtime import launch_split
    from ._checks import check_array

    H, W = cam.height, cam.width
    check_array(rgb, "rgb", wp.float32, (H, W, 3), device)
    for name, a in (("depth", depth), ("alpha", alpha), ("T_final", T_final)):
        check_array(a, name, wp.float32, (H, W), device)
    check_array(n_contrib, "n_contrib", wp.int32, (H, W), device)
    if ranges.shape[0] < cam.tiles_x * cam.tiles_y:
        raise ValueError("rasterize_forward: ranges has fewer rows than the camera has tiles")
    launch_split(rasterize_forward, _pixel_threads(cam), [cam, ranges, splats, splat_rgb, wp.vec3(*background),
                                                           rgb, depth, alpha, T_final, n_contrib],
                 device, threads=threads, min_chunk=min_chunk, align=TILE_SIZE * TILE_SIZE)


def launch_rasterize_alpha(cam: Camera, ranges, splats, alpha, device: str, threads: int | None = None, min_chunk: int = 4096) -> None:
    """Accumulated alpha only (H, W): the cheap path for coverage tests."""
    from ..runtime import launch_split
    from ._checks import check_array

    check_array(alpha, "alpha", wp.float32, (cam.height, cam.width), device)
    launch_split(rasterize_alpha, _pixel_threads(cam), [cam, ranges, splats, alpha], device,
                 threads=threads, min_chunk=min_chunk,
                 align=TILE_SIZE * TILE_SIZE)
