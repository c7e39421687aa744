"""TUM RGB-D and TUM monoVO readers.

TUM RGB-D (https://vision.in.tum.de/data/datasets/rgbd-dataset/file_formats): ``rgb.txt`` (``timestamp filename``),
``rgb/*.png``, optional ``groundtruth.txt`` (TUM poses of the colour camera's optical centre, camera-to-world),
optional ``depth.txt`` + ``depth/*.png`` (16 bit, 5000 units per metre, registered to the colour image). Calibration:
``calib=``, else a ``camera.txt`` in the folder, else the freiburg 1/2/3 defaults named by the folder
(``rgbd_dataset_freiburgN_...``).

TUM monoVO (https://vision.in.tum.de/data/datasets/mono-dataset): ``images/`` or ``images.zip`` (read in place),
``times.txt`` (``id timestamp exposure_ms``), ``camera.txt`` (DSO format), ``pcalib.txt``, ``vignette.png``, and
``groundtruthSync.txt`` (a pose per frame, NaN outside the start and end segments) when present.
"""

from __future__ import annotations

import logging
import re
import threading
import zipfile
from pathlib import Path

import numpy as np

from ..camera import CalibrationError, CameraSpec, OutputSpec, RadTanCamera
from ..geometry import make_pose, quat_xyzw_to_matrix
from ..config import InputConfig
from .common import (HOW_TO_CALIBRATE, CalibArg, find_photometric, load_groundtruth, make_calibration,
                     resolve_camera_spec)
from .errors import DatasetError, as_dataset_errors
from .images import (IMAGE_EXTENSIONS, check_increasing, decode_image, natural_key, parse_float, read_first_image,
                     read_image, read_table)
from .sequence import Sequence, poses_at_times
from .trajectory import Trajectory, matching_time_indices

__all__ = ["TumRgbdSequence", "TumMonoSequence", "TUM_DEPTH_FACTOR", "read_groundtruth_sync", "TUM_RGBD_FREIBURG",
           "tum_rgbd_default"]

log = logging.getLogger(__name__)

TUM_DEPTH_FACTOR = 5000.0  # depth PNG units per metre (TUM RGB-D file formats page)

