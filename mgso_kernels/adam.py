"""Fused Adam for the Gaussian parameters, the per-Gaussian optimiser bookkeeping, and state compaction.

Kernels (each with a NumPy twin in :mod:`mgso_kernels.reference.adam`):

- ``adam_step_gaussians``: one thread per Gaussian updates every parameter group (means, log-scales, quaternions,
  opacity logits, SH DC, SH rest) with its own learning rate, in one launch. Options:

  * bias correction ``BIAS_NONE`` (gsplat's fused ``adam`` kernel), ``BIAS_GLOBAL`` (torch.optim.Adam as 3DGS uses
    it: one step count t for all rows) or ``BIAS_PER_GAUSSIAN`` (each row counts its own updates, so a Gaussian added
    at step 5000 starts Adam afresh: t = 1 on its first update, exactly like a new parameter);
  * ``sparse``: only rows that are visible in this view (``visible[i] != 0``), or, without a mask, whose gradient is
    non-zero, are touched: moments, parameters and step count of the others stay as they are (3DGS's
    ``SparseGaussianAdam``, gsplat's ``SelectiveAdam`` / ``visible_adam``). Dense mode is torch.optim.Adam: every
    row's moments decay and move the parameter even with a zero gradient.

  The update is torch.optim.Adam's: ``m = b1 m + (1-b1) g``, ``v = b2 v + (1-b2) g^2``,
  ``p -= lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps)`` with ``bc_k = 1 - b_k^t`` (1 without bias correction).
  On the CPU the dense mode with SH degree 0 (MGSO's) runs as C++ blocks (``adam_step_gaussians_blocks``): the
  same values bit for bit, the bias corrections once per step count of a block (docs/rasteriser.md).
- ``adam_step_flat``: the same update on a flat float array with one global step (per-keyframe exposures, poses).
- ``gather_rows`` / ``gather_rows_2d``: ``dst[i] = src[index[i]]``, the one primitive the Gaussian map uses to
  remove, clone and split rows of parameters, moments and statistics together.
- ``accumulate_densify_stats``: adds one view's screen-space mean gradients (pixels -> NDC units, see below) to the
  per-Gaussian densification statistics.

Units of the densification statistics (3DGS convention): the gradient is taken with respect to the projected mean in
NDC, x_ndc = 2 x_px / W - 1, so dL/dx_ndc = dL/dx_px * W / 2 (and H / 2 for y). The kernel receives dL/d(mean2d) in
pixels and stores ``|(gx * W/2, gy * H/2)|``, which is what 3DGS's threshold 0.0002 is measured against (graphdeco
``add_densification_stats``; gsplat's ``DefaultStrategy._update_state`` rescales by width/2, height/2 the same way).

Nothing here initialises Warp or compiles at import time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from . import dynamic, runtime
from .dynamic import take_item

wp.set_module_options({"enable_backward": False})

__all__ = [
    "BIAS_NONE", "BIAS_GLOBAL", "BIAS_PER_GAUSSIAN", "GaussianParams", "AdamHyper", "DensifyStats", "AdamRates",
    "adam_step", "adam_step_array", "gather", "accumulate_stats", "make_hyper", "float_view",
]

BIAS_NONE = 0           # no bias correction (gsplat's fused adam kernel)
BIAS_GLOBAL = 1         # one global step count t (torch.optim.Adam, as 3DGS uses it)
BIAS_PER_GAUSSIAN = 2   # each Gaussian counts its own updates


# ------------------------------------------------------------------------------------------------ structs
@wp.struct
class GaussianParams:
    """One Gaussian parameter set (or its gradients, or an Adam moment of it); all arrays have the same length N."""

    means: wp.array(dtype=wp.vec3)          # [N] world units
    log_scales: wp.array(dtype=wp.vec3)     # [N] log of the world-unit standard deviations
    quats: wp.array(dtype=wp.vec4)          # [N] rotation (w, x, y, z), not necessarily unit
    opacity_logits: wp.array(dtype=float)   # [N] opacity = sigmoid(logit)
    sh: wp.array2d(dtype=wp.vec3)           # [N, K] SH coefficients per RGB channel, K = (degree + 1)^2


@wp.struct
class AdamHyper:
    lr_means: float          # learning rate of means (already scaled by scene extent and decayed)
    lr_log_scales: float
    lr_quats: float
    lr_opacity: float
    lr_sh_dc: float          # sh[:, 0]
    lr_sh_rest: float        # sh[:, 1:]
    beta1: float
    beta2: float
    eps: float
    bias_correction: int     # BIAS_NONE / BIAS_GLOBAL / BIAS_PER_GAUSSIAN
    global_step: int         # t >= 1 of this update, used with BIAS_GLOBAL
    sparse: int              # 1: skip rows that are not visible / have no gradient
    use_visible: int         # 1: `visible` decides; 0: a non-zero gradient decides (only read when sparse == 1)


@wp.struct
class DensifyStats:
    """Per-Gaussian densification statistics, accumulated over views and reset by the strategy after a refine."""

    grad2d_sum: wp.array(dtype=float)       # [N] sum over views of |dL/d mean_ndc| (3DGS units, see module doc)
    absgrad2d_sum: wp.array(dtype=float)    # [N] same with AbsGS's per-pixel absolute gradients
    vis_count: wp.array(dtype=wp.int32)     # [N] views in which the Gaussian was visible (radius > 0)
    max_radius_px: wp.array(dtype=float)    # [N] largest screen radius seen, pixels
    views_seen: wp.array(dtype=wp.int32)    # [N] training views in which it was visible since creation (never reset)
    weight_max: wp.array(dtype=float)       # [N] largest over views of its blending weight summed over the pixels


# -------------------------------------------------------------------------------------------------- funcs
@wp.func
def adam_update(p: float, g: float, m: float, v: float, lr: float, b1: float, b2: float, eps: float,
                bc1: float, bc2_sqrt: float):
    m2 = b1 * m + (1.0 - b1) * g
    v2 = b2 * v + (1.0 - b2) * g * g
    p2 = p - (lr / bc1) * m2 / (wp.sqrt(v2) / bc2_sqrt + eps)
    return wp.vec3(p2, m2, v2)


@wp.func
def adam_row_vec3(p: wp.array(dtype=wp.vec3), g: wp.array(dtype=wp.vec3), m: wp.array(dtype=wp.vec3),
                  v: wp.array(dtype=wp.vec3), i: int, lr: float, hp: AdamHyper, bc1: float, bc2_sqrt: float):
    pp = p[i]
    gg = g[i]
    mm = m[i]
    vv = v[i]
    for c in range(3):
        r = adam_update(pp[c], gg[c], mm[c], vv[c], lr, hp.beta1, hp.beta2, hp.eps, bc1, bc2_sqrt)
        pp[c] = r[0]
        mm[c] = r[1]
        vv[c] = r[2]
    p[i] = pp
    m[i] = mm
    v[i] = vv


@wp.func
def adam_row_vec4(p: wp.array(dtype=wp.vec4), g: wp.array(dtype=wp.vec4), m: wp.array(dtype=wp.vec4),
                  v: wp.array(dtype=wp.vec4), i: int, lr: float, hp: AdamHyper, bc1: float, bc2_sqrt: float):
    pp = p[i]
    gg = g[i]
    mm = m[i]
    vv = v[i]
    for c in range(4):
        r = adam_update(pp[c], gg[c], mm[c], vv[c], lr, hp.beta1, hp.beta2, hp.eps, bc1, bc2_sqrt)
        pp[c] = r[0]
        mm[c] = r[1]
        vv[c] = r[2]
    p[i] = pp
    m[i] = mm
    v[i] = vv


@wp.func
def adam_row_sh(p: wp.array2d(dtype=wp.vec3), g: wp.array2d(dtype=wp.vec3), m: wp.array2d(dtype=wp.vec3),
                v: wp.array2d(dtype=wp.vec3), i: int, k: int, lr: float, hp: AdamHyper, bc1: float,
                bc2_sqrt: float):
    pp = p[i, k]
    gg = g[i, k]
    mm = m[i, k]
    vv = v[i, k]
    for c in range(3):
        r = adam_update(pp[c], gg[c], mm[c], vv[c], lr, hp.beta1, hp.beta2, hp.eps, bc1, bc2_sqrt)
        pp[c] = r[0]
        mm[c] = r[1]
        vv[c] = r[2]
    p[i, k] = pp
    m[i, k] = mm
    v[i, k] = vv


@wp.func
def has_gradient(g: GaussianParams, i: int):
    nz = wp.length_sq(g.means[i]) > 0.0 or wp.length_sq(g.log_scales[i]) > 0.0
    nz = nz or wp.length_sq(g.quats[i]) > 0.0 or g.opacity_logits[i] != 0.0
    for k in range(g.sh.shape[1]):
        nz = nz or wp.length_sq(g.sh[i, k]) > 0.0
    return nz


# ------------------------------------------------------------------------------------------------ kernels
@wp.func
def adam_row(i: int, params: GaussianParams, grads: GaussianParams, exp_avg: GaussianParams,
             exp_avg_sq: GaussianParams, steps: wp.array(dtype=wp.int32), visible: wp.array(dtype=wp.uint8),
             hp: AdamHyper):
    """One Adam step of every parameter group of Gaussian ``i``."""
    if hp.sparse != 0:
        if hp.use_visible != 0:
            if visible[i] == wp.uint8(0):
                return
        elif not has_gradient(grads, i):
            return
    t = steps[i] + 1           # every update is counted (the map reports it); BIAS_PER_GAUSSIAN uses it
    steps[i] = t
    if hp.bias_correction == 1:
        t = hp.global_step
    bc1 = float(1.0)
    bc2_sqrt = float(1.0)
    if hp.bias_correction != 0:
        tt = wp.float64(t)
        bc1 = float(wp.float64(1.0) - wp.pow(wp.float64(hp.beta1), tt))
        bc2_sqrt = float(wp.sqrt(wp.float64(1.0) - wp.pow(wp.float64(hp.beta2), tt)))
    adam_row_vec3(params.means, grads.means, exp_avg.means, exp_avg_sq.means, i, hp.lr_means, hp, bc1, bc2_sqrt)
    adam_row_vec3(params.log_scales, grads.log_scales, exp_avg.log_scales, exp_avg_sq.log_scales, i,
                  hp.lr_log_scales, hp, bc1, bc2_sqrt)
    adam_row_vec4(params.quats, grads.quats, exp_avg.quats, exp_avg_sq.quats, i, hp.lr_quats, hp, bc1, bc2_sqrt)
    r = adam_update(params.opacity_logits[i], grads.opacity_logits[i], exp_avg.opacity_logits[i],
                    exp_avg_sq.opacity_logits[i], hp.lr_opacity, hp.beta1, hp.beta2, hp.eps, bc1, bc2_sqrt)
    params.opacity_logits[i] = r[0]
    exp_avg.opacity_logits[i] = r[1]
    exp_avg_sq.opacity_logits[i] = r[2]
    for k in range(params.sh.shape[1]):
        lr = hp.lr_sh_rest
        if k == 0:
            lr = hp.lr_sh_dc
        adam_row_sh(params.sh, grads.sh, exp_avg.sh, exp_avg_sq.sh, i, k, lr, hp, bc1, bc2_sqrt)


@wp.kernel
def adam_step_gaussians(offset: int, params: GaussianParams, grads: GaussianParams, exp_avg: GaussianParams,
                        exp_avg_sq: GaussianParams, steps: wp.array(dtype=wp.int32),
                        visible: wp.array(dtype=wp.uint8), hp: AdamHyper):
    """One Adam step of every parameter group of Gaussian ``offset + tid``."""
    adam_row(offset + wp.tid(), params, grads, exp_avg, exp_avg_sq, steps, visible, hp)


# The CPU's dense Adam in C++ blocks of up to ADAM_BLOCK Gaussians: adam_row's arithmetic in the same order (so the
# same parameters and moments bit for bit), with two changes of order of work: each Gaussian's bias corrections
# (two float64 pow, about half of the kernel's time with per-Gaussian steps) are computed once for each step count
# of a block (Gaussians seeded together have the same; a table of 64 keeps them), and each parameter group is
# updated 16 floats a vector (sqrt and division as one IEEE instruction each, the values of the scalar ones). The
# sparse mode and SH of degree above 0 decline (return 0) to adam_row.
_ADAM_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
enum { BLK = 256 };
const int n = hi - lo;
if (n < 0 || n > BLK || hp.sparse != 0 || steps.strides[0] != 4) return 0;
const int K = params.sh.shape[1];
if (K != 1) return 0;
#define MGSO_ADAM_OK(S) (S.means.strides[0] == 12 && S.log_scales.strides[0] == 12 && S.quats.strides[0] == 16 \
    && S.opacity_logits.strides[0] == 4 && S.sh.strides[0] == 12 && S.sh.strides[1] == 12)
if (!(MGSO_ADAM_OK(params) && MGSO_ADAM_OK(grads) && MGSO_ADAM_OK(exp_avg) && MGSO_ADAM_OK(exp_avg_sq))) return 0;
#undef MGSO_ADAM_OK
typedef float vf __attribute__((ext_vector_type(16)));
const float b1 = hp.beta1, b2 = hp.beta2, eps = hp.eps;
const float ob1 = 1.0f - b1, ob2 = 1.0f - b2;
// the rows' bias corrections, each step count's once: a table of 64 step counts (by t mod 64) holds the last
// computed for each slot (-1: none; a count is never negative), so rows of a few ages in any order (a map in
// spatial order) reuse them
float BC1[BLK], BC2[BLK];
int* ST = (int*)steps.data;
int CT[64];
float CC1[64], CC2[64];
for (int k = 0; k < 64; ++k) { CT[k] = -1; CC1[k] = 1.0f; CC2[k] = 1.0f; }
for (int r = 0; r < n; ++r) {
    int t = ST[lo + r] + 1;
    ST[lo + r] = t;
    if (hp.bias_correction == 1) t = hp.global_step;
    if (hp.bias_correction != 0) {
        const int k = t & 63;
        if (CT[k] != t) {
            const double tt = (double)t;
            CC1[k] = (float)(1.0 - ::pow((double)b1, tt));
            CC2[k] = (float)::sqrt(1.0 - ::pow((double)b2, tt));
            CT[k] = t;
        }
        BC1[r] = CC1[k]; BC2[r] = CC2[k];
    } else {
        BC1[r] = 1.0f; BC2[r] = 1.0f;
    }
}
// one group: C floats a row, rows [lo, hi), learning rate lr
float E1[BLK * 4], E2[BLK * 4];
auto group = [&](void* pp, void* gp, void* mp, void* vp, const int C, const float lr) {
    float* P = (float*)pp + (long)lo * C;
    const float* G = (const float*)gp + (long)lo * C;
    float* M = (float*)mp + (long)lo * C;
    float* V = (float*)vp + (long)lo * C;
    const int cnt = n * C;
    for (int r = 0; r < n; ++r)
        for (int c = 0; c < C; ++c) { E1[r * C + c] = BC1[r]; E2[r * C + c] = BC2[r]; }
    int j = 0;
    for (; j + 16 <= cnt; j += 16) {
        vf p, g, m, v, e1, e2;
        __builtin_memcpy(&p, P + j, 64); __builtin_memcpy(&g, G + j, 64); __builtin_memcpy(&m, M + j, 64);
        __builtin_memcpy(&v, V + j, 64); __builtin_memcpy(&e1, E1 + j, 64); __builtin_memcpy(&e2, E2 + j, 64);
        const vf m2 = b1 * m + ob1 * g;
        const vf v2 = b2 * v + ob2 * g * g;
        const vf p2 = p - lr / e1 * m2 / (__builtin_elementwise_sqrt(v2) / e2 + eps);
        __builtin_memcpy(P + j, &p2, 64); __builtin_memcpy(M + j, &m2, 64); __builtin_memcpy(V + j, &v2, 64);
    }
    for (; j < cnt; ++j) {
        const float m2 = b1 * M[j] + ob1 * G[j];
        const float v2 = b2 * V[j] + ob2 * G[j] * G[j];
        P[j] = P[j] - lr / E1[j] * m2 / (__builtin_sqrtf(v2) / E2[j] + eps);
        M[j] = m2; V[j] = v2;
    }
};
group(params.means.data, grads.means.data, exp_avg.means.data, exp_avg_sq.means.data, 3, hp.lr_means);
group(params.log_scales.data, grads.log_scales.data, exp_avg.log_scales.data, exp_avg_sq.log_scales.data, 3,
      hp.lr_log_scales);
group(params.quats.data, grads.quats.data, exp_avg.quats.data, exp_avg_sq.quats.data, 4, hp.lr_quats);
group(params.opacity_logits.data, grads.opacity_logits.data, exp_avg.opacity_logits.data,
      exp_avg_sq.opacity_logits.data, 1, hp.lr_opacity);
group(params.sh.data, grads.sh.data, exp_avg.sh.data, exp_avg_sq.sh.data, 3, hp.lr_sh_dc);
return 1;
#else
return 0;
#endif
"""


