"""Undistortion's output camera and the odometry: ATE with DSO's ``crop`` against ``keep`` (the default), on the
synthetic room seen through the TUM RGB-D freiburg1 lens.

The room (``mgso.synthetic``) is rendered as a pinhole camera wide enough to hold every ray of the distorted camera,
then distorted with the freiburg1 radial-tangential model (``k1 k2 p1 p2 k3`` of the TUM file-formats page, scaled to
``--width x --height``): each pixel of the distorted image samples the pinhole render (bilinear) at its undistorted
ray. The folder is a TUM RGB-D folder (``rgb.txt``, ``rgb/``, ``groundtruth.txt``) with a DSO ``camera.txt``
(``RadTan fx fy cx cy k1 k2 p1 p2 k3``, input size; no output line, the mode comes from ``input.rectify``), as
``mgso.synthetic.cached_sequence_folder`` writes a pinhole one. The odometry (bundle back end, deterministic on the
CPU) then runs once per mode; ATE is Sim(3)-aligned over all frames with a pose.

    python profiles/undistortion.py [--width 640 --height 480] [--frames 300] [--modes crop,keep,full]
                                    [--motion-scale 1.0] [--seed 0] [--out DIR] [--device cpu] [--set S.K=V ...]

Prints one JSON line: per mode the output intrinsics, the share of the recorded image kept (input pixels whose ray
lands inside the output image), the share of output pixels with a source, and the odometry's figures. PSNR of the
map is not measured here (``mgso run`` on the folder with ``--set input.rectify=MODE`` gives it).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mgso import synthetic  # noqa: E402
from mgso.camera import RadTanCamera  # noqa: E402
from mgso.config import Config, apply_overrides  # noqa: E402
from mgso.eval import compute_ate  # noqa: E402
from mgso.io import TUM_RGBD_FREIBURG, open_sequence, write_tum  # noqa: E402
from mgso.odometry import FrameStatus, Odometry, geometry_for  # noqa: E402
from mgso_kernels import runtime  # noqa: E402


def fr1_lens(width: int, height: int) -> RadTanCamera:
    fx, fy, cx, cy, d = TUM_RGBD_FREIBURG[1]
    return RadTanCamera(fx, fy, cx, cy, 640, 480, *d).resized(width, height)


def write_distorted(folder: Path, lens: RadTanCamera, spec: synthetic.SequenceSpec) -> Path:
    """Render ``spec``'s path through ``lens`` into a TUM RGB-D folder (skipped when it is already complete)."""
    if (folder / "done").is_file():
        return folder
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    W, H = lens.size
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    xn, ok = lens.normalized_from_pixel(np.stack([uu.ravel(), vv.ravel()], 1))
    if not ok.all():
        raise SystemExit(f"the lens cannot undistort {int((~ok).sum())} of its pixels")
    pad = 3.0
    lo, hi = xn.min(axis=0), xn.max(axis=0)
    # a pinhole with the lens's focal lengths whose image holds every ray of the distorted camera
    cx, cy = -lo[0] * lens.fx + pad, -lo[1] * lens.fy + pad
    rw, rh = int(np.ceil(hi[0] * lens.fx + cx + pad)) + 1, int(np.ceil(hi[1] * lens.fy + cy + pad)) + 1
    render_cam = synthetic.SyntheticCamera(lens.fx, lens.fy, cx, cy, rw, rh)
    map_x = (xn[:, 0] * lens.fx + cx).reshape(H, W).astype(np.float32)
    map_y = (xn[:, 1] * lens.fy + cy).reshape(H, W).astype(np.float32)
    scene, traj = spec.scene(), spec.trajectory()
    names = [f"{t:.6f}" for t in traj.timestamps]
    with open(folder / "rgb.txt", "w", encoding="utf-8") as fh:
        fh.write("# color images\n# mgso profiles/undistortion.py: synthetic room through the freiburg1 lens\n")
        for i, name in enumerate(names):
            rgb, _ = synthetic.render(scene, render_cam, traj.cam_to_world[i], supersample=spec.supersample)
            img = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            u8 = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
            cv2.imwrite(str(folder / "rgb" / f"{name}.png"), cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))
            fh.write(f"{name} rgb/{name}.png\n")
    write_tum(folder / "groundtruth.txt", traj)
    d = lens.distortion
    (folder / "camera.txt").write_text(
        f"RadTan {lens.fx:.6f} {lens.fy:.6f} {lens.cx:.6f} {lens.cy:.6f} {d['k1']} {d['k2']} {d['p1']} {d['p2']} "
        f"{d['k3']}\n{W} {H}\n")
    (folder / "done").write_text(json.dumps({"render": dataclasses.asdict(render_cam), **spec.to_dict()}) + "\n")
    return folder


