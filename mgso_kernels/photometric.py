"""DSO's photometric residual, its weights and its Jacobians: the one set of ``@wp.func`` shared by the coarse
tracker (:mod:`mgso_kernels.track`), the epipolar search and the sliding-window bundle adjustment.

Model (DSO, Engel et al. 2017, eq. 4), for a host pixel ``p = (u, v)`` with inverse depth ``idepth`` in the host
and a target frame:

- back-project with the host intrinsics ``h = ((u - cx_h)/fx_h, (v - cy_h)/fy_h, 1)``, move with the host->target
  transform ``X_t = R X_h + t``, which for ``X_h = h / idepth`` is ``P = R h + t * idepth`` up to the positive
  factor ``1/idepth``; ``drescale = 1/P_z``, ``(u_n, v_n) = (P_x, P_y) / P_z``, target pixel ``(Ku, Kv) =
  (fx_t u_n + cx_t, fy_t v_n + cy_t)``, inverse depth in the target ``idepth * drescale``;
- residual ``r = (I_t(Ku, Kv) - b_t) - a_rel * (I_h(p) - b_h)`` with ``a_rel = exp(a_t - a_h) * t_t / t_h``
  (exposure times ``t``; both 1 when unknown) -- DSO ``AffLight::fromToVecExposure``;
- Huber weight ``hw = 1`` if ``|r| < huber_th`` else ``huber_th/|r|`` (DSO ``setting_huberTH = 9``), energy
  ``hw * r^2 * (2 - hw)``;
- gradient weight (DSO ``PointFrameResidual::linearize``): ``w_t = sqrt(c2 / (c2 + |grad I_t|^2))`` with ``c2 =
  setting_outlierTHSumComponent = 50^2``, averaged with the host's pattern weight ``w = 0.5 * (w_t + w_h)``; the
  energy is multiplied by ``grad_weight = w^2``. ``c2 <= 0`` switches it off (``grad_weight = 1``), which is what
  DSO's coarse tracker does (Huber weights only).

Jacobians (exact for the pattern pixel being evaluated, at the current estimate):

- pose: 6-vector ``(v, w)``, translation first, of a **left** perturbation of host->target:
  ``T_th <- exp(delta) * T_th`` (DSO ``SE3::exp(inc) * refToNew``; Sophus/mgso tangent order);
- affine: ``(a_t, b_t, a_h, b_h)``: ``dr/da_t = -a_rel (I_h - b_h)``, ``dr/db_t = -1``, ``dr/da_h = +a_rel (I_h -
  b_h)``, ``dr/db_h = +a_rel``;
- inverse depth of the host point;
- intrinsics ``(fx, fy, cx, cy)`` of a camera shared by host and target (DSO ``d_C_x``/``d_C_y`` without the
  ``SCALE_F``/``SCALE_C`` preconditioning). mgso does not optimise calibration by default; the window may.

The geometric Jacobians ``d(Ku, Kv)/d(.)`` are also available on their own (:func:`projection_jacobians`) because
DSO's window evaluates them once per point at the centre pixel and at the first-estimate linearisation point, and
chains them with each pattern pixel's image gradient.

All scale preconditioning of DSO (``SCALE_XI_ROT``, ``SCALE_A``, ...) is left to the solvers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import warp as wp

from . import runtime
from .image import bilinear_inside, finite3, sample_dI, sample_dI_bilin_derivative

__all__ = [
    "PATTERN_NP", "PATTERN_SIZE", "PATTERN", "PATTERN_PADDING", "HUBER_TH", "OUTLIER_TH", "OUTLIER_TH_SUM_COMPONENT",
    "ProjectionStatus", "STATUS_OK", "STATUS_OOB", "STATUS_BEHIND",
    "vec6f", "vec8f", "vec8i", "mat82f", "Intrinsics", "FramePair", "PhotometricParams", "PixelResidual",
    "make_intrinsics", "make_frame_pair", "fill_frame_pair", "rt_first", "write_pose", "make_photometric_params",
    "affine_from_to",
    "project_pixel", "inverse_K", "project_RKi", "projection_jacobians", "in_margins", "PatternSample",
    "project8", "sample8", "sample_pattern",
    "pose_jacobian", "vec36d", "write_symmetric8",
    "huber_weight", "gradient_weight", "photometric_residual",
    "evaluate_patch_kernel", "extract_patterns_kernel", "PatchResiduals", "evaluate_patches", "HostPatterns",
    "extract_patterns",
]

wp.set_module_options({"enable_backward": False})

# DSO staticPattern[8] ("8 for SSE efficiency", the residualPattern used everywhere): (dx, dy) pixel offsets.
PATTERN_NP = np.array([[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]], dtype=np.float32)
PATTERN_SIZE = 8  # DSO patternNum
PATTERN_PADDING = 2  # DSO patternPadding: the pattern reaches 2 px from its centre
HUBER_TH = 9.0  # DSO setting_huberTH
OUTLIER_TH = 12.0 * 12.0  # DSO setting_outlierTH (per pattern pixel energy)
OUTLIER_TH_SUM_COMPONENT = 50.0 * 50.0  # DSO setting_outlierTHSumComponent (c^2 of the gradient weight)

vec6f = wp.types.vector(length=6, dtype=wp.float32)
vec8f = wp.types.vector(length=8, dtype=wp.float32)
vec8i = wp.types.vector(length=8, dtype=wp.int32)
mat82f = wp.types.matrix(shape=(8, 2), dtype=wp.float32)
vec36d = wp.types.vector(length=36, dtype=wp.float64)  # the upper triangle of a symmetric 8x8, row by row
PATTERN = wp.constant(mat82f(*[float(v) for v in PATTERN_NP.reshape(-1)]))


class ProjectionStatus(IntEnum):
    """Outcome of projecting one pixel into a target."""

    OK = 0
    OOB = 1  # projected outside the image margins, or the sample was not finite
    BEHIND = 2  # P_z <= 0: behind (or at) the target camera centre


STATUS_OK = wp.constant(0)
STATUS_OOB = wp.constant(1)
STATUS_BEHIND = wp.constant(2)


@wp.struct
class Intrinsics:
    """Pinhole intrinsics of one pyramid level, and that level's image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@wp.struct