@wp.func_native(_ADAM_CPP)
def adam_block_cpp(lo: int, hi: int, params: GaussianParams, grads: GaussianParams, exp_avg: GaussianParams,
                   exp_avg_sq: GaussianParams, steps: wp.array(dtype=wp.int32), hp: AdamHyper) -> int:
    """:func:`adam_row` of the Gaussians ``[lo, hi)`` in C++ (above), the same values bit for bit. Returns 1, or 0
    where it does not apply (nothing written)."""
    ...


@wp.kernel
def adam_step_gaussians_blocks(offset: int, block: int, n: int, params: GaussianParams, grads: GaussianParams,
                               exp_avg: GaussianParams, exp_avg_sq: GaussianParams, steps: wp.array(dtype=wp.int32),
                               visible: wp.array(dtype=wp.uint8), hp: AdamHyper, native: int,
                               status: wp.array(dtype=wp.int32)):
    """:func:`adam_step_gaussians` with ``block`` Gaussians a thread, for the CPU: the C++ block first,
    :func:`adam_row` where it declines; ``status[block]`` 1 where the C++ ran."""
    c = offset + wp.tid()
    lo = c * block
    hi = wp.min(lo + block, n)
    done = int(0)
    if native != 0:
        done = adam_block_cpp(lo, hi, params, grads, exp_avg, exp_avg_sq, steps, hp)
    status[c] = done
    if done == 0:
        for i in range(lo, hi):
            adam_row(i, params, grads, exp_avg, exp_avg_sq, steps, visible, hp)


