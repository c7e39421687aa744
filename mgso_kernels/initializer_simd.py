"""The initialiser's block on the CPU, a point's 8 pattern pixels at a time (a native snippet in Warp's kernel).

:func:`init_block_simd` does what one block of :func:`mgso_kernels.initializer.accumulate_init_system` does, with a
point's 8 pattern pixels in the 8 lanes of float vectors (clang's vector extensions: AVX2 on x86-64, two NEON
registers on arm64), as DSO's ``calcResAndGS`` hands its pattern pixels to SSE 4 at a time:

- the pixels' projections, masks, residuals, Huber weights, Jacobians and inverse-depth derivatives are vector
  operations; the bilinear samples are read pixel by pixel (DSO ``getInterpolatedElement33``);
- a point's own sums over its pixels (``jb``, its energy, DSO ``JbBuffer_new``) are lane sums in float32, as in the
  scalar kernel (which also sums a point's 8 pixels in float32 first); its Schur part is summed in float64;
- each term of ``H`` and ``b`` of the points that stay good is a float32 product, summed in float64 lanes over
  the block's points (a lane: one pattern pixel of each point), then over the lanes into the block's partial row.
  The scalar kernel sums a point's 8 products in float32 and adds that into float64; both keep float32 sums to a
  few terms (as :mod:`mgso_kernels.track_simd`).

Why native code: see :mod:`mgso_kernels.track_simd` (Warp's CPU code for value-typed vectors). Where it does not
apply it returns 0 and the kernel runs its scalar loop: on CUDA (the snippet's ``#else``) and when
``InitParams.simd`` is 0 (tests compare the two). The sample's cell is clamped in float before the integer
conversion, so a NaN or infinite projection reads a valid cell; its pixel is masked out as in the scalar loop.
"""

from __future__ import annotations

import warp as wp

from .image_simd import SAMPLE8_CPP
from .photometric import PATTERN_NP

wp.set_module_options({"enable_backward": False})

_PU = ", ".join(f"{float(x):.1f}f" for x in PATTERN_NP[:, 0])
_PV = ", ".join(f"{float(x):.1f}f" for x in PATTERN_NP[:, 1])

