"""Profile the seeding's coverage render on a run's map; prints one JSON line.

    python profiles/coverage.py RUN_DIR [--views 9] [--repeats 3] [--downscale 2] [--threads 1] [--t-stop 0.01]

``RUN_DIR`` is an ``mgso run`` output folder (``map.ply``, ``keyframes.txt``, ``sequence.json``). Its map is rendered
from ``--views`` evenly spaced keyframes at 1/``--downscale`` resolution (the camera recipe of
``mgso.mapping.seeding.render_coverage``), the three variants interleaved view by view, ``--repeats`` rounds after a
warm-up:

- ``forward``: the full forward with colours (the coverage render before 2026-12-03);
- ``alpha_depth``: ``Rasterizer.render_alpha(with_depth=True)`` (the same alpha and depth);
- ``alpha_depth_stop``: the same with ``t_stop`` (``mapping.seeding.coverage_stop``).

Per variant: the median, smallest and largest milliseconds of the render and of its blending. And what the stop
changes against the forward, over the views: the largest alpha change where the forward's alpha is below 0.98,
the pixels that changed side of the visibility threshold (0.5), and the median and 99th percentile of the relative
change of the expected depth (depth / alpha) where alpha > 0.5.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from mgso_kernels import runtime  # noqa: E402


def _poses(keyframes: Path, views: int) -> list[np.ndarray]:
    from scipy.spatial.transform import Rotation

    from mgso.geometry import se3_inverse

    rows = np.atleast_2d(np.loadtxt(keyframes))
    pick = np.unique(np.linspace(0, len(rows) - 1, min(views, len(rows))).round().astype(int))
    out = []
    for r in rows[pick]:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(r[4:8]).as_matrix()
        T[:3, 3] = r[1:4]
        out.append(se3_inverse(T))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--views", type=int, default=9)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="CPU threads of the kernels (0: all)")
    ap.add_argument("--t-stop", type=float, default=0.01)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    run = Path(args.run_dir)
    for name in ("map.ply", "keyframes.txt", "sequence.json"):
        if not (run / name).is_file():
            sys.exit(f"profiles/coverage.py: {run / name}: missing (give an mgso run output folder)")

    device = runtime.init(args.device)
    if args.threads > 0:
        runtime.set_cpu_threads(args.threads)
    from mgso.io.ply import read_gaussians_ply
    from mgso.mapping.gaussian_map import GaussianMap
    from mgso_kernels.splat import Rasterizer, make_camera

    seq = json.loads((run / "sequence.json").read_text())
    k, (W, H) = seq["intrinsics"], seq["image_size_out"]
    s = args.downscale
    gmap = GaussianMap.from_arrays(read_gaussians_ply(run / "map.ply"), device=device)
    p = gmap.float_params()
    rast = Rasterizer(device=device)
    rast.profile = True
    poses = _poses(run / "keyframes.txt", args.views)

    def camera(w2c):
        return make_camera(k["fx"] / s, k["fy"] / s, (k["cx"] + 0.5) / s - 0.5, (k["cy"] + 0.5) / s - 0.5, W // s,
                           H // s, w2c)

    def forward(w2c):
        o = rast.forward(p.means, p.log_scales, p.quats, p.opacity_logits, p.sh, camera(w2c), (0.0, 0.0, 0.0),
                         sh_degree=0)
        return o.alpha.numpy().copy(), o.depth.numpy().copy()

    def alpha_depth(w2c, t_stop=0.0):
        o = rast.render_alpha(p.means, p.log_scales, p.quats, p.opacity_logits, camera(w2c), with_depth=True,
                              t_stop=t_stop)
        return o.alpha.numpy().copy(), o.depth.numpy().copy()

    variants = {"forward": forward, "alpha_depth": alpha_depth,
                "alpha_depth_stop": lambda w2c: alpha_depth(w2c, args.t_stop)}
    for f in variants.values():      # warm-up: kernels loaded, buffers grown
        f(poses[0])
    ms = {v: [] for v in variants}
    blend = {v: [] for v in variants}
    for _ in range(args.repeats):
        for w2c in poses:
            for name, f in variants.items():
                t = time.perf_counter()
                f(w2c)
                ms[name].append(1e3 * (time.perf_counter() - t))
                blend[name].append(1e3 * rast.timings.get("blend", 0.0))
    alpha_err, flipped, rel = 0.0, 0, []
    for w2c in poses:
        a0, d0 = forward(w2c)
        a1, d1 = alpha_depth(w2c, args.t_stop)
        thin = a0 < 0.98
        if thin.any():
            alpha_err = max(alpha_err, float(np.abs(a1 - a0)[thin].max()))
        flipped += int(((a0 >= 0.5) != (a1 >= 0.5)).sum())
        m = (a1 > 0.5) & (a0 > 0.5)
        e0, e1 = d0[m] / a0[m], d1[m] / a1[m]
        rel.append(np.abs(e1 - e0) / np.maximum(np.abs(e0), 1e-9))
    rel = np.concatenate(rel) if rel else np.zeros(1)
    out = {
        "profile": "coverage", "run": str(run), "machine": platform.machine(), "cpu_count": os.cpu_count(),
        "device": device, "threads": args.threads, "gaussians": int(gmap.n), "views": len(poses),
        "size": [W // s, H // s], "t_stop": args.t_stop, "repeats": args.repeats,
        "load_avg_1min": round(os.getloadavg()[0], 2),
        **{f"{v}_ms": {"median": round(statistics.median(x), 1), "min": round(min(x), 1), "max": round(max(x), 1)}
           for v, x in ms.items()},
        **{f"{v}_blend_ms": round(statistics.median(x), 1) for v, x in blend.items()},
        "stop_alpha_change_below_098": alpha_err, "stop_pixels_changed_side_of_05": flipped,
        "stop_expected_depth_rel_change_median": float(np.median(rel)),
        "stop_expected_depth_rel_change_p99": float(np.percentile(rel, 99)),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
