"""Resident memory over a long run: the odometry alone and the whole system on a long synthetic sequence, the
current resident set size every ``--every`` frames, and the sizes of every container that can grow.

The frames are rendered one at a time by :func:`mgso.synthetic.iter_frames` (the synthetic room, its periodic
figure-eight camera path: 314 frames a loop at ``motion_scale`` 1, so 10,000 frames are about 32 loops that keep the
camera moving through the room) and quantised to 8 bits as a PNG reader would give them; nothing is written to disk
and the source's own memory is constant. Each part runs in its own subprocess, so that its memory is its own:

- ``odometry``: :class:`mgso.odometry.Odometry` driven as the ``odometry`` stage of ``mgso run`` drives it (the
  ``bundle`` back end; what the stage keeps of every frame for its figures: its status and two times), then
  ``finish()`` and the two outputs' arrays (the trajectory, the point cloud in the world);
- ``system``: :class:`mgso.system.System` in deterministic mode with the DSO odometry speaking the mapper's messages
  (as the ``full`` stage runs it), with a small mapping budget (``--iterations-per-keyframe``,
  ``--final-iterations``, ``--capacity``); the outputs and the render evaluation are not run.

Resident memory is the current RSS (``/proc/self/statm``, or psutil), not the peak. At each sample the script also
records the containers that grow with the run (frame and keyframe records and their bytes each, measured by walking
the objects; the marginalised point clouds; the mapper's training views and Gaussians), the number of objects the
garbage collector tracks and the live Warp arrays (count and bytes they own): a list that keeps growing or a Warp
array allocated per frame shows there. ``growth_pct`` compares the last sample with the one at ``--warmup`` frames.

    python profiles/memory.py [--frames 10000] [--every 1000] [--warmup 1000] [--width 160 --height 120]
                              [--what odometry|system|both] [--iterations-per-keyframe 5] [--final-iterations 0]
                              [--capacity 100000] [--device cpu] [--set SECTION.KEY=VALUE ...]

Prints **one JSON line** on stdout (a progress line per sample goes to stderr). On the shared 2-core machine, at
160x120, the odometry ran 10,000 frames in 4.5 minutes (37 frames/s, rendering included) and the system in 24 minutes
(7 frames/s with the default budget): estimate with ``--frames 1000``. Results: docs/tracking.md and docs/mgso.md,
"Memory over long runs".
"""

from __future__ import annotations

import argparse
import collections
import enum
import gc
import json
import logging
import os
import platform
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GRAY_WEIGHTS = np.array([0.299, 0.587, 0.114], np.float32)


# --------------------------------------------------------------------------------------------- measuring
def rss_bytes() -> int:
    """The current resident set size of this process in bytes (``/proc/self/statm``, else psutil)."""
    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        pass
    try:
        import psutil
    except ImportError:
        raise SystemExit("profiles/memory.py: cannot read the current resident set size (no /proc/self/statm and "
                         "psutil is not installed)") from None
    return int(psutil.Process().memory_info().rss)


def malloc_info() -> dict | None:
    """glibc's ``mallinfo2``: bytes the C heap holds in use (``in_use_mb``), holds free inside its arenas
    (``free_mb``: fragmentation and freed space not yet returned) and has mapped for large blocks (``mmap_mb``);
    None where it is not available (not glibc, or glibc < 2.33)."""
    import ctypes
    import ctypes.util

    class _Info(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                   "fsmblks", "uordblks", "fordblks", "keepcost")]

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.mallinfo2
    except (OSError, AttributeError):
        return None
    fn.restype = _Info
    m = fn()
    return {"in_use_mb": m.uordblks / 1e6, "free_mb": m.fordblks / 1e6, "mmap_mb": m.hblkhd / 1e6}


def _warp_array_type():
    try:
        import warp as wp
    except ImportError:  # the package needs Warp; keep the helpers usable without it
        return None
    return wp.array


