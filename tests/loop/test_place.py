"""Place recognition (mgso.loop.place): ORB features with DSO's depths, and the keyframe database's candidates.

Synthetic views of the textured room at 320x240; DSO's points are stood in for by high-gradient pixels with their
rendered depth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mgso.camera import PinholeCamera
from mgso.config import LoopConfig
from mgso.loop.place import BinaryVocabulary, PlaceDatabase, extract_features
from mgso.synthetic import SyntheticCamera, camera_path, make_scene, render

from loop_helpers import dso_points

W, H = 320, 240
SCAM = SyntheticCamera.from_fov(W, H)
CAM = PinholeCamera(SCAM.fx, SCAM.fy, SCAM.cx, SCAM.cy, W, H)
PATH = camera_path(314).cam_to_world  # one whole figure-eight
PLACES = (0, 40, 80, 120, 160, 200, 240, 280)  # keyframes at distinct places along it
SETTINGS = LoopConfig()


def features_at(keyframe_id, pose, seed=0, scene=None):
    img, depth = render(scene or make_scene(0), SCAM, pose)
    uv, idp = dso_points(img, depth, seed=seed)
    return extract_features(keyframe_id, img, CAM, uv, idp, SETTINGS), img, depth, uv, idp


@pytest.fixture(scope="module")
def places():
    return {i: features_at(i, PATH[i], seed=i)[0] for i in PLACES}


@pytest.fixture(scope="module")
def revisit():
    """A view near place 120 (3 frames on: 4 cm and 2 degrees away), as a later keyframe."""
    return features_at(1000, PATH[123], seed=7)[0]


def test_features_take_the_nearest_points_depth_within_the_radius():
    f, img, depth, uv, idp = features_at(1, PATH[0], seed=3)
    uv, idp = uv[::3], idp[::3]  # sparser points, so that some keypoints have none within the radius
    uv = uv + np.random.default_rng(1).uniform(-0.5, 0.5, uv.shape)  # sub-pixel positions
    idp = idp * np.random.default_rng(2).uniform(0.9, 1.1, idp.shape)  # DSO's depths are not exact: tell them apart
    f = extract_features(1, img, CAM, uv, idp, SETTINGS)
    assert f.num_features > 300 and f.descriptors.shape == (f.num_features, 32) and f.descriptors.dtype == np.uint8
    d = np.linalg.norm(f.keypoints[:, None, :] - uv[None, :, :], axis=2)
    nearest = d.argmin(axis=1)
    within = d.min(axis=1) <= SETTINGS.depth_radius_px
    assert 50 < within.sum() < f.num_features - 50  # both kinds present, or this shows nothing
    np.testing.assert_array_equal(f.idepths[within], idp[nearest[within]])
    assert np.all(np.isnan(f.idepths[~within]))
    # the depth they carry is the scene's at the keypoint (within DSO's noise here and the 2-pixel offset)
    kp = np.round(f.keypoints[within]).astype(int)
    true = depth[kp[:, 1], kp[:, 0]]
    rel = np.abs(1.0 / f.idepths[within] - true) / true
    assert np.median(rel) < 0.06, np.median(rel)
    # descriptors on DSO's points themselves (LDSO), as many as ORB's patch allows away from the border
    on_points = d.min(axis=1) == 0.0
    inside = np.all((uv >= 32) & (uv <= [W - 33, H - 33]), axis=1)
    assert on_points.sum() >= 0.9 * min(inside.sum(), SETTINGS.orb_features), (on_points.sum(), inside.sum())
    # the others are OpenCV's corners, none within the radius of a point that has a descriptor
    corners = f.keypoints[~on_points]
    assert len(corners) > 50
    assert np.linalg.norm(corners[:, None] - f.keypoints[on_points][None], axis=2).min() > SETTINGS.depth_radius_px


def test_features_drop_bad_points_and_refuse_a_wrong_image():
    f, img, depth, uv, idp = features_at(2, PATH[0])
    bad = idp.copy()
    bad[::2] = np.nan
    g = extract_features(2, img, CAM, uv, bad, SETTINGS)
    assert len(g.points_idepth) == len(idp) - len(idp[::2]) and np.all(np.isfinite(g.points_idepth))
    with pytest.raises(ValueError, match="keyframe 2: image is 160x120, its camera 320x240"):
        extract_features(2, img[::2, ::2], CAM, uv, idp, SETTINGS)
    blank = extract_features(3, np.zeros((H, W, 3), np.float32), CAM, uv[:0], idp[:0], SETTINGS)  # nothing to describe
    assert blank.num_features == 0 and blank.descriptors.shape == (0, 32)


def test_database_ranks_the_revisited_place_first(places, revisit):
    db = PlaceDatabase(prefilter_above=0)
    for f in places.values():
        db.add(f)
    got = db.query(revisit, exclude=(), settings=SETTINGS)
    assert got and got[0].keyframe_id == 120, got
    assert len(got) <= SETTINGS.max_candidates and all(c.matches >= SETTINGS.min_matches for c in got)
    assert got[0].matches > 2 * max([c.matches for c in got[1:]] + [1])
    # excluded ids never come back, even when they are the best match or named as extra
    got = db.query(revisit, exclude=(120, 0), settings=SETTINGS, extra=(120, 0, 280))
    assert all(c.keyframe_id not in (120, 0) for c in got)
    # an extra id is verified whatever its appearance score
    strict = dataclasses.replace(SETTINGS, min_matches=10 ** 6)
    got = db.query(revisit, exclude=(), settings=strict, extra=(280,))
    assert [(c.keyframe_id, c.by_pose) for c in got] == [(280, True)]
    assert db.query(revisit, exclude=(), settings=strict) == []


def test_prefilter_keeps_the_revisited_place(places, revisit):
    exact = PlaceDatabase(prefilter_above=0)
    pre = PlaceDatabase(prefilter_above=4, prefilter_keep=3, vocabulary_words=128)
    for f in places.values():
        exact.add(f)
        pre.add(f)
    assert pre.vocabulary is not None and exact.vocabulary is None
    # the bag of words alone ranks the place first
    q = pre.vocabulary.bow(revisit.descriptors)
    sims = {k: float(pre.vocabulary.bow(f.descriptors) @ q) for k, f in places.items()}
    assert max(sims, key=sims.get) == 120, sims
    least = min(sims, key=sims.get)
    a = exact.query(revisit, (), SETTINGS)
    b = pre.query(revisit, (), SETTINGS, extra=(least,))
    assert exact.last_exact == len(PLACES) and pre.last_exact == 4  # 3 kept + the extra
    assert b[0] == a[0] and b[0].keyframe_id == 120
    assert least in [c.keyframe_id for c in b]


def test_vocabulary_is_deterministic(places):
    descs = [f.descriptors for f in places.values()]
    v1 = BinaryVocabulary.learn(descs, 64, seed=0)
    v2 = BinaryVocabulary.learn(descs, 64, seed=0)
    np.testing.assert_array_equal(v1.words, v2.words)
    np.testing.assert_array_equal(v1.idf, v2.idf)
    b = v1.bow(descs[0])
    assert b.shape == (64,) and abs(np.linalg.norm(b) - 1.0) < 1e-12
