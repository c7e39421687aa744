"""Coarse tracking: residuals of the reference keyframe's points in a new frame and the 8x8 normal equations.

DSO's ``CoarseTracker::calcRes`` + ``calcGSSSE`` in one pass. Parameters, in this order: the left se3 perturbation
``(v, w)`` of ``target_from_host`` (= DSO ``refToNew``) and the new frame's affine ``(a_t, b_t)``. For every point
(host pixel at this pyramid level, host inverse depth, reference intensity) and every residual of it:

- project into the new frame's level (:func:`mgso_kernels.photometric.photometric_residual`), skip when out of
  bounds (DSO: ``Ku > 2, Kv > 2, Ku < w - 3, Kv < h - 3``) or behind;
- ``|r| > cutoff_th`` (DSO ``setting_coarseCutoffTH = 20``, raised by the tracker when more than 60 % saturate):
  the energy takes the constant ``2 * huber_th * cutoff_th - huber_th^2`` and the residual stays out of the system;
- otherwise energy ``hw r^2 (2 - hw)`` (times the gradient weight when ``grad_c2 > 0``; DSO's tracker has none)
  and ``H += W J J^T``, ``b += W J r`` with ``W = hw * grad_weight`` and ``J = dr/d(v, w, a_t, b_t)``.

DSO's tracker uses each depth-map pixel as one residual (``ref_color [N, 1]``); passing ``ref_color [N, 8]`` uses
the 8-pixel pattern around each point instead (same inverse depth for the 8).

Flow indicators (DSO ``lastFlowIndicators``), over every ``flow_stride``-th point (DSO: every 32nd, at level 0):
the mean squared pixel shift of the point centre under ``+-t`` alone (translation only) and under ``R, +-t``
(full), each summed over both signs and divided by ``count + 0.1`` (DSO ``calcRes``: ``rs[2]``, ``rs[4]``).

Reduction: one thread owns a block of ``points_per_block`` points, accumulates in float64 registers and writes one
row of a partial-sum buffer; the launcher sums the rows in float64. No atomics, so the result is bitwise the same
single or split over CPU cores (docs/tracking_kernels.md: 16,000 fp32 outer products summed one by one lost 3e-6
relative). Only the upper triangle of ``H`` is accumulated, element by element into a 36-vector: on the CPU this
form takes half the time of the earlier ones (an 8x8 ``wp.outer`` a residual, or 8 float64 lanes summed at the
block's end; docs/tracking_kernels.md, "One kernel for both devices").
DSO divides ``H`` and ``b`` by the number of terms and scales blocks by ``SCALE_XI_*``/``SCALE_A/B``; that
preconditioning belongs to the solver and is not applied here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from . import runtime
from .image import bilinear_inside, finite, sample_dI
from .photometric import (PATTERN, FramePair, Intrinsics, PhotometricParams, fill_frame_pair, gradient_weight,
                          huber_weight, in_margins, inverse_K, make_photometric_params, pose_jacobian, project_RKi,
                          vec8f, vec36d, write_symmetric8)
from .track_simd import coarse_block_simd

__all__ = [
    "POINTS_PER_BLOCK", "NUM_SLOTS", "TrackParams", "TrackingSystem", "TrackWorkspace", "TrackState",
    "make_track_params", "reduce_tracking_system", "REDUCE_KERNELS", "track_system", "COARSE_CUTOFF_TH",
]

wp.set_module_options({"enable_backward": False})

POINTS_PER_BLOCK = 32  # points per reduction block (one thread each) on a GPU
CPU_POINTS_PER_BLOCK = 128  # on the CPU: the 8-point path sums its lanes and writes a row per 128 points
SPLIT_MIN_POINTS = 4096  # residuals a chunk needs before a launch is split over the CPU cores
COARSE_CUTOFF_TH = 20.0  # DSO setting_coarseCutoffTH

# layout of one row of the partial-sum buffer (float64)
SLOT_H = 0  # 64: H row-major
SLOT_B = 64  # 8: b
SLOT_ENERGY = 72
SLOT_NUM_TERMS = 73  # residuals in bounds (DSO numTermsInE)
SLOT_NUM_INLIERS = 74  # within the cutoff: in H (DSO numTermsInWarped before padding)
SLOT_NUM_SATURATED = 75
SLOT_FLOW_T = 76
SLOT_FLOW_RT = 77
SLOT_FLOW_COUNT = 78
NUM_SLOTS = 79
# mgso_kernels.track_simd.coarse_block_simd writes this layout up to the counts (the kernel adds the flow)
assert (SLOT_H, SLOT_B, SLOT_ENERGY, SLOT_NUM_SATURATED) == (0, 64, 72, 75)

vec8d = wp.types.vector(length=8, dtype=wp.float64)


class TrackState:
    """Per-residual outcome written to ``TrackWorkspace.state``."""

    IN = 0  # in the system
    OOB = 1  # projected out of bounds (or non-finite sample)
    BEHIND = 2  # behind the new camera
    SATURATED = 3  # |r| > cutoff: constant energy, not in the system


@wp.struct
class TrackParams:
    cutoff_th: float  # saturate |r| above this (DSO setting_coarseCutoffTH * levelCutoffRepeat)
    flow_stride: int  # flow indicators from every n-th point; 0 = off (DSO: 32 at level 0)
    points_per_block: int
    simd: int  # 1: DSO's tracker (one residual a point) 8 points at a time on the CPU (coarse_block_simd); 0: scalar


@wp.func
def flow_counts(c: wp.vec2, idp: float, Ki: wp.mat33, RKi: wp.mat33, t: wp.vec3, cam: Intrinsics) -> vec8d:
    """DSO ``calcRes``'s flow indicators of one point centre ``c`` as an increment of a block's counts (see
    :func:`counted`): the squared pixel shifts under ``+t`` and ``-t`` alone, summed, and under ``R, +-t``, summed,
    and the 2 shifts of each."""
    hp = Ki * wp.vec3(c[0], c[1], 1.0)
    rh = RKi * wp.vec3(c[0], c[1], 1.0)
    tt = t * idp
    p1 = hp + tt
    p2 = hp - tt
    p3 = rh + tt
    p4 = rh - tt
    d1 = wp.vec2(cam.fx * p1[0] / p1[2] + cam.cx - c[0], cam.fy * p1[1] / p1[2] + cam.cy - c[1])
    d2 = wp.vec2(cam.fx * p2[0] / p2[2] + cam.cx - c[0], cam.fy * p2[1] / p2[2] + cam.cy - c[1])
    d3 = wp.vec2(cam.fx * p3[0] / p3[2] + cam.cx - c[0], cam.fy * p3[1] / p3[2] + cam.cy - c[1])
    d4 = wp.vec2(cam.fx * p4[0] / p4[2] + cam.cx - c[0], cam.fy * p4[1] / p4[2] + cam.cy - c[1])
    zero = wp.float64(0.0)
    return vec8d(zero, zero, zero, zero, wp.float64(wp.dot(d1, d1) + wp.dot(d2, d2)),
                 wp.float64(wp.dot(d3, d3) + wp.dot(d4, d4)), wp.float64(2.0), zero)


@wp.func
def first_flow_index(start: int, stride: int) -> int:
    """The first point index at or after ``start`` that adds to the flow indicators (every ``stride``-th point; -1
    when ``stride`` is 0): a block then steps it instead of taking a modulo per point."""
    if stride > 0:
        return ((start + stride - 1) // stride) * stride
    return -1


@wp.func
def counted(sums: vec8d, e: float, ok: bool, sat: bool) -> vec8d:
    """A residual added to a block's counts ``(energy, in bounds, within the cutoff, saturated, flow_t, flow_rt,
    flow points, -)``: float64, counts exact below 2^53; written to the partial row from ``SLOT_ENERGY`` on."""
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    return sums + vec8d(wp.float64(e), wp.where(ok, one, zero), wp.where(ok and not sat, one, zero),
                        wp.where(sat, one, zero), zero, zero, zero, zero)


@wp.func
def block_setup(blk: int, n: int, pair: FramePair, cam: Intrinsics, photo: PhotometricParams, params: TrackParams):
    """What both kernels' blocks start from: the block's points ``[start, end)``, a saturated residual's energy,
    ``K^-1``, ``R K^-1`` and the block's first point that adds to the flow indicators."""
    start = blk * params.points_per_block
    end = wp.min(start + params.points_per_block, n)
    max_energy = 2.0 * photo.huber_th * params.cutoff_th - photo.huber_th * photo.huber_th
    Ki = inverse_K(cam)
    return start, end, max_energy, Ki, pair.R * Ki, first_flow_index(start, params.flow_stride)


