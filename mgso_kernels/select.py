"""DSO's pixel selection in nested cells (``PixelSelector::select``), one thread per ``4pot x 4pot`` cell.

A thread walks its cell as DSO's loops do: ``2pot`` cells, then ``pot`` cells, then pixels, row by row. A pixel
inside the margins (``4 <= x < w - 5``, ``4 <= y < h - 4``) is a level-0 candidate when its squared gradient beats
the block threshold ``t0`` (the 32x32 block's, times ``th_factor``), a level-1 candidate when the level-1 squared
gradient at ``(x/2, y/2)`` beats ``t1 = t0 * dw`` and a level-2 candidate when the level-2 one at ``(x/4, y/4)``
beats ``t2 = t1 * dw^2``; its score is ``|(gx, gy) . d|`` with ``d`` the random direction of its ``pot``, ``2pot`` or
``4pot`` cell (or the squared gradient of that level when directions are off). Each ``pot`` cell keeps its best
level-0 pixel (map value 1); a ``2pot`` cell with none keeps its best level-1 pixel (2), unless a level-0 pixel
came first; a ``4pot`` cell with neither keeps its best level-2 pixel (4). Ties go to the first pixel (strict
``>``). Every thread writes only its own cell, so a split launch equals a single one.

Float32 throughout and no fused multiply-add (``fuse_fp`` off), as the NumPy twin: the same pixels win.
Twin: :func:`mgso_kernels.reference.select.select_map`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import runtime

__all__ = ["DIRECTIONS", "BLOCK", "SelectParams", "select_cells", "select_map"]

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

# 16 unit directions at 11.25 degree steps over a half turn (DSO's table holds the same set in another order).
DIRECTIONS = np.stack([np.cos(np.arange(16) * np.pi / 16), np.sin(np.arange(16) * np.pi / 16)], axis=1)
BLOCK = 32  # threshold block size (DSO: 32x32)


@wp.struct
class SelectParams:
    pot: int  # DSO's potential: the smallest cell size
    th_factor: float  # on every threshold (DSO's initialiser: 2)
    dw1: float  # level-1 threshold factor (DSO setting_gradDownweightPerLevel = 0.75)
    dw2: float  # level-2 factor on the level-1 threshold (dw1^2)
    use_directions: int  # 1: score |grad . random direction|; 0: the squared gradient (DSO selectDirectionDistribution)


@wp.func
def _threshold(ths: wp.array2d(dtype=float), y: int, x: int) -> float:
    return ths[wp.min(y >> 5, ths.shape[0] - 1), wp.min(x >> 5, ths.shape[1] - 1)]


@wp.func
def _direction(dirs: wp.array2d(dtype=wp.int32), table: wp.array(dtype=wp.vec2), y: int, x: int,
               cell: int) -> wp.vec2:
    return table[dirs[wp.min(y / cell, dirs.shape[0] - 1), wp.min(x / cell, dirs.shape[1] - 1)]]


@wp.func
def _score(g: float, gd: wp.vec2, d: wp.vec2, use_directions: int) -> float:
    """A candidate's score: ``|grad . d|``, or its squared gradient ``g`` when directions are off."""
    if use_directions != 0:
        return wp.abs(gd[0] * d[0] + gd[1] * d[1])
    return g


@wp.func
def _beats(g: float, t: float, gd: wp.vec2, d: wp.vec2, use_directions: int, best: float) -> float:
    """The pixel's score when its squared gradient ``g`` passes the threshold ``t`` and the score beats ``best``
    (strictly: ties stay with the first pixel, as DSO), else -1 (scores are never negative)."""
    if g > t:
        dn = _score(g, gd, d, use_directions)
        if dn > best:
            return dn
    return -1.0


