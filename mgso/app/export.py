"""``mgso export RUN_DIR --format colmap|nerfstudio``: a finished run's poses and points for offline refinement.

The run's sequence is opened again (``sequence.json``'s path, or ``--input``; the frame selection and undistortion of
the run's ``config.yaml``), the keyframes of ``keyframes.txt`` (or, with ``all_frames``, every frame of
``trajectory.txt``) are found among its frames by timestamp, and their **undistorted** RGB images (the output camera,
the images the mapper trained on) are written as PNGs beside the model:

- ``colmap``: ``images/`` and ``sparse/0/`` with ``cameras.txt`` (one PINHOLE camera), ``images.txt`` (world-to-camera
  poses, an empty 2D-points line each) and ``points3D.txt`` (DSO's points, error 0, empty tracks), and the same model
  in COLMAP's binary files (``*.bin``: gsplat's reader, pycolmap's ``SceneManager``, stops at the first empty line of
  a text ``images.txt``, and reads the binary files first).
- ``nerfstudio``: ``images/``, ``transforms.json`` (OpenGL camera axes) and ``sparse_pc.ply`` (DSO's points).

Pixel centres: mgso puts pixel (0, 0)'s centre at (0, 0); COLMAP, nerfstudio and gsplat at (0.5, 0.5), so the
exported ``cx, cy`` are mgso's plus 0.5. docs/export.md has every convention and transform.
"""

from __future__ import annotations

import json
import logging
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .writer import RunWriter

log = logging.getLogger(__name__)

__all__ = ["FORMATS", "ExportError", "ExportResult", "export_run", "colmap_pose", "nerfstudio_pose",
           "OPENCV_TO_OPENGL"]

FORMATS = ("colmap", "nerfstudio")

#: Right-multiplying a camera-to-world pose of mgso's camera (x right, y down, z forward: OpenCV's) by this gives the
#: pose of the same camera with OpenGL's axes (x right, y up, z back), the convention of nerfstudio's transforms.json.
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])

#: COLMAP's (and nerfstudio's, gsplat's) pixel centres are at +0.5 of mgso's: ``cx_colmap = cx_mgso + 0.5``.
PIXEL_CENTRE_OFFSET = 0.5


class ExportError(Exception):
    """The run folder or its input cannot be exported; the message names the file or path and the problem."""


@dataclass
class ExportResult:
    out: Path
    fmt: str
    images: int
    points: int
    input_path: Path
    written: list[Path] = field(default_factory=list)

    def lines(self) -> list[str]:
        return [f"exported {self.images} images and {self.points} points as {self.fmt} from {self.input_path} "
                f"-> {self.out}"] + [f"wrote {p}" for p in self.written]