@wp.kernel
def adam_step_gaussians_blocks_dynamic(offset: int, shares: wp.array(dtype=wp.int64), n_blocks: int, block: int,
                                       n: int, params: GaussianParams, grads: GaussianParams,
                                       exp_avg: GaussianParams, exp_avg_sq: GaussianParams,
                                       steps: wp.array(dtype=wp.int32), visible: wp.array(dtype=wp.uint8),
                                       hp: AdamHyper, status: wp.array(dtype=wp.int32)):
    """:func:`adam_step_gaussians_blocks`' C++ blocks, a chunk a core taking blocks from ``shares``
    (:mod:`mgso_kernels.dynamic`; the dense step's blocks cost the same, but a core the odometry holds for a while
    is helped): the same values bit for bit; a block the C++ declines is left undone with status 0 (the launcher
    then runs the static kernel)."""
    chunk = offset + wp.tid()
    chunks = shares.shape[0]
    for k in range(chunks):   # its own range, then the others' from their far end
        r = (chunk + k) % chunks
        c = take_item(shares, r, k)
        while c >= 0:
            lo = c * block
            status[c] = adam_block_cpp(lo, wp.min(lo + block, n), params, grads, exp_avg, exp_avg_sq, steps, hp)
            c = take_item(shares, r, k)


