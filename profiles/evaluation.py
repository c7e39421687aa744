"""The render evaluation of a finished run (both protocols), one pass against two; prints one JSON line.

    python profiles/evaluation.py RUN_DIR [--sequence PATH] [--repeats 2] [--frames N]
        [--modes one-pass,per-core,two-pass]

``RUN_DIR`` is an ``mgso run`` output folder (``map.ply``, ``trajectory.txt``, ``keyframes.txt``,
``sequence.json`` or ``--sequence``). Its map is rendered at the poses ``mgso run`` renders at
(``trajectory_refined.txt`` where the run wrote one, else ``trajectory.txt``), without exposure (a multiply-add a
pixel), and evaluated under the MonoGS and Photo-SLAM protocols as ``mgso run`` does:

- ``one-pass``: :func:`mgso.eval.evaluate_protocols` -- each frame rendered once for both protocols, its figures
  taken in a worker thread while the next frame renders (``mgso run`` since 2026-12-05);
- ``per-core``: :func:`mgso.eval.evaluate_protocols` with a render function a core, each on one thread with a
  rasteriser of its own, a frame each in flight (``mgso run`` on the CPU since 2026-12-06);
- ``two-pass``: :func:`mgso.eval.evaluate_renders` once per protocol, every frame of each rendered for it (``mgso
  run`` before). Only this mode runs on an older tree (``PYTHONPATH=OLD_TREE``): then it measures the old metrics.

The modes alternate repeat by repeat; per mode the median, minimum and maximum wall seconds and the process CPU
seconds; the figures of each mode (they must agree); and, from a separate pass over ``--parts-frames`` frames, what
one frame costs: render, reference image, PSNR, SSIM (milliseconds, medians). The renders' PNGs are not written
(``output.save_renders`` adds one PNG encode per MonoGS frame).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--sequence", type=Path, default=None, help="the recording (default: sequence.json's path)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--frames", type=int, default=0, help="only the first N frames with a pose (0: all)")
    ap.add_argument("--parts-frames", type=int, default=20)
    ap.add_argument("--modes", default="one-pass,two-pass")
    args = ap.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    from mgso import eval as ev
    from mgso.geometry import se3_inverse
    from mgso.io import open_sequence, read_trajectory
    from mgso.io.ply import read_gaussians_ply
    from mgso.mapping.trainer import TrainStep
    from mgso_kernels.splat import Rasterizer

    seq_path = args.sequence or Path(json.loads((args.run / "sequence.json").read_text())["path_absolute"])
    seq = open_sequence(str(seq_path))
    g = read_gaussians_ply(args.run / "map.ply")
    # the poses mgso run renders at: the refined trajectory where the map refined keyframe poses (the run's
    # metrics.json, protocols.render_poses), else the odometry's
    refined = args.run / "trajectory_refined.txt"
    traj = read_trajectory(str(refined if refined.is_file() else args.run / "trajectory.txt"))
    kf = read_trajectory(str(args.run / "keyframes.txt"))
    cam = seq.calibration.output
    rast = Rasterizer()
    params = [wp.array(x, dtype=wp.float32, device="cpu") for x in (g.means, g.log_scales, g.quats,
                                                                     g.opacity_logits, g.sh)]
    pose_of = {round(float(t), 6): T for t, T in zip(traj.timestamps, traj.cam_to_world)}
    kf_times = {round(float(t), 6) for t in kf.timestamps}
    tracked, keyframes, w2c = [], [], {}
    for i in range(len(seq)):
        t = round(float(seq.timestamps[i]), 6)
        if t in pose_of:
            tracked.append(i)
            w2c[i] = se3_inverse(pose_of[t])
            if t in kf_times:
                keyframes.append(i)
    if args.frames:
        tracked = tracked[:args.frames]

    # the colour alone, as mgso run renders for its evaluation (a tree older than rgb_only renders everything)
    import inspect
    rgb_kw = {"rgb_only": True} if "rgb_only" in inspect.signature(Rasterizer.forward).parameters else {}

    def render(i, r=rast):
        out = r.forward(*params, TrainStep.camera_struct(cam, w2c[i]), (0.0, 0.0, 0.0), **rgb_kw)
        return np.array(out.rgb.numpy(), np.float32)

    from mgso_kernels import runtime
    cores = runtime.cpu_threads()

    def on_one_thread(r):
        def f(i):
            with runtime.cpu_threads_here(1):
                return render(i, r)
        return f

    def reference(i):
        return seq.load(i).rgb

    sel = {p: ev.select_frames(p, tracked, keyframes) for p in (ev.MONOGS, ev.PHOTO_SLAM)}

    def one_pass():
        return ev.evaluate_protocols(sel, render, reference)

    def two_pass():
        return [ev.evaluate_renders(((render(i), reference(i)) for i in frames), frames, p)
                for p, frames in sel.items()]

    def per_core():
        renders = [on_one_thread(Rasterizer()) for _ in range(cores)]
        return ev.evaluate_protocols(sel, renders, reference)

    runs = {"one-pass": one_pass, "two-pass": two_pass, "per-core": per_core}
    modes = [m for m in args.modes.split(",") if m]
    wall = {m: [] for m in modes}
    cpu = {m: [] for m in modes}
    figures = {}
    render(tracked[0])                                   # compile / warm up
    for _ in range(args.repeats):
        for m in modes:
            t0, c0 = time.perf_counter(), time.process_time()
            res = runs[m]()
            wall[m].append(time.perf_counter() - t0)
            cpu[m].append(time.process_time() - c0)
            figures[m] = {r.protocol_key: {"frames": r.num_frames, "psnr_db": r.mean_psnr, "ssim": r.mean_ssim}
                          for r in res}
    # the SSIM as the protocols take it (float32 since 2026-12-05; an older tree has only float64)
    from mgso.eval import render_metrics as rm
    ssim_kw = {"dtype": rm.PROTOCOL_SSIM_DTYPE} if hasattr(rm, "PROTOCOL_SSIM_DTYPE") else {}
    parts = {"render": [], "reference": [], "psnr": [], "ssim": []}
    for i in tracked[:: max(1, len(tracked) // max(1, args.parts_frames))][:args.parts_frames]:
        t0 = time.perf_counter()
        x = render(i)
        t1 = time.perf_counter()
        y = reference(i)
        t2 = time.perf_counter()
        ev.psnr(x, y)
        t3 = time.perf_counter()
        ev.ssim(x, y, border="valid", **ssim_kw)
        t4 = time.perf_counter()
        for k, v in zip(parts, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            parts[k].append(v * 1000)
    out = {"profile": "evaluation", "run": str(args.run), "sequence": str(seq_path), "gaussians": int(len(g.means)),
           "size": f"{cam.width}x{cam.height}", "frames_with_pose": len(tracked),
           "frames": {p.key: len(f) for p, f in sel.items()}, "repeats": args.repeats,
           "modes": {m: {"wall_s": {"median": statistics.median(wall[m]), "min": min(wall[m]), "max": max(wall[m])},
                         "cpu_s_median": statistics.median(cpu[m]), "figures": figures[m]} for m in modes},
           "frame_ms": {k: round(statistics.median(v), 2) for k, v in parts.items()},
           "load_avg_1min": os.getloadavg()[0]}
    if len(modes) == 2:
        a, b = (statistics.median(wall[m]) for m in modes)
        out["wall_ratio"] = b / a
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
