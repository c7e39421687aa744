"""A folder of images or a video file, plus a calibration.

Image folder: the image files in the folder in natural order (``frame2`` before ``frame10``); timestamps from a
``times.txt`` when present (one timestamp a line, or TUM monoVO's ``id timestamp [exposure_ms]``), else frame index /
``InputConfig.fps``. Video: ``cv2.VideoCapture``; timestamps from the container (``CAP_PROP_POS_MSEC``), read once
when the sequence is opened (a fast ``grab`` pass without decoding to images), falling back to index / fps when the
container's times are not increasing.

Calibration: ``calib=PATH`` (any format :func:`mgso.io.read_camera_file` reads), else ``camera.txt`` or
``calib.txt`` in the folder (for a video: beside it). Without one: a clear error saying how to give one.
Ground truth: ``groundtruth=PATH`` (TUM / KITTI), else ``groundtruth.txt`` / ``groundtruth_tum.txt`` in the folder.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import cv2
import numpy as np

from ..config import InputConfig
from .common import HOW_TO_CALIBRATE, CalibArg, find_photometric, load_groundtruth, make_calibration, \
    resolve_camera_spec
from .errors import DatasetError
from .images import (IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, check_increasing, list_images, parse_float,
                     read_first_image, read_table)
from .sequence import Sequence

__all__ = ["ImageFolderSequence", "VideoSequence", "CALIBRATION_NAMES"]

log = logging.getLogger(__name__)

CALIBRATION_NAMES = ("camera.txt", "calib.txt")
GROUNDTRUTH_NAMES = ("groundtruth.txt", "groundtruth_tum.txt")


def _calibration_spec(calib: CalibArg, folder: Path, size: tuple[int, int], what: str):
    if calib is not None:
        return resolve_camera_spec(calib, size)
    for name in CALIBRATION_NAMES:
        if (folder / name).is_file():
            return resolve_camera_spec(folder / name, size)
    raise DatasetError(f"{what}: no calibration (looked for {' or '.join(CALIBRATION_NAMES)} in {folder}); "
                       f"{HOW_TO_CALIBRATE}")


def _groundtruth(groundtruth, folder: Path, ts: np.ndarray, max_dt: float):
    path = Path(groundtruth) if groundtruth is not None else next(
        (folder / n for n in GROUNDTRUTH_NAMES if (folder / n).is_file()), None)
    if path is None:
        return None, ""
    return load_groundtruth(path, ts, max_dt), str(path)


class ImageFolderSequence(Sequence):
    """Sorted image files of one folder."""

    layout = "images"
    looked_for = "image folder: image files (" + " ".join(IMAGE_EXTENSIONS) + ")"

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and any(p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS for p in path.iterdir())

    def __init__(self, path: str | Path, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth: str | Path | None = None):
        folder = Path(path)
        config = config or InputConfig()
        if not folder.is_dir():
            raise DatasetError(f"{folder}: not a folder")
        self._files = list_images(folder)
        if not self._files:
            raise DatasetError(f"{folder}: no image files ({', '.join(('png', 'jpg', 'bmp', 'tif', 'pgm'))} ...)")
        n = len(self._files)
        exposures = None
        times = folder / "times.txt"
        if times.is_file():
            rows = read_table(times, 1, "times.txt (one timestamp a line, or 'id timestamp [exposure_ms]')")
            if len(rows) != n:
                raise DatasetError(f"{times}: {len(rows)} timestamps for {n} images in {folder}")
            col = 1 if all(len(p) >= 2 for _, p in rows) else 0
            ts = np.array([parse_float(p[col], times, ln, "timestamp") for ln, p in rows])
            check_increasing(ts, str(times), [ln for ln, _ in rows])
            if col == 1 and all(len(p) >= 3 for _, p in rows):
                exposures = np.array([parse_float(p[2], times, ln, "exposure time") for ln, p in rows])
        else:
            if not config.fps > 0:
                raise DatasetError(f"input.fps must be positive, got {config.fps}")
            ts = np.arange(n, dtype=np.float64) / config.fps
        first, first_path = read_first_image(self._files)
        size = (first.shape[1], first.shape[0])
        spec = _calibration_spec(calib, folder, size, str(folder))
        calibration = make_calibration(spec, config, find_photometric(folder, size), image_size=size,
                                       images=str(first_path))
        gt, gt_src = _groundtruth(groundtruth, folder, ts, config.gt_max_dt)
        super().__init__(folder, calibration=calibration, timestamps=ts, config=config, exposures_ms=exposures,
                         groundtruth=gt, groundtruth_source=gt_src, color=first.ndim == 3,
                         name=folder.resolve().name, nominal_fps=None if times.is_file() else config.fps)

    def _image_file(self, k: int) -> Path:
        return self._files[k]

    def _source(self, k: int) -> str:
        return str(self._files[k])


class VideoSequence(Sequence):
    """A video file read with ``cv2.VideoCapture``. Sequential reading is fast; reading backwards reopens the file
    and skips forward (exact, never an approximate seek)."""

    layout = "video"
    looked_for = "video file: " + " ".join(VIDEO_EXTENSIONS)

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_file() and path.suffix.lower() in VIDEO_EXTENSIONS

    def __init__(self, path: str | Path, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth: str | Path | None = None):
        path = Path(path)
        config = config or InputConfig()
        if not path.is_file():
            raise DatasetError(f"{path}: video file not found")
        self._lock = threading.Lock()
        self._video = str(path)
        cap = self._open()
        container_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        limit = config.end if config.end > 0 else None
        msec = []
        while limit is None or len(msec) < limit:
            if not cap.grab():
                break
            msec.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
        cap.release()
        if not msec:
            raise DatasetError(f"{path}: no frames could be read (empty or corrupt video, or a codec OpenCV's "
                               "FFmpeg lacks)")
        ts = np.asarray(msec) / 1000.0
        if len(ts) > 1 and np.any(np.diff(ts) <= 0):
            fps = container_fps if container_fps > 0 else config.fps
            log.warning("%s: container timestamps are not increasing; using frame index / %.3f fps", path, fps)
            ts = np.arange(len(ts), dtype=np.float64) / fps
        self._cap: cv2.VideoCapture | None = None
        self._next = 0
        first = self._read(0)
        size = (first.shape[1], first.shape[0])
        spec = _calibration_spec(calib, path.parent, size, str(path))
        calibration = make_calibration(spec, config, find_photometric(path.parent, size), image_size=size,
                                       images=f"the video {path}")
        gt, gt_src = _groundtruth(groundtruth, path.parent, ts, config.gt_max_dt) if groundtruth is not None \
            else (None, "")
        super().__init__(path, calibration=calibration, timestamps=ts, config=config, groundtruth=gt,
                         groundtruth_source=gt_src, color=first.ndim == 3, name=path.stem,
                         nominal_fps=container_fps or config.fps)

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(self._video)
        if not cap.isOpened():
            raise DatasetError(f"{self._video}: cannot open the video (unsupported container or codec)")
        return cap

    def _read(self, k: int) -> np.ndarray:
        with self._lock:
            if self._cap is None or k < self._next:
                if self._cap is not None:
                    self._cap.release()
                self._cap = self._open()
                self._next = 0
            while self._next < k:
                if not self._cap.grab():
                    raise DatasetError(f"{self._video}: frame {self._next} could not be read")
                self._next += 1
            ok, img = self._cap.read()
            if not ok or img is None:
                raise DatasetError(f"{self._video}: frame {k} could not be decoded")
            self._next = k + 1
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        return img

    def _source(self, k: int) -> str:
        return f"{self._video}#frame{k}"

    def close(self) -> None:
        with self._lock:
            if self._cap is not None:
                self._cap.release()
                self._cap = None
