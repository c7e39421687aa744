"""Projection of 3D Gaussians to screen-space ellipses, forward and hand-written backward (Warp module).

Per Gaussian: ``p_c = R p_w + t``; ``Sigma_3 = M S S^T M^T`` with ``M`` the rotation of the normalised
``w, x, y, z`` quaternion and ``S = diag(exp(log_scales))``; ``Sigma_c = R Sigma_3 R^T``; EWA splatting
``Sigma_2 = J Sigma_c J^T + eps2d I`` with the perspective Jacobian ``J`` evaluated at the tangent clamped to
``[-lim_neg, lim_pos]`` (1.3x the half field of view, :func:`mgso_kernels.splat.camera.make_camera`); ``eps2d``
(0.3 px^2) is the low-pass dilation of 3DGS. By default it is applied **without** the antialiasing opacity
compensation (as the original 3DGS); ``antialiased=1`` multiplies the opacity by
``sqrt(det(Sigma_2 - eps2d I) / det(Sigma_2))`` (Mip-Splatting / gsplat's ``antialiased`` mode), gradient included.
``opacities`` are the effective (compensated) ones. Conic ``(a, b, c)`` = inverse of ``Sigma_2``: ``power = -0.5 (a dx^2 + c dy^2) - b dx dy``.

Culling (``radii = 0``): ``z <= near`` or ``z >= far``; opacity below 1/255 (it can never reach the blending
threshold); non-finite covariance; and the frustum: the cut-off ellipse's bounding box (where
``opacity * exp(power) = 1/255``) misses the rectangle of pixel centres ``[0, W-1] x [0, H-1]``.
``radii`` is 3DGS's screen radius ``ceil(3 sqrt(lambda_max(Sigma_2)))`` for visible Gaussians (what densification
uses), at least 1.

Backward (:func:`project_gaussians_backward`) maps gradients w.r.t. means2d, conics, depths and opacities to
means, log-scales, quaternions (through the normalisation), opacity logits, and per-Gaussian contributions to the
6-vector camera-pose gradient (left perturbation, translation first), summed by :func:`reduce_pose`.

On the CPU both run as C++ blocks of :data:`PROJECT_BLOCK` Gaussians (:func:`project_gaussians_blocks`,
:func:`project_gaussians_backward_blocks`), 16 Gaussians a vector with Warp's own order of operations: the same values
bit for bit (the antialiased mode and CUDA run the thread-per-Gaussian kernels; docs/rasteriser.md).

Twin: :func:`mgso_kernels.reference.splat.project` / ``project_vjp``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .camera import Camera
from .. import dynamic
from ..dynamic import take_item
from ..image import finite
from .common import (ALPHA_MIN, LANES16_CPP, R2_ABS_MARGIN, R2_REL_MARGIN,
                     cutoff_r2, vec6, vec8)

wp.set_module_options({"enable_backward": False})

__all__ = ["project_gaussians", "project_gaussians_backward", "reduce_pose", "vec6d", "POSE_BLOCK"]

vec6d = wp.types.vector(length=6, dtype=wp.float64)
POSE_BLOCK = 256  # Gaussians per partial sum of the pose gradient


@wp.func
def quat_to_rotmat(q: wp.vec4) -> wp.mat33:
    """Unit quaternion (w, x, y, z) -> rotation matrix."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def quat_to_rotmat_vjp(q: wp.vec4, g: wp.mat33) -> wp.vec4:
    """Gradient w.r.t. the unit quaternion entries of sum(g * quat_to_rotmat(q))."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    v_w = 2.0 * (-z * g[0, 1] + y * g[0, 2] + z * g[1, 0] - x * g[1, 2] - y * g[2, 0] + x * g[2, 1])
    v_x = 2.0 * (y * g[0, 1] + z * g[0, 2] + y * g[1, 0] - 2.0 * x * g[1, 1] - w * g[1, 2] + z * g[2, 0]
                 + w * g[2, 1] - 2.0 * x * g[2, 2])
    v_y = 2.0 * (-2.0 * y * g[0, 0] + x * g[0, 1] + w * g[0, 2] + x * g[1, 0] + z * g[1, 2] - w * g[2, 0]
                 + z * g[2, 1] - 2.0 * y * g[2, 2])
    v_z = 2.0 * (-2.0 * z * g[0, 0] - w * g[0, 1] + x * g[0, 2] + w * g[1, 0] - 2.0 * z * g[1, 1]
                 + y * g[1, 2] + x * g[2, 0] + y * g[2, 1])
    return wp.vec4(v_w, v_x, v_y, v_z)


@wp.func
def load_vec3(a: wp.array2d(dtype=float), g: int) -> wp.vec3:
    return wp.vec3(a[g, 0], a[g, 1], a[g, 2])


@wp.func
def load_vec4(a: wp.array2d(dtype=float), g: int) -> wp.vec4:
    return wp.vec4(a[g, 0], a[g, 1], a[g, 2], a[g, 3])


@wp.func
def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + wp.exp(-x))


@wp.func
def ewa_jacobian(pc: wp.vec3, cam: Camera) -> wp.mat33:
    """2x3 perspective Jacobian at the clamped tangent, returned in the first two rows of a mat33."""
    z = pc[2]
    clx = wp.clamp(pc[0] / z, -cam.lim_x_neg, cam.lim_x_pos)
    cly = wp.clamp(pc[1] / z, -cam.lim_y_neg, cam.lim_y_pos)
    return wp.mat33(cam.fx / z, 0.0, -cam.fx * clx / z,
                    0.0, cam.fy / z, -cam.fy * cly / z,
                    0.0, 0.0, 0.0)


@wp.func
def cov2d_of(J: wp.mat33, covc: wp.mat33, eps2d: float) -> wp.vec3:
    """(xx, xy, yy) of J covc J^T + eps2d I (first two rows of J)."""
    m = J * covc * wp.transpose(J)
    return wp.vec3(m[0, 0] + eps2d, m[0, 1], m[1, 1] + eps2d)


@wp.func
def project_one(
    g: int,
    means: wp.array2d(dtype=float),  # [N, 3] world
    log_scales: wp.array2d(dtype=float),  # [N, 3] log of the standard deviations, world units
    quats: wp.array2d(dtype=float),  # [N, 4] w, x, y, z (any norm > 0)
    opacity_logits: wp.array(dtype=float),  # [N] opacity = sigmoid(logit)
    cam: Camera,
    eps2d: float,  # low-pass dilation, px^2
    antialiased: int,  # 1: opacity *= sqrt(det(Sigma_2 - eps2d I) / det(Sigma_2))
    means2d: wp.array(dtype=wp.vec2),  # [N] out, pixels
    conics: wp.array(dtype=wp.vec3),  # [N] out, (a, b, c) inverse 2D covariance, 1/px^2
    depths: wp.array(dtype=float),  # [N] out, camera z
    opacities: wp.array(dtype=float),  # [N] out, effective opacity (sigmoid(logit) [* compensation])
    radii: wp.array(dtype=wp.int32),  # [N] out, 3-sigma screen radius in pixels; 0 = culled
    splats: wp.array(dtype=vec8),  # [N] out, blending data (mx, my, a, b, c, opacity, exp(-a), cut-off r2)
):
    """:func:`project_gaussians` of Gaussian ``g``."""
    p = load_vec3(means, g)
    pc = cam.R * p + cam.t
    z = pc[2]
    op = sigmoid(opacity_logits[g])
    depths[g] = z
    opacities[g] = op
    radii[g] = 0
    means2d[g] = wp.vec2(0.0)
    conics[g] = wp.vec3(0.0)
    if not (z > cam.near and z < cam.far):
        return
    if op < ALPHA_MIN:  # the compensation only lowers it
        return
    q = load_vec4(quats, g)
    qn = wp.normalize(q)
    M = quat_to_rotmat(qn)
    s = load_vec3(log_scales, g)
    S = wp.diag(wp.vec3(wp.exp(s[0]), wp.exp(s[1]), wp.exp(s[2])))
    L = M * S
    covc = cam.R * (L * wp.transpose(L)) * wp.transpose(cam.R)
    J = ewa_jacobian(pc, cam)
    cv = cov2d_of(J, covc, eps2d)
    det = cv[0] * cv[2] - cv[1] * cv[1]
    if not (det > 0.0) or not finite(det):
        return
    if antialiased != 0:
        det_raw = (cv[0] - eps2d) * (cv[2] - eps2d) - cv[1] * cv[1]
        op = op * wp.sqrt(wp.max(det_raw, 0.0) / det)
        opacities[g] = op
        if op < ALPHA_MIN:
            return
    inv_det = 1.0 / det
    mx = cam.fx * pc[0] / z + cam.cx
    my = cam.fy * pc[1] / z + cam.cy
    # frustum: bounding box of the cut-off ellipse d^T conic d <= 2 log(255 opacity) (slightly inflated)
    r2 = cutoff_r2(op)
    ex = wp.sqrt(r2 * cv[0])
    ey = wp.sqrt(r2 * cv[2])
    if mx + ex < 0.0 or mx - ex > float(cam.width - 1) or my + ey < 0.0 or my - ey > float(cam.height - 1):
        return
    a = cv[2] * inv_det
    means2d[g] = wp.vec2(mx, my)
    conics[g] = wp.vec3(a, -cv[1] * inv_det, cv[0] * inv_det)
    splats[g] = vec8(mx, my, a, -cv[1] * inv_det, cv[0] * inv_det, op, wp.exp(-a), r2)
    mid = 0.5 * (cv[0] + cv[2])
    lam = mid + wp.sqrt(wp.max(0.1, mid * mid - det))
    radii[g] = wp.max(1, int(wp.ceil(3.0 * wp.sqrt(lam))))


@wp.kernel
def project_gaussians(
    offset: int,
    means: wp.array2d(dtype=float),  # [N, 3] world
    log_scales: wp.array2d(dtype=float),  # [N, 3] log of the standard deviations, world units
    quats: wp.array2d(dtype=float),  # [N, 4] w, x, y, z (any norm > 0)
    opacity_logits: wp.array(dtype=float),  # [N] opacity = sigmoid(logit)
    cam: Camera,
    eps2d: float,  # low-pass dilation, px^2
    antialiased: int,  # 1: opacity *= sqrt(det(Sigma_2 - eps2d I) / det(Sigma_2))
    means2d: wp.array(dtype=wp.vec2),  # [N] out, pixels
    conics: wp.array(dtype=wp.vec3),  # [N] out, (a, b, c) inverse 2D covariance, 1/px^2
    depths: wp.array(dtype=float),  # [N] out, camera z
    opacities: wp.array(dtype=float),  # [N] out, effective opacity (sigmoid(logit) [* compensation])
    radii: wp.array(dtype=wp.int32),  # [N] out, 3-sigma screen radius in pixels; 0 = culled
    splats: wp.array(dtype=vec8),  # [N] out, blending data (mx, my, a, b, c, opacity, exp(-a), cut-off r2)
):
    project_one(offset + wp.tid(), means, log_scales, quats, opacity_logits, cam, eps2d, antialiased, means2d, conics,
                depths, opacities, radii, splats)


@wp.func
def project_backward_one(
    g: int,
    means: wp.array2d(dtype=float),  # [N, 3]
    log_scales: wp.array2d(dtype=float),  # [N, 3]
    quats: wp.array2d(dtype=float),  # [N, 4]
    opacity_logits: wp.array(dtype=float),  # [N]
    cam: Camera,
    eps2d: float,
    antialiased: int,
    radii: wp.array(dtype=wp.int32),  # [N] 0 = culled: all gradients 0
    v_means2d: wp.array(dtype=wp.vec2),  # [N] upstream
    v_conics: wp.array(dtype=wp.vec3),  # [N] upstream
    v_depths: wp.array(dtype=float),  # [N] upstream (camera z)
    v_opacities: wp.array(dtype=float),  # [N] upstream (d/d effective opacity)
    v_means: wp.array2d(dtype=float),  # [N, 3] out
    v_log_scales: wp.array2d(dtype=float),  # [N, 3] out
    v_quats: wp.array2d(dtype=float),  # [N, 4] out
    v_opacity_logits: wp.array(dtype=float),  # [N] out
    v_pose_partial: wp.array(dtype=vec6),  # [N] out, this Gaussian's term of v_pose
):
    """:func:`project_gaussians_backward` of Gaussian ``g``."""
    if radii[g] == 0:
        for k in range(3):
            v_means[g, k] = 0.0
            v_log_scales[g, k] = 0.0
        for k in range(4):
            v_quats[g, k] = 0.0
        v_opacity_logits[g] = 0.0
        v_pose_partial[g] = vec6(0.0)
        return
    sig = sigmoid(opacity_logits[g])

    # recompute the forward quantities
    p = load_vec3(means, g)
    pc = cam.R * p + cam.t
    x = pc[0]
    y = pc[1]
    z = pc[2]
    q = load_vec4(quats, g)
    qnorm = wp.length(q)
    qn = q / qnorm
    M = quat_to_rotmat(qn)
    ls = load_vec3(log_scales, g)
    s = wp.vec3(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
    L = M * wp.diag(s)
    cov3 = L * wp.transpose(L)
    covc = cam.R * cov3 * wp.transpose(cam.R)
    J = ewa_jacobian(pc, cam)
    cv = cov2d_of(J, covc, eps2d)
    det = cv[0] * cv[2] - cv[1] * cv[1]
    inv_det = 1.0 / det
    a = cv[2] * inv_det
    b = -cv[1] * inv_det
    c = cv[0] * inv_det

    # conic -> 2D covariance: v_Sigma2 = -Q V Q, V = [[va, vb/2], [vb/2, vc]]
    vq = v_conics[g]
    Q = wp.mat22(a, b, b, c)
    V = wp.mat22(vq[0], 0.5 * vq[1], 0.5 * vq[1], vq[2])
    G2 = -(Q * V * Q)
    v_op = v_opacities[g]
    comp = float(1.0)
    if antialiased != 0:
        # comp = sqrt(q), q = det_raw / det: d q / d (A, B, D) of Sigma_2 = [[A, B], [B, D]] (B counted once)
        det_raw = (cv[0] - eps2d) * (cv[2] - eps2d) - cv[1] * cv[1]
        comp = wp.sqrt(wp.max(det_raw, 0.0) / det)
        if comp > 0.0:
            v_ratio = v_op * sig / (2.0 * comp)
            d2 = det * det
            dA = ((cv[2] - eps2d) * det - det_raw * cv[2]) / d2
            dD = ((cv[0] - eps2d) * det - det_raw * cv[0]) / d2
            dB = -2.0 * cv[1] * (det - det_raw) / d2
            G2 = G2 + v_ratio * wp.mat22(dA, 0.5 * dB, 0.5 * dB, dD)
    v_opacity_logits[g] = v_op * comp * sig * (1.0 - sig)
    G = wp.mat33(G2[0, 0], G2[0, 1], 0.0, G2[1, 0], G2[1, 1], 0.0, 0.0, 0.0, 0.0)
    # Sigma2 = J covc J^T (+ eps): v_covc = J^T G J, v_J = 2 G J covc (rows 0, 1)
    v_covc = wp.transpose(J) * G * J
    v_J = 2.0 * (G * J * covc)

    fx = cam.fx
    fy = cam.fy
    clx = wp.clamp(x / z, -cam.lim_x_neg, cam.lim_x_pos)
    cly = wp.clamp(y / z, -cam.lim_y_neg, cam.lim_y_pos)
    z2 = z * z
    vx = float(0.0)
    vy = float(0.0)
    vz = v_depths[g]
    vz += v_J[0, 0] * (-fx / z2) + v_J[1, 1] * (-fy / z2)
    vz += v_J[0, 2] * (fx * clx / z2) + v_J[1, 2] * (fy * cly / z2)
    v_clx = v_J[0, 2] * (-fx / z)
    v_cly = v_J[1, 2] * (-fy / z)
    rx = x / z
    ry = y / z
    if rx >= -cam.lim_x_neg and rx <= cam.lim_x_pos:
        vx += v_clx / z
        vz += -v_clx * x / z2
    if ry >= -cam.lim_y_neg and ry <= cam.lim_y_pos:
        vy += v_cly / z
        vz += -v_cly * y / z2
    vm2 = v_means2d[g]
    vx += fx / z * vm2[0]
    vy += fy / z * vm2[1]
    vz += -fx * x / z2 * vm2[0] - fy * y / z2 * vm2[1]
    v_pc = wp.vec3(vx, vy, vz)

    # pose: translation part v_pc, rotation part (point) pc x v_pc + (covariance) from A = G Sigma - Sigma G
    A = v_covc * covc - covc * v_covc
    v_rot = wp.vec3(A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]) + wp.cross(pc, v_pc)
    v_pose_partial[g] = vec6(v_pc[0], v_pc[1], v_pc[2], v_rot[0], v_rot[1], v_rot[2])

    vm = wp.transpose(cam.R) * v_pc
    v_means[g, 0] = vm[0]
    v_means[g, 1] = vm[1]
    v_means[g, 2] = vm[2]

    # world covariance -> scales and rotation
    v_cov3 = wp.transpose(cam.R) * v_covc * cam.R
    v_L = 2.0 * (v_cov3 * L)
    v_M = v_L * wp.diag(s)
    for k in range(3):
        v_s = M[0, k] * v_L[0, k] + M[1, k] * v_L[1, k] + M[2, k] * v_L[2, k]
        v_log_scales[g, k] = v_s * s[k]
    v_qn = quat_to_rotmat_vjp(qn, v_M)
    v_q = (v_qn - qn * wp.dot(qn, v_qn)) / qnorm
    for k in range(4):
        v_quats[g, k] = v_q[k]


@wp.kernel
def project_gaussians_backward(
    offset: int,
    means: wp.array2d(dtype=float),  # [N, 3]
    log_scales: wp.array2d(dtype=float),  # [N, 3]
    quats: wp.array2d(dtype=float),  # [N, 4]
    opacity_logits: wp.array(dtype=float),  # [N]
    cam: Camera,
    eps2d: float,
    antialiased: int,
    radii: wp.array(dtype=wp.int32),  # [N] 0 = culled: all gradients 0
    v_means2d: wp.array(dtype=wp.vec2),  # [N] upstream
    v_conics: wp.array(dtype=wp.vec3),  # [N] upstream
    v_depths: wp.array(dtype=float),  # [N] upstream (camera z)
    v_opacities: wp.array(dtype=float),  # [N] upstream (d/d effective opacity)
    v_means: wp.array2d(dtype=float),  # [N, 3] out
    v_log_scales: wp.array2d(dtype=float),  # [N, 3] out
    v_quats: wp.array2d(dtype=float),  # [N, 4] out
    v_opacity_logits: wp.array(dtype=float),  # [N] out
    v_pose_partial: wp.array(dtype=vec6),  # [N] out, this Gaussian's term of v_pose
):
    project_backward_one(offset + wp.tid(), means, log_scales, quats, opacity_logits, cam, eps2d, antialiased, radii,
                         v_means2d, v_conics, v_depths, v_opacities, v_means, v_log_scales, v_quats,
                         v_opacity_logits, v_pose_partial)


# The CPU's projection backward in C++ blocks, 16 Gaussians a vector (clang's vector types): the operations of
# project_backward_one in the same order, each as Warp's CPU code does it, so the same gradients bit for bit: matrix
# products as Warp's mat_t mul (each entry a chain of fmaf from 0), matrix-vector products, dot and cross products
# as Warp's vec_t code (no FMA: contraction stays off), min/max/clamp as C's fminf/fmaxf, exp as the C library's
# expf (per lane: the one function Warp calls). Returns 0 where it does not apply (CUDA, arrays not contiguous, the
# antialiased mode) and nothing is written.
_PROJECT_COMMON_CPP = LANES16_CPP + r"""
struct M3 { vf m[3][3]; };
auto clampv = [&](vf x, float a, float b) -> vf { return fmn(fmx((vf)a, x), (vf)b); };   // wp::clamp
auto mm = [](const M3& a, const M3& b) -> M3 {    // Warp's mat_t mul: sum = fmaf(a_ik, b_kj, sum) from 0
    M3 t;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            vf sum = 0.0f;
            for (int k = 0; k < 3; ++k) sum = __builtin_elementwise_fma(a.m[i][k], b.m[k][j], sum);
            t.m[i][j] = sum;
        }
    return t;
};
auto tr = [](const M3& a) -> M3 {
    M3 t;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) t.m[i][j] = a.m[j][i];
    return t;
};
auto diag = [](vf a, vf b, vf c) -> M3 {
    M3 t;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) t.m[i][j] = 0.0f;
    t.m[0][0] = a; t.m[1][1] = b; t.m[2][2] = c;
    return t;
};
auto expv = [](vf x) -> vf { vf r; for (int j = 0; j < 16; ++j) r[j] = ::expf(x[j]); return r; };
M3 RC;                                   // the camera's rotation, every lane
for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) RC.m[i][j] = cam.R.data[i][j];
const float fx = cam.fx, fy = cam.fy, lxn = cam.lim_x_neg, lxp = cam.lim_x_pos, lyn = cam.lim_y_neg,
            lyp = cam.lim_y_pos;