def deep_size(obj, seen: set | None = None) -> int:
    """Bytes held by ``obj`` and everything it references (dataclass fields, slots, containers, NumPy arrays with
    their data, the defaults and closures of functions, Warp arrays with the memory they own). Shared singletons
    (None, booleans, enum members, classes, modules) are not counted; ``seen`` (ids) avoids counting an object twice
    across calls."""
    seen = set() if seen is None else seen
    wp_array = _warp_array_type()
    total = 0
    stack = [obj]
    while stack:
        o = stack.pop()
        if o is None or id(o) in seen or isinstance(o, (bool, type, types.ModuleType, enum.Enum)):
            continue
        seen.add(id(o))
        if isinstance(o, np.ndarray):
            total += sys.getsizeof(o)  # its data too when it owns it
            if o.base is not None:
                stack.append(o.base)
            continue
        if wp_array is not None and isinstance(o, wp_array):
            total += sys.getsizeof(o) + (int(o.capacity) if o.deleter is not None else 0)
            continue
        total += sys.getsizeof(o)
        if isinstance(o, dict):
            stack.extend(o.keys())
            stack.extend(o.values())
        elif isinstance(o, (list, tuple, set, frozenset, collections.deque)):
            stack.extend(o)
        elif isinstance(o, (types.FunctionType, types.MethodType)):
            fn = getattr(o, "__func__", o)
            stack.extend(fn.__defaults__ or ())
            stack.extend(c.cell_contents for c in (fn.__closure__ or ()) if _has_contents(c))
            if isinstance(o, types.MethodType):
                stack.append(o.__self__)
            continue
        if isinstance(o, (str, bytes, int, float, complex)):
            continue
        d = getattr(o, "__dict__", None)
        if isinstance(d, dict):
            stack.append(d)
        for cls in type(o).__mro__:
            for name in getattr(cls, "__slots__", ()):
                if name not in ("__dict__", "__weakref__") and hasattr(o, name):
                    stack.append(getattr(o, name))
    return total


def _has_contents(cell) -> bool:
    try:
        cell.cell_contents
    except ValueError:
        return False
    return True


def bytes_each(items, sample: int = 200) -> float | None:
    """Mean :func:`deep_size` of the last ``sample`` items (plus the 8-byte pointer a list keeps for each)."""
    items = list(items)[-sample:]
    if not items:
        return None
    return deep_size(items) / len(items) - sys.getsizeof([]) / len(items)


def heap_census(wp_array=None) -> tuple[int, collections.Counter, int, int, int]:
    """(objects the garbage collector tracks, their count by type name, live Warp arrays, those that own their
    memory, the bytes they own)."""
    wp_array = wp_array if wp_array is not None else _warp_array_type()
    objs = gc.get_objects()
    by_type = collections.Counter(type(o).__name__ for o in objs)
    n_wp, n_own, wp_bytes = 0, 0, 0
    if wp_array is not None:
        for o in objs:
            if isinstance(o, wp_array):
                n_wp += 1
                if o.deleter is not None:
                    n_own += 1
                    wp_bytes += int(o.capacity)
    n = len(objs)
    del objs
    return n, by_type, n_wp, n_own, wp_bytes


def growth(samples: list[dict], warmup: int) -> dict:
    """RSS growth from the first sample at or after ``warmup`` frames to the last frame sample."""
    frame_samples = [s for s in samples if s["frame"] is not None and not s["tag"]]
    after = [s for s in frame_samples if s["frame"] >= warmup]
    if len(after) < 2:
        return {"warmup_frame": None, "growth_pct": None, "bytes_per_frame": None}
    a, b = after[0], after[-1]
    frames = b["frame"] - a["frame"]
    x = np.array([s["frame"] for s in after], float)
    y = np.array([s["rss_mb"] for s in after], float) * 1e6
    slope = float(np.polyfit(x, y, 1)[0]) if len(after) >= 3 else (b["rss_mb"] - a["rss_mb"]) * 1e6 / frames
    return {"warmup_frame": a["frame"], "rss_at_warmup_mb": a["rss_mb"], "rss_last_mb": b["rss_mb"],
            "growth_pct": 100.0 * (b["rss_mb"] - a["rss_mb"]) / a["rss_mb"],
            "bytes_per_frame": (b["rss_mb"] - a["rss_mb"]) * 1e6 / frames, "bytes_per_frame_fit": slope}


# ----------------------------------------------------------------------------------------------- frames
def synthetic_frames(num_frames: int, width: int, height: int, seed: int = 0):
    """``(spec, iterator of mgso.io.Frame)``: the synthetic room rendered frame by frame, 8-bit quantised."""
    from mgso import synthetic
    from mgso.io.sequence import Frame

    spec = synthetic.SequenceSpec(seed=seed, num_frames=num_frames, width=width, height=height)

    def gen():
        for f in synthetic.iter_frames(spec):
            rgb = np.round(np.clip(f.image, 0.0, 1.0) * 255.0).astype(np.float32) / 255.0
            gray = (rgb @ GRAY_WEIGHTS) * 255.0
            yield Frame(f.index, f.timestamp, gray, None, source=f"synthetic frame {f.index}", rgb=rgb)

    return spec, gen()


