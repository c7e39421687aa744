"""A live camera or stream as input: ``camera:N``, ``rtsp://...``, ``http(s)://...``, ``udp://...`` and the other
network schemes OpenCV's FFmpeg capture opens (docs/live.md).

A live source has no length and no end of its own:

- a capture thread (started at the first frame asked for) reads frames as fast as the device or stream gives them;
  the newest frame waits in a one-frame slot, and a frame that was not taken before the next one came is dropped
  (counted in :attr:`LiveSource.dropped`), never queued;
- timestamps come from the capture's clock (``CAP_PROP_POS_MSEC``: a V4L2 buffer's time, an RTSP/UDP stream's
  presentation time) while it is meaningful (increasing, and after 1 s running at the rate of the local clock within
  10 %, never more than 1 s apart from it), else from ``time.monotonic()`` at the grab (always for ``http(s)://``:
  an MJPEG stream's "time" counts frames at a made-up rate); either way on the Unix-time scale of the first frame and
  strictly increasing;
- it ends when the user stops it (Ctrl-C, SIGTERM: the run's signal handling), when a bounded run's limit is reached
  (``input.live_max_frames``, ``input.live_duration_s``), or when the source delivers nothing for
  ``input.live_timeout_s`` seconds (a camera unplugged, a stream gone), which is treated as the end of the input with
  a warning.

The calibration is required (``calib=``, ``mgso run --calib FILE``): there is no folder to look in. A live source has
no ground truth and cannot read a frame back (:meth:`LiveSource.load` refuses). :attr:`LiveSource.live` is what the
real-time :class:`mgso.system.Player` and the application look for: played without pacing, frames older than
``system.max_lag_ms`` dropped once a newer one waits.

For tests (no camera here), ``pace_fps`` reads a video *file* through the same code as a stream, released at that
frame rate (``LiveSource(path, pace_fps=...)``); at its last frame it stalls like an unplugged camera.
"""

from __future__ import annotations

import collections
import logging
import os
import re
import threading
import time
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from ..config import InputConfig
from .common import CalibArg, make_calibration, resolve_camera_spec
from .errors import DatasetError
from .sequence import Frame

__all__ = ["LiveSource", "is_live_source", "LIVE_SCHEMES"]

log = logging.getLogger(__name__)

#: URL schemes opened as network streams (OpenCV's FFmpeg capture).
LIVE_SCHEMES = ("rtsp", "rtsps", "rtmp", "rtmps", "http", "https", "udp", "tcp", "srt", "rtp")
_CAMERA_RE = re.compile(r"camera:(\d+)", re.IGNORECASE)
_URL_RE = re.compile(r"([a-z][a-z0-9+.-]*)://", re.IGNORECASE)

HOW_TO_CALIBRATE_LIVE = ("give its calibration with --calib FILE (calib=PATH): a DSO camera.txt ('Pinhole fx fy cx "
                         "cy 0' / 'RadTan fx fy cx cy k1 k2 p1 p2' / ..., then 'width height'), one line 'fx fy cx cy "
                         "[k1 k2 p1 p2 [k3]]' in pixels of the stream's frames, an EuRoC sensor.yaml or a KITTI "
                         "calib.txt (docs/live.md)")


def is_live_source(path) -> bool:
    """Whether ``path`` names a live source: ``camera:N`` or a URL of one of :data:`LIVE_SCHEMES`."""
    if not isinstance(path, str):
        return False
    s = path.strip()
    if _CAMERA_RE.fullmatch(s):
        return True
    m = _URL_RE.match(s)
    return bool(m and m.group(1).lower() in LIVE_SCHEMES)


def _describe_source(source: str) -> str:
    m = _CAMERA_RE.fullmatch(source)
    return f"camera {m.group(1)}" if m else source


