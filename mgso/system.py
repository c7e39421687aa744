"""The whole MGSO system: an odometry and the Gaussian mapper joined by typed messages (docs/mgso.md).

::

    frames -> odometry.process(frame) -> OdometryFrame (pose, affine, keyframe?) + messages
                                                 |  KeyframeMessage / PoseUpdate / PointsMessage
                                                 v
                                     Mapper (bounded queue) -> seed, train, densify -> Gaussian map

**The odometry** is any object with the small :class:`OdometrySource` protocol: ``process(frame)`` returns what it
says about the frame (an :class:`OdometryFrame` or anything with the same fields: the pose and the messages it
emits, in order), ``finish() -> messages`` (the last pose updates and the points still in the window),
``trajectory()`` and ``keyframe_trajectory()`` (final poses, TUM-ready). The DSO odometry
(:class:`mgso.odometry.Odometry` made with ``emit_messages=True``) speaks the mapper's messages itself and returns
its :class:`~mgso.odometry.FrameResult`; :class:`mgso.oracle.OracleOdometry` (ground-truth poses and depths) is the
stand-in for tests and profiles.

**Modes** (``system.mode``):

- ``deterministic``: frames in order; after each frame the mapper applies the messages and trains
  ``mapping.mapper.iterations_per_keyframe`` steps after each keyframe, in this thread. The same result on every
  CPU run (bitwise-identical PLY).
- ``realtime``: the mapper trains in a spawned process of its own (:class:`mgso.mapping.process.MapperProcess`;
  ``system.mapper_process: false``: a thread) while the odometry runs, the cores split between them
  (``system.odometry_threads`` / ``mapper_threads``); the odometry never waits for it except on a full queue
  (counted). A recorded sequence is played at its frame rate times ``system.playback_speed``: a
  player thread releases each frame at its time, and the frames that arrive while the odometry is busy wait in order
  until they are ``system.max_lag_ms`` old; an older one is dropped once a newer one waits (counted; 0: only the
  newest frame waits, as a live camera's would).

**Loop closure** (``loop.enabled``, :mod:`mgso.loop`): a :class:`~mgso.loop.closer.LoopCloser` sees every message
of the odometry, looks for a revisit at each keyframe (in the caller's thread in the deterministic mode, on a thread
of its own in real time), and the mapper gets the messages moved into the corrected world and a
:class:`~mgso.messages.LoopCorrection` after each loop. The result's trajectories and point cloud are the
corrected ones (the odometry's stay in ``SystemResult.odometry_trajectory``).

**Without a map** (``System(..., with_map=False)``: the ``tracking`` and ``odometry`` stages of ``mgso run``) the
same loop runs the odometry, the loop closer and the observers, and no mapper: a run of every stage is made and
written the same way (:mod:`mgso.app.outputs`), the map's figures absent.

After the last frame: ``odometry.finish()``, its messages to the mapper, the final refinement; the application
(:mod:`mgso.app.outputs`) then writes the outputs. Ctrl-C (``KeyboardInterrupt``, also when raised by the frame source,
and SIGTERM, which the application turns into one) stops cleanly in both modes: the odometry is finished, the mapper
applies what is queued and stops without the final refinement, and the result says so
(``SystemResult.interrupted``); a second one during ``finish`` or the refinement cuts those short. An error of the
odometry or of the frame source stops the mapper and raises :class:`SystemRunError`, which carries the result of
what was done (so that its outputs can still be written). A frame cut off mid-way by an interrupt is in no result.

Nothing here prints; observers (:mod:`mgso.observers`) get ``on_sequence_start``, ``on_frame`` (an
:class:`OdometryFrame`), ``on_keyframe`` (a :class:`~mgso.messages.KeyframeMessage`),
``on_window_optimized`` (a :class:`~mgso.messages.PoseUpdate`), ``on_points_marginalized`` (a
:class:`~mgso.messages.PointsMessage`), ``on_map_updated`` (from the mapper) and ``on_sequence_end``
(the :class:`SystemResult`).
"""

