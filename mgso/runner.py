"""Run a sequence end to end and write the outputs a user asked for.

``run_sequence`` is what ``mgso run`` and ``mgso demo`` call. It owns the output folder; the SLAM work itself is done
by the stage's engine, which reports through observers and result values. Stages, in order of how far they go:

- ``check``: decode and undistort every frame, check it, and describe the sequence (no tracking).
- ``tracking``: the DSO front end (:class:`mgso.odometry.Odometry` with the fixed-window depth refinement as back end):
  a pose for every tracked frame (``trajectory.txt``), the keyframes (``keyframes.txt``), a per-frame log
  (``frames.csv``), the marginalised points (``points.ply``) and, with ground truth, ATE in ``metrics.json``.
- ``odometry``: the same outputs with the back end ``window.backend`` names (default ``bundle``: DSO's sliding-window
  bundle adjustment with marginalisation, docs/window.md).
- ``full``: the whole MGSO system (:mod:`mgso.system`): the DSO odometry and the Gaussian mapper seeded from its
  points, in deterministic or real-time mode; every output of docs/mgso.md (trajectories, ``map.ply``, ``points.ply``,
  renders, ``metrics.json`` with ATE, PSNR/SSIM, memory and speed).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .config import Config
from .observers import Observer
from .io.trajectory import write_tum

__all__ = ["STAGES", "STAGE_HELP", "DEFAULT_STAGE", "RunSummary", "run_sequence", "run_system"]

log = logging.getLogger(__name__)

STAGES = ("check", "tracking", "odometry", "full")
STAGE_HELP = {"check": "check = decode and check every frame, describe the sequence",
              "tracking": "tracking = DSO front end: pose of every frame, keyframes, ATE with ground truth",
              "odometry": "odometry = DSO front end + sliding-window bundle adjustment (window.backend): trajectory, "
                          "keyframes, point cloud, ATE with ground truth",
              "full": "full = DSO odometry + Gaussian map seeded from its points (MGSO): trajectories, map.ply, "
                      "renders, ATE/PSNR/SSIM"}
DEFAULT_STAGE = "full"


@dataclass
class RunSummary:
    """What a run did, as values; ``lines()`` is the human summary the CLI prints."""

    stage: str
    out_dir: Path
    frames: int = 0
    ok: bool = True
    figures: dict = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)
    written: list[Path] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"stage {self.stage}: {self.frames} frames, {'ok' if self.ok else 'FAILED'}"]
        out += self.messages
        out += [f"wrote {p}" for p in self.written]
        return out


class _NoBar:
    def update(self, n=1):
        pass

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _no_progress(total: int, desc: str):
    return _NoBar()


def _check_frames(seq, summary: RunSummary, progress) -> None:
    t0 = time.perf_counter()
    size = None
    n = 0
    with progress(len(seq), "decode") as bar:
        for frame in seq.frames():
            img = frame.gray
            if size is None:
                size = img.shape
            if not np.all(np.isfinite(img)):
                raise ValueError(f"{frame.source}: image has non-finite values after calibration")
            n += 1
            bar.update(1)
    dt = time.perf_counter() - t0
    summary.frames = n
    summary.figures["decode_fps"] = n / dt if dt > 0 else float("inf")
    summary.messages.append(f"decoded {n} frames at {summary.figures['decode_fps']:.1f} frames/s "
                            f"({size[1]}x{size[0]} after calibration)")


class _FrameBar(Observer):
    """Advances a progress bar per frame and shows keyframes and the map's size."""

    def __init__(self, bar):
        self.bar = bar
        self.keyframes = 0
        self.gaussians = 0

    def on_frame(self, result) -> None:
        self.bar.update(1)

    def on_keyframe(self, msg) -> None:
        self.keyframes += 1
        if hasattr(self.bar, "set_postfix"):
            self.bar.set_postfix({"kf": str(self.keyframes), "gaussians": str(self.gaussians)}, refresh=False)

    def on_map_updated(self, update) -> None:
        self.gaussians = update.num_gaussians


