"""Every reader fed broken inputs: each failure is a DatasetError that names the file and the problem."""

from __future__ import annotations

import re
import zipfile

import cv2
import numpy as np
import pytest
from io_fakes import H, W, imwrite, textured

from mgso.config import InputConfig
from mgso.io import DatasetError, ImageFolderSequence, VideoSequence, open_sequence


def edit(path, old, new, count=1):
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new, count))


def corrupt(path):
    path.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")


def swap_lines(path, i, j, skip_comments=True):
    lines = path.read_text().splitlines(keepends=True)
    idx = [k for k, ln in enumerate(lines) if not (skip_comments and ln.startswith("#"))]
    lines[idx[i]], lines[idx[j]] = lines[idx[j]], lines[idx[i]]
    path.write_text("".join(lines))


def drop_lines(path, n):
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[:-n]))


def resize_image(path, w=W + 2, h=H):
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    imwrite(path, cv2.resize(img, (w, h)))


# Each case: (builder, breaker(folder), message regex, file-name regex that the message must contain, stage)
CASES = {
    # ---------------------------------------------------------------- TUM RGB-D
    "tum_rgbd/listed image missing": (
        "tum_rgbd", lambda d: sorted((d / "rgb").iterdir())[0].unlink(), r"rgb\.txt:4: listed image .* does not exist",
        "open"),
    "tum_rgbd/short line": ("tum_rgbd", lambda d: edit(d / "rgb.txt", " rgb/", "_rgb/"),
                            r"rgb\.txt:4: expected at least 2 fields", "open"),
    "tum_rgbd/times out of order": (
        "tum_rgbd", lambda d: swap_lines(d / "rgb.txt", 1, 2),
        r"rgb\.txt:6: timestamps out of order \(1305031102\.2086\d+ after 1305031102\.2419\d+\)", "open"),
    "tum_rgbd/bad timestamp": ("tum_rgbd", lambda d: edit(d / "rgb.txt", "\n1305", "\nabc"),
                               r"rgb\.txt:4: timestamp is not a number", "open"),
    "tum_rgbd/empty listing": ("tum_rgbd", lambda d: (d / "rgb.txt").write_text("# nothing\n"),
                               r"rgb\.txt: image list .* has no entries", "open"),
    # issue 44: an unreadable first frame is skipped as a later one is (the size comes from the next readable one);
    # the sequence is refused only when none of its first images can be read
    "tum_rgbd/corrupt first image": ("tum_rgbd", lambda d: corrupt(sorted((d / "rgb").iterdir())[0]),
                                     r"\.png: not a readable image", "load0"),
    "tum_rgbd/every image corrupt": ("tum_rgbd", lambda d: [corrupt(p) for p in (d / "rgb").iterdir()],
                                     r"\.png: not a readable image .*and none of the first \d+ images can be read",
                                     "open"),
    "tum_rgbd/corrupt later image": ("tum_rgbd", lambda d: corrupt(sorted((d / "rgb").iterdir())[2]),
                                     r"\.png: not a readable image", "load2"),
    "tum_rgbd/size mismatch": ("tum_rgbd", lambda d: resize_image(sorted((d / "rgb").iterdir())[2]),
                               r"\.png: image is 42x30 but the calibration .* are 40x30", "load2"),
    "tum_rgbd/no calibration": ("tum_rgbd", lambda d: (d / "camera.txt").unlink(),
                                r"no calibration .* freiburg1/2/3 .*calib=PATH", "open"),
    "tum_rgbd/bad camera.txt": ("tum_rgbd", lambda d: (d / "camera.txt").write_text("Pinhole 1 2\n40 30\n"),
                                r"camera\.txt:1: Pinhole takes 5 numbers", "open"),
    "tum_rgbd/bad groundtruth": ("tum_rgbd", lambda d: edit(d / "groundtruth.txt", "\n1305", "\n1305 1"),
                                 r"groundtruth\.txt: 9 columns; expected 8", "open"),
    "tum_rgbd/groundtruth elsewhere in time": (
        "tum_rgbd", lambda d: edit(d / "groundtruth.txt", "\n1305", "\n1405", count=10 ** 6),
        r"groundtruth\.txt: no ground-truth pose within 0\.02 s of any frame", "open"),
    "tum_rgbd/listed depth missing": ("tum_rgbd", lambda d: sorted((d / "depth").iterdir())[1].unlink(),
                                      r"depth\.txt:2: listed depth image .* does not exist", "open"),
    # ---------------------------------------------------------------- TUM monoVO
    "tum_mono/no images": ("tum_mono", lambda d: [p.unlink() for p in (d / "images").iterdir()],
                           r"images: no images", "open"),
    "tum_mono/times count": ("tum_mono", lambda d: drop_lines(d / "times.txt", 1),
                             r"times\.txt: 4 entries for 5 images", "open"),
    "tum_mono/bad exposure": ("tum_mono", lambda d: edit(d / "times.txt", " 12.0000", " -1"),
                              r"times\.txt:3: exposure time must be positive", "open"),
    "tum_mono/no camera.txt": ("tum_mono", lambda d: (d / "camera.txt").unlink(),
                               r"needs camera\.txt .*calib=PATH", "open"),
    "tum_mono/bad pcalib": ("tum_mono", lambda d: (d / "pcalib.txt").write_text("1 2 3"),
                            r"pcalib\.txt: expected at least 256 values", "open"),
    "tum_mono/vignette size": ("tum_mono", lambda d: imwrite(d / "vignette.png", np.ones((5, 5), np.uint8)),
                               r"vignette\.png: vignette is 5x5 but the images are 40x30", "open"),
    "tum_mono/corrupt zip": ("tum_mono_zip", lambda d: (d / "images.zip").write_bytes(b"PK junk"),
                             r"images\.zip: not a readable zip archive", "open"),
    "tum_mono/corrupt zip member": (
        "tum_mono_zip", lambda d: _rewrite_zip_member(d / "images.zip", "00002.jpg", b"garbage"),
        r"images\.zip:00002\.jpg: not a readable image", "load2"),
    # ---------------------------------------------------------------- EuRoC
    "euroc/no data.csv": ("euroc", lambda d: (d / "mav0" / "cam0" / "data.csv").unlink(),
                          r"cam0/data\.csv: not found", "open"),
    "euroc/listed image missing": ("euroc", lambda d: sorted((d / "mav0/cam0/data").iterdir())[3].unlink(),
                                   r"data\.csv:5: listed image .* does not exist", "open"),
    "euroc/timestamp not ns": ("euroc", lambda d: edit(d / "mav0/cam0/data.csv", "\n1403636579763555584,",
                                                       "\n1403636579.763555584,"),
                               r"data\.csv:2: timestamp must be an integer number of nanoseconds", "open"),
    "euroc/out of order": ("euroc", lambda d: swap_lines(d / "mav0/cam0/data.csv", 0, 1),
                           r"data\.csv:3: timestamps out of order", "open"),
    "euroc/no sensor.yaml": ("euroc", lambda d: (d / "mav0/cam0/sensor.yaml").unlink(),
                             r"sensor\.yaml: not found", "open"),
    "euroc/bad sensor.yaml": ("euroc", lambda d: edit(d / "mav0/cam0/sensor.yaml", "resolution: [40, 30]",
                                                      "resolution: [40]"),
                              r"sensor\.yaml: intrinsics needs 4 numbers and resolution 2", "open"),
    "euroc/bad groundtruth csv": (
        "euroc", lambda d: edit(d / "mav0/state_groundtruth_estimate0/data.csv", "\n14036365796", "\n1403x36579"),
        r"state_groundtruth_estimate0/data\.csv:2: timestamp must be an integer", "open"),
    "euroc/wrong camera": ("euroc_cam1", None, r"cam1/data\.csv: not found .*input\.camera", "open"),
    # ---------------------------------------------------------------- KITTI
    "kitti/no images": ("kitti", lambda d: [p.unlink() for p in (d / "image_0").iterdir()],
                        r"image_0: no images", "open"),
    "kitti/short times": ("kitti", lambda d: drop_lines(d / "times.txt", 2),
                          r"times\.txt: 3 timestamps for 5 images", "open"),
    "kitti/no calib": ("kitti", lambda d: (d / "calib.txt").unlink(), r"05: no calib\.txt .*calib=PATH", "open"),
    "kitti/no P0": ("kitti", lambda d: (d / "calib.txt").write_text("P1: 1 0 1 0 0 1 1 0 0 0 1 0\n"),
                    r"calib\.txt: no 'P0:' line", "open"),
    "kitti/bad poses": ("kitti", lambda d: edit(d / "poses_kitti.txt", "e", "x"),
                        r"poses_kitti\.txt:1: not a number", "open"),
    "kitti/too few poses": ("kitti", lambda d: drop_lines(d / "poses_kitti.txt", 2),
                            r"poses_kitti\.txt: 3 KITTI poses, but frame 4", "open"),
    "kitti/size mismatch": ("kitti", lambda d: resize_image(d / "image_0" / "000003.png"),
                            r"000003\.png: image is 42x30", "load3"),
    "kitti/bad camera": ("kitti_cam7", None, r"KITTI camera must be image_0 \.\. image_3", "open"),
    # ---------------------------------------------------------------- Replica
    "replica/no frames": ("replica", lambda d: [p.unlink() for p in (d / "results").glob("frame*")],
                          r"(results: no frame\*\.jpg images|room0: no known dataset layout)", "open"),
    "replica/depth count": ("replica", lambda d: (d / "results" / "depth000003.png").unlink(),
                            r"results: 3 depth images for 4 colour images", "open"),
    "replica/bad traj": ("replica", lambda d: edit(d / "traj.txt", " 1.000000000\n", "\n"),
                         r"traj\.txt:1: expected 16 numbers", "open"),
    "replica/short traj": ("replica", lambda d: drop_lines(d / "traj.txt", 1),
                           r"traj\.txt: 3 poses for 4 frames", "open"),
    "replica/bad cam_params": ("replica", lambda d: (d.parent / "cam_params.json").write_text("{"),
                               r"cam_params\.json: not valid JSON", "open"),
    "replica/no intrinsics": ("replica", lambda d: (d.parent / "cam_params.json").unlink(),
                              r"not NICE-SLAM's 1200x680, and there is no cam_params\.json", "open"),
    # ---------------------------------------------------------------- 7-Scenes
    "7scenes/bad pose": ("7scenes", lambda d: (d / "frame-000002.pose.txt").write_text("1 0 0\n0 1 0\n"),
                         r"frame-000002\.pose\.txt: .* 16 numbers", "open"),
    "7scenes/not a rotation": ("7scenes", lambda d: np.savetxt(d / "frame-000001.pose.txt", np.diag([2, 1, 1, 1])),
                               r"frame-000001\.pose\.txt: the rotation part is not a rotation", "open"),
    "7scenes/odd image size": ("7scenes", lambda d: resize_image(d / "frame-000000.color.png", 320, 240),
                               r"frame-000000\.color\.png: 7-Scenes colour images are 640x480", "open"),
    "7scenes/corrupt image": ("7scenes", lambda d: corrupt(d / "frame-000002.color.png"),
                              r"frame-000002\.color\.png: not a readable image", "load2"),
    "7scenes/bad depth": ("7scenes", lambda d: imwrite(d / "frame-000001.depth.png", np.zeros((480, 640), np.uint8)),
                          r"frame-000001\.depth\.png: 7-Scenes depth must be 16-bit", "depth1"),
    # ---------------------------------------------------------------- image folder
    "images/no calibration": ("images", lambda d: (d / "camera.txt").unlink(),
                              r"my_images: no calibration \(looked for camera\.txt or calib\.txt .*calib=PATH",
                              "open"),
    "images/times count": ("images", lambda d: (d / "times.txt").write_text("1\n2\n"),
                           r"times\.txt: 2 timestamps for 5 images", "open"),
    "images/times order": ("images", lambda d: (d / "times.txt").write_text("1\n2\n3\n3\n4\n"),
                           r"times\.txt:4: timestamps out of order", "open"),
    "images/corrupt": ("images", lambda d: corrupt(d / "img3.png"), r"img3\.png: not a readable image", "load3"),
    "images/size mismatch": ("images", lambda d: resize_image(d / "img4.png"), r"img4\.png: image is 42x30",
                             "load4"),
    "images/bad plain calib": ("images", lambda d: (d / "camera.txt").write_text("30 30 19.5\n"),
                               r"camera\.txt: expected 4 .* got 3", "open"),
    # ---------------------------------------------------------------- video
    "video/corrupt": ("video", lambda p: p.write_bytes(b"RIFF....AVI junk" * 10),
                      r"clip\.avi: (no frames could be read|cannot open)", "open"),
    "video/no calibration": ("video", lambda p: (p.parent / "camera.txt").unlink(),
                             r"clip\.avi: no calibration .*calib=PATH", "open"),
}