class FramePair:
    """Host -> target relative quantities (DSO ``FrameFramePrecalc``)."""

    R: wp.mat33  # rotation of target_from_host
    t: wp.vec3  # translation of target_from_host: X_t = R X_h + t
    a_rel: float  # exp(a_t - a_h) * t_t / t_h
    b_h: float  # host affine offset b_h
    b_t: float  # target affine offset b_t


@wp.struct
class PhotometricParams:
    huber_th: float  # DSO setting_huberTH = 9
    grad_c2: float  # DSO setting_outlierTHSumComponent = 2500; <= 0: no gradient weight (coarse tracker)
    border_lo: float  # a projection is inside when x > border_lo and y > border_lo ...
    border_hi: float  # ... and x < width - border_hi and y < height - border_hi


@wp.struct
class PixelResidual:
    """Everything one pattern pixel contributes. Fields other than ``status`` are 0 unless status is OK."""

    status: int  # ProjectionStatus
    residual: float  # r, intensity units
    huber_weight: float  # hw in (0, 1]
    grad_weight: float  # w^2, multiplies the energy; 1 when gradient weighting is off
    energy: float  # grad_weight * hw * r^2 * (2 - hw)
    target_xy: wp.vec2  # (Ku, Kv) target pixel
    new_idepth: float  # inverse depth in the target
    target_grad: wp.vec2  # (dI/dx, dI/dy) of the target at (Ku, Kv)
    J_pose: vec6f  # dr / d(v, w), left perturbation of target_from_host
    J_aff: wp.vec4  # dr / d(a_t, b_t, a_h, b_h)
    J_idepth: float  # dr / d idepth (host inverse depth)
    J_calib: wp.vec4  # dr / d(fx, fy, cx, cy), camera shared by host and target


# ---------------------------------------------------------------------------------------------- @wp.func
@wp.func
def project_pixel(u: float, v: float, idepth: float, R: wp.mat33, t: wp.vec3, cam_h: Intrinsics,
                  cam_t: Intrinsics):
    """Project host pixel ``(u, v)`` with inverse depth ``idepth`` into the target.

    Returns ``(Ku_Kv: vec2, n: vec3 = (u_n, v_n, drescale), h: vec2 = host normalised (x, y))``. The target is
    in front when ``drescale > 0``; the target inverse depth is ``idepth * drescale``.
    """
    hx = (u - cam_h.cx) / cam_h.fx
    hy = (v - cam_h.cy) / cam_h.fy
    p = R * wp.vec3(hx, hy, 1.0) + t * idepth
    drescale = 1.0 / p[2]
    un = p[0] * drescale
    vn = p[1] * drescale
    return wp.vec2(cam_t.fx * un + cam_t.cx, cam_t.fy * vn + cam_t.cy), wp.vec3(un, vn, drescale), wp.vec2(hx, hy)


