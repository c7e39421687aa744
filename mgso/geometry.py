"""Rigid (SE3) and similarity (Sim3) transforms in NumPy float64.

Conventions, used everywhere in mgso:

- A pose is a 4x4 homogeneous matrix named by direction: ``cam_to_world`` maps camera coordinates to world
  coordinates (``X_w = R X_c + t``), ``world_to_cam`` is its inverse. Camera frame: x right, y down, z forward.
- Tangent vectors put translation first, rotation second, as Sophus (and therefore DSO) do:
  ``se3``: ``xi = (v_x, v_y, v_z, w_x, w_y, w_z)``; ``sim3``: ``(v, w, sigma)`` with scale ``s = exp(sigma)``.
- ``exp`` of a tangent vector is applied on the left when updating (``T <- exp(delta) @ T``) unless a function says
  otherwise.
- A Sim3 is stored as a 4x4 matrix ``[[s R, t], [0, 1]]``.
- Quaternions: every function names its order. ``xyzw`` is the TUM trajectory order (w last); ``wxyz`` is the order of
  the 3DGS PLY ``rot_0..3`` and of Warp's ``wp.quat``-free kernels here. Returned quaternions have ``w >= 0``.

Most functions accept a leading batch dimension (``(..., 3)``, ``(..., 4, 4)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np

__all__ = [
    "hat", "vee", "so3_exp", "so3_log", "so3_left_jacobian", "orthonormalize",
    "se3_exp", "se3_log", "se3_inverse", "se3_adjoint", "se3_interpolate", "make_pose", "transform_points",
    "sim3_exp", "sim3_log", "sim3_inverse", "sim3_from_parts", "sim3_to_parts", "check_sim3",
    "SIM3_ROTATION_TOLERANCE",
    "quat_xyzw_to_matrix", "matrix_to_quat_xyzw", "quat_wxyz_to_matrix", "matrix_to_quat_wxyz",
    "quat_xyzw_to_wxyz", "quat_wxyz_to_xyzw", "quat_normalize",
    "Alignment", "umeyama_alignment", "rotation_angle",
]

_EPS = 1e-10


def _as64(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


# --------------------------------------------------------------------------------------------------------- SO3
def hat(w) -> np.ndarray:
    """Skew-symmetric matrix of ``w`` (..., 3) -> (..., 3, 3): ``hat(a) @ b == cross(a, b)``."""
    w = _as64(w)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def vee(m) -> np.ndarray:
    """Inverse of :func:`hat` (..., 3, 3) -> (..., 3), using the antisymmetric part."""
    m = _as64(m)
    return 0.5 * np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
                          axis=-1)


def _sinc_terms(theta):
    """A = sin(t)/t, B = (1-cos t)/t^2, C = (t - sin t)/t^3, with Taylor series near 0."""
    t2 = theta * theta
    small = theta < 1e-4
    ts = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / (ts * ts))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / (ts * ts * ts))
    return a, b, c


def so3_exp(w) -> np.ndarray:
    """Rodrigues: rotation vector (..., 3) -> rotation matrix (..., 3, 3)."""
    w = _as64(w)
    theta = np.linalg.norm(w, axis=-1)
    a, b, _ = _sinc_terms(theta)
    k = hat(w)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(R) -> np.ndarray:
    """Rotation matrix (..., 3, 3) -> rotation vector (..., 3), accurate near 0 and near pi."""
    R = _as64(R)
    batch = R.shape[:-2]
    Rf = R.reshape(-1, 3, 3)
    out = np.empty((Rf.shape[0], 3))
    for i, r in enumerate(Rf):
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r.tolist()
        # scalar arithmetic (a tenth of the NumPy calls' time on one 3x3; the window logs every keyframe's pose each
        # iteration), the same operations in the same order as the array form, so the same bits; np.arccos, not
        # math.acos, whose last bit differs
        cos_t = min(max(((r00 + r11 + r22) - 1.0) * 0.5, -1.0), 1.0)
        theta = float(np.arccos(cos_t))
        if theta < 1e-4:
            f = 1.0 + theta * theta / 6.0
        elif math.pi - theta < 1e-3:
            # Near pi: axis from the diagonal of (R + I) / 2 = n n^T (+ small antisymmetric part).
            m = 0.5 * (r + r.T) + 0.0
            B = 0.5 * (m + np.eye(3))
            j = int(np.argmax(np.diag(B)))
            n = B[:, j] / np.sqrt(max(B[j, j], _EPS))
            n /= np.linalg.norm(n)
            # choose the sign so that the antisymmetric part agrees
            if np.dot(vee(r), n) < 0:
                n = -n
            out[i] = n * theta
            continue
        else:
            f = theta / math.sin(theta)
        out[i] = (0.5 * (r21 - r12) * f, 0.5 * (r02 - r20) * f, 0.5 * (r10 - r01) * f)
    return out.reshape(batch + (3,))


def so3_left_jacobian(w) -> np.ndarray:
    """Left Jacobian of SO3, the ``V`` matrix of the SE3 exponential: ``t = V(w) v``."""
    w = _as64(w)
    theta = np.linalg.norm(w, axis=-1)
    _, b, c = _sinc_terms(theta)
    k = hat(w)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + b[..., None, None] * k + c[..., None, None] * (k @ k)


def orthonormalize(R) -> np.ndarray:
    """Nearest rotation matrix (SVD), for poses read from files with round-off (7-Scenes has ~4e-4)."""
    R = _as64(R)
    u, _, vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt


def rotation_angle(R) -> np.ndarray:
    """Angle of rotation(s) in radians."""
    R = _as64(R)
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) * 0.5, -1.0, 1.0))


# --------------------------------------------------------------------------------------------------------- SE3
def make_pose(R, t) -> np.ndarray:
    """4x4 pose (batched) from rotation (..., 3, 3) and translation (..., 3)."""
    R, t = _as64(R), _as64(t)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_renormalize(T) -> np.ndarray:
    """The pose with its rotation made orthonormal again (SVD). Chains of pose products (constant-motion guesses
    compose the last two poses every frame) double their round-off each frame: renormalise what is kept."""
    T = _as64(T)
    return make_pose(orthonormalize(T[..., :3, :3]), T[..., :3, 3])


def _se3_exp_one(xi: np.ndarray) -> np.ndarray:
    """:func:`se3_exp` of one ``[6]`` vector in scalar arithmetic (the batched NumPy path costs ~0.3 ms a call in
    small-array overhead; the tracker calls this a few dozen times a frame). Same formulas and series."""
    v0, v1, v2, w0, w1, w2 = (float(x) for x in xi)
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = math.sqrt(t2)
    if theta < 1e-4:
        a, b, c = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    else:
        st, ct = math.sin(theta), math.cos(theta)
        a, b, c = st / theta, (1.0 - ct) / t2, (theta - st) / (t2 * theta)
    # k = hat(w), k @ k = w w^T - t2 I
    kk = ((w0 * w0 - t2, w0 * w1, w0 * w2), (w1 * w0, w1 * w1 - t2, w1 * w2), (w2 * w0, w2 * w1, w2 * w2 - t2))
    k = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    T = np.zeros((4, 4))
    v = (v0, v1, v2)
    for i in range(3):
        for j in range(3):
            eye = 1.0 if i == j else 0.0
            T[i, j] = eye + a * k[i][j] + b * kk[i][j]
        T[i, 3] = sum(((1.0 if i == j else 0.0) + b * k[i][j] + c * kk[i][j]) * v[j] for j in range(3))
    T[3, 3] = 1.0
    return T


def se3_exp(xi) -> np.ndarray:
    """``xi = (v, w)`` (..., 6) -> 4x4 pose (..., 4, 4)."""
    xi = _as64(xi)
    if xi.shape == (6,):
        return _se3_exp_one(xi)
    v, w = xi[..., :3], xi[..., 3:]
    R = so3_exp(w)
    t = np.einsum("...ij,...j->...i", so3_left_jacobian(w), v)
    return make_pose(R, t)


def _se3_log_one(T: np.ndarray) -> np.ndarray:
    """:func:`se3_log` of one 4x4 pose: the rotation by :func:`so3_log`, ``v = V(w)^-1 t`` solved in scalar arithmetic
    (3x3, Cramer) instead of a batched ``np.linalg.solve``."""
    w = so3_log(T[:3, :3])
    w0, w1, w2 = (float(x) for x in w)
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = math.sqrt(t2)
    if theta < 1e-4:
        b, c = 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    else:
        st, ct = math.sin(theta), math.cos(theta)
        b, c = (1.0 - ct) / t2, (theta - st) / (t2 * theta)
    k = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    kk = ((w0 * w0 - t2, w0 * w1, w0 * w2), (w1 * w0, w1 * w1 - t2, w1 * w2), (w2 * w0, w2 * w1, w2 * w2 - t2))
    V = [[(1.0 if i == j else 0.0) + b * k[i][j] + c * kk[i][j] for j in range(3)] for i in range(3)]
    t = [float(T[0, 3]), float(T[1, 3]), float(T[2, 3])]
    det = (V[0][0] * (V[1][1] * V[2][2] - V[1][2] * V[2][1]) - V[0][1] * (V[1][0] * V[2][2] - V[1][2] * V[2][0])
           + V[0][2] * (V[1][0] * V[2][1] - V[1][1] * V[2][0]))
    v = []
    for col in range(3):
        M = [row[:] for row in V]
        for r in range(3):
            M[r][col] = t[r]
        v.append((M[0][0] * (M[1][1] * M[2][2] - M[1][2] * M[2][1]) - M[0][1] * (M[1][0] * M[2][2] - M[1][2] * M[2][0])
                  + M[0][2] * (M[1][0] * M[2][1] - M[1][1] * M[2][0])) / det)
    return np.array([v[0], v[1], v[2], w0, w1, w2])


def se3_log(T) -> np.ndarray:
    """4x4 pose (..., 4, 4) -> ``(v, w)`` (..., 6)."""
    T = _as64(T)
    if T.shape == (4, 4):
        return _se3_log_one(T)
    w = so3_log(T[..., :3, :3])
    V = so3_left_jacobian(w)
    v = np.linalg.solve(V, T[..., :3, 3:4])[..., 0]
    return np.concatenate([v, w], axis=-1)


def se3_inverse(T) -> np.ndarray:
    """Inverse of rigid transform(s), exactly (no general matrix inverse)."""
    T = _as64(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def se3_adjoint(T) -> np.ndarray:
    """6x6 adjoint in ``(v, w)`` order: ``T exp(xi) T^-1 = exp(Ad_T xi)``."""
    T = _as64(T)
    R, t = T[:3, :3], T[:3, 3]
    ad = np.zeros((6, 6))
    ad[:3, :3] = R
    ad[:3, 3:] = hat(t) @ R
    ad[3:, 3:] = R
    return ad


def se3_interpolate(T0, T1, alpha: float) -> np.ndarray:
    """Geodesic interpolation ``T0 exp(alpha log(T0^-1 T1))``; alpha=0 gives T0, alpha=1 gives T1."""
    T0, T1 = _as64(T0), _as64(T1)
    return T0 @ se3_exp(alpha * se3_log(se3_inverse(T0) @ T1))


def transform_points(T, points) -> np.ndarray:
    """Apply a 4x4 transform (SE3 or Sim3) to points (N, 3)."""
    T, p = _as64(T), _as64(points)
    return p @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------------------------------------- Sim3
def sim3_from_parts(R, t, s: float) -> np.ndarray:
    """4x4 matrix ``[[s R, t], [0, 1]]``."""
    S = make_pose(_as64(R) * float(s), t)
    return S


def sim3_to_parts(S) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) of a Sim3 matrix."""
    S = _as64(S)
    sR = S[:3, :3]
    s = float(np.cbrt(np.linalg.det(sR)))
    return sR / s, S[:3, 3].copy(), s


