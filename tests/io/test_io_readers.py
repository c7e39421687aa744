"""Every reader on a tiny fake dataset: layout detection, frames, timestamps, calibration, ground truth, depth."""

from __future__ import annotations

import numpy as np
import pytest
from io_fakes import H, W, poses, textured

from mgso.camera import EquidistantCamera, FOVCamera, RadTanCamera
from mgso.config import InputConfig
from mgso.geometry import orthonormalize
from mgso.io import (DatasetError, EurocSequence, ImageFolderSequence, KittiSequence, ReplicaSequence,
                     SevenScenesSequence, TumMonoSequence, TumRgbdSequence, VideoSequence, detect_layout, open_sequence,
                     read_tum)

DESCRIBE_KEYS = {"layout", "name", "path", "frames", "frames_total", "image_size_in", "image_size_out", "intrinsics",
                 "camera_model", "distortion", "photometric", "groundtruth", "time_span", "fps", "rectify",
                 "undistortion", "color", "depth", "calibration_source", "valid_fraction"}


def check_frame(seq, i, color_expected):
    f = seq.load(i)
    w, h = seq.calibration.output_size
    assert f.index == i and f.timestamp == seq.timestamp(i)
    assert f.gray.dtype == np.float32 and f.gray.shape == (h, w)
    assert f.rgb.dtype == np.float32 and f.rgb.shape == (h, w, 3)
    assert 0.0 <= f.rgb.min() and f.rgb.max() <= 1.0
    if not color_expected:
        np.testing.assert_array_equal(f.rgb[..., 0], f.rgb[..., 2])
    assert f.gray.max() > 20  # real content, 0-255 scale
    return f


def test_tum_rgbd_freiburg_default_gt_and_depth(fakes):
    d = fakes.tum_rgbd(name="rgbd_dataset_freiburg3_fake", n=6, size=(640, 480))
    assert detect_layout(d) == "tum_rgbd"
    seq = open_sequence(d)
    assert isinstance(seq, TumRgbdSequence) and len(seq) == 6 and seq.color
    assert isinstance(seq.calibration.input, RadTanCamera) and not seq.calibration.input.has_distortion
    assert seq.calibration.input.fx == 535.4  # freiburg3 default (no distortion: passed through)
    assert seq.calibration.undistorter.kind == "passthrough"
    f = check_frame(seq, 2, True)
    # gray is OpenCV's BGR->gray of the stored image, exactly (passthrough, no photometric calibration)
    import cv2
    raw = cv2.imread(f.source)
    np.testing.assert_array_equal(f.gray, cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY).astype(np.float32))
    np.testing.assert_allclose(f.rgb, raw[:, :, ::-1] / 255.0, atol=1e-6)
    # ground truth: the 100 Hz pose nearest to each image time (3 ms away), from the file itself
    gt_file = read_tum(d / "groundtruth.txt")
    gt = seq.groundtruth
    assert gt is not None and len(gt) == 6
    for i in range(6):
        j = int(np.argmin(np.abs(gt_file.timestamps - seq.timestamp(i))))
        np.testing.assert_allclose(seq.groundtruth_cam_to_world(i), gt_file.cam_to_world[j])
    assert np.allclose(gt.timestamps, seq.timestamps)
    # depth: 5000 units per metre, associated within 4 ms
    assert seq.has_depth
    np.testing.assert_allclose(seq.load_depth(3), 4.0)
    info = seq.describe()
    assert DESCRIBE_KEYS <= set(info) and info["groundtruth"]["poses"] == 6 and info["frames"] == 6


def test_tum_rgbd_camera_txt_takes_precedence(fakes):
    cam = f"Pinhole 25 26 19.5 14.5 0\n{W} {H}\nnone\n{W} {H}\n"
    d = fakes.tum_rgbd(name="rgbd_dataset_freiburg1_fake", n=3, camera_txt=cam, gt=False, depth=False)
    seq = open_sequence(d)
    out = seq.calibration.output
    assert (out.fx, out.fy, out.cx, out.cy, out.width, out.height) == (25, 26, 19.5, 14.5, W, H)
    assert seq.groundtruth is None and not seq.has_depth and seq.load_depth(0) is None
    assert seq.calibration.undistorter.passthrough