def path_check(spec) -> dict:
    """Per-frame camera motion over the whole path (the path is periodic: it must not stall or jump)."""
    traj = spec.trajectory()
    c = traj.cam_to_world[:, :3, 3]
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    R = traj.cam_to_world[:, :3, :3]
    cos = (np.einsum("nij,nij->n", R[1:], R[:-1]) - 1.0) / 2.0
    turn = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    last = slice(max(len(step) - 314, 0), None)
    return {"frames": len(c), "duration_s": float(traj.timestamps[-1] - traj.timestamps[0]),
            "step_cm": [float(step.min() * 100), float(step.max() * 100)],
            "turn_deg": [float(turn.min()), float(turn.max())],
            "step_cm_mean_first_loop": float(step[:314].mean() * 100),
            "step_cm_mean_last_loop": float(step[last].mean() * 100),
            "timestamps_unique_at_6_decimals": len({f"{t:.6f}" for t in traj.timestamps}) == len(c)}


# ------------------------------------------------------------------------------------------- containers
def _cloud_figures(cloud) -> dict:
    """The window's marginalised point cloud (mgso.window.window.PointCloud): points and the bytes of the chunks
    not yet folded in and of the folded arrays."""
    chunks = getattr(cloud, "_chunks", [])
    chunk_bytes = sum(sum(a.nbytes for a in (c.positions, c.colors, c.point_ids, c.host_keyframe_ids))
                      for c in chunks)
    base = getattr(cloud, "_base", None)
    base_bytes = sum(a.nbytes for a in base) if base else 0
    return {"points": len(cloud), "chunks": len(chunks), "bytes": chunk_bytes + base_bytes,
            "folded_bytes": base_bytes}


def odometry_containers(odo, results=None) -> dict:
    out = {"frames": len(odo.frames), "frame_record_bytes": bytes_each(odo.frames),
           "keyframes": len(odo.keyframes), "keyframe_record_bytes": bytes_each(odo.keyframes.values()),
           "segments": odo.segment + 1, "segment_steps": len(getattr(odo, "_segment_steps", ())),
           "window_keyframes": odo.window.num_keyframes, "active_points": odo.window.active.n,
           "immature_points": odo.window.immature.n, "cloud": _cloud_figures(odo.window.cloud)}
    if results is not None:
        out["frame_results"] = len(results)
        out["frame_result_bytes"] = bytes_each(results)
    return out


def system_containers(system, dso=None) -> dict:
    mapper, log_ = system.mapper, system.frame_log
    views = list(mapper.views)
    cloud = system.cloud
    out = {"frame_log": len(log_),
           "frame_log_bytes_per_frame": deep_size(log_) / len(log_) if len(log_) else None,
           "cloud_points": len(cloud),
           "cloud_bytes": sum(a.nbytes for lst in (cloud.points, cloud.colors, cloud.hosts) for a in lst),
           "views": len(views), "view_bytes": bytes_each(views, sample=20),
           "view_image_bytes": int(views[-1].image.nbytes) if views else None,
           "gaussians": int(mapper.gmap.n), "gaussian_capacity": int(mapper.gmap.capacity),
           "seed_results": len(mapper.stats.seed_results), "mapper_steps": int(mapper.stats.steps),
           "queue": mapper.queue.qsize()}
    if dso is not None:
        out["odometry"] = odometry_containers(dso)
        out["odometry"]["pending_events"] = len(getattr(system.odometry, "_events", getattr(dso, "outbox", ())))
    return out


class Sampler:
    """Records RSS, the containers and a heap census at chosen frames."""

    def __init__(self, label: str, containers):
        self.label, self.containers = label, containers
        self.samples: list[dict] = []
        self.t0 = time.perf_counter()
        self.census: dict[str, collections.Counter] = {}
        self.wp_array = _warp_array_type()

    def sample(self, frame: int | None, tag: str = "") -> None:
        t = time.perf_counter()
        rss = rss_bytes()
        n_obj, by_type, n_wp, n_own, wp_bytes = heap_census(self.wp_array)
        s = {"frame": frame, "tag": tag, "rss_mb": rss / 1e6, "wall_s": t - self.t0, "malloc": malloc_info(),
             "gc_objects": n_obj, "warp_arrays": n_wp, "warp_arrays_owning": n_own, "warp_array_mb": wp_bytes / 1e6,
             **self.containers()}
        s["sample_s"] = time.perf_counter() - t
        self.samples.append(s)
        self.census[tag or str(frame)] = by_type
        print(f"memory.py {self.label}: {tag or f'frame {frame}'}: RSS {rss / 1e6:.1f} MB, {n_obj} objects, "
              f"{n_wp} Warp arrays ({wp_bytes / 1e6:.1f} MB), {s['wall_s']:.0f} s", file=sys.stderr, flush=True)

    def type_growth(self, since: str, until: str, top: int = 12) -> dict:
        a, b = self.census.get(since), self.census.get(until)
        if a is None or b is None:
            return {}
        d = {k: b[k] - a.get(k, 0) for k in b}
        return dict(sorted(((k, v) for k, v in d.items() if v), key=lambda kv: -abs(kv[1]))[:top])


