"""The L1 + D-SSIM chunk kernels' work on the CPU as plain loops over rows (Warp native snippets).

:func:`ssim_forward_rows` and :func:`ssim_backward_rows` do what the threads of
:func:`mgso_kernels.loss_chunks.ssim_forward_chunks` and :func:`~mgso_kernels.loss_chunks.ssim_backward_chunks` do
for a run of neighbouring chunks of one band of rows, with the same float32 operations in the same order: the
horizontal window ``in[f] G0 + (in[f - 3] + in[f + 3]) G1 + ...`` (a tap of d pixels is 3 d floats of the
interleaved row), the vertical window from a ring of the last 11 horizontally filtered rows, SSIM and its partials,
the chain rule of the backward, and each chunk's per-lane sums reduced by the same tree into the same partial slot.
So the results are the chunk kernels' bit for bit (tested), and the reductions after them are unchanged.

Why: the chunk kernels work on 16-float vectors whose horizontal taps are lane permutations across chunks; where
the CPU has AVX-512 these are single instructions, but with AVX2 (two 8-float halves) LLVM builds them from
cross-lane shuffles, and the loss ran about 4x slower on a 2-core AMD EPYC (Zen 3) than on the Xeon it was tuned on
(profiles/splat_opt.py: 83 ms forward + backward at 640x480 on 2 threads, against 19-21 ms there). Here every tap is
a load at an offset from a contiguous row, which clang vectorises for whatever vector width the CPU has (AVX2,
AVX-512, NEON); measured in docs/mapping.md ("The loss as row loops").

Each returns 1, or 0 where it does not apply (on CUDA: the ``#else``), and the caller runs the chunk kernels.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .loss_chunks import CHUNK, WINDOW, AdjointChunks, ChunkImages, vec16

wp.set_module_options({"enable_backward": False})

__all__ = ["BLOCK_CHUNKS", "ssim_forward_rows", "ssim_backward_rows", "ssim_forward_blocks", "ssim_backward_blocks",
           "num_blocks"]

# chunks (16 floats each) a CPU thread filters side by side: a ring of 11 x 5 x 64 floats (14 KB, in L1)
BLOCK_CHUNKS = wp.constant(4)
_HALO = 15          # floats a horizontal window reaches on each side (5 pixels of 3 floats)


def _f32(x: float) -> str:
    """A C float literal of float32(x), enough digits that the C compiler's rounding gives that float."""
    return repr(float(np.float32(x))) + "f"


# C++ shared by both snippets: the window's taps as the chunk kernels have them (G0..G5 horizontal by distance,
# WIN[0..10] vertical), the ring's size, the horizontal window of a row segment and the 16-lane sum tree.
_PRELUDE = r"""
const int BW = @BW@;                 // floats of a block (BLOCK_CHUNKS chunks)
const int HALO = @HALO@;
const float G0 = @G0@, G1 = @G1@, G2 = @G2@, G3 = @G3@, G4 = @G4@, G5 = @G5@;
const float WIN[11] = {@W0@, @W1@, @W2@, @W3@, @W4@, @W5@, @W6@, @W7@, @W8@, @W9@, @W10@};
const int nch = img.nch, H = img.height, width3 = img.width3;
const long F = 16L * nch;                          // floats of a chunk row
const int c_end = c0 + BW / 16 < nch ? c0 + BW / 16 : nch;
const int n = 16 * (c_end - c0);                   // floats of this block
const long f0 = 16L * c0;
// the block's input floats of a row, [f0 - HALO, f0 + n + HALO) (NIN of them), are in the row at [I0, I1)
const int NIN = n + 2 * HALO;
const long FS = f0 - HALO;
const int I0 = FS >= 0 ? 0 : (int)(-FS < NIN ? -FS : NIN);
const int I1 = F - FS >= NIN ? NIN : (F - FS > I0 ? (int)(F - FS) : I0);
const int y1 = y0 + band < H ? y0 + band : H;
// out[k] = in[k] G0 + (in[k - 3] + in[k + 3]) G1 + ... (the chunk kernels' hwindow; in[] has HALO floats before k=0)
auto hwin = [&](const float* in, float* out) {
    for (int k = 0; k < n; ++k) {
        const float* p = in + HALO + k;
        float o = p[0] * G0;
        o = o + (p[-3] + p[3]) * G1;
        o = o + (p[-6] + p[6]) * G2;
        o = o + (p[-9] + p[9]) * G3;
        o = o + (p[-12] + p[12]) * G4;
        o = o + (p[-15] + p[15]) * G5;
        out[k] = o;
    }
};
typedef float v16 __attribute__((ext_vector_type(16)));
auto ld16 = [](const float* p) -> v16 { v16 v; __builtin_memcpy(&v, p, sizeof v); return v; };
auto st16 = [](float* p, v16 v) { __builtin_memcpy(p, &v, sizeof v); };
auto lane_sum16 = [](const float* v) -> float {
    float h[8], q[4];
    for (int k = 0; k < 8; ++k) h[k] = v[k] + v[k + 8];
    for (int k = 0; k < 4; ++k) q[k] = h[k] + h[k + 4];
    return (q[0] + q[2]) + (q[1] + q[3]);
};
auto row_of = [](const wp::array_t<wp::vec_t<16, float>>& a, int y) -> const float* {
    return (const float*)((const char*)a.data + (long)y * a.strides[0]);
};
"""