@wp.func
def write_system(partials: wp.array2d(dtype=wp.float64), blk: int, H: vec36d, g: vec8d):
    """A block's ``H`` (given as its upper triangle) and ``b`` into its partial row."""
    write_symmetric8(partials, blk, SLOT_H, H)
    for a in range(8):
        partials[blk, SLOT_B + a] = g[a]


@wp.func
def coarse_residual(u: float, v: float, idp: float, host_color: float, RKi: wp.mat33, pair: FramePair,
                    cam: Intrinsics, dI_t: wp.array2d(dtype=wp.vec3), photo: PhotometricParams, cutoff_th: float,
                    max_energy: float):
    """One residual of the coarse tracker: the host pixel ``(u, v)`` with inverse depth ``idp`` and
    intensity ``host_color`` in the new frame. Returns ``(r, W, energy, state, in_bounds, saturated, J)``: ``r`` 0
    when not in bounds, ``W`` the weight in the system (0 unless within the cutoff), ``state`` a :class:`TrackState`,
    ``J`` the 8 Jacobian entries (the pose part 0 when not in bounds).
    Branch-free on purpose: Warp merges every variable assigned under a condition with a select, and selecting the
    float64 accumulators per residual costs more than the residual itself; invalid residuals get weight 0."""
    kk, nrm = project_RKi(u, v, idp, RKi, pair.t, cam)
    s = sample_dI(dI_t, kk[0], kk[1])  # clamped: memory-safe even when outside
    ku = kk[0]
    kv = kk[1]
    front = nrm[2] > 0.0
    inside = in_margins(ku, kv, cam.width, cam.height, photo.border_lo, photo.border_hi)
    inside = inside and bilinear_inside(ku, kv, cam.width, cam.height)
    ok = front and inside and finite(s[0])  # DSO checks the intensity only
    hc = host_color - pair.b_h
    r = wp.where(ok, (s[0] - pair.b_t) - pair.a_rel * hc, 0.0)
    sat = ok and wp.abs(r) > cutoff_th
    inl = ok and not sat
    hw = huber_weight(r, photo.huber_th)
    gw = float(1.0)
    if photo.grad_c2 > 0.0:
        gw = gradient_weight(s[1] * s[1] + s[2] * s[2], photo.grad_c2)
        gw = gw * gw
    wgt = wp.where(inl, hw * gw, 0.0)
    e = wp.where(inl, gw * hw * r * r * (2.0 - hw), wp.where(sat, max_energy, 0.0))
    st = wp.where(front, wp.where(ok, wp.where(sat, 3, 0), 1), 2)
    # not ok: every input 0, so the pose part is 0 even for a NaN or infinite inverse depth (0 * inf would reach H)
    jp = pose_jacobian(wp.where(ok, wp.vec2(s[1], s[2]), wp.vec2(0.0)), wp.where(ok, nrm, wp.vec3(0.0)),
                       wp.where(ok, idp, 0.0), cam.fx, cam.fy)
    jf = vec8f(jp[0], jp[1], jp[2], jp[3], jp[4], jp[5], -pair.a_rel * hc, -1.0)
    return r, wgt, e, st, ok, sat, jf