from __future__ import annotations

import logging
import os
import resource
import threading
import time
from array import array
from collections import deque
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, Protocol, Sequence as TSequence

import numpy as np

from mgso.config import Config
from mgso.io.trajectory import Trajectory
from mgso.loop.closer import LoopCloser, LoopStats
from mgso.mapping.mapper import Mapper, MapperStats
from mgso.messages import KeyframeMessage, PointsMessage, PoseUpdate
from mgso.mapping.process import MapperProcess, split_threads
from mgso.observers import Observer, ObserverList
from mgso_kernels import runtime

__all__ = ["OdometrySource", "OdometryFrame", "System", "SystemResult", "SystemRunError", "FrameLog",
           "MarginalizedCloud", "Player", "peak_memory_mb"]

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------- the protocol
@dataclass(frozen=True, eq=False)
class OdometryFrame:
    """What an odometry says about one frame.

    ``cam_to_world``: the pose at tracking time (4x4), ``None`` while there is none (initialising, lost).
    ``affine``: DSO's (a, b) of the frame (0-255 scale); ``exposure_ms``: its exposure time (``None``: unknown).
    ``is_keyframe``: the frame asked to become a keyframe (with DSO's mapping thread the request may go to a later
    frame: the keyframes made are the frames of the keyframe messages, ``SystemResult.keyframe_frames``);
    ``status``: the odometry's word for the frame (e.g. "tracked", "initializing", "lost");
    ``messages``: what it emits for the mapper, in order; ``seconds``: its time on this frame.
    """

    index: int
    timestamp: float
    cam_to_world: np.ndarray | None
    is_keyframe: bool = False
    affine: tuple[float, float] = (0.0, 0.0)
    exposure_ms: float | None = None
    status: str = "tracked"
    messages: tuple = ()
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.cam_to_world is not None


class OdometrySource(Protocol):
    """What the system needs of an odometry (DSO's :class:`mgso.odometry.Odometry` with ``emit_messages=True``, or
    the oracle)."""

    def process(self, frame) -> OdometryFrame:
        """Track (and map, in DSO's sense) one :class:`mgso.io.Frame`; return its pose and the messages."""

    def finish(self) -> TSequence:
        """End of the sequence: the final pose updates and the points left in the window, as messages."""

    def trajectory(self) -> Trajectory:
        """Every frame with a pose, final poses (camera-to-world)."""

    def keyframe_trajectory(self) -> Trajectory:
        """Every keyframe, final poses."""

    #: the Warp device the odometry runs on (the loop closer's photometric check runs there too); ``None``: an
    #: odometry without kernels (the oracle), whose closer then runs on the system's device
    device: str | None


# -------------------------------------------------------------------------------------------- results
@dataclass
class FrameLog:
    """Per processed frame, in order: what evaluation needs."""

    index: list[int] = field(default_factory=list)
    timestamp: list[float] = field(default_factory=list)
    affine: list[tuple[float, float]] = field(default_factory=list)
    exposure_ms: list[float | None] = field(default_factory=list)
    is_keyframe: list[bool] = field(default_factory=list)
    status: list[str] = field(default_factory=list)
    # Kept to what evaluation needs: the per-frame figures of metrics.json's "tracking" section are read back from
    # frames.csv at the end, not gathered here, since in real time the frame loop's work is part of the timing
    # between the tracking thread and DSO's mapping thread (docs/mgso.md, "Two outcomes of the same real-time run").

    def add(self, r: OdometryFrame) -> None:
        self.index.append(int(r.index))
        self.timestamp.append(float(r.timestamp))
        self.affine.append((float(r.affine[0]), float(r.affine[1])))
        self.exposure_ms.append(r.exposure_ms)
        self.is_keyframe.append(bool(r.is_keyframe))
        self.status.append(str(getattr(r.status, "value", r.status)))

    def __len__(self) -> int:
        return len(self.index)


