"""The outputs of a run of every stage that tracks (``mgso run --stage tracking|odometry|full``, ``mgso demo``):
what :class:`mgso.system.System` did, written through the :class:`~mgso.app.writer.RunWriter` in two phases, from
this one place (as DSO sends all its outputs through one output wrapper; docs/mgso.md lists every file and figure).
The ``tracking`` and ``odometry`` stages run the system without a map (``mapper`` is ``None``): the same files and the
same keys, without ``map.ply``, the renders and the map's figures (``null``).

1. **What must exist** (signals deferred): ``trajectory.txt`` (every frame with a pose, TUM; with
   ``output.trajectory_format: kitti`` also ``trajectory_kitti.txt`` and ``keyframes_kitti.txt``), ``keyframes.txt``,
   ``map.ply`` (3DGS layout; with a map), ``points.ply`` (the DSO point cloud with a ``keyframe`` property),
   ``trajectory_refined.txt`` (with ``mapping.train.refine_poses``), ``trajectory_odometry.txt`` (the odometry's own
   poses, when loop closure corrected them: ``trajectory.txt`` and ``keyframes.txt`` are the corrected ones), and
   ``metrics.json`` with the ATE, the counts and the timings (``"evaluation": "pending"``).
2. **Evaluation** (a signal cuts it short): ``trajectory.png`` (``output.plot``, with ground truth), the renders of
   the evaluation frames (``renders/``, ``output.save_renders``) and their PSNR/SSIM, then ``report.png``
   (``output.plot``, with or without ground truth: :func:`mgso.eval.plot_report`; skipped when a signal cut the
   evaluation short); ``metrics.json`` is written again with them (``"evaluation": "done"``, or ``"interrupted"`` /
   ``"failed: ..."`` with the figures of phase 1 kept; a report that could not be drawn is such a failure).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mgso.config import Config
from mgso.geometry import orthonormalize, se3_inverse
from mgso.mapping.mapper import Mapper
from mgso.system import SystemResult, peak_memory_mb

from .signals import StopState, deferred_signals, stop_signals
from .writer import RunWriter

__all__ = ["METRICS_KEYS", "write_run_outputs", "write_outputs"]

log = logging.getLogger(__name__)

#: Every key of a run's metrics.json, the same for every stage that tracks (tests check them; docs/mgso.md explains
#: each).
METRICS_KEYS = (
    "ate", "rpe", "render", "ate_all_frames_m", "ate_keyframes_m", "ate_refined_all_frames_m", "psnr_monogs_db",
    "ssim_monogs", "psnr_photo_slam_db", "ssim_photo_slam", "num_gaussians", "map_size_mb", "peak_memory_mb",
    "tracking_fps", "mapping_iterations_per_s", "end_to_end_fps", "frames", "keyframes", "mode", "interrupted",
    "error", "evaluation", "odometry", "device", "image_size", "timing_s", "mapper", "realtime", "sequence",
    "protocols", "loop", "ate_odometry_all_frames_m", "live", "segments", "tracking_losses", "map_health",
    "map_ready_s", "frame_loop_fps", "stage", "tracking", "trajectory_check",
)

#: A map whose median Gaussian is more transparent than this is fog: the fogged maps measured 0.10 (TUM
#: freiburg1_rpy with the defaults before issue 41, where every keyframe seeded its points again; its training views
#: at 11.9-15.1 dB also give the poor fit's warning) and 0.065-0.084 (the synthetic handheld scenes of
#: tests/mapping/test_handheld.py); the maps of the defaults 0.29-0.75 until the rates for a short schedule
#: (2026-12-06), whose larger, fainter Gaussians give 0.17-0.25 (7-Scenes, freiburg1_rpy, the demo), 0.125 in real
#: time on freiburg1_rpy (0.125 with 3DGS's rates too) and 0.145 on the synthetic handheld scene's compact map
#: (0.15 until then; docs/mapping.md, "Handheld camera", "Rates for a short schedule").
FOG_MEDIAN_OPACITY = 0.11
#: A map that renders its own training views below this PSNR (mean over Mapper.HEALTH_VIEWS of them) does not fit
#: them: 11.9-15.1 dB measured on the fogged TUM maps, 19.4-22.5 dB on TUM, 7-Scenes and KITTI with the defaults
#: since issue 41, 29 dB on the demo (docs/mapping.md, "Handheld camera").
POOR_FIT_PSNR_DB = 18.0
#: The evaluation renders at most this many frames at once on the CPU (one a core, each on one thread).
EVAL_MAX_WORKERS = 8


def map_warning_items(health: dict) -> list[tuple[str, str]]:
    """Each sign of a foggy map in ``health`` (:meth:`mgso.mapping.mapper.Mapper.health`) as (a few words, the full
    line): mostly transparent Gaussians, or training views the map renders badly."""
    out = []
    med = health.get("median_opacity")
    if med is not None and med < FOG_MEDIAN_OPACITY:
        out.append(("mostly transparent",
                    f"the map is mostly transparent (median opacity {med:.2f}, "
                    f"{100 * health['transparent_fraction']:.0f} % of its Gaussians below "
                    f"{Mapper.TRANSPARENT_OPACITY}): fog, many faint Gaussians where the views and the odometry's "
                    "depths disagree (docs/mapping.md, \"Handheld camera\")"))
    fit = health.get("training_view_psnr_db")
    if fit is not None and fit < POOR_FIT_PSNR_DB:
        out.append(("its training views not fitted",
                    f"the map renders its own training views at {fit:.1f} dB (the lowest of "
                    f"{health['training_views_rendered']} at {health['training_view_psnr_min_db']:.1f} dB, below "
                    f"{POOR_FIT_PSNR_DB:g} dB): it does not fit the keyframes it was trained on; views that "
                    "disagree (poses, motion blur, exposure) were averaged (docs/mapping.md, \"Handheld camera\")"))
    return out


def map_warnings(health: dict) -> list[str]:
    """:func:`map_warning_items`' full lines."""
    return [line for _, line in map_warning_items(health)]