// quat_to_rotmat
auto rotmat = [](vf w, vf x, vf y, vf z) -> M3 {
    M3 t;
    t.m[0][0] = 1.0f - 2.0f * (y * y + z * z); t.m[0][1] = 2.0f * (x * y - w * z); t.m[0][2] = 2.0f * (x * z + w * y);
    t.m[1][0] = 2.0f * (x * y + w * z); t.m[1][1] = 1.0f - 2.0f * (x * x + z * z); t.m[1][2] = 2.0f * (y * z - w * x);
    t.m[2][0] = 2.0f * (x * z - w * y); t.m[2][1] = 2.0f * (y * z + w * x); t.m[2][2] = 1.0f - 2.0f * (x * x + y * y);
    return t;
};
// ewa_jacobian (first two rows; the third is zero)
auto jacobian = [&](vf px, vf py, vf z) -> M3 {
    const vf clx = clampv(px / z, -lxn, lxp), cly = clampv(py / z, -lyn, lyp);
    M3 t;
    t.m[0][0] = fx / z; t.m[0][1] = 0.0f; t.m[0][2] = -fx * clx / z;
    t.m[1][0] = 0.0f; t.m[1][1] = fy / z; t.m[1][2] = -fy * cly / z;
    t.m[2][0] = 0.0f; t.m[2][1] = 0.0f; t.m[2][2] = 0.0f;
    return t;
};
"""

_PROJECT_BWD_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
if (antialiased != 0 || means.strides[0] != 12 || means.strides[1] != 4 || log_scales.strides[0] != 12
    || log_scales.strides[1] != 4 || quats.strides[0] != 16 || quats.strides[1] != 4 || opacity_logits.strides[0] != 4
    || radii.strides[0] != 4 || v_means2d.strides[0] != 8 || v_conics.strides[0] != 12 || v_depths.strides[0] != 4
    || v_opacities.strides[0] != 4 || v_means.strides[0] != 12 || v_means.strides[1] != 4
    || v_log_scales.strides[0] != 12 || v_log_scales.strides[1] != 4 || v_quats.strides[0] != 16
    || v_quats.strides[1] != 4 || v_opacity_logits.strides[0] != 4 || v_pose_partial.strides[0] != 24) return 0;
@COMMON@
const float* PM = (const float*)means.data;
const float* PL = (const float*)log_scales.data;
const float* PQ = (const float*)quats.data;
const float* PO = (const float*)opacity_logits.data;
const int* RD = (const int*)radii.data;
const float* VM2 = (const float*)v_means2d.data;
const float* VCN = (const float*)v_conics.data;
const float* VD = (const float*)v_depths.data;
const float* VOP = (const float*)v_opacities.data;
float* OM = (float*)v_means.data;
float* OL = (float*)v_log_scales.data;
float* OQ = (float*)v_quats.data;
float* OO = (float*)v_opacity_logits.data;
float* OP = (float*)v_pose_partial.data;
const float t0 = cam.t[0], t1 = cam.t[1], t2 = cam.t[2];
for (int g0 = lo; g0 < hi; g0 += 16) {
    const int m = hi - g0 < 16 ? hi - g0 : 16;
    // a group none of whose Gaussians this view shows (many of a real map's once it is in spatial order:
    // GaussianMap.sort_spatially): zeros, as its lanes below would write, without the arithmetic
    int shown = 0;
    for (int j = 0; j < m; ++j) shown |= RD[g0 + j];
    if (shown == 0) {
        for (int j = 0; j < m; ++j) {
            const long gi = g0 + j;
            OM[3 * gi] = 0.0f; OM[3 * gi + 1] = 0.0f; OM[3 * gi + 2] = 0.0f;
            OL[3 * gi] = 0.0f; OL[3 * gi + 1] = 0.0f; OL[3 * gi + 2] = 0.0f;
            OQ[4 * gi] = 0.0f; OQ[4 * gi + 1] = 0.0f; OQ[4 * gi + 2] = 0.0f; OQ[4 * gi + 3] = 0.0f;
            OO[gi] = 0.0f;
            float* pp = OP + 6 * gi;
            pp[0] = 0.0f; pp[1] = 0.0f; pp[2] = 0.0f; pp[3] = 0.0f; pp[4] = 0.0f; pp[5] = 0.0f;
        }
        continue;
    }
    vf p0, p1, p2, q0, q1, q2, q3, l0, l1, l2, ol, vm0, vm1, va, vb, vc, vdep, vop;
    for (int j = 0; j < 16; ++j) {
        const long g = g0 + (j < m ? j : 0);
        p0[j] = PM[3 * g]; p1[j] = PM[3 * g + 1]; p2[j] = PM[3 * g + 2];
        q0[j] = PQ[4 * g]; q1[j] = PQ[4 * g + 1]; q2[j] = PQ[4 * g + 2]; q3[j] = PQ[4 * g + 3];
        l0[j] = PL[3 * g]; l1[j] = PL[3 * g + 1]; l2[j] = PL[3 * g + 2];
        ol[j] = PO[g];
        vm0[j] = VM2[2 * g]; vm1[j] = VM2[2 * g + 1];
        va[j] = VCN[3 * g]; vb[j] = VCN[3 * g + 1]; vc[j] = VCN[3 * g + 2];
        vdep[j] = VD[g]; vop[j] = VOP[g];
    }
    const vf sig = 1.0f / (1.0f + expv(-ol));
    // pc = R p + t (mat_t * vec_t: column 0 times p0, plus column 1 times p1, plus column 2 times p2)
    const vf x = RC.m[0][0] * p0 + RC.m[0][1] * p1 + RC.m[0][2] * p2 + t0;
    const vf y = RC.m[1][0] * p0 + RC.m[1][1] * p1 + RC.m[1][2] * p2 + t1;
    const vf z = RC.m[2][0] * p0 + RC.m[2][1] * p1 + RC.m[2][2] * p2 + t2;
    const vf qnorm = sqrtv(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3);   // length(vec4)
    const vf w_ = q0 / qnorm, x_ = q1 / qnorm, y_ = q2 / qnorm, z_ = q3 / qnorm;
    const M3 M = rotmat(w_, x_, y_, z_);
    const vf s0 = expv(l0), s1 = expv(l1), s2 = expv(l2);
    const M3 L = mm(M, diag(s0, s1, s2));
    const M3 cov3 = mm(L, tr(L));
    const M3 covc = mm(mm(RC, cov3), tr(RC));
    const M3 J = jacobian(x, y, z);
    const M3 m2 = mm(mm(J, covc), tr(J));
    const vf cv0 = m2.m[0][0] + eps2d, cv1 = m2.m[0][1], cv2 = m2.m[1][1] + eps2d;
    const vf det = cv0 * cv2 - cv1 * cv1;
    const vf inv_det = 1.0f / det;
    const vf a = cv2 * inv_det, b = -cv1 * inv_det, c = cv0 * inv_det;
    // G2 = -(Q V Q), mat22 products as mat_t mul
    const vf hv = 0.5f * vb;
    auto f2 = [](vf a0, vf b0, vf a1, vf b1) -> vf {
        return __builtin_elementwise_fma(a1, b1, __builtin_elementwise_fma(a0, b0, (vf)0.0f));
    };
    const vf QV00 = f2(a, va, b, hv), QV01 = f2(a, hv, b, vc), QV10 = f2(b, va, c, hv), QV11 = f2(b, hv, c, vc);
    const vf G00 = -f2(QV00, a, QV01, b), G01 = -f2(QV00, b, QV01, c);
    const vf G10 = -f2(QV10, a, QV11, b), G11 = -f2(QV10, b, QV11, c);
    const vf comp = 1.0f;
    const vf v_ol = vop * comp * sig * (1.0f - sig);
    M3 G;
    G.m[0][0] = G00; G.m[0][1] = G01; G.m[0][2] = 0.0f;
    G.m[1][0] = G10; G.m[1][1] = G11; G.m[1][2] = 0.0f;
    G.m[2][0] = 0.0f; G.m[2][1] = 0.0f; G.m[2][2] = 0.0f;
    const M3 v_covc = mm(mm(tr(J), G), J);
    M3 v_J = mm(mm(G, J), covc);
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k) v_J.m[i][k] = v_J.m[i][k] * 2.0f;
    const vf clx = clampv(x / z, -lxn, lxp), cly = clampv(y / z, -lyn, lyp);
    const vf z2 = z * z;
    vf vx = 0.0f, vy = 0.0f, vz = vdep;
    vz = vz + (v_J.m[0][0] * (-fx / z2) + v_J.m[1][1] * (-fy / z2));
    vz = vz + (v_J.m[0][2] * (fx * clx / z2) + v_J.m[1][2] * (fy * cly / z2));
    const vf v_clx = v_J.m[0][2] * (-fx / z), v_cly = v_J.m[1][2] * (-fy / z);
    const vf rx = x / z, ry = y / z;
    const vi inx = (rx >= -lxn) & (rx <= lxp), iny = (ry >= -lyn) & (ry <= lyp);
    vx = sel(inx, vx + v_clx / z, vx);
    vz = sel(inx, vz + -v_clx * x / z2, vz);
    vy = sel(iny, vy + v_cly / z, vy);
    vz = sel(iny, vz + -v_cly * y / z2, vz);
    vx = vx + fx / z * vm0;
    vy = vy + fy / z * vm1;
    vz = vz + (-fx * x / z2 * vm0 - fy * y / z2 * vm1);
    // pose
    const M3 A1 = mm(v_covc, covc), A2 = mm(covc, v_covc);
    const vf r0 = (A1.m[2][1] - A2.m[2][1]) - (A1.m[1][2] - A2.m[1][2]);
    const vf r1 = (A1.m[0][2] - A2.m[0][2]) - (A1.m[2][0] - A2.m[2][0]);
    const vf r2 = (A1.m[1][0] - A2.m[1][0]) - (A1.m[0][1] - A2.m[0][1]);
    const vf vr0 = r0 + (y * vz - z * vy), vr1 = r1 + (z * vx - x * vz), vr2 = r2 + (x * vy - y * vx);
    // means: R^T v_pc (mat_t * vec_t with the transpose's columns, R's rows)
    const vf om0 = RC.m[0][0] * vx + RC.m[1][0] * vy + RC.m[2][0] * vz;
    const vf om1 = RC.m[0][1] * vx + RC.m[1][1] * vy + RC.m[2][1] * vz;
    const vf om2 = RC.m[0][2] * vx + RC.m[1][2] * vy + RC.m[2][2] * vz;
    // world covariance -> scales and rotation
    const M3 v_cov3 = mm(mm(tr(RC), v_covc), RC);
    M3 v_L = mm(v_cov3, L);
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k) v_L.m[i][k] = v_L.m[i][k] * 2.0f;
    const M3 g = mm(v_L, diag(s0, s1, s2));
    const vf ols0 = (M.m[0][0] * v_L.m[0][0] + M.m[1][0] * v_L.m[1][0] + M.m[2][0] * v_L.m[2][0]) * s0;
    const vf ols1 = (M.m[0][1] * v_L.m[0][1] + M.m[1][1] * v_L.m[1][1] + M.m[2][1] * v_L.m[2][1]) * s1;
    const vf ols2 = (M.m[0][2] * v_L.m[0][2] + M.m[1][2] * v_L.m[1][2] + M.m[2][2] * v_L.m[2][2]) * s2;
    // quat_to_rotmat_vjp
    const vf w = w_, qx = x_, qy = y_, qz = z_;
    const vf v_w = 2.0f * (-qz * g.m[0][1] + qy * g.m[0][2] + qz * g.m[1][0] - qx * g.m[1][2] - qy * g.m[2][0]
                           + qx * g.m[2][1]);
    const vf v_x = 2.0f * (qy * g.m[0][1] + qz * g.m[0][2] + qy * g.m[1][0] - 2.0f * qx * g.m[1][1] - w * g.m[1][2]
                           + qz * g.m[2][0] + w * g.m[2][1] - 2.0f * qx * g.m[2][2]);
    const vf v_y = 2.0f * (-2.0f * qy * g.m[0][0] + qx * g.m[0][1] + w * g.m[0][2] + qx * g.m[1][0] + qz * g.m[1][2]
                           - w * g.m[2][0] + qz * g.m[2][1] - 2.0f * qy * g.m[2][2]);
    const vf v_z = 2.0f * (-2.0f * qz * g.m[0][0] - w * g.m[0][1] + qx * g.m[0][2] + w * g.m[1][0]
                           - 2.0f * qz * g.m[1][1] + qy * g.m[1][2] + qx * g.m[2][0] + qy * g.m[2][1]);
    const vf d = 0.0f + w * v_w + qx * v_x + qy * v_y + qz * v_z;     // dot(vec4): from 0
    const vf oq0 = (v_w - w * d) / qnorm, oq1 = (v_x - qx * d) / qnorm, oq2 = (v_y - qy * d) / qnorm,
             oq3 = (v_z - qz * d) / qnorm;
    for (int j = 0; j < m; ++j) {
        const long gi = g0 + j;
        const bool live = RD[gi] != 0;
        OM[3 * gi] = live ? om0[j] : 0.0f; OM[3 * gi + 1] = live ? om1[j] : 0.0f; OM[3 * gi + 2] = live ? om2[j] : 0.0f;
        OL[3 * gi] = live ? ols0[j] : 0.0f; OL[3 * gi + 1] = live ? ols1[j] : 0.0f;
        OL[3 * gi + 2] = live ? ols2[j] : 0.0f;
        OQ[4 * gi] = live ? oq0[j] : 0.0f; OQ[4 * gi + 1] = live ? oq1[j] : 0.0f; OQ[4 * gi + 2] = live ? oq2[j] : 0.0f;
        OQ[4 * gi + 3] = live ? oq3[j] : 0.0f;
        OO[gi] = live ? v_ol[j] : 0.0f;
        float* pp = OP + 6 * gi;
        pp[0] = live ? vx[j] : 0.0f; pp[1] = live ? vy[j] : 0.0f; pp[2] = live ? vz[j] : 0.0f;
        pp[3] = live ? vr0[j] : 0.0f; pp[4] = live ? vr1[j] : 0.0f; pp[5] = live ? vr2[j] : 0.0f;
    }
}
return 1;
#else
return 0;
#endif
""".replace("@COMMON@", _PROJECT_COMMON_CPP)


