"""The ``mgso`` command line: ``run``, ``demo``, ``fit``, ``eval``, ``info``, ``export``, ``view``, ``bench``.

The CLI is where printing, progress bars and exit codes live; the core reports through observers and result values.
Every command that writes files takes ``--out DIR``, checked before any work (:func:`~mgso.app.writer.
check_out_dir`, which makes nothing; :func:`~mgso.app.writer.prepare_out_dir` when the folder is made), writes
through one :class:`~mgso.app.writer.RunWriter` and writes the configuration it used there (``config.yaml``).
Exit codes, the same for every command and stage (README "Exit codes"): 0 done; 1 failed (an error, or no frame
got a pose: the outputs of what was done are written); 2 usage; 128 + the signal's number when a signal stopped
the run (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP: the outputs of what was done are written).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import time
from pathlib import Path
from typing import Sequence

from mgso import __version__
from mgso.config import Config, ConfigError, check_runtime, describe_config, load_config

from .signals import StopState, exit_code_for
from .stages import EXIT_FAILED, EXIT_OK, EXIT_USAGE
from .writer import OutputError, RunWriter, check_out_dir

log = logging.getLogger("mgso")


class CliError(Exception):
    """A user-facing failure: printed as one line, exit code 1 (no traceback)."""


# ------------------------------------------------------------------------------------------------ helpers
def _setup_logging(quiet: bool, verbose: int) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 0 else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    logging.getLogger("mgso").setLevel(level)


def _load_cfg(args) -> Config:
    overrides = list(getattr(args, "set", None) or [])
    if getattr(args, "device", None):
        overrides.append(f"runtime.device={args.device}")
    if getattr(args, "realtime", False):
        overrides.append("system.mode=realtime")
    cfg = load_config(getattr(args, "config", None), overrides)
    check_runtime(cfg)
    return cfg


def _print(args, *lines: str) -> None:
    if not getattr(args, "quiet", False):
        for line in lines:
            print(line)


def _progress(args, total: int, desc: str):
    """A tqdm bar on stderr, or a no-op one with ``--quiet``."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=getattr(args, "quiet", False), dynamic_ncols=True,
                file=sys.stderr)


def _open(path: str, calib: str | None, cfg: Config, groundtruth: str | None = None, *, to_track: bool = True):
    """The sequence at ``path``; ``to_track``: its images checked against the calibration and the tracker's
    pyramid here, in one line, rather than by a kernel's error once tracking starts (issue 44)."""
    from mgso.io import open_sequence

    seq = open_sequence(path, calib=calib, config=cfg.input, groundtruth=groundtruth)
    if to_track:
        _check_images_can_be_tracked(path, seq, cfg)
    return seq


def _check_images_can_be_tracked(path: str, seq, cfg: Config) -> None:
    from mgso.camera import CalibrationError
    from mgso.io import DatasetError

    cam = seq.calibration.output
    w, h = int(cam.width), int(cam.height)
    if not (0.0 <= cam.cx <= w and 0.0 <= cam.cy <= h):
        raise CalibrationError(f"{path}: the principal point ({cam.cx:g}, {cam.cy:g}) lies outside the {w}x{h} "
                               "images: the calibration is for another image size")
    from mgso_kernels.image import plan_pyramid

    t = cfg.tracking
    try:
        plan_pyramid(w, h, levels=t.pyramid_levels, max_levels=t.pyramid_max_levels, min_area=t.pyramid_min_area,
                     mode=t.pyramid_size_mode)
    except ValueError as exc:
        how = "automatic" if t.pyramid_levels == 0 else str(t.pyramid_levels)
        raise DatasetError(f"{path}: {w}x{h} images cannot be tracked: {exc} (tracking.pyramid_levels: {how})") \
            from None


