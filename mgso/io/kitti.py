"""KITTI odometry reader.

``image_0/`` (left gray; ``image_2/`` left colour, via ``InputConfig.camera``), ``calib.txt`` (``P0:`` .. ``P3:``
rectified 3x4 projections), ``times.txt`` (seconds, one a line). Ground truth (camera 0, camera-to-world, KITTI 3x4
rows): ``poses_kitti.txt`` or ``poses.txt`` in the folder, ``../../poses/NN.txt`` of the official layout
(``dataset/sequences/NN``), or a ``groundtruth_tum.txt`` (TUM). For the colour camera the poses are moved by the
baseline in ``P2``. Images are 1241x376 (or near): any size is accepted.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..camera import CalibrationError, CameraSpec, OutputSpec, PinholeCamera
from ..config import InputConfig
from .calibration import CalibrationFormat, numbers, register_calibration_format
from .common import HOW_TO_CALIBRATE, CalibArg, find_photometric, load_groundtruth, make_calibration, \
    resolve_camera_spec
from .errors import DatasetError, as_dataset_errors
from .images import check_increasing, list_images, parse_float, read_first_image, read_table
from .sequence import Sequence
from .trajectory import read_kitti

__all__ = ["KittiSequence", "kitti_camera_dir", "read_kitti_calib"]

log = logging.getLogger(__name__)

KITTI_FPS = 10.0  # KITTI odometry frame rate


def read_kitti_calib(path: str | Path, image_size: tuple[int, int] | None, camera: int = 0) -> tuple[CameraSpec,
                                                                                                     np.ndarray]:
    """KITTI odometry ``calib.txt``: the ``P<camera>:`` line, a row-major 3x4 projection of rectified images.

    Returns the pinhole spec and the 3x4 projection matrix (its last column holds the stereo baseline term)."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: KITTI calib.txt not found")
    key = f"P{camera}"
    for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        if line.strip().startswith(key + ":") or line.strip().startswith(key + " "):
            vals = numbers(line.split(":", 1)[1] if ":" in line else line.split(None, 1)[1])
            if vals is None or len(vals) != 12:
                raise CalibrationError(f"{path}:{n}: {key} needs 12 numbers (3x4 projection), got {line[:80]!r}")
            P = np.array(vals, dtype=np.float64).reshape(3, 4)
            break
    else:
        raise CalibrationError(f"{path}: no '{key}:' line (KITTI projection matrix of camera {camera})")
    if image_size is None:
        raise CalibrationError(f"{path}: KITTI calib.txt holds no image size; it is needed from the images")
    if P[2, 2] == 0 or P[0, 1] != 0 or P[1, 0] != 0:
        raise CalibrationError(f"{path}:{n}: {key} is not a rectified pinhole projection: {P.tolist()}")
    try:
        model = PinholeCamera(P[0, 0] / P[2, 2], P[1, 1] / P[2, 2], P[0, 2] / P[2, 2], P[1, 2] / P[2, 2],
                              *image_size)
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    return CameraSpec(model, OutputSpec(mode="none"), str(path)), P


def kitti_camera_dir(folder: Path, camera: str) -> tuple[Path, int]:
    """``image_N`` folder and camera number for an ``InputConfig.camera`` value ("", "0", "2", "image_2", ...)."""
    name = camera or "image_0"
    digits = "".join(ch for ch in name if ch.isdigit())
    if not digits or int(digits) not in (0, 1, 2, 3):
        raise DatasetError(f"{folder}: KITTI camera must be image_0 .. image_3, got {camera!r}")
    n = int(digits)
    return folder / f"image_{n}", n


