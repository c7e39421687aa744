"""MGSO's mapper (mgso.mapping.mapper) and its messages (mgso.messages), driven by hand-made messages."""

from __future__ import annotations

import dataclasses
import math
import threading

import numpy as np
import pytest

from mgso import synthetic
from mgso.camera import PinholeCamera
from mgso.config import ConfigError, load_config
from mgso.geometry import se3_exp, se3_inverse
from mgso.mapping.mapper import Mapper, MapperError
from mgso.messages import KeyframeMessage, PointsMessage, PointKind, PoseUpdate, Stop, map_exposure
from mgso.mapping.seeding import backproject


@pytest.fixture(scope="module")
def seq():
    return synthetic.make_sequence(seed=0, num_frames=9, width=80, height=60, motion_scale=2.0)


@pytest.fixture(scope="module")
def cam(seq):
    k = seq.intrinsics
    return PinholeCamera(k.fx, k.fy, k.cx, k.cy, k.width, k.height)


def _grid(cam, step=5, margin=2):
    u, v = np.meshgrid(np.arange(margin, cam.width - margin, step), np.arange(margin, cam.height - margin, step))
    return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)


def _kf(seq, cam, i, kid=None, pose=None, **kw):
    uv = _grid(cam)
    ui = uv.astype(int)
    z = seq.depths[i][ui[:, 1], ui[:, 0]].astype(np.float64)
    return KeyframeMessage(i if kid is None else kid, i, float(seq.timestamps[i]), seq.images[i], cam,
                           seq.cam_to_world[i] if pose is None else pose, uv, 1.0 / z, **kw)


def _cfg(*over):
    # DSO's affine as the views' exposure, the alpha rule alone and the odometry's poses as they are: what these
    # tests check (the defaults' other modes, pose refinement among them, have their own tests)
    return load_config(None, ["mapping.mapper.iterations_per_keyframe=3", "mapping.mapper.final_iterations=4",
                              "mapping.capacity=20000", "mapping.mapper.exposure=odometry",
                              "mapping.seeding.depth_tolerance=0", "mapping.train.refine_poses=false", *over])


# ------------------------------------------------------------------------------------------------ messages
def test_messages_check_their_fields(seq, cam):
    m = _kf(seq, cam, 0)
    assert not m.image.flags.writeable and not m.points_uv.flags.writeable and m.kinds.dtype == np.int8
    assert m.num_points == len(_grid(cam))
    with pytest.raises(ValueError, match="image"):
        _kf(seq, cam, 0).__class__(0, 0, 0.0, seq.images[0][:, :10], cam, np.eye(4), m.points_uv, m.idepths)
    with pytest.raises(ValueError, match="idepths"):
        KeyframeMessage(0, 0, 0.0, seq.images[0], cam, np.eye(4), m.points_uv, m.idepths[:-1])
    with pytest.raises(ValueError, match="rigid"):
        KeyframeMessage(0, 0, 0.0, seq.images[0], cam, 2 * np.eye(4), m.points_uv, m.idepths)
    with pytest.raises(ValueError, match="kinds"):
        KeyframeMessage(0, 0, 0.0, seq.images[0], cam, np.eye(4), m.points_uv, m.idepths,
                        kinds=np.full(m.num_points, 9))
    with pytest.raises(ValueError, match="affine"):
        KeyframeMessage(0, 0, 0.0, seq.images[0], cam, np.eye(4), m.points_uv, m.idepths, affine=(math.nan, 0))
    with pytest.raises(ValueError, match=r"PoseUpdate.cam_to_world\[3\]"):
        PoseUpdate({3: np.ones((4, 4))})
    with pytest.raises(ValueError, match="colors"):
        PointsMessage(np.zeros((4, 3)), np.zeros((3, 3)), 0)
    drift = np.eye(4)
    drift[:3, :3] += 1e-3 * np.array([[0.0, 1.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 1.0]])   # round-off of a chain
    m = KeyframeMessage(0, 0, 0.0, seq.images[0], cam, drift, m.points_uv, m.idepths)
    R = m.cam_to_world[:3, :3]
    assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12 and np.abs(R - drift[:3, :3]).max() < 2e-3
    u = PoseUpdate({2: np.eye(4)}, affine={2: (0.1, 2.0)})
    assert u.keyframe_ids == [2] and u.affine[2] == (0.1, 2.0)
    with pytest.raises(TypeError):
        u.cam_to_world[5] = np.eye(4)          # read-only mapping


def test_map_exposure_follows_dsos_model():
    # DSO: I = t e^a L + b (0-255); trainer: image = exp(a') render + b' ([0, 1]); render = L t_ref / 255
    a, b, t, t_ref = 0.2, 12.0, 20.0, 10.0
    ap, bp = map_exposure((a, b), t, t_ref)
    L = 100.0
    image01 = (t * math.exp(a) * L + b) / 255.0
    render = L * t_ref / 255.0
    assert math.exp(ap) * render + bp == pytest.approx(image01)
    assert map_exposure((a, b), None, t_ref) == pytest.approx((a, b / 255.0))   # unknown exposure: DSO uses 1


def test_config_checks_mapper_and_system():
    with pytest.raises(ConfigError, match="mapping.mapper"):
        load_config(None, ["mapping.mapper.queue_size=0"])
    with pytest.raises(ConfigError, match="init"):
        load_config(None, ["mapping.mapper.init=grid"])
    with pytest.raises(ConfigError, match="system.mode"):
        load_config(None, ["system.mode=fast"])


# ------------------------------------------------------------------------------------------ deterministic
def test_the_default_schedule_is_what_the_measurements_chose(wp_device, seq, cam):
    """Issue 44: the mapper's default schedule, which docs/mapping.md's 7-Scenes measurements chose (uniform
    keyframe sampling, 20 steps a keyframe, 1,300 final steps: 22.26 dB, against 18.25 dB with least_used and
    21.51 dB with a fifth of the steps on the newest keyframe; since 2026-12-06 2,000 final steps, the first 80 %
    coarse, in the deterministic mode: 23.11 dB; since the fifth session that day the steps after each keyframe
    coarse and the final's first 60 %: 23.10 dB in 27 % less mapping time; since 2026-12-07 the final's first 80 %
    where the coarse level keeps detail, the first 40 % a level coarser still: 24.59 -> 24.64 dB in 16 % less), was
    pinned by no test. Run as the mapper runs it: each keyframe trains 20 steps, the final refinement asks for 2,000
    (1,600 in real time), and the views are drawn half uniformly, half by their latest losses (since 2026-12-07;
    uniformly in real time and with loss_share 0)."""
    from mgso.config import Config
    from mgso.mapping.views import NewestOrRandomSampler

    mc = Config().mapping.mapper
    assert (mc.sampler, mc.newest_probability, mc.iterations_per_keyframe, mc.final_iterations) == \
        ("random", 0.0, 20, None)
    # half of each draw by the keyframes' losses in the deterministic mode (2026-12-07), uniform in real time
    assert mc.loss_share is None
    assert (mc.draw_loss_share(realtime=False), mc.draw_loss_share(realtime=True)) == (0.5, 0.0)
    assert (mc.final_steps(realtime=False), mc.final_steps(realtime=True)) == (2000, 1600)
    assert (mc.final_share_coarser(realtime=False), mc.final_share_coarser(realtime=True)) == (0.4, 0.6)
    # the deterministic final refinement's coarse share: 0.8 where the coarse level keeps detail (7-Scenes' 320x240),
    # 0.6 below (KITTI's 310x94) or where the level is not known; 0.95 in real time whatever the level
    assert (mc.final_share_coarse(realtime=False, coarse_pixels=320 * 240),
            mc.final_share_coarse(realtime=False, coarse_pixels=310 * 94),
            mc.final_share_coarse(realtime=False), mc.final_share_coarse(realtime=True),
            mc.final_share_coarse(realtime=True, coarse_pixels=320 * 240)) == (0.8, 0.6, 0.6, 0.95, 0.95)
    assert mc.keyframe_steps_coarse is True
    # real time on the CPU: the final refinement's coarse steps may fill 55 s (the map within issue 42's 60 s)
    assert (mc.final_budget(realtime=True, cpu=True), mc.final_budget(realtime=True, cpu=False),
            mc.final_budget(realtime=False, cpu=True)) == (55.0, 0.0, 0.0)

    def drawn(*over) -> np.ndarray:
        mp = Mapper(load_config(None, ["mapping.capacity=20000", *over]), device=wp_device)
        for i in (0, 4, 8):
            mp.submit(_kf(seq, cam, i))
        mp.process_pending()
        ids = [mp.keyframe_ids.index(mp.sampler.next_view(mp.views)) for _ in range(3000)]
        return mp, np.bincount(ids, minlength=3) / 3000

    mp, share = drawn("mapping.mapper.loss_share=0")
    assert type(mp.sampler) is NewestOrRandomSampler and mp.stats.steps == 3 * 20
    assert np.all(np.abs(share - 1 / 3) < 0.04), share           # uniform: the newest no more than the others
    asked = []
    mp.refine = lambda n, seconds=0.0: asked.append((n, seconds)) or 0     # what the final refinement is asked for
    mp.stop()
    assert asked == [(2000, 0.0)] and mp.final_coarse_share() == 0.6    # the deterministic mode: no time budget
    assert Mapper(load_config(None, ["mapping.mapper.keyframe_steps_coarse=false"]),
                  device=wp_device).final_coarse_share() == 0.8       # with full-resolution steps after keyframes
    _, share = drawn("mapping.mapper.newest_probability=0.2", "mapping.mapper.iterations_per_keyframe=0")
    assert share[2] > 1 / 3 + 0.1                                  # the control: the newest favoured is seen
    # mapping.mapper.loss_share: the steps tell the sampler their losses, and it draws by them
    mp, share = drawn("mapping.mapper.loss_share=1")
    p = mp.sampler.other_probabilities(mp.keyframe_ids)
    assert mp.sampler.loss_share == 1.0 and np.ptp(p) > 0.01 and np.all(np.abs(share - p) < 0.04), (p, share)


