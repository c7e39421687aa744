"""Profile the Warp 3DGS rasteriser stage by stage; prints one JSON line.

    python profiles/splat_raster.py [--device cpu] [--sizes 320x240,640x480] [--counts 10000,50000,200000]
                                    [--repeats 5] [--threads 0] [--degree 0]

Scenes (fixed seed, so runs are comparable; TUM-like pinhole camera, fx = fy = 525 at 640x480, scaled with the
width; opacities sigmoid(N(1, 1.5)), median 0.73; SH degree 0 colours unless --degree):

- ``room`` (default): the camera inside a 6 x 3 x 6 m room with three boxes, surfaces at 1-5 m. 80% of the N
  splats lie on the surfaces the camera sees, spread evenly over the image, 20% on surfaces hidden behind them;
  splats are flat along their surface, with on-screen standard deviations log-uniform in 1-10 px (cut-off radii
  3-33 px). At 50k Gaussians and 640x480 the visible surface is covered a few times over, as in a trained map.
- ``volume``: a stress case, N Gaussians filling the frustum at 1-5 m with 1-20 px standard deviations; depth
  complexity grows with N (about 50 blended Gaussians per pixel at 50k, 640x480).

``--run DIR`` profiles a real run's map instead: ``DIR/map.ply`` rendered at the run's image size and intrinsics
(``sequence.json``) from ``--views`` poses spread evenly over ``DIR/trajectory.txt``; ``--sizes`` and ``--counts``
are ignored and the row's ``count`` is the map's size (medians over views and repeats); ``--downscale 2`` renders it
at half that size (the real-time mapper's coarse steps).

Per size and count: medians over ``--repeats`` (after one warm-up) of each stage in milliseconds: forward
``project``, ``bin_count`` (tile counting + prefix scan + reading the pair count), ``bin_keys`` (key emission),
``sort``, ``ranges`` (on the CPU part of ``sort``: its sort from the Gaussians' side makes them), ``sh``, ``pack``,
``blend``, ``forward_total``; backward ``backward_blend``, ``backward_gather``, ``backward_project`` (projection +
SH backward + pose reduction), ``backward_total``; ``alpha_only`` (the cheap coverage render); plus ``pairs`` and
``visible``; ``forward_cpu_ms`` / ``backward_cpu_ms``: median process CPU time of the forward / backward summed over
threads (the compute cost, which moves much less than wall time when other jobs share the cores).
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

from mgso_kernels import runtime  # noqa: E402
from mgso_kernels.splat import Rasterizer, make_camera  # noqa: E402


def _camera(width: int, height: int):
    f = 525.0 * width / 640.0
    return f, (width - 1) / 2.0, (height - 1) / 2.0


def _sh(rng, n, degree):
    K = (degree + 1) ** 2
    sh = np.zeros((n, K, 3))
    sh[:, 0] = rng.uniform(-1.5, 1.5, (n, 3))
    if K > 1:
        sh[:, 1:] = rng.normal(size=(n, K - 1, 3)) * 0.2
    return sh


# the room: walls of the box [-3, 3] x [-1.5, 1.5] x [-1, 5] (camera at the origin looking down +z, y down) and
# three boxes standing on the floor; (min corner, max corner)
_ROOM = (np.array([-3.0, -1.5, -1.0]), np.array([3.0, 1.5, 5.0]))
_BOXES = [(np.array([-1.8, 0.5, 1.8]), np.array([-0.6, 1.5, 2.8])),
          (np.array([0.4, -0.2, 2.5]), np.array([1.6, 1.5, 3.5])),
          (np.array([-0.5, 0.9, 3.6]), np.array([0.7, 1.5, 4.4]))]


def _first_hit(origin, dirs):
    """Distance along unit rays from inside the room to the first surface, and the surface normals."""
    n = len(dirs)
    t_best = np.full(n, np.inf)
    normal = np.zeros((n, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        # room walls: exit distance of the box the camera is in
        t_lo = (_ROOM[0] - origin) * inv
        t_hi = (_ROOM[1] - origin) * inv
        t_exit = np.maximum(t_lo, t_hi)
        axis = np.argmin(t_exit, 1)
        t_best = t_exit[np.arange(n), axis]
        normal[np.arange(n), axis] = -np.sign(dirs[np.arange(n), axis])
        for lo, hi in _BOXES:  # entry distance of each box
            t0 = (lo - origin) * inv
            t1 = (hi - origin) * inv
            tmin = np.minimum(t0, t1)
            tmax = np.maximum(t0, t1)
            t_in = tmin.max(1)
            hit = (t_in <= tmax.min(1)) & (t_in > 0) & (t_in < t_best)
            ax = np.argmax(tmin, 1)
            t_best = np.where(hit, t_in, t_best)
            nrm = np.zeros((n, 3))
            nrm[np.arange(n), ax] = -np.sign(dirs[np.arange(n), ax])
            normal = np.where(hit[:, None], nrm, normal)
    return t_best, normal


def room_scene(rng: np.random.Generator, n: int, width: int, height: int, degree: int = 0):
    """Splats on the surfaces of a room (see module doc): 80% on what the camera sees, spread evenly over the
    image, 20% on surfaces further along the same rays (occluded, as a real map has)."""
    from mgso.geometry import matrix_to_quat_wxyz

    f, cx, cy = _camera(width, height)
    u = rng.uniform(-0.02 * width, 1.02 * width, n)
    v = rng.uniform(-0.02 * height, 1.02 * height, n)
    dirs = np.stack([(u - cx) / f, (v - cy) / f, np.ones(n)], -1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t, normal = _first_hit(np.zeros(3), dirs)
    hidden = rng.random(n) < 0.2  # continue through the first surface to the next one
    if hidden.any():
        t2, n2 = _first_hit(dirs[hidden] * (t[hidden, None] + 1e-3), dirs[hidden])
        t[hidden] = t[hidden] + 1e-3 + t2
        normal[hidden] = n2
    means = dirs * t[:, None]
    z = means[:, 2]
    sig_px = np.exp(rng.uniform(np.log(1.0), np.log(10.0), (n, 2)))  # standard deviation on screen, pixels
    scales = np.concatenate([sig_px, sig_px.min(1, keepdims=True) * 0.1], 1) * (z / f)[:, None]
    # rotation whose third axis is the surface normal, random spin about it
    a = rng.normal(size=(n, 3))
    e1 = a - normal * np.sum(a * normal, 1, keepdims=True)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    quats = matrix_to_quat_wxyz(np.stack([e1, e2, normal], -1))
    scene = dict(means=means, log_scales=np.log(scales), quats=quats, opacity_logits=rng.normal(1.0, 1.5, n),
                 sh=_sh(rng, n, degree))
    scene = {k: np.asarray(v, np.float32) for k, v in scene.items()}
    return scene, make_camera(f, f, cx, cy, width, height, np.eye(4))


def volume_scene(rng: np.random.Generator, n: int, width: int, height: int, degree: int = 0):
    """A stress case: N Gaussians filling the view frustum at 1-5 m (depth complexity grows with N), flattened
    (two standard deviations log-uniform 1-20 px, the third 5-20x thinner), random rotations."""
    f, cx, cy = _camera(width, height)
    z = rng.uniform(1.0, 5.0, n)
    u = rng.uniform(-0.05 * width, 1.05 * width, n)
    v = rng.uniform(-0.05 * height, 1.05 * height, n)
    pc = np.stack([(u - cx) / f * z, (v - cy) / f * z, z], -1)
    sig_px = np.exp(rng.uniform(np.log(1.0), np.log(20.0), (n, 2)))
    thin = sig_px.min(1, keepdims=True) / rng.uniform(5.0, 20.0, (n, 1))
    scales = np.concatenate([sig_px, thin], 1) * (z / f)[:, None]
    scene = dict(means=pc, log_scales=np.log(scales), quats=rng.normal(size=(n, 4)),
                 opacity_logits=rng.normal(1.0, 1.5, n), sh=_sh(rng, n, degree))
    scene = {k: np.asarray(v, np.float32) for k, v in scene.items()}
    return scene, make_camera(f, f, cx, cy, width, height, np.eye(4))


def run_scene(run: str, views: int, device: str, downscale: int = 1):
    """A finished run's map (parameters as Warp arrays) and ``views`` cameras along its trajectory, at the run's
    image size divided by ``downscale`` (a pyramid level's camera: the real-time mapper's coarse steps)."""
    import json as _json
    from pathlib import Path

    import warp as wp

    from mgso.io.ply import read_gaussians_ply
    from mgso.io.trajectory import read_tum

    d = Path(run)
    for name in ("map.ply", "sequence.json", "trajectory.txt"):
        if not (d / name).is_file():
            raise SystemExit(f"splat_raster: {d / name}: missing (--run needs a finished `mgso run` folder)")
    g = read_gaussians_ply(d / "map.ply")
    info = _json.loads((d / "sequence.json").read_text())
    k = info["intrinsics"]
    width, height = (int(x) for x in (info.get("image_size_out") or info["image_size_in"]))
    traj = read_tum(d / "trajectory.txt")
    sh = np.asarray(g.sh, np.float32).reshape(len(g.means), -1, 3)
    params = [wp.array(np.ascontiguousarray(a, np.float32), device=device)
              for a in (g.means, g.log_scales, g.quats, g.opacity_logits, sh)]
    idx = np.linspace(0, len(traj) - 1, views + 2).round().astype(int)[1:-1]
    from mgso.camera import PinholeCamera

    cam = PinholeCamera(k["fx"], k["fy"], k["cx"], k["cy"], width, height)
    if downscale > 1:
        cam = cam.scaled(1.0 / downscale)
        width, height = cam.width, cam.height
    cams = [make_camera(cam.fx, cam.fy, cam.cx, cam.cy, width, height, np.linalg.inv(traj.cam_to_world[i]))
            for i in idx]
    return params, cams, width, height, len(g.means), int(round(np.sqrt(sh.shape[1]))) - 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="320x240,640x480")
    ap.add_argument("--counts", default="10000,50000,200000")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=0, help="CPU threads for split launches (0 = all cores)")
    ap.add_argument("--degree", type=int, default=0)
    ap.add_argument("--scene", choices=("room", "volume"), default="room")
    ap.add_argument("--run", help="profile this finished run's map.ply along its trajectory (see above)")
    ap.add_argument("--downscale", type=int, default=1, help="--run: render at the run's size / this (2: the "
                    "real-time mapper's 320x240 steps of a 640x480 run)")
    ap.add_argument("--views", type=int, default=4, help="--run: poses along the trajectory")
    ap.add_argument("--no-stages", action="store_true",
                    help="totals only: no synchronisation between stages (on a GPU the per-stage timing adds a "
                         "synchronisation per stage to the totals)")
    args = ap.parse_args(argv)
    device = runtime.init(args.device, threads=args.threads)
    import warp as wp

    results = []
    cases = []
    degree = args.degree
    if args.run:
        params, cams, width, height, count, degree = run_scene(args.run, args.views, device, args.downscale)
        cases.append((params, cams, width, height, count))
    else:
        for size in args.sizes.split(","):
            width, height = (int(s) for s in size.lower().split("x"))
            for count in (int(c) for c in args.counts.split(",")):
                rng = np.random.default_rng(1234)
                make = room_scene if args.scene == "room" else volume_scene
                scene, cam = make(rng, count, width, height, args.degree)
                params = [wp.array(scene[k], dtype=wp.float32, device=device)
                          for k in ("means", "log_scales", "quats", "opacity_logits", "sh")]
                cases.append((params, [cam], width, height, count))
    for params, cam_list, width, height, count in cases:
        rng = np.random.default_rng(1234)
        v_rgb = wp.array(rng.normal(size=(height, width, 3)).astype(np.float32) * 1e-3, device=device)
        v_depth = wp.array(rng.normal(size=(height, width)).astype(np.float32) * 1e-3, device=device)
        rast = Rasterizer(device, profile=not args.no_stages)
        fwd, bwd, alpha_only, cpu_f, cpu_b = [], [], [], [], []
        out = None
        pairs = []
        for rep, cam in ((r, c) for c in cam_list for r in range(args.repeats + 1)):
            c0, t0 = time.process_time(), time.perf_counter()
            out = rast.forward(*params, cam)
            wp.synchronize_device(device)
            c1, t1 = time.process_time(), time.perf_counter()
            f_t = dict(rast.timings if not args.no_stages else {}, forward_total=t1 - t0)
            rast.backward(out, v_rgb, v_depth)
            wp.synchronize_device(device)
            c2, t2 = time.process_time(), time.perf_counter()
            b_t = dict(rast.timings if not args.no_stages else {}, backward_total=t2 - t1)
            t3 = time.perf_counter()
            rast.render_alpha(*params[:4], cam)
            wp.synchronize_device(device)
            a_t = time.perf_counter() - t3
            if rep > 0:  # the first run (of each view) allocates and (maybe) compiles
                pairs.append(out.n_pairs)
                fwd.append(f_t)
                bwd.append(b_t)
                alpha_only.append(a_t)
                cpu_f.append(c1 - c0)
                cpu_b.append(c2 - c1)
        row = {"size": f"{width}x{height}", "count": count,
               "pairs": int(statistics.median(pairs)) if pairs else 0,
               "visible": out.num_visible if out else 0}
        for runs in (fwd, bwd):
            for key in runs[0]:
                row[key + "_ms"] = round(1e3 * statistics.median(r[key] for r in runs), 2)
        row["alpha_only_ms"] = round(1e3 * statistics.median(alpha_only), 2)
        row["forward_cpu_ms"] = round(1e3 * statistics.median(cpu_f), 2)
        row["backward_cpu_ms"] = round(1e3 * statistics.median(cpu_b), 2)
        results.append(row)
    print(json.dumps({"profile": "splat_raster", "device": device, "threads": runtime.cpu_threads(),
                      "repeats": args.repeats, "sh_degree": degree, "scene": args.run or args.scene,
                      "cpu": platform.processor() or
                      platform.machine(), "results": results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
