"""Profile of the map's optimisation kernels: L1 + D-SSIM loss (forward + backward) and the fused Adam step.

Prints one JSON line (milliseconds, median of repeats):

    loss_fb_ms / loss_f_ms        {"320x240": ..., "640x480": ...}   forward+backward / forward only
    adam_ms                       {"10000": ..., "50000": ..., "200000": ...}   dense, per-Gaussian bias correction
    adam_global_ms                same, one global step (3DGS)          -> the cost of per-Gaussian steps
    adam_sparse_ms                sparse by visibility mask, 30% visible
    map_refine_ms                 {"200000": ...} clone 2% + split 2% + remove 5% through the map's operations
    cpu_ms                        process CPU time (all threads) of the loss and Adam calls: compute cost, which
                                  unlike wall time hardly moves when other jobs share the cores

Usage: ``python profiles/splat_opt.py [--device cpu] [--repeats 7] [--threads 0]``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp

from mgso_kernels import loss as kloss
from mgso_kernels import runtime


CPU_MS: dict = {}   # process CPU time of the same calls (all threads): stable on a machine shared with other jobs


def _median_ms(fn, repeats: int, warmup: int = 1, key: str | None = None) -> float:
    for _ in range(warmup):
        fn()
    ts, cs = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wp.synchronize()
        ts.append((time.perf_counter() - t0) * 1e3)
        cs.append((time.process_time() - c0) * 1e3)
    if key is not None:
        CPU_MS[key] = round(float(np.median(cs)), 3)
    return round(float(np.median(ts)), 3)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=0)
    args = ap.parse_args()
    device = runtime.init(args.device, threads=args.threads)
    rng = np.random.default_rng(0)
    out: dict = {"device": device, "threads": runtime.cpu_threads() if wp.get_device(device).is_cpu else None}

    out["loss_fb_ms"], out["loss_f_ms"] = {}, {}
    for w, h in ((320, 240), (640, 480)):
        target = rng.random((h, w, 3)).astype(np.float32)
        rendered = np.clip(target + 0.1 * rng.standard_normal((h, w, 3)), 0, 1).astype(np.float32)
        r = wp.array(rendered, dtype=wp.vec3, device=device)
        t = wp.array(target, dtype=wp.vec3, device=device)
        fn = kloss.L1SSIMLoss(h, w, device)
        out["loss_fb_ms"][f"{w}x{h}"] = _median_ms(lambda: fn(r, t, exposure=(0.1, 0.01)), args.repeats,
                                                   key=f"loss_fb_{w}x{h}")
        out["loss_f_ms"][f"{w}x{h}"] = _median_ms(lambda: fn(r, t, compute_grad=False), args.repeats)

    from mgso.config import OptimConfig
    from mgso.mapping.gaussian_map import GaussianMap

    out["adam_ms"], out["adam_global_ms"], out["adam_sparse_ms"], out["map_refine_ms"] = {}, {}, {}, {}
    for n in (10_000, 50_000, 200_000):
        def make(**kw):
            gm = GaussianMap(capacity=int(n * 1.1), sh_degree=0, device=device, optim=OptimConfig(**kw))
            gm.add(rng.standard_normal((n, 3)), rng.uniform(-5, -2, (n, 3)), rng.standard_normal((n, 4)),
                   rng.standard_normal(n), rng.standard_normal((n, 3)))
            for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
                a = getattr(gm.grads, f)
                a.assign((1e-3 * rng.standard_normal(a.numpy().shape)).astype(np.float32))
            return gm
        gm = make(bias_correction="per_gaussian")
        out["adam_ms"][str(n)] = _median_ms(lambda: gm.optimizer_step(100), args.repeats, key=f"adam_{n}")
        gm = make(bias_correction="global")
        out["adam_global_ms"][str(n)] = _median_ms(lambda: gm.optimizer_step(100), args.repeats,
                                                   key=f"adam_global_{n}")
        gm = make(sparse=True)
        vis = wp.array((rng.random(n) < 0.3).astype(np.uint8), dtype=wp.uint8, device=device)
        out["adam_sparse_ms"][str(n)] = _median_ms(lambda: gm.optimizer_step(100, visible=vis), args.repeats)
        if n == 200_000:
            def refine():
                g = make()
                t0 = time.perf_counter()
                g.clone(rng.random(g.n) < 0.02, step=1)
                g.split(rng.random(g.n) < 0.02, step=1, rng=rng)
                g.remove(rng.random(g.n) < 0.05)
                return (time.perf_counter() - t0) * 1e3
            out["map_refine_ms"][str(n)] = round(float(np.median([refine() for _ in range(3)])), 3)
    out["cpu_ms"] = CPU_MS
    print(json.dumps(out))


if __name__ == "__main__":
    main()