def _format_info(info: dict) -> list[str]:
    lines = [f"layout:       {info.get('layout')}",
             f"path:         {info.get('path')}",
             f"frames:       {info.get('frames')}" + (f" (of {info['frames_total']})"
                                                      if info.get("frames_total") != info.get("frames") else "")
             if not info.get("live") else "frames:       live (no length; docs/live.md)"]
    size_in, size_out = info.get("image_size_in"), info.get("image_size_out")
    lines.append(f"image:        {size_in[0]}x{size_in[1]} {'colour' if info.get('color') else 'gray'}"
                 + (f" -> {size_out[0]}x{size_out[1]}" if size_out != size_in else ""))
    dist = info.get("distortion") or {}
    lines.append(f"camera:       {info.get('camera_model')}"
                 + (" (" + ", ".join(f"{k}={v:.6g}" for k, v in dist.items()) + ")" if dist else ""))
    k_in, k = info.get("intrinsics_in", {}), info.get("intrinsics", {})
    fmt = lambda d: "fx={fx:.4f} fy={fy:.4f} cx={cx:.4f} cy={cy:.4f}".format(**d)  # noqa: E731
    lines.append(f"intrinsics:   {fmt(k_in)}  (input)")
    if k != k_in:
        lines.append(f"              {fmt(k)}  (output, rectify={info.get('rectify')}, {info.get('undistortion')})")
    lines.append(f"calibration:  {info.get('calibration_source')}")
    ph = info.get("photometric") or {}
    parts = [n for n in ("response", "vignette", "exposure") if ph.get(n)]
    lines.append(f"photometric:  {', '.join(parts) if parts else 'none'}")
    gt = info.get("groundtruth") or {}
    lines.append(f"ground truth: {str(gt.get('poses')) + ' poses from ' + str(gt.get('source')) if gt.get('present') else 'none'}")
    span = info.get("time_span")
    if span:
        lines.append(f"time:         {span[0]:.3f} .. {span[1]:.3f} s ({info.get('duration_s', 0):.2f} s, "
                     f"{info.get('fps', 0):.1f} fps nominal)")
    return lines


# ----------------------------------------------------------------------------------------------- commands
def cmd_info(args) -> int:
    cfg = _load_cfg(args)
    if args.show_config:
        _print(args, *describe_config(cfg))
        if not args.path:
            return EXIT_OK
    if not args.path:
        raise CliError("info: give a dataset PATH (or --show-config)")
    seq = _open(args.path, args.calib, cfg)
    info = seq.describe()
    if args.json:
        print(json.dumps(info, indent=2, default=str))
    else:
        _print(args, *_format_info(info))
    return EXIT_OK


def cmd_eval(args) -> int:
    from mgso.eval import compute_ate, compute_rpe, format_report
    from mgso.io.trajectory import read_trajectory

    cfg = _load_cfg(args)
    if args.out:                        # before any work, making nothing
        check_out_dir(args.out)
    est = read_trajectory(args.estimate)
    gt_path = Path(args.gt)
    seq = None
    if gt_path.is_dir():
        seq = _open(str(gt_path), args.calib, cfg, to_track=False)
        if seq.groundtruth is None:
            raise CliError(f"{gt_path}: this dataset has no ground truth to evaluate against")
        ref = seq.groundtruth
    else:
        ref = read_trajectory(gt_path)
    ate = compute_ate(est, ref, align=args.align, max_diff=args.max_diff, label=args.label,
                      estimate_name=Path(args.estimate).name, reference_name=gt_path.name)
    rpe = None
    if args.rpe:
        rpe = compute_rpe(est, ref, align=args.align, max_diff=args.max_diff, delta=args.rpe_delta,
                          delta_unit=args.rpe_unit, label=args.label)
    writer = RunWriter(args.out) if args.out else None    # a bad --out fails before any output
    _print(args, format_report(ate=ate, rpe=rpe))
    if writer is not None:
        writer.write_config(cfg)        # as every command that writes a folder (issue 44)
        if seq is not None:             # the ground truth came from a dataset: what was read, as a run says it
            writer.write_sequence(seq)
        writer.write_metrics(ate=ate, rpe=rpe)
        writer.write_trajectory_plot(ate, ref)
        _print(args, *(f"wrote {p}" for p in writer.written_paths()))
    if args.json:
        print(json.dumps(ate.as_dict(), default=str))
    return EXIT_OK


