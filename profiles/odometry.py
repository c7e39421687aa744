"""Accuracy and speed of the whole odometry (DSO front end + the window back end) on the shared recordings: ATE
(Sim(3) Umeyama alignment, all frames with a pose, as ``evo_ape tum GT EST -as``) and frames per second, for each
back end asked for (``bundle``: the sliding-window bundle adjustment, ``fixed``: the stand-in).

    python profiles/odometry.py [--device cpu] [--backends bundle,fixed] [--path P ...] [--frames N]
                                [--set window.X=Y ...] [--threads N]

Defaults: ``kitti00_0-159`` and ``7scenes_redkitchen_0-499`` from the shared data folder (``MGSO_DATA``). The CPU
runs are deterministic (bitwise), so one run per sequence and back end is the figure; DSO's reference numbers (issue
4: 0.572 m / 0.27 m all frames, 119 ms / 22-36 ms a frame on this 2-core machine) vary between its runs because of
its threads. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mgso.config import Config, apply_overrides  # noqa: E402
from mgso.eval import compute_ate  # noqa: E402
from mgso.io import open_sequence  # noqa: E402
from mgso.io.paths import shared_data_dir  # noqa: E402
from mgso.odometry import FrameStatus, Odometry, geometry_for  # noqa: E402
from mgso_kernels import runtime  # noqa: E402

DEFAULT = ("kitti00_0-159", "7scenes_redkitchen_0-499")


def _cpu_steal() -> tuple[int, int] | None:
    """(steal, total) jiffies of the machine from /proc/stat (Linux), None elsewhere: on a shared virtual machine the
    hypervisor's share (steal) slows every run, so a wall time is only comparable with one taken at the same share."""
    try:
        with open("/proc/stat") as fh:
            v = [int(x) for x in fh.readline().split()[1:]]
        return v[7], sum(v[:8])
    except (OSError, ValueError, IndexError):
        return None


def run_one(path: Path, cfg: Config, device: str, frames: int | None) -> dict:
    seq = open_sequence(path, config=cfg.input)
    cam = seq.calibration.output
    odo = Odometry(geometry_for(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cfg), cfg, device=device)
    n = 0
    map_ms = []
    kf_ms = []
    per_wall, per_cpu = [], []  # odo.process alone, a frame (decoding excluded)
    st0, c0 = _cpu_steal(), time.process_time()
    t0 = time.perf_counter()
    for f in seq.frames():
        if frames is not None and n >= frames:
            break
        w0, p0 = time.perf_counter(), time.process_time()
        r = odo.process(f)
        per_wall.append(time.perf_counter() - w0)
        per_cpu.append(time.process_time() - p0)
        if r.status == FrameStatus.TRACKED:
            map_ms.append(r.time_map_s * 1000)
            if r.keyframe_reason:
                kf_ms.append(r.time_map_s * 1000)
        n += 1
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    st1 = _cpu_steal()
    odo.finish()
    traj = odo.trajectory()
    out = {"frames": n, "frames_with_pose": len(traj), "segments": odo.segment + 1, "keyframes": len(odo.keyframes),
           "wall_s": round(wall, 1), "fps": round(n / wall, 3), "ms_per_frame": round(1000 * wall / max(n, 1), 1),
           "cpu_ms_per_frame": round(1000 * cpu / max(n, 1), 1),  # all threads of the process
           "steal_pct": (round(100 * (st1[0] - st0[0]) / max(st1[1] - st0[1], 1), 1) if st0 and st1 else None),
           "keyframe_map_ms_median": round(float(np.median(kf_ms)), 1) if kf_ms else None,
           # odo.process alone (decoding excluded): median and total over the frames, wall and process CPU time
           "process_wall_ms_median": round(1000 * float(np.median(per_wall)), 1) if per_wall else None,
           "process_cpu_ms_median": round(1000 * float(np.median(per_cpu)), 1) if per_cpu else None,
           "process_wall_s": round(float(np.sum(per_wall)), 2), "process_cpu_s": round(float(np.sum(per_cpu)), 2)}
    gt = seq.groundtruth
    if gt is not None and len(traj) >= 3:
        out["ate_all_frames_m"] = round(compute_ate(traj, gt, align="sim3").rmse, 4)
        kfs = odo.keyframe_trajectory()
        if len(kfs) >= 3:
            out["ate_keyframes_m"] = round(compute_ate(kfs, gt, align="sim3").rmse, 4)
        segs = []
        for s in range(odo.segment + 1):
            fr = [f for f in odo.frames if f.pose_valid and f.segment == s]
            if len(fr) >= 3 and odo.segment > 0:
                from mgso.io.trajectory import Trajectory

                st = Trajectory(np.array([f.timestamp for f in fr]),
                                np.stack([odo.to_world(s, f.cam_to_world) for f in fr]))
                segs.append(compute_ate(st, gt, align="sim3").rmse)
        if segs:
            out["segment_ate_median_m"] = round(float(np.median(segs)), 4)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--backends", default="bundle,fixed")
    ap.add_argument("--path", action="append", default=None)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--threads", type=int, default=None,
                    help="threads of the split kernel launches (runtime.set_cpu_threads; default: all cores)")
    args = ap.parse_args()
    device = runtime.init(args.device)
    if args.threads is not None:
        runtime.set_cpu_threads(args.threads)
    base = apply_overrides(Config(), args.set)
    paths = [Path(p) for p in args.path] if args.path else [shared_data_dir() / d for d in DEFAULT]
    out = {"profile": "odometry", "device": device, "cpu_threads": runtime.cpu_threads(),
           "load_avg_1min": round(os.getloadavg()[0], 2)}
    for path in paths:
        res = {}
        for be in args.backends.split(","):
            cfg = dataclasses.replace(base, window=dataclasses.replace(base.window, backend=be))
            res[be] = run_one(path, cfg, device, args.frames)
        out[path.name] = res
    out["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