def write_run_outputs(result: SystemResult, mapper: Mapper | None, seq, cfg: Config, writer: RunWriter, *,
                      odometry_name: str = "", progress: Callable[[int, str], Any] | None = None,
                      state: StopState | None = None, error: str | None = None, frames_unreadable: int = 0,
                      stage: str = "full", device: str | None = None) -> dict:
    """Write the outputs of a run (the two phases of the module doc) and return the metrics as written.

    ``mapper``: the run's mapper, ``None`` for a run without a map (the tracking and odometry stages). ``seq``: the
    :class:`mgso.io.Sequence` the frames came from (images for evaluation, ground truth, camera; may be ``None``: no
    evaluation). ``state``: the run's :class:`~mgso.app.signals.StopState` (``None``: no signal handling, for
    library use). ``error``: the error that stopped the run, recorded in metrics.json. ``stage``: the stage's name
    in metrics.json; ``device``: the run's device (default: the mapper's)."""
    from mgso.eval import EvaluationError, compute_ate

    t_out = time.perf_counter()
    guard = (lambda: deferred_signals(state)) if state is not None else nullcontext
    hurry = (lambda: stop_signals(state)) if state is not None else nullcontext
    traj, kf_traj = result.trajectory, result.keyframe_trajectory
    gt = seq.groundtruth if seq is not None else None
    ate: dict[str, Any] = {}

    run = _Run(result, mapper, seq, cfg, odometry_name, error, frames_unreadable, stage,
               device if device is not None else (mapper.device if mapper is not None else None))
    with guard():
        writer.write_trajectories(traj, kf_traj, cfg.output.trajectory_format)
        if mapper is not None:
            writer.write_gaussians(mapper.gmap.to_numpy())
            run.map_mb = writer.path("map.ply").stat().st_size / 1e6
        # when the outputs were ready: after the last frame, the mapper's catch-up and final refinement (in the run's
        # finish) and the writing of map.ply (without a map: of trajectory.txt)
        run.ready_s = result.finish_seconds + (time.perf_counter() - t_out)
        pts, cols, hosts = result.cloud.arrays()
        writer.write_points(pts, cols, extra={"keyframe": hosts.astype(np.float32)})
        # the map's refinement of the poses (mapping.train.refine_poses): the odometry's trajectory moved by the
        # keyframes' corrections; the map is in its frame
        refined = mapper.refined_trajectory(traj) if mapper is not None and mapper.refines_poses else None
        if refined is not None:
            writer.write_trajectories(refined, None, "tum", name="trajectory_refined")
        odo = result.odometry_trajectory         # before loop closure corrected it (None: nothing corrected)
        if odo is not None:
            writer.write_trajectories(odo, None, "tum", name="trajectory_odometry")
        for key, tr, label in (("all", traj, "all frames"), ("keyframes", kf_traj, "keyframes"),
                               ("refined", refined, "all frames, refined by the map"),
                               ("odometry", odo, "all frames, the odometry's before loop closure")):
            if gt is None or tr is None or len(tr) < 3:
                continue
            try:
                ate[key] = compute_ate(tr, gt, align="sim3", label=label, max_diff=0.01)
            except EvaluationError as exc:
                log.warning("no ATE on %s: %s", label, exc)
        run.frame_rows = _frame_rows(writer)
        run.segments_ate = _segment_ates(result, gt, run.frame_rows)
        figures = _figures(run, ate, [])
        for line in ((figures["trajectory_check"] or {}).get("warnings", [])
                     + (figures["map_health"] or {}).get("warnings", [])):
            log.warning("%s", line)
        figures["evaluation"] = "pending"
        figures["timing_s"]["outputs_and_evaluation"] = time.perf_counter() - t_out
        writer.write_metrics(ate=list(ate.values()), extra=figures)

    renders: list = []
    status = "done"
    try:
        with hurry():
            if "all" in ate and cfg.output.plot:
                writer.write_trajectory_plot(ate["all"], gt, kf_traj.timestamps,
                                             f"{seq.name}: {odometry_name}" if seq is not None else "")
            if mapper is not None:
                renders = _evaluate_renders(result, mapper, seq, cfg, writer,
                                            refined if refined is not None else traj, progress)
    except KeyboardInterrupt as exc:
        if state is not None and state.signum is None:   # not through a handler (raised by a callback)
            state.record_exception(exc)
        status = "interrupted"
        log.warning("evaluation stopped by a signal: metrics.json keeps the trajectory figures, without the "
                    "renders' PSNR/SSIM")
    except Exception as exc:  # noqa: BLE001 - evaluation must not lose the run's outputs
        status = f"failed: {type(exc).__name__}: {exc}"
        log.warning("evaluation failed: %s", exc, exc_info=log.isEnabledFor(logging.DEBUG))

    if cfg.output.plot and status != "interrupted":
        try:
            with hurry():
                figures = _figures(run, ate, renders)
                figures["evaluation"] = status
                _write_report(writer, result, seq, cfg, ate, renders, figures, traj, kf_traj, gt, odometry_name)
        except KeyboardInterrupt as exc:
            if state is not None and state.signum is None:
                state.record_exception(exc)
            status = "interrupted"
            log.warning("report.png was cut short by a signal")
        except Exception as exc:  # noqa: BLE001 - a figure must not lose the run's outputs
            what = f"report.png: {type(exc).__name__}: {exc}"
            status = f"failed: {what}" if status == "done" else f"{status}; {what}"
            log.warning("no report.png: %s", exc, exc_info=log.isEnabledFor(logging.DEBUG))

    with guard():
        figures = _figures(run, ate, renders)
        figures["evaluation"] = status
        figures["timing_s"]["outputs_and_evaluation"] = time.perf_counter() - t_out
        writer.write_metrics(ate=list(ate.values()), renders=renders, extra=figures)
    import json

    metrics = json.loads(writer.path("metrics.json").read_text(encoding="utf-8"))
    metrics["written"] = list(writer.written)
    return metrics


