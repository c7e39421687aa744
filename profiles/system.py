"""Profile the whole system (odometry + mapper, mgso.system) on real recordings: the figures of metrics.json.

For each sequence (default: the 7-Scenes redkitchen and KITTI 00 excerpts of the shared data) the script runs the
system in deterministic mode in a fresh subprocess (so that peak memory is the run's own), writes the outputs of
``mgso run`` into ``--out/<name>`` and prints **one JSON line**: per sequence ATE (Sim3, all frames and keyframes),
PSNR / SSIM under the MonoGS and Photo-SLAM protocols, Gaussians, map size, peak memory, tracking FPS, mapping
iterations per second, end-to-end FPS, frames, keyframes, image size, and the settings.

``--odometry oracle`` (the default until the DSO odometry is plugged into ``mgso.system``): ground-truth poses and
depths (:class:`mgso.oracle.OracleOdometry`; 7-Scenes depth is reprojected from the depth camera, a few cm off);
the odometry figures (ATE, tracking FPS) are then those of ground truth and only the mapping figures mean anything.
KITTI has no depth, so the oracle cannot run there (reported as such).

    python profiles/system.py [--device cpu] [--downscale 2] [--init dso|random] [--iterations-per-keyframe 20]
                              [--final-iterations 300] [--keyframe-every 10] [PATH ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ("ate_all_frames_m", "ate_keyframes_m", "psnr_monogs_db", "ssim_monogs", "psnr_photo_slam_db",
           "ssim_photo_slam", "num_gaussians", "map_size_mb", "peak_memory_mb", "tracking_fps",
           "mapping_iterations_per_s", "end_to_end_fps", "frames", "keyframes", "image_size", "odometry", "mode",
           "timing_s")


def _one(args) -> dict:
    """Run one sequence in this process; returns its figures."""
    import warp as wp

    if hasattr(wp.config, "log_level"):   # stdout carries the JSON only
        wp.config.log_level = logging.WARNING
    from mgso.config import load_config, save_config
    from mgso.io import open_sequence
    from mgso.oracle import OracleOdometry
    from mgso.app.outputs import write_outputs
    from mgso.system import System
    from mgso_kernels import runtime

    over = [f"runtime.device={args.device}", f"mapping.mapper.init={args.init}",
            f"mapping.mapper.iterations_per_keyframe={args.iterations_per_keyframe}",
            f"mapping.mapper.final_iterations={args.final_iterations}", f"mapping.capacity={args.capacity}",
            "system.mode=deterministic", *args.set]
    if args.frames:
        over.append(f"input.end={args.frames}")
    cfg = load_config(None, over)
    if args.downscale > 1:
        cam = open_sequence(args.one, config=cfg.input).calibration.output
        over += [f"input.width={cam.width // args.downscale}", f"input.height={cam.height // args.downscale}"]
        cfg = load_config(None, over)
    device = runtime.init(args.device, threads=cfg.runtime.threads)
    seq = open_sequence(args.one, config=cfg.input)
    name = seq.name
    out = Path(args.out) / f"{name}-{args.odometry}-{args.init}"
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml")
    if args.odometry == "dso":
        from mgso.odometry import Odometry

        odo_device = runtime.resolve_device(cfg.runtime.odometry_device) if cfg.runtime.odometry_device else device
        odo = Odometry.for_camera(seq.calibration.output, cfg, device=odo_device, emit_messages=True)
    else:
        try:
            odo = OracleOdometry.from_sequence(seq, keyframe_every=args.keyframe_every, points=args.points,
                                               idepth_noise=args.idepth_noise)
        except ValueError as exc:
            return {"skipped": str(exc)}
    system = System(odo, cfg, device=device)
    t0 = time.perf_counter()
    result = system.run(seq.frames())
    m = write_outputs(result, system.mapper, seq, cfg, out, odometry_name=odo.name)
    fig = {k: m.get(k) for k in FIGURES}
    fig["wall_s"] = time.perf_counter() - t0
    fig["out"] = str(out)
    fig["densify"] = m["mapper"]["densify"]
    fig["gaussians_seeded"] = m["mapper"]["gaussians_seeded"]
    return fig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="*", help="sequences (default: the shared 7-Scenes and KITTI excerpts)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--odometry", default="oracle", choices=["oracle", "dso"],
                    help="dso: mgso.odometry.Odometry (emit_messages); oracle: ground truth")
    ap.add_argument("--init", default="dso", choices=["dso", "random"])
    ap.add_argument("--downscale", type=int, default=2, help="divide the image size (2: 320x240 for 7-Scenes)")
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (0 = all)")
    ap.add_argument("--keyframe-every", type=int, default=10, help="oracle: a keyframe every N frames (DSO decides "
                                                                   "its own)")
    ap.add_argument("--points", type=int, default=600, help="oracle: DSO points a keyframe")
    ap.add_argument("--idepth-noise", type=float, default=0.02, help="oracle: relative inverse-depth noise")
    ap.add_argument("--iterations-per-keyframe", type=int, default=20)
    ap.add_argument("--final-iterations", type=int, default=300)
    ap.add_argument("--capacity", type=int, default=100_000)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="a config override (repeatable), e.g. --set mapping.densify.refine_start_step=100")
    ap.add_argument("--out", default="/tmp/mgso-profile-system")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(_one(args)))
        return 0
    sys.path.insert(0, str(ROOT))
    from mgso.io.paths import shared_data_dir

    paths = args.paths
    if not paths:
        data = shared_data_dir()
        if data is None:
            raise SystemExit("no sequences given and the shared data was not found (set MGSO_DATA)")
        paths = [str(data / "7scenes_redkitchen_0-499"), str(data / "kitti00_0-159")]
    results = {}
    passthrough = [a for a in (argv if argv is not None else sys.argv[1:]) if a not in paths]
    for p in paths:
        proc = subprocess.run([sys.executable, __file__, *passthrough, "--one", p], capture_output=True, text=True,
                              cwd=str(ROOT))
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
        if proc.returncode != 0 or not lines:
            results[Path(p).name] = {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
        else:
            results[Path(p).name] = json.loads(lines[-1])
    settings = {k: v for k, v in vars(args).items() if k not in ("paths", "one")}
    print(json.dumps({"profile": "system", "odometry": args.odometry,
                      "note": "oracle odometry: ground-truth poses and depths stand in for DSO (not merged yet); "
                              "ATE and tracking FPS are those of ground truth, only the mapping figures measure "
                              "mgso" if args.odometry == "oracle" else "",
                      "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
                      "settings": settings, "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
