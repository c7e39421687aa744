"""Where the map's dB go: the mapper fed by the DSO odometry, by its recording with true poses, and by the oracle.

The odometry is run once per sequence and its stream (every frame's pose and messages, the final messages and
trajectories) is recorded into ``--cache`` (keyed by the sequence, the image size and the odometry's settings); every
mapping variant then replays that stream into a fresh :class:`mgso.system.System`, so a variant costs the mapper's
time only and every variant sees the same odometry. The sources (``--source``, several allowed):

- ``dso``: the recorded DSO odometry as it ran (what ``mgso run`` maps);
- ``dso-gtpose``: the same keyframes, images, points and affine brightness, but every pose replaced by the ground
  truth; DSO's points keep their inverse depth in their host keyframe, scaled by the Sim(3) alignment's scale (the
  decomposition's "(b) true poses, DSO's points");
- ``dso-gtpose-local``: the same, each keyframe's points scaled by DSO's scale around that keyframe (true path length
  over DSO's between the keyframes 5 before and 5 after it) instead of the one alignment scale: DSO's scale drifts
  (about 0.5 to 2.5 units a metre on the 7-Scenes excerpt), which one scale cannot undo;
- ``oracle``: :class:`mgso.oracle.OracleOdometry` (true poses and depth-map points, a keyframe every 10 frames;
  "(c)"), not recorded.

Prints **one JSON line**: per source the figures of ``metrics.json`` (PSNR / SSIM MonoGS, Gaussians, map MB, ATE,
steps, densification) and the wall time.

    MGSO_DATA=../shared/data python profiles/mapping.py ../shared/data/7scenes_redkitchen_0-499 \
        --source dso --source dso-gtpose [--downscale 1] [--set mapping.train.refine_poses=true ...]
"""

from __future__ import annotations

import argparse
import copyreg
import dataclasses
import hashlib
import json
import logging
import pickle
import sys
import time
from pathlib import Path
from types import MappingProxyType, SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mgso.observers import Observer  # noqa: E402


def _mappingproxy(d: dict) -> MappingProxyType:
    return MappingProxyType(d)


copyreg.pickle(MappingProxyType, lambda m: (_mappingproxy, (dict(m),)))   # PoseUpdate's read-only mappings

FIGURES = ("ate_all_frames_m", "ate_keyframes_m", "ate_refined_all_frames_m", "psnr_monogs_db", "ssim_monogs",
           "num_gaussians", "map_size_mb", "keyframes", "mapping_iterations_per_s")


# ------------------------------------------------------------------------------------------- recording
@dataclasses.dataclass
class Recording:
    frames: list            # OdometryFrame per processed frame (messages included)
    final: list             # odometry.finish()
    trajectory: object      # Trajectory
    keyframe_trajectory: object
    name: str


class ReplayOdometry:
    """An :class:`mgso.system.OdometrySource` that plays a :class:`Recording` back (``process`` ignores the frame)."""

    def __init__(self, rec: Recording):
        self.rec = rec
        self.name = rec.name + " (replayed)"
        self.device = None          # no kernels of its own: the loop closer runs on the system's device
        self._k = 0

    def process(self, frame):
        r = self.rec.frames[self._k]
        self._k += 1
        return r

    def finish(self):
        return list(self.rec.final)

    def trajectory(self):
        return self.rec.trajectory

    def keyframe_trajectory(self):
        return self.rec.keyframe_trajectory


RECORDING_FORMAT = 2   # 2: OdometryFrame values and PointsMessage (was: DsoOdometry's frames, MarginalizedPoints)


def _odometry_key(cfg, seq_path: str) -> str:
    from mgso.config import config_to_dict

    d = config_to_dict(cfg)
    keep = {k: d[k] for k in ("input", "tracking", "window", "runtime") if k in d}
    keep["runtime"] = {k: v for k, v in keep["runtime"].items() if k not in ("threads", "blas_threads")}
    # RECORDING_FORMAT: the recorded classes' layout (a recording of another layout is made again)
    h = hashlib.sha1(json.dumps([str(Path(seq_path).resolve()), keep, RECORDING_FORMAT], sort_keys=True,
                                default=str).encode())
    return h.hexdigest()[:16]


