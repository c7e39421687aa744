"""Spherical-harmonic colour, forward and backward (Warp module).

``rgb = max(0, 0.5 + sum_k B_k(d) * sh[g, k])`` with ``d`` the unit vector from the camera centre to the Gaussian's
mean and ``B_k`` the real SH basis of 3DGS (degree 0..3, ``K = (degree + 1)^2`` bases; degree 0 is the constant
``C0 = 0.28209479177387814``, view-independent colour as MGSO uses).

Backward: to the coefficients (zero where the colour was clamped at 0), to the mean through the view direction,
and to the camera pose through the camera centre (for degree >= 1; for degree 0 the direction does not matter and
both are zero). ``v_pose`` uses the package's left perturbation, under which the centre moves by ``-R^T v``
(translation part only).

On the CPU degree 0 runs as C++ blocks (:func:`evaluate_sh_blocks`, :func:`evaluate_sh_backward_blocks`: the same
bits as the kernels, tested); other degrees run the kernels' code there too.

Twin: :func:`mgso_kernels.reference.splat.sh_to_rgb` / ``sh_to_rgb_vjp``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .camera import Camera
from .common import vec6

wp.set_module_options({"enable_backward": False})

__all__ = ["evaluate_sh", "evaluate_sh_backward", "evaluate_sh_blocks", "evaluate_sh_backward_blocks", "vec6", "SH_C0",
           "SH_BLOCK"]

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


@wp.func
def sh_forward_one(g: int, sh: wp.array3d(dtype=float), means: wp.array2d(dtype=float), num_bases: int, cam: Camera,
                   radii: wp.array(dtype=wp.int32), depths: wp.array(dtype=float), rgbz: wp.array(dtype=wp.vec4)):
    """:func:`evaluate_sh`'s work for Gaussian ``g``."""
    if radii[g] == 0:
        rgbz[g] = wp.vec4(0.0)
        return
    d = wp.vec3(1.0, 0.0, 0.0)
    if num_bases > 1:
        d = wp.normalize(view_dir(means, g, cam))
    c = sh_raw_color(sh, g, num_bases, d)
    rgbz[g] = wp.vec4(wp.max(c[0], 0.0), wp.max(c[1], 0.0), wp.max(c[2], 0.0), depths[g])


@wp.func
def sh_backward_one(g: int, sh: wp.array3d(dtype=float), means: wp.array2d(dtype=float), num_bases: int, cam: Camera,
                    radii: wp.array(dtype=wp.int32), v_colors: wp.array(dtype=wp.vec3), v_sh: wp.array3d(dtype=float),
                    v_means: wp.array2d(dtype=float), v_pose_partial: wp.array(dtype=vec6)):
    """:func:`evaluate_sh_backward`'s work for Gaussian ``g``."""
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
    sh_forward_one(offset + wp.tid(), sh, means, num_bases, cam, radii, depths, rgbz)


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
    sh_backward_one(offset + wp.tid(), sh, means, num_bases, cam, radii, v_colors, v_sh, v_means, v_pose_partial)


