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
  10x10 block ``H_cc = sum W J_c J_c^T`` and ``b_c = sum W J_c r`` and writes one row of a float64 partial-sum
  buffer; per pair it writes ``H_cd = sum W J_c J_d`` (10), ``H_dd = sum W J_d^2`` and ``b_d = sum W J_d r``. A
  block's affine rows are formed once from its sums (``a_rel`` is the key's). One launch covers every target (the
  keyframes' level-0 images are one ``[slots, H, W]`` array).
- :func:`schur_points`: one thread per point (pairs sorted by point) sums the point's ``H_dd``, ``b_d`` and its
  frame-point block in absolute frame parameters ``w_p [8 K]`` (adjoints applied); the reduced-camera terms
  ``sum_p w_p w_p^T / H_dd`` and ``sum_p w_p b_d / H_dd`` are then one dense float64 product on the host (BLAS;
  ``[8K, n] x [n, 8K]``, 1-2 ms for 2000 points, where a Warp reduction kernel took ~8 ms).

The caller (``mgso.window.energy``) sums the partial rows, maps the key blocks to absolute parameters and solves the
reduced camera system ``(H_cc - H_sc) x_c = -(b_c - b_sc)``, then back-substitutes ``x_d = -(b_d + w_p . x_c) / H_dd``.
No scaling is applied here (DSO's ``SCALE_*`` preconditioning is the solver's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from . import runtime
from .photometric import (Intrinsics, gradient_weight, huber_weight, inverse_K, make_intrinsics, project_pixel,
                          projection_jacobians, sample_pattern)

__all__ = [
    "PAIR_PARAMS", "FRAME_PARAMS", "NUM_KEY_SLOTS", "SLOT_H", "SLOT_B", "PairState", "WindowParams",
    "make_window_params", "WindowKeys", "PairLinearization", "PointSchur", "linearize_window", "schur_points",
    "linearize_pairs_kernel", "schur_points_kernel", "vec10d", "mat1010d",
]

# LLVM's full SLP depth on the CPU (runtime.cpu_flags_full_slp): linearize_window 0.89x the time, the same bits
wp.set_module_options({"enable_backward": False, "cpu_compiler_flags": runtime.cpu_flags_full_slp()})

PAIR_PARAMS = 10  # (v, w) of target_from_host, a_t, b_t, a_h, b_h
FRAME_PARAMS = 8  # (v, w) of world_to_cam, a, b
SLOT_H = 0  # 100: the key's H_cc, row-major
SLOT_B = 100  # 10: b_c
NUM_KEY_SLOTS = 110

vec10d = wp.types.vector(length=10, dtype=wp.float64)
vec8d = wp.types.vector(length=8, dtype=wp.float64)
vec6d = wp.types.vector(length=6, dtype=wp.float64)
mat66d = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
mat64d = wp.types.matrix(shape=(6, 4), dtype=wp.float64)
mat88d = wp.types.matrix(shape=(8, 8), dtype=wp.float64)
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


@wp.func
def affine_blocks(a_rel: float, s_pu: vec6d, s_pv: vec6d, s_hh: wp.float64, s_h: wp.float64, s_1: wp.float64,
                  s_rh: wp.float64, s_r: wp.float64):
    """The affine parts of a block's sums, in float64: ``(H_pa 6x4, H_aa 4x4, b_a 4)``. A block lies in one key, so
    ``a_rel`` is common to its pairs and the affine Jacobian ``hc u + v`` (``u = (-a, 0, a, 0)``, ``v = (0, -1, 0,
    a)``) factors out of the sums: ``H_pa = (sum pu) u^T + (sum pv) v^T`` with a pair's ``pu = s_hx x + s_hy y``,
    ``pv = s_x x + s_y y`` (``x, y``: the rows of its geometric Jacobian)."""
    a = wp.float64(a_rel)
    z = wp.float64(0.0)
    u = wp.vec4d(-a, z, a, z)
    v = wp.vec4d(z, wp.float64(-1.0), z, a)
    Hpa = wp.outer(s_pu, u) + wp.outer(s_pv, v)
    uv = wp.outer(u, v)
    Haa = s_hh * wp.outer(u, u) + s_h * (uv + wp.transpose(uv)) + s_1 * wp.outer(v, v)
    ba = s_rh * u + s_r * v
    return Hpa, Haa, ba


# ------------------------------------------------------------------------------------------------ kernels
@wp.kernel
def linearize_pairs_kernel(offset: int,
                           block_start: wp.array(dtype=wp.int32),  # [B] range into order
                           block_end: wp.array(dtype=wp.int32),  # [B]
                           order: wp.array(dtype=wp.int32),  # [M] pair indices sorted by key
                           pair_point: wp.array(dtype=wp.int32),  # [M] point index
                           pair_key: wp.array(dtype=wp.int32),  # [M] key index
                           key_target: wp.array(dtype=wp.int32),  # [nk] target slot (index into dI)
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
                           dI: wp.array3d(dtype=wp.vec3),  # [slots, H, W] (I, dx, dy) of each keyframe
                           params: WindowParams,
                           pair_state: wp.array(dtype=wp.int32),  # [M] out: PairState
                           pair_energy: wp.array(dtype=wp.float64),  # [M] out: energy (threshold unless IN)
                           pair_hcd: wp.array(dtype=vec10d),  # [M] out: sum W J_c J_d (0 unless IN)
                           pair_hdd: wp.array(dtype=wp.float64),  # [M] out: sum W J_d^2
                           pair_bd: wp.array(dtype=wp.float64),  # [M] out: sum W J_d r
                           partials: wp.array2d(dtype=wp.float64)):  # [B, NUM_KEY_SLOTS] out
    blk = offset + wp.tid()
    cam = params.cam
    Ki = inverse_K(cam)
    # block sums in float64: the key's blocks must agree with the per-pair H_cd to float64 round-off, else the
    # Schur complement (a difference of nearly equal terms along the weak directions) loses digits
    Hb_pp = mat66d()
    bb_p = vec6d()
    sb_pu = vec6d()
    sb_pv = vec6d()
    sb_hh = wp.float64(0.0)
    sb_h = wp.float64(0.0)
    sb_1 = wp.float64(0.0)
    sb_rh = wp.float64(0.0)
    sb_r = wp.float64(0.0)
    a_blk = float(0.0)
    for q in range(block_start[blk], block_end[blk]):
        j = order[q]
        p = pair_point[j]
        k = pair_key[j]
        dI_t = dI[key_target[k]]
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
        # Per-pixel sums of scalars only (DSO AccumulatorApprox): the geometric Jacobian is the same for the 8
        # pixels, so J_c = (Jx^T g, hc u + v) with g the target gradient, hc = I_h - b_h, u = (-a, 0, a, 0),
        # v = (0, -1, 0, a); the 10x10 block is built once per pair from these sums.
        s_xx = float(0.0)
        s_xy = float(0.0)
        s_yy = float(0.0)
        s_hx = float(0.0)  # sum W gx hc
        s_hy = float(0.0)
        s_x = float(0.0)  # sum W gx
        s_y = float(0.0)
        s_hh = float(0.0)  # sum W hc^2
        s_h = float(0.0)  # sum W hc
        s_1 = float(0.0)  # sum W
        s_rx = float(0.0)  # sum W gx r
        s_ry = float(0.0)
        s_rh = float(0.0)  # sum W hc r
        s_r = float(0.0)  # sum W r
        energy = float(0.0)
        wji2 = float(0.0)
        ps = sample_pattern(c[0], c[1], d, RKi, t, cam, params.border_lo, params.border_hi, dI_t)
        for i in range(8):
            good = ps.good[i] != 0
            if not good:
                ok = False
            hc = color[p, i] - b_h
            r = wp.where(good, (ps.intensity[i] - b_t) - a_rel * hc, 0.0)
            gx = wp.where(good, ps.gx[i], 0.0)
            gy = wp.where(good, ps.gy[i], 0.0)
            g2 = gx * gx + gy * gy
            w = 0.5 * (gradient_weight(g2, params.grad_c2) + weight[p, i])
            hw = huber_weight(r, params.huber_th)
            W = hw * w * w
            energy += w * w * hw * r * r * (2.0 - hw)
            wji2 += W * W * g2
            s_xx += W * gx * gx
            s_xy += W * gx * gy
            s_yy += W * gy * gy
            s_hx += W * gx * hc
            s_hy += W * gy * hc
            s_x += W * gx
            s_y += W * gy
            s_hh += W * hc * hc
            s_h += W * hc
            s_1 += W
            s_rx += W * gx * r
            s_ry += W * gy * r
            s_rh += W * hc * r
            s_r += W * r
        th = key_energy_th[k]
        state = int(STATE_IN)
        if not ok:
            state = STATE_OOB
        elif energy > th or wji2 < params.min_wji2:
            state = STATE_OUTLIER
        pair_state[j] = state
        if state == STATE_IN:
            a_blk = a_rel
            # J_c = (gx x + gy y, hc u + v) with x, y the rows of the geometric Jacobian: the pose rows from the
            # pattern sums; the affine rows factor out of the block (affine_blocks)
            x = vec6d(dku)
            y = vec6d(dkv)
            xx = wp.float64(s_xx)
            xy = wp.float64(s_xy)
            yy = wp.float64(s_yy)
            px = xx * x + xy * y
            py = xy * x + yy * y
            for i in range(6):  # element by element (static indices): wp.outer's 6x6 temporaries cost more
                for jj in range(6):
                    Hb_pp[i, jj] = Hb_pp[i, jj] + (px[i] * x[jj] + py[i] * y[jj])
            bb_p += wp.float64(s_rx) * x + wp.float64(s_ry) * y
            hx = wp.float64(s_hx)
            hy = wp.float64(s_hy)
            gx1 = wp.float64(s_x)
            gy1 = wp.float64(s_y)
            sb_pu += hx * x + hy * y
            sb_pv += gx1 * x + gy1 * y
            sb_hh += wp.float64(s_hh)
            sb_h += wp.float64(s_h)
            sb_1 += wp.float64(s_1)
            sb_rh += wp.float64(s_rh)
            sb_r += wp.float64(s_r)
            dd0 = wp.float64(dd[0])
            dd1 = wp.float64(dd[1])
            cp = dd0 * px + dd1 * py
            hu = hx * dd0 + hy * dd1
            hv = gx1 * dd0 + gy1 * dd1
            a64 = wp.float64(a_rel)
            pair_energy[j] = wp.float64(energy)
            pair_hcd[j] = vec10d(cp[0], cp[1], cp[2], cp[3], cp[4], cp[5], -a64 * hu, -hv, a64 * hu, a64 * hv)
            pair_hdd[j] = xx * dd0 * dd0 + wp.float64(2.0) * xy * dd0 * dd1 + yy * dd1 * dd1
            pair_bd[j] = wp.float64(s_rx) * dd0 + wp.float64(s_ry) * dd1
        else:
            pair_energy[j] = wp.float64(th)
            pair_hcd[j] = vec10d()
            pair_hdd[j] = wp.float64(0.0)
            pair_bd[j] = wp.float64(0.0)
    Hb_pa, Hb_aa, bb_a = affine_blocks(a_blk, sb_pu, sb_pv, sb_hh, sb_h, sb_1, sb_rh, sb_r)
    for i in range(6):
        for j in range(6):
            partials[blk, SLOT_H + i * 10 + j] = Hb_pp[i, j]
        for j in range(4):
            partials[blk, SLOT_H + i * 10 + 6 + j] = Hb_pa[i, j]
            partials[blk, SLOT_H + (6 + j) * 10 + i] = Hb_pa[i, j]
        partials[blk, SLOT_B + i] = bb_p[i]
    for i in range(4):
        for j in range(4):
            partials[blk, SLOT_H + (6 + i) * 10 + 6 + j] = Hb_aa[i, j]
        partials[blk, SLOT_B + 6 + i] = bb_a[i]


@wp.kernel
def schur_points_kernel(offset: int,
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
                        point_w: wp.array2d(dtype=wp.float64)):  # [n, 8 K] out (zeroed): frame-point block
    p = offset + wp.tid()
    hdd = point_extra_h[p]
    bd = point_extra_b[p]
    for j in range(point_start[p], point_start[p + 1]):
        if pair_state[j] != STATE_IN:
            continue
        k = pair_key[j]
        hcd = pair_hcd[j]
        hdd += pair_hdd[j]
        bd += pair_bd[j]
        ht = key_host[k]
        tg = key_target[k]
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


# ---------------------------------------------------------------------------------------------- launchers
def make_window_params(fx: float, fy: float, cx: float, cy: float, width: int, height: int, *,
                       huber_th: float = 9.0, grad_c2: float = 2500.0, border_lo: float = 1.1,
                       border_hi: float = 3.0, min_wji2: float = 2.0) -> WindowParams:
    """Level-0 intrinsics and DSO's residual constants (``setting_huberTH``, ``setting_outlierTHSumComponent``,
    ``projectPoint``'s margins, the ``wJI2_sum < 2`` outlier test)."""
    if not (fx > 0 and fy > 0) or width < 8 or height < 8:
        raise ValueError(f"bad intrinsics fx={fx} fy={fy} size {width}x{height}")
    p = WindowParams()
    p.cam = make_intrinsics(fx, fy, cx, cy, width, height)
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


def _read_view(a, dtype, device: str) -> wp.array:
    """A ``wp.array`` of NumPy ``a`` that one launch only reads: a view of the NumPy memory on the CPU (no allocation,
    no copy: 5 us against 18-105 us for the window's arrays), a copy on a GPU."""
    return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device, copy=not wp.get_device(device).is_cpu)


def _blocks_by_key(pair_key: np.ndarray, pair_target: np.ndarray, pairs_per_block: int):
    """Pairs sorted by (target, key) (a thread's pairs read one image); blocks of at most ``pairs_per_block`` pairs
    that never straddle a key. Returns ``order, block_start, block_end, block_key``."""
    order = np.lexsort((pair_key, pair_target)).astype(np.int32)
    keys = pair_key[order]
    M = len(order)
    if M == 0:
        return order, np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.int64)
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
    return order, bs, be, keys[bs].astype(np.int64)