class KittiSequence(Sequence):
    """A KITTI odometry sequence folder (``dataset/sequences/NN`` or an excerpt with the same files)."""

    layout = "kitti"
    looked_for = "KITTI: image_0/ or image_2/ (with calib.txt, times.txt)"

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and any((path / f"image_{n}").is_dir() for n in range(4))

    def __init__(self, path: str | Path, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth: str | Path | None = None):
        folder = Path(path)
        config = config or InputConfig()
        img_dir, cam_n = kitti_camera_dir(folder, config.camera)
        if not img_dir.is_dir():
            raise DatasetError(f"{img_dir}: not found (KITTI camera {cam_n}; set input.camera to image_0 or "
                               "image_2)")
        self._files = list_images(img_dir)
        if not self._files:
            raise DatasetError(f"{img_dir}: no images")
        n = len(self._files)
        times = folder / "times.txt"
        if times.is_file():
            rows = read_table(times, 1, "KITTI times.txt (one timestamp in seconds a line)")
            if len(rows) < n:
                raise DatasetError(f"{times}: {len(rows)} timestamps for {n} images in {img_dir}")
            frame_ids = self._frame_ids(len(rows))
            ts_all = np.array([parse_float(p[0], times, ln, "timestamp") for ln, p in rows])
            check_increasing(ts_all, str(times), [ln for ln, _ in rows])
            ts = ts_all[frame_ids]
        else:
            log.warning("%s: no times.txt; timestamps are frame number / %.0f Hz", folder, KITTI_FPS)
            ts = self._frame_ids(None) / KITTI_FPS
        check_increasing(ts, str(img_dir))

        first, first_path = read_first_image(self._files)
        size = (first.shape[1], first.shape[0])
        P = None
        if calib is not None:
            spec = resolve_camera_spec(calib, size)
        elif (folder / "calib.txt").is_file():
            with as_dataset_errors():
                spec, P = read_kitti_calib(folder / "calib.txt", size, cam_n)
        else:
            raise DatasetError(f"{folder}: no calib.txt for this KITTI sequence; {HOW_TO_CALIBRATE}")
        calibration = make_calibration(spec, config, find_photometric(folder, size), image_size=size,
                                       images=str(first_path))

        # Ground truth is of camera 0; camera N sits at -P_N[:, 3] / fx along x in the rectified frame.
        cam0_from_camN = np.eye(4)
        if cam_n != 0 and P is not None:
            cam0_from_camN[:3, 3] = -np.linalg.solve(P[:, :3], P[:, 3])
        gt, gt_src = None, ""
        candidates = [folder / "poses_kitti.txt", folder / "poses.txt",
                      folder.resolve().parent.parent / "poses" / f"{folder.resolve().name}.txt",
                      folder / "groundtruth_tum.txt"]
        gt_path = Path(groundtruth) if groundtruth is not None else next((c for c in candidates if c.is_file()), None)
        if gt_path is not None:
            gt = self._load_gt(gt_path, ts, config.gt_max_dt) @ cam0_from_camN
            gt_src = str(gt_path) + (f" (camera 0, moved to camera {cam_n})" if cam_n else "")
        super().__init__(folder, calibration=calibration, timestamps=ts, config=config, groundtruth=gt,
                         groundtruth_source=gt_src, color=first.ndim == 3, name=folder.resolve().name,
                         nominal_fps=KITTI_FPS)

    def _frame_ids(self, count: int | None) -> np.ndarray:
        """Frame number of each image: its integer file name when all are integers (an excerpt may start later),
        else its position."""
        stems = [f.stem for f in self._files]
        if all(s.isdigit() for s in stems):
            ids = np.array([int(s) for s in stems], dtype=np.int64)
            if count is not None and ids.max() >= count:
                raise DatasetError(f"{self._files[int(ids.argmax())]}: frame number {ids.max()} but times.txt has "
                                   f"{count} entries")
            return ids
        return np.arange(len(stems), dtype=np.int64)

    def _load_gt(self, path: Path, ts: np.ndarray, max_dt: float) -> np.ndarray:
        with open(path, "r", encoding="utf-8", errors="replace") as fh:
            first = next((ln for ln in fh if ln.strip() and not ln.startswith("#")), "")
        if len(first.replace(",", " ").split()) != 12:
            return load_groundtruth(path, ts, max_dt)
        with as_dataset_errors():
            traj = read_kitti(path)
        ids = self._frame_ids(None)
        if ids.max() >= len(traj):
            raise DatasetError(f"{path}: {len(traj)} KITTI poses, but frame {ids.max()} is among the images")
        return traj.cam_to_world[ids]

    def _image_file(self, k: int) -> Path:
        return self._files[k]

    def _source(self, k: int) -> str:
        return str(self._files[k])


register_calibration_format(CalibrationFormat(
    "KITTI calib.txt", lambda path, text, lines: bool(lines) and re.match(r"^P\d\s*:", lines[0]) is not None,
    lambda path, image_size: read_kitti_calib(path, image_size, 0)[0]))