def test_tum_rgbd_freiburg1_is_undistorted_keeping_the_field_of_view(fakes):
    d = fakes.tum_rgbd(name="rgbd_dataset_freiburg1_fake", n=2, gt=False, depth=False, size=(640, 480))
    seq = open_sequence(d)
    cal = seq.calibration
    assert cal.input.k1 == pytest.approx(0.2624)
    assert cal.undistorter.kind == "remap" and cal.output_mode == "keep"
    assert cal.output.fx < 1.05 * cal.input.fx  # not DSO's crop (711.2)
    info = seq.describe()
    assert info["rectify"] == "keep" and 0.998 < info["valid_fraction"] < 1.0
    f = seq.load(1)
    # the frame carries the io layer's mask: the pixels without a source, only in the outer 3 rows / columns
    assert f.valid is cal.undistorter.valid_mask and f.valid.shape == f.gray.shape and not f.valid.all()
    assert not f.valid.flags.writeable
    yy, xx = np.nonzero(~f.valid)
    assert np.minimum(np.minimum(xx, 639 - xx), np.minimum(yy, 479 - yy)).max() < 3
    assert f.valid_weights.dtype == np.float32 and f.valid_weights.sum() == f.valid.sum()
    # no black border: the pixels without a source hold the nearest recorded pixel
    assert f.gray[~f.valid].min() > 0 and f.rgb[~f.valid].max() > 0


def test_tum_rgbd_freiburg1_crop_on_request(fakes):
    """Negative control: input.rectify=crop still gives DSO's crop camera, every pixel with a source."""
    d = fakes.tum_rgbd(name="rgbd_dataset_freiburg1_fake", n=2, gt=False, depth=False, size=(640, 480))
    seq = open_sequence(d, config=InputConfig(rectify="crop"))
    out = seq.calibration.output
    assert seq.calibration.output_mode == "crop"
    assert (round(out.fx, 1), round(out.fy, 1)) == (711.2, 533.3)
    assert seq.load(0).valid is None


def test_frames_without_distortion_carry_no_mask(fakes):
    seq = open_sequence(fakes.kitti(n=2))
    assert seq.calibration.undistorter.kind == "passthrough" and seq.load(0).valid is None


def test_tum_mono_folder_with_photometric_and_gt_sync(fakes):
    d = fakes.tum_mono(n=5)
    assert detect_layout(d) == "tum_mono"
    seq = open_sequence(d)
    assert isinstance(seq, TumMonoSequence) and len(seq) == 5 and not seq.color
    assert isinstance(seq.calibration.input, FOVCamera)
    # relative intrinsics converted with DSO's rule (fx * W, cx * W - 0.5)
    assert seq.calibration.input.fx == pytest.approx(0.6 * W) and seq.calibration.input.cx == pytest.approx(
        0.5 * W - 0.5)
    assert seq.exposure_ms(3) == pytest.approx(13.0)
    f = check_frame(seq, 1, False)
    assert f.exposure_ms == pytest.approx(11.0)
    # photometric: gray = undistort(G^-1(raw) / V), with G^-1(x) = (x / 255)^2 * 255 and V = 1 (0.5 on the left)
    raw = seq.load_raw(1)
    expect_in = (raw.astype(np.float64) / 255.0) ** 2 * 255.0
    expect_in[:, :5] *= 2.0
    expect = seq.calibration.undistorter.apply(expect_in.astype(np.float32))
    np.testing.assert_allclose(f.gray, expect, rtol=1e-4, atol=1e-3)
    off = open_sequence(d, config=InputConfig(photometric=False)).load(1)
    assert not np.allclose(off.gray, f.gray)
    # groundtruthSync: only the first and last frames have poses
    assert len(seq.groundtruth) == 2 and seq.groundtruth_cam_to_world(2) is None
    info = seq.describe()
    assert info["photometric"]["response"] and info["photometric"]["vignette"] and info["photometric"]["exposure"]