@wp.func
def _level_sq(grad_sq: wp.array2d(dtype=float), y: int, x: int, shift: int) -> float:
    """The squared gradient of a coarser level at the level-0 pixel ``(x, y)`` (``shift``: the level)."""
    return grad_sq[wp.min(y >> shift, grad_sq.shape[0] - 1), wp.min(x >> shift, grad_sq.shape[1] - 1)]


@wp.kernel
def select_cells(offset: int,
                 grad_sq0: wp.array2d(dtype=float),  # [h, w] level-0 squared gradient
                 dI0: wp.array2d(dtype=wp.vec3),  # [h, w] level-0 (I, gx, gy)
                 grad_sq1: wp.array2d(dtype=float),  # [h1, w1] level 1
                 grad_sq2: wp.array2d(dtype=float),  # [h2, w2] level 2
                 ths: wp.array2d(dtype=float),  # [h // 32, w // 32] block thresholds (squared)
                 dir2: wp.array2d(dtype=wp.int32),  # direction index (0-15) per pot cell
                 dir3: wp.array2d(dtype=wp.int32),  # per 2pot cell
                 dir4: wp.array2d(dtype=wp.int32),  # per 4pot cell
                 table: wp.array(dtype=wp.vec2),  # [16] DIRECTIONS
                 params: SelectParams,
                 out: wp.array2d(dtype=wp.int8)):  # [h, w] out (zeroed): 0, 1, 2 or 4
    cell = offset + wp.tid()
    h = grad_sq0.shape[0]
    w = grad_sq0.shape[1]
    pot = params.pot
    c4 = 4 * pot
    cells_x = (w + c4 - 1) / c4
    y4 = (cell / cells_x) * c4
    x4 = (cell - (cell / cells_x) * cells_x) * c4
    best4 = int(-1)  # pixel index; -2: a finer level already took a pixel in this 4pot cell
    val4 = float(0.0)
    d4 = _direction(dir4, table, y4, x4, c4)
    for y3 in range(0, wp.min(c4, h - y4), 2 * pot):
        for x3 in range(0, wp.min(c4, w - x4), 2 * pot):
            y34 = y3 + y4
            x34 = x3 + x4
            best3 = int(-1)
            val3 = float(0.0)
            d3 = _direction(dir3, table, y34, x34, 2 * pot)
            for y2 in range(0, wp.min(2 * pot, h - y34), pot):
                for x2 in range(0, wp.min(2 * pot, w - x34), pot):
                    y234 = y2 + y34
                    x234 = x2 + x34
                    best2 = int(-1)
                    val2 = float(0.0)
                    d2 = _direction(dir2, table, y234, x234, pot)
                    for y1 in range(0, wp.min(pot, h - y234)):
                        for x1 in range(0, wp.min(pot, w - x234)):
                            yf = y1 + y234
                            xf = x1 + x234
                            if xf < 4 or xf >= w - 5 or yf < 4 or yf >= h - 4:
                                continue
                            t0 = _threshold(ths, yf, xf) * params.th_factor
                            t1 = t0 * params.dw1
                            t2 = t1 * params.dw2
                            px = dI0[yf, xf]
                            gd = wp.vec2(px[1], px[2])
                            g0 = grad_sq0[yf, xf]
                            idx = yf * w + xf
                            ud = params.use_directions
                            s0 = _beats(g0, t0, gd, d2, ud, val2)
                            if s0 >= 0.0:
                                val2 = s0
                                best2 = idx
                                best3 = -2
                                best4 = -2
                            if best3 != -2:
                                s1 = _beats(_level_sq(grad_sq1, yf, xf, 1), t1, gd, d3, ud, val3)
                                if s1 >= 0.0:
                                    val3 = s1
                                    best3 = idx
                                    best4 = -2
                                if best4 != -2:
                                    s2 = _beats(_level_sq(grad_sq2, yf, xf, 2), t2, gd, d4, ud, val4)
                                    if s2 >= 0.0:
                                        val4 = s2
                                        best4 = idx
                    if best2 >= 0:
                        out[best2 / w, best2 - (best2 / w) * w] = wp.int8(1)
                        val3 = 1e10
            if best3 >= 0:
                out[best3 / w, best3 - (best3 / w) * w] = wp.int8(2)
                val4 = 1e10
    if best4 >= 0:
        out[best4 / w, best4 - (best4 / w) * w] = wp.int8(4)