@wp.func
def inverse_K(cam: Intrinsics) -> wp.mat33:
    """``K^-1`` of a level's intrinsics (hoist it out of loops: it has the divisions)."""
    ifx = 1.0 / cam.fx
    ify = 1.0 / cam.fy
    return wp.mat33(ifx, 0.0, -cam.cx * ifx, 0.0, ify, -cam.cy * ify, 0.0, 0.0, 1.0)


@wp.func
def project_RKi(u: float, v: float, idepth: float, RKi: wp.mat33, t: wp.vec3, cam_t: Intrinsics):
    """:func:`project_pixel` with ``RKi = R K_h^-1`` precomputed (DSO ``calcRes``): ``P = RKi (u, v, 1) + t idepth``.

    Returns ``(Ku_Kv: vec2, n: vec3 = (u_n, v_n, drescale))``.
    """
    p = RKi * wp.vec3(u, v, 1.0) + t * idepth
    drescale = 1.0 / p[2]
    un = p[0] * drescale
    vn = p[1] * drescale
    return wp.vec2(cam_t.fx * un + cam_t.cx, cam_t.fy * vn + cam_t.cy), wp.vec3(un, vn, drescale)


@wp.func
def projection_jacobians(n: wp.vec3, h: wp.vec2, idepth: float, R: wp.mat33, t: wp.vec3, cam: Intrinsics):
    """Geometric Jacobians of the target pixel ``(Ku, Kv)`` (DSO ``Jpdxi``, ``Jpdd``, ``Jpdc``).

    ``n = (u_n, v_n, drescale)`` and ``h`` from :func:`project_pixel`. Returns ``(dKu_dxi: vec6, dKv_dxi: vec6,
    dK_didepth: vec2, dKu_dcalib: vec4, dKv_dcalib: vec4)``; pose is the left perturbation ``(v, w)`` of
    target_from_host, calib is ``(fx, fy, cx, cy)`` of a camera shared by host and target.
    """
    un = n[0]
    vn = n[1]
    dr = n[2]
    nid = idepth * dr
    fx = cam.fx
    fy = cam.fy
    dku = vec6f(nid * fx, 0.0, -nid * un * fx, -un * vn * fx, (1.0 + un * un) * fx, -vn * fx)
    dkv = vec6f(0.0, nid * fy, -nid * vn * fy, -(1.0 + vn * vn) * fy, un * vn * fy, un * fy)
    dd = wp.vec2(dr * (t[0] - t[2] * un) * fx, dr * (t[1] - t[2] * vn) * fy)
    # intrinsics: back-projection and projection both move
    ax = dr * (R[2, 0] * un - R[0, 0])
    ay = dr * (R[2, 1] * un - R[0, 1])
    bx = dr * (R[2, 0] * vn - R[1, 0])
    by = dr * (R[2, 1] * vn - R[1, 1])
    dcu = wp.vec4(un + h[0] * ax, (fx / fy) * h[1] * ay, 1.0 + ax, (fx / fy) * ay)
    dcv = wp.vec4((fy / fx) * h[0] * bx, vn + h[1] * by, (fy / fx) * bx, 1.0 + by)
    return dku, dkv, dd, dcu, dcv


@wp.func
def in_margins(x: float, y: float, width: int, height: int, lo: float, hi: float) -> bool:
    """DSO's projection test: ``lo < x < width - hi`` and ``lo < y < height - hi`` (NaN -> False)."""
    return x > lo and y > lo and x < float(width) - hi and y < float(height) - hi


@wp.func
def project8(u: vec8f, v: vec8f, idepth: vec8f, RKi: wp.mat33, t: wp.vec3, cam: Intrinsics):
    """:func:`project_RKi` of 8 pixels: ``(kx, ky, un, vn, drescale)``, 8 each (a pattern's pixels, or the tracker's
    8 lanes), computed before any of them is sampled (:func:`sample8`)."""
    kx = vec8f()
    ky = vec8f()
    un = vec8f()
    vn = vec8f()
    dr = vec8f()
    for i in range(8):
        kk, nrm = project_RKi(u[i], v[i], idepth[i], RKi, t, cam)
        kx[i] = kk[0]
        ky[i] = kk[1]
        un[i] = nrm[0]
        vn[i] = nrm[1]
        dr[i] = nrm[2]
    return kx, ky, un, vn, dr