# C++ body of init_block_simd (names: the stub's parameters; see mgso_kernels.track_simd for the conventions). The
# partial row's layout is mgso_kernels.initializer's: H 0-63, b 64-71, Hsc 72-135, bsc 136-143, energy 144, good 145.
_SNIPPET = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
typedef float v8f __attribute__((ext_vector_type(8)));
typedef int v8i __attribute__((ext_vector_type(8)));
typedef double v8d __attribute__((ext_vector_type(8)));
const v8f PU = (v8f){%PU%};
const v8f PV = (v8f){%PV%};
const float fx = fx_, fy = fy_, cx = cx_, cy = cy_, ifx = ifx_, ify = ify_;
const float R00 = R.data[0][0], R01 = R.data[0][1], R02 = R.data[0][2];
const float R10 = R.data[1][0], R11 = R.data[1][1], R12 = R.data[1][2];
const float R20 = R.data[2][0], R21 = R.data[2][1], R22 = R.data[2][2];
const float t0 = t.c[0], t1 = t.c[1], t2 = t.c[2];
const float xhi = (float)width - 2.0f, yhi = (float)height - 2.0f;
const float w2 = (float)(dI_t.shape[1] - 2), h2 = (float)(dI_t.shape[0] - 2);
const char* dIp = (const char*)dI_t.data;
const int sdy = dI_t.strides[0], sdx = dI_t.strides[1];
auto hsum = [](v8f x) -> float {
    const float a = (x[0] + x[1]) + (x[2] + x[3]), b = (x[4] + x[5]) + (x[6] + x[7]);
    return a + b;
};
// H's upper triangle (36, row by row) then b (8), as 8 float64 lanes each (one lane: one pattern pixel)
v8d acc[44];
for (int q = 0; q < 44; ++q) acc[q] = 0.0;
double Hs[36], gs[8];
for (int q = 0; q < 36; ++q) Hs[q] = 0.0;
for (int q = 0; q < 8; ++q) gs[q] = 0.0;
double e_sum = 0.0, n_good = 0.0;
for (int i = start; i < end; ++i) {
    const wp::vec2 c = wp::index(uv, i);
    const float idn = wp::index(idepth, i);
    const bool good = wp::index(is_good, i);
    const v8f hx = (c.c[0] + PU - cx) * ifx;
    const v8f hy = (c.c[1] + PV - cy) * ify;
    const v8f p0 = R00 * hx + R01 * hy + R02 + t0 * idn;
    const v8f p1 = R10 * hx + R11 * hy + R12 + t1 * idn;
    const v8f p2 = R20 * hx + R21 * hy + R22 + t2 * idn;
    const v8f iz0 = 1.0f / p2;
    const v8f uu0 = p0 * iz0, vv0 = p1 * iz0;
    const v8f nid0 = idn * iz0;
    const v8f ku = fx * uu0 + cx, kv = fy * vv0 + cy;
%SAMPLE8%    v8f rl0;
    for (int l = 0; l < 8; ++l) rl0[l] = wp::index(ref_color, i, l);
    // masks are -1/0 lanes; a pixel that is not ok has every input zeroed, as the scalar loop
    const v8i ok = (ku > 1.0f) & (kv > 1.0f) & (ku < xhi) & (kv < yhi) & (nid0 > 0.0f) & ((s0 - s0) == 0.0f)
                   & ((rl0 - rl0) == 0.0f);
    bool all_ok = true;
    for (int l = 0; l < 8; ++l) all_ok = all_ok && ok[l] != 0;
    const v8f i0 = (v8f)((v8i)s0 & ok), gx = (v8f)((v8i)s1 & ok), gy = (v8f)((v8i)s2 & ok);
    const v8f rl = (v8f)((v8i)rl0 & ok), uu = (v8f)((v8i)uu0 & ok), vv = (v8f)((v8i)vv0 & ok);
    const v8f nid = (v8f)((v8i)nid0 & ok), iz = (v8f)((v8i)iz0 & ok);
    const v8f m = (v8f)((v8i)(v8f)1.0f & ok);
    const v8f res = i0 - a_exp * rl - b0;
    const v8f ares = (v8f)((v8i)res & 0x7fffffff);
    const v8i small = ares < huber_th;
    const v8f hw = (v8f)(((v8i)(v8f)1.0f & small) | ((v8i)(huber_th / ares) & ~small));
    const float e_pt = hsum(hw * res * res * (2.0f - hw));
    const v8f dxdd = (t0 - t2 * uu) * iz, dydd = (t1 - t2 * vv) * iz;
    v8f sq;
    for (int l = 0; l < 8; ++l) sq[l] = __builtin_sqrtf(hw[l]);
    const v8f hws = (v8f)(((v8i)sq & (hw < 1.0f)) | ((v8i)hw & ~(hw < 1.0f)));
    const v8f dxi = hws * gx * fx * m, dyi = hws * gy * fy * m;
    v8f J[8];
    J[0] = nid * dxi;
    J[1] = nid * dyi;
    J[2] = -nid * (uu * dxi + vv * dyi);
    J[3] = -uu * vv * dxi - (1.0f + vv * vv) * dyi;
    J[4] = (1.0f + uu * uu) * dxi + uu * vv * dyi;
    J[5] = -vv * dxi + uu * dyi;
    J[6] = -hws * a_exp * rl * m;
    J[7] = -hws * m;
    const v8f dd = (dxi * dxdd + dyi * dydd) * m;
    const v8f rr = hws * res * m;
    const v8f sx = dxdd * fx, sy = dydd * fy;
    const v8f s2v = (v8f)((v8i)(sx * sx + sy * sy) & ok);
    float s_max = 0.0f;
    for (int l = 0; l < 8; ++l) s_max = s2v[l] > s_max ? s2v[l] : s_max;
    float jbv[8];
    for (int a = 0; a < 8; ++a) jbv[a] = hsum(dd * J[a]);
    const float jr = hsum(rr * dd), jd = hsum(dd * dd);
    // DSO's maxstep at the largest squared step (the scalar kernel's note)
    const float ms = s_max > 0.0f ? __builtin_fminf(1.0f / __builtin_sqrtf(s_max), 1.0e10f) : 1.0e10f;
    const bool good_new = good && all_ok && e_pt <= max_energy && (e_pt - e_pt == 0.0f);
    const double idd = (double)idn, jb8 = (double)jr, jb9 = (double)jd;
    const double jb8r = jb8 + alpha_opt * (idd - 1.0) + coupling * (idd - (double)wp::index(iR, i));
    const double jb9r = 1.0 / (1.0 + jb9 + alpha_opt + coupling);
    for (int a = 0; a < 8; ++a) wp::index(jb_new, i, a) = good ? (double)jbv[a] : 0.0;
    wp::index(jb_new, i, 8) = good_new ? jb8r : (good ? jb8 : 0.0);
    wp::index(jb_new, i, 9) = good_new ? jb9r : (good ? jb9 : 0.0);
    const float e_new = good_new ? e_pt : wp::index(energy, i, 0);
    wp::index(energy_new, i, 0) = e_new;
    const float dr = idn - 1.0f;
    wp::index(energy_new, i, 1) = good_new ? dr * dr : wp::index(energy, i, 1);
    wp::index(is_good_new, i) = good_new;
    wp::index(maxstep, i) = good ? ms : 1.0e10f;
    e_sum += (double)e_new;
    if (good_new) {
        wp::index(last_hessian_new, i) = jd;
        n_good += 1.0;
        int q = 0;
#pragma unroll
        for (int a = 0; a < 8; ++a) {
            acc[36 + a] += __builtin_convertvector(rr * J[a], v8d);
#pragma unroll
            for (int b = a; b < 8; ++b) { acc[q] += __builtin_convertvector(J[a] * J[b], v8d); ++q; }
        }
        double jbd[8];
        for (int a = 0; a < 8; ++a) jbd[a] = (double)jbv[a];
        const double wsc_b = jb9r * jb8r;
        q = 0;
        for (int a = 0; a < 8; ++a) {
            const double wa = jb9r * jbd[a];
            gs[a] += wsc_b * jbd[a];
            for (int b = a; b < 8; ++b) { Hs[q] += wa * jbd[b]; ++q; }
        }
    }
}
int q = 0;
for (int a = 0; a < 8; ++a) {
    for (int b = a; b < 8; ++b) {
        double h = 0.0;
        for (int l = 0; l < 8; ++l) h += acc[q][l];
        wp::index(partials, blk, a * 8 + b) = h;
        wp::index(partials, blk, b * 8 + a) = h;
        wp::index(partials, blk, 72 + a * 8 + b) = Hs[q];
        wp::index(partials, blk, 72 + b * 8 + a) = Hs[q];
        ++q;
    }
    double g = 0.0;
    for (int l = 0; l < 8; ++l) g += acc[36 + a][l];
    wp::index(partials, blk, 64 + a) = g;
    wp::index(partials, blk, 136 + a) = gs[a];
}
wp::index(partials, blk, 144) = e_sum;
wp::index(partials, blk, 145) = n_good;
return 1;
#else
return 0;
#endif
""".replace("%PU%", _PU).replace("%PV%", _PV).replace("%SAMPLE8%", SAMPLE8_CPP)


@wp.func_native(_SNIPPET)
def init_block_simd(blk: int, start: int, end: int, R: wp.mat33, t: wp.vec3, a_exp: float, b0: float, fx_: float,
                    fy_: float, cx_: float, cy_: float, ifx_: float, ify_: float, width: int, height: int,
                    huber_th: float, max_energy: float, alpha_opt: wp.float64, coupling: wp.float64,
                    uv: wp.array(dtype=wp.vec2), ref_color: wp.array2d(dtype=float), idepth: wp.array(dtype=float),
                    is_good: wp.array(dtype=wp.bool), energy: wp.array2d(dtype=float), iR: wp.array(dtype=float),
                    dI_t: wp.array2d(dtype=wp.vec3), energy_new: wp.array2d(dtype=float),
                    is_good_new: wp.array(dtype=wp.bool), jb_new: wp.array2d(dtype=wp.float64),
                    maxstep: wp.array(dtype=float), last_hessian_new: wp.array(dtype=float),
                    partials: wp.array2d(dtype=wp.float64)) -> int:
    """Points ``[start, end)`` of block ``blk`` (see the module docstring): the per-point outputs written and the
    block's partial row filled. Returns 1, or 0 (nothing written) where the snippet does not apply."""
    ...