def select_map(dxy0: np.ndarray, grad_sq, thresholds: np.ndarray, pot: int, dir2: np.ndarray, dir3: np.ndarray,
               dir4: np.ndarray, th_factor: float = 1.0, downweight: float = 0.75, use_directions: bool = True,
               device: str | None = None) -> np.ndarray:
    """DSO ``PixelSelector::select`` for one potential: a ``[H, W]`` int8 map, 0 or 1/2/4 (level 0/1/2).

    ``dxy0 [H, W, 2]`` level-0 gradient, or ``[H, W, 3]`` the pyramid's ``(I, dx, dy)`` (read in place: the gradient
    as a strided view of it was copied, 2 % of the odometry's CPU on KITTI), ``grad_sq`` levels 0-2 squared
    gradients (NumPy), ``thresholds`` ``[H // 32, W // 32]`` block thresholds (squared), ``dir2/dir3/dir4``
    direction indices (0-15) per ``pot`` / ``2pot`` / ``4pot`` cell (at least ``[ceil(H/c), ceil(W/c)]``).
    """
    device = runtime.device_or_cpu(device)
    if pot < 1:
        raise ValueError(f"pot must be >= 1, got {pot}")
    g0 = np.ascontiguousarray(grad_sq[0], np.float32)
    h, w = g0.shape
    dxy = np.asarray(dxy0)
    if dxy.shape == (h, w, 3):  # the pyramid's (I, dx, dy): read in place, no copy
        dI0 = np.ascontiguousarray(dxy, np.float32)
    elif dxy.shape == (h, w, 2):
        dI0 = np.zeros((h, w, 3), np.float32)
        dI0[..., 1:] = dxy
    else:
        raise ValueError(f"dxy0 must be [{h}, {w}, 2] (dx, dy) or [{h}, {w}, 3] (I, dx, dy), got {dxy.shape}")
    for name, d, c in (("dir2", dir2, pot), ("dir3", dir3, 2 * pot), ("dir4", dir4, 4 * pot)):
        if np.asarray(d).shape[0] < -(-h // c) or np.asarray(d).shape[1] < -(-w // c):
            raise ValueError(f"{name} must cover the {-(-h // c)}x{-(-w // c)} cells of size {c}, got "
                             f"{np.asarray(d).shape}")
    p = SelectParams()
    p.pot = int(pot)
    p.th_factor = float(np.float32(th_factor))
    p.dw1 = float(np.float32(downweight))
    p.dw2 = float(np.float32(downweight * downweight))
    p.use_directions = 1 if use_directions else 0
    # the launch only reads these: views of the NumPy arrays on the CPU (no copies of the images), copies on a GPU
    copy = not wp.get_device(device).is_cpu
    f = lambda a, dt: wp.array(np.ascontiguousarray(a, dtype=dt), device=device, copy=copy)  # noqa: E731
    out = wp.zeros((h, w), dtype=wp.int8, device=device)
    c4 = 4 * pot
    cells = (-(-h // c4)) * (-(-w // c4))
    runtime.launch_split(select_cells, cells,
                         [wp.array(g0, dtype=wp.float32, device=device, copy=copy),
                          wp.array(dI0, dtype=wp.vec3, device=device, copy=copy),
                          f(grad_sq[1], np.float32), f(grad_sq[2], np.float32), f(thresholds, np.float32),
                          f(dir2, np.int32), f(dir3, np.int32), f(dir4, np.int32),
                          wp.array(DIRECTIONS.astype(np.float32), dtype=wp.vec2, device=device), p, out],
                         device, min_chunk=256)
    return out.numpy()
