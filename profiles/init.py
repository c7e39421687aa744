"""Per-frame time of DSO's monocular initialiser (:class:`mgso.tracking.initializer.CoarseInitializer`) on the first
frames of the KITTI 00 and 7-Scenes excerpts (at their own sizes after the pyramid crop: 1232x368 and 640x480), and
the initialisation result it reaches, so a speed change can be checked not to change the numbers.

Frame 0 becomes the first frame (``set_first``, timed apart); frames 1..``--frames`` are aligned to it
(``track_frame``, one time each) until the initialiser answers ``INITIALIZED`` or ``FAILED``. The pyramids are built
before timing (the odometry builds them in ``track`` for every frame anyway).

    python profiles/init.py [--device cpu] [--frames 10] [--path DATASET ...] [--repeats 1]

Prints one JSON line: per dataset ``set_first_ms``, ``track_ms_median`` / ``_p90`` / ``_max`` over the aligned
frames (median over ``--repeats`` runs per frame), ``frames_tracked``, ``statuses``, ``initialized_at`` (frame index
or null), ``snapped``, the last result's ``rmse``, ``translation`` (norm of the first-to-new translation, scale: mean
inverse depth 1), ``num_good`` / ``num_points`` (level 0) and ``idepth_mean`` (level 0, good points). The
development machine is shared: the load average is in the output.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mgso.config import Config, apply_overrides  # noqa: E402
from mgso.io import open_sequence  # noqa: E402
from mgso.io.paths import shared_data_dir  # noqa: E402
from mgso.odometry import geometry_for  # noqa: E402
from mgso.tracking.initializer import CoarseInitializer, InitStatus  # noqa: E402
from mgso_kernels import runtime  # noqa: E402
from mgso_kernels.image import ImagePyramid  # noqa: E402


def run_once(pyrs, exposures, geo, cfg: Config, device: str) -> dict:
    ini = CoarseInitializer(geo, cfg.tracking, seed=cfg.runtime.seed, device=device)
    t0 = time.perf_counter()
    first = ini.set_first(pyrs[0], exposures[0])
    set_first_s = time.perf_counter() - t0
    if first.status != InitStatus.FIRST_FRAME:
        return {"error": f"set_first: {first.message}"}
    times, results = [], []
    for pyr, e in zip(pyrs[1:], exposures[1:]):
        t0 = time.perf_counter()
        r = ini.track_frame(pyr, e)
        times.append(time.perf_counter() - t0)
        results.append(r)
        if r.status != InitStatus.TRACKING:
            break
    p0 = ini.points[0]
    last = results[-1]
    return {"set_first_s": set_first_s, "times": times, "results": results,
            "points_per_level": [p.n for p in ini.points],
            "idepth_mean": float(np.mean(p0.idepth[p0.is_good])) if p0.is_good.any() else float("nan"), "last": last}


def profile(path: str, cfg: Config, frames: int, repeats: int, device: str) -> dict:
    c = apply_overrides(cfg, [f"input.end={frames + 1}"])
    seq = open_sequence(path, config=c.input)
    cam = seq.calibration.output
    geo = geometry_for(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, c)
    pyrs, exposures = [], []
    for f in seq.frames():
        img = geo.adjust(np.asarray(f.gray))
        img = np.where(np.isfinite(img), img, 0.0).astype(np.float32)
        pyrs.append(ImagePyramid(geo, device=device).build(img))
        exposures.append(float(getattr(f, "exposure_ms", None) or 0.0))
    runs = [run_once(pyrs, exposures, geo, c, device) for _ in range(max(1, repeats))]
    if "error" in runs[0]:
        return runs[0]
    n = min(len(r["times"]) for r in runs)
    ms = np.median(np.array([r["times"][:n] for r in runs]), axis=0) * 1000
    run = runs[0]
    last = run["last"]
    inits = [i + 1 for i, r in enumerate(run["results"]) if r.status == InitStatus.INITIALIZED]
    return {
        "size": [geo.width, geo.height], "pyramid_levels": geo.levels,
        "points_per_level": run["points_per_level"],
        "set_first_ms": float(np.median([r["set_first_s"] for r in runs]) * 1000),
        "frames_tracked": n, "track_ms_median": float(np.median(ms)), "track_ms_p90": float(np.percentile(ms, 90)),
        "track_ms_max": float(ms.max()), "track_ms": [round(float(x), 1) for x in ms],
        "statuses": [r.status.value for r in run["results"]], "initialized_at": inits[0] if inits else None,
        "snapped": bool(last.snapped), "rmse": float(last.rmse),
        "translation": float(np.linalg.norm(last.first_to_new[:3, 3])),
        "num_points": int(last.num_points), "num_good": int(last.num_good), "idepth_mean": run["idepth_mean"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=10, help="frames aligned after the first (at most)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per dataset; per-frame medians over them")
    ap.add_argument("--path", action="append", default=None, help="dataset(s) (default: the 7-Scenes and KITTI 00 "
                                                                   "excerpts when present)")
    ap.add_argument("--set", action="append", default=[], help="config overrides, e.g. tracking.init_alpha_k=4")
    args = ap.parse_args()
    device = runtime.init(args.device)
    cfg = apply_overrides(Config(), args.set)
    out = {"profile": "init", "device": device, "cpu_threads": runtime.cpu_threads(), "frames": args.frames,
           "repeats": args.repeats, "load_avg_1min": os.getloadavg()[0]}
    paths = args.path
    if paths is None:
        d = shared_data_dir()
        paths = [str(d / n) for n in ("7scenes_redkitchen_0-499", "kitti00_0-159")] if d is not None else []
    for p in paths:
        out[Path(p).name] = profile(p, cfg, args.frames, args.repeats, device)
    out["load_avg_1min_end"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
