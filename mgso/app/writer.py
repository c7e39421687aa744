"""The run writer: the one owner of a run's output folder, from its first file to its last.

Every command that writes a folder (``mgso run`` in each stage, ``mgso demo``, ``mgso fit``) writes it through a
:class:`RunWriter`, and every way a run can end (the last frame, an error, Ctrl-C, SIGTERM, an unreadable frame)
ends in the same calls, so that what was done is on disk:

- the folder is checked before any work (:func:`prepare_out_dir`): a path that is a file, a parent that is a file, a
  folder that cannot be made or written give one :class:`OutputError` line naming the path and the problem;
- every file is written atomically (a temporary name in the folder, then ``os.replace``): a run killed while
  writing leaves the previous complete version or none, never half a ``metrics.json``;
- ``frames.csv`` grows a row per frame as the frames finish (flushed), so that even a run killed with SIGKILL leaves
  the tracking-time pose and status of every frame it processed;
- :attr:`RunWriter.written` lists what was written, in order (the summary the CLI prints).
"""

from __future__ import annotations

import csv
import json
import logging
import os
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

__all__ = ["OutputError", "prepare_out_dir", "RunWriter", "FrameLogWriter", "FRAME_COLUMNS"]

log = logging.getLogger(__name__)


class OutputError(Exception):
    """The output folder cannot be used; the message names the path and the problem (one line)."""


def _read_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


# read once, before any thread starts: os.umask can only be read by setting it
_UMASK = _read_umask()


@contextmanager
def atomic_path(dest: Path) -> Iterator[Path]:
    """Yields a temporary path beside ``dest`` (same suffix); when the block ends without an error it replaces
    ``dest`` (``os.replace``: a reader sees the old file or the new one, never half of one)."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.stem}-", suffix=dest.suffix, dir=dest.parent)
    try:
        # mkstemp makes the file 0600; the output gets the user's umask like any other file they write
        os.fchmod(fd, 0o666 & ~_UMASK)
    finally:
        os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, dest)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _reason(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def check_out_dir(path: str | os.PathLike) -> Path:
    """What :func:`prepare_out_dir` refuses, found without making anything: called before any work (a sequence that
    then fails to open leaves no folder behind). Raises :class:`OutputError`; :func:`prepare_out_dir` still checks
    by writing when the folder is made."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is a file, not a folder (give --out a folder)")
    anc = out if out.exists() else out.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if anc.exists() and not anc.is_dir():
        raise OutputError(f"{out}: cannot make the folder: {anc} is a file")
    if anc.exists() and not os.access(anc, os.W_OK | os.X_OK):
        what = "cannot write into the folder" if anc == out else "cannot make the folder"
        raise OutputError(f"{out}: {what}: Permission denied")
    return out


def prepare_out_dir(path: str | os.PathLike) -> Path:
    """Make ``path`` a usable output folder (created with its parents) or raise :class:`OutputError`: it exists as a
    file, one of its parents is a file, it cannot be created, or nothing can be written into it."""
    out = check_out_dir(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot make the folder: {_reason(exc)}") from None
    try:
        fd, probe = tempfile.mkstemp(prefix=".mgso-write-test-", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"{out}: cannot write into the folder: {_reason(exc)}") from None
    return out


#: Columns of ``frames.csv`` (docs/mgso.md): one row per processed frame, written as the frame finishes. The pose is
#: the frame's pose at tracking time (camera-to-world, TUM order; empty without one); the final poses, refined by the
#: window, are in ``trajectory.txt``.
FRAME_COLUMNS = ("index", "timestamp", "status", "segment", "keyframe", "keyframe_reason", "rmse", "inlier_ratio",
                 "hypotheses", "track_ms", "map_ms", "tx", "ty", "tz", "qx", "qy", "qz", "qw")


class FrameLogWriter:
    """``frames.csv``, a row per frame appended and flushed as the frame finishes (a frame that could not be read
    gets a row too: :func:`unreadable_row`)."""

    def __init__(self, path: Path):
        self.path = path
        self._fh = open(path, "w", newline="", encoding="utf-8")
        self._csv = csv.writer(self._fh)
        self._csv.writerow(FRAME_COLUMNS)
        self._fh.flush()
        self._lock = threading.Lock()   # rows come from the frame loop and from the reader's thread (unreadable)

    def add(self, row: dict) -> None:
        with self._lock:
            if self._fh.closed:
                return
            self._csv.writerow([_cell(row.get(c)) for c in FRAME_COLUMNS])
            self._fh.flush()

    def close(self) -> None:
        with self._lock:
            if not self._fh.closed:
                self._fh.close()


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.6f}" if np.isfinite(v) else ""
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return str(v)


