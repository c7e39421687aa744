"""The whole MGSO system: an odometry and the Gaussian mapper joined by typed messages (docs/mgso.md).

::

    frames -> odometry.process(frame) -> OdometryFrame (pose, affine, keyframe?) + messages
                                                 |  KeyframeMessage / PoseUpdate / MarginalizedPoints
                                                 v
                                     Mapper (bounded queue) -> seed, train, densify -> Gaussian map

**The odometry** is any object with the small :class:`Odometry` protocol: ``process(frame) -> OdometryFrame``
(the frame's pose and the messages it emits, in order), ``finish() -> messages`` (the last pose updates and the
points still in the window), ``trajectory()`` and ``keyframe_trajectory()`` (final poses, TUM-ready). The DSO
odometry plugs in through an adapter; :class:`mgso.oracle.OracleOdometry` (ground-truth poses and depths) is the
stand-in for tests and profiles.

**Modes** (``system.mode``):

- ``deterministic``: frames in order; after each frame the mapper applies the messages and trains
  ``mapping.mapper.iterations_per_keyframe`` steps after each keyframe, in this thread. The same result on every
  CPU run (bitwise-identical PLY).
- ``realtime``: the mapper trains in its own thread while the odometry runs; the odometry never waits for it except
  on a full queue (counted). A recorded sequence is played at its frame rate times ``system.playback_speed``: a
  player thread releases each frame at its time, and a frame that arrives while the odometry is still busy with an
  earlier one replaces it (the earlier one is dropped, as a live camera's would be; counted).

After the last frame: ``odometry.finish()``, its messages to the mapper, the final refinement, then the outputs
(:func:`write_outputs`). Ctrl-C (``KeyboardInterrupt``, also when raised by the frame source) stops cleanly in both
modes: the odometry is finished, the mapper applies what is queued and stops without the final refinement, and the
outputs of what was done are written (``SystemResult.interrupted``).

Nothing here prints; observers (:mod:`mgso.observers`) get ``on_sequence_start``, ``on_frame`` (an
:class:`OdometryFrame`), ``on_keyframe`` (a :class:`~mgso.mapping.messages.KeyframeMessage`),
``on_window_optimized`` (a :class:`~mgso.mapping.messages.PoseUpdate`), ``on_points_marginalized`` (a
:class:`~mgso.mapping.messages.MarginalizedPoints`), ``on_map_updated`` (from the mapper) and ``on_sequence_end``
(the :class:`SystemResult`).
"""

from __future__ import annotations

import json
import logging
import os
import resource
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Protocol, Sequence as TSequence

import cv2
import numpy as np

from mgso.config import Config
from mgso.geometry import orthonormalize, se3_inverse
from mgso.io.trajectory import Trajectory, write_kitti, write_tum
from mgso.mapping.mapper import Mapper, MapperStats
from mgso.mapping.messages import KeyframeMessage, MarginalizedPoints, PoseUpdate
from mgso.observers import Observer, ObserverList

__all__ = ["Odometry", "OdometryFrame", "DsoOdometry", "System", "SystemResult", "FrameLog", "PointCloud", "Player",
           "write_outputs", "METRICS_KEYS"]

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------- the protocol
@dataclass(frozen=True, eq=False)
class OdometryFrame:
    """What an odometry says about one frame.

    ``cam_to_world``: the pose at tracking time (4x4), ``None`` while there is none (initialising, lost).
    ``affine``: DSO's (a, b) of the frame (0-255 scale); ``exposure_ms``: its exposure time (``None``: unknown).
    ``is_keyframe``; ``status``: the odometry's word for the frame (e.g. "tracked", "initializing", "lost");
    ``messages``: what it emits for the mapper, in order; ``seconds``: its time on this frame.
    """

    index: int
    timestamp: float
    cam_to_world: np.ndarray | None
    is_keyframe: bool = False
    affine: tuple[float, float] = (0.0, 0.0)
    exposure_ms: float | None = None
    status: str = "tracked"
    messages: tuple = ()
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.cam_to_world is not None


