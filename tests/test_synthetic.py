"""Synthetic scenes: geometry and conventions (depth, poses, pixel centres), photometry options, folder output."""

from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from mgso import synthetic as S
from mgso.io.trajectory import read_tum

W, H = 160, 120


@pytest.fixture(scope="module")
def seq():
    return S.make_sequence(seed=0, num_frames=12, width=W, height=H, keep_radiance=True)


def _brute_force_depth(scene, cam, T, u, v):
    """Nearest hit over every surface rectangle of the scene (independent of the renderer's slab tests)."""
    R, o = T[:3, :3], T[:3, 3]
    d = R @ np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
    best, which = np.inf, -1
    for k, s in enumerate(scene.surfaces):
        den = d @ s.normal
        if abs(den) < 1e-12:
            continue
        t = ((s.origin - o) @ s.normal) / den
        if t <= 0:
            continue
        q = o + t * d - s.origin
        a, b = q @ s.u_axis, q @ s.v_axis
        if -1e-9 <= a <= s.size[0] + 1e-9 and -1e-9 <= b <= s.size[1] + 1e-9 and t < best:
            best, which = t, k
    return best, which


def test_depth_is_z_depth_on_a_fronto_parallel_wall():
    scene = S.make_scene(0)
    cam = S.SyntheticCamera.from_fov(W, H, 70.0)
    _, depth = S.render(scene, cam, np.eye(4))
    far = scene.room_max[2]
    # rows through the image centre see the far wall (boxes are lower, side walls farther out): z-depth is the
    # wall's distance at every column, although the ray length grows towards the image sides
    band = depth[int(cam.cy) - 1:int(cam.cy) + 2]
    np.testing.assert_allclose(band, far, atol=2e-6)
    ray_len_at_edge = far * np.hypot(1.0, (0 - cam.cx) / cam.fx)
    assert ray_len_at_edge > far + 0.5


def test_depth_matches_brute_force_intersection():
    scene = S.make_scene(0)
    cam = S.SyntheticCamera.from_fov(W, H, 70.0)
    traj = S.camera_path(200, motion_scale=1.0)
    rng = np.random.default_rng(0)
    surfaces_seen = set()
    for i in (0, 90, 199):
        _, depth = S.render(scene, cam, traj.cam_to_world[i])
        for _ in range(150):
            u, v = int(rng.integers(0, W)), int(rng.integers(0, H))
            t, k = _brute_force_depth(scene, cam, traj.cam_to_world[i], u, v)
            assert depth[v, u] == pytest.approx(t, abs=2e-6 * t)
            surfaces_seen.add(k)
    assert {3, 5} <= surfaces_seen and max(surfaces_seen) >= 6  # floor, far wall and some box face


def _reproject(seq, i, j, cam_to_world_j=None, k_shift=0.0):
    """Back-project frame i with its depth and pose, project into frame j: colour and depth residuals."""
    K = seq.K.copy()
    K[0, 2] += k_shift
    K[1, 2] += k_shift
    v, u = np.mgrid[0:H, 0:W]
    z = seq.depths[i].astype(np.float64)
    Xc = (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T) * z[..., None]
    Twi = seq.cam_to_world[i]
    Tjw = np.linalg.inv(seq.cam_to_world[j] if cam_to_world_j is None else cam_to_world_j)
    Xj = (Xc @ Twi[:3, :3].T + Twi[:3, 3]) @ Tjw[:3, :3].T + Tjw[:3, 3]
    p = Xj @ K.T
    uj, vj = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    inside = (uj > 1) & (uj < W - 2) & (vj > 1) & (vj < H - 2) & (Xj[..., 2] > 0)
    dj = map_coordinates(seq.depths[j], [vj, uj], order=1, mode="nearest")
    depth_res = np.abs(dj - Xj[..., 2])
    visible = inside & (depth_res < 0.01 * Xj[..., 2])  # not occluded in frame j
    img_i, img_j = seq.radiance[i], seq.radiance[j]
    cj = np.stack([map_coordinates(img_j[..., c], [vj, uj], order=1, mode="nearest") for c in range(3)], -1)
    colour_err = np.abs(cj - img_i).max(-1)
    return visible, colour_err[visible], depth_res[inside]