def _sim3_V(w, sigma):
    """The matrix ``W`` with ``t = W v`` in the Sim3 exponential (Eade, 'Lie groups for computer vision')."""
    theta = float(np.linalg.norm(w))
    K = hat(w)
    I3 = np.eye(3)
    s = np.exp(sigma)
    if abs(sigma) < 1e-8:
        c0 = 1.0
        if theta < 1e-6:
            c1, c2 = 0.5, 1.0 / 6.0
        else:
            c1 = (1.0 - np.cos(theta)) / theta ** 2
            c2 = (theta - np.sin(theta)) / theta ** 3
    else:
        c0 = (s - 1.0) / sigma
        if theta < 1e-6:
            c1 = ((sigma - 1.0) * s + 1.0) / sigma ** 2
            c2 = (s * (0.5 * sigma ** 2 - sigma + 1.0) - 1.0) / sigma ** 3
        else:
            a = s * np.sin(theta)
            b = s * np.cos(theta)
            c = theta ** 2 + sigma ** 2
            c1 = (a * sigma + (1.0 - b) * theta) / (theta * c)
            c2 = (c0 - ((b - 1.0) * sigma + a * theta) / c) / theta ** 2
    return c0 * I3 + c1 * K + c2 * (K @ K)


def sim3_exp(xi) -> np.ndarray:
    """``(v, w, sigma)`` (7,) -> 4x4 Sim3 matrix with scale ``exp(sigma)``."""
    xi = _as64(xi).reshape(7)
    v, w, sigma = xi[:3], xi[3:6], xi[6]
    R = so3_exp(w)
    return sim3_from_parts(R, _sim3_V(w, sigma) @ v, np.exp(sigma))


