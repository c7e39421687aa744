"""The one interface every dataset reader implements: :class:`Sequence` of :class:`Frame`.

- Frames are decoded lazily (:meth:`Sequence.load`); iterating (:meth:`Sequence.frames`) decodes ahead in a
  background thread with a small bounded queue (OpenCV releases the GIL while decoding and remapping).
- ``start / end / stride`` of :class:`~mgso.config.InputConfig` select the frames; indices ``0 .. len - 1`` of a
  sequence are positions in that selection, and ``Frame.index`` is that position.
- Timestamps are seconds (float64), strictly increasing. Ground truth is camera-to-world of the *camera* (x right,
  y down, z forward), at the frame timestamps, only for frames that have it.
"""

from __future__ import annotations

import abc
import logging
import queue
import threading
from pathlib import Path
from typing import Callable, ClassVar, Iterator

import cv2
import numpy as np

from ..camera import Calibration
from ..config import InputConfig
from .errors import DatasetError
from .images import check_increasing, decode_image, is_jpeg, read_bytes, read_image
from .trajectory import Trajectory, matching_time_indices

__all__ = ["Frame", "Sequence", "poses_at_times"]

log = logging.getLogger(__name__)


class Frame:
    """One input frame, ready for the tracker and the map.

    - ``index``: position in the sequence (after start/end/stride); ``timestamp``: seconds (float).
    - ``gray``: float32 ``[H, W]`` on the 0-255 scale, undistorted and photometrically corrected when the calibration
      has a response / vignette (what DSO tracks on).
    - ``rgb``: float32 ``[H, W, 3]`` in [0, 1], undistorted, not photometrically corrected (gray datasets: the gray
      image replicated). Computed on first access and kept (the mapper needs it for keyframes only).
    - ``exposure_ms``: exposure time in milliseconds when the dataset records it, else ``None``.
    - ``source``: the file (or video position) the frame came from, for messages.
    - ``valid``: bool ``[H, W]`` (read-only, the same array for every frame of a sequence), False at the pixels that
      have no source in the recorded image (the border undistortion leaves; they hold the nearest recorded pixel, not
      black), or ``None`` when every pixel has one. Consumers that compare or train on pixels should leave the False
      ones out (:attr:`valid_weights`).
    """

    __slots__ = ("index", "timestamp", "gray", "exposure_ms", "source", "valid", "_rgb", "_rgb_fn")

    def __init__(self, index: int, timestamp: float, gray: np.ndarray, exposure_ms: float | None = None,
                 source: str = "", rgb: np.ndarray | None = None,
                 rgb_fn: Callable[[], np.ndarray] | None = None, valid: np.ndarray | None = None):
        self.index = int(index)
        self.timestamp = float(timestamp)
        self.gray = gray
        self.exposure_ms = None if exposure_ms is None else float(exposure_ms)
        self.source = source
        self._rgb = rgb
        self._rgb_fn = rgb_fn
        if rgb is None and rgb_fn is None:
            raise ValueError("Frame needs rgb or a function computing it")
        if valid is not None:
            valid = np.asarray(valid)
            if valid.dtype != np.bool_ or valid.shape != gray.shape[:2]:
                raise ValueError(f"Frame.valid must be a bool array of the image's shape {gray.shape[:2]}, got "
                                 f"{valid.dtype} {valid.shape}")
        self.valid = valid

    @property
    def valid_weights(self) -> np.ndarray | None:
        """``valid`` as float32 loss weights (1 = a pixel with a source, 0 = none), or ``None`` when all are valid."""
        return None if self.valid is None else self.valid.astype(np.float32)

    @property
    def rgb(self) -> np.ndarray:
        if self._rgb is None:
            self._rgb = self._rgb_fn()
            self._rgb_fn = None
        return self._rgb

    @property
    def height(self) -> int:
        return int(self.gray.shape[0])

    @property
    def width(self) -> int:
        return int(self.gray.shape[1])

    def __repr__(self) -> str:
        return (f"Frame(index={self.index}, timestamp={self.timestamp:.6f}, size={self.width}x{self.height}, "
                f"exposure_ms={self.exposure_ms}, source={self.source!r})")


def poses_at_times(frame_times: np.ndarray, traj: Trajectory, max_dt: float) -> np.ndarray:
    """``(N, 4, 4)`` pose of ``traj`` nearest in time to each frame time (within ``max_dt`` s), NaN where none."""
    out = np.full((len(frame_times), 4, 4), np.nan)
    i_frame, i_traj = matching_time_indices(frame_times, traj.timestamps, max_dt)
    out[i_frame] = traj.cam_to_world[i_traj]
    return out


