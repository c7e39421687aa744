"""Trajectory plot: a real PNG, the plane choice, and the clear error without matplotlib."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from mgso.eval.ate import compute_ate
from mgso.eval.plot import MatplotlibMissingError, choose_plane, plot_trajectory
from mgso.io.trajectory import Trajectory

from eval_traj_helpers import noisy_estimate


def _ground_trajectory(n=80):
    """A camera-convention path: moves in x-z, y (down) nearly constant."""
    s = np.linspace(0, 2 * np.pi, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = 2.0 * np.sin(s)
    T[:, 2, 3] = 3.0 * np.sin(2 * s)
    T[:, 1, 3] = 0.02 * np.cos(s)
    return Trajectory(np.arange(n) * 0.1, T)


def test_choose_plane_drops_the_flattest_axis():
    ref = _ground_trajectory()
    assert choose_plane(ref.positions) == "xz"
    assert choose_plane(ref.positions[:, [0, 2, 1]]) == "xy"
    assert choose_plane(ref.positions[:, [1, 0, 2]]) == "yz"


def test_plot_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    rng = np.random.default_rng(0)
    ref = _ground_trajectory()
    est = noisy_estimate(rng, ref, scale=0.5, jitter=0.0, drop=0.2)
    ate = compute_ate(est, ref, align="sim3", label="all frames")
    out = plot_trajectory(tmp_path / "sub" / "traj.png", ate, reference=ref,
                          keyframe_timestamps=est.timestamps[::10])
    assert out.is_file() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = cv2.imread(str(out))
    assert img.shape[0] > 400 and img.shape[1] > 500
    # something is drawn: many distinct colours (the colour-mapped estimate, grey ground truth, text)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50
    with pytest.raises(ValueError, match="plane must be"):
        plot_trajectory(tmp_path / "x.png", ate, plane="ab")


def test_missing_matplotlib_says_how_to_install(tmp_path, monkeypatch):
    ref = _ground_trajectory(20)
    ate = compute_ate(ref, ref, align="se3")
    monkeypatch.setitem(sys.modules, "matplotlib.backends.backend_agg", None)
    with pytest.raises(MatplotlibMissingError, match=r"pip install matplotlib"):
        plot_trajectory(tmp_path / "t.png", ate)