def test_keyframes_seed_views_and_train(wp_device, seq, cam):
    mp = Mapper(_cfg(), device=wp_device)
    mp.submit(_kf(seq, cam, 0, exposure_ms=10.0))
    mp.submit(_kf(seq, cam, 4, exposure_ms=20.0, affine=(0.1, 3.0)))
    assert mp.process_pending() == 2
    st = mp.stats
    assert st.keyframes == 2 and mp.keyframe_ids == [0, 4]
    assert st.steps == 2 * 3                          # iterations_per_keyframe after each keyframe
    assert st.seed_results[0].num_added > 100 and mp.gmap.n >= st.gaussians_seeded - st.densify["pruned"]
    # the first keyframe's exposure is the reference; the second's is DSO's affine and the exposure ratio
    assert mp.reference_exposure_ms == 10.0
    assert mp.view_exposure(0) == pytest.approx((0.0, 0.0))
    assert mp.view_exposure(4) == pytest.approx((0.1 + math.log(2.0), 3.0 / 255.0))
    np.testing.assert_allclose(mp.views[4].world_to_cam, se3_inverse(seq.cam_to_world[4]), atol=1e-12)
    stats = mp.stop()
    assert stats.final_steps == 4 and stats.steps == 10 and stats.stopped_by == "stop"


def test_points_too_far_are_counted_in_the_stats(wp_device, seq, cam):
    """A keyframe whose message holds 4 points at nearly zero inverse depth: the mapper's stats (metrics.json's
    ``mapper.points_too_far``) count them, and no Gaussian lies that far; with ``max_depth_factor=0`` none is
    counted and the map reaches them."""
    for factor, far in ((100.0, 4), (0.0, 0)):
        mp = Mapper(_cfg(f"mapping.seeding.max_depth_factor={factor}"), device=wp_device)
        msg = _kf(seq, cam, 0)
        idepth = msg.idepths.copy()
        idepth[[3, 30, 60, 90]] = 1e-7
        mp.submit(KeyframeMessage(0, 0, float(seq.timestamps[0]), seq.images[0], cam, seq.cam_to_world[0],
                                  msg.points_uv, idepth))
        mp.process_pending()
        st = mp.stop()
        assert st.points_too_far == far and st.as_dict()["points_too_far"] == far
        reach = np.linalg.norm(mp.gmap.means.numpy() - seq.cam_to_world[0][:3, 3], axis=1).max()
        assert (reach < 100.0) == (far > 0), reach


@pytest.mark.parametrize("mode", ["odometry", "exposure_time", "none"])
def test_exposure_modes_set_each_views_brightness_model(wp_device, seq, cam, mode):
    """``mapping.mapper.exposure``: DSO's affine and the exposure time (odometry), the exposure time alone, or
    nothing; a pose update's affine moves a view only where the mode reads DSO's affine."""
    mp = Mapper(_cfg(f"mapping.mapper.exposure={mode}"), device=wp_device)
    mp.submit(_kf(seq, cam, 0, exposure_ms=10.0))
    mp.submit(_kf(seq, cam, 4, exposure_ms=20.0, affine=(0.1, 3.0)))
    mp.process_pending()
    want = {"odometry": (0.1 + math.log(2.0), 3.0 / 255.0), "exposure_time": (math.log(2.0), 0.0),
            "none": (0.0, 0.0)}[mode]
    assert mp.view_exposure(4) == pytest.approx(want)
    assert mp.exposure_for((0.1, 3.0), 20.0) == pytest.approx(want)    # what evaluation renders use
    mp.submit(PoseUpdate({4: seq.cam_to_world[4]}, affine={4: (0.3, 6.0)}))
    mp.process_pending()
    moved = {"odometry": (0.3 + math.log(2.0), 6.0 / 255.0)}.get(mode, want)
    assert mp.view_exposure(4) == pytest.approx(moved)
    with pytest.raises(ConfigError, match="exposure"):
        load_config(None, ["mapping.mapper.exposure=auto"])


def test_pose_update_moves_views_and_shifts_exposure(wp_device, seq, cam):
    noisy = seq.cam_to_world[0] @ se3_exp([0.05, 0, 0, 0, 0.02, 0])
    mp = Mapper(_cfg("mapping.train.learn_exposure=true"), device=wp_device)
    mp.submit(_kf(seq, cam, 0, pose=noisy, affine=(0.2, 5.0)))
    mp.process_pending()
    learned = np.array(mp.view_exposure(0)) - np.array(map_exposure((0.2, 5.0), None, None))
    assert np.abs(learned).max() > 0                  # the trainer learned a correction on top of DSO's
    mp.submit(PoseUpdate({0: seq.cam_to_world[0], 7: np.eye(4)}, affine={0: (0.5, 1.0)}))
    mp.process_pending()
    np.testing.assert_allclose(mp.views[0].cam_to_world, seq.cam_to_world[0], atol=1e-12)
    assert mp.stats.poses_applied == 1 and mp.stats.poses_unknown == 1
    # DSO's change of (a, b) moves the view's exposure; what was learned on top is kept
    expect = np.array(map_exposure((0.5, 1.0), None, None)) + learned
    np.testing.assert_allclose(mp.view_exposure(0), expect, atol=1e-12)


def test_marginalized_points_seed_only_where_the_map_is_empty(wp_device, seq, cam):
    # seeds up to 20 px wide (the default's clamp before 2026-12-07): untrained, they cover the points they came
    # from, which this test offers again; the default's 8 px seeds cover about half of them before any training
    mp = Mapper(_cfg("mapping.mapper.iterations_per_keyframe=0", "mapping.seeding.scale_max_px=20"),
                device=wp_device)
    kf = _kf(seq, cam, 0)
    # the keyframe brings only the left half of its points; the right half arrives marginalised later
    left = kf.points_uv[:, 0] < cam.width / 2
    mp.submit(KeyframeMessage(0, 0, kf.timestamp, kf.image, cam, kf.cam_to_world, kf.points_uv[left],
                              kf.idepths[left]))
    mp.process_pending()
    n0 = mp.gmap.n
    pts = backproject(kf.points_uv, 1.0 / kf.idepths, cam, kf.cam_to_world)
    cols = np.full((len(pts), 3), 0.5, np.float32)
    mp.submit(PointsMessage(pts, cols, host_keyframe_id=0))
    mp.submit(PointsMessage(pts, cols, host_keyframe_id=99))      # unknown host: cloud only
    mp.process_pending()
    res = mp.stats.seed_results[-1]
    added = mp.gmap.n - n0
    assert mp.stats.point_messages == 2 and mp.stats.points_received == 2 * len(pts)
    assert res.num_fill == 0                           # no Delaunay fill for marginalised points
    # the right half is new; most of the left half is already covered by the keyframe's seeds
    assert added == res.num_added and (~left).sum() * 0.7 < added < len(pts) * 0.8
    assert res.num_rejected_visibility > 0.5 * left.sum()