_FORWARD = r"""
if (img.x.strides[1] != 64 || img.y.strides[1] != 64 || adj.d_mu_x.strides[1] != 64 || adj.d_xx.strides[1] != 64
    || adj.d_xy.strides[1] != 64 || (img.use_weight != 0 && img.weight.strides[1] != 64)) return 0;
const float gain = img.gain, bias = img.bias;
float ring[11][5][BW];
float xin[BW + 2 * HALO], tin[BW + 2 * HALO], xx[BW + 2 * HALO], tt[BW + 2 * HALO], xt[BW + 2 * HALO];
float sum_w[BW], sum_l1[BW], sum_s[BW];
for (int k = 0; k < BW; ++k) { sum_w[k] = 0.0f; sum_l1[k] = 0.0f; sum_s[k] = 0.0f; }
for (int yy = y0 - 5; yy < y1 + 5; ++yy) {
    const int slot = (yy - y0 + 5) % 11;
    if (yy >= 0 && yy < H) {
        const float* xr = row_of(img.x, yy);
        const float* tr = row_of(img.y, yy);
        // the block's floats of the row: zero outside it, no bounds test inside
        for (int i = 0; i < I0; ++i) { xin[i] = 0.0f; tin[i] = 0.0f; xx[i] = 0.0f; tt[i] = 0.0f; xt[i] = 0.0f; }
        for (int i = I1; i < NIN; ++i) { xin[i] = 0.0f; tin[i] = 0.0f; xx[i] = 0.0f; tt[i] = 0.0f; xt[i] = 0.0f; }
        for (int i = I0; i < I1; ++i) {
            const float xv = xr[FS + i] * gain + bias;
            const float tv = tr[FS + i];
            xin[i] = xv; tin[i] = tv;
            xx[i] = xv * xv; tt[i] = tv * tv; xt[i] = xv * tv;
        }
        hwin(xin, ring[slot][0]);
        hwin(tin, ring[slot][1]);
        hwin(xx, ring[slot][2]);
        hwin(tt, ring[slot][3]);
        hwin(xt, ring[slot][4]);
    } else {
        for (int m = 0; m < 5; ++m)
            for (int k = 0; k < n; ++k) ring[slot][m][k] = 0.0f;
    }
    const int row = yy - 5;
    if (row < y0) continue;
    const int base = (row - y0) % 11;
    // the vertical window, 16 floats a vector, each sum over the 11 taps in order kept in a register (the same
    // sums as a loop over the taps that reads and writes them back at every tap, which is load- and store-bound)
    int slt[11];
    for (int t = 0; t < 11; ++t) { int sl = base + t; if (sl >= 11) sl -= 11; slt[t] = sl; }
    float mx[BW], my[BW], exx[BW], eyy[BW], exy[BW];
    for (int k = 0; k < n; k += 16) {
        v16 a0 = 0.0f, a1 = 0.0f, a2 = 0.0f, a3 = 0.0f, a4 = 0.0f;
        for (int t = 0; t < 11; ++t) {
            const float g = WIN[t];
            a0 = a0 + ld16(&ring[slt[t]][0][k]) * g;
            a1 = a1 + ld16(&ring[slt[t]][1][k]) * g;
            a2 = a2 + ld16(&ring[slt[t]][2][k]) * g;
            a3 = a3 + ld16(&ring[slt[t]][3][k]) * g;
            a4 = a4 + ld16(&ring[slt[t]][4][k]) * g;
        }
        st16(mx + k, a0); st16(my + k, a1); st16(exx + k, a2); st16(eyy + k, a3); st16(exy + k, a4);
    }
    const float* xr = row_of(img.x, row) + f0;
    const float* tr = row_of(img.y, row) + f0;
    const float* wr = img.use_weight != 0 ? row_of(img.weight, row) + f0 : nullptr;
    float* dm = (float*)row_of(adj.d_mu_x, row) + f0;
    float* dxx = (float*)row_of(adj.d_xx, row) + f0;
    float* dxy = (float*)row_of(adj.d_xy, row) + f0;
    for (int k = 0; k < n; ++k) {
        const float valid = f0 + k < width3 ? 1.0f : 0.0f;
        const float wt = wr != nullptr ? wr[k] * valid : valid;
        const float xv = xr[k] * gain + bias;
        const float tv = tr[k];
        // ssim_lane
        const float ux = mx[k], uy = my[k];
        const float sxx = exx[k] - ux * ux;
        const float syy = eyy[k] - uy * uy;
        const float sxy = exy[k] - ux * uy;
        const float n1 = 2.0f * ux * uy + c1;
        const float n2 = 2.0f * sxy + c2;
        const float i1 = 1.0f / (ux * ux + uy * uy + c1);
        const float i2 = 1.0f / (sxx + syy + c2);
        const float inv = i1 * i2;
        const float s = n1 * n2 * inv;
        const float d_mx = 2.0f * uy * (n2 - n1) * inv + 2.0f * ux * s * (i2 - i1);
        dm[k] = wt * d_mx;
        dxx[k] = wt * (-s * i2);
        dxy[k] = wt * (2.0f * n1 * inv);
        const float l1 = __builtin_fabsf(xv - tv);
        sum_w[k] = sum_w[k] + wt;
        sum_l1[k] = sum_l1[k] + wt * l1;
        sum_s[k] = sum_s[k] + wt * s;
    }
}
for (int c = c0; c < c_end; ++c) {
    const int k0 = 16 * (c - c0);
    wp::vec3 p(lane_sum16(sum_w + k0), lane_sum16(sum_l1 + k0), lane_sum16(sum_s + k0));
    wp::index(partials, b * nch + c, 0) = p;
}
return 1;
"""

