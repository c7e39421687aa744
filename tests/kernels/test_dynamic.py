"""Work sharing on the CPU (mgso_kernels.dynamic): each chunk of a split launch takes its own range's items from the
front, then the others' from their back. Every item is taken once, a chunk's share of its own range is a prefix, a
slow chunk's range is shared; a kernel's shared variant gives the static split's outputs bit for bit (the tile blends
forward, coverage and backward, the projection and binning blocks, Adam's blocks), a tile the snippet declines is
blended by the static kernel's Warp code, and the control with the sharing off (use_dynamic(False)) runs none."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from mgso.geometry import se3_exp
from mgso_kernels import adam as wa
from mgso_kernels import dynamic, runtime
from mgso_kernels.reference import splat as ref
from mgso_kernels.splat import Rasterizer, make_camera, raster_bwd, raster_tile
from mgso_kernels.splat import bin as _bin
from mgso_kernels.splat import project as _project
from mgso_kernels.splat import raster as _raster

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


@pytest.fixture
def cpu(wp_device):
    if not wp.get_device(wp_device).is_cpu:
        pytest.skip("dynamic work sharing is for the CPU's split launches")
    return wp_device


@wp.kernel(enable_backward=False)
def _take_items(offset: int, shares: wp.array(dtype=wp.int64), n_items: int, taken: wp.array2d(dtype=wp.int32),
                slow: int):
    chunk = offset + wp.tid()                      # launch_dynamic's chunks are one Warp thread each
    chunks = shares.shape[0]
    for k in range(chunks):
        r = (chunk + k) % chunks
        i = dynamic.take_item(shares, r, k)
        while i >= 0:
            taken[chunk, i] = taken[chunk, i] + 1
            if chunk == 0 and slow > 0:             # the first chunk's items cost more: the others take some
                acc = float(0.0)
                for j in range(slow):
                    acc += wp.sin(float(j + i))
                taken[chunk, i] = taken[chunk, i] + int(acc > 1.0e9)
            i = dynamic.take_item(shares, r, k)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_every_item_is_taken_once_and_a_chunk_starts_with_its_own_range(cpu, threads):
    n = 300_000
    ranges = runtime.split_ranges(n, threads)
    for slow in (0, 0, 200):
        taken = wp.zeros((threads, n), dtype=wp.int32, device=cpu)
        chunks = dynamic.launch_dynamic(_take_items, n, [taken, slow], cpu, threads=threads)
        assert chunks == threads
        t = taken.numpy()
        assert (t.sum(axis=0) == 1).all()          # none twice, none left out
        for c, (lo, hi) in enumerate(ranges):
            # a chunk takes its own range from the front, the others from the back: a prefix and the rest (a chunk
            # whose thread started late, three threads on two cores, may find its range taken)
            m = int(t[c, lo:hi].sum())
            assert (t[c, lo:lo + m] == 1).all()
            assert (t[:, lo + m:hi].sum(axis=0) == 1).all() and (t[c, lo + m:hi] == 0).all()
        if threads > 1 and slow:
            lo, hi = ranges[0]
            assert t[1:, lo:hi].sum() > 0          # the slow chunk's range was shared
    # fewer items than chunks would take: one chunk an item at most
    taken = wp.zeros((3, 2), dtype=wp.int32, device=cpu)
    assert dynamic.launch_dynamic(_take_items, 2, [taken, 0], cpu, threads=3) == 2
    assert (taken.numpy().sum(axis=0) == 1).all()
    assert dynamic.launch_dynamic(_take_items, 0, [taken, 0], cpu, threads=3) == 0


def _scene(seed, n, width, height):
    rng = np.random.default_rng(seed)
    T = se3_exp(rng.normal(size=6) * 0.2)
    cam = ref.RefCamera(fx=70.0, fy=72.0, cx=width / 2 - 0.3, cy=height / 2 + 0.6, width=width, height=height,
                        world_to_cam=T)
    scene = ref.random_scene(rng, n, cam, 1)
    wcam = make_camera(cam.fx, cam.fy, cam.cx, cam.cy, width, height, T, near=cam.near, far=cam.far)
    return rng, scene, wcam


class _Count:
    """Counts launch_dynamic's calls by kernel name."""

    def __init__(self, monkeypatch):
        self.calls: dict[str, int] = {}
        real = dynamic.launch_dynamic

        def counted(kernel, *a, **k):
            self.calls[kernel.key] = self.calls.get(kernel.key, 0) + 1
            return real(kernel, *a, **k)

        monkeypatch.setattr(dynamic, "launch_dynamic", counted)


