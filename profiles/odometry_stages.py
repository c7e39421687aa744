"""Where the odometry's CPU time goes, stage by stage; prints one JSON line.

    python profiles/odometry_stages.py [--path P ...] [--frames N] [--set window.X=Y ...]

Runs :class:`mgso.odometry.Odometry` (the window's bundle adjustment, the deterministic mode) over each sequence
(default: ``kitti00_0-159`` and ``7scenes_redkitchen_0-499`` from the shared data folder) with one launch thread
(``runtime.set_cpu_threads(1)``), so that the calling thread's CPU clock (``time.thread_time``) holds all the work,
kernels included. Each stage is wrapped and charged its own time, its callees' wrapped stages excluded:

- ``pyramid``, ``initializer`` (the frames before the window starts), ``coarse_track`` (the tracker's
  Gauss-Newton over its motion hypotheses), ``trace`` (the immature points' epipolar search, every frame),
  ``activate``, ``optimize`` (the window's bundle adjustment), ``marginalize_points``, ``marginalize_frames``,
  ``tracking_ref`` (the new reference's depth maps), ``new_immature`` (pixel selection a keyframe),
  ``track_other`` / ``map_other`` / ``keyframe_other`` (the rest of :meth:`Odometry.track`, :meth:`Odometry.map` and
  ``_make_keyframe``: decoding, bookkeeping, messages);
- two kernels' launchers apart from the stage that calls them: ``track_system`` (the tracker's residuals and
  system, also by pyramid level: calls, residuals a call, CPU ns a residual with the Python around each launch) and
  ``init_system`` (the initialiser's).

Figures are CPU ms a frame (over all frames of the sequence) and the stage's call count; ``total`` is the thread's
CPU over the run. On a shared machine compare runs taken one after the other, not across days. The wrappers only
read the clock around the calls they wrap.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mgso import odometry as odo_mod  # noqa: E402
from mgso.config import Config, apply_overrides  # noqa: E402
from mgso.io import open_sequence  # noqa: E402
from mgso.io.paths import shared_data_dir  # noqa: E402
from mgso.tracking import coarse_tracker, initializer  # noqa: E402
from mgso_kernels import runtime  # noqa: E402

DEFAULT = ("kitti00_0-159", "7scenes_redkitchen_0-499")


class StageClock:
    """Thread CPU time per stage, each stage's nested (wrapped) stages excluded."""

    def __init__(self):
        self.seconds: dict[str, float] = collections.defaultdict(float)
        self.calls: collections.Counter = collections.Counter()
        self.levels: dict[int, list] = collections.defaultdict(lambda: [0, 0.0, 0])  # width -> [calls, s, residuals]
        self._stack: list[float] = []
        self._undo: list[tuple[object, str, object]] = []

    def wrap(self, owner, name: str, label: str, per_level: bool = False) -> None:
        """Charge ``owner.name`` to ``label``; ``per_level``: also by the pyramid level (``track_system``'s
        ``cam.width``, its fifth argument) with the residuals (its first argument's length)."""
        f = getattr(owner, name)

        @functools.wraps(f)
        def timed(*a, **k):
            t = time.thread_time()
            self._stack.append(0.0)
            try:
                return f(*a, **k)
            finally:
                d = time.thread_time() - t
                nested = self._stack.pop()
                self.seconds[label] += d - nested
                self.calls[label] += 1
                if self._stack:
                    self._stack[-1] += d
                if per_level:
                    lv = self.levels[int(a[4].width)]
                    lv[0] += 1
                    lv[1] += d
                    lv[2] += int(a[0].shape[0])

        self._undo.append((owner, name, f))
        setattr(owner, name, timed)

    def restore(self) -> None:
        for owner, name, f in reversed(self._undo):
            setattr(owner, name, f)
        self._undo.clear()


def run_one(path: Path, cfg: Config, device: str, frames: int | None) -> dict:
    clock = StageClock()

    for owner, name, label in (
            (odo_mod.ImagePyramid, "build", "pyramid"), (odo_mod.Odometry, "_track_initializer", "initializer"),
            (odo_mod.Odometry, "_set_first", "initializer_first"), (odo_mod.Odometry, "_start_window", "start_window"),
            (odo_mod.CoarseTracker, "track_frame", "coarse_track"), (odo_mod, "trace_immature_points", "trace"),
            (odo_mod.PointActivator, "activate", "activate"), (odo_mod, "make_tracking_reference", "tracking_ref"),
            (odo_mod, "make_immature_points", "new_immature"), (odo_mod.Odometry, "track", "track_other"),
            (odo_mod.Odometry, "map", "map_other"), (odo_mod.Odometry, "_make_keyframe", "keyframe_other"),
            (initializer, "init_system", "init_system")):
        clock.wrap(owner, name, label)
    clock.wrap(coarse_tracker, "track_system", "track_system", per_level=True)
    try:
        seq = open_sequence(path, config=cfg.input)
        cam = seq.calibration.output
        odo = odo_mod.Odometry(odo_mod.geometry_for(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cfg), cfg,
                         device=device)
        be = type(odo.back_end)
        for name in ("optimize", "marginalize_points", "marginalize_frames", "flag_frames_for_marginalization"):
            clock.wrap(be, name, name if name != "flag_frames_for_marginalization" else "flag_frames")
        n = 0
        t0 = time.thread_time()
        for f in seq.frames():
            if frames is not None and n >= frames:
                break
            odo.process(f)
            n += 1
        total = time.thread_time() - t0
    finally:
        clock.restore()
    n = max(n, 1)
    stages = {k: {"ms_per_frame": round(1000 * v / n, 2), "calls": clock.calls[k]}
              for k, v in sorted(clock.seconds.items(), key=lambda kv: -kv[1])}
    levels = {}
    for width, (calls, sec, res) in sorted(clock.levels.items(), reverse=True):
        levels[f"width_{width}"] = {"calls": calls, "ms_per_frame": round(1000 * sec / n, 2),
                                    "residuals_per_call": res // max(calls, 1),
                                    "ns_per_residual": round(1e9 * sec / max(res, 1), 1)}
    return {"frames": n, "keyframes": len(odo.keyframes), "total_ms_per_frame": round(1000 * total / n, 2),
            "stages": stages, "track_system_levels": levels}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--path", action="append", default=None)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    device = runtime.init("cpu")
    runtime.set_cpu_threads(1)
    cfg = apply_overrides(Config(), args.set)
    if args.path:
        paths = [Path(p) for p in args.path]
    else:
        base = shared_data_dir()
        if base is None:
            sys.exit("no --path and no shared data folder (set MGSO_DATA)")
        paths = [base / d for d in DEFAULT]
    out = {"profile": "odometry_stages", "device": device, "load_avg_1min": round(os.getloadavg()[0], 2)}
    for path in paths:
        out[path.name] = run_one(path, cfg, device, args.frames)
    out["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
