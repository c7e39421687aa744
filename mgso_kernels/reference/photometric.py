"""NumPy twin of :mod:`mgso_kernels.photometric`: the DSO photometric residual, weights and Jacobians, written
out plainly in float64 over arrays of pixels.

The target image is reached through a ``sampler(x, y) -> (I, gx, gy)`` callable so that finite-difference tests
can use an analytic image (whose gradient is exact) while parity tests use the bilinear sampler of the pyramid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .image import bilinear_inside, sample_dI, sample_dI_bilin_derivative

__all__ = ["PATTERN", "Cam", "Pair", "project_pixel", "projection_jacobians", "photometric_residual",
           "dI_sampler", "extract_patterns", "affine_from_to"]

PATTERN = np.array([[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]], dtype=np.float64)

Sampler = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass
class Cam:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass
class Pair:
    R: np.ndarray  # [3, 3] target_from_host rotation
    t: np.ndarray  # [3]
    a_rel: float
    b_h: float
    b_t: float

    @staticmethod
    def from_pose(T: np.ndarray, a_h=0.0, b_h=0.0, a_t=0.0, b_t=0.0, exposure_h=1.0, exposure_t=1.0) -> "Pair":
        a, _ = affine_from_to(a_h, b_h, a_t, b_t, exposure_h, exposure_t)
        T = np.asarray(T, dtype=np.float64)
        return Pair(T[:3, :3].copy(), T[:3, 3].copy(), a, float(b_h), float(b_t))


def affine_from_to(a_h, b_h, a_t, b_t, exposure_h=1.0, exposure_t=1.0):
    if exposure_h == 0 or exposure_t == 0:
        exposure_h = exposure_t = 1.0
    a = np.exp(np.clip(a_t - a_h, -80.0, 80.0)) * exposure_t / exposure_h   # the kernels' float32 range
    return a, b_t - a * b_h


def project_pixel(u, v, idepth, R, t, cam_h: Cam, cam_t: Cam):
    """``(Ku, Kv, un, vn, drescale, hx, hy)`` arrays."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    idepth = np.asarray(idepth, dtype=np.float64)
    hx = (u - cam_h.cx) / cam_h.fx
    hy = (v - cam_h.cy) / cam_h.fy
    h = np.stack([hx, hy, np.ones_like(hx)], axis=-1)
    P = h @ np.asarray(R, dtype=np.float64).T + np.asarray(t, dtype=np.float64) * idepth[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        dr = 1.0 / P[..., 2]
    un = P[..., 0] * dr
    vn = P[..., 1] * dr
    return cam_t.fx * un + cam_t.cx, cam_t.fy * vn + cam_t.cy, un, vn, dr, hx, hy


def projection_jacobians(un, vn, dr, hx, hy, idepth, R, t, cam: Cam):
    """``(dKu_dxi [...,6], dKv_dxi [...,6], dK_didepth [...,2], dKu_dcalib [...,4], dKv_dcalib [...,4])``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    nid = idepth * dr
    fx, fy = cam.fx, cam.fy
    z = np.zeros_like(un)
    dku = np.stack([nid * fx, z, -nid * un * fx, -un * vn * fx, (1 + un * un) * fx, -vn * fx], axis=-1)
    dkv = np.stack([z, nid * fy, -nid * vn * fy, -(1 + vn * vn) * fy, un * vn * fy, un * fy], axis=-1)
    dd = np.stack([dr * (t[0] - t[2] * un) * fx, dr * (t[1] - t[2] * vn) * fy], axis=-1)
    ax = dr * (R[2, 0] * un - R[0, 0])
    ay = dr * (R[2, 1] * un - R[0, 1])
    bx = dr * (R[2, 0] * vn - R[1, 0])
    by = dr * (R[2, 1] * vn - R[1, 1])
    dcu = np.stack([un + hx * ax, fx / fy * hy * ay, 1 + ax, fx / fy * ay], axis=-1)
    dcv = np.stack([fy / fx * hx * bx, vn + hy * by, fy / fx * bx, 1 + by], axis=-1)
    return dku, dkv, dd, dcu, dcv


def dI_sampler(dI: np.ndarray) -> Sampler:
    """Bilinear sampler of an interleaved ``(I, dx, dy)`` image, as the kernels sample it."""
    dI = np.asarray(dI)

    def sample(x, y):
        s = sample_dI(dI, x, y).astype(np.float64)
        return s[..., 0], s[..., 1], s[..., 2]

    return sample


def photometric_residual(u, v, idepth, host_color, host_weight, pair: Pair, cam_h: Cam, cam_t: Cam,
                         sampler: Sampler, huber_th=9.0, grad_c2=2500.0, border_lo=1.1, border_hi=3.0) -> dict:
    """Everything the ``@wp.func`` returns, for arrays of pattern pixels (float64). Status 0 ok, 1 OOB, 2 behind.

    Fields not defined for a status other than OK are 0, as in the kernel.
    """
    u = np.asarray(u, dtype=np.float64)
    shape = u.shape
    host_color = np.broadcast_to(np.asarray(host_color, dtype=np.float64), shape)
    host_weight = np.broadcast_to(np.asarray(host_weight, dtype=np.float64), shape)
    idepth = np.broadcast_to(np.asarray(idepth, dtype=np.float64), shape)
    ku, kv, un, vn, dr, hx, hy = project_pixel(u, v, idepth, pair.R, pair.t, cam_h, cam_t)
    with np.errstate(invalid="ignore"):
        front = dr > 0
        inside = ((ku > border_lo) & (kv > border_lo) & (ku < cam_t.width - border_hi) & (kv < cam_t.height - border_hi)
                  & bilinear_inside(ku, kv, cam_t.width, cam_t.height))
    status = np.where(front, np.where(inside, 0, 1), 2).astype(np.int32)
    ok = status == 0
    I, gx, gy = (np.zeros(shape) for _ in range(3))
    if ok.any():
        si, sx, sy = sampler(ku[ok], kv[ok])
        I[ok], gx[ok], gy[ok] = si, sx, sy
    finite = np.isfinite(I) & np.isfinite(gx) & np.isfinite(gy)
    status[ok & ~finite] = 1
    ok = status == 0
    hc = host_color - pair.b_h
    r = (I - pair.b_t) - pair.a_rel * hc
    absr = np.abs(r)
    with np.errstate(divide="ignore", invalid="ignore"):
        hw = np.where(absr < huber_th, 1.0, huber_th / absr)
    if grad_c2 > 0:
        w = np.sqrt(grad_c2 / (grad_c2 + gx * gx + gy * gy))
        w = np.where(host_weight >= 0, 0.5 * (w + host_weight), w)
        gw = w * w
    else:
        gw = np.ones(shape)
    dku, dkv, dd, dcu, dcv = projection_jacobians(un, vn, dr, hx, hy, idepth, pair.R, pair.t, cam_t)
    out = dict(
        status=status,
        residual=r,
        huber_weight=hw,
        grad_weight=gw,
        energy=gw * hw * r * r * (2 - hw),
        target_xy=np.stack([ku, kv], axis=-1),
        new_idepth=idepth * dr,
        target_grad=np.stack([gx, gy], axis=-1),
        J_pose=gx[..., None] * dku + gy[..., None] * dkv,
        J_aff=np.stack([-pair.a_rel * hc, -np.ones(shape), pair.a_rel * hc, np.full(shape, pair.a_rel)], axis=-1),
        J_idepth=gx * dd[..., 0] + gy * dd[..., 1],
        J_calib=gx[..., None] * dcu + gy[..., None] * dcv,
    )
    for k, val in out.items():
        if k == "status":
            continue
        mask = ok.reshape(ok.shape + (1,) * (val.ndim - ok.ndim))
        out[k] = np.where(mask, val, 0.0)
    return out


def extract_patterns(dI_h: np.ndarray, host_uv: np.ndarray, grad_c2: float = 2500.0) -> dict:
    """Host pattern of new points: ``color [N,8]``, ``weight [N,8]``, ``grad_h [N,3]``, ``valid [N]``."""
    uv = np.asarray(host_uv, dtype=np.float64)
    x = uv[:, None, 0] + PATTERN[None, :, 0]
    y = uv[:, None, 1] + PATTERN[None, :, 1]
    h, w = dI_h.shape[:2]
    inside = bilinear_inside(x, y, w, h)
    s = sample_dI_bilin_derivative(np.asarray(dI_h), x.astype(dI_h.dtype), y.astype(dI_h.dtype)).astype(np.float64)
    good = inside & np.all(np.isfinite(s), axis=-1)
    s[~good] = 0
    g = np.stack([(s[..., 1] ** 2).sum(1), (s[..., 1] * s[..., 2]).sum(1), (s[..., 2] ** 2).sum(1)], axis=-1)
    return dict(color=s[..., 0], weight=np.sqrt(grad_c2 / (grad_c2 + s[..., 1] ** 2 + s[..., 2] ** 2)),
                grad_h=g, valid=good.all(axis=1))