class Odometry(Protocol):
    """What the system needs of an odometry (DSO through its adapter, or the oracle)."""

    def process(self, frame) -> OdometryFrame:
        """Track (and map, in DSO's sense) one :class:`mgso.io.Frame`; return its pose and the messages."""

    def finish(self) -> TSequence:
        """End of the sequence: the final pose updates and the points left in the window, as messages."""

    def trajectory(self) -> Trajectory:
        """Every frame with a pose, final poses (camera-to-world)."""

    def keyframe_trajectory(self) -> Trajectory:
        """Every keyframe, final poses."""


# -------------------------------------------------------------------------------------------- results
@dataclass
class FrameLog:
    """Per processed frame, in order: what evaluation needs."""

    index: list[int] = field(default_factory=list)
    timestamp: list[float] = field(default_factory=list)
    affine: list[tuple[float, float]] = field(default_factory=list)
    exposure_ms: list[float | None] = field(default_factory=list)
    is_keyframe: list[bool] = field(default_factory=list)
    status: list[str] = field(default_factory=list)

    def add(self, r: OdometryFrame) -> None:
        self.index.append(int(r.index))
        self.timestamp.append(float(r.timestamp))
        self.affine.append((float(r.affine[0]), float(r.affine[1])))
        self.exposure_ms.append(r.exposure_ms)
        self.is_keyframe.append(bool(r.is_keyframe))
        self.status.append(str(r.status))

    def __len__(self) -> int:
        return len(self.index)


@dataclass
class PointCloud:
    """The DSO point cloud: every marginalised point (world, colour in [0, 1], host keyframe id)."""

    points: list[np.ndarray] = field(default_factory=list)
    colors: list[np.ndarray] = field(default_factory=list)
    hosts: list[np.ndarray] = field(default_factory=list)

    def add(self, msg: MarginalizedPoints) -> None:
        if len(msg):
            self.points.append(np.asarray(msg.points))
            self.colors.append(np.asarray(msg.colors))
            self.hosts.append(np.full(len(msg), msg.host_keyframe_id, np.int64))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not self.points:
            return np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
        return np.concatenate(self.points), np.concatenate(self.colors), np.concatenate(self.hosts)

    def __len__(self) -> int:
        return int(sum(len(p) for p in self.points))


@dataclass
class SystemResult:
    """What :meth:`System.run` did (values; the outputs are written by :func:`write_outputs`)."""

    mode: str
    frames_read: int                    # frames the source delivered (played, in real time)
    frames_processed: int               # frames the odometry processed
    frames_dropped: int                 # real time: frames replaced before the odometry could take them
    keyframes: int                      # keyframe messages sent to the mapper
    pose_updates: int                   # pose-update messages sent
    interrupted: bool
    trajectory: Trajectory              # final poses of every frame with one
    keyframe_trajectory: Trajectory
    frame_log: FrameLog
    cloud: PointCloud
    mapper: MapperStats
    odometry_seconds: float             # sum of the odometry's per-frame times
    loop_seconds: float                 # wall time of the frame loop (first frame in -> last frame done)
    finish_seconds: float               # odometry.finish + the mapper's last messages and final refinement
    frames_lost: int = 0                # frames without a pose
    keyframe_frames: list = field(default_factory=list)   # frame index of every keyframe sent to the map

    @property
    def tracking_fps(self) -> float:
        """Frames per second of the odometry alone (frames processed / its time on them)."""
        return self.frames_processed / self.odometry_seconds if self.odometry_seconds > 0 else 0.0

    @property
    def end_to_end_fps(self) -> float:
        """Frames processed per second of the frame loop, odometry and mapping together (the final refinement
        after the last frame is not in it)."""
        return self.frames_processed / self.loop_seconds if self.loop_seconds > 0 else 0.0


# --------------------------------------------------------------------------------------------- playback
_END = object()


