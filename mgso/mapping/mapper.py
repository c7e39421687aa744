"""MGSO's mapping thread: keyframe messages in, a trained Gaussian map out (docs/mgso.md).

The :class:`Mapper` owns the Gaussian map (:class:`~mgso.mapping.gaussian_map.GaussianMap`), the training views
(:class:`~mgso.mapping.views.ViewSet`, one per keyframe) and the trainer. It reads typed messages
(:mod:`mgso.messages`) from a bounded :class:`queue.Queue` and applies them between training steps:

- :class:`~mgso.messages.KeyframeMessage`: seed new Gaussians from the keyframe's DSO points where the map
  is still empty (:func:`~mgso.mapping.seeding.seed_keyframe`: coverage render, Delaunay fill, visibility filter),
  then add the keyframe as a training view with its exposure (below);
- :class:`~mgso.messages.PoseUpdate`: move the views of refined keyframes (the map follows the odometry;
  the odometry never waits for the map);
- :class:`~mgso.messages.PointsMessage`: seed from points with their final depth, seen from their host
  keyframe, where the map is still empty (no Delaunay fill: that keyframe was filled when it arrived); in real time
  the points wait while messages are queued and one host's are seeded together (:meth:`Mapper._on_points`);
- :class:`~mgso.messages.LoopCorrection`: loop closure moved keyframes: move their views, depth points and
  the Gaussians anchored to them by each keyframe's Sim(3);
- :class:`~mgso.messages.Stop`: run the final refinement (``mapping.mapper.final_iterations`` steps over all
  keyframes, chosen as while running) unless the run was interrupted, and stop.

Between messages it trains: :class:`~mgso.mapping.trainer.Trainer` with the
:class:`~mgso.mapping.views.NewestOrRandomSampler` (the newest keyframe with ``mapping.mapper.newest_probability``,
0 by default, otherwise any: in the deterministic mode half of each draw in proportion to the keyframes' latest losses,
``mapping.mapper.loss_share``, in real time uniformly; ``mapping.mapper.sampler``
``least_used``: :class:`~mgso.mapping.views.LeastUsedSampler`), Gaussian-pyramid levels
(``mapping.train.pyramid_levels``) and densification / pruning by the strategy (``mapping.densify``).

**Exposure.** Each view's exposure ``(a', b')`` (the loss compares ``exp(a') render + b'`` with the keyframe) follows
``mapping.mapper.exposure`` (:meth:`Mapper.exposure_for`); with ``odometry`` it starts from DSO's affine brightness
and exposure time (:func:`~mgso.messages.map_exposure`), so the map stores
radiance at the first keyframe's exposure, not each image's brightness; seed colours are converted to radiance the
same way. With ``mapping.train.learn_exposure`` the trainer learns a correction on top (its own Adam per view); a
pose update that refines DSO's (a, b) shifts the view's exposure by DSO's change and keeps the learned correction.

**Modes.** Deterministic (:meth:`process_pending`, in the caller's thread): messages in order, a fixed
``mapping.mapper.iterations_per_keyframe`` steps after each keyframe message (at the pyramid level of
``running_max_pixels`` with ``keyframe_steps_coarse``, the default); the same map on every CPU run.
Real time (:meth:`start`): a thread drains every pending message, trains one step, and repeats; it blocks on the
queue only while it has nothing to train. While messages wait it keeps ``mapping.mapper.running_train_share`` of
its time for training, and while the stream runs it trains at the pyramid level of ``running_max_pixels``; so do
the first ``final_coarse_share`` (0.95 in real time) of the final refinement's steps, the first
``final_coarser_share`` of them (0.6 in real time, 0.4 deterministic) a level coarser still, the rest at full
resolution.
Far behind (``defer_seeding_above``), a keyframe's seeding waits with its marginalised points until the queue is
empty. The real-time system runs the same loop in a process of its own
(:class:`mgso.mapping.process.MapperProcess`). Watchers ask for copies and renders of the map at any time
(:meth:`request_snapshot`, :meth:`request_render`), answered at the next safe point (:meth:`safe_point`).
:meth:`submit` puts a message on the bounded queue; when it is full the caller waits (backpressure), and every wait
is counted in :class:`MapperStats`.

Ownership: the map, the views and the trainer are changed only by the thread that runs the mapper (the caller's in
deterministic mode, the mapping thread in real time). Read them after :meth:`stop` (or between
:meth:`process_pending` calls).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from mgso.config import Config
from mgso.geometry import orthonormalize, se3_exp, se3_inverse, se3_log, sim3_to_parts
from mgso.mapping.gaussian_map import GaussianArrays, GaussianMap
from mgso.messages import (KeyframeMessage, LoopCorrection, MapperMessage, PointsMessage, PoseUpdate, Stop,
                                   map_exposure, sim3_apply_to_pose)
from mgso.mapping.seeding import (COVERAGE_DOWNSCALE, KeyframeSeedInput, SeedResult, SeedStatus, gaussians_from_seeds,
                                  map_seen_from, plan_seeds, seed_keyframe, seed_scales)
from mgso.mapping.snapshot import MapSnapshot, SnapshotBoard, snapshot_of
from mgso.mapping.strategy import DefaultStrategy
from mgso.mapping.trainer import STAGES, StepResult, Trainer, TrainStep, masked_psnr, usable_level
from mgso.mapping.views import LeastUsedSampler, NewestOrRandomSampler, TrainView, ViewSet
from mgso.observers import Observer

__all__ = ["Mapper", "MapperStats", "MapperError", "MapUpdate", "MapState"]

log = logging.getLogger(__name__)

_FLUSH_BUDGET_S = 1.0   # real time: seconds of waiting seedings done each time the queue is empty (Mapper._run)


class MapperError(RuntimeError):
    """The mapping thread failed; the original exception is the ``__cause__``."""


@dataclass
class MapperStats:
    """Counts and times of a mapper's work (values, read after :meth:`Mapper.stop`)."""

    keyframes: int = 0                      # keyframe messages applied (= training views)
    keyframes_untrusted: int = 0            # of them, depths mostly missing the map: no depth term, pose refined
    # of them, where the map's depths were three times theirs or more (mapping.seeding.distrust_median), and the
    # keyframe after whose seeding the run's odometry was judged untrusted (None: never)
    keyframes_scale_broken: int = 0
    odometry_untrusted_at: int | None = None
    # loop corrections that moved only the odometry's poses, the map held (mapping.mapper.loop_moves_untrusted)
    loop_corrections_held: int = 0
    pose_updates: int = 0                   # PoseUpdate messages applied
    poses_applied: int = 0                  # keyframe poses moved by them
    poses_unknown: int = 0                  # poses for keyframes the map does not have (ignored)
    point_messages: int = 0                 # PointsMessage messages
    points_received: int = 0
    # real time: point messages seeded together with an earlier one of the same host keyframe (one coverage render
    # for all), because they arrived while the mapper was behind (see Mapper._on_points)
    points_coalesced: int = 0
    gaussians_seeded: int = 0               # added by seeding (keyframes and marginalised points)
    seeds_skipped_too_few: int = 0          # seedings that added nothing (fewer than min_new_gaussians survived)
    points_too_far: int = 0                 # DSO points not seeded: deeper than max_depth_factor x their median
    steps: int = 0                          # training steps, all of them
    train_seconds: float = 0.0              # wall time inside training steps
    # of it, the seconds of each stage of the steps (trainer.STAGES: render, loss, backward, adam, strategy), and
    # the (tile, Gaussian) pairs the steps' renders listed, summed: where a step's time goes on this run's map
    stage_seconds: dict = field(default_factory=lambda: {name: 0.0 for name in STAGES})
    pairs: int = 0
    final_steps: int = 0                    # steps of the final refinement (included in steps)
    final_coarse_steps: int = 0             # of them at the coarser level (mapping.mapper.final_coarse_share)
    final_coarser_steps: int = 0            # of those a level coarser still (mapping.mapper.final_coarser_share)
    final_budget_s: float = 0.0             # the final refinement's time budget (mapping.mapper.final_budget_s; 0: none)
    final_seconds: float = 0.0
    final_threads: int = 0                  # CPU threads of the final refinement's kernel launches (0: none ran)
    # the mapper's process: its CPU priority while the camera ran and in the final refinement ("SCHED_IDLE",
    # "nice +N", "normal"); "" for a mapper in the odometry's process
    priority: str = ""
    final_priority: str = ""
    seed_seconds: float = 0.0               # wall time seeding (coverage render, plan, add)
    seed_seconds_streaming: float = 0.0     # of it before the stream ended (real time: while the camera ran)
    coverage_renders: int = 0               # seedings that rendered the map's coverage (not: too few points, empty map)
    cpu_seconds: float | None = None        # CPU time of the mapper in real time (its process's, or its thread's)
    queue_waits: int = 0                    # submits that found the queue full and waited (backpressure)
    queue_wait_seconds: float = 0.0
    max_queue_depth: int = 0                # most messages waiting at once (seen at submit)
    # real time: the pyramid level of the steps while the stream ran (mapping.mapper.running_max_pixels), and the
    # steps taken while messages waited (mapping.mapper.running_train_share)
    running_level: int = 0
    steps_while_behind: int = 0
    # steps taken before the stream ended (real time: while the camera ran; the rest are catch-up and final steps)
    steps_while_streaming: int = 0
    # real time: keyframe seedings deferred while the queue was deep (mapping.mapper.defer_seeding_above)
    seedings_deferred: int = 0
    # real time: messages still queued when the stream ended (-1: not seen), and the seconds from then until the
    # last was applied and the waiting points seeded (before the final refinement)
    stream_ended_at_depth: int = -1
    catch_up_seconds: float = 0.0
    image_blocks: int = 0                   # mapper's process: shared-memory blocks of keyframe images it took
    loop_corrections: int = 0               # LoopCorrection messages applied
    gaussians_moved: int = 0                # Gaussians moved by them (each time it moved)
    # keyframes whose pose the map began to refine because a loop correction moved them (loop_refines_poses)
    loop_poses_refined: int = 0
    densify: dict = field(default_factory=lambda: {"refines": 0, "cloned": 0, "split": 0, "pruned": 0,
                                                   "pruned_opacity": 0, "pruned_world": 0, "pruned_screen": 0,
                                                   "pruned_weight": 0, "skipped_capacity": 0, "opacity_resets": 0,
                                                   "clamped_aspect": 0})
    seed_results: list = field(default_factory=list)   # SeedResult per seeding, in order
    # (frame index, timestamp, training steps so far, Gaussians) after each keyframe is applied, and once after the
    # final refinement (frame index -1, timestamp nan): the map's growth over time (report.png); not in as_dict
    history: list = field(default_factory=list)
    stopped_by: str = ""                    # "stop" (end of stream) or "interrupt"
    # the final map's health (Mapper.health, after the final refinement; {} when none ran): its median opacity, the
    # share of nearly transparent Gaussians, and its PSNR on a sample of its own training views
    health: dict = field(default_factory=dict)

    @property
    def iterations_per_s(self) -> float:
        return self.steps / self.train_seconds if self.train_seconds > 0 else 0.0

    def as_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
             if f.name not in ("seed_results", "history", "health")}   # health: metrics.json's map_health
        d["iterations_per_s"] = self.iterations_per_s
        d["seeding"] = [{"keyframe_id": r.keyframe_id, "status": r.status.value, "candidates": r.num_candidates,
                         "fill": r.num_fill, "rejected_visibility": r.num_rejected_visibility,
                         "added": r.num_added, "depth_error_median": r.depth_error_median,
                         "depth_tolerance": r.depth_tolerance_used} for r in self.seed_results]
        return d