def _name_of(source: str) -> str:
    m = _CAMERA_RE.fullmatch(source)
    if m:
        return f"camera{m.group(1)}"
    host = re.sub(r"^[a-z][a-z0-9+.-]*://", "", source, flags=re.IGNORECASE)
    host = host.split("@")[-1]
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", host).strip("_.")
    return name[:60] or "stream"


class _CaptureClock:
    """Timestamps of captured frames (see the module doc): the capture's clock while it is meaningful, else the
    local monotonic clock, on the Unix-time scale of the first frame, strictly increasing."""

    MAX_APART_S = 1.0
    RATE_TOLERANCE = 0.10
    RATE_AFTER_S = 1.0

    def __init__(self, use_capture_clock: bool = True):
        self.use_capture = use_capture_clock
        self.source = "capture" if use_capture_clock else "monotonic"
        self._wall0 = self._mono0 = self._pos0 = None
        self._last_ts = self._last_mono = None
        self._last_pos = None

    def stamp(self, pos_msec: float, mono: float) -> float:
        if self._wall0 is None:
            self._wall0, self._mono0, self._pos0 = time.time(), mono, pos_msec
            self._last_ts, self._last_mono, self._last_pos = self._wall0, mono, pos_msec
            if not (np.isfinite(pos_msec) and pos_msec >= 0):
                self._switch("it gave no time")
            return self._wall0
        ts = None
        if self.source == "capture":
            elapsed_pos = (pos_msec - self._pos0) / 1000.0
            elapsed_mono = mono - self._mono0
            if not (np.isfinite(pos_msec) and pos_msec > self._last_pos):
                self._switch("its times are not increasing")
            elif abs(elapsed_pos - elapsed_mono) > self.MAX_APART_S:
                self._switch(f"it is {elapsed_pos - elapsed_mono:+.2f} s apart from the local clock")
            elif elapsed_mono >= self.RATE_AFTER_S and abs(elapsed_pos / elapsed_mono - 1.0) > self.RATE_TOLERANCE:
                self._switch(f"it runs at {elapsed_pos / elapsed_mono:.2f}x the local clock")
            else:
                ts = self._wall0 + elapsed_pos
        if ts is None:   # monotonic, continuing from the last timestamp
            ts = self._last_ts + (mono - self._last_mono)
        ts = max(ts, self._last_ts + 1e-6)
        self._last_ts, self._last_mono, self._last_pos = ts, mono, pos_msec
        return ts

    def _switch(self, why: str) -> None:
        if self.source == "capture" and self.use_capture:
            log.info("live source: the capture's clock (CAP_PROP_POS_MSEC) is not used from here on: %s; "
                     "timestamps from the local monotonic clock at each grab", why)
        self.source = "monotonic"


