"""Monocular initialisation: DSO's ``CoarseInitializer``, vectorised over points.

The residual pass over all points of a level (DSO ``calcResAndGS``, 90 % of the time when it was NumPy) and the
neighbours' median (DSO ``optReg``) are Warp kernels (:func:`mgso_kernels.initializer.init_system`,
:func:`~mgso_kernels.initializer.smooth_idepths`) on the odometry's device; the rest of the per-point bookkeeping
(steps, acceptance, pyramid propagation) is NumPy on the level's arrays, which the kernels read and write in place
on the CPU (a GPU gets copies of the per-point state, not of the images).

The first frame's points (several pyramid levels, each point with its 10 nearest neighbours on its level and its
nearest "parent" on the next coarser level) start at inverse depth 1. Every following frame is aligned to the first
frame coarse to fine, jointly over the frame's pose and all the points' inverse depths (the 8x8 pose system with the
inverse depths eliminated by a Schur complement, Levenberg-Marquardt damping, DSO's step acceptance by energy):

- Before enough parallax, a strong regulariser (``alpha_w``) pulls inverse depths to 1 and the translation to 0; once
  the translation would cost more than ``alpha_k`` per point, the regulariser switches off (the system has
  "snapped") and each inverse depth is instead coupled (``coupling_weight``) to a smoothed value: ``(1 -
  reg_weight)`` its own plus ``reg_weight`` the median of its neighbours' (``optReg``).
- After each frame the depths are propagated up the pyramid (Hessian-weighted means of the children) so the next
  frame starts from them; at the start of each level they are propagated down from the parents.
- When the frame that snapped is followed by ``init_frames_after_snap`` more frames of the camera (or, mgso's
  addition for fast motion, once the translation reaches ``init_done_translation``),
  :meth:`CoarseInitializer.track_frame` answers ``INITIALIZED``. The frames are counted by the frames' indices
  when the caller gives them: in real time the frames that arrive while the initialiser works are dropped, and
  counting only the frames it aligned made each of the 5 cost about 10 of the camera's at 640x480 (DSO counts
  aligned frames; with nothing dropped the two are the same). The odometry then takes the first frame and this one
  as the first two keyframes and the level-0 points (inverse depths scaled to a mean of 1, as DSO) as the first
  active points.

Deviation from DSO, on purpose: ``optReg`` updates all points of a level at once from the previous smoothed values
(DSO updates them one after the other in place, so a point may see a neighbour's new value); the outcome differs
only in the order of averaging. DSO never gives up; mgso reports ``FAILED`` after ``init_max_frames`` frames without
enough parallax, when the level-0 RMSE exceeds ``init_max_rmse`` (the frames do not match the first one), or when
the first frame has too few points, and the odometry retries from a newer frame.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy.spatial import cKDTree

from mgso_kernels import runtime
from mgso_kernels.image import ImagePyramid, PyramidGeometry
from mgso_kernels.initializer import InitWorkspace, init_system, smooth_idepths
from mgso_kernels.photometric import PATTERN_NP

from ..config import TrackingConfig
from ..geometry import se3_exp, se3_log
from .pixel_selector import PixelSelector
from .sampling import sample_intensity

__all__ = ["CoarseInitializer", "InitStatus", "InitResult", "InitLevel", "grid_max_selection", "make_pixel_status"]

log = logging.getLogger(__name__)

WM = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 10.0, 1000.0])  # DSO wM (SCALE_XI_ROT on Sophus' first three, ...)
NN = 10  # neighbours per point (makeNN)


class InitStatus(str, Enum):
    FIRST_FRAME = "first_frame"  # this frame became the first frame
    TRACKING = "tracking"  # aligned, not enough parallax yet (or waiting the frames after snapping)
    INITIALIZED = "initialized"  # ready: take the first frame and this one as keyframes
    FAILED = "failed"  # gave up (see ``message``); the odometry restarts from a newer frame


@dataclass
class InitResult:
    status: InitStatus
    frames: int  # frames aligned since the first
    snapped: bool
    first_to_new: np.ndarray  # [4, 4] current estimate (scale: mean inverse depth ~ 1 before rescaling)
    affine: tuple[float, float]  # (a, b) of the new frame relative to the first
    rmse: float  # sqrt(photometric energy per residual) at level 0
    num_points: int  # level-0 points of the first frame
    num_good: int  # of them still good
    message: str = ""


# ----------------------------------------------------------------------------------- DSO makePixelStatus
def grid_max_selection(dI: np.ndarray, pot: int, th_fac: float) -> np.ndarray:
    """DSO ``gridMaxSelection``: in each ``pot x pot`` cell (cells start at (1, 1)), among pixels whose squared
    gradient exceeds ``(7.5 th_fac)^2``, the ones with the largest ``|gx|``, ``|gy|``, ``|gx - gy|``, ``|gx + gy|``
    (up to 4 a cell). Returns a ``[h, w]`` bool map."""
    h, w = dI.shape[:2]
    out = np.zeros((h, w), bool)
    nx = len(range(1, w - pot, pot))
    ny = len(range(1, h - pot, pot))
    if nx <= 0 or ny <= 0:
        return out
    gx = dI[1:1 + ny * pot, 1:1 + nx * pot, 1]
    gy = dI[1:1 + ny * pot, 1:1 + nx * pot, 2]
    th = th_fac * 10.0 * 0.75
    good = gx * gx + gy * gy > th * th
    # [ny, pot(dy), nx, pot(dx)] -> [ny, nx, dx, dy] so that a flat argmax scans dx outer, dy inner (DSO's loops)
    def cells(a):  # noqa: E306
        return a.reshape(ny, pot, nx, pot).transpose(0, 2, 3, 1).reshape(ny, nx, pot * pot)
    for score in (np.abs(gx), np.abs(gy), np.abs(gx - gy), np.abs(gx + gy)):
        s = cells(np.where(good, score, 0.0))
        k = np.argmax(s, axis=2)
        best = np.take_along_axis(s, k[..., None], axis=2)[..., 0]
        cy, cx = np.nonzero(best > 0)
        kk = k[cy, cx]
        dx, dy = kk // pot, kk % pot
        out[1 + cy * pot + dy, 1 + cx * pot + dx] = True
    return out


def make_pixel_status(dI: np.ndarray, density: float, sparsity: int, recs_left: int = 5,
                      th_fac: float = 1.0) -> tuple[np.ndarray, int]:
    """DSO ``makePixelStatus``: grid selection with the cell size adapted (recursively) to approach ``density``
    points. Returns ``(map [h, w] bool, new sparsity)`` (DSO keeps the sparsity in a global between calls)."""
    sparsity = max(int(sparsity), 1)
    while True:
        m = grid_max_selection(dI, sparsity, th_fac)
        num = int(m.sum())
        quotia = num / float(density)
        new = int(sparsity * math.sqrt(quotia) + 0.7)
        new = max(new, 1)
        old_th = th_fac
        if new == 1 and sparsity == 1:
            th_fac = 0.5
        if (abs(new - sparsity) < 1 and th_fac == old_th) or (quotia > 0.8 and 1.0 / max(quotia, 1e-12) > 0.8) \
                or recs_left == 0:
            return m, new
        sparsity = new
        recs_left -= 1


# ----------------------------------------------------------------------------------------- per-level state
@dataclass
class InitLevel:
    """Struct-of-arrays of one level's points (DSO ``Pnt``), all ``[n]`` unless said."""

    u: np.ndarray  # pixel x of this level (+0.1, DSO)
    v: np.ndarray
    ref_color: np.ndarray  # [n, 8] first-frame intensity at the pattern pixels (fixed)
    ref_ok: np.ndarray  # [n] all 8 finite
    my_type: np.ndarray
    neighbours: np.ndarray  # [n, 10] indices on this level, -1 none
    parent: np.ndarray  # index on the next level, -1 on the coarsest
    idepth: np.ndarray
    idepth_new: np.ndarray
    iR: np.ndarray  # smoothed inverse depth
    is_good: np.ndarray
    is_good_new: np.ndarray
    energy: np.ndarray  # [n, 2] (photometric, regulariser)
    energy_new: np.ndarray
    last_hessian: np.ndarray
    last_hessian_new: np.ndarray
    maxstep: np.ndarray
    jb: np.ndarray  # [n, 10] (J_pose^T J_d (8), r^T J_d, J_d^T J_d) of the last accepted evaluation
    jb_new: np.ndarray

    @property
    def n(self) -> int:
        return len(self.u)


