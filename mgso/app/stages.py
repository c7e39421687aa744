"""Run a sequence end to end and write what a user asked for: the stages of ``mgso run`` (and ``mgso demo``).

:func:`run_sequence` is the one path every stage takes; it owns the order of the work and of the files, and every
way a run can end goes through it (docs/architecture.md "How a run ends"):

- the sequence's description (``sequence.json``) and ground truth (``groundtruth.txt``) first;
- the work, under :func:`~mgso.app.signals.stop_signals` (Ctrl-C, SIGTERM and SIGHUP become an interrupt), with
  ``frames.csv`` growing a row per frame;
- then, whatever happened (the last frame, an interrupt, an error of the odometry or of the input, a frame that
  could not be read with ``input.on_bad_frame: stop``), the outputs of what was done, under
  :func:`~mgso.app.signals.deferred_signals`, and the evaluation, which a further signal cuts short;
- the :class:`RunSummary` says how it ended and the exit code (the same table for every stage, README "Exit codes").

Stages, in order of how far they go:

- ``check``: decode and undistort every frame, check it, and describe the sequence (no tracking).
- ``tracking``: the DSO front end (:class:`mgso.odometry.Odometry` with the fixed-window depth refinement as back end):
  a pose for every tracked frame (``trajectory.txt``), the keyframes (``keyframes.txt``), a per-frame log
  (``frames.csv``), the marginalised points (``points.ply``), ``metrics.json`` (ATE with ground truth) and
  ``trajectory.png``; with ``loop.enabled`` the loop closer (:mod:`mgso.loop.closer`) sees the odometry's messages
  between frames and the outputs are corrected as the full stage's (``trajectory_odometry.txt`` keeps the odometry's
  own poses, ``metrics.json`` a ``loop`` section).
- ``odometry``: the same outputs with the back end ``window.backend`` names (default ``bundle``: DSO's sliding-window
  bundle adjustment with marginalisation, docs/window.md).
- ``full``: the whole MGSO system (:mod:`mgso.system`): the DSO odometry and the Gaussian mapper seeded from its
  points, in deterministic or real-time mode; every output of the odometry stage plus ``map.ply``, renders and
  PSNR/SSIM (:mod:`mgso.app.full`, docs/mgso.md).
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from mgso.config import Config
from mgso.observers import Observer, ObserverList, no_progress

from .signals import StopState, deferred_signals, exit_code_for, stop_signals
from .writer import RunWriter, frame_row, unreadable_row

__all__ = ["STAGES", "STAGE_HELP", "DEFAULT_STAGE", "EXIT_OK", "EXIT_FAILED", "EXIT_USAGE", "RunSummary",
           "run_sequence", "run_system", "UnreadableFrames"]

log = logging.getLogger(__name__)

STAGES = ("check", "tracking", "odometry", "full")
STAGE_HELP = {"check": "check = decode and check every frame, describe the sequence",
              "tracking": "tracking = DSO front end: pose of every frame, keyframes, ATE with ground truth",
              "odometry": "odometry = DSO front end + sliding-window bundle adjustment (window.backend): trajectory, "
                          "keyframes, point cloud, ATE with ground truth",
              "full": "full = DSO odometry + Gaussian map seeded from its points (MGSO): trajectories, map.ply, "
                      "renders, ATE/PSNR/SSIM"}
DEFAULT_STAGE = "full"

#: Exit codes, the same for every stage and command (README "Exit codes"): 0 finished; 1 failed (an error, or no
#: frame got a pose; what was done is written); 2 usage; 128 + the signal when a signal stopped it (130 Ctrl-C,
#: 143 SIGTERM, 129 SIGHUP; what was done is written).
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


@dataclass
class RunSummary:
    """What a run did, as values; ``lines()`` is the human summary the CLI prints.

    ``outcome``: ``ok``, ``failed`` (``error`` says why) or ``interrupted`` (``signal`` says by what);
    ``exit_code``: the command's exit status for it (see :data:`EXIT_OK`)."""

    stage: str
    out_dir: Path
    frames: int = 0
    outcome: str = "ok"
    error: str | None = None
    signal: str = ""
    exit_code: int = EXIT_OK
    figures: dict = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)
    written: list[Path] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.outcome == "ok"

    def lines(self) -> list[str]:
        word = {"ok": "ok", "failed": "FAILED", "interrupted": f"INTERRUPTED ({self.signal or 'SIGINT'})"}
        out = [f"stage {self.stage}: {self.frames} frames, {word.get(self.outcome, self.outcome)}"]
        out += self.messages          # the error itself: the CLI prints it on stderr, in the one-line form
        out += [f"wrote {p}" for p in self.written]
        return out

    def conclude(self, state: StopState, *, no_pose: bool = False) -> "RunSummary":
        """Set ``outcome`` and ``exit_code`` from how the run ended: a signal, then an error, then no pose."""
        if state.signum is not None:
            self.outcome, self.signal, self.exit_code = "interrupted", state.name, exit_code_for(state.signum)
        elif self.error is not None:
            self.outcome, self.exit_code = "failed", EXIT_FAILED
        elif no_pose:
            self.outcome, self.exit_code = "failed", EXIT_FAILED
        else:
            self.outcome, self.exit_code = "ok", EXIT_OK
        return self


