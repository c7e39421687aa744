"""Sliding-window photometric bundle adjustment: residuals, Jacobians and Hessian blocks of every (point, target)
pair, and the Schur complement over the points' inverse depths (DSO ``PointFrameResidual::linearize``,
``AccumulatedTopHessian`` and ``AccumulatedSCHessian``).

Parameters
----------
A **pair** is one active point (hosted in keyframe ``h``) and one target keyframe ``t``. Its residual depends on the
10 *pair parameters* ``(xi_rel (6), a_t, b_t, a_h, b_h)`` -- the left se3 perturbation ``(v, w)`` of
``target_from_host`` and the two frames' absolute affine brightness -- and on the point's inverse depth ``d``.
A **keyframe** has 8 *frame parameters* ``(xi (6), a, b)``: the left perturbation of its ``world_to_cam`` about its
linearisation point and its affine brightness. With ``T_th = T_t T_h^-1`` a perturbation of the target moves
``T_th`` by ``exp(xi_t)`` and one of the host by ``exp(-Ad(T_th) xi_h)``, so the pose part of the pair parameters is
``xi_rel = xi_t - Ad(T_th) xi_h`` (DSO ``EnergyFunctional::setAdjointsF``), taken at the linearisation point. Pairs
of the same (host, target) keyframes share a **key**; a key holds ``target_from_host`` at the current estimate and
at the linearisation point, and the relative brightness.

Residual (:mod:`mgso_kernels.photometric`, DSO's): for each of the 8 pattern pixels, projected with the *current*
``target_from_host`` and inverse depth, ``r = (I_t - b_t) - a_rel (I_h - b_h)``, Huber weight ``hw`` (9), gradient
weight ``w = (w_t + w_h) / 2`` with ``w_t = sqrt(c2 / (c2 + |grad I_t|^2))``, energy ``w^2 hw r^2 (2 - hw)`` and
system weight ``W = hw w^2``. Jacobians as DSO: the geometric part ``d(Ku, Kv)/d(xi_rel, d)`` once per pair at the
pattern centre **at the linearisation point** of the keyframes (first-estimate Jacobians; the inverse depth is the
current one: DSO moves a point's linearisation point every step), chained with each pattern pixel's target gradient
at the current projection; affine Jacobians ``(-a_rel (I_h - b_h), -1, a_rel (I_h - b_h), a_rel)``.

A pair is ``OOB`` when a pattern pixel falls outside ``border_lo < x < width - border_hi`` (DSO 1.1 / 3), behind the
camera or on a non-finite sample, and ``OUTLIER`` when its energy exceeds its key's threshold (DSO ``max(host, target
frameEnergyTH)``) or ``sum (W |grad I_t|)^2 < 2`` (DSO ``wJI2_sum``); only ``IN`` pairs enter the system, the others
report the threshold as their energy (DSO ``linearize``).

Reductions (no atomics; bitwise equal single, split over CPU cores or on a GPU):

- :func:`linearize_window`: one thread per *block* of pairs of one key (pairs sorted by key) accumulates the key's
  10x10 block ``H_cc = sum W J_c J_c^T`` and ``b_c = sum W J_c r`` in float64 and writes one row of a partial-sum
  buffer; per pair it writes ``H_cd = sum W J_c J_d`` (10), ``H_dd = sum W J_d^2`` and ``b_d = sum W J_d r``. The
  launch runs once per target keyframe (each with its image).
- :func:`schur_points`: one thread per block of points (pairs sorted by point) sums each point's ``H_dd``, ``b_d`` and
  its frame-point block in absolute frame parameters ``w_p [8 K]`` (adjoints applied), writes them, and accumulates
  the Schur terms ``w_p w_p^T / H_dd`` and ``w_p b_d / H_dd`` into its partial row.

The caller (``mgso.window.energy``) sums the partial rows, maps the key blocks to absolute parameters and solves the
reduced camera system ``(H_cc - H_sc) x_c = -(b_c - b_sc)``, then back-substitutes ``x_d = -(b_d + w_p . x_c) / H_dd``.
No scaling is applied here (DSO's ``SCALE_*`` preconditioning is the solver's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from . import runtime
from .image import bilinear_inside, sample_dI
from .photometric import (PATTERN, Intrinsics, gradient_weight, huber_weight, in_margins, inverse_K, project_pixel,
                          project_RKi, projection_jacobians)

__all__ = [
    "PAIR_PARAMS", "FRAME_PARAMS", "NUM_KEY_SLOTS", "SLOT_H", "SLOT_B", "PairState", "WindowParams",
    "make_window_params", "WindowKeys", "PairLinearization", "PointSchur", "linearize_window", "schur_points",
    "linearize_pairs_kernel", "schur_points_kernel", "vec10d", "mat1010d",
]

wp.set_module_options({"enable_backward": False})

PAIR_PARAMS = 10  # (v, w) of target_from_host, a_t, b_t, a_h, b_h
FRAME_PARAMS = 8  # (v, w) of world_to_cam, a, b
SLOT_H = 0  # 100: the key's H_cc, row-major
SLOT_B = 100  # 10: b_c
NUM_KEY_SLOTS = 110

vec10d = wp.types.vector(length=10, dtype=wp.float64)
mat1010d = wp.types.matrix(shape=(10, 10), dtype=wp.float64)


class PairState:
    """Outcome of a pair (values equal :class:`mgso.window.window.ResidualState`)."""

    IN = 1
    OOB = 2
    OUTLIER = 3


STATE_IN = wp.constant(1)
STATE_OOB = wp.constant(2)
STATE_OUTLIER = wp.constant(3)


@wp.struct
class WindowParams:
    cam: Intrinsics  # level-0 intrinsics and image size (shared by all keyframes)
    huber_th: float  # DSO setting_huberTH = 9
    grad_c2: float  # DSO setting_outlierTHSumComponent = 50^2
    border_lo: float  # DSO projectPoint: x > 1.1
    border_hi: float  # ... x < width - 3
    min_wji2: float  # DSO: outlier when sum (W |grad I_t|)^2 < 2


# ------------------------------------------------------------------------------------------------ kernels
@wp.kernel
def linearize_pairs_kernel(offset: int,
                           block_base: int,  # first block of this launch (one launch per target)
                           block_start: wp.array(dtype=wp.int32),  # [B] range into order
                           block_end: wp.array(dtype=wp.int32),  # [B]
                           order: wp.array(dtype=wp.int32),  # [M] pair indices sorted by key
                           pair_point: wp.array(dtype=wp.int32),  # [M] point index
                           pair_key: wp.array(dtype=wp.int32),  # [M] key index
                           key_R: wp.array(dtype=wp.mat33),  # [nk] target_from_host rotation, current
                           key_t: wp.array(dtype=wp.vec3),  # [nk] translation, current
                           key_R0: wp.array(dtype=wp.mat33),  # [nk] at the linearisation point
                           key_t0: wp.array(dtype=wp.vec3),  # [nk]
                           key_aff: wp.array(dtype=wp.vec3),  # [nk] (a_rel, b_h, b_t), current
                           key_energy_th: wp.array(dtype=float),  # [nk] outlier threshold (8-pixel energy)
                           uv: wp.array(dtype=wp.vec2),  # [n] host pixel of the point (level 0)
                           idepth: wp.array(dtype=float),  # [n] host inverse depth
                           color: wp.array2d(dtype=float),  # [n, 8] host intensity per pattern pixel
                           weight: wp.array2d(dtype=float),  # [n, 8] host gradient weight per pattern pixel
                           dI_t: wp.array2d(dtype=wp.vec3),  # [H, W] (I, dx, dy) of this launch's target
                           params: WindowParams,
                           pair_state: wp.array(dtype=wp.int32),  # [M] out: PairState
                           pair_energy: wp.array(dtype=wp.float64),  # [M] out: energy (threshold unless IN)
                           pair_hcd: wp.array(dtype=vec10d),  # [M] out: sum W J_c J_d (0 unless IN)
                           pair_hdd: wp.array(dtype=wp.float64),  # [M] out: sum W J_d^2
                           pair_bd: wp.array(dtype=wp.float64),  # [M] out: sum W J_d r
                           partials: wp.array2d(dtype=wp.float64)):  # [B, NUM_KEY_SLOTS] out
    blk = block_base + offset + wp.tid()
    cam = params.cam
    Ki = inverse_K(cam)
    Hb = mat1010d()
    bb = vec10d()
    for q in range(block_start[blk], block_end[blk]):
        j = order[q]
        p = pair_point[j]
        k = pair_key[j]
        R = key_R[k]
        t = key_t[k]
        aff = key_aff[k]
        a_rel = aff[0]
        b_h = aff[1]
        b_t = aff[2]
        c = uv[p]
        d = idepth[p]
        RKi = R * Ki
        # first-estimate geometry at the pattern centre
        kk0, n0, h0 = project_pixel(c[0], c[1], d, key_R0[k], key_t0[k], cam, cam)
        dku, dkv, dd, dcu, dcv = projection_jacobians(n0, h0, d, key_R0[k], key_t0[k], cam)
        ok = n0[2] > 0.0
        Hp = mat1010d()
        bp = vec10d()
        hcd = vec10d()
        hdd = wp.float64(0.0)
        bd = wp.float64(0.0)
        energy = float(0.0)
        wji2 = float(0.0)
        for i in range(8):
            kk, nrm = project_RKi(c[0] + PATTERN[i, 0], c[1] + PATTERN[i, 1], d, RKi, t, cam)
            ku = kk[0]
            kv = kk[1]
            inside = in_margins(ku, kv, cam.width, cam.height, params.border_lo, params.border_hi)
            inside = inside and bilinear_inside(ku, kv, cam.width, cam.height) and nrm[2] > 0.0
            s = sample_dI(dI_t, ku, kv)  # clamped: memory-safe even when outside
            good = inside and wp.isfinite(s)
            if not good:
                ok = False
            hc = color[p, i] - b_h
            r = wp.where(good, (s[0] - b_t) - a_rel * hc, 0.0)
            gx = wp.where(good, s[1], 0.0)
            gy = wp.where(good, s[2], 0.0)
            g2 = gx * gx + gy * gy
            w = 0.5 * (gradient_weight(g2, params.grad_c2) + weight[p, i])
            hw = huber_weight(r, params.huber_th)
            W = hw * w * w
            energy += w * w * hw * r * r * (2.0 - hw)
            wji2 += W * W * g2
            jc = vec10d(wp.float64(gx * dku[0] + gy * dkv[0]), wp.float64(gx * dku[1] + gy * dkv[1]),
                        wp.float64(gx * dku[2] + gy * dkv[2]), wp.float64(gx * dku[3] + gy * dkv[3]),
                        wp.float64(gx * dku[4] + gy * dkv[4]), wp.float64(gx * dku[5] + gy * dkv[5]),
                        wp.float64(-a_rel * hc), wp.float64(-1.0), wp.float64(a_rel * hc), wp.float64(a_rel))
            jd = wp.float64(gx * dd[0] + gy * dd[1])
            Wd = wp.float64(W)
            rd = wp.float64(r)
            Hp += wp.outer(Wd * jc, jc)
            bp += (Wd * rd) * jc
            hcd += (Wd * jd) * jc
            hdd += Wd * jd * jd
            bd += Wd * jd * rd
        th = key_energy_th[k]
        state = int(STATE_IN)
        if not ok:
            state = STATE_OOB
        elif energy > th or wji2 < params.min_wji2:
            state = STATE_OUTLIER
        inl = wp.where(state == STATE_IN, wp.float64(1.0), wp.float64(0.0))
        Hb += inl * Hp
        bb += inl * bp
        pair_state[j] = state
        pair_energy[j] = wp.where(state == STATE_IN, wp.float64(energy), wp.float64(th))
        pair_hcd[j] = inl * hcd
        pair_hdd[j] = inl * hdd
        pair_bd[j] = inl * bd
    for a in range(10):
        for b in range(10):
            partials[blk, SLOT_H + a * 10 + b] = Hb[a, b]
        partials[blk, SLOT_B + a] = bb[a]


@wp.kernel
def schur_points_kernel(offset: int,
                        points_per_block: int,
                        point_start: wp.array(dtype=wp.int32),  # [n + 1] pair range of each point (point-major)
                        pair_key: wp.array(dtype=wp.int32),  # [M]
                        pair_state: wp.array(dtype=wp.int32),  # [M]
                        pair_hcd: wp.array(dtype=vec10d),  # [M]
                        pair_hdd: wp.array(dtype=wp.float64),  # [M]
                        pair_bd: wp.array(dtype=wp.float64),  # [M]
                        key_host: wp.array(dtype=wp.int32),  # [nk] host slot
                        key_target: wp.array(dtype=wp.int32),  # [nk] target slot
                        key_adj: wp.array2d(dtype=wp.float64),  # [nk, 36] Ad(target_from_host) at lin. point
                        point_extra_h: wp.array(dtype=wp.float64),  # [n] added to H_dd (prior, damping)
                        point_extra_b: wp.array(dtype=wp.float64),  # [n] added to b_d (prior gradient)
                        point_hdd: wp.array(dtype=wp.float64),  # [n] out: H_dd (with the extra term)
                        point_bd: wp.array(dtype=wp.float64),  # [n] out: b_d
                        point_w: wp.array2d(dtype=wp.float64),  # [n, 8 K] out: frame-point block (zeroed)
                        sc_partials: wp.array2d(dtype=wp.float64)):  # [Bp, 8K * 8K + 8K] out
    blk = offset + wp.tid()
    n = point_start.shape[0] - 1
    nf = point_w.shape[1]
    nslots = nf // 8
    start = blk * points_per_block
    end = wp.min(start + points_per_block, n)
    for p in range(start, end):
        hdd = point_extra_h[p]
        bd = point_extra_b[p]
        touched = int(0)
        for j in range(point_start[p], point_start[p + 1]):
            if pair_state[j] != STATE_IN:
                continue
            k = pair_key[j]
            hcd = pair_hcd[j]
            hdd += pair_hdd[j]
            bd += pair_bd[j]
            ht = key_host[k]
            tg = key_target[k]
            touched = touched | (1 << ht) | (1 << tg)
            for a in range(6):
                point_w[p, 8 * tg + a] = point_w[p, 8 * tg + a] + hcd[a]
                acc = wp.float64(0.0)
                for m in range(6):
                    acc += key_adj[k, m * 6 + a] * hcd[m]
                point_w[p, 8 * ht + a] = point_w[p, 8 * ht + a] - acc
            point_w[p, 8 * tg + 6] = point_w[p, 8 * tg + 6] + hcd[6]
            point_w[p, 8 * tg + 7] = point_w[p, 8 * tg + 7] + hcd[7]
            point_w[p, 8 * ht + 6] = point_w[p, 8 * ht + 6] + hcd[8]
            point_w[p, 8 * ht + 7] = point_w[p, 8 * ht + 7] + hcd[9]
        if hdd < wp.float64(1e-10):  # DSO AccumulatedSCHessian::addPoint
            hdd = wp.float64(1e-10)
        point_hdd[p] = hdd
        point_bd[p] = bd
        ih = wp.float64(1.0) / hdd
        for s1 in range(nslots):
            if (touched & (1 << s1)) == 0:
                continue
            for a in range(8):
                wa = point_w[p, 8 * s1 + a] * ih
                sc_partials[blk, nf * nf + 8 * s1 + a] = sc_partials[blk, nf * nf + 8 * s1 + a] + wa * bd
                for s2 in range(nslots):
                    if (touched & (1 << s2)) == 0:
                        continue
                    for b in range(8):
                        col = 8 * s2 + b
                        sc_partials[blk, (8 * s1 + a) * nf + col] = (sc_partials[blk, (8 * s1 + a) * nf + col]
                                                                      + wa * point_w[p, col])


# ---------------------------------------------------------------------------------------------- launchers
def make_window_params(fx: float, fy: float, cx: float, cy: float, width: int, height: int, *,
                       huber_th: float = 9.0, grad_c2: float = 2500.0, border_lo: float = 1.1,
                       border_hi: float = 3.0, min_wji2: float = 2.0) -> WindowParams:
    """Level-0 intrinsics and DSO's residual constants (``setting_huberTH``, ``setting_outlierTHSumComponent``,
    ``projectPoint``'s margins, the ``wJI2_sum < 2`` outlier test)."""
    if not (fx > 0 and fy > 0) or width < 8 or height < 8:
        raise ValueError(f"bad intrinsics fx={fx} fy={fy} size {width}x{height}")
    p = WindowParams()
    c = Intrinsics()
    c.fx, c.fy, c.cx, c.cy, c.width, c.height = float(fx), float(fy), float(cx), float(cy), int(width), int(height)
    p.cam = c
    p.huber_th, p.grad_c2 = float(huber_th), float(grad_c2)
    p.border_lo, p.border_hi, p.min_wji2 = float(border_lo), float(border_hi), float(min_wji2)
    return p


