"""Which pixels of a new keyframe become (immature) points: DSO's ``PixelSelector2`` (the thresholds in NumPy, the
selection in nested cells a Warp kernel, :mod:`mgso_kernels.select`, whose twin is the vectorised NumPy version in
:mod:`mgso_kernels.reference.select`).

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
import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from mgso_kernels.select import BLOCK, DIRECTIONS, select_map

__all__ = ["PixelSelection", "PixelSelector", "DIRECTIONS", "block_thresholds", "select_map"]

log = logging.getLogger(__name__)

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


class PixelSelector:
    """DSO's pixel selector with its state (the potential carried from one keyframe to the next).

    Owner: the front end; one per camera resolution. ``select`` takes the keyframe's pyramid levels 0-2 as
    interleaved ``(I, dx, dy)`` arrays (``ImagePyramid.numpy(l)``) and returns a :class:`PixelSelection`.
    """

    def __init__(self, width: int, height: int, *, min_grad_hist_cut: float = 0.5, min_grad_hist_add: float = 7.0,
                 grad_downweight_per_level: float = 0.75, select_direction_distribution: bool = True,
                 initial_potential: int = 3, seed: int = 0, device: str | None = None):
        if width < BLOCK or height < BLOCK:
            raise ValueError(f"pixel selection needs at least a {BLOCK}x{BLOCK} image, got {width}x{height}")
        if initial_potential < 1:
            raise ValueError(f"initial_potential must be >= 1, got {initial_potential}")
        self.width, self.height = int(width), int(height)
        self.device = device  # where the selection kernel runs (None: the CPU)
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
        return self._make_maps(l0, grad_sq, thresholds, float(density), int(recursions_left),
                               float(th_factor))

    def _make_maps(self, dxy0, grad_sq, thresholds, density, recursions_left, th_factor) -> PixelSelection:
        pot = self.potential
        h, w = grad_sq[0].shape

        def dirs(cell):
            return self._rng.integers(0, 16, size=(-(-h // cell), -(-w // cell)))

        m = select_map(dxy0, grad_sq, thresholds, pot, dirs(pot), dirs(2 * pot), dirs(4 * pot), th_factor,
                       self.downweight, self.use_directions, device=self.device)
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
