"""ATE / RPE figure for figure against evo's Python API (github.com/MichaelGrupp/evo, in the test extra)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

evo = pytest.importorskip("evo")
from evo.core import metrics, sync  # noqa: E402
from evo.core.metrics import PoseRelation, Unit  # noqa: E402
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402
import evo.main_ape as evo_main_ape  # noqa: E402
import evo.main_rpe as evo_main_rpe  # noqa: E402

from mgso.eval.ate import ErrorStats, compute_ate, compute_rpe  # noqa: E402
from mgso.io.trajectory import Trajectory, associate, read_tum  # noqa: E402
from eval_traj_helpers import noisy_estimate, random_traj  # noqa: E402
from test_eval_ate import STATS, _files  # noqa: E402


def _evo_traj(tr: Trajectory) -> PoseTrajectory3D:
    return PoseTrajectory3D(poses_se3=[T.copy() for T in tr.cam_to_world], timestamps=tr.timestamps.copy())


def _evo_flags(align):
    return {"sim3": dict(align=True, correct_scale=True), "se3": dict(align=True, correct_scale=False),
            "none": dict(align=False, correct_scale=False)}[align]


def _evo_ape(ref: Trajectory, est: Trajectory, align, relation=PoseRelation.translation_part, n_to_align=-1,
             max_diff=0.01):
    r, e = sync.associate_trajectories(_evo_traj(ref), _evo_traj(est), max_diff=max_diff)
    res = evo_main_ape.ape(copy.deepcopy(r), copy.deepcopy(e), relation, n_to_align=n_to_align, **_evo_flags(align))
    return res


def _evo_rpe(ref, est, align, relation, delta, unit, all_pairs=False):
    r, e = sync.associate_trajectories(_evo_traj(ref), _evo_traj(est), max_diff=0.01)
    return evo_main_rpe.rpe(copy.deepcopy(r), copy.deepcopy(e), relation, delta=delta, delta_unit=unit,
                            all_pairs=all_pairs, **_evo_flags(align))


def _assert_stats(ours, theirs, tol=1e-9):
    for k in STATS:
        assert getattr(ours, k) == pytest.approx(theirs[k], rel=tol, abs=tol), k


@pytest.mark.data
@pytest.mark.parametrize("which", ["fr1", "kitti"])
@pytest.mark.parametrize("align", ["sim3", "se3", "none"])
def test_files_every_figure_matches_evo_api(data_dir, which, align):
    est_p, gt_p = _files(data_dir)[which]
    est, gt = read_tum(est_p), read_tum(gt_p)
    ours = compute_ate(est, gt, align=align)
    res = _evo_ape(gt, est, align)
    _assert_stats(ours.stats, res.stats)
    assert ours.num_pairs == len(res.np_arrays["error_array"])
    np.testing.assert_allclose(ours.errors, res.np_arrays["error_array"], atol=1e-12)
    # the estimate is what gets aligned, onto the ground truth: our aligned poses are evo's aligned estimate
    evo_est = res.trajectories["estimate"] if "estimate" in res.trajectories else list(res.trajectories.values())[1]
    np.testing.assert_allclose(ours.aligned_estimate.positions, evo_est.positions_xyz, atol=1e-9)
    rot = _evo_ape(gt, est, align, relation=PoseRelation.rotation_angle_deg)
    _assert_stats(ours.rotation_stats, rot.stats, tol=1e-7)
    for rel, field in ((PoseRelation.translation_part, "translation"), (PoseRelation.rotation_angle_deg, "rotation")):
        rr = _evo_rpe(gt, est, align, rel, 1, Unit.frames)
        _assert_stats(getattr(compute_rpe(est, gt, align=align), field), rr.stats, tol=1e-7)


@pytest.mark.data
def test_reference_and_estimate_are_not_interchangeable(data_dir):
    est_p, gt_p = _files(data_dir)["kitti"]
    est, gt = read_tum(est_p), read_tum(gt_p)
    right = compute_ate(est, gt, align="sim3")
    swapped = compute_ate(gt, est, align="sim3")
    # Sim(3) ATE is measured in the reference's units: aligning the ground truth onto the small estimate instead
    # would give a figure about scale-times smaller, not evo's.
    assert right.rmse == pytest.approx(0.257379, abs=1e-4)
    assert swapped.rmse < 0.5 * right.rmse


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("align", ["sim3", "se3", "none"])
def test_random_trajectories_match_evo_api(seed, align):
    rng = np.random.default_rng(seed)
    ref = random_traj(rng, 120)
    est = noisy_estimate(rng, ref)
    ours = compute_ate(est, ref, align=align)
    _assert_stats(ours.stats, _evo_ape(ref, est, align).stats)
    _assert_stats(compute_ate(est, ref, align=align, n_to_align=25).stats,
                  _evo_ape(ref, est, align, n_to_align=25).stats)
    for delta, unit, all_pairs in ((1, "frames", False), (4, "frames", False), (3, "frames", True),
                                   (0.5, "meters", False), (0.5, "meters", True)):
        evo_unit = Unit.frames if unit == "frames" else Unit.meters
        ours_r = compute_rpe(est, ref, align=align, delta=delta, delta_unit=unit, all_pairs=all_pairs)
        for rel, field in ((PoseRelation.translation_part, "translation"),
                           (PoseRelation.rotation_angle_deg, "rotation")):
            theirs = _evo_rpe(ref, est, align, rel, delta, evo_unit, all_pairs)
            _assert_stats(getattr(ours_r, field), theirs.stats, tol=1e-7)


def test_association_with_equal_lengths_follows_evo():
    # Equal lengths: evo matches the estimate's stamps against the reference's (sync.associate_trajectories).
    T = np.tile(np.eye(4), (4, 1, 1))
    est = Trajectory([0.0, 0.1, 0.2, 0.3], T)
    ref = Trajectory([0.0, 0.004, 0.2, 0.3], T)
    e, r = associate(est, ref)
    er, ee = sync.associate_trajectories(_evo_traj(ref), _evo_traj(est), max_diff=0.01)
    np.testing.assert_array_equal(e.timestamps, ee.timestamps)
    np.testing.assert_array_equal(r.timestamps, er.timestamps)
    assert len(e) == 3


def test_metrics_module_rmse_definition_matches_ours():
    # evo's statistics on a plain array (metrics.PE.get_all_statistics), against ErrorStats.
    e = np.random.default_rng(3).gamma(2.0, size=101)
    m = metrics.APE()
    m.error = e
    _assert_stats(ErrorStats.from_errors(e), m.get_all_statistics(), tol=1e-12)