def write_outputs(result: SystemResult, mapper: Mapper, seq, cfg: Config, out_dir, *, odometry_name: str = "",
                  progress: Callable[[int, str], Any] | None = None) -> dict:
    """:func:`write_run_outputs` into the folder ``out_dir`` (made if needed), without signal handling: for
    scripts and profiles that run a :class:`mgso.system.System` themselves."""
    return write_run_outputs(result, mapper, seq, cfg, RunWriter(out_dir), odometry_name=odometry_name,
                             progress=progress)


def _write_report(writer: RunWriter, result: SystemResult, seq, cfg: Config, ate: dict, renders: list, figures: dict,
                  traj, kf_traj, gt, odometry_name: str) -> None:
    """``report.png`` (:func:`mgso.eval.plot_report`) from the run's values."""
    from mgso.eval import PsnrSeries, ReportData, plot_report

    log_ = result.frame_log
    time_of = {int(i): float(t) for i, t in zip(log_.index, log_.timestamp)}
    stamps = list(log_.timestamp) or list(traj.timestamps)
    t0 = float(stamps[0]) if stamps else 0.0
    t_end = float(stamps[-1]) - t0 if stamps else 0.0
    series = [PsnrSeries(r.protocol, np.array([time_of.get(int(f), np.nan) - t0 for f in r.frame_indices]),
                         np.asarray(r.psnr, np.float64)) for r in renders]
    hist = np.array([(t_end if not np.isfinite(t) else t - t0, steps, n) for _, t, steps, n in result.mapper.history],
                    np.float64).reshape(-1, 3)
    sc = cfg.system
    notes = {"psnr": (f"no map: the {figures['stage']} stage runs the odometry alone"
                      if figures["num_gaussians"] is None
                      else "rendering evaluation off (system.eval_monogs, system.eval_photo_slam)"
                      if not (sc.eval_monogs or sc.eval_photo_slam)
                      else f"no rendering evaluation (evaluation: {figures['evaluation']})"
                      if figures["evaluation"] != "done" else "no frame to evaluate (no map or no tracked frame)")}
    if figures["num_gaussians"] is None:
        notes["map"] = notes["psnr"]
    if gt is not None and "all" not in ate:
        notes["error"] = "no trajectory error: the ATE could not be computed (see the log)"
    data = ReportData(title=f"{seq.name}: {odometry_name}" if seq is not None else odometry_name,
                      ate=ate.get("all"), reference=gt, trajectory=traj, keyframe_timestamps=kf_traj.timestamps,
                      t0=t0, psnr=series, map_history=hist, headline=_headline(figures), notes=notes)
    writer.write_with("report.png", lambda p: plot_report(p, data))