def test_tum_mono_zip_reads_members_in_place(fakes):
    d = fakes.tum_mono(n=4, zipped=True, photometric=False, gt_sync=False)
    seq = open_sequence(d)
    assert len(seq) == 4 and ":" in seq.frame_source(0) and seq.frame_source(0).endswith("00000.jpg")
    raw = seq.load_raw(2)
    np.testing.assert_array_equal(raw, textured(2))
    assert not (d / "images").exists()
    with seq:
        pass
    np.testing.assert_array_equal(seq.load_raw(3), textured(3))  # reopened after close


def test_euroc_csv_groundtruth_with_T_BS(fakes):
    T_BS = poses(3, seed=7)[2]
    d = fakes.euroc(n=5, gt="csv", T_BS=T_BS)
    assert detect_layout(d) == "euroc" and detect_layout(d / "mav0") == "euroc"
    seq = open_sequence(d / "mav0")
    assert isinstance(seq, EurocSequence) and len(seq) == 5
    assert seq.timestamp(1) - seq.timestamp(0) == pytest.approx(0.05, abs=1e-6)
    assert isinstance(seq.calibration.input, RadTanCamera) and seq.calibration.undistorter.kind == "remap"
    np.testing.assert_allclose(seq.T_BS, T_BS, atol=1e-12)
    check_frame(seq, 0, False)
    # body poses every 5 ms starting 100 ms before the first image: image i sits on body pose 20 + 10 i
    body = poses(5 * 10 + 40)
    for i in range(5):
        np.testing.assert_allclose(seq.groundtruth_cam_to_world(i), body[20 + 10 * i] @ T_BS, atol=1e-9)


def test_euroc_body_tum_groundtruth(fakes):
    T_BS = poses(2, seed=3)[1]
    d = fakes.euroc(n=4, gt="tum", T_BS=T_BS)
    seq = open_sequence(d)
    body = read_tum(d / "groundtruth_body_tum.txt")
    np.testing.assert_allclose(seq.groundtruth.cam_to_world, body.cam_to_world @ T_BS, atol=1e-9)


def test_kitti_gray_and_color_camera(fakes):
    d = fakes.kitti(n=5)
    assert detect_layout(d) == "kitti"
    seq = open_sequence(d)
    assert isinstance(seq, KittiSequence) and len(seq) == 5
    cam = seq.calibration.output
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (35.0, 35.0, 19.3, 14.1)
    assert seq.calibration.undistorter.passthrough
    assert seq.timestamp(4) == pytest.approx(4 * 0.1036)
    f = check_frame(seq, 3, False)
    np.testing.assert_array_equal(f.gray, textured(3).astype(np.float32))
    T = poses(5)
    np.testing.assert_allclose(seq.groundtruth.cam_to_world, T, atol=1e-8)


def test_kitti_color_camera_moves_gt_by_the_baseline(fakes):
    d = fakes.kitti(n=3, color=True)
    seq = open_sequence(d, config=InputConfig(camera="image_2"))
    assert seq.color
    # P2 = K [I | t] with t_x = 1.75 / 35 = 0.05 m: camera 2 sits at x = -0.05 in camera 0's frame
    T = poses(3)
    expect = T.copy()
    expect[:, :3, 3] += T[:, :3, :3] @ np.array([-0.05, 0.0, 0.0])
    np.testing.assert_allclose(seq.groundtruth.cam_to_world, expect, atol=1e-8)


def test_kitti_excerpt_starting_later_uses_frame_numbers(fakes):
    d = fakes.kitti(n=3, first=4)
    seq = open_sequence(d)
    assert seq.timestamp(0) == pytest.approx(4 * 0.1036)
    np.testing.assert_allclose(seq.groundtruth_cam_to_world(0), poses(7)[4], atol=1e-8)


def test_replica(fakes):
    d = fakes.replica(n=4)
    assert detect_layout(d) == "replica"
    seq = open_sequence(d, config=InputConfig(fps=10.0))
    assert isinstance(seq, ReplicaSequence) and len(seq) == 4 and seq.color
    assert seq.calibration.output.fx == 20.0 and "cam_params.json" in seq.calibration.source
    assert seq.timestamp(3) == pytest.approx(0.3)
    check_frame(seq, 1, True)
    np.testing.assert_allclose(seq.groundtruth.cam_to_world, poses(4), atol=1e-8)
    np.testing.assert_allclose(seq.load_depth(2), 3 * 6553 / 6553.5, rtol=1e-6)


