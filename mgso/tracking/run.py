"""The ``tracking`` stage of ``mgso run``: the odometry over a whole sequence, its files and figures.

Called by :func:`mgso.runner.run_sequence`; writes into the run folder:

- ``trajectory.txt``: every frame that has a pose, camera-to-world (TUM ``timestamp tx ty tz qx qy qz qw``, or KITTI
  3x4 rows with ``output.trajectory_format: kitti``). Frames before initialisation and lost frames have no pose and are
  left out; ``frames.csv`` says which and why. After a tracking loss the trajectory continues in a new segment (see
  :mod:`mgso.odometry`).
- ``keyframes.txt``: the keyframes' final poses (same format).
- ``frames.csv``: per frame ``index, timestamp, status, segment, keyframe, keyframe_reason, rmse, inlier_ratio,
  hypotheses, track_ms, map_ms``.
- ``points.ply``: the marginalised points (and those still active at the end) with their colours.
- ``metrics.json`` (with ground truth): ATE (Sim(3)) of all frames and of the keyframes, per segment when there are
  several, and the run's counts and timings; ``trajectory.png`` when matplotlib is present and ``output.plot`` is on.
"""

from __future__ import annotations

import csv
import logging
import time
from collections import Counter
from pathlib import Path

import numpy as np

from mgso_kernels import runtime

from ..config import Config
from ..io.trajectory import Trajectory, write_kitti, write_tum
from ..observers import Observer, ObserverList
from ..odometry import FrameResult, FrameStatus, Odometry, geometry_for

__all__ = ["run_tracking", "TrackingRunStats"]

log = logging.getLogger(__name__)


class TrackingRunStats(Observer):
    """Collects per-frame results for the log and the figures."""

    def __init__(self):
        self.results: list[FrameResult] = []
        self.lost = []

    def on_frame(self, result):
        self.results.append(result)

    def on_tracking_lost(self, event):
        self.lost.append(event)


def _write_traj(path: Path, traj: Trajectory, fmt: str) -> None:
    if fmt == "kitti":
        write_kitti(path, traj)
    else:
        write_tum(path, traj)


