"""Densification and pruning of the Gaussian map: 3DGS's adaptive density control as a strategy object.

Shape of gsplat's ``strategy/default.py``: a frozen dataclass of hyperparameters (:class:`DefaultStrategy`, built
from :class:`mgso.config.DensifyConfig`), :meth:`~DefaultStrategy.initialize_state`, and two hooks the trainer
calls every step::

    strategy = DefaultStrategy(cfg.mapping.densify)
    state = strategy.initialize_state(seed=cfg.runtime.seed)
    for step in range(steps):
        want_stats = strategy.step_pre_backward(gmap, state, step)
        gmap.zero_grad()
        ... render, loss, backward into gmap.grads ...
        if want_stats:
            gmap.accumulate_stats(v_means2d_px, radii_px, width, height)   # or the rasteriser fills gmap.stats
        gmap.optimizer_step(step)
        result = strategy.step_post_backward(gmap, state, step)           # may change the rows: last

The strategy changes the map only through the map's operations (:meth:`GaussianMap.clone`, ``split``, ``remove``,
``reset_opacity``, ``reset_stats``), so parameters, Adam moments and statistics always move together. It returns
what it did as a :class:`RefineResult` value.

Rules (graphdeco 3DGS ``densify_and_prune`` / gsplat ``DefaultStrategy``; units in brackets):

- Refine at ``step > refine_start_step`` when ``step % refine_every == 0`` and ``step < refine_stop_step`` (0 = never
  stop), skipping ``pause_refine_after_reset`` steps after each opacity reset; also at the strategy's
  ``extra_refine_steps`` (none by default; the mapper's final refinement after an unrefined stream adds one).
- Mean screen-space gradient ``g = grad2d_sum / vis_count`` [NDC units: |dL/d mean_ndc| = |(gx_px W/2, gy_px H/2)|,
  3DGS's threshold 0.0002 is in these units]. Gaussians visible in fewer than ``grow_min_views`` views since the last
  refine do not grow.
- Clone where ``g > grow_grad2d`` and max scale <= ``percent_dense`` x scene extent [world units]; split where
  ``g > grow_grad2d`` and the Gaussian is larger (into ``split_children`` children, scales / (0.8 x children)).
  Clones made in this refine are not split. ``grad_mode = absgrad``: both decisions use AbsGS's absolute gradient
  against ``grow_grad2d_abs`` (gsplat); ``absgs``: clone by ``g``, split by the absolute gradient against
  ``absgs_split_grad2d`` (the AbsGS paper's rule).
- If the map has no room for every candidate, the ones with the largest gradient (relative to their threshold) grow
  first; the rest are counted in ``RefineResult.skipped_capacity`` (grow the map with ``reserve`` to avoid it).
- Prune opacity < ``prune_opacity``; after the first opacity reset interval (``step > reset_every``) also max scale >
  ``prune_scale3d`` x scene extent and, if ``prune_screen_px > 0``, a screen radius above it [pixels]. Without
  opacity resets (``reset_every = 0``: MGSO's mapper) there is no first reset, so no size prune: 3DGS prunes big
  Gaussians once a reset has made them earn their opacity back, and the mapper's scene extent, taken from camera
  centres that hardly move in a handheld recording, is no measure of the scene's size (docs/mapping.md, "The
  size prune needs a reset"). With ``prune_weight_px > 0`` also a Gaussian in view in at least
  ``prune_weight_views`` views since the last refine whose blending weight summed over each view's pixels
  (``stats.weight_max``, full-resolution pixels) stayed below it: hidden behind opaque Gaussians in every view, or
  too faint to show (not in 3DGS; later 3DGS pruning work scores Gaussians by their blending weights over all views
  at once). Gaussians younger than ``prune_min_age`` steps are kept.
- After a refine the rows are put in the Z-order of their means (``sort_spatially``; not in 3DGS): a view then
  culls whole runs of rows, which the CPU's per-Gaussian kernels pass over.
- Statistics are reset after every refine. Every ``reset_every`` steps (while refining is on) opacities are clamped
  to ``reset_opacity_value`` and their Adam moments zeroed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from mgso.config import DensifyConfig
from mgso.mapping.gaussian_map import GaussianMap

__all__ = ["DefaultStrategy", "StrategyState", "RefineResult"]

_GRAD_MODES = ("grad", "absgrad", "absgs")


@dataclass(frozen=True)
class RefineResult:
    """What :meth:`DefaultStrategy.step_post_backward` did at one step."""

    step: int
    refined: bool = False               # a clone/split/prune pass ran
    opacity_reset: bool = False         # opacities were clamped
    cloned: int = 0                     # Gaussians copied
    split: int = 0                      # parents split (each became `split_children` Gaussians)
    pruned: int = 0                     # Gaussians removed, = sum of the three below
    pruned_opacity: int = 0             # ... for opacity < prune_opacity
    pruned_world: int = 0               # ... for max scale > prune_scale3d x extent (and not the above)
    pruned_screen: int = 0              # ... for screen radius > prune_screen_px (and none of the above)
    pruned_weight: int = 0              # ... for a blending weight below prune_weight_px in every view (and none above)
    skipped_capacity: int = 0           # grow candidates left out because the map was full
    clamped_aspect: int = 0             # Gaussians whose longest axes were shortened to max_aspect x the shortest
    n_before: int = 0
    n_after: int = 0


@dataclass
class StrategyState:
    """Mutable running state of a strategy (the statistics themselves live in the map)."""

    rng: np.random.Generator            # draws split children
    refines: int = 0                    # refine passes so far
    last_reset_step: int = -1           # step of the last opacity reset, -1 = none


@dataclass(frozen=True)
class DefaultStrategy:
    """3DGS adaptive density control; hyperparameters are the fields of :class:`mgso.config.DensifyConfig`."""

    cfg: DensifyConfig = field(default_factory=DensifyConfig)
    # steps that refine besides the schedule (while refining is on): the mapper's first refinement of a final
    # refinement that follows an unrefined stream (mapping.mapper.final_refine_after)
    extra_refine_steps: frozenset = frozenset()

    def __post_init__(self):
        c = self.cfg
        problems = []
        if c.refine_every < 1:
            problems.append(f"refine_every must be >= 1, got {c.refine_every}")
        if c.reset_every < 0 or c.refine_stop_step < 0 or c.refine_start_step < 0:
            problems.append("reset_every, refine_start_step and refine_stop_step must be >= 0")
        if c.grad_mode not in _GRAD_MODES:
            problems.append(f"grad_mode must be one of {_GRAD_MODES}, got {c.grad_mode!r}")
        if c.split_children < 2:
            problems.append(f"split_children must be >= 2, got {c.split_children}")
        if not 0.0 < c.reset_opacity_value < 1.0:
            problems.append(f"reset_opacity_value must be in (0, 1), got {c.reset_opacity_value}")
        if not 0.0 <= c.prune_opacity < 1.0:
            problems.append(f"prune_opacity must be in [0, 1), got {c.prune_opacity}")
        if c.max_aspect != 0 and not c.max_aspect >= 1:
            problems.append(f"max_aspect must be 0 (off) or >= 1, got {c.max_aspect}")
        for name in ("grow_grad2d", "grow_grad2d_abs", "absgs_split_grad2d", "percent_dense", "split_scale_factor",
                     "prune_scale3d", "prune_screen_px"):
            if getattr(c, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(c, name)}")
        if problems:
            raise ValueError("mapping.densify: " + "; ".join(problems))

    # ------------------------------------------------------------------------------------------ hooks
    def initialize_state(self, seed: int = 0) -> StrategyState:
        return StrategyState(rng=np.random.default_rng(seed))

    def is_active(self, step: int) -> bool:
        """Whether refining (and opacity resets) are still on at ``step``."""
        return self.cfg.refine_stop_step <= 0 or step < self.cfg.refine_stop_step

    def step_pre_backward(self, gmap: GaussianMap, state: StrategyState, step: int) -> bool:
        """Before the backward: returns whether this step's screen-space statistics are needed (so the trainer can
        skip computing and accumulating them once refining has stopped)."""
        return self.is_active(step)

    def is_refine_step(self, step: int) -> bool:
        c = self.cfg
        scheduled = step > c.refine_start_step and step % c.refine_every == 0
        if not self.is_active(step) or not (scheduled or step in self.extra_refine_steps):
            return False
        return c.reset_every <= 0 or step % c.reset_every >= c.pause_refine_after_reset

    def step_post_backward(self, gmap: GaussianMap, state: StrategyState, step: int,
                           scene_extent: float | None = None) -> RefineResult:
        """After the backward and the optimiser step: refine (grow, prune, reset statistics) and reset opacities
        when due. ``scene_extent`` [world units] defaults to ``gmap.scene_extent``."""
        c = self.cfg
        extent = float(gmap.scene_extent if scene_extent is None else scene_extent)
        res = RefineResult(step=step, n_before=gmap.n, n_after=gmap.n)
        if not self.is_active(step):
            return res
        if self.is_refine_step(step):
            cloned, split, skipped = self._grow(gmap, state, step, extent)
            p_opa, p_world, p_screen, p_weight = self._prune(gmap, step, extent)
            clamped = self.clamp_aspect(gmap)
            if c.sort_spatially:
                gmap.sort_spatially()
            gmap.reset_stats()
            state.refines += 1
            res = dataclasses.replace(res, refined=True, cloned=cloned, split=split, skipped_capacity=skipped,
                                      pruned=p_opa + p_world + p_screen + p_weight, pruned_opacity=p_opa,
                                      pruned_world=p_world, pruned_screen=p_screen, pruned_weight=p_weight,
                                      clamped_aspect=clamped)
        if c.reset_every > 0 and step > 0 and step % c.reset_every == 0:
            gmap.reset_opacity(c.reset_opacity_value)
            state.last_reset_step = step
            res = dataclasses.replace(res, opacity_reset=True)
        return dataclasses.replace(res, n_after=gmap.n)

    # ----------------------------------------------------------------------------------------- rules
    def grow_candidates(self, gmap: GaussianMap, extent: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Masks (clone, split) over the live rows and a priority (gradient / threshold) per row; no change."""
        c = self.cfg
        st = gmap.stats
        count = st.vis_count.numpy().astype(np.float64)
        denom = np.maximum(count, 1.0)
        grad = st.grad2d_sum.numpy().astype(np.float64) / denom
        absgrad = st.absgrad2d_sum.numpy().astype(np.float64) / denom
        seen = count >= max(1, c.grow_min_views)
        small = np.exp(gmap.log_scales.numpy().astype(np.float64)).max(axis=1) <= c.percent_dense * extent
        if c.grad_mode == "grad":
            clone_score = split_score = grad / max(c.grow_grad2d, 1e-30)
        elif c.grad_mode == "absgrad":
            clone_score = split_score = absgrad / max(c.grow_grad2d_abs, 1e-30)
        else:  # absgs
            clone_score = grad / max(c.grow_grad2d, 1e-30)
            split_score = absgrad / max(c.absgs_split_grad2d, 1e-30)
        clone = seen & small & (clone_score > 1.0)
        split = seen & ~small & (split_score > 1.0)
        priority = np.where(small, clone_score, split_score)
        return clone, split, priority

    def _grow(self, gmap: GaussianMap, state: StrategyState, step: int, extent: float) -> tuple[int, int, int]:
        c = self.cfg
        clone, split, priority = self.grow_candidates(gmap, extent)
        per_split = c.split_children - 1
        need = int(clone.sum()) + per_split * int(split.sum())
        room = gmap.capacity - gmap.n
        skipped = 0
        if need > room:
            cand = np.flatnonzero(clone | split)
            order = cand[np.argsort(-priority[cand], kind="stable")]
            cost = np.where(clone[order], 1, per_split)
            take = order[np.cumsum(cost) <= room]
            keep = np.zeros(gmap.n, bool)
            keep[take] = True
            skipped = len(cand) - len(take)
            clone &= keep
            split &= keep
        n_clone = gmap.clone(clone, step=step)
        split = np.concatenate([split, np.zeros(n_clone, bool)])   # this refine's clones are not split
        n_split = gmap.split(split, children=c.split_children, step=step, rng=state.rng,
                             scale_factor=c.split_scale_factor)
        return n_clone, n_split, skipped

    def prune_masks(self, gmap: GaussianMap, step: int, extent: float) -> tuple[np.ndarray, ...]:
        """Exclusive masks (low opacity, too big in the world, too big on screen, hidden or too faint to show) over the
        live rows; no change."""
        c = self.cfg
        logits = gmap.opacity_logits.numpy().astype(np.float64)
        low = 1.0 / (1.0 + np.exp(-logits)) < c.prune_opacity
        world = np.zeros_like(low)
        screen = np.zeros_like(low)
        if c.reset_every > 0 and step > c.reset_every:     # after the first opacity reset (3DGS, gsplat)
            world = np.exp(gmap.log_scales.numpy().astype(np.float64)).max(axis=1) > c.prune_scale3d * extent
            if c.prune_screen_px > 0:
                screen = gmap.stats.max_radius_px.numpy() > c.prune_screen_px
        faint = np.zeros_like(low)
        if c.prune_weight_px > 0:
            st = gmap.stats
            faint = (st.vis_count.numpy() >= c.prune_weight_views) & (st.weight_max.numpy() < c.prune_weight_px)
        if c.prune_min_age > 0:
            young = (step - gmap.created_step.numpy().astype(np.int64)) < c.prune_min_age
            low &= ~young
            world &= ~young
            screen &= ~young
            faint &= ~young
        world &= ~low
        screen &= ~(low | world)
        faint &= ~(low | world | screen)
        return low, world, screen, faint

    def clamp_aspect(self, gmap: GaussianMap) -> int:
        """Shorten every axis longer than ``max_aspect`` x the Gaussian's shortest one to that length (0 = off):
        needles, which views that disagree (a drifting odometry) stretch to fit one view, become discs. Returns how
        many Gaussians changed."""
        r = self.cfg.max_aspect
        if r <= 0 or gmap.n == 0:
            return 0
        ls = gmap.log_scales.numpy().reshape(gmap.n, 3)
        cap = ls.min(axis=1, keepdims=True) + np.float32(np.log(r))
        over = (ls > cap).any(axis=1)
        if over.any():
            gmap.log_scales.assign(np.minimum(ls, cap).astype(np.float32))
        return int(over.sum())

    def _prune(self, gmap: GaussianMap, step: int, extent: float) -> tuple[int, int, int, int]:
        low, world, screen, faint = self.prune_masks(gmap, step, extent)
        gmap.remove(low | world | screen | faint)
        return int(low.sum()), int(world.sum()), int(screen.sum()), int(faint.sum())