#: Gaussians a thread of the CPU's Adam (:func:`adam_step_gaussians_blocks`; the C++ block takes at most 256).
ADAM_BLOCK = 256


@wp.kernel
def adam_step_flat(offset: int, param: wp.array(dtype=float), grad: wp.array(dtype=float),
                   exp_avg: wp.array(dtype=float), exp_avg_sq: wp.array(dtype=float), lr: float, beta1: float,
                   beta2: float, eps: float, bc1: float, bc2_sqrt: float):
    """Dense Adam on a flat float array (bias corrections computed by the caller from one global step)."""
    i = offset + wp.tid()
    r = adam_update(param[i], grad[i], exp_avg[i], exp_avg_sq[i], lr, beta1, beta2, eps, bc1, bc2_sqrt)
    param[i] = r[0]
    exp_avg[i] = r[1]
    exp_avg_sq[i] = r[2]


@wp.kernel
def gather_rows(offset: int, src: wp.array(dtype=Any), index: wp.array(dtype=wp.int32), dst: wp.array(dtype=Any)):
    """dst[i] = src[index[i]] (dst must not alias src)."""
    i = offset + wp.tid()
    dst[i] = src[index[i]]


@wp.kernel
def gather_rows_2d(offset: int, src: wp.array2d(dtype=Any), index: wp.array(dtype=wp.int32),
                   dst: wp.array2d(dtype=Any)):
    """dst[i, :] = src[index[i], :] (dst must not alias src)."""
    i = offset + wp.tid()
    j = index[i]
    for k in range(src.shape[1]):
        dst[i, k] = src[j, k]


