"""The window's energy and its Levenberg-Marquardt minimisation over the reduced camera system (DSO
``FullSystem::optimize`` + ``EnergyFunctional::solveSystemF``).

Variables: per keyframe slot 8 frame parameters ``(v, w, a, b)`` -- a left perturbation of ``world_to_cam`` about its
linearisation point (``world_to_cam = exp(delta_xi) world_to_cam_zero``) and the affine brightness minus its
linearisation value -- and one inverse depth per active point. All solver quantities are in DSO's scaled units: a
scaled parameter times ``SCALE_XI_TRANS = 0.5`` / ``SCALE_XI_ROT = 1`` / ``SCALE_A = 10`` / ``SCALE_B = 1000`` /
``SCALE_IDEPTH = 1`` is the raw one.

Energy (DSO's, ``r^2`` convention; the system is ``H = J^T W J``, ``b = J^T W r``, step ``-H^-1 b``):

- photometric: sum over the candidate pairs (the ``IN`` residuals at the start) of the 8-pixel energy, an ``OOB``
  or ``OUTLIER`` pair counting its threshold (:mod:`mgso_kernels.window`);
- the marginalisation prior ``2 delta^T b_M + delta^T H_M delta`` (:class:`~mgso.window.marginalize.
  MarginalizationPrior`);
- gauge: the first keyframe of a segment is held fixed (pose and affine brightness) while it is in the window, which
  fixes 6 of the monocular window's 7 gauge freedoms (and the global brightness); when it leaves, DSO's prior on it
  (``setting_initialTransPrior = 1e10``, ``setting_initialRotPrior = 1e11``, ``setting_initialAffA/BPrior = 1e14``
  on its scaled parameters) is folded into the marginalisation prior with it; the initialiser's points
  (``has_depth_prior``) carry ``setting_idepthFixPrior = 50^2`` on their inverse depth, as DSO centred on the
  current value (DSO moves ``idepth_zero`` every step: no gradient, it stiffens them; ``idepth_fix_prior_anchored``
  centres it on the initialiser's value instead) and multiplied by ``setting_idepthFixPriorMargFac = 600^2`` when
  they are folded into the marginalisation prior, where their residuals then act as if the depth were known. And,
  as DSO's default (``SOLVER_ORTHOGONALIZE_X_LATER``), each step from the third on (``orthogonalize_from``) is
  projected off the gauge directions of the frame parameters (:meth:`WindowProblem.nullspaces`: scale always, the 6
  pose directions once no keyframe is held), so that first-estimate inconsistencies cannot drive the window along
  its null space. Other keyframes' affine parameters get ``affine_prior_a/b`` (DSO ``setting_affineOptModeA/B``; 0 =
  free, DSO's mode 1).

Each iteration: linearise every candidate pair (Warp), accumulate the key blocks and the Schur complement over the
inverse depths (Warp, per-block partials), add the priors, multiply the diagonal by ``1 + lambda``, solve the
``8 K x 8 K`` reduced system by a dense float64 Cholesky, back-substitute the inverse depths, and take the step.
DSO's defaults: ``lambda = 1e-5`` (``SOLVER_FIX_LAMBDA``) and every finite step kept (``setting_forceAceptStep``,
``force_accept``); with ``force_accept = False`` a step is kept only if the total energy goes down (``lambda *=
0.25``), else undone and retried (``lambda *= 100``). At most ``iterations`` (DSO 6) steps; stop early when the
mean squared step is below DSO's thresholds (``setting_thOptIterations``). Points are not first-estimate: their
inverse depth is linearised where it is (DSO moves ``idepth_zero`` of a point every step), while the keyframes'
geometric Jacobians stay at the linearisation points.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from mgso_kernels import runtime
from mgso_kernels import window as kw
from mgso_kernels.photometric import affine_from_to

from ..config import TrackingConfig, WindowConfig
from ..geometry import hat, orthonormalize, se3_adjoint, se3_exp, se3_inverse, se3_log
from .marginalize import MarginalizationPrior
from .window import ResidualState, Window

__all__ = ["SCALE_XI_ROT", "SCALE_XI_TRANS", "SCALE_A", "SCALE_B", "SCALE_IDEPTH", "frame_scale",
           "WindowProblem", "Linearization", "OptimizeStats", "optimize_window", "new_frame_energy_threshold"]

log = logging.getLogger(__name__)

# DSO HessianBlocks.h
SCALE_XI_ROT = 1.0
SCALE_XI_TRANS = 0.5
SCALE_A = 10.0
SCALE_B = 1000.0
SCALE_IDEPTH = 1.0


def frame_scale() -> np.ndarray:
    """``[8]`` raw = scale * scaled, for ``(v, w, a, b)``."""
    return np.array([SCALE_XI_TRANS] * 3 + [SCALE_XI_ROT] * 3 + [SCALE_A, SCALE_B])


def new_frame_energy_threshold(energies: np.ndarray, config: WindowConfig, tracking: TrackingConfig) -> float:
    """DSO ``setNewFrameEnergyTH`` from the 8-pixel energies of the residuals into the new keyframe (both back ends):
    ``window.frame_energy_th_*`` and ``tracking.overall_energy_th_weight``."""
    if not len(energies):
        return 12.0 * 12.0 * 8
    k = min(int(config.frame_energy_th_n * len(energies)), len(energies) - 1)
    nth = float(np.sqrt(np.partition(energies, k)[k]))
    th = nth * config.frame_energy_th_fac_median
    th = 26.0 * config.frame_energy_th_const_weight + th * (1 - config.frame_energy_th_const_weight)
    return th * th * tracking.overall_energy_th_weight ** 2


@dataclass
class Linearization:
    """One linearisation of a :class:`WindowProblem` at its current state (scaled units where it matters)."""

    pairs: kw.PairLinearization
    schur: kw.PointSchur | None  # None (and H, b, H_sc too): linearised for the energy only (``system=False``)
    energy: float  # total: photometric + priors
    energy_photo: float
    H: np.ndarray | None  # [8K, 8K] scaled reduced-system matrix (without damping)
    b: np.ndarray | None  # [8K] scaled reduced-system gradient
    H_sc: np.ndarray | None  # [8K, 8K] scaled Schur term (in H with a minus sign; damping divides it by 1 + lambda)


@dataclass
class OptimizeStats:
    """What :func:`optimize_window` did."""

    iterations: int
    accepted: int
    energy_start: float
    energy_end: float
    pairs: int
    points: int
    times_ms: dict  # linearize, schur, solve per call (summed)
    history: list  # total energy at the start and after each accepted step


class WindowProblem:
    """The window's keyframes and a set of its active points with their candidate pairs, ready to linearise.

    ``config``: the window's settings (priors, solver constants); ``tracking``: the photometric residual's
    (``huber_th``, ``outlier_th_sum_component``; default :class:`~mgso.config.TrackingConfig`'s). ``points``: indices
    of the active points taking part (default all); pairs are the point's residuals whose state is in ``states``
    (default ``IN``). ``first_slots``: slots carrying the gauge prior (the segment's first keyframe). Changes the
    window only through :meth:`apply_step` / :meth:`restore` (keyframe states, point inverse depths).
    """

    def __init__(self, window: Window, config: WindowConfig, prior: MarginalizationPrior | None = None, *,
                 tracking: TrackingConfig | None = None, points: np.ndarray | None = None, first_slots: tuple = (),
                 states=(ResidualState.IN,), device: str | None = None):
        tracking = tracking or TrackingConfig()
        self.window = window
        self.s = config
        self.prior = prior
        self.device = runtime.device_or_cpu(device)
        a = window.active
        self.K = window.capacity
        self.nf = 8 * self.K
        self.order = list(window.order)
        self._order = np.asarray(self.order, dtype=np.int64)
        self.points = np.arange(a.n) if points is None else np.asarray(points, np.int64)
        rs = a.res_state[self.points]
        mask = np.isin(rs, [int(x) for x in states])
        mask[:, ~window.used_] = False
        pl, tg = np.nonzero(mask)  # point-major
        self.pair_point = pl.astype(np.int32)  # index into self.points
        self.pair_target = tg.astype(np.int32)
        hosts = a.host[self.points]
        self.pair_host = hosts[pl].astype(np.int32)
        self.key_index = np.full((self.K, self.K), -1, np.int64)
        keylist = sorted(set(zip(self.pair_host.tolist(), self.pair_target.tolist())))
        for i, (h, t) in enumerate(keylist):
            self.key_index[h, t] = i
        self.keylist = keylist
        self._key_host = np.array([k[0] for k in keylist], np.int64)
        self._key_target = np.array([k[1] for k in keylist], np.int64)
        self.pair_key = self.key_index[self.pair_host, self.pair_target].astype(np.int32) if len(pl) else \
            np.zeros(0, np.int32)
        self.point_start = np.searchsorted(pl, np.arange(len(self.points) + 1)).astype(np.int32)
        g = window.camera
        self.params = kw.make_window_params(g.fx, g.fy, g.cx, g.cy, window.width, window.height,
                                            huber_th=tracking.huber_th, grad_c2=tracking.outlier_th_sum_component)
        self.images = window.dI0_  # [K, H, W] level-0 (I, dx, dy), indexed by slot
        self._cache: dict = {}  # linearize_window's plan and buffers (the pairs are fixed for the problem)
        self._gauge_basis: np.ndarray | None = None  # orthogonalize's normalised nullspace columns
        self._keys_zero: tuple | None = None  # keys()' parts at the linearisation points
        self.S = np.tile(frame_scale(), self.K)
        # gauge / affine priors on the scaled frame parameters
        self.frame_prior = np.zeros(self.nf)
        for slot in self.order:
            p = np.zeros(8)
            if slot in first_slots:
                p[:3] = config.initial_trans_prior
                p[3:6] = config.initial_rot_prior
                p[6] = config.initial_aff_a_prior
                p[7] = config.initial_aff_b_prior
            else:
                p[6] = config.affine_prior_a
                p[7] = config.affine_prior_b
            self.frame_prior[8 * slot:8 * slot + 8] = p
        self.depth_prior = np.where(a.has_depth_prior[self.points], config.idepth_fix_prior, 0.0)
        # DSO moves a point's idepth_zero to its state every step, so its prior has no gradient and only stiffens
        # the point; anchored (mgso before 2026-11-22), it pulls towards the initialiser's inverse depth
        self.idepth_prior_centre = (a.idepth_zero[self.points].astype(np.float64) if config.idepth_fix_prior_anchored
                                    else None)
        # the segment's first keyframe is held exactly (its prior is infinite while it is in the window; the finite
        # DSO prior above is what the marginalisation folds in when it leaves)
        free = [s for s in self.order if s not in first_slots]
        self._make_rigid()
        self.live = np.concatenate([np.arange(8 * s, 8 * s + 8) for s in free]) if free else np.zeros(0, np.int64)

    def _make_rigid(self) -> None:
        """Project the keyframes' poses back onto SE(3): poses composed by the tracker drift off orthonormality
        (1e-3 after a few dozen frames), which would make ``log(T T0^-1)`` and its re-exponentiation disagree."""
        w = self.window
        o = self._order
        if len(o):
            same = np.all(w.world_to_cam_[o] == w.world_to_cam_zero_[o], axis=(1, 2))
            T = _rigid(w.world_to_cam_[o])
            w.world_to_cam_[o] = T
            w.world_to_cam_zero_[o] = np.where(same[:, None, None], T, _rigid(w.world_to_cam_zero_[o]))

    # ------------------------------------------------------------------------------------------- state
    def delta(self) -> np.ndarray:
        """``[8K]`` scaled frame state minus linearisation point (0 for free slots)."""
        w = self.window
        d = np.zeros(self.nf)
        if self.order:
            o = self._order
            rel = w.world_to_cam_[o] @ se3_inverse(w.world_to_cam_zero_[o])
            raw = np.empty((len(o), 8))
            for i, T in enumerate(rel):  # one at a time: the batched log rounds differently in the last bit
                raw[i, :6] = se3_log(T)
            raw[:, 6:] = w.affine_[o] - w.affine_zero_[o]
            d.reshape(self.K, 8)[o] = raw / frame_scale()
        return d

    def backup(self):
        w = self.window
        return (w.world_to_cam_.copy(), w.affine_.copy(), w.active.idepth[self.points].copy())

    def restore(self, state) -> None:
        w = self.window
        T, A, d = state
        w.world_to_cam_[:] = T
        w.affine_[:] = A
        w.active.idepth[self.points] = d

    def apply_step(self, dx_c: np.ndarray, dx_d: np.ndarray) -> None:
        """Scaled frame step, applied as a left increment ``world_to_cam <- exp(dx) world_to_cam`` (to first order
        DSO's ``state + step`` in the linearisation point's tangent, without a log of the pose), and inverse-depth
        step. The keyframes are moved all at once (NumPy's batched products and SVD give the per-slot bits)."""
        w = self.window
        step = dx_c.reshape(self.K, 8)[self._order]
        moved = np.any(step, axis=1)
        if moved.any():
            slots = self._order[moved]
            raw = step[moved] * frame_scale()
            E = np.stack([se3_exp(r[:6]) for r in raw])  # one at a time, as in delta()
            w.set_keyframe_states(slots, _rigid(E @ w.world_to_cam_[slots]), w.affine_[slots] + raw[:, 6:])
        d = w.active.idepth[self.points].astype(np.float64)
        new = d + dx_d * SCALE_IDEPTH
        w.active.idepth[self.points] = np.where(new > 1e-6 * np.maximum(d, 1e-9), new, 0.5 * d)

    # ---------------------------------------------------------------------------------------- linearise
    def keys(self, energy_th: np.ndarray | None = None) -> kw.WindowKeys:
        """The (host, target) keys at the current state, all at once (NumPy, batched over keys)."""
        w = self.window
        hs, gs = self._key_host, self._key_target
        T = w.world_to_cam_[gs] @ se3_inverse(w.world_to_cam_[hs])
        af, ex = w.affine_.tolist(), w.exposure_.tolist()  # Python floats: Window.affine_rel, a tenth of its cost
        a_rel = np.array([affine_from_to(*af[h], *af[g], ex[h], ex[g])[0] for h, g in self.keylist])
        aff = np.stack([a_rel, w.affine_[hs, 1], w.affine_[gs, 1]], axis=1).reshape(len(hs), 3)
        if self._keys_zero is None:  # the linearisation points do not move during the problem's life
            T0 = w.world_to_cam_zero_[gs] @ se3_inverse(w.world_to_cam_zero_[hs])
            R0, t0 = T0[:, :3, :3], T0[:, :3, 3]
            adj = np.zeros((len(hs), 6, 6))  # se3_adjoint(T0), (v, w) order
            adj[:, :3, :3] = R0
            adj[:, :3, 3:] = hat(t0) @ R0
            adj[:, 3:, 3:] = R0
            self._keys_zero = tuple(a.copy() for a in (R0, t0, adj, hs.astype(np.int32), gs.astype(np.int32)))
            for a in self._keys_zero:
                a.setflags(write=False)  # shared by every step's keys: read-only
        R0, t0, adj, h32, g32 = self._keys_zero
        th = np.maximum(w.energy_th_[hs], w.energy_th_[gs]) if energy_th is None else np.asarray(energy_th)
        return kw.WindowKeys(h32, g32, T[:, :3, :3].copy(), T[:, :3, 3].copy(), R0, t0, aff, th.astype(np.float64),
                             adj)

    def linearize_pairs(self, keys: kw.WindowKeys | None = None) -> kw.PairLinearization:
        a = self.window.active
        keys = keys or self.keys()
        p = self.points
        return kw.linearize_window(self.params, keys, self.pair_point, self.pair_key, a.uv[p], a.idepth[p],
                                   a.color[p], a.weight[p], self.images, pairs_per_block=self.s.pairs_per_block,
                                   device=self.device, cache=self._cache)

    def top_system(self, keys: kw.WindowKeys, lin: kw.PairLinearization):
        """``(H_cc [8K, 8K], b_c [8K])`` raw units: the key blocks mapped to absolute frame parameters (pair
        parameters ``= A (host 8, target 8)``, ``A`` from the key's adjoint; all keys at once)."""
        nk = len(self.keylist)
        H = np.zeros((self.nf, self.nf))
        b = np.zeros(self.nf)
        if not nk:
            return H, b
        A = np.zeros((nk, 10, 16))  # pair params <- (host 8, target 8)
        A[:, :6, 8:14] = np.eye(6)
        A[:, :6, 0:6] = -keys.adj
        A[:, 6, 14] = A[:, 7, 15] = 1.0
        A[:, 8, 6] = A[:, 9, 7] = 1.0
        Hk = np.swapaxes(A, 1, 2) @ lin.key_H @ A
        bk = np.einsum("kai,ka->ki", A, lin.key_b)
        idx = np.concatenate([8 * self._key_host[:, None] + np.arange(8), 8 * self._key_target[:, None] + np.arange(8)],
                             axis=1)  # [nk, 16]
        # summed key by key in order, as np.add.at would (the same bits), a fifth of its time
        H = np.bincount((idx[:, :, None] * self.nf + idx[:, None, :]).ravel(), weights=Hk.ravel(),
                        minlength=self.nf * self.nf).reshape(self.nf, self.nf)
        b = np.bincount(idx.ravel(), weights=bk.ravel(), minlength=self.nf)
        return H, b

    def point_extras(self):
        """Inverse-depth prior of the initialiser's points: ``(extra_h, extra_b)`` raw (``extra_b`` is 0 with DSO's
        prior, whose centre is the point's current inverse depth)."""
        d = self.window.active.idepth[self.points].astype(np.float64)
        eh = self.depth_prior / SCALE_IDEPTH ** 2
        if self.idepth_prior_centre is None:
            return eh, np.zeros_like(eh)
        return eh, eh * (d - self.idepth_prior_centre)

    def linearize(self, keys: kw.WindowKeys | None = None, system: bool = True) -> Linearization:
        """The pairs, the energy and (``system``) the reduced system at the current state; ``system=False`` leaves
        the Schur complement and the system out (``None``): a linearisation no step is solved from (the last one of
        :func:`optimize_window`) needs only the pairs and the energy."""
        keys = keys or self.keys()
        lin = self.linearize_pairs(keys)
        delta = self.delta()
        e_photo = float(np.sum(lin.energy))
        d = self.window.active.idepth[self.points].astype(np.float64)
        e = e_photo + float(np.sum(self.frame_prior * delta * delta))
        if self.idepth_prior_centre is not None:
            e += float(np.sum(self.depth_prior * (d - self.idepth_prior_centre) ** 2))
        has_prior = self.prior is not None and not self.prior.empty
        if has_prior:
            e += self.prior.energy(delta)
        if not system:
            return Linearization(lin, None, e, e_photo, None, None, None)
        eh, eb = self.point_extras()
        sc = kw.schur_points(lin, keys, self.pair_key, self.point_start, self.K, eh, eb, device=self.device)
        Htop, btop = self.top_system(keys, lin)
        S = self.S
        Hsc = sc.H_sc * np.outer(S, S)
        H = Htop * np.outer(S, S) - Hsc + np.diag(self.frame_prior)
        b = (btop - sc.b_sc) * S + self.frame_prior * delta
        if has_prior:
            H = H + self.prior.H
            b = b + self.prior.gradient(delta)
        return Linearization(lin, sc, e, e_photo, H, b, Hsc)

    def nullspaces(self) -> np.ndarray:
        """``[8K, m]`` gauge directions of the frame parameters (scaled), at the linearisation points (DSO
        ``lastNullspaces_pose``/``_scale``): a change of the world frame ``exp(g)`` moves keyframe ``s`` by
        ``Ad(world_to_cam_s) g`` (6 columns, only when no keyframe is held fixed), a change of scale moves its
        translation by ``t_s`` (1 column)."""
        w = self.window
        cols = []
        if len(self.live) == 8 * len(self.order):  # nothing held: the pose gauge is free
            for i in range(6):
                v = np.zeros(self.nf)
                for s in self.order:
                    v[8 * s:8 * s + 6] = se3_adjoint(w.world_to_cam_zero_[s])[:, i]
                cols.append(v)
        v = np.zeros(self.nf)
        for s in self.order:
            v[8 * s:8 * s + 3] = w.world_to_cam_zero_[s][:3, 3]
        cols.append(v)
        N = np.stack(cols, axis=1) / self.S[:, None]
        mask = np.zeros(self.nf, bool)
        mask[self.live] = True
        N[~mask] = 0.0
        return N

    def orthogonalize(self, x: np.ndarray) -> np.ndarray:
        """Remove the gauge directions from a step (DSO ``orthogonalize`` with ``SOLVER_ORTHOGONALIZE_X``)."""
        N = self._gauge_basis
        if N is None:  # the linearisation points do not move during the problem's life: made once (0.4 ms a step)
            N = self.nullspaces()
            norms = np.linalg.norm(N, axis=0)
            N = self._gauge_basis = N[:, norms > 1e-12] / norms[norms > 1e-12]
        if not N.shape[1]:
            return x
        return x - N @ np.linalg.lstsq(N, x, rcond=1e-10)[0]

    def solve(self, L: Linearization, lam: float, orthogonalize: bool | None = None):
        """``(dx_c [8K] scaled, dx_d [n] scaled)`` of the damped reduced system; ``orthogonalize``: project the gauge
        directions out of the step (default: ``window.orthogonalize``)."""
        idx = self.live
        # DSO solveSystemF: the diagonal of the full system times (1 + lambda), frames and points alike, i.e. the
        # top block's diagonal scaled and the Schur term divided by (1 + lambda)
        Hsc = L.H_sc[np.ix_(idx, idx)]
        H = L.H[np.ix_(idx, idx)] + Hsc
        H[np.diag_indices_from(H)] *= 1.0 + lam
        H -= Hsc / (1.0 + lam)
        H[np.diag_indices_from(H)] += 1e-12 * max(np.abs(np.diag(H)).max(), 1.0)
        b = L.b[idx]
        try:
            x = scipy.linalg.cho_solve(scipy.linalg.cho_factor(H, lower=True, check_finite=False), -b,
                                       check_finite=False)
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
            x = np.linalg.lstsq(H, -b, rcond=None)[0]
        dx_c = np.zeros(self.nf)
        dx_c[idx] = x
        if self.s.orthogonalize if orthogonalize is None else orthogonalize:
            dx_c = self.orthogonalize(dx_c)
        # back-substitution (raw point units): H_dd dd = -(b_d + w . dx_raw)
        dx_raw = dx_c * self.S
        sc = L.schur
        dx_d = -(sc.bd + sc.w @ dx_raw) / (sc.hdd * (1.0 + lam)) / SCALE_IDEPTH
        return dx_c, dx_d


def _rigid(T: np.ndarray) -> np.ndarray:
    """The pose(s) ``[..., 4, 4]`` with an orthonormal rotation and a last row ``(0, 0, 0, 1)``."""
    out = np.array(T, dtype=np.float64)
    out[..., :3, :3] = orthonormalize(out[..., :3, :3])
    out[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return out


def optimize_window(problem: WindowProblem, config: WindowConfig, timer: dict | None = None
                    ) -> tuple[Linearization, OptimizeStats]:
    """LM on ``problem`` (see the module text) with ``config``'s solver settings (``iterations``, ``lambda_*``,
    ``force_accept``, ``orthogonalize[_from]``, ``min_iterations``, ``th_opt_iterations``). Returns the linearisation
    at the final state and the stats."""
    import time

    s = config
    times = timer if timer is not None else {}

    def tick(name, t0):
        times[name] = times.get(name, 0.0) + (time.perf_counter() - t0) * 1000

    t0 = time.perf_counter()
    L = problem.linearize()
    tick("linearize", t0)
    e0 = L.energy
    lam = s.lambda_init
    accepted = 0
    it = 0
    history = [e0]
    for it in range(1, s.iterations + 1):
        t0 = time.perf_counter()
        dx_c, dx_d = problem.solve(L, lam, orthogonalize=s.orthogonalize and it - 1 >= s.orthogonalize_from)
        tick("solve", t0)
        if not (np.all(np.isfinite(dx_c)) and np.all(np.isfinite(dx_d))):
            lam *= s.lambda_reject
            continue
        backup = problem.backup()
        problem.apply_step(dx_c, dx_d)
        stop = it == s.iterations or (_can_break(problem, dx_c, s) and it >= s.min_iterations)
        t0 = time.perf_counter()
        # the step that ends the loop is solved from no more: its linearisation is the energy and the pairs' states
        # only (the Schur complement and the system were a third of a linearisation; DSO too accumulates its
        # Hessians only to solve)
        L_new = problem.linearize(system=not stop)
        tick("linearize", t0)
        if L_new.energy < L.energy or (s.force_accept and np.isfinite(L_new.energy)):
            L = L_new
            accepted += 1
            history.append(L.energy)
            lam = max(lam * s.lambda_accept, s.lambda_min)
        else:
            problem.restore(backup)
            lam *= s.lambda_reject
            continue  # the break test judges steps that were taken
        if stop:
            break
    return L, OptimizeStats(it, accepted, e0, L.energy, len(problem.pair_point), len(problem.points), times,
                             history)


def _can_break(problem: WindowProblem, dx_c: np.ndarray, s: WindowConfig) -> bool:
    """DSO ``doStepFromBackup``'s break test on the (scaled) step just applied (the inverse depths are the new ones)."""
    nfr = max(len(problem.order), 1)
    st = dx_c.reshape(-1, 8)[problem.order]
    sum_t = float(np.sum(st[:, :3] ** 2)) / nfr
    sum_r = float(np.sum(st[:, 3:6] ** 2)) / nfr
    sum_a = float(np.sum(st[:, 6] ** 2)) / nfr
    sum_b = float(np.sum(st[:, 7] ** 2)) / nfr
    sum_nid = float(np.mean(np.abs(problem.window.active.idepth[problem.points]))) if len(problem.points) else 1
    th = s.th_opt_iterations
    return bool(np.sqrt(sum_a) < 0.0005 * th and np.sqrt(sum_b) < 0.00005 * th
                and np.sqrt(sum_r) < 0.00005 * th and np.sqrt(sum_t) * sum_nid < 0.00005 * th)
