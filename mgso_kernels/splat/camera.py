"""The pinhole camera every splatting kernel takes, as one ``@wp.struct``, and its Python constructor.

Conventions (the whole of :mod:`mgso_kernels.splat` uses them):

- Camera frame x right, y down, z forward (OpenCV). ``world_to_cam`` maps world points into the camera:
  ``p_c = R p_w + t``.
- A camera-space point projects to ``u = fx x / z + cx``, ``v = fy y / z + cy`` (pixels). Pixel (row v, col u)
  samples the image plane at exactly (u, v): pixel (0, 0) has its centre at (0, 0), not at (0.5, 0.5).
- Gaussians with ``z <= near`` or ``z >= far`` are culled.
- Pose gradients are for a left perturbation ``world_to_cam <- exp(delta) @ world_to_cam`` with
  ``delta = (v, w)``, translation first (``mgso.geometry.se3_exp``).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

__all__ = ["Camera", "make_camera", "camera_centre", "TILE_SIZE"]

TILE_SIZE = 16  # pixels per tile side; tile (tx, ty) covers columns 16 tx .. 16 tx + 15, rows 16 ty .. 16 ty + 15


@wp.struct
class Camera:
    fx: float  # focal length x, pixels
    fy: float  # focal length y, pixels
    cx: float  # principal point x, pixels (pixel centres at integer coordinates)
    cy: float  # principal point y, pixels
    width: int  # image width, pixels
    height: int  # image height, pixels
    near: float  # near plane, camera z units (culls z <= near)
    far: float  # far plane (culls z >= far)
    R: wp.mat33  # world_to_cam rotation
    t: wp.vec3  # world_to_cam translation
    centre: wp.vec3  # camera centre in world coordinates, -R^T t
    lim_x_neg: float  # EWA Jacobian tangent clamp: x/z in [-lim_x_neg, lim_x_pos]
    lim_x_pos: float
    lim_y_neg: float  # y/z in [-lim_y_neg, lim_y_pos]
    lim_y_pos: float
    tiles_x: int  # ceil(width / 16)
    tiles_y: int  # ceil(height / 16)
    tile_stride: int  # blending visits tile (slot * tile_stride) % tiles: spreads a CPU chunk over the image


def make_camera(fx: float, fy: float, cx: float, cy: float, width: int, height: int, world_to_cam,
                near: float = 0.01, far: float = 1e10) -> Camera:
    """Build the :class:`Camera` struct.

    ``world_to_cam``: (4, 4) or (3, 4) array-like (a rigid transform; float64 is fine, stored as float32).
    The tangent clamp used by the EWA Jacobian is ``lim_x_pos = (W - cx)/fx + 0.3 * (0.5 W / fx)`` (and likewise
    for the other sides): 3DGS's ``1.3 * tan(fov_x / 2)`` when the principal point is centred.
    """
    T = np.asarray(world_to_cam, dtype=np.float64)
    if T.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"make_camera: world_to_cam must be 4x4 or 3x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError("make_camera: world_to_cam has non-finite entries")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
        raise ValueError("make_camera: world_to_cam's rotation block is not orthonormal (is it a Sim3 or a "
                         "projection matrix?)")
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"make_camera: image size must be positive, got {width}x{height}")
    if not (fx > 0 and fy > 0):
        raise ValueError(f"make_camera: focal lengths must be positive, got fx={fx}, fy={fy}")
    if not (0 < near < far):
        raise ValueError(f"make_camera: need 0 < near < far, got near={near}, far={far}")
    cam = Camera()
    cam.fx, cam.fy, cam.cx, cam.cy = float(fx), float(fy), float(cx), float(cy)
    cam.width, cam.height = width, height
    cam.near, cam.far = float(near), float(far)
    cam.R = wp.mat33(*R.astype(np.float32).ravel())
    cam.t = wp.vec3(*T[:3, 3].astype(np.float32))
    cam.centre = wp.vec3(*(-R.T @ T[:3, 3]).astype(np.float32))
    thx, thy = 0.5 * width / fx, 0.5 * height / fy
    cam.lim_x_neg = float(cx / fx + 0.3 * thx)
    cam.lim_x_pos = float((width - cx) / fx + 0.3 * thx)
    cam.lim_y_neg = float(cy / fy + 0.3 * thy)
    cam.lim_y_pos = float((height - cy) / fy + 0.3 * thy)
    cam.tiles_x = -(-width // TILE_SIZE)
    cam.tiles_y = -(-height // TILE_SIZE)
    cam.tile_stride = _interleave_stride(cam.tiles_x * cam.tiles_y)
    return cam


def _interleave_stride(n: int) -> int:
    """A stride coprime to n near n / golden ratio: slots 0, 1, 2, ... visit tiles far apart, so each contiguous
    chunk of a split CPU launch gets tiles from all over the image (balanced work when the scene is not)."""
    s = max(1, int(round(n * 0.6180339887)))
    while math.gcd(s, n) != 1:
        s += 1
    return s % n if n > 1 else 0


def camera_centre(cam: Camera) -> np.ndarray:
    return np.array([cam.centre[0], cam.centre[1], cam.centre[2]], dtype=np.float64)
