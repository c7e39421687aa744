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
- ``tracking``: the DSO front end (:class:`mgso.odometry.Odometry` with the fixed-window depth refinement as back end)
  in the system without a map: a pose for every tracked frame (``trajectory.txt``), the keyframes
  (``keyframes.txt``), a per-frame log (``frames.csv``), DSO's points (``points.ply``), ``metrics.json`` (ATE with
  ground truth), ``trajectory.png`` and ``report.png``; with ``loop.enabled`` the loop closer corrects them
  (``trajectory_odometry.txt`` keeps the odometry's own poses, ``metrics.json`` a ``loop`` section).
- ``odometry``: the same with the back end ``window.backend`` names (default ``bundle``: DSO's sliding-window
  bundle adjustment with marginalisation, docs/window.md).
- ``full``: the whole MGSO system (:mod:`mgso.system`): the DSO odometry and the Gaussian mapper seeded from its
  points, in deterministic or real-time mode; every output of the odometry stage plus ``map.ply``, renders and
  PSNR/SSIM.

The three stages that track take one path (:func:`run_system`) and one writer (:mod:`mgso.app.outputs`): the same
files and the same metrics.json keys (the map's ``null`` without one), in both modes (``system.mode: realtime``
plays the frames at their rate to the odometry stages too).
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import threading
import time
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


def _loop_line(lp: dict) -> str:
    """The summary's loop closure line."""
    why = ", ".join(f"{n} {r}" for r, n in lp["rejected"].items())
    return (f"loop closure: {lp['accepted']} loops accepted of {lp['candidates']} candidates verified"
            + (f" (rejected: {why})" if why else "") + f", {lp['seconds']:.1f} s"
            + (f"; it failed and was off from then on: {lp['error']}" if lp.get("error") else "")
            + ("; trajectory.txt is corrected, trajectory_odometry.txt the odometry's" if lp["accepted"] else ""))


# --------------------------------------------------------------------------------------- tracking, odometry, full
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
               observers: tuple = (), with_map: bool = True) -> RunSummary:
    """Run the system (``odometry`` + the Gaussian mapper, :mod:`mgso.system`; ``with_map=False``: the odometry and
    the loop closer alone) over ``seq`` and write every output of ``mgso run`` through ``writer``
    (:mod:`mgso.app.outputs`, the same files and keys for every stage). ``odometry``: an
    :class:`mgso.system.OdometrySource`."""
    from mgso.system import System, SystemRunError

    from .outputs import trajectory_check_line, write_run_outputs

    progress = progress or no_progress
    state = state or StopState()
    summary = summary or RunSummary(stage="full", out_dir=writer.out)
    bad = UnreadableFrames(cfg.input.on_bad_frame, writer, seq)
    bar = progress(_total(seq), f"{cfg.system.mode}" if with_map else "track")
    frame_bar = _FrameBar(bar)
    system = System(odometry, cfg, device=device, observer=ObserverList([frame_bar, *observers]),
                    with_map=with_map)
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
    metrics = write_run_outputs(result, system.mapper, seq, cfg, writer, odometry_name=odometry_name,
                                progress=progress, state=state, error=summary.error, frames_unreadable=len(bad),
                                stage=summary.stage, device=device)
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
    tr = metrics["tracking"]
    repeats = (f", {tr['repeated_frames']} repeated images (the pose of the frame before)"
               if tr["repeated_frames"] else "")
    size = "x".join(map(str, metrics["image_size"])) if metrics.get("image_size") else "?"
    m.append(f"{result.frames_processed} frames ({result.frames_dropped} dropped, {result.frames_lost} without "
             f"pose{unread}{lost}{repeats}), {result.keyframes} keyframes, {tr['points']} DSO points"
             + (f", {metrics['num_gaussians']} Gaussians ({metrics['map_size_mb']:.1f} MB as PLY)" if with_map
                else "") + f"; {size}, {metrics['device']}; peak memory {metrics['peak_memory_mb']:.0f} MB")
    if with_map:
        m.append(f"tracking {metrics['tracking_fps']:.1f} frames/s; the map ready {metrics['map_ready_s']:.1f} s "
                 f"after the last frame; mapping {metrics['mapping_iterations_per_s']:.2f} it/s "
                 f"({result.mapper.steps} steps, {result.mapper.steps_while_streaming} while the frames came); end "
                 f"to end {metrics['end_to_end_fps']:.2f} frames/s until the map was written ({cfg.system.mode})")
    else:
        m.append(f"tracking {metrics['tracking_fps']:.1f} frames/s; end to end {metrics['end_to_end_fps']:.2f} "
                 f"frames/s ({cfg.system.mode}; no map: the {summary.stage} stage)")
    rt = metrics.get("realtime")
    if rt and with_map:
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
    line = trajectory_check_line(metrics)
    if line:
        m.append(line)
    for seg, a in sorted((tr["segments_ate"] or {}).items(), key=lambda kv: int(kv[0])):
        m.append(f"ATE {a['ate_rmse']:.4f} m RMSE (segment {seg} alone, Sim(3) aligned, {a['frames']} poses)")
    for r in metrics["render"]:
        m.append(f"PSNR {r['mean_psnr_db']:.2f} dB, SSIM {r['mean_ssim']:.4f} ({r['protocol']}, "
                 f"{r['num_frames']} frames)")
    summary.written = writer.written_paths()
    return summary.conclude(state, no_pose=no_pose)


def _run_dso(seq, cfg: Config, writer: RunWriter, summary: RunSummary, progress, state: StopState,
             observers: tuple = (), with_map: bool = True) -> None:
    """The tracking, odometry and full stages: DSO (:class:`mgso.odometry.Odometry`) in the system, with or without
    the map; one path and one writer for all three."""
    from mgso.odometry import Odometry
    from mgso_kernels import runtime

    device = runtime.init(cfg.runtime.device, threads=cfg.runtime.threads, blas_threads=cfg.runtime.blas_threads)
    odo_device = runtime.resolve_device(cfg.runtime.odometry_device) if cfg.runtime.odometry_device else device
    # real time: DSO's split, the window optimisation beside the tracking (a keyframe does not stall the frames behind)
    split = cfg.system.mode == "realtime" and cfg.system.odometry_map_thread
    odometry = Odometry.for_camera(seq.calibration.output, cfg, device=odo_device, emit_messages=True,
                                   map_thread=split)
    name = "DSO (mgso.odometry)" if with_map else f"DSO (mgso.odometry, window.backend={cfg.window.backend})"
    run_system(seq, cfg, writer, odometry, odometry_name=name, progress=progress, summary=summary,
               device=device, state=state, observers=observers, with_map=with_map)


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
        _run_dso(seq, cfg_t, writer, summary, progress, state, observers, with_map=False)
    elif stage == "odometry":
        _run_dso(seq, cfg, writer, summary, progress, state, observers, with_map=False)
    else:
        _run_dso(seq, cfg, writer, summary, progress, state, observers)
    if getattr(seq, "live", False):     # why a live source ended (docs/live.md)
        summary.messages.insert(0, seq.end_message())
    writer.close()
    summary.written = writer.written_paths()
    return summary
