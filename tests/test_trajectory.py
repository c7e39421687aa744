import numpy as np
import pytest

from mgso import geometry as g
from mgso.io.trajectory import (Trajectory, TrajectoryError, associate, matching_time_indices, read_kitti,
                                read_trajectory, read_tum, write_kitti, write_tum)


def random_traj(rng, n=20):
    T = g.se3_exp(rng.normal(size=(n, 6)))
    return Trajectory(np.arange(n) * 0.1 + 1000.0, T)


def test_tum_roundtrip(tmp_path, rng):
    tr = random_traj(rng)
    p = tmp_path / "t.txt"
    write_tum(p, tr)
    back = read_tum(p)
    assert np.allclose(back.timestamps, tr.timestamps)
    assert np.allclose(back.cam_to_world, tr.cam_to_world, atol=1e-8)
    assert read_trajectory(p).cam_to_world.shape == (20, 4, 4)


def test_kitti_roundtrip(tmp_path, rng):
    tr = random_traj(rng)
    p = tmp_path / "k.txt"
    write_kitti(p, tr)
    back = read_kitti(p, tr.timestamps)
    assert np.allclose(back.cam_to_world, tr.cam_to_world, atol=1e-8)
    assert np.allclose(read_trajectory(p).timestamps, np.arange(20))


@pytest.mark.parametrize("text, msg", [
    ("1 2 3\n", "expected 8 numbers"),
    ("1 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n", r":2: timestamp out of order \(0\.5 after 1\.0 on line 1\)"),
    ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", r":2: timestamp repeated \(1\.0 after 1\.0 on line 1\)"),
    ("1 0 0 0 0 0 0 x\n", "not a number"),
    ("1 0 0 0 0 0 0 0\n", "zero length"),
    ("# only a comment\n", "no poses"),
])
def test_bad_tum_files_name_file_and_line(tmp_path, text, msg):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(TrajectoryError, match=msg) as e:
        read_tum(p)
    assert "bad.txt" in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(TrajectoryError, match="not found"):
        read_trajectory(tmp_path / "nope.txt")


def test_association_nearest_within_tolerance():
    a = np.array([0.0, 1.0, 2.0, 3.0])
    b = np.array([0.004, 0.9, 2.009, 5.0])
    ia, ib = matching_time_indices(a, b, max_diff=0.01)
    assert ia.tolist() == [0, 2] and ib.tolist() == [0, 2]
    est = Trajectory(a, np.tile(np.eye(4), (4, 1, 1)))
    ref = Trajectory(b, np.tile(np.eye(4), (4, 1, 1)))
    e2, r2 = associate(est, ref, max_diff=0.01)
    assert len(e2) == len(r2) == 2
