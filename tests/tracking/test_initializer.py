"""Monocular initialisation (DSO CoarseInitializer): the grid selection against DSO's loops, success on a synthetic
sequence with the structure right up to scale, and reported (not raised) failures."""

import numpy as np
import pytest

from mgso.config import TrackingConfig
from mgso.geometry import se3_inverse, se3_log
from mgso.tracking.initializer import CoarseInitializer, InitStatus, grid_max_selection, make_pixel_status
from mgso_kernels.image import ImagePyramid, Pinhole, plan_pyramid
from mgso_kernels.reference import image as ref_img
from tracking_helpers import gray_of


def loop_grid_max(dI, pot, th_fac):
    """DSO ``gridMaxSelection`` as its loops."""
    h, w = dI.shape[:2]
    out = np.zeros((h, w), bool)
    th = th_fac * 10 * 0.75
    for y in range(1, h - pot, pot):
        for x in range(1, w - pot, pot):
            best = [(-1, 0.0)] * 4
            for dx in range(pot):
                for dy in range(pot):
                    gx, gy = dI[y + dy, x + dx, 1], dI[y + dy, x + dx, 2]
                    if gx * gx + gy * gy > th * th:
                        for k, v in enumerate((abs(gx), abs(gy), abs(gx - gy), abs(gx + gy))):
                            if v > best[k][1]:
                                best[k] = ((x + dx, y + dy), v)
            for pos, _ in best:
                if pos != -1:
                    out[pos[1], pos[0]] = True
    return out


@pytest.mark.parametrize("pot,th", [(1, 1.0), (3, 1.0), (4, 0.5)])
def test_grid_selection_equals_dso_loops(rng, pot, th):
    img = rng.uniform(0, 255, (30, 41)).astype(np.float32)
    dI, _ = ref_img.gradients(img)
    np.testing.assert_array_equal(grid_max_selection(dI, pot, th), loop_grid_max(dI, pot, th))


def test_pixel_status_approaches_the_density(rng):
    img = rng.uniform(0, 255, (120, 160)).astype(np.float32)
    dI, _ = ref_img.gradients(img)
    m, sparsity = make_pixel_status(dI, 800, 5)
    assert 0.5 * 800 < m.sum() < 2.0 * 800 and sparsity >= 1


@pytest.fixture(scope="module")
def initialised(seq160):
    k = seq160.intrinsics
    geo = plan_pyramid(k.width, k.height, Pinhole(k.fx, k.fy, k.cx, k.cy))
    ini = CoarseInitializer(geo, TrackingConfig())
    pyr = ImagePyramid(geo)
    first = ini.set_first(pyr.build(gray_of(seq160.images[0])))
    results = []
    for i in range(1, 25):
        results.append(ini.track_frame(pyr.build(gray_of(seq160.images[i]))))
        if results[-1].status != InitStatus.TRACKING:
            break
    return geo, ini, first, results


def test_initialisation_succeeds_with_the_true_structure(wp_device, seq160, initialised):
    geo, ini, first, results = initialised
    assert first.status == InitStatus.FIRST_FRAME and first.num_points > 300
    assert [p.n > 0 for p in ini.points] == [True] * geo.levels and all(p.neighbours.shape[1] == 10
                                                                       for p in ini.points)
    r = results[-1]
    assert r.status == InitStatus.INITIALIZED, r
    snapped_at = next(i for i, x in enumerate(results) if x.snapped)
    # DSO: done when frameID > snappedAt + 5, i.e. on the 6th frame after the one that snapped
    assert len(results) == snapped_at + 1 + ini.config.init_frames_after_snap + 1
    n = r.frames
    T_true = se3_inverse(seq160.cam_to_world[n]) @ seq160.cam_to_world[0]
    t_est, t_true = r.first_to_new[:3, 3], T_true[:3, 3]
    assert t_est @ t_true / (np.linalg.norm(t_est) * np.linalg.norm(t_true)) > 0.98  # the direction ...
    rot_err = np.linalg.norm(se3_log(se3_inverse(T_true) @ r.first_to_new)[3:])
    assert rot_err < 0.003  # ... and the rotation are right (0.17 rad of true rotation)
    xy, iR, _ = ini.level0_points()
    depth = seq160.depths[0][xy[:, 1], xy[:, 0]]
    good = ini.points[0].is_good
    scale = np.median(iR[good] * depth[good])  # iR ~ scale / depth
    rel = np.abs(iR[good] * depth[good] / scale - 1)
    assert np.median(rel) < 0.05 and np.mean(rel < 0.2) > 0.8
    # pose and structure share one scale: estimated depths are true depths / scale, and so is the translation
    assert np.linalg.norm(t_est) / np.linalg.norm(t_true) == pytest.approx(1.0 / scale, rel=0.05)


