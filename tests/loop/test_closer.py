"""Loop closure in the whole system (mgso.loop.closer through mgso.system): the oracle odometry with injected drift
around one figure-eight of the synthetic room (the camera comes back to its start), with loop closure on and off."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mgso import synthetic
from mgso.app.outputs import write_outputs
from mgso.config import load_config
from mgso.io import open_sequence
from mgso.io.ply import read_gaussians_ply
from mgso.eval import compute_ate
from mgso.io.trajectory import Trajectory, read_tum
from mgso.observers import Observer, ObserverList
from mgso.oracle import OracleOdometry
from mgso.system import System

# 88 frames at motion scale 4: one figure-eight is 79 frames, so the last 9 see the start again. The drift bends the
# oracle's estimate by 0.1 degrees, 2 mm and 0.3 % of scale a frame (26 % of scale by the end), as an odometry drifts.
LOOP_SEQ = dict(num_frames=88, width=256, height=192, seed=0, motion_scale=4.0)
DRIFT = (0.002, 0.002, 0.003)
ORACLE = dict(keyframe_every=4, points=1000, drift=DRIFT)
BASE = ["mapping.mapper.iterations_per_keyframe=5", "mapping.mapper.final_iterations=30", "output.plot=false",
        "output.save_renders=false", "system.eval_photo_slam=false"]


@pytest.fixture(scope="module")
def loop_folder():
    return synthetic.cached_sequence_folder(**LOOP_SEQ)


def _run(folder, out_dir, *over, oracle=None, frames=None, viewer=None):
    cfg = load_config(None, [*BASE, *over])
    seq = open_sequence(str(folder), config=cfg.input)
    odo = OracleOdometry.from_sequence(seq, **(oracle or ORACLE))
    obs = None
    if viewer is not None:
        viewer.in_step = _ViewerInStep(viewer)
        obs = ObserverList([viewer, viewer.in_step])
    system = System(odo, cfg, observer=obs)
    if viewer is not None:
        viewer.attach(system)                 # as `mgso run --viewer` does
    it = seq.frames() if frames is None else (f for i, f in enumerate(seq.frames()) if i < frames)
    result = system.run(it)
    metrics = write_outputs(result, system.mapper, seq, cfg, out_dir, odometry_name=odo.name)
    metrics["out"] = Path(out_dir)
    return result, metrics, system


class _ViewerInStep(Observer):
    """A live viewer (not started: no server) whose thread's work is done after every frame, as if it kept up:
    the points merged, the loop corrections applied, the frames' path brought up to date (its cache)."""

    def __init__(self, viewer):
        self.viewer = viewer
        self.cache_error = 0.0               # the cached path against the whole path corrected anew, each frame

    def on_frame(self, result) -> None:
        v = self.viewer
        v._merge_points()
        v._apply_loops()
        pos, ts = v._frame_path()
        if v._closer is not None and v._closer.corrected:
            raw = Trajectory(ts, np.stack([T for _, T in v._poses]))
            self.cache_error = max(self.cache_error, float(np.abs(v._closer.correct_trajectory(raw).positions
                                                                  - pos).max()))


@pytest.fixture(scope="module")
def loop_runs(loop_folder, tmp_path_factory):
    try:
        from mgso.app.viewer import LiveViewer

        viewer = LiveViewer(port=0)
    except Exception:  # noqa: BLE001 - viser is an extra; the viewer's test skips without it
        viewer = None
    on = _run(loop_folder, tmp_path_factory.mktemp("loop-on"), viewer=viewer)
    off = _run(loop_folder, tmp_path_factory.mktemp("loop-off"), "loop.enabled=false")
    return on, off, viewer