_BACKWARD = r"""
if (img.x.strides[1] != 64 || img.y.strides[1] != 64 || adj.d_mu_x.strides[1] != 64 || adj.d_xx.strides[1] != 64
    || adj.d_xy.strides[1] != 64 || (img.use_weight != 0 && img.weight.strides[1] != 64)
    || (in_place != 0 && v_chunks.strides[1] != 64) || v_flat.strides[1] != 4) return 0;
const float gain_x = img.gain, bias_x = img.bias;
const float weight_sum = (float)wp::index(totals, 0, 0)[0];
float norm = 0.0f;
if (weight_sum > 0.0f) norm = 1.0f / weight_sum;
const float one_l = 1.0f - lambda_dssim;
float ring[11][3][BW];
float ain[BW + 2 * HALO], bin[BW + 2 * HALO], cin[BW + 2 * HALO];
float sum_a[BW], sum_b[BW];
for (int k = 0; k < BW; ++k) { sum_a[k] = 0.0f; sum_b[k] = 0.0f; }
for (int yy = y0 - 5; yy < y1 + 5; ++yy) {
    const int slot = (yy - y0 + 5) % 11;
    if (yy >= 0 && yy < H) {
        const float* ar = row_of(adj.d_mu_x, yy);
        const float* br = row_of(adj.d_xx, yy);
        const float* cr = row_of(adj.d_xy, yy);
        // the block's floats of the row: zero outside it, no bounds test inside
        for (int i = 0; i < I0; ++i) { ain[i] = 0.0f; bin[i] = 0.0f; cin[i] = 0.0f; }
        for (int i = I1; i < NIN; ++i) { ain[i] = 0.0f; bin[i] = 0.0f; cin[i] = 0.0f; }
        for (int i = I0; i < I1; ++i) {
            ain[i] = ar[FS + i];
            bin[i] = br[FS + i];
            cin[i] = cr[FS + i];
        }
        hwin(ain, ring[slot][0]);
        hwin(bin, ring[slot][1]);
        hwin(cin, ring[slot][2]);
    } else {
        for (int m = 0; m < 3; ++m)
            for (int k = 0; k < n; ++k) ring[slot][m][k] = 0.0f;
    }
    const int row = yy - 5;
    if (row < y0) continue;
    const int base = (row - y0) % 11;
    int slt[11];
    for (int t = 0; t < 11; ++t) { int sl = base + t; if (sl >= 11) sl -= 11; slt[t] = sl; }
    float ga[BW], gb[BW], gc[BW];
    for (int k = 0; k < n; k += 16) {
        v16 a0 = 0.0f, a1 = 0.0f, a2 = 0.0f;
        for (int t = 0; t < 11; ++t) {
            const float g = WIN[t];
            a0 = a0 + ld16(&ring[slt[t]][0][k]) * g;
            a1 = a1 + ld16(&ring[slt[t]][1][k]) * g;
            a2 = a2 + ld16(&ring[slt[t]][2][k]) * g;
        }
        st16(ga + k, a0); st16(gb + k, a1); st16(gc + k, a2);
    }
    const float* xr = row_of(img.x, row) + f0;
    const float* tr = row_of(img.y, row) + f0;
    const float* wr = img.use_weight != 0 ? row_of(img.weight, row) + f0 : nullptr;
    float* vc = in_place != 0 ? (float*)row_of(v_chunks, row) + f0 : nullptr;
    float* vf = (float*)((char*)v_flat.data + (long)row * v_flat.strides[0]);
    for (int k = 0; k < n; ++k) {
        const long f = f0 + k;
        const float valid = f < width3 ? 1.0f : 0.0f;
        const float wt = wr != nullptr ? wr[k] * valid : valid;
        const float xv = xr[k] * gain_x + bias_x;
        const float tv = tr[k];
        const float d = xv - tv;
        const float sgn = d > 0.0f ? 1.0f : (d < 0.0f ? -1.0f : 0.0f);
        const float d_ssim = ga[k] + 2.0f * xv * gb[k] + tv * gc[k];
        const float vx = valid * norm * (one_l * wt * sgn - lambda_dssim * d_ssim);
        if (vc != nullptr) {
            vc[k] = vx * gain;
        } else if (f < width3) {
            vf[f] = vx * gain;
        }
        sum_a[k] = sum_a[k] + vx * (xv - bias);
        sum_b[k] = sum_b[k] + vx;
    }
}
for (int c = c0; c < c_end; ++c) {
    const int k0 = 16 * (c - c0);
    wp::vec3 p(lane_sum16(sum_a + k0), lane_sum16(sum_b + k0), 0.0f);
    wp::index(partials, b * nch + c, 0) = p;
}
return 1;
"""