@wp.func
def sample8(dI_t: wp.array2d(dtype=wp.vec3), kx: vec8f, ky: vec8f):
    """:func:`sample_dI` at 8 points, one after another with nothing between: ``(I, gx, gy)``, 8 each. Clamped, so
    memory-safe wherever the points are. Sampling 8 projections together, after all of them are computed, lets their
    32 loads issue at once instead of one pixel's behind its branches (docs/window.md, "The samples' loads issued
    together")."""
    sI = vec8f()
    sx = vec8f()
    sy = vec8f()
    for i in range(8):
        s = sample_dI(dI_t, kx[i], ky[i])
        sI[i] = s[0]
        sx[i] = s[1]
        sy[i] = s[2]
    return sI, sx, sy


@wp.struct
class PatternSample:
    """The 8 pattern pixels of one point projected into a target (:func:`sample_pattern`)."""

    intensity: vec8f  # bilinear
    gx: vec8f  # bilinear gradient
    gy: vec8f
    un: vec8f  # normalised target coordinates
    vn: vec8f
    dr: vec8f  # drescale (the target is in front when > 0)
    good: vec8i  # 1: in front, inside DSO's margins and the bilinear footprint, the sample finite


@wp.func
def sample_pattern(cu: float, cv: float, idepth: float, RKi: wp.mat33, t: wp.vec3, cam: Intrinsics, lo: float,
                   hi: float, dI_t: wp.array2d(dtype=wp.vec3)) -> PatternSample:
    """The 8 pattern pixels of the host pixel ``(cu, cv)`` with inverse depth ``idepth``, projected into a target
    (:func:`project_RKi`) and sampled there (:func:`sample_dI`); a pixel is good when the projection is in front,
    inside DSO's margins ``lo < x < w - hi`` and the bilinear footprint, and the sample finite. The samples are
    clamped, so memory-safe even when not good.

    In three passes, the 8 projections, then the 8 bilinear samples, then the checks: the samples' 32 loads are
    issued together instead of one pixel's at a time behind its branches. The window's linearisation kernel took
    a fifth less time so (3.05 against 3.92 ms for 13,100 pairs of a 7-Scenes window, one thread), the same bits.
    """
    u = vec8f()
    v = vec8f()
    for i in range(8):
        u[i] = cu + PATTERN[i, 0]
        v[i] = cv + PATTERN[i, 1]
    kx, ky, un, vn, dr = project8(u, v, vec8f(idepth), RKi, t, cam)
    sI, sx, sy = sample8(dI_t, kx, ky)
    good = vec8i()
    for i in range(8):
        inside = in_margins(kx[i], ky[i], cam.width, cam.height, lo, hi)
        inside = inside and bilinear_inside(kx[i], ky[i], cam.width, cam.height) and dr[i] > 0.0
        good[i] = wp.where(inside and finite3(wp.vec3(sI[i], sx[i], sy[i])), 1, 0)
    ps = PatternSample()
    ps.intensity = sI
    ps.gx = sx
    ps.gy = sy
    ps.un = un
    ps.vn = vn
    ps.dr = dr
    ps.good = good
    return ps


@wp.func
def pose_jacobian(grad: wp.vec2, n: wp.vec3, idepth: float, fx: float, fy: float) -> vec6f:
    """``dr/d(v, w)`` of a residual whose target gradient is ``grad`` at a projection with ``n = (u_n, v_n,
    drescale)``: DSO ``calcGSSSE`` (``grad . [fx, fy] * Jpdxi``), left perturbation of target_from_host."""
    un = n[0]
    vn = n[1]
    nid = idepth * n[2]
    dx = grad[0] * fx
    dy = grad[1] * fy
    return vec6f(nid * dx, nid * dy, -nid * (un * dx + vn * dy), -(un * vn * dx + dy * (1.0 + vn * vn)),
                 un * vn * dy + dx * (1.0 + un * un), un * dy - vn * dx)


@wp.func
def write_symmetric8(partials: wp.array2d(dtype=wp.float64), row: int, offset: int, H: vec36d):
    """A symmetric 8x8 given as its upper triangle ``H`` (row by row; the kernels sum only those 36 entries, element
    by element, docs/tracking_kernels.md) into ``partials[row, offset:offset + 64]``, row-major, both halves."""
    q = int(0)
    for a in range(8):
        for b in range(8):
            if b >= a:
                partials[row, offset + a * 8 + b] = H[q]
                partials[row, offset + b * 8 + a] = H[q]
                q += 1


@wp.func
def huber_weight(r: float, th: float) -> float:
    """DSO: 1 inside the threshold, ``th/|r|`` outside (energy ``hw r^2 (2 - hw)``)."""
    a = wp.abs(r)
    if a < th:
        return 1.0
    return th / a