def _make_level(u, v, my_type, ref_dI, width, height) -> InitLevel:
    n = len(u)
    px = u[:, None] + PATTERN_NP[None, :, 0]
    py = v[:, None] + PATTERN_NP[None, :, 1]
    col = sample_intensity(ref_dI, px, py).astype(np.float32)
    ok = np.all(np.isfinite(col), axis=1)
    z = lambda: np.zeros(n, np.float32)  # noqa: E731
    return InitLevel(u=u.astype(np.float32), v=v.astype(np.float32), ref_color=col, ref_ok=ok,
                     my_type=my_type.astype(np.float32), neighbours=np.full((n, NN), -1, np.int64),
                     parent=np.full(n, -1, np.int64), idepth=np.ones(n, np.float32),
                     idepth_new=np.ones(n, np.float32), iR=np.ones(n, np.float32), is_good=np.ones(n, bool),
                     is_good_new=np.ones(n, bool), energy=np.zeros((n, 2), np.float32),
                     energy_new=np.zeros((n, 2), np.float32), last_hessian=z(), last_hessian_new=z(),
                     maxstep=np.full(n, 1e10, np.float32), jb=np.zeros((n, 10), np.float64),
                     jb_new=np.zeros((n, 10), np.float64))


# ---------------------------------------------------------------------------------------------- initializer
class CoarseInitializer:
    """DSO's monocular initialiser. Owner: the odometry. ``set_first`` then ``track_frame`` per frame."""

    def __init__(self, geometry: PyramidGeometry, config: TrackingConfig | None = None, seed: int = 0,
                 device: str | None = None):
        if geometry.camera is None:
            raise ValueError("CoarseInitializer needs a PyramidGeometry with intrinsics")
        self.geometry = geometry
        self.device = runtime.device_or_cpu(device)
        self.config = config or TrackingConfig()
        self.seed = int(seed)
        self.levels_used = geometry.levels
        self.points: list[InitLevel] = []
        self._workspaces: list[InitWorkspace] = []  # per level: the points' fixed data on the device
        self.first_pyramid: ImagePyramid | None = None  # owned copy of the first frame's pyramid
        self.first_frame = None  # the caller's record of the first frame (index, timestamp, exposure, rgb, ...)
        self.first_exposure = 0.0
        self.this_to_next = np.eye(4)
        self.this_to_next_aff = (0.0, 0.0)
        self.snapped = False
        self.frame_id = -1
        self.snapped_at = 0  # frames of the camera from the first frame to the one that snapped (0: not snapped)
        self._first_index: int | None = None  # the first frame's index, when the caller gives indices
        self._sparsity = 5  # DSO's global sparsityFactor (legacy, carried between calls)
        self.alpha_k = self.config.init_alpha_k
        self.alpha_w = self.config.init_alpha_w
        self.reg_weight = self.config.init_reg_weight
        self.coupling_weight = self.config.init_coupling_weight

    @property
    def has_first(self) -> bool:
        return self.frame_id >= 0

    def reset(self) -> None:
        self.points = []
        self._workspaces = []
        self.first_frame = None
        self.frame_id = -1
        self.snapped = False
        self.snapped_at = 0
        self._first_index = None
        self.this_to_next = np.eye(4)
        self.this_to_next_aff = (0.0, 0.0)

    # --------------------------------------------------------------------------------------- first frame
    def set_first(self, pyramid: ImagePyramid, exposure: float = 0.0, frame=None,
                  index: int | None = None) -> InitResult:
        """DSO ``setFirst``: select the points of every level, their neighbours and parents. ``pyramid`` is copied.
        ``index``: the frame's index in the camera's stream (then :meth:`track_frame` counts the camera's frames,
        the dropped ones too). Returns ``FIRST_FRAME``, or ``FAILED`` when level 0 has fewer than
        ``init_min_points`` points."""
        self.reset()
        g = self.geometry
        cfg = self.config
        if self.first_pyramid is None or str(self.first_pyramid.device) != str(pyramid.device):
            self.first_pyramid = ImagePyramid(g, device=pyramid.device)
        import warp as wp
        for lvl in range(g.levels):
            wp.copy(self.first_pyramid.intensity[lvl], pyramid.intensity[lvl])
            wp.copy(self.first_pyramid.dI[lvl], pyramid.dI[lvl])
            wp.copy(self.first_pyramid.grad_sq[lvl], pyramid.grad_sq[lvl])
        self.first_frame = frame
        self.first_exposure = float(exposure or 0.0)
        dens = list(cfg.init_densities)
        w0h0 = g.width * g.height
        pyr = self.first_pyramid
        self.points = []
        for lvl in range(g.levels):
            wl, hl = g.level_size(lvl)
            d = dens[min(lvl, len(dens) - 1)] * w0h0
            dI = pyr.numpy(lvl)
            if lvl == 0:
                sel = PixelSelector(g.width, g.height, min_grad_hist_cut=cfg.min_grad_hist_cut,
                                    min_grad_hist_add=cfg.min_grad_hist_add,
                                    grad_downweight_per_level=cfg.grad_downweight_per_level,
                                    select_direction_distribution=cfg.select_direction_distribution,
                                    initial_potential=3, seed=self.seed, device=self.device)
                lv = [pyr.numpy(i) for i in range(min(3, g.levels))]
                gs = [pyr.grad_sq[i].numpy() for i in range(min(3, g.levels))]
                while len(lv) < 3:
                    lv.append(lv[-1])
                    gs.append(gs[-1])
                ps = sel.select(lv, d, recursions_left=1, th_factor=2.0, grad_sq=gs)
                xy, typ = ps.xy, ps.dso_type
            else:
                m, self._sparsity = make_pixel_status(dI, d, self._sparsity)
                ys, xs = np.nonzero(m)
                xy = np.stack([xs, ys], axis=1)
                typ = np.ones(len(xs), np.int32)
            pad = 2  # DSO patternPadding: keep patternPadding+1 <= x < w - patternPadding - 2
            keep = (xy[:, 0] >= pad + 1) & (xy[:, 0] < wl - pad - 2) & (xy[:, 1] >= pad + 1) & (xy[:, 1] < hl - pad - 2)
            xy, typ = xy[keep], typ[keep]
            self.points.append(_make_level(xy[:, 0] + 0.1, xy[:, 1] + 0.1, typ, dI, wl, hl))
        n0 = self.points[0].n
        if n0 < cfg.init_min_points:
            msg = f"first frame has {n0} points (< init_min_points {cfg.init_min_points})"
            self.reset()
            return InitResult(InitStatus.FAILED, 0, False, np.eye(4), (0.0, 0.0), float("nan"), n0, 0, msg)
        self._make_nn()
        self._workspaces = [InitWorkspace(np.stack([p.u, p.v], axis=1), p.ref_color, self.device,
                                          neighbours=p.neighbours) for p in self.points]
        self.frame_id = 0
        self.snapped_at = 0
        self._first_index = None if index is None else int(index)
        return InitResult(InitStatus.FIRST_FRAME, 0, False, np.eye(4), (0.0, 0.0), float("nan"), n0, n0)

    def _make_nn(self) -> None:
        """DSO ``makeNN``: 10 nearest neighbours on the level (the point itself included, as nanoflann returns it)
        and the nearest point on the next level to ``0.5 p - 0.25``."""
        trees = [cKDTree(np.stack([p.u, p.v], axis=1)) if p.n else None for p in self.points]
        for lvl, p in enumerate(self.points):
            if p.n == 0:
                continue
            k = min(NN, p.n)
            _, idx = trees[lvl].query(np.stack([p.u, p.v], axis=1), k=k)
            idx = np.asarray(idx).reshape(p.n, k)
            p.neighbours[:, :k] = idx
            if lvl + 1 < len(self.points) and trees[lvl + 1] is not None:
                q = np.stack([p.u, p.v], axis=1) * 0.5 - 0.25
                _, par = trees[lvl + 1].query(q, k=1)
                p.parent[:] = par
            else:
                p.parent[:] = -1

    # ------------------------------------------------------------------------------------------- per frame
    def track_frame(self, pyramid: ImagePyramid, exposure: float = 0.0, index: int | None = None) -> InitResult:
        """DSO ``trackFrame``: align the new frame to the first, coarse to fine; ``INITIALIZED`` once the
        translation has been large enough (snapped) for ``init_frames_after_snap`` more frames. ``index``: the
        frame's index in the camera's stream (with the first frame's, :meth:`set_first`): the frames after snapping
        and ``init_max_frames`` count the camera's frames, the ones dropped before reaching here too; without,
        the frames aligned."""
        if not self.has_first:
            raise RuntimeError("CoarseInitializer.track_frame before set_first")
        cfg = self.config
        top = self.levels_used - 1
        if not self.snapped:
            self.this_to_next[:3, 3] = 0.0
            for p in self.points:
                p.iR[:] = 1.0
                p.idepth_new[:] = 1.0
                p.last_hessian[:] = 0.0
        T = self.this_to_next.copy()
        aff = np.array(self.this_to_next_aff, dtype=np.float64)
        if self.first_exposure > 0 and exposure and exposure > 0:
            aff = np.array([math.log(exposure / self.first_exposure), 0.0])
        new_dI = [pyramid.dI[lvl] for lvl in range(self.levels_used)]
        max_its = cfg.init_max_iterations
        res_old = (0.0, 0.0, 1.0)
        for lvl in range(top, -1, -1):
            if lvl < top:
                self._propagate_down(lvl + 1)
            self._reset_points(lvl)
            res_old, H, b, Hsc, bsc = self._calc_res_and_gs(lvl, new_dI[lvl], T, aff)
            self._apply_step(lvl)
            lam = 0.1
            eps = 1e-4
            fails = 0
            iteration = 0
            p = self.points[lvl]
            wl, hl = self.geometry.level_size(lvl)
            while True:
                Hl = H.copy()
                Hl[np.diag_indices(8)] *= 1.0 + lam
                Hl -= Hsc * (1.0 / (1.0 + lam))
                bl = b - bsc * (1.0 / (1.0 + lam))
                sc = 0.01 / (wl * hl)
                Hl = (WM[:, None] * Hl * WM[None, :]) * sc
                bl = WM * bl * sc
                inc = np.zeros(8)
                try:
                    inc[:6] = -(WM[:6] * np.linalg.solve(Hl[:6, :6], bl[:6]))  # DSO fixAffine = true
                except np.linalg.LinAlgError:
                    inc[:] = 0.0
                if not np.all(np.isfinite(inc)):
                    inc[:] = 0.0
                T_new = se3_exp(inc[:6]) @ T
                aff_new = aff + inc[6:]
                self._do_step(lvl, lam, inc)
                res_new, H_n, b_n, Hsc_n, bsc_n = self._calc_res_and_gs(lvl, new_dI[lvl], T_new, aff_new)
                reg = self._calc_ec(lvl)
                e_new = res_new[0] + res_new[1] + reg[1]
                e_old = res_old[0] + res_old[1] + reg[0]
                if e_old > e_new:
                    if res_new[1] == self.alpha_k * p.n:
                        self.snapped = True
                    H, b, Hsc, bsc = H_n, b_n, Hsc_n, bsc_n
                    res_old = res_new
                    aff, T = aff_new, T_new
                    self._apply_step(lvl)
                    self._opt_reg(lvl)
                    lam = max(lam * 0.5, 1e-4)
                    fails = 0
                else:
                    fails += 1
                    lam = min(lam * 4.0, 1e4)
                if not (np.linalg.norm(inc) > eps) or iteration >= max_its[min(lvl, len(max_its) - 1)] or fails >= 2:
                    break
                iteration += 1
        self.this_to_next = T
        self.this_to_next_aff = (float(aff[0]), float(aff[1]))
        for lvl in range(top):
            self._propagate_up(lvl)
        self.frame_id += 1
        camera_frames = self.frame_id     # frames of the camera since the first: the aligned ones, or by index
        if index is not None and self._first_index is not None:
            camera_frames = max(int(index) - self._first_index, self.frame_id)
        if not self.snapped:
            self.snapped_at = 0
        if self.snapped and self.snapped_at == 0:
            self.snapped_at = camera_frames
        p0 = self.points[0]
        rmse = math.sqrt(res_old[0] / max(res_old[2], 1) / 8.0)
        done = self.snapped and (camera_frames > self.snapped_at + cfg.init_frames_after_snap
                                 or np.linalg.norm(T[:3, 3]) >= cfg.init_done_translation)
        status = InitStatus.INITIALIZED if done else InitStatus.TRACKING
        msg = ""
        if not done and not self.snapped and camera_frames >= cfg.init_max_frames:
            status = InitStatus.FAILED
            msg = f"no parallax after {camera_frames} frames (translation {np.linalg.norm(T[:3, 3]):.4f})"
        if not done and not (rmse <= cfg.init_max_rmse):
            status = InitStatus.FAILED
            msg = f"level-0 RMSE {rmse:.1f} above init_max_rmse {cfg.init_max_rmse:g}: the frames do not match"
        if not np.all(np.isfinite(T)):
            status = InitStatus.FAILED
            msg = "the initialiser's pose became non-finite"
        return InitResult(status, self.frame_id, self.snapped, T.copy(), self.this_to_next_aff, rmse, p0.n,
                          int(p0.is_good.sum()), msg)

    # ---------------------------------------------------------------------------------- DSO's internals
    def _calc_res_and_gs(self, lvl: int, dI_new, T: np.ndarray, aff: np.ndarray):
        """DSO ``calcResAndGS``: energies, the 8x8 pose system and its Schur part, per-point ``jb_new``
        (:func:`mgso_kernels.initializer.init_system`), plus the pose regulariser."""
        p = self.points[lvl]
        cam = self.geometry.level_camera(lvl)
        wl, hl = self.geometry.level_size(lvl)
        npts = p.n
        t = T[:3, 3]
        # regulariser (DSO: EAlpha is never filled, so its energy is alpha_w |t|^2 per point)
        alpha_energy = self.alpha_w * (float(t @ t) * npts)
        if alpha_energy > self.alpha_k * npts:
            alpha_opt = 0.0
            alpha_energy = self.alpha_k * npts
        else:
            alpha_opt = self.alpha_w
        ws = self._workspaces[lvl]
        params = ws.params(T, aff, cam.fx, cam.fy, cam.cx, cam.cy, wl, hl, huber_th=self.config.huber_th,
                           max_energy=8 * self.config.outlier_th * 20, alpha_opt=alpha_opt,
                           coupling_weight=self.coupling_weight)
        s = init_system(ws, dI_new, params, idepth=p.idepth_new, is_good=p.is_good,
                        energy=p.energy, iR=p.iR, energy_new=p.energy_new, is_good_new=p.is_good_new,
                        jb_new=p.jb_new, maxstep=p.maxstep, last_hessian_new=p.last_hessian_new)
        H, b = s.H, s.b
        H[0, 0] += alpha_opt * npts
        H[1, 1] += alpha_opt * npts
        H[2, 2] += alpha_opt * npts
        tlog = se3_log(T)[:3]
        b[:3] += tlog * alpha_opt * npts
        return (s.energy, alpha_energy, float(npts)), H, b, s.Hsc, s.bsc

    def _calc_ec(self, lvl: int) -> tuple[float, float, float]:
        p = self.points[lvl]
        if not self.snapped:
            return 0.0, 0.0, float(p.n)
        g = p.is_good_new
        r_old = p.idepth[g] - p.iR[g]
        r_new = p.idepth_new[g] - p.iR[g]
        return (self.coupling_weight * float(np.sum(r_old * r_old)),
                self.coupling_weight * float(np.sum(r_new * r_new)), float(g.sum()))

    def _opt_reg(self, lvl: int) -> None:
        """DSO ``optReg`` (all points at once from the previous values; see the module text):
        :func:`mgso_kernels.initializer.smooth_idepths`."""
        p = self.points[lvl]
        if not self.snapped:
            p.iR[:] = 1.0
            return
        smooth_idepths(self._workspaces[lvl], is_good=p.is_good, iR=p.iR, idepth=p.idepth,
                       reg_weight=self.reg_weight)

    def _propagate_up(self, src: int) -> None:
        ps, pt = self.points[src], self.points[src + 1]
        g = ps.is_good & (ps.parent >= 0)
        num = np.bincount(ps.parent[g], weights=ps.iR[g] * ps.last_hessian[g], minlength=pt.n)
        den = np.bincount(ps.parent[g], weights=ps.last_hessian[g], minlength=pt.n)
        has = den > 0
        pt.iR[:] = 0.0
        pt.iR[has] = (num[has] / den[has]).astype(np.float32)
        pt.idepth[has] = pt.iR[has]
        pt.is_good[has] = True
        self._opt_reg(src + 1)

    def _propagate_down(self, src: int) -> None:
        ps, pt = self.points[src], self.points[src - 1]
        par = pt.parent
        ok = (par >= 0)
        parc = np.where(ok, par, 0)
        ok &= ps.is_good[parc] & (ps.last_hessian[parc] >= 0.1)
        fresh = ok & ~pt.is_good
        pt.iR[fresh] = ps.iR[parc[fresh]]
        pt.idepth[fresh] = pt.iR[fresh]
        pt.idepth_new[fresh] = pt.iR[fresh]
        pt.last_hessian[fresh] = 0.0
        both = ok & pt.is_good & ~fresh
        lh = pt.last_hessian[both]
        plh = ps.last_hessian[parc[both]]
        new = (pt.iR[both] * lh * 2 + ps.iR[parc[both]] * plh) / (lh * 2 + plh)
        pt.iR[both] = new
        pt.idepth[both] = new
        pt.idepth_new[both] = new
        pt.is_good[fresh] = True
        self._opt_reg(src - 1)

    def _reset_points(self, lvl: int) -> None:
        p = self.points[lvl]
        p.energy[:] = 0.0
        p.idepth_new[:] = p.idepth
        if lvl == self.levels_used - 1:
            bad = np.flatnonzero(~p.is_good)
            if len(bad):
                nb = p.neighbours[bad]
                valid = nb >= 0
                nbc = np.where(valid, nb, 0)
                g = valid & p.is_good[nbc]
                cnt = g.sum(axis=1)
                s = np.sum(np.where(g, p.iR[nbc], 0.0), axis=1)
                fix = cnt > 0
                bi = bad[fix]
                val = (s[fix] / cnt[fix]).astype(np.float32)
                p.is_good[bi] = True
                p.iR[bi] = val
                p.idepth[bi] = val
                p.idepth_new[bi] = val

    def _do_step(self, lvl: int, lam: float, inc: np.ndarray) -> None:
        # over every point, kept where good: gathering the good rows first made the product 8x slower (same values)
        p = self.points[lvl]
        b = p.jb[:, 8] + p.jb[:, :8] @ inc
        step = -b * p.jb[:, 9] / (1.0 + lam)
        maxstep = np.minimum(0.25 * p.maxstep, 1e10)
        step = np.clip(step, -maxstep, maxstep)
        np.copyto(p.idepth_new, np.clip(p.idepth + step, 1e-3, 50.0), casting="unsafe", where=p.is_good)

    def _apply_step(self, lvl: int) -> None:
        p = self.points[lvl]
        bad = ~p.is_good
        np.copyto(p.idepth, p.iR, where=bad)
        np.copyto(p.idepth_new, p.iR, where=bad)
        g = p.is_good.copy()
        np.copyto(p.energy, p.energy_new, where=g[:, None])
        np.copyto(p.idepth, p.idepth_new, where=g)
        np.copyto(p.last_hessian, p.last_hessian_new, where=g)
        np.copyto(p.is_good, p.is_good_new, where=g)
        p.jb, p.jb_new = p.jb_new, p.jb

    # ------------------------------------------------------------------------------------------ handover
    def level0_points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(xy [n, 2] int host pixels, iR [n], type [n])`` of level 0 (DSO ``ImmaturePoint(u + 0.5, v + 0.5)``
        truncates ``x + 0.1 + 0.5`` to ``x``)."""
        p = self.points[0]
        xy = np.stack([np.floor(p.u + 0.5), np.floor(p.v + 0.5)], axis=1).astype(np.int64)
        return xy, p.iR.copy(), p.my_type.astype(np.int32)