def _sampled(frames, every: int, sampler: Sampler):
    """Pass the frames on, sampling before frame ``k * every`` (after ``k * every`` frames were processed and
    their messages applied) and once more when the source is exhausted."""
    n = 0
    for f in frames:
        if n and n % every == 0:
            sampler.sample(n)
        yield f
        n += 1
    sampler.sample(n)  # the source is exhausted: every frame has been processed


# ------------------------------------------------------------------------------------------------- parts
def _config(args):
    from mgso.config import load_config

    over = [f"runtime.device={args.device}", "window.backend=bundle", "system.mode=deterministic",
            f"mapping.mapper.iterations_per_keyframe={args.iterations_per_keyframe}",
            f"mapping.mapper.final_iterations={args.final_iterations}", f"mapping.capacity={args.capacity}",
            *args.set]
    return load_config(None, over)


def run_odometry(args) -> dict:
    from mgso.odometry import FrameStatus, Odometry, geometry_for
    from mgso_kernels import runtime

    cfg = _config(args)
    device = runtime.init(cfg.runtime.device, threads=cfg.runtime.threads, blas_threads=cfg.runtime.blas_threads)
    spec, frames = synthetic_frames(args.frames, args.width, args.height, args.seed)
    k = spec.intrinsics
    geo = geometry_for(k.width, k.height, k.fx, k.fy, k.cx, k.cy, cfg)
    odo = Odometry(geo, cfg, device=device)
    results = []  # what the tracking stage keeps of a frame for its figures (frames.csv is written as it goes)
    sampler = Sampler("odometry", lambda: odometry_containers(odo, results))
    sampler.sample(0, "start")
    t0 = time.perf_counter()
    n = 0
    for frame in _sampled(frames, args.every, sampler):
        r = odo.process(frame)
        results.append((r.status, r.time_track_s, r.time_map_s))
        n += 1
    loop_s = time.perf_counter() - t0
    odo.finish()
    traj = odo.trajectory()
    kfs = odo.keyframe_trajectory()
    pts, _ = odo.point_cloud_world()
    sampler.sample(None, "after finish and outputs' arrays")
    return {"frames": n, "frames_with_pose": len(traj), "keyframes": len(kfs), "points": int(len(pts)),
            "segments": odo.segment + 1, "lost": odo.num_lost,
            "statuses": dict(collections.Counter(f.status.value for f in odo.frames)),
            "tracked": int(sum(f.status == FrameStatus.TRACKED for f in odo.frames)),
            "image_size": [geo.width, geo.height], "loop_s": loop_s, "fps": n / loop_s if loop_s else None,
            "samples": sampler.samples, "growth": growth(sampler.samples, args.warmup),
            "types_grown_after_warmup": sampler.type_growth(str(_first_at(sampler, args.warmup)), str(n))}


def _dso_for_system(k, cfg, device):
    """``(the system's odometry, the DSO odometry inside it)``: one object, :class:`mgso.odometry.Odometry` speaking
    the mapper's messages itself (``emit_messages``), as the full stage makes it."""
    from mgso.odometry import Odometry

    odo = Odometry.for_camera(k, cfg, device=device, emit_messages=True)
    return odo, odo


def run_system_part(args) -> dict:
    from mgso.system import System
    from mgso_kernels import runtime

    cfg = _config(args)
    device = runtime.init(cfg.runtime.device, threads=cfg.runtime.threads, blas_threads=cfg.runtime.blas_threads)
    spec, frames = synthetic_frames(args.frames, args.width, args.height, args.seed)
    k = spec.intrinsics
    odo_device = runtime.resolve_device(cfg.runtime.odometry_device) if cfg.runtime.odometry_device else device
    odometry, dso = _dso_for_system(k, cfg, odo_device)
    system = System(odometry, cfg, device=device)
    sampler = Sampler("system", lambda: system_containers(system, dso))
    sampler.sample(0, "start")
    t0 = time.perf_counter()
    result = system.run(_sampled(frames, args.every, sampler), info={"synthetic": spec.to_dict()})
    wall = time.perf_counter() - t0
    sampler.sample(result.frames_processed, "after finish")
    st = result.mapper
    return {"frames": result.frames_processed, "frames_without_pose": result.frames_lost,
            "keyframes": result.keyframes, "views": len(system.mapper.views), "gaussians": int(system.mapper.gmap.n),
            "mapper_steps": st.steps, "gaussians_seeded": st.gaussians_seeded,
            "image_size": [dso.geometry.width, dso.geometry.height], "wall_s": wall,
            "loop_s": result.loop_seconds, "frame_loop_fps": result.frame_loop_fps,
            "tracking_fps": result.tracking_fps, "mapping_train_s": st.train_seconds, "seed_s": st.seed_seconds,
            "samples": sampler.samples, "growth": growth(sampler.samples, args.warmup),
            "types_grown_after_warmup": sampler.type_growth(str(_first_at(sampler, args.warmup)),
                                                            str(result.frames_processed))}


