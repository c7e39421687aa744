"""Densification strategy on hand-made statistics: it clones, splits and prunes exactly what the 3DGS rules say."""

import dataclasses
import math

import numpy as np
import pytest
import warp as wp

from mgso.config import DensifyConfig
from mgso.mapping.gaussian_map import GaussianMap
from mgso.mapping.strategy import DefaultStrategy

EXTENT = 2.0
SMALL = math.log(0.005)    # max scale 0.005 <= 0.01 * 2.0 -> clone candidate
LARGE = math.log(0.05)     # 0.05 > 0.02 -> split candidate, < 0.1 * 2.0 -> not too big
HUGE = math.log(0.5)       # > 0.1 * 2.0 -> too big in the world after the first reset


def _map(wp_device, rows, capacity=64):
    """rows: list of (log_scale, opacity, grad_ndc, absgrad_ndc, vis_count)."""
    n = len(rows)
    gm = GaussianMap(capacity=capacity, sh_degree=0, device=wp_device, scene_extent=EXTENT)
    means = np.zeros((n, 3), np.float32)
    means[:, 0] = np.arange(n)
    op = np.array([r[1] for r in rows])
    gm.add(means, np.array([[r[0]] * 3 for r in rows]), np.tile([1, 0, 0, 0], (n, 1)), np.log(op / (1 - op)),
           np.zeros((n, 3)), step=0)
    count = np.array([r[4] for r in rows], np.int32)
    st = gm.stats
    st.grad2d_sum.assign(np.array([r[2] for r in rows], np.float32) * count)   # sums: mean x count
    st.absgrad2d_sum.assign(np.array([r[3] for r in rows], np.float32) * count)
    st.vis_count.assign(count)
    return gm


ROWS = [  # log_scale, opacity, mean grad (NDC), mean abs grad (NDC), views
    (SMALL, 0.5, 3e-4, 0.0, 4),    # 0 clone
    (LARGE, 0.5, 3e-4, 0.0, 4),    # 1 split
    (SMALL, 0.5, 1e-4, 0.0, 4),    # 2 nothing (low grad)
    (LARGE, 0.5, 1e-4, 9e-4, 4),   # 3 nothing in grad mode; split by abs grad in absgrad mode
    (SMALL, 0.003, 1e-4, 0.0, 4),  # 4 pruned: opacity
    (HUGE, 0.5, 1e-4, 0.0, 4),     # 5 pruned: too big (after the first reset interval)
    (SMALL, 0.5, 0.0, 0.0, 0),     # 6 never seen: nothing
]


def _ids(gm):
    return list(gm.means.numpy()[:, 0].astype(int))


def _cfg(**kw):
    """The rules' settings with the rows left in the order the rules make them (these tests follow rows by place;
    the spatial order after a refine is tested on its own)."""
    return DensifyConfig(sort_spatially=False, **kw)


def test_refine_clones_splits_prunes(wp_device):
    gm = _map(wp_device, ROWS)
    strat = DefaultStrategy(_cfg())
    st = strat.initialize_state(seed=1)
    res = strat.step_post_backward(gm, st, 3100)   # > 500, % 100 == 0, after the first reset (3000)
    assert res.refined and not res.opacity_reset
    assert (res.cloned, res.split, res.pruned_opacity, res.pruned_world, res.pruned_screen) == (1, 1, 1, 1, 0)
    assert res.n_before == 7 and res.n_after == gm.n == 7 + 1 + 1 - 2
    # survivors in order (1 was replaced by its children), then the clone of 0, then the two children of 1
    assert _ids(gm)[:4] == [0, 2, 3, 6]
    assert _ids(gm)[4] == 0
    ls = gm.log_scales.numpy()
    np.testing.assert_allclose(ls[5:], LARGE - math.log(1.6), atol=1e-6)
    assert np.all(gm.created_step.numpy()[4:] == 3100) and np.all(gm.created_step.numpy()[:4] == 0)
    assert not np.any(gm.stats.grad2d_sum.numpy()) and not np.any(gm.stats.vis_count.numpy())   # stats reset


def test_a_refine_puts_the_rows_in_spatial_order_when_set(wp_device):
    """With sort_spatially (the default) a refine ends with the rows in the Z-order of their means: the same rows
    as without it (the control above keeps the rules' order), permuted by spatial_order."""
    from mgso.mapping.gaussian_map import spatial_order

    rows = ROWS * 3
    plain, ordered = _map(wp_device, rows), _map(wp_device, rows)
    for gm, on in ((plain, False), (ordered, True)):
        gm.means.assign(np.random.default_rng(3).uniform(-1, 1, (len(rows), 3)).astype(np.float32))
        strat = DefaultStrategy(DensifyConfig(sort_spatially=on))
        res = strat.step_post_backward(gm, strat.initialize_state(seed=1), 3100)
        assert res.refined and res.n_after == gm.n
    a, b = plain.state_numpy(), ordered.state_numpy()
    order = spatial_order(a["params.means"])
    assert not np.array_equal(order, np.arange(len(order)))
    for name in a:
        np.testing.assert_array_equal(b[name], a[name][order], err_msg=name)


