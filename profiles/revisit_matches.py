"""Can a better descriptor see the 7-Scenes excerpt's revisits? ORB against SIFT on the closest true revisits.

For the sequence's ground-truth poses, the frame pairs at least ``--min-gap`` frames apart whose cameras are within
``--radius-m`` and ``--max-deg`` (the closest ``--pairs`` of them, by distance + angle / 60 degrees), and as a
control pairs ``--control-gaps`` frames apart: each detector's matches (two nearest neighbours, Lowe's ratio 0.75,
as the loop closer's place recognition) and how many of them agree with the true relative pose (Sampson distance
to the epipolar line under ``--epipolar-px``; the control pairs show how tight the true poses are: about 1 px
median at 3 frames). Prints one JSON line.

    MGSO_DATA=../shared/data python profiles/revisit_matches.py [--path P] [--pairs 10] [--features 1500]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _sampson(F: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = np.c_[a, np.ones(len(a))]
    b = np.c_[b, np.ones(len(b))]
    Fa, Ftb = a @ F.T, b @ F
    return np.abs(np.sum(b * Fa, 1)) / np.sqrt(Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Ftb[:, 0] ** 2 + Ftb[:, 1] ** 2)


def main(argv=None) -> int:
    import cv2

    from mgso.config import load_config
    from mgso.geometry import hat, rotation_angle
    from mgso.io import open_sequence

    data = Path(os.environ.get("MGSO_DATA", ROOT.parent / "shared" / "data"))
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--path", default=str(data / "7scenes_redkitchen_0-499"))
    ap.add_argument("--pairs", type=int, default=10)
    ap.add_argument("--min-gap", type=int, default=120, help="frames between the two of a revisit pair")
    ap.add_argument("--radius-m", type=float, default=0.5)
    ap.add_argument("--max-deg", type=float, default=30.0)
    ap.add_argument("--step", type=int, default=5, help="frames between candidates")
    ap.add_argument("--features", type=int, default=1500)
    ap.add_argument("--epipolar-px", type=float, default=5.0)
    ap.add_argument("--control-gaps", default="3,10,20")
    args = ap.parse_args(argv)

    seq = open_sequence(args.path, config=load_config(None, []).input)
    gt = seq.groundtruth
    if gt is None or len(gt.cam_to_world) != len(seq):
        print(json.dumps({"skipped": f"{args.path}: needs ground truth for every frame"}))
        return 0
    cam = seq.calibration.output
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    Ki = np.linalg.inv(K)
    P = gt.cam_to_world

    def rel(i, j):                                            # camera j <- camera i
        return np.linalg.inv(P[j]) @ P[i]

    def dist_deg(T):
        return float(np.linalg.norm(T[:3, 3])), float(np.degrees(rotation_angle(T[:3, :3])))

    pairs = []
    for j in range(0, len(seq), args.step):
        for i in range(0, j - args.min_gap + 1, args.step):
            d, a = dist_deg(rel(i, j))
            if d < args.radius_m and a < args.max_deg:
                pairs.append((d + a / 60.0, i, j))
    pairs = [(i, j) for _, i, j in sorted(pairs)[: args.pairs]]
    controls = [(100, 100 + int(g)) for g in args.control_gaps.split(",")]

    gray = {}

    def img(i):
        if i not in gray:
            gray[i] = cv2.cvtColor((seq.load(i).rgb * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        return gray[i]

    dets = {"orb": (cv2.ORB_create(args.features), cv2.NORM_HAMMING),
            "sift": (cv2.SIFT_create(args.features), cv2.NORM_L2)}

    def measure(i, j) -> dict:
        T = rel(i, j)
        R, t = T[:3, :3], T[:3, 3]
        F = Ki.T @ hat(t) @ R @ Ki
        d, a = dist_deg(T)
        row = {"frames": [i, j], "distance_m": round(d, 3), "angle_deg": round(a, 1)}
        for name, (det, norm) in dets.items():
            ki, di = det.detectAndCompute(img(i), None)
            kj, dj = det.detectAndCompute(img(j), None)
            good = []
            if di is not None and dj is not None and len(di) and len(dj) > 1:
                good = [m for m, n in (x for x in cv2.BFMatcher(norm).knnMatch(di, dj, k=2) if len(x) == 2)
                        if m.distance < 0.75 * n.distance]
            if good:
                a = np.array([ki[g.queryIdx].pt for g in good])
                e = _sampson(F, a, np.array([kj[g.trainIdx].pt for g in good]))
                row[name] = {"matches": len(good), "consistent": int((e < args.epipolar_px).sum()),
                             "median_px": round(float(np.median(e)), 2)}
            else:
                row[name] = {"matches": 0, "consistent": 0, "median_px": None}
        return row

    rev = [measure(i, j) for i, j in pairs]
    ctl = [measure(i, j) for i, j in controls]

    def med(rows, name, key):
        return float(np.median([r[name][key] for r in rows])) if rows else None

    print(json.dumps({"profile": "revisit_matches", "path": args.path, "features": args.features,
                      "epipolar_px": args.epipolar_px,
                      "summary": {n: {"revisit_consistent_median": med(rev, n, "consistent"),
                                      "revisit_matches_median": med(rev, n, "matches"),
                                      "control_consistent_median": med(ctl, n, "consistent")} for n in dets},
                      "revisits": rev, "controls": ctl}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