def test_a_loop_with_drift_is_closed_and_corrects_trajectory_and_map(loop_runs):
    (res, m, system), (res_off, m_off, _), _ = loop_runs
    lp = m["loop"]
    # measured (2026-12-03, 5 steps a keyframe; 2026-12-02 with 10: 0.0225 m, 23.58 -> 24.05 dB): 3 loops accepted
    # (keyframes 19-21 on keyframes 0-1), ATE 0.0695 -> 0.0227 m, PSNR (MonoGS protocol) 23.57 -> 23.95 dB; since
    # the map refines the poses a loop moved (mapping.mapper.loop_refines_poses, 2026-12-06) 23.57 -> 24.30 dB: the
    # bound below fails with those poses held (+0.38 dB)
    assert lp["accepted"] >= 1 and lp["graph_solves"] == lp["accepted"] and lp["corrections_sent"] >= 1
    for rec in lp["loops"]:
        assert rec["candidate_frame_index"] < 16 and rec["frame_index"] >= 72      # the start, seen again
        assert rec["scale"] == pytest.approx(np.exp(-DRIFT[2] * (rec["frame_index"] - rec["candidate_frame_index"])),
                                             rel=0.05)
    assert m_off["loop"] is None and m_off["ate_odometry_all_frames_m"] is None
    # the odometry's own trajectory is the same in both runs, and it is what the disabled run wrote
    assert m["ate_odometry_all_frames_m"] == pytest.approx(m_off["ate_all_frames_m"], rel=1e-9)
    assert m["ate_all_frames_m"] < 0.5 * m_off["ate_all_frames_m"]
    assert m["psnr_monogs_db"] > m_off["psnr_monogs_db"] + 0.4
    assert res.mapper.loop_corrections == lp["corrections_sent"] and res.mapper.gaussians_moved > 0
    assert res_off.mapper.loop_corrections == 0


def test_corrected_outputs_are_written(loop_runs, loop_folder):
    (res, m, system), (_, m_off, _), _ = loop_runs
    out = m["out"]
    assert "trajectory_odometry.txt" in m["written"] and "trajectory_odometry.txt" not in m_off["written"]
    corrected, odo = read_tum(out / "trajectory.txt"), read_tum(out / "trajectory_odometry.txt")
    assert len(corrected) == len(odo) == res.frames_processed
    np.testing.assert_allclose(corrected.cam_to_world, res.trajectory.cam_to_world, atol=1e-6)
    np.testing.assert_allclose(odo.cam_to_world, res.odometry_trajectory.cam_to_world, atol=1e-6)
    # the first frames are the gauge (unmoved); the last ones moved by the loop's correction
    assert np.abs(corrected.cam_to_world[0] - odo.cam_to_world[0]).max() < 1e-6
    assert np.linalg.norm(corrected.cam_to_world[-1][:3, 3] - odo.cam_to_world[-1][:3, 3]) > 0.01
    kf = read_tum(out / "keyframes.txt")
    np.testing.assert_allclose(kf.cam_to_world, res.keyframe_trajectory.cam_to_world, atol=1e-6)
    assert read_gaussians_ply(out / "map.ply").n == m["num_gaussians"]


def test_the_point_cloud_moves_with_its_keyframes(loop_runs, loop_folder):
    """points.ply's DSO points sit where their host keyframe saw them: each corrected point projects into its host's
    corrected pose at the integer pixel the oracle selected it at (a point moved twice, or not at all, does not)."""
    from mgso.geometry import se3_inverse

    (res, m, system), _, _ = loop_runs
    cam = open_sequence(str(loop_folder), config=load_config().input).calibration.output
    corrected, _, hosts = res.cloud.arrays()
    kf = {round(t, 9): T for t, T in zip(res.keyframe_trajectory.timestamps, res.keyframe_trajectory.cam_to_world)}
    moved = 0
    for h in np.unique(hosts):
        sel = hosts == h
        B = se3_inverse(kf[round(system.loop._time[int(h)], 9)])
        pc = corrected[sel] @ B[:3, :3].T + B[:3, 3]
        uv = np.stack([cam.fx * pc[:, 0] / pc[:, 2] + cam.cx, cam.fy * pc[:, 1] / pc[:, 2] + cam.cy], axis=1)
        assert np.abs(uv - np.round(uv)).max() < 1e-3, h
        moved += int(not np.allclose(system.loop.correction_of(int(h)), np.eye(4)))
    assert moved > 0                      # some hosts were corrected