class RunWriter:
    """Owns one run's output folder (see the module doc). ``out_dir`` is checked and created here."""

    def __init__(self, out_dir: str | os.PathLike):
        self.out = prepare_out_dir(out_dir)
        self.written: list[str] = []
        self.frame_log: FrameLogWriter | None = None

    # ------------------------------------------------------------------------------------------ files
    def path(self, name: str) -> Path:
        return self.out / name

    def _note(self, name: str) -> None:
        if "/" in name:  # a file of a folder (renders/000019.png): the folder is what the summary names
            name = name.split("/", 1)[0] + "/"
        if name not in self.written:
            self.written.append(name)

    @contextmanager
    def atomic(self, name: str) -> Iterator[Path]:
        """Yields a temporary path in the folder; when the block ends without an error it becomes ``name``. The
        suffix is kept (writers that pick the format from it, such as OpenCV's, see the right one)."""
        with atomic_path(self.out / name) as tmp:
            yield tmp
        self._note(name)

    def write_with(self, name: str, fn: Callable[[Path], Any]) -> Path:
        """``fn(path)`` writes the file (any writer that takes a path); atomically renamed to ``name``."""
        with self.atomic(name) as tmp:
            fn(tmp)
        return self.out / name

    def write_text(self, name: str, text: str) -> Path:
        return self.write_with(name, lambda p: p.write_text(text, encoding="utf-8"))

    def write_json(self, name: str, obj: Any) -> Path:
        return self.write_text(name, json.dumps(obj, indent=2, default=_json_default, allow_nan=False) + "\n")

    # ------------------------------------------------------------------------------------------ run files
    def write_config(self, cfg) -> Path:
        from mgso.config import save_config

        return self.write_with("config.yaml", lambda p: save_config(cfg, p))

    def write_sequence(self, seq) -> None:
        """``sequence.json`` (what ``mgso info`` says about the input) and, when there is one, ``groundtruth.txt``."""
        from mgso.io.trajectory import write_tum

        info = dict(seq.describe())
        # where relative paths in it start from, so that the input is found from anywhere (mgso export)
        # (a live source's path is a device or a URL: kept as it is)
        info["path_absolute"] = str(seq.path) if info.get("live") else str(Path(seq.path).resolve())
        info["run_cwd"] = os.getcwd()
        self.write_json("sequence.json", info)
        if seq.groundtruth is not None:
            self.write_with("groundtruth.txt", lambda p: write_tum(p, seq.groundtruth))

    def write_trajectories(self, traj, keyframes, fmt: str = "tum", *, name: str = "trajectory") -> None:
        """``trajectory.txt`` and ``keyframes.txt`` in TUM (timestamps included); with ``fmt == "kitti"`` also
        ``<name>_kitti.txt`` and ``keyframes_kitti.txt`` (3x4 rows, KITTI's devkit format)."""
        from mgso.io.trajectory import write_kitti, write_tum

        self.write_with(f"{name}.txt", lambda p: write_tum(p, traj))
        if keyframes is not None:
            self.write_with("keyframes.txt", lambda p: write_tum(p, keyframes))
        if fmt == "kitti":
            self.write_with(f"{name}_kitti.txt", lambda p: write_kitti(p, traj))
            if keyframes is not None:
                self.write_with("keyframes_kitti.txt", lambda p: write_kitti(p, keyframes))

    def write_points(self, points, colors, extra=None, name: str = "points.ply") -> Path:
        from mgso.io.ply import write_point_cloud_ply

        return self.write_with(name, lambda p: write_point_cloud_ply(p, points, colors, extra=extra))

    def write_gaussians(self, arrays, name: str = "map.ply") -> Path:
        from mgso.io.ply import write_gaussians_ply

        return self.write_with(name, lambda p: write_gaussians_ply(p, arrays))

    def write_image(self, name: str, rgb: np.ndarray) -> Path:
        """An RGB float image in [0, 1] (or uint8) as an 8-bit PNG."""
        import cv2

        img = np.asarray(rgb)
        if img.dtype != np.uint8:
            img = np.clip(np.round(np.asarray(img, np.float64) * 255.0), 0, 255).astype(np.uint8)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)

        def write(p: Path) -> None:
            if not cv2.imwrite(str(p), img):
                raise OSError(f"{p}: could not write the PNG")

        return self.write_with(name, write)

    def write_trajectory_plot(self, ate, reference, keyframe_timestamps=None, title: str = "") -> Path | None:
        """``trajectory.png``: the Sim(3)-aligned trajectory of ``ate`` over ``reference``, coloured by error
        (:func:`mgso.eval.plot_trajectory`); ``None`` (logged) without matplotlib."""
        try:
            from mgso.eval import plot_trajectory
        except ImportError as exc:
            log.warning("no trajectory plot: %s", exc)
            return None
        return self.write_with("trajectory.png", lambda p: plot_trajectory(
            p, ate, reference=reference, keyframe_timestamps=keyframe_timestamps, title=title))

    def write_metrics(self, **kwargs) -> Path:
        """``metrics.json`` from :func:`mgso.eval.metrics_report` (``ate=``, ``rpe=``, ``renders=``, ``extra=``)."""
        from mgso.eval.report import metrics_report

        return self.write_json("metrics.json", metrics_report(**kwargs))

    def open_frame_log(self) -> FrameLogWriter:
        """``frames.csv``, written row by row (see :data:`FRAME_COLUMNS`)."""
        if self.frame_log is None:
            self.frame_log = FrameLogWriter(self.out / "frames.csv")
            self._note("frames.csv")
        return self.frame_log

    def close(self) -> None:
        if self.frame_log is not None:
            self.frame_log.close()

    def written_paths(self) -> list[Path]:
        return [self.out / n for n in self.written]


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


