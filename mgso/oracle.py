"""An oracle odometry: ground-truth poses and depths in place of DSO, with optional noise (tests and profiles).

:class:`OracleOdometry` satisfies :class:`mgso.system.OdometrySource` from what a dataset knows: every frame's
ground-truth ``cam_to_world`` and a depth map. It emits the messages DSO would emit, so the mapper and the system
can be tested and measured apart from tracking:

- a keyframe every ``keyframe_every`` frames, with ``points`` pixels chosen by DSO's pixel selector
  (:mod:`mgso.tracking.pixel_selector`) on the keyframe and their inverse depth from the depth map (times
  ``1 + N(0, idepth_noise)``, and by ``exp(N(0, idepth_log_noise))``: errors by factors, as DSO's points that
  little parallax constrains, whose inverse depths on a camera turning in place are off by 2x and more);
- the keyframe's pose with a random error (``pose_noise_m``, ``pose_noise_rad``, per axis) when it is made, then the
  exact pose in a :class:`~mgso.messages.PoseUpdate` at the next keyframe (the window refined it), for the
  keyframes of a ``window`` of the newest ones;
- a keyframe leaving the window marginalises its points (:class:`~mgso.messages.PointsMessage`, world
  positions at the exact pose, colours over DSO's pattern); :meth:`finish` marginalises the rest.

``drift`` (rotation rad, translation m, log-scale, each per frame) bends the whole estimate as an odometry drifts:
frame i's world is moved by the Sim(3) ``D_i = exp(i xi)`` (rotation about the world's y axis, translation along x,
scale), poses, points and inverse depths alike (a keyframe keeps its frame's ``D``; its window refinement gives the
exact pose in that drifted world). A camera that comes back to where it started then sees the place at a different
pose and scale: the loop closure's test (docs/loop.md).

Non-keyframes keep their noisy pose in :meth:`trajectory`; keyframes get the exact one. The affine brightness is
(0, 0) and the frame's exposure time is passed on (DSO with known exposures). It is **not** an odometry: the CLI
never uses it; ``mgso run`` needs the real one.

Depth sources: :meth:`OracleOdometry.from_sequence` takes ``Sequence.load_depth`` (the synthetic TUM RGB-D folders,
TUM RGB-D, 7-Scenes). 7-Scenes' depth is in the depth camera's view (585/585/320/240), not registered to the colour
image; it is reprojected into the colour camera assuming the two share their centre (they are a few cm apart: an
approximation an oracle can live with, said where it is used).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import Callable

import numpy as np

from mgso.camera import PinholeCamera
from mgso.geometry import orthonormalize, se3_exp, sim3_exp
from mgso.io.trajectory import Trajectory
from mgso.messages import KeyframeMessage, PointsMessage, PointKind, PoseUpdate, sim3_apply_to_pose
from mgso.mapping.seeding import backproject, sample_pattern_colors
from mgso.system import OdometryFrame

__all__ = ["OracleOdometry", "register_depth"]

log = logging.getLogger(__name__)


def register_depth(depth: np.ndarray, depth_camera: PinholeCamera, color_camera: PinholeCamera) -> np.ndarray:
    """Reproject a depth map (z in metres, 0 = invalid) from ``depth_camera`` into ``color_camera``, assuming both
    share their centre and orientation (nearest pixel, nearest surface wins); 0 where nothing lands."""
    d = np.asarray(depth, dtype=np.float64)
    v, u = np.nonzero(d > 0)
    z = d[v, u]
    x = (u - depth_camera.cx) / depth_camera.fx
    y = (v - depth_camera.cy) / depth_camera.fy
    u2 = np.round(color_camera.fx * x + color_camera.cx).astype(np.int64)
    v2 = np.round(color_camera.fy * y + color_camera.cy).astype(np.int64)
    ok = (u2 >= 0) & (u2 < color_camera.width) & (v2 >= 0) & (v2 < color_camera.height)
    out = np.full((color_camera.height, color_camera.width), np.inf)
    np.minimum.at(out, (v2[ok], u2[ok]), z[ok])
    out[~np.isfinite(out)] = 0.0
    return out.astype(np.float32)


class OracleOdometry:
    """Ground truth posing as an odometry (see the module doc).

    ``camera``: the pinhole camera of the frames; ``poses(i)`` -> 4x4 ``cam_to_world`` of frame ``i`` or ``None``;
    ``depth(i)`` -> (H, W) z-depth in metres (0 = invalid) or ``None``. Frames without a pose are reported without
    one (``status="lost"``); a keyframe without depth has no points.
    """

    def __init__(self, camera: PinholeCamera, poses: Callable[[int], np.ndarray | None],
                 depth: Callable[[int], np.ndarray | None], *, keyframe_every: int = 5, points: int = 600,
                 idepth_noise: float = 0.0, idepth_log_noise: float = 0.0, pose_noise_m: float = 0.0,
                 pose_noise_rad: float = 0.0, window: int = 7, seed: int = 0, name: str = "oracle",
                 drift: tuple[float, float, float] = (0.0, 0.0, 0.0)):
        if keyframe_every < 1 or window < 1 or points < 1:
            raise ValueError("OracleOdometry: keyframe_every, window and points must be >= 1")
        self.camera = camera
        self.device: str | None = None       # no kernels of its own (the system's loop closer uses its device)
        self._poses = poses
        self._depth = depth
        self.keyframe_every = int(keyframe_every)
        self.points = int(points)
        self.idepth_noise = float(idepth_noise)
        self.idepth_log_noise = float(idepth_log_noise)
        self.pose_noise = (float(pose_noise_m), float(pose_noise_rad))
        rot, trans, log_scale = (float(v) for v in drift)
        self._drift_xi = np.array([trans, 0.0, 0.0, 0.0, rot, 0.0, log_scale])
        self.window_size = int(window)
        self.seed = int(seed)
        self.name = name
        from mgso.tracking.pixel_selector import PixelSelector

        self._selector = PixelSelector(camera.width, camera.height, seed=seed)
        self._window: deque = deque()          # (keyframe id, frame index, true pose, uv, idepth, colours)
        self._frames: list[tuple[float, np.ndarray]] = []       # (timestamp, estimated cam_to_world)
        self._frame_kf: list[int] = []         # keyframe id of each frame in _frames, -1 if none
        self._kf: dict[int, tuple[float, np.ndarray]] = {}      # id -> (timestamp, final pose)
        self._next_kf = 0
        self._since_kf = self.keyframe_every   # the first frame with a pose is a keyframe

    # --------------------------------------------------------------------------------------- builders
    @classmethod
    def from_sequence(cls, seq, **kwargs) -> "OracleOdometry":
        """An oracle over a :class:`mgso.io.Sequence` with ground truth and depth (``load_depth``)."""
        if seq.groundtruth is None:
            raise ValueError(f"{seq.path}: the oracle needs ground-truth poses")
        if not getattr(seq, "has_depth", False):
            raise ValueError(f"{seq.path}: the oracle needs depth maps (this dataset has none)")
        cam = seq.calibration.output
        depth_cam = getattr(seq, "depth_camera", None)

        def pose(i):
            T = seq.groundtruth_cam_to_world(i)
            if T is None:
                return None
            T = np.array(T, dtype=np.float64)
            T[:3, :3] = orthonormalize(T[:3, :3])
            return T

        def depth(i):
            d = seq.load_depth(i)
            if d is None:
                return None
            if depth_cam is not None:
                return register_depth(d, depth_cam, cam)
            return d

        kwargs.setdefault("name", "oracle (ground-truth poses and depth)")
        return cls(cam, pose, depth, **kwargs)

    # ------------------------------------------------------------------------------------------ odometry
    def _noisy(self, T: np.ndarray, index: int) -> np.ndarray:
        sm, sr = self.pose_noise
        if sm <= 0 and sr <= 0:
            return T.copy()
        rng = np.random.default_rng([self.seed, 0x0DD, int(index)])
        xi = np.concatenate([rng.normal(0, sm, 3), rng.normal(0, sr, 3)])
        return T @ se3_exp(xi)

    def drift(self, index: int) -> np.ndarray:
        """The Sim(3) that moves frame ``index``'s world into the drifted estimate (identity without drift)."""
        if not np.any(self._drift_xi):
            return np.eye(4)
        return sim3_exp(int(index) * self._drift_xi)

    def _drifted(self, T: np.ndarray, index: int) -> np.ndarray:
        if not np.any(self._drift_xi):
            return T
        return sim3_apply_to_pose(self.drift(index), T)

    def _drift_scale(self, index: int) -> float:
        return float(np.exp(int(index) * self._drift_xi[6]))

    def _refine_window(self) -> PoseUpdate:
        """The window's keyframes at their exact poses (in the drifted world), kept as their final poses."""
        exact = {e[0]: self._drifted(e[2], e[1]) for e in self._window}
        for kid, T in exact.items():
            self._kf[kid] = (self._kf[kid][0], T)
        return PoseUpdate(exact)

    def _select(self, frame) -> tuple[np.ndarray, np.ndarray]:
        from mgso_kernels.reference.image import build_pyramid

        d = self._depth(frame.index)
        if d is None:
            return np.zeros((0, 2)), np.zeros(0)
        pyr = build_pyramid(np.asarray(frame.gray, np.float32), 3)
        sel = self._selector.select([p[1] for p in pyr], float(self.points))
        xy = sel.xy.astype(np.int64)
        z = np.asarray(d, np.float64)[xy[:, 1], xy[:, 0]]
        ok = np.isfinite(z) & (z > 0)
        xy, z = xy[ok], z[ok]
        idepth = 1.0 / z
        if self.idepth_noise > 0:
            rng = np.random.default_rng([self.seed, 0x1D, int(frame.index)])
            idepth = np.maximum(idepth * (1.0 + self.idepth_noise * rng.standard_normal(len(z))), 1e-6)
        if self.idepth_log_noise > 0:
            rng = np.random.default_rng([self.seed, 0x1E, int(frame.index)])
            idepth = idepth * np.exp(self.idepth_log_noise * rng.standard_normal(len(z)))
        return xy.astype(np.float64), idepth

    def _marginalize(self, entry) -> PointsMessage:
        kid, i, T, uv, idepth, colors = entry
        pts = backproject(uv, 1.0 / idepth, self.camera, T) if len(uv) else np.zeros((0, 3))
        if len(pts) and np.any(self._drift_xi):
            D = self.drift(i)
            pts = pts @ D[:3, :3].T + D[:3, 3]
        return PointsMessage(pts, colors, host_keyframe_id=kid)

    def process(self, frame) -> OdometryFrame:
        t0 = time.perf_counter()
        i = int(frame.index)
        T = self._poses(i)
        exposure = getattr(frame, "exposure_ms", None)
        if T is None:
            return OdometryFrame(i, frame.timestamp, None, status="lost", exposure_ms=exposure,
                                 seconds=time.perf_counter() - t0)
        T_est = self._drifted(self._noisy(T, i), i)
        self._since_kf += 1
        messages = []
        is_kf = self._since_kf >= self.keyframe_every
        kid = -1
        if is_kf:
            self._since_kf = 0
            kid = self._next_kf
            self._next_kf += 1
            if self._window:     # the window refined the earlier keyframes: their exact poses
                messages.append(self._refine_window())
            uv, idepth = self._select(frame)
            rgb = np.asarray(frame.rgb, np.float32)
            colors = sample_pattern_colors(rgb, uv) if len(uv) else np.zeros((0, 3), np.float32)
            messages.append(KeyframeMessage(kid, i, frame.timestamp, rgb, self.camera, T_est, uv,
                                            idepth / self._drift_scale(i),
                                            kinds=np.full(len(uv), int(PointKind.ACTIVE), np.int8),
                                            exposure_ms=exposure))
            self._kf[kid] = (float(frame.timestamp), T_est)
            self._window.append((kid, i, T, uv, idepth, colors))
            while len(self._window) > self.window_size:
                messages.append(self._marginalize(self._window.popleft()))
        self._frames.append((float(frame.timestamp), T_est))
        self._frame_kf.append(kid)
        return OdometryFrame(i, frame.timestamp, T_est, is_keyframe=is_kf, exposure_ms=exposure,
                             status="keyframe" if is_kf else "tracked", messages=tuple(messages),
                             seconds=time.perf_counter() - t0)

    def finish(self) -> list:
        out = []
        if self._window:
            out.append(self._refine_window())
        while self._window:
            out.append(self._marginalize(self._window.popleft()))
        return out

    def trajectory(self) -> Trajectory:
        if not self._frames:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        poses = [self._kf[k][1] if k >= 0 else T for (_, T), k in zip(self._frames, self._frame_kf)]
        return Trajectory(np.array([t for t, _ in self._frames]), np.stack(poses))

    def keyframe_trajectory(self) -> Trajectory:
        if not self._kf:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        ids = sorted(self._kf)
        return Trajectory(np.array([self._kf[k][0] for k in ids]), np.stack([self._kf[k][1] for k in ids]))
