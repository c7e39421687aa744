"""Binning of projected Gaussians into 16x16 tiles: tight tile lists, sort keys, radix sort, per-tile ranges.

**Which tiles a Gaussian is listed in.** A Gaussian only changes a pixel where
``opacity * exp(power) >= 1/255``, i.e. inside its *cut-off ellipse* ``d^T conic d <= r2`` with
``r2 = 2 log(255 opacity)`` (at most 11.06 = 3.33 sigma for opacity 0.99; smaller for fainter Gaussians, where a
fixed 3-sigma square lists many tiles the blend then skips pixel by pixel). A tile is listed iff that ellipse
reaches the tile's rectangle of pixel centres ``[16 tx, 16 tx + 15] x [16 ty, 16 ty + 15]`` (clipped to the
image). The test is exact, not a bounding square or an oriented box: for each tile row the ellipse is cut by the
row's horizontal slab, the x-extent of that convex slice is computed in closed form (either the ellipse's
leftmost/rightmost point, if it lies in the slab, or the boundary at the slab's edges), and the tiles whose columns
meet that extent are listed. This is the tightest possible list (an ellipse-rectangle intersection test, like
gsplat's/StopThePop's tile-ellipse tests but exact), at O(rows) work per Gaussian. ``r2`` is inflated by a
relative 1e-3 (+1e-2, :func:`mgso_kernels.splat.common.cutoff_r2`) so float32 rounding can never drop a tile
the blend would use; the blend applies the exact 1/255 rule itself.

**Keys.** One int64 key per (tile, Gaussian) pair: tile index (row-major, ``ty * tiles_x + tx``) in the high 32
bits, the float32 depth's bit pattern in the low 32 (positive floats sort like their bit patterns; depths are
``> near > 0``). Pairs are counted per Gaussian, offsets come from an exclusive ``wp.utils.array_scan``, and the
keys are sorted with ``wp.utils.radix_sort_pairs`` over bits ``[0, 32 + ceil(log2(tiles)))`` only (on the CPU by
:func:`radix_sort_cpp`, the same stable LSD radix sort in C++ with the digits' histograms in one pass, 11-bit digits:
about twice as fast); both key and value arrays need ``2 * count`` capacity. Radix sort is stable, so depth ties keep
Gaussian index order.

**Values** are pair *slots*: slot ``p`` is the pair's position before sorting, so a Gaussian's slots are the
contiguous range ``[offset_g, offset_g + tiles_touched_g)``. The backward pass accumulates per-pair gradients
into slots and then sums each Gaussian's contiguous range: no cross-thread atomics on the CPU, deterministic.
``pair_gauss[p]`` is the Gaussian of slot ``p``.

**On the CPU** counting and emitting run as C++ blocks of :data:`BIN_BLOCK` Gaussians (:func:`bin_blocks`,
``_BIN_CPP``): the same arithmetic 16 Gaussians (then 16 tile rows) a vector, the same pairs bit for bit; CUDA keeps
the thread-per-Gaussian kernels (docs/rasteriser.md).

Twin: :func:`mgso_kernels.reference.splat.tile_pairs` (brute-force ellipse-rectangle test over every tile).
"""

from __future__ import annotations

import warp as wp

from .. import dynamic
from ..dynamic import take_item
from .camera import TILE_SIZE, Camera
from .common import LANES16_CPP, vec8

wp.set_module_options({"enable_backward": False})

__all__ = ["count_tiles", "emit_pairs", "tile_ranges", "ellipse_row_span", "sort_pairs", "radix_sort_pairs_cpu",
           "sort_pairs_and_ranges", "sort_by_gaussian_scratch"]

TS = wp.constant(TILE_SIZE)


@wp.func
def ellipse_row_span(a: float, b: float, c: float, r2: float, dlo: float, dhi: float) -> wp.vec2:
    """x-extent (relative to the centre) of {a dx^2 + 2 b dx dy + c dy^2 <= r2, dlo <= dy <= dhi}.

    Returns (xmin, xmax); xmin > xmax means the slab misses the ellipse.
    """
    det = a * c - b * b
    syy = a / det  # Sigma_yy
    sxx = c / det  # Sigma_xx
    sxy = -b / det
    ry = wp.sqrt(r2 * syy)
    lo = wp.max(dlo, -ry)
    hi = wp.min(dhi, ry)
    if lo > hi:
        return wp.vec2(1.0, -1.0)
    ex = wp.sqrt(r2 * sxx)  # half-width of the ellipse
    dy_right = sxy * wp.sqrt(r2 / sxx)  # dy of the rightmost point; the leftmost is at -dy_right
    # boundary x at the slab edges: (-b dy +- sqrt(a r2 - det dy^2)) / a
    s_lo = wp.sqrt(wp.max(0.0, a * r2 - det * lo * lo))
    s_hi = wp.sqrt(wp.max(0.0, a * r2 - det * hi * hi))
    xr = wp.max((-b * lo + s_lo) / a, (-b * hi + s_hi) / a)
    xl = wp.min((-b * lo - s_lo) / a, (-b * hi - s_hi) / a)
    if dy_right >= lo and dy_right <= hi:
        xr = ex
    if -dy_right >= lo and -dy_right <= hi:
        xl = -ex
    return wp.vec2(xl, xr)


@wp.func
def row_range(m: wp.vec2, conic: wp.vec3, r2: float, cam: Camera) -> wp.vec2i:
    """Tile rows [ty0, ty1] (inclusive) the ellipse's y-extent reaches; ty0 > ty1 if none."""
    det = conic[0] * conic[2] - conic[1] * conic[1]
    ry = wp.sqrt(r2 * conic[0] / det)
    y_lo = wp.max(m[1] - ry, 0.0)
    y_hi = wp.min(m[1] + ry, float(cam.height - 1))
    if y_lo > y_hi:
        return wp.vec2i(1, 0)
    # rows whose pixel-centre span [16 ty, 16 ty + 15] meets [y_lo, y_hi]
    ty0 = int(wp.ceil((y_lo - float(TS - 1)) / float(TS)))
    ty1 = int(wp.floor(y_hi / float(TS)))
    return wp.vec2i(wp.max(ty0, 0), wp.min(ty1, cam.tiles_y - 1))