def map_health_line(h: dict) -> str | None:
    """report.png's line of ``metrics.json``'s ``map_health``: the median opacity, the training views' PSNR and a few
    words per warning (:func:`map_warnings` in full in the log and metrics.json); None without a map."""
    med, fit = h.get("median_opacity"), h.get("training_view_psnr_db")
    if med is None and fit is None:
        return None
    words = h.get("warning_words", [])
    return (f"map health: median opacity {'n/a' if med is None else format(med, '.2f')}, its training views "
            f"{'n/a' if fit is None else format(fit, '.1f')} dB" + (f"; WARNING: {', '.join(words)}" if words else ""))


def trajectory_check_line(f: dict) -> str | None:
    """One line of ``metrics.json``'s ``trajectory_check`` (``f``: the metrics) for the run's summary and report.png:
    what standing still would score, the ATE's share of it, the scale's drift and a short word per warning (the
    warnings in full are in the log and metrics.json); None without ground truth."""
    tc = f.get("trajectory_check") or {}
    ate = f.get("ate_all_frames_m")
    if not tc or ate is None:
        return None
    still, drift = tc["standing_still_m"], tc.get("scale_drift")
    share = 100 * ate / still if still > 0 else None
    words = tc.get("warning_words", [])
    return (f"trajectory check: standing still {still:.4f} m (the ATE "
            + ("n/a" if share is None else f"{share:.0f} %") + " of it); scale drift "
            + ("unmeasured" if drift is None else f"{drift:.3g}x")
            + (f"; WARNING: {', '.join(words)}" if words else ""))