def sim3_log(S) -> np.ndarray:
    """4x4 Sim3 matrix -> ``(v, w, sigma)``."""
    R, t, s = sim3_to_parts(S)
    w = so3_log(R)
    sigma = np.log(s)
    v = np.linalg.solve(_sim3_V(w, sigma), t)
    return np.concatenate([v, w, [sigma]])


#: Largest ``|R^T R - I|`` (max abs entry, after removing the scale) accepted for a pose or measurement. Poses chained
#: from the odometry carry round-off near 1e-12; a matrix further off than this is not a rotation (a shear, a
#: transposed or mis-built matrix), and is refused rather than silently projected. What is accepted is kept as given
#: (the pose graph re-orthonormalises it on its way to GTSAM: ``mgso.loop.graph.to_gtsam``).
SIM3_ROTATION_TOLERANCE = 1e-5


def check_sim3(S, what: str) -> np.ndarray:
    """``S`` as a float64 4x4 copy (its last row set to exactly ``[0, 0, 0, 1]``) if it is a Sim(3) within
    :data:`SIM3_ROTATION_TOLERANCE`, else ``ValueError`` with a one-line message that starts with ``what`` and says
    what is wrong (loop closure's pose graph and its messages to the mapper check their Sim(3)s with it)."""
    try:
        M = np.array(S, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} is not a Sim(3): not a numeric array ({type(S).__name__})") from None
    if M.shape != (4, 4):
        raise ValueError(f"{what} is not a Sim(3): shape {M.shape}, expected (4, 4)")
    if not np.all(np.isfinite(M)):
        raise ValueError(f"{what} is not a Sim(3): it has non-finite entries (nan or inf)")
    if np.max(np.abs(M[3] - (0.0, 0.0, 0.0, 1.0))) > SIM3_ROTATION_TOLERANCE:
        raise ValueError(f"{what} is not a Sim(3): last row {M[3].tolist()}, expected [0, 0, 0, 1]")
    det = float(np.linalg.det(M[:3, :3]))
    if not det > 0.0:
        raise ValueError(f"{what} is not a Sim(3): det(s R) = {det:.6g} <= 0 (scale <= 0, or a reflection)")
    s = det ** (1.0 / 3.0)
    R = M[:3, :3] / s
    off = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if off > SIM3_ROTATION_TOLERANCE:
        raise ValueError(f"{what} is not a Sim(3): the rotation is not orthonormal after removing the scale "
                         f"(max |R^T R - I| = {off:.3g} > {SIM3_ROTATION_TOLERANCE:g})")
    M[3] = (0.0, 0.0, 0.0, 1.0)  # round-off there has no meaning in a Sim(3); the products downstream assume it exact
    return M