def _rewrite_zip_member(path, member, data):
    with zipfile.ZipFile(path) as zf:
        items = {n: zf.read(n) for n in zf.namelist()}
    items[member] = data
    with zipfile.ZipFile(path, "w") as zf:
        for n, b in items.items():
            zf.writestr(n, b)


def build(fakes, kind):
    if kind == "tum_rgbd":
        return fakes.tum_rgbd(name="my_recording", n=5,
                              camera_txt=f"Pinhole 30 30 19.5 14.5 0\n{W} {H}\nnone\n{W} {H}\n"), None
    if kind == "tum_mono":
        return fakes.tum_mono(n=5), None
    if kind == "tum_mono_zip":
        return fakes.tum_mono(n=5, zipped=True, photometric=False, gt_sync=False), None
    if kind == "euroc":
        return fakes.euroc(n=5), None
    if kind == "euroc_cam1":
        return fakes.euroc(n=2), InputConfig(camera="cam1")
    if kind == "kitti":
        return fakes.kitti(n=5), None
    if kind == "kitti_cam7":
        return fakes.kitti(n=2), InputConfig(camera="image_7")
    if kind == "replica":
        return fakes.replica(n=4), None
    if kind == "7scenes":
        return fakes.seven_scenes(n=3), None
    if kind == "images":
        d = fakes.image_folder(n=5)
        (d / "times.txt").write_text("".join(f"{i}\n" for i in range(5)))
        return d, None
    if kind == "video":
        return fakes.video(n=4), None
    raise AssertionError(kind)