def _image_stack(target_images, slots_needed: np.ndarray, params: WindowParams, device: str) -> wp.array:
    """``[slots, H, W]`` vec3 images: the array itself, or one made from a ``{slot: [H, W] wp.array}`` dict."""
    W, H = params.cam.width, params.cam.height
    if isinstance(target_images, wp.array):
        st = target_images
        if st.dtype != wp.vec3 or st.ndim != 3:
            raise TypeError("target images must be a 3-D wp.array of vec3 [slots, H, W] (I, dx, dy)")
        if (st.shape[2], st.shape[1]) != (W, H):
            raise ValueError(f"target images are {st.shape[2]}x{st.shape[1]}, params say {W}x{H}")
        if len(slots_needed) and int(slots_needed.max()) >= st.shape[0]:
            raise ValueError(f"linearize_window: no image for target slot {int(slots_needed.max())} "
                             f"(the stack has {st.shape[0]})")
        return st
    missing = set(slots_needed.tolist()) - set(target_images)
    if missing:
        raise ValueError(f"linearize_window: no image for target slot(s) {sorted(missing)}")
    n = int(slots_needed.max()) + 1 if len(slots_needed) else 1
    st = wp.zeros((n, H, W), dtype=wp.vec3, device=device)
    for tg in slots_needed.tolist():
        img = target_images[tg]
        if not isinstance(img, wp.array) or img.dtype != wp.vec3 or img.ndim != 2:
            raise TypeError(f"target image of slot {tg} must be a 2-D wp.array of vec3 (I, dx, dy)")
        if (img.shape[1], img.shape[0]) != (W, H):
            raise ValueError(f"target image of slot {tg} is {img.shape[1]}x{img.shape[0]}, params say {W}x{H}")
        wp.copy(st[tg], img)
    return st


