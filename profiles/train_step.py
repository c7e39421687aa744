"""Where a training step's time goes on a finished run's map, level by level and by thread count; prints one JSON line.

    python profiles/train_step.py RUN_DIR [--sequence PATH] [--levels 2,1,0] [--threads 1,2] [--steps 60]

``RUN_DIR`` is an ``mgso run`` output folder (``map.ply``, ``keyframes.txt``, ``sequence.json`` or ``--sequence``;
``profiles/mapping.py``'s replays are such folders). Its map is trained on its keyframes at their poses with the
run's default configuration (:class:`mgso.mapping.trainer.Trainer`, each variant from the same map, its step count
past the densification schedule so that the map does not change size), at each pyramid level of ``--levels`` (2: a
640x480 camera's 160x120) and with each CPU thread count of ``--threads``. After a warm-up that takes every view once
at the level (its image's pyramid level is made then), ``--steps`` steps are timed. Per level and thread count, in
milliseconds a step (medians over the steps):

- ``step_ms`` (wall), ``cpu_ms`` (the process's CPU over all threads);
- the step's stages as :class:`~mgso.mapping.trainer.TrainStep` times them (``render``, ``loss``, ``backward``,
  ``adam``, ``strategy``);
- ``kernels_ms``: the launching thread's time inside Warp's kernel calls (every single launch and the launching
  thread's own chunk of a split one), ``launches``: their number a step, and ``outside_kernels_ms`` = ``step_ms`` -
  ``kernels_ms``: the Python between the kernels, plus, with several threads, the waits for the other chunks of split
  launches. On one thread that difference is the step's Python alone (docs/rasteriser.md, "Python between the
  kernels"). ``kernels_ms`` needs Warp's CPU entry point (``warp._src.context.invoke``); where a Warp version has
  none, it and ``launches`` are null.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--sequence", type=Path, default=None, help="the recording (default: sequence.json's path)")
    ap.add_argument("--levels", default="2,1,0")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--steps", type=int, default=60)
    args = ap.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    from mgso.config import load_config
    from mgso.geometry import se3_inverse
    from mgso.io import open_sequence, read_trajectory
    from mgso.mapping.fit import load_initial_gaussians
    from mgso.mapping.gaussian_map import GaussianMap
    from mgso.mapping.trainer import Trainer
    from mgso.mapping.views import TrainView, ViewSet
    from mgso_kernels import runtime

    runtime.init("cpu")
    seq_path = args.sequence or Path(json.loads((args.run / "sequence.json").read_text())["path_absolute"])
    seq = open_sequence(str(seq_path))
    cfg = load_config()
    kf = read_trajectory(str(args.run / "keyframes.txt"))
    pose_of = {round(float(t), 6): T for t, T in zip(kf.timestamps, kf.cam_to_world)}
    cam = seq.calibration.output
    views = ViewSet()
    for i in range(len(seq)):
        T = pose_of.get(round(float(seq.timestamps[i]), 6))
        if T is not None:
            frame = seq.load(i)
            views.add(TrainView(i, frame.rgb, cam, se3_inverse(T), timestamp=frame.timestamp))
    if not len(views):
        raise SystemExit(f"{args.run}: no keyframe of keyframes.txt is a frame of {seq_path}")
    mc = cfg.mapping
    arrays, _ = load_initial_gaussians(str(args.run / "map.ply"), views, cfg)

    # the launching thread's time inside Warp's CPU kernel calls
    try:
        from warp._src import context as wctx
        real_invoke = wctx.invoke
    except (ImportError, AttributeError):
        wctx = real_invoke = None
    acc = {"s": 0.0, "n": 0, "thread": None}

    def invoke(*a, **k):
        if threading.get_ident() != acc["thread"]:
            return real_invoke(*a, **k)
        t = time.perf_counter()
        try:
            return real_invoke(*a, **k)
        finally:
            acc["s"] += time.perf_counter() - t
            acc["n"] += 1

    if wctx is not None:
        wctx.invoke = invoke
    acc["thread"] = threading.get_ident()

    results: dict = {}
    start = max(mc.densify.refine_stop_step, mc.densify.reset_every) + 1000   # past the densification schedule
    for level in [int(x) for x in args.levels.split(",") if x]:
        for threads in [int(x) for x in args.threads.split(",") if x]:
            gmap = GaussianMap.from_arrays(arrays, capacity=max(mc.capacity, arrays.n), device="cpu", optim=mc.optim)
            trainer = Trainer(gmap, views, mc, seed=0, timing=True, start_step=start)
            walls, cpus, kernels, launches, stages = [], [], [], [], {}
            size = None
            with runtime.cpu_threads_here(threads):
                for v in list(views):
                    trainer.step(view_id=v.view_id, min_level=level)
                for _ in range(args.steps):
                    acc["s"], acc["n"] = 0.0, 0
                    t0, c0 = time.perf_counter(), time.process_time()
                    r = trainer.step(min_level=level)
                    walls.append(time.perf_counter() - t0)
                    cpus.append(time.process_time() - c0)
                    kernels.append(acc["s"])
                    launches.append(acc["n"])
                    for name, sec in r.times.items():
                        stages.setdefault(name, []).append(sec)
                    size = f"{r.width}x{r.height}"
            med = lambda x: round(1e3 * float(np.median(x)), 3)
            out = {"step_ms": med(walls), "cpu_ms": med(cpus), **{f"{k}_ms": med(v) for k, v in stages.items()}}
            if wctx is not None:
                out.update(kernels_ms=med(kernels), launches=float(np.median(launches)),
                           outside_kernels_ms=med(np.array(walls) - np.array(kernels)))
            else:
                out.update(kernels_ms=None, launches=None, outside_kernels_ms=None)
            results.setdefault(size, {})[str(threads)] = out
    if wctx is not None:
        wctx.invoke = real_invoke
    print(json.dumps({"profile": "train_step", "run": str(args.run), "sequence": str(seq_path),
                      "gaussians": int(arrays.n), "views": len(views), "steps": args.steps, "results": results,
                      "load_avg_1min": os.getloadavg()[0]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