@dataclass
class WindowKeys:
    """The (host, target) keyframe pairs of a window, ``nk`` of them (NumPy, float64)."""

    host: np.ndarray  # [nk] int32 host slot
    target: np.ndarray  # [nk] int32 target slot
    R: np.ndarray  # [nk, 3, 3] target_from_host rotation at the current estimate
    t: np.ndarray  # [nk, 3]
    R0: np.ndarray  # [nk, 3, 3] at the linearisation point
    t0: np.ndarray  # [nk, 3]
    aff: np.ndarray  # [nk, 3] (a_rel, b_h, b_t) at the current estimate
    energy_th: np.ndarray  # [nk] outlier threshold of the pair's 8-pixel energy
    adj: np.ndarray  # [nk, 6, 6] Ad(target_from_host) at the linearisation point, (v, w) order

    def __len__(self) -> int:
        return len(self.host)


@dataclass
class PairLinearization:
    """Per pair and per key results of :func:`linearize_window` (NumPy)."""

    state: np.ndarray  # [M] int32 PairState
    energy: np.ndarray  # [M] float64 (the key's threshold unless IN)
    hcd: np.ndarray  # [M, 10] float64
    hdd: np.ndarray  # [M] float64
    bd: np.ndarray  # [M] float64
    key_H: np.ndarray  # [nk, 10, 10] float64 sum over IN pairs
    key_b: np.ndarray  # [nk, 10]


