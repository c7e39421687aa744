"""Tile-sorted alpha blending, hand-written backward (Warp module).

Warp's ``wp.Tape`` is silently wrong for the blending loop (a runtime-bounded loop carrying ``T``), so this adjoint
is written by hand, as 3DGS and gsplat do: per pixel, back to front from the last accumulated Gaussian
(``n_contrib``), rebuilding the transmittance from ``T_final`` (``T_i = T_{i+1} / (1 - alpha_i)``) and keeping the
sum of what lies behind. With ``G = v_rgb``, ``g_i = c_i . G + z_i v_depth`` and ``S_i = sum_{j > i} w_j g_j``:

    v_alpha_i = T_i g_i - (S_i + T_final (background . G) - T_final v_alpha) / (1 - alpha_i)
    v_c_i = w_i G,   v_z_i = w_i v_depth

then through ``alpha = min(0.99, opacity exp(power))`` (zero where the clamp is active) to the opacity, the conic
and the 2D mean. The skip decisions (``power > 0``, ``alpha < 1/255``) are re-evaluated with the forward's own
:func:`mgso_kernels.splat.raster.splat_alpha`, so both passes agree pixel for pixel.

**Accumulation without cross-thread atomics on the CPU.** Each contributing (pixel, pair) adds a 12-vector
``(v_mx, v_my, v_a, v_b, v_c, v_opacity, v_r, v_g, v_b, v_z, |v_mx|, |v_my|)`` into that pair's *slot* (one per
(tile, Gaussian) pair, see :mod:`mgso_kernels.splat.bin`). All pixels of a tile run on one CPU thread (chunks are
whole tiles), so the adds are never concurrent on the CPU; on CUDA ``wp.atomic_add`` is atomic. Then
:func:`gather_gaussian_grads` sums each Gaussian's contiguous slot range. The CPU result is bitwise identical
however the launch is split. The last two components are the AbsGS statistic: the sum over pixels of the absolute
per-pixel 2D-mean gradient.

Twin: :func:`mgso_kernels.reference.splat.render_vjp`.
"""

from __future__ import annotations

import warp as wp

from .camera import Camera
from .raster import ALPHA_MAX, splat_alpha, splat_power, tile_pixel, vec8

wp.set_module_options({"enable_backward": False})

__all__ = ["rasterize_backward", "gather_gaussian_grads", "vec12"]

vec12 = wp.types.vector(length=12, dtype=wp.float32)


@wp.kernel
def rasterize_backward(
    offset: int,
    cam: Camera,
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
    splats: wp.array(dtype=vec8),  # [M] packed, sorted (forward's)
    splat_rgb: wp.array(dtype=wp.vec3),  # [M]
    slots: wp.array(dtype=wp.int32),  # [M] sorted pair slots
    background: wp.vec3,
    T_final: wp.array2d(dtype=float),  # [H, W] forward's
    n_contrib: wp.array2d(dtype=wp.int32),  # [H, W] forward's
    v_rgb: wp.array3d(dtype=float),  # [H, W, 3] upstream
    v_depth: wp.array2d(dtype=float),  # [H, W] upstream
    v_alpha: wp.array2d(dtype=float),  # [H, W] upstream
    use_depth: int,  # 0: v_depth ignored (may be a dummy)
    use_alpha: int,  # 0: v_alpha ignored
    pair_grads: wp.array(dtype=vec12),  # [M] in/out (zeroed by the caller), indexed by slot
):
    tp = tile_pixel(offset + wp.tid(), cam)
    px = tp[1]
    py = tp[2]
    if px >= cam.width or py >= cam.height:
        return
    n = n_contrib[py, px]
    if n == 0:
        return
    start = ranges[tp[0], 0]
    fx = float(px)
    fy = float(py)
    G = wp.vec3(v_rgb[py, px, 0], v_rgb[py, px, 1], v_rgb[py, px, 2])
    vD = float(0.0)
    if use_depth != 0:
        vD = v_depth[py, px]
    vA = float(0.0)
    if use_alpha != 0:
        vA = v_alpha[py, px]
    Tf = T_final[py, px]
    T = Tf
    behind = Tf * (wp.dot(background, G) - vA)  # the background's and alpha's share of d/d alpha_i, times (1-a_i)
    S = float(0.0)
    for k in range(n):
        j = start + n - 1 - k
        s = splats[j]
        power = splat_power(s, fx, fy)
        a = splat_alpha(s, power)
        if a == 0.0:
            continue
        one_minus = 1.0 - a
        T = T / one_minus  # transmittance in front of this Gaussian
        w = a * T
        col = splat_rgb[j]
        gi = wp.dot(col, G) + s[6] * vD
        v_a = T * gi - (S + behind) / one_minus
        S += w * gi
        v_col = w * G
        v_z = w * vD
        # alpha = min(0.99, opacity exp(power)): no gradient where clamped
        r = s[5] * wp.exp(power)
        v_r = float(0.0)
        if r <= ALPHA_MAX:
            v_r = v_a
        v_op = v_r * r / s[5]
        v_pow = v_r * r
        dx = fx - s[0]
        dy = fy - s[1]
        gx = (s[2] * dx + s[3] * dy) * v_pow
        gy = (s[3] * dx + s[4] * dy) * v_pow
        wp.atomic_add(pair_grads, slots[j],
                      vec12(gx, gy, -0.5 * dx * dx * v_pow, -dx * dy * v_pow, -0.5 * dy * dy * v_pow, v_op,
                            v_col[0], v_col[1], v_col[2], v_z, wp.abs(gx), wp.abs(gy)))