@dataclass
class MarginalizedCloud:
    """The DSO point cloud: every marginalised point (world, colour in [0, 1], host keyframe id)."""

    points: list[np.ndarray] = field(default_factory=list)
    colors: list[np.ndarray] = field(default_factory=list)
    hosts: list[np.ndarray] = field(default_factory=list)

    def add(self, msg: PointsMessage) -> None:
        if len(msg):
            self.points.append(np.asarray(msg.points))
            self.colors.append(np.asarray(msg.colors))
            self.hosts.append(np.full(len(msg), msg.host_keyframe_id, np.int64))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not self.points:
            return np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
        return np.concatenate(self.points), np.concatenate(self.colors), np.concatenate(self.hosts)

    def __len__(self) -> int:
        return int(sum(len(p) for p in self.points))


@dataclass
class SystemResult:
    """What :meth:`System.run` did (values; the application writes the outputs: :mod:`mgso.app.outputs`)."""

    mode: str
    frames_read: int                    # frames the source delivered (played, in real time)
    frames_processed: int               # frames the odometry processed
    frames_dropped: int                 # real time: frames replaced before the odometry could take them
    keyframes: int                      # keyframe messages sent to the mapper
    pose_updates: int                   # pose-update messages sent
    interrupted: bool
    trajectory: Trajectory              # final poses of every frame with one
    keyframe_trajectory: Trajectory
    frame_log: FrameLog
    cloud: MarginalizedCloud
    mapper: MapperStats                 # empty without a map (``with_map``)
    odometry_seconds: float             # sum of the odometry's per-frame times
    loop_seconds: float                 # wall time of the frame loop (first frame in -> last frame done)
    finish_seconds: float               # odometry.finish + the mapper's last messages and final refinement
    frames_lost: int = 0                # frames processed that have no pose in the final trajectory
    keyframe_frames: list = field(default_factory=list)   # frame index of every keyframe sent to the map
    mapper_in: str = "caller"           # where the mapper ran: "caller" (deterministic, system.mapper_lead 0), "thread"
    #                                     (real time, or deterministic on a thread of its own) or "process";
    #                                     "none" without a map
    with_map: bool = True               # False: the odometry alone (the tracking and odometry stages)
    repeated_frames: int = 0            # frames that repeated the one before (the odometry gave them its pose)
    cpu_seconds: float = 0.0            # CPU time of this process over the run (all its threads)
    loop: LoopStats | None = None       # loop closure's counts (None: loop.enabled false)
    odometry_trajectory: Trajectory | None = None           # the odometry's own poses when a loop corrected them
    odometry_keyframe_trajectory: Trajectory | None = None
    tracking_losses: list = field(default_factory=list)    # the odometry's TrackingLost events, in order
    segments: int = 1                                       # tracking segments (a loss starts a new one)
    frame_lags: list = field(default_factory=list)          # real time: seconds each frame waited to be taken
    # real time, the odometry's mapping thread: keyframe requests a newer one replaced while frames waited (DSO's
    # catch-up), and requests dropped as made against a keyframe no longer the newest (DSO's needNewKFAfter); None
    # for an odometry without that thread
    keyframe_requests_merged: int | None = None
    keyframe_requests_stale: int | None = None

    @property
    def mapper_cpu_share(self) -> float | None:
        """The mapper's share of the CPU time of the run (real time): its process's over both processes', or its
        thread's over the process's; ``None`` in the deterministic mode."""
        m = self.mapper.cpu_seconds
        if self.mapper_in in ("caller", "none") or m is None:
            return None
        total = self.cpu_seconds + m if self.mapper_in == "process" else self.cpu_seconds
        return m / total if total > 0 else None

    @property
    def tracking_fps(self) -> float:
        """Frames per second of the odometry alone (frames processed / its time on them)."""
        return self.frames_processed / self.odometry_seconds if self.odometry_seconds > 0 else 0.0

    @property
    def frame_loop_fps(self) -> float:
        """Frames processed per second of the frame loop, odometry and mapping together (the final refinement
        after the last frame is not in it; metrics.json's ``end_to_end_fps`` counts until the map is written)."""
        return self.frames_processed / self.loop_seconds if self.loop_seconds > 0 else 0.0


