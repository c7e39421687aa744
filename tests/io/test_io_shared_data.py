"""The readers on the real recordings in ../shared/data (skipped when absent; see its README for the numbers)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from mgso.camera import RadTanCamera
from mgso.config import InputConfig
from mgso.io import open_sequence, read_tum

pytestmark = pytest.mark.data


def test_kitti_excerpt(data_dir):
    seq = open_sequence(data_dir / "kitti00_0-159")
    assert seq.layout == "kitti" and len(seq) == 160
    cal = seq.calibration
    assert cal.input_size == cal.output_size == (1241, 376)
    out = cal.output
    assert (out.fx, out.fy, out.cx, out.cy) == (718.856, 718.856, 607.1928, 185.2157)  # calib.txt P0
    assert cal.undistorter.passthrough
    f = seq.load(159)
    assert f.gray.shape == (376, 1241) and f.rgb.shape == (376, 1241, 3) and f.exposure_ms is None
    gt = seq.groundtruth
    assert len(gt) == 160
    # the same poses as the TUM copy of the ground truth (independent file)
    tum = read_tum(data_dir / "kitti00_0-159" / "groundtruth_tum.txt")
    np.testing.assert_allclose(gt.positions, tum.positions, atol=1e-5)
    np.testing.assert_allclose(gt.timestamps, tum.timestamps, atol=1e-5)
    info = seq.describe()
    assert info["groundtruth"]["poses"] == 160 and info["image_size_in"] == [1241, 376]
    assert 117 < gt.path_length() < 118.5  # README: the car drives 117 m


def _t_bs(path):
    text = path.read_text().replace("%YAML:1.0", "")
    return np.array(yaml.safe_load(text)["T_BS"]["data"], dtype=np.float64).reshape(4, 4)


def test_euroc_excerpt_camera_poses_are_body_poses_times_T_BS(data_dir):
    root = data_dir / "euroc_v101_first95"
    seq = open_sequence(root)
    assert seq.layout == "euroc" and len(seq) == 95
    cal = seq.calibration
    assert isinstance(cal.input, RadTanCamera) and cal.input_size == (752, 480)
    assert cal.input.k1 == pytest.approx(-0.28340811) and cal.undistorter.kind == "remap"
    assert cal.output_mode == "keep"  # the default for a distorted lens
    valid = cal.undistorter.valid_mask
    yy, xx = np.nonzero(~valid)
    assert np.minimum(np.minimum(xx, 751 - xx), np.minimum(yy, 479 - yy)).max() < 3  # only the outer 3 px
    crop = open_sequence(root, config=InputConfig(rectify="crop", end=1)).calibration
    assert crop.undistorter.valid_mask.all()  # crop: every pixel has a source
    assert seq.fps == pytest.approx(20.0, rel=1e-4)
    body = read_tum(root / "groundtruth_body_tum.txt")
    T_BS = _t_bs(root / "mav0" / "cam0" / "sensor.yaml")
    gt = seq.groundtruth
    assert len(gt) == 95
    np.testing.assert_allclose(gt.cam_to_world[0], body.cam_to_world[0] @ T_BS, atol=1e-12)
    np.testing.assert_allclose(gt.cam_to_world[-1], body.cam_to_world[-1] @ T_BS, atol=1e-12)
    # camera and body differ by T_BS's lever arm of about 7 cm, not by nothing
    assert 0.05 < np.linalg.norm(gt.positions[0] - body.positions[0]) < 0.1
    f = seq.load(0)
    assert f.gray.shape == (480, 752) and f.gray.dtype == np.float32 and f.gray.min() >= 0
    full = open_sequence(root, config=InputConfig(rectify="full", end=1))
    assert not full.calibration.undistorter.valid_mask.all()  # full: corners without a source


def test_seven_scenes_excerpt(data_dir):
    root = data_dir / "7scenes_redkitchen_0-499"
    seq = open_sequence(root, config=InputConfig(stride=1))
    assert seq.layout == "7scenes" and len(seq) == 500 and seq.color
    out = seq.calibration.output
    assert (out.fx, out.fy, out.cx, out.cy, out.width, out.height) == (525.0, 525.0, 320.0, 240.0, 640, 480)
    gt = seq.groundtruth
    assert len(gt) == 500
    R = gt.cam_to_world[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    tum = read_tum(root / "groundtruth_tum.txt")  # the README's TUM copy, timestamp = index / 30
    np.testing.assert_allclose(gt.timestamps, tum.timestamps, atol=1e-6)
    np.testing.assert_allclose(gt.positions, tum.positions, atol=1e-6)
    f = seq.load(10)
    assert f.rgb.shape == (480, 640, 3) and f.gray.shape == (480, 640)
    d = seq.load_depth(10)
    assert d.dtype == np.float32 and 0.3 < np.median(d[d > 0]) < 5.0  # an indoor scene, in metres
