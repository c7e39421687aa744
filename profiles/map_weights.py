"""How much of a finished run's map shows: each Gaussian's blending weight along the run's trajectory; one JSON line.

    python profiles/map_weights.py RUN_DIR [--views 16] [--downscale 2] [--shares 0.001,0.005,0.01,0.02]

``RUN_DIR/map.ply`` is rendered from ``--views`` poses spread evenly over ``RUN_DIR/trajectory.txt`` at the run's
size (``sequence.json``) divided by ``--downscale``, as ``profiles/splat_raster.py --run`` does, and the backward
gives each Gaussian's blending weight ``alpha T`` summed over a view's pixels (``Gradients.weights``, which does not
depend on the upstream gradients). Per view the largest is kept (``weight_max``, in pixels of the rendered size, as
``stats.weight_max`` but without the mapper's 4^level), and the sum over the views (``weight``).

For each share S of ``--shares``: the Gaussians of least ``weight_max`` whose ``weight`` together is at most S of
the total: how many (``gaussians``, ``gaussian_share``), the share of the views' (tile, Gaussian) pairs they make
(``pair_share``), their median opacity and their largest ``weight_max``. Then the renders without them against the
renders with them, at 4 of the views (``psnr_vs_full_db``, render against render, not against the images; null where
they are the same) and the blends' mean ``n_contrib`` without them over with them (``n_contrib_ratio``). Also the
share of Gaussians no view blended at all (``never_blended_share``). docs/mapping.md, "Pruning what no view shows", has the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from mgso_kernels import runtime


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a finished `mgso run` folder (map.ply, sequence.json, trajectory.txt)")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--shares", default="0.001,0.005,0.01,0.02")
    ap.add_argument("--threads", type=int, default=0, help="CPU threads for split launches (0 = all cores)")
    args = ap.parse_args(argv)
    device = runtime.init("cpu", threads=args.threads or None)
    import splat_raster
    import warp as wp

    from mgso_kernels.splat import Rasterizer

    params, cams, width, height, n, _ = splat_raster.run_scene(args.run, args.views, device, args.downscale)
    rast = Rasterizer(device)
    weight, weight_max, pairs = np.zeros(n), np.zeros(n), np.zeros(n)
    zero = np.zeros((height, width, 3), np.float32)
    for cam in cams:
        out = rast.forward(*params, cam)
        w = rast.backward(out, zero, absgrad=False).weights.numpy().astype(np.float64)
        weight += w
        weight_max = np.maximum(weight_max, w)
        pairs += rast.tiles_touched_.view(n).numpy()
    opacity = 1.0 / (1.0 + np.exp(-params[3].numpy().astype(np.float64)))
    compared = cams[:: max(1, len(cams) // 4)][:4]
    full = []       # the compared views' renders with every Gaussian, once (rgb, mean n_contrib)
    for cam in compared:
        out = rast.forward(*params, cam)
        full.append((out.rgb.numpy().copy(), float(out.n_contrib.numpy().mean())))
    other = Rasterizer(device)   # the renders without the dropped Gaussians
    order = np.argsort(weight_max, kind="stable")
    cum = np.cumsum(weight[order]) / max(weight.sum(), 1e-30)
    rows = {}
    for share in (float(s) for s in args.shares.split(",")):
        k = int(np.searchsorted(cum, share, side="right"))
        drop = order[:k]
        row = {"gaussians": k, "gaussian_share": round(k / n, 4),
               "pair_share": round(pairs[drop].sum() / pairs.sum(), 4),
               "median_opacity": round(float(np.median(opacity[drop])), 4) if k else None,
               "largest_weight_max_px": round(float(weight_max[drop].max()), 4) if k else None}
        keep = np.ones(n, bool)
        keep[drop] = False
        pruned = [wp.array(p.numpy()[keep], device=device) for p in params]
        psnr, ratio = [], []
        for cam, (a, nc_a) in zip(compared, full):
            less = other.forward(*pruned, cam)
            b, nc_b = less.rgb.numpy(), less.n_contrib.numpy().mean()
            mse = float(np.mean((a - b) ** 2))
            psnr.append(round(10 * np.log10(1.0 / mse), 1) if mse > 0 else None)   # None: the same render
            ratio.append(round(float(nc_b / max(nc_a, 1e-9)), 3))
        row["psnr_vs_full_db"], row["n_contrib_ratio"] = psnr, ratio
        rows[str(share)] = row
    print(json.dumps({"profile": "map_weights", "run": args.run, "gaussians": n, "size": f"{width}x{height}",
                      "views": len(cams), "pairs": int(pairs.sum()),
                      "never_blended_share": round(float((weight == 0).mean()), 4), "shares": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
