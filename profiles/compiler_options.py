"""What Warp's CPU compiler options buy the odometry's kernels; prints one JSON line.

    python profiles/compiler_options.py [--repeats 15]

Warp compiles CPU kernels at -O2 with ``wp.config.cpu_compiler_flags``, which cap LLVM's SLP vectoriser at a
recursion depth of 4 (LLVM's own default is 12). Some mgso modules ask for other options
(``wp.set_module_options``: docs/tracking_kernels.md, "Compiler options on the CPU"). This profile measures each
such choice against Warp's defaults in one process, the variants interleaved repeat by repeat (the machine is
shared and its speed drifts by tens of percent within minutes: only a paired comparison in one run means
anything), on one thread:

- ``window_linearize``: :func:`mgso_kernels.window.linearize_window` on the window of ``profiles/window.py``
  (synthetic room, 7 keyframes, about 2000 points), full SLP depth against Warp's flags;
- ``activation_depth``: :func:`mgso_kernels.activation.point_depth_residuals` on that window's pairs, the same;
- ``init_system``: :func:`mgso_kernels.initializer.init_system`, 8,000 points of a 640x480 synthetic frame against
  the next one, -O3 against -O2;
- ``track_dense_L1`` (the control: a module that keeps Warp's defaults because full SLP depth measured nothing):
  the coarse tracker's system over the dense 320x240 level, full SLP depth against Warp's flags.

Per case: the medians of both variants (ms), the median of the per-repeat ratios ``variant / default`` and whether
the outputs are the same bits (they must be: the options may change speed only). Switching a module's options
reloads it (Warp keeps each compiled variant in its kernel cache, so only the first run compiles); recorded
launches are dropped at each switch and each timed call follows an untimed one.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "window"))

from mgso import synthetic  # noqa: E402
from mgso.config import WindowConfig  # noqa: E402
from mgso.window.energy import WindowProblem  # noqa: E402
from mgso_kernels import activation as ka  # noqa: E402
from mgso_kernels import image as kimg  # noqa: E402
from mgso_kernels import initializer as ki  # noqa: E402
from mgso_kernels import photometric as ph  # noqa: E402
from mgso_kernels import runtime  # noqa: E402
from mgso_kernels import track as tk  # noqa: E402
from mgso_kernels import window as kw  # noqa: E402
from window_helpers import window_from_sequence  # noqa: E402


def digest(*arrays) -> str:
    h = hashlib.md5()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:12]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    runtime.init("cpu")
    runtime.set_cpu_threads(1)
    W, H = 640, 480
    seq = synthetic.make_sequence(seed=0, num_frames=19, width=W, height=H)
    win, _ = window_from_sequence(seq, [0, 3, 6, 9, 12, 15, 18], points_per_kf=2000 // 7, pose_noise=0.004,
                                  depth_noise=0.05)
    prob = WindowProblem(win, WindowConfig(), None, first_slots=(win.order[0],), device="cpu")
    keys = prob.keys()
    a, pts = win.active, prob.points
    g = win.camera
    dparams = ka.make_depth_params(g.fx, g.fy, g.cx, g.cy, win.width, win.height)
    aff = keys.aff[:, :2].copy()
    aff[:, 1] = keys.aff[:, 2] - keys.aff[:, 0] * keys.aff[:, 1]  # (a_rel, b_rel) as the activation passes them

    # the initialiser: frame 0's points against frame 1
    geo = kimg.plan_pyramid(W, H, kimg.Pinhole(g.fx, g.fy, g.cx, g.cy))
    gray = [np.ascontiguousarray(255.0 * seq.images[i] @ np.array([0.299, 0.587, 0.114]), dtype=np.float32)
            for i in (0, 1)]
    p0 = kimg.ImagePyramid(geo, "cpu").build(gray[0])
    p1 = kimg.ImagePyramid(geo, "cpu").build(gray[1])
    rng = np.random.default_rng(0)
    n_init = 8000
    uv0 = np.stack([rng.uniform(4, W - 5, n_init), rng.uniform(4, H - 5, n_init)], axis=1).astype(np.float32)
    uv0 = uv0[np.lexsort((uv0[:, 0], np.floor(uv0[:, 1])))]
    dI0 = p0.numpy(0)
    off = ph.PATTERN_NP
    ref = dI0[np.clip(np.rint(uv0[:, None, 1] + off[None, :, 1]), 0, H - 1).astype(int),
              np.clip(np.rint(uv0[:, None, 0] + off[None, :, 0]), 0, W - 1).astype(int), 0].astype(np.float32)
    T01 = np.linalg.inv(seq.cam_to_world[1]) @ seq.cam_to_world[0]
    iparams = ki.make_init_params(T01, (0.0, 0.0), g.fx, g.fy, g.cx, g.cy, W, H, alpha_opt=0.0)
    init_state = dict(idepth=np.full(n_init, 0.5, np.float32), is_good=np.ones(n_init, bool),
                      energy=np.zeros((n_init, 2), np.float32), iR=np.full(n_init, 0.5, np.float32),
                      energy_new=np.zeros((n_init, 2), np.float32), is_good_new=np.zeros(n_init, bool),
                      jb_new=np.zeros((n_init, 10)), maxstep=np.zeros(n_init, np.float32),
                      last_hessian_new=np.zeros(n_init, np.float32))

    # the tracker's dense level 1
    lvl = 1
    c1 = geo.level_camera(lvl)
    wl, hl = geo.level_size(lvl)
    cam1 = ph.make_intrinsics(c1.fx, c1.fy, c1.cx, c1.cy, wl, hl)
    yy, xx = np.mgrid[2:hl - 2, 2:wl - 2]
    uv1 = np.stack([xx.ravel(), yy.ravel()], axis=1)
    col1 = wp.array(p0.numpy(lvl)[uv1[:, 1], uv1[:, 0], 0][:, None].astype(np.float32), device="cpu")
    uvw1 = wp.array(uv1.astype(np.float32), dtype=wp.vec2, device="cpu")
    idp1 = wp.array(rng.uniform(0.3, 2.0, len(uv1)).astype(np.float32), device="cpu")
    pair1 = ph.make_frame_pair(T01)
    tws = tk.TrackWorkspace(len(uv1), 1, "cpu")

    def run_window(state):
        lin = kw.linearize_window(prob.params, keys, prob.pair_point, prob.pair_key, a.uv[pts], a.idepth[pts],
                                  a.color[pts], a.weight[pts], prob.images, device="cpu", cache=state)
        return digest(lin.state, lin.energy, lin.hcd, lin.hdd, lin.bd, lin.key_H, lin.key_b)

    def run_activation(state):
        r = ka.point_depth_residuals(dparams, keys.target, keys.R, keys.t, aff, prob.pair_point, prob.pair_key,
                                     a.uv[pts], a.idepth[pts], a.color[pts], a.weight[pts], prob.images,
                                     device="cpu")
        return digest(r.energy, r.hdd, r.bd)

    def run_init(state):
        ws = state.setdefault("ws", ki.InitWorkspace(uv0, ref, "cpu"))
        arrs = state.setdefault("arrs", {k: v.copy() for k, v in init_state.items()})
        for k, v in init_state.items():
            arrs[k][...] = v
        s = ki.init_system(ws, p1.dI[0], iparams, threads=1, **arrs)
        return digest(s.H, s.b, s.Hsc, s.bsc, arrs["jb_new"], arrs["energy_new"])

    def run_track(state):
        tws.launches.clear()  # recorded launches point into the module loaded when they were made
        s = tk.track_system(uvw1, idp1, col1, pair1, cam1, p1.dI[lvl], tws, split=False)
        return digest(s.H, s.b)

    slp = runtime.cpu_flags_full_slp()
    cases = {  # name: (module, Warp's default options, the variant, runner)
        "window_linearize": (kw, {"cpu_compiler_flags": None}, {"cpu_compiler_flags": slp}, run_window),
        "activation_depth": (ka, {"cpu_compiler_flags": None}, {"cpu_compiler_flags": slp}, run_activation),
        "init_system": (ki, {"optimization_level": None}, {"optimization_level": 3}, run_init),
        "track_dense_L1": (tk, {"cpu_compiler_flags": None}, {"cpu_compiler_flags": slp}, run_track),
    }
    landed = {name: dict(wp.get_module(m.__name__).options) for name, (m, _, _, _) in cases.items()}
    out = {"profile": "compiler_options", "repeats": args.repeats, "load_avg_1min": round(os.getloadavg()[0], 2),
           "warp": wp.config.version, "warp_cpu_flags": wp.config.cpu_compiler_flags, "full_slp_flags": slp}
    for name, (mod, default, variant, fn) in cases.items():
        times = {"default": [], "variant": []}
        bits = {}
        for _ in range(args.repeats):
            for label, opts in (("default", default), ("variant", variant)):
                wp.set_module_options(opts, module=mod.__name__)
                wp.load_module(mod, device="cpu")
                state: dict = {}
                fn(state)  # untimed: plans, caches, first touch
                t0 = time.perf_counter()
                bits[label] = fn(state)
                times[label].append(time.perf_counter() - t0)
        d, v = np.array(times["default"]), np.array(times["variant"])
        out[name] = {"default_ms": round(1000 * float(np.median(d)), 3),
                     "variant_ms": round(1000 * float(np.median(v)), 3),
                     "ratio_median": round(float(np.median(v / d)), 3),
                     "ratio_p10_p90": [round(float(np.percentile(v / d, q)), 3) for q in (10, 90)],
                     "variant": dict(variant), "same_bits": bits["default"] == bits["variant"]}
        wp.set_module_options({k: landed[name][k] for k in variant}, module=mod.__name__)  # back as landed
    out["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