@wp.func
def col_range(m: wp.vec2, conic: wp.vec3, r2: float, ty: int, cam: Camera) -> wp.vec2i:
    """Tile columns [tx0, tx1] (inclusive) of row ``ty`` that the ellipse reaches; tx0 > tx1 if none."""
    y0 = float(ty * TS)
    y1 = float(wp.min(ty * TS + TS - 1, cam.height - 1))
    span = ellipse_row_span(conic[0], conic[1], conic[2], r2, y0 - m[1], y1 - m[1])
    if span[0] > span[1]:
        return wp.vec2i(1, 0)
    x_lo = wp.max(m[0] + span[0], 0.0)
    x_hi = wp.min(m[0] + span[1], float(cam.width - 1))
    if x_lo > x_hi:
        return wp.vec2i(1, 0)
    tx0 = int(wp.ceil((x_lo - float(TS - 1)) / float(TS)))
    tx1 = int(wp.floor(x_hi / float(TS)))
    return wp.vec2i(wp.max(tx0, 0), wp.min(tx1, cam.tiles_x - 1))


@wp.func
def count_one(g: int, splats: wp.array(dtype=vec8), radii: wp.array(dtype=wp.int32), cam: Camera) -> int:
    """Number of tiles Gaussian ``g`` is listed in (0 if culled)."""
    n = int(0)
    if radii[g] > 0:
        s = splats[g]
        m = wp.vec2(s[0], s[1])
        conic = wp.vec3(s[2], s[3], s[4])
        r2 = s[7]
        rows = row_range(m, conic, r2, cam)
        for ty in range(rows[0], rows[1] + 1):
            cols = col_range(m, conic, r2, ty, cam)
            if cols[1] >= cols[0]:
                n += cols[1] - cols[0] + 1
    return n


@wp.func
def emit_one(g: int, splats: wp.array(dtype=vec8), depths: wp.array(dtype=float), radii: wp.array(dtype=wp.int32),
             pair_offsets: wp.array(dtype=wp.int32), cam: Camera, keys: wp.array(dtype=wp.int64),
             slots: wp.array(dtype=wp.int32), pair_gauss: wp.array(dtype=wp.int32)):
    """Gaussian ``g``'s keys, slots and slot->Gaussian entries from ``pair_offsets[g]`` on, tile rows then columns
    in ascending order."""
    if radii[g] == 0:
        return
    s = splats[g]
    m = wp.vec2(s[0], s[1])
    conic = wp.vec3(s[2], s[3], s[4])
    r2 = s[7]
    depth_bits = wp.int64(wp.cast(depths[g], wp.int32))
    p = pair_offsets[g]
    rows = row_range(m, conic, r2, cam)
    for ty in range(rows[0], rows[1] + 1):
        cols = col_range(m, conic, r2, ty, cam)
        for tx in range(cols[0], cols[1] + 1):
            tile = ty * cam.tiles_x + tx
            keys[p] = (wp.int64(tile) << wp.int64(32)) | depth_bits
            slots[p] = p
            pair_gauss[p] = g
            p += 1


@wp.kernel
def count_tiles(
    offset: int,
    splats: wp.array(dtype=vec8),  # [N] per Gaussian: mean (px), conic, opacity, exp(-a), cut-off r2
    radii: wp.array(dtype=wp.int32),  # [N] 0 = culled
    cam: Camera,
    tiles_touched: wp.array(dtype=wp.int32),  # [N] out
):
    g = offset + wp.tid()
    tiles_touched[g] = count_one(g, splats, radii, cam)


@wp.kernel
def emit_pairs(
    offset: int,
    splats: wp.array(dtype=vec8),  # [N] per Gaussian
    depths: wp.array(dtype=float),  # [N] camera z (> near > 0 for listed Gaussians)
    radii: wp.array(dtype=wp.int32),  # [N]
    pair_offsets: wp.array(dtype=wp.int32),  # [N] exclusive scan of tiles_touched
    cam: Camera,
    keys: wp.array(dtype=wp.int64),  # [>= 2 M] out: tile << 32 | depth bits
    slots: wp.array(dtype=wp.int32),  # [>= 2 M] out: pair slot (= unsorted position)
    pair_gauss: wp.array(dtype=wp.int32),  # [>= M] out: Gaussian of each slot
):
    emit_one(offset + wp.tid(), splats, depths, radii, pair_offsets, cam, keys, slots, pair_gauss)


# The CPU's binning in C++ blocks of up to BIN_BLOCK Gaussians (count_tiles' and emit_pairs' arithmetic, the same
# operations in the same order, so the same tiles bit for bit; Warp's min/max are C's fmin/fmax). The Warp kernels
# compute each tile row's span one Gaussian at a time, seven divisions and six square roots a row in one dependent
# chain; here a block first computes 16 Gaussians' row ranges and the span's per-Gaussian constants (det, the
# half-heights and half-width, the extreme points' dy) a vector at a time, lists the (Gaussian, tile row) items, then
# computes 16 items' column ranges a vector at a time (two roots and four divisions each), and only then counts or
# writes the pairs, in the kernels' order. mode 0: tiles_touched of [lo, hi); mode 1: their keys, slots and
# pair_gauss. With a cache of 4 ints a Gaussian the count keeps the ranges of the Gaussians of up to 3 tile rows and
# the emit writes their pairs from them (docs/rasteriser.md, "The count's tile ranges kept for the emit"). Returns 1,
# or 0 where it does not apply (CUDA, arrays not contiguous, a block too large, more than 1024 tile rows) and nothing
# is written.
_BIN_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
enum { BLK = 256, CAP = 2048, V = 16 };
const int n = hi - lo;
if (n < 0 || n > BLK || tiles_y < 1 || tiles_y > 1024 || tiles_x < 1 || splats.strides[0] != 32
    || radii.strides[0] != 4) return 0;