def test_random_init_adds_what_dso_seeding_would(wp_device, seq, cam):
    counts = {}
    for init in ("dso", "random"):
        mp = Mapper(_cfg(f"mapping.mapper.init={init}", "mapping.mapper.iterations_per_keyframe=0"),
                    device=wp_device)
        mp.submit(_kf(seq, cam, 0))
        mp.process_pending()
        counts[init] = mp.gmap.n
        means = mp.gmap.means.numpy()
        z = (means - seq.cam_to_world[0][:3, 3]) @ seq.cam_to_world[0][:3, 2]
        zt = 1.0 / _kf(seq, cam, 0).idepths
        assert zt.min() - 1e-3 <= z.min() and z.max() <= zt.max() + 1e-3     # inside the points' depth range
        if init == "random":
            # not on the surfaces: the depth of a random Gaussian is unrelated to the surface behind its pixel
            uv = means @ seq.cam_to_world[0][:3, :3] - seq.cam_to_world[0][:3, 3] @ seq.cam_to_world[0][:3, :3]
            px = np.round(cam.fx * uv[:, 0] / uv[:, 2] + cam.cx).astype(int).clip(0, cam.width - 1)
            py = np.round(cam.fy * uv[:, 1] / uv[:, 2] + cam.cy).astype(int).clip(0, cam.height - 1)
            rel = np.abs(z - seq.depths[0][py, px]) / seq.depths[0][py, px]
            assert np.median(rel) > 0.1
    assert counts["dso"] == counts["random"] > 0


def test_stop_without_refinement_applies_pending_messages_only(wp_device, seq, cam):
    mp = Mapper(_cfg(), device=wp_device)
    mp.submit(_kf(seq, cam, 0))
    mp.submit(_kf(seq, cam, 4))
    st = mp.stop(refine=False)
    assert st.keyframes == 2 and st.steps == 0 and st.stopped_by == "interrupt"
    assert mp.stop() is st                             # idempotent


# --------------------------------------------------------------------------------------------- real time
def test_real_time_thread_applies_every_message_and_counts_backpressure(wp_device, seq, cam):
    mp = Mapper(_cfg("mapping.mapper.queue_size=1", "mapping.mapper.final_iterations=2"), device=wp_device)
    assert mp.sampler.loss_share == 0.5
    assert mp.trainer.train_step.strategy.cfg.prune_weight_px == 0.0
    mp.start()
    assert mp.running and mp.sampler.loss_share == 0.0      # real time draws the keyframes uniformly
    assert mp.trainer.train_step.strategy.cfg.prune_weight_px == 0.1   # and prunes what no view shows
    truth = {}
    for i in range(0, 9, 2):
        mp.submit(_kf(seq, cam, i, pose=seq.cam_to_world[i] @ se3_exp([0.03, 0, 0, 0, 0, 0])))
        truth[i] = seq.cam_to_world[i]
        mp.submit(PoseUpdate(dict(truth)))
    st = mp.stop(timeout=60)
    assert not mp.running
    assert st.keyframes == 5 and mp.keyframe_ids == [0, 2, 4, 6, 8]
    assert st.pose_updates == 5 and st.poses_applied == 1 + 2 + 3 + 4 + 5 and st.poses_unknown == 0
    for i, T in truth.items():
        np.testing.assert_allclose(mp.views[i].cam_to_world, T, atol=1e-12)
    assert st.final_steps == 2 and st.stopped_by == "stop"
    assert st.queue_waits > 0 and st.max_queue_depth >= 1    # a queue of 1 makes the sender wait


def _backlog(seq, cam):
    """Two keyframes with a third of their points each, then the rest of each one's points as marginalised
    points in three messages per host, interleaved, as a mapper that fell behind finds them in its queue."""
    msgs, later = [], []
    for kid in (0, 4):
        kf = _kf(seq, cam, kid)
        first = np.arange(len(kf.points_uv)) % 3 == 0
        msgs.append(KeyframeMessage(kid, kid, kf.timestamp, kf.image, cam, kf.cam_to_world, kf.points_uv[first],
                                    kf.idepths[first]))
        rest = np.flatnonzero(~first)
        pts = backproject(kf.points_uv[rest], 1.0 / kf.idepths[rest], cam, kf.cam_to_world)
        cols = np.full((len(pts), 3), 0.5, np.float32)
        later.append([PointsMessage(pts[c], cols[c], host_keyframe_id=kid) for c in np.array_split(
            np.arange(len(pts)), 3)])
    return msgs + [m for trio in zip(*later) for m in trio]


def test_a_mapper_behind_seeds_each_hosts_points_once(wp_device, seq, cam):
    # every seeding renders the map's coverage from the host keyframe; a real-time mapper that finds several point
    # messages of one host waiting seeds them together, when its queue is empty (here: at the end)
    cfg = _cfg("mapping.mapper.iterations_per_keyframe=0", "mapping.seeding.min_new_gaussians=1")
    behind = Mapper(cfg, device=wp_device)
    for m in _backlog(seq, cam):
        behind.submit(m)                              # queued before the thread starts: a backlog of 8
    behind.start()
    st = behind.stop(refine=False, timeout=60)
    # the control: the deterministic mode applies the same messages one by one, a seeding each
    each = Mapper(cfg, device=wp_device)
    for m in _backlog(seq, cam):
        each.submit(m)
    each.process_pending()
    assert st.point_messages == each.stats.point_messages == 6
    assert len(st.seed_results) == 2 + 2 and st.points_coalesced == 4
    assert len(each.stats.seed_results) == 2 + 6 and each.stats.points_coalesced == 0
    assert st.coverage_renders == 3 and each.stats.coverage_renders == 7    # the first keyframe's map is empty
    assert [r.keyframe_id for r in st.seed_results] == [0, 4, 0, 4]      # the hosts in the order they came
    # the same points reach the map: the waiting ones are distinct points, so little is covered twice
    n_behind, n_each = behind.gmap.n, each.gmap.n
    assert n_each > 0 and 0.9 * n_each <= n_behind <= 1.1 * n_each, (n_behind, n_each)


def test_a_hosts_points_wait_until_it_leaves_the_window(wp_device, seq, cam):
    """Real time: a host keyframe marginalises points with each keyframe while it is in the odometry's window (about
    5 hosts a keyframe), and each seeding renders the map's coverage from the host. Its points wait until a pose
    update no longer names it (or SETTLE_KEYFRAMES keyframes passed), then one seeding takes them all."""
    def mapper(settled):
        mp = Mapper(_cfg("mapping.mapper.iterations_per_keyframe=0", "mapping.seeding.min_new_gaussians=1",
                         f"mapping.mapper.seed_points_settled={str(settled).lower()}"), device=wp_device)
        mp._coalesce_points = True                  # as the real-time loop runs it
        msgs = _backlog(seq, cam)                    # keyframes 0 and 4, then three point messages of each host
        kf0, kf4, points = msgs[0], msgs[1], msgs[2:]
        for m in (kf0, PoseUpdate({0: kf0.cam_to_world}), *points[0::2]):
            mp.submit(m)                             # host 0's points while the window is {0}
        mp.process_pending()
        return mp, kf4, points

    mp, kf4, points = mapper(True)
    assert len(mp.stats.seed_results) == 1           # the keyframe's own seeding
    mp._flush_waiting(budget=1.0)                    # the queue is empty, but host 0 is still in the window
    assert len(mp.stats.seed_results) == 1 and sum(len(p[0]) for p in mp._pending_points[0]) > 0
    for m in (kf4, PoseUpdate({4: kf4.cam_to_world}), points[1]):
        mp.submit(m)                                 # host 0 left the window; host 4 is in it
    mp.process_pending()
    mp._flush_waiting(budget=1.0)
    assert [r.keyframe_id for r in mp.stats.seed_results] == [0, 4, 0]       # host 0's points, in one seeding
    assert mp.stats.seed_results[-1].num_points_in == sum(len(m.points) for m in points[0::2])
    assert list(mp._pending_points) == [4]
    mp._flush_waiting()                              # the end of the stream: everything
    assert [r.keyframe_id for r in mp.stats.seed_results] == [0, 4, 0, 4] and not mp._pending_points

    # an odometry whose pose updates name every keyframe: the points are seeded after SETTLE_KEYFRAMES keyframes
    mp, kf4, points = mapper(True)
    mp.SETTLE_KEYFRAMES = 1
    for m in (kf4, PoseUpdate({0: mp.views[0].cam_to_world, 4: kf4.cam_to_world})):
        mp.submit(m)
    mp.process_pending()
    mp._flush_waiting(budget=1.0)
    assert [r.keyframe_id for r in mp.stats.seed_results] == [0, 4, 0]

    # the control: seed_points_settled off, the points are seeded as soon as the queue is empty
    mp, kf4, points = mapper(False)
    mp._flush_waiting(budget=1.0)
    assert [r.keyframe_id for r in mp.stats.seed_results] == [0, 0] and not mp._pending_points


