"""The bar of the odometry: the reference DSO (github.com/JakobEngel/dso, GPL-3; built by you, not shipped) run on the
same frames mgso sees, on the same machine, so that ``profiles/odometry.py``'s figures have a fair comparison.

    python profiles/dso_reference.py --dso /path/to/dso/build/bin/dso_dataset [--path P ...] [--nomt]

For each sequence (default: ``kitti00_0-159``, ``7scenes_redkitchen_0-499`` and ``rgbd_dataset_freiburg1_rpy_0-359``
from the shared data folder; one that is missing there is skipped) the
frames are read with mgso's own reader (undistorted / cropped as mgso tracks them) and written as 8-bit grey PNGs
into a temporary folder (cropped at the right and bottom to a width a multiple of 32 and a height of 16, which DSO
needs: KITTI's 1232x368 becomes 1216x368) with DSO's ``times.txt`` and a ``camera.txt`` (pinhole, no distortion, no
rescaling), then
``dso_dataset preset=0 mode=1 nogui=1 quiet=1 nolog=1`` runs on them: preset 0 plays the sequence without real-time
pacing (DSO's "linearize" operation: every frame is tracked and every keyframe DSO asks for is made, as mgso's
odometry does); mode 1 is "no photometric calibration". Prints one JSON line per run: wall seconds and wall ms a
frame (image decoding included, as in ``profiles/odometry.py``), the process's CPU time a frame
(``process_cpu_ms_per_frame``: all its threads, user + system, from ``getrusage``; the figure to set beside
``profiles/odometry.py``'s ``cpu_ms_per_frame``), DSO's own "ms per frame (single core)" (``dso_cpu_ms_per_frame``:
``clock()``, restarted on every frame until DSO's initialiser succeeds, so its initialisation is left out: 6-8 % of
the process's CPU on both excerpts, 2026-12-03), and the ATE (Sim(3), ``evo_ape -as`` as mgso computes it) of
DSO's ``result.txt``, which holds only the keyframes DSO marginalised (``setting_onlyLogKFPoses``), with what a camera
standing still would score and the scale's drift along it (``standing_still_m``, ``scale_drift``: docs/evaluation.md).
``--keep DIR`` keeps each sequence's DSO folder (its images, ``result.txt``) under DIR.

Building DSO on Debian (no GUI): ``apt install libeigen3-dev libboost-thread-dev libsuitesparse-dev libopencv-dev``,
then its CMake build; recent compilers need ``-std=c++14``, ``-DBOOST_BIND_GLOBAL_PLACEHOLDERS`` and OpenCV 4's
``cv::IMREAD_*`` names, and ``dso_dataset`` is only built with Pangolin unless its viewer is removed from
``main_dso_pangolin.cpp``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mgso.eval import compute_ate  # noqa: E402
from mgso.io import open_sequence  # noqa: E402
from mgso.io.paths import shared_data_dir  # noqa: E402
from mgso.io.trajectory import read_tum  # noqa: E402

DEFAULT = ("kitti00_0-159", "7scenes_redkitchen_0-499", "rgbd_dataset_freiburg1_rpy_0-359")


def prepare(path: Path, out: Path) -> tuple[int, object]:
    """DSO's input folder from mgso's reader; returns (frames, ground truth or None)."""
    seq = open_sequence(path)
    cam = seq.calibration.output
    # DSO's pyramid needs the width a multiple of 32 and the height of 16 (it crashes on KITTI's 1232x368): crop the
    # right and bottom edges, which keeps the principal point
    w, h = cam.width // 32 * 32, cam.height // 16 * 16
    img_dir = out / "images"
    img_dir.mkdir(parents=True)
    lines = []
    n = 0
    for f in seq.frames():
        cv2.imwrite(str(img_dir / f"{f.index:06d}.png"), np.clip(f.gray[:h, :w] + 0.5, 0, 255).astype(np.uint8))
        lines.append(f"{f.index} {f.timestamp:.9f} 0")
        n += 1
    (out / "times.txt").write_text("\n".join(lines) + "\n")
    (out / "camera.txt").write_text(f"Pinhole {cam.fx} {cam.fy} {cam.cx} {cam.cy} 0\n{w} {h}\nnone\n{w} {h}\n")
    return n, seq.groundtruth


def run(dso: str, work: Path, frames: int, gt, nomt: bool) -> dict:
    args = [dso, "preset=0", f"files={work / 'images'}", f"calib={work / 'camera.txt'}", "mode=1", "nogui=1",
            "quiet=1", "nolog=1"] + (["nomt=1"] if nomt else [])
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(args, cwd=work, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    out = {"threads": "nomt" if nomt else "mt", "frames": frames, "returncode": p.returncode,
           "wall_s": round(wall, 1), "wall_ms_per_frame": round(1000 * wall / max(frames, 1), 1),
           # the process's CPU time (all its threads, user + system, its start-up included): the figure to compare
           # with profiles/odometry.py's cpu_ms_per_frame
           "process_cpu_ms_per_frame": round(1000 * cpu / max(frames, 1), 2)}
    m = re.search(r"([0-9.]+)ms per frame \(single core\)", p.stdout + p.stderr)
    if m:
        # DSO's own figure: clock() from the first frame after its initialiser succeeded (main_dso_pangolin.cpp
        # restarts its clock on every frame while the system is not initialised), divided by all frames: it leaves
        # out the initialisation, which profiles/odometry.py counts
        out["dso_cpu_ms_per_frame"] = float(m.group(1))
    res = work / "result.txt"
    if gt is not None and res.exists():
        rows = [ln.split() for ln in res.read_text().splitlines() if ln.strip()]
        if len(rows) >= 3:
            tum = work / "result_tum.txt"
            tum.write_text("\n".join(" ".join(r) for r in rows) + "\n")
            traj = read_tum(tum)
            ate = compute_ate(traj, gt, align="sim3")
            out["ate_marginalized_keyframes_m"] = round(ate.rmse, 4)
            out["marginalized_keyframes"] = len(rows)
            # what the ATE is worth (docs/evaluation.md): a camera standing still's, and the scale's drift
            out["standing_still_m"] = round(ate.motionless_rmse, 4)
            out["scale_drift"] = None if ate.scale_drift is None else round(ate.scale_drift, 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dso", required=True, help="the dso_dataset binary")
    ap.add_argument("--path", action="append", help="sequence folder (repeatable)")
    ap.add_argument("--nomt", action="store_true", help="DSO without its worker threads (nomt=1)")
    ap.add_argument("--keep", help="keep each sequence's DSO folder (images, result.txt) under this folder")
    args = ap.parse_args()
    if not os.access(args.dso, os.X_OK):
        sys.exit(f"{args.dso}: not an executable dso_dataset")
    paths = [Path(p) for p in args.path] if args.path else []
    if not paths:
        base = shared_data_dir()
        if base is None:
            sys.exit("no --path and no shared data folder (set MGSO_DATA)")
        paths = [base / d for d in DEFAULT]
    result = {"profile": "dso_reference", "load_avg_1min": round(os.getloadavg()[0], 2)}
    if args.keep:                       # before any work: a folder --keep would overwrite
        for path in paths:
            if (Path(args.keep) / path.name).exists():
                sys.exit(f"{Path(args.keep) / path.name}: already exists (--keep writes a new folder per sequence)")
    for path in paths:
        if not path.is_dir():
            print(f"{path}: not found, skipped", file=sys.stderr)
            continue
        with (nullcontext(str(Path(args.keep) / path.name)) if args.keep
              else tempfile.TemporaryDirectory(prefix="mgso-dso-")) as work:
            n, gt = prepare(path, Path(work))
            result[path.name] = run(args.dso, Path(work), n, gt, args.nomt)
    result["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