if (mode == 0 && tiles_touched.strides[0] != 4) return 0;
if (mode == 1 && (depths.strides[0] != 4 || pair_offsets.strides[0] != 4 || keys.strides[0] != 8
                  || slots.strides[0] != 4 || pair_gauss.strides[0] != 4)) return 0;
// the count's row and column ranges kept for the emit (cache[4 g .. 4 g + 3]: the first tile row | rows << 16, then
// tx0 | tx1 << 16 of up to 3 rows; -1: not kept), where the caller gives a cache of 4 n ints
const bool use_cache = cache.shape[0] >= 4L * hi && cache.strides[0] == 4 && tiles_x < 32768;
int* CC = (int*)cache.data;
@LANES16@
const float* S = (const float*)splats.data;
const int* R = (const int*)radii.data;
const float Hm1 = (float)(height - 1), Wm1 = (float)(width - 1);
// per Gaussian of the block: the span's constants (ellipse_row_span's, which does not depend on the row)
float CA[BLK], CNB[BLK], CDET[BLK], CAR2[BLK], CRY[BLK], CEX[BLK], CDYR[BLK], CM0[BLK], CM1[BLK];
int CNT[BLK], CUR[BLK];
long long DB[BLK];
// the (Gaussian, tile row) items waiting, and their column ranges
int IK[CAP], ITY[CAP], IX0[CAP], IX1[CAP];
int ni = 0;
// the pairs of Gaussian g in tile row ty, tiles tx0..tx1, from slot p on (its depth bits db); returns the next slot
auto emit_row = [&](int p, int g, int ty, int tx0, int tx1, long long db) -> int {
    long long* K = (long long*)keys.data;
    int* SL = (int*)slots.data;
    int* PG = (int*)pair_gauss.data;
    const long long row = (long long)ty * tiles_x;
    for (int tx = tx0; tx <= tx1; ++tx, ++p) {
        K[p] = ((row + tx) << 32) | db;
        SL[p] = p;
        PG[p] = g;
    }
    return p;
};
auto flush = [&]() {
    for (int i0 = 0; i0 < ni; i0 += V) {
        vf a, nb, det, ar2, ry, ex, dyr, m0, m1;
        vi ty;
        for (int j = 0; j < V; ++j) {
            const int i = i0 + j < ni ? i0 + j : i0;    // past the end: a copy of the first, not stored
            const int k = IK[i];
            a[j] = CA[k]; nb[j] = CNB[k]; det[j] = CDET[k]; ar2[j] = CAR2[k]; ry[j] = CRY[k]; ex[j] = CEX[k];
            dyr[j] = CDYR[k]; m0[j] = CM0[k]; m1[j] = CM1[k]; ty[j] = ITY[i];
        }
        // col_range: the row's pixel centres, relative to the centre
        const vf y0 = __builtin_convertvector(ty * 16, vf);
        const vf y1 = __builtin_convertvector(imn(ty * 16 + 15, (vi)(height - 1)), vf);
        const vf dlo = y0 - m1, dhi = y1 - m1;
        // ellipse_row_span
        const vf slo = fmx(dlo, -ry), shi = fmn(dhi, ry);
        vi miss = slo > shi;
        const vf s_lo = sqrtv(fmx((vf)0.0f, ar2 - det * slo * slo));
        const vf s_hi = sqrtv(fmx((vf)0.0f, ar2 - det * shi * shi));
        vf xr = fmx((nb * slo + s_lo) / a, (nb * shi + s_hi) / a);
        vf xl = fmn((nb * slo - s_lo) / a, (nb * shi - s_hi) / a);
        xr = sel((dyr >= slo) & (dyr <= shi), ex, xr);
        const vf ndyr = -dyr;
        xl = sel((ndyr >= slo) & (ndyr <= shi), -ex, xl);
        miss |= xl > xr;
        const vf x_lo = fmx(m0 + xl, (vf)0.0f), x_hi = fmn(m0 + xr, (vf)Wm1);
        miss |= x_lo > x_hi;
        const vi tx0 = imx(ceili((x_lo - 15.0f) / 16.0f), (vi)0);
        const vi tx1 = imn(floori(x_hi / 16.0f), (vi)(tiles_x - 1));
        const vi t0 = seli(miss, (vi)1, tx0), t1 = seli(miss, (vi)0, tx1);
        const int m = ni - i0 < V ? ni - i0 : V;
        for (int j = 0; j < m; ++j) { IX0[i0 + j] = t0[j]; IX1[i0 + j] = t1[j]; }
    }
    if (mode == 0) {
        for (int i = 0; i < ni; ++i)
            if (IX1[i] >= IX0[i]) CNT[IK[i]] += IX1[i] - IX0[i] + 1;
        if (use_cache) {
            for (int i = 0; i < ni; ++i) {  // the rows of the Gaussians kept (their first row and count: listed)
                int* c = CC + 4L * (lo + IK[i]);
                if (c[0] >= 0) c[1 + ITY[i] - (c[0] & 0xffff)] = IX0[i] | (IX1[i] << 16);
            }
        }
    } else {
        for (int i = 0; i < ni; ++i) {
            const int k = IK[i];
            CUR[k] = emit_row(CUR[k], lo + k, ITY[i], IX0[i], IX1[i], DB[k]);
        }
    }
    ni = 0;
};
for (int k0 = 0; k0 < n; k0 += V) {
    // a group none of whose Gaussians this view shows (many of a real map's once it is in spatial order:
    // GaussianMap.sort_spatially) lists no item: count 0, without the arithmetic
    int shown = 0;
    for (int k = k0; k < k0 + V && k < n; ++k) shown |= R[lo + k];
    if (shown == 0) {
        for (int k = k0; k < k0 + V && k < n; ++k) {
            CNT[k] = 0;
            if (mode == 0 && use_cache) CC[4L * (lo + k)] = 0;
        }
        continue;
    }
    // the emit: the Gaussians whose ranges the count kept write their pairs from them (the same pairs in the same
    // order), the rest are computed below
    int kept = 0;
    if (mode == 1 && use_cache) {
        for (int j = 0; j < V && k0 + j < n; ++j) {
            const int g = lo + k0 + j;
            const int* c = CC + 4L * g;
            if (c[0] < 0) continue;
            kept |= 1 << j;
            const int r = c[0] >> 16;
            if (r == 0) continue;
            int p = ((const int*)pair_offsets.data)[g];
            int bits;
            __builtin_memcpy(&bits, (const float*)depths.data + g, 4);
            const long long db = (long long)bits;
            for (int q = 0; q < r; ++q) p = emit_row(p, g, (c[0] & 0xffff) + q, c[1 + q] & 0xffff, c[1 + q] >> 16, db);
        }
        const int full = (n - k0 < V ? (1 << (n - k0)) : (1 << V)) - 1;
        if (kept == full) continue;
    }
    vf a, b, c, r2, m0, m1;
    vi live;
    for (int j = 0; j < V; ++j) {
        const int k = k0 + j;
        if (k < n) {
            const float* s = S + 8L * (lo + k);
            m0[j] = s[0]; m1[j] = s[1]; a[j] = s[2]; b[j] = s[3]; c[j] = s[4]; r2[j] = s[7];
            live[j] = R[lo + k] > 0 ? -1 : 0;
        } else {
            m0[j] = 0.0f; m1[j] = 0.0f; a[j] = 1.0f; b[j] = 0.0f; c[j] = 1.0f; r2[j] = 1.0f; live[j] = 0;
        }
    }
    // row_range
    const vf det = a * c - b * b;
    const vf ryr = sqrtv(r2 * a / det);
    const vf y_lo = fmx(m1 - ryr, (vf)0.0f), y_hi = fmn(m1 + ryr, (vf)Hm1);
    const vi none = (y_lo > y_hi) | ~live;
    const vi ty0 = seli(none, (vi)1, imx(ceili((y_lo - 15.0f) / 16.0f), (vi)0));
    const vi ty1 = seli(none, (vi)0, imn(floori(y_hi / 16.0f), (vi)(tiles_y - 1)));
    // ellipse_row_span's constants
    const vf syy = a / det, sxx = c / det, sxy = -b / det;
    const vf ry = sqrtv(r2 * syy), ex = sqrtv(r2 * sxx), dyr = sxy * sqrtv(r2 / sxx), ar2 = a * r2, nb = -b;
    const int m = n - k0 < V ? n - k0 : V;
    for (int j = 0; j < m; ++j) {
        const int k = k0 + j;
        CA[k] = a[j]; CNB[k] = nb[j]; CDET[k] = det[j]; CAR2[k] = ar2[j]; CRY[k] = ry[j]; CEX[k] = ex[j];
        CDYR[k] = dyr[j]; CM0[k] = m0[j]; CM1[k] = m1[j];
        CNT[k] = 0;
        if ((kept >> j) & 1) continue;          // its pairs written from the count's ranges above
        if (mode == 1 && live[j]) {
            CUR[k] = ((const int*)pair_offsets.data)[lo + k];
            int bits;
            __builtin_memcpy(&bits, (const float*)depths.data + lo + k, 4);
            DB[k] = (long long)bits;
        }
        const int rows = ty1[j] - ty0[j] + 1;
        if (rows <= 0) {
            if (mode == 0 && use_cache) CC[4L * (lo + k)] = 0;
            continue;
        }
        if (ni + rows > CAP) flush();
        if (mode == 0 && use_cache) CC[4L * (lo + k)] = rows <= 3 ? (ty0[j] | (rows << 16)) : -1;
        for (int t = ty0[j]; t <= ty1[j]; ++t) { IK[ni] = k; ITY[ni] = t; ++ni; }
    }
}
flush();
if (mode == 0) {
    int* T = (int*)tiles_touched.data;
    for (int k = 0; k < n; ++k) T[lo + k] = CNT[k];
}
return 1;
#else
return 0;
#endif
""".replace("@LANES16@", LANES16_CPP)


@wp.func_native(_BIN_CPP)
def bin_block_cpp(mode: int, lo: int, hi: int, splats: wp.array(dtype=vec8), depths: wp.array(dtype=float),
                  radii: wp.array(dtype=wp.int32), pair_offsets: wp.array(dtype=wp.int32), width: int, height: int,
                  tiles_x: int, tiles_y: int, tiles_touched: wp.array(dtype=wp.int32),
                  keys: wp.array(dtype=wp.int64), slots: wp.array(dtype=wp.int32),
                  pair_gauss: wp.array(dtype=wp.int32), cache: wp.array(dtype=wp.int32)) -> int:
    """count_tiles (``mode`` 0) or emit_pairs (1) for the Gaussians ``[lo, hi)`` in C++ (above): the same tiles and
    pairs. ``cache`` (4 ints a Gaussian, or shorter for none): the count keeps the ranges of Gaussians of up to 3
    tile rows there and the emit writes their pairs from them. Returns 1, or 0 where it does not apply (nothing
    written)."""
    ...


@wp.kernel
def bin_blocks(
    offset: int,
    block: int,  # Gaussians a thread (at most 256)
    n: int,
    mode: int,  # 0: count_tiles; 1: emit_pairs
    splats: wp.array(dtype=vec8),
    depths: wp.array(dtype=float),  # mode 1
    radii: wp.array(dtype=wp.int32),
    pair_offsets: wp.array(dtype=wp.int32),  # mode 1
    cam: Camera,
    tiles_touched: wp.array(dtype=wp.int32),  # mode 0 out
    keys: wp.array(dtype=wp.int64),  # mode 1 out
    slots: wp.array(dtype=wp.int32),  # mode 1 out
    pair_gauss: wp.array(dtype=wp.int32),  # mode 1 out
    cache: wp.array(dtype=wp.int32),  # [4 n] the count's kept ranges for the emit (shorter: none)
    native: int,  # 1: the C++ block where it applies; 0: this kernel's loop (raster_tile.use_native)
    status: wp.array(dtype=wp.int32),  # [blocks] out: 1 where the C++ block did the Gaussians
):
    """:func:`count_tiles` or :func:`emit_pairs` with ``block`` Gaussians a thread, for the CPU: the C++ block
    first, the kernels' own functions where it declines."""
    c = offset + wp.tid()
    lo = c * block
    hi = wp.min(lo + block, n)
    done = int(0)
    if native != 0:
        done = bin_block_cpp(mode, lo, hi, splats, depths, radii, pair_offsets, cam.width, cam.height, cam.tiles_x,
                             cam.tiles_y, tiles_touched, keys, slots, pair_gauss, cache)
    status[c] = done
    if done == 0:
        for g in range(lo, hi):
            if mode == 0:
                tiles_touched[g] = count_one(g, splats, radii, cam)
                if cache.shape[0] >= 4 * hi:
                    cache[4 * g] = -1  # nothing kept: the emit computes this Gaussian's pairs
            else:
                emit_one(g, splats, depths, radii, pair_offsets, cam, keys, slots, pair_gauss)