def record(seq, cfg, device, cache: Path, seq_path: str) -> Recording:
    from mgso.messages import KeyframeMessage
    from mgso.odometry import Odometry
    from mgso.system import OdometryFrame

    path = cache / f"{seq.name}-{_odometry_key(cfg, seq_path)}.pkl"
    if path.is_file():
        with open(path, "rb") as fh:
            return pickle.load(fh)
    odo = Odometry.for_camera(seq.calibration.output, cfg, device=device, emit_messages=True)
    frames = []
    for f in seq.frames():   # the frame's values only (a FrameResult holds the tracker's results too)
        r = odo.process(f)
        frames.append(OdometryFrame(r.index, r.timestamp, r.cam_to_world,
                                    is_keyframe=any(isinstance(m, KeyframeMessage) for m in r.messages),
                                    affine=r.affine, exposure_ms=r.exposure_ms, status=r.status.value,
                                    messages=r.messages, seconds=r.seconds))
    final = list(odo.finish())
    rec = Recording(frames, final, odo.trajectory(), odo.keyframe_trajectory(), odo.name)
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as fh:
        pickle.dump(rec, fh, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(path)
    return rec


def with_true_poses(rec: Recording, gt, local_scale: bool = False) -> Recording:
    """``rec`` with every pose replaced by the ground truth at its timestamp, DSO's points moved with their host
    keyframe and scaled by the Sim(3) alignment's scale (DSO's arbitrary scale -> metres). ``local_scale``: each
    keyframe's points scaled by DSO's scale where that keyframe is instead (DSO's scale drifts: about 0.5 to 2.5 units a
    metre on the 7-Scenes excerpt): the true path length over DSO's between the keyframes 5 before and 5 after it."""
    from mgso.eval import compute_ate
    from mgso.io.trajectory import Trajectory
    from mgso.messages import KeyframeMessage, PointsMessage, PoseUpdate

    al = compute_ate(rec.trajectory, gt, align="sim3", max_diff=0.01)
    s_all = float(al.alignment.scale)
    ts_gt = gt.timestamps

    def true(t):
        k = int(np.argmin(np.abs(ts_gt - t)))
        if abs(ts_gt[k] - t) > 0.01:
            return None
        return gt.cam_to_world[k]

    kf_scale: dict[float, float] = {}         # keyframe timestamp -> metres per DSO unit there
    if local_scale:
        kt = rec.keyframe_trajectory
        ok = [i for i, t in enumerate(kt.timestamps) if true(t) is not None]
        t_kf = kt.timestamps[ok]
        p_est = kt.cam_to_world[ok][:, :3, 3]
        p_gt = np.stack([true(t)[:3, 3] for t in t_kf])
        d_est = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p_est, axis=0), axis=1))]
        d_gt = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p_gt, axis=0), axis=1))]
        for i, t in enumerate(t_kf):
            a, b = max(0, i - 5), min(len(t_kf) - 1, i + 5)
            kf_scale[round(float(t), 6)] = (float((d_gt[b] - d_gt[a]) / (d_est[b] - d_est[a]))
                                            if d_est[b] > d_est[a] else s_all)
    host_scale: dict[int, float] = {}         # keyframe id -> its points' scale

    kf_pose: dict[int, np.ndarray] = {}      # keyframe id -> DSO's latest camera-to-world
    kf_true: dict[int, np.ndarray] = {}      # keyframe id -> the true camera-to-world

    def fix(msgs):
        out = []
        for m in msgs:
            if isinstance(m, KeyframeMessage):
                T = true(m.timestamp)
                if T is None:
                    continue
                kf_pose[m.keyframe_id] = m.cam_to_world
                kf_true[m.keyframe_id] = T
                s = host_scale[m.keyframe_id] = kf_scale.get(round(float(m.timestamp), 6), s_all)
                out.append(dataclasses.replace(m, cam_to_world=T, idepths=np.asarray(m.idepths) / s))
            elif isinstance(m, PoseUpdate):
                for k, T in m.cam_to_world.items():
                    if k in kf_pose:
                        kf_pose[k] = T
                poses = {k: kf_true[k] for k in m.cam_to_world if k in kf_true}
                out.append(PoseUpdate(poses, affine=dict(m.affine)))
            elif isinstance(m, PointsMessage):
                h = m.host_keyframe_id
                if h not in kf_pose:
                    continue
                pc = (np.asarray(m.points) - kf_pose[h][:3, 3]) @ kf_pose[h][:3, :3]   # in the host camera
                T = kf_true[h]
                out.append(dataclasses.replace(m, points=(host_scale[h] * pc) @ T[:3, :3].T + T[:3, 3]))
            else:
                out.append(m)
        return tuple(out)

    frames = []
    for r in rec.frames:
        T = true(r.timestamp) if r.cam_to_world is not None else None
        frames.append(dataclasses.replace(r, cam_to_world=T, messages=fix(r.messages)))
    final = list(fix(rec.final))

    def retime(traj):
        keep = [i for i, t in enumerate(traj.timestamps) if true(t) is not None]
        return Trajectory(traj.timestamps[keep], np.stack([true(traj.timestamps[i]) for i in keep]))

    return Recording(frames, final, retime(rec.trajectory), retime(rec.keyframe_trajectory),
                     rec.name + " with true poses")