@dataclass(frozen=True)
class MapUpdate:
    """What ``Observer.on_map_updated`` gets after each keyframe message and at the end of the refinement."""

    keyframe_id: int                        # -1 after the final refinement
    num_gaussians: int
    num_views: int
    steps: int                              # training steps so far
    seed: SeedResult | None
    last_step: StepResult | None


@dataclass
class MapState:
    """What a mapper hands back when it ends in another process (:mod:`mgso.mapping.process`): the map's
    parameters, each view's pose, exposure and camera (not its image), the odometry's poses and exposures it
    followed, the trainer's step count and the stats. :meth:`Mapper.restored` builds a stopped mapper from it that
    renders, refines trajectories and writes the map like the one that trained."""

    gaussians: GaussianArrays
    scene_extent: float
    views: list                 # (view_id, camera, world_to_cam, exposure (a, b), timestamp, name, fixed_pose, uses)
    odo_c2w: dict
    dso_exposure: dict
    exposure_ms: dict
    reference_exposure_ms: float | None
    latest_kid: int | None
    step_count: int
    stats: MapperStats


def _as_seed_input(view: TrainView, uv: np.ndarray, idepth: np.ndarray, colors: np.ndarray | None,
                   weights: np.ndarray | None) -> KeyframeSeedInput:
    return KeyframeSeedInput(view.image, view.camera, view.cam_to_world, uv, idepth, colors=colors, weights=weights,
                             exposure=(float(view.exposure[0]), float(view.exposure[1])),
                             keyframe_id=view.view_id)