@wp.kernel
def bin_blocks_dynamic(
    offset: int,  # the chunk's index (launch_split's offset)
    shares: wp.array(dtype=wp.int64),  # each chunk's range of blocks, taken from both ends (mgso_kernels.dynamic)
    n_blocks: int,
    block: int,
    n: int,
    mode: int,
    splats: wp.array(dtype=vec8),
    depths: wp.array(dtype=float),
    radii: wp.array(dtype=wp.int32),
    pair_offsets: wp.array(dtype=wp.int32),
    cam: Camera,
    tiles_touched: wp.array(dtype=wp.int32),
    keys: wp.array(dtype=wp.int64),
    slots: wp.array(dtype=wp.int32),
    pair_gauss: wp.array(dtype=wp.int32),
    cache: wp.array(dtype=wp.int32),
    status: wp.array(dtype=wp.int32),  # [blocks] out: 1 where the C++ block did the Gaussians, 0 where it declined
):
    """:func:`bin_blocks`' C++ blocks, a chunk a core taking blocks from ``shares`` (:mod:`mgso_kernels.dynamic`):
    the same values bit for bit; a block the C++ declines is left undone with status 0 (the launcher then runs
    :func:`bin_blocks`)."""
    chunk = offset + wp.tid()
    chunks = shares.shape[0]
    for k in range(chunks):   # its own range, then the others' from their far end
        r = (chunk + k) % chunks
        c = take_item(shares, r, k)
        while c >= 0:
            lo = c * block
            status[c] = bin_block_cpp(mode, lo, wp.min(lo + block, n), splats, depths, radii, pair_offsets, cam.width,
                                      cam.height, cam.tiles_x, cam.tiles_y, tiles_touched, keys, slots, pair_gauss,
                                      cache)
            c = take_item(shares, r, k)