class SystemRunError(RuntimeError):
    """The run stopped on an error (``error``, also the ``__cause__``); ``result`` is what was done up to it (the
    mapper stopped without the final refinement), so that the outputs of that can still be written."""

    def __init__(self, result: SystemResult, error: BaseException):
        super().__init__(f"{type(error).__name__}: {error}")
        self.result = result
        self.error = error


# --------------------------------------------------------------------------------------------- playback
_END = object()


def _is_frame(item) -> bool:
    return item is not _END and not isinstance(item, BaseException)


class Player:
    """Plays frames at their timestamps (a recorded sequence as a live camera): a thread reads ``frames`` and
    releases each at ``t0 + (timestamp - first) / speed``; the consumer takes the released frames in order. A frame
    that is ``max_lag`` seconds old while a newer one waits is dropped (counted in :attr:`dropped`): with ``max_lag =
    0`` the consumer always gets the newest frame, as from a live camera; a positive ``max_lag`` lets the frames that
    arrive during a short stall wait (a delay of at most that long) instead of being lost (:attr:`lags`: how long
    each frame taken had waited). ``speed = 0``: no pacing and nothing dropped (the consumer's pace). Errors of the
    source (including ``KeyboardInterrupt``) are raised in the consumer, after the frames released before them.

    A live source (``frames.live`` true: :class:`mgso.io.live.LiveSource`'s frames) is never paced (the device is
    the clock) and always drops as above, whatever ``speed``; it is closed before the player's thread is joined (that
    thread may be waiting in it for the next frame), and the frames the source itself replaced before the player
    took them (``frames.dropped``) are added to :attr:`read` and :attr:`dropped`. When the consumer stops early (an
    interrupted run), the frames read but still waiting count as dropped too: ``read = taken + dropped``, the frame
    the consumer was working on being one of the taken."""

    def __init__(self, frames: Iterable, speed: float = 1.0, max_lag: float = 0.0):
        self.speed = float(speed)
        self.max_lag = max(0.0, float(max_lag))
        self._frames = frames
        self.live = bool(getattr(frames, "live", False))
        self._cond = threading.Condition()
        self._queue: deque = deque()  # (release time, frame / _END / exception), oldest first
        self._stop = threading.Event()
        self.read = 0
        self.dropped = 0
        self.lags = array("d")  # seconds each frame taken waited after its release (8 bytes a frame: runs are long)
        self._thread = threading.Thread(target=self._work, name="mgso-player", daemon=True)

    def _put(self, item, replace: bool) -> bool:
        with self._cond:
            while self._queue and not replace and not self._stop.is_set():
                self._cond.wait(0.05)
            if self._stop.is_set():
                return False
            now = time.perf_counter()
            self._queue.append((now, item))
            self._expire(now)
            self._cond.notify_all()
        return True

    def _expire(self, now: float) -> None:
        """Drop the oldest waiting frames while a newer frame waits behind them and they are ``max_lag`` old (under
        the condition's lock): a frame is taken at most that late, unless it is the newest."""
        q = self._queue
        while (len(q) > 1 and now - q[0][0] >= self.max_lag and _is_frame(q[0][1]) and _is_frame(q[1][1])):
            q.popleft()
            self.dropped += 1

    def _work(self) -> None:
        t0, ts0 = None, None
        try:
            for frame in self._frames:
                if self._stop.is_set():
                    return
                self.read += 1
                if self.speed > 0 and not self.live:
                    if t0 is None:
                        t0, ts0 = time.perf_counter(), float(frame.timestamp)
                    wait = t0 + (float(frame.timestamp) - ts0) / self.speed - time.perf_counter()
                    if wait > 0 and self._stop.wait(wait):
                        return
                if not self._put(frame, replace=self.speed > 0 or self.live):
                    with self._cond:  # read, then the consumer stopped: never processed
                        self.dropped += 1
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            self._put(exc, replace=False)
            return
        self._put(_END, replace=False)

    def __iter__(self) -> Iterator:
        self._thread.start()
        try:
            while True:
                with self._cond:
                    while not self._queue:
                        self._cond.wait(0.05)
                    self._expire(time.perf_counter())
                    released, item = self._queue.popleft()
                    self._cond.notify_all()
                if item is _END:
                    return
                if isinstance(item, BaseException):
                    raise item
                self.lags.append(time.perf_counter() - released)
                yield item
        finally:
            self._stop.set()
            with self._cond:
                self._cond.notify_all()
            close = getattr(self._frames, "close", None)
            if self.live and close is not None:
                close()
            self._thread.join(timeout=5.0)
            with self._cond:  # frames still waiting when the consumer stopped (an interrupted run): never processed
                self.dropped += sum(1 for _, item in self._queue if _is_frame(item))
                self._queue.clear()
            if close is not None and not self.live:
                close()
            if self.live:
                at_source = int(getattr(self._frames, "dropped", 0))
                self.read += at_source
                self.dropped += at_source


