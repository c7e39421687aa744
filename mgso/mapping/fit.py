"""Fit a Gaussian map to a sequence with known poses (what ``mgso fit`` runs; docs/fitting.md).

:func:`fit_sequence` splits the sequence's frames into training views and held-out frames (every
``mapping.train.holdout_every``-th frame, never trained on), makes the initial Gaussians (random points in the
training views' frusta, or a PLY), trains with :class:`~mgso.mapping.trainer.Trainer` for
``mapping.train.iterations`` steps, then renders the held-out frames at their poses and writes through the run
writer it is given (:class:`mgso.app.writer.RunWriter`: ``write_gaussians``, ``write_image``, ``write_metrics``):

- ``map.ply``: the map in the standard 3DGS layout (:mod:`mgso.io.ply`);
- ``renders/NNNNNN.png`` and ``gt/NNNNNN.png``: each held-out frame's render and its image (frame index of the
  sequence selection; 3DGS's ``renders`` / ``gt`` folders);
- ``metrics.json``: PSNR / SSIM of the held-out frames (``mgso.eval``, protocol "held-out every 5th frame"),
  Gaussians, times, iterations and iterations per second, views used, the initial cloud;
- ``config.yaml``: the full configuration used (written by the caller, before the work).

The poses are the sequence's ground truth (``open_sequence(..., groundtruth=FILE)`` replaces it by a trajectory file,
e.g. one estimated by ``mgso run``). Frames without a pose are left out (logged).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, ContextManager

import numpy as np

from mgso.config import Config
from mgso.eval.render_metrics import RenderMetrics, RenderProtocol, evaluate_renders
from mgso.geometry import orthonormalize, se3_inverse
from mgso.io.ply import PlyError, read_gaussians_ply, read_point_cloud_ply
from mgso.mapping.gaussian_map import GaussianArrays, GaussianMap, num_sh_coeffs
from mgso.mapping.init import gaussians_from_points, random_frustum_points
from mgso.mapping.trainer import StepResult, Trainer, TrainSummary
from mgso.mapping.views import TrainView, ViewSet
from mgso.observers import no_progress
from mgso_kernels import runtime

__all__ = ["FitError", "FitResult", "fit_sequence", "split_frames", "heldout_protocol", "load_initial_gaussians"]

log = logging.getLogger(__name__)


class FitError(ValueError):
    """Fitting cannot run on this input; the message names the sequence or file and what is wrong."""


def _ordinal(n: int) -> str:
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def heldout_protocol(every: int) -> RenderProtocol:
    """The rendering protocol of ``mgso fit``: frames at positions 0, every, 2 every, ... of the sequence, never
    trained on; renders clamped to [0, 1]; PSNR over all pixels; SSIM with 3DGS's zero-padded window (the
    'same-zero' border of graphdeco's ``metrics.py``, which evaluates 3DGS's held-out test views the same way)."""
    return RenderProtocol(key="heldout", name=f"held-out every {_ordinal(every)} frame", frame_stride=every,
                          exclude_keyframes=False, exclude_last_frame=False, clamp_rendered=True,
                          psnr_mask_zero_reference=False, ssim_border="same-zero")


def split_frames(n: int, holdout_every: int, max_train_views: int = 0) -> tuple[list[int], list[int]]:
    """(training, held-out) positions among ``n`` frames: positions ``p % holdout_every == 0`` are held out (none
    when ``holdout_every`` is 0); the rest train, thinned to ``max_train_views`` evenly spread ones when > 0."""
    if n < 1:
        raise ValueError("split_frames: no frames")
    held = list(range(0, n, holdout_every)) if holdout_every > 0 else []
    held_set = set(held)
    train = [i for i in range(n) if i not in held_set]
    if max_train_views > 0 and len(train) > max_train_views:
        pick = np.unique(np.round(np.linspace(0, len(train) - 1, max_train_views)).astype(int))
        train = [train[k] for k in pick]
    return train, held


def _pose(seq, i: int) -> np.ndarray | None:
    T = seq.groundtruth_cam_to_world(i)
    if T is None:
        return None
    T = np.array(T, dtype=np.float64)
    T[:3, :3] = orthonormalize(T[:3, :3])   # e.g. 7-Scenes' KinectFusion poses carry 4e-4 orthonormality error
    return T


def _fit_sh(arrays: GaussianArrays, degree: int, where: str) -> GaussianArrays:
    k = num_sh_coeffs(degree)
    if arrays.sh.shape[1] == k:
        return arrays
    log.warning("%s: SH degree %d, the map uses %d: %s", where, arrays.sh_degree, degree,
                "higher bands dropped" if arrays.sh.shape[1] > k else "missing bands start at zero")
    sh = np.zeros((arrays.n, k, 3), np.float32)
    m = min(k, arrays.sh.shape[1])
    sh[:, :m] = arrays.sh[:, :m]
    return GaussianArrays(arrays.means, arrays.log_scales, arrays.quats, arrays.opacity_logits, sh)


def load_initial_gaussians(init: str, views: ViewSet, cfg: Config) -> tuple[GaussianArrays, dict]:
    """The initial Gaussians for ``init``: ``"random"`` (``mapping.train.init_points`` points in the views' frusta,
    coloured from the images), a 3DGS Gaussian PLY (trained further as it is), or a point-cloud PLY (``x y z`` and
    optionally ``red green blue``; Gaussians by :func:`~mgso.mapping.init.gaussians_from_points`). Returns the
    arrays and a description for ``metrics.json``."""
    tc = cfg.mapping.train
    degree = cfg.mapping.sh_degree
    if init == "random":
        rng = np.random.default_rng(cfg.runtime.seed)
        pts, cols, pixel = random_frustum_points(list(views), tc.init_points, tc.init_depth_range, rng)
        cap = tc.init_max_screen_px * pixel if tc.init_max_screen_px > 0 else None
        arrays = gaussians_from_points(pts, cols, opacity=tc.init_opacity, knn=tc.init_knn, max_scale=cap,
                                       sh_degree=degree)
        return arrays, {"kind": "random", "points": int(arrays.n), "depth_range": list(tc.init_depth_range),
                        "max_screen_px": tc.init_max_screen_px}
    path = Path(init)
    try:
        pts, cols, others = read_point_cloud_ply(path)
    except PlyError as exc:
        raise FitError(f"--init: {exc}") from None
    if "f_dc_0" in others and "opacity" in others:
        try:
            arrays = _fit_sh(read_gaussians_ply(path), degree, str(path))
        except PlyError as exc:
            raise FitError(f"--init: {exc}") from None
        return arrays, {"kind": "gaussians", "file": str(path), "points": int(arrays.n)}
    if len(pts) == 0:
        raise FitError(f"--init: {path}: the point cloud is empty")
    if not np.all(np.isfinite(pts)):
        raise FitError(f"--init: {path}: points with non-finite coordinates")
    rgb = None if cols is None else cols.astype(np.float32) / 255.0
    arrays = gaussians_from_points(pts, rgb, opacity=tc.init_opacity, knn=tc.init_knn, sh_degree=degree)
    return arrays, {"kind": "points", "file": str(path), "points": int(arrays.n)}


@dataclass
class FitResult:
    """What :func:`fit_sequence` did and wrote."""

    out_dir: Path
    metrics: RenderMetrics | None          # held-out frames (None when nothing is held out)
    num_gaussians: int
    iterations: int
    train_seconds: float                   # the training loop only
    total_seconds: float                   # loading, init, training, evaluation and writing
    train_frames: list[int]                # frame indices of the sequence selection
    heldout_frames: list[int]
    summary: TrainSummary
    figures: dict = field(default_factory=dict)   # what metrics.json holds besides the render metrics
    written: list[Path] = field(default_factory=list)

    @property
    def iterations_per_s(self) -> float:
        return self.iterations / self.train_seconds if self.train_seconds > 0 else float("inf")

    def lines(self) -> list[str]:
        out = [f"trained {self.iterations} iterations on {len(self.train_frames)} views in {self.train_seconds:.1f} s "
               f"({self.iterations_per_s:.2f} it/s), {self.num_gaussians} Gaussians"]
        if self.metrics is not None:
            out.append(self.metrics.summary())
        out += [f"wrote {p}" for p in self.written]
        return out


def fit_sequence(seq, cfg: Config, writer, *, init: str = "random", device: str | None = None,
                 progress: Callable[[int, str], object] | None = None,
                 on_step: Callable[[StepResult], object] | None = None,
                 should_stop: Callable[[], bool] | None = None,
                 guard: Callable[[], ContextManager] = nullcontext) -> FitResult:
    """Fit a map to ``seq`` (a :class:`mgso.io.Sequence` with poses) and write the outputs through ``writer`` (a
    :class:`mgso.app.writer.RunWriter`, whose folder ``FitResult.out_dir`` is).

    ``cfg``: the full configuration (``mapping`` for the map and training, ``runtime`` for the device and seed);
    ``init``: ``"random"`` or a PLY path (see :func:`load_initial_gaussians`); ``device``: overrides
    ``runtime.device``; ``progress(total, desc)``: returns a progress bar (``update(n)``, optionally
    ``set_postfix(**values)``) used while loading and training (the CLI's tqdm); ``on_step(result)``: called after
    every training step. ``should_stop()``: asked before each step; when it says so the training ends there, the map
    trained so far is written with ``metrics.json`` (``"interrupted": true``) and the held-out evaluation is left
    out. ``guard()``: a context the training and the writing run in (the CLI's: signals recorded, not raised, so
    that a stop lands between two steps and the outputs are whole).
    """
    t_start = time.perf_counter()
    out = Path(writer.out)
    progress = progress or no_progress
    # given poses are trusted unless mapping.train.refine_poses is set
    mc = dataclasses.replace(cfg.mapping, train=cfg.mapping.train.with_pose_refinement(False))
    tc = mc.train
    dev = runtime.init(device or cfg.runtime.device, threads=cfg.runtime.threads,
                       blas_threads=cfg.runtime.blas_threads)
    where = f"{seq.path}"
    if seq.groundtruth is None:
        raise FitError(f"{where}: the sequence has no poses: fit needs ground truth or a trajectory file "
                       "(--poses FILE, TUM or KITTI camera-to-world)")
    train_pos, held_pos = split_frames(len(seq), tc.holdout_every, tc.max_train_views)
    poses = {i: _pose(seq, i) for i in sorted(set(train_pos) | set(held_pos))}
    missing = [i for i, T in poses.items() if T is None]
    if missing:
        log.warning("%s: %d of %d frames have no pose and are left out (first: %s)", where, len(missing),
                    len(poses), missing[:5])
    train_pos = [i for i in train_pos if poses[i] is not None]
    held_pos = [i for i in held_pos if poses[i] is not None]
    if not train_pos:
        raise FitError(f"{where}: no training frame with a pose (of {len(seq)} frames)")
    cam = seq.calibration.output
    valid = getattr(seq.calibration.undistorter, "valid_mask", None)
    mask = None if valid is None or bool(np.all(valid)) else valid.astype(np.float32)

    views = ViewSet()
    with progress(len(train_pos), "load") as bar:
        for i in train_pos:
            frame = seq.load(i)
            views.add(TrainView(i, frame.rgb, cam, se3_inverse(poses[i]), mask=mask, timestamp=frame.timestamp,
                                name=frame.source or f"frame {i}"))
            bar.update(1)

    arrays, init_info = load_initial_gaussians(init, views, cfg)
    if arrays.n > mc.capacity:
        raise FitError(f"--init gives {arrays.n} Gaussians but mapping.capacity is {mc.capacity}")
    gmap = GaussianMap.from_arrays(arrays, capacity=mc.capacity, device=dev, optim=mc.optim)
    trainer = Trainer(gmap, views, mc, seed=cfg.runtime.seed)
    log.info("fit: %d training views, %d held out, %d initial Gaussians (%s), scene extent %.3f", len(views),
             len(held_pos), gmap.n, init_info["kind"], trainer.update_scene_extent())

    last_psnr: list[float | None] = [None]
    refine_totals = {"refines": 0, "cloned": 0, "split": 0, "pruned": 0, "skipped_capacity": 0, "opacity_resets": 0}

    with progress(tc.iterations, "train") as bar:
        def callback(r: StepResult) -> None:
            if r.psnr is not None:
                last_psnr[0] = r.psnr
            if r.refine.refined or r.refine.opacity_reset:
                f = r.refine
                for key, val in (("refines", f.refined), ("cloned", f.cloned), ("split", f.split),
                                 ("pruned", f.pruned), ("skipped_capacity", f.skipped_capacity),
                                 ("opacity_resets", f.opacity_reset)):
                    refine_totals[key] += int(val)
            bar.update(1)
            if r.psnr is not None or r.step == tc.iterations - 1:
                post = {"loss": f"{r.loss:.4f}", "psnr": f"{last_psnr[0]:.2f}" if last_psnr[0] else "-",
                        "gaussians": str(r.num_gaussians)}   # a string: tqdm prints 20000 as 2e+4
                if hasattr(bar, "set_postfix"):
                    bar.set_postfix(post, refresh=False)
            if on_step is not None:
                on_step(r)

        with guard():
            summary = trainer.train(tc.iterations, callback, should_stop=should_stop)
    train_seconds = summary.seconds
    interrupted = summary.steps < tc.iterations

    with guard():           # the outputs whole whatever signal comes while they are written
        written: list[Path] = []
        written.append(writer.write_gaussians(gmap.to_numpy()))
        metrics = None
        if held_pos and not interrupted:
            protocol = heldout_protocol(tc.holdout_every)

            def pairs():
                for i in held_pos:
                    gt = seq.load(i).rgb
                    rgb = trainer.render(cam, se3_inverse(poses[i]))
                    writer.write_image(f"renders/{i:06d}.png", np.clip(rgb, 0.0, 1.0))
                    writer.write_image(f"gt/{i:06d}.png", gt)
                    yield rgb, gt

            metrics = evaluate_renders(pairs(), held_pos, protocol)
            written += [out / "renders", out / "gt"]
        total_seconds = time.perf_counter() - t_start
        n_loss = max(1, min(100, summary.steps // 10)) if summary.steps else 0
        figures = {
            "num_gaussians": int(gmap.n),
            "iterations": int(summary.steps),
            "train_time_s": train_seconds,
            "total_time_s": total_seconds,
            "iterations_per_s": summary.iterations_per_s if summary.steps else 0.0,
            "stage_time_s": summary.times,
            "train_views": len(views),
            "heldout_frames": len(held_pos),
            "image_size": [cam.width, cam.height],
            "device": dev,
            "threads": runtime.cpu_threads(),
            "init": init_info,
            "scene_extent": float(gmap.scene_extent),
            "densification": refine_totals,
            "loss_first": float(summary.losses[:n_loss].mean()) if n_loss else None,
            "loss_last": float(summary.losses[-n_loss:].mean()) if n_loss else None,
            "loss_window": n_loss,
            "sequence": {"path": str(seq.path), "layout": seq.layout, "frames": len(seq)},
            "interrupted": interrupted,
            "evaluation": "skipped: interrupted" if interrupted and held_pos else ("done" if held_pos else "none"),
        }
        written.append(writer.write_metrics(renders=metrics, extra=figures))
        return FitResult(out_dir=out, metrics=metrics, num_gaussians=int(gmap.n), iterations=int(summary.steps),
                         train_seconds=train_seconds, total_seconds=total_seconds, train_frames=train_pos,
                         heldout_frames=held_pos, summary=summary, figures=figures, written=written)