class UnreadableFrames:
    """``input.on_bad_frame``: called by the sequence for a frame that cannot be read (from its prefetch thread).
    ``skip``: a warning, a ``frames.csv`` row with status ``unreadable``, counted; ``stop``: the error stops the run."""

    def __init__(self, policy: str, writer: RunWriter | None, seq=None):
        self.policy = policy
        self.writer = writer
        self.seq = seq
        self.indices: list[int] = []
        self._lock = threading.Lock()

    def __call__(self, index: int, error: Exception) -> bool:
        if self.policy != "skip":
            return False
        log.warning("%s; frame %d skipped (input.on_bad_frame=skip)", error, index)
        with self._lock:
            self.indices.append(int(index))
            if self.writer is not None:
                ts = None
                if self.seq is not None:
                    try:
                        ts = float(self.seq.timestamp(index))
                    except Exception:  # noqa: BLE001 - the row is written without it
                        ts = None
                self.writer.open_frame_log().add(unreadable_row(index, ts))
        return True

    def __len__(self) -> int:
        return len(self.indices)


def _total(seq) -> int | None:
    """The progress bar's total: the sequence's length; ``None`` (unknown) for a live source (docs/live.md)."""
    return None if getattr(seq, "live", False) else len(seq)


def _error_text(exc: BaseException) -> str:
    from mgso.io import DatasetError

    if isinstance(exc, (DatasetError,)):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


# ------------------------------------------------------------------------------------------------ check
def _check_frames(seq, cfg: Config, writer: RunWriter, summary: RunSummary, progress, state: StopState) -> None:
    bad = UnreadableFrames(cfg.input.on_bad_frame, writer, seq)
    t0 = time.perf_counter()
    size, n = None, 0
    try:
        with stop_signals(state), progress(_total(seq), "decode") as bar:
            for frame in seq.frames(on_unreadable=bad):
                img = frame.gray
                if size is None:
                    size = img.shape
                if not np.all(np.isfinite(img)):
                    from mgso.io import DatasetError

                    raise DatasetError(f"{frame.source}: image has non-finite values after calibration")
                n += 1
                bar.update(1)
    except KeyboardInterrupt as exc:
        _record(state, exc)
    except Exception as exc:  # noqa: BLE001 - reported as the run's error
        summary.error = _error_text(exc)
    dt = time.perf_counter() - t0
    summary.frames = n
    summary.figures.update(decode_fps=n / dt if dt > 0 else 0.0, frames_unreadable=len(bad))
    shape = f" ({size[1]}x{size[0]} after calibration)" if size is not None else ""
    summary.messages.append(f"decoded {n} frames at {summary.figures['decode_fps']:.1f} frames/s{shape}"
                            + (f", {len(bad)} unreadable (skipped)" if len(bad) else ""))
    with deferred_signals(state):
        writer.write_metrics(extra={"check": dict(summary.figures, unreadable_frames=list(bad.indices),
                                                  error=summary.error)})
    summary.conclude(state)


