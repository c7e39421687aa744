"""ATE / RPE against evo (github.com/MichaelGrupp/evo): the printed figures of ``evo_ape`` and evo's Python API."""

from __future__ import annotations

import numpy as np
import pytest

from mgso import geometry as g
from mgso.eval.ate import (SCALE_PARTS, EvaluationError, compute_ate, compute_ate_files, compute_rpe, compute_rpe_files,
                           local_scales, motionless_rmse)
from mgso.io.trajectory import Trajectory

from eval_traj_helpers import random_traj

STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")


def _files(data_dir):
    t = data_dir / "trajectories"
    return {
        "fr1": (t / "fr1_xyz_rgbdslam_estimate.txt", t / "fr1_xyz_groundtruth.txt"),
        "kitti": (t / "kitti00_first160_fake_mono_est.txt", data_dir / "kitti00_0-159" / "groundtruth_tum.txt"),
    }


# ------------------------------------------------------------------------------------ figures evo prints
@pytest.mark.data
def test_fr1_xyz_se3_matches_evo_ape_printout(data_dir):
    est, gt = _files(data_dir)["fr1"]
    r = compute_ate_files(est, gt, align="se3")
    # `evo_ape tum fr1_xyz_groundtruth.txt fr1_xyz_rgbdslam_estimate.txt -a` (shared/data/README.md): RMSE 0.013470.
    assert r.rmse == pytest.approx(0.013470, abs=1e-4)
    # The rest of that printout (evo 1.38.1): max 0.034760 mean 0.012024 median 0.011183 min 0.000955 std 0.006071
    assert (r.max, r.mean, r.median, r.min, r.std) == pytest.approx(
        (0.034760, 0.012024, 0.011183, 0.000955, 0.006071), abs=2e-6)
    assert r.align == "se3" and r.scale == 1.0 and "SE(3)" in r.summary() and "0.013470" in r.summary()


@pytest.mark.data
def test_kitti_fake_mono_sim3_matches_evo_ape_printout(data_dir):
    est, gt = _files(data_dir)["kitti"]
    r = compute_ate_files(est, gt, align="sim3")
    # `evo_ape tum ../kitti00_0-159/groundtruth_tum.txt kitti00_first160_fake_mono_est.txt -as`: RMSE 0.257379 m.
    assert r.rmse == pytest.approx(0.257379, abs=1e-4)
    # evo 1.38.1 printout: max 0.553385 mean 0.235424 median 0.216432 min 0.043029 std 0.104019
    assert (r.max, r.mean, r.median, r.min, r.std) == pytest.approx(
        (0.553385, 0.235424, 0.216432, 0.043029, 0.104019), abs=2e-6)
    assert r.num_pairs == 160 and r.scale > 1.5  # the fake estimate is about 3x too small


@pytest.mark.data
def test_fr1_xyz_rpe_matches_evo_rpe_printout(data_dir):
    est, gt = _files(data_dir)["fr1"]
    r = compute_rpe_files(est, gt, align="se3", delta=1, delta_unit="frames")
    # `evo_rpe tum fr1_xyz_groundtruth.txt fr1_xyz_rgbdslam_estimate.txt -a` (evo 1.38.1): rmse 0.005764,
    # mean 0.004816, median 0.004139, max 0.020866, min 0.000171, std 0.003168.
    t = r.translation
    assert (t.rmse, t.mean, t.median, t.max, t.min, t.std) == pytest.approx(
        (0.005764, 0.004816, 0.004139, 0.020866, 0.000171, 0.003168), abs=2e-6)


