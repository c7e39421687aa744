"""Training the Gaussian map on posed images: one step (:class:`TrainStep`) and the loop around it (:class:`Trainer`).

One training step on a view (a :class:`~mgso.mapping.views.TrainView`: image, pinhole camera, ``world_to_cam``,
optional mask, per-view exposure)::

    render (Rasterizer.forward)
      -> L1 + D-SSIM of exp(a) * render + b against the image (L1SSIMLoss; a, b = the view's exposure)
      -> backward (Rasterizer.backward), writing the gradients into the map's gradient buffers
      -> densification statistics (GaussianMap.accumulate_stats, 3DGS's NDC units), when the strategy wants them
      -> Adam on every Gaussian (GaussianMap.optimizer_step); Adam on the view's exposure (learn_exposure) and pose
         (refine_poses), each with its own per-view moments
      -> strategy.step_post_backward (clone / split / prune / opacity reset; may change the rows: last)

:class:`TrainStep` does exactly that and nothing else; MGSO's mapping thread calls it with its own choice of view and
pyramid level. :class:`Trainer` adds what ``mgso fit`` needs around it: a :class:`~mgso.mapping.views.ViewSet`, a
pluggable sampler, the Gaussian-pyramid schedule (Photo-SLAM: a view's first uses are at coarse levels), the scene
extent from the camera centres (3DGS's rule, floored), the step counter and rendering for evaluation.

Ownership: the :class:`~mgso.mapping.gaussian_map.GaussianMap` owns the parameters and Adam moments and is changed
only through its own operations (the step calls them); views own their exposure / pose state (changed by the step
only when learning them is on). The step owns its rasteriser, loss objects and the strategy's running state. Use
one :class:`TrainStep` per thread (the rasteriser's buffers are reused between calls).

Nothing here prints; results are values (:class:`StepResult`, :class:`TrainSummary`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import warp as wp

from mgso.camera import PinholeCamera
from mgso.config import MappingConfig
from mgso.geometry import se3_exp
from mgso.mapping.gaussian_map import GaussianMap, exposure_learning_rate, scene_extent_from_cameras
from mgso.mapping.strategy import DefaultStrategy, RefineResult, StrategyState
from mgso.mapping.views import RandomEpochSampler, TrainView, ViewSampler, ViewSet
from mgso_kernels import runtime
from mgso_kernels.loss import L1SSIMLoss
from mgso_kernels.splat import Rasterizer, make_camera

__all__ = ["StepResult", "TrainStep", "Trainer", "TrainSummary", "STAGES"]

log = logging.getLogger(__name__)

STAGES = ("render", "loss", "backward", "adam", "strategy")   # keys of StepResult.times
_EXPOSURE_EPS = 1e-8   # torch.optim.Adam's default eps, which 3DGS's exposure optimiser uses


@dataclass(frozen=True)
class StepResult:
    """What one training step did."""

    step: int                       # 0-based training step
    view_id: int
    level: int                      # pyramid level trained on (0 = full resolution)
    width: int                      # image size at that level, pixels
    height: int
    loss: float                     # (1 - lambda) L1 + lambda (1 - SSIM)
    l1: float
    ssim: float
    psnr: float | None              # of the exposure-corrected render (clamped to [0, 1]), when computed
    exposure: tuple[float, float]   # the view's (a, b) after the step
    num_gaussians: int              # after the strategy
    num_visible: int                # Gaussians with a screen radius > 0 in this view
    refine: RefineResult            # what the strategy did
    times: dict[str, float] = field(default_factory=dict)   # seconds per stage (STAGES)
    num_pairs: int = 0              # (tile, Gaussian) pairs the render blended (what bounds its cost)


@dataclass(frozen=True)
class TrainSummary:
    """What :meth:`Trainer.train` did."""

    steps: int                      # steps run in this call
    seconds: float                  # wall time of those steps
    losses: np.ndarray              # [steps] loss of each step
    last: StepResult | None
    times: dict[str, float]         # seconds per stage, summed over the steps

    @property
    def iterations_per_s(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else float("inf")


def masked_psnr(rendered: np.ndarray, target: np.ndarray, exposure: tuple[float, float] | None,
                mask: np.ndarray | None) -> float:
    """PSNR (dB) of ``exp(a) rendered + b`` (``exposure`` (a, b); None: as it is), clipped to [0, 1], against
    ``target`` (H, W, 3), over the pixels weighted by ``mask`` (H, W) (None: all); ``inf`` when equal."""
    r = rendered.astype(np.float64)
    if exposure is not None:
        r = math.exp(exposure[0]) * r + exposure[1]
    d = (np.clip(r, 0.0, 1.0) - target) ** 2
    if mask is not None:
        w = mask.astype(np.float64)[..., None]
        mse = float((d * w).sum() / max(3.0 * w.sum(), 1e-30))
    else:
        mse = float(d.mean())
    return 10.0 * math.log10(1.0 / mse) if mse > 0 else float("inf")


class TrainStep:
    """One training iteration on one view (see the module doc): the unit MGSO's mapper reuses.

    ``cfg``: the mapping section (``lambda_dssim``, ``densify``, ``train``; the map carries ``optim``).
    ``device``: Warp device (default: the runtime's). ``strategy``: densification policy (default
    ``DefaultStrategy(cfg.densify)``). ``rasterizer``: a :class:`Rasterizer` to use (default: a new one).
    ``seed``: the strategy's random state (split samples). ``timing=True`` synchronises a GPU after each stage so that
    :attr:`StepResult.times` are per stage (on the CPU launches are synchronous and the times are always exact).
    """

    def __init__(self, cfg: MappingConfig, device: str | None = None, *, strategy: DefaultStrategy | None = None,
                 rasterizer: Rasterizer | None = None, seed: int = 0, timing: bool = False):
        self.cfg = cfg
        self.device = runtime.device_or_cpu(device)
        self.rasterizer = rasterizer if rasterizer is not None else Rasterizer(self.device)
        self.strategy = strategy if strategy is not None else DefaultStrategy(cfg.densify)
        # ONLY changed by __call__ (through the strategy's hooks).
        self.strategy_state: StrategyState = self.strategy.initialize_state(seed)
        # AbsGS statistics only when the strategy reads them (DefaultStrategy's grad_mode "absgrad" / "absgs"; a
        # strategy without that setting gets them)
        self._wants_absgrad = getattr(getattr(self.strategy, "cfg", None), "grad_mode", "absgrad") != "grad"
        self.timing = bool(timing)
        self._sync = timing and not wp.get_device(self.device).is_cpu
        self._losses: dict[tuple[int, int], L1SSIMLoss] = {}
        bg = tuple(float(b) for b in cfg.train.background)
        if len(bg) != 3:
            raise ValueError(f"mapping.train.background must be 3 values (RGB), got {cfg.train.background}")
        self.background = bg

    # ------------------------------------------------------------------------------------------ helpers
    def loss_fn(self, height: int, width: int) -> L1SSIMLoss:
        """The loss object of this image size (scratch buffers made once per size)."""
        key = (int(height), int(width))
        if key not in self._losses:
            self._losses[key] = L1SSIMLoss(height, width, self.device, lambda_dssim=self.cfg.lambda_dssim)
        return self._losses[key]

    def sh_degree_at(self, gmap: GaussianMap, step: int) -> int:
        """SH degree in use at ``step``: one more every ``train.sh_degree_interval`` steps (3DGS)."""
        every = self.cfg.train.sh_degree_interval
        if every <= 0:
            return gmap.sh_degree
        return min(gmap.sh_degree, int(step) // every)

    def _clock(self, t0: float, times: dict, name: str) -> float:
        if self._sync:
            wp.synchronize_device(self.device)
        t = time.perf_counter()
        times[name] = t - t0
        return t

    @staticmethod
    def camera_struct(camera: PinholeCamera, world_to_cam: np.ndarray):
        """The rasteriser's camera for a pinhole ``camera`` at ``world_to_cam``."""
        return make_camera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, world_to_cam)

    # ----------------------------------------------------------------------------------------- the step
    def __call__(self, gmap: GaussianMap, view: TrainView, step: int, *, level: int = 0,
                 with_psnr: bool = False) -> StepResult:
        """Train ``gmap`` on ``view`` at pyramid ``level`` for one step (``step``: the 0-based global step, which
        drives the learning-rate schedules and the densification schedule). Does not change ``view.uses``."""
        if gmap.n == 0:
            raise ValueError("TrainStep: the map has no Gaussians (add initial points first)")
        tc = self.cfg.train
        times: dict[str, float] = {}
        t = time.perf_counter()
        image_wp, mask_wp = view.device_arrays(level, self.device)
        image_np, cam, mask_np = view.level(level)
        H, W = cam.height, cam.width
        camera = self.camera_struct(cam, view.world_to_cam)
        want_stats = self.strategy.step_pre_backward(gmap, self.strategy_state, step)
        p = gmap.float_params()
        out = self.rasterizer.forward(p.means, p.log_scales, p.quats, p.opacity_logits, p.sh, camera,
                                      self.background, sh_degree=self.sh_degree_at(gmap, step))
        t = self._clock(t, times, "render")

        use_exposure = tc.learn_exposure or bool(np.any(view.exposure != 0.0))
        exposure = (float(view.exposure[0]), float(view.exposure[1])) if use_exposure else None
        res = self.loss_fn(H, W)(out.rgb, image_wp, mask=mask_wp, exposure=exposure)
        psnr = masked_psnr(out.rgb.numpy(), image_np, exposure, mask_np) if with_psnr else None
        t = self._clock(t, times, "loss")

        v_depth = v_alpha = None
        if tc.depth_weight > 0 and view.depth_z is not None and len(view.depth_z):
            v_depth, v_alpha = self._depth_term(out, view, level, tc.depth_weight)
        g = self.rasterizer.backward(out, res.v_rendered_hw3, v_depth, v_alpha,
                                     into=gmap.float_grads(),   # into the map's buffers
                                     absgrad=want_stats and self._wants_absgrad)
        if want_stats:
            gmap.accumulate_stats(g.v_means2d.view(wp.vec2), g.radii, W, H,
                                  g.absgrad.view(wp.vec2) if self._wants_absgrad else None,
                                  weights=g.weights, weight_scale=4.0 ** level)   # full-resolution pixels
        radii = g.radii.numpy()
        num_visible = int(np.count_nonzero(radii))
        v_pose = g.v_pose.numpy().astype(np.float64) if tc.refine_poses and not view.fixed_pose else None
        t = self._clock(t, times, "backward")

        gmap.optimizer_step(step)
        o = gmap.optim
        if tc.learn_exposure:
            lr = exposure_learning_rate(o, step)
            view.exposure += view.exposure_adam.update(np.asarray(res.v_exposure), lr, o.beta1, o.beta2,
                                                       _EXPOSURE_EPS)
        if v_pose is not None and np.all(np.isfinite(v_pose)):
            lr = np.array([tc.lr_pose_translation] * 3 + [tc.lr_pose_rotation] * 3)
            delta = view.pose_adam.update(v_pose, lr, o.beta1, o.beta2, _EXPOSURE_EPS)
            view.world_to_cam = se3_exp(delta) @ view.world_to_cam
        t = self._clock(t, times, "adam")

        refine = self.strategy.step_post_backward(gmap, self.strategy_state, step)
        self._clock(t, times, "strategy")
        return StepResult(step=int(step), view_id=view.view_id, level=int(level), width=W, height=H, loss=res.loss,
                          l1=res.l1, ssim=res.ssim, psnr=psnr,
                          exposure=(float(view.exposure[0]), float(view.exposure[1])), num_gaussians=gmap.n,
                          num_visible=num_visible, refine=refine, times=times, num_pairs=int(out.n_pairs))

    @staticmethod
    def _depth_term(out, view: TrainView, level: int, weight: float) -> tuple[np.ndarray, np.ndarray]:
        """Gradients (d/d depth, d/d alpha) of ``weight * mean_p |D(p) / alpha(p) - z_p| / z_p`` over the view's depth
        points where the render covers them (alpha > 0.5): the expected depth of the rendered surface against the
        odometry's depth, relative (the odometry's scale is arbitrary). Keeps Gaussians on the surfaces the
        odometry measured: a floater in front of a point pulls its depth and is pushed back or made transparent."""
        H, W = out.alpha.shape
        f = 0.5 ** level
        u = np.clip(np.floor(view.depth_uv[:, 0] * f + 0.5 * f).astype(np.int64), 0, W - 1)
        v = np.clip(np.floor(view.depth_uv[:, 1] * f + 0.5 * f).astype(np.int64), 0, H - 1)
        alpha = out.alpha.numpy()[v, u].astype(np.float64)
        D = out.depth.numpy()[v, u].astype(np.float64)
        z = view.depth_z
        ok = alpha > 0.5
        v_depth = np.zeros((H, W), np.float32)
        v_alpha = np.zeros((H, W), np.float32)
        if not ok.any():
            return v_depth, v_alpha
        u, v, alpha, D, z = u[ok], v[ok], alpha[ok], D[ok], z[ok]
        g = weight * np.sign(D / alpha - z) / z / len(z)
        np.add.at(v_depth, (v, u), (g / alpha).astype(np.float32))
        np.add.at(v_alpha, (v, u), (-g * D / alpha ** 2).astype(np.float32))
        return v_depth, v_alpha

    # ------------------------------------------------------------------------------------------ render
    def render(self, gmap: GaussianMap, camera: PinholeCamera, world_to_cam: np.ndarray, *,
               exposure: tuple[float, float] | None = None, sh_degree: int | None = None,
               rasterizer: Rasterizer | None = None) -> np.ndarray:
        """A copy of the map's RGB render (H, W, 3) float32 from ``world_to_cam`` with ``camera``; ``exposure``
        (a, b) gives ``exp(a) * render + b`` (not clamped). ``rasterizer``: one of the caller's instead of the
        step's own (a render in another thread needs its own buffers)."""
        if gmap.n == 0:
            return np.broadcast_to(np.asarray(self.background, np.float32),
                                   (camera.height, camera.width, 3)).copy()
        p = gmap.float_params()
        r = rasterizer if rasterizer is not None else self.rasterizer
        out = r.forward(p.means, p.log_scales, p.quats, p.opacity_logits, p.sh,
                        self.camera_struct(camera, world_to_cam), self.background, sh_degree=sh_degree,
                        rgb_only=True)
        rgb = np.array(out.rgb.numpy(), dtype=np.float32, copy=True)
        if exposure is not None:
            rgb = (math.exp(exposure[0]) * rgb + exposure[1]).astype(np.float32)
        return rgb