EXTRA_VIEW_ID = 10_000_000      # extra views' ids: this + the frame's index (never a keyframe id of the recording)


def with_extra_views(rec: Recording, seq, per_interval: int) -> Recording:
    """``rec`` with up to ``per_interval`` tracked frames between two keyframe messages sent to the mapper as
    training views too (issue 12: "training views beyond keyframes"), evenly spaced, without points (they seed
    nothing). Each is anchored to the latest keyframe at its time: its pose is that keyframe's pose times the
    relative pose at tracking time, and it moves when the window moves that keyframe. Frames the MonoGS protocol
    evaluates (every 5th frame with a pose) are never chosen, so both arms are evaluated on the same frames."""
    from mgso.eval import MONOGS, select_frames
    from mgso.messages import KeyframeMessage, PoseUpdate

    with_pose = {round(float(t), 6) for t in rec.trajectory.timestamps}   # the evaluation's frames: the final path's
    evaluated = set(select_frames(MONOGS, [r.index for r in rec.frames if round(float(r.timestamp), 6) in with_pose]))

    # pass 1: the intervals' candidates (tracked, not a keyframe, not an evaluated frame)
    chosen: set[int] = set()
    cand: list[int] = []
    for k, r in enumerate(rec.frames):
        if any(isinstance(m, KeyframeMessage) for m in r.messages):
            if cand:
                pick = np.linspace(0, len(cand) - 1, per_interval + 2)[1:-1] if len(cand) > per_interval else \
                    np.arange(len(cand))
                chosen.update(cand[int(round(p))] for p in pick)
            cand = []
        elif r.status == "tracked" and r.cam_to_world is not None and r.index not in evaluated:
            cand.append(k)
    # pass 2: the stream with the extra views
    kf_pose: dict[int, np.ndarray] = {}
    anchored: dict[int, list[tuple[int, np.ndarray]]] = {}   # keyframe id -> [(view id, keyframe-to-frame)]
    latest: KeyframeMessage | None = None

    def fix(msgs):
        nonlocal latest
        out = []
        for m in msgs:
            if isinstance(m, KeyframeMessage):
                kf_pose[m.keyframe_id] = m.cam_to_world
                latest = m
                out.append(m)
            elif isinstance(m, PoseUpdate):
                poses = dict(m.cam_to_world)
                for kid, T in m.cam_to_world.items():
                    kf_pose[kid] = T
                    for vid, rel in anchored.get(kid, ()):
                        poses[vid] = T @ rel
                out.append(PoseUpdate(poses, affine=dict(m.affine)))
            else:
                out.append(m)
        return tuple(out)

    frames = []
    for k, r in enumerate(rec.frames):
        msgs = fix(r.messages)
        if k in chosen and latest is not None:
            T_kf = kf_pose[latest.keyframe_id]
            rel = np.linalg.inv(T_kf) @ r.cam_to_world
            vid = EXTRA_VIEW_ID + r.index
            anchored.setdefault(latest.keyframe_id, []).append((vid, rel))
            img = seq.load(r.index).rgb
            msgs = msgs + (KeyframeMessage(vid, r.index, r.timestamp, img, latest.camera, T_kf @ rel,
                                           np.zeros((0, 2)), np.zeros(0), affine=r.affine, exposure_ms=r.exposure_ms,
                                           segment=latest.segment, mask=latest.mask),)
        frames.append(dataclasses.replace(r, messages=msgs))
    return Recording(frames, list(fix(rec.final)), rec.trajectory, rec.keyframe_trajectory,
                     rec.name + f" with {len(chosen)} extra views")


