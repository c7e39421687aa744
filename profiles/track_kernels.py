"""Timings of the DSO front-end kernels; prints one JSON line (milliseconds, medians of repeats).

    python profiles/track_kernels.py [--device cpu] [--repeats 20]

Figures: pyramid + gradients at 640x480 and KITTI 1241x376 (cropped to 1232x368); coarse-tracking residuals + 8x8
system for 2000 points x 8 pattern pixels and for a dense depth map (every pixel one residual, DSO's coarse
tracker; ``single_scalar``: its scalar loop, without the CPU's 8-point path) at levels 0-3 of 640x480; the
epipolar search of 2000 immature points; the NumPy pixel selection at 640x480. Kernel figures come
single-threaded (``single``) and split over the CPU cores (``split``). Points are in raster order, as DSO's depth
map and pixel selection produce them. ``load_avg`` is the 1-minute load when the run ended: on a shared machine,
compare figures only between runs with a similar load.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import cv2
import numpy as np
import warp as wp

from mgso_kernels import image as kimg
from mgso_kernels import photometric as ph
from mgso_kernels import runtime
from mgso_kernels import trace as tr
from mgso_kernels import track as tk


def median_ms(fn, repeats: int, sync_device: str) -> float:
    fn()  # warm (compile/load)
    wp.synchronize_device(sync_device)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(sync_device)
        ts.append(time.perf_counter() - t0)
    return round(float(np.median(ts)) * 1e3, 3)


def texture(h, w, seed, sigma=2.0):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
    return (255.0 * (t - t.min()) / (t.max() - t.min())).astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    dev = runtime.init(args.device)
    R = args.repeats
    out: dict = {"device": dev, "threads": runtime.cpu_threads(), "repeats": R, "unit": "ms"}

    # --- pyramid + gradients
    for name, (w, h) in {"640x480": (640, 480), "1241x376": (1241, 376)}.items():
        g = kimg.plan_pyramid(w, h)
        img = g.adjust(texture(h, w, 0))
        pyr = kimg.ImagePyramid(g, dev)
        gpu_img = wp.array(img, dtype=wp.float32, device=dev)
        out[f"pyramid_{name}_levels"] = g.levels
        for split in (False, True):
            out[f"pyramid_{name}_{'split' if split else 'single'}"] = median_ms(
                lambda: pyr.build(gpu_img, split=split), R, dev)

    # --- coarse tracking: 640x480 reference / new frame pyramids
    W, H = 640, 480
    g = kimg.plan_pyramid(W, H, kimg.Pinhole(500.0, 500.0, 319.5, 239.5))
    ref_img = texture(H, W, 1)
    new_img = cv2.warpAffine(ref_img, np.float32([[1, 0, 1.3], [0, 1, -0.6]]), (W, H), borderMode=cv2.BORDER_REFLECT)
    ref_pyr = kimg.ImagePyramid(g, dev).build(ref_img)
    new_pyr = kimg.ImagePyramid(g, dev).build(new_img)
    rng = np.random.default_rng(2)
    pair = ph.make_frame_pair(np.array([[1, 0, 0, 0.002], [0, 1, 0, -0.001], [0, 0, 1, 0.003], [0, 0, 0, 1.0]]))

    def coarse_case(level, uv, pattern):
        c = g.level_camera(level)
        wl, hl = g.level_size(level)
        cam = ph.make_intrinsics(c.fx, c.fy, c.cx, c.cy, wl, hl)
        off = ph.PATTERN_NP if pattern == 8 else np.zeros((1, 2), np.float32)
        dI_ref = ref_pyr.numpy(level)
        x = np.clip(uv[:, None, 0] + off[None, :, 0], 0, wl - 1).astype(int)
        y = np.clip(uv[:, None, 1] + off[None, :, 1], 0, hl - 1).astype(int)
        col = wp.array(dI_ref[y, x, 0].astype(np.float32), device=dev)
        uvw = wp.array(uv.astype(np.float32), dtype=wp.vec2, device=dev)
        idp = wp.array(rng.uniform(0.3, 2.0, len(uv)).astype(np.float32), device=dev)
        ws = tk.TrackWorkspace(len(uv), pattern, dev)
        res = {}
        for split in (False, True):
            res["split" if split else "single"] = median_ms(
                lambda: tk.track_system(uvw, idp, col, pair, cam, new_pyr.dI[level], ws, split=split), R, dev)
        if pattern == 1:  # the scalar loop beside the CPU's 8-point path (mgso_kernels.track_simd; the same on a GPU)
            sc = tk.TrackWorkspace(len(uv), pattern, dev, simd=False)
            res["single_scalar"] = median_ms(
                lambda: tk.track_system(uvw, idp, col, pair, cam, new_pyr.dI[level], sc, split=False), R, dev)
        res["residuals"] = int(len(uv) * pattern)
        return res

    n = 2000
    uv = np.stack([rng.uniform(4, W - 5, n), rng.uniform(4, H - 5, n)], axis=1)
    uv = uv[np.lexsort((uv[:, 0], np.floor(uv[:, 1])))]
    out["coarse_2000x8"] = coarse_case(0, uv, 8)
    for level in range(4):
        wl, hl = g.level_size(level)
        yy, xx = np.mgrid[2:hl - 2, 2:wl - 2]  # DSO makeCoarseDepthL0 keeps 2 <= x < w-2
        out[f"coarse_dense_L{level}"] = coarse_case(level, np.stack([xx.ravel(), yy.ravel()], axis=1), 1)

    # --- trace 2000 immature points (fronto-parallel texture, small motion)
    K = g.camera.matrix()
    dI_h = ref_pyr.dI[0]
    n = 2000
    uv = np.stack([rng.integers(20, W - 20, n), rng.integers(20, H - 20, n)], axis=1).astype(np.float32)
    uv = uv[np.lexsort((uv[:, 0], uv[:, 1]))]
    pat = ph.extract_patterns(dI_h, uv)
    T = np.eye(4)
    T[:3, 3] = [0.02, 0.003, 0.001]
    KRKi, Kt = tr.host_target_projection(K, T)
    params = tr.make_trace_params(W, H)
    arrays = dict(host_uv=wp.array(uv, dtype=wp.vec2, device=dev), host_index=wp.zeros(n, dtype=wp.int32, device=dev),
                  color=wp.array(pat.color, device=dev), weight=wp.array(pat.weight, device=dev),
                  grad_h=wp.array(pat.grad_h, dtype=wp.vec3, device=dev),
                  KRKi=wp.array(KRKi, dtype=wp.mat33, device=dev), Kt=wp.array(Kt, dtype=wp.vec3, device=dev),
                  affine=wp.array(np.array([[1.0, 0.0]], np.float32), dtype=wp.vec2, device=dev))
    outs = dict(trace_uv=wp.zeros(n, dtype=wp.vec2, device=dev),
                pixel_interval=wp.zeros(n, dtype=wp.float32, device=dev),
                energy=wp.zeros(n, dtype=wp.float32, device=dev))
    state = dict(idepth_min=wp.zeros(n, dtype=wp.float32, device=dev),
                 idepth_max=wp.full(n, np.nan, dtype=wp.float32, device=dev),
                 quality=wp.full(n, 10000.0, dtype=wp.float32, device=dev),
                 status=wp.full(n, int(tr.TraceStatus.UNINITIALIZED), dtype=wp.int32, device=dev))

    def trace_once(split):
        state["idepth_min"].fill_(0.0)  # every repeat traces from an unknown depth (the full search)
        state["idepth_max"].fill_(np.nan)
        state["status"].fill_(int(tr.TraceStatus.UNINITIALIZED))
        tr.trace_points(new_pyr.dI[0], **arrays, params=params, **state, **outs, split=split)

    out["trace_2000"] = {("split" if s else "single"): median_ms(lambda: trace_once(s), R, dev) for s in (False, True)}
    st = state["status"].numpy()
    out["trace_2000"]["good_fraction"] = round(float(np.mean(st == tr.TraceStatus.GOOD)), 3)

    # --- pixel selection (NumPy, once per keyframe)
    from mgso.tracking.pixel_selector import PixelSelector

    levels = [ref_pyr.numpy(lvl) for lvl in range(3)]
    grad_sq = [ref_pyr.grad_sq[lvl].numpy() for lvl in range(3)]
    sel = PixelSelector(W, H)
    sel.select(levels, 2000, grad_sq=grad_sq)  # let the potential settle, as it does over a sequence
    t = []
    for _ in range(R):
        t0 = time.perf_counter()
        s = sel.select(levels, 2000, grad_sq=grad_sq)
        t.append(time.perf_counter() - t0)
    out["pixel_select_640x480"] = {"numpy": round(float(np.median(t)) * 1e3, 3), "points": len(s),
                                   "potential": s.potential}
    out["load_avg"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