def cmd_run(args) -> int:
    from .stages import run_sequence

    cfg = _live_and_limits(args, _load_cfg(args))
    _check_viewer(args)                 # viser missing: one line before any work
    if args.out:                        # so is an output folder that cannot be used (nothing made yet)
        check_out_dir(args.out)
    seq = _open(args.path, args.calib, cfg, groundtruth=args.groundtruth)
    if getattr(args, "downscale", None) is not None:
        size = _downscaled_size(seq.calibration.output, args.downscale, "run")
        if size is not None:
            seq.close()
            args.set = list(args.set or []) + [f"input.width={size[0]}", f"input.height={size[1]}"]
            cfg = _live_and_limits(args, _load_cfg(args))
            seq = _open(args.path, args.calib, cfg, groundtruth=args.groundtruth)
    elif (args.stage or "full") == "full":
        _hint_large_frames(seq.calibration.output, cfg)
    writer = RunWriter(args.out or Path("runs") / f"{seq.name}-{time.strftime('%Y%m%d-%H%M%S')}")
    writer.write_config(cfg)
    if getattr(seq, "live", False):
        w, h = seq.calibration.output_size
        _print(args, f"mgso {__version__}: live source {seq.what} ({w}x{h}, {seq.fps:.1f} fps nominal) -> "
                     f"{writer.out}; runs until Ctrl-C, SIGTERM, a limit (--max-frames, --duration) or "
                     f"{cfg.input.live_timeout_s:g} s without a frame")
    else:
        _print(args, f"mgso {__version__}: {seq.layout} sequence {seq.name!r}, {len(seq)} frames -> {writer.out}")
    state = StopState()
    viewer = _start_viewer(args, seq)
    try:
        summary = run_sequence(seq, cfg, writer, stage=args.stage, state=state,
                               progress=lambda total, desc: _progress(args, total, desc),
                               observers=(viewer,) if viewer is not None else ())
    finally:
        if viewer is not None:
            viewer.close()
            _print(args, f"viewer closed; open the finished run with: mgso view {writer.out}")
    _print(args, *summary.lines())
    if summary.outcome == "failed":
        # the reason on stderr too, in the one-line form of every other error
        print(f"mgso {args.command}: error: {summary.error or 'no frame got a pose'} (outputs of what was done in "
              f"{writer.out})", file=sys.stderr)
    elif summary.outcome == "interrupted":
        print(f"mgso {args.command}: {summary.signal or 'SIGINT'}: stopped after {summary.frames} frames; the "
              f"outputs of what was done are in {writer.out}", file=sys.stderr)
    return summary.exit_code


