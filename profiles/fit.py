"""Profile one full training step of the Gaussian map (mgso.mapping.trainer.TrainStep); prints one JSON line.

    python profiles/fit.py [--device cpu] [--sizes 320x240,640x480] [--counts 10000,50000] [--steps 10]
                           [--threads 0]

Scene: the synthetic textured room (mgso.synthetic, 4 views along its path). The map is N Gaussians on the visible
surfaces (back-projected from the views' true depth, drawn at random), kNN scales (3DGS's rule), random rotations
and anisotropy (log-scale noise 0.3), opacities sigmoid(N(1, 1.5)) (median 0.73) and the pixels' colours: the shape
of a trained map, so blending and backward work like they do late in training, not like a fresh random init.

Per size and count, over ``--steps`` steps after two warm-up steps (views taken in turn, densification statistics
accumulated as while refining, but no refine pass so that N stays fixed): the median of each stage of
:attr:`StepResult.times` in milliseconds, ``render`` (projection, binning, sort, SH, blending), ``loss``
(L1 + D-SSIM forward and backward), ``backward`` (rasteriser backward, gradient copy into the map, statistics),
``adam`` (fused Adam over all Gaussians), ``strategy`` (the densification hook on a non-refine step), their sum
``step_ms`` and ``it_per_s = 1000 / step_ms``; ``refine_ms``: one refine pass (clone / split / prune through the map's
operations) at this N, which 3DGS runs every 100 steps; ``visible``: median Gaussians in view; ``cpu_ms``: median
process CPU time of a step summed over threads (the compute cost, steadier than wall time on a shared machine);
``pairs``: median (tile, Gaussian) pairs a render blends, and ``pairs_per_px`` the same a pixel (pairs x 256 / pixels:
the list entries a pixel could visit), what bounds the rasteriser's cost (docs/rasteriser.md, "The arithmetic
against the time"); ``launches_per_step``, ``memsets_per_step``, ``scans_per_step``, ``host_reads_per_step`` and
``syncs_per_step``: what one more step, untimed, sent to the device (:func:`mgso_kernels.runtime.count_device_calls`:
a split CPU launch counts once a chunk; on CUDA every host read waits for the device).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from mgso import synthetic  # noqa: E402
from mgso.camera import PinholeCamera  # noqa: E402
from mgso.config import load_config  # noqa: E402
from mgso.geometry import quat_normalize, se3_inverse  # noqa: E402
from mgso.mapping.gaussian_map import GaussianMap  # noqa: E402
from mgso.mapping.init import gaussians_from_points  # noqa: E402
from mgso.mapping.strategy import DefaultStrategy  # noqa: E402
from mgso.mapping.trainer import STAGES, Trainer  # noqa: E402
from mgso.mapping.views import TrainView, ViewSet  # noqa: E402
from mgso_kernels import runtime  # noqa: E402

FRAMES = (0, 20, 40, 60)


def _scene(width: int, height: int):
    spec = synthetic.SequenceSpec(num_frames=61, width=width, height=height, seed=0)
    scene, k, traj = spec.scene(), spec.intrinsics, spec.trajectory()
    views, pts, cols = ViewSet(), [], []
    cam = PinholeCamera(k.fx, k.fy, k.cx, k.cy, width, height)
    for i in FRAMES:
        img, depth = synthetic.render(scene, k, traj.cam_to_world[i])
        views.add(TrainView(i, img, cam, se3_inverse(traj.cam_to_world[i])))
        p, c = synthetic.depth_to_points(depth, k, traj.cam_to_world[i], img)
        pts.append(p)
        cols.append(c)
    return views, np.concatenate(pts), np.concatenate(cols)


def _map(points, colors, n, device, cfg, rng):
    sel = rng.choice(len(points), size=n, replace=n > len(points))
    g = gaussians_from_points(points[sel] + rng.normal(0, 1e-3, (n, 3)), colors[sel], sh_degree=0)
    g.log_scales += rng.normal(0.0, 0.3, g.log_scales.shape).astype(np.float32)
    g.quats[:] = quat_normalize(rng.normal(size=(n, 4))).astype(np.float32)
    g.opacity_logits[:] = rng.normal(1.0, 1.5, n).astype(np.float32)
    return GaussianMap.from_arrays(g, capacity=2 * n + 16, device=device, optim=cfg.optim)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="320x240,640x480")
    ap.add_argument("--counts", default="10000,50000")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=0)
    args = ap.parse_args()
    device = runtime.init(args.device, threads=args.threads)
    rng = np.random.default_rng(0)
    cfg = load_config(None, ["mapping.densify.refine_start_step=1000000000", "mapping.train.metrics_every=0",
                             "mapping.train.sh_degree_interval=0"]).mapping
    out: dict = {"profile": "fit", "device": device, "machine": platform.processor() or platform.machine(),
                 "threads": runtime.cpu_threads(), "steps": args.steps, "results": {}}
    for size in args.sizes.split(","):
        w, h = (int(v) for v in size.split("x"))
        views, points, colors = _scene(w, h)
        for n in (int(c) for c in args.counts.split(",")):
            gmap = _map(points, colors, n, device, cfg, rng)
            tr = Trainer(gmap, views, cfg, timing=True)
            ids = views.ids()
            for k in range(2):                                    # warm-up (compiles / loads kernels once)
                tr.step(ids[k % len(ids)])
            per = {s: [] for s in STAGES}
            totals, cpu, visible, pairs = [], [], [], []
            for k in range(args.steps):
                c0 = time.process_time()
                r = tr.step(ids[k % len(ids)])
                cpu.append((time.process_time() - c0) * 1e3)
                for s in STAGES:
                    per[s].append(r.times[s] * 1e3)
                totals.append(sum(r.times.values()) * 1e3)
                visible.append(r.num_visible)
                pairs.append(r.num_pairs)
            # one more step, counted: what reaches the device in a step as the mapper takes it (no stage timing,
            # which synchronises a GPU after each stage)
            tr.train_step._sync = False
            with runtime.count_device_calls() as calls:
                tr.step(ids[args.steps % len(ids)])
            strategy = DefaultStrategy(load_config(None, ["mapping.densify.refine_start_step=0",
                                                          "mapping.densify.refine_every=1"]).mapping.densify)
            t0 = time.perf_counter()
            refine = strategy.step_post_backward(gmap, strategy.initialize_state(0), 1)
            refine_ms = (time.perf_counter() - t0) * 1e3
            step_ms = statistics.median(totals)
            res = {f"{s}_ms": round(statistics.median(per[s]), 2) for s in STAGES}
            res.update(step_ms=round(step_ms, 2), it_per_s=round(1e3 / step_ms, 3),
                       cpu_ms=round(statistics.median(cpu), 1), visible=int(statistics.median(visible)),
                       refine_ms=round(refine_ms, 1), refine_grew=refine.cloned + refine.split,
                       pairs=int(statistics.median(pairs)),
                       pairs_per_px=round(statistics.median(pairs) * 256 / (w * h), 1),
                       **{f"{k}_per_step": v for k, v in calls.as_dict().items()})
            out["results"][f"{w}x{h}/{n}"] = res
    print(json.dumps(out))


if __name__ == "__main__":
    main()
