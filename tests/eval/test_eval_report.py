"""Metric report: strict JSON with qualifiers next to every figure."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mgso.eval import (PHOTO_SLAM, compute_ate, compute_rpe, evaluate_renders, format_report, metrics_report,
                       write_metrics_json)
from mgso.io.trajectory import Trajectory

from eval_traj_helpers import noisy_estimate, random_traj


def test_report_json_and_text(tmp_path):
    rng = np.random.default_rng(0)
    ref = random_traj(rng, 40)
    est = noisy_estimate(rng, ref)
    ate_all = compute_ate(est, ref, label="all frames")
    ate_kf = compute_ate(est.subset(slice(0, None, 4)), ref, label="keyframes")
    rpe = compute_rpe(est, ref)
    img = rng.random((16, 16, 3))
    renders = evaluate_renders([(img, img), (img * 0.9, img)], [0, 1], PHOTO_SLAM)  # frame 0: PSNR inf
    p = write_metrics_json(tmp_path / "out" / "metrics.json", ate=[ate_all, ate_kf], rpe=rpe, renders=renders,
                           extra={"sequence": "synthetic"})
    d = json.loads(p.read_text())  # strict JSON: json.loads would still accept Infinity, so check the text too
    assert "Infinity" not in p.read_text() and "NaN" not in p.read_text()
    assert [a["label"] for a in d["ate"]] == ["all frames", "keyframes"]
    assert d["ate"][0]["align"] == "sim3" and d["ate"][0]["translation_m"]["rmse"] == pytest.approx(ate_all.rmse)
    assert d["rpe"][0]["delta_unit"] == "frames" and d["sequence"] == "synthetic"
    assert d["render"][0]["protocol"] == PHOTO_SLAM.name and d["render"][0]["frames"][0]["psnr_db"] is None
    text = format_report(ate=[ate_all, ate_kf], rpe=rpe, renders=renders)
    lines = text.splitlines()
    assert len(lines) == 4 and "ATE RMSE of all frames" in lines[0] and "Sim(3)" in lines[0]
    assert "keyframes" in lines[1] and lines[2].startswith("RPE") and "Photo-SLAM" in lines[3]
    with pytest.raises(ValueError, match="clash"):
        metrics_report(ate=ate_all, extra={"ate": 1})


def test_the_report_warns_when_the_ate_is_worth_little(tmp_path):
    """An estimate whose scale collapses to a hundredth after its first tenth (a monocular odometry on a rotating
    camera, docs/evaluation.md): the report and metrics.json say that standing still would do about as well and that
    the scale drifts; test_report_json_and_text's good estimate gets no such line (its 4 lines)."""
    rng = np.random.default_rng(2)
    ref = random_traj(rng, 100)
    T = ref.cam_to_world.copy()
    steps = np.diff(ref.positions, axis=0) * np.r_[np.ones(10), np.full(89, 0.01)][:, None]
    T[1:, :3, 3] = ref.positions[0] + np.cumsum(steps, axis=0)
    ate = compute_ate(Trajectory(ref.timestamps, T), ref, label="all frames")
    lines = format_report(ate=ate).splitlines()
    assert "standing still" in lines[0] and "drifts" in lines[0]
    assert len(lines) == 3 and all(line.startswith("WARNING: ") for line in lines[1:])
    assert "standing still" in lines[1] and "scale of all frames drifts" in lines[2]
    d = json.loads(write_metrics_json(tmp_path / "metrics.json", ate=ate).read_text())
    assert d["ate"][0]["scale_drift"] > 50 and d["ate"][0]["motionless_rmse_m"] == pytest.approx(ate.motionless_rmse)
