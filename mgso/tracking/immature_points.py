"""Immature points: created on each new keyframe, traced on every frame, activated when their depth is known well
enough (DSO ``FullSystem::makeNewTraces``, ``traceNewCoarse``, ``activatePointsMT``, ``optimizeImmaturePoint``).

- :func:`make_immature_points`: the pixel selector's choice in the new keyframe (``tracking.immature_density``), each
  with its host pattern (intensity, gradient weights, gradient matrix; ``photometric.extract_patterns``).
- :func:`trace_immature_points`: one launch of the epipolar search (``mgso_kernels.trace``) over the immature points
  of every host keyframe in a new frame.
- :class:`PointActivator`: DSO's activation. The distance to the nearest active point in the newest keyframe (level
  1) decides which candidates are activated so that the active set stays spread (a candidate needs
  ``distance >= min_act_dist * type``; ``min_act_dist`` adapts to keep about ``tracking.point_density`` active
  points). Candidates get their inverse depth by :func:`optimize_inverse_depths` (DSO ``optimizeImmaturePoint``:
  a few Gauss-Newton steps on the depth against every other window keyframe, vectorised over points).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from mgso_kernels.activation import DISTANCE_STEPS, make_depth_params, pick_spaced, point_depth_residuals
from mgso_kernels.activation import distance_map as _distance_map
from mgso_kernels.photometric import affine_from_to, extract_patterns
from mgso_kernels.trace import TraceParams, TraceStatus, host_target_projection, make_trace_params, trace_points

from ..config import TrackingConfig
from ..window.window import ResidualState, Window
from .pixel_selector import PixelSelector

__all__ = [
    "make_immature_points", "trace_immature_points", "TraceCounts", "PointActivator", "ActivationResult",
    "optimize_inverse_depths", "DepthOptimization", "distance_map", "distance_stamp", "trace_params_from_config",
]

log = logging.getLogger(__name__)


def trace_params_from_config(width: int, height: int, cfg: TrackingConfig, seed: int = 0) -> TraceParams:
    return make_trace_params(
        width, height, huber_th=cfg.huber_th, step_size=cfg.trace_stepsize, max_pix_search=cfg.max_pix_search,
        min_test_radius=cfg.min_trace_test_radius, gn_iterations=cfg.trace_gn_iterations,
        gn_threshold=cfg.trace_gn_threshold, extra_slack_on_th=cfg.trace_extra_slack_on_th,
        slack_interval=cfg.trace_slack_interval, min_improvement_factor=cfg.trace_min_improvement_factor,
        outlier_th=cfg.outlier_th, overall_energy_th_weight=cfg.overall_energy_th_weight, seed=seed)


# ------------------------------------------------------------------------------------------------- creation
def make_immature_points(window: Window, slot: int, selector: PixelSelector, density: float,
                         grad_c2: float = 2500.0, recursions: int = 1) -> int:
    """Select pixels in keyframe ``slot`` and add them as immature points; returns how many were added (cut to the
    buffer's free capacity, evenly over the selection, with a warning)."""
    pyr = window.pyramids[slot]
    levels = [pyr.numpy(lvl) for lvl in range(min(3, pyr.levels))]
    grad_sq = [pyr.grad_sq[lvl].numpy() for lvl in range(min(3, pyr.levels))]
    if len(levels) < 3:  # the selector looks at three levels; repeat the coarsest when the pyramid is shallower
        levels += [levels[-1]] * (3 - len(levels))
        grad_sq += [grad_sq[-1]] * (3 - len(grad_sq))
    sel = selector.select(levels, density, recursions_left=recursions, grad_sq=grad_sq)
    xy = sel.xy
    if len(xy) == 0:
        return 0
    pat = extract_patterns(pyr.dI[0], xy.astype(np.float32), grad_c2=grad_c2)
    keep = pat.valid & np.all(np.isfinite(pat.color), axis=1)
    xy, typ = xy[keep], sel.dso_type[keep]
    color, weight, grad_h = pat.color[keep], pat.weight[keep], pat.grad_h[keep]
    free = window.immature.free
    if len(xy) > free:
        log.warning("immature-point buffer full: keeping %d of %d new points (raise window.immature_capacity)",
                    free, len(xy))
        pick = np.linspace(0, len(xy) - 1, free).astype(np.int64) if free else np.zeros(0, np.int64)
        xy, typ, color, weight, grad_h = xy[pick], typ[pick], color[pick], weight[pick], grad_h[pick]
    m = len(xy)
    window.immature.append(m, host=slot, uv=xy.astype(np.float32), type=typ, color=color, weight=weight,
                           grad_h=grad_h)
    return m


# ---------------------------------------------------------------------------------------------------- trace
@dataclass(frozen=True)
class TraceCounts:
    """How the last trace went, per :class:`~mgso_kernels.trace.TraceStatus` (DSO's trace statistics)."""

    total: int
    good: int
    oob: int
    outlier: int
    skipped: int
    badcondition: int
    uninitialized: int


def trace_immature_points(window: Window, pyramid, world_to_cam: np.ndarray, affine, exposure: float,
                          params: TraceParams) -> TraceCounts:
    """DSO ``traceNewCoarse``: trace every immature point of the window in a new frame (level 0 of ``pyramid``),
    all hosts in one launch. Updates the immature points' interval, quality, status and trace results in place."""
    im = window.immature
    n = im.n
    if n == 0 or not window.order:
        return TraceCounts(0, 0, 0, 0, 0, 0, 0)
    slots = list(window.order)
    lookup = np.full(window.capacity, -1, np.int32)
    lookup[slots] = np.arange(len(slots), dtype=np.int32)
    T = np.stack([np.asarray(world_to_cam) @ window.cam_to_world(s) for s in slots])
    KRKi, Kt = host_target_projection(window.K(0), T)
    aff = np.array([affine_from_to(window.affine_[s, 0], window.affine_[s, 1], affine[0], affine[1],
                                   window.exposure_[s], exposure) for s in slots], dtype=np.float32)
    host_index = lookup[im.host]
    if np.any(host_index < 0):
        raise RuntimeError("an immature point's host is not in the window")
    dev = window.device
    im.to_device("uv", "color", "weight", "grad_h", "idepth_min", "idepth_max", "quality", "status")
    trace_points(pyramid.dI[0], im.warp("uv"), wp.array(host_index, dtype=wp.int32, device=dev),
                 im.warp("color"), im.warp("weight"), im.warp("grad_h"),
                 wp.array(KRKi, dtype=wp.mat33, device=dev), wp.array(Kt, dtype=wp.vec3, device=dev),
                 wp.array(aff, dtype=wp.vec2, device=dev), params,
                 im.warp("idepth_min"), im.warp("idepth_max"), im.warp("quality"), im.warp("status"),
                 im.warp("trace_uv"), im.warp("pixel_interval"), im.warp("energy"), device=dev)
    im.from_device("idepth_min", "idepth_max", "quality", "status", "trace_uv", "pixel_interval", "energy")
    st = np.bincount(im.status, minlength=6)
    return TraceCounts(n, int(st[TraceStatus.GOOD]), int(st[TraceStatus.OOB]), int(st[TraceStatus.OUTLIER]),
                       int(st[TraceStatus.SKIPPED]), int(st[TraceStatus.BADCONDITION]),
                       int(st[TraceStatus.UNINITIALIZED]))


# ------------------------------------------------------------------------------------------- distance map
MAX_BFS_STEPS = DISTANCE_STEPS  # DSO growDistBFS: k < 40; unreached pixels stay at 1000


def distance_map(seeds: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """DSO ``CoarseDistanceMap::makeDistanceMap``: ``[h, w]`` float32 breadth-first steps to the nearest seed
    (``seeds [N, 2]`` integer ``(x, y)``): :func:`mgso_kernels.activation.distance_map` (DSO's ``growDistBFS``, one
    thread on the CPU)."""
    return _distance_map(seeds, shape, MAX_BFS_STEPS)


def distance_stamp(radius: int) -> np.ndarray:
    """``[2r+1, 2r+1]`` distances of :func:`distance_map` from a single seed at the centre (for incremental
    updates when a point is activated: ``dmap = min(dmap, stamp)`` around it)."""
    size = 2 * radius + 1
    return distance_map(np.array([[radius, radius]]), (size, size))


# ---------------------------------------------------------------------------------------------- activation
@dataclass
class DepthOptimization:
    """Result of :func:`optimize_inverse_depths` for ``m`` candidate points against ``T`` targets."""

    status: np.ndarray  # [m] int8: 1 activate, 0 not constrained enough (stay immature), -1 delete (outlier/NaN)
    idepth: np.ndarray  # [m] float32
    hessian: np.ndarray  # [m] float32 sum of w J_d^2 over the IN residuals (DSO lastHdd)
    res_state: np.ndarray  # [m, slots] uint8 ResidualState of each target (NONE for the host / non-window slots)
    res_energy: np.ndarray  # [m, slots] float32


def optimize_inverse_depths(window: Window, hosts: np.ndarray, uv: np.ndarray, color: np.ndarray,
                            weight: np.ndarray, idepth0: np.ndarray, cfg: TrackingConfig,
                            min_obs: int = 1) -> DepthOptimization:
    """DSO ``optimizeImmaturePoint`` for ``m`` points at once: Gauss-Newton (Levenberg-damped) on each point's inverse
    depth against every window keyframe but its host. Residuals as DSO's immature points (``ImmaturePoint::
    linearizeResidual``): host gradient weights squared, Huber 9, a pair's energy capped at ``8 outlier_th`` (times
    1000 on the first evaluation) and then ``OUTLIER``; a pair that leaves the image is ``OOB`` for good.

    ``status``: 1 when the point ends with a finite depth, ``H_dd >= min_idepth_h_act`` and at least ``min_obs``
    ``IN`` residuals; 0 when it was not constrained enough (it stays immature, DSO returns 0); -1 otherwise (DSO
    deletes it)."""
    m = len(hosts)
    K = window.capacity
    res_state = np.zeros((m, K), np.uint8)
    res_energy = np.zeros((m, K), np.float32)
    status = np.zeros(m, np.int8)
    if m == 0:
        return DepthOptimization(status, np.zeros(0, np.float32), np.zeros(0, np.float32), res_state, res_energy)
    hosts = np.asarray(hosts)
    pt = np.concatenate([np.flatnonzero(hosts != s) for s in window.order])
    tg = np.concatenate([np.full(int(np.sum(hosts != s)), s, np.int64) for s in window.order])
    # keys: the (host, target) keyframe pairs, with target_from_host and the relative brightness
    K = window.capacity
    code = hosts[pt].astype(np.int64) * K + tg
    key_codes, pair_key = np.unique(code, return_inverse=True)
    key_h, key_t = key_codes // K, key_codes % K
    Ts = [window.target_from_host(int(h), int(t)) for h, t in zip(key_h, key_t)]
    key_aff = np.array([window.affine_rel(int(h), int(t)) for h, t in zip(key_h, key_t)]).reshape(-1, 2)
    dev = window.device
    g = window.camera
    params = make_depth_params(g.fx, g.fy, g.cx, g.cy, window.width, window.height, huber_th=cfg.huber_th)
    key_args = (key_t.astype(np.int32), np.array([T[:3, :3] for T in Ts]).reshape(-1, 3, 3),
                np.array([T[:3, 3] for T in Ts]).reshape(-1, 3), key_aff)
    pts = (wp.array(np.ascontiguousarray(uv, np.float32), dtype=wp.vec2, device=dev),
           wp.array(np.ascontiguousarray(color, np.float32), dtype=wp.float32, device=dev),
           wp.array(np.ascontiguousarray(weight, np.float32), dtype=wp.float32, device=dev))
    energy_th = 8 * cfg.outlier_th * cfg.overall_energy_th_weight ** 2
    cur = np.asarray(idepth0, dtype=np.float64).copy()

    def lin(idp, slack, prev_state, prev_e):
        ev = point_depth_residuals(params, *key_args, pt, pair_key, pts[0], idp, pts[1], pts[2], window.dI0_,
                                   device=dev)
        e = ev.energy.astype(np.float64)
        Hdd = ev.hdd.astype(np.float64)
        bd = ev.bd.astype(np.float64)
        th = energy_th * slack
        state = np.where(e > th, ResidualState.OUTLIER, ResidualState.IN).astype(np.uint8)
        e = np.minimum(e, th)
        oob = ~ev.ok | (prev_state == ResidualState.OOB)
        state = np.where(oob, ResidualState.OOB, state).astype(np.uint8)
        e = np.where(oob, prev_e, e)
        Hdd = np.where(oob, 0.0, Hdd)
        bd = np.where(oob, 0.0, bd)
        return (e, state, np.bincount(pt, weights=e, minlength=m), np.bincount(pt, weights=Hdd, minlength=m),
                np.bincount(pt, weights=bd, minlength=m))

    e_pair, state, E, Hdd, bd = lin(cur, 1000.0, np.full(len(pt), ResidualState.IN, np.uint8), np.zeros(len(pt)))
    ok = np.isfinite(E) & (Hdd >= cfg.min_idepth_h_act)
    running = ok.copy()
    lam = np.full(m, 0.1)
    for _ in range(cfg.activation_gn_iterations):
        if not running.any():
            break
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(running, bd / (Hdd * (1.0 + lam)), 0.0)
        new = cur - step
        e_new, st_new, E_new, H_new, b_new = lin(new, 1.0, state, e_pair)
        bad = running & ~(H_new >= cfg.min_idepth_h_act)
        ok &= ~bad
        running &= ~bad
        acc = running & (E_new < E)
        cur = np.where(acc, new, cur)
        Hdd = np.where(acc, H_new, Hdd)
        bd = np.where(acc, b_new, bd)
        E = np.where(acc, E_new, E)
        acc_pair = acc[pt]
        state = np.where(acc_pair, st_new, state)
        e_pair = np.where(acc_pair, e_new, e_pair)
        lam = np.where(acc, lam * 0.5, np.where(running, lam * 5.0, lam))
        running &= ~(np.abs(step) < 1e-4 * np.abs(cur))
    n_in = np.bincount(pt, weights=(state == ResidualState.IN).astype(np.float64), minlength=m)
    good = ok & np.isfinite(cur) & (n_in >= min_obs)
    status[good] = 1
    status[ok & ~good] = -1
    res_state[pt, tg] = np.where(state == ResidualState.IN, ResidualState.IN, ResidualState.NONE)
    res_energy[pt, tg] = e_pair
    res_state[~good] = ResidualState.NONE
    return DepthOptimization(status, cur.astype(np.float32), Hdd.astype(np.float32), res_state, res_energy)


@dataclass
class ActivationResult:
    candidates: int  # immature points that passed the trace criteria and the distance rule
    activated: int
    deleted: int  # immature points removed (never traced well, outliers, OOB, out of view)
    min_act_dist: float  # the distance used (DSO currentMinActDist)
    active_before: int


@dataclass
class PointActivator:
    """DSO's point activation with its adaptive spacing (``currentMinActDist``, carried from keyframe to keyframe).
    Owner: the odometry (one per run)."""

    config: TrackingConfig
    min_act_dist: float = 2.0  # DSO FullSystem constructor: currentMinActDist = 2
    _stamp: np.ndarray = field(default_factory=lambda: distance_stamp(17))

    def adapt(self, num_active: int) -> float:
        """DSO's update of ``currentMinActDist`` from the active point count."""
        d = self.config.point_density
        n = num_active
        if n < d * 0.66:
            self.min_act_dist -= 0.8
        if n < d * 0.8:
            self.min_act_dist -= 0.5
        elif n < d * 0.9:
            self.min_act_dist -= 0.2
        elif n < d:
            self.min_act_dist -= 0.1
        if n > d * 1.5:
            self.min_act_dist += 0.8
        if n > d * 1.3:
            self.min_act_dist += 0.5
        if n > d * 1.15:
            self.min_act_dist += 0.2
        if n > d:
            self.min_act_dist += 0.1
        self.min_act_dist = float(min(max(self.min_act_dist, 0.0), 4.0))
        return self.min_act_dist

    def activate(self, window: Window) -> ActivationResult:
        """DSO ``activatePointsMT`` on the window (its newest keyframe is the one just added)."""
        cfg = self.config
        a, im = window.active, window.immature
        n_before = a.n
        dist_th = self.adapt(a.n)
        newest = window.newest_slot
        g = window.geometry
        w1, h1 = g.level_size(1) if g.levels > 1 else g.level_size(0)
        lvl = 1 if g.levels > 1 else 0
        K1 = window.K(lvl)
        Ki0 = np.linalg.inv(window.K(0))
        # distance map at level 1 of the newest keyframe from the active points of the other keyframes
        seeds = []
        for hs in window.order:
            if hs == newest:
                continue
            idx = np.flatnonzero(a.host == hs)
            if not len(idx):
                continue
            T = window.target_from_host(hs, newest)
            p = self._project(a.uv[idx], a.idepth[idx], K1 @ T[:3, :3] @ Ki0, K1 @ T[:3, 3])
            u = np.floor(p[:, 0] / p[:, 2] + 0.5)
            v = np.floor(p[:, 1] / p[:, 2] + 0.5)
            good = np.isfinite(u) & np.isfinite(v) & (u > 0) & (v > 0) & (u < w1) & (v < h1)
            seeds.append(np.stack([u[good], v[good]], axis=1).astype(np.int64))
        dmap = distance_map(np.concatenate(seeds) if seeds else np.zeros((0, 2), np.int64), (h1, w1))
        # candidates, in DSO's order (hosts oldest first, points in storage order)
        n = im.n
        delete = np.zeros(n, bool)
        cand = []
        st = im.status
        finite_max = np.isfinite(im.idepth_max)
        delete |= ~finite_max | (st == TraceStatus.OUTLIER)
        can = (np.isin(st, (TraceStatus.GOOD, TraceStatus.SKIPPED, TraceStatus.BADCONDITION, TraceStatus.OOB))
               & (im.pixel_interval < cfg.activation_max_pixel_interval) & (im.quality > cfg.min_trace_quality)
               & ((im.idepth_max + im.idepth_min) > 0) & ~delete)
        flagged_host = window.flagged_[im.host]
        delete |= ~can & ~delete & (flagged_host | (st == TraceStatus.OOB))
        for hs in window.order:
            if hs == newest:
                continue
            idx = np.flatnonzero((im.host == hs) & can)
            if not len(idx):
                continue
            T = window.target_from_host(hs, newest)
            p = self._project(im.uv[idx], im.idepth_mid[idx], K1 @ T[:3, :3] @ Ki0, K1 @ T[:3, 3])
            with np.errstate(divide="ignore", invalid="ignore"):
                uf = p[:, 0] / p[:, 2] + 0.5
                vf = p[:, 1] / p[:, 2] + 0.5
            fin = np.isfinite(uf) & np.isfinite(vf)
            u = np.where(fin, np.floor(np.where(fin, uf, 0)), -1).astype(np.int64)
            v = np.where(fin, np.floor(np.where(fin, vf, 0)), -1).astype(np.int64)
            frac = p[:, 0] - np.floor(p[:, 0])  # DSO's jitter: the fractional part of the homogeneous x
            typ = im.type[idx]
            inside = (u > 0) & (u < w1) & (v > 0) & (v < h1)
            delete[idx[~inside]] = True
            # in order, each taken when far enough from those taken before it (the map lowered around each)
            taken = pick_spaced(np.where(inside, u, -1), v, frac, dist_th * typ.astype(np.float64), self._stamp, dmap)
            cand.extend(idx[taken].tolist())
        cand = np.asarray(cand, dtype=np.int64)
        activated = 0
        if len(cand):
            free = a.free
            if len(cand) > free:
                log.warning("active-point buffer full: activating %d of %d candidates (raise window.point_capacity)",
                            free, len(cand))
                cand = cand[:free]
            opt = optimize_inverse_depths(window, im.host[cand], im.uv[cand], im.color[cand], im.weight[cand],
                                          im.idepth_mid[cand], cfg)
            good = opt.status == 1
            if good.any():
                gi = cand[good]
                window.add_active_points(host=im.host[gi], uv=im.uv[gi], idepth=opt.idepth[good],
                                         color=im.color[gi], weight=im.weight[gi], type=im.type[gi],
                                         res_state=opt.res_state[good], idepth_hessian=opt.hessian[good])
                a.res_energy[a.n - int(good.sum()):] = opt.res_energy[good]
                activated = int(good.sum())
            delete[cand[good]] = True
            delete[cand[(opt.status == -1)]] = True
            delete[cand[im.status[cand] == TraceStatus.OOB]] = True
        n_del = int(delete.sum())
        im.keep(~delete)
        return ActivationResult(len(cand), activated, n_del - activated, dist_th, n_before)

    @staticmethod
    def _project(uv: np.ndarray, idepth: np.ndarray, M: np.ndarray, kt: np.ndarray) -> np.ndarray:
        h = np.stack([uv[:, 0], uv[:, 1], np.ones(len(uv))], axis=1).astype(np.float64)
        return h @ M.T + kt[None] * idepth.astype(np.float64)[:, None]
