"""The Gaussian map keeps parameters, Adam moments, statistics and ages consistent through every operation."""

import math

import numpy as np
import pytest
import warp as wp

from mgso.config import OptimConfig
from mgso.mapping.gaussian_map import (SH_C0, GaussianArrays, GaussianMap, MapFullError, means_learning_rate,
                                       quat_wxyz_to_rotmat, scene_extent_from_cameras, spatial_order)


def _arrays(rng, n, k=1, first_id=0):
    means = rng.standard_normal((n, 3)).astype(np.float32)
    means[:, 0] = np.arange(first_id, first_id + n)          # row identity, to follow rows around
    return GaussianArrays(means=means, log_scales=rng.uniform(-4, -1, (n, 3)),
                          quats=rng.standard_normal((n, 4)), opacity_logits=rng.standard_normal(n),
                          sh=rng.standard_normal((n, k, 3)))


def _fill_state(gm, rng):
    """Give every non-parameter buffer distinct non-zero values, so moves and resets are visible."""
    for name, buf, kind in gm._all_buffers():
        if kind == "param":
            continue
        live = buf[: gm.n]
        vals = live.numpy()
        if np.issubdtype(vals.dtype, np.integer):
            new = rng.integers(1, 1000, vals.shape).astype(vals.dtype)
        else:
            new = rng.uniform(0.1, 1.0, vals.shape).astype(vals.dtype)
        live.assign(new)


def _row_ids(state):
    return state["params.means"][:, 0].astype(int)


@pytest.fixture
def gmap(wp_device, rng):
    gm = GaussianMap(capacity=64, sh_degree=1, device=wp_device)
    gm.add(*(getattr(_arrays(rng, 20, 4), f) for f in ("means", "log_scales", "quats", "opacity_logits", "sh")),
           step=7)
    _fill_state(gm, rng)
    return gm


def test_add_roundtrip_and_fresh_state(wp_device, rng):
    gm = GaussianMap(capacity=10, sh_degree=0, device=wp_device)
    a = _arrays(rng, 6)
    idx = gm.add(a.means, a.log_scales, a.quats, a.opacity_logits, a.sh[:, 0], step=3)   # DC-only sh (M, 3)
    assert list(idx) == list(range(6)) and gm.n == 6
    b = gm.to_numpy()
    for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert np.array_equal(getattr(b, f), getattr(a, f)), f
    st = gm.state_numpy()
    assert all(len(v) == 6 for v in st.values())
    assert not np.any(st["exp_avg.means"]) and not np.any(st["adam_steps"]) and not np.any(st["stats.vis_count"])
    assert np.all(st["created_step"] == 3)
    with pytest.raises(MapFullError, match="reserve"):
        gm.add(a.means, a.log_scales, a.quats, a.opacity_logits, a.sh)
    with pytest.raises(ValueError, match="non-finite"):
        bad = a.means.copy()
        bad[0, 1] = np.nan
        gm.add(bad[:1], a.log_scales[:1], a.quats[:1], a.opacity_logits[:1], a.sh[:1])
    with pytest.raises(ValueError, match="sh must be"):
        gm.add(a.means[:1], a.log_scales[:1], a.quats[:1], a.opacity_logits[:1], np.zeros((1, 4, 3)))
    assert gm.n == 6


def test_remove_compacts_every_buffer_in_order(gmap):
    before = gmap.state_numpy()
    mask = np.zeros(gmap.n, bool)
    mask[[0, 3, 4, 19]] = True
    assert gmap.remove(mask) == 4
    after = gmap.state_numpy()
    keep = np.flatnonzero(~mask)
    for name in before:
        assert len(after[name]) == 16, name
        np.testing.assert_array_equal(after[name], before[name][keep], err_msg=name)
    assert list(_row_ids(after)) == [i for i in range(20) if i not in (0, 3, 4, 19)]
    assert not np.any(gmap.grads.means.numpy())


