"""Measure MGSO's seeding on the synthetic scene: fill depth rule (mean vs barycentric), no fill, random init.

For every keyframe of a synthetic sequence (every ``--kf-every``-th frame) the script selects DSO-like points with
DSO's pixel selector (``mgso.tracking.pixel_selector``) on the keyframe, gives them the true inverse depth times
``1 + N(0, --idepth-noise)`` (DSO's depths are not exact), seeds the map with :func:`mgso.mapping.seeding.seed_keyframe`
(visibility filter against the map trained so far), and trains ``--iters-per-kf`` steps on the keyframes seen so
far (L1 + D-SSIM, Adam, no densification: the initialisation is what is compared); then ``--final-iters`` steps.
The ``random`` variant adds, at each keyframe, as many random points in that keyframe's frustum (uniform pixel,
uniform depth in the scene's true depth range) as the ``barycentric`` variant added there.

Printed, one JSON line: the fill's depth error for mean and barycentric depth over several ``fill_max_depth_ratio``
values (``geometry``, no training), and per variant the PSNR on held-out frames (every frame that is not a keyframe,
at its true pose), the Gaussians in the map, the seeding counts, and the fill points' depth error against the true
depth (median / 90th percentile of |z - z_true| / z_true, share above 5 % and 20 %); plus the settings.

    python profiles/seeding_fill.py --variants mean,barycentric,nofill,random
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from types import SimpleNamespace

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--kf-every", type=int, default=6)
    ap.add_argument("--points", type=int, default=600, help="DSO points per keyframe (DSO: 2000 at 640x480)")
    ap.add_argument("--idepth-noise", type=float, default=0.02, help="relative std of the points' inverse depth")
    ap.add_argument("--iters-per-kf", type=int, default=40)
    ap.add_argument("--final-iters", type=int, default=300)
    ap.add_argument("--variants", default="mean,barycentric,nofill,random")
    ap.add_argument("--depth-ratio", type=float, default=None, help="override fill_max_depth_ratio")
    ap.add_argument("--geometry-ratios", default="1.2,1.3,1.5,2,inf",
                    help="fill_max_depth_ratio values of the geometry table (mean and barycentric, no training)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)

    import dataclasses

    import warp as wp

    from mgso import synthetic
    from mgso.camera import PinholeCamera
    from mgso.config import MappingConfig
    from mgso.eval import psnr
    from mgso.mapping import seeding as sd
    from mgso.mapping.init import random_frustum_points
    from mgso.mapping.gaussian_map import GaussianMap, scene_extent_from_cameras
    from mgso.tracking.pixel_selector import PixelSelector
    from mgso_kernels import runtime
    from mgso_kernels.loss import L1SSIMLoss
    from mgso_kernels.reference.image import build_pyramid
    from mgso_kernels.splat import Rasterizer, make_camera

    if hasattr(wp.config, "log_level"):   # stdout carries the one JSON line only (Warp 1.19 logs to stdout)
        wp.config.log_level = logging.WARNING
    device = runtime.init(args.device)
    t0 = time.perf_counter()
    seq = synthetic.make_sequence(seed=args.seed, num_frames=args.frames, width=args.width, height=args.height)
    t_seq = time.perf_counter() - t0
    k = seq.intrinsics
    cam = PinholeCamera(k.fx, k.fy, k.cx, k.cy, k.width, k.height)
    kf_idx = list(range(0, args.frames, args.kf_every))
    eval_idx = [i for i in range(args.frames) if i not in kf_idx]
    w2c = [np.linalg.inv(T) for T in seq.cam_to_world]
    zmin, zmax = float(seq.depths.min()), float(seq.depths.max())

    rng_pts = np.random.default_rng(args.seed)
    msgs = []
    for i in kf_idx:
        gray = (seq.images[i] @ np.array([0.299, 0.587, 0.114]) * 255.0).astype(np.float32)
        pyr = build_pyramid(gray, 3)
        sel = PixelSelector(cam.width, cam.height, seed=i).select([p[1] for p in pyr], args.points)
        z = seq.depths[i][sel.xy[:, 1], sel.xy[:, 0]].astype(np.float64)
        idepth = (1.0 / z) * (1.0 + args.idepth_noise * rng_pts.standard_normal(len(z)))
        msgs.append(sd.KeyframeSeedInput(seq.images[i], cam, seq.cam_to_world[i], sel.xy.astype(np.float64),
                                         np.maximum(idepth, 1e-6), keyframe_id=i))

    base = MappingConfig()
    seed_base = base.seeding if args.depth_ratio is None else dataclasses.replace(
        base.seeding, fill_max_depth_ratio=args.depth_ratio)
    extent = max(scene_extent_from_cameras(seq.cam_to_world[kf_idx][:, :3, 3]), 1.0)
    rast = Rasterizer(device)
    loss_fn = L1SSIMLoss(cam.height, cam.width, device, lambda_dssim=base.lambda_dssim)
    cams = {i: make_camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, w2c[i]) for i in range(args.frames)}

    def train_step(gmap, i, step):
        p = gmap.float_params()
        out = rast.forward(p.means, p.log_scales, p.quats, p.opacity_logits, p.sh, cams[i])
        res = loss_fn(out.rgb, seq.images[i])
        g = rast.backward(out, res.v_rendered_hw3)
        fg = gmap.float_grads()
        for dst, src in ((fg.means, g.v_means), (fg.log_scales, g.v_log_scales), (fg.quats, g.v_quats),
                         (fg.opacity_logits, g.v_opacity_logits), (fg.sh, g.v_sh)):
            wp.copy(dst, src)
        gmap.optimizer_step(step)

    def fill_errors(cfg):  # fill points' depth against the true depth map (nearest pixel)
        errs = []
        for m, i in zip(msgs, kf_idx):
            f = sd.make_candidates(m, cfg).fill
            ui = np.clip(np.round(f.uv).astype(int), 0, [cam.width - 1, cam.height - 1])
            zt = seq.depths[i][ui[:, 1], ui[:, 0]]
            errs.append(np.abs(f.depth - zt) / zt)
        e = np.concatenate(errs) if errs else np.zeros(0)
        if len(e) == 0:
            return {}
        return {"fill_points": int(len(e)), "fill_err_median_pct": round(float(np.median(e)) * 100, 3),
                "fill_err_p90_pct": round(float(np.percentile(e, 90)) * 100, 3),
                "fill_err_gt5pct_share": round(float((e > 0.05).mean()), 4),
                "fill_err_gt20pct_share": round(float((e > 0.2).mean()), 4)}

    geometry = {}
    for ratio in [float(r) for r in args.geometry_ratios.split(",") if r.strip()]:
        for mode in ("mean", "barycentric"):
            cfg = dataclasses.replace(seed_base, fill=True, fill_depth=mode, fill_max_depth_ratio=ratio)
            cands = [sd.make_candidates(m, cfg).fill for m in msgs]
            geometry[f"{mode}@{ratio:g}"] = {
                **fill_errors(cfg), "large_triangles": sum(f.num_large for f in cands),
                "rejected_discontinuity": sum(f.num_rejected_discontinuity for f in cands)}
    added_per_kf: list[int] | None = None
    settings = {**vars(args), "keyframes": len(kf_idx), "eval_frames": len(eval_idx),
                "scene_depth_range_m": [round(zmin, 2), round(zmax, 2)], "seeding": dataclasses.asdict(seed_base)}
    out: dict = {"profile": "seeding_fill", "settings": settings, "geometry": geometry, "variants": {}}
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    if "random" in variants and "barycentric" in variants:   # random matches the barycentric counts
        variants = [v for v in variants if v != "random"] + ["random"]
    for var in variants:
        t1 = time.perf_counter()
        if var in ("mean", "barycentric"):
            cfg = dataclasses.replace(seed_base, fill=True, fill_depth=var)
        elif var in ("nofill", "random"):
            cfg = dataclasses.replace(seed_base, fill=False)
        else:
            raise SystemExit(f"unknown variant {var!r}")
        gmap = GaussianMap(400_000, 0, device, base.optim, scene_extent=extent)
        rng = np.random.default_rng(args.seed + 1)
        step = 0
        results = []
        counts = []
        for j, (m, i) in enumerate(zip(msgs, kf_idx)):
            if var == "random":
                n_add = added_per_kf[j] if added_per_kf is not None else 1000
                if n_add > 0:
                    view = SimpleNamespace(camera=cam, cam_to_world=seq.cam_to_world[i], image=seq.images[i])
                    pts, cols, _ = random_frustum_points([view], n_add, (zmin, zmax), rng)
                    zc = (pts - seq.cam_to_world[i][:3, 3]) @ seq.cam_to_world[i][:3, :3][:, 2]
                    nb = gmap.means.numpy() if gmap.n else None
                    sc = sd.seed_scales(pts, zc, math.sqrt(cam.fx * cam.fy), cfg, nb)
                    g = sd.gaussians_from_seeds(pts, cols, sc, cfg)
                    gmap.add(g.means, g.log_scales, g.quats, g.opacity_logits, g.sh, step=step)
                counts.append(n_add)
            else:
                r = sd.seed_keyframe(gmap, rast, m, cfg, step)
                results.append(r)
                counts.append(r.num_added)
            for _ in range(args.iters_per_kf):
                seen = kf_idx[: j + 1]
                train_step(gmap, seen[int(rng.integers(len(seen)))], step)
                step += 1
        for _ in range(args.final_iters):
            train_step(gmap, kf_idx[int(rng.integers(len(kf_idx)))], step)
            step += 1
        if var == "barycentric":
            added_per_kf = counts
        vals = []
        p = gmap.float_params()
        for i in eval_idx:
            o = rast.forward(p.means, p.log_scales, p.quats, p.opacity_logits, p.sh, cams[i])
            vals.append(psnr(np.clip(o.rgb.numpy(), 0, 1), seq.images[i]))
        rec = {"psnr_heldout": round(float(np.mean(vals)), 3), "gaussians": gmap.n, "added_per_kf": counts,
               "train_steps": step, "seconds": round(time.perf_counter() - t1, 1)}
        if results:
            rec["seed_totals"] = {f: int(sum(getattr(r, f) for r in results)) for f in (
                "num_candidates", "num_fill", "num_large_triangles", "num_rejected_discontinuity",
                "num_rejected_visibility", "num_added")}
            rec["skipped_too_few"] = int(sum(r.skipped_too_few for r in results))
            rec["seed_ms_median"] = round(1000 * float(np.median([r.seconds for r in results])), 1)
        if cfg.fill:
            rec.update(fill_errors(cfg))
        out["variants"][var] = rec
        print(f"{var}: {rec}", file=sys.stderr, flush=True)
    out["settings"]["sequence_seconds"] = round(t_seq, 1)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