def test_a_mapper_far_behind_defers_keyframe_seedings_to_their_points(wp_device, seq, cam):
    """With the queue deep, a keyframe becomes a view at once and its seeding waits with its host's points, so the
    mapper gets through its messages (on 2 cores the queue filled in 80 s of a 640x480 camera and the odometry
    waited). Each host is then seeded keyframe first, then its points, in the order the hosts came."""
    def run(defer):
        # seeds up to 20 px wide, which cover before any training: then the order of the seedings hardly changes
        # what they add (the default's 8 px seeds leave gaps that the later seedings fill: 23 % more deferred)
        cfg = _cfg("mapping.mapper.iterations_per_keyframe=0", "mapping.seeding.min_new_gaussians=1",
                   f"mapping.mapper.defer_seeding_above={defer}", "mapping.mapper.running_train_share=0",
                   "mapping.seeding.scale_max_px=20")
        mp = Mapper(cfg, device=wp_device)
        for m in _backlog(seq, cam):
            mp.submit(m)                              # a backlog of 8 before the thread starts
        mp.start()
        return mp, mp.stop(refine=False, timeout=60)

    deep, st = run(2)
    assert st.seedings_deferred == 2 and st.keyframes == 2 and st.point_messages == 6
    assert [r.keyframe_id for r in st.seed_results] == [0, 0, 4, 4]     # each host's keyframe, then its points
    # the control: never deferred, the keyframes are seeded as they come
    each, st0 = run(0)
    assert st0.seedings_deferred == 0 and [r.keyframe_id for r in st0.seed_results] == [0, 4, 0, 4]
    assert 0.9 * each.gmap.n <= deep.gmap.n <= 1.1 * each.gmap.n, (deep.gmap.n, each.gmap.n)


def test_a_deferred_seeding_follows_its_view_and_waits_for_its_budget(wp_device, seq, cam):
    mp = Mapper(_cfg("mapping.mapper.defer_seeding_above=1", "mapping.seeding.fill=false"), device=wp_device)
    mp._coalesce_points = True                  # as the real-time loop runs it
    moved = seq.cam_to_world[0] @ se3_exp([0.2, 0.0, 0.0, 0.0, 0.0, 0.0])
    kf = _kf(seq, cam, 0)
    mp.submit(kf)
    mp.submit(PoseUpdate({0: moved}))            # queued behind it: the keyframe's seeding is deferred
    mp.process_pending()
    assert mp.stats.seedings_deferred == 1 and mp.gmap.n == 0 and 0 in mp.views
    mp._flush_waiting(budget=0.0)                 # no time left: it waits
    assert mp.gmap.n == 0
    mp._flush_waiting()
    assert mp.gmap.n > 0 and mp.stats.seed_results[-1].keyframe_id == 0
    # seeded from where the view is now: the keyframe's points back-projected with the moved pose
    means = mp.gmap.means.numpy().astype(np.float64)
    truth = backproject(kf.points_uv, 1.0 / kf.idepths, cam, moved)
    old = backproject(kf.points_uv, 1.0 / kf.idepths, cam, kf.cam_to_world)
    d_new = np.linalg.norm(means[:, None] - truth[None], axis=2).min(axis=1)
    d_old = np.linalg.norm(means[:, None] - old[None], axis=2).min(axis=1)
    assert np.median(d_new) < 1e-4 and np.median(d_old) > 0.1


def test_a_mapper_behind_keeps_a_share_for_training_at_a_coarser_level(wp_device, seq, cam):
    """Real time on a small CPU: seeding the keyframes fills the core the odometry leaves, and a mapper that trained
    only when its queue was empty made 1-2 steps while a 640x480 camera ran (docs/mgso.md). With a training share it
    trains while messages wait, at the running level (a cheaper step), and refines at full resolution (with
    final_coarse_share 0; its own test covers the coarse first share)."""
    def run(share):
        cfg = _cfg("mapping.mapper.iterations_per_keyframe=0", "mapping.seeding.min_new_gaussians=1",
                   f"mapping.mapper.running_train_share={share}", "mapping.mapper.running_max_pixels=1200",
                   "mapping.mapper.final_iterations=3", "mapping.mapper.final_coarse_share=0")
        mp = Mapper(cfg, device=wp_device)
        levels, step = [], mp.trainer.step

        def spy(*args, **kw):
            r = step(*args, **kw)
            levels.append(r.level)
            return r

        mp.trainer.step = spy
        for m in _backlog(seq, cam):
            mp.submit(m)                              # a backlog of 8 before the thread starts
        mp.start()
        for _ in range(1200):                         # the stream goes on until the backlog is applied
            if mp.stats.point_messages == 6:
                break
            threading.Event().wait(0.05)
        return mp.stop(timeout=60), levels

    st, levels = run(0.5)
    assert st.keyframes == 2 and st.point_messages == 6 and st.final_steps == 3
    assert st.steps_while_behind > 0 and st.running_level == 1          # 80x60 -> 40x30 = 1,200 pixels
    assert st.history[1][2] >= 1                    # a step between the two keyframes, with 6 messages waiting
    assert levels[:-3] == [1] * (st.steps - 3) and levels[-3:] == [0, 0, 0]
    # the control: without a share nothing trains while messages wait (steps come once the queue is empty)
    st0, levels0 = run(0)
    assert st0.steps_while_behind == 0 and st0.keyframes == 2 and levels0[-3:] == [0, 0, 0]
    assert levels0[0] == 1 and st0.history[1][2] == 0       # no step before both keyframes were applied


@pytest.mark.parametrize("final_threads", [2, None])
def test_what_is_queued_when_the_stream_ends_is_applied_on_the_final_threads(wp_device, seq, cam, final_threads):
    """A mapper behind the camera still has messages queued when the stream ends; the odometry is done then, so the
    rest (seedings included) runs on the final refinement's threads at once, without the training share (a 640x480
    run of 83 s on 2 cores left 209 s of it, on one thread). The control: no final threads, nothing changes."""
    from mgso_kernels import runtime

    setting = runtime.cpu_threads_setting()
    runtime.set_cpu_threads(1)
    try:
        mp = Mapper(_cfg("mapping.mapper.final_iterations=0", "mapping.mapper.running_train_share=0.5"),
                    device=wp_device, final_threads=final_threads)
        seen, handle = [], mp.handle

        def spy(msg):
            seen.append(runtime.cpu_threads())
            return handle(msg)

        mp.handle = spy
        for m in _backlog(seq, cam):
            mp.submit(m)
        # the stream has ended before the thread takes its first message (as stop() would say it), so what the
        # thread does is decided, not raced against stop(): every message after the end (issue 44: a step taken
        # before stop() set the event failed this test once on a busy machine)
        mp.stream_ended.set()
        mp.start()
        st = mp.stop(timeout=60)
        assert st.keyframes == 2 and st.point_messages == 6 and st.steps_while_behind == 0
        assert st.stream_ended_at_depth in (8, 9) and st.catch_up_seconds > 0     # 9: stop()'s Stop came first
        assert set(seen) == {final_threads or 1} and len(seen) == 8
    finally:
        runtime.set_cpu_threads(setting)


@pytest.mark.parametrize("coarse", [False, True])
def test_keyframe_steps_coarse_trains_the_steps_after_a_keyframe_at_the_running_level(wp_device, seq, cam, coarse):
    """mapping.mapper.keyframe_steps_coarse (deterministic mode): the steps after each keyframe at the level
    running_max_pixels gives (80x60 at 4,000 pixels: 40x30), the final refinement at full resolution (its own coarse
    share off); off (the control, the default) every step at full resolution."""
    mp = Mapper(_cfg("mapping.mapper.running_max_pixels=4000", f"mapping.mapper.keyframe_steps_coarse={coarse}",
                     "mapping.mapper.final_coarse_share=0"), device=wp_device)
    levels = []
    step = mp.trainer.step
    mp.trainer.step = lambda view_id=None, min_level=0: levels.append(min_level) or step(view_id, min_level)
    for i in (0, 4):
        mp.submit(_kf(seq, cam, i))
    mp.process_pending()
    mp.stop()
    assert levels == [int(coarse)] * 6 + [0] * 4     # 3 steps after each of 2 keyframes, then 4 final ones


def test_the_running_level_and_when_training_is_owed(wp_device, seq, cam):
    mp = Mapper(_cfg("mapping.mapper.queue_size=4"), device=wp_device)
    assert mp.running_level() == 0                                      # no view yet
    mp.submit(_kf(seq, cam, 0))
    mp.process_pending()
    for pixels, level in ((80_000, 0), (4_800, 0), (4_799, 1), (1_200, 1), (1_199, 1), (1, 1), (0, 0)):
        mp.cfg = dataclasses.replace(mp.cfg, running_max_pixels=pixels)
        assert mp.running_level() == level, pixels      # 80x60, 40x30; not 20x15 (a level keeps 16 pixels a side)
    assert mp._owes_training(busy=3.0, trained=0.9)                     # share 0.25: a third of the busy time
    assert not mp._owes_training(busy=3.0, trained=1.0)
    for _ in range(2):
        mp.queue.put(PoseUpdate({}))
    assert not mp._owes_training(busy=3.0, trained=0.0)                 # half the queue full: messages first
    mp.queue.get()
    assert mp._owes_training(busy=3.0, trained=0.0)
    mp.cfg = dataclasses.replace(mp.cfg, running_train_share=0.0)
    assert not mp._owes_training(busy=3.0, trained=0.0)