# ------------------------------------------------------------------------------------------------ run
def _one(args) -> dict:
    import warp as wp

    if hasattr(wp.config, "log_level"):
        wp.config.log_level = logging.WARNING
    from mgso.config import load_config
    from mgso.io import open_sequence
    from mgso.oracle import OracleOdometry
    from mgso.app.outputs import write_outputs
    from mgso.app.writer import RunWriter
    from mgso.system import System
    from mgso_kernels import runtime

    over = [f"runtime.device={args.device}", "system.mode=deterministic", "system.eval_photo_slam=false",
            "mapping.capacity=500000", *args.set]
    cfg = load_config(None, over)
    if args.downscale > 1:
        cam = open_sequence(args.one, config=cfg.input).calibration.output
        over = [f"input.width={cam.width // args.downscale}", f"input.height={cam.height // args.downscale}"] + over
        cfg = load_config(None, over)
    device = runtime.init(args.device, threads=cfg.runtime.threads)
    seq = open_sequence(args.one, config=cfg.input)
    out = Path(args.out) / f"{seq.name}-{args.source}-{args.tag}"
    # config.yaml and sequence.json as `mgso run` writes them (its writer), so the replay's folder is a run folder
    # to the profiles that read one (blend_depth.py, splat_raster.py --run, map_weights.py, evaluation.py)
    writer = RunWriter(out)
    writer.write_config(cfg)
    writer.write_sequence(seq)
    t0 = time.perf_counter()
    if args.source == "oracle":
        try:
            odo = OracleOdometry.from_sequence(seq, keyframe_every=10, points=600, idepth_noise=0.02)
        except ValueError as exc:
            return {"skipped": str(exc)}
        frames = seq.frames()
    else:
        rec = record(seq, cfg, device, Path(args.cache), args.one)
        if args.source in ("dso-gtpose", "dso-gtpose-local"):
            if seq.groundtruth is None:
                return {"skipped": "no ground truth"}
            rec = with_true_poses(rec, seq.groundtruth, local_scale=args.source == "dso-gtpose-local")
        if args.extra_views:
            rec = with_extra_views(rec, seq, args.extra_views)
        odo = ReplayOdometry(rec)
        frames = [SimpleNamespace(index=r.index, timestamp=r.timestamp) for r in rec.frames]
    t_map = time.perf_counter()
    watcher = ViewWatcher(args.watch_views) if args.watch_views else None
    system = System(odo, cfg, device=device, observer=watcher)
    if watcher is not None:
        watcher.mapper = system.mapper
    result = system.run(frames)
    m = write_outputs(result, system.mapper, seq, cfg, out, odometry_name=odo.name)
    fig = {k: m.get(k) for k in FIGURES}
    fig["steps"] = m["mapper"]["steps"]
    fig["densify"] = m["mapper"]["densify"]
    fig["gaussians_seeded"] = m["mapper"]["gaussians_seeded"]
    sr = system.mapper.stats.seed_results
    fig["seeding"] = {"seedings": len(sr), "candidates": int(sum(r.num_candidates for r in sr)),
                      "rejected_visibility": int(sum(r.num_rejected_visibility for r in sr)),
                      "added": int(sum(r.num_added for r in sr)),
                      "added_first_keyframe": int(sr[0].num_added) if sr else 0,
                      "untrusted": int(system.mapper.stats.keyframes_untrusted),
                      # mapping.seeding.distrust_median: keyframes whose depths missed the map's 3x or more, and the
                      # keyframe after which none was trusted (None: never)
                      "scale_broken": int(system.mapper.stats.keyframes_scale_broken),
                      "odometry_untrusted_at": system.mapper.stats.odometry_untrusted_at,
                      # each keyframe's median relative depth error against the map (the trust test's figure)
                      "depth_error_medians": [None if r.depth_error_median is None else round(r.depth_error_median, 3)
                                              for r in sr]}
    fig["keyframe_psnr"] = _training_view_psnr(system.mapper)
    if watcher is not None:
        fig["watched_views"] = watcher.history
    mono = [r for r in m.get("render") or [] if r.get("protocol_key") == "monogs"]
    fig["psnr_per_frame"] = {f["frame"]: round(f["psnr_db"], 2) for f in mono[0]["frames"]} if mono else {}
    fig["wall_s"] = round(time.perf_counter() - t0, 1)
    fig["mapping_wall_s"] = round(time.perf_counter() - t_map, 1)
    fig["out"] = str(out)
    return fig