for _t in (wp.float32, wp.int32, wp.uint8, wp.vec3, wp.vec4):
    wp.overload(gather_rows, {"src": wp.array(dtype=_t), "index": wp.array(dtype=wp.int32),
                              "dst": wp.array(dtype=_t)})
wp.overload(gather_rows_2d, {"src": wp.array2d(dtype=wp.vec3), "index": wp.array(dtype=wp.int32),
                             "dst": wp.array2d(dtype=wp.vec3)})
del _t


_WEIGHT_UNKNOWN = wp.constant(3.4028234663852886e38)   # the largest float32: no prune_weight_px can fall below it


@wp.kernel
def accumulate_densify_stats(offset: int, v_means2d: wp.array(dtype=wp.vec2), v_means2d_abs: wp.array(dtype=wp.vec2),
                             use_abs: int, radii: wp.array(dtype=Any), ndc_scale: wp.vec2,
                             weights: wp.array(dtype=float), weight_scale: float, stats: DensifyStats):
    """Add one view: for every visible Gaussian (radius > 0) the NDC gradient norm, count and max radius, and
    (``weight_scale`` > 0) the largest blending weight summed over a view's pixels, times ``weight_scale``."""
    i = offset + wp.tid()
    r = float(radii[i])
    if r <= 0.0:
        return
    g = v_means2d[i]
    stats.grad2d_sum[i] = stats.grad2d_sum[i] + wp.length(wp.cw_mul(g, ndc_scale))
    if use_abs != 0:
        ga = v_means2d_abs[i]
        stats.absgrad2d_sum[i] = stats.absgrad2d_sum[i] + wp.length(wp.cw_mul(ga, ndc_scale))
    stats.vis_count[i] = stats.vis_count[i] + 1
    stats.views_seen[i] = stats.views_seen[i] + 1
    stats.max_radius_px[i] = wp.max(stats.max_radius_px[i], r)
    if weight_scale > 0.0:
        stats.weight_max[i] = wp.max(stats.weight_max[i], weights[i] * weight_scale)
    else:
        stats.weight_max[i] = _WEIGHT_UNKNOWN   # a view without weights: nothing known, so nothing pruned for it


