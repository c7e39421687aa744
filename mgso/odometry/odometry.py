"""The DSO odometry loop: frames in one by one, a pose for every frame out (DSO ``FullSystem::addActiveFrame``,
``deliverTrackedFrame``, ``makeKeyFrame``, ``makeNonKeyFrame``, ``initializeFromInitializer``).

:class:`Odometry` holds the coarse tracker, the keyframe policy, the window, the initialiser, the pixel selector and
point activator, a back end (:class:`~mgso.odometry.back_end.WindowBackEnd`: the window's bundle adjustment,
``window.backend``), the segments' similarities (:class:`~mgso.odometry.segments.Segments`) and its messages to the
mapper (:class:`~mgso.odometry.outbox.MapperOutbox`). Work is split as DSO splits it between its tracking and mapping
threads, with typed messages between the halves (:mod:`mgso.odometry.records`):

- :meth:`Odometry.track` (tracking side): builds the frame's pyramid, runs the initialiser or the coarse tracker,
  decides keyframe or not, detects tracking loss, and returns a :class:`TrackedFrame` (the frame's pyramid travels
  with it). A frame that repeats the previous image exactly takes the previous frame's pose untracked
  (``FrameStatus.DUPLICATE``, ``tracking.skip_duplicate_frames``).
- :meth:`Odometry.map` (mapping side): for a keyframe, traces the immature points, lets the back end flag frames,
  adds the keyframe, activates points, optimises, builds the next tracking reference, marginalises points, selects new
  immature points and drops flagged keyframes; for other frames, traces. The new :class:`~mgso.tracking.
  coarse_tracker.TrackingReference` is handed to the tracking side whole (:meth:`_offer_reference`; the tracker
  swaps it in at the start of its next frame, DSO's ``coarseTracker_forNewKF``).

:meth:`Odometry.process` runs both in order (deterministic and single-threaded, for tests and evaluation). With
``map_thread=True`` (DSO's split, for real time; off by default) :meth:`process` tracks the frame and returns, and
:meth:`map` runs on a thread of the odometry's own (:class:`~mgso.odometry.map_thread.MappingThread`), fed by a
queue of :class:`TrackedFrame`: a keyframe's window optimisation no longer delays the frames behind it, the tracker
keeps tracking against the latest reference until the new one is handed over, and when frames wait the older ones
are mapped as non-keyframes (traced only) and only the newest keeps its keyframe request (DSO
``needToKetchupMapping``). The initialiser's frames and a tracking loss
are mapped in order on the calling thread (the queue is emptied first); the mapper's messages are returned by the
next :meth:`process` calls and :meth:`finish`; the observer's keyframe, window and point events come from the
mapping thread. Results are then no longer bit-identical run to run.

**Poses.** Every frame keeps (DSO ``FrameShell``) its ``cam_to_tracking_ref`` and the keyframe it was tracked
against; its ``cam_to_world`` is the reference keyframe's pose times ``cam_to_tracking_ref``, refreshed when the frame
is mapped and again by :meth:`finish` with the keyframes' final poses. Frames before initialisation and lost frames
have no pose.

**Segments.** After a tracking loss the window is emptied (its points go to the point cloud), the initialiser starts
again, and a new segment begins. Inside the odometry every segment lives in its own frame, as DSO's does after a
reset: the segment's first keyframe at the origin, inverse depths of mean 1 (DSO's thresholds assume that scale).
For output the segments are chained: segment ``k > 0`` is mapped into the common world by a similarity
(:meth:`Odometry.segment_similarity`) that puts its first keyframe at the last reliable pose of segment ``k - 1``
(inlier ratio at least 0.5 and RMSE within ``kf_rmse_factor`` x the first RMSE; the frames just before a loss are
often already wrong; the camera is assumed not to have moved since) and sets its scale, which monocular odometry
cannot know, so that the median depth of its first points equals the median depth of the previous segment's last
tracking reference (:mod:`mgso.odometry.segments` keeps the similarities).
:attr:`FrameRecord.cam_to_world` and :attr:`KeyframeRecord.cam_to_world` are in the segment's frame; the
trajectories, :class:`FrameResult`, the observer events and :meth:`Odometry.point_cloud_world` are in the common
world. Every frame carries its segment number.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from mgso_kernels import runtime
from mgso_kernels.image import ImagePyramid, Pinhole, PyramidGeometry, plan_pyramid
from mgso_kernels.photometric import affine_from_to, extract_patterns

from ..camera import PinholeCamera
from ..config import Config
from ..geometry import se3_exp, se3_inverse, se3_log, se3_renormalize
from ..io.trajectory import Trajectory
from ..observers import Observer
from ..tracking.coarse_tracker import (CoarseTracker, TrackResult, TrackingReference, make_tracking_reference,
                                      motion_hypotheses)
from ..tracking.immature_points import (PointActivator, make_immature_points, trace_immature_points,
                                        trace_params_from_config)
from ..tracking.initializer import CoarseInitializer, InitStatus
from ..tracking.keyframe_policy import KeyframeDecision, KeyframePolicy, KeyframeReason
from ..tracking.pixel_selector import PixelSelector
from ..window.window import Window
from .back_end import WindowBackEnd, make_back_end
from .map_thread import MappingThread
from .outbox import MapperOutbox
from .records import (FrameRecord, FrameResult, FrameStatus, KeyframeEvent, KeyframeRecord, LossReason,
                      TrackedFrame, TrackingLost, WindowUpdate)
from .segments import Segments

__all__ = ["Odometry", "geometry_for"]

log = logging.getLogger(__name__)


def geometry_for(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                 config: Config) -> PyramidGeometry:
    """The pyramid geometry (level count, crop, shifted intrinsics) the odometry uses for this camera."""
    t = config.tracking
    return plan_pyramid(width, height, Pinhole(fx, fy, cx, cy), levels=t.pyramid_levels,
                        max_levels=t.pyramid_max_levels, min_area=t.pyramid_min_area, mode=t.pyramid_size_mode)


class _PyramidPool:
    """Pyramids for frames in flight (a frame owns one from ``track`` until it is mapped)."""

    def __init__(self, geometry: PyramidGeometry, device: str):
        self.geometry, self.device = geometry, device
        self._free: list[ImagePyramid] = []
        self._lock = threading.Lock()

    def acquire(self) -> ImagePyramid:
        with self._lock:
            if self._free:
                return self._free.pop()
        return ImagePyramid(self.geometry, device=self.device)

    def release(self, pyr: ImagePyramid) -> None:
        with self._lock:
            self._free.append(pyr)


class Odometry:
    """DSO-style odometry over a sequence (see the module text). ``geometry`` from :func:`geometry_for`."""

    name = "DSO (mgso.odometry)"  # what the outputs call it

    def __init__(self, geometry: PyramidGeometry, config: Config | None = None, *, device: str | None = None,
                 observer: Observer | None = None, back_end: WindowBackEnd | None = None,
                 emit_messages: bool = False, map_thread: bool = False):
        self.config = config or Config()
        self.emit_messages = bool(emit_messages)
        # DSO's split (module text): the mapping half on a thread of its own, fed by a queue
        self.map_thread = bool(map_thread)
        self._valid_src: np.ndarray | None = None  # the frames' validity mask (Frame.valid: the same array for all)
        cfg = self.config
        t = cfg.tracking
        self.geometry = geometry
        self.device = runtime.device_or_cpu(device)
        self.observer = observer or Observer()
        self.window = Window(geometry, max_frames=cfg.window.max_frames, point_capacity=cfg.window.point_capacity,
                             immature_capacity=cfg.window.immature_capacity, device=self.device)
        self.back_end: WindowBackEnd = back_end or make_back_end(cfg, self.device)
        self.tracker = CoarseTracker(geometry, t, device=self.device)
        self.policy = KeyframePolicy.from_config(geometry.width, geometry.height, t)
        self.initializer = CoarseInitializer(geometry, t, seed=cfg.runtime.seed, device=self.device)
        self.selector = PixelSelector(geometry.width, geometry.height, min_grad_hist_cut=t.min_grad_hist_cut,
                                      min_grad_hist_add=t.min_grad_hist_add,
                                      grad_downweight_per_level=t.grad_downweight_per_level,
                                      select_direction_distribution=t.select_direction_distribution,
                                      initial_potential=t.selector_initial_potential, seed=cfg.runtime.seed, device=self.device)
        self.activator = PointActivator(t)
        self.trace_params = trace_params_from_config(geometry.width, geometry.height, t, seed=cfg.runtime.seed)
        self._pool = _PyramidPool(geometry, self.device)
        self._rng = np.random.default_rng(cfg.runtime.seed)
        self.frames: list[FrameRecord] = []
        self.keyframes: dict[int, KeyframeRecord] = {}
        self.segment = 0
        self.initialized = False
        self.losses: list[TrackingLost] = []  # every tracking loss, in order (metrics.json lists them)
        self._ref_lock = threading.Lock()
        self._pending_reference: TrackingReference | None = None
        self._last_good: FrameRecord | None = None  # last reliably tracked frame (chaining segments)
        self._last_median_depth = float("nan")  # of the last tracking reference, in its segment's units
        self._frames_since_kf = 0
        self._init_step: np.ndarray | None = None  # mean cam_k -> cam_k+1 motion of the last initialisation
        self._init_rmse = -1.0  # the last initialisation's level-0 RMSE (loss baseline until a reference has one)
        self._segment_median_depth = float("inf")  # median depth of the segment's first points (its own units)
        self._segment_steps: list[float] = []  # per-frame camera motion of the segment (its own units)
        self._loss_detail = ""  # what the last loss check measured (the message of a jump)
        self._prev_rec: FrameRecord | None = None  # the previous tracked frame (this segment)
        self._prev_image: np.ndarray | None = None  # the previous frame's adjusted image (duplicate detection)
        self.num_duplicates = 0
        self.segments = Segments()  # segment frame -> common world (module text, "Segments")
        c = geometry.camera
        # the messages for the Gaussian mapper (emit_messages), in the odometry's image geometry (the pyramid crop)
        self.outbox = MapperOutbox(self.window, PinholeCamera(c.fx, c.fy, c.cx, c.cy, geometry.width,
                                                              geometry.height), self.segments,
                                   enabled=self.emit_messages)
        # DSO's mapping thread (map_thread): map() runs there, the messages it makes wait for process()
        self._mapping = MappingThread(self.map, self.outbox.drain if self.emit_messages else None,
                                      self._pool.release,
                                      self._newest_keyframe_id if config.tracking.realtime_current_keyframe_requests
                                      else None)

    @classmethod
    def for_camera(cls, camera, config: Config, **kwargs) -> "Odometry":
        """The odometry for an undistorted pinhole ``camera`` (``fx fy cx cy width height``, e.g. a sequence's
        ``calibration.output``); ``kwargs`` as for the constructor (``device``, ``observer``, ``emit_messages``)."""
        c = camera
        return cls(geometry_for(c.width, c.height, c.fx, c.fy, c.cx, c.cy, config), config, **kwargs)

    # ------------------------------------------------------------------------------------------ public
    def process(self, frame) -> FrameResult:
        """Track and map one frame (deterministic order). ``frame``: :class:`mgso.io.Frame`-like (``index``,
        ``timestamp``, ``gray [H, W]`` 0-255, ``rgb``, ``exposure_ms``)."""
        if self.map_thread:
            return self._process_split(frame)
        tracked = self.track(frame)
        t0 = time.perf_counter()
        self.map(tracked)
        return self._result(tracked, frame, t0, self.outbox.drain)

    def _result(self, tracked: TrackedFrame, frame, t0: float, messages) -> FrameResult:
        """The frame's result once its mapping (here) is done or queued: the mapping time on this thread since
        ``t0``, the record's affine and keyframe id, the exposure, and (``emit_messages``) ``messages()``."""
        r = tracked.result
        r.time_map_s = time.perf_counter() - t0
        r.affine = tuple(float(v) for v in tracked.record.affine)
        r.keyframe_id = int(tracked.record.keyframe_id)
        r.exposure_ms = getattr(frame, "exposure_ms", None)
        if self.emit_messages:
            r.messages = tuple(messages())
        return r

    @property
    def num_keyframe_requests_merged(self) -> int:
        """Keyframe requests the mapping thread's catch-up replaced by a newer frame's request (DSO keeps the last)."""
        return self._mapping.num_keyframe_requests_merged

    @property
    def num_keyframe_requests_stale(self) -> int:
        """Keyframe requests the mapping thread dropped: tracked against a keyframe that was no longer the newest
        (``tracking.realtime_current_keyframe_requests``)."""
        return self._mapping.num_keyframe_requests_stale

    def _newest_keyframe_id(self) -> int:
        """The window's newest keyframe id (-1: none); read on the mapping thread, which owns the window."""
        w = self.window
        return max((int(w.keyframe_id_[s]) for s in w.order), default=-1)

    @property
    def num_lost(self) -> int:
        """How many times tracking was lost (each started a new segment)."""
        return len(self.losses)

    def load_kernels(self) -> None:
        """Compile or load every kernel module the odometry launches, now: a real-time run calls it before the
        camera plays, so that its first frames do not wait for Warp to compile (seconds a module when the kernel
        cache is cold) and get dropped."""
        from mgso_kernels import activation, image, initializer, photometric, select, trace, track, window

        runtime.load_modules((image, photometric, select, initializer, track, trace, activation, window), self.device)
        if self.device != "cpu":  # the activation's spacing kernels run on the CPU whatever the device
            runtime.load_modules((activation,), "cpu")

    # ------------------------------------------------------------------------------- the mapping thread
    def _process_split(self, frame) -> FrameResult:
        """:meth:`process` with ``map_thread``: track here, map on the mapping thread (initialiser frames and a loss:
        here, in order). ``time_map_s`` is the time spent mapping on this thread; ``keyframe_id`` is -1 for a
        keyframe mapped on the thread (not known yet); ``messages`` are those the mapping thread has finished."""
        self._mapping.raise_error()
        tracked = self.track(frame)
        t0 = time.perf_counter()
        if tracked.pyramid is not None:
            if tracked.record.status == FrameStatus.TRACKED and tracked.initialize is None:
                self._mapping.submit(tracked)
            else:
                self._mapping.wait()
                self.map(tracked)
                if self.emit_messages:
                    self._mapping.add_ready(self.outbox.drain())
        return self._result(tracked, frame, t0, self._mapping.take_ready)

    def track(self, frame) -> TrackedFrame:
        """The tracking half: returns the message for :meth:`map`."""
        t0 = time.perf_counter()
        gray = np.asarray(frame.gray)
        if gray.ndim != 2 or (gray.shape[1], gray.shape[0]) != (self.geometry.input_width,
                                                                 self.geometry.input_height):
            raise ValueError(f"frame {getattr(frame, 'index', '?')}: gray image is {gray.shape}, the odometry was set "
                             f"up for {self.geometry.input_width}x{self.geometry.input_height}")
        img = np.array(self.geometry.adjust(gray), dtype=np.float32)  # an own copy (adjust may return a view)
        if not np.isfinite(img.sum()):  # rare: NaN / inf pixels become 0 (one reduction instead of a mask each frame)
            img[~np.isfinite(img)] = 0.0
        exposure = float(getattr(frame, "exposure_ms", None) or 0.0)
        valid = getattr(frame, "valid", None)
        if valid is not self._valid_src:  # pixels without a source (undistortion): left out of the map's loss
            self._valid_src = valid
            self.outbox.mask = (None if valid is None or bool(np.all(valid))
                                else (self.geometry.adjust(np.asarray(valid, np.float32)) > 0.5).astype(np.float32))
        rec = FrameRecord(int(frame.index), float(frame.timestamp), self.segment, FrameStatus.INITIALIZING)
        prev_img, self._prev_image = self._prev_image, img
        if (self.config.tracking.skip_duplicate_frames and self.initialized and prev_img is not None
                and np.array_equal(img[::7, ::7], prev_img[::7, ::7])  # a 49th of the pixels rules most frames out
                and np.array_equal(img, prev_img)):
            prev = self.frames[-1] if self.frames else None
            if prev is not None and prev.pose_valid and prev.segment == self.segment:
                tf = self._duplicate(rec, prev, exposure)
                self.frames.append(rec)
                tf.result.time_track_s = time.perf_counter() - t0
                self.observer.on_frame(tf.result)
                return tf
        self.frames.append(rec)
        pyr = self._pool.acquire()
        pyr.build(img)
        rgb = (lambda f=frame: f.rgb)
        if not self.initialized:
            tf = self._track_initializer(rec, pyr, exposure, rgb)
        else:
            tf = self._track_coarse(rec, pyr, exposure, rgb)
        tf.result.time_track_s = time.perf_counter() - t0
        self.observer.on_frame(tf.result)
        return tf

    def map(self, tracked: TrackedFrame) -> None:
        """The mapping half (DSO ``makeKeyFrame`` / ``makeNonKeyFrame``)."""
        if tracked.pyramid is None:  # a duplicate frame: nothing to map
            return
        try:
            if tracked.initialize is not None:
                self._start_window(tracked)
            elif tracked.record.status == FrameStatus.TRACKED:
                if tracked.need_keyframe:
                    self._make_keyframe(tracked)
                else:
                    self._make_non_keyframe(tracked)
        finally:
            self._pool.release(tracked.pyramid)

    def finish(self) -> list:
        """End of the sequence: keyframes still in the window get their final pose, and every frame is re-chained to
        its reference keyframe's final pose (DSO prints the trajectory this way). With ``emit_messages``, returns the
        last messages for the mapper: what is still in the outbox, the final pose of every keyframe and the points
        still active (as :class:`~mgso.messages.PointsMessage`); otherwise ``[]``."""
        if self.map_thread:
            self._mapping.stop()  # every queued frame mapped first
        w = self.window
        for s in w.order:
            kid = int(w.keyframe_id_[s])
            if kid in self.keyframes:
                self.keyframes[kid].cam_to_world = w.cam_to_world(s)
        self._rechain_frames()
        if not self.emit_messages:
            return []
        return self._mapping.take_ready() + self.outbox.final(sorted(self.keyframes),
                                                               self.keyframe_trajectory().cam_to_world, self.segment)

    def segment_similarity(self, segment: int) -> np.ndarray:
        """4x4 similarity ``[[s R, t], [0, 1]]`` from a segment's frame to the common world (identity for 0)."""
        return self.segments.similarity(segment)

    def to_world(self, segment: int, cam_to_world: np.ndarray) -> np.ndarray:
        """A camera pose of ``segment`` in the common world (a rigid pose: the similarity's scale moves the camera
        centre only)."""
        return self.segments.to_world(segment, cam_to_world)

    def trajectory(self) -> Trajectory:
        """Every frame with a pose, camera-to-world in the common world (segments chained)."""
        good = [f for f in self.frames if f.pose_valid]
        if not good:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array([f.timestamp for f in good]),
                          np.stack([self.to_world(f.segment, f.cam_to_world) for f in good]))

    def keyframe_trajectory(self) -> Trajectory:
        """The keyframes, camera-to-world in the common world."""
        kfs = sorted(self.keyframes.values(), key=lambda k: k.keyframe_id)
        if not kfs:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array([k.timestamp for k in kfs]),
                          np.stack([self.to_world(k.segment, k.cam_to_world) for k in kfs]))

    @property
    def point_cloud(self):
        """The window's marginalised points (each in its segment's frame; see :meth:`point_cloud_world`)."""
        return self.window.cloud

    def point_cloud_world(self, include_active: bool = True, with_hosts: bool = False) -> tuple[np.ndarray, ...]:
        """``(positions [M, 3], colours [M, 3])`` of the marginalised points (and, by default, the active ones) in
        the common world; ``with_hosts``: and ``host keyframe ids [M]`` (what points.ply's ``keyframe`` column
        holds in every stage)."""
        cloud = self.window.cloud
        pos, col, seg = cloud.positions.astype(np.float64), cloud.colors, cloud.segments
        hosts = cloud.host_keyframe_ids
        a = self.window.active
        if include_active and a.n:
            pos = np.concatenate([pos, self.window.points_world()])
            col = np.concatenate([col, a.rgb])
            seg = np.concatenate([seg, np.full(a.n, self.segment)])
            hosts = np.concatenate([hosts, self.window.keyframe_id_[a.host[:a.n]].astype(np.int64)])
        out = self.segments.mixed_to_world(pos, seg)
        return (out.astype(np.float32), col, hosts) if with_hosts else (out.astype(np.float32), col)

    # ------------------------------------------------------------------------------------ initialisation
    def _track_initializer(self, rec: FrameRecord, pyr, exposure, rgb) -> TrackedFrame:
        ini = self.initializer
        if not ini.has_first:
            return self._set_first(rec, pyr, exposure, rgb)
        res = ini.track_frame(pyr, exposure, index=rec.index)
        if res.status == InitStatus.FAILED:
            log.info("initialisation failed at frame %d: %s; restarting from it", rec.index, res.message)
            out = self._set_first(rec, pyr, exposure, rgb)
            out.result.status = rec.status = FrameStatus.INIT_FAILED
            out.result.init = res
            return out
        if res.status == InitStatus.INITIALIZED:
            rec.status = FrameStatus.INITIALIZED
            result = FrameResult(rec.index, rec.timestamp, rec.status, rec.segment, None, True, "first", init=res)
            return TrackedFrame(rec, pyr, exposure, rgb, True, KeyframeReason.FIRST.value, result, initialize=res)
        rec.status = FrameStatus.INITIALIZING
        result = FrameResult(rec.index, rec.timestamp, rec.status, rec.segment, None, False, init=res)
        return TrackedFrame(rec, pyr, exposure, rgb, False, "", result)

    def _set_first(self, rec, pyr, exposure, rgb) -> TrackedFrame:
        res = self.initializer.set_first(pyr, exposure, frame=(rec, rgb), index=rec.index)
        rec.status = FrameStatus.FIRST_FRAME if res.status == InitStatus.FIRST_FRAME else FrameStatus.INIT_FAILED
        result = FrameResult(rec.index, rec.timestamp, rec.status, rec.segment, None, False, init=res)
        return TrackedFrame(rec, pyr, exposure, rgb, False, "", result)

    def _start_window(self, tracked: TrackedFrame) -> None:
        """DSO ``initializeFromInitializer`` + ``makeKeyFrame`` of the second frame."""
        ini = self.initializer
        cfg = self.config.tracking
        w = self.window
        first_rec, first_rgb = ini.first_frame
        xy, iR, typ = ini.level0_points()
        rescale = 1.0 / ((float(np.sum(iR)) + 1e-5) / (len(iR) + 1e-5))
        idepth = iR * rescale
        # a new segment lives in its own frame; its chaining similarity is computed here
        if self.segment > 0 and self.segment not in self.segments:
            self.segments.set(self.segment, self._chain_segment(idepth))
        first_to_new = tracked.initialize.first_to_new.copy()
        first_to_new[:3, 3] /= rescale
        # the initialiser's mean motion per frame: the first tracked frame's constant-motion guess (DSO has only
        # the identity there, which fails at car speed). Per frame of the source, not per frame the initialiser
        # saw: in real time frames are dropped while the initialiser is slow, and the motion over the processed
        # frames would overstate the next frame's step by the gap (issue 13: KITTI at 10 fps lost frames 3-8)
        span = int(tracked.record.index) - int(first_rec.index)
        n_frames = span if span >= 1 else max(int(tracked.initialize.frames), 1)
        self._init_rmse = float(tracked.initialize.rmse) if np.isfinite(tracked.initialize.rmse) else -1.0
        self._init_step = se3_exp(se3_log(se3_inverse(first_to_new)) / n_frames)
        pos = idepth > 0
        self._segment_median_depth = float(np.median(1.0 / idepth[pos])) if pos.any() else float("inf")
        self._segment_steps = []
        self._prev_rec = None
        keep = self._rng.random(len(xy)) <= cfg.point_density / max(len(xy), 1)
        xy, idepth, typ = xy[keep], idepth[keep], typ[keep]
        g = self.geometry
        inside = (xy[:, 0] >= 3) & (xy[:, 0] < g.width - 4) & (xy[:, 1] >= 3) & (xy[:, 1] < g.height - 4)
        xy, idepth, typ = xy[inside], idepth[inside], typ[inside]
        c2w_first = np.eye(4)  # each segment starts at its own origin (see the module text)
        first_rec.cam_to_world = c2w_first
        first_rec.status = FrameStatus.FIRST_FRAME
        first_rec.segment = self.segment
        slot0 = w.add_keyframe(frame_index=first_rec.index, timestamp=first_rec.timestamp,
                               world_to_cam=se3_inverse(c2w_first), affine=(0.0, 0.0), exposure=ini.first_exposure,
                               pyramid=ini.first_pyramid, rgb=self._adjusted_rgb(first_rgb), segment=self.segment)
        kid0 = int(w.keyframe_id_[slot0])
        first_rec.keyframe_id = kid0
        self.keyframes[kid0] = KeyframeRecord(kid0, first_rec.index, first_rec.timestamp, self.segment, c2w_first)
        pat = extract_patterns(w.pyramids[slot0].dI[0], xy.astype(np.float32), grad_c2=cfg.outlier_th_sum_component)
        ok = pat.valid
        w.add_active_points(host=np.full(int(ok.sum()), slot0), uv=xy[ok], idepth=idepth[ok], color=pat.color[ok],
                            weight=pat.weight[ok], type=typ[ok], has_depth_prior=True)
        self.observer.on_keyframe(KeyframeEvent(kid0, first_rec.index, first_rec.timestamp, self.segment,
                                                self.to_world(self.segment, c2w_first), KeyframeReason.FIRST.value,
                                                None, 0, w.describe()))
        self.outbox.keyframe(kid0, first_rec, self.to_world(self.segment, c2w_first))
        rec = tracked.record
        rec.cam_to_tracking_ref = se3_inverse(first_to_new)
        rec.tracking_ref = kid0
        rec.cam_to_world = c2w_first @ rec.cam_to_tracking_ref
        rec.affine = (0.0, 0.0)
        tracked.result.cam_to_world = self.to_world(self.segment, rec.cam_to_world)
        self.initialized = True
        self._make_keyframe(tracked)

    def _chain_segment(self, idepth: np.ndarray) -> np.ndarray:
        """The similarity of a new segment: its origin at the previous segment's last reliable pose (common world),
        its scale matching that segment's last median depth (clamped to [0.05, 20] against a broken reference)."""
        last = self._last_good
        if last is None or last.cam_to_world is None:
            return np.eye(4)
        anchor = self.to_world(last.segment, self._chained_pose(last))
        prev = self.segment_similarity(last.segment)
        s_prev = float(np.cbrt(np.linalg.det(prev[:3, :3])))
        med_new = float(np.median(1.0 / idepth[idepth > 0])) if np.any(idepth > 0) else float("nan")
        s = 1.0
        if np.isfinite(self._last_median_depth) and np.isfinite(med_new) and med_new > 0:
            s = float(np.clip(s_prev * self._last_median_depth / med_new, 0.05, 20.0))
        S = np.eye(4)
        S[:3, :3] = s * anchor[:3, :3]
        S[:3, 3] = anchor[:3, 3]
        return S

    # ---------------------------------------------------------------------------------------- tracking
    def _offer_reference(self, ref: TrackingReference) -> None:
        with self._ref_lock:
            self._pending_reference = ref

    def _swap_reference(self) -> None:
        with self._ref_lock:
            ref, self._pending_reference = self._pending_reference, None
        if ref is not None:
            self.tracker.set_reference(ref)

    def _ref_cam_to_world(self, keyframe_id: int) -> np.ndarray:
        w = self.window
        try:
            return w.cam_to_world(w.slot_of_keyframe(keyframe_id))
        except KeyError:
            return self.keyframes[keyframe_id].cam_to_world

    def _tracking_ref_pose(self, keyframe_id: int) -> np.ndarray:
        """The reference keyframe's pose as the tracking thread uses it. With ``map_thread`` the window belongs to the
        mapping thread, whose optimisation moves the keyframes in place step by step (a trial step it then rejects
        too, until it restores the backup): the tracking thread reads the pose the last finished optimisation left in
        the keyframe's record instead (DSO: the shell's ``camToWorld``, written under a lock after each
        optimisation). Reading the window there put a frame tracked during an optimisation where the trial step had
        moved its reference: good residuals, a wrong place, and in real time a loss as a ``jump``. Without the thread
        the window is read, as before (the deterministic mode is unchanged)."""
        if self.map_thread:
            kf = self.keyframes.get(keyframe_id)
            if kf is not None:
                return kf.cam_to_world
        return self._ref_cam_to_world(keyframe_id)

    def _motion_prior(self, rec: FrameRecord, *, per_source_frame: bool = True):
        """``(prev, last, prelast)``: the record before ``rec`` and the two poses whose motion DSO assumes again
        for ``rec`` (``None`` where there are none in this segment). ``per_source_frame``: when the source dropped
        frames the odometry never saw (real time: the player drops what arrives while the odometry is busy), the
        motion is scaled to the gaps, ``prelast`` moved so that ``last``'s step from it covers as many source frames
        as ``rec``'s from ``last`` (DSO's constant motion, per frame of the camera rather than per frame processed).
        Repeated frames (skipped as duplicates) count as no time, as before; with nothing dropped every gap is one
        frame and nothing is scaled, so the deterministic mode is unchanged."""
        recent = self.frames[-8:]                          # rec is the last
        before = [f for f in recent[:-1] if f.status != FrameStatus.DUPLICATE]  # repeats tell no motion
        prev = before[-1] if before else None
        prev2 = before[-2] if len(before) >= 2 else None
        last = prev.cam_to_world if prev is not None and prev.pose_valid and prev.segment == self.segment else None
        prelast = (prev2.cam_to_world if prev2 is not None and prev2.pose_valid and prev2.segment == self.segment
                   else None)
        old_steps = None
        if last is not None and prelast is None and self._init_step is not None:
            prelast = last @ se3_inverse(self._init_step)  # right after initialisation: its mean motion
            old_steps = 1                                  # per source frame (_start_window)
        elif prelast is not None:
            old_steps = self._source_steps(recent, prev2, prev)
        if per_source_frame and last is not None and old_steps is not None:
            ratio = self._source_steps(recent, prev, rec) / old_steps
            if ratio != 1.0:
                step = se3_inverse(prelast) @ last
                prelast = last @ se3_inverse(se3_exp(ratio * se3_log(step)))
        return prev, last, prelast

    @staticmethod
    def _source_steps(recent, a: FrameRecord, b: FrameRecord) -> int:
        """Frames of the source from ``a`` to ``b``, the repeated frames between them not counted."""
        dups = sum(1 for f in recent if a.index < f.index < b.index and f.status == FrameStatus.DUPLICATE)
        return max(int(b.index) - int(a.index) - dups, 1)

    def _track_coarse(self, rec: FrameRecord, pyr, exposure, rgb) -> TrackedFrame:
        t0 = time.perf_counter()
        self._swap_reference()
        cfg = self.config.tracking
        ref = self.tracker.reference
        ref_c2w = self._tracking_ref_pose(ref.keyframe_id)
        prev, last, prelast = self._motion_prior(rec)
        hyps = motion_hypotheses(ref_c2w, last, prelast, rotations=cfg.coarse_rotation_hypotheses,
                                 rotation_delta=cfg.coarse_rotation_delta)
        aff0 = prev.affine if (prev is not None and prev.pose_valid) else (0.0, 0.0)
        budget = cfg.realtime_hypothesis_budget_ms
        deadline = t0 + budget / 1000.0 if self.map_thread and budget > 0 else None   # real time only
        tr = self.tracker.track_frame(pyr, exposure, hyps, aff0, deadline=deadline)
        reason = self._loss(tr)
        if reason is not None:
            return self._lose(rec, pyr, exposure, rgb, tr, reason)
        rec.status = FrameStatus.TRACKED
        rec.cam_to_tracking_ref = se3_renormalize(tr.cam_to_ref)
        rec.tracking_ref = ref.keyframe_id
        rec.affine = tr.affine
        rec.cam_to_world = se3_renormalize(ref_c2w @ rec.cam_to_tracking_ref)
        if self._prev_rec is not None and self._same_chain(ref.keyframe_id):
            self._segment_steps.append(self._step_per_source_frame(rec.cam_to_world))
            if len(self._segment_steps) > 4 * cfg.lost_speed_window:     # only the recent ones are read
                del self._segment_steps[:-cfg.lost_speed_window]
        self._prev_rec = rec
        baseline = tr.baseline_rmse if tr.baseline_rmse > 0 else self._init_rmse
        if tr.inlier_ratio >= 0.5 and (baseline <= 0 or tr.rmse0 <= cfg.kf_rmse_factor * baseline):
            self._last_good = rec  # a reliable pose: where a later segment would be chained
        a_rel, _ = affine_from_to(ref.affine[0], ref.affine[1], tr.affine[0], tr.affine[1], ref.exposure, exposure)
        self._frames_since_kf += 1
        dec: KeyframeDecision = self.policy.decide(tr.flow, a_rel, tr.rmse0, ref.first_rmse, self._frames_since_kf)
        result = FrameResult(rec.index, rec.timestamp, rec.status, rec.segment,
                             self.to_world(rec.segment, rec.cam_to_world), dec.need,
                             dec.reason.value if dec.need else "", track=tr)
        return TrackedFrame(rec, pyr, exposure, rgb, dec.need, dec.reason.value, result)

    def _duplicate(self, rec: FrameRecord, prev: FrameRecord, exposure: float) -> TrackedFrame:
        """A repeated image: the previous frame's pose, kept relative to the same keyframe (to the previous frame
        itself when it is a keyframe) so that it follows the window's corrections. The tracker, the keyframe policy
        and the immature points do not see it: its RMSE of 0 against a keyframe would become the baseline every later
        frame is judged by."""
        self.num_duplicates += 1
        rec.status = FrameStatus.DUPLICATE
        if prev.keyframe_id >= 0:
            rec.tracking_ref, rec.cam_to_tracking_ref = prev.keyframe_id, np.eye(4)
        else:
            rec.tracking_ref, rec.cam_to_tracking_ref = prev.tracking_ref, prev.cam_to_tracking_ref
        rec.affine = prev.affine
        rec.cam_to_world = self._chained_pose(prev)  # with the window's latest correction of its keyframe
        log.debug("frame %d repeats frame %d: pose copied", rec.index, prev.index)
        result = FrameResult(rec.index, rec.timestamp, rec.status, rec.segment,
                             self.to_world(rec.segment, rec.cam_to_world), False)
        return TrackedFrame(rec, None, exposure, None, False, "", result)

    def _loss(self, tr: TrackResult) -> LossReason | None:
        cfg = self.config.tracking
        self._loss_detail = ""              # what a JUMP measured, for the message
        if not (np.all(np.isfinite(tr.ref_to_new)) and np.all(np.isfinite(tr.affine))):
            return LossReason.NON_FINITE
        if not tr.ok:
            return LossReason.NO_HYPOTHESIS
        if not np.isfinite(tr.rmse0):
            return LossReason.NON_FINITE
        baseline = tr.baseline_rmse if tr.baseline_rmse > 0 else self._init_rmse  # a new segment: the init's
        base = max(baseline, cfg.lost_min_rmse)
        if tr.rmse0 > cfg.lost_rmse_factor * base:
            return LossReason.RESIDUAL
        if tr.fit_ratio < cfg.lost_min_inlier_ratio or tr.num_inliers < cfg.lost_min_inliers:
            return LossReason.INLIERS
        ref = self.tracker.reference
        depth = min(ref.median_depth, self._segment_median_depth)  # a map drifted to infinity must not excuse it
        if not np.isfinite(depth) or np.linalg.norm(tr.ref_to_new[:3, 3]) > cfg.lost_max_translation * depth:
            self._loss_detail = (f"; {np.linalg.norm(tr.ref_to_new[:3, 3]):.3g} from the reference, above "
                                 f"{cfg.lost_max_translation:g} x its median depth {depth:.3g}")
            return LossReason.JUMP
        if len(self._segment_steps) >= 5 and self._prev_rec is not None and self._same_chain(ref.keyframe_id):
            step = self._step_per_source_frame(self._tracking_ref_pose(ref.keyframe_id) @ tr.cam_to_ref)
            # the typical motion of the last frames, not of the whole segment: a camera that speeds up, and a
            # monocular scale that drifts, move it (with the segment's median and its first depth, real-time runs on
            # 7-Scenes lost frames that moved 10-14x that median with residuals as good as the frames before)
            depth_now = ref.median_depth if np.isfinite(ref.median_depth) and ref.median_depth > 0 \
                else self._segment_median_depth
            typical = max(float(np.median(self._segment_steps[-cfg.lost_speed_window:])), 0.01 * depth_now)
            if step > cfg.lost_max_speed_factor * typical:
                self._loss_detail = (f"; moved {step:.3g} a source frame, above {cfg.lost_max_speed_factor:g} x the "
                                     f"segment's recent typical {typical:.3g}")
                return LossReason.JUMP
        return None

    def _lose(self, rec, pyr, exposure, rgb, tr: TrackResult, reason: LossReason) -> TrackedFrame:
        baseline = tr.baseline_rmse if tr.baseline_rmse > 0 else self._init_rmse
        ev = TrackingLost(rec.index, rec.timestamp, self.segment, reason, tr.rmse0, baseline,
                          tr.inlier_ratio, f"tracking lost at frame {rec.index} ({reason.value}: rmse {tr.rmse0:.2f}, "
                          f"first rmse {baseline:.2f}, inliers {tr.inlier_ratio:.2f}, in view {tr.view_ratio:.2f}"
                          f"{self._loss_detail})")
        log.warning(ev.message)
        self.losses.append(ev)
        rec.status = FrameStatus.LOST
        self.observer.on_tracking_lost(ev)
        self._end_segment()
        self.segment += 1
        rec.segment = self.segment
        out = self._set_first(rec, pyr, exposure, rgb)
        out.result.status = FrameStatus.LOST
        rec.status = FrameStatus.LOST
        out.result.lost = ev
        out.result.track = tr
        return out

    def _end_segment(self) -> None:
        """Close the window: keyframes keep their last poses, active points go to the point cloud."""
        if self.map_thread:
            self._mapping.wait()  # the mapping thread finishes the frames before the loss first
        w = self.window
        ref = self.tracker.reference
        if ref is not None:
            self._last_median_depth = ref.median_depth
        for s in w.order:
            kid = int(w.keyframe_id_[s])
            if kid in self.keyframes:
                self.keyframes[kid].cam_to_world = w.cam_to_world(s)
                self.keyframes[kid].in_window = False
        if w.active.n:
            pts = w.marginalize_points(np.ones(w.active.n, bool))
            self.observer.on_points_marginalized(pts)
            self.outbox.points(pts)
        w.clear()
        self.tracker.set_reference(None)
        with self._ref_lock:
            self._pending_reference = None
        self.initialized = False
        self._frames_since_kf = 0

    # ------------------------------------------------------------------------------------------ mapping
    @staticmethod
    def _rgb(rgb) -> np.ndarray | None:
        try:
            return rgb() if callable(rgb) else rgb
        except Exception:  # a frame without colour: points get gray
            log.debug("no RGB for the keyframe", exc_info=True)
            return None

    def _adjusted_rgb(self, rgb) -> np.ndarray | None:
        img = self._rgb(rgb)
        return None if img is None else self.geometry.adjust(np.asarray(img, dtype=np.float32))

    def _make_non_keyframe(self, tracked: TrackedFrame) -> None:
        rec = tracked.record
        rec.cam_to_world = self._ref_cam_to_world(rec.tracking_ref) @ rec.cam_to_tracking_ref
        tracked.result.trace = trace_immature_points(self.window, tracked.pyramid, se3_inverse(rec.cam_to_world),
                                                     rec.affine, tracked.exposure, self.trace_params)

    def _make_keyframe(self, tracked: TrackedFrame) -> None:
        w = self.window
        cfg = self.config.tracking
        rec = tracked.record
        rec.cam_to_world = self._ref_cam_to_world(rec.tracking_ref) @ rec.cam_to_tracking_ref
        w2c = se3_inverse(rec.cam_to_world)
        tracked.result.trace = trace_immature_points(w, tracked.pyramid, w2c, rec.affine, tracked.exposure,
                                                     self.trace_params)
        self.back_end.flag_frames_for_marginalization(w)
        slot = w.add_keyframe(frame_index=rec.index, timestamp=rec.timestamp, world_to_cam=w2c, affine=rec.affine,
                              exposure=tracked.exposure, pyramid=tracked.pyramid,
                              rgb=self._adjusted_rgb(tracked.rgb), segment=self.segment)
        kid = int(w.keyframe_id_[slot])
        rec.keyframe_id = kid
        self.keyframes[kid] = KeyframeRecord(kid, rec.index, rec.timestamp, self.segment, rec.cam_to_world.copy())
        self._frames_since_kf = 0
        act = self.activator.activate(w)
        opt = self.back_end.optimize(w)
        for s in w.order:  # the back end may have moved keyframes
            self.keyframes[int(w.keyframe_id_[s])].cam_to_world = w.cam_to_world(s)
        ref = make_tracking_reference(w, cfg, self.device)
        self._last_median_depth = ref.median_depth
        self._offer_reference(ref)
        marg = self.back_end.marginalize_points(w)
        if len(marg):
            self.observer.on_points_marginalized(marg)
            self.outbox.points(marg)
        n_new = make_immature_points(w, slot, self.selector, cfg.immature_density,
                                     grad_c2=cfg.outlier_th_sum_component, recursions=cfg.selector_recursions)
        removed = self.back_end.marginalize_frames(w)
        for kid_r in removed:
            if kid_r in self.keyframes:
                self.keyframes[kid_r].in_window = False
        self.observer.on_keyframe(KeyframeEvent(kid, rec.index, rec.timestamp, self.segment,
                                                self.to_world(self.segment, rec.cam_to_world), tracked.reason, act,
                                                n_new, w.describe()))
        self.outbox.keyframe(kid, rec, self.to_world(self.segment, rec.cam_to_world))
        ids = [int(w.keyframe_id_[s]) for s in w.order]
        poses = np.stack([self.to_world(self.segment, w.cam_to_world(s)) for s in w.order])
        self.observer.on_window_optimized(WindowUpdate(
            ids, poses, self.segments.points_to_world(w.points_world(), self.segment).astype(np.float32),
            w.active.rgb.copy(), opt))
        self.outbox.window_poses(ids, poses)
        if self.tracker.reference is None:  # the very first reference: nothing to wait for
            self._swap_reference()

    def _step_per_source_frame(self, cam_to_world: np.ndarray) -> float:
        """The camera's move from the previous tracked frame to ``cam_to_world`` (the frame being tracked, the last
        record), per frame of the source: in real time the player drops the frames that arrive while the odometry is
        busy, and after a stall of 10 frames (a frame that tries all 31 motion hypotheses takes ~300 ms at 640x480 on
        2 cores) the move is 10 frames' worth, which the speed check (``lost_max_speed_factor`` x the segment's
        typical step) read as a jump and lost tracking. Repeated frames count as no time, as in the motion prior;
        with nothing dropped the gap is one frame and nothing changes (the deterministic mode is bit-identical)."""
        step = float(np.linalg.norm(cam_to_world[:3, 3] - self._prev_pose()[:3, 3]))
        return step / self._source_steps(self.frames[-16:], self._prev_rec, self.frames[-1])

    def _same_chain(self, keyframe_id: int) -> bool:
        """Whether the previous tracked frame hangs on the keyframe a new frame is tracked against (its own keyframe,
        or its tracking reference). On the first frame after the reference changed the two poses hang on different
        keyframes, and their difference holds the window's correction of one keyframe against the other besides the
        camera's motion: real-time runs on 7-Scenes lost such frames as jumps (0.07-0.11 against a typical 0.006-0.007,
        residuals as good as the frames before), the reference having changed while the mapping thread optimised.
        The speed check skips that frame (the distance to the reference is still checked)."""
        p = self._prev_rec
        return (p.keyframe_id if p.keyframe_id >= 0 else p.tracking_ref) == keyframe_id

    def _prev_pose(self) -> np.ndarray:
        """The previous tracked frame's pose against its keyframe's current pose (the window may have moved it
        since: comparing with the pose it had when it was tracked would read the correction as a jump)."""
        return self._chained_pose(self._prev_rec)

    def _chained_pose(self, f: FrameRecord) -> np.ndarray:
        """A frame's pose from its keyframe's current pose (the back end may have moved it since the frame was
        tracked)."""
        if f.keyframe_id >= 0 and f.keyframe_id in self.keyframes:
            return self.keyframes[f.keyframe_id].cam_to_world.copy()
        if f.tracking_ref >= 0 and f.tracking_ref in self.keyframes and f.cam_to_tracking_ref is not None:
            return self.keyframes[f.tracking_ref].cam_to_world @ f.cam_to_tracking_ref
        return f.cam_to_world

    def _rechain_frames(self) -> None:
        for f in self.frames:
            if not f.pose_valid:
                continue
            if f.keyframe_id >= 0 and f.keyframe_id in self.keyframes:
                f.cam_to_world = self.keyframes[f.keyframe_id].cam_to_world.copy()
            elif f.tracking_ref >= 0 and f.tracking_ref in self.keyframes and f.cam_to_tracking_ref is not None:
                f.cam_to_world = self.keyframes[f.tracking_ref].cam_to_world @ f.cam_to_tracking_ref
