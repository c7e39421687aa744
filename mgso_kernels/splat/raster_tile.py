"""Tile-sorted alpha blending with one thread per 16x16 tile, forward and backward, written for CPU SIMD (Warp module).

The CPU default of :class:`mgso_kernels.splat.Rasterizer` (``pixels_per_thread=256``). Same rules and outputs as
:mod:`mgso_kernels.splat.raster` / :mod:`mgso_kernels.splat.raster_bwd` (3DGS's: ``alpha = min(0.99, opacity
exp(power))``, skip ``alpha < 1/255``, stop without accumulating when ``T (1 - alpha) < 1e-4``), organised so that
the compiler turns the per-pixel work into vector instructions:

- **A thread blends a whole tile.** Its state (transmittance, colour, depth, last contributor per pixel; in the
  backward also the upstream gradients and the running sums) lives in 16x16 local matrices. For each Gaussian of
  the tile's depth-sorted list the thread first computes the rows the Gaussian's cut-off ellipse reaches (one
  ``sqrt``), so rows it misses cost nothing; per reached row the exact column span inside the ellipse is a bit mask
  (:func:`row_span_mask`).
- **The 16 pixels of a row are 16 SIMD lanes.** The lane loops have a constant trip count, Warp unrolls them, and
  LLVM's SLP vectoriser packs the 16 identical lane bodies into AVX-512 / AVX2 operations; everything in a lane body
  is branch-free (masks are 0/1 floats and ``wp.where`` selects). ``exp`` is :func:`exp_lane`, a polynomial with an
  exponent bit trick, because a libm call cannot be vectorised (measured: 5.6-6.1 ns per ``expf`` call against
  1.45 ns per lane vectorised on this machine).
- **Per-pixel ``exp(power)``, not a recurrence along the row**: every lane computes its own power
  ``-0.5 a dx^2 - 0.5 c dy^2 - b dx dy``, in the same operations in the forward and the backward
  (:func:`lane_power`), so both passes make the same skip and stop decisions bit for bit.
- **Backward sums per (tile, Gaussian), not per row.** The running gradient sums are 16-lane vectors over all rows
  of the tile; ``dx`` is a per-lane constant and ``dy`` a per-row constant, so the conic and mean gradients need
  only ``sum v_pow``, ``sum dy v_pow`` and ``sum dy^2 v_pow`` per lane, weighted by ``dx`` and ``dx^2`` once at
  the end. One 12-vector per (tile, Gaussian) pair is added to the pair's slot (no cross-thread atomics on the
  CPU, as in :mod:`~mgso_kernels.splat.raster_bwd`; the gather and everything after are shared).

Compiler options of this module: ``-mprefer-vector-width=512`` (let the vectoriser use AVX-512 where the CPU has it;
LLVM's default on these CPUs is 256 bits) and a larger SLP scheduling budget (the backward's lane body is larger than
LLVM's default budget; without it the backward ran 2.3x slower). Both only change code generation, not results.

Measured on this project's 2-core Xeon (single thread, thread CPU time, synthetic room, ``profiles/splat_raster.py``
scenes; docs/rasteriser.md): forward blend 2.4x and backward blend 1.5-1.75x faster than the 16-pixel row kernels.
Results agree with the row kernels to float rounding (the row kernels use an ``exp`` recurrence along the row).
Intended for the CPU: on CUDA a thread per tile leaves the GPU idle, use ``pixels_per_thread=1`` there (the default).

On the CPU each kernel first hands its tile to a C++ snippet (:mod:`~mgso_kernels.splat.raster_tile_cpp`, 1.5-1.8x
faster: the spans of a Gaussian's rows 8 or 16 rows a vector, a tile row's 16 pixels a vector with AVX-512, no
masked stores, FMAs) that computes the same values to float rounding and the same stop decisions (tested); the
Warp code below it runs where the snippet declines (CUDA) or is switched off (:func:`use_native`, for tests and
profiles). Each launch writes which ran into :func:`status_buffer`.

Twin: :func:`mgso_kernels.reference.splat.render` and :func:`~mgso_kernels.reference.splat.render_vjp`.
"""

from __future__ import annotations

import warp as wp

from ..dynamic import take_item
from ..runtime import native_flag, use_native  # the one switch of the CPU's C++ snippets (re-exported here)
from . import raster_tile_cpp
from .camera import TILE_SIZE, Camera
from .common import ALPHA_MAX, ALPHA_MIN, T_MIN, vec8, vec16, vec16i

wp.set_module_options({
    "enable_backward": False,
    "cpu_compiler_flags": "-march=native -mprefer-vector-width=512 -mllvm -slp-schedule-budget=1000000",
})

__all__ = ["TILE_PIXELS", "use_native", "native_flag", "native_lanes", "native_masks", "status_buffer", "exp_lane", "rasterize_forward_tile", "rasterize_alpha_tile", "rasterize_alpha_depth_tile",
           "rasterize_backward_tile", "rasterize_backward_tile_noabs", "rasterize_backward_tile_narrow",
           "rasterize_backward_tile_noabs_narrow", "BWD_ACC_ROWS"]

TILE_PIXELS = TILE_SIZE * TILE_SIZE  # ``pixels_per_thread`` value that selects these kernels

