"""``mgso run PATH --stage tracking``: the files a user gets and the figures in metrics.json."""

import json

import pytest

from mgso import synthetic
from mgso.app.cli import main
from mgso.io.trajectory import read_tum
from mgso.app.outputs import METRICS_KEYS
from mgso.app.stages import STAGE_HELP, STAGES


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return synthetic.write_tum_rgbd(tmp_path_factory.mktemp("syn") / "room", seed=0, num_frames=30, width=160,
                                    height=120)


def test_tracking_stage_writes_trajectory_and_ate(wp_device, folder, tmp_path, capsys):
    assert "tracking" in STAGES and "tracking" in STAGE_HELP
    out = tmp_path / "run"
    assert main(["run", str(folder), "--out", str(out), "--stage", "tracking", "-q"]) == 0
    traj = read_tum(out / "trajectory.txt")
    kfs = read_tum(out / "keyframes.txt")
    metrics = json.loads((out / "metrics.json").read_text())
    fr = metrics["frames"]
    assert fr["processed"] == 30 and fr["in_trajectory"] == len(traj) and 15 <= len(traj) <= 30
    assert metrics["tracking"]["fraction_tracked"] == pytest.approx(len(traj) / 30)
    assert metrics["keyframes"]["in_trajectory"] == len(kfs) >= 3 and fr["tracking_lost"] == 0
    # the full stage's layout, the map's figures null (one writer for every stage: issue 44)
    assert set(METRICS_KEYS) <= set(metrics)
    assert metrics["stage"] == "tracking" and metrics["tracking"]["backend"] == "fixed"
    assert metrics["num_gaussians"] is None and metrics["mapper"] is None and not (out / "map.ply").exists()
    # the odometry's own figures, the per-frame ones read back from frames.csv
    t = metrics["tracking"]
    assert t["status_counts"]["tracked"] >= 10 and sum(t["status_counts"].values()) == 30
    assert t["track_ms_median"] > 0 and t["map_ms_median"] >= 0 and t["points"] > 100
    labels = [a["label"] for a in metrics["ate"]]
    assert labels == ["all frames", "keyframes"]
    assert metrics["ate"][0]["align"] == "sim3" and metrics["ate"][0]["translation_m"]["rmse"] < 0.02
    lines = (out / "frames.csv").read_text().splitlines()
    assert lines[0].startswith("index,timestamp,status") and len(lines) == 31
    assert (out / "points.ply").is_file() and (out / "groundtruth.txt").is_file()
    assert (out / "report.png").is_file() and (out / "trajectory.png").is_file()


def test_the_report_of_a_run_without_a_map_says_so(wp_device, folder, tmp_path):
    """report.png's text panel (one writer for every stage): no "None" where the map's figures would be."""
    from mgso.app.outputs import _headline

    out = tmp_path / "run"
    assert main(["run", str(folder), "--out", str(out), "--stage", "tracking", "-q"]) == 0
    text = "\n".join(_headline(json.loads((out / "metrics.json").read_text())))
    assert "map: none (the tracking stage: the odometry alone)" in text and "None" not in text
    assert "keyframes: " in text and "in the map" not in text
