"""A stand-in for the sliding-window bundle adjustment: fixed-pose inverse-depth refinement and DSO's keeping of the
window (which keyframes and points leave), so that the front end runs on its own.

:class:`FixedWindowBackEnd` has the back-end interface the odometry calls on every keyframe
(:class:`mgso.odometry.WindowBackEnd`); the window engineer's joint optimisation replaces it as a whole:

1. :meth:`~FixedWindowBackEnd.flag_frames_for_marginalization` (before the new keyframe is added): DSO
   ``flagFramesForMarginalization``: keyframes with fewer than 5 % of their points left or a brightness factor to the
   newest beyond ``exp(0.7)``, while more than ``min_frames`` stay; then, if the window is full, the keyframe with the
   lowest distance score (close to the others, far from the newest).
2. :meth:`~FixedWindowBackEnd.optimize` (after the new keyframe and the activation): a few Gauss-Newton steps on
   every active point's inverse depth against the keyframes it has residuals in, **poses and affine parameters fixed**
   (each point alone: a 1x1 system), DSO's residual (window gradient weights, Huber 9) and outlier test (energy above
   the keyframes' thresholds, or too little gradient), the newest keyframe's energy threshold as DSO's
   ``setNewFrameEnergyTH``, and DSO's ``removeOutliers`` (points without an ``IN`` residual are dropped). With
   ``refine_pose`` it then moves the newest keyframe's pose (6 parameters) to fit the points hosted elsewhere.
3. :meth:`~FixedWindowBackEnd.marginalize_points`: DSO ``flagPointsForRemoval``: a point whose residual in the newest
   keyframe is OOB, whose last two residuals are outliers, or whose host leaves goes to the point cloud when it is an
   inlier (enough good residuals, enough Hessian) and is dropped otherwise.
4. :meth:`~FixedWindowBackEnd.marginalize_frames`: the flagged keyframes leave the window (no prior is kept: that is
   the window optimisation's job).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..config import TrackingConfig, WindowConfig
from ..geometry import se3_exp
from ..tracking.point_residuals import evaluate_pairs, make_pairs
from .energy import new_frame_energy_threshold
from .marginalize import flag_frames_for_marginalization, flag_points_for_removal
from .window import MarginalizedPoints, ResidualState, Window

__all__ = ["FixedWindowBackEnd", "DepthRefineResult"]

log = logging.getLogger(__name__)


@dataclass
class DepthRefineResult:
    """What one :meth:`FixedWindowBackEnd.optimize` did."""

    points: int  # active points refined
    residuals: int  # point-frame residuals evaluated in the last step
    inliers: int  # of them IN
    dropped: int  # points without any IN residual afterwards (DSO removeOutliers)
    rmse: float  # sqrt(mean energy per pattern pixel) over IN residuals
    pose_moved: float  # translation norm of the newest keyframe's pose update (refine_pose), 0 if off
    energy_th_newest: float


class FixedWindowBackEnd:
    """Fixed-pose depth refinement + DSO's window keeping (see the module text). Stateless between keyframes.

    ``config``: the window's settings (what leaves the window, the new keyframe's energy threshold; default
    :class:`~mgso.config.WindowConfig`'s); ``tracking``: the refinement's (``refine_iterations``, ``refine_pose``,
    ``refine_pose_iterations``, ``refine_affine``, ``refine_affine_iterations``) and the photometric residual's
    (``huber_th``, ``outlier_th_sum_component``, ``overall_energy_th_weight``)."""

    def __init__(self, config: WindowConfig | None = None, tracking: TrackingConfig | None = None):
        self.config = config or WindowConfig()
        self.tracking = tracking or TrackingConfig()
        self._segment_first: dict[int, int] = {}  # first keyframe id of each segment (DSO: frameID 0 stays)

    # ------------------------------------------------------------------------------- frame marginalisation
    def flag_frames_for_marginalization(self, window: Window) -> list[int]:
        """DSO ``flagFramesForMarginalization`` (called before the new keyframe is added). Returns flagged slots
        (:func:`mgso.window.marginalize.flag_frames_for_marginalization`)."""
        return flag_frames_for_marginalization(window, self.config, self._segment_first)

    def marginalize_frames(self, window: Window) -> list[int]:
        """Remove the flagged keyframes (their remaining points are dropped); returns their keyframe ids."""
        ids = []
        for slot in [o for o in window.order if window.flagged_[o]]:
            window.drop_points(window.active.host == slot)
            ids.append(int(window.keyframe_id_[slot]))
            window.remove_keyframe(slot)
        return ids

    # ------------------------------------------------------------------------------------------ optimise
    def _pairs(self, window: Window, states=(ResidualState.IN, ResidualState.OUTLIER)):
        a = window.active
        rs = a.res_state
        mask = np.isin(rs, [int(x) for x in states])
        pt, tg = np.nonzero(mask)
        return make_pairs(window, a.host, pt, tg)

    def _evaluate(self, window: Window, pairs, idepth):
        a = window.active
        t = self.tracking
        ev = evaluate_pairs(window, pairs, a.uv, a.color, a.weight, idepth, weight_mode="window",
                            huber_th=t.huber_th, grad_c2=t.outlier_th_sum_component)
        e = ev.energy
        wJI2 = np.sum(ev.huber * ev.grad_w * ev.grad_sq, axis=1)
        th = np.maximum(window.energy_th_[a.host[pairs.pt]], window.energy_th_[pairs.tg])
        state = np.where((e > th) | (wJI2 < 2), ResidualState.OUTLIER, ResidualState.IN).astype(np.uint8)
        state = np.where(ev.ok, state, ResidualState.OOB).astype(np.uint8)
        return ev, e, state

    def _set_energy_th(self, window: Window, pairs, e_with_outlier, ok) -> float:
        """DSO ``setNewFrameEnergyTH`` for the newest keyframe (:func:`~mgso.window.energy.
        new_frame_energy_threshold`, the bundle adjustment's rule)."""
        newest = window.newest_slot
        vals = e_with_outlier[(pairs.tg == newest) & ok]
        window.energy_th_[newest] = new_frame_energy_threshold(vals, self.config, self.tracking)
        return float(window.energy_th_[newest])

    def optimize(self, window: Window) -> DepthRefineResult:
        """Refine inverse depths (poses fixed), update residual states, drop points without inliers."""
        s = self.tracking
        a = window.active
        if a.n == 0 or window.num_keyframes < 2:
            return DepthRefineResult(a.n, 0, 0, 0, float("nan"), 0.0, float(window.energy_th_[window.newest_slot]))
        pairs = self._pairs(window)
        m = a.n
        idepth = a.idepth.astype(np.float64).copy()
        ev, e, state = self._evaluate(window, pairs, idepth)
        eth = self._set_energy_th(window, pairs, e, ev.ok)
        ev, e, state = self._evaluate(window, pairs, idepth)
        lam = np.full(m, 1e-2)
        for _ in range(s.refine_iterations):
            inl = (state == ResidualState.IN)[:, None]
            wgt = ev.huber * ev.grad_w * inl
            H = np.bincount(pairs.pt, weights=np.sum(wgt * ev.d_idepth ** 2, axis=1), minlength=m)
            b = np.bincount(pairs.pt, weights=np.sum(wgt * ev.r * ev.d_idepth, axis=1), minlength=m)
            E = np.bincount(pairs.pt, weights=np.where(state == ResidualState.IN, e, 0.0), minlength=m)
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(H > 0, -b / (H * (1.0 + lam)), 0.0)
            new = idepth + step
            new = np.where(new > 1e-6, new, idepth * 0.5)
            ev_n, e_n, st_n = self._evaluate(window, pairs, new)
            # compare each point's energy over the residuals that were IN before the step
            E_n = np.bincount(pairs.pt, weights=np.where(state == ResidualState.IN,
                                                         np.where(st_n == ResidualState.OOB, np.inf, e_n), 0.0),
                              minlength=m)
            acc = (E_n < E) & np.isfinite(new)
            idepth = np.where(acc, new, idepth)
            lam = np.where(acc, lam * 0.5, lam * 4.0)
            accp = acc[pairs.pt]
            ev = _select(accp, ev_n, ev)
            e = np.where(accp, e_n, e)
            state = np.where(accp, st_n, state)
        if s.refine_affine and window.num_keyframes >= 2:
            if self.refine_affine(window, pairs, idepth, state == ResidualState.IN):
                pairs = make_pairs(window, a.host, pairs.pt, pairs.tg)
                ev, e, state = self._evaluate(window, pairs, idepth)
        inl = (state == ResidualState.IN)
        wgt = ev.huber * ev.grad_w * inl[:, None]
        H = np.bincount(pairs.pt, weights=np.sum(wgt * ev.d_idepth ** 2, axis=1), minlength=m)
        a.idepth[:] = idepth
        a.idepth_hessian[:] = H
        a.res_state[pairs.pt, pairs.tg] = state
        a.res_energy[pairs.pt, pairs.tg] = e
        n_in = a.num_residuals(ResidualState.IN)
        a.num_good_residuals[:] = np.maximum(a.num_good_residuals, n_in)
        rmse = float(np.sqrt(np.sum(e[inl]) / max(8 * int(inl.sum()), 1)))
        drop = (n_in == 0) | ~(a.idepth > 0)
        dropped = window.drop_points(drop)
        moved = 0.0
        if s.refine_pose:
            moved = self.refine_newest_pose(window)
        return DepthRefineResult(m, len(pairs), int(inl.sum()), dropped, rmse, moved, eth)

    def refine_affine(self, window: Window, pairs, idepth: np.ndarray, inlier: np.ndarray) -> bool:
        """Gauss-Newton on the affine brightness ``(a, b)`` of every keyframe but the oldest (the gauge), points and
        poses fixed, over the ``inlier`` pairs. Residual pairs run in both directions between keyframes, so a bias
        of the tracker's brightness estimate (bilinear sampling lowers the target's contrast a little) cancels
        instead of adding up from keyframe to keyframe. Returns whether the affine parameters changed."""
        s = self.tracking
        a = window.active
        order = list(window.order)
        nk = len(order)
        col = {slot: i for i, slot in enumerate(order)}
        sel = np.flatnonzero(inlier)
        if len(sel) < 10:
            return False
        pt, tg = pairs.pt[sel], pairs.tg[sel]
        hosts = a.host[pt]
        hi = np.array([col[int(h)] for h in hosts])
        ti = np.array([col[int(t)] for t in tg])
        sub = type(pairs)(pt, tg, pairs.R[sel], pairs.t[sel], pairs.aff[sel])

        def rel_affine():
            """(a_rel, b_rel) per pair, from the window's current affine parameters."""
            key = hosts * 64 + tg
            out = np.zeros((len(key), 2))
            for k in np.unique(key):
                out[key == k] = window.affine_rel(int(k // 64), int(k % 64))
            return out

        def energy_and_system():
            ev = evaluate_pairs(window, sub, a.uv, a.color, a.weight, idepth, weight_mode="window",
                                huber_th=s.huber_th, grad_c2=s.outlier_th_sum_component)
            a_rel = sub.aff[:, 0:1]
            ih = a.color[pt] - window.affine_[hosts, 1][:, None]
            W = ev.huber * ev.grad_w * ev.ok[:, None]
            # per pair sums of the 2x2 products; d r/d(a_t, b_t) = (-a_rel ih, -1), d r/d(a_h, b_h) = (a_rel ih, a_rel)
            s_ii = np.sum(W * ih * ih, axis=1) * a_rel[:, 0] ** 2
            s_i1 = np.sum(W * ih, axis=1) * a_rel[:, 0]
            s_11 = np.sum(W, axis=1)
            g_i = np.sum(W * ih * ev.r, axis=1) * a_rel[:, 0]
            g_1 = np.sum(W * ev.r, axis=1)
            A = a_rel[:, 0]
            # blocks per pair: tt, hh, th (target-host)
            tt = np.stack([s_ii, s_i1, s_i1, s_11], axis=1).reshape(-1, 2, 2)
            hh = np.stack([s_ii, A * s_i1, A * s_i1, A * A * s_11], axis=1).reshape(-1, 2, 2)
            th = -np.stack([s_ii, A * s_i1, s_i1, A * s_11], axis=1).reshape(-1, 2, 2)
            gt = -np.stack([g_i, g_1], axis=1)
            gh = np.stack([g_i, A * g_1], axis=1)
            H = np.zeros((nk, nk, 2, 2))
            g = np.zeros((nk, 2))
            np.add.at(H, (ti, ti), tt)
            np.add.at(H, (hi, hi), hh)
            np.add.at(H, (ti, hi), th)
            np.add.at(H, (hi, ti), np.swapaxes(th, 1, 2))
            np.add.at(g, ti, gt)
            np.add.at(g, hi, gh)
            return float(np.sum(ev.energy)), H.transpose(0, 2, 1, 3).reshape(2 * nk, 2 * nk), g.reshape(-1)

        E, H, g = energy_and_system()
        start = window.affine_[order].copy()
        lam = 1e-3
        changed = False
        for _ in range(s.refine_affine_iterations):
            Hr, gr = H[2:, 2:], g[2:]  # the oldest keyframe fixes the gauge
            Hl = Hr + lam * np.diag(np.diag(Hr)) + 1e-6 * np.eye(len(gr))
            try:
                inc = np.linalg.solve(Hl, -gr)
            except np.linalg.LinAlgError:
                break
            if not np.all(np.isfinite(inc)):
                break
            old = window.affine_[order].copy()
            window.affine_[order[1:]] += inc.reshape(-1, 2)
            sub.aff[:] = rel_affine()
            E_n, H_n, g_n = energy_and_system()
            if E_n < E:
                E, H, g = E_n, H_n, g_n
                lam *= 0.5
                changed = True
            else:
                window.affine_[order] = old
                sub.aff[:] = rel_affine()
                lam *= 4.0
        if not changed:
            window.affine_[order] = start
        return changed

    def refine_newest_pose(self, window: Window) -> float:
        """Gauss-Newton on the newest keyframe's pose (left perturbation of its ``world_to_cam``) against the IN
        residuals of points hosted elsewhere, depths fixed; a step is kept only if the energy goes down."""
        s = self.tracking
        a = window.active
        newest = window.newest_slot
        sel = np.flatnonzero((a.res_state[:, newest] == ResidualState.IN) & (a.host != newest))
        if len(sel) < 20:
            return 0.0
        cam = window.camera
        T0 = window.world_to_cam_[newest].copy()
        moved = 0.0

        def energy_and_system():
            pairs = make_pairs(window, a.host, sel, np.full(len(sel), newest))
            ev = evaluate_pairs(window, pairs, a.uv, a.color, a.weight, a.idepth, weight_mode="window",
                                huber_th=s.huber_th, grad_c2=s.outlier_th_sum_component)
            return pairs, ev

        pairs, ev = energy_and_system()
        E = float(np.sum(ev.energy))
        lam = 1e-3
        for _ in range(s.refine_pose_iterations):
            # per pattern pixel pose Jacobian through the centre projection (DSO's window approximation)
            ku, kv, nid = ev.centre[:, 0], ev.centre[:, 1], ev.centre[:, 2]
            un = (ku - cam.cx) / cam.fx
            vn = (kv - cam.cy) / cam.fy
            gx, gy = _target_gradients(window, newest, pairs, a.uv, a.idepth)
            dx, dy = gx * cam.fx, gy * cam.fy
            J = np.stack([nid[:, None] * dx, nid[:, None] * dy, -nid[:, None] * (un[:, None] * dx + vn[:, None] * dy),
                          -(un * vn)[:, None] * dx - (1 + vn * vn)[:, None] * dy,
                          (1 + un * un)[:, None] * dx + (un * vn)[:, None] * dy,
                          un[:, None] * dy - vn[:, None] * dx], axis=-1)  # [M, 8, 6]
            w = (ev.huber * ev.grad_w * ev.ok[:, None])[..., None]
            H = np.einsum("mki,mkj->ij", J * w, J)
            b = np.einsum("mki,mk->i", J * w, ev.r)
            if not np.all(np.isfinite(H)):
                break
            Hl = H + lam * np.diag(np.diag(H))
            try:
                inc = np.linalg.solve(Hl, -b)
            except np.linalg.LinAlgError:
                break
            T_new = se3_exp(inc) @ window.world_to_cam_[newest]
            old = window.world_to_cam_[newest].copy()
            window.set_keyframe_state(newest, T_new)
            pairs_n, ev_n = energy_and_system()
            E_n = float(np.sum(np.where(ev_n.ok, ev_n.energy, np.inf)))
            if E_n < E:
                pairs, ev, E = pairs_n, ev_n, E_n
                lam *= 0.5
            else:
                window.set_keyframe_state(newest, old)
                lam *= 4.0
            if np.linalg.norm(inc) < 1e-6:
                break
        T = window.world_to_cam_[newest]
        moved = float(np.linalg.norm((T @ np.linalg.inv(T0))[:3, 3]))
        window.set_linearization_point(newest)
        return moved

    # ------------------------------------------------------------------------------- point marginalisation
    def marginalize_points(self, window: Window) -> MarginalizedPoints:
        """DSO ``flagPointsForRemoval`` + ``dropPointsF``/``marginalizePointsF`` (without the prior): flag and remove
        points; inliers go to the point cloud (:func:`mgso.window.marginalize.flag_points_for_removal`)."""
        flag_points_for_removal(window, self.config)
        return window.remove_flagged_points()


def _select(mask: np.ndarray, new, old):
    """Per pair: fields of ``new`` where ``mask`` else ``old`` (PairResiduals)."""
    from ..tracking.point_residuals import PairResiduals

    def pick(x, y):
        m = mask.reshape((-1,) + (1,) * (x.ndim - 1))
        return np.where(m, x, y)

    return PairResiduals(*(pick(getattr(new, f), getattr(old, f)) for f in
                           ("ok", "r", "huber", "grad_w", "d_idepth", "grad_sq", "centre")))


def _target_gradients(window: Window, target: int, pairs, uv, idepth):
    """``(gx, gy) [M, 8]`` image gradients of the target at each pattern pixel's projection."""
    from mgso_kernels.photometric import PATTERN_NP

    from ..tracking.sampling import sample_dI
    cam = window.camera
    pt = pairs.pt
    px = uv[pt, 0][:, None].astype(np.float64) + PATTERN_NP[None, :, 0]
    py = uv[pt, 1][:, None].astype(np.float64) + PATTERN_NP[None, :, 1]
    hx = (px - cam.cx) / cam.fx
    hy = (py - cam.cy) / cam.fy
    idp = np.asarray(idepth, np.float64)[pt][:, None]
    R, t = pairs.R, pairs.t
    P = [R[:, None, i, 0] * hx + R[:, None, i, 1] * hy + R[:, None, i, 2] + t[:, None, i] * idp for i in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        ku = cam.fx * P[0] / P[2] + cam.cx
        kv = cam.fy * P[1] / P[2] + cam.cy
    s = sample_dI(window.pyramids[target].numpy(0), ku.astype(np.float32), kv.astype(np.float32))
    return np.nan_to_num(s[..., 1]), np.nan_to_num(s[..., 2])
