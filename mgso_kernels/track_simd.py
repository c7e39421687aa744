"""The coarse tracker's block on the CPU, eight points at a time (a native snippet in Warp's kernel).

:func:`coarse_block_simd` does what one block of :func:`mgso_kernels.track.reduce_tracking_system` does for DSO's
coarse tracker (one residual a point, ``ref_color [N, 1]``, no gradient weight, no stored Jacobians; the system
or the energy alone), with the arithmetic in vectors of 8 floats (clang's vector extensions: AVX2 on x86-64, two
NEON registers on arm64) the way DSO's ``calcGSSSE`` uses SSE:

- the 8 points' projections, residuals, Huber weights, energies and Jacobians are vector operations; only the
  bilinear samples are read point by point (12 loads a point, as DSO's ``getInterpolatedElement33``);
- each term of ``H``'s upper triangle and ``b`` is a float32 product (as the scalar kernel's ``J``), summed in
  float64 lanes over the block's points, then over the lanes into the block's partial row, which the launcher sums
  in float64 as before (float32 lanes, as DSO's ``Accumulator11``, were 15 % faster and tried first:
  docs/tracking_kernels.md, "Eight points at a time on the CPU");
- the counts are summed in float lanes (exact) and then in float64; the flow indicators (a point in 32) are left
  to the kernel, which adds them with the scalar loop's ``flow_counts``.

Why native code: Warp's CPU code generator writes every value-typed vector as loads and stores of the whole value,
so the same vector arithmetic written in Warp's language ran slower than scalar code (docs/tracking_kernels.md). On
the 2-core machine this block takes 0.38-0.50x the scalar kernel's time on the dense 640x480 levels of
``profiles/track_kernels.py`` (docs/tracking_kernels.md, "Eight points at a time on the CPU").

Where it does not apply it returns 0 and the kernel runs its scalar loop: on CUDA (the snippet's ``#else``), with
8-pixel patterns or gradient weights, or when ``TrackParams.simd`` is 0 (tests compare the two paths). Memory
safety: the sample's cell is clamped in float before the integer conversion, so a NaN or infinite projection reads
a valid cell (its residual is masked out), as the scalar kernel's clamped index does.
"""

from __future__ import annotations

import warp as wp

from .image_simd import SAMPLE8_CPP
from .photometric import FramePair, Intrinsics, PhotometricParams

wp.set_module_options({"enable_backward": False})

