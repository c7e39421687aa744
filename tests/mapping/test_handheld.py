"""The map on a handheld camera (docs/mapping.md, "Handheld camera"): views that disagree, and the map's health.

On TUM RGB-D freiburg1_rpy (a handheld Kinect rolling, pitching and yawing over a desk) DSO's poses drift by 1-8
degrees between views of the same place, its depths are poor (little parallax), and the map became fog. The
synthetic reproduction: the package's room seen by a camera that rotates in place (``synthetic.rotation_path``),
fed to the mapper by the oracle odometry with a drifting rotation and inverse depths off by 80 % and by factors
(their median relative depth error against the map 0.54-0.71, within DSO's 0.46-3.8 on freiburg1_rpy).
"""

from __future__ import annotations

import numpy as np
import pytest

from mgso import synthetic
from mgso.camera import PinholeCamera
from mgso.config import load_config
from mgso.io import open_sequence
from mgso.mapping.mapper import Mapper
from mgso.messages import KeyframeMessage, Stop
from mgso.oracle import OracleOdometry
from mgso.system import System
from mgso.app.outputs import write_outputs

# measured first (96x72, 40 frames, motion_scale 2, 15 steps a keyframe + 100 final): see the test's docstring
BASE = ["mapping.mapper.iterations_per_keyframe=15", "mapping.mapper.final_iterations=100", "output.plot=false",
        "system.eval_photo_slam=false", "output.save_renders=false"]
ORACLE = dict(keyframe_every=4, points=250, idepth_noise=0.8, idepth_log_noise=0.5, drift=(0.006, 0.0, 0.0))
BEFORE = ["mapping.train.depth_weight=0.2", "mapping.train.refine_poses=false",      # the defaults before issue 41
          "mapping.seeding.depth_rule_max_median=0"]


def _run(folder, out, *over):
    cfg = load_config(None, [*BASE, *over])
    seq = open_sequence(str(folder), config=cfg.input)
    odo = OracleOdometry.from_sequence(seq, **ORACLE)
    system = System(odo, cfg)
    result = system.run(seq.frames())
    return write_outputs(result, system.mapper, seq, cfg, out, odometry_name=odo.name)


def test_rotation_path_turns_in_place():
    traj = synthetic.rotation_path(200, motion_scale=3.0)
    c = traj.cam_to_world[:, :3, 3]
    assert np.ptp(c, axis=0).max() < 0.07                           # a few centimetres
    R = traj.cam_to_world[:, :3, :3]
    step = np.degrees([np.arccos(np.clip((np.trace(R[i].T @ R[i + 1]) - 1) / 2, -1, 1)) for i in range(199)])
    assert 0.3 < np.median(step) < 4.0 and step.max() < 6.0          # freiburg1_rpy turns 1-4 degrees a frame
    spec = synthetic.SequenceSpec(num_frames=3)
    assert "path" not in spec.to_dict()                             # the cached figure-eight folders keep their keys
    assert synthetic.SequenceSpec(num_frames=3, path="rotation").key() != spec.key()
    with pytest.raises(ValueError, match="path"):
        synthetic.SequenceSpec(num_frames=3, path="spiral")


def test_the_oracle_puts_a_factor_on_inverse_depths_as_a_point_little_parallax_constrains():
    """OracleOdometry's ``idepth_log_noise``: each keyframe point's inverse depth times exp(N(0, sigma)), so the log
    of its ratio to the true one has spread sigma and no bias; the control without it gives the true depths."""
    folder = synthetic.cached_sequence_folder(num_frames=40, width=96, height=72, seed=0, path="rotation",
                                              motion_scale=2.0)
    seq = open_sequence(str(folder), config=load_config(None, []).input)
    frame = next(iter(seq.frames()))
    truth = seq.load_depth(frame.index)
    logs = {}
    for sigma in (0.0, 0.5):
        odo = OracleOdometry.from_sequence(seq, keyframe_every=4, points=250, idepth_log_noise=sigma)
        kf = next(m for m in odo.process(frame).messages if isinstance(m, KeyframeMessage))
        uv = np.asarray(kf.points_uv).astype(int)
        logs[sigma] = np.log(np.asarray(kf.idepths) * truth[uv[:, 1], uv[:, 0]])
    assert len(logs[0.5]) > 150 and np.abs(logs[0.0]).max() < 1e-5
    assert 0.4 < np.std(logs[0.5]) < 0.6 and abs(np.mean(logs[0.5])) < 0.1