def kept_fraction(lens, out) -> float:
    """Share of the recorded image's pixels whose ray lands inside the output image."""
    vv, uu = np.mgrid[0:lens.height, 0:lens.width].astype(np.float64)
    rays, ok = lens.unproject(np.stack([uu.ravel(), vv.ravel()], 1))
    uv, ok2 = out.project(rays)
    inside = ok & ok2 & (uv[:, 0] >= -0.5) & (uv[:, 0] <= out.width - 0.5) & (uv[:, 1] >= -0.5) & (
        uv[:, 1] <= out.height - 0.5)
    return float(inside.mean())


def run_mode(folder: Path, mode: str, base: Config, device: str) -> dict:
    cfg = dataclasses.replace(base, input=dataclasses.replace(base.input, rectify=mode))
    seq = open_sequence(folder, config=cfg.input)
    cam = seq.calibration.output
    odo = Odometry(geometry_for(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cfg), cfg, device=device)
    n = lost = 0
    t0 = time.perf_counter()
    for f in seq.frames():
        r = odo.process(f)
        lost += int(r.status != FrameStatus.TRACKED)
        n += 1
    wall = time.perf_counter() - t0
    odo.finish()
    traj = odo.trajectory()
    out = {"fx": round(cam.fx, 2), "fy": round(cam.fy, 2), "cx": round(cam.cx, 2), "cy": round(cam.cy, 2),
           "image_kept": round(kept_fraction(seq.calibration.input, cam), 4),
           "pixels_with_source": round(seq.calibration.undistorter.valid_fraction, 4),
           "frames": n, "frames_with_pose": len(traj), "not_tracked": lost, "segments": odo.segment + 1,
           "keyframes": len(odo.keyframes), "wall_s": round(wall, 1)}
    gt = seq.groundtruth
    if gt is not None and len(traj) >= 3:
        out["ate_all_frames_m"] = round(compute_ate(traj, gt, align="sim3").rmse, 4)
        kfs = odo.keyframe_trajectory()
        if len(kfs) >= 3:
            out["ate_keyframes_m"] = round(compute_ate(kfs, gt, align="sim3").rmse, 4)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--motion-scale", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modes", default="crop,keep")
    ap.add_argument("--out", default=None, help="folder for the distorted sequence (default: the synthetic cache)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    device = runtime.init(args.device)
    base = apply_overrides(Config(), args.set)
    spec = synthetic.SequenceSpec(seed=args.seed, num_frames=args.frames, width=args.width, height=args.height,
                                  motion_scale=args.motion_scale)
    lens = fr1_lens(args.width, args.height)
    folder = Path(args.out) if args.out else synthetic.default_cache_dir() / f"fr1lens-{spec.key()}"
    t0 = time.perf_counter()
    write_distorted(folder, lens, spec)
    out = {"profile": "undistortion", "device": device, "load_avg_1min": round(os.getloadavg()[0], 2),
           "lens": "TUM RGB-D freiburg1 radtan (k3 included)", "size": [args.width, args.height],
           "frames": args.frames, "motion_scale": args.motion_scale, "seed": args.seed, "folder": str(folder),
           "render_s": round(time.perf_counter() - t0, 1), "settings": args.set, "psnr": "not measured"}
    for mode in args.modes.split(","):
        out[mode] = run_mode(folder, mode, base, device)
    modes = args.modes.split(",")
    if "crop" in modes and "keep" in modes and "ate_all_frames_m" in out["crop"] and "ate_all_frames_m" in out["keep"]:
        out["ate_crop_vs_keep_m"] = [out["crop"]["ate_all_frames_m"], out["keep"]["ate_all_frames_m"]]
        out["image_kept_crop_vs_keep"] = [out["crop"]["image_kept"], out["keep"]["image_kept"]]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