def test_mapping_thread_failure_reaches_the_sender(wp_device, seq, cam):
    mp = Mapper(_cfg(), device=wp_device)
    mp.start()
    mp.submit(_kf(seq, cam, 0))
    mp.submit(_kf(seq, cam, 0))          # the same keyframe twice: the mapping thread raises
    with pytest.raises(MapperError, match="twice"):
        for _ in range(200):
            threading.Event().wait(0.05)
            mp.submit(PoseUpdate({}))
        mp.stop(timeout=30)


def test_submit_rejects_other_objects(wp_device):
    mp = Mapper(_cfg(), device=wp_device)
    with pytest.raises(TypeError, match="mapper message"):
        mp.submit("keyframe")
    with pytest.raises(ValueError, match="Stop"):
        mp.handle(Stop())
    assert isinstance(PointKind.ACTIVE, int)


# ------------------------------------------------------------------------------------- map-refined poses
def test_map_corrections_survive_pose_updates_and_move_every_frame(wp_device, seq, cam):
    """With pose refinement on, a keyframe's map pose is ``W @ odometry pose``: a pose update from the odometry moves
    the odometry's part and keeps ``W``; the refined trajectory moves each frame by the geodesic interpolation (in
    time) of its neighbouring keyframes' corrections, and the first keyframe (the gauge) is not refined. With
    refinement off the trajectory is returned unchanged (the negative control)."""
    from mgso.geometry import se3_log
    from mgso.io.trajectory import Trajectory

    for on in (True, False):
        mp = Mapper(_cfg(f"mapping.train.refine_poses={str(on).lower()}", "mapping.train.lr_pose_translation=0",
                         "mapping.train.lr_pose_rotation=0", "mapping.mapper.iterations_per_keyframe=0"),
                    device=wp_device)
        for i in (0, 4, 8):
            mp.submit(_kf(seq, cam, i))
        mp.process_pending()
        assert mp.views[0].fixed_pose and not mp.views[4].fixed_pose
        # what the map refined (here set by hand): keyframe 4 moved by W4, keyframe 8 by W8
        W = {0: np.eye(4), 4: se3_exp([0.02, 0.0, -0.01, 0.0, 0.01, 0.0]), 8: se3_exp([0.0, 0.03, 0.0, 0.02, 0, 0])}
        for k in (4, 8):
            mp.views.set_pose(k, se3_inverse(W[k] @ seq.cam_to_world[k]))
        if on:
            for k in (0, 4, 8):
                np.testing.assert_allclose(mp.correction(k), W[k], atol=1e-12)
        new8 = seq.cam_to_world[8] @ se3_exp([0.01, 0, 0, 0, 0, 0.005])
        mp.submit(PoseUpdate({8: new8}))
        mp.process_pending()
        if on:
            np.testing.assert_allclose(mp.views[8].cam_to_world, W[8] @ new8, atol=1e-12)
        else:
            np.testing.assert_allclose(mp.views[8].cam_to_world, new8, atol=1e-12)
        ts = np.array([seq.timestamps[0], seq.timestamps[2], seq.timestamps[6], seq.timestamps[8] + 1.0])
        poses = np.stack([seq.cam_to_world[0], seq.cam_to_world[2], seq.cam_to_world[6], new8])
        traj = Trajectory(ts, poses)
        out = mp.refined_trajectory(traj)
        if not on:
            assert out is traj
            continue
        np.testing.assert_allclose(out.cam_to_world[0], poses[0], atol=1e-9)           # before keyframe 0's time: W0
        half = W[4] @ se3_exp(0.5 * se3_log(se3_inverse(W[4]) @ W[8]))                  # frame 6: half way 4 -> 8
        a2 = (ts[1] - ts[0]) / (seq.timestamps[4] - ts[0])                              # frame 2: between 0 and 4
        np.testing.assert_allclose(out.cam_to_world[1], se3_exp(a2 * se3_log(W[4])) @ poses[1], atol=1e-9)
        np.testing.assert_allclose(out.cam_to_world[2], half @ poses[2], atol=1e-9)
        np.testing.assert_allclose(out.cam_to_world[3], W[8] @ poses[3], atol=1e-9)    # after the last: W8


# ------------------------------------------------------------------------------------------- loop corrections
def test_loop_correction_moves_views_depths_and_anchored_gaussians(wp_device, seq, cam):
    """A LoopCorrection moves keyframe 4's view, depth points and Gaussians by its Sim(3) and leaves keyframe 0's:
    keyframe 4 then renders from its moved pose as it did before, and keyframe 0 renders what it did."""
    from mgso.geometry import sim3_from_parts, so3_exp
    from mgso.messages import LoopCorrection, sim3_apply_to_pose

    mp = Mapper(_cfg("mapping.mapper.iterations_per_keyframe=0", "mapping.train.depth_weight=0.2"), device=wp_device)
    mp.submit(_kf(seq, cam, 0))
    mp.submit(_kf(seq, cam, 8))
    mp.process_pending()
    anchors = mp.gmap.anchor.numpy()
    assert set(np.unique(anchors)) == {0, 8}
    S = sim3_from_parts(so3_exp([0.05, -0.1, 0.02]), np.array([0.3, 0.1, -0.2]), 1.4)
    w2c0, w2c8 = mp.views[0].world_to_cam.copy(), mp.views[8].world_to_cam.copy()
    z8 = mp.views[8].depth_z.copy()
    before = mp.gmap.to_numpy()
    only8 = anchors == 8
    mp.submit(LoopCorrection({8: S, 99: np.eye(4)}, loop=1))        # 99: a keyframe the map does not have
    mp.process_pending()
    assert mp.stats.loop_corrections == 1 and mp.stats.gaussians_moved == int(only8.sum())
    np.testing.assert_array_equal(mp.views[0].world_to_cam, w2c0)
    np.testing.assert_allclose(mp.views[8].cam_to_world, sim3_apply_to_pose(S, se3_inverse(w2c8)), atol=1e-12)
    np.testing.assert_allclose(mp.views[8].depth_z, 1.4 * z8, rtol=1e-12)
    after = mp.gmap.to_numpy()
    np.testing.assert_array_equal(after.means[~only8], before.means[~only8])
    expect = before.means[only8].astype(np.float64) @ S[:3, :3].T + S[:3, 3]
    np.testing.assert_allclose(after.means[only8], expect, atol=1e-5)
    with pytest.raises(ValueError, match=r"LoopCorrection.transforms\[3\].*Sim\(3\)"):
        LoopCorrection({3: -np.eye(4)})
    import pickle
    back = pickle.loads(pickle.dumps(LoopCorrection({8: S}, loop=2)))     # it crosses to the mapper's process
    assert back.loop == 2 and np.array_equal(back.transforms[8], S)


def test_keyframes_a_loop_moved_have_their_poses_refined(wp_device, seq, cam):
    """The pose graph's corrections are not the poses the odometry's depths agree with, so once a LoopCorrection moved
    the map, the keyframes it moved are refined against the map (mapping.mapper.loop_refines_poses): keyframes 4 and
    8 were trusted (fixed poses) and are not after the loop; keyframe 0 holds the gauge and stays fixed even when
    the correction names it; training then moves keyframe 8's pose and not keyframe 0's. The control
    (loop_refines_poses=false) keeps every pose fixed."""
    from mgso.geometry import sim3_from_parts, so3_exp
    from mgso.messages import LoopCorrection

    S = sim3_from_parts(so3_exp([0.01, -0.02, 0.005]), np.array([0.03, 0.01, -0.02]), 1.05)
    for refine in (True, False):
        mp = Mapper(_cfg("mapping.mapper.iterations_per_keyframe=0", "mapping.train.depth_weight=0.2",
                         "mapping.train.refine_poses=null",                 # the default: untrusted ones only
                         f"mapping.mapper.loop_refines_poses={refine}"), device=wp_device)
        for k in (0, 4, 8):
            mp.submit(_kf(seq, cam, k))
        mp.process_pending()
        assert all(mp.views[k].fixed_pose for k in (0, 4, 8))         # trusted keyframes: the odometry's poses
        mp.submit(LoopCorrection({0: np.eye(4), 4: S, 8: S}, loop=1))
        mp.process_pending()
        assert mp.views[0].fixed_pose
        assert [mp.views[k].fixed_pose for k in (4, 8)] == [not refine] * 2
        assert mp.stats.loop_poses_refined == (2 if refine else 0)
        w2c0, w2c8 = mp.views[0].world_to_cam.copy(), mp.views[8].world_to_cam.copy()
        for _ in range(6):
            mp.trainer.step(view_id=8)
            mp.trainer.step(view_id=0)
        np.testing.assert_array_equal(mp.views[0].world_to_cam, w2c0)
        assert (np.abs(mp.views[8].world_to_cam - w2c8).max() > 0) == refine