def test_sort_spatially_moves_every_buffer_with_its_row_into_z_order(wp_device, rng):
    """sort_spatially permutes the rows into the Z-order of their means, every buffer (parameters, moments, step
    counts, statistics, ages, anchors) with its row, and a second call changes nothing. Runs of 16 rows are then small
    boxes of space: on points scattered over a room, the bounding box of 16 consecutive rows has a quarter of the
    diagonal it has in their order of creation (the control: the same rows before sorting)."""
    n = 2000
    gm = GaussianMap(capacity=n, sh_degree=0, device=wp_device)
    a = _arrays(rng, n)
    pts = rng.uniform([-3, -1.5, 0], [3, 1.5, 6], (n, 3)).astype(np.float32)
    a = GaussianArrays(pts, a.log_scales, a.quats, a.opacity_logits, a.sh)
    gm.add(a.means, a.log_scales, a.quats, a.opacity_logits, a.sh, step=4, anchor=rng.integers(0, 9, n))
    _fill_state(gm, rng)
    before = gm.state_numpy()

    def run_extent(means):      # median over runs of 16 rows of the diagonal of their bounding box
        r = means[: n // 16 * 16].reshape(-1, 16, 3)
        return float(np.median(np.linalg.norm(r.max(1) - r.min(1), axis=1)))

    assert gm.sort_spatially()
    after = gm.state_numpy()
    order = spatial_order(before["params.means"])
    assert sorted(order) == list(range(n))
    for name in before:
        np.testing.assert_array_equal(after[name], before[name][order], err_msg=name)
    assert run_extent(after["params.means"]) < 0.4 * run_extent(before["params.means"])    # 0.26 measured
    assert not gm.sort_spatially()                                  # already in order
    np.testing.assert_array_equal(gm.state_numpy()["params.means"], after["params.means"])
    # non-finite and outlying points still get a place (clamped to the box)
    odd = pts[:5].astype(np.float64).copy()
    odd[0] = np.nan
    odd[1] = 1e30
    assert sorted(spatial_order(odd)) == list(range(5))


def test_clone_appends_copies_with_fresh_optimiser_state(gmap):
    before = gmap.state_numpy()
    mask = np.zeros(gmap.n, bool)
    mask[[2, 5, 11]] = True
    assert gmap.clone(mask, step=100) == 3
    after = gmap.state_numpy()
    for name in before:
        assert len(after[name]) == 23, name
        np.testing.assert_array_equal(after[name][:20], before[name], err_msg=name)   # originals untouched
        new = after[name][20:]
        if name.startswith("params.") or name == "anchor":                           # anchors: the parent's
            np.testing.assert_array_equal(new, before[name][[2, 5, 11]], err_msg=name)
        elif name == "created_step":
            assert np.all(new == 100)
        else:
            assert not np.any(new), name                                               # moments, stats, ages zero


def test_split_follows_the_3dgs_rule(gmap):
    before = gmap.state_numpy()
    mask = np.zeros(gmap.n, bool)
    sel = [1, 6, 7]
    mask[sel] = True
    rng_a = np.random.default_rng(5)
    assert gmap.split(mask, children=2, step=200, rng=rng_a) == 3
    after = gmap.state_numpy()
    keep = np.flatnonzero(~mask)
    assert len(after["params.means"]) == 17 + 6
    for name in before:
        np.testing.assert_array_equal(after[name][:17], before[name][keep], err_msg=name)   # survivors first, in order
    parents = np.tile(sel, 2)                                                                # all first children, then
    for f in ("quats", "opacity_logits", "sh"):                                              # all second children
        np.testing.assert_array_equal(after[f"params.{f}"][17:], before[f"params.{f}"][parents])
    np.testing.assert_allclose(after["params.log_scales"][17:], before["params.log_scales"][parents] - math.log(1.6),
                               atol=1e-6)
    # means: parent + R (s * z) with z drawn from the same generator
    z = np.random.default_rng(5).standard_normal((2, 3, 3))
    R = quat_wxyz_to_rotmat(before["params.quats"][sel])
    s = np.exp(before["params.log_scales"][sel].astype(np.float64))
    expect = (before["params.means"][sel][None] + np.einsum("nij,cnj->cni", R, s[None] * z)).reshape(-1, 3)
    np.testing.assert_allclose(after["params.means"][17:], expect, atol=1e-5)
    for name in before:
        if not name.startswith("params.") and name not in ("created_step", "anchor"):
            assert not np.any(after[name][17:]), name
    assert np.all(after["created_step"][17:] == 200)
    np.testing.assert_array_equal(after["anchor"][17:], before["anchor"][parents])     # children: the parent's


def test_reset_opacity_clamps_and_zeroes_only_opacity_moments(gmap):
    before = gmap.state_numpy()
    gmap.reset_opacity(0.01)
    after = gmap.state_numpy()
    cap = math.log(0.01 / 0.99)
    np.testing.assert_allclose(after["params.opacity_logits"],
                               np.minimum(before["params.opacity_logits"], cap), rtol=1e-6)
    assert not np.any(after["exp_avg.opacity_logits"]) and not np.any(after["exp_avg_sq.opacity_logits"])
    for name in before:
        if "opacity" not in name:
            np.testing.assert_array_equal(after[name], before[name], err_msg=name)


def test_full_map_raises_unchanged_and_reserve_grows_keeping_state(gmap):
    gmap.clone(np.ones(gmap.n, bool), step=1)          # 20 -> 40 of 64
    state = gmap.state_numpy()
    with pytest.raises(MapFullError, match="40 more rows, 40 of 64"):
        gmap.clone(np.ones(gmap.n, bool))
    with pytest.raises(MapFullError):
        gmap.split(np.ones(gmap.n, bool), children=2)
    assert gmap.n == 40
    for name, v in gmap.state_numpy().items():
        np.testing.assert_array_equal(v, state[name], err_msg=name)   # a refused change changes nothing
    gmap.reserve(1000)
    assert gmap.capacity == 1000 and gmap.n == 40
    for name, v in gmap.state_numpy().items():
        np.testing.assert_array_equal(v, state[name], err_msg=name)
    assert gmap.clone(np.ones(gmap.n, bool)) == 40
    with pytest.raises(ValueError, match="holds"):
        gmap.reserve(79)


def test_optimizer_step_uses_scheduled_extent_scaled_rates(wp_device, rng):
    cfg = OptimConfig(bias_correction="per_gaussian")
    a = _arrays(rng, 5)
    a.means = (a.means * 1e-3).astype(np.float32)   # small values: the float32 ulp stays far below the step
    for step, lr_expected in ((0, 1.6e-4), (15_000, 1.6e-5), (30_000, 1.6e-6), (90_000, 1.6e-6)):
        gm = GaussianMap.from_arrays(a, device=wp_device, optim=cfg, scene_extent=2.5)
        g = gm.grads
        g.means.assign(np.full((5, 3), 0.3, np.float32))
        g.opacity_logits.assign(np.full(5, -1.0, np.float32))
        rates = gm.optimizer_step(step)
        assert math.isclose(rates.means, 2.5 * lr_expected, rel_tol=1e-9)
        moved = a.means - gm.to_numpy().means
        # first Adam step of a fresh row moves lr * sign(g)
        np.testing.assert_allclose(moved, 2.5 * lr_expected, rtol=1e-3)
        np.testing.assert_allclose(gm.to_numpy().opacity_logits - a.opacity_logits, cfg.lr_opacity, rtol=1e-3)
        assert np.array_equal(gm.log_scales.numpy(), a.log_scales)   # zero gradient, fresh moments: no move
        assert np.all(gm.adam_steps.numpy() == 1)
    assert math.isclose(means_learning_rate(cfg, 7_500, 1.0), math.sqrt(1.6e-4 * math.sqrt(1.6e-4 * 1.6e-6)))


def test_sparse_optimizer_step_skips_invisible(wp_device, rng):
    a = _arrays(rng, 6)
    gm = GaussianMap.from_arrays(a, device=wp_device, optim=OptimConfig(sparse=True))
    gm.grads.means.assign(np.full((6, 3), 0.3, np.float32))
    vis = np.array([1, 0, 1, 0, 0, 1], np.uint8)
    gm.optimizer_step(0, visible=wp.array(vis, dtype=wp.uint8, device=wp_device))
    moved = np.any(gm.to_numpy().means != a.means, axis=1)
    assert np.array_equal(moved, vis.astype(bool))
    assert np.array_equal(gm.adam_steps.numpy(), vis.astype(np.int32))


def test_stats_accumulate_and_reset_keeps_age(wp_device, rng):
    gm = GaussianMap.from_arrays(_arrays(rng, 4), device=wp_device)
    v = np.array([[1e-6, 0], [0, 2e-6], [3e-6, 4e-6], [1, 1]], np.float32)
    radii = np.array([2.0, 5.0, 1.0, 0.0], np.float32)
    for _ in range(2):
        gm.accumulate_stats(wp.array(v, dtype=wp.vec2, device=wp_device), wp.array(radii, device=wp_device), 640, 480)
    st = gm.stats
    ndc = np.hypot(v[:, 0] * 320, v[:, 1] * 240)
    np.testing.assert_allclose(st.grad2d_sum.numpy(), 2 * ndc * (radii > 0), rtol=1e-6)
    assert list(st.vis_count.numpy()) == [2, 2, 2, 0] and list(st.max_radius_px.numpy()) == [2, 5, 1, 0]
    gm.reset_stats()
    assert not np.any(gm.stats.grad2d_sum.numpy()) and not np.any(gm.stats.vis_count.numpy())
    assert list(gm.stats.views_seen.numpy()) == [2, 2, 2, 0]


def test_activated_values(wp_device, rng):
    a = _arrays(rng, 5, k=4)
    act = GaussianMap.from_arrays(a, device=wp_device).activated()
    np.testing.assert_allclose(act.scales, np.exp(a.log_scales), rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(act.quats, axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(act.quats * np.sign(act.quats[:, :1]), a.quats / np.linalg.norm(a.quats, axis=1,
                               keepdims=True) * np.sign(a.quats[:, :1]), rtol=1e-5)
    np.testing.assert_allclose(act.opacities, 1 / (1 + np.exp(-a.opacity_logits)), rtol=1e-6)
    np.testing.assert_allclose(act.rgb, np.maximum(0, 0.5 + SH_C0 * a.sh[:, 0]), rtol=1e-6)


def test_scene_extent_is_the_3dgs_rule():
    c = np.array([[0, 0, 0], [2, 0, 0], [1, 1, 0]], float)
    centroid = c.mean(0)
    assert math.isclose(scene_extent_from_cameras(c), 1.1 * np.linalg.norm(c - centroid, axis=1).max())


def test_float_views_share_memory_and_int_radii(wp_device, rng):
    a = _arrays(rng, 5, k=4)
    gm = GaussianMap.from_arrays(a, device=wp_device)
    fp = gm.float_params()
    assert fp.means.shape == (5, 3) and fp.quats.shape == (5, 4) and fp.sh.shape == (5, 4, 3)
    assert fp.opacity_logits.shape == (5,)
    np.testing.assert_array_equal(fp.sh.numpy(), a.sh)
    fg = gm.float_grads()
    fg.quats.assign(np.ones((5, 4), np.float32))          # a rasteriser writing float rows ...
    assert np.all(gm.grads.quats.numpy() == 1.0)           # ... lands in the map's gradient buffers
    radii = wp.array(np.array([3, 0, 1, 0, 7], np.int32), device=wp_device)
    v = wp.array(np.ones((5, 2), np.float32), dtype=wp.vec2, device=wp_device)
    gm.accumulate_stats(v, radii, 8, 6)
    assert list(gm.stats.vis_count.numpy()) == [1, 0, 1, 0, 1]
    np.testing.assert_allclose(gm.stats.grad2d_sum.numpy()[0], 5.0)   # |(1 * 4, 1 * 3)|



def test_the_views_of_the_live_rows_are_kept_until_the_rows_or_buffers_change(gmap, rng):
    """The views a training step asks for (params, grads, moments, statistics, float views) are made once while the
    rows and buffers stay, and follow every change of either: the row count (clone, remove) and the buffers (reserve);
    each view always shows the rows it names. The control: a map changed between two asks gives new views."""
    names = ("params", "grads", "exp_avg", "exp_avg_sq", "stats")

    def views():
        return [getattr(gmap, n) for n in names] + [gmap.float_params(), gmap.float_grads()]

    def check(vs):
        n = gmap.n
        for v in vs:
            for f in ("means", "vis_count"):
                if hasattr(v, f):
                    assert getattr(v, f).shape[0] == n
        np.testing.assert_array_equal(vs[-2].means.numpy(), gmap.params_.means.numpy()[:n])

    first = views()
    check(first)
    again = views()
    assert all(a is b for a, b in zip(first, again))              # nothing changed: the same objects
    gmap.clone(np.ones(gmap.n, bool), step=1)                       # 20 -> 40 rows
    grown = views()
    check(grown)
    assert all(a is not b for a, b in zip(first, grown))
    keep = np.zeros(gmap.n, bool)
    keep[::3] = True
    gmap.remove(~keep)
    check(views())
    before = views()
    gmap.reserve(500)                                               # new buffers, the same rows
    moved = views()
    check(moved)
    assert all(a is not b for a, b in zip(before, moved))
    assert moved[-2].means.ptr == gmap.params_.means.ptr           # the new buffers' memory
    gmap.float_grads().means.assign(np.full((gmap.n, 3), 2.0, np.float32))
    assert np.all(gmap.grads.means.numpy() == 2.0)

# ------------------------------------------------------------------------------------- anchors (loop closure)
def _add(gm, arrays, **kw):
    return gm.add(arrays.means, arrays.log_scales, arrays.quats, arrays.opacity_logits, arrays.sh, **kw)


def test_anchors_follow_their_rows_through_clone_split_remove_and_reserve(wp_device):
    rng = np.random.default_rng(3)
    gm = GaussianMap(64, 0, device=wp_device)
    _add(gm, _arrays(rng, 5), anchor=7)
    _add(gm, _arrays(rng, 4, first_id=5), anchor=np.array([1, 2, 3, 4]))
    _add(gm, _arrays(rng, 2, first_id=9))                   # unanchored: -1
    expect = {0: 7, 1: 7, 2: 7, 3: 7, 4: 7, 5: 1, 6: 2, 7: 3, 8: 4, 9: -1, 10: -1}

    def check():
        ids = gm.means.numpy()[:, 0].round().astype(int)
        got = gm.anchor.numpy()
        for i, a in zip(ids, got):
            assert a == expect[i], (i, a)

    check()
    gm.clone(np.isin(np.arange(gm.n), [0, 6, 9]), step=3)    # copies keep their parent's anchor
    check()
    gm.remove(np.isin(np.arange(gm.n), [1, 5]))
    check()
    gm.reserve(128)
    check()
    mask = np.zeros(gm.n, bool)
    mask[[2, 4]] = True
    anchors_split = set(gm.anchor.numpy()[mask])
    n0 = gm.n
    gm.split(mask, children=2, step=4, rng=rng)              # children inherit (their means move: check the set)
    assert gm.n == n0 + 2
    assert set(gm.anchor.numpy()[-4:]) == anchors_split
    with pytest.raises(ValueError, match="anchor"):
        _add(gm, _arrays(rng, 3), anchor=np.array([1, 2]))


def test_transform_anchored_moves_only_its_keyframes_gaussians_and_renders_the_same(wp_device):
    """A Sim(3) of the world applied to a keyframe's Gaussians and to the camera gives the same image (a similarity
    changes the world's scale, not what a camera sees of it); the other keyframe's Gaussians do not move."""
    from mgso.camera import PinholeCamera
    from mgso.config import load_config
    from mgso.geometry import make_pose, se3_inverse, sim3_from_parts, so3_exp
    from mgso.messages import sim3_apply_to_pose
    from mgso.mapping.trainer import TrainStep

    rng = np.random.default_rng(5)
    n = 300
    means = np.c_[rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n), rng.uniform(3, 5, n)].astype(np.float32)
    arr = GaussianArrays(means, np.full((n, 3), -3.2, np.float32) + rng.uniform(-0.3, 0.3, (n, 3)).astype(np.float32),
                         rng.standard_normal((n, 4)).astype(np.float32), np.full(n, 2.0, np.float32),
                         rng.uniform(-1, 1, (n, 1, 3)).astype(np.float32))
    gm = GaussianMap(n, 0, device=wp_device)
    gm.add(arr.means, arr.log_scales, arr.quats, arr.opacity_logits, arr.sh, anchor=np.where(np.arange(n) < 200, 4, 9))
    cam = PinholeCamera(60.0, 60.0, 39.5, 29.5, 80, 60)
    c2w = make_pose(so3_exp([0.02, -0.05, 0.01]), [0.1, -0.05, 0.2])
    step = TrainStep(load_config().mapping, wp_device)
    S = sim3_from_parts(so3_exp([0.1, 0.3, -0.2]), np.array([0.5, -1.0, 2.0]), 1.7)
    # only keyframe 4's Gaussians in view for the comparison: 9's are kept aside and checked unmoved
    before = gm.to_numpy()
    gm_only4 = GaussianMap(n, 0, device=wp_device)
    gm_only4.add(*(getattr(before, f)[:200] for f in ("means", "log_scales", "quats", "opacity_logits", "sh")),
                 anchor=4)
    img0 = step.render(gm_only4, cam, se3_inverse(c2w))
    assert gm_only4.transform_anchored({4: S, 9: np.eye(4)}) == 200
    img1 = step.render(gm_only4, cam, se3_inverse(sim3_apply_to_pose(S, c2w)))
    assert img0.std() > 0.05                                     # the view shows something
    assert np.abs(img1 - img0).max() < 2e-3
    # a negative control: the camera moved without the Gaussians sees a different image
    img_wrong = step.render(gm, cam, se3_inverse(sim3_apply_to_pose(S, c2w)))
    assert np.abs(img_wrong - img0).mean() > 0.02
    moved = gm.transform_anchored({4: S})
    after = gm.to_numpy()
    assert moved == 200
    np.testing.assert_array_equal(after.means[200:], before.means[200:])     # keyframe 9's stay
    expect = before.means[:200].astype(np.float64) @ S[:3, :3].T + S[:3, 3]
    np.testing.assert_allclose(after.means[:200], expect, rtol=0, atol=1e-5)
    np.testing.assert_allclose(after.log_scales[:200], before.log_scales[:200] + math.log(1.7), atol=1e-6)