@dataclass
class PointSchur:
    """Per point results of :func:`schur_points` and the summed Schur terms (NumPy float64)."""

    hdd: np.ndarray  # [n] H_dd including the extra term (at least 1e-10)
    bd: np.ndarray  # [n]
    w: np.ndarray  # [n, 8 K] frame-point block in absolute frame parameters (slot-major)
    H_sc: np.ndarray  # [8 K, 8 K] sum w w^T / H_dd
    b_sc: np.ndarray  # [8 K] sum w b_d / H_dd


def _arr(a, dtype, shape, name):
    a = np.ascontiguousarray(a, dtype=dtype)
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    return a


def _blocks_by_key(pair_key: np.ndarray, pair_target: np.ndarray, pairs_per_block: int):
    """Pairs sorted by (target, key); blocks of at most ``pairs_per_block`` pairs that never straddle a key.
    Returns ``order, block_start, block_end, block_key, target_block_ranges``."""
    order = np.lexsort((pair_key, pair_target)).astype(np.int32)
    keys = pair_key[order]
    M = len(order)
    if M == 0:
        return order, np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.int64), {}
    cuts = np.flatnonzero(np.diff(keys)) + 1
    seg_start = np.concatenate([[0], cuts])
    seg_end = np.concatenate([cuts, [M]])
    starts, ends = [], []
    for s, e in zip(seg_start, seg_end):
        b = np.arange(s, e, pairs_per_block)
        starts.append(b)
        ends.append(np.minimum(b + pairs_per_block, e))
    bs = np.concatenate(starts).astype(np.int32)
    be = np.concatenate(ends).astype(np.int32)
    bkey = keys[bs].astype(np.int64)
    btarget = pair_target[order][bs]
    ranges = {}
    for tg in np.unique(btarget):
        idx = np.flatnonzero(btarget == tg)
        ranges[int(tg)] = (int(idx[0]), int(idx[-1]) + 1)
    return order, bs, be, bkey, ranges


