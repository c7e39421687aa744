"""Odometry with the window bundle adjustment against the stand-in back end (poses fixed) on the synthetic room."""

import dataclasses

import numpy as np
import pytest

from mgso import synthetic
from mgso.config import Config
from mgso.eval import compute_ate
from mgso.io.sequence import Frame
from mgso.odometry import Odometry, geometry_for
from mgso.window.backend import WindowOptimizer
from mgso.window.depth_refine import FixedWindowBackEnd

GRAY = np.array([0.299, 0.587, 0.114], np.float32)


@pytest.fixture(scope="module")
def room():
    return synthetic.make_sequence(seed=0, num_frames=60, width=160, height=120)


def run(seq, backend):
    cfg = Config()
    cfg = dataclasses.replace(cfg, window=dataclasses.replace(cfg.window, backend=backend))
    k = seq.intrinsics
    odo = Odometry(geometry_for(k.width, k.height, k.fx, k.fy, k.cx, k.cy, cfg), cfg)
    for i, img in enumerate(seq.images):
        odo.process(Frame(i, float(seq.timestamps[i]), (img @ GRAY) * np.float32(255.0), None, rgb=img))
    odo.finish()
    return odo


def test_bundle_adjustment_beats_tracking_alone(wp_device, room):
    fixed = run(room, "fixed")
    bundle = run(room, "bundle")
    assert isinstance(fixed.back_end, FixedWindowBackEnd) and isinstance(bundle.back_end, WindowOptimizer)
    assert bundle.segment == 0 and len(bundle.trajectory()) >= 45
    ate_f = compute_ate(fixed.trajectory(), room.trajectory).rmse
    ate_b = compute_ate(bundle.trajectory(), room.trajectory).rmse
    kf_f = compute_ate(fixed.keyframe_trajectory(), room.trajectory).rmse
    kf_b = compute_ate(bundle.keyframe_trajectory(), room.trajectory).rmse
    # measured (75 cm path): with DSO's solver and depth prior (2026-11-22) all frames 1.76 mm vs 2.35 mm, keyframes
    # 1.28 vs 2.60 mm; before, 1.05 vs 2.35 and 0.72 vs 2.60 mm (an H100 run 1.41 vs 2.25 mm). Single synthetic runs
    # move by that much with any numerical change (the demo's room went the other way: 2.5 -> 1.3 mm)
    assert ate_b < 0.85 * ate_f, (ate_b, ate_f)
    assert kf_b < 0.6 * kf_f, (kf_b, kf_f)
    # the back end kept a prior and the points it marginalised are in the cloud with colours
    assert bundle.back_end.prior is not None and not bundle.back_end.prior.empty
    cloud = bundle.point_cloud
    assert len(cloud) > 100 and np.all((cloud.colors >= 0) & (cloud.colors <= 1))
