"""``mgso export RUN_DIR --format colmap|nerfstudio`` (issue 15): the exports are read back with parsers written here
from the formats' specifications (COLMAP's text and binary model, nerfstudio's transforms.json), not with mgso's own
writer, and checked against the run's keyframes.txt, the dataset's own images and its ground-truth camera, and by
projecting the points into the exported images (a wrong axis convention fails that check: the negative controls)."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from plyfile import PlyData

from mgso import synthetic
from mgso.app.cli import main
from mgso.io.trajectory import read_tum

W, H = 96, 72


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A synthetic room (24 frames, 96x72, TUM RGB-D layout) and an odometry run on it."""
    base = tmp_path_factory.mktemp("export")
    room = synthetic.write_tum_rgbd(base / "room", seed=0, num_frames=24, width=W, height=H)
    out = base / "run"
    assert main(["run", str(room), "--out", str(out), "--stage", "odometry", "-q", "--set", "output.plot=false"]) == 0
    assert len(read_tum(out / "keyframes.txt")) >= 3
    return room, out


# --------------------------------------------------------------------------------------------- format readers
def _data_lines(path: Path) -> list[str]:
    """Lines of a COLMAP text file without the comments; blank lines kept (images.txt's 2D-points lines)."""
    return [ln.rstrip("\n") for ln in path.read_text().splitlines(keepends=True) if not ln.startswith("#")]