def _end_input(seq):
    """A live source's :meth:`~mgso.io.live.LiveSource.end`, which the first Ctrl-C calls (docs/live.md), else
    ``None``."""
    return seq.end if getattr(seq, "live", False) else None


def _record(state: StopState, exc: BaseException) -> None:
    """A KeyboardInterrupt that did not come through our handler (raised by a frame source, a test): count it."""
    if state.signum is None:
        state.record_exception(exc)


# ------------------------------------------------------------------------------------- tracking, odometry
def _run_tracking(seq, cfg: Config, writer: RunWriter, summary: RunSummary, progress, state: StopState) -> None:
    from mgso.odometry import FrameStatus, Odometry, geometry_for
    from mgso_kernels import runtime

    device = runtime.init(cfg.runtime.device, threads=cfg.runtime.threads, blas_threads=cfg.runtime.blas_threads)
    cam = seq.calibration.output
    geo = geometry_for(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cfg)
    frame_log = writer.open_frame_log()
    # loop closure (loop.enabled): the full stage's closer and pose graph on the odometry's messages, between
    # frames (deterministic: the same loops on every run); the odometry's own poses and window are never changed
    closer = None
    if cfg.loop.enabled:
        from mgso.loop.closer import LoopCloser

        closer = LoopCloser(cfg, device=device)
    odo = Odometry(geo, cfg, device=device, emit_messages=closer is not None)
    bad = UnreadableFrames(cfg.input.on_bad_frame, writer, seq)
    t0 = time.perf_counter()
    n = 0
    done: set[int] = set()
    track_ms, map_ms = [], []   # of tracked frames (a FrameResult a frame would hold 2 KB: profiles/memory.py)
    try:
        with stop_signals(state, _end_input(seq)), progress(_total(seq), "track") as bar:
            for frame in seq.frames(on_unreadable=bad):
                r = odo.process(frame)
                if closer is not None:
                    _to_closer(closer, r.messages)
                with state.held():        # a signal here would leave a row without its count
                    frame_log.add(frame_row(r))
                    done.add(r.index)
                    if r.status == FrameStatus.TRACKED:
                        track_ms.append(r.time_track_s * 1000)
                        map_ms.append(r.time_map_s * 1000)
                    n += 1
                bar.update(1)
    except KeyboardInterrupt as exc:
        _record(state, exc)
        log.warning("interrupted after %d frames: writing what was done", n)
    except Exception as exc:  # noqa: BLE001 - the frames before it are written, the error reported
        summary.error = _error_text(exc)
        log.debug("tracking failed", exc_info=True)
    wall = time.perf_counter() - t0
    try:
        with stop_signals(state):
            final = odo.finish()
            if closer is not None and state.signum is None:
                _to_closer(closer, final, final=True)
                closer.finish()
    except KeyboardInterrupt as exc:  # a further signal: the poses stay as they are
        _record(state, exc)
    except Exception as exc:  # noqa: BLE001
        if summary.error is None:
            summary.error = _error_text(exc)

    # a frame cut off mid-way by an interrupt is in no output
    summary.frames = n
    if closer is not None:
        closer.close()                    # an interrupt drops the loops not yet solved; those found stay
    with deferred_signals(state):
        traj = odo.trajectory().at_times({float(f.timestamp) for f in odo.frames if f.index in done})
        kfs = odo.keyframe_trajectory()
        pts, cols, hosts = odo.point_cloud_world(with_hosts=True)
        traj_odo = None                   # the odometry's own poses, when a loop corrected them
        if closer is not None and closer.corrected:
            traj_odo = traj
            traj, kfs = closer.correct_trajectory(traj), closer.correct_keyframes(kfs)
            pts = closer.correct_points(pts, hosts)
            writer.write_trajectories(traj_odo, None, "tum", name="trajectory_odometry")
        writer.write_trajectories(traj, kfs, cfg.output.trajectory_format)
        # the full stage's layout: a keyframe column with each point's host keyframe id
        writer.write_points(pts, cols, extra={"keyframe": hosts.astype(np.float32)})
        records = [f for f in odo.frames if f.index in done]
        counts = Counter(f.status.value for f in records)
        tracked = len(traj)
        summary.figures.update({
            "frames": n, "frames_with_pose": tracked, "fraction_tracked": tracked / n if n else 0.0,
            "frames_unreadable": len(bad), "keyframes": len(kfs), "segments": odo.segment + 1,
            "tracking_lost": odo.num_lost, "repeated_frames": odo.num_duplicates, "status_counts": dict(counts),
            "points": int(len(pts)), "wall_s": wall, "fps": n / wall if wall else 0.0,
            "track_ms_median": float(np.median(track_ms)) if track_ms else None,
            "map_ms_median": float(np.median(map_ms)) if map_ms else None,
            "device": device, "image_size": [geo.width, geo.height], "pyramid_levels": geo.levels,
            "interrupted": state.signum is not None, "error": summary.error,
        })
        ates = _tracking_ate(seq, odo, traj, kfs, summary, traj_odo)
        f = summary.figures
        # the figures the full stage also reports, under the full stage's keys (issue 44: one name for one figure;
        # the "tracking" section keeps this stage's own detail)
        shared = {"ate_all_frames_m": f.get("ate_rmse_all_frames"), "ate_keyframes_m": f.get("ate_rmse_keyframes"),
                  "tracking_fps": f["fps"],
                  "frames": {"processed": n, "unreadable": len(bad), "without_pose": n - tracked,
                             "in_trajectory": tracked, "tracking_lost": odo.num_lost},
                  "keyframes": {"in_trajectory": len(kfs)}, "interrupted": f["interrupted"], "error": f["error"],
                  "device": device, "image_size": [geo.width, geo.height],
                  "loop": None if closer is None else closer.stats.as_dict(),
                  "ate_odometry_all_frames_m": f.get("ate_rmse_odometry_all_frames")}
        writer.write_metrics(ate=ates, extra={"tracking": summary.figures, **shared})
    lp = shared["loop"]
    if lp:
        summary.messages.append(_loop_line(lp))
    repeats = f" ({odo.num_duplicates} repeated images: pose of the frame before)" if odo.num_duplicates else ""
    unread = f", {len(bad)} unreadable frames skipped" if len(bad) else ""
    summary.messages.insert(0, f"tracked {tracked}/{n} frames ({100.0 * tracked / max(n, 1):.1f}%){repeats}{unread}, "
                               f"{len(kfs)} keyframes, {odo.num_lost} tracking losses, {len(pts)} points; "
                               f"{n / wall if wall else 0:.2f} frames/s ({geo.width}x{geo.height}, {device})")
    if ates and cfg.output.plot:
        try:
            with stop_signals(state):
                writer.write_trajectory_plot(ates[0], seq.groundtruth, kfs.timestamps,
                                             f"{seq.name}: DSO ({summary.stage} stage)")
        except KeyboardInterrupt:
            log.warning("the trajectory plot was cut short by a signal")
    if tracked == 0 and n:
        summary.messages.append("no frame got a pose: the odometry never initialised (a monocular start needs the "
                                "camera to translate; see the log for the initialiser's reasons)")
    summary.conclude(state, no_pose=(tracked == 0 and n > 0))


