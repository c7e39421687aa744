"""Spherical-harmonic colour, forward and backward (Warp module).

``rgb = max(0, 0.5 + sum_k B_k(d) * sh[g, k])`` with ``d`` the unit vector from the camera centre to the Gaussian's
mean and ``B_k`` the real SH basis of 3DGS (degree 0..3, ``K = (degree + 1)^2`` bases; degree 0 is the constant
``C0 = 0.28209479177387814``, view-independent colour as MGSO uses).

Backward: to the coefficients (zero where the colour was clamped at 0), to the mean through the view direction,
and to the camera pose through the camera centre (for degree >= 1; for degree 0 the direction does not matter and
both are zero). ``v_pose`` uses the package's left perturbation, under which the centre moves by ``-R^T v``
(translation part only).

Twin: :func:`mgso_kernels.reference.splat.sh_to_rgb` / ``sh_to_rgb_vjp``.
"""

from __future__ import annotations

import warp as wp

from .camera import Camera
from .common import vec6

wp.set_module_options({"enable_backward": False})

__all__ = ["evaluate_sh", "evaluate_sh_backward", "vec6", "SH_C0"]

SH_C0 = wp.constant(0.28209479177387814)
SH_C1 = wp.constant(0.4886025119029199)
SH_C2_0 = wp.constant(1.0925484305920792)
SH_C2_1 = wp.constant(-1.0925484305920792)
SH_C2_2 = wp.constant(0.31539156525252005)
SH_C2_3 = wp.constant(-1.0925484305920792)
SH_C2_4 = wp.constant(0.5462742152960396)
SH_C3_0 = wp.constant(-0.5900435899266435)
SH_C3_1 = wp.constant(2.890611442640554)
SH_C3_2 = wp.constant(-0.4570457994644658)
SH_C3_3 = wp.constant(0.3731763325901154)
SH_C3_4 = wp.constant(-0.4570457994644658)
SH_C3_5 = wp.constant(1.445305721320277)
SH_C3_6 = wp.constant(-0.5900435899266435)


@wp.func
def sh_coeff(sh: wp.array3d(dtype=float), g: int, k: int) -> wp.vec3:
    return wp.vec3(sh[g, k, 0], sh[g, k, 1], sh[g, k, 2])


@wp.func
def sh_basis(d: wp.vec3, k: int) -> float:
    """Basis function k (0..15) at unit direction d."""
    x = d[0]
    y = d[1]
    z = d[2]
    if k == 0:
        return SH_C0
    if k == 1:
        return -SH_C1 * y
    if k == 2:
        return SH_C1 * z
    if k == 3:
        return -SH_C1 * x
    if k == 4:
        return SH_C2_0 * x * y
    if k == 5:
        return SH_C2_1 * y * z
    if k == 6:
        return SH_C2_2 * (2.0 * z * z - x * x - y * y)
    if k == 7:
        return SH_C2_3 * x * z
    if k == 8:
        return SH_C2_4 * (x * x - y * y)
    if k == 9:
        return SH_C3_0 * y * (3.0 * x * x - y * y)
    if k == 10:
        return SH_C3_1 * x * y * z
    if k == 11:
        return SH_C3_2 * y * (4.0 * z * z - x * x - y * y)
    if k == 12:
        return SH_C3_3 * z * (2.0 * z * z - 3.0 * x * x - 3.0 * y * y)
    if k == 13:
        return SH_C3_4 * x * (4.0 * z * z - x * x - y * y)
    if k == 14:
        return SH_C3_5 * z * (x * x - y * y)
    return SH_C3_6 * x * (x * x - 3.0 * y * y)