def _first_at(sampler: Sampler, warmup: int):
    for s in sampler.samples:
        if s["frame"] is not None and s["frame"] >= warmup and not s["tag"]:
            return s["frame"]
    return None


# -------------------------------------------------------------------------------------------------- main
def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=10000, help="frames of the synthetic sequence (default 10000)")
    ap.add_argument("--every", type=int, default=1000, help="sample every N frames (default 1000)")
    ap.add_argument("--warmup", type=int, default=None, help="growth is measured from the first sample at or after "
                                                             "this many frames (default: --every)")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--seed", type=int, default=0, help="the synthetic room's seed")
    ap.add_argument("--what", default="both", choices=["odometry", "system", "both"])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iterations-per-keyframe", type=int, default=5, help="system: training steps a keyframe")
    ap.add_argument("--final-iterations", type=int, default=0, help="system: final refinement steps")
    ap.add_argument("--capacity", type=int, default=100_000, help="system: most Gaussians the map holds")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="a config override (repeatable)")
    ap.add_argument("--one", choices=["odometry", "system"], help=argparse.SUPPRESS)
    return ap


def _check(ap, args) -> None:
    if args.frames < 1:
        ap.error(f"--frames must be >= 1, got {args.frames}")
    if args.every < 1:
        ap.error(f"--every must be >= 1, got {args.every}")
    if args.width < 16 or args.height < 16:
        ap.error(f"--width/--height must be at least 16x16, got {args.width}x{args.height}")
    if args.iterations_per_keyframe < 0 or args.final_iterations < 0 or args.capacity < 1:
        ap.error("--iterations-per-keyframe and --final-iterations must be >= 0, --capacity >= 1")
    if args.warmup is None:
        args.warmup = args.every
    if args.warmup < 0:
        ap.error(f"--warmup must be >= 0, got {args.warmup}")


def main(argv=None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    _check(ap, args)
    if args.one:
        sys.path.insert(0, str(ROOT))
        import warp as wp

        wp.config.quiet = True
        logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
        from mgso.config import ConfigError

        try:
            fig = run_odometry(args) if args.one == "odometry" else run_system_part(args)
        except ConfigError as exc:
            print(f"profiles/memory.py: {exc}", file=sys.stderr)
            return 2
        print(json.dumps(fig))
        return 0
    sys.path.insert(0, str(ROOT))
    from mgso import synthetic
    from mgso.config import ConfigError

    try:  # a bad --set is reported once, before any part starts
        _config(args)
    except ConfigError as exc:
        print(f"profiles/memory.py: {exc}", file=sys.stderr)
        return 2
    spec = synthetic.SequenceSpec(seed=args.seed, num_frames=args.frames, width=args.width, height=args.height)
    out = {"profile": "memory", "machine": platform.node(), "cpu_count": os.cpu_count(),
           "load_avg_1min": os.getloadavg()[0], "rss_source": "/proc/self/statm" if
           os.path.exists("/proc/self/statm") else "psutil",
           "settings": {k: v for k, v in vars(args).items() if k != "one"}, "path": path_check(spec)}
    parts = ["odometry", "system"] if args.what == "both" else [args.what]
    passthrough = [a for a in (argv if argv is not None else sys.argv[1:])]
    for part in parts:
        t0 = time.perf_counter()
        cmd = [sys.executable, str(Path(__file__).resolve()), *passthrough, "--one", part]
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, cwd=str(ROOT))
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
        if proc.returncode != 0 or not lines:
            out[part] = {"error": f"exit status {proc.returncode} (see stderr)"}
        else:
            out[part] = json.loads(lines[-1])
        out[part]["process_s"] = time.perf_counter() - t0
    out["load_avg_1min_end"] = os.getloadavg()[0]
    print(json.dumps(out))
    return 0 if all("error" not in out[p] for p in parts) else 1


if __name__ == "__main__":
    sys.exit(main())
