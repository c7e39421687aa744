"""Open any supported dataset by what its folder holds (or a video by its file type)."""

from __future__ import annotations

from pathlib import Path

from ..config import InputConfig
from .common import CalibArg
from .errors import DatasetError
from .euroc import EurocSequence
from .folder import ImageFolderSequence, VideoSequence
from .images import VIDEO_EXTENSIONS
from .kitti import KittiSequence
from .live import LiveSource, is_live_source
from .replica import ReplicaSequence
from .sequence import Sequence
from .sevenscenes import SevenScenesSequence
from .tum import TumMonoSequence, TumRgbdSequence

__all__ = ["open_sequence", "detect_layout", "LAYOUTS"]

#: The layouts in the order the detection asks them (the first that recognises a path wins: EuRoC's ``mav0`` folder
#: before an image folder, a TUM RGB-D folder's ``rgb.txt`` before its images). A new layout is a
#: :class:`~mgso.io.sequence.Sequence` with ``layout``, ``looked_for`` and ``recognises`` added here.
_DETECTED: tuple[type[Sequence], ...] = (EurocSequence, TumRgbdSequence, TumMonoSequence, KittiSequence,
                                         ReplicaSequence, SevenScenesSequence, ImageFolderSequence, VideoSequence)

LAYOUTS: dict[str, type] = {**{cls.layout: cls for cls in _DETECTED},
                            "live": LiveSource}   # camera:N, rtsp:// http:// udp:// ... (docs/live.md): no length

_LOOKED_FOR = tuple(cls.looked_for for cls in _DETECTED) + (
    "live camera or stream: camera:N, rtsp://..., http://..., udp://... (with --calib)",)


def detect_layout(path: str | Path) -> str:
    """The layout name (a key of :data:`LAYOUTS`) of a dataset folder, video file or live source."""
    if is_live_source(path):
        return "live"
    path = Path(path).expanduser()
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    if path.is_file() and not VideoSequence.recognises(path):
        raise DatasetError(f"{path}: a file that is not a video ({' '.join(VIDEO_EXTENSIONS)}); give a dataset "
                           "folder or a video file")
    for cls in _DETECTED:
        if cls.recognises(path):
            return cls.layout
    raise DatasetError(f"{path}: no known dataset layout here. Looked for: " + "; ".join(_LOOKED_FOR))


def open_sequence(path: str | Path, calib: CalibArg = None, config: InputConfig | None = None, *,
                  layout: str | None = None, groundtruth: str | Path | None = None) -> Sequence:
    """Open a dataset folder or video file as a :class:`Sequence`, detecting its layout; a live camera or stream
    (``camera:N``, ``rtsp://...``, ``http://...``, ...: :func:`mgso.io.live.is_live_source`) as a
    :class:`~mgso.io.live.LiveSource` (no length, no end of its own, ``calib`` required; docs/live.md).

    ``calib``: a calibration file (DSO camera.txt, EuRoC sensor.yaml, KITTI calib.txt, Replica cam_params.json,
    ``fx fy cx cy [k1 k2 p1 p2 [k3]]``) or those numbers as a string, a :class:`~mgso.camera.CameraSpec` or a ready
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