@pytest.mark.parametrize("case", list(CASES))
def test_broken_input_is_a_clear_error(fakes, case):
    kind, breaker, message, stage = CASES[case]
    path, config = build(fakes, kind)
    if breaker is not None:
        breaker(path)
    with pytest.raises(DatasetError) as err:
        seq = open_sequence(path, config=config)
        assert stage != "open", f"{case}: opening should have failed"
        if stage.startswith("load"):
            seq.load(int(stage[4:]))
        elif stage.startswith("depth"):
            seq.load_depth(int(stage[5:]))
    assert re.search(message, str(err.value)), f"{case}: {err.value}"


def test_detection_failures_list_what_was_looked_for(tmp_path):
    with pytest.raises(DatasetError, match="no such file or folder"):
        open_sequence(tmp_path / "absent")
    (tmp_path / "notes.md").write_text("hello")
    with pytest.raises(DatasetError, match=r"notes\.md: a file that is not a video"):
        open_sequence(tmp_path / "notes.md")
    with pytest.raises(DatasetError, match=r"no known dataset layout here\. Looked for: EuRoC: mav0/cam0/data\.csv;"
                                           r" TUM RGB-D: rgb\.txt;.*7-Scenes.*video file"):
        open_sequence(tmp_path)
    with pytest.raises(DatasetError, match="no image files"):
        ImageFolderSequence(tmp_path, calib=None)
    with pytest.raises(DatasetError, match="video file not found"):
        VideoSequence(tmp_path / "x.mp4")
    with pytest.raises(DatasetError, match="unknown layout"):
        open_sequence(tmp_path, layout="bogus")