def _make_reduce_kernel(with_system: bool, store_jacobians: bool):
    """One kernel per variant: the flags are resolved at code generation (``wp.static``) so that no select of the
    8x8 accumulator is generated (see the loop comment)."""

    @wp.kernel
    def reduce_tracking_system(offset: int,
                               host_uv: wp.array(dtype=wp.vec2),  # [N] reference points, this level's pixels
                               idepth: wp.array(dtype=float),  # [N] inverse depth in the reference keyframe
                               ref_color: wp.array2d(dtype=float),  # [N, P] reference intensity, P = 1 or 8
                               pair: FramePair,  # reference -> new frame, affine
                               cam: Intrinsics,  # this level (shared by reference and new frame)
                               dI_t: wp.array2d(dtype=wp.vec3),  # [h, w] new frame (I, dx, dy) at this level
                               photo: PhotometricParams,
                               params: TrackParams,
                               residual: wp.array2d(dtype=float),  # [N, P] out: r (0 when not in bounds)
                               weight: wp.array2d(dtype=float),  # [N, P] out: W in the system (0 when not in it)
                               state: wp.array2d(dtype=wp.int32),  # [N, P] out: TrackState
                               jacobian: wp.array2d(dtype=vec8f),  # [N, P] out if store_jacobians, else [1, 1]
                               partials: wp.array2d(dtype=wp.float64)):  # [blocks, NUM_SLOTS] out
        blk = offset + wp.tid()
        n = host_uv.shape[0]
        start, end, max_energy, Ki, RKi, next_flow = block_setup(blk, n, pair, cam, photo, params)
        done = int(0)
        if wp.static(not store_jacobians):
            if params.simd != 0:  # the CPU's 8-point path where it applies (mgso_kernels.track_simd), else 0
                done = coarse_block_simd(blk, start, end, next_flow, max_energy, Ki, RKi, host_uv, idepth, ref_color,
                                         pair, cam, dI_t, photo, params.cutoff_th, params.flow_stride, residual,
                                         weight, state, partials, wp.static(1 if with_system else 0))
        if done == 0:
            npat = ref_color.shape[1]
            H = vec36d()  # the upper triangle of H, row by row (symmetric: the lower half is written from it)
            g = vec8d()
            sums = vec8d()  # energy, counts, flow sums (see counted)
            for i in range(start, end):
                c = host_uv[i]
                idp = idepth[i]
                if i == next_flow:
                    next_flow += params.flow_stride
                    sums = sums + flow_counts(c, idp, Ki, RKi, pair.t, cam)
                for k in range(npat):
                    u = c[0]
                    v = c[1]
                    if npat == 8:
                        u = u + PATTERN[k, 0]
                        v = v + PATTERN[k, 1]
                    r, wgt, e, st, ok, sat, jf = coarse_residual(u, v, idp, ref_color[i, k], RKi, pair, cam, dI_t,
                                                                 photo, params.cutoff_th, max_energy)
                    sums = counted(sums, e, ok, sat)
                    residual[i, k] = r
                    weight[i, k] = wgt
                    state[i, k] = st
                    if wp.static(store_jacobians):
                        jacobian[i, k] = jf
                    if wp.static(with_system):
                        # element by element into the triangle (all indices static once the loops unroll): the same
                        # products as wp.outer(W J, J), without an 8x8 temporary a residual
                        wd = wp.float64(wgt)
                        wr = wd * wp.float64(r)
                        q = int(0)
                        for a in range(8):
                            ja = wp.float64(jf[a])
                            wa = wd * ja
                            g[a] = g[a] + wr * ja
                            for b in range(8):
                                if b >= a:
                                    H[q] = H[q] + wa * wp.float64(jf[b])
                                    q += 1
            write_system(partials, blk, H, g)
            for q in range(7):
                partials[blk, SLOT_ENERGY + q] = sums[q]
        else:  # the snippet wrote the system and the counts; the flow indicators are the scalar loop's
            flow = vec8d()
            i = next_flow
            while i >= 0 and i < end:  # next_flow is -1 without flow indicators
                flow = flow + flow_counts(host_uv[i], idepth[i], Ki, RKi, pair.t, cam)
                i += params.flow_stride
            for q in range(SLOT_FLOW_T, NUM_SLOTS):
                partials[blk, q] = flow[q - SLOT_ENERGY]

    return reduce_tracking_system