def test_views_that_disagree_fog_the_map_of_before_and_not_the_defaults(tmp_path):
    """The camera turns in place for 40 frames; every frame's world drifts by 0.34 degrees a frame (14 degrees
    over the run: revisited places disagree, as DSO's segments did on freiburg1_rpy) and the keyframes' inverse
    depths are off by 80 % (N(0, 0.8) relative noise) and by factors (exp(N(0, 0.5)): a point little parallax
    constrains is off by 2x and more): the keyframes' median relative depth error against the map 0.54-0.71, as
    DSO's on freiburg1_rpy (0.46-3.8). The defaults of before (a sparse depth term pulling the map to those
    depths, the odometry's poses taken as they are, and the seeding's depth rule seeding every point whose depth
    the map misses by 10 %) make fog: 4,139 Gaussians of median opacity 0.074 (4,165 and 0.077 with the 20-pixel
    seeds of before 2026-12-07), which the summary flags. With the
    defaults since issue 41 the keyframes after the first are not trusted (their depths miss the map by more than
    the 0.5 median of mapping.seeding.depth_rule_max_median): no re-seeding, no depth term, their poses refined;
    the map keeps the first keyframes' 223 seeds, median opacity 0.156 (0.152 with 20-pixel seeds), which it does
    not flag.

    Measured (MonoGS protocol, with the rates for a short schedule of 2026-12-06; 26.80 and 24.87 dB, 0.074 and
    0.141 before them): 28.08 dB before, 24.65 dB now, with seeds of at most 8 pixels (since 2026-12-07; 28.11 and
    25.68 dB with the 20 pixels of before). At this test's budget (15 steps a keyframe + 100 final) the compact map
    is 3.4 dB worse on this scene, the cost of growing by densification alone from the first keyframes' seeds (the
    narrower seeds cover less of the view to grow from); on TUM
    freiburg1_rpy (3,660 steps) the change is worth 6 dB (docs/mapping.md, "Handheld camera"). With relative noise
    alone (80 %: medians 0.47-0.56, 9 of 19 keyframes trusted at 0.5, median opacity 0.065; 50 %: 0.34-0.41, every
    keyframe trusted) the map fogs: the threshold separates a handheld camera's depths from a moving camera's
    (7-Scenes: 0.02-0.2, a stretch to 0.6), not every noise level."""
    from mgso.app.outputs import FOG_MEDIAN_OPACITY, map_warnings
    folder = synthetic.cached_sequence_folder(num_frames=40, width=96, height=72, seed=0, path="rotation",
                                              motion_scale=2.0)
    before = _run(folder, tmp_path / "before", *BEFORE)
    now = _run(folder, tmp_path / "now")
    hb, hn = before["map_health"], now["map_health"]
    assert hb["median_opacity"] < FOG_MEDIAN_OPACITY and hn["median_opacity"] > 1.5 * hb["median_opacity"]
    assert any("mostly transparent" in w for w in map_warnings(hb))
    assert not any("mostly transparent" in w for w in map_warnings(hn))
    assert now["num_gaussians"] < before["num_gaussians"] / 5
    assert now["psnr_monogs_db"] > before["psnr_monogs_db"] - 4.5
    assert now["ate_refined_all_frames_m"] is not None        # the evaluation's poses: the map's refinement


