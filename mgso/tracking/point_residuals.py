"""Photometric residuals of points against window keyframes, vectorised in NumPy over (point, target) pairs x the
8 pattern pixels, with the inverse-depth derivative: the per-point work of activation (DSO ``ImmaturePoint::
linearizeResidual``) and of the fixed-window depth refinement (DSO ``PointFrameResidual::linearize``, depth part).

Geometry and weights are the ones of :mod:`mgso_kernels.photometric` (DSO's): pattern pixel ``(u+dx, v+dy)`` of the
host is back-projected with the point's inverse depth, moved by ``target_from_host``, projected, and must land in
``1.1 < x < w - 3`` (the window's margins) in front of the camera; the residual is ``I_t - (a_rel I_h + b_rel)``;
Huber weight at 9; the gradient weight is the host's (``weight_mode="host"``, immature points) or the mean of host and
target weights (``"window"``), squared.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mgso_kernels.photometric import PATTERN_NP

from ..window.window import Window
from .sampling import inside, sample_level

__all__ = ["PairSet", "make_pairs", "PairResiduals", "evaluate_pairs"]


@dataclass
class PairSet:
    """``M`` (point, target) pairs: ``pt [M]`` index into the caller's point arrays, ``tg [M]`` target slot, and the
    relative pose / brightness of each pair at the current estimates."""

    pt: np.ndarray  # [M] int64
    tg: np.ndarray  # [M] int64 target slot
    R: np.ndarray  # [M, 3, 3] target_from_host rotation
    t: np.ndarray  # [M, 3]
    aff: np.ndarray  # [M, 2] (a_rel, b_rel): I_t ~ a_rel I_h + b_rel

    def __len__(self) -> int:
        return len(self.pt)


def make_pairs(window: Window, hosts: np.ndarray, pt: np.ndarray, tg: np.ndarray) -> PairSet:
    """Pairs ``(pt[i], tg[i])`` for points with host slots ``hosts`` (indexed by ``pt``)."""
    pt = np.asarray(pt, dtype=np.int64)
    tg = np.asarray(tg, dtype=np.int64)
    M = len(pt)
    R = np.zeros((M, 3, 3))
    t = np.zeros((M, 3))
    aff = np.zeros((M, 2))
    hp = np.asarray(hosts)[pt] if M else np.zeros(0, np.int64)
    if M:
        key = hp * 64 + tg
        for k in np.unique(key):
            sel = key == k
            hs, ts = int(k // 64), int(k % 64)
            T = window.target_from_host(hs, ts)
            R[sel] = T[:3, :3]
            t[sel] = T[:3, 3]
            aff[sel] = window.affine_rel(hs, ts)
    return PairSet(pt, tg, R, t, aff)


@dataclass
class PairResiduals:
    """Per pair and pattern pixel ``[M, 8]`` (``ok [M]``: all 8 pixels in bounds, in front, finite)."""

    ok: np.ndarray  # [M] bool
    r: np.ndarray  # [M, 8] residual
    huber: np.ndarray  # [M, 8] Huber weight
    grad_w: np.ndarray  # [M, 8] squared gradient weight
    d_idepth: np.ndarray  # [M, 8] dr / d inverse depth
    grad_sq: np.ndarray  # [M, 8] |grad I_t|^2 at the projection
    centre: np.ndarray  # [M, 3] (Ku, Kv, new inverse depth) of the pattern centre in the target

    @property
    def energy(self) -> np.ndarray:
        """``[M]`` sum over the pattern of ``grad_w hw r^2 (2 - hw)`` (0 where not ok)."""
        e = np.sum(self.grad_w * self.huber * self.r * self.r * (2.0 - self.huber), axis=1)
        return np.where(self.ok, e, 0.0)


def evaluate_pairs(window: Window, pairs: PairSet, uv: np.ndarray, color: np.ndarray, weight: np.ndarray,
                   idepth: np.ndarray, *, weight_mode: str = "window", huber_th: float = 9.0,
                   grad_c2: float = 2500.0, border_lo: float = 1.1, border_hi: float = 3.0) -> PairResiduals:
    """Residuals of the pairs at the points' ``idepth [m]`` (``uv [m, 2]``, ``color/weight [m, 8]`` host pattern)."""
    if weight_mode not in ("window", "host"):
        raise ValueError(f"weight_mode must be 'window' or 'host', got {weight_mode!r}")
    cam = window.camera
    w, h = window.width, window.height
    pt = pairs.pt
    M = len(pt)
    R, t = pairs.R, pairs.t
    px = uv[pt, 0][:, None].astype(np.float64) + PATTERN_NP[None, :, 0]  # [M, 8]
    py = uv[pt, 1][:, None].astype(np.float64) + PATTERN_NP[None, :, 1]
    hx = (px - cam.cx) / cam.fx
    hy = (py - cam.cy) / cam.fy
    idp = np.asarray(idepth, dtype=np.float64)[pt][:, None]
    Px = R[:, None, 0, 0] * hx + R[:, None, 0, 1] * hy + R[:, None, 0, 2] + t[:, None, 0] * idp
    Py = R[:, None, 1, 0] * hx + R[:, None, 1, 1] * hy + R[:, None, 1, 2] + t[:, None, 1] * idp
    Pz = R[:, None, 2, 0] * hx + R[:, None, 2, 1] * hy + R[:, None, 2, 2] + t[:, None, 2] * idp
    with np.errstate(divide="ignore", invalid="ignore"):
        dres = 1.0 / Pz
        un = Px * dres
        vn = Py * dres
    ku = cam.fx * un + cam.cx
    kv = cam.fy * vn + cam.cy
    okp = (dres > 0) & inside(ku, kv, w, h, border_lo, border_hi)
    s = np.zeros((M, 8, 3), np.float32)
    for slot in np.unique(pairs.tg):
        sel = pairs.tg == slot
        s[sel] = sample_level(window.pyramids[int(slot)].dI[0], ku[sel], kv[sel])
    okp &= np.isfinite(s).all(axis=2)
    ok = okp.all(axis=1)
    s = np.where(okp[..., None], s, 0.0)
    r = s[..., 0] - (pairs.aff[:, 0:1] * color[pt] + pairs.aff[:, 1:2])
    ar = np.abs(r)
    hw = np.where(ar < huber_th, 1.0, huber_th / np.maximum(ar, 1e-12))
    g2 = s[..., 1].astype(np.float64) ** 2 + s[..., 2].astype(np.float64) ** 2
    wh = weight[pt].astype(np.float64)
    if weight_mode == "host":
        gw = wh * wh
    else:
        wt = np.sqrt(grad_c2 / (grad_c2 + g2))
        gw = (0.5 * (wt + wh)) ** 2
    d_id = np.where(okp, s[..., 1] * cam.fx * dres * (t[:, 0:1] - t[:, 2:3] * un)
                    + s[..., 2] * cam.fy * dres * (t[:, 1:2] - t[:, 2:3] * vn), 0.0)
    r = np.where(okp, r, 0.0)
    centre = np.stack([ku[:, 4], kv[:, 4], idp[:, 0] * dres[:, 4]], axis=1)  # pattern pixel 4 is (0, 0)
    return PairResiduals(ok, r, hw, gw, d_id, g2, centre)