def test_initialisation_failure_is_reported(wp_device, seq160):
    k = seq160.intrinsics
    geo = plan_pyramid(k.width, k.height, Pinhole(k.fx, k.fy, k.cx, k.cy))
    ini = CoarseInitializer(geo, TrackingConfig(init_max_frames=4))
    pyr = ImagePyramid(geo)
    black = ini.set_first(pyr.build(np.zeros((geo.height, geo.width), np.float32)))
    assert black.status == InitStatus.FAILED and "points" in black.message and not ini.has_first
    with pytest.raises(RuntimeError, match="set_first"):
        ini.track_frame(pyr)
    img = gray_of(seq160.images[0])
    assert ini.set_first(pyr.build(img)).status == InitStatus.FIRST_FRAME
    statuses = [ini.track_frame(pyr.build(img)).status for _ in range(4)]  # a camera that does not move
    assert statuses[:3] == [InitStatus.TRACKING] * 3 and statuses[3] == InitStatus.FAILED


def test_frames_after_snapping_count_the_cameras_frames_when_indices_are_given(wp_device, seq160):
    """In real time the frames that arrive while the initialiser works are dropped. Given the frames' indices, the
    frames after snapping are the camera's (DSO's 5), not the ones aligned: with every 3rd frame aligned it is done
    two aligned frames after snapping (the camera's 6 frames later) instead of 6. The control: consecutive
    indices and no indices give the same answers as each other, frame for frame."""
    k = seq160.intrinsics
    geo = plan_pyramid(k.width, k.height, Pinhole(k.fx, k.fy, k.cx, k.cy))
    pyr = ImagePyramid(geo)
    after = TrackingConfig().init_frames_after_snap

    def run(frames, indexed):
        ini = CoarseInitializer(geo, TrackingConfig(init_done_translation=10.0))  # the frame count decides
        ini.set_first(pyr.build(gray_of(seq160.images[frames[0]])), index=frames[0] if indexed else None)
        out = []
        for i in frames[1:]:
            r = ini.track_frame(pyr.build(gray_of(seq160.images[i])), index=i if indexed else None)
            out.append((i, r.status, r.snapped, r.first_to_new.round(12).tobytes()))
            if r.status != InitStatus.TRACKING:
                break
        return out

    every = list(range(0, 40))
    plain, counted = run(every, False), run(every, True)
    assert plain == counted and plain[-1][1] == InitStatus.INITIALIZED
    third = list(range(0, 40, 3))
    aligned = run(third, False)
    camera = run(third, True)
    snap = next(n for n, r in enumerate(camera) if r[2])
    assert aligned[-1][1] == camera[-1][1] == InitStatus.INITIALIZED
    assert len(aligned) == snap + 1 + after + 1                       # DSO: 6 aligned frames after the snap
    assert len(camera) == snap + 1 + after // 3 + 1                   # the camera's 6 frames: 2 aligned ones
    assert camera[-1][0] - camera[snap][0] == 3 * (after // 3 + 1) > after