@wp.func
def sh_basis_grad(d: wp.vec3, k: int) -> wp.vec3:
    """d B_k / d (x, y, z), the components treated as independent."""
    x = d[0]
    y = d[1]
    z = d[2]
    if k == 0:
        return wp.vec3(0.0)
    if k == 1:
        return wp.vec3(0.0, -SH_C1, 0.0)
    if k == 2:
        return wp.vec3(0.0, 0.0, SH_C1)
    if k == 3:
        return wp.vec3(-SH_C1, 0.0, 0.0)
    if k == 4:
        return SH_C2_0 * wp.vec3(y, x, 0.0)
    if k == 5:
        return SH_C2_1 * wp.vec3(0.0, z, y)
    if k == 6:
        return SH_C2_2 * wp.vec3(-2.0 * x, -2.0 * y, 4.0 * z)
    if k == 7:
        return SH_C2_3 * wp.vec3(z, 0.0, x)
    if k == 8:
        return SH_C2_4 * wp.vec3(2.0 * x, -2.0 * y, 0.0)
    if k == 9:
        return SH_C3_0 * wp.vec3(6.0 * x * y, 3.0 * x * x - 3.0 * y * y, 0.0)
    if k == 10:
        return SH_C3_1 * wp.vec3(y * z, x * z, x * y)
    if k == 11:
        return SH_C3_2 * wp.vec3(-2.0 * x * y, 4.0 * z * z - x * x - 3.0 * y * y, 8.0 * y * z)
    if k == 12:
        return SH_C3_3 * wp.vec3(-6.0 * x * z, -6.0 * y * z, 6.0 * z * z - 3.0 * x * x - 3.0 * y * y)
    if k == 13:
        return SH_C3_4 * wp.vec3(4.0 * z * z - 3.0 * x * x - y * y, -2.0 * x * y, 8.0 * x * z)
    if k == 14:
        return SH_C3_5 * wp.vec3(2.0 * x * z, -2.0 * y * z, x * x - y * y)
    return SH_C3_6 * wp.vec3(3.0 * x * x - 3.0 * y * y, -6.0 * x * y, 0.0)


@wp.func
def view_dir(means: wp.array2d(dtype=float), g: int, cam: Camera) -> wp.vec3:
    """Unnormalised direction from the camera centre to the mean, world frame."""
    return wp.vec3(means[g, 0], means[g, 1], means[g, 2]) - cam.centre


@wp.func
def sh_raw_color(sh: wp.array3d(dtype=float), g: int, num_bases: int, d: wp.vec3) -> wp.vec3:
    c = wp.vec3(0.5)
    for k in range(num_bases):
        c += sh_basis(d, k) * sh_coeff(sh, g, k)
    return c


@wp.kernel
def evaluate_sh(
    offset: int,
    sh: wp.array3d(dtype=float),  # [N, K, 3] SH coefficients
    means: wp.array2d(dtype=float),  # [N, 3] world
    num_bases: int,  # (degree + 1)^2 <= K
    cam: Camera,
    radii: wp.array(dtype=wp.int32),  # [N] 0 = culled (colour not computed, set to 0)
    depths: wp.array(dtype=float),  # [N] camera z, copied into the 4th component for the blend
    rgbz: wp.array(dtype=wp.vec4),  # [N] out, (R, G, B, depth)
):
    g = offset + wp.tid()
    if radii[g] == 0:
        rgbz[g] = wp.vec4(0.0)
        return
    d = wp.vec3(1.0, 0.0, 0.0)
    if num_bases > 1:
        d = wp.normalize(view_dir(means, g, cam))
    c = sh_raw_color(sh, g, num_bases, d)
    rgbz[g] = wp.vec4(wp.max(c[0], 0.0), wp.max(c[1], 0.0), wp.max(c[2], 0.0), depths[g])