def test_seven_scenes(fakes):
    d = fakes.seven_scenes(n=4)
    assert detect_layout(d) == "7scenes"
    seq = open_sequence(d)
    assert isinstance(seq, SevenScenesSequence) and len(seq) == 4
    cam = seq.calibration.output
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (525.0, 525.0, 320.0, 240.0)  # never the depth camera's 585
    assert seq.timestamp(3) == pytest.approx(0.1)
    gt = seq.groundtruth.cam_to_world
    R = gt[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(R, orthonormalize(poses(4)[:, :3, :3] * 1.0002), atol=1e-12)
    np.testing.assert_allclose(seq.load_depth(2), 1.002)
    assert seq.depth_camera.fx == 585.0


@pytest.mark.parametrize("ext", ["jpg", "png"])
def test_a_jpeg_frame_is_tracked_on_its_luma_plane_and_keeps_its_colour(fakes, ext, monkeypatch):
    """A JPEG's gray is its luma plane, decoded without the colour (``IMREAD_GRAYSCALE``, as the reference DSO reads
    its images; 2.4 ms less CPU a 7-Scenes frame); its RGB is exactly what decoding the colour gives, decoded from
    the bytes read once, only when asked for. A PNG is decoded once and converted, as before."""
    import cv2

    d = fakes.seven_scenes(n=2, ext=ext)
    seq = open_sequence(d)
    src = seq.frame_source(1)
    # saturated colour blocks: where decoded colour clips, its conversion leaves the luma the encoder stored
    rng = np.random.default_rng(0)
    blocks = rng.choice([0, 255], size=(30, 40, 3)).astype(np.uint8)
    assert cv2.imwrite(src, cv2.resize(blocks, (640, 480), interpolation=cv2.INTER_NEAREST))
    colour = cv2.imread(src, cv2.IMREAD_UNCHANGED)
    luma = cv2.imread(src, cv2.IMREAD_GRAYSCALE)
    converted = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
    reads = []
    import mgso.io.sequence as sequence_mod
    real_read_bytes = sequence_mod.read_bytes
    monkeypatch.setattr(sequence_mod, "read_bytes", lambda path: reads.append(path) or real_read_bytes(path))
    f = seq.load(1)
    assert len(reads) == 1
    np.testing.assert_array_equal(f.gray, (luma if ext == "jpg" else converted).astype(np.float32))
    np.testing.assert_array_equal(f.rgb, seq.calibration.rgb_from_raw(colour))
    assert len(reads) == 1  # the colour from the bytes kept with the frame, not the file again
    if ext == "jpg":
        assert np.any(luma != converted)  # the two grays differ (chroma round-off): the test can tell them apart
        assert np.abs(luma.astype(int) - converted.astype(int)).mean() < 2.0


def test_image_folder_natural_order_and_fps(fakes):
    d = fakes.image_folder(n=12)
    assert detect_layout(d) == "images"
    seq = open_sequence(d, config=InputConfig(fps=20.0))
    assert isinstance(seq, ImageFolderSequence) and len(seq) == 12
    assert seq.frame_source(10).endswith("img10.png") and seq.frame_source(2).endswith("img2.png")
    assert seq.timestamp(10) == pytest.approx(0.5) and seq.fps == pytest.approx(20.0)
    check_frame(seq, 0, True)


def test_image_folder_times_txt_and_calib_argument(fakes, tmp_path):
    d = fakes.image_folder(n=4, times=True, calib=None)
    calib = tmp_path / "cam.txt"
    calib.write_text("28 29 19.5 14.5 -0.05 0.01 0 0\n")  # plain fx fy cx cy k1 k2 p1 p2
    seq = open_sequence(d, calib=calib)
    assert seq.timestamp(3) == pytest.approx(100.12)
    assert isinstance(seq.calibration.input, RadTanCamera) and seq.calibration.output_mode == "keep"


def test_the_calibration_given_as_numbers(fakes, tmp_path, monkeypatch):
    """``calib=`` may be the numbers of a plain intrinsics file themselves (``mgso run clip.mp4 --calib "fx fy cx
    cy"``): the same camera as the file; a wrong count names the numbers; a file of that name wins."""
    d = fakes.image_folder(n=3, calib=None)
    inline = open_sequence(d, calib="28 29 19.5 14.5 -0.05 0.01 0 0")
    (tmp_path / "cam.txt").write_text("28 29 19.5 14.5 -0.05 0.01 0 0\n")
    from_file = open_sequence(d, calib=tmp_path / "cam.txt")
    assert inline.calibration.input == from_file.calibration.input
    assert isinstance(inline.calibration.input, RadTanCamera) and inline.calibration.output_mode == "keep"
    assert open_sequence(d, calib="30,30,19.5,14.5").calibration.input.fx == 30.0
    with pytest.raises(DatasetError, match=r"30 30 19\.5: expected 4 \(fx fy cx cy\), 8 .* got 3"):
        open_sequence(d, calib="30 30 19.5")
    with pytest.raises(DatasetError, match="not found"):
        open_sequence(d, calib="cam2.txt")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "31").write_text("31 31 19.5 14.5\n")   # a file named like a number is read as the file
    assert open_sequence(d, calib="31").calibration.input.fx == 31.0


