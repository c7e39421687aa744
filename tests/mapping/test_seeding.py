"""MGSO's seeding (mgso.mapping.seeding): back-projection, Delaunay fill, visibility filter, new Gaussians."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mgso import synthetic
from mgso.camera import PinholeCamera
from mgso.config import Config, ConfigError, MappingConfig, SeedingConfig, apply_overrides
from mgso.mapping import seeding as sd
from mgso.mapping.gaussian_map import SH_C0, GaussianMap


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def seq():
    """A small synthetic sequence with exact poses and z-depth (docs/synthetic.md)."""
    return synthetic.make_sequence(seed=0, num_frames=2, width=160, height=120)


@pytest.fixture(scope="module")
def cam(seq):
    k = seq.intrinsics
    return PinholeCamera(k.fx, k.fy, k.cx, k.cy, k.width, k.height)


def _grid_points(cam, step=8, margin=3):
    u, v = np.meshgrid(np.arange(margin, cam.width - margin, step), np.arange(margin, cam.height - margin, step))
    return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)


def _message(seq, cam, uv, frame=0, **kw):
    ui = np.round(uv).astype(int)
    z = seq.depths[frame][ui[:, 1], ui[:, 0]].astype(np.float64)
    return sd.KeyframeSeedInput(seq.images[frame], cam, seq.cam_to_world[frame], uv, 1.0 / z, keyframe_id=frame,
                                **kw)


def _depth_of(points, cam_to_world):
    T = np.asarray(cam_to_world)
    return (points - T[:3, 3]) @ T[:3, :3][:, 2]


def _project(points, cam, cam_to_world):
    T = np.asarray(cam_to_world)
    pc = (points - T[:3, 3]) @ T[:3, :3]
    return np.stack([cam.fx * pc[:, 0] / pc[:, 2] + cam.cx, cam.fy * pc[:, 1] / pc[:, 2] + cam.cy], axis=1), pc[:, 2]


# --------------------------------------------------------------------------------------------- the message
def test_pattern_is_dsos():
    from mgso_kernels.photometric import PATTERN_NP

    np.testing.assert_array_equal(sd.PATTERN, PATTERN_NP)


def test_message_checks_its_arrays(seq, cam):
    uv = _grid_points(cam)
    idepth = np.ones(len(uv))
    T = seq.cam_to_world[0]
    with pytest.raises(ValueError, match="image"):
        sd.KeyframeSeedInput(seq.images[0][:, :10], cam, T, uv, idepth)
    with pytest.raises(ValueError, match="idepths"):
        sd.KeyframeSeedInput(seq.images[0], cam, T, uv, idepth[:-1])
    with pytest.raises(ValueError, match="points_uv"):
        sd.KeyframeSeedInput(seq.images[0], cam, T, uv[:, :1], idepth)
    sim3 = T.copy()
    sim3[:3, :3] *= 2.0
    with pytest.raises(ValueError, match="rigid"):
        sd.KeyframeSeedInput(seq.images[0], cam, sim3, uv, idepth)
    with pytest.raises(ValueError, match="kinds"):
        sd.KeyframeSeedInput(seq.images[0], cam, T, uv, idepth, kinds=np.full(len(uv), 7))
    with pytest.raises(TypeError, match="fx, fy"):
        sd.KeyframeSeedInput(seq.images[0], object(), T, uv, idepth)
    m = sd.KeyframeSeedInput(seq.images[0], seq.intrinsics, T, uv, idepth)   # duck-typed intrinsics
    assert isinstance(m.camera, PinholeCamera) and not m.points_uv.flags.writeable


def test_config_is_checked():
    with pytest.raises(ConfigError, match="mapping.seeding"):
        SeedingConfig(fill_depth="median")
    with pytest.raises(ConfigError, match="visibility_threshold"):
        SeedingConfig(visibility_threshold=0.0)
    assert MappingConfig().seeding.min_new_gaussians == 30   # MGSO's rule (issue 6)
    cfg = apply_overrides(Config(), ["mapping.seeding.fill_depth=mean", "mapping.seeding.alpha_downscale=1"])
    assert cfg.mapping.seeding.fill_depth == "mean" and cfg.mapping.seeding.alpha_downscale == 1
    with pytest.raises(ConfigError, match="knn"):
        apply_overrides(Config(), ["mapping.seeding.knn=0"])


# ---------------------------------------------------------------------------------------- back-projection
def test_backprojected_points_lie_on_the_true_surface_with_its_colour(seq, cam):
    """Points at true inverse depth, seen from the *other* frame: they project onto the true surface there."""
    uv = _grid_points(cam, step=5)
    msg = _message(seq, cam, uv)
    cand = sd.make_candidates(msg, SeedingConfig(fill=False))
    assert cand.n == len(uv) and cand.num_invalid == 0
    # 1) re-projected into the keyframe: the same pixel and the true depth there
    uv_k, z_k = _project(cand.means, cam, seq.cam_to_world[0])
    np.testing.assert_allclose(uv_k, uv, atol=1e-6)
    np.testing.assert_allclose(z_k, seq.depths[0][uv[:, 1].astype(int), uv[:, 0].astype(int)], rtol=1e-6)
    # 2) in the second frame the point lies on the surface the true depth map of that frame shows at its
    #    projection: inverse depth is affine in the image over a plane, so where the 3x3 neighbourhood is planar
    #    (no edge, no occlusion) bilinear interpolation of the true inverse depth is exact
    uv2, z2 = _project(cand.means, cam, seq.cam_to_world[1])
    inside = (uv2[:, 0] > 2) & (uv2[:, 0] < cam.width - 3) & (uv2[:, 1] > 2) & (uv2[:, 1] < cam.height - 3)
    inv = 1.0 / seq.depths[1].astype(np.float64)
    ui = np.round(uv2[inside]).astype(int)
    ddx = np.abs(inv[ui[:, 1], ui[:, 0] - 1] + inv[ui[:, 1], ui[:, 0] + 1] - 2 * inv[ui[:, 1], ui[:, 0]])
    ddy = np.abs(inv[ui[:, 1] - 1, ui[:, 0]] + inv[ui[:, 1] + 1, ui[:, 0]] - 2 * inv[ui[:, 1], ui[:, 0]])
    planar = np.maximum(ddx, ddy) < 1e-3 * inv[ui[:, 1], ui[:, 0]]
    assert inside.sum() > 0.8 * len(uv) and planar.sum() > 0.7 * inside.sum()
    zt = 1.0 / sd._bilinear(inv, uv2[inside, 0], uv2[inside, 1])
    rel = np.abs(z2[inside][planar] - zt[planar]) / zt[planar]
    assert np.median(rel) < 1e-4 and np.percentile(rel, 95) < 1e-3, (np.median(rel), np.percentile(rel, 95))
    # colour: the image's mean over DSO's 8-pixel pattern (integer offsets: exact pixel values)
    img = seq.images[0].astype(np.float64)
    ui = uv.astype(int)
    expect = np.mean([img[ui[:, 1] + dy, ui[:, 0] + dx] for dx, dy in sd.PATTERN.astype(int)], axis=0)
    np.testing.assert_allclose(cand.colors, expect, atol=1e-6)
    # and a given colour wins; an exposure (a, b) is removed: radiance = (I - b) / exp(a)
    given = np.tile([0.2, 0.4, 0.6], (len(uv), 1))
    c2 = sd.make_candidates(_message(seq, cam, uv, colors=given, exposure=(math.log(2.0), 0.1)),
                            SeedingConfig(fill=False)).colors
    np.testing.assert_allclose(c2, (given - 0.1) / 2.0, atol=1e-6)


def test_bad_points_are_dropped_and_kinds_filtered(seq, cam):
    uv = _grid_points(cam, step=10)
    msg0 = _message(seq, cam, uv)
    idepth = msg0.idepths.copy()
    idepth[:3] = [0.0, -1.0, np.nan]
    uv2 = uv.copy()
    uv2[3] = [-5.0, 10.0]
    kinds = np.full(len(uv), int(sd.PointKind.ACTIVE), np.int8)
    kinds[4:10] = sd.PointKind.IMMATURE
    kinds[10:12] = sd.PointKind.MARGINALIZED
    weights = np.ones(len(uv))
    weights[12] = 0.01
    msg = sd.KeyframeSeedInput(msg0.image, cam, msg0.cam_to_world, uv2, idepth, kinds=kinds, weights=weights)
    off = SeedingConfig(fill=False)
    assert sd.make_candidates(msg, off).num_invalid == 4
    assert sd.make_candidates(msg, dataclasses.replace(off, use_immature=False)).num_invalid == 4 + 6
    assert sd.make_candidates(msg, dataclasses.replace(off, min_point_weight=0.5)).num_invalid == 4 + 1


def test_points_drifted_to_zero_inverse_depth_are_dropped_before_the_fill(seq, cam):
    """DSO's active points whose inverse depth went to nearly zero (measured on 7-Scenes: 1e3-1e10 times the median
    depth) are not seeded, and do not spoil the triangles around them. Control: ``max_depth_factor=0`` seeds them."""
    uv = _grid_points(cam, step=20)            # triangles of 200 px^2: the fill fills them
    msg0 = _message(seq, cam, uv)
    idepth = msg0.idepths.copy()
    far = np.array([10, 20, 30])
    idepth[far] = [1e-9, 1e-4, 1.0 / (150.0 * np.median(1.0 / msg0.idepths))]
    idepth[5] = 1.0 / (50.0 * np.median(1.0 / msg0.idepths))      # far, but within the limit: kept
    msg = sd.KeyframeSeedInput(msg0.image, cam, msg0.cam_to_world, uv, idepth)
    cfg = SeedingConfig()
    c = sd.make_candidates(msg, cfg)
    assert c.num_too_far == 3 and c.num_invalid == 0 and c.num_points == len(uv) - 3
    assert c.depth.max() < 51.0 * np.median(1.0 / msg0.idepths)
    plan = sd.plan_seeds(msg, cfg)
    assert plan.result.num_too_far == 3 and plan.gaussians.n == c.n
    ctrl = sd.make_candidates(msg, dataclasses.replace(cfg, max_depth_factor=0.0))
    assert ctrl.num_too_far == 0 and ctrl.depth.max() == pytest.approx(1e9)
    # the far vertices' triangles straddle a depth jump: the fill skips them with the points in, fills them without
    assert ctrl.fill.num_rejected_discontinuity > c.fill.num_rejected_discontinuity
    assert c.fill.n > ctrl.fill.n


# ------------------------------------------------------------------------------------------ Delaunay fill
def _plane_points(normal, d, cam, uv):
    """Camera-frame z of the plane n . X = d seen at pixels uv: 1/z = n . K^-1 [u, v, 1] / d (affine in u, v)."""
    rays = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, np.ones(len(uv))], axis=1)
    return d / (rays @ np.asarray(normal))


def test_fill_fills_large_triangles_and_skips_small_ones(cam):
    # two clusters of dense points (small triangles) and one big empty triangle between them
    rng = np.random.default_rng(0)
    dense = np.concatenate([rng.uniform([5, 5], [40, 40], (60, 2)), rng.uniform([110, 70], [150, 110], (60, 2))])
    cfg = SeedingConfig(fill_min_triangle_area_px=200.0, fill_area_per_point_px=1e9)   # centroids only
    z = np.full(len(dense), 2.0)
    f = sd.delaunay_fill(dense, z, cfg)
    tri = np.array([[5.0, 115.0], [155.0, 5.0], [155.0, 115.0]])
    f2 = sd.delaunay_fill(np.concatenate([dense, tri]), np.full(len(dense) + 3, 2.0), cfg)
    assert f.num_triangles > 100 and f2.num_large > f.num_large
    # every filled triangle is large, every large one (flat depth) is filled, with exactly its centroid
    from scipy.spatial import Delaunay

    d = Delaunay(np.concatenate([dense, tri]))
    P = d.points[d.simplices]
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert f2.num_large == int((area > 200).sum()) == f2.num_filled == f2.n
    np.testing.assert_allclose(f2.uv, P[f2.triangle].mean(axis=1))
    assert np.all(area[f2.triangle] > 200)
    assert f2.n < 0.2 * f2.num_triangles        # the small triangles of the clusters get nothing


def test_fill_spreads_points_over_very_large_triangles():
    uv = np.array([[0.0, 0.0], [120.0, 0.0], [0.0, 90.0]])
    area = 0.5 * 120 * 90
    cfg = SeedingConfig(fill_min_triangle_area_px=100.0, fill_area_per_point_px=area / 9.0)   # k = 3
    f = sd.delaunay_fill(uv, np.full(3, 2.0), cfg)
    assert f.n == 9
    # the k^2 sub-triangle centroids: inside, mean = the centroid, pairwise well apart
    np.testing.assert_allclose(f.uv.mean(axis=0), uv.mean(axis=0), atol=1e-9)
    assert np.all(f.uv[:, 0] > 0) and np.all(f.uv[:, 1] > 0) and np.all(f.uv[:, 0] / 120 + f.uv[:, 1] / 90 < 1)
    dist = np.linalg.norm(f.uv[:, None] - f.uv[None], axis=2) + np.eye(9) * 1e9
    assert dist.min() > 0.5 * math.sqrt(area / 9)
    capped = sd.delaunay_fill(uv, np.full(3, 2.0), dataclasses.replace(cfg, fill_max_subdivisions=2))
    assert capped.n == 4


def test_fill_skips_triangles_across_a_depth_discontinuity():
    # left half of the vertices on a wall at 2 m, right half on one at 4 m: triangles joining them straddle the edge
    u, v = np.meshgrid(np.linspace(0, 150, 6), np.linspace(0, 110, 5))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    z = np.where(uv[:, 0] < 75, 2.0, 4.0)
    cfg = SeedingConfig(fill_min_triangle_area_px=50.0, fill_max_depth_ratio=1.3)
    f = sd.delaunay_fill(uv, z, cfg)
    assert f.num_rejected_discontinuity > 0 and f.num_filled > 0
    assert f.num_filled + f.num_rejected_discontinuity == f.num_large
    assert np.all(np.isin(f.depth, [2.0, 4.0]))           # no fill point between the two walls
    loose = sd.delaunay_fill(uv, z, dataclasses.replace(cfg, fill_max_depth_ratio=3.0))
    assert loose.num_rejected_discontinuity == 0 and np.any((loose.depth > 2.01) & (loose.depth < 3.99))


@pytest.mark.parametrize("mode", ["mean", "barycentric"])
def test_fill_depth_on_a_plane(cam, mode):
    """A slanted plane (a floor seen obliquely): barycentric inverse depth is exact, the mean is close."""
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (40, 2))
    normal = np.array([0.0, -0.6, -0.8])
    normal /= np.linalg.norm(normal)
    z = _plane_points(normal, -3.0, cam, uv)
    assert np.all(z > 0) and z.max() / z.min() > 1.5
    cfg = SeedingConfig(fill_min_triangle_area_px=60.0, fill_depth=mode, fill_max_depth_ratio=10.0,
                        fill_area_per_point_px=300.0)
    f = sd.delaunay_fill(uv, z, cfg)
    assert f.n > 20
    truth = _plane_points(normal, -3.0, cam, f.uv)
    rel = np.abs(f.depth - truth) / truth
    if mode == "barycentric":
        assert rel.max() < 1e-9
    else:
        assert rel.max() < 0.15 and np.median(rel) < 0.05 and rel.max() > 1e-4   # close, but not exact


def test_fill_depth_on_the_synthetic_scene(seq, cam):
    """Fill points from true vertex depths on the synthetic room: within a few percent of the true depth."""
    uv = _grid_points(cam, step=12)
    for mode in ("mean", "barycentric"):
        cfg = SeedingConfig(fill_depth=mode, fill_min_triangle_area_px=50.0, fill_max_depth_ratio=1.3)
        cand = sd.make_candidates(_message(seq, cam, uv), cfg)
        f = cand.fill
        assert f.n > 100 and cand.n == len(uv) + f.n
        ui = np.round(f.uv).astype(int)
        truth = seq.depths[0][ui[:, 1], ui[:, 0]]
        rel = np.abs(f.depth - truth) / truth
        assert np.median(rel) < 0.02 and np.mean(rel > 0.2) < 0.03, (mode, np.median(rel), np.mean(rel > 0.2))
        assert np.all(cand.kinds[len(uv):] == sd.PointKind.FILL)


def test_fill_degenerate_inputs():
    cfg = SeedingConfig()
    assert sd.delaunay_fill(np.zeros((2, 2)), np.ones(2), cfg).n == 0
    line = np.stack([np.arange(10.0), np.arange(10.0)], axis=1)
    assert sd.delaunay_fill(line, np.ones(10), cfg).num_triangles == 0


# ------------------------------------------------------------------------------------------- new Gaussians
def test_new_gaussians_scale_opacity_rotation_colour():
    rng = np.random.default_rng(2)
    means = rng.uniform(-1, 1, (50, 3)) + [0, 0, 5]
    depth = means[:, 2]
    cfg = SeedingConfig(scale_min_px=1e-6, scale_max_px=1e6)
    s = sd.seed_scales(means, depth, 100.0, cfg)
    # brute force: mean distance to the 3 nearest other points
    dist = np.linalg.norm(means[:, None] - means[None], axis=2)
    np.fill_diagonal(dist, np.inf)
    np.testing.assert_allclose(s, np.sort(dist, axis=1)[:, :3].mean(axis=1), rtol=1e-12)
    # neighbours from the map count too
    extra = means[:5] + 1e-3
    s2 = sd.seed_scales(means, depth, 100.0, cfg, extra)
    allp = np.concatenate([means, extra])
    d2 = np.linalg.norm(means[:, None] - allp[None], axis=2)
    d2[np.arange(50), np.arange(50)] = np.inf
    np.testing.assert_allclose(s2, np.sort(d2, axis=1)[:, :3].mean(axis=1), rtol=1e-12)
    # clamped to the pixel footprint depth / f
    tight = sd.seed_scales(means, depth, 100.0, SeedingConfig(scale_min_px=0.5, scale_max_px=2.0))
    assert np.all(tight <= 2.0 * depth / 100 + 1e-12) and np.all(tight >= 0.5 * depth / 100 - 1e-12)
    assert np.any(np.isclose(tight, 2.0 * depth / 100))
    # the parameter arrays
    colors = rng.uniform(0, 1, (50, 3))
    g = sd.gaussians_from_seeds(means, colors, s, SeedingConfig(), sh_degree=1)
    act = g.activated()
    np.testing.assert_allclose(act.opacities, 0.1, rtol=1e-6)
    np.testing.assert_allclose(g.quats, np.tile([1, 0, 0, 0], (50, 1)))
    np.testing.assert_allclose(act.scales, np.repeat(s[:, None], 3, axis=1), rtol=1e-5)
    np.testing.assert_allclose(0.5 + SH_C0 * g.sh[:, 0], colors, atol=1e-6)
    assert g.sh.shape == (50, 4, 3) and np.all(g.sh[:, 1:] == 0)


# --------------------------------------------------------------------------------------- visibility filter
def test_sample_alpha_at_full_and_half_resolution():
    W, H = 9, 6
    full = np.zeros((H, W))
    full[:, 4:] = 1.0
    uv = np.array([[0.0, 0.0], [8.0, 5.0], [3.0, 2.0], [4.0, 2.0]])
    np.testing.assert_allclose(sd.sample_alpha(full, uv, W, H), [0, 1, 0, 1])
    half = np.zeros((3, 4))
    half[:, 2:] = 1.0                      # low-res columns 2, 3 = full-res columns 4..7
    np.testing.assert_allclose(sd.sample_alpha(half, np.array([[1.0, 1.0], [6.0, 1.0], [3.5, 1.0]]), W, H),
                               [0.0, 1.0, 0.5])
    with pytest.raises(ValueError, match="downscale"):
        sd.sample_alpha(np.zeros((4, 4)), uv, W, H)


def test_visibility_filter_in_the_array_part(seq, cam):
    uv = _grid_points(cam, step=6)
    msg = _message(seq, cam, uv)
    cfg = SeedingConfig(fill=False)
    empty = sd.plan_seeds(msg, cfg)
    assert empty.result.status is sd.SeedStatus.ADDED and empty.gaussians.n == len(uv)
    alpha = np.zeros((cam.height, cam.width))
    alpha[:, : cam.width // 2] = 0.9                     # the left half is covered
    half = sd.plan_seeds(msg, cfg, alpha=alpha)
    left = uv[:, 0] < cam.width // 2
    assert half.result.num_rejected_visibility == left.sum() and half.gaussians.n == (~left).sum()
    uv_new, _ = _project(half.gaussians.means.astype(np.float64), cam, seq.cam_to_world[0])
    assert np.all(uv_new[:, 0] > cam.width // 2 - 1)
    full = sd.plan_seeds(msg, cfg, alpha=np.full((cam.height // 2, cam.width // 2), 0.9))
    assert full.gaussians.n == 0 and full.result.num_rejected_visibility == len(uv)


def test_fewer_than_min_survivors_adds_nothing(seq, cam):
    uv = _grid_points(cam, step=6)
    msg = _message(seq, cam, uv)
    cfg = SeedingConfig(fill=False)
    alpha = np.ones((cam.height, cam.width))
    alpha[:, :8] = 0.0                                    # only the points in 8 columns are in empty space
    few = (uv[:, 0] < 8).sum()
    assert 0 < few < 30
    plan = sd.plan_seeds(msg, cfg, alpha=alpha)
    assert plan.result.status is sd.SeedStatus.TOO_FEW and plan.result.skipped_too_few
    assert plan.gaussians.n == 0 and plan.result.num_survivors == few and plan.result.num_added == 0
    # with the rule relaxed below the survivors they are added: the 30 is what stopped them
    relaxed = sd.plan_seeds(msg, dataclasses.replace(cfg, min_new_gaussians=few), alpha=alpha)
    assert relaxed.gaussians.n == few


# ------------------------------------------------------------------------------------------- with the map
@pytest.fixture(scope="module")
def rast(wp_device):
    from mgso_kernels.splat import Rasterizer

    return Rasterizer(wp_device)


def _covering_map(seq, cam, device, frame=0, stride=2, cols=None):
    """Opaque Gaussians on the true surface at every ``stride``-th pixel (optionally only columns < cols)."""
    pts, colors = synthetic.depth_to_points(seq.depths[frame], seq.intrinsics, seq.cam_to_world[frame],
                                            seq.images[frame], stride=stride)
    if cols is not None:
        uv, _ = _project(pts, cam, seq.cam_to_world[frame])
        keep = uv[:, 0] < cols
        pts, colors = pts[keep], colors[keep]
    z = _depth_of(pts, seq.cam_to_world[frame])
    n = len(pts)
    gm = GaussianMap(n + 20_000, 0, device)
    logit = math.log(0.95 / 0.05)
    gm.add(pts, np.log(1.5 * stride * z / cam.fx)[:, None].repeat(3, 1), np.tile([1.0, 0, 0, 0], (n, 1)),
           np.full(n, logit), ((colors - 0.5) / SH_C0).astype(np.float32))
    return gm


def test_seed_keyframe_adds_nothing_where_the_map_covers_the_view(seq, cam, rast, wp_device):
    uv = _grid_points(cam, step=4)
    msg = _message(seq, cam, uv, frame=1)
    cfg = SeedingConfig(depth_tolerance=0.0)            # the alpha rule alone (the depth rule: its own test)
    # an empty map: every candidate is added
    empty = GaussianMap(20_000, 0, wp_device)
    r0 = sd.seed_keyframe(empty, rast, msg, cfg, step=7)
    assert r0.status is sd.SeedStatus.ADDED and r0.num_added == r0.num_candidates == empty.n > 500
    assert r0.num_rejected_visibility == 0 and np.all(empty.created_step.numpy() == 7)
    assert not r0.coverage_rendered                     # nothing to render (MapperStats.coverage_renders counts it)
    # a map covering the whole view (placed on the true surface of frame 0, seen from the nearby frame 1)
    cov = sd.render_coverage(_covering_map(seq, cam, wp_device), rast, cam, msg.world_to_cam, 2)
    assert np.mean(cov.alpha > 0.5) > 0.97
    gm = _covering_map(seq, cam, wp_device)
    n0 = gm.n
    r1 = sd.seed_keyframe(gm, rast, msg, cfg, step=8)
    assert gm.n == n0 and r1.num_added == 0 and r1.status is sd.SeedStatus.TOO_FEW and r1.coverage_rendered
    assert r1.num_rejected_visibility >= r1.num_candidates - 30
    # bypassing the filter (threshold 1: nothing is ever covered enough) would add them all
    r_bypass = sd.seed_keyframe(gm, rast, msg, dataclasses.replace(cfg, visibility_threshold=1.0), step=8)
    assert r_bypass.num_added == r_bypass.num_candidates > 500


class _CountingRasterizer:
    """The rasterizer, counting its coverage renders."""

    def __init__(self, rast):
        self.rast = rast
        self.renders = 0

    def render_alpha(self, *a, **k):
        self.renders += 1
        return self.rast.render_alpha(*a, **k)

    def forward(self, *a, **k):
        self.renders += 1
        return self.rast.forward(*a, **k)


def test_a_batch_smaller_than_the_minimum_is_skipped_without_rendering(seq, cam, rast, wp_device):
    """Fewer candidates than ``min_new_gaussians`` can never leave enough survivors: the seeding says too few without
    the coverage render (most batches of marginalised points are that small, and the render was most of their
    seeding's time). Negative control: a batch of the minimum's size is rendered, and so is this one with a lower
    minimum, whose visibility filter then has something to say."""
    gm = _covering_map(seq, cam, wp_device, cols=cam.width // 2)          # the right half is empty
    n0 = gm.n
    uv = _grid_points(cam, step=8)
    right = uv[uv[:, 0] > cam.width // 2 + 8]
    # seeds up to 20 px wide: the 30 added below cover some of the 29 offered again (the default's 8 px do not)
    cfg = SeedingConfig(fill=False, depth_tolerance=0.0, min_new_gaussians=30, scale_max_px=20.0)
    counting = _CountingRasterizer(rast)
    small = _message(seq, cam, right[:29], frame=0)
    r = sd.seed_keyframe(gm, counting, small, cfg, step=1)
    assert counting.renders == 0 and r.status is sd.SeedStatus.TOO_FEW and r.num_candidates == 29
    assert not r.coverage_rendered and r.num_added == 0 and gm.n == n0
    r30 = sd.seed_keyframe(gm, counting, _message(seq, cam, right[:30], frame=0), cfg, step=1)
    assert counting.renders == 1 and r30.coverage_rendered and r30.status is sd.SeedStatus.ADDED
    n1 = gm.n
    r_low = sd.seed_keyframe(gm, counting, small, dataclasses.replace(cfg, min_new_gaussians=10), step=2)
    assert counting.renders == 2 and r_low.coverage_rendered and r_low.num_candidates == 29
    assert r_low.num_rejected_visibility > 0                              # the 30 just added cover some (6)
    assert gm.n - n1 == r_low.num_added


def test_seed_keyframe_fills_only_the_uncovered_part(seq, cam, rast, wp_device):
    uv = _grid_points(cam, step=4)
    msg = _message(seq, cam, uv, frame=0)
    gm = _covering_map(seq, cam, wp_device, cols=cam.width // 2)      # the left half is mapped
    n0 = gm.n
    r = sd.seed_keyframe(gm, rast, msg, SeedingConfig(depth_tolerance=0.0), step=3)   # the alpha rule alone
    assert r.status is sd.SeedStatus.ADDED and r.num_added == gm.n - n0 > 200
    assert r.num_rejected_visibility > 0.35 * r.num_candidates
    new_means = gm.means.numpy()[n0:].astype(np.float64)
    uv_new, _ = _project(new_means, cam, seq.cam_to_world[0])
    assert np.all(uv_new[:, 0] > cam.width // 2 - 6)    # nothing under the covered half (blur of its edge aside)
    act = gm.activated()
    np.testing.assert_allclose(act.opacities[n0:], 0.1, rtol=1e-5)
    np.testing.assert_allclose(act.quats[n0:], np.tile([1.0, 0, 0, 0], (gm.n - n0, 1)), atol=1e-7)


def test_seed_keyframe_respects_the_capacity(seq, cam, rast, wp_device):
    uv = _grid_points(cam, step=4)
    msg = _message(seq, cam, uv)
    gm = GaussianMap(300, 0, wp_device)
    r = sd.seed_keyframe(gm, rast, msg, SeedingConfig(fill=False), step=0)
    assert gm.n == 300 and r.num_added == 300 and r.num_dropped_capacity == len(uv) - 300
    r2 = sd.seed_keyframe(gm, rast, _message(seq, cam, uv, frame=1), SeedingConfig(visibility_threshold=1.0), 1)
    assert r2.status is sd.SeedStatus.MAP_FULL and gm.n == 300
    # a full map is not rendered (nothing could be added): every point offered counts as dropped
    assert not r2.coverage_rendered and r2.num_dropped_capacity == r2.num_points_in == len(uv)
    # the control: a map with Gaussians and room renders its coverage (the first seeding's empty map had nothing to
    # render)
    assert not r.coverage_rendered
    roomy = GaussianMap(2 * len(uv), 0, wp_device)
    sd.seed_keyframe(roomy, rast, msg, SeedingConfig(fill=False), step=0)
    r3 = sd.seed_keyframe(roomy, rast, _message(seq, cam, uv, frame=1), SeedingConfig(visibility_threshold=1.0), 1)
    assert r3.coverage_rendered and r3.status is sd.SeedStatus.ADDED


def test_disabled_seeding_adds_nothing(seq, cam, rast, wp_device):
    gm = GaussianMap(100, 0, wp_device)
    r = sd.seed_keyframe(gm, rast, _message(seq, cam, _grid_points(cam)), SeedingConfig(enabled=False), 0)
    assert r.status is sd.SeedStatus.DISABLED and gm.n == 0 and not r.coverage_rendered


def test_depth_tolerance_seeds_where_the_covering_map_has_the_wrong_depth(seq, cam, rast, wp_device):
    """A map that covers the view but whose surface sits 30 % behind the true one (every Gaussian pushed along its
    camera ray of frame 0) hides the keyframe's points from the alpha test; ``depth_tolerance`` keeps the points
    whose depth the map misses. Measured: 1131 candidates, all kept with the surface 30 % off, 180 (on depth
    edges, where the half-resolution render blends two depths) with the right surface; 0 with the alpha test
    alone (the negative controls)."""
    uv = _grid_points(cam, step=4)
    msg = _message(seq, cam, uv, frame=0)
    c = seq.cam_to_world[0][:3, 3]
    for push, tol, expect_added in ((1.3, 0.1, True), (1.0, 0.1, False), (1.3, 0.0, False)):
        gm = _covering_map(seq, cam, wp_device)
        m = gm.means.numpy().astype(np.float64)
        gm.means.assign((c + push * (m - c)).astype(np.float32))
        n0 = gm.n
        # the rule itself, even where every point disagrees (depth_rule_max_median: the next test)
        r = sd.seed_keyframe(gm, rast, msg, SeedingConfig(depth_tolerance=tol, depth_rule_max_median=0), step=3)
        if expect_added:
            assert r.status is sd.SeedStatus.ADDED and r.num_added > 0.8 * r.num_candidates, (push, tol, r)
            z_new = _depth_of(gm.means.numpy()[n0:].astype(np.float64), seq.cam_to_world[0])
            uv_new, _ = _project(gm.means.numpy()[n0:].astype(np.float64), cam, seq.cam_to_world[0])
            assert np.all(z_new < 1.15 * _depth_of(gm.means.numpy()[:n0].astype(np.float64),
                                                    seq.cam_to_world[0]).max())
        elif tol > 0:       # a right surface: only points on depth edges, where the render blends two depths
            assert r.num_added < 0.25 * r.num_candidates, (push, tol, r)
        else:
            assert r.num_added == 0 and r.num_rejected_visibility >= r.num_candidates - 30, (push, tol, r)
    with pytest.raises(ConfigError, match="depth_tolerance"):
        SeedingConfig(depth_tolerance=-0.1)


def test_the_depth_rule_stands_down_where_most_depths_disagree(seq, cam, rast, wp_device):
    """``depth_rule_max_median``: the covering map of the test above with the surface 30 % behind the true one over
    the whole view (every point disagrees: the odometry's depths against a map they do not fit, a handheld camera's
    case) or over its left quarter only (a surface the map lacks there). With the whole view off, the median error
    of the covered candidates is above 0.25, the depth rule stands down and the alpha rule alone adds nothing; the
    control, the rule always on (0), seeds nearly every candidate again. With a quarter off the median is small, the
    rule runs and seeds where the map misses: on the left."""
    uv = _grid_points(cam, step=4)
    msg = _message(seq, cam, uv, frame=0)
    c = seq.cam_to_world[0][:3, 3]
    res = {}
    for part, max_median in ((1.0, 0.25), (1.0, 0.0), (0.25, 0.25)):
        gm = _covering_map(seq, cam, wp_device)
        m = gm.means.numpy().astype(np.float64)
        left = _project(m, cam, seq.cam_to_world[0])[0][:, 0] < part * cam.width
        m[left] = c + 1.3 * (m[left] - c)
        gm.means.assign(m.astype(np.float32))
        n0 = gm.n
        cfg = SeedingConfig(depth_tolerance=0.1, depth_rule_max_median=max_median)
        r = sd.seed_keyframe(gm, rast, msg, cfg, step=3)
        res[part, max_median] = (r, _project(gm.means.numpy()[n0:].astype(np.float64), cam, seq.cam_to_world[0])[0])
    r, _ = res[1.0, 0.25]
    assert r.depth_error_median > 0.25 and r.depth_tolerance_used == math.inf and r.num_added == 0, r
    r, _ = res[1.0, 0.0]
    assert r.depth_error_median is None and r.num_added > 0.8 * r.num_candidates, r
    r, uv_new = res[0.25, 0.25]
    assert r.depth_error_median < 0.1 and r.depth_tolerance_used == 0.1, r
    assert 0.1 * r.num_candidates < r.num_added < 0.5 * r.num_candidates, r
    assert np.mean(uv_new[:, 0] < 0.3 * cam.width) > 0.55, r     # 0.69 measured; the rest on depth edges