@pytest.mark.parametrize("settings, message", [
    (dict(start=9), r"input\.start=9 selects no frames \(the sequence has 5 frames\)"),
    (dict(stride=0), r"input\.stride (must be )?>= 1"),
    (dict(rectify="cropped"), r"input\.rectify must be one of"),
    (dict(width=-3), r"input\.width (and input\.height )?must be >= 0"),
])
def test_bad_input_config(fakes, settings, message):
    # the configuration may refuse a setting when it is built (ConfigError) or the reader when it opens
    with pytest.raises((DatasetError, ValueError), match=message):
        open_sequence(fakes.kitti(n=5), config=InputConfig(**settings))


def test_prefetch_raises_reader_errors_in_order(fakes):
    d = fakes.kitti(n=5)
    (d / "image_0" / "000003.png").write_bytes(b"junk")
    seq = open_sequence(d)
    got = []
    with pytest.raises(DatasetError, match=r"000003\.png: not a readable image"):
        for f in seq.frames(prefetch=2):
            got.append(f.index)
    assert got == [0, 1, 2]


def test_textured_helper_is_not_constant():
    assert textured(0).std() > 10


def test_calibration_of_another_size_is_refused_when_opening(fakes, tmp_path):
    """``mgso info VIDEO --calib FILE`` printed the calibration's size as the video's: the video (written with
    OpenCV's VideoWriter, 40x30) and a camera.txt for 80x60 now fail at opening, naming both sizes."""
    p = fakes.video(n=3)
    other = tmp_path / "cam80.txt"
    other.write_text("Pinhole 60 60 39.5 29.5 0\n80 60\nnone\n80 60\n")
    with pytest.raises(DatasetError, match=r"cam80\.txt: the calibration is for 80x60 images but the video "
                                           r".*clip\.avi is 40x30"):
        open_sequence(p, calib=other)
    # the same lens at the video's size opens, and describes the video's size (negative control)
    same = tmp_path / "cam40.txt"
    same.write_text(f"Pinhole 30 30 19.5 14.5 0\n{W} {H}\nnone\n{W} {H}\n")
    info = open_sequence(p, calib=same).describe()
    assert info["image_size_in"] == [W, H] and info["image_size_out"] == [W, H]
    # a file without a size takes the video's
    plain = tmp_path / "plain.txt"
    plain.write_text("30 30 19.5 14.5\n")
    assert open_sequence(p, calib=plain).describe()["image_size_in"] == [W, H]
    # an image folder with a calibration of another size: the same one-line error, naming the first image
    d = fakes.image_folder(n=2, calib=None)
    with pytest.raises(DatasetError, match=r"cam80\.txt: the calibration is for 80x60 images but .*\.png is 40x30"):
        open_sequence(d, calib=other)


