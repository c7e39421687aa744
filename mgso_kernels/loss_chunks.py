"""The L1 + D-SSIM loss's kernels for the standard window (11 x 11, sigma 1.5), vectorised over chunks of 16 floats
(Warp module; used by :class:`mgso_kernels.loss.L1SSIMLoss`, which documents the algorithm).

A row of an (H, W, 3) image is 3W interleaved floats, cut into chunks of 16 consecutive floats ([H, nch] arrays of
16-vectors). Every operation is lane-wise on chunks, so LLVM emits vector instructions (AVX-512 on this project's
CPU): filtering is channel-agnostic, a horizontal tap of d pixels is a shift of 3 d floats (a constant lane
permutation of a chunk and its neighbours), and a vertical tap is the same chunk of another row. One thread handles
a chunk column over a band of rows and keeps the last 11 horizontally filtered rows in a ring buffer, so the
horizontally filtered maps never go to memory.

Module compiler options: ``-fno-unroll-loops`` keeps Warp's small vector operations (loops over the 16 lanes) for
LLVM's loop vectoriser, which makes single 16-lane instructions of them (fully unrolled first, the SLP vectoriser
split them into 2- and 4-lane pieces), and a high inline threshold inlines the horizontal window into the kernels.
Measured (forward kernel, 320x240, one thread): 16.7 ms without them, 11.9 ms with the first, 5.5 ms with both.
They change code generation only, not results. They would slow the per-pixel kernels of :mod:`mgso_kernels.loss`
(their runtime-bound loops need unrolling), hence the separate module.

The per-thread partial sums and the totals are (n, 1) columns: Warp 1.19 compiles a second, unit-stride copy of a
1-D-launched CPU kernel that takes a 1-D array and has a rolled loop; these kernels touch those arrays once per thread,
so that copy only lengthened the module's compile (17 s against 13 s on this machine, fresh cache).

Twin: :mod:`mgso_kernels.reference.loss`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

wp.set_module_options({
    "enable_backward": False,
    "cpu_compiler_flags": "-march=native -mprefer-vector-width=512 -fno-unroll-loops -mllvm -inline-threshold=5000",
})

__all__ = ["WINDOW", "CHUNK", "BAND_CPU", "BAND_GPU", "ChunkImages", "AdjointChunks", "stage_chunks", "ssim_forward_chunks",
           "ssim_backward_chunks", "vec16"]

SSIM_WINDOW = 11


def _window() -> np.ndarray:
    x = np.arange(SSIM_WINDOW, dtype=np.float64) - SSIM_WINDOW // 2
    g = np.exp(-(x * x) / (2.0 * 1.5 * 1.5))
    return (g / g.sum()).astype(np.float32)   # = mgso_kernels.loss.gaussian_window() (checked there)


CHUNK = 16          # floats per chunk (one AVX-512 register)
BAND_CPU = 64       # rows per thread on the CPU (the ring costs 10 extra horizontal rows per band)
BAND_GPU = 1        # rows per thread on CUDA (plenty of threads)

vec16 = wp.types.vector(length=CHUNK, dtype=wp.float32)
vec8f = wp.types.vector(length=8, dtype=wp.float32)
vec11 = wp.types.vector(length=SSIM_WINDOW, dtype=wp.float32)
ring5 = wp.types.matrix(shape=(5 * SSIM_WINDOW, CHUNK), dtype=wp.float32)   # 11 rows x 5 maps
ring3 = wp.types.matrix(shape=(3 * SSIM_WINDOW, CHUNK), dtype=wp.float32)   # 11 rows x 3 maps

WINDOW = _window()   # the taps built into these kernels
_G = WINDOW
WIN = wp.constant(vec11(*(float(v) for v in _G)))       # the standard window, vertical taps
G0 = wp.constant(float(_G[5]))                          # horizontal taps by distance (the window is symmetric)
G1 = wp.constant(float(_G[6]))
G2 = wp.constant(float(_G[7]))
G3 = wp.constant(float(_G[8]))
G4 = wp.constant(float(_G[9]))
G5 = wp.constant(float(_G[10]))
del _G


@wp.struct
class ChunkImages:
    """The image pair as chunks of 16 floats of the interleaved rows, [H, nch]; chunks outside [0, nch) are zero."""

    x: wp.array2d(dtype=vec16)        # rendered (exposure applied as gain * x + bias in the kernels)
    y: wp.array2d(dtype=vec16)        # target
    weight: wp.array2d(dtype=vec16)   # per-float pixel weight (read only when use_weight == 1)
    use_weight: int
    gain: float                       # exp(a); 1 for staged x (already exposed)
    bias: float                       # b; 0 for staged x
    nch: int                          # chunks per row, ceil(3 W / 16)
    height: int
    width3: int                       # 3 W: floats per row that are pixels (later lanes are padding)


@wp.struct
class AdjointChunks:
    d_mu_x: wp.array2d(dtype=vec16)   # [H, nch] w dSSIM / d mu_x
    d_xx: wp.array2d(dtype=vec16)     # [H, nch] w dSSIM / d E[x^2]
    d_xy: wp.array2d(dtype=vec16)     # [H, nch] w dSSIM / d E[xy]


@wp.func
def shifted(lo: vec16, hi: vec16, o: int):
    """Lanes o .. o + 15 of the 32 lanes (lo, hi), o in [0, 16] (a constant after inlining: one permutation)."""
    v = vec16(0.0)
    for k in range(CHUNK):
        v[k] = wp.where(k + o < CHUNK, lo[wp.min(k + o, CHUNK - 1)], hi[wp.max(k + o - CHUNK, 0)])
    return v


@wp.func
def hwindow(p: vec16, q: vec16, n: vec16):
    """Horizontal zero-padded window of chunk q (p, n: its neighbours): a tap of d pixels is a shift of 3 d floats."""
    out = q * G0
    out = out + (shifted(p, q, 13) + shifted(q, n, 3)) * G1
    out = out + (shifted(p, q, 10) + shifted(q, n, 6)) * G2
    out = out + (shifted(p, q, 7) + shifted(q, n, 9)) * G3
    out = out + (shifted(p, q, 4) + shifted(q, n, 12)) * G4
    out = out + (shifted(p, q, 1) + shifted(q, n, 15)) * G5
    return out


@wp.func
def lane_sum16(v: vec16) -> float:
    """Sum of the 16 lanes as a tree."""
    h = vec8f(0.0)
    for k in range(8):
        h[k] = v[k] + v[k + 8]
    q = wp.vec4(0.0)
    for k in range(4):
        q[k] = h[k] + h[k + 4]
    return (q[0] + q[2]) + (q[1] + q[3])


@wp.func
def chunk_at(a: wp.array2d(dtype=vec16), row: int, c: int, nch: int):
    """Chunk c of the row, zero outside [0, nch) (branch-free: a clamped load times 0 or 1)."""
    inside = wp.where(c >= 0 and c < nch, 1.0, 0.0)
    return a[row, wp.clamp(c, 0, nch - 1)] * inside


@wp.func
def exposed_chunk(img: ChunkImages, row: int, c: int):
    """gain * x + bias on the chunk (zero outside the image's chunks)."""
    inside = wp.where(c >= 0 and c < img.nch, 1.0, 0.0)
    return (img.x[row, wp.clamp(c, 0, img.nch - 1)] * img.gain + vec16(img.bias)) * inside


@wp.func
def lane_weights(img: ChunkImages, row: int, c: int, valid: vec16):
    w = valid
    if img.use_weight != 0:
        w = wp.cw_mul(img.weight[row, c], valid)
    return w


@wp.func
def valid_lanes(c: int, width3: int):
    v = vec16(0.0)
    f0 = c * CHUNK
    for k in range(CHUNK):
        v[k] = wp.where(f0 + k < width3, 1.0, 0.0)
    return v


@wp.func
def ssim_lane(mx: float, my: float, exx: float, eyy: float, exy: float, c1: float, c2: float):
    """SSIM from the filtered moments and dSSIM/d(mu_x, E[x^2], E[xy]) (as ssim_and_partials, two divisions)."""
    sxx = exx - mx * mx
    syy = eyy - my * my
    sxy = exy - mx * my
    n1 = 2.0 * mx * my + c1
    n2 = 2.0 * sxy + c2
    i1 = 1.0 / (mx * mx + my * my + c1)
    i2 = 1.0 / (sxx + syy + c2)
    inv = i1 * i2
    s = n1 * n2 * inv
    d_mx = 2.0 * my * (n2 - n1) * inv + 2.0 * mx * s * (i2 - i1)
    return wp.vec4(s, d_mx, -s * i2, 2.0 * n1 * inv)


@wp.kernel
def stage_chunks(offset: int, rendered: wp.array2d(dtype=wp.vec3), target: wp.array2d(dtype=wp.vec3),
                 weight: wp.array2d(dtype=float), use_weight: int, gain: float, bias: float, nch: int,
                 stage_images: int, x: wp.array2d(dtype=vec16), y: wp.array2d(dtype=vec16),
                 w_chunks: wp.array2d(dtype=vec16)):
    """Copy the image pair (``gain * rendered + bias``, target; ``stage_images``) and/or the pixel weights
    (``use_weight``) into zero-padded chunks, one thread per chunk (for widths whose rows are not whole chunks, and for
    masks)."""
    i = offset + wp.tid()
    row = i // nch
    c = i - row * nch
    w = rendered.shape[1]
    xv = vec16(0.0)
    yv = vec16(0.0)
    wv = vec16(0.0)
    for k in range(CHUNK):
        f = c * CHUNK + k
        px = f // 3
        if px < w:
            ch = f - 3 * px
            if stage_images != 0:
                xv[k] = rendered[row, px][ch] * gain + bias
                yv[k] = target[row, px][ch]
            if use_weight != 0:
                wv[k] = weight[row, px]
    if stage_images != 0:
        x[row, c] = xv
        y[row, c] = yv
    if use_weight != 0:
        w_chunks[row, c] = wv


@wp.kernel
def ssim_forward_chunks(offset: int, img: ChunkImages, band: int, c1: float, c2: float, adj: AdjointChunks,
                        partials: wp.array2d(dtype=wp.vec3)):
    """One thread per (band of rows, chunk column): SSIM and L1 per float, their weighted sums, and the weighted
    SSIM partials (step 1 of the module doc)."""
    i = offset + wp.tid()
    b = i // img.nch
    c = i - b * img.nch
    y0 = b * band
    y1 = wp.min(y0 + band, img.height)
    valid = valid_lanes(c, img.width3)
    ring = ring5(0.0)
    sum_w = vec16(0.0)
    sum_l1 = vec16(0.0)
    sum_s = vec16(0.0)
    for yy in range(y0 - 5, y1 + 5):
        slot = (yy - y0 + 5) % 11
        if yy >= 0 and yy < img.height:
            xp = exposed_chunk(img, yy, c - 1)
            xq = exposed_chunk(img, yy, c)
            xn = exposed_chunk(img, yy, c + 1)
            tp = chunk_at(img.y, yy, c - 1, img.nch)
            tq = chunk_at(img.y, yy, c, img.nch)
            tn = chunk_at(img.y, yy, c + 1, img.nch)
            ring[slot * 5 + 0] = hwindow(xp, xq, xn)
            ring[slot * 5 + 1] = hwindow(tp, tq, tn)
            ring[slot * 5 + 2] = hwindow(wp.cw_mul(xp, xp), wp.cw_mul(xq, xq), wp.cw_mul(xn, xn))
            ring[slot * 5 + 3] = hwindow(wp.cw_mul(tp, tp), wp.cw_mul(tq, tq), wp.cw_mul(tn, tn))
            ring[slot * 5 + 4] = hwindow(wp.cw_mul(xp, tp), wp.cw_mul(xq, tq), wp.cw_mul(xn, tn))
        else:
            for m in range(5):
                ring[slot * 5 + m] = vec16(0.0)
        row = yy - 5
        if row >= y0:
            mx = vec16(0.0)
            my = vec16(0.0)
            exx = vec16(0.0)
            eyy = vec16(0.0)
            exy = vec16(0.0)
            base = (row - y0) % 11
            for t in range(SSIM_WINDOW):
                sl = base + t
                if sl >= 11:
                    sl = sl - 11
                g = WIN[t]
                mx = mx + ring[sl * 5 + 0] * g
                my = my + ring[sl * 5 + 1] * g
                exx = exx + ring[sl * 5 + 2] * g
                eyy = eyy + ring[sl * 5 + 3] * g
                exy = exy + ring[sl * 5 + 4] * g
            wt = lane_weights(img, row, c, valid)
            xv = exposed_chunk(img, row, c)
            tv = img.y[row, c]
            d_mx = vec16(0.0)
            d_xx = vec16(0.0)
            d_xy = vec16(0.0)
            sv = vec16(0.0)
            l1 = vec16(0.0)
            for k in range(CHUNK):
                q = ssim_lane(mx[k], my[k], exx[k], eyy[k], exy[k], c1, c2)
                d_mx[k] = wt[k] * q[1]
                d_xx[k] = wt[k] * q[2]
                d_xy[k] = wt[k] * q[3]
                sv[k] = q[0]
                l1[k] = wp.abs(xv[k] - tv[k])
            adj.d_mu_x[row, c] = d_mx
            adj.d_xx[row, c] = d_xx
            adj.d_xy[row, c] = d_xy
            sum_w = sum_w + wt
            sum_l1 = sum_l1 + wp.cw_mul(wt, l1)
            sum_s = sum_s + wp.cw_mul(wt, sv)
    partials[i, 0] = wp.vec3(lane_sum16(sum_w), lane_sum16(sum_l1), lane_sum16(sum_s))


@wp.kernel
def ssim_backward_chunks(offset: int, img: ChunkImages, band: int, adj: AdjointChunks,
                         totals: wp.array2d(dtype=wp.vec3d), lambda_dssim: float, gain: float, bias: float,
                         v_chunks: wp.array2d(dtype=vec16), v_flat: wp.array2d(dtype=float), in_place: int,
                         partials: wp.array2d(dtype=wp.vec3)):
    """One thread per (band, chunk column): dL/dI (to ``v_chunks`` when the rows are whole chunks, else lane by lane
    to ``v_flat`` [H, 3W]) and per-thread (dL/da, dL/db) partials (step 3 of the module doc). ``gain``, ``bias``:
    the exposure (a, b) for dL/dI = exp(a) dL/dI' and dI'/da = I' - b."""
    i = offset + wp.tid()
    b = i // img.nch
    c = i - b * img.nch
    y0 = b * band
    y1 = wp.min(y0 + band, img.height)
    valid = valid_lanes(c, img.width3)
    weight_sum = float(totals[0, 0][0])   # 3 x the pixel weights: every pixel has three lanes
    norm = float(0.0)
    if weight_sum > 0.0:
        norm = 1.0 / weight_sum
    ring = ring3(0.0)
    sum_a = vec16(0.0)
    sum_b = vec16(0.0)
    for yy in range(y0 - 5, y1 + 5):
        slot = (yy - y0 + 5) % 11
        if yy >= 0 and yy < img.height:
            ring[slot * 3 + 0] = hwindow(chunk_at(adj.d_mu_x, yy, c - 1, img.nch), adj.d_mu_x[yy, c],
                                         chunk_at(adj.d_mu_x, yy, c + 1, img.nch))
            ring[slot * 3 + 1] = hwindow(chunk_at(adj.d_xx, yy, c - 1, img.nch), adj.d_xx[yy, c],
                                         chunk_at(adj.d_xx, yy, c + 1, img.nch))
            ring[slot * 3 + 2] = hwindow(chunk_at(adj.d_xy, yy, c - 1, img.nch), adj.d_xy[yy, c],
                                         chunk_at(adj.d_xy, yy, c + 1, img.nch))
        else:
            for m in range(3):
                ring[slot * 3 + m] = vec16(0.0)
        row = yy - 5
        if row >= y0:
            ga = vec16(0.0)
            gb = vec16(0.0)
            gc = vec16(0.0)
            base = (row - y0) % 11
            for t in range(SSIM_WINDOW):
                sl = base + t
                if sl >= 11:
                    sl = sl - 11
                g = WIN[t]
                ga = ga + ring[sl * 3 + 0] * g
                gb = gb + ring[sl * 3 + 1] * g
                gc = gc + ring[sl * 3 + 2] * g
            xv = exposed_chunk(img, row, c)
            tv = img.y[row, c]
            wt = lane_weights(img, row, c, valid)
            vx = vec16(0.0)
            for k in range(CHUNK):
                d = xv[k] - tv[k]
                sgn = wp.where(d > 0.0, 1.0, wp.where(d < 0.0, -1.0, 0.0))
                d_ssim = ga[k] + 2.0 * xv[k] * gb[k] + tv[k] * gc[k]
                vx[k] = valid[k] * norm * ((1.0 - lambda_dssim) * wt[k] * sgn - lambda_dssim * d_ssim)
            if in_place != 0:
                v_chunks[row, c] = vx * gain
            else:
                for k in range(CHUNK):
                    f = c * CHUNK + k
                    if f < img.width3:
                        v_flat[row, f] = vx[k] * gain
            sum_a = sum_a + wp.cw_mul(vx, xv - vec16(bias))
            sum_b = sum_b + vx
    partials[i, 0] = wp.vec3(lane_sum16(sum_a), lane_sum16(sum_b), 0.0)
