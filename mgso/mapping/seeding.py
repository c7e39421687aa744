"""MGSO's seeding: new Gaussians from a keyframe's DSO points, only where the map is still empty.

The rule (MGSO, Hu et al. ICRA 2025; docs/seeding.md), per keyframe:

1. **Candidates.** DSO's points of the keyframe (active, marginalised and, optionally, immature points with a good
   depth interval), back-projected with the keyframe's refined ``cam_to_world`` and their inverse depth,
   ``X_w = R (K^-1 [u, v, 1] / idepth) + t``. Colour: the mean of the RGB keyframe image over DSO's 8-pixel pattern
   around the point (bilinear), unless the message gives one.
2. **Low-gradient fill.** Delaunay triangulation of the points in the image (``scipy.spatial.Delaunay``); every
   triangle larger than ``fill_min_triangle_area_px`` gets points inside it: its centroid, or the centroids of the
   k x k congruent sub-triangles for very large ones (k = ceil(sqrt(area / fill_area_per_point_px)), capped). Their
   depth is the mean of the vertex depths (MGSO) or the barycentric interpolation of the vertex inverse depths
   (exact on a plane, since inverse depth is affine in the image over a plane). Triangles whose vertex depths differ
   by more than ``fill_max_depth_ratio`` are skipped: they straddle a depth discontinuity, and a fill point would
   float between the foreground and the background.
3. **Visibility.** The current map's accumulated alpha rendered from the keyframe (:func:`render_coverage`, at a
   reduced resolution) is sampled at every candidate; only candidates with ``alpha < visibility_threshold`` are
   kept. When fewer than ``min_new_gaussians`` survive, nothing is added (MGSO: 30).
4. **New Gaussians.** Opacity 0.1 (as a logit), identity rotation, SH DC from the colour, isotropic scale = the mean
   distance to the ``knn`` (3) nearest neighbours among the new points and the map's Gaussians visible from the
   keyframe (``scipy.spatial.cKDTree``), clamped to ``[scale_min_px, scale_max_px] * depth / f`` (the keyframe's
   pixel footprint at the point's depth).

:func:`plan_seeds` is the pure array part (no map, no Warp); :func:`seed_keyframe` renders the coverage of a
:class:`~mgso.mapping.gaussian_map.GaussianMap`, plans and adds. Conventions: camera x right, y down, z forward;
pixel centres at integer coordinates; poses named by direction.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from mgso.camera import PinholeCamera
from mgso.config import SeedingConfig
from mgso.geometry import se3_inverse
from mgso.mapping.gaussian_map import GaussianArrays, GaussianMap, rgb_to_sh_dc
from mgso.messages import PointKind, check_points, frozen_array as _frozen_array

__all__ = [
    "PointKind", "SeedStatus", "KeyframeSeedInput", "FillPoints", "SeedCandidates", "SeedResult", "SeedPlan",
    "Coverage", "sample_pattern_colors", "backproject", "delaunay_fill", "make_candidates", "sample_alpha",
    "seed_scales", "gaussians_from_seeds", "plan_seeds", "render_coverage", "map_seen_from", "seed_keyframe",
    "COVERAGE_DOWNSCALE",
]

log = logging.getLogger(__name__)

# DSO's 8-pixel residual pattern (mgso_kernels.photometric.PATTERN_NP, DSO patternP = staticPattern[8]); kept here as
# a copy so that importing this module does not import Warp kernels. tests/mapping/test_seeding.py checks equality.
PATTERN = np.array([[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]], dtype=np.float64)


# mapping.seeding.alpha_downscale null: the coverage render's downscale in the deterministic mode (and for callers
# outside a mapper); a mapper with a thread or process of its own takes 4 instead (Mapper.coverage_downscale)
COVERAGE_DOWNSCALE = 2


class SeedStatus(enum.Enum):
    ADDED = "added"                 # Gaussians were added
    TOO_FEW = "too_few"             # fewer than min_new_gaussians survived the visibility filter
    NO_POINTS = "no_points"         # the message had no usable point
    DISABLED = "disabled"           # cfg.enabled is false
    MAP_FULL = "map_full"           # the map had no room at all


# ---------------------------------------------------------------------------------------------- the message
def _as_pinhole(camera) -> PinholeCamera:
    if isinstance(camera, PinholeCamera):
        return camera
    try:
        return PinholeCamera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    except AttributeError:
        raise TypeError("KeyframeSeedInput.camera: expected an object with fx, fy, cx, cy, width, height (e.g. "
                        f"mgso.camera.PinholeCamera), got {type(camera).__name__}") from None


@dataclass(frozen=True, eq=False)
class KeyframeSeedInput:
    """What the seeding needs of one keyframe (the system builds it from the window; plain arrays).

    - ``image``: (H, W, 3) float32 RGB in [0, 1], the keyframe as recorded (undistorted).
    - ``camera``: pinhole intrinsics of ``image`` (``mgso.camera.PinholeCamera`` or anything with ``fx, fy, cx, cy,
      width, height``; pixel centres at integer coordinates).
    - ``cam_to_world``: (4, 4) refined pose of the keyframe (rigid).
    - ``points_uv``: (M, 2) pixel coordinates (x, y) of DSO's points hosted by this keyframe.
    - ``idepths``: (M,) their inverse depths (1 / camera z) in the keyframe.
    - ``kinds``: optional (M,) :class:`PointKind` codes (default: all ACTIVE).
    - ``weights``: optional (M,) confidences (e.g. the inverse-depth Hessian); ``cfg.min_point_weight`` drops the
      weak ones.
    - ``colors``: optional (M, 3) RGB in [0, 1]; default: the image over DSO's 8-pixel pattern (bilinear mean).
    - ``exposure``: optional affine brightness (a, b) of this keyframe in the image's [0, 1] units, the model of the
      trainer's loss (``image = exp(a) * radiance + b``); colours are converted to radiance ``(I - b) / exp(a)``.
    - ``keyframe_id``: the caller's id, copied into the result.

    Arrays are copied, made read-only, and checked; bad input raises ``ValueError`` naming the field.
    """

    image: np.ndarray
    camera: PinholeCamera
    cam_to_world: np.ndarray
    points_uv: np.ndarray
    idepths: np.ndarray
    kinds: np.ndarray | None = None
    weights: np.ndarray | None = None
    colors: np.ndarray | None = None
    exposure: tuple[float, float] | None = None
    keyframe_id: int = -1

    def __post_init__(self):
        cam = _as_pinhole(self.camera)
        object.__setattr__(self, "camera", cam)
        W, H = cam.width, cam.height
        img = np.asarray(self.image)
        if img.shape != (H, W, 3):
            raise ValueError(f"KeyframeSeedInput.image: expected ({H}, {W}, 3) RGB for a {W}x{H} camera, got "
                             f"{img.shape}")
        if not np.issubdtype(img.dtype, np.floating):
            raise ValueError(f"KeyframeSeedInput.image: expected float RGB in [0, 1], got dtype {img.dtype}")
        object.__setattr__(self, "image", _frozen_array(img.astype(np.float32, copy=True)))
        T = np.array(self.cam_to_world, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"KeyframeSeedInput.cam_to_world: expected a finite 4x4 matrix, got shape {T.shape}")
        if np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() > 1e-4 or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise ValueError("KeyframeSeedInput.cam_to_world: not a rigid transform (rotation block not orthonormal "
                             "or last row not 0 0 0 1; a Sim3 must be converted to SE3 first)")
        object.__setattr__(self, "cam_to_world", _frozen_array(T))
        uv, idepths, kinds, weights, colors = check_points("KeyframeSeedInput", self.points_uv, self.idepths,
                                                           self.kinds, self.weights, self.colors)
        for name, v in (("points_uv", uv), ("idepths", idepths), ("kinds", kinds), ("weights", weights),
                        ("colors", colors)):
            object.__setattr__(self, name, v)
        if self.exposure is not None:
            a, b = (float(v) for v in self.exposure)
            if not (math.isfinite(a) and math.isfinite(b)):
                raise ValueError(f"KeyframeSeedInput.exposure: (a, b) must be finite, got {self.exposure}")
            object.__setattr__(self, "exposure", (a, b))

    @classmethod
    def from_message(cls, msg, exposure: tuple[float, float] | None = None) -> "KeyframeSeedInput":
        """What :func:`seed_keyframe` needs of a :class:`~mgso.messages.KeyframeMessage` (``exposure``: the
        trainer's (a', b') of the view, so that seed colours are radiance)."""
        return cls(msg.image, msg.camera, msg.cam_to_world, msg.points_uv, msg.idepths, kinds=msg.kinds,
                   weights=msg.weights, colors=msg.colors, exposure=exposure, keyframe_id=msg.keyframe_id)

    @property
    def num_points(self) -> int:
        return int(self.points_uv.shape[0])

    @property
    def world_to_cam(self) -> np.ndarray:
        return se3_inverse(self.cam_to_world)


# ----------------------------------------------------------------------------------------------- helpers
def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (float64) of ``image`` (H, W[, C]) at (x, y), coordinates clamped to the pixel centres'
    range. Only the four neighbours of each sample are read (no copy of the image)."""
    h, w = image.shape[:2]
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, w - 1.0)
    y = np.clip(np.asarray(y, dtype=np.float64), 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = x - x0
    fy = y - y0
    if image.ndim == 3:
        fx = fx[..., None]
        fy = fy[..., None]
    top = image[y0, x0].astype(np.float64) * (1 - fx) + image[y0, x1].astype(np.float64) * fx
    bottom = image[y1, x0].astype(np.float64) * (1 - fx) + image[y1, x1].astype(np.float64) * fx
    return top * (1 - fy) + bottom * fy


def sample_pattern_colors(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(M, 3) mean colour of ``image`` (H, W, 3) over DSO's 8-pixel pattern around each ``uv`` (M, 2), bilinear,
    pattern pixels clamped to the image."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    img = np.asarray(image)
    x = uv[:, 0][None, :] + PATTERN[:, 0][:, None]        # (8, M)
    y = uv[:, 1][None, :] + PATTERN[:, 1][:, None]
    return _bilinear(img, x, y).mean(axis=0).astype(np.float32)


def backproject(uv: np.ndarray, depth: np.ndarray, camera: PinholeCamera, cam_to_world: np.ndarray) -> np.ndarray:
    """(M, 3) world points of pixels ``uv`` (M, 2) at camera z ``depth`` (M,): ``X_w = R (z K^-1 [u, v, 1]) + t``."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(depth, dtype=np.float64).reshape(-1)
    pc = np.stack([(uv[:, 0] - camera.cx) / camera.fx * z, (uv[:, 1] - camera.cy) / camera.fy * z, z], axis=1)
    T = np.asarray(cam_to_world, dtype=np.float64)
    return pc @ T[:3, :3].T + T[:3, 3]


# ----------------------------------------------------------------------------------------- Delaunay fill
@dataclass(frozen=True)
class FillPoints:
    """Points made inside large Delaunay triangles of a keyframe's points.

    ``uv`` (F, 2) pixels, ``depth`` (F,) camera z, ``triangle`` (F,) index of the Delaunay simplex each lies in;
    counts: ``num_triangles`` (all), ``num_large`` (area above the threshold), ``num_rejected_discontinuity``
    (large ones skipped for their vertex depth ratio), ``num_filled`` (large ones that got points).
    """

    uv: np.ndarray
    depth: np.ndarray
    triangle: np.ndarray
    num_triangles: int
    num_large: int
    num_rejected_discontinuity: int
    num_filled: int

    @property
    def n(self) -> int:
        return int(self.uv.shape[0])

    @classmethod
    def empty(cls, num_triangles: int = 0) -> "FillPoints":
        return cls(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), num_triangles, 0, 0, 0)