def linearize_window(params: WindowParams, keys: WindowKeys, pair_point: np.ndarray, pair_key: np.ndarray,
                     uv: np.ndarray, idepth: np.ndarray, color: np.ndarray, weight: np.ndarray,
                     target_images: dict, *, pairs_per_block: int = 32, device: str | None = None
                     ) -> PairLinearization:
    """Linearise ``M`` pairs (see the module text).

    ``pair_point [M]`` index into the point arrays ``uv [n, 2]`` (pixels), ``idepth [n]``, ``color/weight [n, 8]``;
    ``pair_key [M]`` index into ``keys``; ``target_images``: target slot -> ``wp.array2d(vec3) [H, W]`` level-0
    ``(I, dx, dy)`` (a keyframe pyramid's ``dI[0]``). Returns per pair and per key float64 NumPy arrays.
    """
    device = device or runtime.default_device()
    nk = len(keys)
    M = int(np.asarray(pair_point).shape[0])
    n = int(np.asarray(uv).shape[0])
    pp = _arr(pair_point, np.int32, (M,), "pair_point")
    pk = _arr(pair_key, np.int32, (M,), "pair_key")
    if M and (pk.min() < 0 or pk.max() >= nk or pp.min() < 0 or pp.max() >= n):
        raise ValueError("linearize_window: pair_point / pair_key out of range")
    uv = _arr(uv, np.float32, (n, 2), "uv")
    idp = _arr(idepth, np.float32, (n,), "idepth")
    col = _arr(color, np.float32, (n, 8), "color")
    wgt = _arr(weight, np.float32, (n, 8), "weight")
    pair_target = keys.target[pk] if M else np.zeros(0, np.int32)
    missing = set(np.unique(pair_target).tolist()) - set(target_images)
    if missing:
        raise ValueError(f"linearize_window: no image for target slot(s) {sorted(missing)}")
    order, bs, be, bkey, ranges = _blocks_by_key(pk, pair_target, pairs_per_block)
    B = len(bs)
    f = lambda a, dt: wp.array(np.ascontiguousarray(a), dtype=dt, device=device)  # noqa: E731
    key_args = [f(keys.R.astype(np.float32), wp.mat33), f(keys.t.astype(np.float32), wp.vec3),
                f(keys.R0.astype(np.float32), wp.mat33), f(keys.t0.astype(np.float32), wp.vec3),
                f(keys.aff.astype(np.float32), wp.vec3), f(keys.energy_th.astype(np.float32), wp.float32)]
    pts = [f(uv, wp.vec2), f(idp, wp.float32), f(col, wp.float32), f(wgt, wp.float32)]
    out_state = wp.zeros(M, dtype=wp.int32, device=device)
    out_energy = wp.zeros(M, dtype=wp.float64, device=device)
    out_hcd = wp.zeros(M, dtype=vec10d, device=device)
    out_hdd = wp.zeros(M, dtype=wp.float64, device=device)
    out_bd = wp.zeros(M, dtype=wp.float64, device=device)
    partials = wp.zeros((max(B, 1), NUM_KEY_SLOTS), dtype=wp.float64, device=device)
    if B:
        w_bs, w_be, w_order = f(bs, wp.int32), f(be, wp.int32), f(order, wp.int32)
        w_pp, w_pk = f(pp, wp.int32), f(pk, wp.int32)
        for tg, (b0, b1) in sorted(ranges.items()):
            img = target_images[tg]
            if not isinstance(img, wp.array) or img.dtype != wp.vec3 or img.ndim != 2:
                raise TypeError(f"target image of slot {tg} must be a 2-D wp.array of vec3 (I, dx, dy)")
            if (img.shape[1], img.shape[0]) != (params.cam.width, params.cam.height):
                raise ValueError(f"target image of slot {tg} is {img.shape[1]}x{img.shape[0]}, params say "
                                 f"{params.cam.width}x{params.cam.height}")
            runtime.launch_split(linearize_pairs_kernel, b1 - b0,
                                 [b0, w_bs, w_be, w_order, w_pp, w_pk, *key_args, *pts, img, params, out_state,
                                  out_energy, out_hcd, out_hdd, out_bd, partials], device, min_chunk=8)
    part = partials.numpy()[:B]
    kH = np.zeros((nk, NUM_KEY_SLOTS))
    if B:
        np.add.at(kH, bkey, part)
    return PairLinearization(out_state.numpy(), out_energy.numpy(), out_hcd.numpy().reshape(M, 10),
                             out_hdd.numpy(), out_bd.numpy(), kH[:, :100].reshape(nk, 10, 10), kH[:, 100:110])


