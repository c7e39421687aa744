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
:func:`radix_sort_cpp`, the same stable LSD radix sort in C++ with the digits' histograms in one pass, 8-bit digits:
about twice as fast); both key and value arrays need ``2 * count`` capacity. Radix sort is stable, so depth ties keep
Gaussian index order.

**Values** are pair *slots*: slot ``p`` is the pair's position before sorting, so a Gaussian's slots are the
contiguous range ``[offset_g, offset_g + tiles_touched_g)``. The backward pass accumulates per-pair gradients
into slots and then sums each Gaussian's contiguous range: no cross-thread atomics on the CPU, deterministic.
``pair_gauss[p]`` is the Gaussian of slot ``p``.

Twin: :func:`mgso_kernels.reference.splat.tile_pairs` (brute-force ellipse-rectangle test over every tile).
"""

from __future__ import annotations

import warp as wp

from .camera import TILE_SIZE, Camera
from .common import vec8

wp.set_module_options({"enable_backward": False})

__all__ = ["count_tiles", "emit_pairs", "tile_ranges", "ellipse_row_span", "sort_pairs", "radix_sort_pairs_cpu"]

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


@wp.kernel
def count_tiles(
    offset: int,
    splats: wp.array(dtype=vec8),  # [N] per Gaussian: mean (px), conic, opacity, exp(-a), cut-off r2
    radii: wp.array(dtype=wp.int32),  # [N] 0 = culled
    cam: Camera,
    tiles_touched: wp.array(dtype=wp.int32),  # [N] out
):
    g = offset + wp.tid()
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
    tiles_touched[g] = n


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
    g = offset + wp.tid()
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
                       min_chunk: int = 4096) -> None:
    """``tiles_touched[g]`` = number of tiles Gaussian g is listed in (0 if culled)."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = splats.shape[0]
    for name, a, dt in (("splats", splats, vec8), ("radii", radii, wp.int32),
                        ("tiles_touched", tiles_touched, wp.int32)):
        check_array(a, name, dt, (n,), device)
    launch_split(count_tiles, n, [splats, radii, cam, tiles_touched], device, threads=threads, min_chunk=min_chunk)


def launch_emit_pairs(splats, depths, radii, pair_offsets, cam: Camera, keys, slots, pair_gauss, n_pairs: int,
                      device: str, threads: int | None = None, min_chunk: int = 4096) -> None:
    """Write the unsorted keys, slots and slot->Gaussian map; keys/slots need ``2 * n_pairs`` capacity."""
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
    launch_split(emit_pairs, n, [splats, depths, radii, pair_offsets, cam, keys, slots, pair_gauss], device,
                 threads=threads, min_chunk=min_chunk)


# A stable LSD radix sort of (int64 key, int32 value) pairs over bits [0, end_bit), 8 bits a pass, the passes'
# histograms counted in one read of the keys, the second halves of the arrays as the scratch (Warp's
# radix_sort_pairs takes the same layout and gives the same order: both stable over the same digits). 4.9 against
# 9.4 ms for 245k pairs, 20 against 41-43 ms for 972k (one Zen 3 thread; docs/rasteriser.md). Returns 0 where the
# arrays are not contiguous, and on CUDA.
_SORT_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
if (keys.strides[0] != 8 || values.strides[0] != 4 || keys.shape[0] < 2 * n || values.shape[0] < 2 * n
    || end_bit < 1 || end_bit > 64) return 0;
unsigned long long* k0 = (unsigned long long*)keys.data;
int* v0 = (int*)values.data;
unsigned long long* k1 = k0 + n;
int* v1 = v0 + n;
const int passes = (end_bit + 7) / 8;
unsigned cnt[8][256];
for (int p = 0; p < passes; ++p)
    for (int r = 0; r < 256; ++r) cnt[p][r] = 0;
for (int i = 0; i < n; ++i) {
    const unsigned long long k = k0[i];
    for (int p = 0; p < passes; ++p) cnt[p][(k >> (8 * p)) & 255]++;
}
for (int p = 0; p < passes; ++p) {
    unsigned sum = 0;
    for (int r = 0; r < 256; ++r) { const unsigned c = cnt[p][r]; cnt[p][r] = sum; sum += c; }
}
for (int p = 0; p < passes; ++p) {
    const int shift = 8 * p;
    unsigned* c = cnt[p];
    for (int i = 0; i < n; ++i) {
        const unsigned o = c[(k0[i] >> shift) & 255]++;
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
"""


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
