"""EuRoC MAV (ASL folder layout) reader.

``mav0/cam0/data.csv`` (``#timestamp [ns],filename``), ``mav0/cam0/data/*.png``, ``mav0/cam0/sensor.yaml``
(intrinsics, distortion, resolution, ``T_BS`` = camera-to-body). Ground truth is of the *body* (IMU) frame: from
``mav0/state_groundtruth_estimate0/data.csv`` (``timestamp ns, p_RS_R xyz, q_RS wxyz, ...``) when present, else a TUM
file of body poses beside ``mav0`` (``groundtruth_body_tum.txt``); camera pose = body pose @ ``T_BS``. A file passed
as ``groundtruth=`` is taken as camera poses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import read_euroc_sensor_yaml
from ..config import InputConfig
from ..geometry import make_pose, quat_wxyz_to_matrix
from .common import CalibArg, find_photometric, load_groundtruth, make_calibration, resolve_camera_spec
from .errors import DatasetError, as_dataset_errors
from .images import check_increasing, read_image, read_table
from .sequence import Sequence, poses_at_times
from .trajectory import Trajectory

__all__ = ["EurocSequence", "euroc_root", "read_euroc_groundtruth_csv"]

BODY_GROUNDTRUTH_NAMES = ("groundtruth_body_tum.txt", "groundtruth_body.txt")


def euroc_root(path: Path) -> Path | None:
    """The folder holding ``mav0`` (``path`` itself or its parent when ``path`` is ``mav0``), or ``None``."""
    if (path / "mav0").is_dir():
        return path
    if path.name == "mav0" and path.is_dir():
        return path.parent
    return None


def _ns_to_s(value: str, path: Path, line: int) -> float:
    try:
        ns = int(value)
    except ValueError:
        raise DatasetError(f"{path}:{line}: timestamp must be an integer number of nanoseconds, got {value!r}") \
            from None
    return ns / 1e9


def read_euroc_groundtruth_csv(path: str | Path) -> Trajectory:
    """``state_groundtruth_estimate0/data.csv``: body-to-world poses (``p_RS_R``, ``q_RS`` w first)."""
    path = Path(path)
    rows = read_table(path, 8, "EuRoC ground truth (timestamp ns, p xyz, q wxyz, ...)")
    ts = np.empty(len(rows))
    vals = np.empty((len(rows), 7))
    for i, (n, parts) in enumerate(rows):
        ts[i] = _ns_to_s(parts[0], path, n)
        try:
            vals[i] = [float(p) for p in parts[1:8]]
        except ValueError:
            raise DatasetError(f"{path}:{n}: not a number in {' '.join(parts[:8])[:80]!r}") from None
    if not np.all(np.isfinite(vals)):
        raise DatasetError(f"{path}: non-finite value in the ground truth")
    check_increasing(ts, str(path), [n for n, _ in rows])
    if np.any(np.linalg.norm(vals[:, 3:7], axis=1) < 1e-6):
        raise DatasetError(f"{path}: quaternion of zero length")
    return Trajectory(ts, make_pose(quat_wxyz_to_matrix(vals[:, 3:7]), vals[:, 0:3]))


class EurocSequence(Sequence):
    """EuRoC MAV sequence (``path``: the folder holding ``mav0``, or ``mav0`` itself); camera from
    ``InputConfig.camera`` (default ``cam0``)."""

    layout = "euroc"

    def __init__(self, path: str | Path, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth: str | Path | None = None):
        path = Path(path)
        config = config or InputConfig()
        root = euroc_root(path)
        if root is None:
            raise DatasetError(f"{path}: not a EuRoC folder (no mav0/)")
        cam = config.camera or "cam0"
        cam_dir = root / "mav0" / cam
        csv = cam_dir / "data.csv"
        if not csv.is_file():
            raise DatasetError(f"{csv}: not found (EuRoC camera {cam!r}; set input.camera to cam0 or cam1)")
        rows = read_table(csv, 2, "EuRoC image list (timestamp [ns],filename)")
        ts = np.array([_ns_to_s(p[0], csv, n) for n, p in rows])
        check_increasing(ts, str(csv), [n for n, _ in rows])
        self._files = [cam_dir / "data" / p[1] for _, p in rows]
        for (n, _), f in zip(rows, self._files):
            if not f.is_file():
                raise DatasetError(f"{csv}:{n}: listed image {f} does not exist")
        first = read_image(self._files[0])
        size = (first.shape[1], first.shape[0])

        yaml_path = cam_dir / "sensor.yaml"
        self.T_BS = np.eye(4)  # camera-to-body
        if yaml_path.is_file():
            with as_dataset_errors():
                yaml_spec, self.T_BS = read_euroc_sensor_yaml(yaml_path)
        elif calib is None:
            raise DatasetError(f"{yaml_path}: not found; a EuRoC camera needs its sensor.yaml (or calib=PATH)")
        spec = resolve_camera_spec(calib, size) if calib is not None else yaml_spec
        calibration = make_calibration(spec, config, find_photometric(root, size))

        gt, gt_src = None, ""
        gt_csv = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
        body_tum = next((root / n for n in BODY_GROUNDTRUTH_NAMES if (root / n).is_file()), None)
        if groundtruth is not None:
            gt, gt_src = load_groundtruth(Path(groundtruth), ts, config.gt_max_dt), str(groundtruth)
        elif gt_csv.is_file():
            traj = read_euroc_groundtruth_csv(gt_csv)
            gt = poses_at_times(ts, traj, config.gt_max_dt) @ self.T_BS
            gt_src = f"{gt_csv} (body) @ T_BS"
        elif body_tum is not None:
            gt = load_groundtruth(body_tum, ts, config.gt_max_dt, cam_from_gt=self.T_BS)
            gt_src = f"{body_tum} (body) @ T_BS"
        super().__init__(root, calibration=calibration, timestamps=ts, config=config, groundtruth=gt,
                         groundtruth_source=gt_src, color=first.ndim == 3, name=root.resolve().name,
                         nominal_fps=None)  # measured: EuRoC-format recordings of other rigs differ

    def _read(self, k: int) -> np.ndarray:
        return read_image(self._files[k])

    def _source(self, k: int) -> str:
        return str(self._files[k])