@wp.kernel
def gather_gaussian_grads(
    offset: int,
    pair_offsets: wp.array(dtype=wp.int32),  # [N] first slot of each Gaussian
    tiles_touched: wp.array(dtype=wp.int32),  # [N] number of slots
    pair_grads: wp.array(dtype=vec12),  # [M] by slot
    v_means2d: wp.array(dtype=wp.vec2),  # [N] out, d/d mean2d (pixels)
    v_conics: wp.array(dtype=wp.vec3),  # [N] out
    v_opacities: wp.array(dtype=float),  # [N] out, d/d opacity (after the sigmoid)
    v_colors: wp.array(dtype=wp.vec3),  # [N] out
    v_depths: wp.array(dtype=float),  # [N] out, through the depth output only
    absgrad: wp.array(dtype=wp.vec2),  # [N] out, sum over pixels of |per-pixel v_mean2d|
):
    g = offset + wp.tid()
    acc = vec12(0.0)
    p0 = pair_offsets[g]
    for p in range(p0, p0 + tiles_touched[g]):
        acc += pair_grads[p]
    v_means2d[g] = wp.vec2(acc[0], acc[1])
    v_conics[g] = wp.vec3(acc[2], acc[3], acc[4])
    v_opacities[g] = acc[5]
    v_colors[g] = wp.vec3(acc[6], acc[7], acc[8])
    v_depths[g] = acc[9]
    absgrad[g] = wp.vec2(acc[10], acc[11])


@wp.kernel
def accumulate_densify_stats(
    offset: int,
    v_means2d: wp.array(dtype=wp.vec2),  # [N] this view's d/d mean2d, pixels
    absgrad: wp.array(dtype=wp.vec2),  # [N] this view's AbsGS sums, pixels
    radii: wp.array(dtype=wp.int32),  # [N] 0 = not visible in this view
    scale: wp.vec2,  # multiplies the pixel gradients (W/2, H/2 gives 3DGS's NDC units)
    grad2d_sum: wp.array(dtype=float),  # [N] in/out: sum over views of |scale * v_mean2d|
    absgrad2d_sum: wp.array(dtype=float),  # [N] in/out: sum over views of |scale * absgrad|
    count: wp.array(dtype=wp.int32),  # [N] in/out: views in which the Gaussian was visible
    max_radii: wp.array(dtype=float),  # [N] in/out: max over views of radii (pixels)
):
    g = offset + wp.tid()
    r = radii[g]
    if r == 0:
        return
    v = v_means2d[g]
    a = absgrad[g]
    grad2d_sum[g] = grad2d_sum[g] + wp.length(wp.vec2(v[0] * scale[0], v[1] * scale[1]))
    absgrad2d_sum[g] = absgrad2d_sum[g] + wp.length(wp.vec2(a[0] * scale[0], a[1] * scale[1]))
    count[g] = count[g] + 1
    max_radii[g] = wp.max(max_radii[g], float(r))


# ------------------------------------------------------------------------------------------------- launchers
def launch_rasterize_backward(cam: Camera, ranges, splats, splat_rgb, slots, background, T_final, n_contrib, v_rgb,
                              v_depth, v_alpha, pair_grads, n_pairs: int, device: str,
                              threads: int | None = None, min_chunk: int = 4096) -> None:
    """Per-pair gradients (zeroed here, then accumulated) from the upstream image gradients.

    ``v_depth`` / ``v_alpha`` may be ``None`` (no gradient through that output).
    """
    from ..runtime import launch_split
    from ._checks import check_array
    from .raster import TILE_SIZE

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
    launch_split(rasterize_backward, cam.tiles_x * cam.tiles_y * TILE_SIZE * TILE_SIZE,
                 [cam, ranges, splats, splat_rgb, slots, wp.vec3(*background), T_final, n_contrib, v_rgb, v_depth,
                  v_alpha, use_depth, use_alpha, pair_grads], device, threads=threads, min_chunk=min_chunk, align=TILE_SIZE * TILE_SIZE)


def launch_gather_gaussian_grads(pair_offsets, tiles_touched, pair_grads, v_means2d, v_conics, v_opacities, v_colors,
                                 v_depths, absgrad, device: str, threads: int | None = None, min_chunk: int = 4096) -> None:
    """Sum each Gaussian's slot range into per-Gaussian screen-space gradients (all outputs overwritten)."""
    from ..runtime import launch_split

    n = v_means2d.shape[0]
    launch_split(gather_gaussian_grads, n, [pair_offsets, tiles_touched, pair_grads, v_means2d, v_conics,
                                            v_opacities, v_colors, v_depths, absgrad], device, threads=threads, min_chunk=min_chunk)


def launch_accumulate_densify_stats(v_means2d, absgrad, radii, scale, grad2d_sum, absgrad2d_sum, count, max_radii,
                                    device: str, threads: int | None = None, min_chunk: int = 4096) -> None:
    from ..runtime import launch_split

    n = v_means2d.shape[0]
    launch_split(accumulate_densify_stats, n, [v_means2d, absgrad, radii, wp.vec2(*scale), grad2d_sum,
                                               absgrad2d_sum, count, max_radii], device, threads=threads, min_chunk=min_chunk)