class Mapper:
    """MGSO's mapping thread (see the module doc).

    ``config``: the full configuration (``mapping`` for the map, training, seeding and the mapper; ``runtime.seed``
    for the sampler and the random-init baseline). ``device``: Warp device (initialised by the caller;
    default: the runtime's). ``observer``: gets :class:`MapUpdate` values through ``on_map_updated`` (from the
    mapping thread in real time).
    """

    #: mapping.seeding.distrust_median: keyframes whose median relative depth error passes it before the run's
    #: odometry is judged untrusted (one could be a bad keyframe; freiburg1_rpy gives 180-220 such seedings)
    DISTRUST_KEYFRAMES = 3
    # real time: a host's waiting points are seeded after this many keyframes even while the odometry's pose updates
    # still name it (DSO's window holds 7 keyframes; _settled)
    SETTLE_KEYFRAMES = 8
    #: mapping.mapper.final_budget_s: the full-resolution steps taken first and timed (the rest reckoned at the
    #: cheaper), and the most coarse steps, as a multiple of their planned count (a small map or a fast machine does
    #: not train on for the whole budget)
    BUDGET_PROBE_STEPS = 2
    BUDGET_MAX_FACTOR = 2.0

    def __init__(self, config: Config, *, device: str | None = None, observer: Observer | None = None,
                 messages: "queue.Queue | None" = None, board: SnapshotBoard | None = None,
                 safe_point_hook: Callable[[], None] | None = None, drain_until_stop: bool = False,
                 final_threads: int | None = None, before_final: Callable[[], None] | None = None):
        self.config = config
        # mapping.train.refine_poses null: the map refines the poses of the keyframes whose depths disagree with it
        # (the seeding's depth rule stood down), true: of every keyframe but the first, false: of none
        self._refine_untrusted_only = config.mapping.train.refine_poses is None
        self._first_kid: int | None = None  # the view that holds the map's gauge
        mc = dataclasses.replace(config.mapping, train=config.mapping.train.with_pose_refinement(True))
        self.mc = mc
        self.cfg = mc.mapper
        seed = int(config.runtime.seed)
        self.gmap = GaussianMap(mc.capacity, mc.sh_degree, device=device, optim=mc.optim)
        self.device = self.gmap.device
        self.views = ViewSet()
        if self.cfg.sampler == "random":
            # the deterministic mode's share; start() and run_here() set the real-time one
            self.sampler: LeastUsedSampler = NewestOrRandomSampler(
                self.cfg.newest_probability, seed=seed, loss_share=self.cfg.draw_loss_share(realtime=False))
        else:
            self.sampler = LeastUsedSampler(self.cfg.newest_probability, seed=seed)
        densify = mc.densify if self.cfg.opacity_reset else dataclasses.replace(mc.densify, reset_every=0)
        # the mapper's own densification settings, where set (0: mapping.densify's, what `mgso fit` uses)
        own = {k: getattr(self.cfg, k) for k in ("refine_every", "prune_opacity", "grow_grad2d")}
        own["prune_weight_px"] = self.cfg.weight_prune_px(realtime=False)   # real time: _real_time_settings
        densify = dataclasses.replace(densify, **{k: v for k, v in own.items() if v > 0})
        step = TrainStep(mc, self.device, strategy=DefaultStrategy(densify), seed=seed)
        self.trainer = Trainer(self.gmap, self.views, mc, device=self.device, sampler=self.sampler,
                               train_step=step, seed=seed)
        self.observer = observer or Observer()
        self.stats = MapperStats()
        # the messages' queue: a bounded queue.Queue of its own, or the caller's (the mapper's process: messages
        # and images from the main process)
        self.queue: queue.Queue = messages if messages is not None else queue.Queue(maxsize=self.cfg.queue_size)
        self._rng = np.random.default_rng([seed, 0x5EED])
        # DSO's part of each view's exposure, so that a refined (a, b) shifts the view and keeps what was learned.
        self._dso_exposure: dict[int, tuple[float, float]] = {}
        self._exposure_ms: dict[int, float | None] = {}
        # The odometry's latest pose of each keyframe (camera-to-world). A view's pose in the map is
        # ``correction(kid) @ odometry pose``: identity unless the map refines poses (mapping.train.refine_poses).
        self._odo_c2w: dict[int, np.ndarray] = {}
        self._latest_kid: int | None = None
        self.reference_exposure_ms: float | None = None   # the first keyframe's exposure time (None: unknown)
        self._last_step: StepResult | None = None
        self._thread: threading.Thread | None = None
        # the real-time schedule (start() / run_here()); the deterministic mode's own thread (start_in_order) keeps
        # the deterministic schedule
        self._realtime = False
        # start_in_order: keyframes the odometry may run ahead of the mapper's thread (None: no such thread)
        self._lead: threading.Semaphore | None = None
        self._interrupt = threading.Event()
        self._done = threading.Event()      # set by the mapping thread as it ends (see stop)
        self._error: BaseException | None = None
        self._stopped = False
        # Watchers' requests for copies and renders of the map, served at safe points (mgso.mapping.snapshot; the
        # mapper's process passes one that forwards to the main process).
        self.board = board if board is not None else SnapshotBoard()
        # Called at every safe point by the thread that owns the map (the mapper's process polls its pipes here).
        self.safe_point_hook = safe_point_hook
        # After an interrupt, keep applying messages until Stop arrives instead of ending when the queue looks empty
        # (the mapper's process: messages may still be in the pipe when the interrupt arrives).
        self.drain_until_stop = bool(drain_until_stop)
        # CPU threads of the final refinement's kernel launches (None: as while running). The mapper's process
        # runs on its share of the cores while the camera runs; after Stop the odometry has finished and waits,
        # so the refinement takes every core (0).
        self.final_threads: int | None = final_threads
        # Called as the final refinement begins (the mapper's process: its priority back to normal where allowed).
        self.before_final = before_final
        # Real time: set when the stream has ended (stop() was called; the mapper's process: by the main process,
        # before Stop is queued). The messages still queued then are applied on the final refinement's threads and
        # priority, without the training share: the odometry is done and waits for the map (_end_of_stream).
        self.stream_ended = threading.Event()
        self._final_resources = False
        self._end_t0 = 0.0
        # Real time: point messages' points by host keyframe, waiting while messages are queued (the mapper is
        # behind); seeded when the queue is empty, before a loop correction and at the end (_flush_waiting).
        self._coalesce_points = False
        self._pending_points: dict[int, list[tuple]] = {}
        # Real time, behind the camera: keyframes' own seedings, waiting with their points (mapping.mapper.
        # defer_seeding_above); each keyframe also holds its place in _pending_points' order.
        self._pending_keyframes: dict[int, KeyframeSeedInput] = {}
        # Real time: the keyframes of the odometry's window (its latest PoseUpdate), and for each host with points
        # waiting the keyframe count when they first arrived. A host still in the window marginalises more points
        # with each keyframe (about 5 hosts a keyframe on 7-Scenes): its points wait until it leaves the window
        # (mapping.mapper.seed_points_settled), so that one coverage render seeds all of them.
        self._window: frozenset[int] | None = None
        self._pending_since: dict[int, int] = {}

    def load_kernels(self) -> None:
        """Compile or load every kernel module the mapper launches, now (real time: before the camera plays; a
        compile at the first keyframe would take the cores from the odometry's first frames)."""
        from mgso_kernels import adam, loss, loss_chunks, loss_simd, runtime
        from mgso_kernels.splat import bin as sbin, project, raster, raster_bwd, raster_tile, sh

        runtime.load_modules((project, sbin, raster, raster_tile, raster_bwd, sh, loss, loss_chunks, loss_simd, adam),
                             self.device)

    # ------------------------------------------------------------------------------------------ queue
    @property
    def running(self) -> bool:
        """Whether the real-time mapping thread is alive."""
        return self._thread is not None and not self._done.is_set()

    def submit(self, msg: MapperMessage) -> None:
        """Put ``msg`` on the queue. When it is full: in real time the caller waits for room (counted in
        ``stats.queue_waits`` / ``queue_wait_seconds``); in deterministic mode the pending messages are applied
        first. Raises :class:`MapperError` if the mapping thread has failed."""
        if not isinstance(msg, (KeyframeMessage, PoseUpdate, PointsMessage, LoopCorrection, Stop)):
            raise TypeError(f"Mapper.submit: expected a mapper message, got {type(msg).__name__}")
        self._raise_if_failed()
        depth = self.queue.qsize()
        self.stats.max_queue_depth = max(self.stats.max_queue_depth, depth + 1)
        if self._thread is None:
            if self.queue.full():
                self.process_pending()
            self.queue.put_nowait(msg)
            return
        if self._lead is not None:
            self._put_in_order(msg)
            return
        try:
            self.queue.put_nowait(msg)
            return
        except queue.Full:
            pass
        self.stats.queue_waits += 1
        t0 = time.perf_counter()
        log.warning("mapper queue full (%d messages): the odometry waits for the map", self.cfg.queue_size)
        self._put_waiting(msg)
        self.stats.queue_wait_seconds += time.perf_counter() - t0

    def _put_in_order(self, msg: MapperMessage) -> None:
        """The deterministic mode's thread (start_in_order): a keyframe waits until fewer than the lead's keyframes
        are ahead of it, every message for room in the queue. Waiting is this mode's normal (the mapper is the
        slower side): not counted."""
        if isinstance(msg, KeyframeMessage):
            while not self._lead.acquire(timeout=0.1):
                self._raise_if_stopped("the lead's keyframes")
        self._put_waiting(msg)

    def _put_waiting(self, msg: MapperMessage) -> None:
        """Put ``msg`` once the queue has room, raising :class:`MapperError` if the mapping thread stops meanwhile."""
        while True:
            try:
                self.queue.put(msg, timeout=0.1)
                return
            except queue.Full:
                self._raise_if_stopped("queue room")

    def _raise_if_stopped(self, what: str) -> None:
        if not self.running:
            self._raise_if_failed()
            raise MapperError(f"the mapping thread stopped while the odometry waited for {what}")

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            raise MapperError(f"the mapping thread failed: {type(err).__name__}: {err}") from err

    # ------------------------------------------------------------------------------------ deterministic
    def process_pending(self, iterations_per_keyframe: int | None = None) -> int:
        """Deterministic mode: apply every queued message in order, training ``iterations_per_keyframe`` steps
        (default ``mapping.mapper.iterations_per_keyframe``) after each keyframe message; a :class:`Stop` runs the
        final refinement (when asked) and ends. Returns the messages applied."""
        if self._thread is not None:
            raise RuntimeError("Mapper.process_pending: the mapper runs in its own thread (real-time mode)")
        n_iter = self.cfg.iterations_per_keyframe if iterations_per_keyframe is None else int(iterations_per_keyframe)
        done = 0
        while True:
            try:
                msg = self.queue.get_nowait()
            except queue.Empty:
                self.safe_point()
                return done
            done += 1
            if isinstance(msg, Stop):
                self._finish(msg)
                return done
            self.handle(msg)
            self._train_after(msg, n_iter)

    def _train_after(self, msg: MapperMessage, iterations: int) -> None:
        """Deterministic mode: ``iterations`` steps after a keyframe message (none once interrupted), at the level of
        ``running_max_pixels`` where ``keyframe_steps_coarse``."""
        if isinstance(msg, KeyframeMessage) and not self._interrupt.is_set():
            self.train(iterations, level=self.running_level() if self.cfg.keyframe_steps_coarse else 0)

    def start_in_order(self, lead: int) -> None:
        """Deterministic mode on a thread of its own: the messages are applied in order and
        ``mapping.mapper.iterations_per_keyframe`` steps trained after each keyframe, as :meth:`process_pending`
        does, while the odometry goes on with the next frames, at most ``lead`` keyframes ahead (``submit`` waits
        beyond that). The map depends only on the messages and their order, so it is the same, bit for bit, as the
        mapper's in the caller's thread; the odometry's time and the mapper's overlap (docs/mgso.md, "The
        deterministic mode on two threads"). :meth:`stop` ends it as it ends the real-time thread."""
        if self._thread is not None:
            raise RuntimeError("Mapper.start_in_order: already started")
        if lead < 1:
            raise ValueError(f"Mapper.start_in_order: lead must be at least 1 keyframe, got {lead}")
        self._lead = threading.Semaphore(int(lead))
        self._thread = threading.Thread(target=self._as_thread, args=(self._in_order,), name="mgso-mapper",
                                        daemon=True)
        self._thread.start()

    def _in_order(self) -> None:
        n_iter = self.cfg.iterations_per_keyframe
        while True:
            self.safe_point()
            try:
                msg = self.queue.get(timeout=0.05)
            except queue.Empty:
                continue
            if isinstance(msg, Stop):
                self._finish(msg)
                return
            self.handle(msg)
            self._train_after(msg, n_iter)
            if isinstance(msg, KeyframeMessage):
                self._lead.release()

    def _as_thread(self, loop: Callable[[], None]) -> None:
        """A mapping thread's ``loop``, its error handed to the odometry side (at its next submit, or at stop), its
        CPU time counted and its end signalled (``_done``)."""
        cpu0 = time.thread_time()
        try:
            loop()
        except BaseException as exc:
            log.exception("the mapping thread failed")
            self._error = exc
        finally:
            self.stats.cpu_seconds = time.thread_time() - cpu0
            self._done.set()

    # ------------------------------------------------------------------------------------------ real time
    def start(self) -> None:
        """Real-time mode: start the mapping thread (drain messages, train, repeat)."""
        if self._thread is not None:
            raise RuntimeError("Mapper.start: already started")
        self._thread = threading.Thread(target=self._run, name="mgso-mapper", daemon=True)
        self._real_time_settings()
        self._thread.start()

    def run_here(self) -> BaseException | None:
        """Real-time mode in the calling thread (the mapper's process runs it in its main thread): the mapping
        loop until :class:`Stop` or an interrupt, then its error (``None`` when it ended well; the error is
        handed over, not raised)."""
        if self._thread is not None:
            raise RuntimeError("Mapper.run_here: already started")
        self._thread = threading.current_thread()
        self._real_time_settings()
        self._run()
        err, self._error = self._error, None
        return err

    def _real_time_settings(self) -> None:
        """The keyframe draw's ``mapping.mapper.loss_share`` for real time (its null: uniform) and the weight prune's
        ``mapping.mapper.prune_weight_px`` (its null: 0.1)."""
        self._realtime = True
        if isinstance(self.sampler, NewestOrRandomSampler):
            self.sampler.loss_share = self.cfg.draw_loss_share(realtime=True)
        px = self.cfg.weight_prune_px(realtime=True)
        ts = self.trainer.train_step
        if px > 0 and ts.strategy.cfg.prune_weight_px != px:
            ts.strategy = dataclasses.replace(ts.strategy, cfg=dataclasses.replace(ts.strategy.cfg,
                                                                                    prune_weight_px=px))

    def interrupt(self) -> None:
        """Stop as soon as the queued messages are applied (views, poses, seeds), without training on; in real
        time from any thread."""
        self._interrupt.set()

    def final_coarse_share(self) -> float:
        """``mapping.mapper.final_coarse_share``, its null resolved: 0.95 in real time (a mapping thread or process:
        the map the camera leaves has had a few dozen steps, and is ready about twice as soon); in the deterministic
        mode (with its 2,000 final steps and coarse steps after each keyframe) 0.8 where the coarse level's image
        has at least ``MapperConfig.COARSE_DETAIL_PIXELS``, 0.6 below (0.8 with the keyframes' steps at full
        resolution)."""
        level = self.running_level()
        pixels = None
        if level > 0:
            cam = self.views[self._latest_kid].camera
            pixels = (cam.width >> level) * (cam.height >> level)
        return self.cfg.final_share_coarse(realtime=self._realtime, coarse_pixels=pixels)

    def final_coarser_share(self) -> float:
        """``mapping.mapper.final_coarser_share``, its null resolved: 0.6 in real time, 0.4 in the deterministic
        mode."""
        return self.cfg.final_share_coarser(realtime=self._realtime)

    def final_iterations(self) -> int:
        """``mapping.mapper.final_iterations``, its null resolved: 1,600 in real time (a mapping thread or process:
        the map is awaited after the stream), 2,000 in the deterministic mode."""
        return self.cfg.final_steps(realtime=self._realtime)

    def final_budget(self) -> float:
        """``mapping.mapper.final_budget_s``, its null resolved: 55 s in real time (a mapping thread or process) with
        the map on the CPU, 0 (the step count alone) on CUDA and in the deterministic mode."""
        import warp as wp

        return self.cfg.final_budget(realtime=self._realtime, cpu=wp.get_device(self.device).is_cpu)

    def running_level(self) -> int:
        """The pyramid level of the real-time steps while the stream runs: the finest whose image has at most
        ``running_max_pixels`` pixels (0: off), at least 16 pixels a side (the newest view's size)."""
        limit = self.cfg.running_max_pixels
        if limit <= 0 or self._latest_kid is None or self._latest_kid not in self.views:
            return 0
        cam = self.views[self._latest_kid].camera
        level = 0
        while (cam.width >> level) * (cam.height >> level) > limit:
            level += 1
        return usable_level(cam, level)

    def _owes_training(self, busy: float, trained: float) -> bool:
        """Real time, messages waiting: whether the steps taken meanwhile (``trained`` seconds) are behind
        ``running_train_share`` of the time (with ``busy``, the seconds handling messages), with the queue at most
        half full (beyond that the odometry's waits come closer: the messages go first)."""
        share = self.cfg.running_train_share
        return (share > 0 and self.cfg.running_training and trained < share / (1.0 - share) * busy
                and self.can_train()
                and not self._interrupt.is_set() and not self.stream_ended.is_set()
                and self.queue.qsize() < self.cfg.queue_size // 2)

    def _run(self) -> None:
        self._as_thread(self._real_time)

    def _real_time(self) -> None:
        self._coalesce_points = True
        busy = trained = 0.0        # seconds handling messages, and training while messages waited
        while True:
            self.safe_point()
            if self._owes_training(busy, trained):
                t0 = time.perf_counter()
                self._step(self.running_level())
                trained += time.perf_counter() - t0
                self.stats.steps_while_behind += 1
                continue
            try:
                msg = self.queue.get_nowait()
            except queue.Empty:
                t0 = time.perf_counter()
                # caught up: the seedings that waited, a host keyframe at a time, for a second at most (a long
                # flush would let the queue fill meanwhile); all of them once the run is ending
                ending = self._interrupt.is_set() or self.stream_ended.is_set()
                self._flush_waiting(None if ending else _FLUSH_BUDGET_S)
                busy += time.perf_counter() - t0
                if self._interrupt.is_set() and not self.drain_until_stop:
                    self.stats.stopped_by = "interrupt"
                    return
                if (self.can_train() and not self._interrupt.is_set()
                        and (self.cfg.running_training or self.stream_ended.is_set())):
                    self._step(self.running_level())
                    continue
                try:
                    msg = self.queue.get(timeout=0.05)
                except queue.Empty:
                    continue
            if isinstance(msg, Stop):
                self._finish(msg)
                return
            t0 = time.perf_counter()
            self.handle(msg)
            busy += time.perf_counter() - t0

    def stop(self, refine: bool = True, timeout: float | None = None) -> MapperStats:
        """End the stream: in real time, send :class:`Stop` (``refine``: run the final refinement) and wait for the
        thread; in deterministic mode apply what is pending and the refinement. Idempotent. Raises
        :class:`MapperError` when the mapping thread failed."""
        if self._stopped:
            self._raise_if_failed()
            return self.stats
        if not refine:
            self._interrupt.set()          # apply what is queued (views, poses, seeds), then stop without training
        self.stream_ended.set()
        if self._thread is None:
            self.submit(Stop(refine))
            self.process_pending()
        else:
            if not self._done.is_set():
                self.submit(Stop(refine))
            # Wait on an Event, not Thread.join: a KeyboardInterrupt inside join() can leave CPython (<= 3.12)
            # reporting the thread as stopped while it still runs (bpo-45274's fix releases the lock the running
            # thread holds), and the caller would then render while the thread still trains.
            t0 = time.perf_counter()
            while not self._done.wait(0.05):
                if timeout is not None and time.perf_counter() - t0 > timeout:
                    raise MapperError(f"the mapping thread did not stop within {timeout} s")
            self._thread.join(1.0)
        self._stopped = True
        self._raise_if_failed()
        return self.stats

    def _take_final_resources(self) -> None:
        """Once: the final refinement's threads (``final_threads``) and priority (``before_final``)."""
        if self._final_resources:
            return
        self._final_resources = True
        from mgso_kernels import runtime

        if self.final_threads is not None:
            runtime.set_cpu_threads(self.final_threads)
        if self.before_final is not None:
            self.before_final()

    def _end_of_stream(self) -> None:
        """The stream has ended while messages may still be queued (a mapper behind the camera): the rest of its
        work, seeding included, gets the final refinement's resources at once (a 640x480 run of 83 s on 2 cores
        left 209 s of it, docs/mgso.md)."""
        if self.stats.stream_ended_at_depth < 0:
            self.stats.stream_ended_at_depth = self.queue.qsize()
            self._end_t0 = time.perf_counter()
        self._take_final_resources()

    def _finish(self, msg: Stop) -> None:
        if self._realtime and self.stream_ended.is_set():
            self._end_of_stream()
        self._flush_waiting()
        if self.stats.stream_ended_at_depth >= 0:
            self.stats.catch_up_seconds = time.perf_counter() - self._end_t0
        if msg.refine and not self._interrupt.is_set():
            from mgso_kernels import runtime

            self._take_final_resources()
            steps = self.final_iterations()
            self.stats.final_threads = runtime.cpu_threads() if steps > 0 else 0
            self.refine(steps, seconds=self.final_budget())
            # an interrupt during the refinement ends it early (train() checks it between steps)
            self.stats.stopped_by = "interrupt" if self._interrupt.is_set() else "stop"
            if not self._interrupt.is_set():
                self.stats.health = self.health()
        else:
            self.stats.stopped_by = "interrupt"
        self.stats.history.append((-1, float("nan"), self.stats.steps, int(self.gmap.n)))
        self.observer.on_map_updated(MapUpdate(-1, self.gmap.n, len(self.views), self.stats.steps, None,
                                               self._last_step))

    # ------------------------------------------------------------------------------------------ messages
    def handle(self, msg: MapperMessage) -> None:
        """Apply one message (not :class:`Stop`) now, in the calling thread."""
        if isinstance(msg, KeyframeMessage):
            self._on_keyframe(msg)
        elif isinstance(msg, PoseUpdate):
            self._on_pose_update(msg)
        elif isinstance(msg, PointsMessage):
            self._on_points(msg)
        elif isinstance(msg, LoopCorrection):
            self._flush_waiting()                # seeded where the views were when the points arrived
            self._on_loop_correction(msg)
        elif isinstance(msg, Stop):
            raise ValueError("Mapper.handle: Stop ends the stream (use stop())")
        else:
            raise TypeError(f"Mapper.handle: unknown message {type(msg).__name__}")

    def _on_keyframe(self, msg: KeyframeMessage) -> None:
        kid = msg.keyframe_id
        if kid in self.views:
            raise ValueError(f"keyframe {kid} reached the map twice")
        if self.reference_exposure_ms is None and msg.exposure_ms:
            self.reference_exposure_ms = msg.exposure_ms
        exposure = self.exposure_for(msg.affine, msg.exposure_ms)
        w2c = msg.world_to_cam
        if self.refines_poses and self._latest_kid is not None:
            # the odometry's drift since the previous keyframe is small: start from that keyframe's correction
            w2c = se3_inverse(self.correction(self._latest_kid) @ msg.cam_to_world)
        view = TrainView(kid, msg.image, msg.camera, w2c, mask=msg.mask, exposure=exposure,
                         timestamp=msg.timestamp, name=f"keyframe {kid} (frame {msg.frame_index})")
        seed_in = KeyframeSeedInput.from_message(msg, exposure=exposure)
        if self.refines_poses:
            seed_in = dataclasses.replace(seed_in, cam_to_world=view.cam_to_world)
        res = None
        if self._coalesce_points and 0 < self.cfg.defer_seeding_above <= self.queue.qsize():
            # behind the camera: the view now (poses and training follow it), its seeding with its points later
            self._pending_points.setdefault(kid, [])
            self._pending_keyframes[kid] = seed_in
            self.stats.seedings_deferred += 1
        else:
            res = self._seed(seed_in, self.mc.seeding)
        # a keyframe whose depths mostly miss the map's (the seeding's depth rule stood down: a handheld camera's
        # poor depths, or a pose the map disagrees with) is not trusted: no depth term, and its pose is refined
        untrusted = res is not None and res.depth_tolerance_used == math.inf
        self.stats.keyframes_untrusted += int(untrusted)
        limit = self.mc.seeding.distrust_median
        if limit > 0 and res is not None and res.depth_error_median is not None and res.depth_error_median > limit:
            self.stats.keyframes_scale_broken += 1
        if (limit > 0 and not self.odometry_untrusted
                and self.stats.keyframes_scale_broken >= self.DISTRUST_KEYFRAMES):
            # the odometry's scale broke: none of its keyframes is trusted, earlier ones included
            self.stats.odometry_untrusted_at = kid
            for v in self.views:
                v.depth_uv = v.depth_z = None
                v.fixed_pose = v.view_id == self._first_kid
        untrusted = untrusted or self.odometry_untrusted
        if self.mc.train.depth_weight > 0 and msg.num_points and not untrusted:
            view.set_depth_points(msg.points_uv, 1.0 / np.asarray(msg.idepths, np.float64))
        # the first keyframe holds the map's gauge
        view.fixed_pose = len(self.views) == 0 or (self._refine_untrusted_only and not untrusted)
        if self._first_kid is None:
            self._first_kid = kid
        self.views.add(view)
        self._odo_c2w[kid] = np.array(msg.cam_to_world, dtype=np.float64)
        self._latest_kid = kid
        self._dso_exposure[kid] = exposure
        self._exposure_ms[kid] = msg.exposure_ms
        self.stats.keyframes += 1
        self.stats.history.append((int(msg.frame_index), float(msg.timestamp), self.stats.steps, int(self.gmap.n)))
        self.observer.on_map_updated(MapUpdate(kid, self.gmap.n, len(self.views), self.stats.steps, res,
                                               self._last_step))

    def _on_pose_update(self, msg: PoseUpdate) -> None:
        self.stats.pose_updates += 1
        if msg.cam_to_world:
            self._window = frozenset(msg.cam_to_world)
        for kid, c2w in msg.cam_to_world.items():
            if kid not in self.views:
                self.stats.poses_unknown += 1
                continue
            if self.refines_poses:      # keep what the map corrected, move with the odometry
                c2w = self.correction(kid) @ c2w
            self._odo_c2w[kid] = np.array(msg.cam_to_world[kid], dtype=np.float64)
            self.views.set_pose(kid, se3_inverse(c2w))
            self.stats.poses_applied += 1
        for kid, ab in msg.affine.items():
            if kid not in self.views:
                continue
            new = self.exposure_for(ab, self._exposure_ms.get(kid))
            old = self._dso_exposure[kid]
            view = self.views[kid]
            self.views.set_exposure(kid, view.exposure[0] + new[0] - old[0], view.exposure[1] + new[1] - old[1])
            self._dso_exposure[kid] = new

    def _on_loop_correction(self, msg: LoopCorrection) -> None:
        """Loop closure moved keyframes: each view (and the odometry pose it follows) moves by its keyframe's Sim(3),
        its depth points scale with it, and the Gaussians anchored to it move with it."""
        self.stats.loop_corrections += 1
        if self.odometry_untrusted and self.refines_poses and not self.cfg.loop_moves_untrusted:
            # the map refines every keyframe's pose itself (the odometry's scale broke): it holds its keyframes and
            # Gaussians where the images put them, and only the odometry's poses it follows move, so that its
            # corrections (map pose = W @ odometry pose) absorb the loop's
            for kid, S in msg.transforms.items():
                if kid in self._odo_c2w:
                    self._odo_c2w[kid] = sim3_apply_to_pose(S, self._odo_c2w[kid])
            self.stats.loop_corrections_held += 1
            return
        for kid, S in msg.transforms.items():
            if kid not in self.views:
                continue
            view = self.views[kid]
            self.views.set_pose(kid, se3_inverse(sim3_apply_to_pose(S, view.cam_to_world)))
            if kid in self._odo_c2w:
                self._odo_c2w[kid] = sim3_apply_to_pose(S, self._odo_c2w[kid])
            if view.depth_z is not None and len(view.depth_z):
                view.set_depth_points(view.depth_uv, view.depth_z * sim3_to_parts(S)[2])
        self.stats.gaussians_moved += self.gmap.transform_anchored(msg.transforms)
        if self.cfg.loop_refines_poses and self.refines_poses:
            # the pose graph spreads the loop's error over the keyframes: closer to the truth, but no longer the
            # poses the odometry's depths (and the Gaussians seeded from them) agree with, so the map refines them
            for kid in msg.transforms:
                if kid in self.views and kid != self._first_kid and self.views[kid].fixed_pose:
                    self.views[kid].fixed_pose = False
                    self.stats.loop_poses_refined += 1

    def _on_points(self, msg: PointsMessage) -> None:
        self.stats.point_messages += 1
        self.stats.points_received += len(msg)
        if not self.cfg.seed_marginalized or len(msg) == 0 or msg.host_keyframe_id not in self.views:
            return
        view = self.views[msg.host_keyframe_id]
        T = se3_inverse(self._odo_c2w[msg.host_keyframe_id])     # the points are in the odometry's world
        pc = msg.points @ T[:3, :3].T + T[:3, 3]
        cam = view.camera
        z = pc[:, 2]
        ok = z > 1e-6
        if not ok.any():
            return
        zs = np.where(ok, z, 1.0)
        uv = np.stack([cam.fx * pc[:, 0] / zs + cam.cx, cam.fy * pc[:, 1] / zs + cam.cy], axis=1)
        ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5)
        if not ok.any():
            return
        weights = None if msg.weights is None else msg.weights[ok]
        points = (uv[ok], 1.0 / z[ok], msg.colors[ok], weights)
        if self._coalesce_points:
            # Real time: a seeding renders the map's coverage from the host keyframe, and the odometry sends a
            # message for every host whose points a keyframe marginalises (about 5 a keyframe): a 640x480 run on 2
            # cores spent 69 % of its message handling seeding them (docs/mgso.md). The points wait for the queue
            # to empty instead, and all of one host's are seeded at once (from the keyframe's coordinates of their
            # arrival: a pose update in between moves them with the view).
            pending = self._pending_points.setdefault(msg.host_keyframe_id, [])
            if pending:
                self.stats.points_coalesced += 1
            self._pending_since.setdefault(msg.host_keyframe_id, self.stats.keyframes)
            pending.append(points)
            return
        self._seed_points(msg.host_keyframe_id, [points])

    def _seed_points(self, host: int, parts: list[tuple]) -> None:
        """Seed points of one host keyframe (``parts``: ``(uv, idepth, colors, weights)`` in its camera), seen from
        the keyframe where the map is still empty, without the Delaunay fill."""
        uv, idepth, colors = (np.concatenate([p[i] for p in parts]) for i in range(3))
        weights = None if any(p[3] is None for p in parts) else np.concatenate([p[3] for p in parts])
        seed_in = _as_seed_input(self.views[host], uv, idepth, colors, weights)
        self._seed(seed_in, dataclasses.replace(self.mc.seeding, fill=False))

    def _flush_waiting(self, budget: float | None = None) -> None:
        """Seed what waited (real time), host by host in the order they first arrived: a keyframe's own seeding
        deferred while the mapper was behind (from the view's pose now: a pose update in between moved it), then
        its points. ``budget``: seconds after which the rest waits for the next call (None: everything, the points
        of hosts still in the odometry's window included). With a budget and ``mapping.mapper.seed_points_settled``
        a host's points wait while it is in the window (:meth:`_settled`)."""
        t0 = time.perf_counter()
        settled_only = budget is not None and self.cfg.seed_points_settled
        for host in list(self._pending_points):
            if budget is not None and time.perf_counter() - t0 >= budget:
                return
            seed_in = self._pending_keyframes.pop(host, None)
            if host not in self.views:
                self._pending_points.pop(host, None)
                self._pending_since.pop(host, None)
                continue
            if seed_in is not None:
                self._seed(dataclasses.replace(seed_in, cam_to_world=self.views[host].cam_to_world), self.mc.seeding)
            if settled_only and not self._settled(host):
                continue
            parts = self._pending_points.pop(host)
            self._pending_since.pop(host, None)
            if parts:
                self._seed_points(host, parts)

    def _settled(self, host: int) -> bool:
        """Whether ``host`` will marginalise no more points: it has left the odometry's window (not in its latest
        pose update), or its first points waited through ``SETTLE_KEYFRAMES`` keyframes (an odometry whose pose
        updates do not name its window)."""
        if self._window is None or host not in self._window:
            return True
        return self.stats.keyframes - self._pending_since.get(host, self.stats.keyframes) >= self.SETTLE_KEYFRAMES

    def exposure_for(self, affine: tuple[float, float], exposure_ms: float | None) -> tuple[float, float]:
        """The trainer's exposure ``(a', b')`` of an image with the odometry's affine brightness ``affine`` (0-255)
        and exposure time ``exposure_ms``, by ``mapping.mapper.exposure``: ``odometry`` (DSO's affine and the
        exposure time, :func:`~mgso.messages.map_exposure`), ``exposure_time`` (the exposure time's gain
        only) or ``none`` (the image as it is). Evaluation renders use the same rule."""
        mode = self.cfg.exposure
        if mode == "none":
            return 0.0, 0.0
        if mode == "exposure_time":
            return map_exposure((0.0, 0.0), exposure_ms, self.reference_exposure_ms)
        return map_exposure(affine, exposure_ms, self.reference_exposure_ms)

    # ------------------------------------------------------------------------------------- map-refined poses
    @property
    def refines_poses(self) -> bool:
        """Whether the map corrects the odometry's keyframe poses (``mapping.train.refine_poses``)."""
        return bool(self.mc.train.refine_poses)

    @property
    def odometry_untrusted(self) -> bool:
        """Whether the run's odometry was judged untrusted (``mapping.seeding.distrust_median``: its scale broke)."""
        return self.stats.odometry_untrusted_at is not None

    def correction(self, keyframe_id: int) -> np.ndarray:
        """The map's correction of a keyframe's pose: the rigid ``W`` with ``map pose = W @ odometry pose``
        (camera-to-world; identity when the map refines no pose)."""
        return self.views[keyframe_id].cam_to_world @ se3_inverse(self._odo_c2w[keyframe_id])

    def refined_trajectory(self, trajectory):
        """``trajectory`` (the odometry's poses, camera-to-world) moved by the map's keyframe corrections: a frame
        between two keyframes takes the geodesic interpolation (in time) of their corrections, a frame before the
        first or after the last keyframe that keyframe's. Unchanged when the map refines no pose."""
        from mgso.io.trajectory import Trajectory

        ids = [k for k in self.views.ids() if k in self._odo_c2w and self.views[k].timestamp is not None]
        if not self.refines_poses or not ids or len(trajectory) == 0:
            return trajectory
        ids.sort(key=lambda k: self.views[k].timestamp)
        kts = np.array([float(self.views[k].timestamp) for k in ids])
        W = [self.correction(k) for k in ids]
        out = np.empty_like(trajectory.cam_to_world)
        for i, (t, T) in enumerate(zip(trajectory.timestamps, trajectory.cam_to_world)):
            j = int(np.searchsorted(kts, t, side="right"))
            if j == 0:
                C = W[0]
            elif j >= len(ids):
                C = W[-1]
            else:
                a = (t - kts[j - 1]) / max(kts[j] - kts[j - 1], 1e-12)
                C = W[j - 1] @ se3_exp(a * se3_log(se3_inverse(W[j - 1]) @ W[j]))
            out[i] = C @ T
            out[i][:3, :3] = orthonormalize(out[i][:3, :3])
        return Trajectory(trajectory.timestamps.copy(), out)

    # ------------------------------------------------------------------------------------------ seeding
    def coverage_downscale(self) -> int:
        """``mapping.seeding.alpha_downscale``, its null resolved: 4 in real time (a mapping thread or process: the
        seedings take most of the mapper's core while the camera runs, and a quarter-resolution coverage leaves it
        about 40 % more training steps; docs/seeding.md), 2 in the deterministic mode."""
        ds = self.mc.seeding.alpha_downscale
        if ds is None:
            ds = 4 if self._realtime else COVERAGE_DOWNSCALE
        return int(ds)

    def _seed(self, seed_in: KeyframeSeedInput, scfg) -> SeedResult:
        t0 = time.perf_counter()
        step = self.trainer.step_count
        if scfg.alpha_downscale is None:
            scfg = dataclasses.replace(scfg, alpha_downscale=self.coverage_downscale())
        if self.cfg.init == "dso":
            res = seed_keyframe(self.gmap, self.trainer.train_step.rasterizer, seed_in, scfg, step)
        else:
            res = self._seed_random(seed_in, scfg, step)
        dt = time.perf_counter() - t0
        self.stats.seed_seconds += dt
        if not self.stream_ended.is_set():
            self.stats.seed_seconds_streaming += dt
        self.stats.gaussians_seeded += res.num_added
        self.stats.coverage_renders += int(res.coverage_rendered)
        self.stats.seeds_skipped_too_few += int(res.skipped_too_few)
        self.stats.points_too_far += res.num_too_far
        self.stats.seed_results.append(res)
        log.debug("seeding keyframe %d: %s, %d candidates, %d added, %d Gaussians", res.keyframe_id,
                  res.status.value, res.num_candidates, res.num_added, self.gmap.n)
        return res

    def _seed_random(self, seed_in: KeyframeSeedInput, scfg, step: int) -> SeedResult:
        """The baseline of MGSO's claim: as many Gaussians as DSO seeding would add here, at random pixels of the
        keyframe with a depth uniform over its points' depth range (what the odometry knows), coloured from the
        image (as radiance), with the seeding's scale rule and opacity."""
        gmap = self.gmap
        alpha, depth, neighbours = map_seen_from(gmap, self.trainer.train_step.rasterizer, seed_in, scfg)
        plan = plan_seeds(seed_in, scfg, alpha, neighbours, sh_degree=gmap.sh_degree, depth=depth)
        n = min(plan.gaussians.n, gmap.capacity - gmap.n)
        res = dataclasses.replace(plan.result, coverage_rendered=alpha is not None)
        if n <= 0:
            return dataclasses.replace(res, num_added=0)
        cam = seed_in.camera
        z_pts = plan.candidates.depth
        z_lo, z_hi = float(z_pts.min()), float(z_pts.max())
        if not z_hi > z_lo:
            z_hi = z_lo * 1.01
        u = self._rng.integers(cam.width, size=n)
        v = self._rng.integers(cam.height, size=n)
        z = self._rng.uniform(z_lo, z_hi, size=n)
        pc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], axis=1)
        T = seed_in.cam_to_world
        means = pc @ T[:3, :3].T + T[:3, 3]
        rgb = seed_in.image[v, u].astype(np.float64)
        if seed_in.exposure is not None:
            a, b = seed_in.exposure
            rgb = (rgb - b) / math.exp(a)
        focal = math.sqrt(cam.fx * cam.fy)
        scales = seed_scales(means, z, focal, scfg, neighbours)
        g: GaussianArrays = gaussians_from_seeds(means, np.clip(rgb, 0.0, 1.0), scales, scfg, gmap.sh_degree)
        gmap.add(g.means, g.log_scales, g.quats, g.opacity_logits, g.sh, step=step,
                 anchor=-1 if seed_in.keyframe_id is None else int(seed_in.keyframe_id))
        return dataclasses.replace(res, status=SeedStatus.ADDED, num_added=n)

    # ------------------------------------------------------------------------------------------ training
    def can_train(self) -> bool:
        """Whether a training step can run: enough views and at least one Gaussian."""
        return len(self.views) >= self.cfg.min_train_views and self.gmap.n > 0

    def _step(self, level: int = 0) -> StepResult:
        """One training step; ``level``: at least this pyramid level (the real-time steps while the stream runs)."""
        t0 = time.perf_counter()
        r = self.trainer.step(min_level=level)
        if level and not self.stream_ended.is_set():
            self.stats.running_level = level
        self.stats.train_seconds += time.perf_counter() - t0
        self.stats.steps += 1
        for name, seconds in r.times.items():
            self.stats.stage_seconds[name] = self.stats.stage_seconds.get(name, 0.0) + seconds
        self.stats.pairs += r.num_pairs
        self.stats.steps_while_streaming += int(not self.stream_ended.is_set())
        self._last_step = r
        f = r.refine
        if f.refined or f.opacity_reset:
            d = self.stats.densify
            d["refines"] += int(f.refined)
            d["cloned"] += f.cloned
            d["split"] += f.split
            d["pruned"] += f.pruned
            d["pruned_opacity"] += f.pruned_opacity
            d["pruned_world"] += f.pruned_world
            d["pruned_screen"] += f.pruned_screen
            d["pruned_weight"] += f.pruned_weight
            d["skipped_capacity"] += f.skipped_capacity
            d["clamped_aspect"] += f.clamped_aspect
            d["opacity_resets"] += int(f.opacity_reset)
        return r

    def train(self, iterations: int, level: int = 0) -> int:
        """Run up to ``iterations`` training steps now (fewer when nothing can be trained yet), at pyramid level
        ``level`` or coarser. Returns the steps."""
        done = 0
        for _ in range(int(iterations)):
            self.safe_point()
            if not self.can_train() or self._interrupt.is_set():   # stop(refine=False) ends a refinement too
                break
            self._step(level)
            done += 1
        return done

    def refine(self, iterations: int, seconds: float = 0.0) -> int:
        """The final refinement: ``iterations`` steps over all keyframes (the sampler's choice). With ``seconds`` > 0
        (``mapping.mapper.final_budget_s``) the coarse steps go on past their share of the steps while that time
        allows (:meth:`_train_within`): as many as fit before the full-resolution steps at the end (reckoned at the
        cheaper of the ``BUDGET_PROBE_STEPS`` of them taken first, each timed), up to ``BUDGET_MAX_FACTOR`` times as
        many as planned, never fewer."""
        t0 = time.perf_counter()
        self.stats.final_budget_s = float(seconds)
        self._bring_refining_forward()
        # its first share at the real-time level (coarse to fine: the untrained map's first steps need no fine
        # detail; a step at 320x240 costs about a third of one at 640x480), then at full resolution
        coarse = round(iterations * self.final_coarse_share())
        level = self.running_level() if coarse > 0 else 0
        if level == 0:
            coarse = 0                  # no coarser level (a small camera, running_max_pixels 0)
        # and the first of those a level coarser still (final_coarser_share; where the camera has one)
        coarser = min(round(iterations * self.final_coarser_share()), coarse)
        coarser_level = usable_level(self.views[self._latest_kid].camera, level + 1) if coarser else level
        if coarser_level == level:
            coarser = 0
        budget = seconds > 0 and coarse > 0
        done = self.train(coarser, level=coarser_level)
        self.stats.final_coarser_steps += done
        full = not self._interrupt.is_set() and self.can_train()
        tail = iterations - coarse      # the full-resolution steps at the end
        probe, reserve = 0, 0.0
        if full and budget:
            # two of them now, each timed: the time the coarse steps leave the rest is reckoned at the cheaper (the
            # first full-resolution step of a run grows buffers and costs more)
            cost = math.inf
            while full and probe < min(self.BUDGET_PROBE_STEPS, tail):
                t = time.perf_counter()
                full = self.train(1) == 1
                cost = min(cost, time.perf_counter() - t)
                probe += int(full)
            reserve = (tail - probe) * cost if tail > probe else 0.0
        if full:                        # the planned coarse steps; with a budget up to BUDGET_MAX_FACTOR times as many
            planned = coarse - coarser
            n, full = self._train_within(t0 + seconds if budget else math.inf, level, reserve, least=planned,
                                         most=round(self.BUDGET_MAX_FACTOR * planned) if budget else planned)
            done += n
        self.stats.final_coarse_steps += done
        done += probe
        if full:                        # not interrupted, nor out of views
            done += self.train(tail - probe)
        self.stats.final_steps += done
        self.stats.final_seconds += time.perf_counter() - t0
        return done

    def _train_within(self, deadline: float, level: int, reserve: float, least: int, most: int) -> tuple[int, bool]:
        """``least`` steps at ``level``, then more, at most ``most``, while the time before ``deadline``
        (``time.perf_counter``) holds one more (at the mean of these) and ``reserve`` seconds after it. Returns the
        steps and whether training may go on (not interrupted, views to train)."""
        t_start = time.perf_counter()
        done = 0
        while done < most:
            now = time.perf_counter()
            per = (now - t_start) / done if done else 0.0
            if done >= least and now + per + reserve >= deadline:
                return done, True
            if self.train(1, level=level) == 0:
                return done, False
            done += 1
        return done, True

    def _bring_refining_forward(self) -> None:
        """Before the final refinement: where the stream left the map unrefined (real time on a small CPU: a few
        steps while the camera ran, every seed untrained), the first refinement comes at the global step
        ``mapping.mapper.final_refine_after`` after the refinement's first instead of at the first scheduled one
        (after ``refine_start_step``, at a multiple of ``refine_every``): its opacity prune drops the
        seeds training did not keep, and the rest of the refinement runs on the smaller map (docs/mgso.md). A map
        refined while the stream ran keeps its schedule."""
        after = self.cfg.final_refine_after
        ts = self.trainer.train_step
        st = ts.strategy
        if after <= 0 or not isinstance(st, DefaultStrategy) or ts.strategy_state.refines > 0:
            return
        c = st.cfg
        now = self.trainer.step_count
        first = max(c.refine_start_step + 1, now)
        scheduled = -(-first // c.refine_every) * c.refine_every       # the first step the schedule refines
        at = now + after
        if at < scheduled and st.is_active(at):
            ts.strategy = dataclasses.replace(st, extra_refine_steps=st.extra_refine_steps | {at})
            log.debug("final refinement: a first refinement at step %d (the schedule's first: %d)", at, scheduled)

    # ------------------------------------------------------------------------------------------ health
    HEALTH_VIEWS = 8            # training views rendered by health(), evenly spread over the keyframes
    TRANSPARENT_OPACITY = 0.1   # a Gaussian below this opacity counts as nearly transparent

    def health(self, max_views: int | None = None) -> dict:
        """How the map fits what it was trained on (values, not warnings; the application decides what to say):
        ``median_opacity`` and ``transparent_fraction`` (opacity below :attr:`TRANSPARENT_OPACITY`) of the
        Gaussians, and ``training_view_psnr_db``, the mean PSNR of the map on up to ``max_views`` (default
        :attr:`HEALTH_VIEWS`) of its training views, evenly spread, at their map poses and exposures, full
        resolution, over their valid pixels (``training_view_psnr_min_db`` the lowest). A map that cannot render its
        own training views, or is mostly nearly transparent, is fog: the views disagree (poses, blur, exposure) or
        training had too few steps. Rendering costs a fraction of a second a view."""
        out: dict = {"num_gaussians": int(self.gmap.n)}
        if self.gmap.n:
            op = self.gmap.activated().opacities.astype(np.float64)
            out["median_opacity"] = round(float(np.median(op)), 4)
            out["transparent_fraction"] = round(float(np.mean(op < self.TRANSPARENT_OPACITY)), 4)
        ids = [k for k in self.views.ids() if self.views[k].image is not None]
        k = self.HEALTH_VIEWS if max_views is None else int(max_views)
        if ids and k > 0:
            pick = [ids[int(i)] for i in np.unique(np.linspace(0, len(ids) - 1, min(k, len(ids))).round())]
            vals = [min(self.view_psnr(vid), 99.0) for vid in pick]
            out["training_views_rendered"] = len(vals)
            out["training_view_psnr_db"] = round(float(np.mean(vals)), 2)
            out["training_view_psnr_min_db"] = round(float(np.min(vals)), 2)
        return out

    # ------------------------------------------------------------------------------------------ watchers
    def safe_point(self) -> None:
        """Between two steps or messages, in the thread that owns the map: the hook, then the watchers' open
        requests (:mod:`mgso.mapping.snapshot`)."""
        if self.safe_point_hook is not None:
            self.safe_point_hook()
        if self._realtime and self.stream_ended.is_set() and not self._final_resources:
            self._end_of_stream()
        if not self.board.pending:
            return
        want, cap, render = self.board.take_requests()
        if want:
            self.board.publish_snapshot(snapshot_of(self.gmap, self.views, self.stats.steps, cap))
        if render is not None:
            try:
                img = self.render(render.camera, render.world_to_cam, exposure=render.exposure)
            except Exception as exc:  # noqa: BLE001 - a watcher's bad request must not stop the mapper
                log.warning("render request %d failed: %s: %s", render.ticket, type(exc).__name__, exc)
            else:
                self.board.publish_render(render.ticket, img)

    def request_snapshot(self, max_gaussians: int | None = None) -> None:
        """Ask for a :class:`~mgso.mapping.snapshot.MapSnapshot` at the next safe point (never waits; a stopped
        mapper answers at once). ``max_gaussians`` keeps the most opaque ones."""
        self.board.request_snapshot(max_gaussians)
        if self._stopped:
            self.safe_point()

    def latest_snapshot(self) -> MapSnapshot | None:
        """The newest snapshot published (``None`` before the first)."""
        return self.board.latest_snapshot()

    def request_render(self, camera, world_to_cam, exposure=None) -> int:
        """Ask for a render of the map at the next safe point (never waits); returns its ticket."""
        ticket = self.board.request_render(camera, world_to_cam, exposure)
        if self._stopped:
            self.safe_point()
        return ticket

    def latest_render(self) -> tuple[int, np.ndarray] | None:
        """``(ticket, (H, W, 3) float32 image)`` of the newest render published."""
        return self.board.latest_render()

    # ------------------------------------------------------------------------------------------ results
    def export_state(self) -> MapState:
        """The map, the views' poses and the stats as a :class:`MapState` (read after the mapper stopped)."""
        views = [(v.view_id, v.camera, v.world_to_cam.copy(), (float(v.exposure[0]), float(v.exposure[1])),
                  v.timestamp, v.name, bool(v.fixed_pose), int(v.uses)) for v in self.views]
        return MapState(self.gmap.to_numpy(), float(self.gmap.scene_extent), views, dict(self._odo_c2w),
                        dict(self._dso_exposure), dict(self._exposure_ms), self.reference_exposure_ms,
                        self._latest_kid, int(self.trainer.step_count), self.stats)

    @classmethod
    def restored(cls, config: Config, state: MapState, *, device: str | None = None,
                 observer: Observer | None = None) -> "Mapper":
        """A stopped mapper holding ``state`` (from :meth:`export_state` of a mapper that ran elsewhere): it renders,
        writes its map and refines trajectories like that one; its views have no images, so it trains no more."""
        n = int(state.gaussians.n)
        small = dataclasses.replace(config, mapping=dataclasses.replace(config.mapping, capacity=max(1, n)))
        m = cls(small, device=device, observer=observer)
        m.config = config
        if n:
            m.gmap.load(state.gaussians)
        m.gmap.scene_extent = float(state.scene_extent)
        for vid, cam, w2c, exposure, ts, name, fixed, uses in state.views:
            m.views.add(TrainView.pose_only(vid, cam, w2c, exposure=exposure, timestamp=ts, name=name,
                                            fixed_pose=fixed, uses=uses))
        m._odo_c2w = dict(state.odo_c2w)
        m._dso_exposure = dict(state.dso_exposure)
        m._exposure_ms = dict(state.exposure_ms)
        m.reference_exposure_ms = state.reference_exposure_ms
        m._latest_kid = state.latest_kid
        m.trainer.step_count = int(state.step_count)
        m.stats = state.stats
        m._stopped = True
        return m

    @property
    def keyframe_ids(self) -> list[int]:
        return self.views.ids()

    def render(self, camera, world_to_cam: np.ndarray, exposure: tuple[float, float] | None = None, *,
               rasterizer=None) -> np.ndarray:
        """(H, W, 3) float32 render of the map from ``world_to_cam`` with ``camera`` (a pinhole camera);
        ``exposure`` (a', b') gives ``exp(a') render + b'``. Call after :meth:`stop` in real-time mode.
        ``rasterizer``: a :class:`~mgso_kernels.splat.Rasterizer` of the caller's (:meth:`new_rasterizer`) instead
        of the trainer's, so that several threads can render the stopped map at once."""
        return self.trainer.render(camera, world_to_cam, exposure=exposure, rasterizer=rasterizer)

    def new_rasterizer(self):
        """A rasteriser of its own on the map's device, for :meth:`render` from another thread."""
        from mgso_kernels.splat import Rasterizer
        return Rasterizer(self.gmap.device)

    def view_psnr(self, keyframe_id: int) -> float:
        """The map's PSNR (dB) on a training view: rendered at its map pose with its exposure, full resolution,
        over its valid pixels (``inf`` when equal). Call after :meth:`stop` in real-time mode."""
        v = self.views[keyframe_id]
        return masked_psnr(self.render(v.camera, v.world_to_cam), v.image, self.view_exposure(keyframe_id), v.mask)

    def view_exposure(self, keyframe_id: int) -> tuple[float, float]:
        v = self.views[keyframe_id]
        return float(v.exposure[0]), float(v.exposure[1])