# ----------------------------------------------------------------------------------------------- system
class System:
    """Odometry + mapper (see the module doc). ``odometry``: an :class:`OdometrySource`; ``config``: the full
    configuration (``system``, ``mapping``); ``device``: Warp device (initialised by the caller);
    ``observer``: one observer or an :class:`~mgso.observers.ObserverList`; ``with_map``: ``False`` runs the odometry
    (and the loop closer) without a mapper (``self.mapper`` is ``None``)."""

    def __init__(self, odometry: OdometrySource, config: Config, *, device: str | None = None,
                 observer: Observer | None = None, with_map: bool = True):
        self.odometry = odometry
        self.config = config
        self.observer = observer if observer is not None else ObserverList()
        self.realtime = config.system.mode == "realtime"
        sc = config.system
        self.odometry_threads: int | None = None
        self._share_pending = False      # real time: the odometry on every core until the first keyframe
        self.mapper: Mapper | MapperProcess | None = None
        # deterministic mode: keyframes the odometry may run ahead of the mapper's own thread (0: the mapper trains in
        # this thread after each frame; system.mapper_lead)
        self.mapper_lead = 0
        if not with_map:
            pass
        elif self.realtime and sc.mapper_process:
            self.odometry_threads, mapper_threads = split_threads(sc.odometry_threads, sc.mapper_threads)
            self.mapper = MapperProcess(
                config, device=device, observer=self.observer, threads=mapper_threads, nice=sc.mapper_nice,
                idle=sc.mapper_sched_idle, image_slots=sc.image_slots)
        else:
            self.mapper = Mapper(config, device=device, observer=self.observer)
            if not self.realtime:
                lead = sc.mapper_lead
                if lead is None:     # (a GPU's mapper beside the CPU's odometry: not measured yet)
                    lead = 4 if runtime.device_is_cpu(self.mapper.device) else 0
                self.mapper_lead = int(lead)
        self.loop: LoopCloser | None = None
        if config.loop.enabled:
            self.loop = LoopCloser(config, device=odometry.device or device, background=self.realtime,
                                   nice=config.system.mapper_nice)
        self.cloud = MarginalizedCloud()
        self.frame_log = FrameLog()
        self._keyframes = 0
        self._keyframe_frames: list[int] = []
        self._pose_updates = 0

    @property
    def mapper_in(self) -> str:
        """Where the mapper runs: ``"caller"`` (the deterministic mode with ``system.mapper_lead`` 0: this thread,
        between frames), ``"thread"`` (real time, or the deterministic mode's own thread), ``"process"``, or
        ``"none"`` without a map."""
        if self.mapper is None:
            return "none"
        if isinstance(self.mapper, MapperProcess):
            return "process"
        return "thread" if self.realtime or self.mapper_lead else "caller"

    def _send(self, msg, final: bool = False) -> None:
        """One odometry message to the loop closer, the counters, the observers and the mapper, in that order
        (``final``: one of ``odometry.finish()``'s)."""
        raw = msg                            # the odometry's world (the DSO cloud is corrected at the end)
        if self.loop is not None:
            self.loop.observe(msg, final=final)
            msg = self.loop.correct(msg)     # the map's (the same object until a loop moved something)
        if isinstance(msg, KeyframeMessage):
            if self._share_pending:             # the mapper has work from now on: the odometry takes its share
                self._share_pending = False
                runtime.set_cpu_threads(self.odometry_threads)
            self._keyframes += 1
            self._keyframe_frames.append(msg.frame_index)
            self.observer.on_keyframe(msg)
        elif isinstance(msg, PoseUpdate):
            self._pose_updates += 1
            self.observer.on_window_optimized(msg)
        elif isinstance(msg, PointsMessage):
            self.cloud.add(raw)
            self.observer.on_points_marginalized(msg)
        else:
            raise TypeError(f"the odometry emitted {type(msg).__name__}, not a mapper message")
        if self.mapper is not None:
            self.mapper.submit(msg)

    def _send_correction(self, corr) -> None:
        """A loop's correction (from ``LoopCloser.poll`` / ``finish``; ``None``: none) to the mapper and observers."""
        if corr is not None:
            if self.mapper is not None:
                self.mapper.submit(corr)
            self.observer.on_loop_closed(corr)

    def _dispatch(self, messages) -> None:
        for msg in messages:
            self._send(msg)
        if self.loop is not None:
            self._send_correction(self.loop.poll())
        if not self.realtime and self.mapper is not None and not self.mapper_lead:
            self.mapper.process_pending()

    def run(self, frames: Iterable, *, info: Any = None, hold: Callable[[], Any] | None = None,
            log_frame: Callable[[Any], None] | None = None) -> SystemResult:
        """Run over ``frames`` (``mgso.io.Frame`` objects, e.g. ``Sequence.frames()``) and stop the mapper.

        ``log_frame(result)``: called with each frame's :class:`OdometryFrame` as it is counted (the application's
        frames.csv row). ``hold``: a context manager factory around that bookkeeping (the count, the frame log,
        ``log_frame``; not the observers, which may wait: a paused viewer), in which a stop signal must not land
        (the application's ``StopState.held``: frames.csv's rows and the count agree however the run is stopped).

        Real-time mode plays them through a :class:`Player` at ``system.playback_speed`` times their rate.
        Returns a :class:`SystemResult` (:mod:`mgso.app.outputs` writes the files); raises :class:`SystemRunError` on an
        error, with the result of what was done."""
        self.observer.on_sequence_start(info)
        self._cpu0 = time.process_time()
        player = None
        threads_before = None
        if self.realtime:
            player = Player(frames, self.config.system.playback_speed, self.config.system.max_lag_ms / 1000.0)
            source: Iterable = player
            if self.odometry_threads is not None:      # the cores split with the mapper's process
                # ... from the first keyframe on: until the initialiser succeeds the mapper has nothing to train,
                # and the initialiser's frames on one core dropped 2-4 camera frames each at 640x480
                threads_before = runtime.cpu_threads_setting()
                self._share_pending = True
            if self.mapper is not None:
                self.mapper.start()
        else:
            source = frames
            if self.mapper is not None and self.mapper_lead:
                self.mapper.start_in_order(self.mapper_lead)
        try:
            return self._run(source, player, hold or nullcontext, log_frame)
        finally:
            if self.loop is not None:
                self.loop.close()
            if threads_before is not None:
                runtime.set_cpu_threads(threads_before)
            close = getattr(self.mapper, "close", None)     # (None without a map)
            if close is not None:               # a mapper process left by an unexpected exit: no orphan
                close()

    def _run(self, source: Iterable, player: "Player | None", hold: Callable[[], Any],
             log_frame: Callable[[Any], None] | None) -> SystemResult:
        interrupted = False
        error: Exception | None = None
        processed, read, odo_s = 0, 0, 0.0
        t_loop = time.perf_counter()
        it = iter(source)
        try:
            if self.realtime or self.mapper_lead:
                # real time: a compile would drop the first frames, done before the camera plays; the deterministic
                # mode's mapper thread: no two threads compile at once
                for part in (self.odometry, self.mapper):     # (a mapper's process loads its own before "ready")
                    if part is None:
                        continue
                    load_kernels = getattr(part, "load_kernels", None)
                    if load_kernels is not None:
                        load_kernels()
            wait_ready = getattr(self.mapper, "wait_ready", None)
            if wait_ready is not None:
                # the mapper's process starts (imports, Warp) before the camera plays: its start-up would take the
                # odometry's core while the first frames arrive
                wait_ready()
            t_loop = time.perf_counter()     # the camera plays from the first frame asked for
            for frame in it:
                read += 1
                t0 = time.perf_counter()
                r = self.odometry.process(frame)
                dt = r.seconds if r.seconds > 0 else time.perf_counter() - t0
                odo_s += dt
                with hold():
                    processed += 1
                    self.frame_log.add(r)
                    if log_frame is not None:
                        log_frame(r)
                self.observer.on_frame(r)
                self._dispatch(r.messages)
        except KeyboardInterrupt:
            interrupted = True
        except Exception as exc:  # noqa: BLE001 - the work done so far is returned with the error
            error = exc
            log.debug("the run failed after %d frames", processed, exc_info=True)
        finally:
            loop_s = time.perf_counter() - t_loop
            close = getattr(it, "close", None)
            if close is not None:        # stop the player's / the prefetch's thread now
                try:
                    close()
                except KeyboardInterrupt:
                    # a signal while they stop (a thread's join, tens of ms; a second Ctrl-C): until 2026-12-07 it
                    # left _run and no output was written
                    interrupted = True
        t_fin = time.perf_counter()
        final = []
        try:
            if interrupted:              # here, where a second signal is caught as in the odometry's last step
                self._stop_training()
                log.warning("interrupted after %d frames: finishing the odometry and writing what was done",
                            processed)
            final = list(self.odometry.finish())
        except KeyboardInterrupt:        # a second signal during the odometry's last step: keep what it has
            interrupted = True
        except Exception:  # an odometry interrupted or broken mid-frame may not finish cleanly: keep what it has
            if not (interrupted or error is not None):
                raise
            log.warning("the odometry could not finish after the %s", "interrupt" if error is None else "error",
                        exc_info=log.isEnabledFor(logging.DEBUG))
        try:
            if error is not None:
                self._abort()
            else:
                self._dispatch_final(final, interrupted)
        except KeyboardInterrupt:      # a second Ctrl-C during the refinement: stop it, still write
            interrupted = True
            if self.mapper is not None:
                self.mapper.stop(refine=False)
        except Exception as exc:
            # the mapper failed at the end (its thread's error handed over at stop, or its final refinement's): the
            # result of what was done is still returned with it, and written
            error = exc
            log.debug("the mapper failed after %d frames", processed, exc_info=True)
            try:
                self._abort()
            except KeyboardInterrupt:  # a signal while its thread stops: the result is still returned
                interrupted = True
        finish_s = time.perf_counter() - t_fin
        if player is not None:
            read = player.read
        done = set(self.frame_log.timestamp)   # a frame cut off mid-way by an interrupt is not in the results
        traj = self.odometry.trajectory().at_times(done)
        kf_traj = self.odometry.keyframe_trajectory().at_times(done)
        odo_traj = odo_kf = None
        cloud = self.cloud
        if self.loop is not None and self.loop.corrected:
            odo_traj, odo_kf = traj, kf_traj
            traj, kf_traj = self.loop.correct_trajectory(traj), self.loop.correct_keyframes(kf_traj)
            cloud = _corrected_cloud(self.cloud, self.loop)
        # without a pose in the end (a frame that had none when it was tracked may get one later: DSO's first
        # frame, once the initialiser succeeds)
        lost = processed - len(traj)
        result = SystemResult(
            mode=self.config.system.mode, frames_read=read, frames_processed=processed,
            frames_dropped=player.dropped if player is not None else 0, keyframes=self._keyframes,
            frame_lags=list(player.lags) if player is not None else [],
            keyframe_requests_merged=(getattr(self.odometry, "num_keyframe_requests_merged", None)
                                      if getattr(self.odometry, "map_thread", False) else None),
            keyframe_requests_stale=(getattr(self.odometry, "num_keyframe_requests_stale", None)
                                     if getattr(self.odometry, "map_thread", False) else None),
            pose_updates=self._pose_updates, interrupted=interrupted,
            trajectory=traj, keyframe_trajectory=kf_traj, frame_log=self.frame_log, cloud=cloud,
            mapper=self.mapper.stats if self.mapper is not None else MapperStats(), odometry_seconds=odo_s,
            loop_seconds=loop_s,
            finish_seconds=finish_s, frames_lost=lost, keyframe_frames=list(self._keyframe_frames),
            mapper_in=self.mapper_in,
            with_map=self.mapper is not None, repeated_frames=int(getattr(self.odometry, "num_duplicates", 0)),
            cpu_seconds=time.process_time() - self._cpu0,
            loop=None if self.loop is None else self.loop.stats, odometry_trajectory=odo_traj,
            odometry_keyframe_trajectory=odo_kf, tracking_losses=list(getattr(self.odometry, "losses", ())),
            segments=int(getattr(self.odometry, "segment", 0)) + 1)
        self.observer.on_sequence_end(result)
        if error is not None:
            raise SystemRunError(result, error) from error
        return result

    def _abort(self) -> None:
        """The run failed: stop the mapping thread without training (its own failure, if any, is logged)."""
        if self.loop is not None:
            self.loop.close()
        if self.mapper is None:
            return
        try:
            self.mapper.stop(refine=False, timeout=60)
        except Exception:  # the original error is the one to raise
            log.exception("stopping the mapper after a failure")

    def _stop_training(self) -> None:
        """Interrupted: the deterministic mode's mapper thread trains no more from now on (the keyframes still queued
        are applied without it, as the mapper in the odometry's thread would), so the run stops promptly."""
        if self.mapper_lead:
            self.mapper.interrupt()

    def _dispatch_final(self, final, interrupted: bool) -> None:
        if interrupted:
            self._stop_training()
        for msg in final:                    # observers see the end of the stream too (a viewer's final keyframe
            self._send(msg, final=True)      # poses and the window's last points)
        loop = self.loop
        if loop is not None:
            if interrupted:
                loop.close()              # the loops not yet solved are dropped; those found are kept
            self._send_correction(loop.finish())
        if self.mapper is None:
            return
        steps = self.config.mapping.mapper.final_steps(self.realtime)
        if not interrupted and steps > 0 and self._keyframes:    # minutes on a CPU: say what and how to cut it
            log.info("final refinement: %d mapping steps over the %d keyframes (Ctrl-C cuts it short; the outputs are "
                     "written either way)", steps, self._keyframes)
        self.mapper.stop(refine=not interrupted)


def _corrected_cloud(cloud: MarginalizedCloud, loop: LoopCloser) -> MarginalizedCloud:
    """The DSO point cloud moved by each host keyframe's loop correction."""
    pts, cols, hosts = cloud.arrays()
    out = MarginalizedCloud()
    if len(pts):
        out.points.append(loop.correct_points(pts, hosts))
        out.colors.append(cols)
        out.hosts.append(hosts)
    return out


# ----------------------------------------------------------------------------------------------- figures
def peak_memory_mb() -> float:
    """Peak resident set size of this process in MB (``resource.getrusage(RUSAGE_SELF).ru_maxrss``: KiB on Linux,
    bytes on macOS): everything the process held at its peak (Python, Warp buffers on the CPU, images)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    scale = 1.0 if os.uname().sysname == "Darwin" else 1024.0
    return rss * scale / 1e6