mat16 = wp.types.matrix(shape=(TILE_SIZE, TILE_SIZE), dtype=wp.float32)
mat32x8 = wp.types.matrix(shape=(2 * TILE_SIZE, TILE_SIZE // 2), dtype=wp.float32)   # half rows: see the forward
vec8f = wp.types.vector(length=8, dtype=wp.float32)

LANES = wp.constant(TILE_SIZE)
LOG2E = wp.constant(1.4426950408889634)
LN2_HI = wp.constant(0.693359375)  # ln 2 split in two (Cody-Waite): n * LN2_HI is exact for |n| < 2^9
LN2_LO = wp.constant(-2.12194440e-4)
BWD_ACC_ROWS = 11  # running-sum rows of the backward (see rasterize_backward_tile)

_status: dict = {}


def status_buffer(dim: int, device) -> wp.array:
    """The int32 array of ``dim`` flags a tile kernel writes (1 where its C++ snippet did the tile), one per
    (device, size), reused from launch to launch; read it after a launch to see which code ran."""
    key = (str(device), int(dim))
    if key not in _status:
        _status[key] = wp.zeros(int(dim), dtype=wp.int32, device=device)
    return _status[key]


@wp.func_native(raster_tile_cpp.lanes_probe())
def _lanes_cpp() -> int:
    """The lane width this module's tile snippets compiled at (16 or 8; 0 where they do not run: CUDA)."""
    ...


@wp.kernel
def _lanes_kernel(out: wp.array(dtype=wp.int32)):
    out[0] = _lanes_cpp()


@wp.func_native(raster_tile_cpp.masks_probe())
def _masks_cpp() -> int:
    """1 where this module's tile snippets take their lanes' decisions in AVX-512 mask registers, else 0."""
    ...


@wp.kernel
def _masks_kernel(out: wp.array(dtype=wp.int32)):
    out[0] = _masks_cpp()


def native_masks(device="cpu") -> bool:
    """Whether the tile snippets as compiled on ``device`` keep their lanes' decisions (which pixels take a Gaussian,
    which stop) in AVX-512 mask registers (16 lanes with AVX-512F, 8 with AVX-512VL); False where they keep them in
    0/1 float lanes (no AVX-512, or ``MGSO_TILE_MASKS=0``) or do not run (CUDA). Either way the same outputs bit for
    bit."""
    out = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(_masks_kernel, dim=1, inputs=[out], device=device)
    return bool(out.numpy()[0])


def native_lanes(device="cpu") -> int:
    """The lane width of the tile snippets as compiled on ``device``: 16 (a whole tile row in an AVX-512 vector), 8
    (half a row, AVX2 or the portable vector code), 0 where the snippets do not run (CUDA)."""
    out = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(_lanes_kernel, dim=1, inputs=[out], device=device)
    return int(out.numpy()[0])


@wp.func_native("""
union { int i; float f; } u;
u.i = (n + 127) << 23;
return u.f;
""")
def pow2i(n: int) -> float:
    """2^n for an integer n in [-126, 127] (the float with exponent field n + 127): the bit trick every vector exp
    uses. Plain C++, valid for the CPU and CUDA compilers."""
    ...


@wp.func
def exp_lane(x: float) -> float:
    """exp(x) for x <= 0 (x below -87 gives about 1.6e-38): ``x = n ln2 + f`` with ``|f| <= ln2 / 2``, degree-7
    Taylor polynomial in f, times 2^n. Max relative error 9.3e-8 (1.6 float32 ulp) over [-87, 0] (tested), like
    ``expf``; unlike a libm call it vectorises."""
    x = wp.max(x, -87.0)
    n = wp.floor(x * LOG2E + 0.5)
    f = x - n * LN2_HI - n * LN2_LO
    p = 1.0 + f * (1.0 + f * (0.5 + f * (0.16666667 + f * (0.041666668 + f * (0.008333334 + f * (
        0.0013888889 + f * 0.0001984127))))))
    return p * pow2i(int(n))


@wp.func
def lane_power(a: float, dx: float, cyy: float, bdy: float) -> float:
    """power = -0.5 a dx^2 + cyy - bdy dx with cyy = -0.5 c dy^2, bdy = b dy: the one expression both passes use."""
    return -0.5 * a * dx * dx + cyy - bdy * dx


@wp.func
def tile_of(slot: int, cam: Camera) -> wp.vec4i:
    """Thread slot -> (tile, x0, y0, nx + 32 ny): the tile of the interleaved order and its size inside the image."""
    tile = (slot * cam.tile_stride) % (cam.tiles_x * cam.tiles_y)
    ty = tile // cam.tiles_x
    tx = tile - ty * cam.tiles_x
    x0 = tx * LANES
    y0 = ty * LANES
    nx = wp.min(LANES, cam.width - x0)
    ny = wp.min(LANES, cam.height - y0)
    return wp.vec4i(tile, x0, y0, nx + 32 * ny)


@wp.func
def tile_rows(my: float, a: float, r2: float, det: float, fy0: float, ny: int) -> wp.vec2i:
    """Rows [lo, hi] of the tile (relative to its first row, clipped to [0, ny)) that the cut-off ellipse
    ``a dx^2 + 2 b dx dy + c dy^2 <= r2`` reaches: ``|dy| <= sqrt(r2 a / det)``; lo > hi: none."""
    ry = wp.sqrt(a * r2 / det)
    lo = wp.max(int(wp.ceil(my - ry - fy0)), 0)
    hi = wp.min(int(wp.floor(my + ry - fy0)), ny - 1)
    return wp.vec2i(lo, hi)


@wp.func
def row_span_mask(mx: float, a: float, b: float, r2: float, det: float, inv_a: float, dy: float, x0: int,
                  nx: int) -> int:
    """Bit k set iff column x0 + k (k < nx) of the row at ``dy`` lies inside the cut-off ellipse; 0 if none."""
    disc = a * r2 - det * dy * dy
    if disc < 0.0:
        return 0
    half = wp.sqrt(disc) * inv_a
    xc = mx - b * dy * inv_a
    lo = wp.max(int(wp.ceil(xc - half)) - x0, 0)
    hi = wp.min(int(wp.floor(xc + half)) - x0, nx - 1)
    if lo > hi:
        return 0
    return ((1 << (hi - lo + 1)) - 1) << lo


@wp.func
def lane_sum(v: vec16) -> float:
    """Sum of the 16 lanes as a tree (vectorises; a sequential sum would be 16 dependent adds)."""
    h = vec8f(0.0)
    for k in range(8):
        h[k] = v[k] + v[k + 8]
    q = wp.vec4(0.0)
    for k in range(4):
        q[k] = h[k] + h[k + 4]
    return (q[0] + q[2]) + (q[1] + q[3])


_CONSTS = {"ALPHA_MAX": 0.99, "ALPHA_MIN": 1.0 / 255.0, "T_MIN": 1.0e-4, "LOG2E": 1.4426950408889634,
           "LN2_HI": 0.693359375, "LN2_LO": -2.12194440e-4}


@wp.func_native(raster_tile_cpp.fill(raster_tile_cpp.FORWARD, _CONSTS))
def forward_tile_cpp(tile: int, x0: int, y0: int, nx: int, ny: int, ranges: wp.array2d(dtype=wp.int32),
                     splats: wp.array(dtype=vec8), splat_rgbz: wp.array(dtype=wp.vec4), background: wp.vec3,
                     rgb: wp.array3d(dtype=float), depth: wp.array2d(dtype=float), alpha: wp.array2d(dtype=float),
                     T_final: wp.array2d(dtype=float), n_contrib: wp.array2d(dtype=wp.int32), only_rgb: int) -> int:
    """:func:`rasterize_forward_tile`'s work for one tile in C++ (:mod:`~mgso_kernels.splat.raster_tile_cpp`): the
    same outputs to float rounding, the same stop decisions; ``only_rgb``: the colour alone (the other images are not
    written). Returns 1, or 0 (nothing written) where it does not apply."""
    ...


@wp.kernel
def rasterize_forward_tile(
    offset: int,
    cam: Camera,
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2] [start, end) into the sorted pairs
    splats: wp.array(dtype=vec8),  # [M] packed, sorted (mx, my, a, b, c, opacity, exp(-a), r2)
    splat_rgbz: wp.array(dtype=wp.vec4),  # [M] packed, sorted: r, g, b, depth
    background: wp.vec3,  # RGB
    rgb: wp.array3d(dtype=float),  # [H, W, 3] out
    depth: wp.array2d(dtype=float),  # [H, W] out, sum w z (unnormalised)
    alpha: wp.array2d(dtype=float),  # [H, W] out, 1 - T_final
    T_final: wp.array2d(dtype=float),  # [H, W] out
    n_contrib: wp.array2d(dtype=wp.int32),  # [H, W] out, 1 + tile-list position of the last accumulated Gaussian
    only_rgb: int,  # 1: rgb alone (depth, alpha, T_final and n_contrib may be placeholders, not written)
    native: int,  # 1: the C++ snippet where it applies (the CPU); 0: this kernel's own code
    status: wp.array(dtype=wp.int32),  # [threads] out: 1 where the snippet did the tile
):
    i = offset + wp.tid()
    tl = tile_of(i, cam)
    tile = tl[0]
    x0 = tl[1]
    y0 = tl[2]
    nx = tl[3] % 32
    ny = tl[3] // 32
    if native != 0:
        if forward_tile_cpp(tile, x0, y0, nx, ny, ranges, splats, splat_rgbz, background, rgb, depth, alpha, T_final,
                            n_contrib, only_rgb) != 0:
            status[i] = 1
            return
    status[i] = 0
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    # the tile's state as half rows: row r's pixels 0-7 at 2r, 8-15 at 2r + 1; a Gaussian's span inside a row is
    # often narrower than 8 pixels, and a half it misses is not blended at all
    T = mat32x8(1.0)
    Cr = mat32x8(0.0)
    Cg = mat32x8(0.0)
    Cb = mat32x8(0.0)
    D = mat32x8(0.0)
    L = mat32x8(0.0)  # last accumulated list position + 1 (a float: exact below 2^24)
    row_done = vec16i(0)  # bit k of row r: pixel stopped
    full = (1 << nx) - 1
    rows_left = ny
    fy0 = float(y0)
    fx0 = float(x0)
    for j in range(start, end):
        s = splats[j]
        mx = s[0]
        my = s[1]
        a = s[2]
        b = s[3]
        c = s[4]
        op = s[5]
        r2 = s[7]
        det = a * c - b * b
        inv_a = 1.0 / a
        rows = tile_rows(my, a, r2, det, fy0, ny)
        col = splat_rgbz[j]
        pos = float(j - start + 1)
        dx0 = fx0 - mx
        for r in range(rows[0], rows[1] + 1):
            done = row_done[r]
            if done == full:
                continue
            dy = fy0 + float(r) - my
            m = row_span_mask(mx, a, b, r2, det, inv_a, dy, x0, nx) & ~done
            if m == 0:
                continue
            cyy = -0.5 * c * dy * dy
            bdy = b * dy
            newly = int(0)
            for h in range(2):
                mh = (m >> (8 * h)) & 255
                if mh != 0:
                    q = 2 * r + h
                    Tr = T[q]
                    Crr = Cr[q]
                    Cgr = Cg[q]
                    Cbr = Cb[q]
                    Dr = D[q]
                    Lr = L[q]
                    nh = int(0)
                    for k in range(8):
                        dx = dx0 + float(8 * h + k)     # as the 16-lane rows did: the same images bit for bit
                        al = wp.min(ALPHA_MAX, op * exp_lane(lane_power(a, dx, cyy, bdy)))
                        ok = wp.where(al >= ALPHA_MIN, float((mh >> k) & 1), 0.0)
                        Tk = Tr[k]
                        Tn = Tk * (1.0 - al)
                        stop = wp.where(Tn < T_MIN, ok, 0.0)
                        acc = ok - stop
                        w = acc * al * Tk
                        Crr[k] = Crr[k] + w * col[0]
                        Cgr[k] = Cgr[k] + w * col[1]
                        Cbr[k] = Cbr[k] + w * col[2]
                        Dr[k] = Dr[k] + w * col[3]
                        Tr[k] = wp.where(acc > 0.0, Tn, Tk)
                        Lr[k] = wp.where(acc > 0.0, pos, Lr[k])
                        nh = nh | (int(stop) << k)
                    T[q] = Tr
                    Cr[q] = Crr
                    Cg[q] = Cgr
                    Cb[q] = Cbr
                    D[q] = Dr
                    L[q] = Lr
                    newly = newly | (nh << (8 * h))
            if newly != 0:
                done = done | newly
                row_done[r] = done
                if done == full:
                    rows_left -= 1
        if rows_left == 0:
            break
    for r in range(ny):
        y = y0 + r
        for k in range(nx):
            x = x0 + k
            q = 2 * r + k // 8
            kk = k % 8
            Tk = T[q, kk]
            rgb[y, x, 0] = Cr[q, kk] + Tk * background[0]
            rgb[y, x, 1] = Cg[q, kk] + Tk * background[1]
            rgb[y, x, 2] = Cb[q, kk] + Tk * background[2]
            if only_rgb == 0:
                depth[y, x] = D[q, kk]
                alpha[y, x] = 1.0 - Tk
                T_final[y, x] = Tk
                n_contrib[y, x] = int(L[q, kk])


@wp.kernel
def rasterize_forward_tile_dynamic(
    offset: int,  # the chunk's index (launch_split's offset)
    shares: wp.array(dtype=wp.int64),  # each chunk's range of tile slots, taken from both ends (mgso_kernels.dynamic)
    n_slots: int,
    cam: Camera,
    ranges: wp.array2d(dtype=wp.int32),
    splats: wp.array(dtype=vec8),
    splat_rgbz: wp.array(dtype=wp.vec4),
    background: wp.vec3,
    rgb: wp.array3d(dtype=float),
    depth: wp.array2d(dtype=float),
    alpha: wp.array2d(dtype=float),
    T_final: wp.array2d(dtype=float),
    n_contrib: wp.array2d(dtype=wp.int32),
    only_rgb: int,
    status: wp.array(dtype=wp.int32),  # [slots] out: 1 where the snippet did the tile, 0 where it declined
):
    """:func:`rasterize_forward_tile`'s snippet, a chunk a core taking tile slots from ``shares``
    (:func:`mgso_kernels.dynamic.launch_dynamic`): the same outputs bit for bit. A tile the snippet declines is
    left undone with status 0 (the launcher then runs :func:`rasterize_forward_tile`)."""
    chunk = offset + wp.tid()
    chunks = shares.shape[0]
    for k in range(chunks):   # its own range, then the others' from their far end
        r = (chunk + k) % chunks
        i = take_item(shares, r, k)
        while i >= 0:
            tl = tile_of(i, cam)
            status[i] = forward_tile_cpp(tl[0], tl[1], tl[2], tl[3] % 32, tl[3] // 32, ranges, splats, splat_rgbz,
                                         background, rgb, depth, alpha, T_final, n_contrib, only_rgb)
            i = take_item(shares, r, k)


def _alpha_tile_kernel(with_depth: bool):
    """The coverage kernel, with or without the accumulated depth (``wp.static``: two compiled variants).

    3DGS's blend for the transmittance only (no colour, nothing saved for a backward pass), plus the coverage stop:
    a pixel also stops once the Gaussian it has just accumulated took its transmittance below ``t_stop``. With
    ``t_stop <= T_MIN`` (1e-4) that never happens and alpha (and depth) are the full render's bit for bit; with
    ``t_stop = 0.01`` alpha is exact wherever it is below 0.99 and at least 0.99 elsewhere, and the depth sum
    misses at most a weight of 0.01 (what a seeding's coverage test needs, for about 40 % less blending on a dense
    map; docs/seeding.md).
    """

    @wp.func_native(raster_tile_cpp.fill(raster_tile_cpp.ALPHA, dict(_CONSTS, DEPTH=int(with_depth))))
    def alpha_tile_cpp(tile: int, x0: int, y0: int, nx: int, ny: int, ranges: wp.array2d(dtype=wp.int32),
                       splats: wp.array(dtype=vec8), splat_rgbz: wp.array(dtype=wp.vec4), t_stop: float,
                       alpha: wp.array2d(dtype=float), depth: wp.array2d(dtype=float)) -> int:
        """:func:`rasterize_alpha_tile`'s work for one tile in C++: the same alpha (and depth) to float rounding.
        Returns 1, or 0 (nothing written) where it does not apply."""
        ...

    @wp.kernel
    def rasterize_alpha_tile(
        offset: int,
        cam: Camera,
        ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
        splats: wp.array(dtype=vec8),  # [M] packed, sorted
        splat_rgbz: wp.array(dtype=wp.vec4),  # [M] packed, sorted: depth in [3] (read only with depth)
        t_stop: float,  # the coverage stop (see above); <= T_MIN: the full render's rule only
        alpha: wp.array2d(dtype=float),  # [H, W] out, accumulated alpha = 1 - T_final
        depth: wp.array2d(dtype=float),  # [H, W] out with depth, sum w z (unnormalised); else not written
        native: int,  # 1: the C++ snippet where it applies (the CPU); 0: this kernel's own code
        status: wp.array(dtype=wp.int32),  # [threads] out: 1 where the snippet did the tile
    ):
        it = offset + wp.tid()
        tl = tile_of(it, cam)
        tile = tl[0]
        x0 = tl[1]
        y0 = tl[2]
        nx = tl[3] % 32
        ny = tl[3] // 32
        if native != 0:
            if alpha_tile_cpp(tile, x0, y0, nx, ny, ranges, splats, splat_rgbz, t_stop, alpha, depth) != 0:
                status[it] = 1
                return
        status[it] = 0
        T = mat16(1.0)
        D = mat16(0.0)
        row_done = vec16i(0)
        full = (1 << nx) - 1
        rows_left = ny
        fy0 = float(y0)
        fx0 = float(x0)
        for j in range(ranges[tile, 0], ranges[tile, 1]):
            s = splats[j]
            mx = s[0]
            my = s[1]
            a = s[2]
            b = s[3]
            c = s[4]
            op = s[5]
            r2 = s[7]
            det = a * c - b * b
            inv_a = 1.0 / a
            rows = tile_rows(my, a, r2, det, fy0, ny)
            z = float(0.0)
            if wp.static(with_depth):
                z = splat_rgbz[j][3]
            dx0 = fx0 - mx
            for r in range(rows[0], rows[1] + 1):
                done = row_done[r]
                if done == full:
                    continue
                dy = fy0 + float(r) - my
                m = row_span_mask(mx, a, b, r2, det, inv_a, dy, x0, nx) & ~done
                if m == 0:
                    continue
                cyy = -0.5 * c * dy * dy
                bdy = b * dy
                Tr = T[r]
                Dr = D[r]
                newly = int(0)
                for k in range(LANES):
                    dx = dx0 + float(k)
                    al = wp.min(ALPHA_MAX, op * exp_lane(lane_power(a, dx, cyy, bdy)))
                    ok = wp.where(al >= ALPHA_MIN, float((m >> k) & 1), 0.0)
                    Tk = Tr[k]
                    Tn = Tk * (1.0 - al)
                    stop = wp.where(Tn < T_MIN, ok, 0.0)
                    acc = ok - stop
                    if wp.static(with_depth):
                        Dr[k] = Dr[k] + acc * al * Tk * z
                    Tr[k] = wp.where(acc > 0.0, Tn, Tk)
                    covered = wp.where(Tn < t_stop, acc, 0.0)  # accumulated, and now below the coverage stop
                    newly = newly | (int(stop + covered) << k)
                T[r] = Tr
                if wp.static(with_depth):
                    D[r] = Dr
                if newly != 0:
                    done = done | newly
                    row_done[r] = done
                    if done == full:
                        rows_left -= 1
            if rows_left == 0:
                break
        for r in range(ny):
            for k in range(nx):
                alpha[y0 + r, x0 + k] = 1.0 - T[r, k]
                if wp.static(with_depth):
                    depth[y0 + r, x0 + k] = D[r, k]

    @wp.kernel
    def rasterize_alpha_tile_dynamic(
        offset: int,  # the chunk's index (launch_split's offset)
        shares: wp.array(dtype=wp.int64),  # each chunk's range of tile slots, taken from both ends (mgso_kernels.dynamic)
        n_slots: int,
        cam: Camera,
        ranges: wp.array2d(dtype=wp.int32),
        splats: wp.array(dtype=vec8),
        splat_rgbz: wp.array(dtype=wp.vec4),
        t_stop: float,
        alpha: wp.array2d(dtype=float),
        depth: wp.array2d(dtype=float),
        status: wp.array(dtype=wp.int32),  # [slots] out: 1 where the snippet did the tile, 0 where it declined
    ):
        """The snippet of the kernel above, a chunk a core taking tile slots from ``shares`` (see
        :func:`rasterize_forward_tile_dynamic`)."""
        chunk = offset + wp.tid()
        chunks = shares.shape[0]
        for k in range(chunks):   # its own range, then the others' from their far end
            r = (chunk + k) % chunks
            i = take_item(shares, r, k)
            while i >= 0:
                tl = tile_of(i, cam)
                status[i] = alpha_tile_cpp(tl[0], tl[1], tl[2], tl[3] % 32, tl[3] // 32, ranges, splats, splat_rgbz, t_stop,
                                           alpha, depth)
                i = take_item(shares, r, k)

    return rasterize_alpha_tile, rasterize_alpha_tile_dynamic


rasterize_alpha_tile, rasterize_alpha_tile_dynamic = _alpha_tile_kernel(False)
# the coverage alpha and the accumulated depth
rasterize_alpha_depth_tile, rasterize_alpha_depth_tile_dynamic = _alpha_tile_kernel(True)


def _backward_tile_cpp(with_absgrad: bool, narrow: bool = False):
    @wp.func_native(raster_tile_cpp.fill(raster_tile_cpp.BACKWARD, dict(_CONSTS, ABSGRAD=int(with_absgrad)),
                                         lanes=8 if narrow else None))
    def backward_tile_cpp(tile: int, x0: int, y0: int, nx: int, ny: int, ranges: wp.array2d(dtype=wp.int32),
                          splats: wp.array(dtype=vec8), splat_rgbz: wp.array(dtype=wp.vec4),
                          slots: wp.array(dtype=wp.int32), background: wp.vec3, T_final: wp.array2d(dtype=float),
                          n_contrib: wp.array2d(dtype=wp.int32), v_rgb: wp.array3d(dtype=float),
                          v_depth: wp.array2d(dtype=float), v_alpha: wp.array2d(dtype=float), use_depth: int,
                          use_alpha: int, pair_grads: wp.array(dtype=vec16)) -> int:
        """:func:`rasterize_backward_tile`'s work for one tile in C++: the same sums to float rounding. Returns 1,
        or 0 (nothing written) where it does not apply."""
        ...

    return backward_tile_cpp


_backward_tile_cpp_abs = _backward_tile_cpp(True)
_backward_tile_cpp_noabs = _backward_tile_cpp(False)
_backward_tile_cpp_abs_narrow = _backward_tile_cpp(True, narrow=True)
_backward_tile_cpp_noabs_narrow = _backward_tile_cpp(False, narrow=True)


def _backward_tile_kernel(with_absgrad: bool, narrow: bool = False):
    """The backward tile kernel, with or without the AbsGS sums, its snippet at the CPU's lanes or at 8 (``narrow``:
    the same values bit for bit; faster on small images, ``raster_bwd.NARROW_BACKWARD_PIXELS``): four variants."""
    backward_tile_cpp = ((_backward_tile_cpp_abs_narrow if narrow else _backward_tile_cpp_abs) if with_absgrad
                         else (_backward_tile_cpp_noabs_narrow if narrow else _backward_tile_cpp_noabs))

    @wp.kernel
    def rasterize_backward_tile(
        offset: int,
        cam: Camera,
        ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
        splats: wp.array(dtype=vec8),  # [M] packed, sorted (forward's)
        splat_rgbz: wp.array(dtype=wp.vec4),  # [M] r, g, b, depth
        slots: wp.array(dtype=wp.int32),  # [M] sorted pair slots
        background: wp.vec3,
        T_final: wp.array2d(dtype=float),  # [H, W] forward's
        n_contrib: wp.array2d(dtype=wp.int32),  # [H, W] forward's
        v_rgb: wp.array3d(dtype=float),  # [H, W, 3] upstream
        v_depth: wp.array2d(dtype=float),  # [H, W] upstream
        v_alpha: wp.array2d(dtype=float),  # [H, W] upstream
        use_depth: int,  # 0: v_depth ignored (may be a dummy)
        use_alpha: int,  # 0: v_alpha ignored
        acc_rows: int,  # BWD_ACC_ROWS, passed at run time so that the running sums stay in (L1) memory
        pair_grads: wp.array(dtype=vec16),  # [M] in/out (zeroed by the caller), indexed by slot
        native: int,  # 1: the C++ snippet where it applies (the CPU); 0: this kernel's own code
        status: wp.array(dtype=wp.int32),  # [threads] out: 1 where the snippet did the tile
    ):
        it = offset + wp.tid()
        tl = tile_of(it, cam)
        tile = tl[0]
        x0 = tl[1]
        y0 = tl[2]
        nx = tl[3] % 32
        ny = tl[3] // 32
        if native != 0:
            if backward_tile_cpp(tile, x0, y0, nx, ny, ranges, splats, splat_rgbz, slots, background, T_final,
                                 n_contrib, v_rgb, v_depth, v_alpha, use_depth, use_alpha, pair_grads) != 0:
                status[it] = 1
                return
        status[it] = 0
        start = ranges[tile, 0]
        # per pixel: T (rebuilt back to front from T_final), S (sum over the Gaussians behind of w g, plus the
        # background's and alpha's share), upstream gradients, n_contrib
        T = mat16(0.0)
        S = mat16(0.0)
        GR = mat16(0.0)
        GG = mat16(0.0)
        GB = mat16(0.0)
        VD = mat16(0.0)
        NC = mat16(0.0)
        row_max = vec16i(0)  # largest n_contrib of each row
        n_max = int(0)
        for r in range(ny):
            y = y0 + r
            rm = int(0)
            for k in range(nx):
                x = x0 + k
                Tf = T_final[y, x]
                T[r, k] = Tf
                gr = v_rgb[y, x, 0]
                gg = v_rgb[y, x, 1]
                gb = v_rgb[y, x, 2]
                GR[r, k] = gr
                GG[r, k] = gg
                GB[r, k] = gb
                vA = float(0.0)
                if use_depth != 0:
                    VD[r, k] = v_depth[y, x]
                if use_alpha != 0:
                    vA = v_alpha[y, x]
                S[r, k] = Tf * (background[0] * gr + background[1] * gg + background[2] * gb - vA)
                nc = n_contrib[y, x]
                NC[r, k] = float(nc)
                rm = wp.max(rm, nc)
            row_max[r] = rm
            n_max = wp.max(n_max, rm)
        # running sums of one Gaussian over the tile, per lane: 0 v_pow, 1 dy v_pow, 2 dy^2 v_pow, 3 v_alpha_raw E
        # (opacity), 4-6 w G (colour), 7 w v_depth, 8-9 |per-pixel d/d mean2d| (AbsGS), 10 w (the blending weight);
        # rows acc_rows.. unused
        ACC = mat16(0.0)
        fy0 = float(y0)
        fx0 = float(x0)
        for jj in range(n_max):
            i = n_max - 1 - jj  # position in the tile list, back to front
            fi = float(i)
            j = start + i
            s = splats[j]
            mx = s[0]
            my = s[1]
            a = s[2]
            b = s[3]
            c = s[4]
            op = s[5]
            r2 = s[7]
            det = a * c - b * b
            inv_a = 1.0 / a
            rows = tile_rows(my, a, r2, det, fy0, ny)
            col = splat_rgbz[j]
            dx0 = fx0 - mx
            for q in range(acc_rows):
                ACC[q] = vec16(0.0)
            hit = int(0)
            for r in range(rows[0], rows[1] + 1):
                if row_max[r] <= i:
                    continue
                dy = fy0 + float(r) - my
                m = row_span_mask(mx, a, b, r2, det, inv_a, dy, x0, nx)
                if m == 0:
                    continue
                hit = 1
                cyy = -0.5 * c * dy * dy
                bdy = b * dy
                Tr = T[r]
                Sr = S[r]
                GRr = GR[r]
                GGr = GG[r]
                GBr = GB[r]
                VDr = VD[r]
                NCr = NC[r]
                span = vec16(0.0)
                for k in range(LANES):
                    span[k] = float((m >> k) & 1)
                for k in range(LANES):
                    dx = dx0 + float(k)
                    e = exp_lane(lane_power(a, dx, cyy, bdy))
                    raw = op * e
                    al = wp.min(ALPHA_MAX, raw)
                    ok = wp.where(NCr[k] > fi, wp.where(al >= ALPHA_MIN, span[k], 0.0), 0.0)
                    inv = 1.0 / (1.0 - al)
                    Tk = Tr[k] * inv  # transmittance in front of this Gaussian
                    w = al * Tk
                    gi = col[0] * GRr[k] + col[1] * GGr[k] + col[2] * GBr[k] + col[3] * VDr[k]
                    v_al = Tk * gi - Sr[k] * inv
                    okb = ok > 0.0
                    Tr[k] = wp.where(okb, Tk, Tr[k])
                    Sr[k] = wp.where(okb, Sr[k] + w * gi, Sr[k])
                    v_raw = wp.where(raw <= ALPHA_MAX, v_al, 0.0) * ok  # no gradient through the 0.99 clamp
                    v_pow = v_raw * raw
                    wk = w * ok
                    ACC[0, k] = ACC[0, k] + v_pow
                    ACC[1, k] = ACC[1, k] + dy * v_pow
                    ACC[2, k] = ACC[2, k] + dy * dy * v_pow
                    ACC[3, k] = ACC[3, k] + v_raw * e
                    ACC[4, k] = ACC[4, k] + wk * GRr[k]
                    ACC[5, k] = ACC[5, k] + wk * GGr[k]
                    ACC[6, k] = ACC[6, k] + wk * GBr[k]
                    ACC[7, k] = ACC[7, k] + wk * VDr[k]
                    ACC[10, k] = ACC[10, k] + wk
                    if wp.static(with_absgrad):
                        mp = wp.abs(v_pow)
                        ACC[8, k] = ACC[8, k] + wp.abs(a * dx + bdy) * mp
                        ACC[9, k] = ACC[9, k] + wp.abs(b * dx + c * dy) * mp
                T[r] = Tr
                S[r] = Sr
            if hit != 0:
                # sum_px dx v_pow, sum dx^2 v_pow, sum dx dy v_pow: dx is the lane's constant
                dxv = vec16(0.0)
                for k in range(LANES):
                    dxv[k] = dx0 + float(k)
                V = ACC[0]
                P1 = lane_sum(wp.cw_mul(dxv, V))
                P2 = lane_sum(wp.cw_mul(wp.cw_mul(dxv, dxv), V))
                Q1 = lane_sum(ACC[1])
                Q2 = lane_sum(wp.cw_mul(dxv, ACC[1]))
                Q3 = lane_sum(ACC[2])
                g = vec16(
                    a * P1 + b * Q1, b * P1 + c * Q1, -0.5 * P2, -Q2, -0.5 * Q3, lane_sum(ACC[3]), lane_sum(ACC[4]),
                    lane_sum(ACC[5]), lane_sum(ACC[6]), lane_sum(ACC[7]), lane_sum(ACC[8]), lane_sum(ACC[9]),
                    lane_sum(ACC[10]), 0.0, 0.0, 0.0)
                wp.atomic_add(pair_grads, slots[j], g)

    @wp.kernel
    def rasterize_backward_tile_dynamic(
        offset: int,  # the chunk's index (launch_split's offset)
        shares: wp.array(dtype=wp.int64),  # each chunk's range of tile slots, taken from both ends (mgso_kernels.dynamic)
        n_slots: int,
        cam: Camera,
        ranges: wp.array2d(dtype=wp.int32),
        splats: wp.array(dtype=vec8),
        splat_rgbz: wp.array(dtype=wp.vec4),
        slots: wp.array(dtype=wp.int32),
        background: wp.vec3,
        T_final: wp.array2d(dtype=float),
        n_contrib: wp.array2d(dtype=wp.int32),
        v_rgb: wp.array3d(dtype=float),
        v_depth: wp.array2d(dtype=float),
        v_alpha: wp.array2d(dtype=float),
        use_depth: int,
        use_alpha: int,
        acc_rows: int,  # unused (the Warp code's; the same inputs as the kernel above)
        pair_grads: wp.array(dtype=vec16),  # [M] in/out (zeroed by the caller), indexed by slot
        status: wp.array(dtype=wp.int32),  # [slots] out: 1 where the snippet did the tile, 0 where it declined
    ):
        """The snippet of the kernel above, a chunk a core taking tile slots from ``shares`` (see
        :func:`rasterize_forward_tile_dynamic`): a tile's pairs are its own, so the sums are the static split's bit
        for bit."""
        chunk = offset + wp.tid()
        chunks = shares.shape[0]
        for k in range(chunks):   # its own range, then the others' from their far end
            r = (chunk + k) % chunks
            i = take_item(shares, r, k)
            while i >= 0:
                tl = tile_of(i, cam)
                status[i] = backward_tile_cpp(tl[0], tl[1], tl[2], tl[3] % 32, tl[3] // 32, ranges, splats, splat_rgbz,
                                              slots, background, T_final, n_contrib, v_rgb, v_depth, v_alpha, use_depth,
                                              use_alpha, pair_grads)
                i = take_item(shares, r, k)

    return rasterize_backward_tile, rasterize_backward_tile_dynamic


rasterize_backward_tile, rasterize_backward_tile_dynamic = _backward_tile_kernel(True)
# AbsGS sums skipped (absgrad = 0)
rasterize_backward_tile_noabs, rasterize_backward_tile_noabs_dynamic = _backward_tile_kernel(False)
# the same with the snippet at 8 lanes (half a tile row a vector) where the CPU has 16
rasterize_backward_tile_narrow, rasterize_backward_tile_narrow_dynamic = _backward_tile_kernel(True, narrow=True)
rasterize_backward_tile_noabs_narrow, rasterize_backward_tile_noabs_narrow_dynamic = _backward_tile_kernel(
    False, narrow=True)


def launch_tiles(kernel, dynamic_kernel, dim: int, inputs: list, device, *, threads: int | None = None,
                 min_chunk: int = 1) -> None:
    """Launch a tile kernel over its ``dim`` tile slots: ``kernel(offset, *inputs, native, status)`` split over the
    cores by :func:`~mgso_kernels.runtime.launch_split`, or, on the CPU with the snippets on, where more than one
    chunk would run and :func:`mgso_kernels.dynamic.use_dynamic` is on, ``dynamic_kernel(offset, shares, dim,
    *inputs, status)``: each chunk takes its own range's slots, then what the others have left
    (:mod:`mgso_kernels.dynamic`; the same outputs bit for bit). Should the snippet decline a tile there (arrays it
    does not take), the static kernel runs all of them again, with its Warp code where the snippet declines.
    ``min_chunk``: fewest slots a chunk."""
    from .. import dynamic
    from ..runtime import launch_split

    status = status_buffer(dim, device)
    if native_flag() and dynamic.launch_shared(dynamic_kernel, dim, inputs, status, device, threads=threads,
                                               min_items=min_chunk):
        return
    launch_split(kernel, dim, [*inputs, native_flag(), status], device, threads=threads, min_chunk=min_chunk)
