"""NumPy twin of the 3DGS rasteriser (:mod:`mgso_kernels.splat`): brute force, float64, slow and obvious.

Every Gaussian is tested against every pixel (no tiles, no sort keys); the rules are those of the Warp kernels:

- projection: world-to-camera, covariance ``M S S^T M^T`` from the normalised ``w, x, y, z`` quaternion and
  ``exp(log_scales)``, EWA splatting with the perspective Jacobian evaluated at a tangent clamped to 1.3x the half
  field of view (see :func:`tangent_limits`), a low-pass dilation ``eps2d`` (0.3 px^2) on the 2D covariance
  diagonal, conic = inverse 2D covariance, depth = camera z; culled when ``z <= near`` or ``z >= far``;
- colour: ``max(0, 0.5 + sum_k SH_k(dir) * sh[:, k])`` with ``dir`` the unit vector from the camera centre to the
  mean;
- blending, front to back in float32-depth order (stable, ties by index): ``power = -0.5 d^T conic d`` (skip if
  ``> 0``), ``alpha = min(0.99, opacity * exp(power))``, skip if ``alpha < 1/255``, stop (without accumulating)
  as soon as ``T * (1 - alpha) < 1e-4``; ``rgb = sum w_i c_i + T_final * background``,
  ``depth = sum w_i z_i`` (not normalised), ``alpha = 1 - T_final``.

``t_stop`` (:func:`render`; the coverage kernels' ``Rasterizer.render_alpha(t_stop=...)``): a pixel also stops
once the Gaussian it has just accumulated took its transmittance below ``t_stop``; 0 (the default) changes nothing.

``cutoffs=False`` turns off everything that makes the image jump (the 1/255 skip, the 0.99 clamp, the early stop),
so that central finite differences of the twin are meaningful; the analytic gradients (:func:`render_vjp`) follow
the same switch.

Pixel convention: pixel (row v, col u) samples the image plane at (u, v), i.e. pixel (0, 0) has its centre at
(0, 0). Pose gradients are for a left perturbation ``world_to_cam <- exp(delta) @ world_to_cam`` with
``delta = (v, w)``, translation first.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "SH_C0", "SH_C1", "SH_C2", "SH_C3", "RefCamera", "tangent_limits", "quat_to_rotmat", "quat_to_rotmat_vjp",
    "sh_basis", "sh_basis_grad", "sh_to_rgb", "sh_to_rgb_vjp", "project", "project_vjp", "tile_pairs", "sorted_pairs",
    "render", "render_vjp", "ALPHA_MIN", "ALPHA_MAX", "T_MIN", "num_sh_bases", "random_scene",
]

# Real spherical-harmonic constants (the ones 3DGS and gsplat use; sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!) factors).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)

ALPHA_MIN = 1.0 / 255.0  # skip a Gaussian at a pixel below this alpha
ALPHA_MAX = 0.99  # clamp alpha (keeps 1 - alpha invertible for the backward pass)
T_MIN = 1e-4  # stop a pixel once its transmittance would fall below this


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


@dataclass(frozen=True)
class RefCamera:
    """Pinhole camera: intrinsics in pixels, ``world_to_cam`` 4x4 (x right, y down, z forward)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    world_to_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    near: float = 0.01
    far: float = 1e10

    @property
    def R(self) -> np.ndarray:
        return np.asarray(self.world_to_cam, np.float64)[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return np.asarray(self.world_to_cam, np.float64)[:3, 3]

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t


def tangent_limits(cam) -> tuple[float, float, float, float]:
    """(lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos): the x/z, y/z range the EWA Jacobian is evaluated in.

    The image edges' tangents widened by 0.3 half-fields of view: ``lim_x_pos = (W - cx)/fx + 0.3 * 0.5 W/fx``,
    which is 3DGS's ``1.3 * tan(fovx / 2)`` when the principal point is centred (gsplat's form for an off-centre one).
    """
    thx = 0.5 * cam.width / cam.fx
    thy = 0.5 * cam.height / cam.fy
    return (cam.cx / cam.fx + 0.3 * thx, (cam.width - cam.cx) / cam.fx + 0.3 * thx,
            cam.cy / cam.fy + 0.3 * thy, (cam.height - cam.cy) / cam.fy + 0.3 * thy)


# ----------------------------------------------------------------------------------------------------- rotation
def quat_to_rotmat(qn: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions w, x, y, z -> (N, 3, 3) rotation matrices."""
    w, x, y, z = qn[:, 0], qn[:, 1], qn[:, 2], qn[:, 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def quat_to_rotmat_vjp(qn: np.ndarray, v_m: np.ndarray) -> np.ndarray:
    """Gradient w.r.t. the (unit) quaternion entries of ``sum(v_m * quat_to_rotmat(qn))``."""
    w, x, y, z = qn[:, 0], qn[:, 1], qn[:, 2], qn[:, 3]
    g = v_m
    v_w = 2 * (-z * g[:, 0, 1] + y * g[:, 0, 2] + z * g[:, 1, 0] - x * g[:, 1, 2] - y * g[:, 2, 0] + x * g[:, 2, 1])
    v_x = 2 * (y * g[:, 0, 1] + z * g[:, 0, 2] + y * g[:, 1, 0] - 2 * x * g[:, 1, 1] - w * g[:, 1, 2]
               + z * g[:, 2, 0] + w * g[:, 2, 1] - 2 * x * g[:, 2, 2])
    v_y = 2 * (-2 * y * g[:, 0, 0] + x * g[:, 0, 1] + w * g[:, 0, 2] + x * g[:, 1, 0] + z * g[:, 1, 2]
               - w * g[:, 2, 0] + z * g[:, 2, 1] - 2 * y * g[:, 2, 2])
    v_z = 2 * (-2 * z * g[:, 0, 0] - w * g[:, 0, 1] + x * g[:, 0, 2] + w * g[:, 1, 0] - 2 * z * g[:, 1, 1]
               + y * g[:, 1, 2] + x * g[:, 2, 0] + y * g[:, 2, 1])
    return np.stack([v_w, v_x, v_y, v_z], -1)


# ---------------------------------------------------------------------------------------------------------- SH
def sh_basis(d: np.ndarray, degree: int) -> np.ndarray:
    """Real SH basis at unit directions ``d`` (N, 3): (N, (degree+1)^2), 3DGS's sign convention."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = [np.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, -1)


def sh_basis_grad(d: np.ndarray, degree: int) -> np.ndarray:
    """d sh_basis / d (x, y, z), treating the components as independent: (N, K, 3)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    o = np.zeros_like(x)
    out = [np.stack([o, o, o], -1)]
    if degree >= 1:
        out += [np.stack([o, -SH_C1 + o, o], -1), np.stack([o, o, SH_C1 + o], -1), np.stack([-SH_C1 + o, o, o], -1)]
    if degree >= 2:
        c = SH_C2
        out += [c[0] * np.stack([y, x, o], -1), c[1] * np.stack([o, z, y], -1),
                c[2] * np.stack([-2 * x, -2 * y, 4 * z], -1), c[3] * np.stack([z, o, x], -1),
                c[4] * np.stack([2 * x, -2 * y, o], -1)]
    if degree >= 3:
        c = SH_C3
        xx, yy, zz = x * x, y * y, z * z
        out += [c[0] * np.stack([6 * x * y, 3 * xx - 3 * yy, o], -1),
                c[1] * np.stack([y * z, x * z, x * y], -1),
                c[2] * np.stack([-2 * x * y, 4 * zz - xx - 3 * yy, 8 * y * z], -1),
                c[3] * np.stack([-6 * x * z, -6 * y * z, 6 * zz - 3 * xx - 3 * yy], -1),
                c[4] * np.stack([4 * zz - 3 * xx - yy, -2 * x * y, 8 * x * z], -1),
                c[5] * np.stack([2 * x * z, -2 * y * z, xx - yy], -1),
                c[6] * np.stack([3 * xx - 3 * yy, -6 * x * y, o], -1)]
    return np.stack(out, 1)


def sh_to_rgb(sh: np.ndarray, means: np.ndarray, cam_centre: np.ndarray, degree: int) -> np.ndarray:
    """(N, K, 3) coefficients -> (N, 3) colour ``max(0, 0.5 + sum_k B_k(dir) sh_k)``, dir = unit(mean - centre).

    Only the first ``(degree + 1)^2`` coefficients are used.
    """
    dirs = means - cam_centre[None]
    d = dirs / np.maximum(np.linalg.norm(dirs, axis=-1, keepdims=True), 1e-12)
    k = num_sh_bases(degree)
    raw = 0.5 + np.einsum("nk,nkc->nc", sh_basis(d, degree), sh[:, :k])
    return np.maximum(raw, 0.0)


def sh_to_rgb_vjp(sh, means, cam_centre, degree, v_rgb):
    """Gradients of ``sum(v_rgb * sh_to_rgb(...))``: (v_sh (N, K, 3), v_means (N, 3), v_cam_centre (3,))."""
    dirs = means - cam_centre[None]
    norm = np.maximum(np.linalg.norm(dirs, axis=-1, keepdims=True), 1e-12)
    d = dirs / norm
    k = num_sh_bases(degree)
    basis = sh_basis(d, degree)
    raw = 0.5 + np.einsum("nk,nkc->nc", basis, sh[:, :k])
    v_raw = np.where(raw > 0.0, v_rgb, 0.0)
    v_sh = np.zeros_like(sh, dtype=np.float64)
    v_sh[:, :k] = basis[:, :, None] * v_raw[:, None, :]
    # d colour / d unit direction, then through the normalisation
    v_d = np.einsum("nkj,nkc,nc->nj", sh_basis_grad(d, degree), sh[:, :k], v_raw)
    v_dirs = (v_d - d * np.sum(d * v_d, -1, keepdims=True)) / norm
    return v_sh, v_dirs, -v_dirs.sum(0)


# -------------------------------------------------------------------------------------------------- projection
def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def project(means, log_scales, quats, opacity_logits, cam, eps2d: float = 0.3, antialiased: bool = False) -> dict:
    """Project N Gaussians. Returns a dict of (N, ...) float64 arrays: means2d (pixels), conics (a, b, c) with
    ``power = -0.5 (a dx^2 + c dy^2) - b dx dy``, cov2d (2, 2, dilated), depths (camera z), opacities (the
    effective ones: ``sigmoid(logit)``, times ``sqrt(det(cov2d - eps2d I) / det(cov2d))`` when ``antialiased``,
    Mip-Splatting's compensation), valid (near < z < far), and the intermediates :func:`project_vjp` needs."""
    means = np.asarray(means, np.float64)
    R, t = cam.R, cam.t
    pc = means @ R.T + t
    q = np.asarray(quats, np.float64)
    qnorm = np.linalg.norm(q, axis=-1, keepdims=True)
    qn = q / qnorm
    M = quat_to_rotmat(qn)
    s = np.exp(np.asarray(log_scales, np.float64))
    L = M * s[:, None, :]
    cov3 = L @ np.swapaxes(L, 1, 2)
    covc = R[None] @ cov3 @ R.T[None]
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    lxn, lxp, lyn, lyp = tangent_limits(cam)
    with np.errstate(divide="ignore", invalid="ignore"):
        rx, ry = x / z, y / z
    clx, cly = np.clip(rx, -lxn, lxp), np.clip(ry, -lyn, lyp)
    J = np.zeros((len(means), 2, 3))
    J[:, 0, 0] = cam.fx / z
    J[:, 0, 2] = -cam.fx * clx / z
    J[:, 1, 1] = cam.fy / z
    J[:, 1, 2] = -cam.fy * cly / z
    cov2 = J @ covc @ np.swapaxes(J, 1, 2) + eps2d * np.eye(2)[None]
    det = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] ** 2
    conics = np.stack([cov2[:, 1, 1] / det, -cov2[:, 0, 1] / det, cov2[:, 0, 0] / det], -1)
    means2d = np.stack([cam.fx * rx + cam.cx, cam.fy * ry + cam.cy], -1)
    valid = (z > cam.near) & (z < cam.far)
    sig = _sigmoid(np.asarray(opacity_logits, np.float64))
    det_raw = (cov2[:, 0, 0] - eps2d) * (cov2[:, 1, 1] - eps2d) - cov2[:, 0, 1] ** 2
    comp = np.sqrt(np.maximum(det_raw, 0.0) / det) if antialiased else np.ones_like(det)
    return dict(means2d=means2d, conics=conics, cov2d=cov2, depths=z, opacities=sig * comp, valid=valid,
                pc=pc, qn=qn, qnorm=qnorm, M=M, s=s, L=L, cov3=cov3, covc=covc, J=J, clx=clx, cly=cly,
                clipped_x=(rx < -lxn) | (rx > lxp), clipped_y=(ry < -lyn) | (ry > lyp), sig=sig, comp=comp,
                det=det, det_raw=det_raw, eps2d=eps2d, antialiased=antialiased)


def project_vjp(proj: dict, cam, v_means2d, v_conics, v_depths, v_opacities):
    """Gradients through :func:`project` (float64): (v_means (N, 3), v_log_scales (N, 3), v_quats (N, 4),
    v_opacity_logits (N,), v_pose (6,)); ``v_opacities`` is w.r.t. the effective opacities. The pose gradient is
    for ``world_to_cam <- exp(delta) @ world_to_cam``, delta = (v, w)."""
    R = cam.R
    pc, J, covc, conics = proj["pc"], proj["J"], proj["covc"], proj["conics"]
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    fx, fy = cam.fx, cam.fy
    # conic -> 2D covariance: d conic = -Q dSigma Q
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    Q = np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)
    V = np.stack([np.stack([v_conics[:, 0], 0.5 * v_conics[:, 1]], -1),
                  np.stack([0.5 * v_conics[:, 1], v_conics[:, 2]], -1)], -2)
    G = -Q @ V @ Q  # v_cov2d
    sig, comp = proj["sig"], proj["comp"]
    v_logits = v_opacities * comp * sig * (1.0 - sig)
    if proj["antialiased"]:
        # comp = sqrt(q), q = det_raw / det; d q / d (A, B, D) of cov2d = [[A, B], [B, D]] (B counted once)
        cov2, det, det_raw, eps = proj["cov2d"], proj["det"], proj["det_raw"], proj["eps2d"]
        A, B, D = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            v_q = np.where(comp > 0, v_opacities * sig / (2.0 * comp), 0.0)
        dA = ((D - eps) * det - det_raw * D) / det ** 2
        dD = ((A - eps) * det - det_raw * A) / det ** 2
        dB = -2.0 * B * (det - det_raw) / det ** 2
        G = G + v_q[:, None, None] * np.stack([np.stack([dA, 0.5 * dB], -1), np.stack([0.5 * dB, dD], -1)], -2)
    Jt = np.swapaxes(J, 1, 2)
    v_covc = Jt @ G @ J
    v_J = 2.0 * G @ J @ covc
    v_pc = np.zeros_like(pc)
    # J entries: J00 = fx/z, J02 = -fx clx / z, J11 = fy/z, J12 = -fy cly / z
    v_pc[:, 2] += v_J[:, 0, 0] * (-fx / z ** 2) + v_J[:, 1, 1] * (-fy / z ** 2)
    v_pc[:, 2] += v_J[:, 0, 2] * (fx * proj["clx"] / z ** 2) + v_J[:, 1, 2] * (fy * proj["cly"] / z ** 2)
    v_clx = v_J[:, 0, 2] * (-fx / z)
    v_cly = v_J[:, 1, 2] * (-fy / z)
    nx = ~proj["clipped_x"]
    ny = ~proj["clipped_y"]
    v_pc[:, 0] += np.where(nx, v_clx / z, 0.0)
    v_pc[:, 2] += np.where(nx, -v_clx * x / z ** 2, 0.0)
    v_pc[:, 1] += np.where(ny, v_cly / z, 0.0)
    v_pc[:, 2] += np.where(ny, -v_cly * y / z ** 2, 0.0)
    # means2d
    v_pc[:, 0] += fx / z * v_means2d[:, 0]
    v_pc[:, 1] += fy / z * v_means2d[:, 1]
    v_pc[:, 2] += -fx * x / z ** 2 * v_means2d[:, 0] - fy * y / z ** 2 * v_means2d[:, 1]
    v_pc[:, 2] += v_depths
    # camera covariance -> world covariance and the pose rotation
    v_cov3 = R.T[None] @ v_covc @ R[None]
    A = v_covc @ covc - covc @ v_covc
    v_rot = np.stack([A[:, 2, 1] - A[:, 1, 2], A[:, 0, 2] - A[:, 2, 0], A[:, 1, 0] - A[:, 0, 1]], -1)
    v_rot += np.cross(pc, v_pc)
    v_pose = np.concatenate([v_pc.sum(0), v_rot.sum(0)])
    v_means = v_pc @ R
    # cov3 = L L^T, L = M diag(s)
    L, M, s = proj["L"], proj["M"], proj["s"]
    v_L = 2.0 * v_cov3 @ L
    v_M = v_L * s[:, None, :]
    v_s = np.sum(M * v_L, axis=1)
    v_log_scales = v_s * s
    qn, qnorm = proj["qn"], proj["qnorm"]
    v_qn = quat_to_rotmat_vjp(qn, v_M)
    v_quats = (v_qn - qn * np.sum(qn * v_qn, -1, keepdims=True)) / qnorm
    return v_means, v_log_scales, v_quats, v_logits, v_pose


# ----------------------------------------------------------------------------------------------------- binning
def _ellipse_rect_min(m, conic, x0, x1, y0, y1):
    """min over the rectangle [x0, x1] x [y0, y1] of (p - m)^T Q (p - m) (exact, convex)."""
    a, b, c = conic
    if x0 <= m[0] <= x1 and y0 <= m[1] <= y1:
        return 0.0
    best = np.inf
    for xe in (x0, x1):  # vertical edges: minimise over y
        dx = xe - m[0]
        dy = np.clip(-b * dx / c, y0 - m[1], y1 - m[1])
        best = min(best, a * dx * dx + 2 * b * dx * dy + c * dy * dy)
    for ye in (y0, y1):  # horizontal edges: minimise over x
        dy = ye - m[1]
        dx = np.clip(-b * dy / a, x0 - m[0], x1 - m[0])
        best = min(best, a * dx * dx + 2 * b * dx * dy + c * dy * dy)
    return best


def tile_pairs(proj: dict, cam, tile_size: int = 16, scale_r2: float = 1.0) -> set[tuple[int, int]]:
    """All (tile index, Gaussian index) pairs whose cut-off ellipse reaches the tile (brute force).

    The cut-off ellipse is where ``opacity * exp(power) = 1/255``: ``d^T conic d <= 2 log(255 opacity)``
    (times ``scale_r2``). A tile's rectangle is spanned by its pixel centres (pixels are sampled at integer
    coordinates). Tiles are numbered row-major, ``ty * tiles_x + tx``.
    """
    tiles_x = -(-cam.width // tile_size)
    tiles_y = -(-cam.height // tile_size)
    out = set()
    for g in np.nonzero(proj["valid"])[0]:
        op = proj["opacities"][g]
        if op * 255.0 < 1.0:
            continue
        r2 = 2.0 * np.log(255.0 * op) * scale_r2
        for ty in range(tiles_y):
            for tx in range(tiles_x):
                x0, y0 = tx * tile_size, ty * tile_size
                x1 = min(x0 + tile_size, cam.width) - 1
                y1 = min(y0 + tile_size, cam.height) - 1
                if _ellipse_rect_min(proj["means2d"][g], proj["conics"][g], x0, x1, y0, y1) <= r2:
                    out.add((ty * tiles_x + tx, int(g)))
    return out


# --------------------------------------------------------------------------------------------------- rendering
def sorted_pairs(keys: np.ndarray, n_tiles: int) -> tuple[np.ndarray, np.ndarray]:
    """The pairs' order by (tile, depth) and each tile's [start, end) in it ([0, 0) without pairs): ``keys`` (M,)
    int64, tile in the high 32 bits, the depth's float32 bits in the low 32 (``bin.emit_pairs``). Returns ``order``
    (M,), the pairs' positions before sorting (the slots), ties kept in slot order, and ``ranges`` (n_tiles, 2)."""
    order = np.argsort(np.asarray(keys, np.int64), kind="stable")
    tiles = np.asarray(keys, np.int64)[order] >> 32
    ranges = np.zeros((n_tiles, 2), np.int32)
    for t in np.unique(tiles):
        idx = np.flatnonzero(tiles == t)
        ranges[t] = (idx[0], idx[-1] + 1)
    return order.astype(np.int32), ranges


def _blend(proj, colors, cam, background, cutoffs, t_stop: float = 0.0):
    """Vectorised over pixels, sequential over depth-sorted Gaussians. Returns per-pixel outputs and the
    (P, N) per-Gaussian alpha / transmittance matrices (in sorted order) the backward pass reuses."""
    H, W = cam.height, cam.width
    vv, uu = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    u, v = uu.ravel(), vv.ravel()
    P = u.size
    idx = np.nonzero(proj["valid"])[0]
    order = idx[np.argsort(proj["depths"][idx].astype(np.float32), kind="stable")]
    n = len(order)
    T = np.ones(P)
    done = np.zeros(P, bool)
    C = np.zeros((P, 3))
    D = np.zeros(P)
    alphas = np.zeros((P, n))  # effective alpha (0 where skipped)
    raw = np.zeros((P, n))  # opacity * exp(power)
    Tb = np.zeros((P, n))  # transmittance before the Gaussian
    unclamped = np.zeros((P, n), bool)
    for k, g in enumerate(order):
        a, b, c = proj["conics"][g]
        dx = u - proj["means2d"][g, 0]
        dy = v - proj["means2d"][g, 1]
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        r = proj["opacities"][g] * np.exp(power)
        if cutoffs:
            alpha = np.minimum(ALPHA_MAX, r)
            use = (power <= 0.0) & (alpha >= ALPHA_MIN) & ~done
            Tn = T * (1.0 - alpha)
            stop = use & (Tn < T_MIN)
            done |= stop
            use &= ~stop
            unclamped[:, k] = r <= ALPHA_MAX
        else:
            alpha = r
            use = np.ones(P, bool)
            Tn = T * (1.0 - alpha)
            unclamped[:, k] = True
        w = np.where(use, alpha * T, 0.0)
        C += w[:, None] * colors[g][None]
        D += w * proj["depths"][g]
        alphas[:, k] = np.where(use, alpha, 0.0)
        raw[:, k] = r
        Tb[:, k] = T
        T = np.where(use, Tn, T)
        if cutoffs:
            done |= use & (Tn < t_stop)  # the coverage stop: accumulated, and now below t_stop
    rgb = C + T[:, None] * np.asarray(background, np.float64)[None]
    return dict(rgb=rgb.reshape(H, W, 3), depth=D.reshape(H, W), alpha=(1.0 - T).reshape(H, W),
                T_final=T.reshape(H, W), order=order, alphas=alphas, raw=raw, Tb=Tb, unclamped=unclamped,
                u=u, v=v)


def render(means, log_scales, quats, opacity_logits, sh, cam, background=(0.0, 0.0, 0.0), sh_degree=None,
           eps2d: float = 0.3, cutoffs: bool = True, antialiased: bool = False, t_stop: float = 0.0) -> dict:
    """Render (H, W) with every Gaussian against every pixel. Returns rgb (H, W, 3), depth (H, W) (unnormalised
    ``sum w_i z_i``), alpha (H, W), T_final (H, W), plus the projection (``proj``) and colours (``colors``).
    ``t_stop``: the coverage stop (module docstring)."""
    sh = np.asarray(sh, np.float64)
    if sh_degree is None:
        sh_degree = int(round(np.sqrt(sh.shape[1]))) - 1
    proj = project(means, log_scales, quats, opacity_logits, cam, eps2d, antialiased)
    colors = sh_to_rgb(sh, np.asarray(means, np.float64), cam.centre, sh_degree)
    out = _blend(proj, colors, cam, background, cutoffs, t_stop)
    out.update(proj=proj, colors=colors)
    return out


def render_vjp(means, log_scales, quats, opacity_logits, sh, cam, background, v_rgb, v_depth=None, v_alpha=None,
               sh_degree=None, eps2d: float = 0.3, cutoffs: bool = True, antialiased: bool = False) -> dict:
    """Analytic gradients of ``sum(v_rgb * rgb) + sum(v_depth * depth) + sum(v_alpha * alpha)``.

    Returns v_means, v_log_scales, v_quats, v_opacity_logits, v_sh, v_pose (6,), and the per-Gaussian screen-space
    quantities v_means2d (N, 2), absgrad (N, 2) (sum over pixels of |per-pixel v_means2d|, AbsGS), v_conics,
    v_opacities, v_colors, v_depths, and weights (N,): not a gradient, the sum over pixels of each Gaussian's blending
    weight alpha T where it is used.
    """
    sh = np.asarray(sh, np.float64)
    if sh_degree is None:
        sh_degree = int(round(np.sqrt(sh.shape[1]))) - 1
    fw = render(means, log_scales, quats, opacity_logits, sh, cam, background, sh_degree, eps2d, cutoffs,
                antialiased)
    proj, colors = fw["proj"], fw["colors"]
    N = len(proj["depths"])
    H, W = cam.height, cam.width
    P = H * W
    G = np.asarray(v_rgb, np.float64).reshape(P, 3)
    vD = np.zeros(P) if v_depth is None else np.asarray(v_depth, np.float64).reshape(P)
    vA = np.zeros(P) if v_alpha is None else np.asarray(v_alpha, np.float64).reshape(P)
    order, al, Tb, raw = fw["order"], fw["alphas"], fw["Tb"], fw["raw"]
    Tf = fw["T_final"].reshape(P)
    bg = np.asarray(background, np.float64)
    col = colors[order]  # (n, 3)
    z = proj["depths"][order]
    w = al * Tb
    per = (G @ col.T) + vD[:, None] * z[None]  # (P, n): c_i . G + z_i vD
    wper = w * per
    after = np.cumsum(wper[:, ::-1], axis=1)[:, ::-1] - wper  # sum over j > i
    used = al > 0.0 if cutoffs else np.ones_like(al, bool)
    # the background and alpha terms: d T_f / d alpha_i = -T_f / (1 - alpha_i)
    bgterm = (G @ bg) * Tf - vA * Tf
    v_al = Tb * per - (after + bgterm[:, None]) / (1.0 - al)
    v_al = np.where(used, v_al, 0.0)
    v_raw = np.where(fw["unclamped"], v_al, 0.0)
    out_v_col = np.zeros((N, 3))
    out_v_z = np.zeros(N)
    out_v_col[order] = w.T @ G
    out_v_z[order] = w.T @ vD
    weights = np.zeros(N)
    weights[order] = np.where(used, w, 0.0).sum(axis=0)
    v_conics = np.zeros((N, 3))
    v_means2d = np.zeros((N, 2))
    absgrad = np.zeros((N, 2))
    v_opac = np.zeros(N)
    u, v = fw["u"], fw["v"]
    for k, g in enumerate(order):
        a, b, c = proj["conics"][g]
        dx = u - proj["means2d"][g, 0]
        dy = v - proj["means2d"][g, 1]
        op = proj["opacities"][g]
        e = raw[:, k] / op if op > 0 else np.zeros(P)
        v_opac[g] = np.sum(v_raw[:, k] * e)
        v_pow = v_raw[:, k] * raw[:, k]
        v_conics[g] = [np.sum(-0.5 * dx * dx * v_pow), np.sum(-dx * dy * v_pow), np.sum(-0.5 * dy * dy * v_pow)]
        gx = (a * dx + b * dy) * v_pow
        gy = (b * dx + c * dy) * v_pow
        v_means2d[g] = [gx.sum(), gy.sum()]
        absgrad[g] = [np.abs(gx).sum(), np.abs(gy).sum()]
    v_means, v_log_scales, v_quats, v_logits, v_pose = project_vjp(proj, cam, v_means2d, v_conics, out_v_z, v_opac)
    v_sh, v_means_sh, v_centre = sh_to_rgb_vjp(sh, np.asarray(means, np.float64), cam.centre, sh_degree, out_v_col)
    v_means = v_means + v_means_sh
    # camera centre C = -R^T t; under world_to_cam <- exp(delta) world_to_cam, dC/dv = -R^T, dC/dw = 0
    v_pose = v_pose + np.concatenate([-cam.R @ v_centre, np.zeros(3)])
    return dict(v_means=v_means, v_log_scales=v_log_scales, v_quats=v_quats, v_opacity_logits=v_logits,
                v_sh=v_sh, v_pose=v_pose, v_means2d=v_means2d, absgrad=absgrad, v_conics=v_conics,
                v_opacities=v_opac, v_colors=out_v_col, v_depths=out_v_z, weights=weights, forward=fw)


# ------------------------------------------------------------------------------------------------ test scenes
def random_scene(rng: np.random.Generator, n: int, cam, degree: int = 0, depth_range=(1.0, 5.0),
                 px_range=(1.0, 6.0), hard_cases: bool = True, sh_scale: float = 0.5) -> dict:
    """A random set of N Gaussians seen by ``cam``, as float64 arrays of the parameter layout.

    Most Gaussians lie in the view frustum at ``depth_range`` with standard deviations of ``px_range`` pixels.
    ``hard_cases`` mixes in (about an eighth each) Gaussians behind the camera or inside the near plane, partly
    off-screen, very thin (one scale 1/300 of the others), large (covering many tiles), centred exactly on tile
    borders, and nearly transparent (opacity below 1/255).
    """
    z = rng.uniform(*depth_range, n)
    u = rng.uniform(0, cam.width - 1, n)
    v = rng.uniform(0, cam.height - 1, n)
    # a pixel at depth z is z / f wide
    px_scale = rng.uniform(*px_range, (n, 3)) * (z / cam.fx)[:, None]
    logit = rng.uniform(-2.0, 4.0, n)
    if hard_cases:
        kind = rng.integers(0, 8, n)
        z = np.where(kind == 1, rng.uniform(-3.0, cam.near, n), z)  # behind / inside near plane
        off = kind == 2  # partly off-screen: centre up to 15 px outside the border
        u = np.where(off, np.where(rng.random(n) < 0.5, -rng.uniform(0, 15, n),
                                   cam.width - 1 + rng.uniform(0, 15, n)), u)
        thin = kind == 3
        px_scale[thin, rng.integers(0, 3, thin.sum())] /= 300.0
        big = kind == 4
        px_scale[big] *= rng.uniform(3.0, 6.0, (big.sum(), 1))
        border = kind == 5  # centred on a tile corner (or edge)
        u = np.where(border, 16.0 * rng.integers(1, max(2, cam.width // 16), n), u)
        v = np.where(border & (rng.random(n) < 0.7), 16.0 * rng.integers(1, max(2, cam.height // 16), n), v)
        logit = np.where(kind == 6, rng.uniform(-9.0, -6.0, n), logit)  # opacity < 1/255
    zz = np.where(np.abs(z) < 1e-3, 1e-3, z)
    pc = np.stack([(u - cam.cx) / cam.fx * zz, (v - cam.cy) / cam.fy * zz, z], -1)
    means = (pc - cam.t) @ cam.R  # R^T (pc - t)
    K = num_sh_bases(degree)
    sh = rng.normal(size=(n, K, 3)) * sh_scale
    sh[:, 0] = rng.uniform(-1.2, 1.2, (n, 3))  # colour 0.5 + C0 sh0 in about [0.16, 0.84]
    return dict(means=means, log_scales=np.log(np.abs(px_scale) + 1e-9), quats=rng.normal(size=(n, 4)),
                opacity_logits=logit, sh=sh)