@wp.func_native(_PROJECT_BWD_CPP)
def project_backward_cpp(lo: int, hi: int, means: wp.array2d(dtype=float), log_scales: wp.array2d(dtype=float),
                         quats: wp.array2d(dtype=float), opacity_logits: wp.array(dtype=float), cam: Camera,
                         eps2d: float, antialiased: int, radii: wp.array(dtype=wp.int32),
                         v_means2d: wp.array(dtype=wp.vec2), v_conics: wp.array(dtype=wp.vec3),
                         v_depths: wp.array(dtype=float), v_opacities: wp.array(dtype=float),
                         v_means: wp.array2d(dtype=float), v_log_scales: wp.array2d(dtype=float),
                         v_quats: wp.array2d(dtype=float), v_opacity_logits: wp.array(dtype=float),
                         v_pose_partial: wp.array(dtype=vec6)) -> int:
    """:func:`project_backward_one` of the Gaussians ``[lo, hi)`` in C++ (above): the same values bit for bit.
    Returns 1, or 0 where it does not apply (nothing written)."""
    ...


@wp.kernel
def project_gaussians_backward_blocks(
    offset: int,
    block: int,  # Gaussians a thread
    n: int,
    means: wp.array2d(dtype=float),
    log_scales: wp.array2d(dtype=float),
    quats: wp.array2d(dtype=float),
    opacity_logits: wp.array(dtype=float),
    cam: Camera,
    eps2d: float,
    antialiased: int,
    radii: wp.array(dtype=wp.int32),
    v_means2d: wp.array(dtype=wp.vec2),
    v_conics: wp.array(dtype=wp.vec3),
    v_depths: wp.array(dtype=float),
    v_opacities: wp.array(dtype=float),
    v_means: wp.array2d(dtype=float),
    v_log_scales: wp.array2d(dtype=float),
    v_quats: wp.array2d(dtype=float),
    v_opacity_logits: wp.array(dtype=float),
    v_pose_partial: wp.array(dtype=vec6),
    native: int,  # 1: the C++ block where it applies; 0: the function's loop (raster_tile.use_native)
    status: wp.array(dtype=wp.int32),  # [blocks] out: 1 where the C++ block did the Gaussians
):
    """:func:`project_gaussians_backward` with ``block`` Gaussians a thread, for the CPU: the C++ block first,
    :func:`project_backward_one` where it declines."""
    c = offset + wp.tid()
    lo = c * block
    hi = wp.min(lo + block, n)
    done = int(0)
    if native != 0:
        done = project_backward_cpp(lo, hi, means, log_scales, quats, opacity_logits, cam, eps2d, antialiased, radii,
                                    v_means2d, v_conics, v_depths, v_opacities, v_means, v_log_scales, v_quats,
                                    v_opacity_logits, v_pose_partial)
    status[c] = done
    if done == 0:
        for g in range(lo, hi):
            project_backward_one(g, means, log_scales, quats, opacity_logits, cam, eps2d, antialiased, radii,
                                 v_means2d, v_conics, v_depths, v_opacities, v_means, v_log_scales, v_quats,
                                 v_opacity_logits, v_pose_partial)