def test_the_live_viewer_follows_the_loop(loop_runs, loop_folder):
    """What a live viewer shows after the loops is the corrected run: its frames' path is the corrected trajectory
    (the odometry's own ends centimetres away: the negative control), its keyframe frusta the corrected keyframes,
    its DSO points the corrected point cloud."""
    (res, m, system), _, viewer = loop_runs
    if viewer is None:
        pytest.skip('the viewer needs viser: pip install "mgso[viewer]" (or "[test]")')
    assert viewer.loops == m["loop"]["corrections_sent"] >= 1
    viewer._merge_points()
    viewer._apply_loops()
    pos, ts = viewer._frame_path()              # brought up to date frame by frame during the run (its cache)
    raw = Trajectory(np.array([t for t, _ in viewer._poses]), np.stack([T for _, T in viewer._poses]))
    np.testing.assert_allclose(ts, raw.timestamps)
    np.testing.assert_allclose(pos, system.loop.correct_trajectory(raw).positions, atol=1e-9)
    gt = open_sequence(str(loop_folder), config=load_config().input).groundtruth
    at = np.repeat(np.eye(4)[None], len(pos), axis=0)
    at[:, :3, 3] = pos                                                  # the ATE takes positions only
    shown = compute_ate(Trajectory(ts, at), gt, align="sim3", max_diff=0.01).rmse
    tracked = compute_ate(raw, gt, align="sim3", max_diff=0.01).rmse
    # measured: the path shown 0.0227 m (as trajectory.txt), the odometry's own poses 0.0695 m (the control);
    # the path kept up to date frame by frame equal to the whole path corrected anew (0.0)
    assert shown == pytest.approx(m["ate_all_frames_m"], rel=1e-6)
    assert tracked == pytest.approx(m["ate_odometry_all_frames_m"], rel=0.05) and shown < 0.5 * tracked
    assert viewer.in_step.cache_error < 1e-9
    kf = {round(t, 9): T for t, T in zip(res.keyframe_trajectory.timestamps, res.keyframe_trajectory.cam_to_world)}
    moved = 0
    for kid, T in viewer._kf_poses.items():
        want = kf[round(system.loop._time[kid], 9)]
        np.testing.assert_allclose(T, want, atol=1e-6)
        moved += int(not np.allclose(system.loop.correction_of(kid), np.eye(4)))
    assert moved > 0 and len(viewer._kf_poses) == len(kf)
    points, _, _ = res.cloud.arrays()
    np.testing.assert_allclose(np.concatenate(viewer._cloud_p), points, atol=1e-4)


def test_without_a_revisit_nothing_is_accepted_and_nothing_changes(loop_folder, tmp_path):
    """The first 44 frames (half a figure-eight: no place seen twice): no loop accepted, and the run is bit for bit
    the run without loop closure (the trajectory and the map, trained 2 steps a keyframe and 5 at the end)."""
    few = ("mapping.mapper.iterations_per_keyframe=2", "mapping.mapper.final_iterations=5")
    res, m, system = _run(loop_folder, tmp_path / "on", *few, frames=44)
    res_off, m_off, system_off = _run(loop_folder, tmp_path / "off", *few, "loop.enabled=false", frames=44)
    assert m["loop"]["keyframes"] == 11 and m["loop"]["accepted"] == 0
    assert res.odometry_trajectory is None
    np.testing.assert_array_equal(res.trajectory.cam_to_world, res_off.trajectory.cam_to_world)
    a, b = system.mapper.gmap.to_numpy(), system_off.mapper.gmap.to_numpy()
    np.testing.assert_array_equal(a.means, b.means)
    np.testing.assert_array_equal(a.sh, b.sh)


