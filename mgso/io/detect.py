"""Open any supported dataset by what its folder holds (or a video by its file type)."""

from __future__ import annotations

import re
from pathlib import Path

from ..config import InputConfig
from .common import CalibArg
from .errors import DatasetError
from .euroc import EurocSequence, euroc_root
from .folder import ImageFolderSequence, VideoSequence
from .images import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS
from .kitti import KittiSequence
from .live import LiveSource, is_live_source
from .replica import ReplicaSequence
from .sequence import Sequence
from .sevenscenes import SevenScenesSequence
from .tum import TumMonoSequence, TumRgbdSequence

__all__ = ["open_sequence", "detect_layout", "LAYOUTS"]

LAYOUTS: dict[str, type[Sequence]] = {
    "euroc": EurocSequence,
    "tum_rgbd": TumRgbdSequence,
    "tum_mono": TumMonoSequence,
    "kitti": KittiSequence,
    "replica": ReplicaSequence,
    "7scenes": SevenScenesSequence,
    "images": ImageFolderSequence,
    "video": VideoSequence,
    "live": LiveSource,       # camera:N, rtsp:// http:// udp:// ... (docs/live.md); not a Sequence: no length
}

_LOOKED_FOR = (
    "EuRoC: mav0/cam0/data.csv",
    "TUM RGB-D: rgb.txt",
    "TUM monoVO: times.txt with images/ or images.zip",
    "KITTI: image_0/ or image_2/ (with calib.txt, times.txt)",
    "Replica (NICE-SLAM): results/frame*.jpg",
    "7-Scenes: frame-XXXXXX.color.png/.jpg",
    "image folder: image files (" + " ".join(IMAGE_EXTENSIONS) + ")",
    "video file: " + " ".join(VIDEO_EXTENSIONS),
    "live camera or stream: camera:N, rtsp://..., http://..., udp://... (with --calib)",
)


def detect_layout(path: str | Path) -> str:
    """The layout name (a key of :data:`LAYOUTS`) of a dataset folder, video file or live source."""
    if is_live_source(path):
        return "live"
    path = Path(path).expanduser()
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    if path.is_file():
        if path.suffix.lower() in VIDEO_EXTENSIONS:
            return "video"
        raise DatasetError(f"{path}: a file that is not a video ({' '.join(VIDEO_EXTENSIONS)}); give a dataset "
                           "folder or a video file")
    if euroc_root(path) is not None:
        return "euroc"
    if (path / "rgb.txt").is_file():
        return "tum_rgbd"
    if (path / "times.txt").is_file() and ((path / "images").is_dir() or (path / "images.zip").is_file()):
        return "tum_mono"
    if any((path / f"image_{n}").is_dir() for n in range(4)):
        return "kitti"
    if (path / "results").is_dir() and any(
            re.fullmatch(r"frame.*\.(jpg|jpeg|png)", p.name) for p in (path / "results").iterdir()):
        return "replica"
    names = [p.name for p in path.iterdir() if p.is_file()]
    if any(re.fullmatch(r"frame-\d+\.color\.(png|jpg|jpeg)", n, re.IGNORECASE) for n in names):
        return "7scenes"
    if any(Path(n).suffix.lower() in IMAGE_EXTENSIONS for n in names):
        return "images"
    raise DatasetError(f"{path}: no known dataset layout here. Looked for: " + "; ".join(_LOOKED_FOR))


def open_sequence(path: str | Path, calib: CalibArg = None, config: InputConfig | None = None, *,
                  layout: str | None = None, groundtruth: str | Path | None = None) -> Sequence:
    """Open a dataset folder or video file as a :class:`Sequence`, detecting its layout; a live camera or stream
    (``camera:N``, ``rtsp://...``, ``http://...``, ...: :func:`mgso.io.live.is_live_source`) as a
    :class:`~mgso.io.live.LiveSource` (no length, no end of its own, ``calib`` required; docs/live.md).

    ``calib``: a calibration file (DSO camera.txt, EuRoC sensor.yaml, KITTI calib.txt, Replica cam_params.json,
    ``fx fy cx cy [k1 k2 p1 p2 [k3]]``), a :class:`~mgso.camera.CameraSpec` or a ready
    :class:`~mgso.camera.Calibration`; it overrides what the dataset brings. ``config``: frame selection,
    undistortion output, camera choice (:class:`~mgso.config.InputConfig`). ``layout``: skip detection (a key of
    :data:`LAYOUTS`). ``groundtruth``: a TUM or KITTI file of *camera* poses, overriding the dataset's own.
    """
    name = layout or detect_layout(path)
    if name == "live":    # a URL is no Path (Path("rtsp://h/x") would lose a slash)
        return LiveSource(str(path), calib=calib, config=config or InputConfig(), groundtruth=groundtruth)
    path = Path(path).expanduser()
    if name not in LAYOUTS:
        raise DatasetError(f"unknown layout {name!r}; known: {sorted(LAYOUTS)}")
    return LAYOUTS[name](path, calib=calib, config=config or InputConfig(), groundtruth=groundtruth)