@pytest.mark.parametrize("size,n", [((128, 96), 3000), ((53, 35), 700)])
def test_the_dynamic_render_equals_the_static_split_bit_for_bit(cpu, monkeypatch, size, n):
    rng, scene, cam = _scene(5, n, *size)
    v_rgb = rng.normal(size=(size[1], size[0], 3)).astype(np.float32)
    v_depth = rng.normal(size=(size[1], size[0])).astype(np.float32)
    v_alpha = rng.normal(size=(size[1], size[0])).astype(np.float32)
    count = _Count(monkeypatch)

    def run(on):
        before = dynamic.use_dynamic(on)
        try:
            # chunks of one tile and one block, so that even the small image has several
            rast = Rasterizer(cpu, threads=2, min_chunk=1)
            out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3))
            r = {k: getattr(out, k).numpy().copy() for k in ("rgb", "depth", "alpha", "T_final", "n_contrib", "radii")}
            for absgrad in (True, False):
                out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3))
                g = rast.backward(out, v_rgb, v_depth, v_alpha, absgrad=absgrad)
                for name in ("v_means", "v_log_scales", "v_quats", "v_opacity_logits", "v_sh", "v_pose", "v_means2d",
                             "absgrad", "weights"):
                    r[f"{name}/{absgrad}"] = getattr(g, name).numpy().copy()
            for t_stop in (0.0, 0.01):
                a = rast.render_alpha(*(scene[k] for k in PARAMS[:4]), cam, with_depth=True, t_stop=t_stop)
                r[f"coverage/{t_stop}"] = a.alpha.numpy().copy()
                r[f"coverage_depth/{t_stop}"] = a.depth.numpy().copy()
            r["coverage_only"] = rast.render_alpha(*(scene[k] for k in PARAMS[:4]), cam).alpha.numpy().copy()
        finally:
            dynamic.use_dynamic(before)
        return r

    static = run(False)
    assert not count.calls                           # the control: none ran
    got = run(True)
    assert (static["alpha"] > 0.5).mean() > 0.3      # a scene that is drawn
    for key, want in static.items():
        assert np.array_equal(got[key], want), key
    names = set(count.calls)
    small = size[0] * size[1] <= raster_bwd.NARROW_BACKWARD_PIXELS       # the 8-lane backward
    want_kernels = {raster_tile.rasterize_forward_tile_dynamic.key, raster_tile.rasterize_alpha_tile_dynamic.key,
                    raster_tile.rasterize_alpha_depth_tile_dynamic.key,
                    (raster_tile.rasterize_backward_tile_narrow_dynamic if small
                     else raster_tile.rasterize_backward_tile_dynamic).key,
                    (raster_tile.rasterize_backward_tile_noabs_narrow_dynamic if small
                     else raster_tile.rasterize_backward_tile_noabs_dynamic).key,
                    _project.project_gaussians_blocks_dynamic.key,
                    _project.project_gaussians_backward_blocks_dynamic.key, _bin.bin_blocks_dynamic.key}
    assert want_kernels <= names, want_kernels - names
    # and the snippets did every tile (none declined to the static kernel's Warp code)
    tiles = cam.tiles_x * cam.tiles_y
    assert (raster_tile.status_buffer(tiles, cpu).numpy()[:tiles] == 1).all()


