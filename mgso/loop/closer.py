"""The loop closer: detect revisits, correct the keyframes by a Sim(3) pose graph, tell the map (docs/loop.md).

The system (:class:`mgso.system.System`) shows the closer every message the odometry emits, in the odometry's world
(:meth:`LoopCloser.observe`), and sends the mapper the message moved into the corrected world
(:meth:`LoopCloser.correct`). After each frame it asks for a finished loop (:meth:`LoopCloser.poll`), which comes as
a :class:`~mgso.messages.LoopCorrection` for the mapper: the Sim(3) each keyframe moved by.

**What the closer keeps.** Per keyframe: the odometry's latest pose ``T_k`` (its world, never changed by the closer:
the odometry goes on in its own world, as LDSO's does) and a correction ``C_k``, a Sim(3) of the world, so that the
keyframe's pose in the corrected world is ``C_k T_k``. Every correction is the identity until the first loop, and
then every message passes unchanged: a run without a loop is the run without the closer, bit for bit.

**A loop** (:meth:`_detect`, for each new keyframe ``k``):

1. ORB features on DSO's points (:func:`mgso.loop.place.extract_features`), stored in the place database.
2. Candidates: old keyframes that share enough ratio-test matches (appearance), and those whose corrected camera is
   near ``k``'s (``loop.proximity_depths``); the newest ``loop.min_keyframe_gap`` keyframes (the window and its
   neighbours) never.
3. Verification (:func:`mgso.loop.verify.verify`): Sim(3) RANSAC on the matches with DSO depths, then DSO's
   photometric residual from the RANSAC pose. The first accepted candidate gives a loop edge; every rejection is
   counted by its reason.
4. The pose graph (:class:`mgso.loop.graph.PoseGraph`, GTSAM) over every keyframe: odometry edges from the odometry's
   relative poses to the ``loop.odometry_neighbours`` previous keyframes, every loop edge found so far, the first
   keyframe fixed.
5. The corrections: a keyframe the window has marginalised takes the graph's solution, ``C_k = P_k T_k^-1``. The
   window's keyframes, and every keyframe after them, move rigidly with the newest one, ``C_cur = P_k T_k^-1``: the
   window's own optimisation (its marginalisation prior is in its world) stays consistent, and its keyframes take
   the graph's solution when a later loop is solved after they left the window (LDSO does the same: the window runs
   on, the pose graph corrects the keyframes behind it).

The mapper gets, for every keyframe whose correction changed, ``D_k = C_k' C_k^-1``.

**Threads.** In the deterministic mode a keyframe's detection runs at once, in the caller's thread: the same loops on
every run. ``background=True`` (real time) runs detection, verification and the graph on a thread of their own, so
that tracking never waits; a loop found there is applied at the next :meth:`poll` (keyframes made meanwhile take the
new ``C_cur``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import queue
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from mgso.config import Config
from mgso.geometry import sim3_exp, sim3_inverse, sim3_log, sim3_to_parts, so3_log
from mgso.io.trajectory import Trajectory
from mgso.messages import (KeyframeMessage, LoopCorrection, PointsMessage, PoseUpdate,
                                   sim3_apply_to_pose)

__all__ = ["LoopCloser", "LoopStats", "LoopRecord"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopRecord:
    """One accepted loop: the new keyframe, the old one it closed on, the evidence, how far it moved the trajectory
    (the newest keyframe's correction: translation in the odometry's units, rotation in degrees, scale) and the loop
    edge itself (``relative``: the verified 4x4 Sim(3) from the new keyframe's camera to the old one's, as rows)."""

    keyframe_id: int
    candidate_id: int
    frame_index: int
    candidate_frame_index: int
    matches: int
    inliers: int
    rmse: float | None
    scale: float | None
    correction_translation: float
    correction_degrees: float
    correction_scale: float
    graph_seconds: float
    relative: list | None = None


@dataclass
class LoopStats:
    """Counts and times of the loop closer (metrics.json "loop")."""

    enabled: bool = True
    keyframes: int = 0                      # keyframes seen
    queries: int = 0                        # place queries made (keyframes old enough to have candidates)
    keyframes_skipped: int = 0              # real time: keyframes neither stored nor searched (a newer one waited)
    candidates: int = 0                     # candidates verified
    accepted: int = 0                       # loops accepted (each solved the graph)
    rejected: dict = field(default_factory=dict)     # reason -> candidates rejected for it
    graph_solves: int = 0
    seconds: float = 0.0                    # features, queries, verification and the graph, all together
    corrections_sent: int = 0               # LoopCorrection messages handed to the mapper
    error: str | None = None                # what stopped loop closure (it is then off for the rest of the run)
    loops: list = field(default_factory=list)        # LoopRecord per accepted loop

    def as_dict(self) -> dict:
        return {"enabled": self.enabled, "keyframes": self.keyframes, "queries": self.queries,
                "keyframes_skipped": self.keyframes_skipped,
                "candidates": self.candidates, "accepted": self.accepted,
                "rejected": dict(sorted(self.rejected.items())),
                "rejected_total": int(sum(self.rejected.values())), "graph_solves": self.graph_solves,
                "seconds": self.seconds, "corrections_sent": self.corrections_sent, "error": self.error,
                "loops": [dict(r.__dict__) for r in self.loops]}


def _rigid_as_sim3(T: np.ndarray) -> np.ndarray:
    return np.asarray(T, dtype=np.float64).copy()


@dataclass
class _Solve:
    """What a detection job hands back: the loop, and the new corrections of the keyframes it knew."""

    record: LoopRecord
    corrections: dict           # keyframe id -> C_k (Sim(3)) for the keyframes marginalised at the time
    current: np.ndarray         # C_cur: the window's keyframes and all later ones


class LoopCloser:
    """See the module doc. ``config``: the full configuration (``loop``, ``tracking`` for the photometric check);
    ``device``: the Warp device of the photometric check; ``background``: run detection on a thread of its own;
    ``nice``: on Linux, that thread's niceness increment (the system passes ``system.mapper_nice``: tracking first
    when the cores are short)."""

    def __init__(self, config: Config, *, device: str | None = None, background: bool = False, nice: int = 0):
        from mgso.loop.place import PlaceDatabase

        self.config = config
        self.cfg = config.loop
        self.device = device
        self.background = bool(background)
        self.nice = int(nice)
        self.stats = LoopStats(enabled=bool(self.cfg.enabled))
        self.db = PlaceDatabase(self.cfg.prefilter_above, self.cfg.prefilter_keep, self.cfg.vocabulary_words)
        self._features: dict[int, object] = {}
        self._odo: dict[int, np.ndarray] = {}           # keyframe id -> odometry cam_to_world (latest)
        self._frame: dict[int, int] = {}
        self._time: dict[int, float] = {}
        self._order: list[int] = []
        self._active: set[int] = set()                  # the window's keyframes (latest PoseUpdate + newer)
        self._C: dict[int, np.ndarray] = {}             # keyframe id -> correction C_k
        self._C_cur = np.eye(4)
        self._sent: dict[int, np.ndarray] = {}          # the correction the mapper has of each keyframe
        self._loop_edges: list[tuple[int, int, np.ndarray]] = []    # (candidate, keyframe, relative Sim(3))
        self._lock = threading.Lock()
        self._ready: list[_Solve] = []
        self._error: BaseException | None = None
        self._jobs: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._loops = 0
        self._off = False                          # after a failure: no more searches, the corrections kept
        self._rest = threading.Event()             # set when the run ends: no more resting between jobs
        if self.background and self.cfg.enabled:
            self._jobs = queue.Queue()
            self._thread = threading.Thread(target=self._work, name="mgso-loop", daemon=True)
            self._thread.start()

    @property
    def enabled(self) -> bool:
        return bool(self.cfg.enabled)

    @property
    def corrected(self) -> bool:
        """Whether any loop has moved anything (until then every message and trajectory passes unchanged)."""
        return self._loops > 0

    # ----------------------------------------------------------------------------------------- the stream
    def observe(self, msg, final: bool = False) -> None:
        """A message of the odometry, in its world: keep the keyframes' poses and the window, and look for a loop
        at each new keyframe (now, or on the closer's thread). ``final``: one of ``odometry.finish()``'s messages,
        whose pose update names every keyframe, not the window's."""
        if isinstance(msg, KeyframeMessage):
            kid = msg.keyframe_id
            with self._lock:
                self._odo[kid] = np.array(msg.cam_to_world, dtype=np.float64)
                self._frame[kid] = msg.frame_index
                self._time[kid] = msg.timestamp
                self._order.append(kid)
                self._active.add(kid)
                self._C[kid] = self._C_cur.copy()
            self.stats.keyframes += 1
            if self.enabled and not self._off:
                job = (kid, msg.image, msg.camera, np.asarray(msg.points_uv), np.asarray(msg.idepths))
                if self._jobs is not None:
                    self._jobs.put(job)
                else:
                    try:
                        self._run_job(job)
                    except Exception as exc:  # noqa: BLE001 - loop closure is off, the run goes on
                        self._fail(exc)
        elif isinstance(msg, PoseUpdate):
            with self._lock:
                for kid, T in msg.cam_to_world.items():
                    if kid in self._odo:
                        self._odo[kid] = np.array(T, dtype=np.float64)
                ids = set(msg.cam_to_world)
                if ids and not final:     # the window's keyframes: those just optimised, and any newer
                    newest = max(ids)
                    self._active = ids | {k for k in self._active if k > newest}

    @property
    def window_keyframes(self) -> list[int]:
        """The keyframes the closer takes for the odometry's window (moved rigidly by a loop's correction)."""
        with self._lock:
            return sorted(self._active)

    def correction_of(self, keyframe_id: int) -> np.ndarray:
        """The correction ``C_k`` of a keyframe (the current one for a keyframe the closer has not seen)."""
        with self._lock:
            return self._C.get(int(keyframe_id), self._C_cur).copy()

    def correct(self, msg):
        """``msg`` moved from the odometry's world into the corrected one (the same object while nothing is
        corrected)."""
        if not self.corrected:
            if isinstance(msg, KeyframeMessage):
                self._sent[msg.keyframe_id] = np.eye(4)
            return msg
        if isinstance(msg, KeyframeMessage):
            C = self.correction_of(msg.keyframe_id)
            self._sent[msg.keyframe_id] = C
            s = sim3_to_parts(C)[2]
            return dataclasses.replace(msg, cam_to_world=sim3_apply_to_pose(C, msg.cam_to_world),
                                       idepths=np.asarray(msg.idepths) / s)
        if isinstance(msg, PoseUpdate):
            poses = {k: sim3_apply_to_pose(self.correction_of(k), T) for k, T in msg.cam_to_world.items()}
            return PoseUpdate(poses, dict(msg.affine))
        if isinstance(msg, PointsMessage):
            if len(msg) == 0:
                return msg
            C = self.correction_of(msg.host_keyframe_id)
            pts = np.asarray(msg.points) @ C[:3, :3].T + C[:3, 3]
            return PointsMessage(pts, msg.colors, host_keyframe_id=msg.host_keyframe_id, weights=msg.weights)
        return msg

    def _fail(self, exc: BaseException) -> None:
        """Loop closure failed: it is off for the rest of the run (no more searches; the corrections found so far
        stay, so the map and the trajectories stay consistent); the error is in ``stats.error`` and the log."""
        if self.stats.error is None:
            self.stats.error = f"{type(exc).__name__}: {exc}"
            log.warning("loop closure failed and is off for the rest of the run (the corrections so far are kept): "
                        "%s", self.stats.error, exc_info=log.isEnabledFor(logging.DEBUG) and exc)
        self._off = True

    def poll(self) -> LoopCorrection | None:
        """A loop finished since the last call: apply its corrections and return what the mapper must do (the Sim(3)
        each keyframe it has moved by), or ``None``. A failure on the closer's thread turns loop closure off here
        (:meth:`_fail`)."""
        if self._error is not None:
            err, self._error = self._error, None
            self._fail(err)
        with self._lock:
            ready, self._ready = self._ready, []
        if not ready:
            return None
        for solve in ready:
            self._apply(solve)
        deltas = {}
        for kid, sent in list(self._sent.items()):
            new = self.correction_of(kid)
            if not np.allclose(new, sent, rtol=0, atol=1e-12):
                deltas[kid] = new @ sim3_inverse(sent)
                self._sent[kid] = new
        if not deltas:
            return None
        self.stats.corrections_sent += 1
        return LoopCorrection(deltas, loop=self._loops)

    def finish(self, timeout: float | None = None) -> LoopCorrection | None:
        """End of the stream: wait for the closer's thread to finish the keyframes queued (``timeout``: give up
        after so many seconds, the loops not yet solved are dropped) and return the last correction."""
        if self._thread is not None:
            self._rest.set()
            self._jobs.put(None)
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("loop closure: the closer's thread did not finish within %s s; its last keyframes "
                            "are not searched", timeout)
            self._thread = None
        return self.poll()

    def close(self) -> None:
        """Stop the closer's thread without waiting for its queue (an interrupted run)."""
        if self._thread is not None:
            while True:
                try:
                    self._jobs.get_nowait()
                except queue.Empty:
                    break
            self._rest.set()
            self._jobs.put(None)
            self._thread.join(5.0)
            self._thread = None

    # ------------------------------------------------------------------------------------------ outputs
    def correct_keyframes(self, trajectory: Trajectory) -> Trajectory:
        """Keyframe poses (the odometry's, by timestamp) moved by their corrections."""
        if not self.corrected or len(trajectory) == 0:
            return trajectory
        by_time = {round(t, 9): k for k, t in self._time.items()}
        out = trajectory.cam_to_world.copy()
        for i, t in enumerate(trajectory.timestamps):
            k = by_time.get(round(float(t), 9))
            C = self.correction_of(k) if k is not None else self._interpolated(float(t))
            out[i] = sim3_apply_to_pose(C, out[i])
        return Trajectory(trajectory.timestamps.copy(), out)

    def correct_trajectory(self, trajectory: Trajectory) -> Trajectory:
        """Every frame's pose moved by the correction of its time: a keyframe's own, between two keyframes the
        geodesic interpolation (in time) of theirs, before the first or after the last keyframe that keyframe's."""
        if not self.corrected or len(trajectory) == 0:
            return trajectory
        out = trajectory.cam_to_world.copy()
        for i, t in enumerate(trajectory.timestamps):
            out[i] = sim3_apply_to_pose(self._interpolated(float(t)), out[i])
        return Trajectory(trajectory.timestamps.copy(), out)

    def correct_points(self, points: np.ndarray, hosts: np.ndarray) -> np.ndarray:
        """World points (the DSO cloud) moved by their host keyframe's correction."""
        if not self.corrected or len(points) == 0:
            return points
        out = np.array(points, dtype=np.float64, copy=True)
        for h in np.unique(hosts):
            sel = hosts == h
            C = self.correction_of(int(h))
            out[sel] = out[sel] @ C[:3, :3].T + C[:3, 3]
        return out

    def _interpolated(self, t: float) -> np.ndarray:
        with self._lock:
            ids = sorted(self._time, key=lambda k: self._time[k])
            if not ids:
                return self._C_cur.copy()
            times = np.array([self._time[k] for k in ids])
            j = int(np.searchsorted(times, t, side="right"))
            if j == 0:
                return self._C.get(ids[0], self._C_cur).copy()
            if j >= len(ids):
                return self._C.get(ids[-1], self._C_cur).copy()
            A = self._C.get(ids[j - 1], self._C_cur)
            B = self._C.get(ids[j], self._C_cur)
        if np.allclose(A, B, rtol=0, atol=1e-12):
            return A.copy()
        a = (t - times[j - 1]) / max(times[j] - times[j - 1], 1e-12)
        return A @ sim3_exp(a * sim3_log(sim3_inverse(A) @ B))

    # --------------------------------------------------------------------------------------- detection
    def _work(self) -> None:
        if self.nice > 0 and hasattr(os, "setpriority"):
            try:    # Linux: a thread's own niceness (its native id is a task id); elsewhere the whole process's
                if sys.platform.startswith("linux"):
                    tid = threading.get_native_id()
                    os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + self.nice)
            except OSError:
                log.debug("loop closure: could not lower the closer thread's priority", exc_info=True)
        share = float(self.cfg.realtime_cpu_share)
        while True:
            jobs = [self._jobs.get()]
            while jobs[-1] is not None:       # everything that waits: the newest is taken, the older ones skipped
                try:
                    jobs.append(self._jobs.get_nowait())
                except queue.Empty:
                    break
            ending = jobs[-1] is None
            jobs = [j for j in jobs if j is not None]
            # a closer that fell behind stays bounded in time and memory: the places of the skipped keyframes are
            # seen by their neighbours (a place spans several keyframes), and the pose graph has every keyframe
            self.stats.keyframes_skipped += max(0, len(jobs) - 1)
            t0 = time.perf_counter()
            try:
                for job in jobs[-1:]:
                    self._run_job(job)
            except BaseException as exc:  # noqa: BLE001 - handed to the system's thread at the next poll
                self._error = exc
                return
            if ending:
                return
            # the duty cycle: at most `share` of a core, so that the tracking keeps its own
            busy = time.perf_counter() - t0
            if 0 < share < 1 and busy > 0:
                self._rest.wait(busy * (1.0 / share - 1.0))

    def _run_job(self, job) -> None:
        t0 = time.perf_counter()
        try:
            solve = self._detect(*job)
        finally:
            self.stats.seconds += time.perf_counter() - t0
        if solve is not None:
            with self._lock:
                self._ready.append(solve)

    def _reject(self, reason: str) -> None:
        self.stats.rejected[reason] = self.stats.rejected.get(reason, 0) + 1

    def _detect(self, kid: int, image, camera, points_uv, idepths) -> _Solve | None:
        from mgso.loop.place import extract_features
        from mgso.loop.verify import verify

        cfg = self.cfg
        feats = extract_features(kid, image, camera, points_uv, idepths, cfg)
        with self._lock:
            order = list(self._order)
            pos = order.index(kid)
            recent = set(order[max(0, pos - cfg.min_keyframe_gap):]) | self._active
            old = [k for k in order[:pos] if k not in recent and k in self._features]
            near = self._near(kid, old, idepths)
        self._features[kid] = feats
        cands = []
        if old:
            self.stats.queries += 1
            cands = self.db.query(feats, exclude=recent | {kid}, settings=cfg, extra=near)
            # the best by appearance, pose-proximity ones included: loop.max_candidates bounds the verification's
            # cost (a few tens of ms each)
            cands = sorted(cands, key=lambda c: -c.matches)[: cfg.max_candidates]
        self.db.add(feats)
        for cand in cands:
            self.stats.candidates += 1
            v = verify(feats, self._features[cand.keyframe_id], cfg, device=self.device, rng_seed=kid,
                       tracking=self.config.tracking)
            if not v.accepted:
                self._reject(v.reason)
                continue
            return self._solve(kid, cand.keyframe_id, v)
        return None

    def _near(self, kid: int, old: list[int], idepths) -> list[int]:
        """Old keyframes whose corrected camera centre is within ``loop.proximity_depths`` x the new keyframe's
        median depth of its own (and looking within 60 degrees of its direction)."""
        f = self.cfg.proximity_depths
        if f <= 0 or not old or len(idepths) == 0:
            return []
        good = np.asarray(idepths)[np.asarray(idepths) > 0]
        if len(good) == 0:
            return []
        radius = f * float(np.median(1.0 / good))
        P = sim3_apply_to_pose(self._C.get(kid, self._C_cur), self._odo[kid])
        out = []
        for k in old:
            Q = sim3_apply_to_pose(self._C.get(k, self._C_cur), self._odo[k])
            if np.linalg.norm(Q[:3, 3] - P[:3, 3]) <= radius * sim3_to_parts(self._C.get(kid, self._C_cur))[2]:
                if float(P[:3, 2] @ Q[:3, 2]) >= 0.5:
                    out.append(k)
        return out

    def _solve(self, kid: int, cand: int, v) -> _Solve:
        from mgso.loop.graph import PoseGraph

        cfg = self.cfg
        with self._lock:
            order = list(self._order[: self._order.index(kid) + 1])
            odo = {k: self._odo[k].copy() for k in order}
            C = {k: self._C.get(k, self._C_cur).copy() for k in order}
            active = set(self._active)
            self._loop_edges.append((cand, kid, np.asarray(v.relative, dtype=np.float64)))
            loops = list(self._loop_edges)
        t0 = time.perf_counter()
        g = PoseGraph()
        for k in order:
            g.add_node(k, C[k] @ _rigid_as_sim3(odo[k]))
        for i, k in enumerate(order):
            for j in order[max(0, i - cfg.odometry_neighbours): i]:
                g.add_edge(j, k, sim3_inverse(odo[j]) @ odo[k], kind="odometry")
        for a, b, rel in loops:
            if a in odo and b in odo:
                g.add_edge(a, b, rel, information=cfg.loop_edge_weight, kind="loop")
        g.fix(order[0])
        res = g.optimize(cfg.graph_iterations)
        seconds = time.perf_counter() - t0
        self.stats.graph_solves += 1
        new = {k: res.poses[k] @ sim3_inverse(_rigid_as_sim3(odo[k])) for k in order}
        current = new[kid]
        marg = {k: new[k] for k in order if k not in active and k != kid}
        delta = current @ sim3_inverse(C[kid])
        R, t, s = sim3_to_parts(delta)
        rec = LoopRecord(kid, cand, self._frame.get(kid, -1), self._frame.get(cand, -1), int(v.matches),
                         int(v.inliers), None if v.rmse is None else float(v.rmse),
                         None if v.scale is None else float(v.scale),
                         correction_translation=float(np.linalg.norm(t)),
                         correction_degrees=float(np.degrees(np.linalg.norm(so3_log(R)))),
                         correction_scale=s, graph_seconds=seconds,
                         relative=np.asarray(v.relative, dtype=np.float64).tolist())
        self.stats.accepted += 1
        self.stats.loops.append(rec)
        log.info("loop closed: keyframe %d (frame %d) on keyframe %d (frame %d), %d inliers; the newest keyframe "
                 "moved %.3g (odometry units), %.2f degrees, scale x%.3f", kid, rec.frame_index, cand,
                 rec.candidate_frame_index, rec.inliers, rec.correction_translation, rec.correction_degrees,
                 rec.correction_scale)
        return _Solve(rec, marg, current)

    def _apply(self, solve: _Solve) -> None:
        with self._lock:
            for k, Ck in solve.corrections.items():
                self._C[k] = Ck
            for k in self._order:        # the window's keyframes and every one after the solve: rigidly
                if k not in solve.corrections:
                    self._C[k] = solve.current.copy()
            self._C_cur = solve.current.copy()
        self._loops += 1