def test_exact_similarity_is_recovered():
    rng = np.random.default_rng(5)
    ref = random_traj(rng, 50)
    # an exact Sim(3) copy of the reference (scale 1/4), no noise
    S = g.sim3_from_parts(g.so3_exp([0.3, -0.2, 0.9]), [1.0, -2.0, 0.5], 0.25)
    R, t, s = g.sim3_to_parts(S)
    T = ref.cam_to_world.copy()
    T[:, :3, 3] = s * ref.positions @ R.T + t
    T[:, :3, :3] = R @ ref.cam_to_world[:, :3, :3]
    exact = Trajectory(ref.timestamps, T)
    r = compute_ate(exact, ref, align="sim3")
    assert r.rmse < 1e-9 and r.rotation_stats.max < 1e-5
    assert r.scale == pytest.approx(4.0, rel=1e-9)
    np.testing.assert_allclose(r.alignment.matrix() @ S, np.eye(4), atol=1e-9)
    assert compute_rpe(exact, ref, align="sim3").translation.max < 1e-9
    # without scale correction the relative translations are 4x too short
    rigid = compute_rpe(exact, ref, align="se3")
    steps = np.linalg.norm(np.diff(ref.positions, axis=0), axis=1)
    assert rigid.translation.mean == pytest.approx(0.75 * steps.mean(), rel=1e-6)
    assert compute_ate(exact, ref, align="se3").rmse > 0.1


def test_too_few_pairs_says_how_many_and_where():
    rng = np.random.default_rng(0)
    ref = random_traj(rng, 30, t0=100.0)
    est = random_traj(rng, 30, t0=200.0)
    with pytest.raises(EvaluationError) as e:
        compute_ate(est, ref)
    msg = str(e.value)
    assert "only 0 pose pairs" in msg and "max_diff = 0.01 s" in msg
    assert "t = [200.000000, 202.900000]" in msg and "t = [100.000000, 102.900000]" in msg
    with pytest.raises(EvaluationError, match="only 2 pose pairs"):
        compute_ate(Trajectory(ref.timestamps[:2], ref.cam_to_world[:2]), ref)
    with pytest.raises(EvaluationError, match="align must be"):
        compute_ate(ref, ref, align="sim2")


def test_static_estimate_cannot_be_sim3_aligned():
    rng = np.random.default_rng(0)
    ref = random_traj(rng, 20)
    still = Trajectory(ref.timestamps, np.tile(np.eye(4), (20, 1, 1)))
    with pytest.raises(EvaluationError, match="does not move"):
        compute_ate(still, ref, align="sim3")
    assert compute_ate(still, ref, align="se3").num_pairs == 20


def test_files_error_names_the_files(tmp_path):
    rng = np.random.default_rng(0)
    from mgso.io.trajectory import write_tum

    write_tum(tmp_path / "gt.txt", random_traj(rng, 10, t0=0.0))
    write_tum(tmp_path / "est.txt", random_traj(rng, 10, t0=50.0))
    with pytest.raises(EvaluationError) as e:
        compute_ate_files(tmp_path / "est.txt", tmp_path / "gt.txt")
    assert "est.txt" in str(e.value) and "gt.txt" in str(e.value)


def test_rpe_options_are_checked():
    rng = np.random.default_rng(0)
    ref = random_traj(rng, 10)
    with pytest.raises(EvaluationError, match="whole number"):
        compute_rpe(ref, ref, delta=1.5)
    with pytest.raises(EvaluationError, match="delta_unit"):
        compute_rpe(ref, ref, delta_unit="seconds")
    with pytest.raises(EvaluationError, match="no pose pair"):
        compute_rpe(ref, ref, delta=50)
    r = compute_rpe(ref, ref, delta=2, delta_unit="f", align="none")
    assert r.translation.max < 1e-15 and len(r.id_pairs) == 4 and "RPE" in r.summary()
    d = r.as_dict()
    assert d["num_deltas"] == 4 and d["translation_m"]["rmse"] < 1e-15


# ---------------------------------------------------------------------------- what an ATE is worth (not in evo)
def _scaled_path(ref: Trajectory, scales) -> Trajectory:
    """``ref`` with each step's translation multiplied by ``scales[k]`` (a monocular odometry whose scale drifts)."""
    T = ref.cam_to_world.copy()
    steps = np.diff(ref.positions, axis=0) * np.asarray(scales, dtype=np.float64)[:, None]
    T[1:, :3, 3] = ref.positions[0] + np.cumsum(steps, axis=0)
    return Trajectory(ref.timestamps, T)