def _live_and_limits(args, cfg: Config) -> Config:
    """``mgso run``'s input limits and a live source's settings (docs/live.md).

    A live camera or stream always runs in real time (``system.mode=realtime``; a deterministic run of it is
    meaningless: a warning when ``--set system.mode=deterministic`` asked for one) and has no ground truth, so no
    evaluation that reads frames back (``system.eval_monogs`` / ``eval_photo_slam`` off); ``--max-frames N`` and
    ``--duration S`` bound it (``input.live_max_frames`` / ``input.live_duration_s``). For a recorded sequence
    ``--max-frames N`` keeps its first N selected frames (``input.end``); ``--duration`` is for live sources."""
    import dataclasses

    from mgso.io import is_live_source

    n, dur = getattr(args, "max_frames", None), getattr(args, "duration", None)
    if n is not None and n < 1:
        raise CliError(f"run: --max-frames must be >= 1, got {n}")
    if dur is not None and not dur > 0:
        raise CliError(f"run: --duration must be > 0 seconds, got {dur}")
    inp, sysc = cfg.input, cfg.system
    if is_live_source(args.path):
        if n is not None:
            inp = dataclasses.replace(inp, live_max_frames=n)
        if dur is not None:
            inp = dataclasses.replace(inp, live_duration_s=dur)
        asked = [s for s in (getattr(args, "set", None) or []) if s.replace(" ", "").startswith("system.mode=")]
        if sysc.mode != "realtime" and asked:
            log.warning("%s: a live source always runs in real time (a deterministic run of a live camera makes no "
                        "sense); system.mode=%s ignored", args.path, sysc.mode)
        sysc = dataclasses.replace(sysc, mode="realtime", eval_monogs=False, eval_photo_slam=False)
    else:
        if dur is not None:
            raise CliError("run: --duration bounds a live camera or stream; for a recorded sequence give "
                           "--max-frames N (or --set input.end=N)")
        if n is not None:
            end = inp.start + (n - 1) * inp.stride + 1
            inp = dataclasses.replace(inp, end=min(end, inp.end) if inp.end else end)
    return dataclasses.replace(cfg, input=inp, system=sysc)


#: The demo's mapping budget (a few minutes on a 2-core CPU; docs/mgso.md): fewer steps a keyframe than a recorded
#: run's default and densification from step 200, so that the small map gets its detail within the budget. Any
#: ``--set`` of the user comes after these and wins.
DEMO_OVERRIDES = ("mapping.mapper.iterations_per_keyframe=30", "mapping.mapper.final_iterations=300",
                  "mapping.densify.refine_start_step=200")


def cmd_demo(args) -> int:
    from mgso.synthetic import cached_sequence_folder

    args.set = list(DEMO_OVERRIDES) + list(args.set or [])
    _load_cfg(args)                     # a bad --set fails before the scene is made
    _check_viewer(args)
    if args.out is None:
        args.out = str(Path("runs") / f"demo-{time.strftime('%Y%m%d-%H%M%S')}")
    check_out_dir(args.out)             # before the scene is made (nothing made yet)
    _print(args, "making the built-in synthetic scene (cached after the first run) ...")
    folder = cached_sequence_folder(**_demo_scene_params(args))
    args.path, args.calib, args.groundtruth = str(folder), None, None
    return cmd_run(args)


