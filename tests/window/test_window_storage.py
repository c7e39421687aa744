"""The window's keyframe slots and point buffers: who changes what, capacity errors, residual columns, zero-copy
Warp views, marginalisation into the point cloud."""

import numpy as np
import pytest
import warp as wp

from mgso.geometry import make_pose, se3_inverse, so3_exp
from mgso.window.window import (ActivePoints, ImmaturePoints, PointFlag, ResidualState, Window, WindowFullError)
from mgso_kernels.image import ImagePyramid, Pinhole, plan_pyramid

W, H = 96, 64


@pytest.fixture
def geo():
    return plan_pyramid(W, H, Pinhole(80.0, 80.0, 47.5, 31.5), levels=2)


def pyramid_of(geo, value=100.0, rgb=None):
    pyr = ImagePyramid(geo)
    img = np.full((geo.height, geo.width), value, np.float32)
    img += np.arange(geo.width, dtype=np.float32)[None, :]  # something non-constant
    return pyr.build(img)


def add_kf(win, geo, i, T=None, value=100.0):
    rgb = np.zeros((geo.height, geo.width, 3), np.float32)
    rgb[..., 0] = i / 10.0
    return win.add_keyframe(frame_index=i, timestamp=0.1 * i,
                            world_to_cam=np.eye(4) if T is None else T, pyramid=pyramid_of(geo, value), rgb=rgb)


def test_slots_order_and_capacity(wp_device, geo):
    win = Window(geo, max_frames=3, point_capacity=100, immature_capacity=100)
    assert win.capacity == 4
    slots = [add_kf(win, geo, i) for i in range(4)]
    assert win.order == slots and win.newest_slot == slots[-1]
    assert list(win.keyframe_id_[slots]) == [0, 1, 2, 3]
    with pytest.raises(WindowFullError):
        add_kf(win, geo, 4)
    win.remove_keyframe(slots[1])
    assert win.order == [slots[0], slots[2], slots[3]]
    s = add_kf(win, geo, 5)
    assert s == slots[1]  # the freed slot is reused ...
    assert win.order[-1] == s and win.keyframe_id_[s] == 4  # ... as the newest keyframe with a new id
    with pytest.raises(KeyError):
        win.remove_keyframe(99)


def test_add_keyframe_copies_pyramid_and_rgb(wp_device, geo):
    win = Window(geo, max_frames=3)
    pyr = pyramid_of(geo, 50.0)
    s = win.add_keyframe(frame_index=7, timestamp=1.0, world_to_cam=np.eye(4), pyramid=pyr,
                         rgb=np.full((geo.height, geo.width, 3), 0.25, np.float32), exposure=12.0)
    before = win.pyramids[s].intensity[0].numpy().copy()
    pyr.build(np.zeros((geo.height, geo.width), np.float32))  # the caller reuses its pyramid
    np.testing.assert_array_equal(win.pyramids[s].intensity[0].numpy(), before)
    assert np.all(win.rgb_[s] == 0.25) and win.exposure_[s] == 12.0 and win.frame_index_[s] == 7
    with pytest.raises(ValueError, match="rgb"):
        win.add_keyframe(frame_index=8, timestamp=1.1, world_to_cam=np.eye(4), pyramid=pyr,
                         rgb=np.zeros((3, 3, 3), np.float32))
    with pytest.raises(ValueError, match="finite"):
        win.add_keyframe(frame_index=8, timestamp=1.1, world_to_cam=np.full((4, 4), np.nan), pyramid=pyr)


def test_residual_columns_follow_keyframes(wp_device, geo):
    win = Window(geo, max_frames=4)
    s0 = add_kf(win, geo, 0)
    uv = np.array([[20.0, 20.0], [30.0, 25.0]], np.float32)
    win.add_active_points(host=[s0, s0], uv=uv, idepth=[0.5, 1.0], color=np.ones((2, 8)), weight=np.ones((2, 8)))
    a = win.active
    assert np.all(a.res_state == ResidualState.NONE)  # only the host exists
    s1 = add_kf(win, geo, 1)
    assert np.all(a.res_state[:, s1] == ResidualState.IN) and np.all(a.res_state[:, s0] == ResidualState.NONE)
    win.add_active_points(host=[s1], uv=uv[:1], idepth=[2.0], color=np.ones((1, 8)), weight=np.ones((1, 8)))
    assert a.res_state[2, s0] == ResidualState.IN and a.res_state[2, s1] == ResidualState.NONE
    with pytest.raises(RuntimeError, match="hosts"):
        win.remove_keyframe(s1)  # it still hosts an active point
    win.drop_points(a.host == s1)
    assert win.points_left_[s1] == 1
    win.remove_keyframe(s1)
    assert np.all(a.res_state[:, s1] == ResidualState.NONE)