#: Gaussians a thread of the CPU's projection blocks.
PROJECT_BLOCK = 256


_PROJECT_FWD_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
if (antialiased != 0 || means.strides[0] != 12 || means.strides[1] != 4 || log_scales.strides[0] != 12
    || log_scales.strides[1] != 4 || quats.strides[0] != 16 || quats.strides[1] != 4 || opacity_logits.strides[0] != 4
    || means2d.strides[0] != 8 || conics.strides[0] != 12 || depths.strides[0] != 4 || opacities.strides[0] != 4
    || radii.strides[0] != 4 || splats.strides[0] != 32) return 0;
@COMMON@
const float* PM = (const float*)means.data;
const float* PL = (const float*)log_scales.data;
const float* PQ = (const float*)quats.data;
const float* PO = (const float*)opacity_logits.data;
float* OM2 = (float*)means2d.data;
float* OC = (float*)conics.data;
float* OD = (float*)depths.data;
float* OOP = (float*)opacities.data;
int* ORD = (int*)radii.data;
float* OS = (float*)splats.data;
const float t0 = cam.t[0], t1 = cam.t[1], t2 = cam.t[2];
const float near_ = cam.near, far_ = cam.far, cx = cam.cx, cy = cam.cy;
const float Wm1 = (float)(cam.width - 1), Hm1 = (float)(cam.height - 1);
const float AMIN = @ALPHA_MIN@, RREL = @R2_REL@, RABS = @R2_ABS@;
for (int g0 = lo; g0 < hi; g0 += 16) {
    const int m = hi - g0 < 16 ? hi - g0 : 16;
    vf p0, p1, p2, ol;
    for (int j = 0; j < 16; ++j) {
        const long g = g0 + (j < m ? j : 0);
        p0[j] = PM[3 * g]; p1[j] = PM[3 * g + 1]; p2[j] = PM[3 * g + 2]; ol[j] = PO[g];
    }
    const vf x = RC.m[0][0] * p0 + RC.m[0][1] * p1 + RC.m[0][2] * p2 + t0;
    const vf y = RC.m[1][0] * p0 + RC.m[1][1] * p1 + RC.m[1][2] * p2 + t1;
    const vf z = RC.m[2][0] * p0 + RC.m[2][1] * p1 + RC.m[2][2] * p2 + t2;
    const vf op = 1.0f / (1.0f + expv(-ol));
    // the lanes past the culls by depth and opacity (the compensation, off here, only lowers it)
    const vi go = (z > near_) & (z < far_) & ~(op < AMIN);
    int any = 0;
    for (int j = 0; j < m; ++j) {
        const long g = g0 + j;
        OD[g] = z[j]; OOP[g] = op[j]; ORD[g] = 0;
        OM2[2 * g] = 0.0f; OM2[2 * g + 1] = 0.0f;
        OC[3 * g] = 0.0f; OC[3 * g + 1] = 0.0f; OC[3 * g + 2] = 0.0f;
        any |= go[j];
    }
    if (!any) continue;
    vf q0, q1, q2, q3, l0, l1, l2;
    for (int j = 0; j < 16; ++j) {
        const long g = g0 + (j < m ? j : 0);
        q0[j] = PQ[4 * g]; q1[j] = PQ[4 * g + 1]; q2[j] = PQ[4 * g + 2]; q3[j] = PQ[4 * g + 3];
        l0[j] = PL[3 * g]; l1[j] = PL[3 * g + 1]; l2[j] = PL[3 * g + 2];
    }
    {
        // a group that lies wholly off the image (many of a real map's once it is in spatial order: see
        // GaussianMap.sort_spatially) is passed over before its covariances: its screen extent is at most
        // sqrt(r2 (|J row|^2 s_max^2 + eps2d)) with r2 at opacity 1 and s_max <= 2^ceil(log2(e) max log-scale), both
        // with a margin, and a pixel more; where that extent misses the image the lane's exact test below misses it
        // too, so the outputs are those already written (a NaN or infinite scale is never shown either)
        const vf lmax = fmx(fmx(l0, l1), l2);
        const vf e2 = fmn(fmx(__builtin_elementwise_ceil(lmax * 1.4427f + 0.01f), (vf)-126.0f), (vf)127.0f);
        const vf smax = (vf)((__builtin_convertvector(e2, vi) + 127) << 23);
        const vf s2 = smax * smax * 1.01f;
        const vf rx = x / z, ry = y / z;
        const vf bx = sqrtv(@R2_BOUND@ * (fx * fx / (z * z) * (1.0f + rx * rx) * s2 + eps2d)) + 1.0f;
        const vf by = sqrtv(@R2_BOUND@ * (fy * fy / (z * z) * (1.0f + ry * ry) * s2 + eps2d)) + 1.0f;
        const vf bmx = fx * x / z + cx, bmy = fy * y / z + cy;
        const vi off = (bmx + bx < 0.0f) | (bmx - bx > Wm1) | (bmy + by < 0.0f) | (bmy - by > Hm1);
        const vi maybe = go & ~off;
        int shown = 0;
        for (int j = 0; j < m; ++j) shown |= maybe[j];
        if (!shown) continue;
    }
    // normalize(vec4): q / length(q) where length > 0, else the zero vector
    const vf len = sqrtv(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3);
    const vi pos = len > 0.0f;
    const vf w_ = sel(pos, q0 / len, (vf)0.0f), x_ = sel(pos, q1 / len, (vf)0.0f), y_ = sel(pos, q2 / len, (vf)0.0f),
             z_ = sel(pos, q3 / len, (vf)0.0f);
    const M3 M = rotmat(w_, x_, y_, z_);
    vf s0, s1, s2;
    for (int j = 0; j < 16; ++j) {
        s0[j] = go[j] ? ::expf(l0[j]) : 1.0f; s1[j] = go[j] ? ::expf(l1[j]) : 1.0f;
        s2[j] = go[j] ? ::expf(l2[j]) : 1.0f;
    }
    const M3 L = mm(M, diag(s0, s1, s2));
    const M3 covc = mm(mm(RC, mm(L, tr(L))), tr(RC));
    const M3 J = jacobian(x, y, z);
    const M3 m2 = mm(mm(J, covc), tr(J));
    const vf cv0 = m2.m[0][0] + eps2d, cv1 = m2.m[0][1], cv2 = m2.m[1][1] + eps2d;
    const vf det = cv0 * cv2 - cv1 * cv1;
    const vi ok = go & (det > 0.0f) & (det - det == 0.0f);
    const vf inv_det = 1.0f / det;
    const vf mx = fx * x / z + cx, my = fy * y / z + cy;
    vf lg;
    for (int j = 0; j < 16; ++j) lg[j] = ok[j] ? ::logf(255.0f * op[j]) : 1.0f;
    const vf r2 = 2.0f * lg * (1.0f + RREL) + RABS;
    const vf ex = sqrtv(r2 * cv0), ey = sqrtv(r2 * cv2);
    const vi vis = ok & ~((mx + ex < 0.0f) | (mx - ex > Wm1) | (my + ey < 0.0f) | (my - ey > Hm1));
    const vf a = cv2 * inv_det, b = -cv1 * inv_det, c = cv0 * inv_det;
    vf ea;
    for (int j = 0; j < 16; ++j) ea[j] = vis[j] ? ::expf(-a[j]) : 0.0f;
    const vf mid = 0.5f * (cv0 + cv2);
    const vf lam = mid + sqrtv(fmx((vf)0.1f, mid * mid - det));
    const vi rad = ceili(3.0f * sqrtv(lam));
    for (int j = 0; j < m; ++j) {
        if (!vis[j]) continue;
        const long g = g0 + j;
        OM2[2 * g] = mx[j]; OM2[2 * g + 1] = my[j];
        OC[3 * g] = a[j]; OC[3 * g + 1] = b[j]; OC[3 * g + 2] = c[j];
        float* sp = OS + 8 * g;
        sp[0] = mx[j]; sp[1] = my[j]; sp[2] = a[j]; sp[3] = b[j]; sp[4] = c[j]; sp[5] = op[j]; sp[6] = ea[j];
        sp[7] = r2[j];
        ORD[g] = rad[j] > 1 ? rad[j] : 1;
    }
}
return 1;
#else
return 0;
#endif
"""
for _name, _value in (("@COMMON@", _PROJECT_COMMON_CPP), ("@ALPHA_MIN@", ALPHA_MIN), ("@R2_REL@", R2_REL_MARGIN),
                      ("@R2_ABS@", R2_ABS_MARGIN),
                      ("@R2_BOUND@", 1.001 * (2.0 * np.log(255.0) * (1.0 + R2_REL_MARGIN) + R2_ABS_MARGIN))):
    _PROJECT_FWD_CPP = _PROJECT_FWD_CPP.replace(
        _name, _value if isinstance(_value, str) else repr(float(np.float32(_value))) + "f")
del _name, _value


@wp.func_native(_PROJECT_FWD_CPP)
def project_cpp(lo: int, hi: int, means: wp.array2d(dtype=float), log_scales: wp.array2d(dtype=float),
                quats: wp.array2d(dtype=float), opacity_logits: wp.array(dtype=float), cam: Camera, eps2d: float,
                antialiased: int, means2d: wp.array(dtype=wp.vec2), conics: wp.array(dtype=wp.vec3),
                depths: wp.array(dtype=float), opacities: wp.array(dtype=float), radii: wp.array(dtype=wp.int32),
                splats: wp.array(dtype=vec8)) -> int:
    """:func:`project_one` of the Gaussians ``[lo, hi)`` in C++ (above): the same values bit for bit. Returns 1, or
    0 where it does not apply (nothing written)."""
    ...


@wp.kernel
def project_gaussians_blocks(
    offset: int,
    block: int,  # Gaussians a thread
    n: int,
    means: wp.array2d(dtype=float),
    log_scales: wp.array2d(dtype=float),
    quats: wp.array2d(dtype=float),
    opacity_logits: wp.array(dtype=float),
    cam: Camera,
    eps2d: float,
    antialiased: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    opacities: wp.array(dtype=float),
    radii: wp.array(dtype=wp.int32),
    splats: wp.array(dtype=vec8),
    native: int,  # 1: the C++ block where it applies; 0: the function's loop (raster_tile.use_native)
    status: wp.array(dtype=wp.int32),  # [blocks] out: 1 where the C++ block did the Gaussians
):
    """:func:`project_gaussians` with ``block`` Gaussians a thread, for the CPU: the C++ block first,
    :func:`project_one` where it declines."""
    c = offset + wp.tid()
    lo = c * block
    hi = wp.min(lo + block, n)
    done = int(0)
    if native != 0:
        done = project_cpp(lo, hi, means, log_scales, quats, opacity_logits, cam, eps2d, antialiased, means2d, conics,
                           depths, opacities, radii, splats)
    status[c] = done
    if done == 0:
        for g in range(lo, hi):
            project_one(g, means, log_scales, quats, opacity_logits, cam, eps2d, antialiased, means2d, conics, depths,
                        opacities, radii, splats)


@wp.kernel
def project_gaussians_blocks_dynamic(
    offset: int,  # the chunk's index (launch_split's offset)
    shares: wp.array(dtype=wp.int64),  # each chunk's range of blocks, taken from both ends (mgso_kernels.dynamic)
    n_blocks: int,
    block: int,
    n: int,
    means: wp.array2d(dtype=float),
    log_scales: wp.array2d(dtype=float),
    quats: wp.array2d(dtype=float),
    opacity_logits: wp.array(dtype=float),
    cam: Camera,
    eps2d: float,
    antialiased: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    depths: wp.array(dtype=float),
    opacities: wp.array(dtype=float),
    radii: wp.array(dtype=wp.int32),
    splats: wp.array(dtype=vec8),
    status: wp.array(dtype=wp.int32),  # [blocks] out: 1 where the C++ block did the Gaussians, 0 where it declined
):
    """:func:`project_gaussians_blocks`' C++ blocks, a chunk a core taking blocks from ``shares``
    (:func:`mgso_kernels.dynamic.launch_blocks`): the same values bit for bit. A block the C++ declines is left
    undone with status 0 (the launcher then runs :func:`project_gaussians_blocks`)."""
    chunk = offset + wp.tid()
    chunks = shares.shape[0]
    for k in range(chunks):   # its own range, then the others' from their far end
        r = (chunk + k) % chunks
        c = take_item(shares, r, k)
        while c >= 0:
            lo = c * block
            status[c] = project_cpp(lo, wp.min(lo + block, n), means, log_scales, quats, opacity_logits, cam, eps2d,
                                    antialiased, means2d, conics, depths, opacities, radii, splats)
            c = take_item(shares, r, k)


@wp.kernel
def project_gaussians_backward_blocks_dynamic(
    offset: int,  # the chunk's index (launch_split's offset)
    shares: wp.array(dtype=wp.int64),  # each chunk's range of blocks, taken from both ends (mgso_kernels.dynamic)
    n_blocks: int,
    block: int,
    n: int,
    means: wp.array2d(dtype=float),
    log_scales: wp.array2d(dtype=float),
    quats: wp.array2d(dtype=float),
    opacity_logits: wp.array(dtype=float),
    cam: Camera,
    eps2d: float,
    antialiased: int,
    radii: wp.array(dtype=wp.int32),
    v_means2d: wp.array(dtype=wp.vec2),
    v_conics: wp.array(dtype=wp.vec3),
    v_depths: wp.array(dtype=float),
    v_opacities: wp.array(dtype=float),
    v_means: wp.array2d(dtype=float),
    v_log_scales: wp.array2d(dtype=float),
    v_quats: wp.array2d(dtype=float),
    v_opacity_logits: wp.array(dtype=float),
    v_pose_partial: wp.array(dtype=vec6),
    status: wp.array(dtype=wp.int32),  # [blocks] out: 1 where the C++ block did the Gaussians, 0 where it declined
):
    """:func:`project_gaussians_backward_blocks`' C++ blocks, a chunk a core taking blocks from ``shares``
    (see :func:`project_gaussians_blocks_dynamic`)."""
    chunk = offset + wp.tid()
    chunks = shares.shape[0]
    for k in range(chunks):   # its own range, then the others' from their far end
        r = (chunk + k) % chunks
        c = take_item(shares, r, k)
        while c >= 0:
            lo = c * block
            status[c] = project_backward_cpp(lo, wp.min(lo + block, n), means, log_scales, quats, opacity_logits, cam,
                                             eps2d, antialiased, radii, v_means2d, v_conics, v_depths, v_opacities,
                                             v_means, v_log_scales, v_quats, v_opacity_logits, v_pose_partial)
            c = take_item(shares, r, k)


@wp.kernel
def reduce_pose(
    offset: int,
    v_pose_partial: wp.array(dtype=vec6),  # [N] per-Gaussian terms
    n: int,
    block_sums: wp.array(dtype=vec6d),  # [ceil(N / POSE_BLOCK)] out, float64
):
    blk = offset + wp.tid()
    acc = vec6d(wp.float64(0.0))
    start = blk * POSE_BLOCK
    end = wp.min(start + POSE_BLOCK, n)
    for i in range(start, end):
        p = v_pose_partial[i]
        for k in range(6):
            acc[k] = acc[k] + wp.float64(p[k])
    block_sums[blk] = acc


@wp.kernel
def finish_pose(
    block_sums: wp.array(dtype=vec6d),  # [B]
    n_blocks: int,
    v_pose: wp.array(dtype=float),  # [6] out
):
    acc = vec6d(wp.float64(0.0))
    for b in range(n_blocks):
        acc += block_sums[b]
    for k in range(6):
        v_pose[k] = float(acc[k])


# ------------------------------------------------------------------------------------------------- launchers
def launch_project(means, log_scales, quats, opacity_logits, cam: Camera, eps2d: float, antialiased: bool, means2d,
                   conics, depths, opacities, radii, splats, device: str, threads: int | None = None,
                   min_chunk: int = 4096):
    """Project ``N = means.shape[0]`` Gaussians into the given output arrays (each at least N long). On the CPU in
    C++ blocks of :data:`PROJECT_BLOCK` Gaussians (returns their status: 1 where the C++ ran), elsewhere the
    thread-per-Gaussian kernel (None)."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = means.shape[0]
    for name, a, shape in (("means", means, (n, 3)), ("log_scales", log_scales, (n, 3)), ("quats", quats, (n, 4)),
                           ("opacity_logits", opacity_logits, (n,))):
        check_array(a, name, wp.float32, shape, device)
    for name, a, dt in (("means2d", means2d, wp.vec2), ("conics", conics, wp.vec3), ("depths", depths, wp.float32),
                        ("opacities", opacities, wp.float32), ("radii", radii, wp.int32), ("splats", splats, vec8)):
        check_array(a, name, dt, (n,), device)
    inputs = [means, log_scales, quats, opacity_logits, cam, float(eps2d), int(bool(antialiased)), means2d, conics,
              depths, opacities, radii, splats]
    if wp.get_device(device).is_cpu:
        from .raster_tile import native_flag

        return dynamic.launch_blocks(project_gaussians_blocks, project_gaussians_blocks_dynamic, n, PROJECT_BLOCK,
                                     inputs, native_flag(), device, threads=threads, min_chunk=min_chunk)
    launch_split(project_gaussians, n, inputs, device, threads=threads, min_chunk=min_chunk)
    return None