@pytest.mark.parametrize("noise", [False, True])
def test_the_summary_warns_when_the_map_does_not_fit_its_training_views(noise):
    """Mapper.health renders the map's own training views after the final refinement; app.outputs.map_warnings turns
    a low PSNR there into the summary's warning. Six keyframes of the room, 60 steps: the map fits them (about
    25 dB measured, no warning); the control gives each keyframe an image of independent noise in place of the room,
    views no map can agree with (about 11 dB: the warning); and the trained map made nearly transparent (the
    other warning, fog's median opacity)."""
    from mgso.app.outputs import FOG_MEDIAN_OPACITY, POOR_FIT_PSNR_DB, map_warnings
    seq = synthetic.make_sequence(seed=0, num_frames=6, width=80, height=60, motion_scale=1.0)
    k = seq.intrinsics
    cam = PinholeCamera(k.fx, k.fy, k.cx, k.cy, k.width, k.height)
    cfg = load_config(None, ["mapping.mapper.iterations_per_keyframe=0", "mapping.mapper.final_iterations=60",
                             "mapping.capacity=20000"])
    m = Mapper(cfg)
    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.arange(2, 78, 5), np.arange(2, 58, 5))
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    for i in range(6):
        z = seq.depths[i][uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(np.float64)
        img = rng.random(seq.images[i].shape, dtype=np.float32) if noise else seq.images[i]
        m.submit(KeyframeMessage(i, i, float(seq.timestamps[i]), img, cam, seq.cam_to_world[i], uv, 1.0 / z))
    m.submit(Stop(True))
    m.process_pending()
    h = m.stats.health
    assert h["training_views_rendered"] == 6 and 0.0 < h["median_opacity"] < 1.0
    assert 0.0 <= h["transparent_fraction"] <= 1.0 and h["training_view_psnr_min_db"] <= h["training_view_psnr_db"]
    warned = map_warnings(h)
    if noise:
        assert h["training_view_psnr_db"] < POOR_FIT_PSNR_DB - 3 and len(warned) == 1
        assert "training views" in warned[0]
    else:
        assert h["training_view_psnr_db"] > POOR_FIT_PSNR_DB + 3 and warned == []
        assert h["median_opacity"] > FOG_MEDIAN_OPACITY
        # the same map made nearly transparent (every opacity 0.05, as fog's faint Gaussians): the other warning
        m.gmap.opacity_logits.assign(np.full(m.gmap.n, np.log(0.05 / 0.95), np.float32))
        faint = m.health()
        assert faint["median_opacity"] == pytest.approx(0.05, abs=1e-3) and faint["transparent_fraction"] == 1.0
        assert any("mostly transparent" in w for w in map_warnings(faint))


def _tum_run(folder, out, *over):
    """The full system (DSO odometry + mapper) on the first 40 frames of the recording at 160x120, a small budget."""
    from mgso.odometry import Odometry
    from mgso_kernels import runtime

    cfg = load_config(None, ["input.width=160", "input.height=120", "input.end=40",
                             "mapping.mapper.iterations_per_keyframe=5", "mapping.mapper.final_iterations=50",
                             "system.eval_photo_slam=false", "output.plot=false", "output.save_renders=false", *over])
    seq = open_sequence(str(folder), config=cfg.input)
    odo = Odometry.for_camera(seq.calibration.output, cfg, device=runtime.resolve_device("cpu"), emit_messages=True)
    system = System(odo, cfg)
    result = system.run(seq.frames())
    return write_outputs(result, system.mapper, seq, cfg, out, odometry_name="DSO"), system.mapper


def test_on_tum_freiburg1_rpy_the_depth_rule_stands_down_and_the_map_does_not_grow_with_the_run(data_dir, tmp_path):
    """The real handheld recording (TUM RGB-D freiburg1_rpy, its first 40 frames at 160x120, 5 steps a keyframe +
    50 final; skips without ../shared/data). DSO's depths of the rotating camera miss the map's, over a seeding's
    covered candidates, by a median of 0.75 (measured), so the seeding's depth rule stands down on 45 of the 55
    seedings after the first keyframe (the threshold 0.5; 52 at 0.4, 53 at 0.25) and the map grows from the first
    seeds: 8,500 Gaussians, against 26,108 with the rule always on (the control: the defaults of before issue 41 in
    this respect), which re-seeds nearly every point of every keyframe (with the 20-pixel seeds of before
    2026-12-07, which cover more of a view before training, 3,792 against 26,598; 1,831 at 0.4). At this small
    budget the compact map renders a little worse (17.4 against 17.6 dB; 15.7 against 16.1 with the 20-pixel
    seeds); over a whole run it pays (at 640x480 the defaults give 20.09 dB; no depth
    term and every pose refined with the rule always on, 17.84 dB: docs/mapping.md, "Handheld camera"), so the
    floor here only catches a broken run."""
    folder = data_dir / "rgbd_dataset_freiburg1_rpy_0-359"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    now, m = _tum_run(folder, tmp_path / "now")
    ctl, c = _tum_run(folder, tmp_path / "control", "mapping.seeding.depth_rule_max_median=0")
    later = [r for r in m.stats.seed_results[1:] if r.depth_error_median is not None]
    assert len(later) >= 8 and sum(r.depth_tolerance_used == float("inf") for r in later) >= 0.6 * len(later)
    assert np.median([r.depth_error_median for r in later]) > 0.5
    # the control: the rule always on, at its tolerance
    assert all(r.depth_error_median is None for r in c.stats.seed_results)
    assert sum(r.depth_tolerance_used == 0.1 for r in c.stats.seed_results) >= len(later)
    assert now["num_gaussians"] * 2 < ctl["num_gaussians"]
    assert now["psnr_monogs_db"] > 12.0 and now["tracking_losses"] == [] and now["ate_all_frames_m"] < 0.05