@wp.kernel
def tile_ranges(
    offset: int,
    keys: wp.array(dtype=wp.int64),  # [M] sorted
    n_pairs: int,
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2] out (zeroed by the caller): [start, end) into sorted pairs
):
    j = offset + wp.tid()
    tile = int(keys[j] >> wp.int64(32))
    if j == 0:
        ranges[tile, 0] = j
    elif int(keys[j - 1] >> wp.int64(32)) != tile:
        ranges[tile, 0] = j
    if j == n_pairs - 1:
        ranges[tile, 1] = j + 1
    elif int(keys[j + 1] >> wp.int64(32)) != tile:
        ranges[tile, 1] = j + 1


# ------------------------------------------------------------------------------------------------- launchers
def tile_key_bits(n_tiles: int) -> int:
    """Bits the radix sort must look at: 32 depth bits plus enough for the largest tile index."""
    return 32 + max(1, int(n_tiles - 1).bit_length())


def launch_count_tiles(splats, radii, cam: Camera, tiles_touched, device: str, threads: int | None = None,
                       min_chunk: int = 4096, cache=None):
    """``tiles_touched[g]`` = number of tiles Gaussian g is listed in (0 if culled). On the CPU the C++ blocks of
    :func:`bin_blocks` (returns their status array: 1 where the C++ ran); elsewhere :func:`count_tiles` (None).
    ``cache``: an int32 array of at least 4 n ints (CPU) where the count keeps the tile ranges of the Gaussians of up
    to 3 tile rows, for the :func:`launch_emit_pairs` that follows with the same arrays (it then writes their pairs
    without computing them again: the same pairs)."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = splats.shape[0]
    for name, a, dt in (("splats", splats, vec8), ("radii", radii, wp.int32),
                        ("tiles_touched", tiles_touched, wp.int32)):
        check_array(a, name, dt, (n,), device)
    if _is_cpu(device):
        return _launch_blocks(0, n, splats, None, radii, None, cam, tiles_touched, None, None, None, device,
                              threads, min_chunk, cache)
    launch_split(count_tiles, n, [splats, radii, cam, tiles_touched], device, threads=threads, min_chunk=min_chunk)
    return None


def launch_emit_pairs(splats, depths, radii, pair_offsets, cam: Camera, keys, slots, pair_gauss, n_pairs: int,
                      device: str, threads: int | None = None, min_chunk: int = 4096, cache=None):
    """Write the unsorted keys, slots and slot->Gaussian map; keys/slots need ``2 * n_pairs`` capacity. Returns what
    :func:`launch_count_tiles` returns. ``cache``: the one the count of the same splats, radii and camera filled
    (CPU; None: every pair computed)."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = splats.shape[0]
    for name, a, dt in (("splats", splats, vec8), ("depths", depths, wp.float32), ("radii", radii, wp.int32),
                        ("pair_offsets", pair_offsets, wp.int32)):
        check_array(a, name, dt, (n,), device)
    if keys.dtype is not wp.int64 or slots.dtype is not wp.int32 or pair_gauss.dtype is not wp.int32:
        raise TypeError("emit_pairs: keys must be int64, slots and pair_gauss int32")
    if keys.shape[0] < 2 * n_pairs or slots.shape[0] < 2 * n_pairs or pair_gauss.shape[0] < n_pairs:
        raise ValueError(f"emit_pairs: buffers too small for {n_pairs} pairs (keys/slots need 2x for the sort)")
    if _is_cpu(device):
        return _launch_blocks(1, n, splats, depths, radii, pair_offsets, cam, None, keys, slots, pair_gauss, device,
                              threads, min_chunk, cache)
    launch_split(emit_pairs, n, [splats, depths, radii, pair_offsets, cam, keys, slots, pair_gauss], device,
                 threads=threads, min_chunk=min_chunk)
    return None