def _quat_wxyz_to_R(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def read_colmap_text(sparse: Path) -> dict:
    cams = [ln.split() for ln in _data_lines(sparse / "cameras.txt") if ln.strip()]
    assert len(cams) == 1 and cams[0][1] == "PINHOLE"
    _, _, w, h, fx, fy, cx, cy = cams[0]
    lines = _data_lines(sparse / "images.txt")
    images = []
    for head, pts2d in zip(lines[0::2], lines[1::2]):    # two lines an image; the second is empty
        e = head.split()
        assert len(e) == 10 and pts2d.strip() == ""
        R = _quat_wxyz_to_R([float(v) for v in e[1:5]])
        images.append({"id": int(e[0]), "R": R, "t": np.array([float(v) for v in e[5:8]]), "camera": int(e[8]),
                       "name": e[9]})
    assert len(lines) == 2 * len(images)
    pts = np.array([[float(v) for v in ln.split()] for ln in _data_lines(sparse / "points3D.txt") if ln.strip()])
    return {"size": (int(w), int(h)), "K": (float(fx), float(fy), float(cx), float(cy)), "images": images,
            "xyz": pts[:, 1:4], "rgb": pts[:, 4:7].astype(np.uint8), "error": pts[:, 7], "track_cols": pts.shape[1]}


def read_colmap_binary(sparse: Path) -> dict:
    b = (sparse / "cameras.bin").read_bytes()
    (n,) = struct.unpack_from("<Q", b, 0)
    cam_id, model, w, h = struct.unpack_from("<iiQQ", b, 8)
    K = struct.unpack_from("<4d", b, 32)
    assert n == 1 and model == 1 and len(b) == 64      # PINHOLE is model 1
    b = (sparse / "images.bin").read_bytes()
    (n,) = struct.unpack_from("<Q", b, 0)
    off, images = 8, []
    for _ in range(n):
        vals = struct.unpack_from("<i7di", b, off)
        off += 64
        end = b.index(b"\0", off)
        name = b[off:end].decode()
        (n2d,) = struct.unpack_from("<Q", b, end + 1)
        off = end + 9 + 24 * n2d
        images.append({"id": vals[0], "q": np.array(vals[1:5]), "t": np.array(vals[5:8]), "name": name})
    assert off == len(b)
    b = (sparse / "points3D.bin").read_bytes()
    (n,) = struct.unpack_from("<Q", b, 0)
    off, xyz, rgb = 8, [], []
    for _ in range(n):
        _pid, x, y, z, r, g, bl, _err, tl = struct.unpack_from("<Q3d3BdQ", b, off)
        off += 8 + 24 + 3 + 8 + 8 + 8 * tl
        xyz.append((x, y, z))
        rgb.append((r, g, bl))
    assert off == len(b)
    return {"size": (w, h), "K": K, "images": images, "xyz": np.array(xyz), "rgb": np.array(rgb, np.uint8)}


def _png(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


# --------------------------------------------------------------------------------------------- the checks
def project_check(K, size, world_to_cam, images, xyz, rgb, *, opengl: bool = False) -> tuple[float, float, float]:
    """Project every point into every image with the format's own camera model and pixel convention (COLMAP: x right,
    y down, z forward, ``u = fx x / z + cx`` with pixel (0, 0) covering [0, 1) x [0, 1); nerfstudio: the same pixels,
    the camera's x right, y up, z back). Returns (fraction of the points in front of a camera that land inside its
    image, median colour difference 0-255 where they land, correlation of the points' brightness with the image's
    there). The correlation tells a right pose from a wrong one most clearly: the scene's colours vary little (an
    image's standard deviation is about 17 of 255), so a wrong pose still finds similar colours."""
    fx, fy, cx, cy = K
    w, h = size
    front = inside = 0
    diffs, seen, own = [], [], []
    for T, img in zip(world_to_cam, images):
        Xc = xyz @ T[:3, :3].T + T[:3, 3]
        if opengl:      # camera looks down -z, y up: pixel rows grow downwards
            z = -Xc[:, 2]
            u, v = fx * Xc[:, 0] / np.where(z > 0, z, 1) + cx, -fy * Xc[:, 1] / np.where(z > 0, z, 1) + cy
        else:
            z = Xc[:, 2]
            u, v = fx * Xc[:, 0] / np.where(z > 0, z, 1) + cx, fy * Xc[:, 1] / np.where(z > 0, z, 1) + cy
        ok = z > 1e-6
        front += int(ok.sum())
        inb = ok & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        inside += int(inb.sum())
        px, py = np.floor(u[inb]).astype(int), np.floor(v[inb]).astype(int)
        seen.append(img[py, px].astype(float))
        own.append(rgb[inb].astype(float))
    if not inside:
        return 0.0, 255.0, 0.0
    seen, own = np.concatenate(seen), np.concatenate(own)
    diff = float(np.median(np.abs(seen - own).mean(axis=1)))
    corr = float(np.corrcoef(seen.mean(axis=1), own.mean(axis=1))[0, 1]) if len(seen) > 2 else 0.0
    return inside / front, diff, corr


def _passes(fraction: float, median_diff: float, corr: float) -> bool:
    """Measured on this scene: the export 0.98 inside, median 7.7, correlation 0.86; a pose inverted 0.86, 18, 0.34;
    the camera's y or x axis flipped 0.98, 18, 0.00 / 0.14; the OpenGL axes taken for OpenCV's: no point in front."""
    return fraction > 0.8 and median_diff < 12.0 and corr > 0.7


def _room_rgb_at(room: Path, t: float) -> np.ndarray:
    for ln in (room / "rgb.txt").read_text().splitlines():
        if ln and not ln.startswith("#") and abs(float(ln.split()[0]) - t) < 1e-6:
            return _png(room / ln.split()[1])
    raise AssertionError(f"no image at {t}")


# --------------------------------------------------------------------------------------------- tests
def test_colmap_export_matches_the_run(run, tmp_path):
    room, out = run
    exp = tmp_path / "colmap"
    assert main(["export", str(out), "--format", "colmap", "--out", str(exp), "-q"]) == 0
    model = read_colmap_text(exp / "sparse" / "0")
    kf = read_tum(out / "keyframes.txt")
    assert len(model["images"]) == len(kf)
    assert model["size"] == (W, H)
    # the ground-truth camera of the scene, in COLMAP's pixel convention (pixel centres at +0.5)
    cam = synthetic.SyntheticCamera.from_fov(W, H)
    assert np.allclose(model["K"], (cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5), atol=1e-6)
    assert np.allclose(model["K"][2:], (W / 2, H / 2), atol=1e-6)
    # camera-to-world rebuilt from COLMAP's world-to-camera = keyframes.txt
    for im, T in zip(model["images"], kf.cam_to_world):
        c2w = np.eye(4)
        c2w[:3, :3] = im["R"].T
        c2w[:3, 3] = -im["R"].T @ im["t"]
        np.testing.assert_allclose(c2w, T, atol=1e-6)
    # the images are the dataset's own (a pinhole camera: undistortion is the identity) at the keyframes' times
    for im, t in zip(model["images"], kf.timestamps):
        np.testing.assert_array_equal(_png(exp / "images" / im["name"]), _room_rgb_at(room, t))
    # the points are points.ply's, error 0 and no tracks
    ply = PlyData.read(str(out / "points.ply"))["vertex"]
    np.testing.assert_allclose(model["xyz"], np.stack([ply["x"], ply["y"], ply["z"]], 1), atol=1e-6)
    np.testing.assert_array_equal(model["rgb"], np.stack([ply["red"], ply["green"], ply["blue"]], 1))
    assert model["track_cols"] == 8 and np.all(model["error"] == 0)
    # the binary model says the same
    binm = read_colmap_binary(exp / "sparse" / "0")
    assert binm["size"] == model["size"] and np.allclose(binm["K"], model["K"])
    assert [i["name"] for i in binm["images"]] == [i["name"] for i in model["images"]]
    for ib, it in zip(binm["images"], model["images"]):
        np.testing.assert_allclose(_quat_wxyz_to_R(ib["q"]), it["R"], atol=1e-9)
        np.testing.assert_allclose(ib["t"], it["t"], atol=1e-9)
    np.testing.assert_allclose(binm["xyz"], model["xyz"], atol=1e-9)
    np.testing.assert_array_equal(binm["rgb"], model["rgb"])


def _colmap_w2c(model) -> list[np.ndarray]:
    out = []
    for im in model["images"]:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = im["R"], im["t"]
        out.append(T)
    return out


def test_colmap_points_project_onto_their_colours(run, tmp_path):
    """DSO's points, projected with cameras.txt and images.txt, land inside the exported images where those have the
    points' colours. Negative controls: the same check with a wrong convention (camera-to-world taken for
    world-to-camera, or the y axis flipped) fails."""
    _, out = run
    exp = tmp_path / "colmap"
    assert main(["export", str(out), "--format", "colmap", "--out", str(exp), "-q"]) == 0
    m = read_colmap_text(exp / "sparse" / "0")
    imgs = [_png(exp / "images" / im["name"]) for im in m["images"]]
    w2c = _colmap_w2c(m)
    figures = project_check(m["K"], m["size"], w2c, imgs, m["xyz"], m["rgb"])
    assert _passes(*figures), figures
    # negative controls: a pose inverted, an axis flipped
    inverted = [np.linalg.inv(T) for T in w2c]
    assert not _passes(*project_check(m["K"], m["size"], inverted, imgs, m["xyz"], m["rgb"]))
    for flip in ([1.0, -1.0, 1.0, 1.0], [-1.0, 1.0, 1.0, 1.0]):
        flipped = [np.diag(flip) @ T for T in w2c]
        assert not _passes(*project_check(m["K"], m["size"], flipped, imgs, m["xyz"], m["rgb"]))


def test_nerfstudio_export_matches_the_run(run, tmp_path):
    _, out = run
    exp = tmp_path / "ns"
    assert main(["export", str(out), "--format", "nerfstudio", "--out", str(exp), "-q"]) == 0
    meta = json.loads((exp / "transforms.json").read_text())
    kf = read_tum(out / "keyframes.txt")
    assert meta["camera_model"] in ("OPENCV", "PINHOLE") and (meta["w"], meta["h"]) == (W, H)
    assert all(meta.get(k, 0.0) == 0.0 for k in ("k1", "k2", "p1", "p2"))
    cam = synthetic.SyntheticCamera.from_fov(W, H)
    K = (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    assert np.allclose(K, (cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5), atol=1e-6)
    assert len(meta["frames"]) == len(kf)
    gl = [np.array(f["transform_matrix"], float) for f in meta["frames"]]
    for T_gl, T in zip(gl, kf.cam_to_world):
        np.testing.assert_allclose(T_gl @ np.diag([1.0, -1.0, -1.0, 1.0]), T, atol=1e-6)
        assert not np.allclose(T_gl, T, atol=1e-3)   # the axes did change: a plain copy of the pose fails here
    ply = PlyData.read(str(exp / meta["ply_file_path"]))["vertex"]
    xyz = np.stack([ply["x"], ply["y"], ply["z"]], 1).astype(float)
    rgb = np.stack([ply["red"], ply["green"], ply["blue"]], 1)
    imgs = [_png(exp / f["file_path"]) for f in meta["frames"]]
    w2c = [np.linalg.inv(T) for T in gl]
    figures = project_check(K, (W, H), w2c, imgs, xyz, rgb, opengl=True)
    assert _passes(*figures), figures
    # negative control: the OpenGL matrices read as OpenCV ones (the convention left out) fail
    assert not _passes(*project_check(K, (W, H), w2c, imgs, xyz, rgb, opengl=False))


def test_all_frames_exports_every_pose(run, tmp_path):
    _, out = run
    exp = tmp_path / "ns_all"
    assert main(["export", str(out), "--format", "nerfstudio", "--out", str(exp), "--all-frames", "-q"]) == 0
    meta = json.loads((exp / "transforms.json").read_text())
    traj = read_tum(out / "trajectory.txt")
    assert len(traj) > len(read_tum(out / "keyframes.txt"))
    assert len(meta["frames"]) == len(traj) == len(list((exp / "images").glob("*.png")))
    for f, T in zip(meta["frames"], traj.cam_to_world):
        np.testing.assert_allclose(np.array(f["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0]), T, atol=1e-6)


def test_moved_input_is_one_line_and_input_fixes_it(tmp_path, capsys):
    room = synthetic.write_tum_rgbd(tmp_path / "room", seed=0, num_frames=12, width=64, height=48)
    out = tmp_path / "run"
    assert main(["run", str(room), "--out", str(out), "--stage", "odometry", "-q", "--set", "output.plot=false"]) == 0
    moved = tmp_path / "moved"
    shutil.move(str(room), str(moved))
    capsys.readouterr()
    exp = tmp_path / "exp"
    assert main(["export", str(out), "--format", "colmap", "--out", str(exp), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(room) in err and "--input" in err and "Traceback" not in err
    assert not exp.exists()
    assert main(["export", str(out), "--format", "colmap", "--out", str(exp), "--input", str(moved), "-q"]) == 0
    m = read_colmap_text(exp / "sparse" / "0")
    assert len(m["images"]) == len(read_tum(out / "keyframes.txt")) and m["size"] == (64, 48)
    # --input naming another sequence (another image size) is refused in one line, naming it
    other = synthetic.write_tum_rgbd(tmp_path / "other", seed=0, num_frames=12, width=80, height=60)
    capsys.readouterr()
    assert main(["export", str(out), "--format", "colmap", "--out", str(tmp_path / "exp2"), "--input", str(other),
                 "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(other) in err and "not the input of this run" in err


def test_bad_run_dir_and_out_are_one_line(run, tmp_path, capsys):
    _, out = run
    capsys.readouterr()
    assert main(["export", str(tmp_path / "nothing"), "--format", "colmap", "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nothing" in err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["export", str(out), "--format", "nerfstudio", "--out", str(blocker), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(blocker) in err and "is a file" in err
    assert main(["export", str(out), "--format", "colmap", "--out", str(out), "-q"]) == 1
    assert "run folder itself" in capsys.readouterr().err


def test_a_pose_left_in_mgso_axes_fails_the_checks(run, tmp_path, monkeypatch):
    """Negative control on the writer: with nerfstudio's axis change switched off (mgso's camera-to-world copied as
    it is), the read-back poses and the projection check fail."""
    from mgso.app import export

    _, out = run
    monkeypatch.setattr(export, "nerfstudio_pose", lambda T: np.asarray(T, float))
    exp = tmp_path / "ns_off"
    assert main(["export", str(out), "--format", "nerfstudio", "--out", str(exp), "-q"]) == 0
    meta = json.loads((exp / "transforms.json").read_text())
    gl = [np.array(f["transform_matrix"], float) for f in meta["frames"]]
    kf = read_tum(out / "keyframes.txt")
    assert not np.allclose(gl[-1] @ np.diag([1.0, -1.0, -1.0, 1.0]), kf.cam_to_world[-1], atol=1e-6)
    ply = PlyData.read(str(exp / meta["ply_file_path"]))["vertex"]
    xyz = np.stack([ply["x"], ply["y"], ply["z"]], 1).astype(float)
    rgb = np.stack([ply["red"], ply["green"], ply["blue"]], 1)
    imgs = [_png(exp / f["file_path"]) for f in meta["frames"]]
    K = (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    assert not _passes(*project_check(K, (W, H), [np.linalg.inv(T) for T in gl], imgs, xyz, rgb, opengl=True))


def test_a_distorted_lens_exports_the_undistorted_camera_and_masks(tmp_path):
    """A RadTan lens undistorted with DSO's ``full`` output: the exports carry the output camera (not the lens'), the
    images are the undistorted ones, and nerfstudio gets masks of the pixels without a source, as many as
    sequence.json's valid_fraction says."""
    room = synthetic.write_tum_rgbd(tmp_path / "room", seed=0, num_frames=24, width=W, height=H)
    (room / "camera.txt").write_text(f"RadTan 68.551104 68.551104 47.5 35.5 -0.2 0.05 0 0\n{W} {H}\nfull\n{W} {H}\n")
    out = tmp_path / "run"
    main(["run", str(room), "--out", str(out), "--stage", "odometry", "-q", "--set", "output.plot=false"])
    assert len(read_tum(out / "keyframes.txt")) >= 2
    info = json.loads((out / "sequence.json").read_text())
    k = info["intrinsics"]
    assert abs(k["fx"] - 68.551104) > 1.0 and 0.5 < info["valid_fraction"] < 0.99   # the lens is really undistorted
    assert main(["export", str(out), "--format", "nerfstudio", "--out", str(tmp_path / "ns"), "-q"]) == 0
    meta = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    assert np.allclose((meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]),
                       (k["fx"], k["fy"], k["cx"] + 0.5, k["cy"] + 0.5), atol=1e-9)
    kf = read_tum(out / "keyframes.txt")
    for f, t in zip(meta["frames"], kf.timestamps):
        mask = cv2.imread(str(tmp_path / "ns" / f["mask_path"]), cv2.IMREAD_GRAYSCALE)
        assert mask.shape == (H, W) and set(np.unique(mask)) == {0, 255}
        assert abs((mask > 0).mean() - info["valid_fraction"]) < 1e-9
        assert np.abs(_png(tmp_path / "ns" / f["file_path"]).astype(int) - _room_rgb_at(room, t)).mean() > 5
    assert main(["export", str(out), "--format", "colmap", "--out", str(tmp_path / "col"), "-q"]) == 0
    m = read_colmap_text(tmp_path / "col" / "sparse" / "0")
    assert np.allclose(m["K"], (k["fx"], k["fy"], k["cx"] + 0.5, k["cy"] + 0.5), atol=1e-9)
    assert not (tmp_path / "col" / "masks").exists()


def test_a_run_started_with_a_relative_path_exports_from_anywhere(run, tmp_path, monkeypatch):
    """sequence.json keeps the input as typed (relative to where the run started) and its absolute path; the export
    finds the input from another folder. Without the absolute path it could not (negative control)."""
    room, out = run
    monkeypatch.chdir(room.parent)
    rel_out = tmp_path / "rel"
    assert main(["run", room.name, "--out", str(rel_out), "--stage", "check", "-q"]) == 0
    info = json.loads((rel_out / "sequence.json").read_text())
    assert info["path"] == room.name and info["path_absolute"] == str(room.resolve())
    for name in ("keyframes.txt", "trajectory.txt", "points.ply"):
        shutil.copy(out / name, rel_out / name)
    monkeypatch.chdir(tmp_path)
    assert main(["export", str(rel_out), "--format", "colmap", "--out", str(tmp_path / "e1"), "-q"]) == 0
    del info["path_absolute"]
    (rel_out / "sequence.json").write_text(json.dumps(info))
    assert main(["export", str(rel_out), "--format", "colmap", "--out", str(tmp_path / "e2"), "-q"]) == 1


def test_a_run_given_the_intrinsics_as_numbers_exports_with_them(run, tmp_path):
    """``mgso run ... --calib "fx fy cx cy"``: sequence.json keeps the numbers as the calibration's source and the
    export opens the input with them again (not with the folder's own camera.txt, whose fx differs)."""
    room, out = run
    num_out = tmp_path / "num"
    assert main(["run", str(room), "--out", str(num_out), "--stage", "check", "-q", "--calib", "70 70 47.5 35.5"]) == 0
    info = json.loads((num_out / "sequence.json").read_text())
    assert info["calibration_source"] == "70 70 47.5 35.5" and info["intrinsics"]["fx"] == 70.0
    for name in ("keyframes.txt", "trajectory.txt", "points.ply"):
        shutil.copy(out / name, num_out / name)
    assert main(["export", str(num_out), "--format", "colmap", "--out", str(tmp_path / "col"), "-q"]) == 0
    m = read_colmap_text(tmp_path / "col" / "sparse" / "0")
    assert np.allclose(m["K"], (70.0, 70.0, 48.0, 36.0), atol=1e-9)
    assert not np.allclose(json.loads((out / "sequence.json").read_text())["intrinsics"]["fx"], 70.0)


def test_a_calibration_file_kept_beside_the_input_under_another_name_is_used_again(run, tmp_path):
    """``--calib`` names a file inside the input folder that its reader does not look for (``cam2.txt`` beside the
    room's own camera.txt, fx 70 against 68.55): the export opens the input with it again, as the run did; the
    room's own camera.txt, found by the reader, is left to the reader (the run without --calib exports too)."""
    room, out = run
    src = tmp_path / "room"
    shutil.copytree(room, src)
    (src / "cam2.txt").write_text(f"Pinhole 70 70 47.5 35.5 0\n{W} {H}\nnone\n{W} {H}\n")
    for name, extra in (("with", ["--calib", str(src / "cam2.txt")]), ("own", [])):
        o = tmp_path / name
        assert main(["run", str(src), "--out", str(o), "--stage", "check", "-q", *extra]) == 0
        for f in ("keyframes.txt", "trajectory.txt", "points.ply"):
            shutil.copy(out / f, o / f)
        assert main(["export", str(o), "--format", "colmap", "--out", str(tmp_path / f"col_{name}"), "-q"]) == 0
        k = read_colmap_text(tmp_path / f"col_{name}" / "sparse" / "0")["K"]
        assert np.allclose(k[0], 70.0 if name == "with" else 68.551104, atol=1e-6), (name, k)
