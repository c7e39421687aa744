"""The CPU's tile blends as plain C++ (the text of Warp native snippets used by :mod:`~mgso_kernels.splat.raster_tile`).

:mod:`~mgso_kernels.splat.raster_tile`'s kernels, a thread per 16x16 tile, do per Gaussian of the tile's list and per
tile row it reaches: the row's span (a ``sqrt``), a branch on the span, then 16 (or 8) lanes of blending on a copy of
the row's state that is written back. Measured on a Zen 3 core (docs/rasteriser.md) that costs about 200 cycles a
row visit, four to five times the lanes' arithmetic: the lanes wait on the span and on the branches around them, one
row after the other. These snippets compute the same thing in another order of work:

- **Per Gaussian, the lane constants once**: ``dx = x0 + k - mean_x`` and ``-0.5 a dx^2`` for the 16 columns (the
  same products, in the same order, as :func:`~mgso_kernels.splat.raster_tile.lane_power` makes per row).
- **Spans first, then the blend**: the rows the Gaussian reaches are turned into a compact list of the half rows
  (8 pixels, one AVX2 vector) that have a live pixel inside its ellipse, without a branch per half; then the list is
  blended, each entry in place on the tile's state, with no branch inside an entry. Entries are independent (a pixel
  belongs to one), so the core overlaps them.
- No select on a value just loaded from the same place (``T = Tk * (took ? 1 - alpha : 1)`` instead of
  ``took ? Tn : Tk``): LLVM makes such a select a masked store, slow on Zen 3 and not forwarded to the next load.
- The backward lists half rows the same way, the left halves and the right ones in two blocks, and does a block in
  two passes: the first blends back to front and keeps each entry's ``v_pow`` and ``w``, the second sums what the
  gradients need per lane, each sum in a register (one pass reading and writing eight sums through memory every
  entry took 112-119 against 102 ms a backward blend, 640x480, 50k Gaussians, one Zen 3 thread; docs/rasteriser.md).
  The lane sums are those of one pass in list order, bit for bit, reduced by the Warp kernel's tree.

Every value is the Warp kernel's to float rounding: the same operations, but with FMAs where the snippets ask for one
(``__builtin_elementwise_fma``; contraction stays off elsewhere) and ``exp_lane``'s polynomial in Estrin's form
(measured at most 2e-6 of an array's largest value apart, and the same stop decisions, ``n_contrib``, on the tests'
scenes). The forward, coverage and backward snippets share ``vexp`` and the power's expression, so they make the
same skip and stop decisions bit for bit, and :mod:`mgso_kernels.reference.splat` stays the twin. The FMAs and the
shorter dependency chain of Estrin's form took a forward blend from 74-75 to 62-64 ms and a backward blend from
135-144 to 119-126 ms (640x480, 50k Gaussians, one Zen 3 thread; docs/rasteriser.md); reading the loop constants from a
stack array and single x86 instructions for min, max and the lanes' bits (each behind ``__AVX__``) took the forward
blend on to 55-56 ms and the coverage render from 80-81 to 72-74 ms, bit for bit. Each snippet returns 1, or 0
where it does not apply (CUDA, or arrays that are not contiguous) and the Warp code after it runs.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FORWARD", "ALPHA", "BACKWARD", "fill"]


def _f32(x: float) -> str:
    """A C float literal of float32(x) (enough digits that the compiler's rounding gives that float)."""
    return repr(float(np.float32(x))) + "f"


# shared by the snippets: the blend's constants and exp_lane's polynomial (raster_tile.exp_lane, the same operations)
_PRELUDE = r"""
const float AMAX = @ALPHA_MAX@, AMIN = @ALPHA_MIN@, TMIN = @T_MIN@;
const float LOG2E_ = @LOG2E@, LN2HI = @LN2_HI@, LN2LO = @LN2_LO@;
typedef float v8f __attribute__((ext_vector_type(8)));
typedef int v8i __attribute__((ext_vector_type(8)));
const v8i LANE = {0, 1, 2, 3, 4, 5, 6, 7};
const v8i BIT = {1, 2, 4, 8, 16, 32, 64, 128};
// 8 ints from anywhere (a v8i pointer must be 32-byte aligned)
auto ldi = [](const int* p) -> v8i { v8i v; __builtin_memcpy(&v, p, sizeof v); return v; };
// a ? b : c per lane, bit for bit (a: a comparison's all-ones / zero lanes)
auto sel = [](v8i a, v8f b, v8f c) -> v8f { return (v8f)((a & (v8i)b) | (~a & (v8i)c)); };
// wp::min(k, v) as Warp's CPU code has it (C fmin: a NaN v gives k); on x86 one vminps(v, k), which returns its
// second operand where either is NaN or they are equal (the same value), v where v < k: the same result; LLVM made
// fmin's NaN rule a compare, a second compare and two blends
auto vmin = [&](v8f k, v8f v) -> v8f {
#if defined(__AVX__)
    return __builtin_ia32_minps256(v, k);
#else
    return sel(k <= v, k, sel(v == v, v, k));
#endif
};
// max(a, b) of lanes that are never NaN (vmaxps on x86; __builtin_elementwise_max adds fmax's NaN rule)
auto vmax = [](v8f a, v8f b) -> v8f {
#if defined(__AVX__)
    return __builtin_ia32_maxps256(a, b);
#else
    return __builtin_elementwise_max(a, b);
#endif
};
// the lanes of a comparison (all-ones / zero) as 8 bits, lane k at bit k (vmovmskps on x86: one instruction where
// OR-reducing the lanes' bits took eight)
auto bits8 = [&](v8i c) -> int {
#if defined(__AVX__)
    return __builtin_ia32_movmskps256((v8f)c);
#else
    return __builtin_reduce_or(c & BIT);
#endif
};
// a b + c rounded once (an FMA instruction; the snippets say where they want one, contraction stays off)
auto fma8 = [](v8f a, v8f b, v8f c) -> v8f { return __builtin_elementwise_fma(a, b, c); };
// vexp's constants and the blend's thresholds as vectors in a stack array that the compiler cannot fold back into
// constants (the empty asm statement tells it the array may have changed): the loops read them as memory operands,
// where LLVM rematerialised each from the constant pool on every list entry (a movabs and a broadcast, under Warp's
// large code model: 26 of an entry's 100 instructions). The same values, so the same results bit for bit
enum { KX_MIN, K_LOG2E, K_HALF, K_NLN2HI, K_NLN2LO, K_P3, K_P5, K_P4, K_P7, K_P6, K_AMAX, K_AMIN, K_TMIN, K_N };
alignas(32) float KV[K_N][8];
{
    const float k1[K_N] = {-87.0f, LOG2E_, 0.5f, -LN2HI, -LN2LO, 0.16666667f, 0.008333334f, 0.041666668f,
                           0.0001984127f, 0.0013888889f, AMAX, AMIN, TMIN};
    for (int i = 0; i < K_N; ++i)
        for (int k = 0; k < 8; ++k) KV[i][k] = k1[i];
}
asm volatile("" : : "r"(&KV[0][0]) : "memory");
auto kv = [&](int i) -> v8f { return *(const v8f*)KV[i]; };
// exp(x) per lane: exp_lane's range reduction and polynomial with FMAs, the polynomial in Estrin's form (three
// dependent steps after f instead of Horner's seven); within float rounding of exp_lane (the images and gradients
// against the Warp kernels', tests/kernels/test_splat_tile.py)
auto vexp = [&](v8f x) -> v8f {
#if defined(__AVX__)
    x = __builtin_ia32_maxps256(x, kv(KX_MIN));     // vmaxps(x, k): k where x is NaN, as the select below
#else
    x = sel(x >= kv(KX_MIN), x, kv(KX_MIN));
#endif
    const v8f nf = __builtin_elementwise_floor(fma8(x, kv(K_LOG2E), kv(K_HALF)));
    const v8f f = fma8(nf, kv(K_NLN2LO), fma8(nf, kv(K_NLN2HI), x));
    const v8f f2 = f * f, f4 = f2 * f2;
    const v8f p01 = 1.0f + f, p23 = fma8(f, kv(K_P3), kv(K_HALF));
    const v8f p45 = fma8(f, kv(K_P5), kv(K_P4));
    const v8f p67 = fma8(f, kv(K_P7), kv(K_P6));
    const v8f p = fma8(f4, fma8(f2, p67, p45), fma8(f2, p23, p01));
    return p * (v8f)((__builtin_convertvector(nf, v8i) + 127) << 23);
};
if (splats.strides[0] != 32 || splat_rgbz.strides[0] != 16) return 0;
const float* sp = (const float*)splats.data;
const float* cp = (const float*)splat_rgbz.data;
const float fy0 = (float)y0, fx0 = (float)x0;
// one Gaussian of the tile's list, and the rows [lo, hi] of the tile its cut-off ellipse reaches (tile_rows)
struct Splat { float mx, my, a, b, c, op, r2, det, inv_a; int lo, hi; };
auto load_splat = [&](int j) -> Splat {
    const float* s = sp + 8L * j;
    Splat g;
    g.mx = s[0]; g.my = s[1]; g.a = s[2]; g.b = s[3]; g.c = s[4]; g.op = s[5]; g.r2 = s[7];
    g.det = g.a * g.c - g.b * g.b;
    g.inv_a = 1.0f / g.a;
    const float ry = wp::sqrt(g.a * g.r2 / g.det);
    const int lo0 = (int)wp::ceil(g.my - ry - fy0);
    const int hi0 = (int)wp::floor(g.my + ry - fy0);
    g.lo = lo0 > 0 ? lo0 : 0;
    g.hi = hi0 < ny - 1 ? hi0 : ny - 1;
    return g;
};
// list_halves(g, done, rmax, i): per row r in [lo, hi] (8 rows a vector) the span of the row inside the cut-off
// ellipse as a bit mask (row_span_mask's operations), less the bits of done[r], and none where rmax[r] <= i; then
// the half rows (q = 2 r + 0 / 1) with a bit left, listed in hq / hm (their 8 bits) with the row's -0.5 c dy^2,
// b dy and dy in hc, hb, hd: the left halves (q even) at 0, 1, ..., the right ones at 16, 17, ..., each block in
// row order. Sets nl and nr to their numbers. done and rmax hold 32 rows (16 and a vector's overhang).
alignas(32) int no_rows[32], all_rows[32];     // none done; no row's list ends
for (int r = 0; r < 32; ++r) { no_rows[r] = 0; all_rows[r] = 2147483647; }
alignas(32) int mrow[16];
alignas(32) float dyr[16], cyyr[16], bdyr[16];
int hq[32], hm[32];
float hc[32], hb[32], hd[32];
int nl = 0, nr = 0;
auto list_halves = [&](const Splat& g, const int* done, const int* rmax, int i) {
    const int lo = g.lo, hi = g.hi, nrows = hi - lo + 1;
    const float ar2 = g.a * g.r2, hc_ = -0.5f * g.c;
    for (int r8 = 0; r8 < nrows; r8 += 8) {
        const v8i rr = (v8i)(lo + r8) + LANE;
        const v8f dy = ((v8f)fy0 + __builtin_convertvector(rr, v8f)) - g.my;
        const v8f disc = ar2 - g.det * dy * dy;
        const v8f half = __builtin_elementwise_sqrt(sel(disc < 0.0f, (v8f)0.0f, disc)) * g.inv_a;
        const v8f xc = g.mx - g.b * dy * g.inv_a;
        const v8i lm = __builtin_elementwise_max(
            __builtin_convertvector(__builtin_elementwise_ceil(xc - half), v8i) - x0, (v8i)0);
        const v8i h = __builtin_elementwise_min(
            __builtin_convertvector(__builtin_elementwise_floor(xc + half), v8i) - x0, (v8i)(nx - 1));
        const v8i live = ~(disc < 0.0f) & (lm <= h) & (rr <= hi) & (ldi(rmax + lo + r8) > i);
        // shift counts kept in [0, 16] where the row is not live (a vector shift by 32 or more is undefined)
        const v8i l = __builtin_elementwise_min(lm, (v8i)15);
        const v8i len = __builtin_elementwise_min(__builtin_elementwise_max(h - l + 1, (v8i)0), (v8i)16);
        const v8i span = (((v8i)1 << len) - 1) << l;
        *(v8i*)(mrow + r8) = span & ~ldi(done + lo + r8) & live;
        *(v8f*)(dyr + r8) = dy;
        *(v8f*)(cyyr + r8) = hc_ * dy * dy;
        *(v8f*)(bdyr + r8) = g.b * dy;
    }
    int a = 0, b = 16;
    for (int t = 0; t < nrows; ++t) {
        const int m = mrow[t], q = 2 * (lo + t);
        const float cyy = cyyr[t], bdy = bdyr[t], dy = dyr[t];
        hq[a] = q; hm[a] = m & 255; hc[a] = cyy; hb[a] = bdy; hd[a] = dy; a += (m & 255) != 0;
        hq[b] = q + 1; hm[b] = (m >> 8) & 255; hc[b] = cyy; hb[b] = bdy; hd[b] = dy; b += (m >> 8) != 0;
    }
    nl = a;
    nr = b - 16;
};
// per column k of the tile: dx = x0 + k - mean_x and -0.5 a dx^2 (lane_power's first product)
alignas(64) float dxl[16], pa[16];
auto lane_constants = [&](const Splat& g) {
    const float dx0 = fx0 - g.mx;
    const float ha = -0.5f * g.a;
    for (int k = 0; k < 16; ++k) {
        const float dx = dx0 + (float)k;
        dxl[k] = dx;
        pa[k] = ha * dx * dx;
    }
};
// the forward and the coverage: the stopped pixels nh (8 bits) of half row q join row_done; a row that is full
// now counts off rows_left
auto mark_done = [](int* row_done, int full, int& rows_left, int q, int nh) {
    if (nh != 0) {
        const int r = q >> 1;
        const int old = row_done[r];
        const int now = old | (nh << (8 * (q & 1)));
        row_done[r] = now;
        if (now == full && old != full) --rows_left;
    }
};
// the power -0.5 (a dx^2 + c dy^2) - b dx dy of list entry e's 8 pixels: one expression for the forward, the
// coverage and the backward, so that they compute each alpha alike
auto entry_power = [&](int e) -> v8f {
    const int off = 8 * (hq[e] & 1);
    return fma8(-(v8f)hb[e], *(const v8f*)(dxl + off), *(const v8f*)(pa + off) + (v8f)hc[e]);
};
// the forward's and the coverage's step for entry e of a Gaussian of opacity vop: its alpha, the transmittance
// before (Tk) and after (Tn), the pixels it stops (stop) and those that take it (acc, 0/1); the half row's T is
// updated to took ? Tn : Tk without a select on what was loaded from the same place (LLVM makes that a masked store,
// which Zen 3 runs slowly and cannot forward to the next Gaussian's load): Tk * 1 is Tk
struct Step { v8f al, Tk, Tn, stop, acc; };
typedef float HalfRow[8];   // a tile state's half row (a pointer to float[8]: Warp defines a macro float(x))
auto front_step = [&](int e, HalfRow* T, v8f vop) -> Step {
    const int q = hq[e];
    Step s;
    s.al = vmin(kv(K_AMAX), vop * vexp(entry_power(e)));
    const v8f bit = __builtin_convertvector(((v8i)hm[e] >> LANE) & 1, v8f);
    const v8f ok = sel(s.al >= kv(K_AMIN), bit, (v8f)0.0f);
    s.Tk = *(v8f*)T[q];
    s.Tn = s.Tk * (1.0f - s.al);
    s.stop = sel(s.Tn < kv(K_TMIN), ok, (v8f)0.0f);
    s.acc = ok - s.stop;
    *(v8f*)T[q] = s.Tk * sel(s.acc > 0.0f, 1.0f - s.al, (v8f)1.0f);
    return s;
};
"""

FORWARD = r"""
const int start = wp::index(ranges, tile, 0);
const int end = wp::index(ranges, tile, 1);
// the tile's state as 32 half rows of 8 pixels: row r's pixels 0-7 at 2r, 8-15 at 2r + 1
alignas(64) float T[32][8], CR[32][8], CG[32][8], CB[32][8], DD[32][8], LL[32][8];
for (int q = 0; q < 32; ++q)
    for (int k = 0; k < 8; ++k) {
        T[q][k] = 1.0f; CR[q][k] = 0.0f; CG[q][k] = 0.0f; CB[q][k] = 0.0f; DD[q][k] = 0.0f; LL[q][k] = 0.0f;
    }
alignas(32) int row_done[32];   // 16 rows and a vector's overhang
for (int r = 0; r < 32; ++r) row_done[r] = 0;
const int full = (1 << nx) - 1;
int rows_left = ny;
for (int j = start; j < end; ++j) {
    const Splat g = load_splat(j);
    list_halves(g, row_done, all_rows, 0);
    if (nl + nr == 0) continue;
    lane_constants(g);
    const float* col = cp + 4L * j;
    const v8f vc0 = col[0], vc1 = col[1], vc2 = col[2], vc3 = col[3], vop = g.op, vpos = (float)(j - start + 1);
    for (int e = nl > 0 ? 0 : 16; e < 16 + nr; e = e + 1 == nl ? 16 : e + 1) {   // the left block, the right one
        const int q = hq[e];
        const Step st = front_step(e, T, vop);
        const v8f w = st.acc * st.al * st.Tk;
        *(v8f*)CR[q] = fma8(w, vc0, *(v8f*)CR[q]);
        *(v8f*)CG[q] = fma8(w, vc1, *(v8f*)CG[q]);
        *(v8f*)CB[q] = fma8(w, vc2, *(v8f*)CB[q]);
        *(v8f*)DD[q] = fma8(w, vc3, *(v8f*)DD[q]);
        // L = took ? pos : L without a select on the loaded value (see front_step): L only grows along the list
        *(v8f*)LL[q] = vmax(*(v8f*)LL[q], sel(st.acc > 0.0f, vpos, (v8f)0.0f));
        const int nh = bits8(st.stop > 0.0f);
        mark_done(row_done, full, rows_left, q, nh);
    }
    if (rows_left == 0) break;
}
for (int r = 0; r < ny; ++r) {
    const int y = y0 + r;
    for (int k = 0; k < nx; ++k) {
        const int x = x0 + k, q = 2 * r + (k >> 3), kk = k & 7;
        const float Tk = T[q][kk];
        wp::index(rgb, y, x, 0) = CR[q][kk] + Tk * background[0];
        wp::index(rgb, y, x, 1) = CG[q][kk] + Tk * background[1];
        wp::index(rgb, y, x, 2) = CB[q][kk] + Tk * background[2];
        wp::index(depth, y, x) = DD[q][kk];
        wp::index(alpha, y, x) = 1.0f - Tk;
        wp::index(T_final, y, x) = Tk;
        wp::index(n_contrib, y, x) = (int)LL[q][kk];
    }
}
return 1;
"""

ALPHA = r"""
const int start = wp::index(ranges, tile, 0);
const int end = wp::index(ranges, tile, 1);
alignas(64) float T[32][8], DD[32][8];
for (int q = 0; q < 32; ++q)
    for (int k = 0; k < 8; ++k) { T[q][k] = 1.0f; DD[q][k] = 0.0f; }
alignas(32) int row_done[32];   // 16 rows and a vector's overhang
for (int r = 0; r < 32; ++r) row_done[r] = 0;
const int full = (1 << nx) - 1;
int rows_left = ny;
const v8f vts = t_stop;
for (int j = start; j < end; ++j) {
    const Splat g = load_splat(j);
    list_halves(g, row_done, all_rows, 0);
    if (nl + nr == 0) continue;
    lane_constants(g);
    const v8f vz = @DEPTH@ ? cp[4L * j + 3] : 0.0f, vop = g.op;
    for (int e = nl > 0 ? 0 : 16; e < 16 + nr; e = e + 1 == nl ? 16 : e + 1) {   // the left block, the right one
        const int q = hq[e];
        const Step st = front_step(e, T, vop);
        if (@DEPTH@) *(v8f*)DD[q] = fma8(st.acc * st.al * st.Tk, vz, *(v8f*)DD[q]);
        const v8f covered = sel(st.Tn < vts, st.acc, (v8f)0.0f);
        const int nh = bits8(st.stop + covered > 0.0f);
        mark_done(row_done, full, rows_left, q, nh);
    }
    if (rows_left == 0) break;
}
for (int r = 0; r < ny; ++r)
    for (int k = 0; k < nx; ++k) {
        const int q = 2 * r + (k >> 3), kk = k & 7;
        wp::index(alpha, y0 + r, x0 + k) = 1.0f - T[q][kk];
        if (@DEPTH@) wp::index(depth, y0 + r, x0 + k) = DD[q][kk];
    }
return 1;
"""

BACKWARD = r"""
const int start = wp::index(ranges, tile, 0);
// per pixel, half rows as in the forward: T (rebuilt back to front from T_final), S (what lies behind), the upstream
// gradients, n_contrib; lanes outside the image stay 0 (n_contrib 0: never blended)
alignas(64) float T[32][8], S[32][8], GR[32][8], GG[32][8], GB[32][8], VD[32][8], NC[32][8];
for (int q = 0; q < 32; ++q)
    for (int k = 0; k < 8; ++k) {
        T[q][k] = 0.0f; S[q][k] = 0.0f; GR[q][k] = 0.0f; GG[q][k] = 0.0f; GB[q][k] = 0.0f; VD[q][k] = 0.0f;
        NC[q][k] = 0.0f;
    }
alignas(32) int row_max[32];   // the largest n_contrib of each row (16 and a vector's overhang)
for (int r = 0; r < 32; ++r) row_max[r] = 0;
int n_max = 0;
for (int r = 0; r < ny; ++r) {
    const int y = y0 + r;
    int rm = 0;
    for (int k = 0; k < nx; ++k) {
        const int x = x0 + k, q = 2 * r + (k >> 3), kk = k & 7;
        const float Tf = wp::index(T_final, y, x);
        T[q][kk] = Tf;
        const float gr = wp::index(v_rgb, y, x, 0), gg = wp::index(v_rgb, y, x, 1), gb = wp::index(v_rgb, y, x, 2);
        GR[q][kk] = gr; GG[q][kk] = gg; GB[q][kk] = gb;
        float vA = 0.0f;
        if (use_depth != 0) VD[q][kk] = wp::index(v_depth, y, x);
        if (use_alpha != 0) vA = wp::index(v_alpha, y, x);
        S[q][kk] = Tf * (background[0] * gr + background[1] * gg + background[2] * gb - vA);
        const int nc = wp::index(n_contrib, y, x);
        NC[q][kk] = (float)nc;
        rm = rm > nc ? rm : nc;
    }
    row_max[r] = rm;
    n_max = n_max > rm ? n_max : rm;
}
if (slots.strides[0] != 4 || pair_grads.strides[0] != 48) return 0;
const int* slot_p = (const int*)slots.data;
float* grads = (float*)pair_grads.data;
// one Gaussian's running sums over the tile, per lane (0-7 the left half, 8-15 the right): 0 v_pow, 1 dy v_pow,
// 2 dy^2 v_pow, 3 v_alpha_raw E, 4-6 w G, 7 w v_depth, 8-9 the AbsGS sums
alignas(64) float ACC[10][16];
for (int jj = 0; jj < n_max; ++jj) {
    const int i = n_max - 1 - jj;
    const float fi = (float)i;
    const int j = start + i;
    const Splat g = load_splat(j);
    list_halves(g, no_rows, row_max, i);
    if (nl + nr == 0) continue;
    lane_constants(g);
    const float a = g.a, b = g.b, c = g.c;
    const float* col = cp + 4L * j;
    const float c0 = col[0], c1 = col[1], c2 = col[2], c3 = col[3];
    const v8f vop = g.op;
    // the entries [e0, e1) of one block (off 0: the left halves, 8: the right ones) in two passes: the first
    // blends back to front, sums v_raw E and keeps each entry's v_pow and w ok (VP, WK); the second sums those per
    // lane, each sum in a register (the same lane sums in the same order as one loop over both blocks that adds to
    // ACC[.][off] as it goes), stored in ACC[.][off .. off + 7] at the end
    alignas(64) float VP[32][8], WK[32][8];
    auto blend_block = [&](const int off, const int e0, const int e1) __attribute__((always_inline)) {
        v8f s3 = 0.0f;
        for (int e = e0; e < e1; ++e) {
            const int q = hq[e];
            const v8f ev = vexp(entry_power(e));
            const v8f raw = vop * ev;
            const v8f al = vmin(kv(K_AMAX), raw);
            const v8f bit = __builtin_convertvector(((v8i)hm[e] >> LANE) & 1, v8f);
            const v8f ok = sel(*(const v8f*)NC[q] > fi, sel(al >= kv(K_AMIN), bit, (v8f)0.0f), (v8f)0.0f);
            const v8f inv = 1.0f / (1.0f - al);
            const v8f Tq = *(const v8f*)T[q];
            const v8f Sq = *(const v8f*)S[q];
            const v8f gR = *(const v8f*)GR[q], gG = *(const v8f*)GG[q], gB = *(const v8f*)GB[q];
            const v8f vD = *(const v8f*)VD[q];
            const v8f Tk = Tq * inv;
            const v8f w = al * Tk;
            const v8f gi = fma8((v8f)c3, vD, fma8((v8f)c2, gB, fma8((v8f)c1, gG, c0 * gR)));
            const v8f v_al = fma8(Tk, gi, -(Sq * inv));
            const v8i okb = ok > 0.0f;
            // T = ok ? Tk : T and S = ok ? S + w gi : S, without a select on what was loaded from the same place
            // (see the forward): T inv is Tk, T 1 is T; S + -0 is S (also where S is -0)
            *(v8f*)T[q] = Tq * sel(okb, inv, (v8f)1.0f);
            *(v8f*)S[q] = Sq + sel(okb, w * gi, (v8f)-0.0f);
            const v8f v_raw = sel(raw <= kv(K_AMAX), v_al, (v8f)0.0f) * ok;
            *(v8f*)VP[e] = v_raw * raw;
            s3 = fma8(v_raw, ev, s3);
            *(v8f*)WK[e] = w * ok;
        }
        const v8f dx = *(const v8f*)(dxl + off);
        v8f s0 = 0.0f, s1 = 0.0f, s2 = 0.0f, s4 = 0.0f, s5 = 0.0f, s6 = 0.0f, s7 = 0.0f, s8 = 0.0f,
            s9 = 0.0f;
        for (int e = e0; e < e1; ++e) {
            const int q = hq[e];
            const float dy = hd[e], bdy = hb[e];
            const v8f v_pow = *(const v8f*)VP[e], wk = *(const v8f*)WK[e];
            s0 = s0 + v_pow;
            s1 = fma8((v8f)dy, v_pow, s1);
            s2 = fma8((v8f)(dy * dy), v_pow, s2);
            s4 = fma8(wk, *(const v8f*)GR[q], s4);
            s5 = fma8(wk, *(const v8f*)GG[q], s5);
            s6 = fma8(wk, *(const v8f*)GB[q], s6);
            s7 = fma8(wk, *(const v8f*)VD[q], s7);
            if (@ABSGRAD@) {
                const v8f mp = __builtin_elementwise_abs(v_pow);
                s8 = fma8(__builtin_elementwise_abs(fma8((v8f)a, dx, (v8f)bdy)), mp, s8);
                s9 = fma8(__builtin_elementwise_abs(fma8((v8f)b, dx, (v8f)(c * dy))), mp, s9);
            }
        }
        *(v8f*)(ACC[0] + off) = s0; *(v8f*)(ACC[1] + off) = s1; *(v8f*)(ACC[2] + off) = s2;
        *(v8f*)(ACC[3] + off) = s3; *(v8f*)(ACC[4] + off) = s4; *(v8f*)(ACC[5] + off) = s5;
        *(v8f*)(ACC[6] + off) = s6; *(v8f*)(ACC[7] + off) = s7; *(v8f*)(ACC[8] + off) = s8;
        *(v8f*)(ACC[9] + off) = s9;
    };
    blend_block(0, 0, nl);
    blend_block(8, 16, 16 + nr);
    // sum_px dx v_pow, sum dx^2 v_pow, sum dx dy v_pow (dx is the lane's constant), each lane sum as raster_tile's
    auto lane_sum = [](const float* v) -> float {
        float h[8], q4[4];
        for (int k = 0; k < 8; ++k) h[k] = v[k] + v[k + 8];
        for (int k = 0; k < 4; ++k) q4[k] = h[k] + h[k + 4];
        return (q4[0] + q4[2]) + (q4[1] + q4[3]);
    };
    alignas(64) float t1[16], t2[16], t3[16];
    for (int k = 0; k < 16; ++k) {
        t1[k] = dxl[k] * ACC[0][k];
        t2[k] = dxl[k] * dxl[k] * ACC[0][k];
        t3[k] = dxl[k] * ACC[1][k];
    }
    const float P1 = lane_sum(t1), P2 = lane_sum(t2), Q1 = lane_sum(ACC[1]), Q2 = lane_sum(t3), Q3 = lane_sum(ACC[2]);
    float* pg = grads + 12L * slot_p[j];
    pg[0] = pg[0] + (a * P1 + b * Q1);
    pg[1] = pg[1] + (b * P1 + c * Q1);
    pg[2] = pg[2] + -0.5f * P2;
    pg[3] = pg[3] + -Q2;
    pg[4] = pg[4] + -0.5f * Q3;
    for (int t = 3; t < 10; ++t) pg[t + 2] = pg[t + 2] + lane_sum(ACC[t]);
}
return 1;
"""


def fill(body: str, consts: dict[str, float | int]) -> str:
    """The snippet: CPU only (clang), no contraction into FMAs but the snippet's own ``fma8`` (so the forward and
    the backward compute each alpha the same way), the prelude and ``body`` with the constants filled in (a float as
    a float32 literal, an int as itself)."""
    text = ("#if defined(__clang__) && !defined(__CUDA_ARCH__)\n{\n#pragma clang fp contract(off)\n"
            + _PRELUDE + body + "\n}\n#else\nreturn 0;\n#endif\n")
    for name, value in consts.items():
        text = text.replace(f"@{name}@", str(value) if isinstance(value, int) else _f32(value))
    if "@" in text:
        raise ValueError("raster_tile_cpp: a value of the snippet is not filled in")
    return text