def test_a_tile_the_snippet_declines_is_blended_by_the_static_kernel(cpu):
    """Splats the forward snippet does not take (a strided array): the dynamic kernel leaves every tile undone and
    the static kernel's Warp code blends them, as it does with the dynamic sharing off."""
    _, scene, cam = _scene(9, 600, 96, 80)
    rast = Rasterizer(cpu, threads=2, min_chunk=1)
    out = rast.forward(*(scene[k] for k in PARAMS), cam, (0.1, 0.2, 0.3))
    m = out.n_pairs
    tiles = cam.tiles_x * cam.tiles_y
    wide = wp.zeros(2 * m, dtype=raster_tile.vec8, device=cpu)
    strided = wide[::2]                                 # the same splats, 64 bytes apart
    strided.assign(rast.splats_.full[:m])
    res = []
    for on in (True, False):
        before = dynamic.use_dynamic(on)
        try:
            o = [wp.zeros((cam.height, cam.width, 3), dtype=float, device=cpu)] + [
                wp.zeros((cam.height, cam.width), dtype=float, device=cpu) for _ in range(3)] + [
                wp.zeros((cam.height, cam.width), dtype=wp.int32, device=cpu)]
            _raster.launch_rasterize_forward(cam, rast.ranges_.full, strided, rast.splat_rgbz_.full, (0.1, 0.2, 0.3),
                                             *o, cpu, threads=2, min_chunk=1, seg=raster_tile.TILE_PIXELS)
            assert (raster_tile.status_buffer(tiles, cpu).numpy()[:tiles] == 0).all()   # the Warp code did them
            res.append([a.numpy().copy() for a in o])
        finally:
            dynamic.use_dynamic(before)
    for a, b in zip(*res):
        assert np.array_equal(a, b)
    np.testing.assert_allclose(res[0][0], out.rgb.numpy(), atol=2e-5)          # the snippet's image, to rounding


def test_adams_dynamic_blocks_update_as_the_static_split(cpu, rng, monkeypatch):
    n = 20_000                                          # two chunks of Adam's 8192 Gaussians and more
    count = _Count(monkeypatch)

    def group(scale):
        s = wa.GaussianParams()
        s.means = wp.array((scale * rng.standard_normal((n, 3))).astype(np.float32), dtype=wp.vec3, device=cpu)
        s.log_scales = wp.array((scale * rng.standard_normal((n, 3))).astype(np.float32), dtype=wp.vec3, device=cpu)
        s.quats = wp.array((scale * rng.standard_normal((n, 4))).astype(np.float32), dtype=wp.vec4, device=cpu)
        s.opacity_logits = wp.array((scale * rng.standard_normal(n)).astype(np.float32), device=cpu)
        s.sh = wp.array((scale * rng.standard_normal((n, 1, 3))).astype(np.float32), dtype=wp.vec3, device=cpu)
        return s

    p0, grads = group(1.0), [group(0.1) for _ in range(3)]
    steps0 = rng.integers(0, 5, n).astype(np.int32)
    rates = wa.AdamRates(means=1.6e-4, log_scales=5e-3, quats=1e-3, opacity_logits=2.5e-2, sh_dc=2.5e-3,
                         sh_rest=1e-4)

    def run(on):
        params, m, v = group(0.0), group(0.0), group(0.0)
        for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
            getattr(params, f).assign(getattr(p0, f))
        steps = wp.array(steps0, dtype=wp.int32, device=cpu)
        before = dynamic.use_dynamic(on)
        try:
            with runtime.cpu_threads_here(2):
                for it, g in enumerate(grads):
                    hp = wa.make_hyper(rates, bias_correction=wa.BIAS_PER_GAUSSIAN, global_step=it + 1)
                    st = wa.adam_step(params, g, m, v, steps, hp, device=cpu)
                    assert (st.numpy() == 1).all()
        finally:
            dynamic.use_dynamic(before)
        return [getattr(s, f).numpy() for s in (params, m, v) for f in ("means", "log_scales", "quats",
                                                                         "opacity_logits", "sh")] + [steps.numpy()]

    static = run(False)
    assert not count.calls
    got = run(True)
    assert count.calls.get(wa.adam_step_gaussians_blocks_dynamic.key) == 3
    for a, b in zip(static, got):
        assert np.array_equal(a, b)
    assert not np.array_equal(static[0], p0.means.numpy())
