"""Which pixels of a new keyframe become (immature) points: DSO's ``PixelSelector2``, vectorised in NumPy.

It runs once per keyframe. The steps, as in DSO:

1. **Adaptive thresholds.** The image is cut into 32x32 blocks; in each, a histogram of the integer gradient
   magnitude ``int(sqrt(dx^2 + dy^2))`` (clipped at 48) gives the median (``min_grad_hist_cut = 0.5``) plus
   ``min_grad_hist_add = 7``; the block thresholds are averaged over 3x3 neighbouring blocks and squared (they
   are compared with squared gradients).
2. **Selection in nested cells** of ``pot x pot``, ``2pot x 2pot`` and ``4pot x 4pot`` pixels (``pot``, DSO's
   *potential*, starts at 3): in each ``pot`` cell the pixel whose level-0 squared gradient exceeds the threshold
   and whose gradient projects most strongly onto a random direction is taken (level 0); a ``2pot`` cell with no
   such pixel takes the best pixel whose level-1 gradient (the 2x2-averaged image) exceeds ``0.75`` times the
   threshold (level 1); a ``4pot`` cell with neither takes the best at level 2 (threshold times ``0.75^3``). The
   random directions (one of 16, a seeded RNG per cell) spread the gradient directions of the selected points.
3. **Density control** (DSO ``makeMaps``). The count behaves like ``K / (pot + 1)^2``. With ``recursions_left``
   (DSO: 1) the selection is redone at the ideal potential when it found fewer than 1/1.25 or more than 4 times
   the wanted number; a selection more than 1/0.95 times too large is thinned at random to the wanted density.
   The ideal potential carries over to the next keyframe.

Differences from DSO, on purpose: DSO picks the random directions from a fixed table indexed by the running count
of selected points (a sequential dependency); here each cell draws its own direction from a seeded generator. The
thresholds of pixels right of / below the last whole 32x32 block use the nearest block (DSO reads past the row).
"""

from __future__ import annotations

import functools
import itertools
import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["PixelSelection", "PixelSelector", "DIRECTIONS", "block_thresholds", "select_map"]

log = logging.getLogger(__name__)

# 16 unit directions at 11.25 degree steps over a half turn (DSO's table holds the same set in another order).
DIRECTIONS = np.stack([np.cos(np.arange(16) * np.pi / 16), np.sin(np.arange(16) * np.pi / 16)], axis=1)

BLOCK = 32  # threshold block size (DSO: 32x32)
HIST_MAX = 48  # gradient magnitudes clipped here (DSO)


@dataclass(frozen=True)
class PixelSelection:
    """Selected pixels of one keyframe, in raster order (row by row)."""

    xy: np.ndarray  # [N, 2] int32 level-0 pixel (x, y)
    level: np.ndarray  # [N] int8: 0, 1 or 2, the level whose threshold the pixel passed (DSO type = 2**level)
    potential: int  # the cell size used for this selection
    num_candidates: int  # selected before the random thinning

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @property
    def dso_type(self) -> np.ndarray:
        """DSO's ``PixelSelectorStatus`` value (1, 2, 4) kept by an immature point as ``my_type``."""
        return (1 << self.level.astype(np.int32)).astype(np.int32)


