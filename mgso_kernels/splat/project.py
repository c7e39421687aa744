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

Twin: :func:`mgso_kernels.reference.splat.project` / ``project_vjp``.
"""

from __future__ import annotations

import warp as wp

from .camera import Camera
from ..image import finite
from .common import ALPHA_MIN, cutoff_r2, vec6, vec8

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
    g = offset + wp.tid()
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
    g = offset + wp.tid()
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
                   min_chunk: int = 4096) -> None:
    """Project ``N = means.shape[0]`` Gaussians into the given output arrays (each at least N long)."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = means.shape[0]
    for name, a, shape in (("means", means, (n, 3)), ("log_scales", log_scales, (n, 3)), ("quats", quats, (n, 4)),
                           ("opacity_logits", opacity_logits, (n,))):
        check_array(a, name, wp.float32, shape, device)
    for name, a, dt in (("means2d", means2d, wp.vec2), ("conics", conics, wp.vec3), ("depths", depths, wp.float32),
                        ("opacities", opacities, wp.float32), ("radii", radii, wp.int32), ("splats", splats, vec8)):
        check_array(a, name, dt, (n,), device)
    launch_split(project_gaussians, n, [means, log_scales, quats, opacity_logits, cam, float(eps2d),
                                        int(bool(antialiased)), means2d, conics, depths, opacities, radii, splats],
                 device, threads=threads,
                 min_chunk=min_chunk)


def launch_project_backward(means, log_scales, quats, opacity_logits, cam: Camera, eps2d: float, antialiased: bool,
                            radii, v_means2d, v_conics, v_depths, v_opacities, v_means, v_log_scales, v_quats,
                            v_opacity_logits, v_pose_partial, device: str, threads: int | None = None,
                            min_chunk: int = 4096) -> None:
    """Gradients through the projection (see :func:`project_gaussians_backward`); outputs are overwritten."""
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
    launch_split(project_gaussians_backward, n, [means, log_scales, quats, opacity_logits, cam, float(eps2d),
                                                 int(bool(antialiased)), radii,
                                                 v_means2d, v_conics, v_depths, v_opacities, v_means, v_log_scales,
                                                 v_quats, v_opacity_logits, v_pose_partial], device,
                 threads=threads, min_chunk=min_chunk)


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