# ------------------------------------------------------------------------------------------- the CPU's blocks
# Degree 0 (num_bases 1, MGSO's default) on the CPU as C++ blocks (native snippets): a Gaussian's colour is
# max(0, 0.5 + C0 sh[g, 0]) and its coefficients' gradient C0 v where that is > 0, a handful of float operations that
# Warp's per-Gaussian code wrapped in indexing and the basis's switch (the two kernels were 4.4 % of a 160x120 training
# step on one Zen 4 thread, as much as the projection; docs/rasteriser.md). The same operations in the same order,
# one per statement and no contraction into FMAs: the same bits (tested against this module's kernels with
# runtime.use_native off). Higher degrees, arrays that are not contiguous and CUDA run the kernels above.
_SH0_FWD_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
{
#pragma clang fp contract(off)
if (num_bases != 1 || sh.strides[2] != 4 || sh.strides[1] != 12 || sh.strides[0] != 12 * sh.shape[1]
    || radii.strides[0] != 4 || depths.strides[0] != 4 || rgbz.strides[0] != 16) return 0;
const long K3 = 3L * sh.shape[1];
const float* __restrict S = (const float*)sh.data;
const int* __restrict R = (const int*)radii.data;
const float* __restrict D = (const float*)depths.data;
float* __restrict O = (float*)rgbz.data;
const float c0 = @C0@;
for (int g = lo; g < hi; ++g) {
    float* o = O + 4L * g;
    const float* c = S + K3 * g;
    // Warp's max(x, 0): x >= 0 ? x : 0 (a NaN gives 0)
    const float r = 0.5f + c0 * c[0], gr = 0.5f + c0 * c[1], b = 0.5f + c0 * c[2];
    const bool vis = R[g] != 0;
    o[0] = vis ? (r >= 0.0f ? r : 0.0f) : 0.0f;
    o[1] = vis ? (gr >= 0.0f ? gr : 0.0f) : 0.0f;
    o[2] = vis ? (b >= 0.0f ? b : 0.0f) : 0.0f;
    o[3] = vis ? D[g] : 0.0f;
}
return 1;
}
#else
return 0;
#endif
"""

_SH0_BWD_CPP = r"""
#if defined(__clang__) && !defined(__CUDA_ARCH__)
{
#pragma clang fp contract(off)
if (num_bases != 1 || sh.strides[2] != 4 || sh.strides[1] != 12 || sh.strides[0] != 12 * sh.shape[1]
    || v_sh.strides[2] != 4 || v_sh.strides[1] != 12 || v_sh.strides[0] != 12 * v_sh.shape[1]
    || v_sh.shape[1] != sh.shape[1] || radii.strides[0] != 4 || v_colors.strides[0] != 12) return 0;
const long K3 = 3L * sh.shape[1];
// restrict: the outputs never alias the inputs (Warp's arrays of one call); without it each store was ordered before
// the next Gaussian's loads and the loop stayed scalar
const float* __restrict S = (const float*)sh.data;
const int* __restrict R = (const int*)radii.data;
const float* __restrict V = (const float*)v_colors.data;
float* __restrict O = (float*)v_sh.data;
const float c0 = @C0@;
// c0 (vr where raw > 0, else 0) is c0 v there and +0 elsewhere (c0 > 0), as is a culled Gaussian's: one select of
// values computed in every lane, so that the loop has no branch and vectorises (a select of a load the compiler may
// not hoist became two branches a channel, mispredicted on a real map's visibility)
auto one = [&](int g) __attribute__((always_inline)) {
    float* o = O + K3 * g;
    const float* c = S + K3 * g;
    const float* v = V + 3L * g;
    const bool vis = R[g] != 0;
    for (int i = 0; i < 3; ++i) {
        const float raw = 0.5f + c0 * c[i];
        const float cv = c0 * v[i];     // loaded and multiplied always, then selected: no branch
        o[i] = (vis & (raw > 0.0f)) ? cv : 0.0f;
    }
};
if (K3 == 3) {
    for (int g = lo; g < hi; ++g) one(g);
} else {
    for (int g = lo; g < hi; ++g) {
        one(g);
        float* o = O + K3 * g;
        for (long k = 3; k < K3; ++k) o[k] = 0.0f;
    }
}
return 1;
}
#else
return 0;
#endif
"""
_SH0_FWD_CPP = _SH0_FWD_CPP.replace("@C0@", repr(float(np.float32(SH_C0))) + "f")
_SH0_BWD_CPP = _SH0_BWD_CPP.replace("@C0@", repr(float(np.float32(SH_C0))) + "f")


@wp.func_native(_SH0_FWD_CPP)
def sh0_forward_cpp(lo: int, hi: int, sh: wp.array3d(dtype=float), num_bases: int, radii: wp.array(dtype=wp.int32),
                    depths: wp.array(dtype=float), rgbz: wp.array(dtype=wp.vec4)) -> int:
    """:func:`evaluate_sh` of the Gaussians ``[lo, hi)`` at degree 0 in C++ (above). Returns 1, or 0 where it does
    not apply (nothing written)."""
    ...


@wp.func_native(_SH0_BWD_CPP)
def sh0_backward_cpp(lo: int, hi: int, sh: wp.array3d(dtype=float), num_bases: int,
                     radii: wp.array(dtype=wp.int32), v_colors: wp.array(dtype=wp.vec3),
                     v_sh: wp.array3d(dtype=float)) -> int:
    """:func:`evaluate_sh_backward` of the Gaussians ``[lo, hi)`` at degree 0 in C++ (above; degree 0 adds nothing
    to ``v_means`` or ``v_pose_partial``). Returns 1, or 0 where it does not apply (nothing written)."""
    ...


@wp.kernel
def evaluate_sh_blocks(offset: int, block: int, n: int, sh: wp.array3d(dtype=float), means: wp.array2d(dtype=float),
                       num_bases: int, cam: Camera, radii: wp.array(dtype=wp.int32), depths: wp.array(dtype=float),
                       rgbz: wp.array(dtype=wp.vec4), native: int, status: wp.array(dtype=wp.int32)):
    """:func:`evaluate_sh` with ``block`` Gaussians a thread, for the CPU: the C++ block at degree 0, this loop
    where it declines; ``status`` 1 where the C++ block ran."""
    c = offset + wp.tid()
    lo = c * block
    hi = wp.min(lo + block, n)
    done = int(0)
    if native != 0:
        done = sh0_forward_cpp(lo, hi, sh, num_bases, radii, depths, rgbz)
    status[c] = done
    if done == 0:
        for g in range(lo, hi):
            sh_forward_one(g, sh, means, num_bases, cam, radii, depths, rgbz)


@wp.kernel
def evaluate_sh_backward_blocks(offset: int, block: int, n: int, sh: wp.array3d(dtype=float),
                                means: wp.array2d(dtype=float), num_bases: int, cam: Camera,
                                radii: wp.array(dtype=wp.int32), v_colors: wp.array(dtype=wp.vec3),
                                v_sh: wp.array3d(dtype=float), v_means: wp.array2d(dtype=float),
                                v_pose_partial: wp.array(dtype=vec6), native: int,
                                status: wp.array(dtype=wp.int32)):
    """:func:`evaluate_sh_backward` with ``block`` Gaussians a thread, for the CPU: the C++ block at degree 0, this
    loop where it declines; ``status`` 1 where the C++ block ran."""
    c = offset + wp.tid()
    lo = c * block
    hi = wp.min(lo + block, n)
    done = int(0)
    if native != 0:
        done = sh0_backward_cpp(lo, hi, sh, num_bases, radii, v_colors, v_sh)
    status[c] = done
    if done == 0:
        for g in range(lo, hi):
            sh_backward_one(g, sh, means, num_bases, cam, radii, v_colors, v_sh, v_means, v_pose_partial)


#: Gaussians a thread of the CPU's SH blocks (:func:`evaluate_sh_blocks`).
SH_BLOCK = 1024


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
                       threads: int | None = None, min_chunk: int = 4096):
    """Colours + depth (N,) vec4 of the Gaussians with ``radii > 0`` (others get 0). On the CPU returns the call's
    per-block status (an int32 Warp array, 1 where the C++ block ran), else None."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = _check_sh(sh, means, num_bases, device)
    check_array(radii, "radii", wp.int32, (n,), device)
    check_array(depths, "depths", wp.float32, (n,), device)
    check_array(rgbz, "rgbz", wp.vec4, (n,), device)
    if str(device).startswith("cpu"):
        from ..runtime import launch_blocks, native_flag

        # blocks of SH_BLOCK Gaussians, a thread each: the C++ block at degree 0 (above)
        return launch_blocks(evaluate_sh_blocks, n, SH_BLOCK, [sh, means, int(num_bases), cam, radii, depths, rgbz],
                             native_flag(), device, threads=threads, min_chunk=min_chunk)
    launch_split(evaluate_sh, n, [sh, means, int(num_bases), cam, radii, depths, rgbz], device, threads=threads,
                 min_chunk=min_chunk)
    return None


