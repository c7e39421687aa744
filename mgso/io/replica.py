"""Replica as NICE-SLAM renders it.

``results/frame000000.jpg ...``, ``results/depth000000.png ...`` (16 bit, ``scale`` units per metre, 6553.5 by
default), ``traj.txt`` (one 4x4 camera-to-world a row, 16 numbers, OpenCV camera axes: NICE-SLAM's reader flips the
y and z columns to reach its own OpenGL-style axes). Intrinsics: ``calib=``, else ``cam_params.json`` in the scene
folder or its parent (as in the release), else NICE-SLAM's Replica defaults (1200x680, fx = fy = 600, cx = 599.5,
cy = 339.5; configs/Replica/replica.yaml of github cvg/nice-slam). No timestamps: frame index / ``InputConfig.fps``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from ..camera import CalibrationError, CameraSpec, OutputSpec, PinholeCamera
from ..config import InputConfig
from .calibration import CalibrationFormat, register_calibration_format
from .common import (HOW_TO_CALIBRATE, CalibArg, find_photometric, load_groundtruth, make_calibration,
                     resolve_camera_spec)
from .errors import DatasetError, as_dataset_errors
from .images import list_images, read_first_image, read_image
from .sequence import Sequence

__all__ = ["ReplicaSequence", "read_replica_traj", "read_replica_cam_params", "REPLICA_NICE_SLAM"]

# NICE-SLAM's Replica renders: configs/Replica/replica.yaml of github cvg/nice-slam (H 680, W 1200, fx = fy = 600,
# cx 599.5, cy 339.5, png_depth_scale 6553.5); the same numbers as the release's cam_params.json.
REPLICA_NICE_SLAM = {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}


def read_replica_cam_params(path: str | Path) -> tuple[CameraSpec, float]:
    """Replica ``cam_params.json``: ``{"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}`` (``scale`` or
    ``png_depth_scale``: depth PNG units per metre). Returns the pinhole spec and the depth scale."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: cam_params.json not found")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: not valid JSON: {exc}") from None
    cam = data.get("camera", data) if isinstance(data, dict) else None
    if not isinstance(cam, dict):
        raise CalibrationError(f"{path}: expected {{'camera': {{w, h, fx, fy, cx, cy}}}}")
    missing = [k for k in ("w", "h", "fx", "fy", "cx", "cy") if k not in cam]
    if missing:
        raise CalibrationError(f"{path}: missing {missing} in the camera entry")
    try:
        model = PinholeCamera(float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]),
                              int(cam["w"]), int(cam["h"]))
        scale = float(cam.get("scale", cam.get("png_depth_scale", REPLICA_NICE_SLAM["scale"])))
    except (TypeError, ValueError, CalibrationError) as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    return CameraSpec(model, OutputSpec(mode="none"), str(path)), scale


def read_replica_traj(path: str | Path) -> np.ndarray:
    """``traj.txt``: ``(N, 4, 4)`` camera-to-world, one row of 16 numbers a pose."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: trajectory not found")
    poses = []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for n, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            if len(parts) != 16:
                raise DatasetError(f"{path}:{n}: expected 16 numbers (a 4x4 camera-to-world), got {len(parts)}")
            try:
                T = np.array([float(p) for p in parts]).reshape(4, 4)
            except ValueError:
                raise DatasetError(f"{path}:{n}: not a number in {s[:80]!r}") from None
            if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
                raise DatasetError(f"{path}:{n}: not a rigid transform (non-finite or last row not 0 0 0 1)")
            poses.append(T)
    if not poses:
        raise DatasetError(f"{path}: no poses")
    return np.asarray(poses)


class ReplicaSequence(Sequence):
    """A NICE-SLAM Replica scene folder (``results/`` and ``traj.txt``)."""

    layout = "replica"
    looked_for = "Replica (NICE-SLAM): results/frame*.jpg"

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return (path / "results").is_dir() and any(
            re.fullmatch(r"frame.*\.(jpg|jpeg|png)", p.name) for p in (path / "results").iterdir())

    def __init__(self, path: str | Path, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth: str | Path | None = None):
        folder = Path(path)
        config = config or InputConfig()
        results = folder / "results"
        self._files = list_images(results, r"frame.*\.(jpg|jpeg|png)") if results.is_dir() else []
        if not self._files:
            raise DatasetError(f"{results}: no frame*.jpg images (a NICE-SLAM Replica scene has results/"
                               "frame000000.jpg ...)")
        n = len(self._files)
        self._depth_files = list_images(results, r"depth.*\.png")
        if self._depth_files and len(self._depth_files) != n:
            raise DatasetError(f"{results}: {len(self._depth_files)} depth images for {n} colour images")
        first, first_path = read_first_image(self._files)
        size = (first.shape[1], first.shape[0])
        self.depth_scale = REPLICA_NICE_SLAM["scale"]
        params = next((p for p in (folder / "cam_params.json", folder.resolve().parent / "cam_params.json")
                       if p.is_file()), None)
        if calib is not None:
            spec = resolve_camera_spec(calib, size)
        elif params is not None:
            with as_dataset_errors():
                spec, self.depth_scale = read_replica_cam_params(params)
        else:
            d = REPLICA_NICE_SLAM
            if size != (d["w"], d["h"]):
                raise DatasetError(f"{folder}: images are {size[0]}x{size[1]}, not NICE-SLAM's {d['w']}x{d['h']}, "
                                   f"and there is no cam_params.json; {HOW_TO_CALIBRATE}")
            spec = CameraSpec(PinholeCamera(d["fx"], d["fy"], d["cx"], d["cy"], d["w"], d["h"]),
                              OutputSpec(mode="none"), "NICE-SLAM Replica default intrinsics")
        calibration = make_calibration(spec, config, find_photometric(folder, size), image_size=size,
                                       images=str(first_path))

        ts = np.arange(n, dtype=np.float64) / config.fps
        gt, gt_src = None, ""
        traj = folder / "traj.txt"
        if groundtruth is not None:
            gt, gt_src = load_groundtruth(Path(groundtruth), ts, config.gt_max_dt), str(groundtruth)
        elif traj.is_file():
            poses = read_replica_traj(traj)
            if len(poses) < n:
                raise DatasetError(f"{traj}: {len(poses)} poses for {n} frames")
            gt, gt_src = poses[:n], str(traj)
        super().__init__(folder, calibration=calibration, timestamps=ts, config=config, groundtruth=gt,
                         groundtruth_source=gt_src, color=first.ndim == 3, has_depth=bool(self._depth_files),
                         name=folder.resolve().name, nominal_fps=config.fps)

    def _image_file(self, k: int) -> Path:
        return self._files[k]

    def _source(self, k: int) -> str:
        return str(self._files[k])

    def _read_depth(self, k: int) -> np.ndarray | None:
        if not self._depth_files:
            return None
        f = self._depth_files[k]
        d = read_image(f)
        if d.ndim != 2:
            raise DatasetError(f"{f}: depth must be a single-channel image")
        return d.astype(np.float32) / np.float32(self.depth_scale)


register_calibration_format(CalibrationFormat(
    "Replica cam_params.json", lambda path, text, lines: path.suffix.lower() == ".json",
    lambda path, image_size: read_replica_cam_params(path)[0]))