def run_system(seq, cfg: Config, out_dir: Path, odometry, *, odometry_name: str = "",
               progress: Callable[[int, str], object] | None = None, summary: RunSummary | None = None,
               device: str | None = None) -> RunSummary:
    """Run the whole system (``odometry`` + the Gaussian mapper, :mod:`mgso.system`) over ``seq`` and write every
    output of ``mgso run`` into ``out_dir`` (docs/mgso.md). ``odometry``: an :class:`mgso.system.Odometry`."""
    from .observers import ObserverList
    from .system import System, write_outputs

    progress = progress or _no_progress
    summary = summary or RunSummary(stage="full", out_dir=Path(out_dir))
    bar = progress(len(seq), f"{cfg.system.mode}")
    frame_bar = _FrameBar(bar)
    try:
        system = System(odometry, cfg, device=device, observer=ObserverList([frame_bar]))
        result = system.run(seq.frames(), info=seq.describe())
    finally:
        bar.close()
    metrics = write_outputs(result, system.mapper, seq, cfg, out_dir, odometry_name=odometry_name,
                            progress=progress)
    summary.frames = result.frames_processed
    summary.ok = True
    summary.figures.update({k: metrics.get(k) for k in (
        "ate_all_frames_m", "ate_keyframes_m", "psnr_monogs_db", "ssim_monogs", "psnr_photo_slam_db",
        "ssim_photo_slam", "num_gaussians", "map_size_mb", "peak_memory_mb", "tracking_fps",
        "mapping_iterations_per_s", "end_to_end_fps")})
    m = summary.messages
    if result.interrupted:
        m.append(f"interrupted after {result.frames_processed} frames: outputs of what was done")
    m.append(f"{result.frames_processed} frames ({result.frames_dropped} dropped, {result.frames_lost} without "
             f"pose), {result.keyframes} keyframes, {metrics['num_gaussians']} Gaussians "
             f"({metrics['map_size_mb']:.1f} MB as PLY), peak memory {metrics['peak_memory_mb']:.0f} MB")
    m.append(f"tracking {metrics['tracking_fps']:.1f} frames/s, mapping {metrics['mapping_iterations_per_s']:.2f} "
             f"it/s ({result.mapper.steps} steps), end to end {metrics['end_to_end_fps']:.2f} frames/s "
             f"({cfg.system.mode})")
    if metrics["frames"]["in_trajectory"] == 0 and result.frames_processed:
        m.append("no frame got a pose: the odometry never initialised (a monocular start needs the camera to "
                 "translate; see the log for the initialiser's reasons)")
    for a in metrics["ate"]:
        m.append(f"ATE {a['translation_m']['rmse']:.4f} m RMSE ({a['label']}, Sim(3) aligned, "
                 f"{a['num_pairs']} poses)")
    for r in metrics["render"]:
        m.append(f"PSNR {r['mean_psnr_db']:.2f} dB, SSIM {r['mean_ssim']:.4f} ({r['protocol']}, "
                 f"{r['num_frames']} frames)")
    summary.written += [Path(out_dir) / w for w in metrics["written"]]
    return summary


def run_sequence(seq, cfg: Config, out_dir: Path, *, stage: str | None = None,
                 progress: Callable[[int, str], object] | None = None) -> RunSummary:
    """Run ``stage`` on ``seq`` and write into ``out_dir`` (which exists)."""
    stage = stage or DEFAULT_STAGE
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; available: {', '.join(STAGES)}")
    progress = progress or _no_progress
    out_dir = Path(out_dir)
    summary = RunSummary(stage=stage, out_dir=out_dir)

    info = seq.describe()
    (out_dir / "sequence.json").write_text(json.dumps(info, indent=2, default=str) + "\n")
    summary.written.append(out_dir / "sequence.json")
    if seq.groundtruth is not None:
        write_tum(out_dir / "groundtruth.txt", seq.groundtruth)
        summary.written.append(out_dir / "groundtruth.txt")

    if stage == "check":
        _check_frames(seq, summary, progress)
    elif stage == "tracking":
        import dataclasses

        from .tracking.run import run_tracking

        # the front end with the stand-in back end (poses fixed); the window optimisation is the odometry stage
        cfg_t = dataclasses.replace(cfg, window=dataclasses.replace(cfg.window, backend="fixed"))
        run_tracking(seq, cfg_t, out_dir, summary, progress)
    elif stage == "odometry":
        from .tracking.run import run_tracking

        run_tracking(seq, cfg, out_dir, summary, progress)
    elif stage == "full":
        from mgso_kernels import runtime
        from .system import DsoOdometry

        device = runtime.init(cfg.runtime.device, threads=cfg.runtime.threads, blas_threads=cfg.runtime.blas_threads)
        odo_device = runtime.resolve_device(cfg.runtime.odometry_device) if cfg.runtime.odometry_device else device
        odometry = DsoOdometry(seq.calibration.output, cfg, device=odo_device)
        run_system(seq, cfg, out_dir, odometry, odometry_name=odometry.name, progress=progress, summary=summary,
                   device=device)
    return summary