def _view_psnr(mapper, v) -> float:
    """The map's PSNR on training view ``v`` (Mapper.view_psnr: its map pose, exposure and valid pixels)."""
    return round(mapper.view_psnr(v.view_id), 2)


class ViewWatcher(Observer):
    """``--watch-views N``: after every keyframe the mapper takes, the PSNR of its first N training views (the
    oldest keyframes) rendered from the map as it is then, with the step count, the map's size and the mapper's
    densification totals: when and by what an early view's fit is lost."""

    def __init__(self, n: int):
        self.n = int(n)
        self.mapper = None
        self.history: list = []

    def on_map_updated(self, u) -> None:
        m = self.mapper
        if m is None or not len(m.views):
            return
        ids = sorted(m.views.ids())[: self.n]
        d = m.stats.densify
        self.history.append({"keyframe": int(u.keyframe_id), "steps": int(u.steps), "gaussians": int(u.num_gaussians),
                             "psnr": {int(i): _view_psnr(m, m.views[i]) for i in ids},
                             "densify": dict(d)})


def _training_view_psnr(mapper) -> dict:
    """The final map's PSNR on its own training views (the keyframes, at their map poses, full resolution, with the
    view's exposure): high here and low on the evaluated frames between them means the map fits its views and not
    the space between (overfitting); low here too means the views disagree (the map cannot fit them all)."""
    if mapper is None or not len(mapper.views):
        return {}
    per = {int(v.view_id): _view_psnr(mapper, v) for v in mapper.views}
    vals = np.array(list(per.values()))
    return {"mean_db": round(float(vals.mean()), 2), "per_view": per}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="*", help="sequences (default: the shared 7-Scenes excerpt)")
    ap.add_argument("--source", action="append", choices=["dso", "dso-gtpose", "dso-gtpose-local", "oracle"],
                    help="what feeds the mapper (repeatable; default dso)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--downscale", type=int, default=1, help="divide the image size (2: 320x240 for 7-Scenes)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="setting (repeatable)")
    ap.add_argument("--tag", default="default", help="names the output folder of this variant")
    ap.add_argument("--watch-views", type=int, default=0, metavar="N",
                    help="after every keyframe, the PSNR of the first N training views (diagnostic; costs renders)")
    ap.add_argument("--extra-views", type=int, default=0, metavar="N",
                    help="replayed sources: up to N tracked frames between two keyframes also become training views "
                         "(never an evaluated frame; pair with a smaller mapping.mapper.iterations_per_keyframe for "
                         "the same number of steps)")
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "mgso" / "odometry-recordings"))
    ap.add_argument("--out", default="/tmp/mgso-profile-mapping")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.extra_views < 0 or args.watch_views < 0:
        ap.error("--extra-views and --watch-views take a count >= 0")
    if args.one:
        args.source = (args.source or ["dso"])[0]
        print(json.dumps(_one(args)))
        return 0
    import os
    import subprocess

    data = Path(os.environ.get("MGSO_DATA", ROOT.parent / "shared" / "data"))
    paths = args.paths or [str(data / "7scenes_redkitchen_0-499")]
    res = {"settings": args.set, "downscale": args.downscale, "tag": args.tag, "sequences": {}}
    for p in paths:
        for src in args.source or ["dso"]:
            cmd = [sys.executable, __file__, "--one", p, "--source", src, "--device", args.device, "--downscale",
                   str(args.downscale), "--tag", args.tag, "--cache", args.cache, "--out", args.out,
                   "--watch-views", str(args.watch_views), "--extra-views", str(args.extra_views)]
            for s in args.set:
                cmd += ["--set", s]
            r = subprocess.run(cmd, capture_output=True, text=True)
            key = f"{Path(p).name}:{src}"
            if r.returncode != 0:
                res["sequences"][key] = {"error": r.stderr.strip().splitlines()[-1:] or [f"exit {r.returncode}"]}
                continue
            res["sequences"][key] = json.loads(r.stdout.strip().splitlines()[-1])
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