def test_point_buffers_append_keep_and_full(wp_device, geo):
    im = ImmaturePoints(5)
    sl = im.append(3, host=[0, 1, 1], uv=np.arange(6, dtype=np.float32).reshape(3, 2), type=[1, 2, 4])
    assert sl == slice(0, 3) and im.n == 3
    assert np.isnan(im.idepth_max).all() and np.all(im.quality == 10000)  # DSO's initial state
    assert np.all(im.status == 5)  # UNINITIALIZED
    old = im.keep(np.array([True, False, True]))
    assert list(old) == [0, 2] and im.n == 2
    np.testing.assert_array_equal(im.uv, [[0, 1], [4, 5]])
    assert np.isnan(im.idepth_max_[2:]).all() and np.all(im.host_[2:] == -1)  # freed entries reset
    with pytest.raises(WindowFullError, match="capacity 5"):
        im.append(4)
    with pytest.raises(TypeError, match="unknown field"):
        im.append(1, colour=1.0)
    ap = ActivePoints(4, columns=3)
    assert ap.res_state_.shape == (4, 3)


def test_warp_views_are_zero_copy(wp_device, geo):
    im = ImmaturePoints(8, device="cpu")       # zero-copy views are the CPU storage's (a GPU copy is to_device's)
    im.append(4, uv=np.ones((4, 2), np.float32))
    w_uv = im.warp("uv")
    assert w_uv.dtype == wp.vec2 and w_uv.shape == (4,)
    w_q = im.warp("quality")
    w_q.fill_(3.0)  # a kernel writing through the view writes the window's storage
    assert np.all(im.quality == 3.0) and np.all(im.quality_[4:] == 10000)
    w_c = im.warp("color")
    assert w_c.shape == (4, 8) and w_c.ptr == im.color_.ctypes.data


def test_marginalize_points_back_projects_with_colour(wp_device, geo):
    win = Window(geo, max_frames=3)
    c2w = make_pose(so3_exp([0.0, 0.3, 0.0]), [1.0, 2.0, 3.0])
    s = add_kf(win, geo, 2, T=se3_inverse(c2w))
    cam = win.camera
    uv = np.array([[40.0, 30.0], [10.0, 50.0], [80.0, 5.0]], np.float32)
    idepth = np.array([0.5, 0.25, 2.0], np.float32)
    win.add_active_points(host=[s] * 3, uv=uv, idepth=idepth, color=np.ones((3, 8)), weight=np.ones((3, 8)))
    assert np.allclose(win.active.rgb[:, 0], 0.2) and np.allclose(win.active.rgb[:, 1:], 0.0)  # host RGB
    win.active.flag[:] = [PointFlag.MARGINALIZE, PointFlag.KEEP, PointFlag.DROP]
    out = win.remove_flagged_points()
    assert len(out) == 1 and win.active.n == 1 and win.points_left_[s] == 2
    d = 1.0 / 0.5
    pc = np.array([(40.0 - cam.cx) / cam.fx * d, (30.0 - cam.cy) / cam.fy * d, d])
    np.testing.assert_allclose(win.cloud.positions[0], c2w[:3, :3] @ pc + c2w[:3, 3], rtol=1e-5)
    np.testing.assert_allclose(win.cloud.colors[0], [0.2, 0.0, 0.0], atol=1e-6)
    assert win.cloud.point_ids[0] == 0 and len(win.cloud) == 1
    win.clear()
    assert win.num_keyframes == 0 and win.active.n == 0 and len(win.cloud) == 1  # the cloud outlives the window