class LiveSource:
    """A live camera or stream (see the module doc). ``source``: ``camera:N``, a stream URL, or (``pace_fps``) a video
    file read as a stream. ``calib``: required. ``config``: ``live_timeout_s``, ``live_max_frames``,
    ``live_duration_s``, ``width``/``height``/``rectify`` as for any input.

    Iterate :meth:`frames` (one iteration at a time); :attr:`captured`, :attr:`dropped` count frames; after the
    iteration :attr:`end_reason` says why it ended (``timeout``, ``max_frames``, ``duration``, ``interrupt``: the run's
    :meth:`end` on the first Ctrl-C, ``stopped``)."""

    layout = "live"
    live = True

    def __init__(self, source: str, calib: CalibArg = None, config: InputConfig | None = None,
                 groundtruth=None, *, pace_fps: float | None = None):
        self.config = config or InputConfig()
        self.source = str(source).strip()
        self.path = self.source
        self.name = _name_of(self.source)
        self.what = _describe_source(self.source)
        self.pace_fps = None if pace_fps is None else float(pace_fps)
        if self.pace_fps is not None and not self.pace_fps > 0:
            raise DatasetError(f"{self.what}: pace_fps must be positive, got {pace_fps}")
        if groundtruth is not None:
            raise DatasetError(f"{self.what}: a live source has no ground truth (--groundtruth is for recorded "
                               "sequences)")
        self.groundtruth = None
        self.groundtruth_source = ""
        self.has_depth = False
        if calib is None:
            raise DatasetError(f"{self.what}: a live source needs a calibration; {HOW_TO_CALIBRATE_LIVE}")
        self._cap = self._open()
        try:
            ok, first = self._cap.read()     # a probe for the image size; not delivered
            if not ok or first is None:
                raise DatasetError(f"{self.what}: opened, but no frame came (a camera in use by another program, "
                                   "a stream without video, or a codec OpenCV's FFmpeg lacks)")
            first = _plain(first)
            size = (first.shape[1], first.shape[0])
            spec = resolve_camera_spec(calib, size)
            self.calibration = make_calibration(spec, self.config, None, image_size=size,
                                                images=f"the frames of {self.what}")
        except BaseException:
            self._cap.release()
            self._cap = None
            raise
        self.color = first.ndim == 3
        fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self._nominal_fps = self.pace_fps or (fps if 0 < fps < 1000 else None)
        # the capture thread and the consumer share these (under self._cond)
        self._cond = threading.Condition()
        self._slot: tuple | None = None        # (index, timestamp, raw image)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._ended = ""                       # the capture thread's own reason to end (a limit)
        self._last_capture = 0.0               # monotonic time of the last captured frame
        self._times: collections.deque = collections.deque(maxlen=256)   # (index, timestamp) of recent frames
        self._iterating = False
        self.captured = 0
        self.dropped = 0
        self.delivered = 0
        self.end_reason = ""
        # an MJPEG stream over HTTP numbers its frames at a made-up rate: its "time" is never the camera's
        self.clock = _CaptureClock(use_capture_clock=not re.match(r"https?://", self.source, re.IGNORECASE))

    # ------------------------------------------------------------------------------------------- opening
    def _open(self) -> cv2.VideoCapture:
        timeout_ms = int(max(1.0, self.config.live_timeout_s) * 1000)
        # FFmpeg's own lines ("Connection refused"): our one line says it. Read once, when OpenCV first loads FFmpeg
        # (any capture, a camera's too); OPENCV_FFMPEG_LOGLEVEL set by the user wins
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
        old_level = _quiet_opencv()
        try:
            m = _CAMERA_RE.fullmatch(self.source)
            if m:
                cap = cv2.VideoCapture(int(m.group(1)))
            elif self.pace_fps is not None:
                if not Path(self.source).is_file():
                    raise DatasetError(f"{self.source}: video file not found")
                cap = cv2.VideoCapture(self.source)
            else:
                cap = cv2.VideoCapture(self.source, cv2.CAP_FFMPEG,
                                       [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms,
                                        cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms])
        except cv2.error as exc:
            raise DatasetError(f"{self.what}: cannot be opened ({str(exc).strip().splitlines()[-1]})") from None
        finally:
            _restore_opencv(old_level)
        if not cap.isOpened():
            cap.release()
            hint = ("no such camera, or it is in use or not permitted" if _CAMERA_RE.fullmatch(self.source)
                    else "nothing answers there, the address or path is wrong, or the stream is not video "
                         "OpenCV's FFmpeg can read")
            raise DatasetError(f"{self.what}: cannot be opened ({hint})")
        return cap

    # ------------------------------------------------------------------------------------------- capture
    def _capture(self) -> None:
        cap = self._cap
        c = self.config
        t_pace = None
        n_pace = 0
        old_level = _quiet_opencv()
        try:
            while not self._stop.is_set() and not self._ended:
                if self.pace_fps is not None:
                    if t_pace is None:
                        t_pace = time.monotonic()
                    wait = t_pace + n_pace / self.pace_fps - time.monotonic()
                    if wait > 0 and self._stop.wait(wait):
                        break
                    n_pace += 1
                ok, img = cap.read()
                mono = time.monotonic()
                if not ok or img is None:
                    # nothing now (a stall, the end of a stand-in file): the consumer's timeout decides
                    if self._stop.wait(0.01 if self.pace_fps is None else 1.0 / self.pace_fps):
                        break
                    continue
                ts = self.clock.stamp(float(cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0), mono)
                with self._cond:
                    if self._ended or self._stop.is_set():
                        # the stream ended (Ctrl-C: end(); a close) while this frame was being read: it is not part
                        # of the run. Counted, it was a frame captured that nobody read or dropped (CI: captured 47
                        # against 46 read after a Ctrl-C)
                        break
                    if c.live_duration_s > 0 and self.captured and ts - self._first_ts >= c.live_duration_s:
                        self._ended = "duration"
                        self._cond.notify_all()
                        break
                    if self.captured == 0:
                        self._first_ts = ts
                    index = self.captured
                    self.captured += 1
                    if self._slot is not None:
                        self.dropped += 1
                    self._slot = (index, ts, _plain(img))
                    self._times.append((index, ts))
                    self._last_capture = mono
                    if c.live_max_frames > 0 and self.captured >= c.live_max_frames:
                        self._ended = "max_frames"
                    self._cond.notify_all()
                if self._ended:
                    break
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            with self._cond:
                self._error = exc
                self._cond.notify_all()
        finally:
            _restore_opencv(old_level)

    def frames(self, prefetch: int | None = None, on_unreadable=None) -> "_LiveFrames":
        """The frames as they come (see the class doc); ``prefetch`` is ignored (the capture thread is the reader).
        ``on_unreadable(index, error)``: a frame that cannot be used (a size that changed mid-stream) is skipped when
        it returns true, else the error is raised."""
        if self._cap is None:
            raise DatasetError(f"{self.what}: the live source was closed")
        if self._iterating or (self._thread is not None and self._thread.is_alive()):
            raise DatasetError(f"{self.what}: a live source can be iterated once at a time")
        self._iterating = True
        return _LiveFrames(self, on_unreadable)

    def _start_capture(self) -> None:
        """At the first frame asked for (not when :meth:`frames` is called: what the device gives while the run is
        still starting, its mapper's process spawning, would only be dropped)."""
        self._first_ts = 0.0
        self._stop.clear()
        self._slot, self._ended, self._error, self.end_reason = None, "", None, ""
        self._last_capture = time.monotonic()
        self._thread = threading.Thread(target=self._capture, name=f"mgso-capture-{self.name}", daemon=True)
        self._thread.start()

    def _next_raw(self, closed: threading.Event):
        """The next captured frame ``(index, timestamp, raw)``, or ``None`` at the end (see the module doc)."""
        timeout = float(self.config.live_timeout_s)
        with self._cond:
            while True:
                if self._error is not None:
                    exc, self._error = self._error, None
                    if isinstance(exc, (DatasetError, KeyboardInterrupt)):
                        raise exc
                    raise DatasetError(f"{self.what}: reading failed: {type(exc).__name__}: {exc}") from exc
                if self._slot is not None:
                    item, self._slot = self._slot, None
                    return item
                if closed.is_set() or self._stop.is_set():
                    self.end_reason = self.end_reason or "stopped"
                    return None
                if self._ended:
                    self.end_reason = self._ended
                    if self._ended != "interrupt":
                        log.info("%s: %s reached: the end of the input", self.what,
                                 f"input.live_max_frames={self.config.live_max_frames}" if self._ended == "max_frames"
                                 else f"input.live_duration_s={self.config.live_duration_s}")
                    return None
                idle = time.monotonic() - self._last_capture
                if idle >= timeout:
                    self.end_reason = "timeout"
                    log.warning("%s: no frame for %.1f s (input.live_timeout_s; a camera unplugged, a stream gone?): "
                                "ending the run as at the end of the input, after %d frames", self.what, idle,
                                self.captured)
                    return None
                self._cond.wait(min(0.1, timeout - idle))

    def end(self) -> bool:
        """End the stream here, as a limit would (``end_reason`` ``interrupt``): the iteration stops within 0.1 s
        and the run finishes as at the end of its input, final refinement included. Returns whether this ended a
        stream that was delivering; ``False`` when it had already ended or was not started (a caller then stops the
        run its usual way). Safe from a signal handler: it only sets a flag that the capture thread and the consumer
        poll, and takes no lock (the handler may run while this thread holds one)."""
        if not self._iterating or self._thread is None or self._ended or self._stop.is_set() or self.end_reason:
            return False
        self._ended = "interrupt"
        return True

    def _frame(self, index: int, ts: float, raw: np.ndarray) -> Frame:
        w, h = self.calibration.input_size
        if raw.shape[1] != w or raw.shape[0] != h:
            raise DatasetError(f"{self.what}: frame {index} is {raw.shape[1]}x{raw.shape[0]} but the calibration "
                               f"({self.calibration.source or 'camera'}) and the first frame are {w}x{h}")
        gray_raw = raw if raw.ndim == 2 else cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
        gray = self.calibration.gray_from_raw(gray_raw, photometric=self.config.photometric)
        calib = self.calibration
        return Frame(index, ts, gray, None, f"{self.source}#frame{index}", rgb_fn=lambda: calib.rgb_from_raw(raw),
                     valid=calib.valid_mask)

    def _end_iteration(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._iterating = False

    # ------------------------------------------------------------------------------------------- the Sequence face
    def __len__(self) -> int:
        """Frames captured so far (a live source has no length; this is 0 before :meth:`frames`)."""
        return self.captured

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames())

    def timestamp(self, i: int) -> float:
        """The timestamp of a recent frame ``i`` (the last 256 captured)."""
        with self._cond:
            for k, ts in self._times:
                if k == i:
                    return ts
        raise IndexError(f"{self.what}: frame {i} is not a recent frame")

    def load(self, i: int) -> Frame:
        raise DatasetError(f"{self.what}: a live source cannot read frame {i} back (only what it delivers as it "
                           "comes)")

    __getitem__ = load

    @property
    def timestamps(self) -> np.ndarray:
        raise DatasetError(f"{self.what}: a live source has no list of timestamps")

    @property
    def fps(self) -> float:
        """The nominal frame rate the device or stream reports (``input.fps`` when it reports none)."""
        return float(self._nominal_fps or self.config.fps)

    def describe(self) -> dict:
        """What ``mgso info`` prints (and ``sequence.json`` holds); ``frames`` is ``None``: a live source has no
        length."""
        cal = self.calibration
        out = cal.output
        return {
            "layout": self.layout, "name": self.name, "path": self.source, "live": True,
            "frames": None, "frames_total": None,
            "color": self.color,
            "image_size_in": list(cal.input_size), "image_size_out": list(cal.output_size),
            "camera_model": cal.input.model_name, "distortion": cal.input.distortion,
            "intrinsics_in": {"fx": cal.input.fx, "fy": cal.input.fy, "cx": cal.input.cx, "cy": cal.input.cy},
            "intrinsics": {"fx": out.fx, "fy": out.fy, "cx": out.cx, "cy": out.cy},
            "rectify": cal.output_mode, "undistortion": cal.undistorter.kind,
            "valid_fraction": cal.undistorter.valid_fraction, "calibration_source": cal.source or None,
            "photometric": {**cal.photometric.describe(), "exposure": False,
                            "applied": bool(self.config.photometric and not cal.photometric.is_identity)},
            "groundtruth": {"present": False, "poses": 0, "source": None},
            "depth": False,
            "fps": self.fps,
            "live_timeout_s": self.config.live_timeout_s,
            "live_max_frames": self.config.live_max_frames, "live_duration_s": self.config.live_duration_s,
        }

    def end_info(self) -> dict:
        """What ``metrics.json`` keeps of the capture: frames captured, replaced at the source, the clock of the
        timestamps and why the input ended (:attr:`end_reason`)."""
        return {"captured": self.captured, "dropped_at_source": self.dropped, "clock": self.clock.source,
                "end_reason": self.end_reason or None}

    def end_message(self) -> str:
        """One line: how many frames came, how many the source itself dropped, and why the input ended."""
        c = self.config
        why = {"timeout": f"no frame for {c.live_timeout_s:g} s (input.live_timeout_s): the camera or stream stopped "
                          "delivering",
               "max_frames": f"the limit of {c.live_max_frames} frames (input.live_max_frames, --max-frames)",
               "duration": f"the limit of {c.live_duration_s:g} s (input.live_duration_s, --duration)",
               "interrupt": "Ctrl-C (the first one ends a live stream as its end; a second cuts the final "
                            "refinement short)",
               "stopped": "stopped by the run (a signal, an error or the end of the work)"}.get(self.end_reason,
                                                                                              "not ended")
        return (f"live source {self.what}: {self.captured} frames captured, {self.dropped} replaced at the source "
                f"before they were taken, timestamps from the {'capture' if self.clock.source == 'capture' else 'local monotonic'} "
                f"clock; input ended by {why}")

    def close(self) -> None:
        """Stop the capture thread and release the device or stream."""
        self._end_iteration()
        if self._thread is not None and self._thread.is_alive():
            return   # blocked in the device's read: released with the process (never from under the read)
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __enter__(self) -> "LiveSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        w, h = self.calibration.output_size
        return f"LiveSource({self.source!r}, {w}x{h})"