def sim3_inverse(S) -> np.ndarray:
    """Inverse of a Sim3 matrix: ``[[R^T / s, -R^T t / s], [0, 1]]``."""
    R, t, s = sim3_to_parts(S)
    return sim3_from_parts(R.T, -(R.T @ t) / s, 1.0 / s)


# ------------------------------------------------------------------------------------------------- quaternions
def quat_normalize(q) -> np.ndarray:
    q = _as64(q)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < _EPS):
        raise ValueError("quaternion of zero length")
    return q / n


def quat_xyzw_to_wxyz(q) -> np.ndarray:
    q = _as64(q)
    return np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)


def quat_wxyz_to_xyzw(q) -> np.ndarray:
    q = _as64(q)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def quat_wxyz_to_matrix(q) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` (normalised here) -> rotation matrix."""
    q = quat_normalize(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quat_xyzw_to_matrix(q) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` (TUM order) -> rotation matrix."""
    return quat_wxyz_to_matrix(quat_xyzw_to_wxyz(q))


def matrix_to_quat_wxyz(R) -> np.ndarray:
    """Rotation matrix -> unit quaternion ``(w, x, y, z)`` with ``w >= 0`` (Shepperd's method)."""
    R = _as64(R)
    batch = R.shape[:-2]
    Rf = R.reshape(-1, 3, 3)
    out = np.empty((Rf.shape[0], 4))
    for i, m in enumerate(Rf):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        if tr > 0:
            s = 2.0 * np.sqrt(tr + 1.0)
            q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[i] = -q if q[0] < 0 else q
    return out.reshape(batch + (4,))


def matrix_to_quat_xyzw(R) -> np.ndarray:
    """Rotation matrix -> unit quaternion ``(x, y, z, w)`` (TUM order) with ``w >= 0``."""
    return quat_wxyz_to_xyzw(matrix_to_quat_wxyz(R))


# ------------------------------------------------------------------------------------------------- alignment
@dataclass(frozen=True)
class Alignment:
    """``dst ~= scale * rotation @ src + translation`` (Umeyama 1991)."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float

    def matrix(self) -> np.ndarray:
        """The alignment as a 4x4 Sim3 matrix."""
        return sim3_from_parts(self.rotation, self.translation, self.scale)

    def apply_points(self, points) -> np.ndarray:
        return self.scale * (_as64(points) @ self.rotation.T) + self.translation

    def apply_poses(self, cam_to_world) -> np.ndarray:
        """Align camera-to-world poses (N, 4, 4): rotate and move them, scale their positions."""
        T = _as64(cam_to_world).copy()
        T[..., :3, :3] = np.einsum("ij,...jk->...ik", self.rotation, T[..., :3, :3])
        T[..., :3, 3] = self.apply_points(T[..., :3, 3])
        return T


def umeyama_alignment(src, dst, with_scale: bool) -> Alignment:
    """Least-squares similarity (or rigid, ``with_scale=False``) transform taking ``src`` (N, 3) onto ``dst``.

    Umeyama, "Least-squares estimation of transformation parameters between two point patterns", PAMI 1991; the
    same estimator evo uses for ``evo_ape -a`` / ``-as``.
    """
    src, dst = _as64(src), _as64(dst)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama_alignment needs two (N, 3) arrays of the same shape, got {src.shape} and "
                         f"{dst.shape}")
    n = src.shape[0]
    if n < 3:
        raise ValueError(f"umeyama_alignment needs at least 3 point pairs, got {n}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs * xs).sum() / n
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    if with_scale:
        if var_s < _EPS:
            raise ValueError("umeyama_alignment: the source points are all the same point; scale is undefined")
        s = float(np.trace(np.diag(D) @ S) / var_s)
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s
    return Alignment(rotation=R, translation=t, scale=s)