def _subtriangle_barycentrics(k: int) -> np.ndarray:
    """(k^2, 3) barycentric coordinates of the centroids of the k x k congruent sub-triangles of a triangle (k
    segments per edge): evenly spread points, the centroid itself for k = 1."""
    out = []
    for i in range(k):
        for j in range(k - i):
            out.append(((i + 1.0 / 3.0) / k, (j + 1.0 / 3.0) / k))          # upward sub-triangles
            if i + j <= k - 2:
                out.append(((i + 2.0 / 3.0) / k, (j + 2.0 / 3.0) / k))      # downward ones
    ab = np.array(out)
    return np.column_stack([ab, 1.0 - ab.sum(axis=1)])


def delaunay_fill(uv: np.ndarray, depth: np.ndarray, cfg: SeedingConfig) -> FillPoints:
    """Fill points inside the large triangles of the Delaunay triangulation of ``uv`` (M, 2) (see module doc).

    ``depth`` (M,): camera z of the vertices (> 0). ``cfg.fill_depth``: ``"mean"`` (MGSO: the mean of the three
    vertex depths, the same for every point of a triangle) or ``"barycentric"`` (1 / the barycentric interpolation of
    the vertex inverse depths at the point: exact on a planar surface).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(depth, dtype=np.float64).reshape(-1)
    if z.shape != (len(uv),):
        raise ValueError(f"delaunay_fill: depth must be ({len(uv)},), got {z.shape}")
    if len(uv) < 3:
        return FillPoints.empty()
    try:
        tri = Delaunay(uv)
    except QhullError:                    # all points collinear (or coincident): no triangle
        return FillPoints.empty()
    simp = tri.simplices                  # (T, 3) vertex indices
    P = uv[simp]                          # (T, 3, 2)
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    large = area > cfg.fill_min_triangle_area_px
    Z = z[simp]
    ratio = Z.max(axis=1) / Z.min(axis=1)
    straddle = large & (ratio > cfg.fill_max_depth_ratio)
    fill = large & ~straddle
    idx = np.flatnonzero(fill)
    if len(idx) == 0:
        return FillPoints(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), len(simp), int(large.sum()),
                          int(straddle.sum()), 0)
    k = np.clip(np.ceil(np.sqrt(area[idx] / cfg.fill_area_per_point_px)), 1, cfg.fill_max_subdivisions)
    k = k.astype(np.int64)
    uvs, depths, tris = [], [], []
    for kk in np.unique(k):
        sel = idx[k == kk]
        B = _subtriangle_barycentrics(int(kk))                        # (S, 3)
        pts = np.einsum("sv,tvc->tsc", B, P[sel])                     # (t, S, 2)
        if cfg.fill_depth == "mean":
            d = np.repeat(Z[sel].mean(axis=1)[:, None], len(B), axis=1)
        else:
            d = 1.0 / np.einsum("sv,tv->ts", B, 1.0 / Z[sel])
        uvs.append(pts.reshape(-1, 2))
        depths.append(d.reshape(-1))
        tris.append(np.repeat(sel, len(B)))
    return FillPoints(np.concatenate(uvs), np.concatenate(depths), np.concatenate(tris), len(simp),
                      int(large.sum()), int(straddle.sum()), len(idx))


# -------------------------------------------------------------------------------------------- candidates
@dataclass(frozen=True)
class SeedCandidates:
    """Every candidate of one keyframe before the visibility filter: DSO's usable points first, then fill points.

    ``uv`` (C, 2) pixels, ``depth`` (C,) camera z, ``means`` (C, 3) world, ``colors`` (C, 3) RGB radiance in
    [0, 1], ``kinds`` (C,) :class:`PointKind`; ``num_points_in`` (the message's), ``num_invalid`` (dropped: inverse
    depth not finite and positive, outside the image, weight or kind filtered), ``num_too_far`` (dropped: deeper
    than ``max_depth_factor`` times the median depth of the message's valid points), ``fill`` (the fill's counts).
    """

    uv: np.ndarray
    depth: np.ndarray
    means: np.ndarray
    colors: np.ndarray
    kinds: np.ndarray
    num_points_in: int
    num_invalid: int
    fill: FillPoints
    num_too_far: int = 0

    @property
    def n(self) -> int:
        return int(self.uv.shape[0])

    @property
    def num_points(self) -> int:
        """Candidates that are DSO points (not fill)."""
        return self.n - self.fill.n


def make_candidates(msg: KeyframeSeedInput, cfg: SeedingConfig) -> SeedCandidates:
    """Back-project the message's usable points and add the Delaunay fill (steps 1-2 of the module doc)."""
    cam = msg.camera
    uv, idepth, kinds = msg.points_uv, msg.idepths, msg.kinds
    ok = np.isfinite(idepth) & (idepth > 0) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5)
    if not cfg.use_immature:
        ok &= kinds != PointKind.IMMATURE
    if msg.weights is not None and cfg.min_point_weight > 0:
        ok &= msg.weights >= cfg.min_point_weight
    num_invalid = int((~ok).sum())
    if cfg.max_depth_factor > 0 and ok.any():
        # DSO's active points whose inverse depth the window drove to nearly zero (no parallax to hold it) sit
        # thousands to 1e10 times farther than the rest: as Gaussians they are junk, and the map's extent with them
        # (docs/seeding.md). Dropped before the fill, so that they do not spoil their triangles either.
        ok &= idepth * (cfg.max_depth_factor * np.median(1.0 / idepth[ok])) >= 1.0
    uv_p = uv[ok]
    z_p = 1.0 / idepth[ok]
    if cfg.fill:
        fill = delaunay_fill(uv_p, z_p, cfg)
    else:
        fill = FillPoints.empty()
    all_uv = np.concatenate([uv_p, fill.uv])
    if msg.colors is None:
        colors = sample_pattern_colors(msg.image, all_uv).astype(np.float64)
    else:
        colors = np.concatenate([msg.colors[ok], sample_pattern_colors(msg.image, fill.uv)]).astype(np.float64)
    if msg.exposure is not None:
        a, b = msg.exposure
        colors = (colors - b) / math.exp(a)
    all_z = np.concatenate([z_p, fill.depth])
    return SeedCandidates(
        uv=all_uv, depth=all_z, means=backproject(all_uv, all_z, cam, msg.cam_to_world),
        colors=np.clip(colors, 0.0, 1.0).astype(np.float32),
        kinds=np.concatenate([kinds[ok], np.full(fill.n, int(PointKind.FILL), np.int8)]).astype(np.int8),
        num_points_in=msg.num_points, num_invalid=num_invalid, fill=fill,
        num_too_far=int((~ok).sum()) - num_invalid)