class _LiveFrames:
    """One iteration over a :class:`LiveSource`: an iterator whose :meth:`close` may be called from any thread (the
    real-time player closes it from the consumer's while its own thread waits in ``__next__``)."""

    def __init__(self, src: LiveSource, on_unreadable):
        self._src = src
        self._on_unreadable = on_unreadable
        self._closed = threading.Event()
        self._done = False
        self._started = False

    def __iter__(self) -> "_LiveFrames":
        return self

    def __next__(self) -> Frame:
        src = self._src
        if not self._started and not self._done:
            self._started = True
            src._start_capture()
        while not self._done:
            try:
                item = src._next_raw(self._closed)
                if item is None:
                    break
                index, ts, raw = item
                try:
                    frame = src._frame(index, ts, raw)
                except DatasetError as exc:
                    if self._on_unreadable is not None and self._on_unreadable(index, exc):
                        continue
                    raise
            except BaseException:
                self.close()
                raise
            src.delivered += 1
            return frame
        self.close()
        raise StopIteration

    @property
    def dropped(self) -> int:
        """Frames the capture replaced before they were taken (the player adds them to its own count)."""
        return self._src.dropped

    @property
    def captured(self) -> int:
        return self._src.captured

    live = True

    def close(self) -> None:
        if self._done:
            return
        self._done = True
        self._closed.set()
        if self._started and not self._src.end_reason:
            # closed by another thread while this iteration was between frames: it ends at its next __next__
            # without waiting in _next_raw, which would have said so
            self._src.end_reason = "stopped"
        self._src._end_iteration()

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - at interpreter exit
            pass


def _plain(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3 and img.shape[2] == 1:
        return img[:, :, 0]
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def _quiet_opencv():
    """OpenCV's own warnings (a camera index that does not exist, a stream's read timeout) are said by our one line
    instead; returns the previous level for :func:`_restore_opencv`."""
    try:
        lg = cv2.utils.logging
        old = lg.getLogLevel()
        lg.setLogLevel(lg.LOG_LEVEL_ERROR)
        return old
    except AttributeError:  # an OpenCV without the logging utilities
        return None


def _restore_opencv(old) -> None:
    if old is not None:
        try:
            cv2.utils.logging.setLogLevel(old)
        except AttributeError:
            pass
