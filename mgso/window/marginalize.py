"""What leaves the sliding window, and the prior that keeps what it knew (DSO ``FullSystem::flagFramesFor
Marginalization``, ``flagPointsForRemoval``, ``EnergyFunctional::marginalizePointsF`` / ``marginalizeFrame``).

Choices (shared by every back end; :class:`~mgso.window.depth_refine.FixedWindowBackEnd` and
:class:`~mgso.window.backend.WindowOptimizer` both call them):

- :func:`flag_frames_for_marginalization` (before the new keyframe is added): keyframes with fewer than 5 % of their
  points left or a brightness factor to the newest beyond ``exp(0.7)``, while more than ``min_frames`` stay; then, if
  the window is full, the keyframe with the lowest distance score (close to the others, far from the newest; the
  segment's first keyframe and the newest ``min_frame_age`` are never chosen).
- :func:`flag_points_for_removal` (after the optimisation): a point whose residual in the newest keyframe is OOB,
  whose residuals in the two newest keyframes are outliers, that keeps too few residuals outside the frames about to
  leave, or whose host leaves, is marginalised when it is an inlier (enough good residuals and inverse-depth
  Hessian) and dropped otherwise; points without an IN residual are dropped.

Their constants are DSO's and fields of :class:`~mgso.config.WindowConfig` (``min_points_remaining``,
``max_log_aff_fac_in_window``, ``min_frame_age``, ``min_good_active_res_for_marg``, ``min_good_res_for_marg``,
``min_idepth_h_marg``, and ``min_frames`` / ``max_frames``).

The prior (:class:`MarginalizationPrior`) is ``E_M(delta) = 2 delta^T b_M + delta^T H_M delta`` over the frame
parameters of the window's slots (8 each, DSO's scaled units, ``delta`` = state minus linearisation point). Points are
folded in by a Schur complement of their inverse depth with first-estimate Jacobians and the gradient taken back to
the linearisation point (DSO ``res_toZeroF``), times ``marg_weight_fac`` (DSO ``setting_margWeightFac``); a keyframe
leaves by a Schur complement of its 8 parameters. A keyframe's linearisation point never moves once the prior holds
anything of it (the back end only moves the newest keyframe's, which the prior cannot yet hold).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..config import WindowConfig
from .window import PointFlag, ResidualState, Window

__all__ = ["flag_frames_for_marginalization", "flag_points_for_removal", "MarginalizationPrior"]

log = logging.getLogger(__name__)


def flag_frames_for_marginalization(window: Window, s: WindowConfig, segment_first: dict[int, int]) -> list[int]:
    """DSO ``flagFramesForMarginalization``: sets ``window.flagged_`` and returns the flagged slots. ``s``: the
    window's settings (``min_frames``, ``max_frames``, ``min_points_remaining``, ``max_log_aff_fac_in_window``,
    ``min_frame_age``). ``segment_first``: first keyframe id of each segment (filled here; that keyframe is never
    chosen by the distance score, as DSO's frame 0)."""
    order = list(window.order)
    if not order:
        return []
    latest = order[-1]
    flagged = 0
    out = []
    for slot in order:
        n_in = window.points_in(slot)
        n_out = int(window.points_left_[slot])
        a_rel, _ = window.affine_rel(latest, slot)
        if ((n_in < s.min_points_remaining * (n_in + n_out) or abs(math.log(a_rel)) > s.max_log_aff_fac_in_window)
                and len(order) - flagged > s.min_frames):
            window.flagged_[slot] = True
            flagged += 1
            out.append(slot)
    if len(order) - flagged >= s.max_frames:
        latest_id = window.keyframe_id_[latest]
        seg = int(window.segment_[latest])
        first_id = segment_first.setdefault(seg, min(int(window.keyframe_id_[o]) for o in order))
        best, best_slot = 1.0, -1
        for slot in order:
            kid = window.keyframe_id_[slot]
            if kid > latest_id - s.min_frame_age or kid == first_id or window.flagged_[slot]:
                continue
            score = 0.0
            for other in order:
                if window.keyframe_id_[other] > latest_id - s.min_frame_age + 1 or other == slot:
                    continue
                score += 1.0 / (1e-5 + np.linalg.norm(window.target_from_host(slot, other)[:3, 3]))
            score *= -math.sqrt(np.linalg.norm(window.target_from_host(slot, latest)[:3, 3]))
            if score < best:
                best, best_slot = score, slot
        if best_slot >= 0:
            window.flagged_[best_slot] = True
            out.append(best_slot)
    return out


def flag_points_for_removal(window: Window, s: WindowConfig) -> np.ndarray:
    """DSO ``flagPointsForRemoval``: writes ``window.active.flag`` (KEEP / MARGINALIZE / DROP) and returns it.
    ``s``: the window's settings (``min_good_active_res_for_marg``, ``min_good_res_for_marg``,
    ``min_idepth_h_marg``)."""
    a = window.active
    flag = np.full(a.n, PointFlag.KEEP, np.int8)
    if a.n == 0:
        return flag
    order = window.order
    newest = order[-1]
    second = order[-2] if len(order) > 1 else -1
    rs = a.res_state
    n_res = np.count_nonzero((rs == ResidualState.IN) | (rs == ResidualState.OUTLIER), axis=1)
    n_in = np.count_nonzero(rs == ResidualState.IN, axis=1)
    vis_in_marg = np.zeros(a.n, np.int64)
    for f in (o for o in order if window.flagged_[o]):
        vis_in_marg += rs[:, f] == ResidualState.IN
    last0 = rs[:, newest]
    last1 = rs[:, second] if second >= 0 else np.zeros(a.n, np.uint8)
    oob = ((n_res >= s.min_good_active_res_for_marg) & (a.num_good_residuals > s.min_good_res_for_marg + 10)
           & (n_res - vis_in_marg < s.min_good_active_res_for_marg))
    oob |= (last0 == ResidualState.OOB) & (a.host != newest)
    oob |= (n_res >= 2) & (last0 == ResidualState.OUTLIER) & (last1 == ResidualState.OUTLIER)
    leave = oob | window.flagged_[a.host]
    inlier = ((n_res >= s.min_good_active_res_for_marg) & (a.num_good_residuals >= s.min_good_res_for_marg)
              & (a.idepth_hessian > s.min_idepth_h_marg))
    flag[leave & inlier] = PointFlag.MARGINALIZE
    flag[leave & ~inlier] = PointFlag.DROP
    flag[(a.idepth < 0) | (n_in == 0) & (a.host != newest)] = PointFlag.DROP
    a.flag[:] = flag
    return flag


class MarginalizationPrior:
    """``H_M [8K, 8K]``, ``b_M [8K]`` over the frame parameters of the window's ``K`` slots (scaled, at the
    linearisation points). Rows of a slot belong to the keyframe whose id is ``keyframe_id[slot]``; :meth:`sync`
    clears a slot whose keyframe changed (a new segment after a loss, a reused slot)."""

    def __init__(self, num_slots: int):
        self.num_slots = int(num_slots)
        nf = 8 * self.num_slots
        self.H = np.zeros((nf, nf))
        self.b = np.zeros(nf)
        self.keyframe_id = np.full(self.num_slots, -1, np.int64)

    def _sl(self, slot: int) -> slice:
        return slice(8 * slot, 8 * slot + 8)

    def clear_slot(self, slot: int) -> None:
        sl = self._sl(slot)
        self.H[sl, :] = 0.0
        self.H[:, sl] = 0.0
        self.b[sl] = 0.0

    def sync(self, window: Window) -> None:
        """Clear slots whose keyframe is not the one the prior knows."""
        for s in range(self.num_slots):
            kid = int(window.keyframe_id_[s]) if window.used_[s] else -1
            if kid != self.keyframe_id[s]:
                self.clear_slot(s)
                self.keyframe_id[s] = kid

    @property
    def empty(self) -> bool:
        return not np.any(self.H)

    def energy(self, delta: np.ndarray) -> float:
        """``2 delta^T b_M + delta^T H_M delta`` (``delta [8K]`` scaled state minus linearisation point)."""
        return float(delta @ (2.0 * self.b + self.H @ delta))

    def gradient(self, delta: np.ndarray) -> np.ndarray:
        """Half the gradient of :meth:`energy`: ``b_M + H_M delta`` (the system's ``b`` convention)."""
        return self.b + self.H @ delta

    def add(self, H: np.ndarray, b: np.ndarray) -> None:
        self.H += 0.5 * (H + H.T)
        self.b += b

    def marginalize_frame(self, slot: int, frame_prior: np.ndarray | None = None) -> None:
        """Schur complement of the slot's 8 parameters out of the prior (after adding the keyframe's own prior
        diagonal ``frame_prior [8]``, centred at its linearisation point, as DSO ``marginalizeFrame``)."""
        sl = self._sl(slot)
        if frame_prior is not None:
            self.H[sl, sl] += np.diag(frame_prior)
        Hff = self.H[sl, sl]
        if np.any(Hff):
            # precondition by the diagonal (DSO scales by sqrt of the diagonal before inverting)
            d = np.sqrt(np.maximum(np.abs(np.diag(Hff)), 1e-30))
            inv = np.linalg.pinv(Hff / np.outer(d, d), rcond=1e-12) / np.outer(d, d)
            Hrf = self.H[:, sl].copy()
            Hrf[sl] = 0.0
            self.H -= Hrf @ inv @ Hrf.T
            self.b -= Hrf @ (inv @ self.b[sl])
        self.clear_slot(slot)
        self.H = 0.5 * (self.H + self.H.T)
        self.keyframe_id[slot] = -1