def _to_closer(closer, messages, final: bool = False) -> None:
    """The odometry's messages of a frame (or of its end) to the loop closer, then its correction collected (the
    stage keeps none: its outputs are corrected at the end)."""
    for msg in messages:
        closer.observe(msg, final=final)
        closer.correct(msg)
    closer.poll()


def _loop_line(lp: dict) -> str:
    """The summary's loop closure line (the same for every stage)."""
    why = ", ".join(f"{n} {r}" for r, n in lp["rejected"].items())
    return (f"loop closure: {lp['accepted']} loops accepted of {lp['candidates']} candidates verified"
            + (f" (rejected: {why})" if why else "") + f", {lp['seconds']:.1f} s"
            + (f"; it failed and was off from then on: {lp['error']}" if lp.get("error") else "")
            + ("; trajectory.txt is corrected, trajectory_odometry.txt the odometry's" if lp["accepted"] else ""))


def _tracking_ate(seq, odo, traj, kfs, summary: RunSummary, traj_odo=None) -> list:
    from mgso.eval import EvaluationError, compute_ate
    from mgso.io.trajectory import Trajectory

    gt = seq.groundtruth
    ates: list = []
    if gt is None or len(traj) < 3:
        return ates
    try:
        ate = compute_ate(traj, gt, align="sim3", label="all frames")
        ates.append(ate)
        summary.messages.append(ate.summary() + " [all frames with a pose]")
        summary.figures["ate_rmse_all_frames"] = ate.rmse
        if len(kfs) >= 3:
            ak = compute_ate(kfs, gt, align="sim3", label="keyframes")
            ates.append(ak)
            summary.messages.append(ak.summary() + " [keyframes]")
            summary.figures["ate_rmse_keyframes"] = ak.rmse
        if traj_odo is not None and len(traj_odo) >= 3:
            ao = compute_ate(traj_odo, gt, align="sim3", label="all frames, the odometry's before loop closure")
            ates.append(ao)
            summary.messages.append(ao.summary() + " [the odometry's, before loop closure]")
            summary.figures["ate_rmse_odometry_all_frames"] = ao.rmse
        segs = {}
        for s in range(odo.segment + 1):
            fr = [f for f in odo.frames if f.pose_valid and f.segment == s]
            if len(fr) >= 3 and odo.segment > 0:
                st = Trajectory(np.array([f.timestamp for f in fr]),
                                np.stack([odo.to_world(s, f.cam_to_world) for f in fr]))
                a = compute_ate(st, gt, align="sim3", label=f"segment {s}")
                segs[str(s)] = {"frames": len(fr), "ate_rmse": a.rmse}
        if segs:
            summary.figures["segments_ate"] = segs
    except EvaluationError as exc:  # evaluation must not lose the run's outputs
        log.warning("ATE not computed: %s", exc)
        summary.messages.append(f"ATE not computed: {exc}")
    return ates