def test_the_mappers_prune_threshold_replaces_densifys(wp_device, seq, cam):
    """mapping.mapper.prune_opacity prunes faint Gaussians at each refinement (0.05 by default); 0 leaves
    mapping.densify's 3DGS threshold (0.005): the negative control keeps more of the same map."""
    counts = {}
    for prune in (0.05, 0.0):
        mp = Mapper(_cfg(f"mapping.mapper.prune_opacity={prune}", "mapping.mapper.refine_every=10",
                         "mapping.mapper.grow_grad2d=0",           # densify's threshold: clones to prune
                         "mapping.densify.refine_start_step=0", "mapping.mapper.iterations_per_keyframe=10",
                         "mapping.seeding.init_opacity=0.03"), device=wp_device)
        assert mp.trainer.train_step.strategy.cfg.prune_opacity == (prune or 0.005)
        mp.submit(_kf(seq, cam, 0))
        mp.submit(_kf(seq, cam, 8))
        mp.process_pending()
        counts[prune] = (mp.gmap.n, mp.stats.densify["pruned"])
    # measured: 639 pruned, none left, against 595 pruned and 44 left
    assert counts[0.05][1] > counts[0.0][1] and counts[0.05][0] < counts[0.0][0], counts


def test_the_mappers_weight_prune_replaces_densifys(wp_device, seq, cam):
    """mapping.mapper.prune_weight_px replaces mapping.densify's (off, 3DGS): at each refinement the mapper prunes the
    Gaussians whose blending weight, measured by its training steps, stayed below it in every view since the last
    one. Its null is 0.1 in real time (the real-time test above) and off in the deterministic mode. The synthetic
    room hides no seed, so a threshold of 5 pixels shows the wiring; the negative controls (0, null) prune none for
    weight and keep more of the same map (measured: 26 of 487 pruned at 5 pixels)."""
    from mgso.config import Config

    mc = Config().mapping.mapper
    assert mc.prune_weight_px is None
    assert (mc.weight_prune_px(realtime=False), mc.weight_prune_px(realtime=True)) == (0.0, 0.1)
    res = {}
    for px in (None, 5.0, 0.0):
        over = [] if px is None else [f"mapping.mapper.prune_weight_px={px}"]
        mp = Mapper(_cfg("mapping.mapper.refine_every=10", "mapping.densify.refine_start_step=0",
                         "mapping.mapper.iterations_per_keyframe=12", *over), device=wp_device)
        assert mp.trainer.train_step.strategy.cfg.prune_weight_px == (px or 0.0)
        mp.submit(_kf(seq, cam, 0))
        mp.submit(_kf(seq, cam, 8))
        mp.process_pending()
        res[px] = (mp.gmap.n, mp.stats.densify["pruned_weight"])
    assert res[5.0][1] > 0 and res[0.0][1] == res[None][1] == 0 and res[5.0][0] < res[0.0][0] == res[None][0], res


def test_the_mapper_prunes_no_gaussian_for_its_size_without_opacity_resets(wp_device, seq, cam):
    """The world-size prune waits for the first opacity reset (3DGS, gsplat), and the mapper makes none: with a
    threshold every Gaussian exceeds, its refinements prune none for size. The control keeps the resets
    (mapping.mapper.opacity_reset, every 5 steps): the same threshold then prunes after the first one."""
    def run(*over):
        mp = Mapper(_cfg("mapping.mapper.refine_every=10", "mapping.densify.refine_start_step=0",
                         "mapping.mapper.iterations_per_keyframe=12", "mapping.densify.prune_scale3d=1e-6", *over),
                    device=wp_device)
        mp.submit(_kf(seq, cam, 0))
        mp.submit(_kf(seq, cam, 8))
        mp.process_pending()
        return mp.stats.densify

    d = run()
    assert d["refines"] >= 2 and d["pruned_world"] == 0 and d["opacity_resets"] == 0, d
    control = run("mapping.mapper.opacity_reset=true", "mapping.densify.reset_every=5",
                  "mapping.densify.reset_opacity_value=0.9")    # a reset that leaves them above the opacity prune
    assert control["opacity_resets"] >= 1 and control["pruned_world"] > 0, control


def test_a_final_refinement_after_an_unrefined_stream_prunes_early(wp_device, seq, cam):
    """mapping.mapper.final_refine_after: a mapper that did not refine while the stream ran (real time on a small
    CPU) refines that many steps into its final refinement, and its untrained seeds are pruned there; the control
    (0) does not refine at all in the same steps (the schedule's first refinement: after step 500), and a map
    already refined while the stream ran keeps its schedule."""
    def run(after, *over):
        mp = Mapper(_cfg(f"mapping.mapper.final_refine_after={after}", "mapping.mapper.refine_every=10",
                         "mapping.mapper.iterations_per_keyframe=1", "mapping.seeding.init_opacity=0.03", *over),
                    device=wp_device)
        mp.submit(_kf(seq, cam, 0))
        mp.submit(_kf(seq, cam, 8))
        mp.process_pending()
        seeded = mp.gmap.n
        mp.refine(30)
        return mp, seeded

    mp, seeded = run(5)
    # 2 steps while the stream ran (0-1): the final refinement's steps 2-31, the first refinement at step 2 + 5
    assert mp.trainer.train_step.strategy.extra_refine_steps == {7}
    assert mp.stats.densify["refines"] == 1 and mp.stats.densify["pruned_opacity"] > 0.5 * seeded, \
        (seeded, mp.stats.densify)
    control, _ = run(0)
    assert control.stats.densify["refines"] == 0 and control.gmap.n >= seeded       # the control: nothing pruned
    refined, _ = run(5, "mapping.densify.refine_start_step=1", "mapping.mapper.iterations_per_keyframe=6")
    assert refined.stats.densify["refines"] >= 1                                     # at step 10, while streaming
    assert refined.trainer.train_step.strategy.extra_refine_steps == frozenset()     # its schedule kept


def _final_levels(device, seq, cam, *over, realtime=False):
    """Run a mapper on keyframe 0 of ``seq`` (20 final steps) and record every training step's (level, width,
    height); returns them and the mapper's stats. The step count's schedule: no time budget (its own test)."""
    mp = Mapper(_cfg("mapping.mapper.final_iterations=20", "mapping.mapper.final_budget_s=0", *over), device=device)
    seen = []
    step = mp.trainer.step

    def recording(*a, **kw):
        r = step(*a, **kw)
        seen.append((r.level, r.width, r.height))
        return r

    mp.trainer.step = recording
    if realtime:
        mp.start()
    mp.submit(_kf(seq, cam, 0))
    st = mp.stop()
    assert st.final_steps == 20
    return seen, st


def test_the_final_refinements_first_share_trains_coarse(wp_device, seq, cam, monkeypatch):
    """mapping.mapper.final_coarse_share: the first share of the final refinement's steps train at the level
    running_max_pixels gives (the real-time mapper's level while the stream runs), the rest at full resolution;
    the control (0) trains every final step at full resolution. Its default (null) is 0.95 in real time; in the
    deterministic mode, whose steps after each keyframe train coarse too (keyframe_steps_coarse), 0.8 where the
    coarse level's image has at least MapperConfig.COARSE_DETAIL_PIXELS and 0.6 below (0.6 everywhere until
    2026-12-07; 0.8 with the keyframes' steps at full resolution, 0 until 2026-12-06)."""
    from mgso.config import MapperConfig

    full, half = (0, 80, 60), (1, 40, 30)     # 80x60 views: level 1 is the finest with at most 1,500 pixels

    def levels(*over, realtime=False):
        seen, st = _final_levels(wp_device, seq, cam, "mapping.mapper.running_max_pixels=1500",
                                 "mapping.mapper.iterations_per_keyframe=2", *over, realtime=realtime)
        return seen, st.final_coarse_steps

    kf_full = "mapping.mapper.keyframe_steps_coarse=false"
    assert levels("mapping.mapper.final_coarse_share=0.7", kf_full) == ([full] * 2 + [half] * 14 + [full] * 6, 14)
    assert levels("mapping.mapper.final_coarse_share=0", kf_full) == ([full] * 22, 0)     # the control
    assert levels(kf_full) == ([full] * 2 + [half] * 16 + [full] * 4, 16)       # 0.8 with full keyframe steps
    assert levels() == ([half] * 2 + [half] * 12 + [full] * 8, 12)              # the default, deterministic: 0.6
    # 0.8 where the coarse level's image has at least COARSE_DETAIL_PIXELS (here 40 x 30 = 1,200 pixels)
    monkeypatch.setattr(MapperConfig, "COARSE_DETAIL_PIXELS", 1200)
    assert levels() == ([half] * 2 + [half] * 16 + [full] * 4, 16)
    monkeypatch.setattr(MapperConfig, "COARSE_DETAIL_PIXELS", 1201)             # the control: one pixel short
    assert levels() == ([half] * 2 + [half] * 12 + [full] * 8, 12)
    seen, coarse = levels(realtime=True)                                        # the default in real time
    assert coarse == 19 and seen[-20:] == [half] * 19 + [full], seen    # 40 x 30: no level coarser with 16 px a side
    assert set(seen[:-20]) <= {half}                                            # its steps while streaming