def run_tracking(seq, cfg: Config, out_dir: Path, summary, progress, observers=()) -> Odometry:
    """Run the odometry over ``seq`` and write the stage's files; figures go into ``summary``."""
    device = runtime.init(cfg.runtime.device, threads=cfg.runtime.threads, blas_threads=cfg.runtime.blas_threads)
    cam = seq.calibration.output
    geo = geometry_for(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cfg)
    stats = TrackingRunStats()
    odo = Odometry(geo, cfg, device=device, observer=ObserverList([stats, *observers]))
    t0 = time.perf_counter()
    n = 0
    with progress(len(seq), "track") as bar:
        for frame in seq.frames():
            odo.process(frame)
            n += 1
            bar.update(1)
    wall = time.perf_counter() - t0
    odo.finish()
    summary.frames = n
    fmt = cfg.output.trajectory_format
    traj = odo.trajectory()
    kfs = odo.keyframe_trajectory()
    _write_traj(out_dir / "trajectory.txt", traj, fmt)
    _write_traj(out_dir / "keyframes.txt", kfs, fmt)
    summary.written += [out_dir / "trajectory.txt", out_dir / "keyframes.txt"]
    _write_frames_csv(out_dir / "frames.csv", odo, stats)
    summary.written.append(out_dir / "frames.csv")
    pts, cols = odo.point_cloud_world()
    from ..io.ply import write_point_cloud_ply

    write_point_cloud_ply(out_dir / "points.ply", pts, cols)
    summary.written.append(out_dir / "points.ply")

    counts = Counter(f.status.value for f in odo.frames)
    tracked = len(traj)
    track_ms = [r.time_track_s * 1000 for r in stats.results if r.status == FrameStatus.TRACKED]
    map_ms = [r.time_map_s * 1000 for r in stats.results if r.status == FrameStatus.TRACKED]
    figures = {
        "frames": n, "frames_with_pose": tracked, "fraction_tracked": tracked / n if n else 0.0,
        "keyframes": len(kfs), "segments": odo.segment + 1, "tracking_lost": odo.num_lost,
        "repeated_frames": odo.num_duplicates,
        "status_counts": dict(counts), "points": int(len(pts)), "wall_s": wall, "fps": n / wall if wall else 0.0,
        "track_ms_median": float(np.median(track_ms)) if track_ms else None,
        "map_ms_median": float(np.median(map_ms)) if map_ms else None,
        "device": device, "image_size": [geo.width, geo.height], "pyramid_levels": geo.levels,
    }
    summary.figures.update(figures)
    repeats = f" ({odo.num_duplicates} repeated images: pose of the frame before)" if odo.num_duplicates else ""
    summary.messages.append(f"tracked {tracked}/{n} frames ({100.0 * tracked / max(n, 1):.1f}%){repeats}, "
                            f"{len(kfs)} keyframes, {odo.num_lost} tracking losses, {len(pts)} points; "
                            f"{n / wall if wall else 0:.2f} frames/s ({geo.width}x{geo.height}, {device})")
    gt = seq.groundtruth
    ates = []
    if gt is not None and tracked >= 3:
        from ..eval import compute_ate, write_metrics_json

        try:
            ate = compute_ate(traj, gt, align="sim3", label="all frames")
            ates.append(ate)
            summary.messages.append(ate.summary() + " [all frames with a pose]")
            summary.figures["ate_rmse_all_frames"] = ate.rmse
            if len(kfs) >= 3:
                ak = compute_ate(kfs, gt, align="sim3", label="keyframes")
                ates.append(ak)
                summary.messages.append(ak.summary() + " [keyframes]")
                summary.figures["ate_rmse_keyframes"] = ak.rmse
            segs = {}
            for s in range(odo.segment + 1):
                fr = [f for f in odo.frames if f.pose_valid and f.segment == s]
                if len(fr) >= 3 and odo.segment > 0:
                    st = Trajectory(np.array([f.timestamp for f in fr]),
                                    np.stack([odo.to_world(s, f.cam_to_world) for f in fr]))
                    a = compute_ate(st, gt, align="sim3", label=f"segment {s}")
                    segs[str(s)] = {"frames": len(fr), "ate_rmse": a.rmse}
            if segs:
                summary.figures["segments_ate"] = segs
        except Exception as exc:  # evaluation must not lose the run's outputs
            log.warning("ATE not computed: %s", exc)
            summary.messages.append(f"ATE not computed: {exc}")
        write_metrics_json(out_dir / "metrics.json", ate=ates, extra={"tracking": _json(summary.figures)})
        summary.written.append(out_dir / "metrics.json")
        if ates and cfg.output.plot:
            try:
                from ..eval import plot_trajectory

                plot_trajectory(out_dir / "trajectory.png", ates[0], reference=gt,
                                keyframe_timestamps=kfs.timestamps)
                summary.written.append(out_dir / "trajectory.png")
            except ImportError as exc:
                log.info("no trajectory plot: %s", exc)
    else:
        from ..eval import write_metrics_json

        write_metrics_json(out_dir / "metrics.json", extra={"tracking": _json(summary.figures)})
        summary.written.append(out_dir / "metrics.json")
    if tracked == 0:
        summary.ok = False
        summary.messages.append("no frame could be tracked (initialisation never succeeded)")
    return odo


def _json(d):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out[k] = _json(v)
        elif isinstance(v, (np.floating, np.integer)):
            out[k] = v.item()
        else:
            out[k] = v
    return out


def _write_frames_csv(path: Path, odo: Odometry, stats: TrackingRunStats) -> None:
    by_index = {r.index: r for r in stats.results}
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["index", "timestamp", "status", "segment", "keyframe", "keyframe_reason", "rmse", "inlier_ratio",
                    "hypotheses", "track_ms", "map_ms"])
        for f in odo.frames:
            r = by_index.get(f.index)
            tr = r.track if r is not None else None
            w.writerow([f.index, f"{f.timestamp:.6f}", f.status.value, f.segment, f.keyframe_id,
                        r.keyframe_reason if r is not None else "",
                        f"{tr.rmse0:.4f}" if tr is not None else "", f"{tr.inlier_ratio:.4f}" if tr is not None else "",
                        tr.hypotheses_tried if tr is not None else "",
                        f"{r.time_track_s * 1000:.2f}" if r is not None else "",
                        f"{r.time_map_s * 1000:.2f}" if r is not None else ""])