@wp.func
def gradient_weight(grad_sq: float, c2: float) -> float:
    """DSO's residual scale ``sqrt(c2 / (c2 + |grad I|^2))``; its square multiplies the energy."""
    return wp.sqrt(c2 / (c2 + grad_sq))


@wp.func
def photometric_residual(u: float, v: float, idepth: float, host_color: float, host_weight: float,
                         pair: FramePair, cam_h: Intrinsics, cam_t: Intrinsics,
                         dI_t: wp.array2d(dtype=wp.vec3), params: PhotometricParams) -> PixelResidual:
    """Residual, weights and Jacobians of one pattern pixel.

    ``(u, v)``: host pixel of this pattern pixel (centre + pattern offset), host-level pixels. ``idepth``: the
    point's host inverse depth. ``host_color``: host intensity there. ``host_weight``: the host's gradient
    weight ``sqrt(c2/(c2+|grad I_h|^2))`` at that pixel (DSO ``point->weights``), or a negative value to use the
    target weight alone. ``dI_t``: the target level's ``(I, dx, dy)``.
    """
    out = PixelResidual()
    kk, n, h = project_pixel(u, v, idepth, pair.R, pair.t, cam_h, cam_t)
    if not (n[2] > 0.0):
        out.status = STATUS_BEHIND
        return out
    ku = kk[0]
    kv = kk[1]
    if not (in_margins(ku, kv, cam_t.width, cam_t.height, params.border_lo, params.border_hi)
            and bilinear_inside(ku, kv, dI_t.shape[1], dI_t.shape[0])):
        out.status = STATUS_OOB
        return out
    s = sample_dI(dI_t, ku, kv)
    if not finite3(s):
        out.status = STATUS_OOB
        return out
    gx = s[1]
    gy = s[2]
    hc = host_color - pair.b_h
    r = (s[0] - pair.b_t) - pair.a_rel * hc
    hw = huber_weight(r, params.huber_th)
    gw = float(1.0)
    if params.grad_c2 > 0.0:
        w = gradient_weight(gx * gx + gy * gy, params.grad_c2)
        if host_weight >= 0.0:
            w = 0.5 * (w + host_weight)
        gw = w * w
    dku, dkv, dd, dcu, dcv = projection_jacobians(n, h, idepth, pair.R, pair.t, cam_t)
    out.status = STATUS_OK
    out.residual = r
    out.huber_weight = hw
    out.grad_weight = gw
    out.energy = gw * hw * r * r * (2.0 - hw)
    out.target_xy = kk
    out.new_idepth = idepth * n[2]
    out.target_grad = wp.vec2(gx, gy)
    out.J_pose = pose_jacobian(wp.vec2(gx, gy), n, idepth, cam_t.fx, cam_t.fy)
    out.J_aff = wp.vec4(-pair.a_rel * hc, -1.0, pair.a_rel * hc, pair.a_rel)
    out.J_idepth = gx * dd[0] + gy * dd[1]
    out.J_calib = gx * dcu + gy * dcv
    return out


# ------------------------------------------------------------------------------------------------ kernels
@wp.kernel
def evaluate_patch_kernel(offset: int,
                          host_uv: wp.array(dtype=wp.vec2),  # [N] pattern centres, host pixels
                          idepth: wp.array(dtype=float),  # [N] host inverse depth
                          host_color: wp.array2d(dtype=float),  # [N, 8] host intensity per pattern pixel
                          host_weight: wp.array2d(dtype=float),  # [N, 8] host gradient weight (or < 0)
                          pair: FramePair,
                          cam_h: Intrinsics,
                          cam_t: Intrinsics,
                          dI_t: wp.array2d(dtype=wp.vec3),  # [H, W] target (I, dx, dy)
                          params: PhotometricParams,
                          status: wp.array2d(dtype=wp.int32),  # [N, 8] out
                          residual: wp.array2d(dtype=float),  # [N, 8] out
                          huber_w: wp.array2d(dtype=float),  # [N, 8] out
                          grad_w: wp.array2d(dtype=float),  # [N, 8] out
                          energy: wp.array2d(dtype=float),  # [N, 8] out
                          target_xy: wp.array2d(dtype=wp.vec2),  # [N, 8] out
                          J_pose: wp.array2d(dtype=vec6f),  # [N, 8] out
                          J_aff: wp.array2d(dtype=wp.vec4),  # [N, 8] out
                          J_idepth: wp.array2d(dtype=float),  # [N, 8] out
                          J_calib: wp.array2d(dtype=wp.vec4)):  # [N, 8] out
    i = offset + wp.tid()
    p = i // 8
    k = i - p * 8
    c = host_uv[p]
    res = photometric_residual(c[0] + PATTERN[k, 0], c[1] + PATTERN[k, 1], idepth[p], host_color[p, k],
                               host_weight[p, k], pair, cam_h, cam_t, dI_t, params)
    status[p, k] = res.status
    residual[p, k] = res.residual
    huber_w[p, k] = res.huber_weight
    grad_w[p, k] = res.grad_weight
    energy[p, k] = res.energy
    target_xy[p, k] = res.target_xy
    J_pose[p, k] = res.J_pose
    J_aff[p, k] = res.J_aff
    J_idepth[p, k] = res.J_idepth
    J_calib[p, k] = res.J_calib


