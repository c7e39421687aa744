"""EuRoC MAV (ASL folder layout) reader.

``mav0/cam0/data.csv`` (``#timestamp [ns],filename``), ``mav0/cam0/data/*.png``, ``mav0/cam0/sensor.yaml``
(intrinsics, distortion, resolution, ``T_BS`` = camera-to-body). Ground truth is of the *body* (IMU) frame: from
``mav0/state_groundtruth_estimate0/data.csv`` (``timestamp ns, p_RS_R xyz, q_RS wxyz, ...``) when present, else a TUM
file of body poses beside ``mav0`` (``groundtruth_body_tum.txt``); camera pose = body pose @ ``T_BS``. A file passed
as ``groundtruth=`` is taken as camera poses.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import yaml

from ..camera import (CalibrationError, CameraModel, CameraSpec, EquidistantCamera, FOVCamera, OutputSpec,
                      PinholeCamera, RadTanCamera)
from ..config import InputConfig
from ..geometry import make_pose, quat_wxyz_to_matrix
from .calibration import CalibrationFormat, register_calibration_format
from .common import CalibArg, find_photometric, load_groundtruth, make_calibration, resolve_camera_spec
from .errors import DatasetError, as_dataset_errors
from .images import check_increasing, read_first_image, read_table
from .sequence import Sequence, poses_at_times
from .trajectory import Trajectory

__all__ = ["EurocSequence", "euroc_root", "read_euroc_groundtruth_csv", "read_euroc_sensor_yaml"]

BODY_GROUNDTRUTH_NAMES = ("groundtruth_body_tum.txt", "groundtruth_body.txt")


class _OpenCVYamlLoader(yaml.SafeLoader):
    """PyYAML loader that reads OpenCV FileStorage YAML (``%YAML:1.0`` header, ``!!opencv-matrix`` tags)."""


def _opencv_matrix(loader, node):
    m = loader.construct_mapping(node, deep=True)
    return np.asarray(m["data"], dtype=np.float64).reshape(int(m["rows"]), int(m["cols"]))


_OpenCVYamlLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _opencv_matrix)


def _load_opencv_yaml(path: Path) -> dict:
    text = path.read_text(encoding="utf-8", errors="replace")
    text = re.sub(r"^%YAML[: ]\s*1\.\d+\s*$", "", text, count=1, flags=re.MULTILINE)
    try:
        data = yaml.load(text, Loader=_OpenCVYamlLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a YAML mapping at the top level")
    return data


def _matrix4(value, path: Path, key: str) -> np.ndarray:
    if isinstance(value, dict) and "data" in value:
        value = value["data"]
    try:
        T = np.asarray(value, dtype=np.float64).reshape(4, 4)
    except (ValueError, TypeError):
        raise CalibrationError(f"{path}: {key} must be a 4x4 matrix (16 numbers)") from None
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{path}: {key} is not a rigid transform (last row must be 0 0 0 1)")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise CalibrationError(f"{path}: the rotation part of {key} is not a rotation")
    return T


def read_euroc_sensor_yaml(path: str | Path) -> tuple[CameraSpec, np.ndarray]:
    """EuRoC / Kalibr ``sensor.yaml`` of a camera: ``intrinsics [fu fv cu cv]``, ``distortion_model``
    (``radial-tangential`` / ``radtan``, ``equidistant``, ``fov``, ``none``), ``distortion_coefficients``,
    ``resolution [w h]``, ``T_BS`` (camera-to-body, 4x4). Returns the spec (rectified with ``keep``) and ``T_BS``
    (identity when absent). The ``%YAML:1.0`` header PyYAML rejects is removed before parsing."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: sensor.yaml not found")
    d = _load_opencv_yaml(path)
    for key in ("intrinsics", "resolution"):
        if key not in d:
            raise CalibrationError(f"{path}: missing key {key!r} (a EuRoC camera sensor.yaml has intrinsics, "
                                   "distortion_model, distortion_coefficients, resolution, T_BS)")
    cam_model = str(d.get("camera_model", "pinhole")).lower()
    if cam_model != "pinhole":
        raise CalibrationError(f"{path}: camera_model {cam_model!r} is not supported (only pinhole with a "
                               "distortion model)")
    try:
        k = [float(v) for v in d["intrinsics"]]
        res = [int(v) for v in d["resolution"]]
        coeffs = [float(v) for v in d.get("distortion_coefficients", []) or []]
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: intrinsics, resolution and distortion_coefficients must be lists of "
                               "numbers") from None
    if len(k) != 4 or len(res) != 2:
        raise CalibrationError(f"{path}: intrinsics needs 4 numbers and resolution 2, got {len(k)} and {len(res)}")
    dm = str(d.get("distortion_model", "none")).lower().replace("_", "-")
    w, h = res
    try:
        if dm in ("radial-tangential", "radtan", "plumb-bob"):
            if len(coeffs) not in (4, 5):
                raise CalibrationError(f"{path}: radial-tangential needs 4 or 5 coefficients, got {len(coeffs)}")
            model: CameraModel = RadTanCamera(*k, w, h, *coeffs)
        elif dm in ("equidistant", "fisheye", "kannala-brandt"):
            if len(coeffs) != 4:
                raise CalibrationError(f"{path}: equidistant needs 4 coefficients, got {len(coeffs)}")
            model = EquidistantCamera(*k, w, h, *coeffs)
        elif dm == "fov":
            if len(coeffs) != 1:
                raise CalibrationError(f"{path}: fov needs 1 coefficient (omega), got {len(coeffs)}")
            model = FOVCamera(*k, w, h, omega=coeffs[0])
        elif dm in ("none", "pinhole", ""):
            model = PinholeCamera(*k, w, h)
        else:
            raise CalibrationError(f"{path}: unknown distortion_model {dm!r} (expected radial-tangential, "
                                   "equidistant, fov or none)")
    except CalibrationError as exc:
        msg = str(exc)
        raise CalibrationError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    T_BS = _matrix4(d["T_BS"], path, "T_BS") if "T_BS" in d else np.eye(4)
    return CameraSpec(model, OutputSpec(mode="keep" if model.has_distortion else "none"), str(path)), T_BS


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

    looked_for = "EuRoC: mav0/cam0/data.csv"

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and euroc_root(path) is not None

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
        first, first_path = read_first_image(self._files)
        size = (first.shape[1], first.shape[0])

        yaml_path = cam_dir / "sensor.yaml"
        self.T_BS = np.eye(4)  # camera-to-body
        if yaml_path.is_file():
            with as_dataset_errors():
                yaml_spec, self.T_BS = read_euroc_sensor_yaml(yaml_path)
        elif calib is None:
            raise DatasetError(f"{yaml_path}: not found; a EuRoC camera needs its sensor.yaml (or calib=PATH)")
        spec = resolve_camera_spec(calib, size) if calib is not None else yaml_spec
        calibration = make_calibration(spec, config, find_photometric(root, size), image_size=size,
                                       images=str(first_path))

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

    def _image_file(self, k: int) -> Path:
        return self._files[k]

    def _source(self, k: int) -> str:
        return str(self._files[k])


register_calibration_format(CalibrationFormat(
    "EuRoC sensor.yaml",
    lambda path, text, lines: (path.suffix.lower() in (".yaml", ".yml") or text.lstrip().startswith("%YAML")
                               or re.search(r"^\s*intrinsics\s*:", text, flags=re.MULTILINE) is not None),
    lambda path, image_size: read_euroc_sensor_yaml(path)[0]))