#: Gaussians a thread of the CPU's binning (:func:`bin_blocks`; the C++ block takes at most 256).
BIN_BLOCK = 256


def _is_cpu(device) -> bool:
    return wp.get_device(device).is_cpu


def _launch_blocks(mode, n, splats, depths, radii, pair_offsets, cam, tiles_touched, keys, slots, pair_gauss,
                   device, threads, min_chunk, cache=None):
    """The CPU's count (mode 0) or emit (1) in blocks of BIN_BLOCK Gaussians (:func:`bin_blocks`), spread over the
    cores; returns the blocks' status (1 where the C++ block ran)."""
    from ..runtime import placeholder
    from .raster_tile import native_flag

    f32, i32 = placeholder(wp.float32, 1, device), placeholder(wp.int32, 1, device)
    i64 = placeholder(wp.int64, 1, device)
    inputs = [mode, splats, f32 if depths is None else depths, radii, i32 if pair_offsets is None else pair_offsets,
              cam, i32 if tiles_touched is None else tiles_touched, i64 if keys is None else keys,
              i32 if slots is None else slots, i32 if pair_gauss is None else pair_gauss,
              i32 if cache is None else cache]
    return dynamic.launch_blocks(bin_blocks, bin_blocks_dynamic, n, BIN_BLOCK, inputs, native_flag(), device,
                                 threads=threads, min_chunk=min_chunk)


#: Bits of a digit of the CPU's radix sort: 11 sorts a 640x480 view's 43 key bits in 4 passes where 8 took 6 (1.9 ->
#: 1.6 ms for 245k pairs, 8.4 -> 7.6 ms for 972k, 1.4 -> 1.2 ms on a real-time 320x240 step; one Zen 5 thread,
#: docs/rasteriser.md); any width gives the same order.
SORT_DIGIT_BITS = 11

# A stable LSD radix sort of (int64 key, int32 value) pairs over bits [0, end_bit), SORT_DIGIT_BITS a pass, the
# passes' histograms counted in one read of the keys, the second halves of the arrays as the scratch (Warp's
# radix_sort_pairs takes the same layout and gives the same order: both stable over their digits). 4.9 against
# 9.4 ms for 245k pairs, 20 against 41-43 ms for 972k with 8-bit digits (one Zen 3 thread; docs/rasteriser.md).
# Returns 0 where the arrays are not contiguous, and on CUDA.
_SORT_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
if (keys.strides[0] != 8 || values.strides[0] != 4 || keys.shape[0] < 2 * n || values.shape[0] < 2 * n
    || end_bit < 1 || end_bit > 64) return 0;
enum { DB = @DIGIT_BITS@, NB = 1 << DB, MAXP = (64 + DB - 1) / DB };
unsigned long long* k0 = (unsigned long long*)keys.data;
int* v0 = (int*)values.data;
unsigned long long* k1 = k0 + n;
int* v1 = v0 + n;
const int passes = (end_bit + DB - 1) / DB;
unsigned cnt[MAXP][NB];      // 48 KB of stack at 11-bit digits
for (int p = 0; p < passes; ++p)
    for (int r = 0; r < NB; ++r) cnt[p][r] = 0;
