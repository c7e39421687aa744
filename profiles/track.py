"""Per-frame time of coarse tracking (DSO ``trackNewCoarse``: all motion hypotheses tried, all pyramid levels) and
its split between Warp kernel launches and Python, at 640x480 (synthetic room) and at a dataset's own size.

Runs the whole odometry (initialisation, keyframes, point management) over the first frames so that the tracking
references are the real ones, and times only :meth:`CoarseTracker.track_frame` of the tracked frames. "Kernel" time
is the wall time spent inside ``mgso_kernels.runtime.launch_split`` (kernel work plus launch overhead, split over
the CPU cores); the rest of ``track_frame`` is Python (LM solves, se3 maths, building launch arguments).

    python profiles/track.py [--device cpu] [--frames 40] [--path DATASET ...] [--no-synthetic]

Prints one JSON line. The development machine is shared: the load average is in the output; compare runs at
similar load.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mgso import synthetic  # noqa: E402
from mgso.config import Config, apply_overrides  # noqa: E402
from mgso.io import open_sequence  # noqa: E402
from mgso.io.paths import shared_data_dir  # noqa: E402
from mgso.io.sequence import Frame  # noqa: E402
from mgso.odometry import FrameStatus, Odometry, geometry_for  # noqa: E402
from mgso.tracking import coarse_tracker  # noqa: E402
from mgso_kernels import runtime  # noqa: E402


class Timer:
    """Wraps CoarseTracker.track_frame and runtime.launch_split to time both."""

    def __init__(self):
        self.in_track = False
        self.kernel_s = 0.0
        self.frames: list[dict] = []
        self._orig_track = coarse_tracker.CoarseTracker.track_frame
        self._orig_launch = runtime.launch_split

    def __enter__(self):
        timer = self

        def launch(*a, **k):
            if not timer.in_track:
                return timer._orig_launch(*a, **k)
            t0 = time.perf_counter()
            try:
                return timer._orig_launch(*a, **k)
            finally:
                timer.kernel_s += time.perf_counter() - t0

        def track(tracker, *a, **k):
            timer.in_track = True
            timer.kernel_s = 0.0
            t0 = time.perf_counter()
            try:
                r = timer._orig_track(tracker, *a, **k)
            finally:
                timer.in_track = False
            dt = time.perf_counter() - t0
            timer.frames.append({"s": dt, "kernel_s": timer.kernel_s, "hyp": r.hypotheses_tried, "it": r.iterations,
                                 "points": r.num_reference_points})
            return r

        runtime.launch_split = launch
        coarse_tracker.CoarseTracker.track_frame = track
        return self

    def __exit__(self, *exc):
        runtime.launch_split = self._orig_launch
        coarse_tracker.CoarseTracker.track_frame = self._orig_track
        return False


def profile_frames(frames, width, height, fx, fy, cx, cy, cfg: Config, device: str) -> dict:
    geo = geometry_for(width, height, fx, fy, cx, cy, cfg)
    odo = Odometry(geo, cfg, device=device)
    with Timer() as tm:
        statuses = [odo.process(f).status for f in frames]
    tracked = [f for f in tm.frames]
    if not tracked:
        return {"error": "no frame was tracked", "statuses": [s.value for s in statuses]}
    ms = np.array([f["s"] for f in tracked]) * 1000
    ks = np.array([f["kernel_s"] for f in tracked]) * 1000
    return {
        "size": [geo.width, geo.height], "pyramid_levels": geo.levels, "frames": len(frames),
        "tracked_frames": len(tracked), "lost": int(sum(s == FrameStatus.LOST for s in statuses)),
        "track_ms_median": float(np.median(ms)), "track_ms_p90": float(np.percentile(ms, 90)),
        "track_ms_mean": float(ms.mean()),
        "kernel_share": float(ks.sum() / ms.sum()), "python_share": float(1 - ks.sum() / ms.sum()),
        "kernel_ms_median": float(np.median(ks)),
        "hypotheses_mean": float(np.mean([f["hyp"] for f in tracked])),
        "lm_iterations_mean": float(np.mean([f["it"] for f in tracked])),
        "reference_points_l0_median": float(np.median([f["points"] for f in tracked])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=40, help="frames per sequence (initialisation included)")
    ap.add_argument("--path", action="append", default=None, help="dataset(s) at their own size (default: KITTI 00 "
                                                                   "and 7-Scenes excerpts when present)")
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--set", action="append", default=[], help="config overrides, e.g. tracking.coarse_pattern=true")
    args = ap.parse_args()
    device = runtime.init(args.device)
    cfg = apply_overrides(Config(), args.set)
    out = {"profile": "track", "device": device, "cpu_threads": runtime.cpu_threads(),
           "load_avg_1min": os.getloadavg()[0]}
    if not args.no_synthetic:
        seq = synthetic.make_sequence(seed=0, num_frames=args.frames, width=640, height=480)
        k = seq.intrinsics
        gray = [(img @ np.array([0.299, 0.587, 0.114], np.float32)) * 255 for img in seq.images]
        frames = [Frame(i, float(seq.timestamps[i]), gray[i], None, rgb=seq.images[i]) for i in range(len(gray))]
        out["640x480"] = {"source": "synthetic room", **profile_frames(frames, 640, 480, k.fx, k.fy, k.cx, k.cy, cfg,
                                                                         device)}
    paths = args.path
    if paths is None:
        d = shared_data_dir()
        paths = [str(d / n) for n in ("kitti00_0-159", "7scenes_redkitchen_0-499")] if d is not None else []
    for p in paths:
        c = apply_overrides(cfg, [f"input.end={args.frames}"])
        seq = open_sequence(p, config=c.input)
        cam = seq.calibration.output
        out[Path(p).name] = profile_frames(list(seq.frames()), cam.width, cam.height, cam.fx, cam.fy, cam.cx,
                                           cam.cy, c, device)
    out["load_avg_1min_end"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