def test_reprojection_colour_and_depth_consistency(seq):
    # Frames 0 and 11 are ~21 cm and several degrees apart.
    visible, err, depth_res = _reproject(seq, 0, 11)
    assert visible.mean() > 0.7
    assert np.median(err) < 0.005 and np.percentile(err, 90) < 0.03
    assert np.median(depth_res) < 5e-5  # exact depth + exact poses + pixel centres at integers
    # the same check fails with a wrong pose, a transposed rotation or a half-pixel principal point error
    _, err_wrong, _ = _reproject(seq, 0, 11, cam_to_world_j=seq.cam_to_world[3])
    assert np.median(err_wrong) > 10 * np.median(err)
    T = seq.cam_to_world[11].copy()
    T[:3, :3] = T[:3, :3].T
    vis_t, err_t, _ = _reproject(seq, 0, 11, cam_to_world_j=T)
    assert vis_t.mean() < 0.3 or np.median(err_t) > 10 * np.median(err)
    _, _, depth_res_shift = _reproject(seq, 0, 11, k_shift=0.5)
    assert np.median(depth_res_shift) > 10 * np.median(depth_res)


def test_depth_to_points_lands_on_the_surfaces(seq):
    pts, cols = S.depth_to_points(seq.depths[0], seq.intrinsics, seq.cam_to_world[0], seq.radiance[0], stride=4)
    assert pts.shape == (30 * 40, 3) and cols.shape == (30 * 40, 3)
    scene = seq.scene
    # every point lies on the room's boundary or on a box face
    on_room = np.min(np.abs(np.concatenate([pts - scene.room_min, pts - scene.room_max], axis=1)), axis=1) < 1e-4
    on_box = np.zeros(len(pts), bool)
    for box in scene.boxes:
        q = np.abs((pts - box.centre) @ box.rotation) - box.half_size
        on_box |= (np.abs(q).min(axis=1) < 1e-4) & (q.max(axis=1) < 1e-4)
    assert np.all(on_room | on_box)
    assert on_box.any() and on_room.any()