def test_no_size_pruning_before_first_reset_and_no_refine_off_schedule(wp_device):
    strat = DefaultStrategy(_cfg())
    gm = _map(wp_device, ROWS)
    res = strat.step_post_backward(gm, strat.initialize_state(), 1000)
    assert res.refined and res.pruned_world == 0 and res.pruned_opacity == 1
    for step in (400, 500, 1050, 15_000, 15_100):   # before start, at start (strict), off the interval, after stop
        gm = _map(wp_device, ROWS)
        res = strat.step_post_backward(gm, strat.initialize_state(), step)
        assert not res.refined and gm.n == 7 and res.cloned == res.split == res.pruned == 0, step


def test_no_size_pruning_without_opacity_resets(wp_device):
    """Without resets (MGSO's mapper: reset_every 0) there is no first reset, so the world-size and screen-size
    prunes never run; the opacity prune does. Control: the same rows with resets on are pruned for size."""
    for reset_every, world in ((0, 0), (3000, 1)):
        strat = DefaultStrategy(_cfg(reset_every=reset_every, refine_stop_step=0, prune_screen_px=1.0))
        for step in (600, 3100, 50_000):
            gm = _map(wp_device, ROWS)
            gm.stats.max_radius_px.assign(np.full(7, 5.0, np.float32))   # every row above 1 px on screen
            res = strat.step_post_backward(gm, strat.initialize_state(), step)
            after_reset = reset_every > 0 and step > reset_every
            assert res.refined and res.pruned_opacity == 1, (reset_every, step)
            assert res.pruned_world == (world if after_reset else 0), (reset_every, step)
            # the rows the grow left with their radius (row 1 became two new children), less the opacity's and size's
            assert res.pruned_screen == (6 - 1 - world if after_reset else 0), (reset_every, step)


def test_opacity_reset(wp_device):
    strat = DefaultStrategy(_cfg())
    gm = _map(wp_device, ROWS)
    res = strat.step_post_backward(gm, strat.initialize_state(), 6000)
    assert res.opacity_reset and res.refined
    op = 1 / (1 + np.exp(-gm.opacity_logits.numpy()))
    assert np.all(op <= 0.01 + 1e-6)
    gm = _map(wp_device, ROWS)
    assert not strat.step_post_backward(gm, strat.initialize_state(), 6001).opacity_reset
    paused = DefaultStrategy(_cfg(pause_refine_after_reset=200))
    assert not paused.step_post_backward(_map(wp_device, ROWS), paused.initialize_state(), 6100).refined
    assert paused.step_post_backward(_map(wp_device, ROWS), paused.initialize_state(), 6200).refined


def test_absgrad_modes(wp_device):
    strat = DefaultStrategy(_cfg(grad_mode="absgrad"))     # abs grad decides both, threshold 0.0008
    gm = _map(wp_device, ROWS)
    res = strat.step_post_backward(gm, strat.initialize_state(), 3100)
    assert (res.cloned, res.split) == (0, 1) and 3 not in _ids(gm)[:4]
    strat = DefaultStrategy(_cfg(grad_mode="absgs"))       # clone by grad, split by abs grad > 0.0004
    gm = _map(wp_device, ROWS)
    res = strat.step_post_backward(gm, strat.initialize_state(), 3100)
    assert (res.cloned, res.split) == (1, 1) and _ids(gm)[:4] == [0, 1, 2, 6]


def test_capacity_bounds_growth_by_priority(wp_device):
    rows = [(SMALL, 0.5, g, 0.0, 2) for g in (3e-4, 9e-4, 5e-4, 1e-4)]
    gm = _map(wp_device, rows, capacity=6)
    strat = DefaultStrategy(_cfg())
    res = strat.step_post_backward(gm, strat.initialize_state(), 600)
    assert res.cloned == 2 and res.skipped_capacity == 1 and gm.n == 6
    assert _ids(gm)[4:] == [1, 2]      # the two largest gradients grew


def test_min_views_and_min_age(wp_device):
    strat = DefaultStrategy(_cfg(grow_min_views=5))
    gm = _map(wp_device, ROWS)
    res = strat.step_post_backward(gm, strat.initialize_state(), 3100)
    assert res.cloned == 0 and res.split == 0
    strat = DefaultStrategy(_cfg(prune_min_age=5000))
    gm = _map(wp_device, ROWS)
    res = strat.step_post_backward(gm, strat.initialize_state(), 3100)
    assert res.pruned == 0