def pose_columns(cam_to_world) -> dict:
    """The ``tx .. qw`` cells of a pose (camera-to-world 4x4), empty without one."""
    if cam_to_world is None:
        return {}
    from mgso.geometry import matrix_to_quat_xyzw, orthonormalize

    T = np.asarray(cam_to_world, np.float64)
    q = matrix_to_quat_xyzw(orthonormalize(T[None, :3, :3]))[0]
    return {"tx": T[0, 3], "ty": T[1, 3], "tz": T[2, 3], "qx": q[0], "qy": q[1], "qz": q[2], "qw": q[3]}


def frame_row(r) -> dict:
    """A ``frames.csv`` row from what an odometry says about a frame: a :class:`mgso.odometry.FrameResult` (DSO,
    with its tracking figures) or any object with ``index``, ``timestamp``, ``status``, ``cam_to_world``."""
    status = getattr(r, "status", "")
    row = {"index": r.index, "timestamp": float(r.timestamp), "status": getattr(status, "value", status),
           "segment": getattr(r, "segment", None),
           "keyframe_reason": getattr(r, "keyframe_reason", "") or ""}
    # the keyframe id, -1 for other frames; empty when the frame asked for a keyframe and the answer comes later (DSO's
    # first frame, made a keyframe when the initialiser succeeds; with the odometry's mapping thread, which makes
    # only the newest waiting frame a keyframe): keyframes.txt lists the keyframes made
    kf = getattr(r, "keyframe_id", None)
    if getattr(r, "is_keyframe", False) and (kf is None or kf < 0):
        row["keyframe"] = ""
    else:
        row["keyframe"] = -1 if kf is None else kf
    tr = getattr(r, "track", None)
    if tr is not None:
        row.update(rmse=float(tr.rmse0), inlier_ratio=float(tr.inlier_ratio), hypotheses=int(tr.hypotheses_tried))
    if hasattr(r, "time_track_s"):
        row.update(track_ms=r.time_track_s * 1000.0, map_ms=r.time_map_s * 1000.0)
    elif getattr(r, "seconds", 0):
        row["track_ms"] = r.seconds * 1000.0
    row.update(pose_columns(getattr(r, "cam_to_world", None)))
    return row


def unreadable_row(index: int, timestamp: float | None) -> dict:
    return {"index": index, "timestamp": timestamp, "status": "unreadable"}

