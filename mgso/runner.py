"""Run a sequence end to end and write the outputs a user asked for.

``run_sequence`` is what ``mgso run`` and ``mgso demo`` call. It owns the output folder; the SLAM work itself is done
by the stage's engine, which reports through observers and result values. Stages, in order of how far they go:

- ``check``: decode and undistort every frame, check it, and describe the sequence (no tracking).
- ``tracking``: the DSO front end (:class:`mgso.odometry.Odometry` with the fixed-window depth refinement as back end):
  a pose for every tracked frame (``trajectory.txt``), the keyframes (``keyframes.txt``), a per-frame log
  (``frames.csv``), the marginalised points (``points.ply``) and, with ground truth, ATE in ``metrics.json``.
- ``odometry``: the same outputs with the back end ``window.backend`` names (default ``bundle``: DSO's sliding-window
  bundle adjustment with marginalisation, docs/window.md).
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
from .io.trajectory import write_tum

__all__ = ["STAGES", "STAGE_HELP", "DEFAULT_STAGE", "RunSummary", "run_sequence"]

log = logging.getLogger(__name__)

STAGES = ("check", "tracking", "odometry")
STAGE_HELP = {"check": "check = decode and check every frame, describe the sequence",
              "tracking": "tracking = DSO front end: pose of every frame, keyframes, ATE with ground truth",
              "odometry": "odometry = DSO front end + sliding-window bundle adjustment (window.backend): trajectory, "
                          "keyframes, point cloud, ATE with ground truth"}
DEFAULT_STAGE = "check"


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
    return summary