def _downscaled_size(cam, factor: int, command: str) -> tuple[int, int] | None:
    """``--downscale N``: the frames' size (``cam``, the calibration's output camera) divided by N, as
    ``input.width`` / ``input.height`` (None for 1: the size as it is)."""
    if factor < 1:
        raise CliError(f"{command}: --downscale must be >= 1, got {factor}")
    if factor == 1:
        return None
    w, h = int(cam.width // factor), int(cam.height // factor)
    if w < 16 or h < 16:
        raise CliError(f"{command}: --downscale {factor} makes {cam.width}x{cam.height} images smaller than 16x16")
    return w, h


#: Pixels a frame above which a run on the CPU says how to train at a smaller size (twice 640x480: the size the
#: defaults and docs/measured.md's figures are for)
LARGE_FRAME_PIXELS = 2 * 640 * 480


def _hint_large_frames(cam, cfg: Config) -> None:
    """One warning when frames much larger than 640x480 are mapped (the full stage) on the CPU, where a training
    step's cost grows with the pixels (a 1920x1080 clip of 20 frames spent 5 minutes in its final refinement on 2
    cores): how to train at a smaller size (``--downscale``)."""
    from mgso_kernels.runtime import resolve_device

    w, h = int(cam.width), int(cam.height)
    if w * h <= LARGE_FRAME_PIXELS:
        return
    try:
        if not resolve_device(cfg.runtime.device).startswith("cpu"):
            return
    except Exception:   # an unusable device is reported where the run starts it
        return
    k = 2
    while (w // k) * (h // k) > LARGE_FRAME_PIXELS // 2:
        k += 1
    log.warning("%dx%d frames on the CPU: each mapping step costs about %.0fx one at 640x480 and the map can take many "
                "minutes after the last frame; --downscale %d runs at %dx%d", w, h, w * h / (640 * 480), k, w // k,
                h // k)


def cmd_fit(args) -> int:
    from mgso.mapping.fit import fit_sequence

    overrides = []
    if args.iterations is not None:
        overrides.append(f"mapping.train.iterations={args.iterations}")
    if args.max_frames is not None:
        overrides.append(f"mapping.train.max_train_views={args.max_frames}")
    if args.stride is not None:
        overrides.append(f"input.stride={args.stride}")
    args.set = list(args.set or []) + overrides
    cfg = _load_cfg(args)
    if args.out:
        check_out_dir(args.out)
    if args.downscale is not None:
        size = None
        if args.downscale != 1:
            size = _downscaled_size(_open(args.path, args.calib, cfg, groundtruth=args.poses).calibration.output,
                                    args.downscale, "fit")
        if size is not None:
            args.set += [f"input.width={size[0]}", f"input.height={size[1]}"]
            cfg = _load_cfg(args)
    seq = _open(args.path, args.calib, cfg, groundtruth=args.poses)
    init = args.init
    if init != "random" and not Path(init).is_file():
        raise CliError(f"fit: --init {init}: no such file (give 'random' or a PLY file)")
    writer = RunWriter(args.out or Path("runs") / f"fit-{seq.name}-{time.strftime('%Y%m%d-%H%M%S')}")
    writer.write_config(cfg)
    writer.write_sequence(seq)          # what was read, first, as a run writes it (sequence.json, groundtruth.txt)
    size = seq.calibration.output.size
    _print(args, f"mgso {__version__} fit: {seq.layout} sequence {seq.name!r}, {len(seq)} frames at "
                 f"{size[0]}x{size[1]}, {cfg.mapping.train.iterations} iterations, init {init} -> {writer.out}")

    def progress(total: int, desc: str):
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit="frame" if desc == "load" else "it",
                    disable=getattr(args, "quiet", False), dynamic_ncols=True, file=sys.stderr)

    from .signals import deferred_signals

    # Ctrl-C, SIGTERM, SIGHUP while training: recorded, the step under way finishes, and the map trained so far is
    # written (map.ply, metrics.json "interrupted"), as a run writes what was done; the exit code names the signal
    state = StopState()
    result = fit_sequence(seq, cfg, writer, init=init, progress=progress,
                          should_stop=lambda: state.signum is not None,
                          guard=lambda: deferred_signals(state, "training (the map trained so far is written)"))
    _print(args, *result.lines())
    if state.signum is not None:
        print(f"mgso fit: {state.name}: stopped after {result.iterations} of {cfg.mapping.train.iterations} "
              f"iterations; the map trained so far is in {writer.out}", file=sys.stderr)
        return exit_code_for(state.signum)
    return EXIT_OK


def cmd_export(args) -> int:
    from .export import ExportError, export_run

    try:
        result = export_run(args.run_dir, args.out, args.format, input_path=args.input, calib=args.calib,
                            all_frames=args.all_frames, progress=lambda total, desc: _progress(args, total, desc))
    except ExportError as exc:
        raise CliError(str(exc)) from None
    _print(args, *result.lines())
    return EXIT_OK


def _check_viewer(args) -> None:
    """``--viewer``: viser installed and the full stage, else one line before any work."""
    if not getattr(args, "viewer", False):
        return
    from .viewer import ViewerError, check_address, require_viser

    try:
        require_viser()
        check_address(args.host, args.port)
    except ViewerError as exc:
        raise CliError(str(exc)) from None
    if (args.stage or "full") != "full":
        raise CliError(f"--viewer shows the full system (the Gaussian map): it cannot be used with --stage {args.stage}")


def _start_viewer(args, seq):
    """The live viewer of ``mgso run/demo --viewer`` (docs/viewer.md), started, or ``None``."""
    if not getattr(args, "viewer", False):
        return None
    from .viewer import LiveViewer, ViewerError

    _check_viewer(args)
    try:
        viewer = LiveViewer(args.host, args.port, groundtruth=seq.groundtruth).start()
    except ViewerError as exc:
        raise CliError(str(exc)) from None
    print(f"mgso viewer: {viewer.url} (open it in a browser; docs/viewer.md)", file=sys.stderr, flush=True)
    return viewer


def cmd_view(args) -> int:
    from mgso.config import ConfigError, check_runtime, load_config

    from .viewer import ViewerError, check_address, open_run

    device = args.device or "cpu"
    try:        # the device refused as run refuses it, before the map is read and served
        check_runtime(load_config(None, [f"runtime.device={device}"]))
        check_address(args.host, args.port)
        scene = open_run(args.run_dir, args.host, args.port, device=device)
    except (ViewerError, ConfigError) as exc:
        raise CliError(f"--device: {exc}" if isinstance(exc, ConfigError) else str(exc)) from None
    print(f"mgso viewer: {scene.url} (open it in a browser; Ctrl-C to stop)", file=sys.stderr, flush=True)
    try:
        while True:
            time.sleep(1.0)
    finally:
        scene.close()


def _viewer_args(p: argparse.ArgumentParser, *, flag: bool = True) -> None:
    from .viewer import DEFAULT_HOST, DEFAULT_PORT

    if flag:
        p.add_argument("--viewer", action="store_true",
                       help="watch the run live in a browser (needs pip install \"mgso[viewer]\"; docs/viewer.md)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT,
                   help=f"viewer port (default {DEFAULT_PORT}; the next free one when it is taken)")
    p.add_argument("--host", default=DEFAULT_HOST,
                   help=f"viewer address (default {DEFAULT_HOST}: this machine only; 0.0.0.0 opens the viewer, "
                        "without any password, to everyone who can reach this machine on the network; from a remote "
                        "machine prefer ssh -L, docs/viewer.md)")


def _demo_scene_params(args) -> dict:
    return dict(num_frames=args.frames, width=args.width, height=args.height, seed=args.seed)


# -------------------------------------------------------------------------------------------------- parser
def _common(p: argparse.ArgumentParser, *, config: bool = True) -> None:
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars, only warnings and errors")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v: debug)")
    if config:
        p.add_argument("--config", metavar="PROFILE", help="config profile: a built-in name (default, fast) or a YAML "
                                                           "file (may use inherit_from)")
        p.add_argument("--set", metavar="SECTION.KEY=VALUE", action="append", default=[],
                       help="override one setting, e.g. --set window.max_frames=6 (repeatable)")
        p.add_argument("--device", help="cpu, cuda, cuda:N or auto (overrides runtime.device)")


def build_parser() -> argparse.ArgumentParser:
    from .stages import DEFAULT_STAGE, STAGE_HELP, STAGES

    parser = argparse.ArgumentParser(prog="mgso", description="Monocular SLAM with a Gaussian Splatting map "
                                                              "(DSO tracking + DSO-seeded 3DGS mapping).")
    parser.add_argument("--version", action="version", version=f"mgso {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("run", help="run on a recorded sequence (dataset folder, image folder or video) or a live "
                                   "camera or stream (camera:N, rtsp://..., http://...: docs/live.md)")
    p.add_argument("path", help="dataset folder, image folder or video file (layout detected), or a live source: "
                                "camera:N (OpenCV's camera N), rtsp:// http:// udp:// ... (with --calib)")
    p.add_argument("--out", help="output folder (default runs/<name>-<time>)")
    p.add_argument("--calib", help="calibration when the dataset has none: a file (DSO camera.txt, EuRoC sensor.yaml, "
                                   "KITTI calib.txt, or one line 'fx fy cx cy [k1 k2 p1 p2 [k3]]') or those numbers "
                                   "themselves, e.g. --calib '525 525 319.5 239.5'")
    p.add_argument("--groundtruth", help="ground-truth trajectory file (TUM or KITTI) of camera poses")
    p.add_argument("--downscale", type=int, help="divide the frames' size by this (2 = half width and height; sets "
                                                 "input.width/height): a large camera's frames on a CPU")
    p.add_argument("--stage", choices=STAGES, default=None,
                   help=f"how far to go (default {DEFAULT_STAGE}): " + "; ".join(STAGE_HELP[s] for s in STAGES))
    p.add_argument("--realtime", action="store_true",
                   help="play the sequence at its frame rate as a live camera would, the map trained in its own "
                        "process; frames that arrive while the odometry is busy wait up to system.max_lag_ms (250) "
                        "and are dropped after that (system.mode=realtime; default: deterministic; a live camera or "
                        "stream always runs so)")
    p.add_argument("--max-frames", type=int, metavar="N",
                   help="stop after N frames: a live source's first N captured (input.live_max_frames), a recorded "
                        "sequence's first N selected (input.end)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="a live camera or stream: stop after S seconds of frames (input.live_duration_s)")
    _viewer_args(p)
    _common(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", help="run on the built-in synthetic scene (made once into a cache folder)")
    p.add_argument("--out", help="output folder (default runs/demo-<time>)")
    p.add_argument("--frames", type=int, default=120, help="frames of the synthetic sequence")
    p.add_argument("--width", type=int, default=160, help="image width (160x120: a few minutes on a 2-core CPU)")
    p.add_argument("--height", type=int, default=120, help="image height")
    p.add_argument("--seed", type=int, default=0, help="scene seed")
    p.add_argument("--stage", choices=STAGES, default=None, help="as for run")
    p.add_argument("--realtime", action="store_true", help="as for run")
    _viewer_args(p)
    _common(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("fit", help="fit a Gaussian map to a sequence with known poses (ground truth or --poses), "
                                   "evaluate it on held-out frames")
    p.add_argument("path", help="dataset folder, image folder or video file (layout detected)")
    p.add_argument("--out", help="output folder (default runs/fit-<name>-<time>): map.ply, renders/, gt/, "
                                 "metrics.json, config.yaml")
    p.add_argument("--poses", help="trajectory file of camera poses (TUM or KITTI camera-to-world), instead of the "
                                   "dataset's ground truth")
    p.add_argument("--init", default="random", help="initial Gaussians: 'random' (points in the view frusta, "
                                                    "mapping.train.init_*) or a PLY file (a point cloud, or a 3DGS "
                                                    "map to train further)")
    p.add_argument("--iterations", type=int, help="training steps (mapping.train.iterations)")
    p.add_argument("--max-frames", type=int, help="train on at most this many views, evenly spread "
                                                  "(mapping.train.max_train_views)")
    p.add_argument("--stride", type=int, help="use every n-th frame of the sequence (input.stride); every 5th of "
                                              "those is held out")
    p.add_argument("--downscale", type=int, help="divide the image size by this (2 = half resolution, sets "
                                                 "input.width/height): CPU speed")
    p.add_argument("--calib", help="calibration file, when the dataset has none")
    _common(p)
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("eval", help="ATE (and RPE) of a trajectory file against ground truth")
    p.add_argument("estimate", help="estimated trajectory (TUM or KITTI format)")
    p.add_argument("--gt", required=True, help="ground-truth trajectory file, or a dataset folder with ground truth")
    p.add_argument("--align", choices=["sim3", "se3", "none"], default="sim3",
                   help="alignment before the error (sim3 for monocular; evo_ape -as / -a)")
    p.add_argument("--max-diff", type=float, default=0.01, help="timestamp association tolerance in seconds (evo: "
                                                                "0.01)")
    p.add_argument("--label", default="", help="which poses these are, printed with the figures (e.g. 'all frames')")
    p.add_argument("--rpe", action="store_true", help="also the relative pose error")
    p.add_argument("--rpe-delta", type=float, default=1, help="RPE delta")
    p.add_argument("--rpe-unit", choices=["frames", "meters"], default="frames", help="RPE delta unit")
    p.add_argument("--calib", help="calibration, when --gt is a dataset folder that needs one")
    p.add_argument("--out", help="write metrics.json and trajectory.png there")
    p.add_argument("--json", action="store_true", help="print the ATE figures as one JSON line")
    _common(p)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("export", help="a finished run's keyframes (undistorted images, poses) and DSO's points as a "
                                      "COLMAP model or a nerfstudio transforms.json (docs/export.md)")
    p.add_argument("run_dir", metavar="RUN_DIR", help="the output folder of an mgso run")
    p.add_argument("--format", required=True, choices=["colmap", "nerfstudio"],
                   help="colmap: images/ + sparse/0/ (cameras, images, points3D; text and binary); nerfstudio: "
                        "images/ + transforms.json + sparse_pc.ply")
    p.add_argument("--out", help="output folder (default RUN_DIR/<format>)")
    p.add_argument("--input", help="the run's input sequence, when it has moved since the run (default: the path in "
                                   "RUN_DIR/sequence.json)")
    p.add_argument("--calib", help="calibration file, when the run's --calib file has moved")
    p.add_argument("--all-frames", action="store_true",
                   help="every frame with a pose in trajectory.txt, not only the keyframes of keyframes.txt")
    _common(p, config=False)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("view", help="open a finished run (its folder, or a map.ply) in the browser viewer until "
                                    "Ctrl-C (docs/viewer.md)")
    p.add_argument("run_dir", metavar="RUN_DIR", help="the output folder of an mgso run, or a map.ply")
    _viewer_args(p, flag=False)
    p.add_argument("--device", help="where 'render from this view' runs: cpu (default), cuda, cuda:N or auto")
    _common(p, config=False)
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("info", help="what is detected in a dataset path: layout, frames, calibration, ground truth")
    p.add_argument("path", nargs="?", help="dataset folder, image folder or video file")
    p.add_argument("--calib", help="calibration file, when the dataset has none")
    p.add_argument("--json", action="store_true", help="print the description as JSON")
    p.add_argument("--show-config", action="store_true", help="print every setting with its reason")
    _common(p)
    p.set_defaults(func=cmd_info)

    from .bench import add_parser as add_bench_parser   # mgso bench (docs/bench.md)

    add_bench_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return EXIT_USAGE
    _setup_logging(args.quiet, args.verbose)
    from mgso.camera import CalibrationError
    from mgso.eval import EvaluationError
    from mgso.io import DatasetError
    from mgso.io.ply import PlyError
    from mgso.io.trajectory import TrajectoryError

    errors: tuple = (CliError, ConfigError, OutputError, DatasetError, CalibrationError, TrajectoryError,
                     EvaluationError, PlyError)
    if args.command == "fit":  # imports Warp and the trainer: only for the command that needs them
        from mgso.mapping.fit import FitError

        errors += (FitError,)
    from .signals import Terminated, stop_signals

    state = StopState()
    try:
        with stop_signals(state):   # before a run's own handling begins (and for the commands without one)
            return args.func(args)
    except errors as exc:
        print(f"mgso {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except OSError as exc:   # a full disk, a file that vanished: one line, never a traceback
        print(f"mgso {args.command}: error: {exc.filename or ''}{': ' if exc.filename else ''}"
              f"{exc.strerror or exc}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Terminated) else signal.SIGINT
        print(f"mgso {args.command}: interrupted ({'SIGINT' if signum == signal.SIGINT else str(exc)})",
              file=sys.stderr)
        return exit_code_for(signum)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