def test_standing_still_is_the_ate_of_an_estimate_that_never_moves():
    rng = np.random.default_rng(3)
    ref = random_traj(rng, 60)
    still = Trajectory(ref.timestamps, np.tile(np.eye(4), (60, 1, 1)))
    # what SE(3) alignment leaves of a constant estimate is the reference's spread about its mean
    r = compute_ate(still, ref, align="se3")
    assert r.rmse == pytest.approx(r.motionless_rmse, rel=1e-9)
    assert r.motionless_rmse == pytest.approx(motionless_rmse(ref.positions), rel=1e-12)
    assert any("standing still" in w for w in r.warnings())
    # an estimate whose positions are right is far below it, and says nothing
    good = compute_ate(_scaled_path(ref, np.full(59, 0.3)), ref, align="sim3")
    assert good.rmse < 1e-9 and good.motionless_rmse > 0.1 and good.warnings() == []
    assert "standing still" in good.summary() and good.as_dict()["motionless_rmse_m"] == good.motionless_rmse
    # a scale collapsed to a hundredth after the first tenth: the Sim(3) ATE is near what standing still gets
    collapsed = compute_ate(_scaled_path(ref, np.r_[np.ones(6), np.full(53, 0.01)]), ref, align="sim3")
    assert collapsed.rmse > 0.8 * collapsed.motionless_rmse


def test_local_scales_follow_a_drifting_scale():
    rng = np.random.default_rng(4)
    ref = random_traj(rng, 200)
    # held scale: every part's scale is the whole's
    held = compute_ate(_scaled_path(ref, np.full(199, 0.25)), ref, align="sim3")
    np.testing.assert_allclose(held.local_scales, 1.0, rtol=1e-9)
    assert len(held.local_scales) == SCALE_PARTS and held.scale_drift == pytest.approx(1.0, rel=1e-9)
    # the estimate's scale shrinks 16x along the way (a step's translation from 1 to 1/16): the parts' scales
    # (reference over estimate) grow by about that, and the drift says so
    decay = np.geomspace(1.0, 1 / 16, 199)
    r = compute_ate(_scaled_path(ref, decay), ref, align="sim3")
    assert np.all(np.diff(r.local_scales) > 0)
    assert 8 < r.scale_drift < 16
    assert any("drifts" in w for w in r.warnings()) and "drifts" in r.summary()
    assert r.as_dict()["scale_drift"] == r.scale_drift and len(r.as_dict()["local_scales"]) == SCALE_PARTS
    # parts whose reference hardly moves do not count: a reference at rest for its first half
    T = ref.cam_to_world.copy()
    T[:100, :3, 3] = T[100, :3, 3]
    rest = Trajectory(ref.timestamps, T)
    assert len(local_scales(_scaled_path(rest, np.full(199, 0.5)).positions, rest.positions)) == SCALE_PARTS // 2
    # an estimate at one point in a part gives inf there, and an infinite drift
    est = _scaled_path(ref, np.r_[np.ones(100), np.zeros(99)]).positions
    s = local_scales(est, ref.positions)
    assert np.isinf(s[-1]) and np.all(np.isfinite(s[:5]))
    # ... and so does one that moves by less than the alignment can take (1e-7 m: Umeyama refuses it), as a run's
    # second segment did on freiburg1_rpy; a wholly motionless estimate gives no parts, never an error
    est[100:] += rng.normal(scale=1e-7, size=(100, 3))
    r = compute_ate(_scaled_path(ref, np.r_[np.ones(100), np.full(99, 1e-8)]), ref, align="sim3")
    assert np.isinf(r.local_scales[-1]) and np.isinf(r.scale_drift)
    assert np.isinf(local_scales(est, ref.positions)[-1])
    assert len(local_scales(np.zeros((200, 3)) + 1e-7 * rng.normal(size=(200, 3)), ref.positions)) == 0