def test_screen_size_pruning(wp_device):
    strat = DefaultStrategy(_cfg(prune_screen_px=20.0))
    gm = _map(wp_device, ROWS)
    gm.stats.max_radius_px.assign(np.array([25, 0, 0, 0, 0, 0, 30], np.float32))
    res = strat.step_post_backward(gm, strat.initialize_state(), 3100)
    # rows 0 and 6 were drawn larger than 20 px; row 0's clone (made in this refine, no radius yet) stays
    assert res.pruned_screen == 2 and _ids(gm) == [2, 3, 0, 1, 1]


def test_weight_pruning_removes_what_no_view_shows(wp_device):
    """``prune_weight_px``: a Gaussian in view in at least ``prune_weight_views`` views since the last refine whose
    largest blending weight over them is below the threshold is pruned (0: hidden in all); one above it, one in view
    too few times, or a young one is kept. Off (0, 3DGS) nothing is pruned for it."""
    rows = [(SMALL, 0.5, 1e-4, 0.0, v) for v in (5, 5, 2, 0, 5, 5)]
    weight = np.array([0.0, 0.5, 0.0, 0.0, 0.0, 0.05], np.float32)
    created = np.array([0, 0, 0, 0, 2900, 0], np.int32)
    for px, views, min_age, want in ((0.1, 3, 500, [1, 2, 3, 4]), (0.0, 3, 0, [0, 1, 2, 3, 4, 5]),
                                     (0.1, 3, 0, [1, 2, 3]), (0.1, 6, 0, [0, 1, 2, 3, 4, 5]),
                                     (0.01, 3, 0, [1, 2, 3, 5])):
        gm = _map(wp_device, rows)
        gm.stats.weight_max.assign(weight)
        gm.created_step.assign(created)
        strat = DefaultStrategy(_cfg(prune_weight_px=px, prune_weight_views=views, prune_min_age=min_age))
        res = strat.step_post_backward(gm, strat.initialize_state(), 3000)
        assert res.refined and _ids(gm) == want, (px, views, min_age)
        assert res.pruned_weight == 6 - len(want) == res.pruned, (px, views, min_age)


def test_pixel_gradients_are_converted_to_ndc(wp_device):
    """The 0.0002 threshold is in NDC units: a pixel gradient g counts as |(gx W/2, gy H/2)|."""
    W, H = 640, 480
    gm = _map(wp_device, [(SMALL, 0.5, 0.0, 0.0, 0)] * 2)
    v = np.array([[0.00025 / (W / 2), 0.0], [0.0, 0.00015 / (H / 2)]], np.float32)
    for _ in range(3):
        gm.accumulate_stats(wp.array(v, dtype=wp.vec2, device=wp_device),
                            wp.array(np.ones(2, np.float32), device=wp_device), W, H)
    strat = DefaultStrategy(_cfg())
    res = strat.step_post_backward(gm, strat.initialize_state(), 600)
    assert res.cloned == 1 and _ids(gm) == [0, 1, 0]


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="refine_every"):
        DefaultStrategy(_cfg(refine_every=0))
    with pytest.raises(ValueError, match="grad_mode"):
        DefaultStrategy(dataclasses.replace(DensifyConfig(), grad_mode="nope"))


def test_max_aspect_turns_needles_into_discs_only_when_set(wp_device):
    """``max_aspect``: at a refine, axes longer than max_aspect x the shortest are shortened to that length; the
    shortest axis and the Gaussians within the bound keep their scales. Off (0, 3DGS) nothing changes."""
    ls = np.log(np.array([[1.0, 1.0, 1.0], [1.0, 2.0, 50.0], [0.1, 5.0, 0.3], [0.2, 0.2, 1.9]], np.float32))
    for aspect, want in ((0.0, np.exp(ls)), (10.0, [[1, 1, 1], [1, 2, 10], [0.1, 1.0, 0.3], [0.2, 0.2, 1.9]])):
        gm = GaussianMap(capacity=8, sh_degree=0, device=wp_device, scene_extent=EXTENT)
        gm.add(np.zeros((4, 3)), ls, np.tile([1, 0, 0, 0], (4, 1)), np.zeros(4), np.zeros((4, 3)), step=0)
        strat = DefaultStrategy(_cfg(refine_start_step=0, refine_every=10, max_aspect=aspect))
        res = strat.step_post_backward(gm, strat.initialize_state(0), 10)
        assert res.refined and res.clamped_aspect == (2 if aspect else 0)
        np.testing.assert_allclose(np.exp(gm.log_scales.numpy()), want, rtol=1e-5)
    with pytest.raises(ValueError, match="max_aspect"):
        DefaultStrategy(_cfg(max_aspect=0.5))
