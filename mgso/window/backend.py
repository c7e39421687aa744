"""DSO's back end: sliding-window photometric bundle adjustment with marginalisation (:class:`WindowOptimizer`).

The odometry (:class:`mgso.odometry.Odometry`) calls it on every keyframe, in DSO's order:

1. :meth:`~WindowOptimizer.flag_frames_for_marginalization` before the new keyframe is added
   (:func:`~mgso.window.marginalize.flag_frames_for_marginalization`).
2. :meth:`~WindowOptimizer.optimize` after the new keyframe and the point activation: the new keyframe's energy
   threshold (DSO ``setNewFrameEnergyTH``), then Levenberg-Marquardt on all keyframes' poses and affine brightness and
   all active points' inverse depths (:func:`~mgso.window.energy.optimize_window`), the residual states written back
   (``IN``/``OOB``/``OUTLIER``), points without an ``IN`` residual dropped (DSO ``removeOutliers``), and the newest
   keyframe's linearisation point moved to its optimised state (DSO ``setEvalPT`` after ``optimize``). The odometry
   then builds the next tracking reference from the optimised window.
3. :meth:`~WindowOptimizer.marginalize_points`: DSO ``flagPointsForRemoval``; the points to marginalise are folded
   into the prior (Schur complement of their inverse depth, first-estimate Jacobians, gradient at the linearisation
   point, ``setting_margWeightFac``) and go to the point cloud; the others are dropped.
4. :meth:`~WindowOptimizer.marginalize_frames`: each flagged keyframe's 8 parameters are marginalised out of the
   prior (with its own gauge prior when it is the segment's first keyframe), then it leaves the window.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from mgso_kernels import window as kw

from ..config import TrackingConfig, WindowConfig
from .energy import WindowProblem, new_frame_energy_threshold, optimize_window
from .marginalize import MarginalizationPrior, flag_frames_for_marginalization, flag_points_for_removal
from .window import MarginalizedPoints, PointFlag, ResidualState, Window

__all__ = ["WindowOptimizer", "OptimizeResult"]

log = logging.getLogger(__name__)


@dataclass
class OptimizeResult:
    """What one :meth:`WindowOptimizer.optimize` did (the ``opt`` field of ``WindowUpdate``)."""

    points: int  # active points optimised
    residuals: int  # candidate (point, keyframe) residuals
    inliers: int  # of them IN after the optimisation
    dropped: int  # points without an IN residual afterwards
    rmse: float  # sqrt(energy per pattern pixel) over IN residuals at the end
    iterations: int
    accepted: int
    energy_start: float
    energy_end: float
    energy_th_newest: float
    times_ms: dict = field(default_factory=dict)


class WindowOptimizer:
    """The joint window optimisation with a marginalisation prior (see the module text).

    ``config``: the window's settings (solver, priors, what leaves the window; default :class:`~mgso.config.
    WindowConfig`'s); ``tracking``: the photometric residual's (``huber_th``, ``outlier_th_sum_component``,
    ``overall_energy_th_weight``). Holds the prior (``H_M``, ``b_M``) and the first keyframe of each segment between
    keyframes; everything else lives in the window.
    """

    def __init__(self, config: WindowConfig | None = None, tracking: TrackingConfig | None = None,
                 device: str | None = None):
        self.config = config or WindowConfig()
        self.tracking = tracking or TrackingConfig()
        self.device = device
        self.prior: MarginalizationPrior | None = None
        self._segment_first: dict[int, int] = {}
        self.last_times_ms: dict = {}

    def _prior_for(self, window: Window) -> MarginalizationPrior:
        if self.prior is None or self.prior.num_slots != window.capacity:
            self.prior = MarginalizationPrior(window.capacity)
        self.prior.sync(window)
        return self.prior

    def _first_slots(self, window: Window) -> tuple:
        out = []
        for s in window.order:
            seg = int(window.segment_[s])
            first = self._segment_first.setdefault(seg, min(int(window.keyframe_id_[o]) for o in window.order
                                                             if int(window.segment_[o]) == seg))
            if int(window.keyframe_id_[s]) == first:
                out.append(s)
        return tuple(out)

    # --------------------------------------------------------------------------------------- interface
    def flag_frames_for_marginalization(self, window: Window) -> list[int]:
        return flag_frames_for_marginalization(window, self.config, self._segment_first)

    def optimize(self, window: Window) -> OptimizeResult:
        s = self.config
        a = window.active
        times: dict = {}
        if a.n == 0 or window.num_keyframes < 2:
            return OptimizeResult(a.n, 0, 0, 0, float("nan"), 0, 0, 0.0, 0.0,
                                  float(window.energy_th_[window.newest_slot]) if window.order else 0.0)
        prior = self._prior_for(window)
        first = self._first_slots(window)
        problem = WindowProblem(window, s, prior, tracking=self.tracking, first_slots=first, device=self.device)
        newest = window.newest_slot
        # DSO setNewFrameEnergyTH: from the new keyframe's residuals before any is judged
        t0 = time.perf_counter()
        keys = problem.keys()
        keys.energy_th[keys.target == newest] = np.inf
        into = np.flatnonzero(keys.target[problem.pair_key] == newest)  # only the residuals into the new keyframe
        pts = problem.points
        lin0 = kw.linearize_window(problem.params, keys, problem.pair_point[into], problem.pair_key[into],
                                   a.uv[pts], a.idepth[pts], a.color[pts], a.weight[pts], problem.images,
                                   device=problem.device)
        times["threshold"] = (time.perf_counter() - t0) * 1000
        window.energy_th_[newest] = new_frame_energy_threshold(lin0.energy[lin0.state == ResidualState.IN], s,
                                                               self.tracking)
        L, stats = optimize_window(problem, s, times)
        # write the residual states back
        lin = L.pairs
        pts = problem.points[problem.pair_point]
        tg = problem.pair_target
        a.res_state[pts, tg] = lin.state.astype(np.uint8)
        a.res_energy[pts, tg] = lin.energy.astype(np.float32)
        inl = lin.state == ResidualState.IN
        hdd = np.bincount(problem.pair_point[inl], weights=lin.hdd[inl], minlength=len(problem.points))
        a.idepth_hessian[problem.points] = hdd
        n_in = a.num_residuals(ResidualState.IN)
        a.num_good_residuals[:] = np.maximum(a.num_good_residuals, n_in)
        drop = (n_in == 0) | ~(a.idepth > 0) | ~np.isfinite(a.idepth)
        rmse = float(np.sqrt(np.sum(lin.energy[inl]) / max(8 * int(inl.sum()), 1)))
        dropped = window.drop_points(drop)
        window.set_linearization_point(newest)
        self.last_times_ms = times
        return OptimizeResult(len(problem.points), len(problem.pair_point), int(inl.sum()), dropped, rmse,
                              stats.iterations, stats.accepted, stats.energy_start, stats.energy_end,
                              float(window.energy_th_[newest]), times)

    def marginalize_points(self, window: Window) -> MarginalizedPoints:
        flag = flag_points_for_removal(window, self.config)
        marg = np.flatnonzero(flag == PointFlag.MARGINALIZE)
        if len(marg) and window.num_keyframes >= 2:
            t0 = time.perf_counter()
            self.fold_points(window, marg)
            self.last_times_ms["marginalize_points"] = (time.perf_counter() - t0) * 1000
        return window.remove_flagged_points()

    def fold_points(self, window: Window, points: np.ndarray) -> None:
        """Fold the active points ``points`` (their IN residuals) into the prior by a Schur complement of their
        inverse depths, at the current state, with the gradient taken back to the linearisation point."""
        s = self.config
        prior = self._prior_for(window)
        problem = WindowProblem(window, s, None, tracking=self.tracking, points=points, first_slots=(),
                                device=self.device)
        if not len(problem.pair_point):
            return
        keys = problem.keys()
        lin = problem.linearize_pairs(keys)
        eh, eb = problem.point_extras()
        # DSO marginalizePointsF: an initialiser point's depth prior is multiplied by setting_idepthFixPriorMargFac as
        # it is folded, so that its residuals enter the prior as if its depth were known: they hold the scale
        fac = s.idepth_fix_prior_marg_fac
        sc = kw.schur_points(lin, keys, problem.pair_key, problem.point_start, problem.K, eh * fac, eb * fac,
                             device=problem.device)
        Htop, btop = problem.top_system(keys, lin)
        S = problem.S
        delta_raw = problem.delta() * S
        # gradient at the linearisation point of the frames (points are linearised where they are)
        g0_c = btop - Htop @ delta_raw
        g0_d = sc.bd - sc.w @ delta_raw
        H = Htop - sc.H_sc
        b = g0_c - (sc.w / sc.hdd[:, None]).T @ g0_d
        f = s.marg_weight_fac
        prior.add(f * H * np.outer(S, S), f * b * S)

    def marginalize_frames(self, window: Window) -> list[int]:
        ids = []
        prior = self._prior_for(window)
        first = self._first_slots(window)
        s = self.config
        for slot in [o for o in window.order if window.flagged_[o]]:
            window.drop_points(window.active.host == slot)
            fp = None
            if slot in first:
                fp = np.array([s.initial_trans_prior] * 3 + [s.initial_rot_prior] * 3
                              + [s.initial_aff_a_prior, s.initial_aff_b_prior])
            else:
                fp = np.array([0.0] * 6 + [s.affine_prior_a, s.affine_prior_b])
            prior.marginalize_frame(slot, fp)
            ids.append(int(window.keyframe_id_[slot]))
            window.remove_keyframe(slot)
        return ids


