"""A window filled from a noise-free synthetic sequence: keyframes at true (or perturbed) poses, points with their
true inverse depth (or perturbed), for the back-end tests."""

from __future__ import annotations

import os

import numpy as np

from mgso import synthetic
from mgso.geometry import se3_exp, se3_inverse
from mgso.window.window import Window
from mgso_kernels import runtime
from mgso_kernels.image import ImagePyramid, plan_pyramid
from mgso_kernels.photometric import extract_patterns

GRAY = np.array([0.299, 0.587, 0.114], np.float32)


def make_sequence(num_frames=16):
    return synthetic.make_sequence(seed=0, num_frames=num_frames, width=160, height=120)


def window_from_sequence(seq, frames, points_per_kf=150, *, seed=0, pose_noise=0.0, depth_noise=0.0,
                         max_frames=7, depth_prior_first=True):
    """Keyframes ``frames`` of ``seq`` (world_to_cam = true, the first keyframe's frame as world origin), points on
    high-gradient pixels of each keyframe with their true inverse depth, residuals IN in every other keyframe.
    ``pose_noise`` (se3 sigma) perturbs every keyframe but the first, ``depth_noise`` (relative) the depths; the
    linearisation points are the perturbed states."""
    rng = np.random.default_rng(seed)
    k = seq.intrinsics
    geo = plan_pyramid(k.width, k.height, camera=_pinhole(k))
    device = runtime.init(os.environ.get("MGSO_TEST_DEVICE", "cpu"))   # the wp_device fixture's (no global default)
    w = Window(geo, max_frames=max_frames, point_capacity=4000, immature_capacity=200, device=device)
    c2w0 = seq.trajectory.cam_to_world[frames[0]]
    truth = {}
    for i, f in enumerate(frames):
        pyr = ImagePyramid(geo, device=device).build(seq.images[f] @ GRAY * np.float32(255.0))
        w2c_true = se3_inverse(c2w0) @ seq.trajectory.cam_to_world[f]
        w2c_true = se3_inverse(w2c_true)
        w2c = w2c_true if i == 0 else se3_exp(rng.normal(0, pose_noise, 6)) @ w2c_true
        slot = w.add_keyframe(frame_index=f, timestamp=float(f), world_to_cam=w2c, pyramid=pyr,
                              rgb=seq.images[f])
        truth[slot] = w2c_true
    for i, f in enumerate(frames):
        slot = w.order[i]
        dI = w.pyramids[slot].numpy(0)
        g2 = dI[..., 1] ** 2 + dI[..., 2] ** 2
        g2[:6, :] = g2[-6:, :] = g2[:, :6] = g2[:, -6:] = 0
        cand = np.flatnonzero(g2 > np.quantile(g2, 0.8))
        pick = rng.choice(cand, size=min(points_per_kf, len(cand)), replace=False)
        uv = np.stack([pick % w.width, pick // w.width], axis=1).astype(np.float32)
        depth = seq.depths[f][uv[:, 1].astype(int), uv[:, 0].astype(int)]
        idepth = (1.0 / depth) * (1.0 + rng.normal(0, depth_noise, len(depth)))
        pat = extract_patterns(w.pyramids[slot].dI[0], uv)
        ok = pat.valid & np.isfinite(idepth)
        w.add_active_points(host=np.full(int(ok.sum()), slot), uv=uv[ok], idepth=idepth[ok].astype(np.float32),
                            color=pat.color[ok], weight=pat.weight[ok],
                            has_depth_prior=bool(depth_prior_first and i == 0))
    return w, truth


def _pinhole(k):
    from mgso_kernels.image import Pinhole

    return Pinhole(k.fx, k.fy, k.cx, k.cy)


def true_idepth(seq, window: Window, frames) -> np.ndarray:
    a = window.active
    out = np.zeros(a.n)
    for i, f in enumerate(frames):
        sel = a.host == window.order[i]
        uv = a.uv[sel]
        out[sel] = 1.0 / seq.depths[f][uv[:, 1].astype(int), uv[:, 0].astype(int)]
    return out