def _cpp(body: str) -> str:
    """The snippet: CPU only (clang), no contraction into FMAs (the chunk kernels make none), the prelude, ``body``,
    with the window's taps and the block's size filled in."""
    text = ("#if defined(__clang__) && !defined(__CUDA_ARCH__)\n{\n#pragma clang fp contract(off)\n"
            + _PRELUDE + body + "\n}\n#else\nreturn 0;\n#endif\n")
    subs = {"BW": str(BLOCK_CHUNKS * CHUNK), "HALO": str(_HALO)}
    subs.update({f"G{d}": _f32(WINDOW[5 + d]) for d in range(6)})
    subs.update({f"W{t}": _f32(WINDOW[t]) for t in range(11)})
    for name, value in subs.items():
        text = text.replace(f"@{name}@", value)
    if "@" in text:
        raise ValueError("loss_simd: a value of the snippet is not filled in")
    return text


@wp.func_native(_cpp(_FORWARD))
def ssim_forward_rows(b: int, c0: int, y0: int, band: int, img: ChunkImages, c1: float, c2: float,
                      adj: AdjointChunks, partials: wp.array2d(dtype=wp.vec3)) -> int:
    """Rows ``[y0, y0 + band)`` (band ``b``) of chunks ``[c0, c0 + BLOCK_CHUNKS)``: what the chunk threads
    ``(b, c)`` of :func:`~mgso_kernels.loss_chunks.ssim_forward_chunks` write (the SSIM partial maps and each chunk's
    partial sums). Returns 1, or 0 (nothing written) where it does not apply."""
    ...


