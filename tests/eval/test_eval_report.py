"""Metric report: strict JSON with qualifiers next to every figure."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mgso.eval import (PHOTO_SLAM, compute_ate, compute_rpe, evaluate_renders, format_report, metrics_report,
                       write_metrics_json)

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