# -------------------------------------------------------------------------------------------- visibility
def sample_alpha(alpha: np.ndarray, uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """(C,) the coverage ``alpha`` at full-resolution pixels ``uv`` (C, 2) of a ``width`` x ``height`` keyframe.

    ``alpha`` is (height, width), or rendered at 1/s resolution with shape (height // s, width // s) for an integer
    s (:func:`render_coverage`'s layout: low-resolution pixel j covers full-resolution pixels [j s, (j + 1) s)),
    sampled bilinearly at ``(u + 0.5) / s - 0.5``.
    """
    alpha = np.asarray(alpha, dtype=np.float64)
    if alpha.ndim != 2 or alpha.shape[0] < 1 or alpha.shape[1] < 1:
        raise ValueError(f"sample_alpha: alpha must be a non-empty (H, W) array, got shape {alpha.shape}")
    h, w = alpha.shape
    s = height // h
    if s < 1 or h != height // s or w != width // s:
        raise ValueError(f"sample_alpha: alpha of shape {alpha.shape} is neither the keyframe's {height}x{width} "
                         f"nor an integer downscale of it (height // s, width // s)")
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if s == 1:
        return _bilinear(alpha, uv[:, 0], uv[:, 1])
    return _bilinear(alpha, (uv[:, 0] + 0.5) / s - 0.5, (uv[:, 1] + 0.5) / s - 0.5)


# ----------------------------------------------------------------------------------------- new Gaussians
def seed_scales(means: np.ndarray, depths: np.ndarray, focal: float, cfg: SeedingConfig,
                neighbour_means: np.ndarray | None = None) -> np.ndarray:
    """(N,) isotropic scales of new Gaussians at ``means`` (N, 3): the mean distance to their ``cfg.knn`` nearest
    neighbours among the other new points and ``neighbour_means`` (K, 3) (the map's Gaussians near the view),
    clamped to ``[scale_min_px, scale_max_px] * depth / focal`` (``depths`` (N,) camera z in the keyframe, ``focal``
    in pixels). Where fewer than ``knn`` neighbours exist the mean is over those that do; none at all gives the
    upper clamp.
    """
    p = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    n = len(p)
    z = np.asarray(depths, dtype=np.float64).reshape(-1)
    lo = cfg.scale_min_px * z / focal
    hi = cfg.scale_max_px * z / focal
    if n == 0:
        return np.zeros(0)
    pts = p
    if neighbour_means is not None and len(neighbour_means):
        pts = np.concatenate([p, np.asarray(neighbour_means, dtype=np.float64).reshape(-1, 3)])
    k = min(cfg.knn, len(pts) - 1)
    if k < 1:
        return hi.copy()
    # the nearest is the point itself (distance 0). The tree is built for one query of the new points: unbalanced
    # and without shrinking its nodes' boxes it builds about twice as fast (the query is exact either way: the same
    # distances), 1,500 seeds among 20,000 neighbours 5.3 -> 3.3 ms (docs/seeding.md)
    d, _ = cKDTree(pts, balanced_tree=False, compact_nodes=False).query(p, k=k + 1)
    d = np.asarray(d).reshape(n, k + 1)[:, 1:]
    return np.clip(d.mean(axis=1), lo, hi)


def gaussians_from_seeds(means: np.ndarray, colors: np.ndarray, scales: np.ndarray, cfg: SeedingConfig,
                         sh_degree: int = 0) -> GaussianArrays:
    """The parameter arrays of new Gaussians (the map's layout, ready for ``GaussianMap.add``): ``means`` (N, 3),
    log of the isotropic ``scales`` (N,), identity rotation (w, x, y, z) = (1, 0, 0, 0), opacity
    ``cfg.init_opacity`` as a logit, SH DC from ``colors`` (N, 3) RGB in [0, 1] (higher bands zero)."""
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    n = len(means)
    scales = np.asarray(scales, dtype=np.float64).reshape(-1)
    if scales.shape != (n,) or (n and not np.all(scales > 0)):
        raise ValueError(f"gaussians_from_seeds: scales must be ({n},) and positive")
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1.0
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(np.asarray(colors, dtype=np.float32).reshape(n, 3))
    logit = math.log(cfg.init_opacity / (1.0 - cfg.init_opacity))
    return GaussianArrays(means=means.astype(np.float32), log_scales=np.repeat(np.log(scales)[:, None], 3, axis=1),
                          quats=quats, opacity_logits=np.full(n, logit, np.float32), sh=sh)


# ------------------------------------------------------------------------------------------------ results
@dataclass(frozen=True)
class SeedResult:
    """Counts of one keyframe's seeding (what happened, not printed).

    ``num_points_in``: points in the message; ``num_invalid``: dropped before anything (bad inverse depth, outside
    the image, kind/weight filtered); ``num_too_far``: dropped as far beyond the message's median depth
    (``max_depth_factor``); ``num_candidates``: usable points + fill points; ``num_fill``: fill points;
    ``num_triangles`` / ``num_large_triangles`` / ``num_rejected_discontinuity``: the Delaunay fill's triangles;
    ``num_rejected_visibility``: candidates where the map's alpha was already >= the threshold; ``num_survivors``:
    candidates left; ``num_added``: Gaussians added (0 when ``skipped_too_few``); ``num_dropped_capacity``:
    survivors not added because the map was full; ``status``; ``seconds``: wall time of the seeding.
    """

    keyframe_id: int
    status: SeedStatus
    num_points_in: int = 0
    num_invalid: int = 0
    num_too_far: int = 0
    num_candidates: int = 0
    num_fill: int = 0
    num_triangles: int = 0
    num_large_triangles: int = 0
    num_rejected_discontinuity: int = 0
    num_rejected_visibility: int = 0
    num_survivors: int = 0
    num_added: int = 0
    num_dropped_capacity: int = 0
    seconds: float = 0.0
    coverage_rendered: bool = True      # False: no render (seeding off, an empty map, fewer candidates than
                                        # min_new_gaussians, a full map)
    # the depth rule (depth_tolerance > 0): the median relative depth error of the covered candidates
    # (depth_rule_max_median > 0) and the tolerance applied (inf: skipped, the median above that); None: no rule
    depth_error_median: float | None = None
    depth_tolerance_used: float | None = None

    @property
    def skipped_too_few(self) -> bool:
        return self.status is SeedStatus.TOO_FEW


@dataclass(frozen=True)
class SeedPlan:
    """What :func:`plan_seeds` decided: ``gaussians`` to add (n = 0 when nothing is to be added), ``result`` (counts;
    ``num_added`` = ``gaussians.n`` before the map's capacity is known), and the candidates with their ``alpha``
    (C,) and ``keep`` (C,) mask for inspection."""

    gaussians: GaussianArrays
    result: SeedResult
    candidates: SeedCandidates
    alpha: np.ndarray
    keep: np.ndarray


def _empty_gaussians(sh_degree: int) -> GaussianArrays:
    k = (sh_degree + 1) ** 2
    return GaussianArrays(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, k, 3)))