class Player:
    """Plays frames at their timestamps (a recorded sequence as a live camera): a thread reads ``frames`` and
    releases each at ``t0 + (timestamp - first) / speed``; the consumer takes the newest released frame. A frame
    released while the previous one was not yet taken replaces it (counted in :attr:`dropped`). ``speed = 0``: no
    pacing and nothing dropped (the consumer's pace). Errors of the source (including ``KeyboardInterrupt``) are
    raised in the consumer."""

    def __init__(self, frames: Iterable, speed: float = 1.0):
        self.speed = float(speed)
        self._frames = frames
        self._cond = threading.Condition()
        self._slot: Any = None
        self._has = False
        self._stop = threading.Event()
        self.read = 0
        self.dropped = 0
        self._thread = threading.Thread(target=self._work, name="mgso-player", daemon=True)

    def _put(self, item, replace: bool) -> bool:
        with self._cond:
            while self._has and not replace and not self._stop.is_set():
                self._cond.wait(0.05)
            if self._stop.is_set():
                return False
            if self._has and item is not _END and not isinstance(item, BaseException):
                self.dropped += 1
            self._slot, self._has = item, True
            self._cond.notify_all()
        return True

    def _work(self) -> None:
        t0, ts0 = None, None
        try:
            for frame in self._frames:
                if self._stop.is_set():
                    return
                self.read += 1
                if self.speed > 0:
                    if t0 is None:
                        t0, ts0 = time.perf_counter(), float(frame.timestamp)
                    wait = t0 + (float(frame.timestamp) - ts0) / self.speed - time.perf_counter()
                    if wait > 0 and self._stop.wait(wait):
                        return
                if not self._put(frame, replace=self.speed > 0):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            self._put(exc, replace=False)
            return
        self._put(_END, replace=False)

    def __iter__(self) -> Iterator:
        self._thread.start()
        try:
            while True:
                with self._cond:
                    while not self._has:
                        self._cond.wait(0.05)
                    item, self._slot, self._has = self._slot, None, False
                    self._cond.notify_all()
                if item is _END:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            self._stop.set()
            with self._cond:
                self._cond.notify_all()
            self._thread.join(timeout=5.0)
            close = getattr(self._frames, "close", None)
            if close is not None:
                close()


# ----------------------------------------------------------------------------------------------- system
class System:
    """Odometry + mapper (see the module doc). ``odometry``: an :class:`Odometry`; ``config``: the full
    configuration (``system``, ``mapping``); ``device``: Warp device (initialised by the caller);
    ``observer``: one observer or an :class:`~mgso.observers.ObserverList`."""

    def __init__(self, odometry: Odometry, config: Config, *, device: str | None = None,
                 observer: Observer | None = None):
        self.odometry = odometry
        self.config = config
        self.observer = observer if observer is not None else ObserverList()
        self.mapper = Mapper(config, device=device, observer=self.observer)
        self.realtime = config.system.mode == "realtime"
        self.cloud = PointCloud()
        self.frame_log = FrameLog()
        self._keyframes = 0
        self._keyframe_frames: list[int] = []
        self._pose_updates = 0

    def _dispatch(self, messages) -> None:
        for msg in messages:
            if isinstance(msg, KeyframeMessage):
                self._keyframes += 1
                self._keyframe_frames.append(msg.frame_index)
                self.observer.on_keyframe(msg)
            elif isinstance(msg, PoseUpdate):
                self._pose_updates += 1
                self.observer.on_window_optimized(msg)
            elif isinstance(msg, MarginalizedPoints):
                self.cloud.add(msg)
                self.observer.on_points_marginalized(msg)
            else:
                raise TypeError(f"the odometry emitted {type(msg).__name__}, not a mapper message")
            self.mapper.submit(msg)
        if not self.realtime:
            self.mapper.process_pending()

    def run(self, frames: Iterable, *, info: Any = None) -> SystemResult:
        """Run over ``frames`` (``mgso.io.Frame`` objects, e.g. ``Sequence.frames()``) and stop the mapper.

        Real-time mode plays them through a :class:`Player` at ``system.playback_speed`` times their rate.
        Returns a :class:`SystemResult`; :func:`write_outputs` writes the files."""
        self.observer.on_sequence_start(info)
        player = None
        if self.realtime:
            player = Player(frames, self.config.system.playback_speed)
            source: Iterable = player
            self.mapper.start()
        else:
            source = frames
        interrupted = False
        processed, read, odo_s, lost = 0, 0, 0.0, 0
        t_loop = time.perf_counter()
        it = iter(source)
        try:
            for frame in it:
                read += 1
                t0 = time.perf_counter()
                r = self.odometry.process(frame)
                dt = r.seconds if r.seconds > 0 else time.perf_counter() - t0
                odo_s += dt
                processed += 1
                lost += int(not r.ok)
                self.frame_log.add(r)
                self.observer.on_frame(r)
                self._dispatch(r.messages)
        except KeyboardInterrupt:
            interrupted = True
            log.warning("interrupted after %d frames: finishing the odometry and writing what was done", processed)
        except BaseException:
            self._abort()
            raise
        finally:
            close = getattr(it, "close", None)
            if close is not None:        # stop the player's / the prefetch's thread now
                close()
        loop_s = time.perf_counter() - t_loop
        t_fin = time.perf_counter()
        try:
            final = list(self.odometry.finish())
        except Exception:  # an odometry interrupted mid-frame may not finish cleanly: keep what it has
            if not interrupted:
                raise
            log.exception("odometry.finish failed after the interrupt")
            final = []
        try:
            self._dispatch_final(final, interrupted)
        except KeyboardInterrupt:      # a second Ctrl-C during the refinement: stop it, still write
            interrupted = True
            self.mapper.stop(refine=False)
        finish_s = time.perf_counter() - t_fin
        if player is not None:
            read = player.read
        result = SystemResult(
            mode=self.config.system.mode, frames_read=read, frames_processed=processed,
            frames_dropped=player.dropped if player is not None else 0, keyframes=self._keyframes,
            pose_updates=self._pose_updates, interrupted=interrupted, trajectory=self.odometry.trajectory(),
            keyframe_trajectory=self.odometry.keyframe_trajectory(), frame_log=self.frame_log, cloud=self.cloud,
            mapper=self.mapper.stats, odometry_seconds=odo_s, loop_seconds=loop_s, finish_seconds=finish_s,
            frames_lost=lost, keyframe_frames=list(self._keyframe_frames))
        self.observer.on_sequence_end(result)
        return result

    def _abort(self) -> None:
        """The run failed: stop the mapping thread without training (its own failure, if any, is logged)."""
        try:
            self.mapper.stop(refine=False, timeout=60)
        except Exception:  # the original error is the one to raise
            log.exception("stopping the mapper after a failure")

    def _dispatch_final(self, final, interrupted: bool) -> None:
        for msg in final:
            if isinstance(msg, PoseUpdate):
                self._pose_updates += 1
            elif isinstance(msg, MarginalizedPoints):
                self.cloud.add(msg)
            elif isinstance(msg, KeyframeMessage):
                self._keyframes += 1
                self._keyframe_frames.append(msg.frame_index)
            self.mapper.submit(msg)
        self.mapper.stop(refine=not interrupted)


