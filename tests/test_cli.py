"""The command line as a user runs it: exit codes, one-line errors, files written."""

import json

import pytest

from mgso import synthetic
from mgso.app.cli import main
from mgso.io.trajectory import read_tum


@pytest.fixture(scope="module")
def tiny_folder(tmp_path_factory):
    return synthetic.write_tum_rgbd(tmp_path_factory.mktemp("syn") / "room", seed=1, num_frames=6, width=96,
                                    height=72)


def test_info_describes_synthetic_folder(tiny_folder, capsys):
    assert main(["info", str(tiny_folder), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["layout"] == "tum_rgbd" and info["frames"] == 6
    assert info["image_size_out"] == [96, 72]
    assert info["groundtruth"]["present"] and info["groundtruth"]["poses"] == 6


def test_run_check_writes_outputs(tiny_folder, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(tiny_folder), "--out", str(out), "--stage", "check", "-q"]) == 0
    assert (out / "config.yaml").is_file() and (out / "sequence.json").is_file()
    gt = read_tum(out / "groundtruth.txt")
    assert len(gt) == 6


def test_run_downscale_halves_the_frames(tiny_folder, tmp_path, capsys):
    """``mgso run --downscale 2`` reads the frames at half the width and height (the intrinsics with them); 1 leaves
    them as they are; 0 or a size under 16x16 is a one-line error before any work."""
    out = tmp_path / "half"
    assert main(["run", str(tiny_folder), "--out", str(out), "--stage", "check", "-q", "--downscale", "2"]) == 0
    info = json.loads((out / "sequence.json").read_text())
    assert info["image_size_out"] == [48, 36] and info["intrinsics"]["fx"] < 40
    assert main(["run", str(tiny_folder), "--out", str(tmp_path / "same"), "--stage", "check", "-q",
                 "--downscale", "1"]) == 0
    assert json.loads((tmp_path / "same" / "sequence.json").read_text())["image_size_out"] == [96, 72]
    for bad, msg in (("0", "must be >= 1"), ("5", "smaller than 16x16")):
        assert main(["run", str(tiny_folder), "--out", str(tmp_path / f"b{bad}"), "--stage", "check",
                     "--downscale", bad]) == 1
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err and not (tmp_path / f"b{bad}").exists()


def test_large_frames_on_the_cpu_get_a_hint(caplog):
    """A full run of frames much larger than 640x480 on the CPU says once how to train at a smaller size; 640x480
    frames get no word (the control)."""
    from mgso.app import cli
    from mgso.camera import PinholeCamera
    from mgso.config import load_config

    cfg = load_config(None, ["runtime.device=cpu"])
    with caplog.at_level("WARNING", logger="mgso"):
        cli._hint_large_frames(PinholeCamera(1552.0, 1549.0, 955.8, 586.0, 1920, 1080), cfg)
        cli._hint_large_frames(PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480), cfg)
    hints = [r.getMessage() for r in caplog.records]
    assert len(hints) == 1 and "1920x1080 frames on the CPU" in hints[0] and "--downscale 3 runs at 640x360" in hints[0]


def test_errors_are_one_line_and_exit_1(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nothing")]) == 1
    err = capsys.readouterr().err
    assert "nothing" in err and "Traceback" not in err
    assert main(["info", str(tmp_path), "--set", "window.max_frames=many"]) == 1
    assert "expected an integer" in capsys.readouterr().err
    bad = tmp_path / "est.txt"
    bad.write_text("0 0 0\n")
    assert main(["eval", str(bad), "--gt", str(bad)]) == 1
    assert "est.txt" in capsys.readouterr().err


def test_eval_prints_evo_figures(data_dir, tmp_path, capsys):
    """evo's figures for these files are given in ../shared/data/README.md (evo_ape -a / -as)."""
    tr = data_dir / "trajectories"
    assert main(["eval", str(tr / "fr1_xyz_rgbdslam_estimate.txt"), "--gt", str(tr / "fr1_xyz_groundtruth.txt"),
                 "--align", "se3", "--json"]) == 0
    se3 = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert abs(se3["translation_m"]["rmse"] - 0.013470) < 1e-4
    assert main(["eval", str(tr / "kitti00_first160_fake_mono_est.txt"), "--gt", str(data_dir / "kitti00_0-159"),
                 "--align", "sim3", "--json", "--out", str(tmp_path)]) == 0
    sim3 = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert abs(sim3["translation_m"]["rmse"] - 0.257379) < 1e-4
    assert (tmp_path / "metrics.json").is_file() and (tmp_path / "trajectory.png").is_file()
    # the ground truth came from a dataset folder: what was read is written as a run writes it (issue 44)
    assert json.loads((tmp_path / "sequence.json").read_text())["layout"] == "kitti"
    assert (tmp_path / "groundtruth.txt").is_file()