def _headline(f: dict) -> list[str]:
    """The text panel of report.png: the headline figures of metrics.json."""
    def num(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    fr, kf = f["frames"], f["keyframes"]
    size = f"{f['image_size'][0]}x{f['image_size'][1]}" if f.get("image_size") else "?"
    what = "+ map" if f["num_gaussians"] is not None else f"alone ({f['stage']} stage)"
    lines = [f"{f['odometry'] or 'odometry'} {what}, {f['mode']} mode, {size}, device {f['device']}",
             f"frames: {fr['processed']} processed of {fr['read']} read, {fr['dropped']} dropped, "
             f"{fr['without_pose']} without pose"
             + (f", tracking lost {fr['tracking_lost']}x" if fr.get("tracking_lost") else "")
             + f"; keyframes: {kf['sent']}" + (f" ({kf['in_map']} in the map)" if kf["in_map"] is not None else "")]
    if f["ate_all_frames_m"] is None:
        lines.append("ATE: no ground truth")
    else:
        ref = (f", refined {f['ate_refined_all_frames_m']:.4f} m" if f["ate_refined_all_frames_m"] is not None
               else "")
        odo = (f", odometry before loop closure {f['ate_odometry_all_frames_m']:.4f} m"
               if f.get("ate_odometry_all_frames_m") is not None else "")
        lines.append(f"ATE RMSE (Sim(3)): all frames {f['ate_all_frames_m']:.4f} m, keyframes "
                     f"{num(f['ate_keyframes_m'], '.4f')} m{ref}{odo}")
        line = trajectory_check_line(f)
        if line:
            lines.append(line)
    lp = f.get("loop")
    if lp is not None:
        lines.append(f"loop closure: {lp['accepted']} loops accepted, {lp['rejected_total']} candidates rejected "
                     f"of {lp['candidates']} verified")
    psnr = []
    if f["psnr_monogs_db"] is not None:
        psnr.append(f"MonoGS protocol {f['psnr_monogs_db']:.2f} dB / SSIM {f['ssim_monogs']:.3f}")
    if f["psnr_photo_slam_db"] is not None:
        psnr.append(f"Photo-SLAM protocol {f['psnr_photo_slam_db']:.2f} dB / SSIM {f['ssim_photo_slam']:.3f}")
    lines.append("PSNR: " + ("; ".join(psnr) if psnr else "not evaluated"))
    if f["num_gaussians"] is None:
        lines.append(f"map: none (the {f['stage']} stage: the odometry alone); peak memory "
                     f"{num(f['peak_memory_mb'], '.0f')} MB")
    else:
        lines.append(f"map: {f['num_gaussians']:,} Gaussians, {f['map_size_mb']:.2f} MB; peak memory "
                     f"{num(f['peak_memory_mb'], '.0f')} MB")
    line = map_health_line(f.get("map_health") or {})
    if line:
        lines.append(line)
    if f["map_ready_s"] is None:
        lines.append(f"speed: tracking {f['tracking_fps']:.2f} frames/s; end to end {f['end_to_end_fps']:.2f} "
                     "frames/s")
    else:
        lines.append(f"speed: tracking {f['tracking_fps']:.2f} frames/s; the map ready {f['map_ready_s']:.1f} s "
                     f"after the last frame; end to end {f['end_to_end_fps']:.2f} frames/s; mapping "
                     f"{f['mapping_iterations_per_s']:.1f} steps/s")
    lines.append(f"interrupted: {'yes' if f['interrupted'] else 'no'}; evaluation: {f['evaluation']}"
                 + (f"; error: {f['error']}" if f.get("error") else ""))
    return lines


def _evaluate_renders(result: SystemResult, mapper: Mapper, seq, cfg: Config, writer: RunWriter, render_traj,
                      progress) -> list:
    """Rendering quality at the final poses (no alignment needed: the map is in their frame)."""
    from mgso.eval import MONOGS, PHOTO_SLAM, evaluate_protocols, select_frames
    from mgso_kernels import runtime

    pose_at = {float(t): T for t, T in zip(render_traj.timestamps, render_traj.cam_to_world)}
    log_ = result.frame_log
    tracked = [k for k in range(len(log_)) if log_.timestamp[k] in pose_at]
    tracked_idx = [log_.index[k] for k in tracked]
    pos_of = {log_.index[k]: k for k in tracked}
    # keyframes = the frames that reached the map as training views (a keyframe message each), not the frames'
    # is_keyframe: DSO announces its first keyframe frames after its own frame (when the initialiser succeeds), and
    # with the odometry's mapping thread (real time) is_keyframe is the tracker's request, which the thread grants
    # to the newest waiting frame only (most frames of a real-time run ask: docs/evaluation.md)
    kf_idx = sorted(set(result.keyframe_frames))
    cam = seq.calibration.output if seq is not None else None
    sc = cfg.system

    def exposure_of(k: int):
        if not sc.eval_exposure:
            return None
        return mapper.exposure_for(log_.affine[k], log_.exposure_ms[k])

    def renderer(rasterizer=None, threads: int = 0):
        def render(i: int) -> np.ndarray:
            k = pos_of[i]
            w2c = se3_inverse(pose_at[log_.timestamp[k]])
            w2c[:3, :3] = orthonormalize(w2c[:3, :3])
            with runtime.cpu_threads_here(threads):
                return mapper.render(cam, w2c, exposure=exposure_of(k), rasterizer=rasterizer)
        return render

    save_renders = cfg.output.save_renders

    def on_frame(i: int, rgb, gt_img, keys) -> None:
        if save_renders and MONOGS.key in keys:
            if sc.renders_side_by_side:
                writer.write_image(f"renders/{i:06d}.png", np.concatenate([gt_img, np.clip(rgb, 0, 1)], axis=1))
            else:
                writer.write_image(f"renders/{i:06d}.png", np.clip(rgb, 0, 1))
                writer.write_image(f"gt/{i:06d}.png", gt_img)
        if bar is not None:
            bar.update(1)

    if not (seq is not None and mapper.gmap.n > 0 and tracked_idx):
        return []
    selections = {proto: select_frames(proto, tracked_idx, kf_idx)
                  for proto, on in ((MONOGS, sc.eval_monogs), (PHOTO_SLAM, sc.eval_photo_slam)) if on}
    selections = {proto: frames for proto, frames in selections.items() if frames}
    if not selections:
        return []
    # each frame rendered once for every protocol that takes it; its figures (and the saved PNGs) in a worker thread
    # while the next frame renders
    n_frames = len(set().union(*selections.values()))
    bar = progress(n_frames, "eval " + " + ".join(p.key for p in selections)) if progress is not None else None
    # on the CPU a frame a core, each rendered on one thread (a rasteriser each): the render's serial parts (sort,
    # projection), the reference image and the metrics then overlap instead of leaving a core idle (docs/evaluation.md)
    workers = min(runtime.cpu_threads(), EVAL_MAX_WORKERS) if str(mapper.gmap.device).startswith("cpu") else 1
    renders = [renderer()] if workers < 2 else [renderer(mapper.new_rasterizer(), 1) for _ in range(workers)]
    try:
        return evaluate_protocols(selections, renders, lambda i: seq.load(i).rgb, on_frame=on_frame)
    finally:
        if bar is not None:
            bar.close()


@dataclass
class _Run:
    """What the figures of metrics.json are made from (the values of one run, gathered as the outputs are written)."""

    result: SystemResult
    mapper: Mapper | None
    seq: Any
    cfg: Config
    odometry_name: str
    error: str | None
    frames_unreadable: int
    stage: str
    device: str | None
    map_mb: float | None = None            # map.ply's size (None: no map)
    ready_s: float = 0.0                   # seconds from the last frame until map.ply (else trajectory.txt) was written
    segments_ate: dict | None = None
    frame_rows: list = field(default_factory=list)     # frames.csv read back at the end


def _frame_rows(writer: RunWriter) -> list[dict]:
    """``frames.csv`` as written (its rows as strings), read back at the end: the per-frame figures of the
    ``tracking`` section come from it, not from more bookkeeping in the frame loop (see :class:`mgso.system.FrameLog`).
    Empty for a run without one (:func:`write_outputs`)."""
    import csv

    log_ = writer.frame_log
    if log_ is None or not log_.path.is_file():
        return []
    with open(log_.path, newline="", encoding="utf-8") as fh:
        return [r for r in csv.DictReader(fh) if r.get("status") != "unreadable"]


def _segment_ates(result: SystemResult, gt, rows: list[dict]) -> dict | None:
    """The ATE of each tracking segment on its own (Sim(3) aligned: a segment after a loss has its own scale), on
    the odometry's poses before loop closure, the frames' segments from ``frames.csv``'s ``rows``; ``None`` for a
    run of one segment or without ground truth."""
    from mgso.eval import EvaluationError, compute_ate

    if gt is None or result.segments < 2 or not rows:
        return None
    traj = result.odometry_trajectory if result.odometry_trajectory is not None else result.trajectory
    out = {}
    for seg in range(result.segments):
        stamps = {float(r["timestamp"]) for r in rows if r.get("segment") == str(seg)}
        part = traj.at_times(stamps)
        if len(part) < 3:
            continue
        try:
            out[str(seg)] = {"frames": len(part), "ate_rmse": compute_ate(part, gt, align="sim3",
                                                                          label=f"segment {seg}").rmse}
        except EvaluationError as exc:
            log.warning("no ATE on segment %d: %s", seg, exc)
    return out or None


def _median_of(rows: list[dict], column: str) -> float | None:
    """The median of a ``frames.csv`` column over the tracked frames that have it (``None``: none has)."""
    vals = [float(r[column]) for r in rows if r.get("status") == "tracked" and r.get(column)]
    return float(np.median(vals)) if vals else None


def _tracking_figures(run: _Run) -> dict:
    """The odometry's own figures, the same for every stage: how the frames went (the odometry's word for each),
    its time a tracked frame (from frames.csv), the point cloud's size and each segment's ATE."""
    log_ = run.result.frame_log
    return {"status_counts": dict(Counter(log_.status)), "repeated_frames": run.result.repeated_frames,
            "fraction_tracked": len(run.result.trajectory) / len(log_) if len(log_) else 0.0,
            "track_ms_median": _median_of(run.frame_rows, "track_ms"),
            "map_ms_median": _median_of(run.frame_rows, "map_ms"),
            "points": len(run.result.cloud), "segments_ate": run.segments_ate,
            "backend": run.cfg.window.backend}


def _map_health(health: dict) -> dict:
    """metrics.json's ``map_health``: :meth:`Mapper.health`'s figures, the warnings in full and in a few words."""
    items = map_warning_items(health)
    return {**health, "warnings": [line for _, line in items], "warning_words": [words for words, _ in items]}


def _trajectory_check(ate) -> dict | None:
    """What the all-frames ATE is worth (docs/evaluation.md, "What an ATE is worth"): the ATE a camera standing
    still would get, each tenth's own scale over the whole's, their drift, and the warnings; None without it."""
    if ate is None:
        return None
    items = ate.warning_items()
    return {"standing_still_m": ate.motionless_rmse, "local_scales": [float(x) for x in ate.local_scales],
            "scale_drift": ate.scale_drift, "warnings": [line for _, line in items],
            "warning_words": [words for words, _ in items]}


def _figures(run: _Run, ate: dict, renders: list) -> dict:
    from mgso.eval import MONOGS, PHOTO_SLAM

    result, mapper, seq, cfg = run.result, run.mapper, run.seq, run.cfg
    by_key = {r.protocol_key: r for r in renders}
    st = result.mapper
    cam = seq.calibration.output if seq is not None else None
    sc = cfg.system
    has_map = mapper is not None
    refined = "refined" in ate or (has_map and mapper.refines_poses)
    map_ready_s = run.ready_s if has_map else None
    return {
        "ate_all_frames_m": ate["all"].rmse if "all" in ate else None,
        "ate_keyframes_m": ate["keyframes"].rmse if "keyframes" in ate else None,
        "ate_refined_all_frames_m": ate["refined"].rmse if "refined" in ate else None,
        "ate_odometry_all_frames_m": ate["odometry"].rmse if "odometry" in ate else None,
        "trajectory_check": _trajectory_check(ate.get("all")),
        "psnr_monogs_db": by_key["monogs"].mean_psnr if "monogs" in by_key else None,
        "ssim_monogs": by_key["monogs"].mean_ssim if "monogs" in by_key else None,
        "psnr_photo_slam_db": by_key["photo-slam"].mean_psnr if "photo-slam" in by_key else None,
        "ssim_photo_slam": by_key["photo-slam"].mean_ssim if "photo-slam" in by_key else None,
        "num_gaussians": int(mapper.gmap.n) if has_map else None,
        "map_size_mb": run.map_mb,
        "peak_memory_mb": peak_memory_mb(),
        "tracking_fps": result.tracking_fps,
        "mapping_iterations_per_s": st.iterations_per_s if has_map else None,
        "end_to_end_fps": (result.frames_processed / (result.loop_seconds + run.ready_s)
                           if result.loop_seconds + run.ready_s > 0 else 0.0),
        "frame_loop_fps": result.frame_loop_fps,
        "map_ready_s": map_ready_s,
        "frames": {"read": result.frames_read, "processed": result.frames_processed,
                   "dropped": result.frames_dropped, "unreadable": int(run.frames_unreadable),
                   "without_pose": result.frames_lost, "in_trajectory": len(result.trajectory),
                   "tracking_lost": len(result.tracking_losses)},
        "segments": result.segments,
        # each loss: the frame, why (docs/tracking.md "Tracking loss"), its figures (non-finite ones become null in
        # metrics_report); a new segment starts after it
        "tracking_losses": [{"frame": e.frame_index, "timestamp": e.timestamp, "segment": e.segment,
                             "reason": getattr(e.reason, "value", str(e.reason)), "rmse": float(e.rmse),
                             "first_rmse": float(e.first_rmse), "inlier_ratio": float(e.inlier_ratio)}
                            for e in result.tracking_losses],
        "keyframes": {"sent": result.keyframes, "in_map": len(mapper.views) if has_map else None,
                      "in_trajectory": len(result.keyframe_trajectory),
                      "requests_merged": result.keyframe_requests_merged,
                      "requests_stale": result.keyframe_requests_stale},
        "stage": run.stage,
        "mode": result.mode,
        "interrupted": result.interrupted,
        "error": run.error,
        "odometry": run.odometry_name,
        "device": run.device,
        "image_size": None if cam is None else [cam.width, cam.height],
        "timing_s": {"odometry": result.odometry_seconds, "frame_loop": result.loop_seconds,
                     "finish_and_final_refinement": result.finish_seconds,
                     "mapping_train": st.train_seconds if has_map else None,
                     "final_refinement": st.final_seconds if has_map else None,
                     "seeding": st.seed_seconds if has_map else None,
                     "outputs_and_evaluation": None},
        "tracking": _tracking_figures(run),
        "mapper": {k: v for k, v in st.as_dict().items() if k != "seeding"} if has_map else None,
        "realtime": None if result.mode != "realtime" else _realtime(result, cfg, st if has_map else None),
        "loop": None if result.loop is None else result.loop.as_dict(),
        "map_health": None if not st.health else _map_health(st.health),
        "sequence": None if seq is None else {"path": str(seq.path), "layout": seq.layout, "name": seq.name,
                                              "frames": len(seq)},
        # a live source: frames captured, replaced at the source, the timestamps' clock, why the input ended
        "live": seq.end_info() if getattr(seq, "live", False) else None,
        "protocols": {
            "ate": "RMSE of positions after Sim(3) Umeyama alignment (evo_ape -as), on all frames with a pose and on "
                   "keyframes",
            "psnr_monogs_db": MONOGS.name, "psnr_photo_slam_db": PHOTO_SLAM.name,
            "render_poses": ("the odometry's final poses moved by the map's keyframe corrections "
                             "(trajectory_refined.txt; no alignment: the map is in their frame)" if refined
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
            "end_to_end_fps": "frames processed / wall time from the first frame until map.ply was written (the "
                              "frame loop, then the mapper's catch-up and final refinement; without a map: until "
                              "trajectory.txt was written)",
            "frame_loop_fps": "frames processed / wall time of the frame loop alone (odometry and mapping while the "
                              "frames came; what end_to_end_fps was before 2026-12-05)",
            "map_ready_s": "seconds from the end of the frame loop (the last frame) until map.ply was written",
            "segments_ate": "tracking.segments_ate: each segment's ATE on its own, Sim(3) aligned, on the odometry's "
                            "poses before loop closure",
        },
    }


def _realtime(result: SystemResult, cfg: Config, st) -> dict:
    """metrics.json's ``realtime`` section: how the played frames went and what the mapper did meanwhile (``st``: its
    :class:`~mgso.mapping.mapper.MapperStats`; ``None`` without a map, whose entries are then null: the same keys)."""
    def m(name: str):
        return None if st is None else getattr(st, name)

    return {
        "mapper_in": result.mapper_in,
        "mapper_priority": m("priority") or None,   # its process's while the camera ran (SCHED_IDLE, nice +N)
        "frames_tracked_fraction": (result.frames_processed / result.frames_read if result.frames_read else None),
        # steps before the stream ended; the others are catch-up steps (messages still queued) and final ones
        "mapping_steps_running": m("steps_while_streaming"), "mapping_steps_final": m("final_steps"),
        # of the steps while running: those taken while messages waited (the training share), and their level
        "mapping_steps_while_behind": m("steps_while_behind"), "running_level": m("running_level"),
        # messages still queued when the stream ended, and the seconds the mapper took to apply them (and to seed the
        # points that waited) before its final refinement
        "mapper_queue_at_end": (None if st is None or st.stream_ended_at_depth < 0 else st.stream_ended_at_depth),
        "mapper_catch_up_seconds": m("catch_up_seconds"),
        "mapper_cpu_seconds": m("cpu_seconds"), "main_process_cpu_seconds": result.cpu_seconds,
        "mapper_cpu_share": result.mapper_cpu_share,
        "queue_waits": m("queue_waits"), "queue_wait_seconds": m("queue_wait_seconds"),
        # how long the frames taken waited after the camera (the player) released them: system.max_lag_ms
        "max_lag_ms": cfg.system.max_lag_ms,
        "frame_lag_ms_median": (round(1000 * float(np.median(result.frame_lags)), 2) if result.frame_lags
                                else None),
        "frame_lag_ms_max": round(1000 * max(result.frame_lags), 2) if result.frame_lags else None}