@functools.lru_cache(maxsize=8)
def _block_codes(h: int, w: int) -> np.ndarray:
    """``block_index * 49`` per pixel of the whole 32x32 blocks; pixels outside ``1 <= x <= w-2, 1 <= y <= h-2``
    (not counted by DSO) go to a spare bin past the last block."""
    h32, w32 = h // BLOCK, w // BLOCK
    hb, wb = h32 * BLOCK, w32 * BLOCK
    code = ((np.arange(hb, dtype=np.int32) // BLOCK)[:, None] * w32
            + (np.arange(wb, dtype=np.int32) // BLOCK)[None, :]) * (HIST_MAX + 1)
    spare = h32 * w32 * (HIST_MAX + 1)
    code[0, :] = spare
    code[:, 0] = spare
    code[h - 1:, :] = spare
    code[:, w - 1:] = spare
    code.setflags(write=False)
    return code


def block_thresholds(grad_sq0: np.ndarray, hist_cut: float = 0.5, hist_add: float = 7.0) -> np.ndarray:
    """DSO ``makeHists``: smoothed squared gradient thresholds per 32x32 block, ``[H // 32, W // 32]``."""
    h, w = grad_sq0.shape
    h32, w32 = h // BLOCK, w // BLOCK
    if h32 < 1 or w32 < 1:
        raise ValueError(f"image {w}x{h} is smaller than one {BLOCK}x{BLOCK} threshold block")
    hb, wb = h32 * BLOCK, w32 * BLOCK
    nbins = h32 * w32 * (HIST_MAX + 1)
    g = np.sqrt(np.maximum(grad_sq0[:hb, :wb], 0))
    np.minimum(g, HIST_MAX, out=g)
    code = g.astype(np.int32)
    code += _block_codes(h, w)  # block * 49, and an extra bin for the pixels DSO does not count
    hist = np.bincount(code.ravel(), minlength=nbins + HIST_MAX + 1)[:nbins].reshape(h32 * w32, HIST_MAX + 1)
    total = hist.sum(axis=1)
    th = (total * hist_cut + 0.5).astype(np.int64)
    above = np.cumsum(hist, axis=1) > th[:, None]  # DSO computeHistQuantil: first bin where the count passes th
    quant = np.where(above.any(axis=1), np.argmax(above, axis=1), 90)
    ths = (quant + hist_add).astype(np.float64).reshape(h32, w32)
    pad = np.pad(ths, 1)
    cnt = np.pad(np.ones_like(ths), 1)
    s = sum(pad[1 + dy: 1 + dy + h32, 1 + dx: 1 + dx + w32] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
    n = sum(cnt[1 + dy: 1 + dy + h32, 1 + dx: 1 + dx + w32] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
    return (s / n) ** 2


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


class PixelSelector:
    """DSO's pixel selector with its state (the potential carried from one keyframe to the next).

    Owner: the front end; one per camera resolution. ``select`` takes the keyframe's pyramid levels 0-2 as
    interleaved ``(I, dx, dy)`` arrays (``ImagePyramid.numpy(l)``) and returns a :class:`PixelSelection`.
    """

    def __init__(self, width: int, height: int, *, min_grad_hist_cut: float = 0.5, min_grad_hist_add: float = 7.0,
                 grad_downweight_per_level: float = 0.75, select_direction_distribution: bool = True,
                 initial_potential: int = 3, seed: int = 0):
        if width < BLOCK or height < BLOCK:
            raise ValueError(f"pixel selection needs at least a {BLOCK}x{BLOCK} image, got {width}x{height}")
        if initial_potential < 1:
            raise ValueError(f"initial_potential must be >= 1, got {initial_potential}")
        self.width, self.height = int(width), int(height)
        self.hist_cut = float(min_grad_hist_cut)
        self.hist_add = float(min_grad_hist_add)
        self.downweight = float(grad_downweight_per_level)
        self.use_directions = bool(select_direction_distribution)
        self.potential = int(initial_potential)  # ONLY changed in select (DSO currentPotential)
        self._rng = np.random.default_rng(seed)

    def select(self, levels: Sequence[np.ndarray], density: float, recursions_left: int = 1,
               th_factor: float = 1.0, grad_sq: Sequence[np.ndarray] | None = None) -> PixelSelection:
        """Select about ``density`` pixels.

        ``levels``: at least three ``[H_l, W_l, 3]`` arrays ``(I, dx, dy)`` of pyramid levels 0, 1, 2 (level 0
        of ``width x height``). ``grad_sq``: optional squared gradients per level to threshold instead of
        ``dx^2 + dy^2`` (DSO weights them by the inverse response's slope when photometric calibration is on).
        ``th_factor`` scales every threshold (DSO's initializer uses 2).
        """
        if len(levels) < 3:
            raise ValueError(f"pixel selection needs pyramid levels 0-2, got {len(levels)} level(s)")
        l0 = np.asarray(levels[0])
        if l0.shape != (self.height, self.width, 3):
            raise ValueError(f"level 0 is {l0.shape}, expected ({self.height}, {self.width}, 3)")
        if not density > 0:
            raise ValueError(f"density must be > 0, got {density}")
        if grad_sq is None:
            grad_sq = [np.asarray(lv)[..., 1] ** 2 + np.asarray(lv)[..., 2] ** 2 for lv in levels[:3]]
        thresholds = block_thresholds(grad_sq[0], self.hist_cut, self.hist_add)
        return self._make_maps(l0[..., 1:3], grad_sq, thresholds, float(density), int(recursions_left),
                               float(th_factor))

    def _make_maps(self, dxy0, grad_sq, thresholds, density, recursions_left, th_factor) -> PixelSelection:
        pot = self.potential
        h, w = grad_sq[0].shape

        def dirs(cell):
            return self._rng.integers(0, 16, size=(-(-h // cell), -(-w // cell)))

        m = select_map(dxy0, grad_sq, thresholds, pot, dirs(pot), dirs(2 * pot), dirs(4 * pot), th_factor,
                       self.downweight, self.use_directions)
        have = int(np.count_nonzero(m))
        quotia = density / max(have, 1)
        K = have * (pot + 1) ** 2
        ideal = max(int(np.sqrt(K / density) - 1), 1)
        if recursions_left > 0 and quotia > 1.25 and pot > 1:
            self.potential = min(ideal, pot - 1)
            log.debug("pixel selector: %d of %g wanted at potential %d, retry with %d", have, density, pot,
                      self.potential)
            return self._make_maps(dxy0, grad_sq, thresholds, density, recursions_left - 1, th_factor)
        if recursions_left > 0 and quotia < 0.25:
            self.potential = max(ideal, pot + 1)
            log.debug("pixel selector: %d of %g wanted at potential %d, retry with %d", have, density, pot,
                      self.potential)
            return self._make_maps(dxy0, grad_sq, thresholds, density, recursions_left - 1, th_factor)
        ys, xs = np.nonzero(m)  # raster order
        lv = m[ys, xs]
        if quotia < 0.95:
            keep = self._rng.random(len(ys)) <= quotia
            ys, xs, lv = ys[keep], xs[keep], lv[keep]
        self.potential = ideal
        level = np.select([lv == 1, lv == 2], [0, 1], 2).astype(np.int8)
        return PixelSelection(np.stack([xs, ys], axis=1).astype(np.int32), level, pot, have)
