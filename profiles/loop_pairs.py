"""Every keyframe pair of a recorded DSO stream through the loop closer's verification, judged by the ground truth;
prints one JSON line.

The odometry's stream is recorded once per sequence (profiles/mapping.py's recorder and cache, as profiles/loop.py);
each keyframe's features are made as the closer makes them, and every pair at least ``loop.min_keyframe_gap``
keyframes apart is verified (``mgso.loop.verify.verify``), whatever place recognition would have proposed. The
pairs are classed by the ground truth's relative pose of the two keyframes' frames: ``near`` (within ``--near-m``
and ``--near-deg``: true revisits a closer should close), ``far`` (beyond ``--far-m`` or ``--far-deg``) and ``mid``.
Per class: the verification's reasons; for the near pairs by angle (0-5 and 5-``--near-deg`` degrees); every
accepted pair's rotation error against the ground truth (a wrong loop is one more than ``--wrong-deg`` off).

``--matches N`` also samples N near pairs 5-``--near-deg`` degrees apart and counts, as the verification matches
them (mutual ratio-test ORB matches), how many are right (Sampson distance under ``--epipolar-px`` to the true
epipolar geometry) among all, among those with a depth in the new keyframe, and, for comparison, among OpenCV's ORB
alone (1,500 corners over its pyramid): medians.

    MGSO_DATA=../shared/data python profiles/loop_pairs.py ../shared/data/rgbd_dataset_freiburg1_rpy_0-359 \
        [--set loop.epipolar_check=false] [--matches 25]
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "profiles"))


def _match_quality(pairs, feats, cam, args) -> dict:
    import cv2
    from revisit_matches import _sampson  # profiles/revisit_matches.py: the Sampson distance to the epipolar line

    from mgso.geometry import hat
    from mgso.loop.verify import mutual_matches

    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    Ki = np.linalg.inv(K)
    orb = cv2.ORB_create(1500)
    rows = collections.defaultdict(list)
    for k, c, rel in pairs:
        F = Ki.T @ hat(rel[:3, 3]) @ rel[:3, :3] @ Ki
        fk, fc = feats[k], feats[c]
        pr = mutual_matches(fk.descriptors, fc.descriptors, args.match_ratio)
        right = _sampson(F, fk.keypoints[pr[:, 0]], fc.keypoints[pr[:, 1]]) < args.epipolar_px if len(pr) else \
            np.zeros(0, bool)
        depth = np.isfinite(fk.idepths[pr[:, 0]]) if len(pr) else np.zeros(0, bool)
        k1, d1 = orb.detectAndCompute(fk.gray, None)
        k2, d2 = orb.detectAndCompute(fc.gray, None)
        po = mutual_matches(d1, d2, args.match_ratio) if d1 is not None and d2 is not None else np.zeros((0, 2), int)
        ro = _sampson(F, np.array([k1[i].pt for i in po[:, 0]]), np.array([k2[j].pt for j in po[:, 1]])) \
            < args.epipolar_px if len(po) else np.zeros(0, bool)
        for key, val in (("matches", len(pr)), ("right", int(right.sum())), ("with_depth", int(depth.sum())),
                         ("right_with_depth", int((right & depth).sum())),
                         ("right_without_depth", int((right & ~depth).sum())),
                         ("orb_alone_matches", len(po)), ("orb_alone_right", int(ro.sum()))):
            rows[key].append(val)
    return {"pairs": len(pairs), **{k: float(np.median(v)) for k, v in rows.items()}}


def recording(path: str, args) -> dict:
    import mapping

    main_module = sys.modules["__main__"]       # recordings made by profiles/mapping.py name its classes so
    for name in ("Recording", "_mappingproxy"):
        if not hasattr(main_module, name):
            setattr(main_module, name, getattr(mapping, name))
    from mgso.config import load_config
    from mgso.geometry import rotation_angle
    from mgso.io import open_sequence
    from mgso.loop.place import extract_features
    from mgso.loop.verify import verify
    from mgso.messages import KeyframeMessage
    from mgso_kernels import runtime

    base = load_config(None, [])
    cfg = load_config(None, args.set)
    seq = open_sequence(path, config=base.input)
    if seq.groundtruth is None:
        return {"skipped": f"{path}: no ground truth"}
    # the odometry's settings are the defaults' (the recording's key); args.set changes the verification only
    rec = mapping.record(seq, base, runtime.init("cpu", threads=base.runtime.threads), Path(args.cache), path)
    kfs = [m for r in rec.frames for m in r.messages if isinstance(m, KeyframeMessage)]
    gt = seq.groundtruth.cam_to_world
    feats = {m.keyframe_id: extract_features(m.keyframe_id, m.image, m.camera, np.asarray(m.points_uv),
                                             np.asarray(m.idepths), cfg.loop) for m in kfs}
    ids = [m.keyframe_id for m in kfs]
    frame = {m.keyframe_id: m.frame_index for m in kfs}
    rows, sample = [], []
    t0 = time.perf_counter()
    for a, k in enumerate(ids):
        for c in ids[:max(0, a - cfg.loop.min_keyframe_gap)]:
            rel = np.linalg.inv(gt[frame[c]]) @ gt[frame[k]]          # new keyframe's camera -> old keyframe's
            d = float(np.linalg.norm(rel[:3, 3]))
            ang = float(np.degrees(rotation_angle(rel[:3, :3])))
            cls = "near" if d < args.near_m and ang < args.near_deg else \
                "far" if d > args.far_m or ang > args.far_deg else "mid"
            v = verify(feats[k], feats[c], cfg.loop, device="cpu", rng_seed=k, tracking=cfg.tracking)
            err = None
            if v.accepted:
                S = v.relative
                R = S[:3, :3] / np.cbrt(np.linalg.det(S[:3, :3]))
                err = float(np.degrees(rotation_angle(R.T @ rel[:3, :3])))
            rows.append((cls, ang, v.reason, err))
            if cls == "near" and ang >= 5.0:
                sample.append((k, c, rel))
    wall = time.perf_counter() - t0

    def reasons(sel):
        return {"pairs": len(sel), "reasons": dict(collections.Counter(r[2] for r in sel).most_common())}

    out = {"keyframes": len(ids), "verify_s": round(wall, 1)}
    for cls in ("near", "mid", "far"):
        out[cls] = reasons([r for r in rows if r[0] == cls])
    near = [r for r in rows if r[0] == "near"]
    out["near_0-5deg"] = reasons([r for r in near if r[1] < 5.0])
    out[f"near_5-{args.near_deg:g}deg"] = reasons([r for r in near if r[1] >= 5.0])
    errs = [r[3] for r in rows if r[3] is not None]
    out["accepted"] = len(errs)
    out[f"accepted_wrong_over_{args.wrong_deg:g}deg"] = sum(e > args.wrong_deg for e in errs)
    if errs:
        out["accepted_rotation_error_deg"] = {"median": round(float(np.median(errs)), 2),
                                              "max": round(float(np.max(errs)), 2)}
    if args.matches and sample:
        pick = np.random.default_rng(0).choice(len(sample), min(args.matches, len(sample)), replace=False)
        out["match_quality_5deg_up"] = _match_quality([sample[i] for i in sorted(pick)], feats, kfs[0].camera, args)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="+")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "mgso" / "odometry-recordings"))
    ap.add_argument("--near-m", type=float, default=0.3)
    ap.add_argument("--near-deg", type=float, default=18.0)
    ap.add_argument("--far-m", type=float, default=0.8)
    ap.add_argument("--far-deg", type=float, default=40.0)
    ap.add_argument("--wrong-deg", type=float, default=5.0)
    ap.add_argument("--matches", type=int, default=0, help="near pairs 5 degrees or more apart to count matches of")
    ap.add_argument("--match-ratio", type=float, default=0.75)
    ap.add_argument("--epipolar-px", type=float, default=3.0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import warp as wp

    if hasattr(wp.config, "log_level"):
        wp.config.log_level = logging.WARNING
    out = {"profile": "loop_pairs", "settings": args.set,
           "recordings": {Path(p).name: recording(p, args) for p in args.paths}}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
