"""Tiny fake datasets of every supported layout, written with cv2 into a temporary folder (used by tests/io)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import cv2
import numpy as np

from mgso.geometry import make_pose, matrix_to_quat_wxyz, matrix_to_quat_xyzw, so3_exp

W, H = 40, 30  # fake image size


def textured(seed: int, w: int = W, h: int = H, color: bool = False) -> np.ndarray:
    """A smooth random uint8 texture (gray [h, w] or BGR [h, w, 3])."""
    rng = np.random.default_rng(seed)
    shape = (h, w, 3) if color else (h, w)
    img = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), 1.5)
    img = (img - img.min()) / max(1e-6, float(img.max() - img.min())) * 235 + 10
    return img.astype(np.uint8)


def poses(n: int, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) camera-to-world poses along a gentle curve."""
    rng = np.random.default_rng(seed)
    w = np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)
    t = np.cumsum(rng.normal(0, 0.1, (n, 3)), axis=0)
    return make_pose(so3_exp(w), t)


def write_tum_traj(path: Path, ts, T) -> None:
    q = matrix_to_quat_xyzw(T[:, :3, :3])
    with open(path, "w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, p, qq in zip(ts, T[:, :3, 3], q):
            fh.write(f"{t:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {qq[0]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f}\n")


def imwrite(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img), path


class Fakes:
    """Builders; each returns the dataset folder (or file) and writes ``n`` frames of size W x H."""

    def __init__(self, root: Path):
        self.root = root

    def tum_rgbd(self, name: str = "rgbd_dataset_freiburg3_fake", n: int = 6, camera_txt: str | None = None,
                 gt: bool = True, depth: bool = True, t0: float = 1305031102.175304,
                 size: tuple[int, int] = (W, H)) -> Path:
        d = self.root / name
        w, h = size
        ts = t0 + np.arange(n) / 30.0
        d.mkdir(parents=True)
        with open(d / "rgb.txt", "w") as fh:
            fh.write("# color images\n# file: 'fake'\n# timestamp filename\n")
            for i, t in enumerate(ts):
                imwrite(d / "rgb" / f"{t:.6f}.png", textured(i, w, h, color=True))
                fh.write(f"{t:.6f} rgb/{t:.6f}.png\n")
        if depth:
            with open(d / "depth.txt", "w") as fh:
                for i, t in enumerate(ts):
                    td = t + 0.004
                    imwrite(d / "depth" / f"{td:.6f}.png", np.full((h, w), 5000 * (1 + i), np.uint16))
                    fh.write(f"{td:.6f} depth/{td:.6f}.png\n")
        if gt:  # 100 Hz poses, offset from the images by a few ms
            tg = t0 - 0.5 + np.arange(int((n / 30.0 + 1.0) * 100)) / 100.0 + 0.003
            write_tum_traj(d / "groundtruth.txt", tg, poses(len(tg)))
        if camera_txt is not None:
            (d / "camera.txt").write_text(camera_txt)
        return d

    def tum_mono(self, n: int = 5, zipped: bool = False, photometric: bool = True, gt_sync: bool = True) -> Path:
        d = self.root / "sequence_01"
        d.mkdir(parents=True)
        imgs = {f"{i:05d}.jpg": textured(i) for i in range(n)}
        if zipped:
            with zipfile.ZipFile(d / "images.zip", "w") as zf:
                for name, img in imgs.items():
                    zf.writestr(name, cv2.imencode(".png", img)[1].tobytes())
        else:
            for name, img in imgs.items():
                imwrite(d / "images" / name.replace(".jpg", ".png"), img)
        with open(d / "times.txt", "w") as fh:
            for i in range(n):
                fh.write(f"{i:05d} {1400000000.0 + i * 0.05:.6f} {10.0 + i:.4f}\n")
        (d / "camera.txt").write_text(f"0.6 0.8 0.5 0.5 0.9\n{W} {H}\ncrop\n{W} {H}\n")
        if photometric:
            (d / "pcalib.txt").write_text(" ".join(f"{(i / 255.0) ** 2 * 255.0:.6f}" for i in range(256)) + "\n")
            vig = np.full((H, W), 60000, np.uint16)
            vig[:, :5] = 30000
            imwrite(d / "vignette.png", vig)
        if gt_sync:
            T = poses(n)
            q = matrix_to_quat_xyzw(T[:, :3, :3])
            with open(d / "groundtruthSync.txt", "w") as fh:
                for i in range(n):
                    if 1 <= i < n - 1:
                        fh.write(f"{1400000000.0 + i * 0.05:.6f} NaN NaN NaN NaN NaN NaN NaN\n")
                    else:
                        p = T[i, :3, 3]
                        fh.write(f"{1400000000.0 + i * 0.05:.6f} {p[0]} {p[1]} {p[2]} {q[i, 0]} {q[i, 1]} "
                                 f"{q[i, 2]} {q[i, 3]}\n")
        return d

    def euroc(self, n: int = 5, gt: str = "csv", T_BS: np.ndarray | None = None) -> Path:
        d = self.root / "MH_fake"
        cam = d / "mav0" / "cam0"
        ns = 1403636579763555584 + np.arange(n, dtype=np.int64) * 50_000_000
        cam.mkdir(parents=True)
        with open(cam / "data.csv", "w") as fh:
            fh.write("#timestamp [ns],filename\n")
            for i, t in enumerate(ns):
                imwrite(cam / "data" / f"{t}.png", textured(i))
                fh.write(f"{t},{t}.png\n")
        T_BS = np.eye(4) if T_BS is None else T_BS
        data = ", ".join(repr(float(v)) for v in T_BS.reshape(-1))
        (cam / "sensor.yaml").write_text(
            "%YAML:1.0\n# General sensor definitions.\nsensor_type: camera\ncomment: fake\n"
            f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\nrate_hz: 20\nresolution: [{W}, {H}]\n"
            "camera_model: pinhole\nintrinsics: [30.0, 31.0, 19.5, 14.5] #fu, fv, cu, cv\n"
            "distortion_model: radial-tangential\ndistortion_coefficients: [-0.1, 0.01, 0.001, -0.0005]\n")
        if gt == "csv":
            tg = ns[0] - 100_000_000 + np.arange(n * 10 + 40, dtype=np.int64) * 5_000_000
            T = poses(len(tg))
            q = matrix_to_quat_wxyz(T[:, :3, :3])
            g = d / "mav0" / "state_groundtruth_estimate0"
            g.mkdir(parents=True)
            with open(g / "data.csv", "w") as fh:
                fh.write("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
                         "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y, v_RS_R_z, b_w_x, b_w_y, b_w_z, b_a_x, b_a_y, "
                         "b_a_z\n")
                for t, p, qq in zip(tg, T[:, :3, 3], q):
                    fh.write(f"{t},{p[0]},{p[1]},{p[2]},{qq[0]},{qq[1]},{qq[2]},{qq[3]}" + ",0" * 9 + "\n")
        elif gt == "tum":
            write_tum_traj(d / "groundtruth_body_tum.txt", ns / 1e9, poses(n))
        return d

    def kitti(self, n: int = 5, color: bool = False, first: int = 0) -> Path:
        d = self.root / "05"
        sub = "image_2" if color else "image_0"
        for i in range(first, first + n):
            imwrite(d / sub / f"{i:06d}.png", textured(i, color=color))
        (d / "times.txt").write_text("".join(f"{i * 0.1036:.6e}\n" for i in range(first + n)))
        P0 = "P0: 35.0 0 19.3 0 0 35.0 14.1 0 0 0 1 0"
        P2 = "P2: 35.0 0 19.3 1.75 0 35.0 14.1 0 0 0 1 0"
        (d / "calib.txt").write_text(f"{P0}\nP1: 35.0 0 19.3 -18.0 0 35.0 14.1 0 0 0 1 0\n{P2}\n")
        T = poses(first + n)
        (d / "poses_kitti.txt").write_text("".join(" ".join(f"{v:.9e}" for v in t[:3].reshape(-1)) + "\n"
                                                    for t in T))
        return d

    def replica(self, n: int = 4, cam_params: bool = True) -> Path:
        d = self.root / "room0"
        for i in range(n):
            imwrite(d / "results" / f"frame{i:06d}.jpg", textured(i, color=True))
            imwrite(d / "results" / f"depth{i:06d}.png", np.full((H, W), 6553 * (i + 1), np.uint16))
        T = poses(n)
        (d / "traj.txt").write_text("".join(" ".join(f"{v:.9f}" for v in t.reshape(-1)) + "\n" for t in T))
        if cam_params:
            (d.parent / "cam_params.json").write_text(
                '{"camera": {"w": %d, "h": %d, "fx": 20.0, "fy": 20.0, "cx": 19.5, "cy": 14.5, "scale": 6553.5}}'
                % (W, H))
        return d

    def seven_scenes(self, n: int = 4, ext: str = "png") -> Path:
        d = self.root / "seq-01"
        T = poses(n)
        for i in range(n):
            imwrite(d / f"frame-{i:06d}.color.{ext}", textured(i, 640, 480, color=True))
            imwrite(d / f"frame-{i:06d}.depth.png", np.full((480, 640), 1000 + i, np.uint16))
            Ti = T[i].copy()
            Ti[:3, :3] *= 1.0002  # the files carry round-off; the reader re-orthonormalises
            np.savetxt(d / f"frame-{i:06d}.pose.txt", Ti)
        np.savetxt(d / "camera-intrinsics.txt", np.array([[585.0, 0, 320], [0, 585.0, 240], [0, 0, 1]]))
        return d

    def image_folder(self, n: int = 5, times: bool = False, calib: str | None = "30 30 19.5 14.5\n") -> Path:
        d = self.root / "my_images"
        for i in range(n):
            imwrite(d / f"img{i}.png", textured(i, color=True))  # natural order: img2 before img10
        if times:
            (d / "times.txt").write_text("".join(f"{100 + 0.04 * i:.6f}\n" for i in range(n)))
        if calib is not None:
            (d / "camera.txt").write_text(calib)
        return d

    def video(self, n: int = 6, fps: float = 10.0) -> Path:
        d = self.root / "clip"
        d.mkdir(parents=True)
        p = d / "clip.avi"
        vw = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
        assert vw.isOpened()
        for i in range(n):
            img = textured(i, color=True)
            img[:, :] = np.clip(img.astype(int) // 4 + 40 * i, 0, 255).astype(np.uint8)  # brightness encodes i
            vw.write(img)
        vw.release()
        (d / "camera.txt").write_text(f"Pinhole 30 30 19.5 14.5 0\n{W} {H}\nnone\n{W} {H}\n")
        return p