for (int i = 0; i < n; ++i) {
    const unsigned long long k = k0[i];
    for (int p = 0; p < passes; ++p) cnt[p][(k >> (DB * p)) & (NB - 1)]++;
}
for (int p = 0; p < passes; ++p) {
    unsigned sum = 0;
    for (int r = 0; r < NB; ++r) { const unsigned c = cnt[p][r]; cnt[p][r] = sum; sum += c; }
}
for (int p = 0; p < passes; ++p) {
    const int shift = DB * p;
    unsigned* c = cnt[p];
    for (int i = 0; i < n; ++i) {
        const unsigned o = c[(k0[i] >> shift) & (NB - 1)]++;
        k1[o] = k0[i];
        v1[o] = v0[i];
    }
    unsigned long long* tk = k0; k0 = k1; k1 = tk;
    int* tv = v0; v0 = v1; v1 = tv;
}
if (passes & 1) {   // the result is in the second halves: back to the first
    __builtin_memcpy(k1, k0, 8L * n);
    __builtin_memcpy(v1, v0, 4L * n);
}
return 1;
#else
return 0;
#endif
""".replace("@DIGIT_BITS@", str(SORT_DIGIT_BITS))


@wp.func_native(_SORT_CPP)
def radix_sort_cpp(n: int, end_bit: int, keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32)) -> int:
    """The stable radix sort above of the first ``n`` pairs, in place. Returns 1, or 0 (nothing done) where it does
    not apply."""
    ...


@wp.kernel
def radix_sort_pairs_cpu(n: int, end_bit: int, keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32),
                         native: int, status: wp.array(dtype=wp.int32)):
    """One thread: :func:`radix_sort_cpp` (``native`` 1), its result in ``status[0]`` (0: the caller sorts)."""
    done = int(0)
    if native != 0:
        done = radix_sort_cpp(n, end_bit, keys, values)
    status[0] = done


# The pairs sorted from the Gaussians' side, for the CPU (the rasteriser's layout: Gaussian g's pairs are the slots
# [offsets[g], offsets[g] + touched[g]), all with g's depth bits): the Gaussians with pairs are radix-sorted by their
# depth bits (stable, so ties keep index order), the pairs counted per tile, and each Gaussian's pairs then placed, in
# that depth order, at their tiles' next places. That is the order of the stable radix sort of the pairs' keys (within
# a tile by depth, ties by slot, as a Gaussian has one pair a tile and the slots grow with the index), bit for bit,
# and the tiles' [start, end) fall out of the counts; but it moves the slots once and no key, where the radix sort
# moved keys and slots four times (a 640x480 view's 43 key bits): 6.8 against 18 ms of sort and ranges for 765k pairs
# on one Intel thread. The scratch is the slots' second half and ``scratch`` (4 n + 2 + n_tiles ints: no allocation
# in the snippet, which Warp's CPU JIT may not link). Returns 0 (nothing written) where the layout does not hold (the
# Gaussians' slots not one after the other, m in all; a tile outside [0, n_tiles)) or the arrays are not contiguous or
# too short, and on CUDA.
_SORT_BY_GAUSSIAN_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
if (keys.strides[0] != 8 || values.strides[0] != 4 || keys.shape[0] < m || values.shape[0] < 2 * m
    || offsets.strides[0] != 4 || touched.strides[0] != 4 || offsets.shape[0] < n || touched.shape[0] < n
    || ranges.strides[0] != 8 || ranges.strides[1] != 4 || ranges.shape[0] < n_tiles || n_tiles < 1) return 0;
enum { DB = @DIGIT_BITS@, NB = 1 << DB, DP = (32 + DB - 1) / DB };
unsigned long long* K = (unsigned long long*)keys.data;
int* V = (int*)values.data;
int* V2 = V + m;
const int* off = (const int*)offsets.data;
const int* tt = (const int*)touched.data;
int* R = (int*)ranges.data;
// the layout: Gaussian g's pairs at [off[g], off[g] + tt[g]), one after the other, m of them (else nothing written)
{
    long at = 0;
    for (int g = 0; g < n; ++g) {
        if (tt[g] < 0 || (tt[g] > 0 && off[g] != at)) return 0;
        at += tt[g];
    }
    if (at != m) return 0;
}
// the scratch: the Gaussians' depth bits and indices (twice, for the radix sort's passes), the tiles' counts
if (scratch.strides[0] != 4 || scratch.shape[0] < 4L * n + 2 + n_tiles) return 0;
unsigned* dk = (unsigned*)scratch.data;
int* gi = (int*)scratch.data + (2L * n + 1);
unsigned* tc = (unsigned*)scratch.data + (4L * n + 2);
// the pairs per tile (and that every tile is one of the n_tiles: else nothing is written)
for (int t = 0; t < n_tiles; ++t) tc[t] = 0;
for (int j = 0; j < m; ++j) {
    const unsigned long long t = K[j] >> 32;
    if (t >= (unsigned long long)n_tiles) return 0;
    tc[t]++;
}
// the Gaussians with pairs, by their depth bits (a stable LSD radix sort, the digits' counts in one read)
int nv = 0;
for (int g = 0; g < n; ++g)
    if (tt[g] > 0) { dk[nv] = (unsigned)(K[off[g]] & 0xffffffffULL); gi[nv] = g; ++nv; }
{
    unsigned cnt[DP * NB];      // 24 KB of stack at 11-bit digits
    for (int i = 0; i < DP * NB; ++i) cnt[i] = 0;
    for (int v = 0; v < nv; ++v)
        for (int p = 0; p < DP; ++p) cnt[p * NB + ((dk[v] >> (DB * p)) & (NB - 1))]++;
    for (int p = 0; p < DP; ++p) {
        unsigned sum = 0;
        for (int r = 0; r < NB; ++r) { const unsigned c = cnt[p * NB + r]; cnt[p * NB + r] = sum; sum += c; }
    }
    unsigned* d0 = dk; unsigned* d1 = dk + nv;
    int* g0 = gi; int* g1 = gi + nv;
    for (int p = 0; p < DP; ++p) {
        unsigned* c = cnt + p * NB;
        for (int v = 0; v < nv; ++v) {
            const unsigned o = c[(d0[v] >> (DB * p)) & (NB - 1)]++;
            d1[o] = d0[v];
            g1[o] = g0[v];
        }
        unsigned* td = d0; d0 = d1; d1 = td;
        int* tg = g0; g0 = g1; g1 = tg;
    }
    if (g0 != gi) for (int v = 0; v < nv; ++v) gi[v] = g0[v];   // the sorted order at gi[0 .. nv)
}
// each tile's [start, end) ([0, 0) where it has none, as tile_ranges leaves it), the counts becoming the cursors
{
    unsigned start = 0;
    for (int t = 0; t < n_tiles; ++t) {
        const unsigned c = tc[t];
        R[2 * t] = c > 0 ? (int)start : 0;
        R[2 * t + 1] = c > 0 ? (int)(start + c) : 0;
        tc[t] = start;
        start += c;
    }
}
// the values moved, the keys left as they were (the rasteriser reads no key after the sort)
for (int v = 0; v < nv; ++v) {
    const int g = gi[v];
    const int j1 = off[g] + tt[g];
    for (int j = off[g]; j < j1; ++j) V2[tc[K[j] >> 32]++] = V[j];
}
__builtin_memcpy(V, V2, 4L * m);
return 1;
#else
return 0;
#endif
""".replace("@DIGIT_BITS@", str(SORT_DIGIT_BITS))