def usable_level(camera, level: int) -> int:
    """``level``, lowered until ``camera``'s image at that pyramid level is at least 16 pixels wide and high."""
    while level > 0 and (camera.width >> level < 16 or camera.height >> level < 16):
        level -= 1
    return level


class Trainer:
    """Trains ``gmap`` on the views of ``views``: sampler, pyramid schedule, scene extent, step counter.

    ``gmap``: the map (owned by the caller; changed only through its operations). ``views``: the training views
    (the caller may add views, remove them and set their poses between steps). ``cfg``: the mapping section.
    ``sampler``: chooses the next view (default :class:`RandomEpochSampler` with ``seed``). ``train_step``: the
    :class:`TrainStep` to use (default: a new one on ``device``). ``start_step``: the first step's number.
    """

    def __init__(self, gmap: GaussianMap, views: ViewSet, cfg: MappingConfig, *, device: str | None = None,
                 sampler: ViewSampler | None = None, train_step: TrainStep | None = None, seed: int = 0,
                 timing: bool = False, start_step: int = 0):
        self.gmap = gmap
        self.views = views
        self.cfg = cfg
        self.sampler = sampler if sampler is not None else RandomEpochSampler(seed)
        self.train_step = train_step if train_step is not None else TrainStep(
            cfg, device if device is not None else gmap.device, seed=seed, timing=timing)
        # ONLY changed by step().
        self.step_count = int(start_step)
        self._extent_version = -1

    # --------------------------------------------------------------------------------------- schedules
    def pyramid_level(self, view: TrainView) -> int:
        """Photo-SLAM's coarse-to-fine schedule: a view's first ``pyramid_uses`` uses are at the coarsest level
        (``pyramid_levels - 1``), the next ``pyramid_uses`` one level finer, ..., then full resolution. Levels are
        limited to those at least 16 pixels wide and high."""
        tc = self.cfg.train
        if tc.pyramid_levels <= 1 or tc.pyramid_uses <= 0:
            return 0
        return usable_level(view.camera, max(0, tc.pyramid_levels - 1 - view.uses // tc.pyramid_uses))

    def update_scene_extent(self) -> float:
        """3DGS's scene extent (``scene_extent_margin`` x the largest camera distance from the cameras' centroid),
        at least ``train.min_scene_extent``; written to ``gmap.scene_extent`` when the views changed."""
        if self._extent_version != self.views.version and len(self.views):
            extent = scene_extent_from_cameras(self.views.camera_centres(), self.cfg.scene_extent_margin)
            self.gmap.scene_extent = max(extent, self.cfg.train.min_scene_extent)
            self._extent_version = self.views.version
        return self.gmap.scene_extent

    # -------------------------------------------------------------------------------------------- steps
    def step(self, view_id: int | None = None, min_level: int = 0) -> StepResult:
        """One training step on ``view_id`` (default: the sampler's choice), at the pyramid schedule's level or
        ``min_level``, whichever is coarser (the real-time mapper's cheaper steps while the stream runs)."""
        if len(self.views) == 0:
            raise ValueError("Trainer.step: no views to train on")
        self.update_scene_extent()
        vid = self.sampler.next_view(self.views) if view_id is None else int(view_id)
        view = self.views[vid]
        every = self.cfg.train.metrics_every
        result = self.train_step(self.gmap, view, self.step_count, level=max(self.pyramid_level(view), min_level),
                                 with_psnr=every > 0 and self.step_count % every == 0)
        view.uses += 1
        self.step_count += 1
        observe = getattr(self.sampler, "observe", None)
        if observe is not None:
            observe(vid, result.loss, result.level)
        return result

    def train(self, iterations: int, callback: Callable[[StepResult], object] | None = None,
              should_stop: Callable[[], bool] | None = None) -> TrainSummary:
        """Run ``iterations`` steps; ``callback(result)`` after each (progress bars, observers); ``should_stop()``,
        asked before each step, ends the training early (a signal recorded by the caller): the summary then counts
        the steps taken."""
        losses = np.zeros(int(iterations))
        totals = {k: 0.0 for k in STAGES}
        last = None
        t0 = time.perf_counter()
        for k in range(int(iterations)):
            if should_stop is not None and should_stop():
                return TrainSummary(steps=k, seconds=time.perf_counter() - t0, losses=losses[:k], last=last,
                                    times=totals)
            last = self.step()
            losses[k] = last.loss
            for name, sec in last.times.items():
                totals[name] = totals.get(name, 0.0) + sec
            if callback is not None:
                callback(last)
        return TrainSummary(steps=int(iterations), seconds=time.perf_counter() - t0, losses=losses, last=last,
                            times=totals)

    # ------------------------------------------------------------------------------------------ render
    def render(self, camera: PinholeCamera, world_to_cam: np.ndarray,
               exposure: tuple[float, float] | None = None, rasterizer: Rasterizer | None = None) -> np.ndarray:
        """RGB render (H, W, 3) float32 of the current map (SH degree in use at the current step); ``rasterizer``:
        see :meth:`TrainStep.render`."""
        degree = self.train_step.sh_degree_at(self.gmap, self.step_count)
        return self.train_step.render(self.gmap, camera, world_to_cam, exposure=exposure, sh_degree=degree,
                                      rasterizer=rasterizer)

    def render_view(self, view_id: int) -> np.ndarray:
        """Render of a training view at full resolution with its current pose and exposure."""
        v = self.views[view_id]
        return self.render(v.camera, v.world_to_cam, exposure=(float(v.exposure[0]), float(v.exposure[1])))