# the dtypes of linearize_window's per-call inputs: the keys' target, R, t, R0, t0, affine, energy threshold, and the
# points' inverse depths
_KEY_DTYPES = (wp.int32, wp.mat33, wp.vec3, wp.mat33, wp.vec3, wp.vec3, wp.float32, wp.float32)
_KEY_NP = (np.int32,) + (np.float32,) * 7


def linearize_window(params: WindowParams, keys: WindowKeys, pair_point: np.ndarray, pair_key: np.ndarray,
                     uv: np.ndarray, idepth: np.ndarray, color: np.ndarray, weight: np.ndarray,
                     target_images, *, pairs_per_block: int = 32, device: str | None = None,
                     cache: dict | None = None) -> PairLinearization:
    """Linearise ``M`` pairs (see the module text).

    ``pair_point [M]`` index into the point arrays ``uv [n, 2]`` (pixels), ``idepth [n]``, ``color/weight [n, 8]``;
    ``pair_key [M]`` index into ``keys``; ``target_images``: the level-0 ``(I, dx, dy)`` of the keyframes, a
    ``wp.array3d(vec3) [slots, H, W]`` indexed by slot (the window's :attr:`~mgso.window.window.Window.dI0_`), or a
    dict slot -> ``wp.array2d(vec3) [H, W]`` (copied into one). Returns per pair and per key float64 NumPy arrays.
    ``cache``: a dict the caller keeps while the pairs, ``uv``, ``color`` and ``weight`` stay the same (the iterations
    of one optimisation); the block plan, those inputs and the output buffers are made once and reused.
    """
    device = device or runtime.device_of(
        target_images if not isinstance(target_images, dict) else next(iter(target_images.values()), None))
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
    f = lambda a, dt: _read_view(a, dt, device)  # noqa: E731
    if cache is None or "order" not in cache:
        pair_target = keys.target[pk] if M else np.zeros(0, np.int32)
        stack = _image_stack(target_images, np.unique(pair_target).astype(np.int64), params, device)
        order, bs, be, bkey = _blocks_by_key(pk, pair_target, pairs_per_block)
        B = len(bs)
        c = dict(order=order, bkey=bkey, B=B, stack=stack, w_bs=f(bs, wp.int32), w_be=f(be, wp.int32),
                 w_order=f(order, wp.int32), w_pp=f(pp, wp.int32), w_pk=f(pk, wp.int32), uv=f(uv, wp.vec2),
                 col=f(col, wp.float32), wgt=f(wgt, wp.float32),
                 out_state=wp.zeros(M, dtype=wp.int32, device=device),
                 out_energy=wp.zeros(M, dtype=wp.float64, device=device),
                 out_hcd=wp.zeros(M, dtype=vec10d, device=device),
                 out_hdd=wp.zeros(M, dtype=wp.float64, device=device),
                 out_bd=wp.zeros(M, dtype=wp.float64, device=device),
                 partials=wp.zeros((max(B, 1), NUM_KEY_SLOTS), dtype=wp.float64, device=device))
        # the blocks of a key are contiguous (sorted by target, then key): each key's partial rows are summed in
        # order, all keys at once, step j adding the j-th block of every key that has one (keys with the most
        # blocks first, so those are a leading slice); the same bits as np.add.at one row after another, a tenth
        # of its time (it was 3 % of the odometry's CPU time)
        seg = np.flatnonzero(np.r_[True, bkey[1:] != bkey[:-1]]) if B else np.zeros(0, np.int64)
        length = np.diff(np.r_[seg, B])
        most = np.argsort(-length, kind="stable")
        seg, length = seg[most], length[most]
        steps = [(int(np.count_nonzero(length > j)), seg[length > j] + j) for j in range(1, int(length.max(initial=0)))]
        c.update(seg=seg, seg_key=bkey[seg], seg_steps=steps, recorded={})
        if cache is not None:
            cache.update(c)
    else:
        c = cache
    bkey, B = c["bkey"], c["B"]
    key_np = (keys.target, keys.R, keys.t, keys.R0, keys.t0, keys.aff, keys.energy_th, idp)
    if wp.get_device(device).is_cpu:
        # the keys' and inverse depths' arrays are kept in the cache and refilled: the launch then sees the same
        # arrays each iteration and is recorded once (runtime.launch_split ``recorded``)
        if c.get("key_n") != (nk, n):
            bufs = tuple(np.zeros((m,) + np.shape(a)[1:], nt) for a, nt, m in zip(key_np, _KEY_NP, (nk,) * 7 + (n,)))
            c.update(key_n=(nk, n), key_bufs=bufs, key_wp=[f(b, dt) for b, dt in zip(bufs, _KEY_DTYPES)])
            c["recorded"].clear()
        for buf, a in zip(c["key_bufs"], key_np):
            np.copyto(buf, np.asarray(a).reshape(buf.shape), casting="unsafe")
        key_args, recorded = c["key_wp"], c["recorded"]
    else:
        key_args = [f(np.asarray(a).astype(nt), dt) for a, dt, nt in zip(key_np, _KEY_DTYPES, _KEY_NP)]
        recorded = None
    pts = [c["uv"], key_args[7], c["col"], c["wgt"]]
    out_state, out_energy, out_hcd, out_hdd, out_bd, partials = (
        c["out_state"], c["out_energy"], c["out_hcd"], c["out_hdd"], c["out_bd"], c["partials"])
    if B:
        runtime.launch_split(linearize_pairs_kernel, B,
                             [c["w_bs"], c["w_be"], c["w_order"], c["w_pp"], c["w_pk"], *key_args[:7], *pts,
                              c["stack"], params, out_state, out_energy, out_hcd, out_hdd, out_bd, partials], device,
                             min_chunk=8, recorded=recorded)
    part = partials.numpy()[:B]
    kH = np.zeros((nk, NUM_KEY_SLOTS))
    if B:
        acc = part[c["seg"]]
        for count, rows in c["seg_steps"]:
            acc[:count] += part[rows]
        kH[c["seg_key"]] = acc
    return PairLinearization(out_state.numpy().copy(), out_energy.numpy().copy(),
                             out_hcd.numpy().reshape(M, 10).copy(), out_hdd.numpy().copy(), out_bd.numpy().copy(),
                             kH[:, :100].reshape(nk, 10, 10), kH[:, 100:110])