def plan_seeds(msg: KeyframeSeedInput, cfg: SeedingConfig, alpha: np.ndarray | None = None,
               neighbour_means: np.ndarray | None = None, sh_degree: int = 0,
               depth: np.ndarray | None = None, candidates: SeedCandidates | None = None) -> SeedPlan:
    """The array part of the seeding (no map, no Warp): candidates, visibility filter, new Gaussians.

    ``alpha``: the current map's accumulated alpha seen from the keyframe, (H, W) or an integer downscale of it
    (:func:`sample_alpha`); ``None`` = an empty map (every candidate passes). ``neighbour_means`` (K, 3): the map's
    Gaussians near the view, neighbours for the scales. ``sh_degree``: the map's. ``depth``: the map's accumulated
    depth in the same layout as ``alpha``; with ``cfg.depth_tolerance > 0`` a candidate the map covers is kept too
    when the map's expected depth there differs from the candidate's by more than that fraction (the map has no
    surface where the odometry measured one: SplaTAM's depth-error rule with the odometry's points).
    ``candidates``: :func:`make_candidates` of ``msg`` and ``cfg`` when the caller has made them already.
    """
    t0 = time.perf_counter()
    if not cfg.enabled:
        res = SeedResult(msg.keyframe_id, SeedStatus.DISABLED, num_points_in=msg.num_points)
        empty = SeedCandidates(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3), np.float32),
                               np.zeros(0, np.int8), msg.num_points, 0, FillPoints.empty())
        return SeedPlan(_empty_gaussians(sh_degree), res, empty, np.zeros(0), np.zeros(0, bool))
    cand = make_candidates(msg, cfg) if candidates is None else candidates
    cam = msg.camera
    if alpha is None:
        a = np.zeros(cand.n)
    else:
        a = sample_alpha(alpha, cand.uv, cam.width, cam.height)
    keep = a < cfg.visibility_threshold
    depth_median = tolerance = None
    if depth is not None and alpha is not None and cfg.depth_tolerance > 0 and cand.n:
        d_sum = sample_alpha(depth, cand.uv, cam.width, cam.height)
        expected = d_sum / np.maximum(a, 1e-6)
        rel = np.abs(expected - cand.depth) / cand.depth
        tolerance = cfg.depth_tolerance
        covered = ~keep
        if cfg.depth_rule_max_median > 0 and covered.sum() >= max(cfg.min_new_gaussians, 1):
            # the odometry's depths against the map's where the map covers them: when most of them disagree (a
            # handheld camera's poor depths), the disagreement is the odometry's noise, not surfaces the map lacks,
            # and the rule would seed everywhere again; the alpha rule alone then
            depth_median = float(np.median(rel[covered]))
            if depth_median > cfg.depth_rule_max_median:
                tolerance = math.inf
        keep |= rel > tolerance
    survivors = int(keep.sum())
    counts = dict(num_points_in=cand.num_points_in, num_invalid=cand.num_invalid, num_too_far=cand.num_too_far,
                  num_candidates=cand.n,
                  num_fill=cand.fill.n, num_triangles=cand.fill.num_triangles,
                  num_large_triangles=cand.fill.num_large,
                  num_rejected_discontinuity=cand.fill.num_rejected_discontinuity,
                  num_rejected_visibility=cand.n - survivors, num_survivors=survivors,
                  depth_error_median=depth_median, depth_tolerance_used=tolerance)
    if cand.n == 0:
        status = SeedStatus.NO_POINTS
    elif survivors < max(cfg.min_new_gaussians, 1):
        status = SeedStatus.TOO_FEW
    else:
        status = SeedStatus.ADDED
    if status is not SeedStatus.ADDED:
        res = SeedResult(msg.keyframe_id, status, **counts, seconds=time.perf_counter() - t0)
        return SeedPlan(_empty_gaussians(sh_degree), res, cand, a, keep)
    means = cand.means[keep]
    focal = math.sqrt(cam.fx * cam.fy)
    near = None
    if neighbour_means is not None and len(neighbour_means):
        nb = np.asarray(neighbour_means, dtype=np.float64).reshape(-1, 3)
        margin = cfg.scale_max_px * float(cand.depth[keep].max()) / focal
        lo, hi = means.min(axis=0) - margin, means.max(axis=0) + margin
        near = nb[np.all((nb >= lo) & (nb <= hi), axis=1)]
    scales = seed_scales(means, cand.depth[keep], focal, cfg, near)
    g = gaussians_from_seeds(means, cand.colors[keep], scales, cfg, sh_degree)
    res = SeedResult(msg.keyframe_id, status, **counts, num_added=g.n, seconds=time.perf_counter() - t0)
    return SeedPlan(g, res, cand, a, keep)