_END = object()


class Sequence(abc.ABC):
    """A dataset: frames, timestamps, calibration, optional ground truth and depth.

    Subclasses read the raw data: :meth:`_read` (raw decoded image of underlying frame ``k``), :meth:`_source`,
    and optionally :meth:`_read_depth`. The base class selects frames, checks sizes, applies the calibration.
    """

    layout: ClassVar[str] = "abstract"
    #: what :func:`mgso.io.detect.detect_layout` looks for (said when a folder matches no layout)
    looked_for: ClassVar[str] = ""

    @classmethod
    def recognises(cls, path: Path) -> bool:
        """Whether ``path`` (an existing file or folder) holds this layout; the detection asks the layouts in
        :data:`mgso.io.detect.LAYOUTS`' order and takes the first that says yes."""
        return False

    def __init__(self, path: Path, *, calibration: Calibration, timestamps: np.ndarray,
                 config: InputConfig | None = None, exposures_ms: np.ndarray | None = None,
                 groundtruth: np.ndarray | None = None, groundtruth_source: str = "", color: bool = False,
                 has_depth: bool = False, name: str | None = None, nominal_fps: float | None = None):
        self.path = Path(path)
        self.config = config if config is not None else InputConfig()
        self.calibration = calibration
        self._ts_all = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        n = len(self._ts_all)
        if n == 0:
            raise DatasetError(f"{self.path}: no frames")
        if not np.all(np.isfinite(self._ts_all)):
            raise DatasetError(f"{self.path}: non-finite timestamp")
        check_increasing(self._ts_all, str(self.path))
        self._exp_all = None if exposures_ms is None else np.asarray(exposures_ms, dtype=np.float64).reshape(-1)
        if self._exp_all is not None and len(self._exp_all) != n:
            raise DatasetError(f"{self.path}: {len(self._exp_all)} exposure times for {n} frames")
        if groundtruth is not None:
            groundtruth = np.asarray(groundtruth, dtype=np.float64).reshape(-1, 4, 4)
            if len(groundtruth) != n:
                raise DatasetError(f"{groundtruth_source or self.path}: {len(groundtruth)} ground-truth poses for "
                                   f"{n} frames")
            if not np.isfinite(groundtruth).any():
                groundtruth = None
        self._gt_all = groundtruth
        self.groundtruth_source = groundtruth_source if groundtruth is not None else ""
        self.color = bool(color)
        self.has_depth = bool(has_depth)
        self.name = name or self.path.stem or str(self.path)
        self._nominal_fps = nominal_fps
        self._indices = self._select(n)
        self._gt_cache: Trajectory | None = None

    # ------------------------------------------------------------------------------------------- selection
    def _select(self, n: int) -> np.ndarray:
        c = self.config
        if c.start < 0 or c.end < 0 or c.stride < 1:
            raise DatasetError(f"{self.path}: input.start and input.end must be >= 0 and input.stride >= 1, got "
                               f"start={c.start}, end={c.end}, stride={c.stride}")
        end = n if c.end == 0 else min(c.end, n)
        if c.start >= end:
            raise DatasetError(f"{self.path}: input.start={c.start} selects no frames (the sequence has {n} frames"
                               + (f", end={c.end}" if c.end else "") + ")")
        return np.arange(c.start, end, c.stride, dtype=np.int64)

    @property
    def frames_total(self) -> int:
        """Frames in the dataset before start/end/stride."""
        return len(self._ts_all)

    @property
    def source_indices(self) -> np.ndarray:
        """Index in the full dataset of each selected frame."""
        return self._indices.copy()

    def __len__(self) -> int:
        return len(self._indices)

    def _k(self, i: int) -> int:
        n = len(self._indices)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {self.name} with {n} frames")
        return int(self._indices[i])

    # ------------------------------------------------------------------------------------------- raw access
    def _read(self, k: int) -> np.ndarray:
        """Raw decoded image of underlying frame ``k``: uint8/uint16, gray ``[H, W]`` or BGR ``[H, W, 3]``. By
        default the layout's :meth:`_image_file`, decoded as stored; a layout without one file a frame (a video, an
        archive) overrides this."""
        path = self._image_file(k)
        if path is None:
            raise NotImplementedError(f"{type(self).__name__} has neither _read nor _image_file")
        return read_image(path)

    @abc.abstractmethod
    def _source(self, k: int) -> str:
        """Where underlying frame ``k`` comes from (a path), for messages."""

    def _image_file(self, k: int) -> Path | None:
        """The image file of underlying frame ``k`` when the layout keeps one file a frame (:meth:`_read` decodes it
        as stored), ``None`` otherwise (a video, an archive: those override :meth:`_read`). :meth:`load` then reads
        the file once and decodes a JPEG's gray straight from its luma plane, its colour only when the frame's RGB is
        asked for (keyframes)."""
        return None

    def _read_depth(self, k: int) -> np.ndarray | None:
        """Depth of underlying frame ``k`` in metres, float32, input geometry; ``None`` when absent."""
        return None

    # ------------------------------------------------------------------------------------------- public
    def timestamp(self, i: int) -> float:
        """Timestamp of frame ``i`` in seconds."""
        return float(self._ts_all[self._k(i)])

    @property
    def timestamps(self) -> np.ndarray:
        """(N,) float64 seconds of the selected frames."""
        return self._ts_all[self._indices].copy()

    def exposure_ms(self, i: int) -> float | None:
        if self._exp_all is None:
            return None
        return float(self._exp_all[self._k(i)])

    def frame_source(self, i: int) -> str:
        return self._source(self._k(i))

    @property
    def fps(self) -> float:
        """Nominal frame rate of the selection: the layout's rate (KITTI 10, EuRoC 20, TUM RGB-D and 7-Scenes 30, a
        video's container rate, ``input.fps`` where timestamps are made up) divided by the stride; where the layout
        has no nominal rate (timestamps from a file), :attr:`measured_fps`."""
        if self._nominal_fps:
            return float(self._nominal_fps) / self.config.stride
        return self.measured_fps

    @property
    def measured_fps(self) -> float:
        """1 / median interval of the selected timestamps (``input.fps`` / stride for a single frame)."""
        ts = self.timestamps
        if len(ts) >= 2:
            return float(1.0 / np.median(np.diff(ts)))
        return float(self.config.fps) / self.config.stride

    def _sized(self, raw: np.ndarray, k: int) -> np.ndarray:
        w, h = self.calibration.input_size
        if raw.shape[1] != w or raw.shape[0] != h:
            raise DatasetError(f"{self._source(k)}: image is {raw.shape[1]}x{raw.shape[0]} but the calibration "
                               f"({self.calibration.source or 'camera'}) and the other images are {w}x{h}")
        return raw

    def load_raw(self, i: int) -> np.ndarray:
        """The raw decoded image of frame ``i`` (input geometry, as stored), with its size checked."""
        k = self._k(i)
        return self._sized(self._read(k), k)

    def load(self, i: int) -> Frame:
        """Decode, photometrically correct and undistort frame ``i``.

        A JPEG file's gray is its luma plane, decoded without the colour (what the reference DSO reads; the decoded
        colour converted differs only where saturated colour clips: 0.8 % of 7-Scenes' pixels, at most 8 grey levels);
        the colour is decoded from the file's bytes, kept with the frame, when its RGB is first asked for (a colour
        decode that fails then raises the same :class:`DatasetError`). Other images are decoded once, as stored, and
        converted."""
        k = self._k(i)
        path = self._image_file(k)
        data = read_bytes(path) if path is not None else None
        if data is not None and is_jpeg(data):
            src = self._source(k)
            gray_raw = self._sized(decode_image(data, src, gray=True), k)
            raw_of: Callable[[], np.ndarray] = lambda: self._sized(decode_image(data, src), k)  # noqa: E731
        else:
            raw = self._sized(self._read(k) if data is None else decode_image(data, self._source(k)), k)
            gray_raw = raw if raw.ndim == 2 else cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
            raw_of = lambda: raw  # noqa: E731
        try:
            gray = self.calibration.gray_from_raw(gray_raw, photometric=self.config.photometric)
        except DatasetError:
            raise
        except ValueError as exc:  # e.g. a 16-bit raw value beyond an 8-bit response curve
            raise DatasetError(f"{self._source(k)}: {exc}") from None
        calib = self.calibration
        exp = None if self._exp_all is None else float(self._exp_all[k])
        return Frame(i if i >= 0 else i + len(self), float(self._ts_all[k]), gray, exp, self._source(k),
                     rgb_fn=lambda: calib.rgb_from_raw(raw_of()), valid=calib.valid_mask)

    __getitem__ = load

    def load_depth(self, i: int) -> np.ndarray | None:
        """Depth of frame ``i`` in metres (float32 ``[H, W]``, 0 = invalid), undistorted with nearest-neighbour
        sampling; ``None`` when the dataset has no depth for it. For checking geometry, never a tracking input."""
        k = self._k(i)
        d = self._read_depth(k)
        if d is None:
            return None
        w, h = self.calibration.input_size
        if d.shape[:2] != (h, w):
            raise DatasetError(f"{self._source(k)}: depth is {d.shape[1]}x{d.shape[0]}, the images are {w}x{h}")
        return self.calibration.undistorter.apply_nearest(d)

    @property
    def groundtruth(self) -> Trajectory | None:
        """Camera-to-world of the camera at the timestamps of the selected frames that have ground truth."""
        if self._gt_all is None:
            return None
        if self._gt_cache is None:
            poses = self._gt_all[self._indices]
            keep = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
            if not keep.any():
                return None
            self._gt_cache = Trajectory(self._ts_all[self._indices][keep], poses[keep])
        return self._gt_cache

    def groundtruth_cam_to_world(self, i: int) -> np.ndarray | None:
        """Ground-truth camera-to-world (4x4) of frame ``i``, or ``None``."""
        if self._gt_all is None:
            return None
        T = self._gt_all[self._k(i)]
        return T.copy() if np.all(np.isfinite(T)) else None

    def frames(self, prefetch: int | None = None, on_unreadable=None) -> Iterator[Frame]:
        """Iterate over the frames; with ``prefetch > 0`` (default ``InputConfig.prefetch``) a background thread
        decodes up to that many frames ahead. Errors of the reader are raised here, in order.

        ``on_unreadable(index, error)``: called when frame ``index`` cannot be read (a :class:`DatasetError`: a
        truncated or corrupt image, a wrong size); returning true skips the frame and goes on, false raises the
        error (``None``: raise). The caller decides (``input.on_bad_frame``) and counts."""
        n_ahead = self.config.prefetch if prefetch is None else int(prefetch)

        def load(i: int) -> Frame | None:
            try:
                return self.load(i)
            except DatasetError as exc:
                if on_unreadable is not None and on_unreadable(i, exc):
                    return None
                raise

        if n_ahead <= 0:
            for i in range(len(self)):
                f = load(i)
                if f is not None:
                    yield f
            return
        q: queue.Queue = queue.Queue(maxsize=n_ahead)
        stop = threading.Event()

        def put(item) -> bool:
            while not stop.is_set():
                try:
                    q.put(item, timeout=0.05)
                    return True
                except queue.Full:
                    continue
            return False

        def work():
            try:
                for i in range(len(self)):
                    if stop.is_set():
                        return
                    f = load(i)
                    if f is not None and not put(f):
                        return
            except BaseException as exc:  # handed to the consumer, raised there
                put(exc)
                return
            put(_END)

        thread = threading.Thread(target=work, name=f"mgso-prefetch-{self.name}", daemon=True)
        thread.start()
        try:
            while True:
                item = q.get()
                if item is _END:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            stop.set()
            thread.join(timeout=5.0)

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def close(self) -> None:
        """Release open files (a video capture, a zip archive); loading again reopens them where possible."""

    def __enter__(self) -> "Sequence":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> dict:
        """What ``mgso info`` prints: layout, sizes, intrinsics, calibration, ground truth, time span."""
        cal = self.calibration
        ts = self.timestamps
        gt = self.groundtruth
        c = self.config
        out = cal.output
        return {
            "layout": self.layout,
            "name": self.name,
            "path": str(self.path),
            "frames": len(self),
            "frames_total": self.frames_total,
            "selection": {"start": c.start, "end": c.end, "stride": c.stride},
            "color": self.color,
            "image_size_in": list(cal.input_size),
            "image_size_out": list(cal.output_size),
            "camera_model": cal.input.model_name,
            "distortion": cal.input.distortion,
            "intrinsics_in": {"fx": cal.input.fx, "fy": cal.input.fy, "cx": cal.input.cx, "cy": cal.input.cy},
            "intrinsics": {"fx": out.fx, "fy": out.fy, "cx": out.cx, "cy": out.cy},
            "rectify": cal.output_mode,
            "undistortion": cal.undistorter.kind,
            "valid_fraction": cal.undistorter.valid_fraction,
            "calibration_source": cal.source or None,
            "photometric": {**cal.photometric.describe(), "exposure": self._exp_all is not None,
                            "applied": bool(c.photometric and not cal.photometric.is_identity)},
            "groundtruth": {"present": gt is not None, "poses": 0 if gt is None else len(gt),
                            "source": self.groundtruth_source or None},
            "depth": self.has_depth,
            "time_span": [float(ts[0]), float(ts[-1])],
            "duration_s": float(ts[-1] - ts[0]),
            "fps": self.fps,
            "fps_measured": self.measured_fps,
        }

    def __repr__(self) -> str:
        w, h = self.calibration.output_size
        return f"{type(self).__name__}({str(self.path)!r}, frames={len(self)}, {w}x{h})"