def schur_points(lin: PairLinearization, keys: WindowKeys, pair_key: np.ndarray, point_start: np.ndarray,
                 num_slots: int, extra_h: np.ndarray | None = None, extra_b: np.ndarray | None = None, *,
                 device: str | None = None) -> PointSchur:
    """Per point sums and the Schur complement over the inverse depths (see the module text).

    Pairs must be point-major: point ``p`` owns pairs ``point_start[p]:point_start[p+1]`` (``point_start [n+1]``).
    ``num_slots``: keyframe slots ``K`` (the frame parameters are ``8 K``, slot-major). ``extra_h/extra_b [n]``: added
    to each point's ``H_dd`` / ``b_d`` (an inverse-depth prior, damping).
    """
    device = runtime.device_or_cpu(device)
    M = len(lin.state)
    ps = _arr(point_start, np.int32, (np.asarray(point_start).shape[0],), "point_start")
    n = len(ps) - 1
    if n < 0 or (n >= 0 and len(ps) and (ps[0] != 0 or ps[-1] != M or np.any(np.diff(ps) < 0))):
        raise ValueError("schur_points: point_start must rise from 0 to the number of pairs")
    if num_slots < 1:
        raise ValueError(f"schur_points: num_slots must be at least 1, got {num_slots}")
    nf = 8 * num_slots
    eh = np.zeros(n) if extra_h is None else _arr(extra_h, np.float64, (n,), "extra_h")
    eb = np.zeros(n) if extra_b is None else _arr(extra_b, np.float64, (n,), "extra_b")
    f = lambda a, dt: _read_view(a, dt, device)  # noqa: E731
    hdd = wp.zeros(n, dtype=wp.float64, device=device)
    bd = wp.zeros(n, dtype=wp.float64, device=device)
    w = wp.zeros((n, nf), dtype=wp.float64, device=device)
    if n:
        runtime.launch_split(schur_points_kernel, n,
                             [f(ps, wp.int32), f(_arr(pair_key, np.int32, (M,), "pair_key"), wp.int32),
                              f(lin.state.astype(np.int32), wp.int32), f(lin.hcd, vec10d), f(lin.hdd, wp.float64),
                              f(lin.bd, wp.float64), f(keys.host.astype(np.int32), wp.int32),
                              f(keys.target.astype(np.int32), wp.int32),
                              f(keys.adj.reshape(len(keys), 36), wp.float64), f(eh, wp.float64), f(eb, wp.float64),
                              hdd, bd, w], device, min_chunk=256)
    hdd_np, bd_np, w_np = hdd.numpy(), bd.numpy(), w.numpy()
    # the reduced-camera term is one dense product (BLAS, float64): sum_p w_p w_p^T / H_dd and sum_p w_p b_d / H_dd
    wi = w_np / hdd_np[:, None]
    return PointSchur(hdd_np, bd_np, w_np, wi.T @ w_np, wi.T @ bd_np)