# (with_system, store_jacobians) -> kernel. All variants are defined at import so the module compiles once.
REDUCE_KERNELS = {
    (True, False): _make_reduce_kernel(True, False),
    (False, False): _make_reduce_kernel(False, False),
    (True, True): _make_reduce_kernel(True, True),
}
reduce_tracking_system = REDUCE_KERNELS[(True, False)]  # the default variant: residuals and the 8x8 system


# ---------------------------------------------------------------------------------------------- launchers
@dataclass
class TrackingSystem:
    """Sums over one level's residuals (all float64). Parameter order: ``(v, w, a_t, b_t)``."""

    H: np.ndarray  # [8, 8] sum of W J J^T over residuals within the cutoff
    b: np.ndarray  # [8] sum of W J r
    energy: float  # sum of energies, saturated residuals at 2 huber cutoff - huber^2 (DSO rs[0])
    num_terms: int  # residuals in bounds (DSO rs[1], numTermsInE)
    num_inliers: int  # residuals within the cutoff, in H
    num_saturated: int  # residuals beyond the cutoff
    flow_t_sum: float  # sum of squared pixel shifts, translation only (+-t)
    flow_rt_sum: float  # sum of squared pixel shifts, rotation and +-t
    flow_count: int  # number of shifts summed (2 per sampled point)

    @property
    def saturated_ratio(self) -> float:
        """DSO ``rs[5]``: saturated / in bounds (the tracker raises the cutoff when > 0.6)."""
        return self.num_saturated / self.num_terms if self.num_terms else 0.0

    @property
    def mean_energy(self) -> float:
        """DSO's per-level figure ``E / numTermsInE`` (its square root is ``lastResiduals[lvl]``)."""
        return self.energy / self.num_terms if self.num_terms else float("inf")

    @property
    def flow_indicators(self) -> tuple[float, float, float]:
        """DSO ``lastFlowIndicators``: ``(shift_t, 0, shift_rt)``, each ``sum / (count + 0.1)``."""
        return (self.flow_t_sum / (self.flow_count + 0.1), 0.0, self.flow_rt_sum / (self.flow_count + 0.1))