def test_each_layout_carries_its_detection_and_what_it_looks_for(tmp_path):
    """Issue 44: a layout is one class (``layout``, ``looked_for``, ``recognises``), not three parallel lists; the
    detection's message is made of the classes' texts, and each class recognises only its own folder."""
    from mgso.io import LAYOUTS, detect_layout
    from mgso.io.detect import _DETECTED, _LOOKED_FOR

    assert [c.layout for c in _DETECTED] == [k for k in LAYOUTS if k != "live"]
    assert all(c.looked_for and c.looked_for in _LOOKED_FOR for c in _DETECTED)
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    imwrite(imgs / "0001.png", textured(0))
    (tmp_path / "tum").mkdir()
    (tmp_path / "tum" / "rgb.txt").write_text("# none\n")
    imwrite(tmp_path / "tum" / "0001.png", textured(0))            # a TUM folder holds images too: TUM first
    assert [c.layout for c in _DETECTED if c.recognises(imgs)] == ["images"]
    assert [c.layout for c in _DETECTED if c.recognises(tmp_path / "tum")] == ["tum_rgbd", "images"]
    assert detect_layout(tmp_path / "tum") == "tum_rgbd" and detect_layout(imgs) == "images"


def test_dataset_calibration_formats_are_registered_by_their_readers(tmp_path):
    """read_camera_file imports no dataset reader (the io circle of issue 44): EuRoC, KITTI and Replica register
    their formats; a format registered by a new reader is recognised the same way, and replaced by name."""
    from mgso.camera import CameraSpec, OutputSpec, PinholeCamera
    from mgso.io import calibration as cal

    assert {"EuRoC sensor.yaml", "KITTI calib.txt", "Replica cam_params.json"} <= {f.name for f in cal._FORMATS}
    (tmp_path / "calib.txt").write_text("P0: 500 0 320 0 0 500 240 0 0 0 1 0\n")
    assert cal.read_camera_file(tmp_path / "calib.txt", (640, 480)).model.fx == 500
    (tmp_path / "cam.toy").write_text("TOY 250\n")
    spec = CameraSpec(PinholeCamera(250, 250, 159.5, 119.5, 320, 240), OutputSpec(mode="none"), "toy")
    before = list(cal._FORMATS)
    try:
        cal.register_calibration_format(cal.CalibrationFormat(
            "toy", lambda p, text, lines: bool(lines) and lines[0].startswith("TOY"), lambda p, size: spec))
        assert cal.read_camera_file(tmp_path / "cam.toy") is spec
        n = len(cal._FORMATS)
        cal.register_calibration_format(cal.CalibrationFormat("toy", lambda p, t, ln: False, lambda p, s: spec))
        assert len(cal._FORMATS) == n
        with pytest.raises(Exception, match="cam.toy"):           # no longer recognised: the plain reader's error
            cal.read_camera_file(tmp_path / "cam.toy")
    finally:
        cal._FORMATS[:] = before