# ----------------------------------------------------------------------------------------------- outputs
#: Every key of metrics.json (tests check them; docs/mgso.md explains each).
METRICS_KEYS = (
    "ate", "render", "ate_all_frames_m", "ate_keyframes_m", "ate_refined_all_frames_m", "psnr_monogs_db",
    "ssim_monogs", "psnr_photo_slam_db",
    "ssim_photo_slam", "num_gaussians", "map_size_mb", "peak_memory_mb", "tracking_fps", "mapping_iterations_per_s",
    "end_to_end_fps", "frames", "keyframes", "mode", "interrupted", "odometry", "device", "image_size",
    "timing_s", "mapper", "sequence", "protocols",
)


def _to_u8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(rgb, np.float64) * 255.0), 0, 255).astype(np.uint8)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(_to_u8(rgb), cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: could not write the PNG")


def peak_memory_mb() -> float:
    """Peak resident set size of this process in MB (``resource.getrusage(RUSAGE_SELF).ru_maxrss``: KiB on Linux,
    bytes on macOS): everything the process held at its peak (Python, Warp buffers on the CPU, images)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    scale = 1.0 if os.uname().sysname == "Darwin" else 1024.0
    return rss * scale / 1e6


def write_outputs(result: SystemResult, mapper: Mapper, seq, cfg: Config, out_dir: str | Path, *,
                  odometry_name: str = "", progress: Callable[[int, str], Any] | None = None) -> dict:
    """Write the outputs of a run into ``out_dir`` and return the metrics (also written as ``metrics.json``).

    Files: ``trajectory.txt`` (every frame with a pose, TUM; also ``trajectory_kitti.txt`` with
    ``output.trajectory_format: kitti``), ``keyframes.txt`` (TUM), ``map.ply`` (3DGS layout), ``points.ply`` (the
    DSO point cloud with a ``keyframe`` property), ``renders/NNNNNN.png`` (input | render of the MonoGS evaluation
    frames, ``output.save_renders``), ``metrics.json`` and, with ground truth, ``trajectory.png``
    (``output.plot``). ``seq``: the :class:`mgso.io.Sequence` the frames came from (images for evaluation, ground
    truth, camera). ``config.yaml`` is the caller's (the CLI writes it before the run).
    """
    from mgso.eval import (MONOGS, PHOTO_SLAM, EvaluationError, compute_ate, evaluate_renders, select_frames,
                           write_metrics_json)
    from mgso.io.ply import write_gaussians_ply, write_point_cloud_ply

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[str] = []
    t_out = time.perf_counter()

    traj, kf_traj = result.trajectory, result.keyframe_trajectory
    write_tum(out / "trajectory.txt", traj)
    write_tum(out / "keyframes.txt", kf_traj)
    written += ["trajectory.txt", "keyframes.txt"]
    if cfg.output.trajectory_format == "kitti":
        write_kitti(out / "trajectory_kitti.txt", traj)
        written.append("trajectory_kitti.txt")
    write_gaussians_ply(out / "map.ply", mapper.gmap.to_numpy())
    map_mb = (out / "map.ply").stat().st_size / 1e6
    pts, cols, hosts = result.cloud.arrays()
    write_point_cloud_ply(out / "points.ply", pts, cols, extra={"keyframe": hosts.astype(np.float32)})
    written += ["map.ply", "points.ply"]

    # ---- trajectory accuracy
    ate_results, ate_all, ate_kf = [], None, None
    gt = seq.groundtruth if seq is not None else None
    if gt is not None and len(traj) >= 3:
        try:
            ate_all = compute_ate(traj, gt, align="sim3", label="all frames", max_diff=0.01)
            ate_results.append(ate_all)
        except EvaluationError as exc:
            log.warning("no ATE on all frames: %s", exc)
        if len(kf_traj) >= 3:
            try:
                ate_kf = compute_ate(kf_traj, gt, align="sim3", label="keyframes", max_diff=0.01)
                ate_results.append(ate_kf)
            except EvaluationError as exc:
                log.warning("no ATE on keyframes: %s", exc)
        if ate_all is not None and cfg.output.plot:
            try:
                from mgso.eval import plot_trajectory

                plot_trajectory(out / "trajectory.png", ate_all, reference=gt, keyframe_timestamps=kf_traj.timestamps,
                                title=f"{seq.name}: {odometry_name}")
                written.append("trajectory.png")
            except ImportError as exc:
                log.warning("no trajectory plot: %s", exc)

    # ---- the map's refinement of the poses (mapping.train.refine_poses): a second
    # trajectory, the odometry's moved by the keyframes' corrections; the map is in its frame
    refined = mapper.refined_trajectory(traj) if mapper.refines_poses else None
    ate_refined = None
    if refined is not None:
        write_tum(out / "trajectory_refined.txt", refined)
        written.append("trajectory_refined.txt")
        if gt is not None and len(refined) >= 3:
            try:
                ate_refined = compute_ate(refined, gt, align="sim3", label="all frames, refined by the map",
                                          max_diff=0.01)
                ate_results.append(ate_refined)
            except EvaluationError as exc:
                log.warning("no ATE of the map-refined trajectory: %s", exc)

    # ---- rendering quality at the tracked poses (final estimates; no alignment needed: the map is in their frame)
    renders = []
    render_traj = refined if refined is not None else traj
    pose_at = {float(t): T for t, T in zip(render_traj.timestamps, render_traj.cam_to_world)}
    log_ = result.frame_log
    tracked = [k for k in range(len(log_)) if log_.timestamp[k] in pose_at]
    tracked_idx = [log_.index[k] for k in tracked]
    pos_of = {log_.index[k]: k for k in tracked}
    # keyframes = every frame that reached the map as a training view (DSO's first keyframe is announced frames
    # after its own frame, when the initialiser succeeds: OdometryFrame.is_keyframe cannot say it)
    kf_idx = sorted(set(result.keyframe_frames) | {log_.index[k] for k in range(len(log_)) if log_.is_keyframe[k]})
    cam = seq.calibration.output if seq is not None else None
    sc = cfg.system

    def exposure_of(k: int):
        if not sc.eval_exposure:
            return None
        return mapper.exposure_for(log_.affine[k], log_.exposure_ms[k])

    def pairs(indices, save: bool, bar):
        for i in indices:
            k = pos_of[i]
            w2c = se3_inverse(pose_at[log_.timestamp[k]])
            w2c[:3, :3] = orthonormalize(w2c[:3, :3])
            rgb = mapper.render(cam, w2c, exposure=exposure_of(k))
            gt_img = seq.load(i).rgb
            if save:
                if sc.renders_side_by_side:
                    _write_png(out / "renders" / f"{i:06d}.png", np.concatenate([gt_img, np.clip(rgb, 0, 1)], axis=1))
                else:
                    _write_png(out / "renders" / f"{i:06d}.png", np.clip(rgb, 0, 1))
                    _write_png(out / "gt" / f"{i:06d}.png", gt_img)
            if bar is not None:
                bar.update(1)
            yield rgb, gt_img

    can_render = seq is not None and mapper.gmap.n > 0 and tracked_idx
    for proto, on in ((MONOGS, sc.eval_monogs), (PHOTO_SLAM, sc.eval_photo_slam)):
        if not (on and can_render):
            continue
        frames = select_frames(proto, tracked_idx, kf_idx)
        if not frames:
            continue
        save = proto is MONOGS and cfg.output.save_renders
        bar = progress(len(frames), f"eval {proto.key}") if progress is not None else None
        try:
            renders.append(evaluate_renders(pairs(frames, save, bar), frames, proto))
        finally:
            if bar is not None:
                bar.close()
        if save:
            written.append("renders/")

    by_key = {r.protocol_key: r for r in renders}
    st = result.mapper
    metrics_extra = {
        "ate_all_frames_m": None if ate_all is None else ate_all.rmse,
        "ate_keyframes_m": None if ate_kf is None else ate_kf.rmse,
        "ate_refined_all_frames_m": None if ate_refined is None else ate_refined.rmse,
        "psnr_monogs_db": by_key["monogs"].mean_psnr if "monogs" in by_key else None,
        "ssim_monogs": by_key["monogs"].mean_ssim if "monogs" in by_key else None,
        "psnr_photo_slam_db": by_key["photo-slam"].mean_psnr if "photo-slam" in by_key else None,
        "ssim_photo_slam": by_key["photo-slam"].mean_ssim if "photo-slam" in by_key else None,
        "num_gaussians": int(mapper.gmap.n),
        "map_size_mb": map_mb,
        "peak_memory_mb": peak_memory_mb(),
        "tracking_fps": result.tracking_fps,
        "mapping_iterations_per_s": st.iterations_per_s,
        "end_to_end_fps": result.end_to_end_fps,
        "frames": {"read": result.frames_read, "processed": result.frames_processed,
                   "dropped": result.frames_dropped, "without_pose": result.frames_lost,
                   "in_trajectory": len(traj)},
        "keyframes": {"sent": result.keyframes, "in_map": len(mapper.views), "in_trajectory": len(kf_traj)},
        "mode": result.mode,
        "interrupted": result.interrupted,
        "odometry": odometry_name,
        "device": mapper.device,
        "image_size": None if cam is None else [cam.width, cam.height],
        "timing_s": {"odometry": result.odometry_seconds, "frame_loop": result.loop_seconds,
                     "finish_and_final_refinement": result.finish_seconds, "mapping_train": st.train_seconds,
                     "final_refinement": st.final_seconds, "seeding": st.seed_seconds,
                     "outputs_and_evaluation": None},
        "mapper": {k: v for k, v in st.as_dict().items() if k != "seeding"},
        "sequence": None if seq is None else {"path": str(seq.path), "layout": seq.layout, "name": seq.name,
                                              "frames": len(seq)},
        "protocols": {
            "ate": "RMSE of positions after Sim(3) Umeyama alignment (evo_ape -as), on all frames with a pose and on "
                   "keyframes",
            "psnr_monogs_db": MONOGS.name, "psnr_photo_slam_db": PHOTO_SLAM.name,
            "render_poses": ("the odometry's final poses moved by the map's keyframe corrections "
                             "(trajectory_refined.txt; no alignment: the map is in their frame)" if refined is not None
                             else "the odometry's final poses (no alignment: the map is in the odometry's frame)"),
            "render_exposure": (f"each frame's exposure by mapping.mapper.exposure = {cfg.mapping.mapper.exposure} "
                                "(odometry: DSO's affine and exposure time), as in training"
                                if sc.eval_exposure else "none (the map's radiance)"),
            "map_size_mb": "map.ply as written, 10^6 bytes",
            "peak_memory_mb": "resource.getrusage(RUSAGE_SELF).ru_maxrss: peak resident set size of the whole "
                              "process, 10^6 bytes",
            "tracking_fps": "frames processed / the odometry's time on them",
            "mapping_iterations_per_s": "training steps / the mapper's time inside them (final refinement "
                                        "included)",
            "end_to_end_fps": "frames processed / wall time of the frame loop (odometry and mapping; the final "
                              "refinement after the last frame is not in it)",
        },
    }
    metrics_extra["timing_s"]["outputs_and_evaluation"] = time.perf_counter() - t_out
    write_metrics_json(out / "metrics.json", ate=ate_results, renders=renders, extra=metrics_extra)
    written.append("metrics.json")
    with open(out / "metrics.json", encoding="utf-8") as fh:
        metrics = json.load(fh)
    metrics["written"] = written
    return metrics


# ------------------------------------------------------------------------------------ the DSO odometry
class DsoOdometry:
    """The DSO odometry (:class:`mgso.odometry.Odometry`: coarse tracker, window, initialiser) as an
    :class:`Odometry` of the system: its observer events become mapper messages.

    - ``on_keyframe`` -> :class:`~mgso.mapping.messages.KeyframeMessage`: the keyframe's RGB image and camera in the
      odometry's image geometry (the pyramid crop), its pose in the common world, DSO's affine (a, b) and exposure
      time, and DSO's points that see it: every active point of the window (depth refined by the window), projected
      into the new keyframe (the depth map the coarse tracker tracks against; a new keyframe hosts no point with a
      depth yet).
    - ``on_window_optimized`` -> :class:`~mgso.mapping.messages.PoseUpdate` of every keyframe in the window (poses and
      affine).
    - ``on_points_marginalized`` -> :class:`~mgso.mapping.messages.MarginalizedPoints`, one per host keyframe, in the
      common world.
    - :meth:`finish`: the odometry's final poses of every keyframe, and the points still active.

    ``camera``: the sequence's undistorted pinhole camera; ``config``: the full configuration; ``device``: Warp's;
    ``observer``: also gets the odometry's own events (tracking loss, ...).
    """

    def __init__(self, camera, config: Config, *, device: str | None = None, observer: Observer | None = None):
        from mgso.camera import PinholeCamera
        from mgso.odometry import Odometry as _Dso, geometry_for

        self.geometry = geometry_for(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, config)
        g = self.geometry
        c = g.camera
        self.camera = PinholeCamera(c.fx, c.fy, c.cx, c.cy, g.width, g.height)
        self._events: list = []
        fan = ObserverList([_EventLog(self._events)] + ([observer] if observer is not None else []))
        self.dso = _Dso(g, config, device=device, observer=fan)
        self.name = "DSO (mgso.odometry)"

    # ------------------------------------------------------------------------------------------ messages
    def _world_points(self, positions: np.ndarray, segment: int) -> np.ndarray:
        S = self.dso.segment_similarity(segment)
        return np.asarray(positions, np.float64) @ S[:3, :3].T + S[:3, 3]

    def _keyframe_message(self, ev) -> KeyframeMessage | None:
        w = self.dso.window
        try:
            slot = w.slot_of_keyframe(ev.keyframe_id)
        except KeyError:       # marginalised within its own step (cannot happen with DSO's rule; be safe)
            log.warning("keyframe %d left the window before it reached the map", ev.keyframe_id)
            return None
        if w.rgb_ is None:
            raise RuntimeError("the odometry's window keeps no RGB images (keep_rgb=False): the map needs them")
        c2w = np.asarray(ev.cam_to_world, np.float64)
        pts = self._world_points(w.points_world(), ev.segment) if w.active.n else np.zeros((0, 3))
        T = se3_inverse(c2w)
        pc = pts @ T[:3, :3].T + T[:3, 3]
        cam = self.camera
        ok = pc[:, 2] > 1e-6
        z = np.where(ok, pc[:, 2], 1.0)
        uv = np.stack([cam.fx * pc[:, 0] / z + cam.cx, cam.fy * pc[:, 1] / z + cam.cy], axis=1)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
        exposure = float(w.exposure_[slot])
        return KeyframeMessage(ev.keyframe_id, ev.frame_index, ev.timestamp, w.rgb_[slot], cam, c2w, uv[ok],
                               1.0 / z[ok], affine=tuple(w.affine_[slot]),
                               exposure_ms=exposure if exposure > 0 else None, segment=ev.segment)

    def _pose_update(self, ev) -> PoseUpdate:
        w = self.dso.window
        aff = {}
        for kid in ev.keyframe_ids:
            try:
                aff[int(kid)] = tuple(w.affine_[w.slot_of_keyframe(int(kid))])
            except KeyError:
                pass
        return PoseUpdate({int(k): T for k, T in zip(ev.keyframe_ids, ev.cam_to_world)}, affine=aff)

    def _points(self, marg) -> list[MarginalizedPoints]:
        if not len(marg):
            return []
        pos = self._world_points(marg.positions, marg.segment)
        hosts = np.asarray(marg.host_keyframe_ids)
        return [MarginalizedPoints(pos[hosts == h], np.asarray(marg.colors)[hosts == h], host_keyframe_id=int(h))
                for h in np.unique(hosts)]

    def _drain(self) -> list:
        out = []
        for kind, ev in self._events:
            if kind == "keyframe":
                msg = self._keyframe_message(ev)
                if msg is not None:
                    out.append(msg)
            elif kind == "window":
                out.append(self._pose_update(ev))
            elif kind == "points":
                out += self._points(ev)
        self._events.clear()
        return out

    # ------------------------------------------------------------------------------------------ protocol
    def process(self, frame) -> OdometryFrame:
        r = self.dso.process(frame)
        rec = self.dso.frames[-1]
        msgs = self._drain()
        # DSO emits the keyframe after its window update: the mapper gets the keyframe first, then the poses
        kfs = [m for m in msgs if isinstance(m, KeyframeMessage)]
        rest = [m for m in msgs if not isinstance(m, KeyframeMessage)]
        return OdometryFrame(r.index, r.timestamp, r.cam_to_world, is_keyframe=bool(kfs),
                             affine=tuple(rec.affine), exposure_ms=getattr(frame, "exposure_ms", None),
                             status=r.status.value, messages=tuple(kfs + rest),
                             seconds=r.time_track_s + r.time_map_s)

    def finish(self) -> list:
        self.dso.finish()
        out = self._drain()
        kt = self.dso.keyframe_trajectory()
        ids = sorted(self.dso.keyframes)
        if ids:
            out.append(PoseUpdate({k: T for k, T in zip(ids, kt.cam_to_world)}))
        w = self.dso.window
        if w.active.n:
            seg = int(w.segment_[w.order[-1]]) if w.order else self.dso.segment
            pos = self._world_points(w.points_world(), seg)
            hosts = w.keyframe_id_[w.active.host]
            for h in np.unique(hosts):
                out.append(MarginalizedPoints(pos[hosts == h], w.active.rgb[hosts == h], host_keyframe_id=int(h)))
        return out

    def trajectory(self) -> Trajectory:
        return self.dso.trajectory()

    def keyframe_trajectory(self) -> Trajectory:
        return self.dso.keyframe_trajectory()


class _EventLog(Observer):
    """Collects the odometry's events in order (the adapter turns them into messages after each frame)."""

    def __init__(self, events: list):
        self.events = events

    def on_keyframe(self, ev) -> None:
        self.events.append(("keyframe", ev))

    def on_window_optimized(self, ev) -> None:
        self.events.append(("window", ev))

    def on_points_marginalized(self, ev) -> None:
        self.events.append(("points", ev))