class TrackWorkspace:
    """Preallocated outputs of :func:`track_system` for up to ``capacity`` points of ``pattern_size`` residuals.

    Owner: the coarse tracker (one per pyramid level, or one sized for level 0 shared by all levels). The live
    part of the last call is ``residual``/``weight``/``state`` (``[n, P]`` views); the full buffers carry a
    trailing underscore.

    ``points_per_block``: points a thread sums (default :data:`CPU_POINTS_PER_BLOCK` on the CPU,
    :data:`POINTS_PER_BLOCK` on a GPU, where threads are what is scarce). ``simd``: let the CPU take DSO's tracker
    8 points at a time (:mod:`mgso_kernels.track_simd`; float32 lanes in each block's sums); False keeps the scalar
    loop, whose block sums are float64 throughout.
    """

    def __init__(self, capacity: int, pattern_size: int = 1, device: str | None = None,
                 store_jacobians: bool = False, points_per_block: int | None = None, simd: bool = True):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if pattern_size not in (1, 8):
            raise ValueError(f"pattern_size must be 1 (DSO coarse tracker) or 8 (pattern), got {pattern_size}")
        self.device = runtime.device_or_cpu(device)
        if points_per_block is None:
            points_per_block = CPU_POINTS_PER_BLOCK if wp.get_device(self.device).is_cpu else POINTS_PER_BLOCK
        self.simd = bool(simd)
        if points_per_block < 1:
            raise ValueError(f"points_per_block must be >= 1, got {points_per_block}")
        self.capacity = int(capacity)
        self.pattern_size = int(pattern_size)
        self.points_per_block = int(points_per_block)
        self.store_jacobians = bool(store_jacobians)
        shape = (self.capacity, self.pattern_size)
        self.residual_ = wp.zeros(shape, dtype=float, device=self.device)
        self.weight_ = wp.zeros(shape, dtype=float, device=self.device)
        self.state_ = wp.zeros(shape, dtype=wp.int32, device=self.device)
        self.jacobian_ = wp.zeros(shape if store_jacobians else (1, 1), dtype=vec8f, device=self.device)
        self.partials_ = wp.zeros((-(-self.capacity // self.points_per_block), NUM_SLOTS), dtype=wp.float64,
                                  device=self.device)
        # on the CPU a NumPy view of the partial rows, made once (an LM iteration reads them; 3 us a view)
        self.partials_host = self.partials_.numpy() if wp.get_device(self.device).is_cpu else None
        self.n = 0
        self._params: dict = {}
        self.launches: dict = {}  # runtime.launch_split's recorded launches (the same arrays every iteration)
        self._pair = FramePair()  # frame_pair's struct: one object, so a recorded launch holds it by reference
        self._checked: tuple | None = None  # track_system's last inputs, checked (wp.arrays only)

    @property
    def residual(self) -> wp.array:
        return self.residual_[: self.n]

    @property
    def weight(self) -> wp.array:
        return self.weight_[: self.n]

    @property
    def state(self) -> wp.array:
        return self.state_[: self.n]

    @property
    def jacobian(self) -> wp.array:
        if not self.store_jacobians:
            raise ValueError("this TrackWorkspace was made with store_jacobians=False")
        return self.jacobian_[: self.n]

    def params(self, huber_th: float, grad_c2: float, border_lo: float, border_hi: float, cutoff_th: float,
               flow_stride: int) -> tuple[PhotometricParams, TrackParams]:
        """The kernel's parameter structs, made once per distinct setting (a Warp struct costs ~40 us to fill)."""
        key = (huber_th, grad_c2, border_lo, border_hi, cutoff_th, flow_stride)
        got = self._params.get(key)
        if got is None:
            got = (make_photometric_params(huber_th, grad_c2, border_lo, border_hi),
                   make_track_params(cutoff_th, flow_stride, self.points_per_block, self.simd))
            if len(self._params) > 64:
                self._params.clear()
            self._params[key] = got
        return got

    def frame_pair(self, target_from_host: np.ndarray, a_h: float = 0.0, b_h: float = 0.0, a_t: float = 0.0,
                   b_t: float = 0.0, exposure_h: float = 1.0, exposure_t: float = 1.0) -> FramePair:
        """:func:`~mgso_kernels.photometric.make_frame_pair` into the workspace's own struct, valid until the next
        call: an iterative tracker passes the same object every iteration, so :func:`track_system`'s recorded launch
        sets no parameter at all (a 64-point iteration, pair and system: 45-55 us against 75-80 us, new structs)."""
        return fill_frame_pair(self._pair, target_from_host, a_h, b_h, a_t, b_t, exposure_h, exposure_t)

    @property
    def num_blocks(self) -> int:
        return -(-self.n // self.points_per_block)


def make_track_params(cutoff_th: float = COARSE_CUTOFF_TH, flow_stride: int = 32,
                      points_per_block: int = POINTS_PER_BLOCK, simd: bool = True) -> TrackParams:
    p = TrackParams()
    p.cutoff_th = float(cutoff_th)
    p.flow_stride = int(flow_stride)
    p.points_per_block = int(points_per_block)
    p.simd = int(bool(simd))
    return p


def _as_warp(name: str, a, dtype, shape_tail: tuple, device: str) -> wp.array:
    if isinstance(a, wp.array):
        if a.dtype != dtype:
            raise TypeError(f"{name}: expected dtype {dtype.__name__}, got {a.dtype.__name__}")
        return a
    arr = np.ascontiguousarray(a, dtype=np.float32)
    want = (arr.shape[0],) + shape_tail
    if dtype is wp.vec2:
        if arr.shape != (arr.shape[0], 2):
            raise ValueError(f"{name}: expected [N, 2], got {arr.shape}")
    elif arr.shape != want:
        raise ValueError(f"{name}: expected {want}, got {arr.shape}")
    return wp.array(arr, dtype=dtype, device=device)


def track_system(host_uv, idepth, ref_color, pair: FramePair, cam: Intrinsics, dI_t: wp.array,
                 workspace: TrackWorkspace, *, cutoff_th: float = COARSE_CUTOFF_TH, huber_th: float = 9.0,
                 grad_c2: float = 0.0, border_lo: float = 2.0, border_hi: float = 3.0, flow_stride: int = 32,
                 with_system: bool = True, split: bool = True, threads: int | None = None) -> TrackingSystem:
    """Residuals of ``N`` reference points in the new frame and their 8x8 system (one pyramid level).

    ``host_uv [N, 2]`` pixels of this level in the reference keyframe (DSO ``pc_u, pc_v``), ``idepth [N]``
    (``pc_idepth``), ``ref_color [N, P]`` (``pc_color``; ``P = 1`` as DSO, or 8 for the pattern), ``pair``:
    reference -> new frame pose and affine (:func:`~mgso_kernels.photometric.make_frame_pair`), ``cam`` this
    level's intrinsics (:func:`~mgso_kernels.photometric.make_intrinsics`), ``dI_t`` the new frame's level
    ``(I, dx, dy)``. Inputs may be wp.arrays on the workspace's device (kept across iterations: no copies) or
    NumPy (converted). Defaults are DSO's coarse tracker: Huber 9, cutoff 20, no gradient weight, margins 2/3,
    flow from every 32nd point (pass ``flow_stride=0`` at levels > 0 to match DSO exactly).
    """
    ws = workspace
    dev = ws.device
    last = ws._checked
    if (last is not None and host_uv is last[0] and idepth is last[1] and ref_color is last[2] and dI_t is last[3]
            and cam is last[4] and cam.width == last[5] and cam.height == last[6]):
        # the arrays of the last call (an iteration of the same level): checked then, and a wp.array's shape and
        # dtype cannot change (12 us an iteration)
        uv, idp, col = host_uv, idepth, ref_color
    else:
        uv = _as_warp("host_uv", host_uv, wp.vec2, (2,), dev)
        n = uv.shape[0]
        idp = _as_warp("idepth", idepth, wp.float32, (), dev)
        col = _as_warp("ref_color", ref_color, wp.float32, (ws.pattern_size,), dev)
        if idp.shape != (n,) or col.shape != (n, ws.pattern_size):
            raise ValueError(f"host_uv has {n} points but idepth is {idp.shape} and ref_color {col.shape} "
                             f"(expected ({n},) and ({n}, {ws.pattern_size}))")
        if n > ws.capacity:
            raise ValueError(f"{n} points exceed the TrackWorkspace capacity {ws.capacity}")
        if not isinstance(dI_t, wp.array) or dI_t.dtype != wp.vec3 or dI_t.ndim != 2:
            raise TypeError("dI_t must be a 2-D wp.array of vec3 (I, dx, dy)")
        if (dI_t.shape[1], dI_t.shape[0]) != (cam.width, cam.height):
            raise ValueError(f"dI_t is {dI_t.shape[1]}x{dI_t.shape[0]} but cam says {cam.width}x{cam.height}")
        ws.n = n
        given = (host_uv is uv and idepth is idp and ref_color is col)  # NumPy inputs are converted every call
        ws._checked = (uv, idp, col, dI_t, cam, cam.width, cam.height) if given else None
    if not cutoff_th > 0:
        raise ValueError(f"cutoff_th must be > 0, got {cutoff_th}")
    photo, params = ws.params(huber_th, grad_c2, border_lo, border_hi, cutoff_th, flow_stride)
    kernel = REDUCE_KERNELS[(True, True) if ws.store_jacobians else (bool(with_system), False)]
    blocks = ws.num_blocks
    if blocks:
        # split over the cores only from SPLIT_MIN_POINTS points a chunk: a split launch costs ~0.3 ms more than a
        # single one, about what 2000 residuals take (2000 points: 0.45 ms single, 0.8 ms split; 8000: 1.28 / 1.17)
        runtime.launch_split(kernel, blocks,
                             [uv, idp, col, pair, cam, dI_t, photo, params, ws.residual_, ws.weight_, ws.state_,
                              ws.jacobian_, ws.partials_], dev,
                             min_chunk=max(1, SPLIT_MIN_POINTS // (ws.points_per_block * ws.pattern_size)),
                             threads=(threads if split else 1), recorded=ws.launches)
    part = ws.partials_host if ws.partials_host is not None else ws.partials_.numpy()
    s = part[:blocks].sum(axis=0) if blocks else np.zeros(NUM_SLOTS)  # a new array: H and b may be views of it
    e, terms, inl, sat, ft, frt, fc = s[SLOT_ENERGY:NUM_SLOTS].tolist()
    return TrackingSystem(H=s[SLOT_H:SLOT_H + 64].reshape(8, 8), b=s[SLOT_B:SLOT_B + 8], energy=e,
                          num_terms=int(terms), num_inliers=int(inl), num_saturated=int(sat), flow_t_sum=ft,
                          flow_rt_sum=frt, flow_count=int(fc))