# ------------------------------------------------------------------------------------------ with the map
@dataclass(frozen=True)
class Coverage:
    """The map seen from a keyframe: ``alpha`` (h, w) float32 accumulated opacity at 1/``downscale`` resolution (a
    NumPy copy), ``visible`` (N,) bool per map row (screen radius > 0 in that render)."""

    alpha: np.ndarray
    visible: np.ndarray
    downscale: int
    depth: np.ndarray | None = None     # (h, w) accumulated depth sum_i w_i z_i (expected depth = depth / alpha)


def render_coverage(gmap: GaussianMap, rasterizer, camera, world_to_cam: np.ndarray, downscale: int = 2,
                    with_depth: bool = False, t_stop: float = 0.0) -> Coverage:
    """Render the map's accumulated alpha (and with ``with_depth`` its accumulated depth) from a keyframe at
    1/``downscale`` resolution (``Rasterizer.render_alpha``; ``t_stop``: its coverage stop, 0 = the full render's).

    The reduced camera follows docs/rasteriser.md: ``fx / s, fy / s, (cx + 0.5) / s - 0.5, (cy + 0.5) / s - 0.5``,
    size ``(W // s, H // s)`` (pixel centres at integer coordinates), so low-resolution pixel j covers
    full-resolution pixels ``[j s, (j + 1) s)``. An empty map gives zero alpha without rendering.
    """
    from mgso_kernels.splat import make_camera  # Warp only when a map is involved

    cam = _as_pinhole(camera)
    s = int(downscale)
    if s < 1:
        raise ValueError(f"render_coverage: downscale must be >= 1, got {downscale}")
    w, h = cam.width // s, cam.height // s
    if w < 1 or h < 1:
        raise ValueError(f"render_coverage: a {cam.width}x{cam.height} image cannot be downscaled by {s}")
    if gmap.n == 0:
        return Coverage(np.zeros((h, w), np.float32), np.zeros(0, bool), s,
                        np.zeros((h, w), np.float32) if with_depth else None)
    rc = make_camera(cam.fx / s, cam.fy / s, (cam.cx + 0.5) / s - 0.5, (cam.cy + 0.5) / s - 0.5, w, h,
                     np.asarray(world_to_cam, dtype=np.float64))
    p = gmap.float_params()
    out = rasterizer.render_alpha(p.means, p.log_scales, p.quats, p.opacity_logits, rc, with_depth=with_depth,
                                  t_stop=t_stop)
    return Coverage(np.array(out.alpha.numpy(), dtype=np.float32, copy=True), out.radii.numpy() > 0, s,
                    np.array(out.depth.numpy(), dtype=np.float32, copy=True) if with_depth else None)


