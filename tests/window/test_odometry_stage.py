"""``mgso run PATH --stage odometry``: trajectory, keyframes, coloured point cloud and ATE with the window BA."""

import json

import pytest
from plyfile import PlyData

from mgso import synthetic
from mgso.app.cli import main
from mgso.io.trajectory import read_tum
from mgso.app.stages import STAGE_HELP, STAGES


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return synthetic.write_tum_rgbd(tmp_path_factory.mktemp("syn") / "room", seed=0, num_frames=24, width=160,
                                    height=120)


def test_odometry_stage_writes_outputs(wp_device, folder, tmp_path):
    assert "odometry" in STAGES and "odometry" in STAGE_HELP
    out = tmp_path / "run"
    assert main(["run", str(folder), "--out", str(out), "--stage", "odometry", "-q"]) == 0
    traj = read_tum(out / "trajectory.txt")
    kfs = read_tum(out / "keyframes.txt")
    metrics = json.loads((out / "metrics.json").read_text())
    fr = metrics["frames"]
    assert fr["processed"] == 24 and fr["in_trajectory"] == len(traj) >= 12
    assert metrics["keyframes"]["in_trajectory"] == len(kfs) >= 3 and metrics["tracking"]["backend"] == "bundle"
    assert [a["label"] for a in metrics["ate"]] == ["all frames", "keyframes"]
    assert metrics["ate"][0]["translation_m"]["rmse"] < 0.01
    ply = PlyData.read(str(out / "points.ply"))
    v = ply["vertex"]
    assert len(v) > 100 and {"x", "y", "z", "red", "green", "blue"} <= set(v.data.dtype.names)