@wp.kernel
def extract_patterns_kernel(offset: int,
                            dI_h: wp.array2d(dtype=wp.vec3),  # [H, W] host (I, dx, dy)
                            host_uv: wp.array(dtype=wp.vec2),  # [N] pattern centres, host pixels
                            grad_c2: float,  # setting_outlierTHSumComponent
                            color: wp.array2d(dtype=float),  # [N, 8] out: host intensity
                            weight: wp.array2d(dtype=float),  # [N, 8] out: sqrt(c2 / (c2 + |grad|^2))
                            grad_h: wp.array(dtype=wp.vec3),  # [N] out: sum over pattern (gx^2, gx gy, gy^2)
                            valid: wp.array(dtype=wp.int32)):  # [N] out: 1 if all 8 samples inside and finite
    i = offset + wp.tid()
    c = host_uv[i]
    g = wp.vec3(0.0)
    ok = int(1)
    for k in range(8):
        x = c[0] + PATTERN[k, 0]
        y = c[1] + PATTERN[k, 1]
        s = wp.vec3(0.0)
        if bilinear_inside(x, y, dI_h.shape[1], dI_h.shape[0]):
            s = sample_dI_bilin_derivative(dI_h, x, y)
        else:
            ok = 0
        if not finite3(s):
            ok = 0
            s = wp.vec3(0.0)
        color[i, k] = s[0]
        weight[i, k] = gradient_weight(s[1] * s[1] + s[2] * s[2], grad_c2)
        g = g + wp.vec3(s[1] * s[1], s[1] * s[2], s[2] * s[2])
    grad_h[i] = g
    valid[i] = ok