for _t in (wp.float32, wp.int32):
    wp.overload(accumulate_densify_stats, {"offset": int, "v_means2d": wp.array(dtype=wp.vec2),
                                           "v_means2d_abs": wp.array(dtype=wp.vec2), "use_abs": int,
                                           "radii": wp.array(dtype=_t), "ndc_scale": wp.vec2,
                                           "weights": wp.array(dtype=float), "weight_scale": float,
                                           "stats": DensifyStats})
del _t


def float_view(a: wp.array) -> wp.array:
    """Zero-copy float32 view of a contiguous vector array: vec2/3/4 [N] -> (N, 2/3/4), vec3 [N, K] -> (N, K, 3);
    float32 arrays are returned as they are. For kernels (e.g. the rasteriser's) that take ``array2d(float)`` rows."""
    if a.dtype == wp.float32:
        return a
    length = getattr(a.dtype, "_length_", None)
    if length is None or a.dtype._wp_scalar_type_ != wp.float32:
        raise ValueError(f"float_view: expected a float32 vector array, got {a.dtype}")
    if not a.is_contiguous:
        raise ValueError("float_view: the array must be contiguous")
    v = wp.array(ptr=a.ptr, dtype=wp.float32, shape=tuple(a.shape) + (length,), device=a.device)
    v._ref = a   # keep the owner alive
    return v


# ----------------------------------------------------------------------------------------------- launchers
@dataclass(frozen=True)
class AdamRates:
    """Learning rates of one step, per parameter group (means already scaled by scene extent and decayed)."""

    means: float
    log_scales: float
    quats: float
    opacity_logits: float
    sh_dc: float
    sh_rest: float


def make_hyper(rates: AdamRates, *, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-15,
               bias_correction: int = BIAS_GLOBAL, global_step: int = 1, sparse: bool = False,
               use_visible: bool = False) -> AdamHyper:
    """Fill an :class:`AdamHyper` struct (checks the values)."""
    if bias_correction not in (BIAS_NONE, BIAS_GLOBAL, BIAS_PER_GAUSSIAN):
        raise ValueError(f"bias_correction must be BIAS_NONE, BIAS_GLOBAL or BIAS_PER_GAUSSIAN, got {bias_correction}")
    if bias_correction == BIAS_GLOBAL and global_step < 1:
        raise ValueError(f"global_step must be >= 1 (the step count after this update), got {global_step}")
    if not (0.0 <= beta1 < 1.0 and 0.0 <= beta2 < 1.0):
        raise ValueError(f"Adam betas must be in [0, 1), got ({beta1}, {beta2})")
    hp = AdamHyper()
    hp.lr_means = float(rates.means)
    hp.lr_log_scales = float(rates.log_scales)
    hp.lr_quats = float(rates.quats)
    hp.lr_opacity = float(rates.opacity_logits)
    hp.lr_sh_dc = float(rates.sh_dc)
    hp.lr_sh_rest = float(rates.sh_rest)
    hp.beta1, hp.beta2, hp.eps = float(beta1), float(beta2), float(eps)
    hp.bias_correction = int(bias_correction)
    hp.global_step = int(global_step)
    hp.sparse = int(bool(sparse))
    hp.use_visible = int(bool(use_visible))
    return hp