def test_camera_path_and_motion_scale():
    slow = S.camera_path(40, motion_scale=1.0, fps=30.0)
    fast = S.camera_path(40, motion_scale=3.0, fps=30.0)
    step = np.linalg.norm(np.diff(slow.positions, axis=0), axis=1)
    assert 0.008 < step.mean() < 0.03
    np.testing.assert_allclose(slow.timestamps, np.arange(40) / 30.0)
    # motion_scale speeds the camera along the same curve: frame k of the fast path is frame 3k of the slow one
    np.testing.assert_allclose(fast.cam_to_world[:13], slow.cam_to_world[0:39:3], atol=1e-12)
    R = slow.cam_to_world[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    angles = np.degrees(np.arccos(np.clip((np.trace(np.swapaxes(R[:-1], 1, 2) @ R[1:], axis1=1, axis2=2) - 1) / 2,
                                          -1, 1)))
    assert 0.05 < angles.mean() < 1.5  # it rotates, smoothly
    assert np.all(slow.cam_to_world[:, 2, 2] > 0.7)  # looking into the room (+z)


def test_scene_has_smooth_and_textured_regions(seq):
    gray = seq.radiance[0].mean(-1)
    gy, gx = np.gradient(gray)
    g = np.hypot(gx, gy) * 255.0  # gray levels per pixel
    low = np.mean(g < 1.0)
    high = np.mean(g > 6.0)
    assert 0.1 < low < 0.8, low  # areas where MGSO must fill in with Delaunay points
    assert high > 0.05, high  # and plenty of trackable gradient
    assert seq.radiance[0].std(axis=(0, 1)).min() > 0.03  # colour, not gray


def test_edges_are_antialiased():
    scene = S.make_scene(0)
    cam = S.SyntheticCamera.from_fov(W, H, 70.0)
    T = S.camera_path(1).cam_to_world[0]
    ref, _ = S.render(scene, cam, T, supersample=6)
    plain, _ = S.render(scene, cam, T, supersample=1)
    aa, _ = S.render(scene, cam, T, supersample=2)
    # compare on geometric edge pixels (where the surface changes), against 6x6 supersampling there
    _, sid = S._cast(scene, T[:3, 3], S._pixel_grid(cam.fx, cam.fy, cam.cx, cam.cy, W, H)[2] @ T[:3, :3].T,
                     *S._pixel_grid(cam.fx, cam.fy, cam.cx, cam.cy, W, H)[:2], np.linalg.inv(T),
                     (cam.fx, cam.fy, cam.cx, cam.cy))
    edges = S._edge_pixels(sid.reshape(H, W))
    assert 0.01 < edges.mean() < 0.3
    e_plain = np.abs(plain - ref)[edges].mean()
    e_aa = np.abs(aa - ref)[edges].mean()
    assert e_aa < 0.6 * e_plain
    # away from edges the two agree closely (texture filtering is mip-mapped in both)
    assert np.abs(aa - plain)[~edges].max() < 1e-6


def test_exposure_changes_are_known_and_applied(tmp_path):
    s = S.make_sequence(seed=0, num_frames=20, width=64, height=48, exposure_variation=0.3,
                        exposure_period_frames=16, keep_radiance=True)
    g = s.gains
    assert g.min() < 0.85 and g.max() > 1.15
    np.testing.assert_allclose(s.exposures_ms, 10.0 * g)
    for i in (0, 7, 19):
        np.testing.assert_allclose(s.images[i], np.clip(g[i] * s.radiance[i], 0, 1), atol=1e-6)
    # the radiance itself does not change with exposure: the same scene point keeps its value
    flat = S.make_sequence(seed=0, num_frames=20, width=64, height=48, keep_radiance=True)
    np.testing.assert_array_equal(flat.radiance, s.radiance)
    assert np.all(flat.gains == 1.0)


def test_vignetting_and_noise_are_known_and_applied():
    s = S.make_sequence(seed=0, num_frames=2, width=W, height=H, vignette_strength=0.4, keep_radiance=True)
    V = s.vignette
    assert V[int(s.intrinsics.cy), int(s.intrinsics.cx)] == pytest.approx(1.0, abs=1e-3)
    assert V.min() == pytest.approx(0.6, abs=1e-6) and V[0, 0] == pytest.approx(0.6, abs=1e-6)
    np.testing.assert_allclose(s.images[1], np.clip(s.radiance[1] * V[..., None], 0, 1), atol=1e-6)
    n = S.make_sequence(seed=0, num_frames=2, width=W, height=H, noise_sigma=0.02, keep_radiance=True)
    resid = (n.images - n.radiance)[(n.radiance > 0.1) & (n.radiance < 0.8)]
    assert resid.std() == pytest.approx(0.02, rel=0.05) and abs(resid.mean()) < 1e-3
    n2 = S.make_sequence(seed=0, num_frames=2, width=W, height=H, noise_sigma=0.02)
    np.testing.assert_array_equal(n.images, n2.images)  # seeded noise


def _tree_digest(folder):
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_tum_folder_is_deterministic_and_parses(tmp_path):
    params = dict(seed=0, num_frames=6, width=W, height=H, exposure_variation=0.2, vignette_strength=0.3)
    a = S.write_tum_rgbd(tmp_path / "a", **params)
    b = S.write_tum_rgbd(tmp_path / "b", S.SequenceSpec(**params))
    seq = S.make_sequence(**params)
    c = S.write_tum_rgbd(tmp_path / "c", seq)  # from memory: the same bytes as streamed
    da = _tree_digest(a)
    assert da == _tree_digest(b) == _tree_digest(c)
    other = S.write_tum_rgbd(tmp_path / "d", **{**params, "seed": 1})
    assert _tree_digest(other)["rgb/0.000000.png"] != da["rgb/0.000000.png"]
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "camera.txt", "README.txt", "exposures.txt",
                 "vignette.png", "pcalib.txt", "synthetic.json"):
        assert (a / name).is_file(), name

    # rgb.txt / depth.txt: TUM 'timestamp filename' lines after '#' comments
    rows = [ln.split() for ln in (a / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    drows = [ln.split() for ln in (a / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == len(drows) == 6
    gt = read_tum(a / "groundtruth.txt")
    np.testing.assert_allclose(gt.timestamps, [float(r[0]) for r in rows])
    np.testing.assert_allclose(gt.cam_to_world, seq.cam_to_world, atol=1e-8)
    for k, ((t, f), (_, df)) in enumerate(zip(rows, drows)):
        img = cv2.imread(str(a / f), cv2.IMREAD_UNCHANGED)
        assert img.dtype == np.uint8 and img.shape == (H, W, 3)
        np.testing.assert_array_equal(cv2.cvtColor(img, cv2.COLOR_BGR2RGB),
                                      np.round(seq.images[k] * 255).astype(np.uint8))
        dep = cv2.imread(str(a / df), cv2.IMREAD_UNCHANGED)
        assert dep.dtype == np.uint16 and dep.shape == (H, W)
        np.testing.assert_allclose(dep / 5000.0, seq.depths[k], atol=0.5 / 5000 + 1e-6)
    lines = (a / "camera.txt").read_text().splitlines()
    head = lines[0].split()
    assert head[0] == "Pinhole" and len(lines) == 4 and lines[2] == "none"
    fx, fy, cx, cy, zero = map(float, head[1:])
    np.testing.assert_allclose([fx, fy, cx, cy, zero], [*np.diag(seq.K)[:2], seq.K[0, 2], seq.K[1, 2], 0], atol=1e-6)
    assert lines[1].split() == lines[3].split() == [str(W), str(H)]
    assert (cx, cy) == ((W - 1) / 2, (H - 1) / 2)
    ex = np.loadtxt(a / "exposures.txt")
    np.testing.assert_allclose(ex[:, 0], gt.timestamps, atol=1e-6)
    np.testing.assert_allclose(ex[:, 1], seq.exposures_ms, atol=1e-6)
    vig = cv2.imread(str(a / "vignette.png"), cv2.IMREAD_UNCHANGED)
    assert vig.dtype == np.uint16
    np.testing.assert_allclose(vig / 65535.0, seq.vignette, atol=1e-5)
    with pytest.raises(FileExistsError, match="not empty"):
        S.write_tum_rgbd(a, **params)
    S.write_tum_rgbd(a, overwrite=True, **{**params, "exposure_variation": 0.0, "num_frames": 3})
    assert not (a / "exposures.txt").exists() and len(list((a / "rgb").iterdir())) == 3
    a = S.write_tum_rgbd(a, overwrite=True, **params)
    readme = (a / "README.txt").read_text()
    assert "seed = 0" in readme and "z-depth" in readme
    assert json.loads((a / "synthetic.json").read_text())["seed"] == 0


def test_cached_sequence_folder_reuses(tmp_path):
    p1 = S.cached_sequence_folder(cache_dir=tmp_path, seed=0, num_frames=3, width=48, height=32)
    mtime = (p1 / "rgb.txt").stat().st_mtime_ns
    p2 = S.cached_sequence_folder(cache_dir=tmp_path, seed=0, num_frames=3, width=48, height=32)
    assert p1 == p2 and (p2 / "rgb.txt").stat().st_mtime_ns == mtime
    p3 = S.cached_sequence_folder(cache_dir=tmp_path, seed=0, num_frames=4, width=48, height=32)
    assert p3 != p1 and len(list((p3 / "rgb").iterdir())) == 4
    assert sorted(q.name for q in tmp_path.iterdir()) == sorted([p1.name, p3.name])  # no temporary leftovers
    with pytest.raises(TypeError, match="unknown synthetic sequence parameter"):
        S.cached_sequence_folder(cache_dir=tmp_path, seeed=3)


def test_bad_requests_are_refused():
    scene = S.make_scene(0)
    cam = S.SyntheticCamera.from_fov(W, H)
    T = np.eye(4)
    T[0, 3] = 10.0
    with pytest.raises(ValueError, match="outside the room"):
        S.render(scene, cam, T)
    T = np.eye(4)
    T[:3, 3] = scene.boxes[0].centre
    with pytest.raises(ValueError, match="inside a box"):
        S.render(scene, cam, T)
    with pytest.raises(ValueError, match="vignette strength"):
        S.vignette_factor(10, 10, 1.5)
    with pytest.raises(ValueError, match="num_frames"):
        S.SequenceSpec(num_frames=0)
    with pytest.raises(ValueError, match="vignette_strength"):
        S.SequenceSpec(vignette_strength=1.0)


def test_optional_photograph_on_the_far_wall():
    pytest.importorskip("matplotlib")
    with_photo = S.make_scene(0, texels_per_metre=32.0, photo=True)
    plain = S.make_scene(0, texels_per_metre=32.0)
    assert with_photo.photo and not plain.photo
    far_a, far_b = with_photo.surfaces[5].texture, plain.surfaces[5].texture
    changed = np.any(far_a != far_b, axis=-1)
    assert 0.01 < changed.mean() < 0.3  # a poster-sized patch, the rest of the wall as before
    np.testing.assert_array_equal(with_photo.surfaces[3].texture, plain.surfaces[3].texture)