def test_a_time_budget_fills_the_final_refinement_with_coarse_steps(wp_device, seq, cam, monkeypatch):
    """mapping.mapper.final_budget_s: the final refinement's coarse steps go on past their planned count while the
    time left holds one more and the full-resolution steps at its end (reckoned at the cheaper of two of them, taken
    first), up to BUDGET_MAX_FACTOR times their planned count, never fewer; the steps at full resolution always run.
    On a clock that only the steps move: a coarse step 1 s, a full one 3 s."""
    from types import SimpleNamespace

    import mgso.mapping.mapper as mapper_mod

    def refined(seconds, tail=2, first=3.0):
        mp = Mapper(_cfg("mapping.mapper.running_max_pixels=1500", "mapping.mapper.iterations_per_keyframe=0",
                         f"mapping.mapper.final_coarse_share={1 - tail / 20}"), device=wp_device)
        mp.submit(_kf(seq, cam, 0))
        mp.process_pending()
        clock = [0.0]
        monkeypatch.setattr(mapper_mod, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
        seen = []
        step = mp.trainer.step

        def timed(*a, **kw):
            r = step(*a, **kw)
            clock[0] += 1.0 if r.level else (first if 0 not in seen else 3.0)
            seen.append(r.level)
            return r

        mp.trainer.step = timed
        done = mp.refine(20, seconds=seconds)            # planned: 18 at 40x30, then 2 at 80x60
        monkeypatch.undo()
        assert done == len(seen) == mp.stats.final_steps and mp.stats.final_budget_s == seconds
        if seconds:                                   # two full-resolution steps timed, the coarse ones, the rest
            rest = len(seen) - (tail - 2)
            assert seen[:2] == [0, 0] and set(seen[2:rest]) == {1} and seen[rest:] == [0] * (tail - 2)
        else:
            assert seen[-tail:] == [0] * tail and set(seen[:-tail]) == {1}
        return mp.stats.final_coarse_steps, clock[0]

    assert refined(0.0) == (18, 24.0)                 # the control: no budget, the planned steps
    assert refined(40.0) == (33, 39.0)                # 2 x 3 + 33 + 1 = 40: a 34th would end at the budget
    assert refined(10.0) == (18, 24.0)                # short: the planned steps (the budget only adds)
    assert refined(1000.0) == (36, 42.0)              # long: at most twice the planned coarse steps
    # the full-resolution steps still to come are reckoned at the cheaper of the two timed ones: 4 of them, the first
    # 9 s (a run's first step at a size grows its buffers): 9 + 3, then 21 coarse, + 1 + 2 x 3 = 40 (reckoned at 9 s:
    # the planned 16 only)
    assert refined(40.0, tail=4, first=9.0) == (21, 39.0)
    assert Mapper(_cfg(), device=wp_device).final_budget() == 0.0     # the deterministic mode: the step count alone
    rt = Mapper(_cfg(), device=wp_device)
    rt.start()
    try:
        assert rt.final_budget() == 55.0                # real time with the map on the CPU
    finally:
        rt.stop(refine=False, timeout=60)


def test_the_final_refinements_first_steps_go_a_level_coarser_still(wp_device):
    """mapping.mapper.final_coarser_share: the first share of the final refinement's steps (within
    final_coarse_share) a pyramid level coarser than running_max_pixels gives; its default (null) is 0.6 in real time
    (0.4 until 2026-12-07) and 0.4 in the deterministic mode (0 there until 2026-12-07); the control (0) trains them
    at the running level."""
    big = synthetic.make_sequence(seed=0, num_frames=1, width=128, height=96)
    k = big.intrinsics
    cam = PinholeCamera(k.fx, k.fy, k.cx, k.cy, k.width, k.height)
    full, half, quarter = (0, 128, 96), (1, 64, 48), (2, 32, 24)

    def levels(*over, realtime=False):
        seen, st = _final_levels(wp_device, big, cam, "mapping.mapper.running_max_pixels=3072",
                                 "mapping.mapper.iterations_per_keyframe=0", *over, realtime=realtime)
        return seen[-20:], st.final_coarse_steps, st.final_coarser_steps

    share = "mapping.mapper.final_coarse_share=0.9"
    assert levels(share, "mapping.mapper.final_coarser_share=0.3") == (
        [quarter] * 6 + [half] * 12 + [full] * 2, 18, 6)
    assert levels(share, "mapping.mapper.final_coarser_share=0") == ([half] * 18 + [full] * 2, 18, 0)  # the control
    assert levels(share) == ([quarter] * 8 + [half] * 10 + [full] * 2, 18, 8)   # the deterministic default: 0.4
    assert levels(realtime=True) == ([quarter] * 12 + [half] * 7 + [full], 19, 12)  # real time: 0.6 of 20
    # within the coarse share: asking for more than it gives the coarse share's steps, all a level coarser
    assert levels(share, "mapping.mapper.final_coarser_share=1") == ([quarter] * 18 + [full] * 2, 18, 18)


def test_the_coverage_render_is_a_quarter_resolution_in_real_time(wp_device, seq, cam, monkeypatch):
    """mapping.seeding.alpha_downscale null: the seedings' coverage renders at 1/4 resolution in real time (a
    mapping thread or process: about 40 % more training steps while the camera runs on 2 cores, docs/seeding.md) and at
    1/2 in the deterministic mode; a number is taken as it is in both. Recorded at the coverage render itself."""
    from mgso.mapping import seeding

    render = seeding.render_coverage
    seen = []

    def recording(gmap, rasterizer, camera, world_to_cam, downscale=2, **kw):
        seen.append(downscale)
        return render(gmap, rasterizer, camera, world_to_cam, downscale, **kw)

    monkeypatch.setattr(seeding, "render_coverage", recording)

    def downscales(*over, realtime=False):
        seen.clear()
        mp = Mapper(_cfg("mapping.mapper.iterations_per_keyframe=1", "mapping.mapper.final_iterations=0", *over),
                    device=wp_device)
        if realtime:
            mp.start()
        for i in (0, 4, 8):
            mp.submit(_kf(seq, cam, i))
            if not realtime:
                mp.process_pending()
        mp.stop()
        assert mp.stats.keyframes == 3
        return set(seen)

    assert downscales() == {2}                                          # the default, deterministic
    assert downscales(realtime=True) == {4}                             # the default in real time
    assert downscales("mapping.seeding.alpha_downscale=3", realtime=True) == {3}     # a number as it is
    assert downscales("mapping.seeding.alpha_downscale=3") == {3}


def test_random_sampler_keeps_training_the_first_keyframes(wp_device, seq, cam):
    """mapping.mapper.sampler=random: the newest keyframe with newest_probability, otherwise any keyframe, so the
    first keyframe keeps being trained while later ones arrive. Negative control: least_used gives a new keyframe
    every step until it has the others' uses (with steps a keyframe = the uses each has), so the first keyframe
    is not trained again: on 7-Scenes its view fell from 20 to 10 dB before the final refinement
    (docs/mapping.md)."""
    uses = {}
    for sampler in ("random", "least_used"):
        mp = Mapper(_cfg(f"mapping.mapper.sampler={sampler}", "mapping.mapper.iterations_per_keyframe=8"),
                    device=wp_device)
        for i in range(0, 9, 2):
            mp.submit(_kf(seq, cam, i))
            mp.process_pending()
        uses[sampler] = mp.views[0].uses
    # measured: random 13 of 40 steps (8 while it was the only view), least_used 8 (its own steps only)
    assert uses["least_used"] <= 9 and uses["random"] >= 11, uses


def test_the_mappers_grow_threshold_replaces_densifys(wp_device, seq, cam):
    """mapping.mapper.grow_grad2d is the mapper's clone/split threshold (0.0008 by default); 0 leaves mapping.densify's
    3DGS threshold (0.0002): the negative control grows more of the same map."""
    grown = {}
    for grow in (0.0008, 0.0):
        mp = Mapper(_cfg(f"mapping.mapper.grow_grad2d={grow}", "mapping.mapper.refine_every=10",
                         "mapping.densify.refine_start_step=0", "mapping.mapper.iterations_per_keyframe=30"),
                    device=wp_device)
        assert mp.trainer.train_step.strategy.cfg.grow_grad2d == (grow or 0.0002)
        for i in (0, 4, 8):
            mp.submit(_kf(seq, cam, i))
            mp.process_pending()
        d = mp.stats.densify
        grown[grow] = d["cloned"] + d["split"]
    assert grown[0.0] > 1.5 * grown[0.0008], grown             # measured 566 against 299 split


def test_a_keyframe_whose_depths_miss_the_map_is_not_trusted(wp_device, seq, cam):
    """The defaults (mapping.train.refine_poses null, depth_weight 0.2, the depth rule standing down above a median
    error of 0.5): keyframe 0 seeds and trains; keyframe 1 sees the same place with its true depths (trusted: its
    depth points feed the depth term, its pose stays the odometry's); keyframe 2 comes at keyframe 1's image and
    pose but with depths three times too far (the median error 0.67 against the map: not trusted, no depth term, the map
    refines its pose). The control with refine_poses true refines every pose but the first."""
    over = ["mapping.mapper.iterations_per_keyframe=10", "mapping.mapper.final_iterations=0",
            "mapping.capacity=20000", "mapping.mapper.exposure=odometry"]
    for refine in ("null", "true"):
        mp = Mapper(load_config(None, [*over, f"mapping.train.refine_poses={refine}"]), device=wp_device)
        mp.submit(_kf(seq, cam, 0))
        mp.submit(_kf(seq, cam, 2, kid=1))
        far = _kf(seq, cam, 2, kid=2)
        mp.submit(KeyframeMessage(2, 2, far.timestamp, far.image, cam, far.cam_to_world, far.points_uv,
                                  np.asarray(far.idepths) / 3.0))
        mp.process_pending()
        res = {r.keyframe_id: r for r in mp.stats.seed_results}
        assert res[1].depth_tolerance_used == 0.1 and res[1].depth_error_median < 0.5
        assert res[2].depth_tolerance_used == math.inf and res[2].depth_error_median > 0.5
        assert mp.stats.keyframes_untrusted == 1
        assert mp.views[1].depth_z is not None and mp.views[2].depth_z is None
        assert [mp.views[k].fixed_pose for k in range(3)] == ([True, True, False] if refine == "null"
                                                               else [True, False, False])


def test_a_run_whose_scale_broke_trusts_none_of_its_keyframes(wp_device, seq, cam):
    """mapping.seeding.distrust_median: keyframe 0 seeds, keyframes 1 and 2 see the same place with their true depths
    (trusted), then keyframes come with depths four times too near (median error 3 against the map, above 2: not
    trusted). The third of them makes the run's odometry untrusted: the earlier trusted keyframes lose their depth term
    and get their poses refined too, the first keeps the gauge, and later keyframes are not trusted either. The
    control (0: each keyframe alone) keeps keyframes 1 and 2 trusted."""
    over = ["mapping.mapper.iterations_per_keyframe=5", "mapping.mapper.final_iterations=0",
            "mapping.capacity=20000", "mapping.mapper.exposure=odometry"]
    for limit in (2.0, 0.0):
        mp = Mapper(load_config(None, [*over, f"mapping.seeding.distrust_median={limit}"]), device=wp_device)
        mp.submit(_kf(seq, cam, 0))
        mp.submit(_kf(seq, cam, 2, kid=1))
        mp.submit(_kf(seq, cam, 2, kid=2))
        near = _kf(seq, cam, 2, kid=3)
        for kid in range(3, 6):
            mp.submit(KeyframeMessage(kid, 2, near.timestamp, near.image, cam, near.cam_to_world, near.points_uv,
                                      np.asarray(near.idepths) * 4.0))
            mp.process_pending()
            if kid == 4:    # two such keyframes: not yet
                assert mp.views[1].depth_z is not None and mp.views[1].fixed_pose
        res = {r.keyframe_id: r for r in mp.stats.seed_results}
        assert all(res[k].depth_error_median > 2.5 for k in range(3, 6))
        assert mp.stats.keyframes_untrusted == 3
        if limit:
            assert mp.stats.keyframes_scale_broken == 3 and mp.stats.odometry_untrusted_at == 5
            assert [mp.views[k].fixed_pose for k in range(6)] == [True] + [False] * 5
            assert all(mp.views[k].depth_z is None for k in range(6))
            mp.submit(_kf(seq, cam, 2, kid=6))     # true depths again, after the break: not trusted
            mp.process_pending()
            assert not mp.views[6].fixed_pose and mp.views[6].depth_z is None
        else:
            assert mp.stats.keyframes_scale_broken == 0 and mp.stats.odometry_untrusted_at is None
            assert [mp.views[k].fixed_pose for k in range(6)] == [True, True, True] + [False] * 3
            assert mp.views[1].depth_z is not None and mp.views[2].depth_z is not None


def test_a_map_that_refines_every_pose_holds_its_keyframes_on_a_loop(wp_device, seq, cam):
    """Once the run's odometry is not trusted (mapping.seeding.distrust_median fired: the map refines every pose), a
    LoopCorrection moves the odometry's poses the map follows, not the map: the views and Gaussians stay, and the
    map's correction of the keyframe (map pose = W @ odometry pose) absorbs the loop's Sim(3), so a frame the
    odometry puts at the corrected pose renders from where the map holds it. The control
    (mapping.mapper.loop_moves_untrusted=true) moves the view as test_loop_correction_moves_views_depths_and_anchored_
    gaussians does."""
    from mgso.geometry import sim3_from_parts, so3_exp
    from mgso.messages import LoopCorrection, sim3_apply_to_pose

    over = ["mapping.mapper.iterations_per_keyframe=2", "mapping.mapper.final_iterations=0",
            "mapping.capacity=20000", "mapping.mapper.exposure=odometry"]
    S = sim3_from_parts(so3_exp([0.05, -0.1, 0.02]), np.array([0.3, 0.1, -0.2]), 1.4)
    for moves in (False, True):
        mp = Mapper(load_config(None, [*over, f"mapping.mapper.loop_moves_untrusted={moves}"]), device=wp_device)
        mp.submit(_kf(seq, cam, 0))
        near = _kf(seq, cam, 2, kid=1)
        for kid in range(1, 4):     # three keyframes whose depths are a quarter of the truth: the rule fires
            mp.submit(KeyframeMessage(kid, 2, near.timestamp, near.image, cam, near.cam_to_world, near.points_uv,
                                      np.asarray(near.idepths) * 4.0))
        mp.process_pending()
        assert mp.stats.odometry_untrusted_at == 3
        c2w3, odo3 = mp.views[3].cam_to_world.copy(), mp._odo_c2w[3].copy()
        before = mp.gmap.to_numpy()
        mp.submit(LoopCorrection({0: S, 3: S}, loop=1))    # keyframe 0 holds the seeds
        mp.process_pending()
        np.testing.assert_allclose(mp._odo_c2w[3], sim3_apply_to_pose(S, odo3), atol=1e-12)
        if not moves:
            assert mp.stats.loop_corrections_held == 1 and mp.stats.gaussians_moved == 0
            np.testing.assert_array_equal(mp.views[3].cam_to_world, c2w3)
            np.testing.assert_array_equal(mp.gmap.to_numpy().means, before.means)
            np.testing.assert_allclose(mp.correction(3) @ sim3_apply_to_pose(S, odo3), c2w3, atol=1e-9)
        else:
            assert mp.stats.loop_corrections_held == 0 and mp.stats.gaussians_moved > 0
            np.testing.assert_allclose(mp.views[3].cam_to_world, sim3_apply_to_pose(S, c2w3), atol=1e-9)
    # a map that refines no pose (mapping.train.refine_poses=false) cannot hold itself against the odometry: it moves
    mp = Mapper(load_config(None, [*over, "mapping.train.refine_poses=false"]), device=wp_device)
    mp.submit(_kf(seq, cam, 0))
    for kid in range(1, 4):
        mp.submit(KeyframeMessage(kid, 2, near.timestamp, near.image, cam, near.cam_to_world, near.points_uv,
                                  np.asarray(near.idepths) * 4.0))
    mp.process_pending()
    assert mp.stats.odometry_untrusted_at == 3
    c2w3 = mp.views[3].cam_to_world.copy()
    mp.submit(LoopCorrection({0: S, 3: S}, loop=1))
    mp.process_pending()
    assert mp.stats.loop_corrections_held == 0
    np.testing.assert_allclose(mp.views[3].cam_to_world, sim3_apply_to_pose(S, c2w3), atol=1e-9)