def schur_points(lin: PairLinearization, keys: WindowKeys, pair_key: np.ndarray, point_start: np.ndarray,
                 num_slots: int, extra_h: np.ndarray | None = None, extra_b: np.ndarray | None = None, *,
                 points_per_block: int = 64, device: str | None = None) -> PointSchur:
    """Per point sums and the Schur complement over the inverse depths (see the module text).

    Pairs must be point-major: point ``p`` owns pairs ``point_start[p]:point_start[p+1]`` (``point_start [n+1]``).
    ``num_slots``: keyframe slots ``K`` (the frame parameters are ``8 K``, slot-major). ``extra_h/extra_b [n]``: added
    to each point's ``H_dd`` / ``b_d`` (an inverse-depth prior, damping).
    """
    device = device or runtime.default_device()
    M = len(lin.state)
    ps = _arr(point_start, np.int32, (np.asarray(point_start).shape[0],), "point_start")
    n = len(ps) - 1
    if n < 0 or (n >= 0 and len(ps) and (ps[0] != 0 or ps[-1] != M or np.any(np.diff(ps) < 0))):
        raise ValueError("schur_points: point_start must rise from 0 to the number of pairs")
    if num_slots < 1 or num_slots > 30:
        raise ValueError(f"schur_points: num_slots must be in [1, 30], got {num_slots}")
    nf = 8 * num_slots
    eh = np.zeros(n) if extra_h is None else _arr(extra_h, np.float64, (n,), "extra_h")
    eb = np.zeros(n) if extra_b is None else _arr(extra_b, np.float64, (n,), "extra_b")
    nb = max(1, -(-n // points_per_block))
    f = lambda a, dt: wp.array(np.ascontiguousarray(a), dtype=dt, device=device)  # noqa: E731
    hdd = wp.zeros(n, dtype=wp.float64, device=device)
    bd = wp.zeros(n, dtype=wp.float64, device=device)
    w = wp.zeros((n, nf), dtype=wp.float64, device=device)
    part = wp.zeros((nb, nf * nf + nf), dtype=wp.float64, device=device)
    if n:
        runtime.launch_split(schur_points_kernel, nb,
                             [int(points_per_block), f(ps, wp.int32), f(_arr(pair_key, np.int32, (M,), "pair_key"),
                                                                        wp.int32),
                              f(lin.state.astype(np.int32), wp.int32), f(lin.hcd, vec10d), f(lin.hdd, wp.float64),
                              f(lin.bd, wp.float64), f(keys.host.astype(np.int32), wp.int32),
                              f(keys.target.astype(np.int32), wp.int32),
                              f(keys.adj.reshape(len(keys), 36), wp.float64), f(eh, wp.float64), f(eb, wp.float64),
                              hdd, bd, w, part], device, min_chunk=2)
    tot = part.numpy().sum(axis=0)
    return PointSchur(hdd.numpy(), bd.numpy(), w.numpy(), tot[: nf * nf].reshape(nf, nf), tot[nf * nf:])