def map_seen_from(gmap: GaussianMap, rasterizer, msg: KeyframeSeedInput, cfg: SeedingConfig
                  ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """What the seeding tests a keyframe's candidates against: the map's coverage ``alpha`` and accumulated ``depth``
    (only with ``cfg.depth_tolerance > 0``) at 1/``alpha_downscale`` resolution, and the means of the Gaussians
    visible from the keyframe (neighbours for the scales). ``(None, None, None)`` for an empty map."""
    if gmap.n == 0:
        return None, None, None
    ds = COVERAGE_DOWNSCALE if cfg.alpha_downscale is None else cfg.alpha_downscale
    cov = render_coverage(gmap, rasterizer, msg.camera, msg.world_to_cam, ds,
                          with_depth=cfg.depth_tolerance > 0, t_stop=cfg.coverage_stop)
    neighbours = gmap.means.numpy()[cov.visible] if cov.visible.any() else None
    return cov.alpha, cov.depth, neighbours


def seed_keyframe(gmap: GaussianMap, rasterizer, msg: KeyframeSeedInput, cfg: SeedingConfig, step: int) -> SeedResult:
    """MGSO's seeding of one keyframe into ``gmap``: render the coverage, plan, add (new rows get
    ``created_step = step``). Call it between training iterations (it changes the map's structure).

    When the map has room for only part of the survivors, an evenly strided subset is added and the rest is counted
    in ``num_dropped_capacity`` (the map never grows here: ``mapping.capacity`` is a hard budget). A map already full
    is not rendered: the result is ``MAP_FULL`` with every point offered in ``num_dropped_capacity``.
    """
    t0 = time.perf_counter()
    if not cfg.enabled:
        return SeedResult(msg.keyframe_id, SeedStatus.DISABLED, num_points_in=msg.num_points, coverage_rendered=False)
    if gmap.n >= gmap.capacity:
        # nothing can be added, so nothing is rendered or planned (a long real-time run's map at its capacity spent a
        # coverage render of 500,000 Gaussians on each of its last 51 seedings); the points offered count as dropped
        log.warning("seeding keyframe %s: the map is full (%d Gaussians), %d points not seeded", msg.keyframe_id,
                    gmap.n, msg.num_points)
        return SeedResult(msg.keyframe_id, SeedStatus.MAP_FULL, num_points_in=msg.num_points,
                          num_dropped_capacity=msg.num_points, coverage_rendered=False,
                          seconds=time.perf_counter() - t0)
    cand = make_candidates(msg, cfg)
    if cand.n < max(cfg.min_new_gaussians, 1):
        # the survivors of the visibility filter are a subset of the candidates: too few whatever the map covers,
        # so the coverage render (most of a seeding's time) is not needed. Most batches of marginalised points are
        # this small (7-Scenes at 320x240: 317 of 525, 16.7 of the 29.1 s of their seeding; docs/seeding.md)
        plan = plan_seeds(msg, cfg, None, None, sh_degree=gmap.sh_degree, candidates=cand)
        return _replace(plan.result, num_rejected_visibility=0, num_survivors=0, coverage_rendered=False,
                        seconds=time.perf_counter() - t0)
    alpha, depth, neighbours = map_seen_from(gmap, rasterizer, msg, cfg)
    plan = plan_seeds(msg, cfg, alpha, neighbours, sh_degree=gmap.sh_degree, depth=depth, candidates=cand)
    res = _replace(plan.result, coverage_rendered=alpha is not None)     # None: an empty map, nothing rendered
    g = plan.gaussians
    if g.n == 0:
        return _replace(res, seconds=time.perf_counter() - t0)
    room = gmap.capacity - gmap.n       # > 0: a full map returned above
    dropped = 0
    if room < g.n:
        sel = np.linspace(0, g.n - 1, room).round().astype(np.int64)
        dropped = g.n - room
        g = GaussianArrays(g.means[sel], g.log_scales[sel], g.quats[sel], g.opacity_logits[sel], g.sh[sel])
        log.warning("seeding keyframe %s: room for %d of %d seeds (mapping.capacity)", msg.keyframe_id, room,
                    room + dropped)
    gmap.add(g.means, g.log_scales, g.quats, g.opacity_logits, g.sh, step=step, anchor=_anchor(msg))
    return _replace(res, num_added=g.n, num_dropped_capacity=dropped, seconds=time.perf_counter() - t0)


def _anchor(msg: KeyframeSeedInput) -> int:
    """The keyframe new Gaussians are anchored to (loop closure moves them with it; -1: none)."""
    return -1 if msg.keyframe_id is None else int(msg.keyframe_id)


def _replace(res: SeedResult, **changes) -> SeedResult:
    return dataclasses.replace(res, **changes)


# ------------------------------------------------------------------------------------ random comparison
