"""Time of one window optimisation per keyframe (the bundle-adjustment back end, :mod:`mgso.window.backend`) on a
window of the synthetic room: 7 keyframes and about 2000 active points (DSO's sizes), every point with a residual in
every other keyframe, poses 4 mm / depths 5 % off the truth.

Each repeat restores the same window and runs what the odometry runs on a keyframe: ``optimize`` (energy threshold,
Levenberg-Marquardt, write-back) and ``marginalize_points`` (one keyframe flagged: its points folded into the prior)
and ``marginalize_frames``. Reported per stage (medians and p90 over repeats, milliseconds): ``linearize`` (pair
residuals + key blocks + Schur, all linearisations of the call, summed), ``solve`` (reduced system, summed),
``threshold`` (the new keyframe's energy threshold), ``optimize`` (whole call), ``marginalize`` (points + frame), and
per linearisation the split ``pairs_kernel`` / ``schur`` / ``assemble`` (one call each, repeated).

    python profiles/window.py [--device cpu] [--repeats 7] [--points 2000] [--size 640x480]

Prints one JSON line. The development machine is shared: the load average is in the output.
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
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "window"))

from mgso import synthetic  # noqa: E402
from mgso.window.backend import WindowOptimizer  # noqa: E402
from mgso.config import WindowConfig  # noqa: E402
from mgso.window.energy import WindowProblem  # noqa: E402
from mgso_kernels import runtime  # noqa: E402
from mgso_kernels import window as kw  # noqa: E402
from window_helpers import window_from_sequence  # noqa: E402


def stats(xs):
    xs = np.asarray(xs, float)
    return {"median": round(float(np.median(xs)), 2), "p90": round(float(np.percentile(xs, 90)), 2)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--points", type=int, default=2000)
    ap.add_argument("--size", default="640x480")
    args = ap.parse_args()
    device = runtime.init(args.device)
    W, H = (int(v) for v in args.size.split("x"))
    frames = [0, 3, 6, 9, 12, 15, 18]
    seq = synthetic.make_sequence(seed=0, num_frames=frames[-1] + 1, width=W, height=H)
    w, _ = window_from_sequence(seq, frames, points_per_kf=args.points // len(frames), pose_noise=0.004,
                                depth_noise=0.05)
    a = w.active
    snap = (w.world_to_cam_.copy(), w.world_to_cam_zero_.copy(), w.affine_.copy(), w.affine_zero_.copy(),
            w.energy_th_.copy(), w.flagged_.copy(), w.points_left_.copy(), list(w.order), w.used_.copy(),
            w.keyframe_id_.copy(), {f.name: getattr(a, f.name + "_").copy() for f in a.fields()}, a.n)

    def restore():
        (w.world_to_cam_[:], w.world_to_cam_zero_[:], w.affine_[:], w.affine_zero_[:], w.energy_th_[:],
         w.flagged_[:], w.points_left_[:]) = snap[:7]
        w.order[:] = snap[7]
        w.used_[:] = snap[8]
        w.keyframe_id_[:] = snap[9]
        for name, arr in snap[10].items():
            getattr(a, name + "_")[:] = arr
        a.n = snap[11]

    out = {"profile": "window", "device": device, "cpu_threads": runtime.cpu_threads(),
           "load_avg_1min": round(os.getloadavg()[0], 2), "size": [W, H], "keyframes": len(frames),
           "points": int(a.n), "residuals": int(np.sum(a.res_state == 1))}
    times = {k: [] for k in ("optimize", "linearize", "solve", "threshold", "marginalize", "iterations",
                             "accepted")}
    s = WindowConfig()
    for rep in range(args.repeats + 1):
        restore()
        be = WindowOptimizer(s, device=device)
        t0 = time.perf_counter()
        r = be.optimize(w)
        t1 = time.perf_counter()
        w.flagged_[w.order[1]] = True  # as if flagFramesForMarginalization had chosen the second keyframe
        be.marginalize_points(w)
        be.marginalize_frames(w)
        t2 = time.perf_counter()
        if rep == 0:
            continue  # warm-up: Warp module load
        times["optimize"].append((t1 - t0) * 1000)
        times["marginalize"].append((t2 - t1) * 1000)
        times["linearize"].append(r.times_ms.get("linearize", 0.0))
        times["solve"].append(r.times_ms.get("solve", 0.0))
        times["threshold"].append(r.times_ms.get("threshold", 0.0))
        times["iterations"].append(r.iterations)
        times["accepted"].append(r.accepted)
    out.update({k: stats(v) for k, v in times.items()})
    # one linearisation split into its parts
    restore()
    p = WindowProblem(w, s, None, first_slots=(w.order[0],), device=device)
    parts = {"pairs_kernel": [], "schur": [], "assemble": [], "linearize_one": [], "solve_one": []}
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        keys = p.keys()
        lin = p.linearize_pairs(keys)
        t1 = time.perf_counter()
        eh, eb = p.point_extras()
        kw.schur_points(lin, keys, p.pair_key, p.point_start, p.K, eh, eb, device=device)
        t2 = time.perf_counter()
        p.top_system(keys, lin)
        t3 = time.perf_counter()
        L = p.linearize()
        t4 = time.perf_counter()
        p.solve(L, 0.1)
        t5 = time.perf_counter()
        parts["pairs_kernel"].append((t1 - t0) * 1000)
        parts["schur"].append((t2 - t1) * 1000)
        parts["assemble"].append((t3 - t2) * 1000)
        parts["linearize_one"].append((t4 - t3) * 1000)
        parts["solve_one"].append((t5 - t4) * 1000)
    out.update({k: stats(v) for k, v in parts.items()})
    out["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