# ------------------------------------------------------------------------------------------------ full
class _FrameBar(Observer):
    """Advances a progress bar per frame and shows keyframes and the map's size."""

    def __init__(self, bar):
        self.bar = bar
        self.keyframes = 0
        self.gaussians = 0

    def on_frame(self, result) -> None:
        self.bar.update(1)

    def on_keyframe(self, msg) -> None:
        self.keyframes += 1
        if hasattr(self.bar, "set_postfix"):
            self.bar.set_postfix({"kf": str(self.keyframes), "gaussians": str(self.gaussians)}, refresh=False)

    def on_map_updated(self, update) -> None:
        self.gaussians = update.num_gaussians


def run_system(seq, cfg: Config, writer: RunWriter, odometry, *, odometry_name: str = "",
               progress: Callable[[int, str], object] | None = None, summary: RunSummary | None = None,
               device: str | None = None, state: StopState | None = None,
               observers: tuple = ()) -> RunSummary:
    """Run the whole system (``odometry`` + the Gaussian mapper, :mod:`mgso.system`) over ``seq`` and write every
    output of ``mgso run`` through ``writer`` (:mod:`mgso.app.full`). ``odometry``: an
    :class:`mgso.system.OdometrySource`."""
    from mgso.system import System, SystemRunError

    from .full import write_full_outputs

    progress = progress or no_progress
    state = state or StopState()
    summary = summary or RunSummary(stage="full", out_dir=writer.out)
    bad = UnreadableFrames(cfg.input.on_bad_frame, writer, seq)
    bar = progress(_total(seq), f"{cfg.system.mode}")
    frame_bar = _FrameBar(bar)
    system = System(odometry, cfg, device=device,
                    observer=ObserverList([frame_bar, *observers]))
    frame_log = writer.open_frame_log()
    frames = seq.frames(on_unreadable=bad)
    for obs in observers:      # a watcher (the live viewer) that asks the mapper for copies, sees the frames
        if hasattr(obs, "attach"):
            obs.attach(system)
        if hasattr(obs, "watch"):
            frames = obs.watch(frames)
    try:
        with stop_signals(state, _end_input(seq)):
            result = system.run(frames, info=seq.describe(), hold=state.held,
                                log_frame=lambda r: frame_log.add(frame_row(r)))
    except SystemRunError as exc:
        result = exc.result
        summary.error = _error_text(exc.error)
        log.debug("the run failed", exc_info=exc.error)
    finally:
        bar.close()
    if result.interrupted and state.signum is None:
        state.record(signal.SIGINT)
    metrics = write_full_outputs(result, system.mapper, seq, cfg, writer, odometry_name=odometry_name,
                                 progress=progress, state=state, error=summary.error, frames_unreadable=len(bad))
    summary.frames = result.frames_processed
    summary.figures.update({k: metrics.get(k) for k in (
        "ate_all_frames_m", "ate_keyframes_m", "psnr_monogs_db", "ssim_monogs", "psnr_photo_slam_db",
        "ssim_photo_slam", "num_gaussians", "map_size_mb", "peak_memory_mb", "tracking_fps",
        "mapping_iterations_per_s", "end_to_end_fps", "map_ready_s")})
    m = summary.messages
    if result.interrupted or summary.error:
        m.append(f"stopped after {result.frames_processed} frames: the outputs are of what was done"
                 + (f" (evaluation {metrics['evaluation']})" if metrics["evaluation"] != "done" else ""))
    unread = f", {len(bad)} unreadable" if len(bad) else ""
    n_lost = len(result.tracking_losses)
    lost = f", {n_lost} tracking loss{'es' if n_lost != 1 else ''}" if n_lost else ""
    m.append(f"{result.frames_processed} frames ({result.frames_dropped} dropped, {result.frames_lost} without "
             f"pose{unread}{lost}), {result.keyframes} keyframes, {metrics['num_gaussians']} Gaussians "
             f"({metrics['map_size_mb']:.1f} MB as PLY), peak memory {metrics['peak_memory_mb']:.0f} MB")
    m.append(f"tracking {metrics['tracking_fps']:.1f} frames/s; the map ready {metrics['map_ready_s']:.1f} s after "
             f"the last frame; mapping {metrics['mapping_iterations_per_s']:.2f} it/s ({result.mapper.steps} steps, "
             f"{result.mapper.steps_while_streaming} while the frames came); end to end "
             f"{metrics['end_to_end_fps']:.2f} frames/s until the map was written ({cfg.system.mode})")
    rt = metrics.get("realtime")
    if rt:
        share = rt["mapper_cpu_share"]
        m.append(f"real time: {result.frames_processed} of {result.frames_read} frames tracked "
                 f"({result.frames_dropped} dropped); mapper in a {rt['mapper_in']}"
                 + (f" ({rt['mapper_priority']})" if rt.get("mapper_priority") else "")
                 + f": {rt['mapping_steps_running']} "
                 f"steps while the camera ran"
                 + (f" (at 1/{2 ** rt['running_level']} resolution)" if rt.get("running_level") else "")
                 + f", {rt['mapping_steps_final']} after"
                 + (f"; {rt['mapper_queue_at_end']} messages still queued when the camera stopped, applied in "
                    f"{rt['mapper_catch_up_seconds']:.1f} s" if rt.get("mapper_queue_at_end") else "")
                 + (f", {100 * share:.0f}% of the CPU" if share is not None else "")
                 + (f"; the odometry waited for the map {rt['queue_waits']} times ({rt['queue_wait_seconds']:.1f} s)"
                    if rt["queue_waits"] else ""))
    lp = metrics.get("loop")
    if lp:
        m.append(_loop_line(lp))
    no_pose = metrics["frames"]["in_trajectory"] == 0 and result.frames_processed > 0
    if no_pose:
        m.append("no frame got a pose: the odometry never initialised (a monocular start needs the camera to "
                 "translate; see the log for the initialiser's reasons)")
    for a in metrics["ate"]:
        m.append(f"ATE {a['translation_m']['rmse']:.4f} m RMSE ({a['label']}, Sim(3) aligned, "
                 f"{a['num_pairs']} poses)")
    for r in metrics["render"]:
        m.append(f"PSNR {r['mean_psnr_db']:.2f} dB, SSIM {r['mean_ssim']:.4f} ({r['protocol']}, "
                 f"{r['num_frames']} frames)")
    summary.written = writer.written_paths()
    return summary.conclude(state, no_pose=no_pose)