@wp.kernel
def evaluate_sh_backward(
    offset: int,
    sh: wp.array3d(dtype=float),  # [N, K, 3]
    means: wp.array2d(dtype=float),  # [N, 3]
    num_bases: int,
    cam: Camera,
    radii: wp.array(dtype=wp.int32),  # [N]
    v_colors: wp.array(dtype=wp.vec3),  # [N] upstream
    v_sh: wp.array3d(dtype=float),  # [N, K, 3] out (written, all K)
    v_means: wp.array2d(dtype=float),  # [N, 3] in/out: the view-direction term is added
    v_pose_partial: wp.array(dtype=vec6),  # [N] in/out: the camera-centre term is added
):
    g = offset + wp.tid()
    K = sh.shape[1]
    if radii[g] == 0:
        for k in range(K):
            for ch in range(3):
                v_sh[g, k, ch] = 0.0
        return
    d = wp.vec3(1.0, 0.0, 0.0)
    dirs = view_dir(means, g, cam)
    norm = wp.length(dirs)
    if num_bases > 1:
        d = dirs / norm
    raw = sh_raw_color(sh, g, num_bases, d)
    vc = v_colors[g]
    v_raw = wp.vec3(wp.where(raw[0] > 0.0, vc[0], 0.0), wp.where(raw[1] > 0.0, vc[1], 0.0),
                    wp.where(raw[2] > 0.0, vc[2], 0.0))
    v_d = wp.vec3(0.0)
    for k in range(K):
        if k < num_bases:
            b = sh_basis(d, k)
            v_sh[g, k, 0] = b * v_raw[0]
            v_sh[g, k, 1] = b * v_raw[1]
            v_sh[g, k, 2] = b * v_raw[2]
            if k > 0:
                v_d += sh_basis_grad(d, k) * wp.dot(sh_coeff(sh, g, k), v_raw)
        else:
            v_sh[g, k, 0] = 0.0
            v_sh[g, k, 1] = 0.0
            v_sh[g, k, 2] = 0.0
    if num_bases > 1:
        v_dir = (v_d - d * wp.dot(d, v_d)) / norm
        v_means[g, 0] = v_means[g, 0] + v_dir[0]
        v_means[g, 1] = v_means[g, 1] + v_dir[1]
        v_means[g, 2] = v_means[g, 2] + v_dir[2]
        # centre c = -R^T t moves by -R^T v under the left perturbation: v_pose[:3] += R (sum_g v_dir)
        v_t = cam.R * v_dir
        p = v_pose_partial[g]
        v_pose_partial[g] = vec6(p[0] + v_t[0], p[1] + v_t[1], p[2] + v_t[2], p[3], p[4], p[5])


# ------------------------------------------------------------------------------------------------- launchers
def _check_sh(sh, means, num_bases, device):
    from ._checks import check_array

    n, k = sh.shape[0], sh.shape[1]
    check_array(sh, "sh", wp.float32, (n, k, 3), device)
    check_array(means, "means", wp.float32, (n, 3), device)
    if not 1 <= num_bases <= k:
        raise ValueError(f"sh: {num_bases} bases asked for, the array has {k}")
    if num_bases not in (1, 4, 9, 16):
        raise ValueError(f"num_bases must be (degree + 1)^2 for degree 0..3, got {num_bases}")
    return n


def launch_evaluate_sh(sh, means, num_bases: int, cam: Camera, radii, depths, rgbz, device: str,
                       threads: int | None = None, min_chunk: int = 4096) -> None:
    """Colours + depth (N,) vec4 of the Gaussians with ``radii > 0`` (others get 0)."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = _check_sh(sh, means, num_bases, device)
    check_array(radii, "radii", wp.int32, (n,), device)
    check_array(depths, "depths", wp.float32, (n,), device)
    check_array(rgbz, "rgbz", wp.vec4, (n,), device)
    launch_split(evaluate_sh, n, [sh, means, int(num_bases), cam, radii, depths, rgbz], device, threads=threads,
                 min_chunk=min_chunk)


def launch_evaluate_sh_backward(sh, means, num_bases: int, cam: Camera, radii, v_colors, v_sh, v_means,
                                v_pose_partial, device: str, threads: int | None = None, min_chunk: int = 4096) -> None:
    """Writes ``v_sh`` (N, K, 3); adds the view-direction terms to ``v_means`` and ``v_pose_partial``."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = _check_sh(sh, means, num_bases, device)
    check_array(radii, "radii", wp.int32, (n,), device)
    check_array(v_colors, "v_colors", wp.vec3, (n,), device)
    check_array(v_sh, "v_sh", wp.float32, tuple(sh.shape), device)
    check_array(v_means, "v_means", wp.float32, (n, 3), device)
    check_array(v_pose_partial, "v_pose_partial", vec6, (n,), device)
    launch_split(evaluate_sh_backward, n, [sh, means, int(num_bases), cam, radii, v_colors, v_sh, v_means,
                                           v_pose_partial], device, threads=threads, min_chunk=min_chunk)
