"""The CPU's tile blends as plain C++ (the text of Warp native snippets used by :mod:`~mgso_kernels.splat.raster_tile`).

:mod:`~mgso_kernels.splat.raster_tile`'s kernels, a thread per 16x16 tile, do per Gaussian of the tile's list and per
tile row it reaches: the row's span (a ``sqrt``), a branch on the span, then 16 (or 8) lanes of blending on a copy of
the row's state that is written back. Measured on a Zen 3 core (docs/rasteriser.md) that costs about 200 cycles a
row visit, four to five times the lanes' arithmetic: the lanes wait on the span and on the branches around them, one
row after the other. These snippets compute the same thing in another order of work:

- **Per Gaussian, the lane constants once**: ``dx = x0 + k - mean_x`` and ``-0.5 a dx^2`` for the 16 columns (the
  same products, in the same order, as :func:`~mgso_kernels.splat.raster_tile.lane_power` makes per row).
- **Spans first, then the blend**: the rows the Gaussian reaches are turned into a compact list of the lane rows
  that have a live pixel inside its ellipse, without a branch per row; then the list is blended, each entry in place
  on the tile's state, with no branch inside an entry. Entries are independent (a pixel belongs to one), so the core
  overlaps them. A lane row is a whole tile row (16 pixels, one AVX-512 vector) where the compiler targets AVX-512,
  half of one (8 pixels, one AVX2 vector) elsewhere: the same arithmetic per pixel and the same order of every lane's
  sums, so the two widths give the same outputs bit for bit (tested); a Gaussian that covers both halves of a row
  costs one entry instead of two (640x480 on a real 7-Scenes map, one Zen 5 thread: forward blend 41-42 -> 30-31 ms,
  backward blend 63-74 -> 51-56 ms; docs/rasteriser.md). ``MGSO_TILE_LANES=8`` in the environment keeps 8 lanes
  (read at import; for the test and profiles that compare the two).
- With AVX-512 the rows with a bit left are packed into each list by one compress (16 lanes), the lanes' decisions
  (which pixels take a Gaussian, which stop) are mask registers (16 lanes with AVX-512F, 8 with AVX-512VL; 0/1 float
  lanes elsewhere, or with ``MGSO_TILE_MASKS=0``), and each loop prepares the next pair (its Gaussian, its rows'
  spans) before it blends the entries of the pair before it; the images are read and written through plain
  pointers. The same outputs bit for bit (docs/rasteriser.md, "The blends' bookkeeping").
- No select on a value just loaded from the same place (``T = Tk * (took ? 1 - alpha : 1)`` instead of
  ``took ? Tn : Tk``): LLVM makes such a select a masked store, slow on Zen 3 and not forwarded to the next load.
- The backward lists lane rows the same way (with 8 lanes the left halves and the right ones in two blocks) and
  does a block in two passes: the first blends back to front and keeps each entry's ``v_pow`` and ``w``, the second sums what the
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

import os

import numpy as np

__all__ = ["FORWARD", "ALPHA", "BACKWARD", "fill", "lanes_probe", "masks_probe"]


def _f32(x: float) -> str:
    """A C float literal of float32(x) (enough digits that the compiler's rounding gives that float)."""
    return repr(float(np.float32(x))) + "f"


# shared by the snippets: the blend's constants and exp_lane's polynomial (raster_tile.exp_lane, the same operations).
# The lanes are @W@ pixels of a tile row: 8 (a half row, one AVX2 register) or 16 (a whole row, one AVX-512
# register); the rows' spans are computed W rows a vector
_PRELUDE = r"""
const float AMAX = @ALPHA_MAX@, AMIN = @ALPHA_MIN@, TMIN = @T_MIN@;
const float LOG2E_ = @LOG2E@, LN2HI = @LN2_HI@, LN2LO = @LN2_LO@;
typedef float v8f __attribute__((ext_vector_type(8)));
typedef float vf __attribute__((ext_vector_type(@W@)));    // the lanes: @W@ pixels of a tile row, or @W@ rows
typedef int vi __attribute__((ext_vector_type(@W@)));
const vi LANE = {@LANES@};
// the state's lane rows (a tile row is QPR of them: row r's pixels W k .. W k + W - 1 at QPR r + k)
const int NQ = 256 / @W@, QPR = 16 / @W@;
// W ints from anywhere (a vi pointer must be aligned to its size)
auto ldi = [](const int* p) -> vi { vi v; __builtin_memcpy(&v, p, sizeof v); return v; };
// a ? b : c per lane, bit for bit (a: a comparison's all-ones / zero lanes)
auto sel = [](vi a, vf b, vf c) -> vf { return (vf)((a & (vi)b) | (~a & (vi)c)); };
// wp::min(k, v) as Warp's CPU code has it (C fmin: a NaN v gives k); on x86 one vminps(v, k), which returns its
// second operand where either is NaN or they are equal (the same value), v where v < k: the same result; LLVM made
// fmin's NaN rule a compare, a second compare and two blends
auto vmin = [&](vf k, vf v) -> vf {
#if @W@ == 16 && defined(__AVX512F__)
    return __builtin_ia32_minps512(v, k, 4);
#elif @W@ == 8 && defined(__AVX__)
    return __builtin_ia32_minps256(v, k);
#else
    return sel(k <= v, k, sel(v == v, v, k));
#endif
};
// max(a, b) of lanes that are never NaN (vmaxps on x86; __builtin_elementwise_max adds fmax's NaN rule)
auto vmax = [](vf a, vf b) -> vf {
#if @W@ == 16 && defined(__AVX512F__)
    return __builtin_ia32_maxps512(a, b, 4);
#elif @W@ == 8 && defined(__AVX__)
    return __builtin_ia32_maxps256(a, b);
#else
    return __builtin_elementwise_max(a, b);
#endif
};
// the lanes of a comparison (all-ones / zero) as bits, lane k at bit k (vmovmskps / vpmovd2m on x86: one
// instruction where OR-reducing the lanes' bits took eight)
auto lane_bits = [&](vi c) -> int {
#if @W@ == 16 && defined(__AVX512DQ__)
    return (int)(unsigned short)__builtin_ia32_cvtd2mask512(c);
#elif @W@ == 8 && defined(__AVX__)
    return __builtin_ia32_movmskps256((vf)c);
#else
    return __builtin_reduce_or(c & ((vi)1 << LANE));
#endif
};
// a b + c rounded once (an FMA instruction; the snippets say where they want one, contraction stays off)
auto fmav = [](vf a, vf b, vf c) -> vf { return __builtin_elementwise_fma(a, b, c); };
// AVX-512's mask registers for the lanes' decisions (16 lanes with AVX-512F, 8 with AVX-512VL): kcmp_ge / kcmp_lt /
// kcmp_le(a, b, m) are m & (a >= b), m & (a < b), m & (a <= b), ordered (false where a lane is NaN, as C's
// comparisons); ksel(m, a, b) is m ? a : b per lane
#if @MASKS@ && ((@W@ == 16 && defined(__AVX512F__)) || (@W@ == 8 && defined(__AVX512VL__)))
#define TILE_MASKS 1
#if @W@ == 16
typedef unsigned short kmask;
typedef float vn_ __attribute__((__vector_size__(64)));
auto kcmp_ge = [](vf a, vf b, kmask m) -> kmask { return __builtin_ia32_cmpps512_mask((vn_)a, (vn_)b, 0x1d, m, 4); };
auto kcmp_lt = [](vf a, vf b, kmask m) -> kmask { return __builtin_ia32_cmpps512_mask((vn_)a, (vn_)b, 0x11, m, 4); };
auto kcmp_le = [](vf a, vf b, kmask m) -> kmask { return __builtin_ia32_cmpps512_mask((vn_)a, (vn_)b, 0x12, m, 4); };
auto ksel = [](kmask m, vf a, vf b) -> vf { return (vf)__builtin_ia32_selectps_512(m, (vn_)a, (vn_)b); };
#else
typedef unsigned char kmask;
typedef float vn_ __attribute__((__vector_size__(32)));
auto kcmp_ge = [](vf a, vf b, kmask m) -> kmask { return __builtin_ia32_cmpps256_mask((vn_)a, (vn_)b, 0x1d, m); };
auto kcmp_lt = [](vf a, vf b, kmask m) -> kmask { return __builtin_ia32_cmpps256_mask((vn_)a, (vn_)b, 0x11, m); };
auto kcmp_le = [](vf a, vf b, kmask m) -> kmask { return __builtin_ia32_cmpps256_mask((vn_)a, (vn_)b, 0x12, m); };
auto ksel = [](kmask m, vf a, vf b) -> vf { return (vf)__builtin_ia32_selectps_256(m, (vn_)a, (vn_)b); };
#endif
#endif
// vexp's constants and the blend's thresholds as vectors in a stack array that the compiler cannot fold back into
// constants (the empty asm statement tells it the array may have changed): the loops read them as memory operands,
// where LLVM rematerialised each from the constant pool on every list entry (a movabs and a broadcast, under Warp's
// large code model: 26 of an entry's 100 instructions). The same values, so the same results bit for bit
enum { KX_MIN, K_LOG2E, K_HALF, K_NLN2HI, K_NLN2LO, K_P3, K_P5, K_P4, K_P7, K_P6, K_AMAX, K_AMIN, K_TMIN, K_N };
alignas(64) float KV[K_N][@W@];
{
    const float k1[K_N] = {-87.0f, LOG2E_, 0.5f, -LN2HI, -LN2LO, 0.16666667f, 0.008333334f, 0.041666668f,
                           0.0001984127f, 0.0013888889f, AMAX, AMIN, TMIN};
    for (int i = 0; i < K_N; ++i)
        for (int k = 0; k < @W@; ++k) KV[i][k] = k1[i];
}
asm volatile("" : : "r"(&KV[0][0]) : "memory");
auto kv = [&](int i) -> vf { return *(const vf*)KV[i]; };
// exp(x) per lane: exp_lane's range reduction and polynomial with FMAs, the polynomial in Estrin's form (three
// dependent steps after f instead of Horner's seven); within float rounding of exp_lane (the images and gradients
// against the Warp kernels', tests/kernels/test_splat_tile.py)
auto vexp = [&](vf x) -> vf {
    x = vmax(x, kv(KX_MIN));     // vmaxps(x, k): k where x is NaN
    const vf nf = __builtin_elementwise_floor(fmav(x, kv(K_LOG2E), kv(K_HALF)));
    const vf f = fmav(nf, kv(K_NLN2LO), fmav(nf, kv(K_NLN2HI), x));
    const vf f2 = f * f, f4 = f2 * f2;
    const vf p01 = 1.0f + f, p23 = fmav(f, kv(K_P3), kv(K_HALF));
    const vf p45 = fmav(f, kv(K_P5), kv(K_P4));
    const vf p67 = fmav(f, kv(K_P7), kv(K_P6));
    const vf p = fmav(f4, fmav(f2, p67, p45), fmav(f2, p23, p01));
    return p * (vf)((__builtin_convertvector(nf, vi) + 127) << 23);
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
// The lists: prepare(j, rmax, i) takes pair j (its Gaussian, and with 16 lanes its rows' spans and constants, none
// of which depends on the tile's state); list_prepared(p, done) then lists, per row r in [lo, hi], the span of the
// row inside the cut-off ellipse as a bit mask (row_span_mask's operations), less the bits of done[r], and none
// where rmax[r] <= i: the lane rows with a bit left, in hq (their index q in the state) and hm (their W bits) with
// the row's -0.5 c dy^2, b dy and dy in hc, hb, hd. With 16 lanes the rows at 0, 1, ...; with 8 the left halves
// (q = 2 r) at 0, 1, ..., the right ones (q = 2 r + 1) at 16, 17, ..., each block in row order. Sets nl and nr to
// the blocks' sizes (nr = 0 with 16 lanes). done and rmax hold 32 rows (16 and a vector's overhang).
// The loops prepare the next pair before they blend the entries of the pair before it, so the core works on both at
// once: a pair's chain from its loads through the divisions and square roots to its list was otherwise waited for,
// pair after pair (the per-pair work was a quarter of a 640x480 forward blend's samples; preparing ahead took the
// blend 5-10 % down, docs/rasteriser.md)
alignas(32) int no_rows[32], all_rows[32];     // none done; no row's list ends
for (int r = 0; r < 32; ++r) { no_rows[r] = 0; all_rows[r] = 2147483647; }
alignas(64) int hq[32], hm[32];
alignas(64) float hc[32], hb[32], hd[32];
int nl = 0, nr = 0;
// W rows of g from row r0 (r0 .. r0 + W - 1 of the tile): their index, dy, and the span inside the cut-off ellipse
// as W bits (row_span_mask's operations) where the row is live (inside the image, within [lo, hi], and rmax[r] > i)
struct RowSpans { vi rr, sl; vf dy; };
auto row_spans = [&](const Splat& g, int r0, const int* rmax, int i) -> RowSpans {
    const float ar2 = g.a * g.r2;
    RowSpans o;
    o.rr = (vi)r0 + LANE;
    o.dy = ((vf)fy0 + __builtin_convertvector(o.rr, vf)) - g.my;
    const vf disc = ar2 - g.det * o.dy * o.dy;
    const vf half = __builtin_elementwise_sqrt(sel(disc < 0.0f, (vf)0.0f, disc)) * g.inv_a;
    const vf xc = g.mx - g.b * o.dy * g.inv_a;
    const vi lm = __builtin_elementwise_max(
        __builtin_convertvector(__builtin_elementwise_ceil(xc - half), vi) - x0, (vi)0);
    const vi h = __builtin_elementwise_min(
        __builtin_convertvector(__builtin_elementwise_floor(xc + half), vi) - x0, (vi)(nx - 1));
    const vi live = ~(disc < 0.0f) & (lm <= h) & (o.rr <= g.hi) & (ldi(rmax + r0) > i);
    // shift counts kept in [0, 16] where the row is not live (a vector shift by 32 or more is undefined)
    const vi l = __builtin_elementwise_min(lm, (vi)15);
    const vi len = __builtin_elementwise_min(__builtin_elementwise_max(h - l + 1, (vi)0), (vi)16);
    o.sl = ((((vi)1 << len) - 1) << l) & live;
    return o;
};
#if @W@ == 16 && defined(__AVX512F__)
struct Pre { Splat g; vi rr, sl; vf dy, cyy, bdy; };   // sl: the rows' spans where the rows are live
auto prepare = [&](int j, const int* rmax, int i) -> Pre {
    Pre p;
    p.g = load_splat(j);
    const RowSpans o = row_spans(p.g, p.g.lo, rmax, i);
    p.rr = o.rr;
    p.sl = o.sl;
    p.dy = o.dy;
    p.cyy = -0.5f * p.g.c * o.dy * o.dy;
    p.bdy = p.g.b * o.dy;
    return p;
};
// 16 lanes: a tile's rows (at most 16) are one vector, and the rows with a bit left are packed to the front of
// each list by one compress a list (vpcompressd into a register, then a plain store: the compress to memory is
// microcoded on Zen 4), in row order, where that loop's stores and conditional
// increments took a tenth of a 640x480 forward blend (one Zen 4 thread, docs/rasteriser.md)
auto list_prepared = [&](const Pre& p, const int* done) {
    typedef int v16si_ __attribute__((__vector_size__(64)));
    typedef float v16sf_ __attribute__((__vector_size__(64)));
    const vi m = p.sl & ~ldi(done + p.g.lo);
    const unsigned short k = (unsigned short)lane_bits(m != 0);
    const vi zi = 0;
    const vf zf = 0.0f;
    *(vi*)hq = (vi)__builtin_ia32_compresssi512_mask((v16si_)p.rr, (v16si_)zi, k);
    *(vi*)hm = (vi)__builtin_ia32_compresssi512_mask((v16si_)m, (v16si_)zi, k);
    *(vf*)hc = (vf)__builtin_ia32_compresssf512_mask((v16sf_)p.cyy, (v16sf_)zf, k);
    *(vf*)hb = (vf)__builtin_ia32_compresssf512_mask((v16sf_)p.bdy, (v16sf_)zf, k);
    *(vf*)hd = (vf)__builtin_ia32_compresssf512_mask((v16sf_)p.dy, (v16sf_)zf, k);
    nl = __builtin_popcount(k);
    nr = 0;
};
#else
// 8 lanes (the only width without AVX-512): the rows' spans 8 rows a vector, then each row's two halves listed in
// their blocks by a scalar loop
struct Pre { Splat g; const int* rmax; int i; };
auto prepare = [&](int j, const int* rmax, int i) -> Pre { return Pre{load_splat(j), rmax, i}; };
alignas(64) int mrow[16];
alignas(64) float dyr[16], cyyr[16], bdyr[16];
auto list_prepared = [&](const Pre& p, const int* done) {
    const Splat& g = p.g;
    const int lo = g.lo, nrows = g.hi - lo + 1;
    const float hc_ = -0.5f * g.c;
    for (int r8 = 0; r8 < nrows; r8 += @W@) {
        const RowSpans o = row_spans(g, lo + r8, p.rmax, p.i);
        *(vi*)(mrow + r8) = o.sl & ~ldi(done + lo + r8);
        *(vf*)(dyr + r8) = o.dy;
        *(vf*)(cyyr + r8) = hc_ * o.dy * o.dy;
        *(vf*)(bdyr + r8) = g.b * o.dy;
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
#endif
// the forward's and the coverage's walk down a tile's list: first_pair(start, end) prepares the first pair; each
// step hands over the prepared pair j and prepares j + 1 (next_pair(j, end, nxt))
auto first_pair = [&](int start, int end) -> Pre {
    Pre p;
    if (start < end) p = prepare(start, all_rows, 0);
    return p;
};
auto next_pair = [&](int j, int end, Pre& nxt) -> Pre {
    const Pre cur = nxt;
    if (j + 1 < end) nxt = prepare(j + 1, all_rows, 0);
    return cur;
};
// the list's entries in order: the left block [0, nl), then the right one [16, 16 + nr)
auto first_entry = [&]() -> int { return nl > 0 ? 0 : 16; };
auto next_entry = [&](int e) -> int { return e + 1 == nl ? 16 : e + 1; };
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
// the first column of lane row q
auto col0 = [](int q) -> int { return @W@ * (q % QPR); };
// the forward and the coverage: the stopped pixels nh (W bits) of lane row q join row_done; a row that is full
// now counts off rows_left
auto mark_done = [&](int* row_done, int full, int& rows_left, int q, int nh) {
    if (nh != 0) {
        const int r = q / QPR;
        const int old = row_done[r];
        const int now = old | (nh << col0(q));
        row_done[r] = now;
        if (now == full && old != full) --rows_left;
    }
};
// the power -0.5 (a dx^2 + c dy^2) - b dx dy of list entry e's W pixels: one expression for the forward, the
// coverage and the backward, so that they compute each alpha alike
auto entry_power = [&](int e) -> vf {
    const int off = col0(hq[e]);
    return fmav(-(vf)hb[e], *(const vf*)(dxl + off), *(const vf*)(pa + off) + (vf)hc[e]);
};
// the forward's and the coverage's step for entry e of a Gaussian of opacity vop: its alpha, the transmittance
// before (Tk) and after (Tn), the pixels it stops (stop) and those that take it (acc); the lane row's T is
// updated to took ? Tn : Tk without a select on what was loaded from the same place (LLVM makes that a masked store,
// which Zen 3 runs slowly and cannot forward to the next Gaussian's load): Tk * 1 is Tk. What the blends read of a
// step: took_w (the blending weight acc al Tk), took_or0(s, v) (acc ? v : 0), stop_bits(s) and cover_bits(s, t)
// (the pixels that stop, and those that stop or take the transmittance below t, as W bits)
typedef float LaneRow[@W@];   // a tile state's lane row (a pointer to float[W]: Warp defines a macro float(x))
#ifdef TILE_MASKS
// with AVX-512 the pixels that take and stop are mask registers, where the 0/1 float lanes made the chain from one
// Gaussian's T to the next's a compare, a masked move, a subtraction and a second compare longer (a lane row's T is
// loaded, updated and stored by each Gaussian of the list that reaches it, one after the other); the same values
struct Step { vf al, Tk, Tn; kmask stop, acc; };
auto front_step = [&](int e, LaneRow* T, vf vop) -> Step {
    const int q = hq[e];
    Step s;
    s.al = vmin(kv(K_AMAX), vop * vexp(entry_power(e)));
    const kmask ok = kcmp_ge(s.al, kv(K_AMIN), (kmask)hm[e]);
    s.Tk = *(vf*)T[q];
    const vf om = 1.0f - s.al;
    s.Tn = s.Tk * om;
    s.stop = kcmp_lt(s.Tn, kv(K_TMIN), ok);
    s.acc = ok & ~s.stop;
    *(vf*)T[q] = s.Tk * ksel(s.acc, om, (vf)1.0f);
    return s;
};
// acc al Tk is al Tk where acc is 1 and +0 where it is 0 (al and Tk are finite and not negative)
auto took_w = [&](const Step& s) -> vf { return ksel(s.acc, s.al * s.Tk, (vf)0.0f); };
auto took_or0 = [&](const Step& s, vf v) -> vf { return ksel(s.acc, v, (vf)0.0f); };
auto stop_bits = [](const Step& s) -> int { return s.stop; };
auto cover_bits = [&](const Step& s, vf t) -> int { return s.stop | kcmp_lt(s.Tn, t, s.acc); };
#else
struct Step { vf al, Tk, Tn, stop, acc; };   // stop, acc: 0 or 1 per lane
auto front_step = [&](int e, LaneRow* T, vf vop) -> Step {
    const int q = hq[e];
    Step s;
    s.al = vmin(kv(K_AMAX), vop * vexp(entry_power(e)));
    const vf bit = __builtin_convertvector(((vi)hm[e] >> LANE) & 1, vf);
    const vf ok = sel(s.al >= kv(K_AMIN), bit, (vf)0.0f);
    s.Tk = *(vf*)T[q];
    s.Tn = s.Tk * (1.0f - s.al);
    s.stop = sel(s.Tn < kv(K_TMIN), ok, (vf)0.0f);
    s.acc = ok - s.stop;
    *(vf*)T[q] = s.Tk * sel(s.acc > 0.0f, 1.0f - s.al, (vf)1.0f);
    return s;
};
auto took_w = [&](const Step& s) -> vf { return s.acc * s.al * s.Tk; };
auto took_or0 = [&](const Step& s, vf v) -> vf { return sel(s.acc > 0.0f, v, (vf)0.0f); };
auto stop_bits = [&](const Step& s) -> int { return lane_bits(s.stop > 0.0f); };
auto cover_bits = [&](const Step& s, vf t) -> int {
    return lane_bits(s.stop + sel(s.Tn < t, s.acc, (vf)0.0f) > 0.0f);
};
#endif
"""

FORWARD = r"""
// the outputs are written through plain pointers (below), so the snippet declines images that are not contiguous
// (the rasteriser's are)
const long width = rgb.shape[1];
auto flat2 = [&](const auto& a) -> bool {
    return a.shape[1] == width && a.strides[1] == 4 && a.strides[0] == 4 * width;
};
if (!(rgb.strides[2] == 4 && rgb.strides[1] == 12 && rgb.strides[0] == 12 * width
      && (only_rgb != 0 || (flat2(depth) && flat2(alpha) && flat2(T_final) && flat2(n_contrib)))))
    return 0;
const int start = wp::index(ranges, tile, 0);
const int end = wp::index(ranges, tile, 1);
// the tile's state as NQ lane rows of W pixels (see the prelude)
alignas(64) float T[NQ][@W@], CR[NQ][@W@], CG[NQ][@W@], CB[NQ][@W@], DD[NQ][@W@], LL[NQ][@W@];
for (int q = 0; q < NQ; ++q)
    for (int k = 0; k < @W@; ++k) {
        T[q][k] = 1.0f; CR[q][k] = 0.0f; CG[q][k] = 0.0f; CB[q][k] = 0.0f; DD[q][k] = 0.0f; LL[q][k] = 0.0f;
    }
alignas(32) int row_done[32];   // 16 rows and a vector's overhang
for (int r = 0; r < 32; ++r) row_done[r] = 0;
const int full = (1 << nx) - 1;
int rows_left = ny;
// the blend, once with the depth and the last list position (FULL, what the backward needs) and once with the colour
// alone (only_rgb: renders without a gradient), the choice made once a tile: tag's type says which
auto blend = [&](auto tag) {
    constexpr bool FULL = sizeof(*tag) == 2;
    Pre nxt = first_pair(start, end);
    for (int j = start; j < end; ++j) {
        const Pre cur = next_pair(j, end, nxt);
        const Splat& g = cur.g;
        list_prepared(cur, row_done);
        if (nl + nr == 0) continue;
        lane_constants(g);
        const float* col = cp + 4L * j;
        const vf vc0 = col[0], vc1 = col[1], vc2 = col[2], vc3 = col[3], vop = g.op, vpos = (float)(j - start + 1);
        for (int e = first_entry(); e < 16 + nr; e = next_entry(e)) {
            const int q = hq[e];
            const Step st = front_step(e, T, vop);
            const vf w = took_w(st);
            *(vf*)CR[q] = fmav(w, vc0, *(vf*)CR[q]);
            *(vf*)CG[q] = fmav(w, vc1, *(vf*)CG[q]);
            *(vf*)CB[q] = fmav(w, vc2, *(vf*)CB[q]);
            if constexpr (FULL) {
                *(vf*)DD[q] = fmav(w, vc3, *(vf*)DD[q]);
                // L = took ? pos : L without a select on the loaded value (see front_step): L only grows along the list
                *(vf*)LL[q] = vmax(*(vf*)LL[q], took_or0(st, vpos));
            }
            const int nh = stop_bits(st);
            mark_done(row_done, full, rows_left, q, nh);
        }
        if (rows_left == 0) break;
    }
};
if (only_rgb != 0)
    blend((const char(*)[1])nullptr);
else
    blend((const char(*)[2])nullptr);
// the outputs through plain pointers, which the compiler turns into vector stores, where wp::index's strided
// stores, a pixel at a time, took a tenth of a 640x480 forward blend (one Zen 4 thread, docs/rasteriser.md); the
// same values
const float *Tf = &T[0][0], *Rf = &CR[0][0], *Gf = &CG[0][0], *Bf = &CB[0][0], *Df = &DD[0][0], *Lf = &LL[0][0];
const float bg0 = background[0], bg1 = background[1], bg2 = background[2];
for (int r = 0; r < ny; ++r) {
    // the lane rows of a tile row are contiguous: pixel (r, k) at 16 r + k of each state
    const long o = (long)(y0 + r) * width + x0;
    const int s0 = 16 * r;
    float* pr = (float*)rgb.data + 3 * o;
    for (int k = 0; k < nx; ++k) {
        const float Tk = Tf[s0 + k];
        pr[3 * k] = Rf[s0 + k] + Tk * bg0;
        pr[3 * k + 1] = Gf[s0 + k] + Tk * bg1;
        pr[3 * k + 2] = Bf[s0 + k] + Tk * bg2;
    }
    if (only_rgb != 0) continue;
    float* pd = (float*)depth.data + o;
    float* pa = (float*)alpha.data + o;
    float* pt = (float*)T_final.data + o;
    int* pn = (int*)n_contrib.data + o;
    for (int k = 0; k < nx; ++k) {
        const float Tk = Tf[s0 + k];
        pd[k] = Df[s0 + k];
        pa[k] = 1.0f - Tk;
        pt[k] = Tk;
        pn[k] = (int)Lf[s0 + k];
    }
}
return 1;
"""

ALPHA = r"""
// the outputs are written through plain pointers (below): images that are not contiguous make the snippet decline
const long width = alpha.shape[1];
if (!(alpha.strides[1] == 4 && alpha.strides[0] == 4 * width
      && (!@DEPTH@ || (depth.shape[1] == width && depth.strides[1] == 4 && depth.strides[0] == 4 * width))))
    return 0;
const int start = wp::index(ranges, tile, 0);
const int end = wp::index(ranges, tile, 1);
alignas(64) float T[NQ][@W@], DD[NQ][@W@];
for (int q = 0; q < NQ; ++q)
    for (int k = 0; k < @W@; ++k) { T[q][k] = 1.0f; DD[q][k] = 0.0f; }
alignas(32) int row_done[32];   // 16 rows and a vector's overhang
for (int r = 0; r < 32; ++r) row_done[r] = 0;
const int full = (1 << nx) - 1;
int rows_left = ny;
const vf vts = t_stop;
Pre nxt = first_pair(start, end);
for (int j = start; j < end; ++j) {
    const Pre cur = next_pair(j, end, nxt);
    const Splat& g = cur.g;
    list_prepared(cur, row_done);
    if (nl + nr == 0) continue;
    lane_constants(g);
    const vf vz = @DEPTH@ ? cp[4L * j + 3] : 0.0f, vop = g.op;
    for (int e = first_entry(); e < 16 + nr; e = next_entry(e)) {
        const int q = hq[e];
        const Step st = front_step(e, T, vop);
        if (@DEPTH@) *(vf*)DD[q] = fmav(took_w(st), vz, *(vf*)DD[q]);
        const int nh = cover_bits(st, vts);
        mark_done(row_done, full, rows_left, q, nh);
    }
    if (rows_left == 0) break;
}
// the outputs through plain pointers (pixel (r, k) at 16 r + k of each state), as the forward's
const float *Tf = &T[0][0], *Df = &DD[0][0];
for (int r = 0; r < ny; ++r) {
    const long o = (long)(y0 + r) * width + x0;
    float* pa = (float*)alpha.data + o;
    for (int k = 0; k < nx; ++k) pa[k] = 1.0f - Tf[16 * r + k];
    if (@DEPTH@) {
        float* pd = (float*)depth.data + o;
        for (int k = 0; k < nx; ++k) pd[k] = Df[16 * r + k];
    }
}
return 1;
"""

BACKWARD = r"""
const int start = wp::index(ranges, tile, 0);
// per pixel, lane rows as in the forward: T (rebuilt back to front from T_final), S (what lies behind), the upstream
// gradients, n_contrib; lanes outside the image stay 0 (n_contrib 0: never blended)
alignas(64) float T[NQ][@W@], S[NQ][@W@], GR[NQ][@W@], GG[NQ][@W@], GB[NQ][@W@], VD[NQ][@W@], NC[NQ][@W@];
for (int q = 0; q < NQ; ++q)
    for (int k = 0; k < @W@; ++k) {
        T[q][k] = 0.0f; S[q][k] = 0.0f; GR[q][k] = 0.0f; GG[q][k] = 0.0f; GB[q][k] = 0.0f; VD[q][k] = 0.0f;
        NC[q][k] = 0.0f;
    }
alignas(32) int row_max[32];   // the largest n_contrib of each row (16 and a vector's overhang)
for (int r = 0; r < 32; ++r) row_max[r] = 0;
int n_max = 0;
// the inputs through plain pointers (the lane rows of a tile row are contiguous: pixel (r, k) at 16 r + k of each
// state) instead of wp::index's strided loads, a pixel at a time (with the mask registers and the prepared pairs, the
// backward blend 92-93 -> 66-70 ms at 640x480 on one thread; docs/rasteriser.md); images that are not contiguous
// make the snippet decline
const long width = v_rgb.shape[1];
auto flat2 = [&](const auto& a) -> bool {
    return a.shape[1] == width && a.strides[1] == 4 && a.strides[0] == 4 * width;
};
if (!(v_rgb.strides[2] == 4 && v_rgb.strides[1] == 12 && v_rgb.strides[0] == 12 * width && flat2(T_final)
      && flat2(n_contrib) && (use_depth == 0 || flat2(v_depth)) && (use_alpha == 0 || flat2(v_alpha))))
    return 0;
{
    float *Tp = &T[0][0], *Sp = &S[0][0], *Rp = &GR[0][0], *Gp = &GG[0][0], *Bp = &GB[0][0], *Dp = &VD[0][0];
    float* Np = &NC[0][0];
    const float bg0 = background[0], bg1 = background[1], bg2 = background[2];
    for (int r = 0; r < ny; ++r) {
        const long o = (long)(y0 + r) * width + x0;
        const int s0 = 16 * r;
        const float* pt = (const float*)T_final.data + o;
        const float* pg = (const float*)v_rgb.data + 3 * o;
        const float* pd = use_depth != 0 ? (const float*)v_depth.data + o : nullptr;
        const float* pa = use_alpha != 0 ? (const float*)v_alpha.data + o : nullptr;
        const int* pn = (const int*)n_contrib.data + o;
        int rm = 0;
        for (int k = 0; k < nx; ++k) {
            const float Tf = pt[k];
            Tp[s0 + k] = Tf;
            const float gr = pg[3 * k], gg = pg[3 * k + 1], gb = pg[3 * k + 2];
            Rp[s0 + k] = gr; Gp[s0 + k] = gg; Bp[s0 + k] = gb;
            float vA = 0.0f;
            if (use_depth != 0) Dp[s0 + k] = pd[k];
            if (use_alpha != 0) vA = pa[k];
            Sp[s0 + k] = Tf * (bg0 * gr + bg1 * gg + bg2 * gb - vA);
            const int nc = pn[k];
            Np[s0 + k] = (float)nc;
            rm = rm > nc ? rm : nc;
        }
        row_max[r] = rm;
        n_max = n_max > rm ? n_max : rm;
    }
}
if (slots.strides[0] != 4 || pair_grads.strides[0] != 64) return 0;
const int* slot_p = (const int*)slots.data;
float* grads = (float*)pair_grads.data;
// one Gaussian's running sums over the tile, per column (0-15): 0 v_pow, 1 dy v_pow, 2 dy^2 v_pow, 3 v_alpha_raw E,
// 4-6 w G, 7 w v_depth, 8-9 the AbsGS sums, 10 w (the blending weight)
alignas(64) float ACC[11][16];
typedef float v16f __attribute__((ext_vector_type(16)));
typedef float v4f __attribute__((ext_vector_type(4)));
typedef float v2f __attribute__((ext_vector_type(2)));
auto tree16 = [](v16f v) -> float {
    const v8f h = __builtin_shufflevector(v, v, 0, 1, 2, 3, 4, 5, 6, 7)
                  + __builtin_shufflevector(v, v, 8, 9, 10, 11, 12, 13, 14, 15);
    const v4f q = __builtin_shufflevector(h, h, 0, 1, 2, 3) + __builtin_shufflevector(h, h, 4, 5, 6, 7);
    const v2f r = __builtin_shufflevector(q, q, 0, 1) + __builtin_shufflevector(q, q, 2, 3);
    return r[0] + r[1];
};
Pre nxt;
if (n_max > 0) nxt = prepare(start + n_max - 1, row_max, n_max - 1);
for (int jj = 0; jj < n_max; ++jj) {
    const int i = n_max - 1 - jj;
    const float fi = (float)i;
    const int j = start + i;
    const Pre cur = nxt;
    if (i > 0) nxt = prepare(j - 1, row_max, i - 1);
    const Splat& g = cur.g;
    list_prepared(cur, no_rows);
    if (nl + nr == 0) continue;
    lane_constants(g);
    const float a = g.a, b = g.b, c = g.c;
    const float* col = cp + 4L * j;
    const float c0 = col[0], c1 = col[1], c2 = col[2], c3 = col[3];
    const vf vop = g.op;
    // the entries [e0, e1) of one block (off: its first column, 0, or 8 for 8 lanes' right halves) in two passes:
    // the first blends back to front, sums v_raw E and keeps each entry's v_pow and w ok (VP, WK); the second sums
    // those per lane, each sum in a register (the same lane sums in the same order as one loop over the list that
    // adds to ACC[.][column] as it goes), stored in ACC[.][off .. off + W - 1] at the end
    alignas(64) float VP[32][@W@], WK[32][@W@];
    auto blend_block = [&](const int off, const int e0, const int e1) __attribute__((always_inline)) {
        const vf dx = *(const vf*)(dxl + off);
        vf s0 = 0.0f, s1 = 0.0f, s2 = 0.0f, s3 = 0.0f, s4 = 0.0f, s5 = 0.0f, s6 = 0.0f, s7 = 0.0f, s8 = 0.0f,
            s9 = 0.0f, s10 = 0.0f;
        for (int e = e0; e < e1; ++e) {
            const int q = hq[e];
            const vf ev = vexp(entry_power(e));
            const vf raw = vop * ev;
            const vf al = vmin(kv(K_AMAX), raw);
            const vf inv = 1.0f / (1.0f - al);
            const vf Tq = *(const vf*)T[q];
            const vf Sq = *(const vf*)S[q];
            const vf gR = *(const vf*)GR[q], gG = *(const vf*)GG[q], gB = *(const vf*)GB[q];
            const vf vD = *(const vf*)VD[q];
            const vf Tk = Tq * inv;
            const vf w = al * Tk;
            const vf gi = fmav((vf)c3, vD, fmav((vf)c2, gB, fmav((vf)c1, gG, c0 * gR)));
            const vf v_al = fmav(Tk, gi, -(Sq * inv));
            // T = ok ? Tk : T and S = ok ? S + w gi : S, without a select on what was loaded from the same place
            // (see the forward): T inv is Tk, T 1 is T; S + -0 is S (also where S is -0)
#ifdef TILE_MASKS
            // ok as a mask register; where the float lanes multiplied by 0 (a -0 where v_al < 0) the masked lanes
            // are +0: the same sums bit for bit (each starts at +0 and x + -0, x + +0 and fma(y, -0, x) are x there)
            const kmask okm = kcmp_lt((vf)fi, *(const vf*)NC[q], kcmp_ge(al, kv(K_AMIN), (kmask)hm[e]));
            *(vf*)T[q] = Tq * ksel(okm, inv, (vf)1.0f);
            *(vf*)S[q] = Sq + ksel(okm, w * gi, (vf)-0.0f);
            const vf v_raw = ksel(kcmp_le(raw, kv(K_AMAX), okm), v_al, (vf)0.0f);
            s3 = fmav(v_raw, ev, s3);
            *(vf*)VP[e] = v_raw * raw;
            *(vf*)WK[e] = ksel(okm, w, (vf)0.0f);
#else
            const vf bit = __builtin_convertvector(((vi)hm[e] >> LANE) & 1, vf);
            const vf ok = sel(*(const vf*)NC[q] > fi, sel(al >= kv(K_AMIN), bit, (vf)0.0f), (vf)0.0f);
            const vi okb = ok > 0.0f;
            *(vf*)T[q] = Tq * sel(okb, inv, (vf)1.0f);
            *(vf*)S[q] = Sq + sel(okb, w * gi, (vf)-0.0f);
            const vf v_raw = sel(raw <= kv(K_AMAX), v_al, (vf)0.0f) * ok;
            s3 = fmav(v_raw, ev, s3);
            *(vf*)VP[e] = v_raw * raw;
            *(vf*)WK[e] = w * ok;
#endif
        }
        for (int e = e0; e < e1; ++e) {
            const int q = hq[e];
            const float dy = hd[e], bdy = hb[e];
            const vf v_pow = *(const vf*)VP[e], wk = *(const vf*)WK[e];
            s0 = s0 + v_pow;
            s1 = fmav((vf)dy, v_pow, s1);
            s2 = fmav((vf)(dy * dy), v_pow, s2);
            s4 = fmav(wk, *(const vf*)GR[q], s4);
            s5 = fmav(wk, *(const vf*)GG[q], s5);
            s6 = fmav(wk, *(const vf*)GB[q], s6);
            s7 = fmav(wk, *(const vf*)VD[q], s7);
            s10 = s10 + wk;
            if (@ABSGRAD@) {
                const vf mp = __builtin_elementwise_abs(v_pow);
                s8 = fmav(__builtin_elementwise_abs(fmav((vf)a, dx, (vf)bdy)), mp, s8);
                s9 = fmav(__builtin_elementwise_abs(fmav((vf)b, dx, (vf)(c * dy))), mp, s9);
            }
        }
        *(vf*)(ACC[0] + off) = s0; *(vf*)(ACC[1] + off) = s1; *(vf*)(ACC[2] + off) = s2;
        *(vf*)(ACC[3] + off) = s3; *(vf*)(ACC[4] + off) = s4; *(vf*)(ACC[5] + off) = s5;
        *(vf*)(ACC[6] + off) = s6; *(vf*)(ACC[7] + off) = s7; *(vf*)(ACC[8] + off) = s8;
        *(vf*)(ACC[9] + off) = s9; *(vf*)(ACC[10] + off) = s10;
    };
#if @W@ == 8
    blend_block(0, 0, nl);
    blend_block(8, 16, 16 + nr);
#else
    blend_block(0, 0, nl);
#endif
    // sum_px dx v_pow, sum dx^2 v_pow, sum dx dy v_pow (dx is the column's constant) and the other sums over the
    // 16 columns, each by raster_tile's tree (v[k] + v[k + 8], then + 4, then (0 + 2) + (1 + 3)) as vector halves
    // added, where 13 scalar trees of 15 additions each took a sixth of the backward blend
    const v16f dx16 = *(const v16f*)dxl, a0 = *(const v16f*)ACC[0], a1 = *(const v16f*)ACC[1];
    float* pg = grads + 16L * slot_p[j];
#if @W@ == 16
    // the thirteen trees at once, transposed: each level adds the same lane pairs as tree16 for up to 16 vectors
    // together, two vectors' halves side by side in one register (two permutes and an add a level and pair), so every
    // sum is tree16's bit for bit in a third of the instructions; lane k of the result is the sum of input k
    const v16f z16 = 0.0f;
    const v16f in0 = dx16 * a0, in1 = dx16 * dx16 * a0, in2 = a1, in3 = dx16 * a1, in4 = *(const v16f*)ACC[2];
    const v16f in5 = *(const v16f*)ACC[3], in6 = *(const v16f*)ACC[4], in7 = *(const v16f*)ACC[5];
    const v16f in8 = *(const v16f*)ACC[6], in9 = *(const v16f*)ACC[7];
    const v16f in10 = @ABSGRAD@ ? *(const v16f*)ACC[8] : z16, in11 = @ABSGRAD@ ? *(const v16f*)ACC[9] : z16;
    const v16f in12 = *(const v16f*)ACC[10];
    // level 1: [v0..7 + v8..15 of A | the same of B]
    auto l1 = [](v16f A, v16f B) -> v16f {
        return __builtin_shufflevector(A, B, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23)
               + __builtin_shufflevector(A, B, 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31);
    };
    // level 2: four halves of 8 -> four quarters of 4 (h0..3 + h4..7)
    auto l2 = [](v16f X, v16f Y) -> v16f {
        return __builtin_shufflevector(X, Y, 0, 1, 2, 3, 8, 9, 10, 11, 16, 17, 18, 19, 24, 25, 26, 27)
               + __builtin_shufflevector(X, Y, 4, 5, 6, 7, 12, 13, 14, 15, 20, 21, 22, 23, 28, 29, 30, 31);
    };
    // level 3: eight quarters of 4 -> eight pairs (q0, q1 + q2, q3)
    auto l3 = [](v16f X, v16f Y) -> v16f {
        return __builtin_shufflevector(X, Y, 0, 1, 4, 5, 8, 9, 12, 13, 16, 17, 20, 21, 24, 25, 28, 29)
               + __builtin_shufflevector(X, Y, 2, 3, 6, 7, 10, 11, 14, 15, 18, 19, 22, 23, 26, 27, 30, 31);
    };
    // level 4: sixteen pairs -> sixteen sums (r0 + r1)
    auto l4 = [](v16f X, v16f Y) -> v16f {
        return __builtin_shufflevector(X, Y, 0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30)
               + __builtin_shufflevector(X, Y, 1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    };
    const v16f F = l4(l3(l2(l1(in0, in1), l1(in2, in3)), l2(l1(in4, in5), l1(in6, in7))),
                      l3(l2(l1(in8, in9), l1(in10, in11)), l2(l1(in12, z16), z16)));
    const float P1 = F[0], P2 = F[1], Q1 = F[2], Q2 = F[3], Q3 = F[4];
    float R[8];                 // the sums of ACC[3..10]
    for (int t = 0; t < 8; ++t) R[t] = F[t + 5];
#else
    const float P1 = tree16(dx16 * a0), P2 = tree16(dx16 * dx16 * a0), Q1 = tree16(a1), Q2 = tree16(dx16 * a1);
    const float Q3 = tree16(*(const v16f*)ACC[2]);
    float R[8];
    for (int t = 0; t < 8; ++t) R[t] = tree16(*(const v16f*)ACC[t + 3]);
#endif
    // stores, not adds: a pair is one tile's and visited once, into the zeroed pairs (a zero plus x is x, and a -0
    // stored where the add made +0 sums alike in the gather, whose sum starts at +0), and a store reads nothing: the
    // read of a random pair before its add cost 6-15 % of the backward blend (docs/rasteriser.md)
    pg[0] = a * P1 + b * Q1;
    pg[1] = b * P1 + c * Q1;
    pg[2] = -0.5f * P2;
    pg[3] = -Q2;
    pg[4] = -0.5f * Q3;
    for (int t = 0; t < 8; ++t) pg[t + 5] = R[t];
}
return 1;
"""


def lanes_probe() -> str:
    """A snippet that returns the lane width :func:`fill`'s snippets compile at in the same module (16 or 8), 0 where
    they do not run (CUDA)."""
    wide = "#if defined(__AVX512F__)\nreturn 16;\n#else\nreturn 8;\n#endif\n" if _LANES == 16 else "return 8;\n"
    return "#if defined(__clang__) && !defined(__CUDA_ARCH__)\n" + wide + "#else\nreturn 0;\n#endif\n"


def masks_probe() -> str:
    """A snippet that returns 1 where :func:`fill`'s snippets at the module's lane width take their lanes' decisions
    in AVX-512 mask registers (16 lanes with AVX-512F, 8 with AVX-512VL; not with ``MGSO_TILE_MASKS=0``), 0 where
    they keep them in 0/1 float lanes or do not run (CUDA)."""
    vl = "#if defined(__AVX512VL__)\nreturn 1;\n#else\nreturn 0;\n#endif\n"
    if not _MASKS:
        wide = "return 0;\n"
    elif _LANES == 16:
        wide = "#if defined(__AVX512F__)\nreturn 1;\n#else\n" + vl + "#endif\n"
    else:
        wide = vl
    return "#if defined(__clang__) && !defined(__CUDA_ARCH__)\n" + wide + "#else\nreturn 0;\n#endif\n"


def _masks_from_env() -> bool:
    """Whether the snippets may take their lanes' decisions in AVX-512 mask registers (the default) or keep them in
    0/1 float lanes as on a CPU without AVX-512 (``MGSO_TILE_MASKS=0`` in the environment, read once at import: for
    the test that compares the two, bit for bit)."""
    value = os.environ.get("MGSO_TILE_MASKS", "1").strip()
    if value not in ("0", "1"):
        raise ValueError(f"MGSO_TILE_MASKS={value!r}: 1 (AVX-512 mask registers where the CPU has them) or 0")
    return value == "1"


def _lanes_from_env() -> int:
    """The lane width the snippets ask for where the CPU has AVX-512: 16 (a whole tile row a vector), or 8 when the
    environment sets ``MGSO_TILE_LANES=8`` (read once, at import: for the test and profiles that compare the two).
    Where the compiler targets no AVX-512 the snippets use 8 lanes either way."""
    value = os.environ.get("MGSO_TILE_LANES", "16").strip()
    if value not in ("8", "16"):
        raise ValueError(f"MGSO_TILE_LANES={value!r}: the tile snippets' lane width is 8 or 16")
    return int(value)


_LANES = _lanes_from_env()
_MASKS = _masks_from_env()


def _with_lanes(text: str, width: int) -> str:
    return (text.replace("@W@", str(width))
            .replace("@LANES@", ", ".join(str(k) for k in range(width))))


def fill(body: str, consts: dict[str, float | int], lanes: int | None = None) -> str:
    """The snippet: CPU only (clang), no contraction into FMAs but the snippet's own ``fmav`` (so the forward and
    the backward compute each alpha the same way), the prelude and ``body`` with the constants filled in (a float as
    a float32 literal, an int as itself), at 16 lanes where the compiler targets AVX-512 (and :func:`lanes` is 16),
    at 8 otherwise; ``lanes=8``: at 8 everywhere (the backward on small images, where most Gaussians reach a few
    pixels of a tile row: ``mgso_kernels.splat.raster_bwd.NARROW_BACKWARD_PIXELS``)."""
    if lanes not in (None, 8):
        raise ValueError(f"raster_tile_cpp.fill: lanes must be None or 8, got {lanes!r}")
    code = _PRELUDE + body + "\n#undef TILE_MASKS\n"
    wide = _with_lanes(code, 16) if _LANES == 16 and lanes is None else None
    text = "#if defined(__clang__) && !defined(__CUDA_ARCH__)\n{\n#pragma clang fp contract(off)\n"
    if wide is not None:
        text += "#if defined(__AVX512F__)\n" + wide + "\n#else\n" + _with_lanes(code, 8) + "\n#endif\n"
    else:
        text += _with_lanes(code, 8)
    text += "\n}\n#else\nreturn 0;\n#endif\n"
    for name, value in dict(consts, MASKS=int(_MASKS)).items():
        text = text.replace(f"@{name}@", str(value) if isinstance(value, int) else _f32(value))
    if "@" in text:
        raise ValueError("raster_tile_cpp: a value of the snippet is not filled in")
    return text