def test_video(fakes):
    p = fakes.video(n=6, fps=10.0)
    assert detect_layout(p) == "video"
    seq = open_sequence(p)
    assert isinstance(seq, VideoSequence) and len(seq) == 6
    np.testing.assert_allclose(seq.timestamps, np.arange(6) * 0.1, atol=1e-6)
    means = [seq.load(i).gray.mean() for i in (0, 1, 2, 3, 4, 5)]
    assert np.all(np.diff(means) > 20)  # brightness encodes the frame number
    # random access backwards gives the same frame as sequential access
    np.testing.assert_array_equal(seq.load(1).gray, open_sequence(p).load(1).gray)
    np.testing.assert_array_equal(seq.load(4).gray, seq.load(4).gray)
    seq.close()
    np.testing.assert_array_equal(seq.load(2).gray, open_sequence(p).load(2).gray)


def test_selection_start_end_stride(fakes):
    d = fakes.kitti(n=5)
    full = open_sequence(d)
    seq = open_sequence(d, config=InputConfig(start=1, end=5, stride=2))
    assert len(seq) == 2 and seq.frames_total == 5
    assert seq.timestamp(1) == full.timestamp(3)
    np.testing.assert_array_equal(seq.load(1).gray, full.load(3).gray)
    assert len(seq.groundtruth) == 2
    np.testing.assert_allclose(seq.groundtruth.cam_to_world[1], full.groundtruth.cam_to_world[3])
    assert seq.load(-1).index == 1
    with pytest.raises(IndexError):
        seq.load(2)


def test_prefetch_iteration_matches_load(fakes):
    d = fakes.kitti(n=5)
    seq = open_sequence(d, config=InputConfig(prefetch=2))
    frames = list(seq)
    assert [f.index for f in frames] == list(range(5))
    for f in frames:
        np.testing.assert_array_equal(f.gray, seq.load(f.index).gray)
    # stopping early does not hang or leak the worker
    it = seq.frames(prefetch=1)
    next(it)
    it.close()
    assert [f.index for f in seq.frames(prefetch=0)] == list(range(5))


def test_output_size_and_rectify_overrides(fakes):
    d = fakes.euroc(n=2, gt="none")
    seq = open_sequence(d, config=InputConfig(width=20, rectify="full"))
    assert seq.calibration.output_size == (20, 15) and seq.calibration.output_mode == "full"
    assert seq.load(0).gray.shape == (15, 20)
    k = open_sequence(fakes.kitti(n=2), config=InputConfig(width=20, height=15))
    cam = k.calibration.output
    assert k.calibration.undistorter.kind == "resize"
    assert cam.fx == pytest.approx(35.0 * 20 / W) and cam.cx == pytest.approx((19.3 + 0.5) * 20 / W - 0.5)


def test_ready_calibration_objects_are_used_as_given(fakes):
    from mgso.camera import Calibration
    cal = Calibration.create(EquidistantCamera(20, 20, 19.5, 14.5, W, H, 0.01, 0.0, 0.0, 0.0), "crop")
    seq = open_sequence(fakes.image_folder(n=2, calib=None), calib=cal)
    assert seq.calibration is cal