# --------------------------------------------------------------------------------------------------- poses
def colmap_pose(cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's image pose from mgso's camera-to-world: ``(qvec (qw, qx, qy, qz), tvec)`` of world-to-camera,
    ``X_cam = R(qvec) X_world + tvec`` (the camera axes are the same: x right, y down, z forward)."""
    from mgso.geometry import matrix_to_quat_wxyz, orthonormalize

    T = np.asarray(cam_to_world, np.float64)
    R_cw = orthonormalize(T[None, :3, :3])[0]
    R = R_cw.T
    return matrix_to_quat_wxyz(R[None])[0], -R @ T[:3, 3]


def nerfstudio_pose(cam_to_world: np.ndarray) -> np.ndarray:
    """nerfstudio's ``transform_matrix``: camera-to-world with OpenGL camera axes, ``T @ diag(1, -1, -1, 1)``."""
    return np.asarray(cam_to_world, np.float64) @ OPENCV_TO_OPENGL


# --------------------------------------------------------------------------------------------------- the run
def _run_file(run_dir: Path, name: str) -> Path:
    p = run_dir / name
    if not p.is_file():
        raise ExportError(f"{p}: not found (is {run_dir} the folder of an mgso run?)")
    return p


def _read_run(run_dir: Path):
    from mgso.config import load_config

    if not run_dir.is_dir():
        raise ExportError(f"{run_dir}: no such run folder")
    seq_json = _run_file(run_dir, "sequence.json")
    try:
        info = json.loads(seq_json.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise ExportError(f"{seq_json}: not valid JSON ({exc})") from None
    if not isinstance(info, dict) or "path" not in info:
        raise ExportError(f"{seq_json}: has no 'path' of the input sequence")
    cfg = load_config(_run_file(run_dir, "config.yaml"))
    return info, cfg


def _reader_finds(path: Path, calib_file: Path, input_cfg) -> bool:
    """Whether the dataset at ``path`` finds ``calib_file`` as its calibration by itself (a ``--calib`` file kept
    beside a video under another name than camera.txt is not found so)."""
    from mgso.io import open_sequence

    try:
        seq = open_sequence(path, config=input_cfg)
    except Exception:  # noqa: BLE001 - no calibration of its own, or no dataset: not found
        return False
    try:
        src = seq.calibration.source
        return bool(src) and Path(src).expanduser().resolve() == calib_file.resolve()
    finally:
        seq.close()


def _calibration_arg(info: dict, old_input: Path, calib: str | None, input_cfg=None) -> str | None:
    """The run's ``--calib`` file, when it had one: a calibration source that names a file the dataset's reader does
    not find by itself (one it finds, inside the folder, it finds again; a built-in default is a description), or
    the numbers themselves where the run was given them."""
    if calib is not None:
        return calib
    src = info.get("calibration_source")
    if not src:
        return None
    from mgso.io.calibration import inline_intrinsics

    if inline_intrinsics(src):      # the run's --calib was the numbers themselves
        return src
    p = Path(src)
    if not p.is_absolute() and info.get("run_cwd"):   # relative to where the run was started
        p = Path(info["run_cwd"]) / p
    folder = old_input if old_input.suffix == "" else old_input.parent
    try:
        p.relative_to(folder)
        inside = True
    except ValueError:
        inside = False
    if inside:   # the dataset's own file, found again by its reader; or a --calib file kept beside the input
        return str(p) if p.is_file() and not _reader_finds(old_input, p, input_cfg) else None
    if p.is_file():
        return str(p)
    if p.suffix.lower() in (".txt", ".yaml", ".yml", ".json"):
        raise ExportError(f"the run's calibration file {p} is gone or moved (give --calib FILE)")
    return None     # a dataset's built-in default ("TUM RGB-D freiburg1 default calibration")


def _open_input(info: dict, cfg, input_path: str | None, calib: str | None):
    from mgso.io import open_sequence

    old = Path(info["path"])
    if not old.is_absolute() and info.get("path_absolute"):   # written by runs since sequence.json had it
        old = Path(info["path_absolute"])
    path = Path(input_path).expanduser() if input_path else old
    if not path.exists():
        if input_path:
            raise ExportError(f"--input {path}: no such file or folder")
        if not path.is_absolute():
            raise ExportError(f"the run's input {path} is not found from {Path.cwd()} (a path relative to the folder "
                              "the run was started in; give --input PATH)")
        raise ExportError(f"the run's input {path} is gone or moved (give --input PATH)")
    seq = open_sequence(path, calib=_calibration_arg(info, old, calib, cfg.input), config=cfg.input)
    # the input must be the one the run saw: its output camera and frame count
    out = seq.calibration.output
    want = info.get("intrinsics") or {}
    size = list(seq.calibration.output_size)
    got = {"fx": out.fx, "fy": out.fy, "cx": out.cx, "cy": out.cy}
    if want and (list(info.get("image_size_out", size)) != size
                 or any(abs(float(want[k]) - got[k]) > 1e-6 * max(1.0, abs(got[k])) for k in got if k in want)):
        raise ExportError(f"{path}: its output camera ({size[0]}x{size[1]}, fx={got['fx']:.6g} fy={got['fy']:.6g} "
                          f"cx={got['cx']:.6g} cy={got['cy']:.6g}) is not the run's ({info.get('image_size_out')}, "
                          f"{want}): not the input of this run")
    return seq, path


def _frames_for(seq, traj, poses_file: Path) -> np.ndarray:
    """For each pose of ``traj``, the index of the sequence's frame with its timestamp."""
    ts = seq.timestamps
    gaps = np.diff(ts)
    tol = min(1e-3, 0.25 * float(gaps.min())) if len(gaps) else 1e-3
    i_traj = np.arange(len(traj))
    idx = np.full(len(traj), -1, np.int64)
    from mgso.io.trajectory import matching_time_indices

    i_pose, i_frame = matching_time_indices(traj.timestamps, ts, tol)
    idx[i_pose] = i_frame
    missing = i_traj[idx < 0]
    if len(missing):
        raise ExportError(f"{poses_file}: the pose at t={traj.timestamps[missing[0]]:.6f} matches no frame of "
                          f"{seq.path} ({len(missing)} of {len(traj)} poses do not; is it the run's input?)")
    return idx


# --------------------------------------------------------------------------------------------------- writers
def _g(x: float) -> str:
    return repr(float(x))


def _colmap_camera(cam) -> tuple[float, float, float, float]:
    return (float(cam.fx), float(cam.fy), float(cam.cx) + PIXEL_CENTRE_OFFSET, float(cam.cy) + PIXEL_CENTRE_OFFSET)


def _write_colmap(writer: RunWriter, cam, size, names, poses, pts, cols) -> None:
    w, h = size
    fx, fy, cx, cy = _colmap_camera(cam)
    writer.write_text("sparse/0/cameras.txt", "# Camera list with one line of data per camera:\n"
                      "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
                      f"1 PINHOLE {w} {h} {_g(fx)} {_g(fy)} {_g(cx)} {_g(cy)}\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(names)}, mean observations per image: 0"]
    qt = [colmap_pose(T) for T in poses]
    for i, (name, (q, t)) in enumerate(zip(names, qt), start=1):
        lines.append(f"{i} " + " ".join(_g(v) for v in (*q, *t)) + f" 1 {name}")
        lines.append("")
    writer.write_text("sparse/0/images.txt", "\n".join(lines) + "\n")
    plines = ["# 3D point list with one line of data per point:",
              "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
              f"# Number of points: {len(pts)}, mean track length: 0"]
    for i, (p, c) in enumerate(zip(pts, cols), start=1):
        plines.append(f"{i} {_g(p[0])} {_g(p[1])} {_g(p[2])} {int(c[0])} {int(c[1])} {int(c[2])} 0")
    writer.write_text("sparse/0/points3D.txt", "\n".join(plines) + "\n")

    # the same model in COLMAP's binary format (little endian; colmap/src/colmap/scene/reconstruction_io.cc)
    def cameras_bin(p: Path) -> None:
        p.write_bytes(struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, w, h) + struct.pack("<4d", fx, fy, cx, cy))

    def images_bin(p: Path) -> None:
        parts = [struct.pack("<Q", len(names))]
        for i, (name, (q, t)) in enumerate(zip(names, qt), start=1):
            parts.append(struct.pack("<i7di", i, *q, *t, 1) + name.encode("utf-8") + b"\0" + struct.pack("<Q", 0))
        p.write_bytes(b"".join(parts))

    def points_bin(p: Path) -> None:
        rec = np.zeros(len(pts), dtype=[("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("err", "<f8"),
                                        ("track", "<u8")])
        rec["id"] = np.arange(1, len(pts) + 1)
        rec["xyz"], rec["rgb"] = pts, cols
        p.write_bytes(struct.pack("<Q", len(pts)) + rec.tobytes())

    writer.write_with("sparse/0/cameras.bin", cameras_bin)
    writer.write_with("sparse/0/images.bin", images_bin)
    writer.write_with("sparse/0/points3D.bin", points_bin)


def _write_nerfstudio(writer: RunWriter, cam, size, names, poses, masks, points_ply: Path | None) -> None:
    w, h = size
    fx, fy, cx, cy = _colmap_camera(cam)
    frames = []
    for name, T, mask in zip(names, poses, masks):
        fr = {"file_path": f"images/{name}", "transform_matrix": nerfstudio_pose(T).tolist()}
        if mask is not None:
            fr["mask_path"] = f"masks/{mask}"
        frames.append(fr)
    meta = {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": int(w), "h": int(h),
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames}
    if points_ply is not None:
        meta["ply_file_path"] = "sparse_pc.ply"
        data = points_ply.read_bytes()
        writer.write_with("sparse_pc.ply", lambda p: p.write_bytes(data))
    writer.write_json("transforms.json", meta)


# --------------------------------------------------------------------------------------------------- export
def export_run(run_dir: str | Path, out_dir: str | Path | None, fmt: str, *, input_path: str | None = None,
               calib: str | None = None, all_frames: bool = False,
               progress: Callable[[int, str], object] | None = None) -> ExportResult:
    """Export the run in ``run_dir`` as ``fmt`` (:data:`FORMATS`) into ``out_dir`` (default ``run_dir/<fmt>``).

    ``input_path`` replaces the run's input path (a moved dataset), ``calib`` its calibration file; ``all_frames``
    exports every frame of ``trajectory.txt`` instead of the keyframes. ``progress(total, desc)`` returns a bar with
    ``update()`` and ``close()``. Raises :class:`ExportError` (one line) for a run or input that cannot be used, and
    :class:`~mgso.app.writer.OutputError` for a bad ``out_dir``.
    """
    from mgso.io.ply import read_point_cloud_ply
    from mgso.io.trajectory import read_tum

    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; known: {', '.join(FORMATS)}")
    run_dir = Path(run_dir)
    info, cfg = _read_run(run_dir)
    poses_file = _run_file(run_dir, "trajectory.txt" if all_frames else "keyframes.txt")
    if not poses_file.read_text(encoding="utf-8", errors="replace").strip():
        raise ExportError(f"{poses_file}: no poses (the run gave no frame a pose)")
    traj = read_tum(poses_file)
    points_ply = run_dir / "points.ply"
    if points_ply.is_file():
        pts, cols, _ = read_point_cloud_ply(points_ply)
        pts = np.asarray(pts, np.float64)
        cols = np.full((len(pts), 3), 128, np.uint8) if cols is None else cols
    else:
        log.warning("%s: not found; the export has no points", points_ply)
        points_ply, pts, cols = None, np.zeros((0, 3)), np.zeros((0, 3), np.uint8)

    out = Path(out_dir) if out_dir is not None else run_dir / fmt
    if out.resolve() == run_dir.resolve():
        raise ExportError(f"{out}: is the run folder itself; give --out another folder")
    seq, in_path = _open_input(info, cfg, input_path, calib)
    try:
        idx = _frames_for(seq, traj, poses_file)
        writer = RunWriter(out)       # after the checks: a run that cannot be exported leaves no folder behind
        cam, size = seq.calibration.output, tuple(int(v) for v in seq.calibration.output_size)
        names, masks = [], []
        bar = progress(len(idx), "export") if progress is not None else None
        for i in idx:
            frame = seq.load(int(i))
            name = f"frame_{int(i):06d}.png"
            writer.write_image(f"images/{name}", frame.rgb)
            mask = None
            if fmt == "nerfstudio" and frame.valid is not None and not frame.valid.all():
                mask = name
                writer.write_image(f"masks/{name}", frame.valid.astype(np.uint8) * 255)
            names.append(name)
            masks.append(mask)
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
    finally:
        seq.close()
    if fmt == "colmap":
        _write_colmap(writer, cam, size, names, traj.cam_to_world, pts, cols)
    else:
        _write_nerfstudio(writer, cam, size, names, traj.cam_to_world, masks, points_ply)
    return ExportResult(out=writer.out, fmt=fmt, images=len(names), points=len(pts), input_path=in_path,
                        written=writer.written_paths())