def _check_group(name: str, s: GaussianParams, n: int, k: int) -> None:
    for f, want in (("means", wp.vec3), ("log_scales", wp.vec3), ("quats", wp.vec4), ("opacity_logits", wp.float32)):
        a = getattr(s, f)
        if a is None or a.dtype != want or a.shape[0] != n:
            raise ValueError(f"adam_step: {name}.{f} must be a Warp array of {n} {want.__name__}, got "
                             f"{None if a is None else (a.dtype.__name__, a.shape)}")
    if s.sh is None or s.sh.dtype != wp.vec3 or tuple(s.sh.shape) != (n, k):
        raise ValueError(f"adam_step: {name}.sh must be a Warp array [{n}, {k}] of vec3, got "
                         f"{None if s.sh is None else s.sh.shape}")


def adam_step(params: GaussianParams, grads: GaussianParams, exp_avg: GaussianParams, exp_avg_sq: GaussianParams,
              steps: wp.array, hyper: AdamHyper, visible: wp.array | None = None,
              device: str | None = None):
    """One fused Adam step over all Gaussians and parameter groups (in place). On the CPU in C++ blocks of
    :data:`ADAM_BLOCK` Gaussians (returns their status: 1 where the C++ ran; dense mode, SH degree 0), elsewhere the
    thread-per-Gaussian kernel (None).

    ``params``, ``grads``, ``exp_avg``, ``exp_avg_sq``: :class:`GaussianParams` over the same N Gaussians.
    ``steps``: [N] int32 updates received per Gaussian (incremented for every updated row).
    ``visible``: [N] uint8, required when ``hyper.sparse`` and ``hyper.use_visible`` are set.
    """
    device = device or runtime.device_of(params.means)
    n = params.means.shape[0]
    k = params.sh.shape[1] if params.sh is not None else 0
    for name, s in (("params", params), ("grads", grads), ("exp_avg", exp_avg), ("exp_avg_sq", exp_avg_sq)):
        _check_group(name, s, n, k)
    if steps.dtype != wp.int32 or steps.shape[0] != n:
        raise ValueError(f"adam_step: steps must be {n} int32, got {steps.dtype.__name__} {steps.shape}")
    if hyper.sparse and hyper.use_visible:
        if visible is None or visible.dtype != wp.uint8 or visible.shape[0] != n:
            raise ValueError(f"adam_step: sparse update by visibility needs visible as {n} uint8")
    if visible is None:
        visible = wp.empty(1, dtype=wp.uint8, device=device)
    if n == 0:
        return
    if wp.get_device(device).is_cpu:
        inputs = [params, grads, exp_avg, exp_avg_sq, steps, visible, hyper]
        if hyper.sparse or k != 1:   # the C++ takes the dense mode of SH degree 0 only (else every block declines)
            return runtime.launch_blocks(adam_step_gaussians_blocks, n, ADAM_BLOCK, inputs, runtime.native_flag(),
                                         device, min_chunk=8192)
        return dynamic.launch_blocks(adam_step_gaussians_blocks, adam_step_gaussians_blocks_dynamic, n, ADAM_BLOCK,
                                     inputs, runtime.native_flag(), device, min_chunk=8192)
    runtime.launch_split(adam_step_gaussians, n, [params, grads, exp_avg, exp_avg_sq, steps, visible, hyper],
                         device, min_chunk=8192)
    return None


def adam_step_array(param: wp.array, grad: wp.array, exp_avg: wp.array, exp_avg_sq: wp.array, lr: float, step: int,
                    beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-15, bias_correction: bool = True,
                    device: str | None = None) -> None:
    """Dense Adam step (step count ``step`` >= 1 after this update) on flat float32 arrays of equal length."""
    device = device or runtime.device_of(param)
    n = param.size
    for name, a in (("grad", grad), ("exp_avg", exp_avg), ("exp_avg_sq", exp_avg_sq)):
        if a.dtype != param.dtype or a.size != n:
            raise ValueError(f"adam_step_array: {name} must match param ({param.dtype.__name__}, {n} values)")
    if param.dtype != wp.float32:
        raise ValueError(f"adam_step_array: float32 arrays expected, got {param.dtype.__name__}")
    if step < 1:
        raise ValueError(f"adam_step_array: step must be >= 1, got {step}")
    bc1 = 1.0 - beta1 ** step if bias_correction else 1.0
    bc2s = float(np.sqrt(1.0 - beta2 ** step)) if bias_correction else 1.0
    flat = [a.flatten() if a.ndim > 1 else a for a in (param, grad, exp_avg, exp_avg_sq)]
    runtime.launch_split(adam_step_flat, n, [*flat, float(lr), float(beta1), float(beta2), float(eps), float(bc1),
                                             bc2s], device)