def test_realtime_closes_the_loop_on_its_own_thread(loop_folder, tmp_path):
    """Real time: detection, verification and the graph on the closer's thread, the mapper in its process; the loop
    is still found (played as fast as the odometry takes frames, nothing dropped) and the trajectory corrected."""
    res, m, system = _run(loop_folder, tmp_path, "system.mode=realtime", "system.playback_speed=0")
    assert system.loop.background and m["loop"]["accepted"] >= 1
    assert res.mapper.loop_corrections >= 1
    assert m["ate_all_frames_m"] < 0.5 * m["ate_odometry_all_frames_m"]


@pytest.mark.parametrize("mode", ["deterministic", "realtime"])
def test_a_failure_turns_loop_closure_off_and_the_run_goes_on(loop_folder, tmp_path, monkeypatch, mode):
    """A failure of loop closure (here on the closer's thread, in real time) does not stop the SLAM run: loop closure
    is off from then on, the outputs are written, and metrics.json and the log say what failed."""
    import mgso.loop.place as place

    calls = {"n": 0}

    def broken(*a, **k):
        calls["n"] += 1
        raise MemoryError("no room for features")

    monkeypatch.setattr(place, "extract_features", broken)
    # 32 frames (8 keyframes): the first search fails, and the run goes on for seven more keyframes
    res, m, system = _run(loop_folder, tmp_path, f"system.mode={mode}", "system.playback_speed=0", frames=32)
    assert m["loop"]["error"] == "MemoryError: no room for features"
    assert m["loop"]["accepted"] == 0 and res.frames_processed == 32 and m["loop"]["keyframes"] == 8
    assert calls["n"] == 1                                  # off after the failure: no more searches
    assert (m["out"] / "map.ply").is_file() and m["ate_all_frames_m"] is not None


def test_the_window_is_what_the_last_window_update_named_not_the_final_one(loop_folder):
    """The odometry's window optimisations name the window's keyframes; its finish() names every keyframe. The
    closer moves the window rigidly and gives the others the graph's solution, so the final update must not make
    every keyframe a window keyframe."""
    from mgso.loop.closer import LoopCloser
    from mgso.messages import KeyframeMessage, PoseUpdate

    cfg = load_config(None, BASE)
    seq = open_sequence(str(loop_folder), config=cfg.input)
    odo = OracleOdometry.from_sequence(seq, **{**ORACLE, "window": 3})
    closer = LoopCloser(cfg)
    kids = []
    for i, f in enumerate(seq.frames()):
        for m in odo.process(f).messages:
            closer.observe(m)
            if isinstance(m, KeyframeMessage):
                kids.append(m.keyframe_id)
        if i == 40:
            break
    # the oracle's window update at keyframe k names the 3 before it; k itself is newer: 4 in the window
    assert closer.window_keyframes == kids[-4:]
    everything = PoseUpdate({k: np.eye(4) for k in kids})   # what DSO's finish() sends: every keyframe
    closer.observe(everything, final=True)
    assert closer.window_keyframes == kids[-4:]
    closer.observe(everything)                     # the negative control: taken as a window update
    assert closer.window_keyframes == kids


def test_the_closer_runs_on_the_odometrys_device_or_else_the_systems(loop_folder):
    """Issue 44: the closer took ``getattr(odometry, "device", None)``: with the oracle (no kernels, no device) it
    ran on the CPU whatever device the run was given. Now an odometry says its device; the oracle's None means the
    system's."""
    cfg = load_config(None, BASE)
    seq = open_sequence(str(loop_folder), config=cfg.input)
    oracle = OracleOdometry.from_sequence(seq, **ORACLE)
    assert oracle.device is None
    assert System(oracle, cfg, device="cpu").loop.device == "cpu"

    class OnDevice:                  # an odometry on a device of its own: the closer follows it
        device = "cpu:odometry"

        def __getattr__(self, name):
            return getattr(oracle, name)

    assert System(OnDevice(), cfg, device="cpu").loop.device == "cpu:odometry"