@wp.func_native(_cpp(_BACKWARD))
def ssim_backward_rows(b: int, c0: int, y0: int, band: int, img: ChunkImages, adj: AdjointChunks,
                       totals: wp.array2d(dtype=wp.vec3d), lambda_dssim: float, gain: float, bias: float,
                       v_chunks: wp.array2d(dtype=vec16),
                       v_flat: wp.array2d(dtype=float), in_place: int,
                       partials: wp.array2d(dtype=wp.vec3)) -> int:
    """The same for :func:`~mgso_kernels.loss_chunks.ssim_backward_chunks` (dL/dI and the exposure partials)."""
    ...


def num_blocks(nch: int) -> int:
    """Blocks of :data:`BLOCK_CHUNKS` chunks in a row of ``nch`` chunks (the last may be shorter)."""
    return -(-int(nch) // BLOCK_CHUNKS)


@wp.kernel
def ssim_forward_blocks(offset: int, img: ChunkImages, band: int, nblk: int, c1: float, c2: float,
                        adj: AdjointChunks, partials: wp.array2d(dtype=wp.vec3), status: wp.array(dtype=wp.int32)):
    """One thread per (band, block of chunks): :func:`ssim_forward_rows`; ``status[i]`` 1 when it ran (the CPU)."""
    i = offset + wp.tid()
    b = i // nblk
    cb = i - b * nblk
    status[i] = ssim_forward_rows(b, cb * BLOCK_CHUNKS, b * band, band, img, c1, c2, adj, partials)


@wp.kernel
def ssim_backward_blocks(offset: int, img: ChunkImages, band: int, nblk: int, adj: AdjointChunks,
                         totals: wp.array2d(dtype=wp.vec3d), lambda_dssim: float, gain: float, bias: float,
                         v_chunks: wp.array2d(dtype=vec16), v_flat: wp.array2d(dtype=float), in_place: int,
                         partials: wp.array2d(dtype=wp.vec3), status: wp.array(dtype=wp.int32)):
    """One thread per (band, block of chunks): :func:`ssim_backward_rows`; ``status[i]`` 1 when it ran."""
    i = offset + wp.tid()
    b = i // nblk
    cb = i - b * nblk
    status[i] = ssim_backward_rows(b, cb * BLOCK_CHUNKS, b * band, band, img, adj, totals, lambda_dssim, gain,
                                   bias, v_chunks, v_flat, in_place, partials)
