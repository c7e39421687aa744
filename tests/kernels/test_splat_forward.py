"""Forward pass of the Warp rasteriser against its brute-force NumPy twin; binning against a brute-force tile test."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from mgso.geometry import se3_exp
from mgso_kernels.reference import splat as ref
from mgso_kernels.splat import TILE_SIZE, Rasterizer, make_camera


def _camera(rng, width=64, height=48, f=55.0):
    T = se3_exp(rng.normal(size=6) * 0.2)
    return ref.RefCamera(fx=f, fy=f * 1.05, cx=width / 2 - 0.7, cy=height / 2 + 0.4, width=width, height=height,
                         world_to_cam=T)


def _wcam(c: ref.RefCamera):
    return make_camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.world_to_cam, near=c.near, far=c.far)


def _render_both(rast, scene, cam, bg=(0.1, 0.2, 0.3), degree=None):
    out = rast.forward(scene["means"], scene["log_scales"], scene["quats"], scene["opacity_logits"], scene["sh"],
                       _wcam(cam), bg, sh_degree=degree)
    r = ref.render(scene["means"], scene["log_scales"], scene["quats"], scene["opacity_logits"], scene["sh"], cam,
                   bg, degree)
    return out, r


@pytest.mark.parametrize("seed,n,degree,size", [(0, 40, 0, (64, 48)), (1, 30, 1, (48, 40)), (2, 25, 3, (37, 29)),
                                                (3, 200, 0, (64, 48))])
def test_forward_matches_twin(wp_device, seed, n, degree, size):
    rng = np.random.default_rng(seed)
    cam = _camera(rng, *size)
    scene = ref.random_scene(rng, n, cam, degree)
    out, r = _render_both(Rasterizer(wp_device), scene, cam)
    # the scene must exercise what it claims: culled Gaussians, thin and saturated pixels (the dense one stops early)
    assert 0 < out.num_visible < n
    assert r["alpha"].max() > 0.999 and (r["alpha"].min() < 0.5 or n > 100)
    for key, tol in (("rgb", 2e-5), ("alpha", 2e-5), ("depth", 1e-4)):
        a = getattr(out, key).numpy()
        b = r[key]
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, atol=tol * max(1.0, np.abs(b).max()), rtol=0, err_msg=key)
    # T_final is what the backward pass starts from
    np.testing.assert_allclose(out.T_final.numpy(), r["T_final"], atol=2e-5)
    # culling agrees with the twin's near/far rule and with "touches the image at 1/255"
    proj = r["proj"]
    radii = out.radii.numpy()
    assert not np.any(radii[~proj["valid"]])


def test_background_and_empty_scene(wp_device):
    rng = np.random.default_rng(5)
    cam = _camera(rng, 40, 24)
    rast = Rasterizer(wp_device)
    scene = ref.random_scene(rng, 20, cam, 0)
    # everything behind the camera: only background, alpha 0, nothing listed
    pc = np.c_[rng.normal(size=(20, 2)), -rng.uniform(0.5, 2, 20)]
    scene["means"] = (pc - cam.t) @ cam.R
    out, r = _render_both(rast, scene, cam, bg=(0.25, 0.5, 0.75))
    assert out.n_pairs == 0 and out.num_visible == 0
    assert np.allclose(out.rgb.numpy(), [0.25, 0.5, 0.75]) and np.all(out.alpha.numpy() == 0)
    # no Gaussians at all
    out = rast.forward(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, 1, 3)),
                       _wcam(cam), (1.0, 0.0, 0.0))
    assert out.n_pairs == 0 and np.allclose(out.rgb.numpy(), [1.0, 0.0, 0.0])
    g = rast.backward(out, np.ones((24, 40, 3), np.float32), np.ones((24, 40), np.float32))
    assert g.v_means.shape == (0, 3) and g.v_sh.shape == (0, 1, 3) and np.all(g.v_pose.numpy() == 0)


def _pairs(rast, out):
    m = out.n_pairs
    keys = rast.keys_.full.numpy()[:m]
    slots = rast.slots_.full.numpy()[:m]
    if rast.device_is_cpu:  # the CPU's sort moves the slots only (bin.sort_pairs_and_ranges): keys stay as emitted
        keys = keys[slots]
    gauss = rast.pair_gauss_.full.numpy()[slots]
    return keys, slots, gauss


def test_binning_is_exact_and_sorted(wp_device):
    rng = np.random.default_rng(11)
    cam = _camera(rng, 72, 40)  # 5 x 3 tiles, the last column and row cut by the border
    scene = ref.random_scene(rng, 150, cam, 0)
    rast = Rasterizer(wp_device)
    out, r = _render_both(rast, scene, cam)
    keys, slots, gauss = _pairs(rast, out)
    tiles = keys >> 32
    got = set(zip(tiles.tolist(), gauss.tolist()))
    assert len(got) == out.n_pairs  # no duplicates
    # exact ellipse-rectangle test, with a 1% margin either way for float32 rounding
    inner = ref.tile_pairs(r["proj"], cam, TILE_SIZE, scale_r2=0.99)
    outer = ref.tile_pairs(r["proj"], cam, TILE_SIZE, scale_r2=1.01)
    assert inner <= got, f"missing pairs: {sorted(inner - got)[:10]}"
    assert got <= outer, f"extra pairs: {sorted(got - outer)[:10]}"
    # and tighter than the bounding squares 3DGS lists (so the test above is not vacuous)
    tiles_x = -(-cam.width // TILE_SIZE)
    proj = r["proj"]
    square = 0
    for g in np.nonzero(out.radii.numpy())[0]:
        m2, rad = proj["means2d"][g], np.sqrt(2 * np.log(255 * proj["opacities"][g])
                                              * max(np.linalg.eigvalsh(proj["cov2d"][g])))
        x0, x1 = np.clip(np.floor((m2[0] - rad) / 16), 0, tiles_x - 1), np.clip(np.floor((m2[0] + rad) / 16), 0,
                                                                                tiles_x - 1)
        y0, y1 = np.clip(np.floor((m2[1] - rad) / 16), 0, 2), np.clip(np.floor((m2[1] + rad) / 16), 0, 2)
        square += (x1 - x0 + 1) * (y1 - y0 + 1)
    assert out.n_pairs < square
    # every pixel a Gaussian reaches with alpha >= 1/255 lies in a tile that lists it
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    for g in np.nonzero(proj["valid"])[0]:
        a, b, c = proj["conics"][g]
        dx, dy = uu - proj["means2d"][g, 0], vv - proj["means2d"][g, 1]
        alpha = proj["opacities"][g] * np.exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy)
        hit = np.argwhere(alpha >= 1.0 / 255.0)
        for t in set(((hit[:, 0] // 16) * tiles_x + hit[:, 1] // 16).tolist()):
            assert (t, g) in got
    # sorted by tile, then depth; ranges index the sorted list exactly
    assert np.all(np.diff(tiles) >= 0)
    depths = out.depths.numpy()[gauss]
    same = np.diff(tiles) == 0
    assert np.all(np.diff(depths)[same] >= 0)
    ranges = rast.ranges_.full.numpy()[: cam.width // 16 * 0 + tiles_x * 3]
    for t in range(tiles_x * 3):
        sel = np.nonzero(tiles == t)[0]
        if len(sel):
            assert ranges[t, 0] == sel[0] and ranges[t, 1] == sel[-1] + 1
        else:
            assert ranges[t, 0] == ranges[t, 1]
    # slots: each Gaussian's slots are the contiguous range [offset, offset + tiles_touched)
    touched = out.tiles_touched.numpy()
    offsets = rast.pair_offsets_.full.numpy()[: len(touched)]
    for g in np.nonzero(touched)[0]:
        assert np.all(gauss[np.isin(slots, np.arange(offsets[g], offsets[g] + touched[g]))] == g)


def test_render_alpha_matches_forward(wp_device):
    rng = np.random.default_rng(21)
    cam = _camera(rng, 64, 48)
    scene = ref.random_scene(rng, 100, cam, 1)
    rast = Rasterizer(wp_device)
    out = rast.forward(scene["means"], scene["log_scales"], scene["quats"], scene["opacity_logits"], scene["sh"],
                       _wcam(cam))
    full = out.alpha.numpy().copy()
    radii = out.radii.numpy().copy()
    a = rast.render_alpha(scene["means"], scene["log_scales"], scene["quats"], scene["opacity_logits"], _wcam(cam))
    assert np.array_equal(a.alpha.numpy(), full)
    assert np.array_equal(a.radii.numpy(), radii) and a.n_pairs == out.n_pairs
    with pytest.raises(RuntimeError, match="stale"):
        rast.backward(out, np.zeros((48, 64, 3), np.float32))


@pytest.mark.parametrize("seg", [16, TILE_SIZE * TILE_SIZE])
def test_coverage_with_depth_and_its_stop_match_the_twin(wp_device, seg):
    """render_alpha(with_depth=True): without the stop the full render's alpha and depth; with t_stop = 0.01 the
    twin's, which equal the full render's wherever a pixel stays below 0.99 (the seeding's coverage test)."""
    rng = np.random.default_rng(23)
    cam = _camera(rng, 64, 48)
    scene = ref.random_scene(rng, 60, cam, 0)
    rast = Rasterizer(wp_device, pixels_per_thread=seg)
    p4 = [scene[k] for k in ("means", "log_scales", "quats", "opacity_logits")]
    out = rast.forward(*p4, scene["sh"], _wcam(cam))
    full = {k: getattr(out, k).numpy().copy() for k in ("alpha", "depth")}
    exact = rast.render_alpha(*p4, _wcam(cam), with_depth=True)
    if wp.get_device(wp_device).is_cpu:  # the same operations in the same order (measured: equal on the CPU)
        assert np.array_equal(exact.alpha.numpy(), full["alpha"])
        assert np.array_equal(exact.depth.numpy(), full["depth"])
    np.testing.assert_allclose(exact.alpha.numpy(), full["alpha"], atol=1e-6, rtol=0)
    np.testing.assert_allclose(exact.depth.numpy(), full["depth"], atol=1e-6 * full["depth"].max(), rtol=0)
    assert rast.render_alpha(*p4, _wcam(cam)).depth is None
    cov = rast.render_alpha(*p4, _wcam(cam), with_depth=True, t_stop=0.01)
    a, d = cov.alpha.numpy(), cov.depth.numpy()
    r = ref.render(*p4, scene["sh"], cam, t_stop=0.01)
    np.testing.assert_allclose(a, r["alpha"], atol=2e-5, rtol=0)
    np.testing.assert_allclose(d, r["depth"], atol=1e-4 * r["depth"].max(), rtol=0)
    # the stop does something here (against the exact render above: 42 % of the pixels stop early), and only
    # where a pixel's alpha reached 0.99; the rest, thin pixels among them, is the full render's
    stopped = np.abs(a - full["alpha"]) > 1e-5
    assert 0.2 < stopped.mean() < 0.8 and np.all(a[stopped] >= 0.99 - 1e-6)
    thin = full["alpha"] < 0.98
    assert thin.mean() > 0.2
    np.testing.assert_allclose(a[thin], full["alpha"][thin], atol=1e-6, rtol=0)
    # the expected depth of a stopped pixel misses at most a weight of 0.01 (measured: 0.5 % of the farthest depth)
    zmax = float(r["proj"]["depths"][r["proj"]["valid"]].max())
    err = np.abs(d / np.maximum(a, 1e-6) - full["depth"] / np.maximum(full["alpha"], 1e-6))[a > 0.5]
    assert 0 < err.max() < 0.012 * zmax
    with pytest.raises(ValueError, match="t_stop"):
        rast.render_alpha(*p4, _wcam(cam), t_stop=1.0)


def test_split_forward_is_bitwise_identical(wp_device):
    if not wp.get_device(wp_device).is_cpu:
        pytest.skip("splitting only applies to CPU launches")
    rng = np.random.default_rng(31)
    cam = _camera(rng, 80, 56)
    scene = ref.random_scene(rng, 200, cam, 1)
    single = Rasterizer(wp_device, threads=1)
    split = Rasterizer(wp_device, threads=3, min_chunk=16)
    a = single.forward(*(scene[k] for k in ("means", "log_scales", "quats", "opacity_logits", "sh")), _wcam(cam))
    b = split.forward(*(scene[k] for k in ("means", "log_scales", "quats", "opacity_logits", "sh")), _wcam(cam))
    for key in ("rgb", "depth", "alpha", "T_final", "n_contrib", "radii", "means2d"):
        assert np.array_equal(getattr(a, key).numpy(), getattr(b, key).numpy()), key


def test_buffers_grow_then_stay(wp_device):
    rng = np.random.default_rng(41)
    cam = _camera(rng, 48, 32)
    rast = Rasterizer(wp_device)
    small = ref.random_scene(rng, 10, cam, 0)
    big = ref.random_scene(rng, 200, cam, 0)
    args = ("means", "log_scales", "quats", "opacity_logits", "sh")
    rast.forward(*(small[k] for k in args), _wcam(cam))
    rast.forward(*(big[k] for k in args), _wcam(cam))
    grown = rast.reallocations
    m = rast.forward(*(big[k] for k in args), _wcam(cam)).n_pairs
    assert rast.keys_.capacity >= 2 * m and rast.slots_.capacity >= 2 * m  # the radix sort's 2x
    assert rast.splats_.capacity >= m and rast.means2d_.capacity >= 200
    for _ in range(3):
        out = rast.forward(*(big[k] for k in args), _wcam(cam))
        rast.backward(out, np.ones((32, 48, 3), np.float32))
    after_first_backward = rast.reallocations
    for _ in range(2):
        out = rast.forward(*(big[k] for k in args), _wcam(cam))
        rast.backward(out, np.ones((32, 48, 3), np.float32))
    assert rast.reallocations == after_first_backward
    assert after_first_backward - grown <= 20  # backward buffers, allocated once


def test_bad_input_errors(wp_device):
    rng = np.random.default_rng(0)
    cam = _camera(rng, 32, 32)
    rast = Rasterizer(wp_device)
    s = ref.random_scene(rng, 5, cam, 0)
    with pytest.raises(ValueError, match=r"quats: expected shape \(5, 4\)"):
        rast.forward(s["means"], s["log_scales"], s["quats"][:, :3], s["opacity_logits"], s["sh"], _wcam(cam))
    with pytest.raises(ValueError, match="sh: expected"):
        rast.forward(s["means"], s["log_scales"], s["quats"], s["opacity_logits"], np.zeros((5, 5, 3)), _wcam(cam))
    with pytest.raises(ValueError, match="sh_degree"):
        rast.forward(s["means"], s["log_scales"], s["quats"], s["opacity_logits"], s["sh"], _wcam(cam), sh_degree=2)
    with pytest.raises(TypeError, match="make_camera"):
        rast.forward(s["means"], s["log_scales"], s["quats"], s["opacity_logits"], s["sh"], cam)
    with pytest.raises(ValueError, match="orthonormal"):
        make_camera(10, 10, 5, 5, 10, 10, np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="background"):
        rast.forward(s["means"], s["log_scales"], s["quats"], s["opacity_logits"], s["sh"], _wcam(cam), (0, 0))
    out = rast.forward(s["means"], s["log_scales"], s["quats"], s["opacity_logits"], s["sh"], _wcam(cam))
    with pytest.raises(ValueError, match="v_rgb"):
        rast.backward(out, np.zeros((32, 31, 3)))


def test_vector_typed_inputs_are_viewed(wp_device):
    rng = np.random.default_rng(3)
    cam = _camera(rng, 32, 32)
    s = ref.random_scene(rng, 30, cam, 0)
    rast = Rasterizer(wp_device)
    a = rast.forward(s["means"], s["log_scales"], s["quats"], s["opacity_logits"], s["sh"], _wcam(cam)).rgb.numpy()
    a = a.copy()
    means = wp.array(s["means"].astype(np.float32), dtype=wp.vec3, device=wp_device)
    quats = wp.array(s["quats"].astype(np.float32), dtype=wp.vec4, device=wp_device)
    b = rast.forward(means, s["log_scales"], quats, s["opacity_logits"], s["sh"], _wcam(cam)).rgb.numpy()
    assert np.array_equal(a, b)
