"""Loop closure (docs/loop.md): the synthetic drifted loop through the whole system with loop closure on and off, and
the loop closer alone on recordings of the DSO odometry; prints one JSON line.

- ``synthetic``: the oracle odometry with injected drift around one figure-eight of the synthetic room (the setup of
  tests/loop/test_closer.py unless changed by the options), the whole deterministic system, outputs and evaluation,
  once with ``loop.enabled=true`` and once with ``false``: loops accepted, ATE, PSNR (MonoGS protocol), Gaussians,
  the closer's seconds.
- ``recordings``: each sequence's DSO stream (recorded once by profiles/mapping.py's recorder and kept in its cache)
  replayed into a :class:`mgso.loop.closer.LoopCloser` alone (no mapping): keyframes, candidates, loops accepted,
  rejections by reason, the closer's seconds, and the ATE of the odometry's trajectory and of the corrected one.

    python profiles/loop.py                                   # the synthetic loop and the shared 7-Scenes excerpt
    python profiles/loop.py ../shared/data/kitti00_0-159 --no-synthetic --set loop.prefilter_keep=30
    python profiles/loop.py --out-and-back --no-synthetic    # the 7-Scenes excerpt out on its even frames, back on
                                                             # its odd ones: a revisit of every place (real images)

``--out-and-back`` (7-Scenes layout only) makes, under ``--work`` (default /tmp/mgso-out-and-back), a folder of
symbolic links to each sequence's files, nothing copied: frames 0, 2, 4, ... of the recording, then its odd frames
backwards (..., 5, 3, 1), numbered 0, 1, 2, ... (played at 30 frames/s: the camera goes out and comes back over the
same path at twice its speed, with the same ground truth). The shared excerpt never comes back to a place closely
enough to verify a loop (docs/loop.md); this one does at every place on the way back, with images that are the
neighbours of the ones seen on the way out (a thirtieth of a second apart), not the same images. The folder is an
ordinary 7-Scenes sequence: ``profiles/mapping.py``, ``profiles/dso_reference.py`` and ``mgso run`` take it too.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "profiles"))


def synthetic(args) -> dict:
    from mgso import synthetic as syn
    from mgso.app.outputs import write_outputs
    from mgso.config import load_config
    from mgso.io import open_sequence
    from mgso.oracle import OracleOdometry
    from mgso.system import System

    folder = syn.cached_sequence_folder(num_frames=args.frames, width=args.width, height=args.width * 3 // 4,
                                        seed=0, motion_scale=args.motion_scale)
    drift = tuple(float(x) for x in args.drift.split(","))
    out = {"frames": args.frames, "size": [args.width, args.width * 3 // 4], "motion_scale": args.motion_scale,
           "drift_per_frame": drift, "points": args.points}
    for loop in ("true", "false"):
        cfg = load_config(None, ["mapping.mapper.iterations_per_keyframe=10", "mapping.mapper.final_iterations=30",
                                 "output.plot=false", "output.save_renders=false", "system.eval_photo_slam=false",
                                 f"loop.enabled={loop}", *args.set])
        seq = open_sequence(str(folder), config=cfg.input)
        odo = OracleOdometry.from_sequence(seq, keyframe_every=4, points=args.points, drift=drift)
        t0 = time.perf_counter()
        system = System(odo, cfg)
        res = system.run(seq.frames())
        with tempfile.TemporaryDirectory() as tmp:
            m = write_outputs(res, system.mapper, seq, cfg, tmp, odometry_name=odo.name)
        lp = m["loop"] or {}
        out["loop_" + ("on" if loop == "true" else "off")] = {
            "ate_all_frames_m": m["ate_all_frames_m"], "ate_odometry_all_frames_m": m["ate_odometry_all_frames_m"],
            "psnr_monogs_db": m["psnr_monogs_db"], "num_gaussians": m["num_gaussians"],
            "loops_accepted": lp.get("accepted"), "candidates": lp.get("candidates"),
            "closer_s": lp.get("seconds"), "wall_s": round(time.perf_counter() - t0, 1),
            "loops": [{k: r[k] for k in ("keyframe_id", "candidate_id", "frame_index", "candidate_frame_index",
                                         "inliers", "scale", "correction_degrees", "correction_scale")}
                      for r in lp.get("loops", [])]}
    return out


def recording(path: str, args) -> dict:
    import mapping

    # recordings made by running profiles/mapping.py name its classes as __main__'s
    main_module = sys.modules["__main__"]
    for name in ("Recording", "_mappingproxy"):
        if not hasattr(main_module, name):
            setattr(main_module, name, getattr(mapping, name))
    from mgso.config import load_config
    from mgso.eval import compute_ate
    from mgso.io import open_sequence
    from mgso.loop.closer import LoopCloser
    from mgso_kernels import runtime

    cfg = load_config(None, args.set)
    seq = open_sequence(path, config=cfg.input)
    rec = mapping.record(seq, cfg, runtime.init("cpu", threads=cfg.runtime.threads), Path(args.cache), path)
    closer = LoopCloser(cfg)
    t0 = time.perf_counter()
    for r in rec.frames:
        for msg in r.messages:
            closer.observe(msg)
            closer.correct(msg)
        closer.poll()
    for msg in rec.final:
        closer.observe(msg, final=True)
        closer.correct(msg)
    closer.finish()
    wall = time.perf_counter() - t0
    st = closer.stats.as_dict()
    out = {k: st[k] for k in ("keyframes", "queries", "candidates", "accepted", "rejected", "graph_solves",
                              "error")}
    out["closer_s"] = round(st["seconds"], 2)
    out["closer_s_per_keyframe"] = round(st["seconds"] / max(1, st["keyframes"]), 4)
    out["wall_s"] = round(wall, 2)
    out["loops"] = [{k: r[k] for k in ("frame_index", "candidate_frame_index", "inliers", "rmse", "scale")}
                    for r in st["loops"]]
    if seq.groundtruth is not None:
        out["ate_odometry_m"] = compute_ate(rec.trajectory, seq.groundtruth, align="sim3", max_diff=0.01).rmse
        out["ate_corrected_m"] = compute_ate(closer.correct_trajectory(rec.trajectory), seq.groundtruth,
                                             align="sim3", max_diff=0.01).rmse
    return out


def out_and_back(src: str | Path, work: str | Path) -> Path:
    """The out-and-back folder of the 7-Scenes-layout sequence ``src`` under ``work`` (links, made once)."""
    from mgso.io.sevenscenes import _COLOR      # the reader's own pattern of a colour image's name

    src = Path(src).resolve()
    numbers = sorted(int(m.group(1)) for m in (_COLOR.fullmatch(p.name) for p in src.iterdir()) if m)
    if not numbers:
        raise SystemExit(f"profiles/loop.py: {src}: --out-and-back takes a 7-Scenes layout (frame-XXXXXX.color.*)")
    order = [n for n in numbers if n % 2 == 0] + [n for n in reversed(numbers) if n % 2 == 1]
    dst = Path(work) / f"{src.name}-out-and-back"
    dst.mkdir(parents=True, exist_ok=True)
    for f in src.iterdir():                                          # calibration and other shared files
        if not f.name.startswith("frame-") and not (dst / f.name).exists():
            (dst / f.name).symlink_to(f)
    for new, old in enumerate(order):
        for f in src.glob(f"frame-{old:06d}.*"):
            link = dst / f.name.replace(f"frame-{old:06d}", f"frame-{new:06d}", 1)
            if not link.exists():
                link.symlink_to(f)
    return dst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="*", help="sequences for the recordings part (default: the shared 7-Scenes "
                                             "excerpt when it is there)")
    ap.add_argument("--no-synthetic", action="store_true", help="skip the synthetic loop")
    ap.add_argument("--frames", type=int, default=88)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--motion-scale", type=float, default=4.0)
    ap.add_argument("--drift", default="0.002,0.002,0.003", help="rotation rad, translation m, log-scale per frame")
    ap.add_argument("--points", type=int, default=1000)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "mgso" / "odometry-recordings"))
    ap.add_argument("--out-and-back", action="store_true",
                    help="replay each sequence out on its even frames and back on its odd ones (7-Scenes layout)")
    ap.add_argument("--work", default="/tmp/mgso-out-and-back", help="where --out-and-back makes its folders")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import warp as wp

    if hasattr(wp.config, "log_level"):
        wp.config.log_level = logging.WARNING
    from mgso.io.paths import shared_data_dir

    paths = list(args.paths)
    if not paths:
        root = shared_data_dir()
        if root is not None and (root / "7scenes_redkitchen_0-499").is_dir():
            paths = [str(root / "7scenes_redkitchen_0-499")]
    if args.out_and_back:
        paths = [str(out_and_back(p, args.work)) for p in paths]
    result: dict = {"profile": "loop", "settings": args.set}
    if not args.no_synthetic:
        result["synthetic"] = synthetic(args)
    result["recordings"] = {Path(p).name: recording(p, args) for p in paths}
    print(json.dumps(result, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
