"""Pieces the dataset readers share: calibration resolution, photometric files, ground-truth loading."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Union

import numpy as np

from ..camera import Calibration, CameraSpec, PhotometricCalibration, RECTIFY_MODES
from .calibration import read_camera_file
from ..config import InputConfig
from .errors import DatasetError, as_dataset_errors
from .sequence import poses_at_times
from .trajectory import Trajectory, read_trajectory

__all__ = ["CalibArg", "make_calibration", "check_image_size", "find_photometric", "resolve_camera_spec",
           "load_groundtruth",
           "HOW_TO_CALIBRATE"]

log = logging.getLogger(__name__)

CalibArg = Union[str, Path, CameraSpec, Calibration, None]

HOW_TO_CALIBRATE = ("give one with calib=PATH (mgso run --calib PATH) or put a camera.txt in the folder: either a "
                    "DSO camera.txt ('Pinhole fx fy cx cy 0' / 'RadTan fx fy cx cy k1 k2 p1 p2' / ... then "
                    "'width height', 'crop|full|none', 'width height') or one line 'fx fy cx cy [k1 k2 p1 p2 [k3]]'; "
                    "EuRoC sensor.yaml and KITTI calib.txt work too (see docs/datasets.md)")


def output_size(config: InputConfig, calib_out: tuple[int, int] | None) -> tuple[int, int] | None:
    """Output size from ``input.width`` / ``input.height``; one alone keeps the calibration's aspect ratio."""
    w, h = config.width, config.height
    if w < 0 or h < 0:
        raise DatasetError(f"input.width and input.height must be >= 0, got {w} x {h}")
    if w == 0 and h == 0:
        return None
    if w and h:
        return (w, h)
    if calib_out is None:
        raise DatasetError("input.width and input.height must both be given here")
    cw, ch = calib_out
    return (w, max(1, round(w * ch / cw))) if w else (max(1, round(h * cw / ch)), h)


def resolve_camera_spec(calib: CalibArg, image_size: tuple[int, int]) -> CameraSpec | Calibration:
    """A ``calib=`` argument (path, spec or ready calibration) as a spec or calibration."""
    if isinstance(calib, (CameraSpec, Calibration)):
        return calib
    with as_dataset_errors():
        return read_camera_file(Path(calib).expanduser(), image_size)


def check_image_size(spec: CameraSpec | Calibration, image_size: tuple[int, int] | None, images: str) -> None:
    """The calibration must be of the images' size: a calibration of another size (``calib=`` a file of another
    camera or resolution) is refused when the sequence is opened, with both sizes, not at the first frame (and not
    shown as the image size by ``mgso info``)."""
    if image_size is None:
        return
    model = spec.input if isinstance(spec, Calibration) else spec.model
    source = spec.source or "the calibration"
    if tuple(model.size) != tuple(image_size):
        raise DatasetError(f"{source}: the calibration is for {model.width}x{model.height} images but {images} is "
                           f"{image_size[0]}x{image_size[1]}; give the calibration of this camera at this "
                           "resolution")


def make_calibration(spec: CameraSpec | Calibration, config: InputConfig,
                     photometric: PhotometricCalibration | None = None, *, image_size: tuple[int, int] | None = None,
                     images: str = "the first image") -> Calibration:
    """The calibration a sequence uses: the spec with ``input.rectify`` / ``input.width`` / ``input.height`` applied
    and the photometric calibration attached. A ready :class:`Calibration` is used as it is. ``image_size``: the
    size of the recorded images (``images`` names them in the error), which the calibration must have."""
    check_image_size(spec, image_size, images)
    if isinstance(spec, Calibration):
        return spec
    if config.rectify and config.rectify not in RECTIFY_MODES:
        raise DatasetError(f"input.rectify must be one of {RECTIFY_MODES} or empty, got {config.rectify!r}")
    size = output_size(config, spec.output.size or spec.model.size)
    with as_dataset_errors():
        return Calibration.from_spec(spec, rectify=config.rectify or None, size=size, photometric=photometric)


def find_photometric(folder: Path, image_size: tuple[int, int]) -> PhotometricCalibration | None:
    """``pcalib.txt`` and ``vignette.png`` of a folder (TUM monoVO names), either optional."""
    pcalib = folder / "pcalib.txt"
    vignette = folder / "vignette.png"
    if not pcalib.is_file() and not vignette.is_file():
        return None
    with as_dataset_errors():
        return PhotometricCalibration.from_files(pcalib if pcalib.is_file() else None,
                                                 vignette if vignette.is_file() else None, image_size)


def load_groundtruth(path: Path, frame_times: np.ndarray, max_dt: float,
                     cam_from_gt: np.ndarray | None = None) -> np.ndarray:
    """A TUM or KITTI trajectory file associated to the frame times (nearest pose within ``max_dt`` s; a KITTI file
    has one pose per frame). ``cam_from_gt``: right-multiplied transform (e.g. EuRoC's body-to-camera ``T_BS``).
    Returns ``(N, 4, 4)`` camera-to-world, NaN where a frame has no pose."""
    with as_dataset_errors():
        traj: Trajectory = read_trajectory(path, timestamps=None)
    if _is_kitti(path):
        if len(traj) < len(frame_times):
            raise DatasetError(f"{path}: {len(traj)} KITTI poses for {len(frame_times)} frames")
        poses = traj.cam_to_world[:len(frame_times)].copy()
    else:
        poses = poses_at_times(frame_times, traj, max_dt)
        if not np.isfinite(poses).any():
            raise DatasetError(f"{path}: no ground-truth pose within {max_dt} s of any frame (frames "
                               f"{frame_times[0]:.3f}..{frame_times[-1]:.3f} s, poses {traj.timestamps[0]:.3f}.."
                               f"{traj.timestamps[-1]:.3f} s); are the clocks the same?")
    if cam_from_gt is not None:
        poses = poses @ cam_from_gt
    return poses


def _is_kitti(path: Path) -> bool:
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for line in fh:
            s = line.strip()
            if s and not s.startswith("#"):
                return len(s.replace(",", " ").split()) == 12
    return False
