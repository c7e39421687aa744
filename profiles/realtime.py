"""Profile the real-time mode as a user runs it: ``mgso run SEQ --realtime`` (a recorded sequence played at its frame
rate), once per variant, each in its own process; prints **one JSON line**.

Per sequence and variant: frames read, tracked (processed) and dropped, the fraction tracked, the tracking losses
(frame and reason), keyframes sent and in the map, keyframe requests merged and dropped as stale, mapping steps
while the camera ran and in the final refinement, the mapper's share of the CPU and its CPU seconds, seconds
seeding, training and refining, its longest queue,
tracking and end-to-end frames per second, ATE and PSNR (MonoGS protocol), the queue waits, how long the frames
taken had waited (median and largest, ms; ``system.max_lag_ms``), and the wall time.
The variants (default ``process`` and ``thread``) differ only by their settings, measured one after the other on
the same machine: compare the ratios in one run, not figures of different days.

``--deterministic``: also the deterministic run given as many mapping steps in all as the real-time run of the
first variant made (while the camera ran and in the final refinement), all of them in the final refinement
(``iterations_per_keyframe=0``: on a CPU the real-time mapper trains a few steps while the camera runs, fewer than
one a keyframe), for the PSNR comparison of issue 13; it is slow at 640x480 (minutes).

    python profiles/realtime.py [PATH ...] [--downscale 1] [--speed 1] [--variant NAME=SET,SET ...]
                                [--deterministic] [--set SECTION.KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

VARIANTS = {
    "process": ["system.mapper_process=true"],
    "thread": ["system.mapper_process=false"],
}


def _run(path: str, out: Path, overrides: list[str], realtime: bool) -> dict:
    cmd = [sys.executable, "-m", "mgso.app.cli", "run", path, "--out", str(out), "-q"]
    if realtime:
        cmd.append("--realtime")
    for o in overrides:
        cmd += ["--set", o]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=str(ROOT))
    wall = time.perf_counter() - t0
    mfile = out / "metrics.json"
    if not mfile.is_file():
        return {"error": (proc.stderr.strip().splitlines() or [f"exit {proc.returncode}"])[-1], "wall_s": wall}
    m = json.loads(mfile.read_text())
    st = m.get("mapper", {})
    fr = m.get("frames", {})
    rt = m.get("realtime") or {}
    stream_s = (m.get("timing_s") or {}).get("frame_loop")
    read = fr.get("read") or 0
    return {
        "exit_code": proc.returncode, "wall_s": round(wall, 2),
        "frames_read": read, "frames_tracked": fr.get("processed"), "frames_dropped": fr.get("dropped"),
        "tracked_fraction": round(fr.get("processed", 0) / read, 4) if read else None,
        "frames_without_pose": fr.get("without_pose"),
        "tracking_losses": [f"{x['frame']}:{x['reason']}" for x in m.get("tracking_losses") or []],
        "keyframes_sent": m.get("keyframes", {}).get("sent"), "keyframes_in_map": m.get("keyframes", {}).get("in_map"),
        "keyframe_requests_merged": m.get("keyframes", {}).get("requests_merged"),
        "keyframe_requests_stale": m.get("keyframes", {}).get("requests_stale"),
        "mapping_steps_running": st.get("steps", 0) - st.get("final_steps", 0),
        "mapping_steps_while_behind": st.get("steps_while_behind"), "running_level": st.get("running_level"),
        "mapper_queue_at_end": st.get("stream_ended_at_depth"), "mapper_catch_up_s": st.get("catch_up_seconds"),
        "mapping_steps_final": st.get("final_steps"), "queue_waits": st.get("queue_waits"),
        "queue_wait_s": st.get("queue_wait_seconds"), "mapper_queue_max": st.get("max_queue_depth"),
        "mapper_cpu_s": st.get("cpu_seconds"), "mapper_seed_s": st.get("seed_seconds"),
        "mapper_seed_streaming_s": st.get("seed_seconds_streaming"), "coverage_renders": st.get("coverage_renders"),
        "stream_s": stream_s,
        "mapper_train_s": st.get("train_seconds"), "mapper_final_s": st.get("final_seconds"),
        "mapper_final_budget_s": st.get("final_budget_s"),
        "seed_share_of_stream": (round(st["seed_seconds_streaming"] / stream_s, 3)
                                 if st.get("seed_seconds_streaming") is not None and stream_s else None),
        "frame_lag_ms_median": rt.get("frame_lag_ms_median"), "frame_lag_ms_max": rt.get("frame_lag_ms_max"),
        "mapper_in": rt.get("mapper_in"), "mapper_cpu_share": rt.get("mapper_cpu_share"),
        "tracking_fps": m.get("tracking_fps"), "end_to_end_fps": m.get("end_to_end_fps"),
        "ate_all_frames_m": m.get("ate_all_frames_m"), "psnr_monogs_db": m.get("psnr_monogs_db"),
        "num_gaussians": m.get("num_gaussians"), "peak_memory_mb": m.get("peak_memory_mb"),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="*", help="sequences (default: the shared 7-Scenes excerpt)")
    ap.add_argument("--downscale", type=int, default=1, help="divide the image size (2: 320x240 for 7-Scenes)")
    ap.add_argument("--speed", type=float, default=1.0, help="system.playback_speed")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=SET,SET",
                    help="a variant and its overrides (repeatable; default: process and thread)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="an override for every variant")
    ap.add_argument("--deterministic", action="store_true",
                    help="also the deterministic run with the first variant's steps a keyframe")
    ap.add_argument("--out", default="", help="keep the run folders here (default: a temporary folder)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from mgso.io.paths import shared_data_dir

    paths = args.paths
    if not paths:
        data = shared_data_dir()
        if data is None:
            raise SystemExit("no sequences given and the shared data was not found (set MGSO_DATA)")
        paths = [str(data / "7scenes_redkitchen_0-499")]
    variants = dict(VARIANTS)
    if args.variant:
        variants = {}
        for v in args.variant:
            name, _, sets = v.partition("=")
            variants[name] = [s for s in sets.split(",") if s]
    base = ["system.eval_photo_slam=false", f"system.playback_speed={args.speed}", *args.set]
    out_root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="mgso-profile-realtime-"))
    results: dict = {}
    for p in paths:
        name = Path(p).name
        size = []
        if args.downscale > 1:
            from mgso.config import load_config
            from mgso.io import open_sequence

            cam = open_sequence(p, config=load_config(None).input).calibration.output
            size = [f"input.width={cam.width // args.downscale}", f"input.height={cam.height // args.downscale}"]
        res = {}
        for vname, sets in variants.items():
            res[vname] = _run(p, out_root / name / vname, [*base, *size, *sets], realtime=True)
        if args.deterministic:
            first = res[next(iter(variants))]
            steps = (first.get("mapping_steps_running") or 0) + (first.get("mapping_steps_final") or 0)
            res["deterministic_same_steps"] = _run(
                p, out_root / name / "deterministic",
                [*base, *size, *variants[next(iter(variants))], "system.mode=deterministic",
                 "mapping.mapper.iterations_per_keyframe=0", f"mapping.mapper.final_iterations={steps}"],
                realtime=False)
            res["deterministic_same_steps"]["final_iterations"] = steps
        results[name] = res
    print(json.dumps({"profile": "realtime", "machine": platform.processor() or platform.machine(),
                      "cpu_count": os.cpu_count(), "speed": args.speed, "downscale": args.downscale,
                      "overrides": base, "variants": variants, "out": str(out_root), "results": results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
