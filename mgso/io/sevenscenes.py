"""Microsoft 7-Scenes reader (one ``seq-NN`` folder, or an excerpt with the same files).

``frame-XXXXXX.color.png`` (``.jpg`` in some redistributions), ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world,
metres; rotations re-orthonormalised here: the files carry about 4e-4 of round-off), ``frame-XXXXXX.depth.png``
(uint16 millimetres, 0 and 65535 invalid). Colour intrinsics: ``calib=``, else the customary fx = fy = 525,
cx = 320, cy = 240, no distortion. The folder's ``camera-intrinsics.txt`` is the *depth* camera's (585, 585, 320, 240)
and is never used for colour; the depth maps are in that camera's view, not registered to the colour image
(:attr:`SevenScenesSequence.depth_camera`). Poses come from KinectFusion on depth. Timestamps: frame number / 30 s.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..camera import CameraSpec, OutputSpec, PinholeCamera
from ..config import InputConfig
from ..geometry import orthonormalize
from .common import HOW_TO_CALIBRATE, CalibArg, find_photometric, load_groundtruth, make_calibration, \
    resolve_camera_spec
from .errors import DatasetError
from .images import list_images, read_first_image, read_image
from .sequence import Sequence

__all__ = ["SevenScenesSequence", "read_7scenes_pose", "SEVEN_SCENES_FPS", "SEVEN_SCENES_COLOR"]

log = logging.getLogger(__name__)

SEVEN_SCENES_FPS = 30.0  # Kinect v1 frame rate
# Microsoft 7-Scenes colour camera: not calibrated by the dataset; the customary choice (fx = fy = 525, principal
# point at the image centre, no distortion), see ../shared/data/README.md. The folder's camera-intrinsics.txt
# (585, 585, 320, 240) is the depth camera's.
SEVEN_SCENES_COLOR = (525.0, 525.0, 320.0, 240.0)
_COLOR = re.compile(r"frame-(\d+)\.color\.(png|jpg|jpeg)", re.IGNORECASE)


def read_7scenes_pose(path: Path) -> np.ndarray:
    """A 7-Scenes ``.pose.txt``: 4x4 camera-to-world; rotation re-orthonormalised. Non-finite entries (frames
    where tracking failed) give a NaN pose."""
    try:
        vals = path.read_text(encoding="utf-8", errors="replace").split()
        T = np.array([float(v) for v in vals], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{path}: a 7-Scenes pose file must hold 16 numbers (4x4 camera-to-world)") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read pose file: {exc}") from None
    if T.size != 16:
        raise DatasetError(f"{path}: a 7-Scenes pose file must hold 16 numbers (4x4), got {T.size}")
    T = T.reshape(4, 4)
    if not np.all(np.isfinite(T)):
        return np.full((4, 4), np.nan)
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        raise DatasetError(f"{path}: last row of the pose must be 0 0 0 1, got {T[3].tolist()}")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-2 or np.linalg.det(R) <= 0:
        raise DatasetError(f"{path}: the rotation part is not a rotation (R R^T deviates from I by "
                           f"{np.abs(R @ R.T - np.eye(3)).max():.3g})")
    T[:3, :3] = orthonormalize(R)
    return T


class SevenScenesSequence(Sequence):
    """7-Scenes frames in one folder."""

    layout = "7scenes"
    looked_for = "7-Scenes: frame-XXXXXX.color.png/.jpg"

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and any(p.is_file() and _COLOR.fullmatch(p.name) for p in path.iterdir())

    def __init__(self, path: str | Path, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth: str | Path | None = None):
        folder = Path(path)
        config = config or InputConfig()
        files = [p for p in list_images(folder) if _COLOR.fullmatch(p.name)]
        if not files:
            raise DatasetError(f"{folder}: no frame-XXXXXX.color.png/.jpg images")
        numbers = np.array([int(_COLOR.fullmatch(p.name).group(1)) for p in files], dtype=np.int64)
        order = np.argsort(numbers, kind="stable")
        self._files = [files[i] for i in order]
        numbers = numbers[order]
        if np.any(np.diff(numbers) == 0):
            dup = self._files[int(np.nonzero(np.diff(numbers) == 0)[0][0]) + 1]
            raise DatasetError(f"{dup}: two colour images with the same frame number")
        stems = [folder / p.name[: p.name.lower().index(".color.")] for p in self._files]
        ts = numbers.astype(np.float64) / SEVEN_SCENES_FPS
        first, first_path = read_first_image(self._files)
        size = (first.shape[1], first.shape[0])
        if calib is not None:
            spec = resolve_camera_spec(calib, size)
        else:
            if size != (640, 480):
                raise DatasetError(f"{self._files[0]}: 7-Scenes colour images are 640x480, this one is "
                                   f"{size[0]}x{size[1]}; the default intrinsics do not apply: {HOW_TO_CALIBRATE}")
            spec = CameraSpec(PinholeCamera(*SEVEN_SCENES_COLOR, 640, 480), OutputSpec(mode="none"),
                              "7-Scenes customary colour intrinsics (525, 525, 320, 240)")
        calibration = make_calibration(spec, config, find_photometric(folder, size), image_size=size,
                                       images=str(first_path))

        gt, gt_src = None, ""
        if groundtruth is not None:
            gt, gt_src = load_groundtruth(Path(groundtruth), ts, config.gt_max_dt), str(groundtruth)
        else:
            pose_files = [Path(f"{s}.pose.txt") for s in stems]
            present = [p.is_file() for p in pose_files]
            if any(present):
                gt = np.stack([read_7scenes_pose(p) if ok else np.full((4, 4), np.nan)
                               for p, ok in zip(pose_files, present)])
                missing = len(present) - sum(present)
                if missing:
                    log.warning("%s: %d of %d frames have no .pose.txt", folder, missing, len(present))
                gt_src = f"{folder}/frame-*.pose.txt"
        self._depth_files = [Path(f"{s}.depth.png") for s in stems]
        has_depth = any(p.is_file() for p in self._depth_files)
        self.depth_camera: PinholeCamera | None = None
        if has_depth:
            self.depth_camera = self._depth_intrinsics(folder, size)
        super().__init__(folder, calibration=calibration, timestamps=ts, config=config, groundtruth=gt,
                         groundtruth_source=gt_src, color=first.ndim == 3, has_depth=has_depth,
                         name=folder.resolve().name, nominal_fps=SEVEN_SCENES_FPS)

    @staticmethod
    def _depth_intrinsics(folder: Path, size: tuple[int, int]) -> PinholeCamera:
        f = folder / "camera-intrinsics.txt"
        if f.is_file():
            try:
                K = np.array([float(v) for v in f.read_text().split()]).reshape(3, 3)
                return PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], *size)
            except ValueError:
                raise DatasetError(f"{f}: expected a 3x3 matrix (the depth camera's intrinsics)") from None
        return PinholeCamera(585.0, 585.0, 320.0, 240.0, *size)

    def _image_file(self, k: int) -> Path:
        return self._files[k]

    def _source(self, k: int) -> str:
        return str(self._files[k])

    def _read_depth(self, k: int) -> np.ndarray | None:
        f = self._depth_files[k]
        if not f.is_file():
            return None
        d = read_image(f)
        if d.ndim != 2 or d.dtype != np.uint16:
            raise DatasetError(f"{f}: 7-Scenes depth must be 16-bit single channel, got {d.dtype} {d.shape}")
        out = d.astype(np.float32) / np.float32(1000.0)
        out[(d == 0) | (d == 65535)] = 0.0
        return out

    def load_depth(self, i: int) -> np.ndarray | None:
        """Depth in metres of frame ``i`` **in the depth camera's view** (:attr:`depth_camera`, 585/585/320/240),
        which is not registered to the colour image; 0 = invalid."""
        k = self._k(i)
        return self._read_depth(k)