def test_a_loop_with_a_threefold_scale_drift_is_closed(loop_folder, tmp_path):
    """Issue 43: monocular scale drifting 3x between the passes (1.25 % a frame over the 88 frames) is what a real
    first pass does; the Sim(3) loop edge and the pose graph take it. Measured: 3 loops (frames 76-84 on 0-4, scales
    0.37-0.38), ATE 0.229 -> 0.080 m (the same with loop.geometry=current). The map after the loop renders 1.1 dB
    below the run without loop closure (22.39 against 23.52 dB): not asserted, reported in docs/loop.md."""
    drift = (DRIFT[0], DRIFT[1], 0.0125)
    # the trajectory alone: no training and no renders (the loops and the ATE do not depend on them)
    _, m, _ = _run(loop_folder, tmp_path, "mapping.mapper.iterations_per_keyframe=0",
                   "mapping.mapper.final_iterations=0", "system.eval_monogs=false", oracle=dict(ORACLE, drift=drift))
    lp = m["loop"]
    assert lp["accepted"] >= 1
    for rec in lp["loops"]:
        assert rec["scale"] == pytest.approx(np.exp(-drift[2] * (rec["frame_index"] - rec["candidate_frame_index"])),
                                             rel=0.1)
    assert m["ate_odometry_all_frames_m"] > 0.15                       # the drift is there (measured 0.229 m)
    assert m["ate_all_frames_m"] < 0.5 * m["ate_odometry_all_frames_m"]   # halved (measured 0.35x)

def test_the_odometry_stage_closes_loops_too(loop_folder, tmp_path):
    """`mgso run --stage odometry` runs the same closer and pose graph on DSO's messages (issue 43): the loop
    section in metrics.json, the corrected outputs, the odometry's own poses in trajectory_odometry.txt. Control:
    with loop.enabled=false the same odometry writes exactly those poses as its trajectory (the closer never
    changes the odometry), and no loop section."""
    from mgso.app.cli import main

    on, off = tmp_path / "on", tmp_path / "off"
    assert main(["run", str(loop_folder), "--out", str(on), "--stage", "odometry", "-q",
                 "--set", "output.plot=false"]) == 0
    assert main(["run", str(loop_folder), "--out", str(off), "--stage", "odometry", "-q",
                 "--set", "output.plot=false", "--set", "loop.enabled=false"]) == 0
    m_on = json.loads((on / "metrics.json").read_text())
    m_off = json.loads((off / "metrics.json").read_text())
    lp = m_on["loop"]
    # measured: 54 keyframes, 61 candidates, 20 loops (DSO barely drifts here: ATE 1.07 -> 1.05 mm)
    assert lp["keyframes"] == m_on["keyframes"]["in_trajectory"] and lp["accepted"] >= 5 and lp["candidates"] >= 20
    assert lp["accepted"] + sum(lp["rejected"].values()) == lp["candidates"]
    assert m_on["ate_all_frames_m"] <= 1.1 * m_on["ate_odometry_all_frames_m"]
    assert m_off["loop"] is None and m_off["ate_odometry_all_frames_m"] is None
    assert not (off / "trajectory_odometry.txt").exists()
    odo, plain = read_tum(on / "trajectory_odometry.txt"), read_tum(off / "trajectory.txt")
    np.testing.assert_array_equal(odo.cam_to_world, plain.cam_to_world)
    assert m_off["ate_all_frames_m"] == m_on["ate_odometry_all_frames_m"]
    corrected = read_tum(on / "trajectory.txt")
    assert np.abs(corrected.positions - plain.positions).max() > 0     # the loops moved it
