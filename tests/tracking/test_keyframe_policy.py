"""DSO's keyframe rule: large flow, brightness change, residual growth, and mgso's maximum interval."""

import math

import pytest

from mgso.config import TrackingConfig
from mgso.tracking.keyframe_policy import KeyframePolicy, KeyframeReason


@pytest.fixture
def policy():
    return KeyframePolicy.from_config(640, 480, TrackingConfig())


def test_small_motion_is_not_a_keyframe(policy):
    d = policy.decide((4.0, 0.0, 9.0), 1.01, rmse=5.0, first_rmse=4.0, frames_since_keyframe=3)
    assert not d.need and d.reason == KeyframeReason.NONE
    # DSO's weights at 640x480: 0.04 sqrt(4) + 0.02 sqrt(9) + 2 |log 1.01|
    assert d.score == pytest.approx(0.04 * 2 + 0.02 * 3 + 2 * math.log(1.01))


def test_large_flow_makes_a_keyframe(policy):
    # translation-only flow of 25 px (DSO threshold: 1 / 0.04 = 25 px at 640x480)
    assert not policy.decide((24.0 ** 2, 0, 0), 1.0, 5.0, 5.0, 1).need
    d = policy.decide((26.0 ** 2, 0, 0), 1.0, 5.0, 5.0, 1)
    assert d.need and d.reason == KeyframeReason.FLOW
    # full (rotation + translation) flow counts half as much: 50 px
    assert policy.decide((0, 0, 51.0 ** 2), 1.0, 5.0, 5.0, 1).need
    # relative to the image size: the same pixels count twice at half the size
    small = KeyframePolicy.from_config(320, 240, TrackingConfig())
    assert small.decide((13.0 ** 2, 0, 0), 1.0, 5.0, 5.0, 1).need


def test_brightness_change_makes_a_keyframe(policy):
    assert not policy.decide((0, 0, 0), math.exp(0.45), 5.0, 5.0, 1).need
    d = policy.decide((0, 0, 0), math.exp(-0.55), 5.0, 5.0, 1)  # |log a| > 1 / maxAffineWeight = 0.5
    assert d.need and d.reason == KeyframeReason.BRIGHTNESS


def test_residual_growth_and_interval(policy):
    d = policy.decide((0, 0, 0), 1.0, rmse=10.5, first_rmse=5.0, frames_since_keyframe=1)
    assert d.need and d.reason == KeyframeReason.RMSE
    assert not policy.decide((0, 0, 0), 1.0, rmse=10.5, first_rmse=-1.0, frames_since_keyframe=1).need
    assert not policy.decide((0, 0, 0), 1.0, 5.0, 5.0, 1000).need  # no interval limit by default (DSO)
    limited = KeyframePolicy.from_config(640, 480, TrackingConfig(kf_max_interval=10))
    d = limited.decide((0, 0, 0), 1.0, 5.0, 5.0, 10)
    assert d.need and d.reason == KeyframeReason.INTERVAL
    more = KeyframePolicy.from_config(640, 480, TrackingConfig(kf_global_weight=2.0))
    assert more.decide((13.0 ** 2, 0, 0), 1.0, 5.0, 5.0, 1).need  # twice the weight: half the flow