# TUM RGB-D colour cameras: fx fy cx cy and OpenCV distortion d0..d4 = k1 k2 p1 p2 k3, from the table "Intrinsic
# Camera Calibration of the Kinect" on https://vision.in.tum.de/data/datasets/rgbd-dataset/file_formats (reproduced
# verbatim in many repositories' comments); freiburg3 lists no distortion.
TUM_RGBD_FREIBURG = {
    1: (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    2: (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    3: (535.4, 539.2, 320.1, 247.6, (0.0, 0.0, 0.0, 0.0, 0.0)),
}


def tum_rgbd_default(which: int | str, width: int = 640, height: int = 480) -> CameraSpec:
    """The TUM RGB-D freiburg 1/2/3 colour calibration (``which``: 1, 2, 3, ``"fr2"``, ``"freiburg2"`` or a folder
    name such as ``rgbd_dataset_freiburg2_xyz``), distorted models rectified with ``keep`` (docs/datasets.md: DSO's ``crop`` zooms freiburg1 1.37x)."""
    n = which
    if isinstance(which, str):
        m = re.search(r"(?:freiburg|fr)([123])", which)
        if not m:
            raise CalibrationError(f"no TUM RGB-D camera named in {which!r} (expected freiburg1/2/3 or fr1/2/3)")
        n = int(m.group(1))
    if n not in TUM_RGBD_FREIBURG:
        raise CalibrationError(f"TUM RGB-D camera must be 1, 2 or 3, got {which!r}")
    fx, fy, cx, cy, d = TUM_RGBD_FREIBURG[n]
    if (width, height) != (640, 480):
        raise CalibrationError(f"the TUM RGB-D freiburg{n} calibration is for 640x480 images, these are "
                               f"{width}x{height}")
    model = RadTanCamera(fx, fy, cx, cy, width, height, d[0], d[1], d[2], d[3], d[4])
    mode = "keep" if model.has_distortion else "none"
    return CameraSpec(model, OutputSpec(mode=mode), f"TUM RGB-D freiburg{n} default calibration")


def _read_listing(path: Path, what: str, folder: Path) -> tuple[np.ndarray, list[Path], list[int]]:
    rows = read_table(path, 2, what)
    ts, files, lines = [], [], []
    for n, parts in rows:
        ts.append(parse_float(parts[0], path, n, "timestamp"))
        files.append(folder / parts[1])
        lines.append(n)
    ts = np.asarray(ts, dtype=np.float64)
    check_increasing(ts, str(path), lines)
    return ts, files, lines


class TumRgbdSequence(Sequence):
    """TUM RGB-D sequence folder (also what the synthetic scene generator writes, with its own camera.txt)."""

    layout = "tum_rgbd"
    looked_for = "TUM RGB-D: rgb.txt"

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return (path / "rgb.txt").is_file()

    def __init__(self, path: str | Path, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth: str | Path | None = None):
        folder = Path(path)
        config = config or InputConfig()
        listing = folder / "rgb.txt"
        ts, files, lines = _read_listing(listing, "image list (rgb.txt: 'timestamp filename')", folder)
        for f, n in zip(files, lines):
            if not f.is_file():
                raise DatasetError(f"{listing}:{n}: listed image {f} does not exist")
        self._files = files
        first, first_path = read_first_image(files)
        size = (first.shape[1], first.shape[0])
        if calib is not None:
            spec = resolve_camera_spec(calib, size)
        elif (folder / "camera.txt").is_file():
            spec = resolve_camera_spec(folder / "camera.txt", size)
        else:
            name = folder.resolve().name
            if not re.search(r"freiburg[123]", name):
                raise DatasetError(f"{folder}: no calibration for this TUM RGB-D folder: no camera.txt and the "
                                   f"folder name {name!r} names no freiburg1/2/3 camera; {HOW_TO_CALIBRATE}")
            with as_dataset_errors():
                spec = tum_rgbd_default(name, *size)
        calibration = make_calibration(spec, config, find_photometric(folder, size), image_size=size,
                                       images=str(first_path))

        gt, gt_src = None, ""
        gt_path = Path(groundtruth) if groundtruth is not None else folder / "groundtruth.txt"
        if groundtruth is not None or gt_path.is_file():
            gt = load_groundtruth(gt_path, ts, config.gt_max_dt)
            gt_src = str(gt_path)

        self._depth_files = self._associate_depth(folder, ts, files, config.gt_max_dt)
        super().__init__(folder, calibration=calibration, timestamps=ts, config=config, groundtruth=gt,
                         groundtruth_source=gt_src, color=first.ndim == 3,
                         has_depth=any(d is not None for d in self._depth_files), name=folder.resolve().name,
                         nominal_fps=None)  # measured from the timestamps (TUM: about 30 Hz)

    @staticmethod
    def _associate_depth(folder: Path, ts: np.ndarray, files: list[Path], max_dt: float) -> list[Path | None]:
        listing = folder / "depth.txt"
        if listing.is_file():
            dts, dfiles, dlines = _read_listing(listing, "depth list (depth.txt: 'timestamp filename')", folder)
            out: list[Path | None] = [None] * len(ts)
            i_img, i_dep = matching_time_indices(ts, dts, max_dt)
            for a, b in zip(i_img, i_dep):
                if not dfiles[b].is_file():
                    raise DatasetError(f"{listing}:{dlines[b]}: listed depth image {dfiles[b]} does not exist")
                out[a] = dfiles[b]
            return out
        depth_dir = folder / "depth"
        if depth_dir.is_dir():  # no listing: depth images named like the colour images
            return [(depth_dir / f.name) if (depth_dir / f.name).is_file() else None for f in files]
        return [None] * len(ts)

    def _image_file(self, k: int) -> Path:
        return self._files[k]

    def _source(self, k: int) -> str:
        return str(self._files[k])

    def _read_depth(self, k: int) -> np.ndarray | None:
        f = self._depth_files[k]
        if f is None:
            return None
        d = read_image(f)
        if d.ndim != 2 or d.dtype != np.uint16:
            raise DatasetError(f"{f}: a TUM depth image must be 16-bit single channel, got {d.dtype} {d.shape}")
        return d.astype(np.float32) / np.float32(TUM_DEPTH_FACTOR)


def read_groundtruth_sync(path: str | Path) -> Trajectory:
    """TUM monoVO ``groundtruthSync.txt``: ``timestamp tx ty tz qx qy qz qw`` a frame, ``NaN`` where unknown; rows
    with NaN are skipped."""
    path = Path(path)
    rows = read_table(path, 8, "groundtruthSync.txt ('timestamp tx ty tz qx qy qz qw')")
    ts, vals = [], []
    for n, parts in rows:
        if len(parts) != 8:
            raise DatasetError(f"{path}:{n}: expected 8 numbers, got {len(parts)}")
        try:
            v = [float(p) for p in parts]
        except ValueError:
            raise DatasetError(f"{path}:{n}: not a number in {' '.join(parts)[:80]!r}") from None
        if not np.all(np.isfinite(v)):
            continue
        ts.append(v[0])
        vals.append(v[1:])
    if not ts:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    ts = np.asarray(ts)
    check_increasing(ts, str(path))
    v = np.asarray(vals)
    if np.any(np.linalg.norm(v[:, 3:7], axis=1) < 1e-6):
        raise DatasetError(f"{path}: quaternion of zero length")
    return Trajectory(ts, make_pose(quat_xyzw_to_matrix(v[:, 3:7]), v[:, 0:3]))


class TumMonoSequence(Sequence):
    """TUM monoVO sequence folder (DSO's ``dso_dataset files=... calib=... gamma=... vignette=...``)."""

    layout = "tum_mono"
    looked_for = "TUM monoVO: times.txt with images/ or images.zip"

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return (path / "times.txt").is_file() and ((path / "images").is_dir() or (path / "images.zip").is_file())

    def __init__(self, path: str | Path, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth: str | Path | None = None):
        folder = Path(path)
        config = config or InputConfig()
        self._lock = threading.Lock()
        self._zip: zipfile.ZipFile | None = None
        images_dir, images_zip = folder / "images", folder / "images.zip"
        if images_dir.is_dir():
            self._names = sorted((p.name for p in images_dir.iterdir()
                                  if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS), key=natural_key)
            self._base = str(images_dir)
        elif images_zip.is_file():
            try:
                self._zip = zipfile.ZipFile(images_zip)
            except (zipfile.BadZipFile, OSError) as exc:
                raise DatasetError(f"{images_zip}: not a readable zip archive: {exc}") from None
            self._names = sorted((n for n in self._zip.namelist()
                                  if not n.endswith("/") and Path(n).suffix.lower() in IMAGE_EXTENSIONS),
                                 key=natural_key)
            self._base = str(images_zip)
        else:
            raise DatasetError(f"{folder}: a TUM monoVO folder needs images/ or images.zip")
        if not self._names:
            raise DatasetError(f"{self._base}: no images")

        times = folder / "times.txt"
        rows = read_table(times, 2, "times.txt ('id timestamp [exposure_ms]')")
        if len(rows) != len(self._names):
            raise DatasetError(f"{times}: {len(rows)} entries for {len(self._names)} images in {self._base}")
        ts = np.array([parse_float(p[1], times, n, "timestamp") for n, p in rows])
        check_increasing(ts, str(times), [n for n, _ in rows])
        exposures = None
        if all(len(p) >= 3 for _, p in rows):
            exposures = np.array([parse_float(p[2], times, n, "exposure time") for n, p in rows])
            bad = np.nonzero(exposures <= 0)[0]
            if len(bad):
                raise DatasetError(f"{times}:{rows[int(bad[0])][0]}: exposure time must be positive, got "
                                   f"{exposures[bad[0]]}")

        first = self._read(0)
        size = (first.shape[1], first.shape[0])
        cam = Path(calib) if isinstance(calib, (str, Path)) else folder / "camera.txt"
        if calib is None and not cam.is_file():
            raise DatasetError(f"{folder}: a TUM monoVO folder needs camera.txt (DSO format); {HOW_TO_CALIBRATE}")
        spec = resolve_camera_spec(calib if calib is not None else cam, size)
        calibration = make_calibration(spec, config, find_photometric(folder, size), image_size=size,
                                       images=self._source(0))

        gt, gt_src = None, ""
        if groundtruth is not None:
            gt, gt_src = load_groundtruth(Path(groundtruth), ts, config.gt_max_dt), str(groundtruth)
        elif (folder / "groundtruthSync.txt").is_file():
            traj = read_groundtruth_sync(folder / "groundtruthSync.txt")
            if len(traj):
                gt, gt_src = poses_at_times(ts, traj, config.gt_max_dt), str(folder / "groundtruthSync.txt")
        super().__init__(folder, calibration=calibration, timestamps=ts, config=config, exposures_ms=exposures,
                         groundtruth=gt, groundtruth_source=gt_src, color=first.ndim == 3,
                         name=folder.resolve().name)

    def _read(self, k: int) -> np.ndarray:
        name = self._names[k]
        if self._zip is not None:
            try:
                with self._lock:
                    if self._zip.fp is None:  # closed: reopen
                        self._zip = zipfile.ZipFile(self._base)
                    data = self._zip.read(name)
            except (zipfile.BadZipFile, OSError, KeyError) as exc:
                raise DatasetError(f"{self._base}:{name}: cannot read from the zip archive: {exc}") from None
            return decode_image(data, f"{self._base}:{name}")
        return read_image(Path(self._base) / name)

    def _source(self, k: int) -> str:
        sep = ":" if self._zip is not None else "/"
        return f"{self._base}{sep}{self._names[k]}"

    def close(self) -> None:
        with self._lock:
            if self._zip is not None:
                self._zip.close()