# ---------------------------------------------------------------------------------------------- launchers
def make_intrinsics(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> Intrinsics:
    """An :class:`Intrinsics` struct (a level's fx, fy, cx, cy in pixels and its image size)."""
    if not (fx > 0 and fy > 0):
        raise ValueError(f"focal lengths must be positive, got fx={fx}, fy={fy}")
    if width < 2 or height < 2:
        raise ValueError(f"image size must be at least 2x2, got {width}x{height}")
    s = Intrinsics()
    s.fx, s.fy, s.cx, s.cy = float(fx), float(fy), float(cx), float(cy)
    s.width, s.height = int(width), int(height)
    return s


AFFINE_EXP_LIMIT = 80.0  # |a_t - a_h| beyond this is clamped in affine_from_to (exp(88.7) overflows float32)


def affine_from_to(a_h: float, b_h: float, a_t: float, b_t: float, exposure_h: float = 1.0,
                   exposure_t: float = 1.0) -> tuple[float, float]:
    """DSO ``AffLight::fromToVecExposure``: ``(a_rel, b_rel)`` with ``I_t ~ a_rel * I_h + b_rel``.

    ``a_rel = exp(a_t - a_h) * t_t / t_h``, ``b_rel = b_t - a_rel * b_h``; an exposure of 0 (unknown) sets both
    exposures to 1. The exponent is clamped to +-80 (a brightness ratio of 5e34, far beyond any image pair): a
    window whose affine has diverged gives a ratio that still fits the kernels' float32, not an OverflowError.
    """
    if exposure_h == 0 or exposure_t == 0:
        exposure_h = exposure_t = 1.0
    a = math.exp(min(max(a_t - a_h, -AFFINE_EXP_LIMIT), AFFINE_EXP_LIMIT)) * exposure_t / exposure_h
    return a, b_t - a * b_h


def make_frame_pair(target_from_host: np.ndarray, a_h: float = 0.0, b_h: float = 0.0, a_t: float = 0.0,
                    b_t: float = 0.0, exposure_h: float = 1.0, exposure_t: float = 1.0) -> FramePair:
    """A :class:`FramePair` from a 4x4 ``target_from_host`` (= ``world_to_cam_t @ cam_to_world_h``) and the two
    frames' affine brightness parameters and exposure times."""
    return fill_frame_pair(FramePair(), target_from_host, a_h, b_h, a_t, b_t, exposure_h, exposure_t)


def rt_first(struct_type) -> bool:
    """Whether a Warp struct type's first 12 float32s are its ``R: mat33`` (row-major) then ``t: vec3`` fields, so
    that :func:`write_pose` may write them through a NumPy view of an instance's memory (another layout, a future
    Warp's, falls back to setting the fields)."""
    c = struct_type.ctype
    return (hasattr(c, "R") and hasattr(c, "t") and c.R.offset == 0 and c.R.size == 36 and c.t.offset == 36
            and c.t.size == 12)


def write_pose(p, T: np.ndarray, view: bool) -> None:
    """A struct's ``R`` and ``t`` fields from a 4x4 pose ``T``, through a view of its memory when ``view``
    (:func:`rt_first` of its type): 9 us against 20 us for new ``wp.mat33`` / ``wp.vec3`` values; the float64 ->
    float32 rounding is the same (to nearest, as ``wp.mat33`` of Python floats)."""
    if view:
        v = np.frombuffer(p.__ctype__(), dtype=np.float32, count=12)
        v[:9] = T[:3, :3].ravel()
        v[9:] = T[:3, 3]
    else:
        p.R = wp.mat33(*T[:3, :3].reshape(-1).tolist())
        p.t = wp.vec3(*T[:3, 3].tolist())


_RT_FIRST = rt_first(FramePair)


def fill_frame_pair(p: FramePair, target_from_host: np.ndarray, a_h: float = 0.0, b_h: float = 0.0, a_t: float = 0.0,
                    b_t: float = 0.0, exposure_h: float = 1.0, exposure_t: float = 1.0) -> FramePair:
    """:func:`make_frame_pair` into an existing struct ``p`` (returned): the rotation and translation written through
    a view of the struct's memory (the fields alias it) instead of built as ``wp.mat33`` / ``wp.vec3`` (the coarse
    tracker fills one a Gauss-Newton iteration: 9 us against 20 us for a new struct, one thread)."""
    T = np.asarray(target_from_host, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"target_from_host must be a finite 4x4 matrix, got shape {T.shape}")
    write_pose(p, T, _RT_FIRST)
    p.a_rel = affine_from_to(a_h, b_h, a_t, b_t, exposure_h, exposure_t)[0]
    p.b_h = float(b_h)
    p.b_t = float(b_t)
    return p


def make_photometric_params(huber_th: float = HUBER_TH, grad_c2: float = OUTLIER_TH_SUM_COMPONENT,
                            border_lo: float = 1.1, border_hi: float = 3.0) -> PhotometricParams:
    """Defaults are the window's (DSO ``projectPoint``: ``Ku > 1.1``, ``Ku < w - 3``); the coarse tracker uses
    ``grad_c2=0, border_lo=2, border_hi=3`` (DSO ``calcRes``)."""
    p = PhotometricParams()
    p.huber_th, p.grad_c2 = float(huber_th), float(grad_c2)
    p.border_lo, p.border_hi = float(border_lo), float(border_hi)
    return p


@dataclass
class PatchResiduals:
    """Per point and pattern pixel (``[N, 8, ...]``) results of :func:`evaluate_patches` (NumPy)."""

    status: np.ndarray  # [N, 8] int32 ProjectionStatus
    residual: np.ndarray  # [N, 8]
    huber_weight: np.ndarray  # [N, 8]
    grad_weight: np.ndarray  # [N, 8]
    energy: np.ndarray  # [N, 8]
    target_xy: np.ndarray  # [N, 8, 2]
    J_pose: np.ndarray  # [N, 8, 6]
    J_aff: np.ndarray  # [N, 8, 4]  (a_t, b_t, a_h, b_h)
    J_idepth: np.ndarray  # [N, 8]
    J_calib: np.ndarray  # [N, 8, 4]  (fx, fy, cx, cy)


def _f32(name: str, a, shape) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=np.float32)
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    return a


