"""Initial Gaussians for training: random points in the view frusta, or a given point cloud.

Rules (3DGS ``create_from_pcd``, MGSO's seeding):

- isotropic scale = the mean distance of a point to its ``knn`` (3) nearest neighbours (``scipy.spatial.cKDTree``),
  floored at ``min_scale`` (coincident points would give log(0));
- identity rotation (w, x, y, z) = (1, 0, 0, 0);
- opacity 0.1 (stored as its logit);
- colour: SH DC of the point's RGB (higher SH bands zero).

:func:`random_frustum_points` draws points uniformly over the views (one view per point), uniformly over the
view's pixels and uniformly in depth over ``depth_range`` (camera z, world units), and colours each with the image
at the pixel it was drawn from (its projection into that view).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from mgso.mapping.gaussian_map import GaussianArrays, rgb_to_sh_dc

__all__ = ["random_frustum_points", "gaussians_from_points", "knn_mean_distance"]


def knn_mean_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """(N,) mean distance of each point to its ``k`` nearest other points (fewer when N <= k; 0 for one point)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n <= 1:
        return np.zeros(n)
    kk = min(int(k), n - 1)
    d, _ = cKDTree(pts).query(pts, k=kk + 1)   # the first neighbour is the point itself
    return np.asarray(d, dtype=np.float64).reshape(n, kk + 1)[:, 1:].mean(axis=1)


def gaussians_from_points(points: np.ndarray, colors: np.ndarray | None = None, *, opacity: float = 0.1,
                          knn: int = 3, min_scale: float = 1e-4, max_scale: np.ndarray | float | None = None,
                          sh_degree: int = 0) -> GaussianArrays:
    """Gaussians at ``points`` (N, 3) with ``colors`` (N, 3) RGB in [0, 1] (grey 0.5 when None): isotropic scale
    from the mean distance to the ``knn`` nearest neighbours (at least ``min_scale``), identity rotation, opacity
    ``opacity``."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"gaussians_from_points: points must be (N, 3), got shape {pts.shape}")
    n = len(pts)
    if n == 0:
        raise ValueError("gaussians_from_points: no points")
    if not np.all(np.isfinite(pts)):
        raise ValueError("gaussians_from_points: points have non-finite coordinates")
    if colors is None:
        rgb = np.full((n, 3), 0.5)
    else:
        rgb = np.asarray(colors, dtype=np.float64)
        if rgb.shape != (n, 3):
            raise ValueError(f"gaussians_from_points: colors must be ({n}, 3), got {rgb.shape}")
        if rgb.size and rgb.max() > 1.0 + 1e-6:
            raise ValueError("gaussians_from_points: colors must be RGB in [0, 1] (divide uint8 by 255)")
    if not 0.0 < opacity < 1.0:
        raise ValueError(f"gaussians_from_points: opacity must be in (0, 1), got {opacity}")
    scale = knn_mean_distance(pts, knn)
    if max_scale is not None:
        scale = np.minimum(scale, np.broadcast_to(np.asarray(max_scale, dtype=np.float64), scale.shape))
    scale = np.maximum(scale, float(min_scale))
    K = (int(sh_degree) + 1) ** 2
    sh = np.zeros((n, K, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(rgb)
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1.0
    return GaussianArrays(means=pts.astype(np.float32), log_scales=np.repeat(np.log(scale)[:, None], 3, axis=1),
                          quats=quats, opacity_logits=np.full(n, math.log(opacity / (1.0 - opacity))), sh=sh)


def random_frustum_points(views, n: int, depth_range: tuple[float, float],
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` random points inside the views' frusta, and their colours.

    ``views``: :class:`~mgso.mapping.views.TrainView` objects (anything with ``image``, ``camera``,
    ``cam_to_world``). Each point picks a view uniformly, a pixel uniformly and a camera depth uniformly in
    ``depth_range`` (near, far; world units); its colour is the view's image at that pixel.
    Returns (points (n, 3) float64 world, colours (n, 3) float32 RGB, pixel sizes (n,): the world size of one
    pixel at the point's depth in the view it was drawn from, z / f).
    """
    views = list(views)
    if not views:
        raise ValueError("random_frustum_points: no views")
    near, far = (float(d) for d in depth_range)
    if not 0.0 < near < far:
        raise ValueError(f"random_frustum_points: depth_range must satisfy 0 < near < far, got {depth_range}")
    if n < 1:
        raise ValueError(f"random_frustum_points: n must be >= 1, got {n}")
    which = rng.integers(len(views), size=n)
    points = np.empty((n, 3))
    colors = np.empty((n, 3), np.float32)
    pixel = np.empty(n)
    for k, view in enumerate(views):
        sel = np.flatnonzero(which == k)
        if len(sel) == 0:
            continue
        cam = view.camera
        u = rng.integers(cam.width, size=len(sel))
        v = rng.integers(cam.height, size=len(sel))
        z = rng.uniform(near, far, size=len(sel))
        pc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], axis=1)
        T = view.cam_to_world
        points[sel] = pc @ T[:3, :3].T + T[:3, 3]
        colors[sel] = view.image[v, u]
        pixel[sel] = z / np.sqrt(cam.fx * cam.fy)
    return points, colors, pixel