def _run_full(seq, cfg: Config, writer: RunWriter, summary: RunSummary, progress, state: StopState,
              observers: tuple = ()) -> None:
    from mgso.odometry import Odometry
    from mgso_kernels import runtime

    device = runtime.init(cfg.runtime.device, threads=cfg.runtime.threads, blas_threads=cfg.runtime.blas_threads)
    odo_device = runtime.resolve_device(cfg.runtime.odometry_device) if cfg.runtime.odometry_device else device
    # real time: DSO's split, the window optimisation beside the tracking (a keyframe does not stall the frames behind)
    split = cfg.system.mode == "realtime" and cfg.system.odometry_map_thread
    odometry = Odometry.for_camera(seq.calibration.output, cfg, device=odo_device, emit_messages=True,
                                   map_thread=split)
    run_system(seq, cfg, writer, odometry, odometry_name="DSO (mgso.odometry)", progress=progress, summary=summary,
               device=device, state=state, observers=observers)


# ------------------------------------------------------------------------------------------------ entry
def run_sequence(seq, cfg: Config, writer: RunWriter, *, stage: str | None = None,
                 progress: Callable[[int, str], object] | None = None,
                 state: StopState | None = None, observers: tuple = ()) -> RunSummary:
    """Run ``stage`` on ``seq`` and write through ``writer`` (see the module doc). Returns the summary, whose
    ``exit_code`` is the command's. ``observers``: more observers of the full stage's system (the live viewer);
    one with ``attach(system)`` gets the :class:`~mgso.system.System` before the run, one with ``watch(frames)``
    wraps the frames (to see each input frame)."""
    stage = stage or DEFAULT_STAGE
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; available: {', '.join(STAGES)}")
    progress = progress or no_progress
    state = state or StopState()
    summary = RunSummary(stage=stage, out_dir=writer.out)
    with deferred_signals(state):
        writer.write_sequence(seq)
    if state.signum is not None:      # stopped before the work began
        summary.messages.append(f"{state.name} before the first frame: nothing run")
        summary.conclude(state)
    elif stage == "check":
        _check_frames(seq, cfg, writer, summary, progress, state)
    elif stage == "tracking":
        # the front end with the stand-in back end (poses fixed); the window optimisation is the odometry stage
        cfg_t = dataclasses.replace(cfg, window=dataclasses.replace(cfg.window, backend="fixed"))
        _run_tracking(seq, cfg_t, writer, summary, progress, state)
    elif stage == "odometry":
        _run_tracking(seq, cfg, writer, summary, progress, state)
    else:
        _run_full(seq, cfg, writer, summary, progress, state, observers)
    if getattr(seq, "live", False):     # why a live source ended (docs/live.md)
        summary.messages.insert(0, seq.end_message())
    writer.close()
    summary.written = writer.written_paths()
    return summary