def evaluate_patches(host_uv: np.ndarray, idepth: np.ndarray, host_color: np.ndarray, host_weight: np.ndarray,
                     pair: FramePair, cam_h: Intrinsics, cam_t: Intrinsics, dI_t: wp.array,
                     params: PhotometricParams | None = None, device: str | None = None) -> PatchResiduals:
    """Evaluate :func:`photometric_residual` for ``N`` points x the 8 pattern pixels (tests, tools).

    ``host_uv [N, 2]`` host pixels, ``idepth [N]``, ``host_color [N, 8]``, ``host_weight [N, 8]`` (negative:
    target weight only), ``dI_t [H, W] vec3`` the target level. Returns NumPy arrays shaped ``[N, 8, ...]``.
    """
    device = device or str(dI_t.device)
    n = np.asarray(host_uv).shape[0]
    uv = _f32("host_uv", host_uv, (n, 2))
    idp = _f32("idepth", idepth, (n,))
    col = _f32("host_color", host_color, (n, 8))
    wgt = _f32("host_weight", host_weight, (n, 8))
    if not isinstance(dI_t, wp.array) or dI_t.dtype != wp.vec3 or dI_t.ndim != 2:
        raise TypeError("dI_t must be a 2-D wp.array of vec3 (I, dx, dy)")
    if (dI_t.shape[1], dI_t.shape[0]) != (cam_t.width, cam_t.height):
        raise ValueError(f"dI_t is {dI_t.shape[1]}x{dI_t.shape[0]} but cam_t says {cam_t.width}x{cam_t.height}")
    params = params or make_photometric_params()
    outs = dict(status=wp.zeros((n, 8), dtype=wp.int32, device=device),
                residual=wp.zeros((n, 8), dtype=float, device=device),
                huber_weight=wp.zeros((n, 8), dtype=float, device=device),
                grad_weight=wp.zeros((n, 8), dtype=float, device=device),
                energy=wp.zeros((n, 8), dtype=float, device=device),
                target_xy=wp.zeros((n, 8), dtype=wp.vec2, device=device),
                J_pose=wp.zeros((n, 8), dtype=vec6f, device=device),
                J_aff=wp.zeros((n, 8), dtype=wp.vec4, device=device),
                J_idepth=wp.zeros((n, 8), dtype=float, device=device),
                J_calib=wp.zeros((n, 8), dtype=wp.vec4, device=device))
    if n:
        runtime.launch_split(evaluate_patch_kernel, n * 8,
                             [wp.array(uv, dtype=wp.vec2, device=device), wp.array(idp, device=device),
                              wp.array(col, device=device), wp.array(wgt, device=device), pair, cam_h, cam_t, dI_t,
                              params, *outs.values()], device)
    return PatchResiduals(**{k: v.numpy() for k, v in outs.items()})


@dataclass
class HostPatterns:
    """A new point's host pattern (DSO ``ImmaturePoint`` constructor): what the trace and the window keep."""

    color: np.ndarray  # [N, 8] host intensity per pattern pixel
    weight: np.ndarray  # [N, 8] sqrt(c2 / (c2 + |grad I_h|^2))
    grad_h: np.ndarray  # [N, 3] sum over the pattern of (gx^2, gx*gy, gy^2) (DSO gradH)
    valid: np.ndarray  # [N] bool: every pattern sample inside and finite


def extract_patterns(dI_h: wp.array, host_uv, grad_c2: float = OUTLIER_TH_SUM_COMPONENT,
                     out: dict | None = None, device: str | None = None) -> HostPatterns:
    """Sample the host pattern of ``N`` new points at ``host_uv [N, 2]`` (host pixels) from ``dI_h``.

    Uses the gradient of the bilinear interpolant (DSO ``getInterpolatedElement33BiLin``), as DSO does when it
    creates an immature point. ``host_uv`` may be a NumPy ``[N, 2]`` or a ``wp.array(dtype=vec2)``.
    """
    device = device or str(dI_h.device)
    if isinstance(host_uv, wp.array):
        uv_w = host_uv
        n = uv_w.shape[0]
    else:
        uv = np.asarray(host_uv, dtype=np.float32)
        n = uv.shape[0]
        uv_w = wp.array(_f32("host_uv", uv, (n, 2)), dtype=wp.vec2, device=device)
    color = wp.zeros((n, 8), dtype=float, device=device)
    weight = wp.zeros((n, 8), dtype=float, device=device)
    grad_h = wp.zeros(n, dtype=wp.vec3, device=device)
    valid = wp.zeros(n, dtype=wp.int32, device=device)
    if n:
        runtime.launch_split(extract_patterns_kernel, n, [dI_h, uv_w, float(grad_c2), color, weight, grad_h, valid],
                             device)
    if out is not None:
        out.update(color=color, weight=weight, grad_h=grad_h, valid=valid)
    return HostPatterns(color.numpy(), weight.numpy(), grad_h.numpy().reshape(n, 3), valid.numpy().astype(bool))
