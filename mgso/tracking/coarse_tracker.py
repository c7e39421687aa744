"""Coarse tracking of every frame against the newest keyframe (DSO ``CoarseTracker`` and
``FullSystem::trackNewCoarse``).

Two halves, as in DSO, so that a mapping thread can build the next reference while the tracker works:

- :func:`make_tracking_reference` (mapping side, after each keyframe's optimisation): projects all active points of
  the window into the newest keyframe, averages their inverse depths per pixel weighted by their Hessian, sums the
  map down the pyramid and dilates it on every level (DSO ``makeCoarseDepthL0``: diagonal neighbours on levels 0-1,
  4-neighbours on coarser ones), and keeps per level the pixels with a depth as tracking points (pixel, inverse
  depth, reference intensity). The result, a :class:`TrackingReference`, is handed to the tracker with
  :meth:`CoarseTracker.set_reference` (DSO swaps ``coarseTracker_forNewKF`` in; no attribute poking). Its second
  half, :func:`reference_from_points`, builds a reference from any keyframe's pyramid and points without a window
  (the loop closure's photometric check, :mod:`mgso.loop.verify`).
- :class:`CoarseTracker` (tracking side): :meth:`~CoarseTracker.track_levels` is DSO's ``trackNewestCoarse``
  (coarse-to-fine Levenberg-Marquardt on pose and affine brightness, DSO's damping schedule, step acceptance by
  mean energy, cutoff raised and the level repeated when too many residuals saturate, abort when a level is worse
  than the best so far); :meth:`~CoarseTracker.track_frame` is ``trackNewCoarse``'s loop over the motion hypotheses
  of :func:`motion_hypotheses` with early exit once the RMSE is good enough.

Pose parameters are the left se3 perturbation of ``ref_to_new`` (translation first), then the new frame's affine
``(a, b)``; DSO's scaling ``SCALE_XI_ROT = 1``, ``SCALE_XI_TRANS = 0.5``, ``SCALE_A = 10``, ``SCALE_B = 1000`` is
applied to the system as DSO's tracker does (there the first three, Sophus' translation, get ``SCALE_XI_ROT``).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from mgso.arrays import unique
from mgso_kernels.image import ImagePyramid, PyramidGeometry
from mgso_kernels import runtime
from mgso_kernels.photometric import PATTERN_NP, make_intrinsics, affine_from_to
from mgso_kernels.track import TrackWorkspace, TrackingSystem, track_system

from ..config import TrackingConfig
from ..geometry import quat_wxyz_to_matrix, se3_exp, se3_inverse, se3_log, make_pose
from ..window.window import ResidualState, Window

__all__ = [
    "TrackingReference", "ReferenceLevel", "make_tracking_reference", "reference_from_points", "CoarseTracker",
    "LevelsResult", "TrackResult", "motion_hypotheses", "coarse_depth_maps", "coarse_depth_points", "SCALE",
]

log = logging.getLogger(__name__)

# DSO's parameter scaling in the coarse tracker: (v, w, a, b); DSO applies SCALE_XI_ROT to Sophus' first three
# (the translation) and SCALE_XI_TRANS to the rotation.
SCALE = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 10.0, 1000.0])
# the parameters a step solves for when the affine a and / or b are fixed
_FREE = {(fa, fb): np.array([i for i in range(8) if not ((i == 6 and fa) or (i == 7 and fb))])
         for fa in (False, True) for fb in (False, True)}


# ------------------------------------------------------------------------------------------------ reference
@dataclass
class ReferenceLevel:
    """Tracking points of the reference at one pyramid level (DSO ``pc_u, pc_v, pc_idepth, pc_color``)."""

    uv: wp.array  # [N] vec2, pixels of this level
    idepth: wp.array  # [N] float32, inverse depth in the reference
    color: wp.array  # [N, P] float32 reference intensity (P = 1, or 8 with the pattern)
    n: int


@dataclass
class TrackingReference:
    """What the tracker needs of its reference keyframe; built by :func:`make_tracking_reference` on the mapping
    side and handed over whole (:meth:`CoarseTracker.set_reference`). Only the tracker changes ``first_rmse``."""

    keyframe_id: int
    frame_index: int
    segment: int
    world_to_cam: np.ndarray  # [4, 4] the keyframe's pose when the reference was built
    affine: tuple[float, float]  # (a, b) of the keyframe
    exposure: float  # exposure time, 0 = unknown
    levels: list[ReferenceLevel]
    idepth_maps: list[np.ndarray]  # per level [h, w] float32 inverse depth, -1 where none (DSO idepth[lvl])
    num_points_l0: int
    median_depth: float  # median depth of the level-0 tracking points (scale bookkeeping across segments)
    first_rmse: float = -1.0  # DSO firstCoarseRMSE: RMSE of the first frame tracked against this reference

    @property
    def cam_to_world(self) -> np.ndarray:
        return se3_inverse(self.world_to_cam)


# the neighbours DSO's dilation averages, (dy, dx) in the order their values are summed (row-major, as a 3x3
# correlation sums them): levels 0-1 the diagonal ones (DSO i+1+w, i-1-w, i+w-1, i-w+1), coarser levels the 4-neighbours
_DIAG_OFFSETS = ((-1, -1), (-1, 1), (1, -1), (1, 1))
_CROSS_OFFSETS = ((-1, 0), (0, -1), (0, 1), (1, 0))


def coarse_depth_points(geometry: PyramidGeometry, uv: np.ndarray, idepth: np.ndarray,
                        weight: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """DSO ``makeCoarseDepthL0`` on the pixels that get a depth: per level ``(pixels, idepth_sum, weight_sum)``,
    ``pixels`` the raster indices (``y * w + x``, ascending) of the pixels with ``weight_sum > 0``, the sums float32.

    The points ``uv [N, 2]`` (level-0 pixels, rounded) are splatted with ``idepth [N] * weight [N]`` and ``weight``,
    2x2 blocks are summed down the pyramid, then each level is dilated once (levels 0-1: a pixel without a depth and
    not on the border takes the mean of its diagonal neighbours with one; coarser: of its 4-neighbours), all from the
    sums before the dilation. The same bits as the dense maps (``tests/tracking/test_coarse_tracker.py`` compares
    them); the work is the points' (a keyframe's ~2,000), not the image's: 2.6 ms against 9.5 ms at KITTI's
    1241x376, where the dense maps were 8 % of the odometry's CPU time."""
    w0, h0 = geometry.width, geometry.height
    u = np.floor(uv[:, 0] + 0.5).astype(np.int64)
    v = np.floor(uv[:, 1] + 0.5).astype(np.int64)
    ok = (u >= 0) & (v >= 0) & (u < w0) & (v < h0) & np.isfinite(idepth) & (weight > 0)
    pix, inv = np.unique(v[ok] * w0 + u[ok], return_inverse=True)
    # np.bincount adds each bin's weights in the points' order, float64, as over the whole image
    id0 = np.bincount(inv, weights=(idepth[ok] * weight[ok]).astype(np.float64), minlength=len(pix)).astype(np.float32)
    w0s = np.bincount(inv, weights=weight[ok].astype(np.float64), minlength=len(pix)).astype(np.float32)
    pos = w0s > 0  # a weight below float32's range counts as none, as in the dense maps
    sums = [(pix[pos], id0[pos], w0s[pos])]
    wp_ = w0
    for lvl in range(1, geometry.levels):  # 2x2 sums of the level above, before its dilation
        wl, hl = geometry.level_size(lvl)
        pix_p, id_p, w_p = sums[-1]
        x, y = pix_p % wp_, pix_p // wp_
        inside = (x < 2 * wl) & (y < 2 * hl)
        x, y = x[inside], y[inside]
        parent, inv = np.unique((y // 2) * wl + x // 2, return_inverse=True)
        quad = (y % 2) * 2 + (x % 2)  # the dense sum's order: (0, 0) + (0, 1) + (1, 0) + (1, 1)
        out = []
        for val in (id_p[inside], w_p[inside]):
            q = np.zeros((len(parent), 4), np.float32)
            q[inv, quad] = val
            out.append(((q[:, 0] + q[:, 1]) + q[:, 2]) + q[:, 3])
        sums.append((parent, out[0], out[1]))
        wp_ = wl
    result = []
    for lvl, (pix, idl, wsl) in enumerate(sums):
        wl, hl = geometry.level_size(lvl)
        if hl < 3 or wl < 3 or not len(pix):
            result.append((pix, idl, wsl))
            continue
        offsets = _DIAG_OFFSETS if lvl < 2 else _CROSS_OFFSETS
        x, y = pix % wl, pix // wl
        # pixels with an occupied neighbour (the offsets are symmetric)
        cand = unique(np.concatenate([(y - dy) * wl + (x - dx) for dy, dx in offsets]))
        cx, cy = cand % wl, cand // wl
        inner = (cx >= 1) & (cx <= wl - 2) & (cy >= 1) & (cy <= hl - 2)
        cand = cand[inner]
        slot = np.full(hl * wl, -1, np.int32)  # pixel -> its index in ``pix`` (a lookup; 0.1 ms at KITTI's size)
        slot[pix] = np.arange(len(pix), dtype=np.int32)
        cand = cand[slot[cand] < 0]
        cnt = np.zeros(len(cand), np.float32)
        s_id = np.zeros(len(cand), np.float32)
        s_w = np.zeros(len(cand), np.float32)
        idz, wz = np.append(idl, np.float32(0)), np.append(wsl, np.float32(0))  # slot -1 reads the 0 at the end
        for dy, dx in offsets:  # summed in float32 in the correlation's order
            at = slot[cand + (dy * wl + dx)]
            cnt += at >= 0
            s_id += idz[at]
            s_w += wz[at]
        allpix = np.concatenate([pix, cand])
        order = np.argsort(allpix, kind="stable")
        result.append((allpix[order], np.concatenate([idl, s_id / cnt])[order],
                       np.concatenate([wsl, s_w / cnt])[order]))
    return result


def coarse_depth_maps(geometry: PyramidGeometry, uv: np.ndarray, idepth: np.ndarray,
                      weight: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """DSO ``makeCoarseDepthL0`` as images: per level ``(idepth_sum [h, w], weight_sum [h, w])`` float32, 0 where no
    depth (:func:`coarse_depth_points`, scattered). A pixel's inverse depth is ``idepth_sum / weight_sum`` where
    ``weight_sum > 0``."""
    ids, wss = [], []
    for lvl, (pix, idl, wsl) in enumerate(coarse_depth_points(geometry, uv, idepth, weight)):
        wl, hl = geometry.level_size(lvl)
        for lst, val in ((ids, idl), (wss, wsl)):
            a = np.zeros(hl * wl, np.float32)
            a[pix] = val
            lst.append(a.reshape(hl, wl))
    return ids, wss


def make_tracking_reference(window: Window, config: TrackingConfig, device: str | None = None) -> TrackingReference:
    """Build the coarse tracker's reference from the window's newest keyframe (DSO ``setCoarseTrackingRef``).

    Points used: every active point with an ``IN`` residual in the newest keyframe, projected with the current
    estimates; weight ``sqrt(1e-3 * H_dd)`` (DSO ``sqrt(1e-3 / HdiF)``) from ``idepth_hessian``.
    """
    device = device or window.device
    g = window.geometry
    slot = window.newest_slot
    a = window.active
    use = np.flatnonzero(a.res_state[:, slot] == ResidualState.IN) if a.n else np.zeros(0, np.int64)
    uv_t = np.zeros((0, 2))
    id_t = np.zeros(0)
    wt = np.zeros(0)
    if len(use):
        cam = g.camera
        K = cam.matrix()
        Ki = np.linalg.inv(K)
        uv_t, id_t, wt = [], [], []
        hosts = a.host[use]
        for h in unique(hosts):
            idx = use[hosts == h]
            T = window.target_from_host(int(h), slot)
            M = K @ T[:3, :3] @ Ki
            kt = K @ T[:3, 3]
            uv = a.uv[idx].astype(np.float64)
            idp = a.idepth[idx].astype(np.float64)
            p = np.stack([uv[:, 0], uv[:, 1], np.ones(len(idx))], axis=1) @ M.T + kt[None] * idp[:, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                uv_t.append(p[:, :2] / p[:, 2:3])
                id_t.append(idp / p[:, 2])
            wt.append(np.sqrt(1e-3 * np.maximum(a.idepth_hessian[idx].astype(np.float64), 1e-6)))
        uv_t, id_t, wt = np.concatenate(uv_t), np.concatenate(id_t), np.concatenate(wt)
        good = np.isfinite(id_t) & (id_t > 0) & np.all(np.isfinite(uv_t), axis=1)
        uv_t, id_t, wt = uv_t[good], id_t[good], wt[good]
    return reference_from_points(
        g, window.pyramids[slot], uv_t, id_t, wt, config, keyframe_id=int(window.keyframe_id_[slot]),
        frame_index=int(window.frame_index_[slot]), segment=int(window.segment_[slot]),
        world_to_cam=window.world_to_cam_[slot].copy(),
        affine=(float(window.affine_[slot, 0]), float(window.affine_[slot, 1])),
        exposure=float(window.exposure_[slot]), device=device)


def reference_from_points(geometry: PyramidGeometry, pyramid: ImagePyramid, uv: np.ndarray, idepth: np.ndarray,
                          weight: np.ndarray | None = None, config: TrackingConfig | None = None, *,
                          keyframe_id: int = -1, frame_index: int = -1, segment: int = 0,
                          world_to_cam: np.ndarray | None = None, affine: tuple[float, float] = (0.0, 0.0),
                          exposure: float = 0.0, device: str | None = None) -> TrackingReference:
    """A :class:`TrackingReference` from a keyframe's image pyramid and points, without a :class:`Window` (what
    :func:`make_tracking_reference` does once it has projected the window's points; the loop closure's photometric
    check uses it on an old keyframe).

    ``uv [N, 2]`` level-0 pixels of ``geometry`` (rounded to the nearest pixel), ``idepth [N]`` inverse depths in the
    keyframe, ``weight [N]`` their weights in the per-pixel average (default 1; points with a weight <= 0 or a
    non-finite inverse depth are ignored). The depth maps are DSO's (:func:`coarse_depth_maps`); every pixel of a
    level with a positive depth 2 pixels or more from the border is a tracking point. ``world_to_cam`` defaults to
    the identity, ``exposure`` 0 = unknown.
    """
    g = geometry
    config = config or TrackingConfig()
    device = device or pyramid.device
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    idepth = np.asarray(idepth, dtype=np.float64).reshape(-1)
    weight = np.ones(len(idepth)) if weight is None else np.asarray(weight, dtype=np.float64).reshape(-1)
    if not (len(uv) == len(idepth) == len(weight)):
        raise ValueError(f"reference_from_points: {len(uv)} pixels, {len(idepth)} inverse depths and {len(weight)} "
                         "weights; expected as many of each")
    pyr = pyramid
    levels, maps = [], []
    pattern = bool(config.coarse_pattern)
    for lvl, (pix, idl, wsl) in enumerate(coarse_depth_points(g, uv, idepth, weight)):
        wl, hl = g.level_size(lvl)
        img = pyr.intensity[lvl].numpy()
        xs, ys = pix % wl, pix // wl
        d = idl / wsl
        # every pixel with a depth 2 or more from the border, in raster order (``pix`` ascends)
        sel = (xs >= 2) & (xs < wl - 2) & (ys >= 2) & (ys < hl - 2) & (d > 0) & np.isfinite(img.reshape(-1)[pix])
        xs, ys, d = xs[sel], ys[sel], d[sel]
        depth = np.full(hl * wl, -1.0, np.float32)
        depth[pix[sel]] = d
        maps.append(depth.reshape(hl, wl))
        if pattern:
            px = np.clip(xs[:, None] + PATTERN_NP[None, :, 0].astype(np.int64), 0, wl - 1)
            py = np.clip(ys[:, None] + PATTERN_NP[None, :, 1].astype(np.int64), 0, hl - 1)
            col = img[py, px].astype(np.float32)
        else:
            col = img[ys, xs].astype(np.float32)[:, None]
        n = len(xs)
        levels.append(ReferenceLevel(
            uv=wp.array(np.stack([xs, ys], axis=1).astype(np.float32).reshape(n, 2), dtype=wp.vec2, device=device),
            idepth=wp.array(d.astype(np.float32), dtype=wp.float32, device=device),
            color=wp.array(np.ascontiguousarray(col), dtype=wp.float32, device=device), n=n))
    d0 = maps[0][maps[0] > 0]
    med = float(np.median(1.0 / d0)) if len(d0) else float("nan")
    return TrackingReference(
        keyframe_id=int(keyframe_id), frame_index=int(frame_index), segment=int(segment),
        world_to_cam=np.eye(4) if world_to_cam is None else np.array(world_to_cam, dtype=np.float64),
        affine=(float(affine[0]), float(affine[1])), exposure=float(exposure), levels=levels, idepth_maps=maps,
        num_points_l0=levels[0].n, median_depth=med)


# ------------------------------------------------------------------------------------------------- hypotheses
@functools.lru_cache(maxsize=4)
def _small_rotations(delta: float) -> tuple[np.ndarray, ...]:
    """DSO's 26 rotations: quaternions ``(1, d_x, d_y, d_z)`` normalised, each d in {-delta, 0, +delta}, in DSO's
    order (single axes, pairs, triples). Made once per ``delta`` (read-only): every tracked frame asks for them."""
    d = delta
    comps = [(d, 0, 0), (0, d, 0), (0, 0, d), (-d, 0, 0), (0, -d, 0), (0, 0, -d),
             (d, d, 0), (0, d, d), (d, 0, d), (-d, d, 0), (0, -d, d), (-d, 0, d),
             (d, -d, 0), (0, d, -d), (d, 0, -d), (-d, -d, 0), (0, -d, -d), (-d, 0, -d),
             (-d, -d, -d), (-d, -d, d), (-d, d, -d), (-d, d, d), (d, -d, -d), (d, -d, d), (d, d, -d), (d, d, d)]
    out = tuple(make_pose(quat_wxyz_to_matrix(np.array([1.0, *c])), np.zeros(3)) for c in comps)
    for R in out:
        R.flags.writeable = False
    return out


def motion_hypotheses(ref_cam_to_world: np.ndarray, last_cam_to_world: np.ndarray | None,
                      prelast_cam_to_world: np.ndarray | None, *, rotations: bool = True,
                      rotation_delta: float = 0.02) -> list[np.ndarray]:
    """``ref_to_new`` guesses in DSO's order (``trackNewCoarse``): constant motion, double, half, zero motion since
    the last frame, zero motion from the reference, then 26 small rotations of the constant-motion guess. With no
    valid last two poses: only the identity (zero motion from the reference)."""
    if last_cam_to_world is None or prelast_cam_to_world is None:
        return [np.eye(4)]
    last_to_prelast = se3_inverse(prelast_cam_to_world) @ last_cam_to_world
    ref_to_last = se3_inverse(last_cam_to_world) @ ref_cam_to_world
    new_to_last = last_to_prelast  # assume the same motion again
    inv = se3_inverse(new_to_last)
    const = inv @ ref_to_last
    out = [const, inv @ inv @ ref_to_last, se3_inverse(se3_exp(0.5 * se3_log(new_to_last))) @ ref_to_last,
           ref_to_last, np.eye(4)]
    if rotations:
        out += [const @ R for R in _small_rotations(rotation_delta)]
    return out


# ---------------------------------------------------------------------------------------------------- tracker
@dataclass
class LevelsResult:
    """Outcome of one coarse-to-fine run (DSO ``trackNewestCoarse``) from one starting guess."""

    ok: bool
    ref_to_new: np.ndarray
    affine: tuple[float, float]
    rmse: np.ndarray  # [levels] sqrt(E / n) per level, NaN where not reached (DSO lastResiduals)
    flow: tuple[float, float, float]  # DSO lastFlowIndicators (t only, 0, rt) at level 0
    stats0: TrackingSystem | None  # the last accepted system at level 0
    iterations: int


@dataclass
class TrackResult:
    """The coarse tracker's answer for one frame (DSO ``trackNewCoarse``'s return and the shell it fills)."""

    ok: bool  # a hypothesis converged within the checks (DSO haveOneGood)
    ref_to_new: np.ndarray  # [4, 4]
    affine: tuple[float, float]  # (a, b) of the new frame
    rmse: np.ndarray  # [levels] best RMSE per level over the hypotheses tried (DSO achievedRes)
    flow: tuple[float, float, float]  # (translation-only, rotation-only (0), full) mean squared pixel shift
    hypotheses_tried: int
    iterations: int  # LM iterations over all hypotheses and levels
    num_terms: int  # level-0 residuals in bounds of the winning run
    num_inliers: int  # level-0 residuals within the cutoff
    num_reference_points: int  # level-0 points of the reference
    reference_keyframe_id: int
    first_rmse: float  # the reference's first RMSE (after this frame)
    baseline_rmse: float  # the first RMSE known before this frame: this reference's, or the previous reference's
    # when this is the first frame tracked against it (-1 when none); what a residual blow-up is measured against

    world_to_cam: np.ndarray | None = None  # [4, 4] ref_to_new @ the reference's world_to_cam when it was built

    @property
    def cam_to_ref(self) -> np.ndarray:
        return se3_inverse(self.ref_to_new)

    @property
    def rmse0(self) -> float:
        return float(self.rmse[0])

    @property
    def inlier_ratio(self) -> float:
        """Level-0 residuals within the cutoff / reference points at level 0."""
        return self.num_inliers / self.num_reference_points if self.num_reference_points else 0.0

    @property
    def view_ratio(self) -> float:
        """Level-0 residuals in bounds (the reference's points that project into the frame) / reference points at
        level 0: the overlap of the frame with its reference."""
        return self.num_terms / self.num_reference_points if self.num_reference_points else 0.0

    @property
    def fit_ratio(self) -> float:
        """Level-0 residuals within the cutoff / those in bounds: how well the points the frame sees fit it,
        whatever share of the reference's points it sees (:attr:`view_ratio`)."""
        return self.num_inliers / self.num_terms if self.num_terms else 0.0


class CoarseTracker:
    """Tracks frames against a :class:`TrackingReference` (DSO ``CoarseTracker``). Owns its workspaces and the
    last frame's RMSE (DSO ``lastCoarseRMSE``); the reference is swapped in whole by :meth:`set_reference`."""

    def __init__(self, geometry: PyramidGeometry, config: TrackingConfig | None = None, device: str | None = None):
        if geometry.camera is None:
            raise ValueError("CoarseTracker needs a PyramidGeometry with intrinsics")
        self.geometry = geometry
        self.config = config or TrackingConfig()
        self.device = runtime.device_or_cpu(device)
        p = 8 if self.config.coarse_pattern else 1
        self.workspaces = []
        self.cams = []
        for lvl in range(geometry.levels):
            wl, hl = geometry.level_size(lvl)
            self.workspaces.append(TrackWorkspace(max(1, wl * hl), pattern_size=p, device=device))
            c = geometry.level_camera(lvl)
            self.cams.append(make_intrinsics(c.fx, c.fy, c.cx, c.cy, wl, hl))
        self.reference: TrackingReference | None = None
        self.last_rmse = np.full(geometry.levels, 100.0)  # DSO lastCoarseRMSE (constructor: 100)
        self._previous_first_rmse = -1.0

    def set_reference(self, reference: TrackingReference | None) -> None:
        """Swap in a new reference (DSO: ``coarseTracker_forNewKF`` becomes ``coarseTracker``); ``None`` clears it
        (a new tracking segment)."""
        if reference is not None and len(reference.levels) != self.geometry.levels:
            raise ValueError("reference built for another pyramid")
        if reference is None:
            self._previous_first_rmse = -1.0
            self.last_rmse[:] = 100.0
        elif self.reference is not None and self.reference.first_rmse > 0:
            self._previous_first_rmse = self.reference.first_rmse
        self.reference = reference

    # ------------------------------------------------------------------------------------------ one run
    def _affine_mode(self, exposure: float) -> tuple[bool, bool]:
        c = self.config
        ref = self.reference
        fixed_exp = c.affine_fixed_with_exposure and exposure > 0 and ref.exposure > 0
        return (fixed_exp or c.affine_opt_a < 0), (fixed_exp or c.affine_opt_b < 0)

    def _system(self, lvl: int, T: np.ndarray, aff, exposure: float, dI: wp.array, cutoff: float) -> TrackingSystem:
        ref = self.reference
        L = ref.levels[lvl]
        ws = self.workspaces[lvl]
        pair = ws.frame_pair(T, ref.affine[0], ref.affine[1], aff[0], aff[1], ref.exposure, exposure)
        c = self.config
        return track_system(L.uv, L.idepth, L.color, pair, self.cams[lvl], dI, ws,
                            cutoff_th=cutoff, huber_th=c.huber_th, flow_stride=c.coarse_flow_stride if lvl == 0 else 0)

    @staticmethod
    def _mean(s: TrackingSystem) -> float:
        return s.energy / s.num_terms if s.num_terms else float("inf")

    def _solve(self, H: np.ndarray, b: np.ndarray, lam: float, fix_a: bool, fix_b: bool) -> np.ndarray:
        """The damped step on the free parameters (the affine ones may be fixed): ``H``'s diagonal times ``1 + lam``.
        Without index arrays when nothing is fixed (the common case; an LM iteration's host time counts)."""
        inc = np.zeros(8)
        if fix_a or fix_b:
            free = _FREE[(fix_a, fix_b)]
            Hl = H[free][:, free]
            rhs = -b[free]
        else:
            free = slice(None)
            Hl = H.copy()
            rhs = -b
        Hl.flat[::Hl.shape[0] + 1] *= 1.0 + lam
        try:
            inc[free] = np.linalg.solve(Hl, rhs)
        except np.linalg.LinAlgError:
            inc[:] = np.nan
        return inc

    def track_levels(self, pyramid: ImagePyramid, exposure: float, ref_to_new: np.ndarray, affine,
                     min_res_for_abort: np.ndarray, coarsest_level: int | None = None) -> LevelsResult:
        """DSO ``trackNewestCoarse`` from one guess; ``min_res_for_abort [levels]`` (NaN = no bound)."""
        ref = self.reference
        if ref is None:
            raise RuntimeError("CoarseTracker has no reference: set_reference first")
        c = self.config
        nlev = self.geometry.levels
        top = nlev - 1 if coarsest_level is None else int(coarsest_level)
        fix_a, fix_b = self._affine_mode(exposure)
        rmse = np.full(nlev, np.nan)
        flow = (1000.0, 1000.0, 1000.0)
        T = np.asarray(ref_to_new, dtype=np.float64).copy()
        aff = np.array([0.0 if fix_a else affine[0], 0.0 if fix_b else affine[1]], dtype=np.float64)
        iters_total = 0
        have_repeated = False
        stats0 = None
        lvl = top
        while lvl >= 0:
            dI = pyramid.dI[lvl]
            if ref.levels[lvl].n == 0:
                return LevelsResult(False, T, tuple(aff), rmse, flow, None, iters_total)
            repeat = 1.0
            s_old = self._system(lvl, T, aff, exposure, dI, c.coarse_cutoff_th * repeat)
            while s_old.saturated_ratio > c.coarse_saturated_ratio and repeat < c.coarse_max_cutoff_repeat:
                repeat *= 2.0
                s_old = self._system(lvl, T, aff, exposure, dI, c.coarse_cutoff_th * repeat)
            H, b = self._scaled(s_old)
            lam = c.coarse_lambda
            max_it = c.coarse_max_iterations[min(lvl, len(c.coarse_max_iterations) - 1)]
            for _ in range(max_it):
                iters_total += 1
                inc = self._solve(H, b, lam, fix_a, fix_b)
                extrap = 1.0
                if lam < c.coarse_lambda_extrapolation_limit:
                    extrap = math.sqrt(math.sqrt(c.coarse_lambda_extrapolation_limit / lam))
                inc *= extrap
                inc_scaled = inc * SCALE
                if not np.all(np.isfinite(inc_scaled)):
                    inc_scaled[:] = 0.0
                T_new = se3_exp(inc_scaled[:6]) @ T
                aff_new = aff + inc_scaled[6:]
                if abs(aff_new[0] - ref.affine[0]) < 20.0:  # exp() must stay finite; such a step is rejected
                    s_new = self._system(lvl, T_new, aff_new, exposure, dI, c.coarse_cutoff_th * repeat)
                else:
                    s_new = None
                if s_new is not None and self._mean(s_new) < self._mean(s_old):
                    H, b = self._scaled(s_new)
                    s_old, T, aff = s_new, T_new, aff_new
                    lam *= 0.5
                else:
                    lam *= 4.0
                    if lam < c.coarse_lambda_extrapolation_limit:
                        lam = c.coarse_lambda_extrapolation_limit
                if not (np.linalg.norm(inc) > c.coarse_min_step):
                    break
            rmse[lvl] = math.sqrt(self._mean(s_old)) if s_old.num_terms else float("nan")
            flow = s_old.flow_indicators
            if lvl == 0:
                stats0 = s_old
            if rmse[lvl] > c.coarse_abort_factor * min_res_for_abort[lvl]:  # NaN bound: never
                return LevelsResult(False, T, tuple(aff), rmse, flow, stats0, iters_total)
            if repeat > 1 and not have_repeated:
                have_repeated = True
                continue  # DSO repeats the level once when the cutoff had to be raised
            lvl -= 1
        ok = True
        rel = affine_from_to(ref.affine[0], ref.affine[1], aff[0], aff[1], ref.exposure, exposure)
        if (c.affine_opt_a != 0 and abs(aff[0]) > 1.2) or (c.affine_opt_b != 0 and abs(aff[1]) > 200):
            ok = False
        if not (np.isfinite(rel[0]) and rel[0] > 0 and np.isfinite(rel[1])):
            ok = False
        elif (c.affine_opt_a == 0 and not fix_a and abs(math.log(rel[0])) > 1.5) or \
                (c.affine_opt_b == 0 and not fix_b and abs(rel[1]) > 200):
            ok = False
        if not (np.all(np.isfinite(T)) and np.all(np.isfinite(aff))):
            ok = False
        return LevelsResult(ok, T, (float(aff[0]), float(aff[1])), rmse, flow, stats0, iters_total)

    def _scaled(self, s: TrackingSystem) -> tuple[np.ndarray, np.ndarray]:
        n = max(s.num_inliers, 1)
        H = s.H / n * SCALE[:, None] * SCALE[None, :]
        b = s.b / n * SCALE
        return H, b

    # ----------------------------------------------------------------------------------------- one frame
    def track_frame(self, pyramid: ImagePyramid, exposure: float, hypotheses: list[np.ndarray],
                    affine_init=(0.0, 0.0), deadline: float | None = None) -> TrackResult:
        """DSO ``trackNewCoarse``: try the ``ref_to_new`` hypotheses in order, keep the best level-0 RMSE, stop
        once it is below ``retrack_threshold`` x the last frame's. Updates ``last_rmse`` and the reference's
        ``first_rmse`` (on the first frame tracked against it).

        ``deadline`` (a ``time.perf_counter()`` value; real time only): once a hypothesis has tracked well, stop
        trying the others when the deadline has passed, even above the re-track threshold (the frames behind this
        one are waiting; the hypotheses of such a frame end within 4e-4 of each other, docs/window.md)."""
        ref = self.reference
        if ref is None:
            raise RuntimeError("CoarseTracker has no reference: set_reference first")
        if not hypotheses:
            raise ValueError("track_frame needs at least one hypothesis")
        c = self.config
        nlev = self.geometry.levels
        baseline = ref.first_rmse if ref.first_rmse > 0 else self._previous_first_rmse
        achieved = np.full(nlev, np.nan)
        have_good = False
        best: LevelsResult | None = None
        tried = 0
        iters = 0
        for T0 in hypotheses:
            res = self.track_levels(pyramid, exposure, T0, affine_init, achieved)
            tried += 1
            iters += res.iterations
            if res.ok and np.isfinite(res.rmse[0]) and not (res.rmse[0] >= achieved[0]):
                best = res
                have_good = True
            if have_good:
                for i in range(nlev):
                    if not np.isfinite(achieved[i]) or achieved[i] > res.rmse[i]:
                        achieved[i] = res.rmse[i]
            if have_good and achieved[0] < self.last_rmse[0] * c.retrack_threshold:
                break
            if have_good and deadline is not None and time.perf_counter() >= deadline:
                break
        if not have_good:
            log.info("coarse tracking failed for every hypothesis (%d tried)", tried)
            T = np.asarray(hypotheses[0], dtype=np.float64)
            self.last_rmse = achieved
            return TrackResult(False, T, tuple(affine_init), achieved, (0.0, 0.0, 0.0), tried, iters, 0, 0,
                               ref.num_points_l0, ref.keyframe_id, ref.first_rmse, baseline, T @ ref.world_to_cam)
        self.last_rmse = achieved.copy()
        if ref.first_rmse < 0:
            ref.first_rmse = float(achieved[0])
        s0 = best.stats0
        return TrackResult(True, best.ref_to_new, best.affine, achieved, best.flow, tried, iters,
                           s0.num_terms if s0 else 0, s0.num_inliers if s0 else 0, ref.num_points_l0,
                           ref.keyframe_id, ref.first_rmse, baseline, best.ref_to_new @ ref.world_to_cam)