def launch_evaluate_sh_backward(sh, means, num_bases: int, cam: Camera, radii, v_colors, v_sh, v_means,
                                v_pose_partial, device: str, threads: int | None = None, min_chunk: int = 4096):
    """Writes ``v_sh`` (N, K, 3); adds the view-direction terms to ``v_means`` and ``v_pose_partial``. On the CPU
    returns the call's per-block status (1 where the C++ block ran), else None."""
    from ..runtime import launch_split
    from ._checks import check_array

    n = _check_sh(sh, means, num_bases, device)
    check_array(radii, "radii", wp.int32, (n,), device)
    check_array(v_colors, "v_colors", wp.vec3, (n,), device)
    check_array(v_sh, "v_sh", wp.float32, tuple(sh.shape), device)
    check_array(v_means, "v_means", wp.float32, (n, 3), device)
    check_array(v_pose_partial, "v_pose_partial", vec6, (n,), device)
    if str(device).startswith("cpu"):
        from ..runtime import launch_blocks, native_flag

        return launch_blocks(evaluate_sh_backward_blocks, n, SH_BLOCK, [sh, means, int(num_bases), cam, radii,
                                                                        v_colors, v_sh, v_means, v_pose_partial],
                             native_flag(), device, threads=threads, min_chunk=min_chunk)
    launch_split(evaluate_sh_backward, n, [sh, means, int(num_bases), cam, radii, v_colors, v_sh, v_means,
                                           v_pose_partial], device, threads=threads, min_chunk=min_chunk)
    return None