# C++ body of coarse_block_simd. Names are the stub's parameters; Warp's generated code defines float()/int() as
# macros, so conversions are C casts, and the CPU build has no libm declarations (hence __builtin_fminf).
_SNIPPET = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
typedef float v8f __attribute__((ext_vector_type(8)));
typedef int v8i __attribute__((ext_vector_type(8)));
typedef double v8d __attribute__((ext_vector_type(8)));
if (ref_color.shape[1] != 1 || photo.grad_c2 > 0.0f) return 0;
const float fx = cam.fx, fy = cam.fy, cx = cam.cx, cy = cam.cy;
const float xhi = (float)cam.width - photo.border_hi, yhi = (float)cam.height - photo.border_hi;
const float lo = photo.border_lo;
const float wm1 = (float)(cam.width - 1), hm1 = (float)(cam.height - 1);
const float w2 = (float)(dI_t.shape[1] - 2), h2 = (float)(dI_t.shape[0] - 2);
const float hth = photo.huber_th, cutoff = cutoff_th;
const float a_rel = pair.a_rel, b_h = pair.b_h, b_t = pair.b_t;
const float t0 = pair.t.c[0], t1 = pair.t.c[1], t2 = pair.t.c[2];
const float m00 = RKi.data[0][0], m01 = RKi.data[0][1], m02 = RKi.data[0][2];
const float m10 = RKi.data[1][0], m11 = RKi.data[1][1], m12 = RKi.data[1][2];
const float m20 = RKi.data[2][0], m21 = RKi.data[2][1], m22 = RKi.data[2][2];
const char* uvp = (const char*)host_uv.data;
const char* idp = (const char*)idepth.data;
const char* colp = (const char*)ref_color.data;
const char* dIp = (const char*)dI_t.data;
const int suv = host_uv.strides[0], sid = idepth.strides[0], scol = ref_color.strides[0];
const int sdy = dI_t.strides[0], sdx = dI_t.strides[1];
// H's upper triangle (36, row by row) and b (8) as 8 float64 lanes each; the counts as float lanes
v8d acc[36];
for (int q = 0; q < 36; ++q) acc[q] = 0.0;
v8d accb[8];
for (int a = 0; a < 8; ++a) accb[a] = 0.0;
v8d se = 0.0;
v8f sok = 0.0f, sinl = 0.0f, ssat = 0.0f;
for (int i0 = start; i0 < end; i0 += 8) {
    const int m = end - i0 < 8 ? end - i0 : 8;
    // a short last group repeats point i0 in its spare lanes; `lane` masks them out of every sum and store
    v8f u, v, id, col;
    for (int l = 0; l < 8; ++l) {
        const int i = l < m ? i0 + l : i0;
        const float* pu = (const float*)(uvp + (long)i * suv);
        u[l] = pu[0]; v[l] = pu[1];
        id[l] = *(const float*)(idp + (long)i * sid);
        col[l] = *(const float*)(colp + (long)i * scol);
    }
    const v8f p0 = m00 * u + m01 * v + m02 + t0 * id;
    const v8f p1 = m10 * u + m11 * v + m12 + t1 * id;
    const v8f p2 = m20 * u + m21 * v + m22 + t2 * id;
    const v8f dr = 1.0f / p2;
    const v8f un = p0 * dr, vn = p1 * dr;
    const v8f ku = fx * un + cx, kv = fy * vn + cy;
    // bilinear (I, dx, dy), point by point
%SAMPLE8%    // masks are -1/0 lanes; a select is (x & mask) | (y & ~mask) on the bits
    const v8i lane = (v8i){0, 1, 2, 3, 4, 5, 6, 7} < m;
    const v8i front = dr > 0.0f;
    const v8i inside = (ku > lo) & (kv > lo) & (ku < xhi) & (kv < yhi) & (ku >= 0.0f) & (kv >= 0.0f) & (ku <= wm1)
                       & (kv <= hm1);
    const v8i ok = lane & front & inside & ((s0 - s0) == 0.0f);
    const v8f hc = col - b_h;
    const v8f r = (v8f)((v8i)((s0 - b_t) - a_rel * hc) & ok);
    const v8f ar = (v8f)((v8i)r & 0x7fffffff);
    const v8i sat = ok & (ar > cutoff);
    const v8i inl = ok & ~sat;
    const v8f hwd = hth / ar;
    const v8f hw = (v8f)(((v8i)(v8f)1.0f & (ar < hth)) | ((v8i)hwd & ~(ar < hth)));
    const v8f wgt = (v8f)((v8i)hw & inl);
    const v8f e_in = hw * r * r * (2.0f - hw);
    const v8f e = (v8f)(((v8i)e_in & inl) | ((v8i)(v8f)max_energy & sat));
    const v8i st = (front & ((ok & (sat & 3)) | (~ok & 1))) | (~front & 2);
    for (int l = 0; l < m; ++l) {
        wp::index(residual, i0 + l, 0) = r[l];
        wp::index(weight, i0 + l, 0) = wgt[l];
        wp::index(state, i0 + l, 0) = st[l];
    }
    se += __builtin_convertvector(e, v8d);
    sok += (v8f)((v8i)(v8f)1.0f & ok);
    sinl += (v8f)((v8i)(v8f)1.0f & inl);
    ssat += (v8f)((v8i)(v8f)1.0f & sat);
    const v8f nid = id * dr;
    const v8f dx = (v8f)((v8i)(s1 * fx) & ok), dy = (v8f)((v8i)(s2 * fy) & ok);
    v8f J[8];
    J[0] = nid * dx;
    J[1] = nid * dy;
    J[2] = -nid * (un * dx + vn * dy);
    J[3] = -(un * vn * dx + dy * (1.0f + vn * vn));
    J[4] = un * vn * dy + dx * (1.0f + un * un);
    J[5] = un * dy - vn * dx;
    J[6] = -a_rel * hc;
    J[7] = -1.0f;
    for (int a = 0; a < 6; ++a) J[a] = (v8f)((v8i)J[a] & ok);  // 0, not 0 * inf, where not ok
    if (with_system) {
        const v8f wr = wgt * r;
        int q = 0;
#pragma unroll
        for (int a = 0; a < 8; ++a) {
            const v8f wa = wgt * J[a];
            accb[a] += __builtin_convertvector(wr * J[a], v8d);
#pragma unroll
            for (int b = a; b < 8; ++b) { acc[q] += __builtin_convertvector(wa * J[b], v8d); ++q; }
        }
    }
}
// the lanes summed in float64 into the partial row (mgso_kernels.track's layout: H 0-63, b 64-71, counts 72-75)
auto lanes = [](v8d x) -> double {
    double s = 0.0;
    for (int l = 0; l < 8; ++l) s += x[l];
    return s;
};
int q = 0;
for (int a = 0; a < 8; ++a) {
    for (int b = a; b < 8; ++b) {
        const double h = lanes(acc[q++]);
        wp::index(partials, blk, a * 8 + b) = h;
        wp::index(partials, blk, b * 8 + a) = h;
    }
    wp::index(partials, blk, 64 + a) = lanes(accb[a]);
}
double cnt[4] = {0.0, 0.0, 0.0, 0.0};
for (int l = 0; l < 8; ++l) {
    cnt[0] += se[l];
    cnt[1] += (double)sok[l];
    cnt[2] += (double)sinl[l];
    cnt[3] += (double)ssat[l];
}
wp::index(partials, blk, 72) = cnt[0];
wp::index(partials, blk, 73) = cnt[1];
wp::index(partials, blk, 74) = cnt[2];
wp::index(partials, blk, 75) = cnt[3];
return 1;
#else
return 0;
#endif
""".replace("%SAMPLE8%", SAMPLE8_CPP)


@wp.func_native(_SNIPPET)
def coarse_block_simd(blk: int, start: int, end: int, next_flow: int, max_energy: float, Ki: wp.mat33,
                      RKi: wp.mat33, host_uv: wp.array(dtype=wp.vec2), idepth: wp.array(dtype=float),
                      ref_color: wp.array2d(dtype=float), pair: FramePair, cam: Intrinsics,
                      dI_t: wp.array2d(dtype=wp.vec3), photo: PhotometricParams, cutoff_th: float, flow_stride: int,
                      residual: wp.array2d(dtype=float), weight: wp.array2d(dtype=float),
                      state: wp.array2d(dtype=wp.int32), partials: wp.array2d(dtype=wp.float64),
                      with_system: int) -> int:
    """Points ``[start, end)`` of block ``blk`` (see the module docstring): residuals, weights and states written,
    the block's partial row filled up to its counts (``H`` and ``b`` zero unless ``with_system``; the flow slots are
    the caller's). Returns 1, or 0 (nothing written) where the snippet does not apply."""
    ...