def gather(src: wp.array, index: wp.array, dst: wp.array, device: str | None = None) -> None:
    """``dst[i] = src[index[i]]`` for i < len(index); 1-D arrays of float32/int32/uint8/vec3/vec4 or 2-D vec3."""
    device = device or runtime.device_of(src)
    m = index.shape[0]
    if m == 0:
        return
    if dst.shape[0] < m or dst.dtype != src.dtype or dst.ndim != src.ndim:
        raise ValueError(f"gather: dst ({dst.dtype.__name__}, {dst.shape}) cannot hold {m} rows of src "
                         f"({src.dtype.__name__}, {src.shape})")
    if src.ndim == 1:
        runtime.launch_split(gather_rows, m, [src, index, dst], device)
    elif src.ndim == 2:
        if src.shape[1] != dst.shape[1]:
            raise ValueError(f"gather: column counts differ ({src.shape[1]} vs {dst.shape[1]})")
        runtime.launch_split(gather_rows_2d, m, [src, index, dst], device)
    else:
        raise ValueError(f"gather: 1-D or 2-D arrays expected, got {src.ndim}-D")


def accumulate_stats(stats: DensifyStats, v_means2d: wp.array, radii: wp.array, width: int, height: int,
                     v_means2d_abs: wp.array | None = None, device: str | None = None,
                     weights: wp.array | None = None, weight_scale: float = 1.0) -> None:
    """Add one training view's screen-space statistics to ``stats`` (all arrays over the same N Gaussians).

    ``v_means2d``: [N] vec2, dL/d(projected mean) in **pixels** (what the rasteriser's backward produces);
    ``v_means2d_abs``: [N] vec2, AbsGS's sum over pixels of |per-pixel gradient|, pixels (optional);
    ``weights``: [N] float, each Gaussian's blending weight summed over the view's pixels (``Gradients.weights``,
    optional): ``weight_max`` keeps the largest over the views, times ``weight_scale`` (the pixels of the full
    resolution one of this view's pixels covers, 4^level, so that views at every pyramid level count alike). It is
    zero for a Gaussian hidden behind opaque ones in every pixel, or fainter than 1/255 in all. A view added without
    ``weights`` sets ``weight_max`` of its visible Gaussians to the largest float32 (unknown: nothing pruned for it);
    ``radii``: [N] float32 or int32 screen radius in pixels, 0 for Gaussians not drawn in this view;
    ``width``, ``height``: the image size, pixels (for the pixel -> NDC conversion, x W/2 and x H/2).
    """
    device = device or runtime.device_of(stats.grad2d_sum)
    n = stats.grad2d_sum.shape[0]
    if v_means2d.dtype != wp.vec2 or v_means2d.shape[0] != n:
        raise ValueError(f"accumulate_stats: v_means2d must be {n} vec2 (pixels), got {v_means2d.dtype.__name__} "
                         f"{v_means2d.shape}")
    if radii.dtype not in (wp.float32, wp.int32) or radii.shape[0] != n:
        raise ValueError(f"accumulate_stats: radii must be {n} float32 or int32 (pixels), got "
                         f"{radii.dtype.__name__} {radii.shape}")
    use_abs = v_means2d_abs is not None
    if use_abs and (v_means2d_abs.dtype != wp.vec2 or v_means2d_abs.shape[0] != n):
        raise ValueError(f"accumulate_stats: v_means2d_abs must be {n} vec2")
    use_weights = weights is not None
    if use_weights and (weights.dtype != wp.float32 or weights.shape[0] != n):
        raise ValueError(f"accumulate_stats: weights must be {n} float32")
    if use_weights and not weight_scale > 0:
        raise ValueError(f"accumulate_stats: weight_scale must be > 0, got {weight_scale}")
    if width < 1 or height < 1:
        raise ValueError(f"accumulate_stats: bad image size {width}x{height}")
    if n == 0:
        return
    if not use_weights:
        weights = runtime.placeholder(wp.float32, 1, device)
    runtime.launch_split(accumulate_densify_stats, n,
                         [v_means2d, v_means2d_abs if use_abs else v_means2d, int(use_abs), radii,
                          wp.vec2(0.5 * width, 0.5 * height), weights,
                          float(weight_scale) if use_weights else 0.0, stats], device)