@wp.func_native(_SORT_BY_GAUSSIAN_CPP)
def sort_by_gaussian_cpp(n: int, m: int, n_tiles: int, offsets: wp.array(dtype=wp.int32),
                         touched: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int64),
                         values: wp.array(dtype=wp.int32), ranges: wp.array2d(dtype=wp.int32),
                         scratch: wp.array(dtype=wp.int32)) -> int:
    """The per-Gaussian sort above of the first ``m`` pairs' values of ``n`` Gaussians, in place, and the tiles'
    ranges. Returns 1, or 0 (nothing written) where it does not apply."""
    ...


@wp.kernel
def sort_by_gaussian_cpu(n: int, m: int, n_tiles: int, offsets: wp.array(dtype=wp.int32),
                         touched: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int64),
                         values: wp.array(dtype=wp.int32), ranges: wp.array2d(dtype=wp.int32),
                         scratch: wp.array(dtype=wp.int32), native: int, status: wp.array(dtype=wp.int32)):
    """One thread: :func:`sort_by_gaussian_cpp` (``native`` 1), its result in ``status[0]`` (0: the caller sorts)."""
    done = int(0)
    if native != 0:
        done = sort_by_gaussian_cpp(n, m, n_tiles, offsets, touched, keys, values, ranges, scratch)
    status[0] = done


def sort_by_gaussian_scratch(n: int, n_tiles: int) -> int:
    """Ints of scratch :func:`sort_pairs_and_ranges` needs on the CPU for ``n`` Gaussians and ``n_tiles`` tiles."""
    return 4 * n + 2 + n_tiles


def sort_pairs_and_ranges(keys, slots, n_pairs: int, n_tiles: int, pair_offsets, tiles_touched, ranges, *,
                          scratch=None) -> int:
    """Sort the rasteriser's pair slots by (tile, depth) in place (stable) and fill ``ranges`` (tiles, 2) with each
    tile's [start, end) ([0, 0) for a tile without pairs), for pairs laid out as :func:`emit_pairs` writes them
    (Gaussian g's at the slots ``[pair_offsets[g], pair_offsets[g] + tiles_touched[g])``, each with g's depth bits).
    On the CPU by :data:`_SORT_BY_GAUSSIAN_CPP` (the slots moved once, the keys left as they were; returns 2), else,
    or where that declines, :func:`sort_pairs` and :func:`launch_tile_ranges` (the keys sorted too; returns what
    :func:`sort_pairs` returns): the same slots and ranges bit for bit (the twin:
    :func:`mgso_kernels.reference.splat.sorted_pairs`). ``scratch``: an int32 array of at least
    :func:`sort_by_gaussian_scratch` ints on the CPU (made here when None)."""
    if ranges.dtype is not wp.int32 or ranges.ndim != 2 or ranges.shape[1] != 2 or ranges.shape[0] < n_tiles:
        raise TypeError(f"sort_pairs_and_ranges: ranges must be an int32 array of shape ({n_tiles}, 2)")
    device = keys.device
    if device.is_cpu and n_pairs > 0:
        from .raster_tile import native_flag

        n = tiles_touched.shape[0]
        if scratch is None:
            scratch = wp.empty(sort_by_gaussian_scratch(n, n_tiles), dtype=wp.int32, device=device)
        status = wp.zeros(1, dtype=wp.int32, device=device)   # a call's own (renders may sort on two threads)
        wp.launch(sort_by_gaussian_cpu, dim=1, inputs=[n, n_pairs, n_tiles, pair_offsets, tiles_touched, keys, slots,
                                                        ranges, scratch, native_flag(), status], device=device)
        if int(status.numpy()[0]) == 1:
            return 2
    ran = sort_pairs(keys, slots, n_pairs, n_tiles)
    launch_tile_ranges(keys, n_pairs, ranges[:n_tiles], str(device))
    return ran


def sort_pairs(keys, slots, n_pairs: int, n_tiles: int) -> int:
    """Radix-sort the first ``n_pairs`` (key, slot) pairs by (tile, depth), in place (stable): on the CPU in C++
    (:func:`radix_sort_cpp`; ``raster_tile.use_native(False)`` switches it off), else, or where that declines,
    with ``wp.utils.radix_sort_pairs``; the same order either way. Returns 1 where the C++ sort ran, else 0."""
    if n_pairs <= 0:
        return 0
    end_bit = tile_key_bits(n_tiles)
    device = keys.device
    if device.is_cpu:
        from .raster_tile import native_flag

        status = wp.zeros(1, dtype=wp.int32, device=device)   # a call's own (renders may sort on two threads)
        wp.launch(radix_sort_pairs_cpu, dim=1, inputs=[n_pairs, end_bit, keys, slots, native_flag(), status],
                  device=device)
        if int(status.numpy()[0]) == 1:
            return 1
    wp.utils.radix_sort_pairs(keys, slots, n_pairs, begin_bit=0, end_bit=end_bit)
    return 0


def launch_tile_ranges(keys, n_pairs: int, ranges, device: str, threads: int | None = None,
                       min_chunk: int = 4096) -> None:
    """Zero ``ranges`` (tiles, 2) and fill each tile's [start, end) in the sorted keys."""
    from ..runtime import launch_split

    if ranges.dtype is not wp.int32 or ranges.ndim != 2 or ranges.shape[1] != 2:
        raise TypeError("tile_ranges: ranges must be an int32 array of shape (tiles, 2)")
    ranges.zero_()
    if n_pairs > 0:
        launch_split(tile_ranges, n_pairs, [keys, n_pairs, ranges], device, threads=threads, min_chunk=min_chunk)
