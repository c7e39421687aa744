"""NumPy twin of :mod:`mgso_kernels.select`: DSO's selection in nested cells, vectorised over the image (the cell
layout ``[Y4, y3, y2, y1, X4, x3, x2, x1]`` of the image padded to a multiple of ``4 pot``; the argmax per cell runs
in DSO's scan order so ties go to the first pixel, as DSO's strict ``>``). Equal to DSO's nested loops
(``tests/tracking/test_pixel_selector.py``)."""

from __future__ import annotations

import itertools
from typing import Sequence

import numpy as np

from ..select import BLOCK, DIRECTIONS

__all__ = ["select_map"]


def _up(a: np.ndarray, f: int, h: int, w: int) -> np.ndarray:
    """``a[y // f, x // f]`` for ``y < h, x < w`` (edge-extended where ``a`` is short)."""
    ny, nx = -(-h // f), -(-w // f)
    if a.shape[0] < ny or a.shape[1] < nx:
        a = np.pad(a, ((0, max(0, ny - a.shape[0])), (0, max(0, nx - a.shape[1]))), mode="edge")
    return np.repeat(np.repeat(a[:ny, :nx], f, axis=0), f, axis=1)[:h, :w]


def _cell_argmax(a8: np.ndarray, red: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Per cell of ``a8 [Y4, y3, y2, y1, X4, x3, x2, x1]``: (any value > 0, index of the first maximum in the scan
    order given by the reduced dims ``red``). Results are ordered ``[Y4, X4, (y3, x3, (y2, x2))]``."""
    keep = [d for d in range(8) if d not in red]
    n = int(np.prod([a8.shape[d] for d in red]))
    if n <= 64:  # few slots: elementwise over strided views (NumPy reductions over short axes are slow)
        views = []
        for combo in itertools.product(*[range(a8.shape[d]) for d in red]):
            idx = [slice(None)] * 8
            for d, v in zip(red, combo):
                idx[d] = v
            views.append(a8[tuple(idx)])
        m = views[0].copy()
        for v in views[1:]:
            np.maximum(m, v, out=m)
        arg = np.zeros(m.shape, np.int64)
        for k in range(n - 1, -1, -1):
            arg[views[k] == m] = k
    else:
        t = a8.transpose(keep + list(red)).reshape([a8.shape[d] for d in keep] + [n])
        arg = t.argmax(axis=-1)
        m = np.take_along_axis(t, arg[..., None], axis=-1)[..., 0]
    # keep dims come as (Y4, [y3, [y2]], X4, [x3, [x2]]): interleave to (Y4, X4, y3, x3, y2, x2)
    half = len(keep) // 2
    order = [j for pair in zip(range(half), range(half, 2 * half)) for j in pair]
    return (m > 0).transpose(order), arg.transpose(order)


def select_map(dxy0: np.ndarray, grad_sq: Sequence[np.ndarray], thresholds: np.ndarray, pot: int,
               dir2: np.ndarray, dir3: np.ndarray, dir4: np.ndarray, th_factor: float = 1.0,
               downweight: float = 0.75, use_directions: bool = True) -> np.ndarray:
    """DSO ``PixelSelector::select`` for one potential: a ``[H, W]`` int8 map, 0 or 1/2/4 (level 0/1/2).

    ``dxy0 [H, W, 2]`` level-0 gradient, ``grad_sq`` levels 0-2 squared gradients, ``thresholds`` from
    :func:`block_thresholds`, ``dir2/dir3/dir4`` direction indices (0-15) per ``pot``/``2pot``/``4pot`` cell
    (at least ``[ceil(H/c), ceil(W/c)]``).

    Everything is computed in the cell layout ``[Y4, y3, y2, y1, X4, x3, x2, x1]`` of the image padded to a
    multiple of ``4 pot`` (a view), with per-cell directions broadcast; the argmax per cell runs in DSO's scan
    order so ties go to the first pixel as in DSO's strict ``>``.
    """
    h, w = grad_sq[0].shape
    c4 = 4 * pot
    Y4, X4 = -(-h // c4), -(-w // c4)
    hp, wpad = Y4 * c4, X4 * c4
    shape8 = (Y4, 2, 2, pot, X4, 2, 2, pot)

    def padded(a, dtype=np.float32):
        out = np.zeros((hp, wpad), dtype)
        out[:h, :w] = a
        return out.reshape(shape8)

    # level-1/2 thresholds are the level-0 block thresholds (blocks of 32 contain whole 2x2 and 4x4 cells), so
    # levels 1 and 2 are compared at their own resolution and only the boolean result is upsampled
    t0 = thresholds.astype(np.float32) * np.float32(th_factor)
    t1 = t0 * np.float32(downweight)
    t2 = t1 * np.float32(downweight * downweight)
    pass0 = padded(grad_sq[0] > _up(t0, BLOCK, h, w), bool)
    g1, g2 = grad_sq[1], grad_sq[2]
    pass1 = padded(_up(g1 > _up(t1, BLOCK // 2, *g1.shape), 2, h, w), bool)
    pass2 = padded(_up(g2 > _up(t2, BLOCK // 4, *g2.shape), 4, h, w), bool)
    valid = np.zeros((hp, wpad), bool)
    valid[4:h - 4, 4:w - 5] = True
    valid = valid.reshape(shape8)
    gx, gy = padded(dxy0[..., 0]), padded(dxy0[..., 1])

    gx2, gy2 = gx.reshape(hp, wpad), gy.reshape(hp, wpad)

    def along(dir_idx: np.ndarray, cell: int, fallback: np.ndarray) -> np.ndarray:
        """|gradient . direction of the pixel's cell| in the cell layout (4-D views, in-place arithmetic)."""
        if not use_directions:
            return padded(fallback)
        ny, nx = hp // cell, wpad // cell
        idx = np.pad(dir_idx, ((0, max(0, ny - dir_idx.shape[0])), (0, max(0, nx - dir_idx.shape[1]))),
                     mode="edge")[:ny, :nx]
        d = DIRECTIONS.astype(np.float32)[idx]  # [ny, nx, 2]
        out = gx2.reshape(ny, cell, nx, cell) * d[:, None, :, None, 0]
        out += gy2.reshape(ny, cell, nx, cell) * d[:, None, :, None, 1]
        np.abs(out, out=out)
        return out.reshape(shape8)

    s0 = along(dir2, pot, grad_sq[0])
    s1 = along(dir3, 2 * pot, _up(g1, 2, h, w))
    s2 = along(dir4, c4, _up(g2, 4, h, w))

    # candidate scores: s > 0 exactly for candidates (a candidate needs s > 0), 0 elsewhere
    has0, arg0 = _cell_argmax(s0 * (valid & pass0), (3, 7))  # pot cells: (y1, x1)
    has1, arg1 = _cell_argmax(s1 * (valid & pass1), (2, 6, 3, 7))  # 2pot cells: (y2, x2, y1, x1)
    has2, arg2 = _cell_argmax(s2 * (valid & pass2), (1, 5, 2, 6, 3, 7))  # 4pot cells
    any0_2 = has0.reshape(Y4, X4, 2, 2, 4).any(axis=-1)
    take1 = has1 & ~any0_2  # level 1: cells of 2pot with no level-0 candidate
    blocked = any0_2.reshape(Y4, X4, 4).any(axis=-1) | has1.reshape(Y4, X4, 4).any(axis=-1)
    take2 = has2 & ~blocked  # level 2: cells of 4pot with no level-0 and no level-1 candidate

    pp = pot * pot
    out = np.zeros((hp, wpad), np.int8)
    Y, X, y3, x3, y2, x2 = np.nonzero(has0)
    a = arg0[Y, X, y3, x3, y2, x2]
    out[Y * c4 + (2 * y3 + y2) * pot + a // pot, X * c4 + (2 * x3 + x2) * pot + a % pot] = 1
    Y, X, y3, x3 = np.nonzero(take1)
    a = arg1[Y, X, y3, x3]
    y2, x2, r = a // (2 * pp), (a // pp) % 2, a % pp
    out[Y * c4 + (2 * y3 + y2) * pot + r // pot, X * c4 + (2 * x3 + x2) * pot + r % pot] = 2
    Y, X = np.nonzero(take2)
    a = arg2[Y, X]
    y3, x3, y2, x2, r = a // (8 * pp), (a // (4 * pp)) % 2, (a // (2 * pp)) % 2, (a // pp) % 2, a % pp
    out[Y * c4 + (2 * y3 + y2) * pot + r // pot, X * c4 + (2 * x3 + x2) * pot + r % pot] = 4
    return out[:h, :w]