def launch_project_backward(means, log_scales, quats, opacity_logits, cam: Camera, eps2d: float, antialiased: bool,
                            radii, v_means2d, v_conics, v_depths, v_opacities, v_means, v_log_scales, v_quats,
                            v_opacity_logits, v_pose_partial, device: str, threads: int | None = None,
                            min_chunk: int = 4096):
    """Gradients through the projection (see :func:`project_gaussians_backward`); outputs are overwritten. On the
    CPU in C++ blocks of :data:`PROJECT_BLOCK` Gaussians (returns their status: 1 where the C++ ran), elsewhere the
    thread-per-Gaussian kernel (None)."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = means.shape[0]
    for name, a, dt, shape in (("means", means, wp.float32, (n, 3)), ("log_scales", log_scales, wp.float32, (n, 3)),
                               ("quats", quats, wp.float32, (n, 4)),
                               ("opacity_logits", opacity_logits, wp.float32, (n,)),
                               ("radii", radii, wp.int32, (n,)), ("v_means2d", v_means2d, wp.vec2, (n,)),
                               ("v_conics", v_conics, wp.vec3, (n,)), ("v_depths", v_depths, wp.float32, (n,)),
                               ("v_opacities", v_opacities, wp.float32, (n,)),
                               ("v_means", v_means, wp.float32, (n, 3)),
                               ("v_log_scales", v_log_scales, wp.float32, (n, 3)),
                               ("v_quats", v_quats, wp.float32, (n, 4)),
                               ("v_opacity_logits", v_opacity_logits, wp.float32, (n,)),
                               ("v_pose_partial", v_pose_partial, vec6, (n,))):
        check_array(a, name, dt, shape, device)
    inputs = [means, log_scales, quats, opacity_logits, cam, float(eps2d), int(bool(antialiased)), radii, v_means2d,
              v_conics, v_depths, v_opacities, v_means, v_log_scales, v_quats, v_opacity_logits, v_pose_partial]
    if wp.get_device(device).is_cpu:
        from .raster_tile import native_flag

        return dynamic.launch_blocks(project_gaussians_backward_blocks, project_gaussians_backward_blocks_dynamic, n,
                                     PROJECT_BLOCK, inputs, native_flag(), device, threads=threads,
                                     min_chunk=min_chunk)
    launch_split(project_gaussians_backward, n, inputs, device, threads=threads, min_chunk=min_chunk)
    return None


def launch_reduce_pose(v_pose_partial, block_sums, v_pose, device: str, threads: int | None = None,
                       min_chunk: int = 4096) -> None:
    """Sum the (N,) per-Gaussian pose terms into ``v_pose`` (6,) in float64 blocks of :data:`POSE_BLOCK`."""
    from ..runtime import launch_split

    n = v_pose_partial.shape[0]
    n_blocks = max(1, -(-n // POSE_BLOCK))
    if block_sums.shape[0] < n_blocks:
        raise ValueError(f"block_sums: need {n_blocks} entries, got {block_sums.shape[0]}")
    launch_split(reduce_pose, n_blocks, [v_pose_partial, n, block_sums], device, threads=threads, min_chunk=16)
    wp.launch(finish_pose, dim=1, inputs=[block_sums, n_blocks, v_pose], device=device)
