"""Synthetic textured scenes rendered with exact poses and depth: the ground truth for tests and the demo.

A closed room (floor, ceiling, four walls) with a few boxes standing on the floor, every surface a procedural colour
texture (multi-octave value noise, stripes, blobs, text-like marks, and smooth low-gradient areas), rendered
analytically by ray casting in NumPy: per pixel an exact ray-plane / ray-box intersection (so depth is exact), the
texture sampled trilinearly from a mip pyramid with the level set by the pixel's footprint (so far and grazing
surfaces do not alias), and every pixel on a geometric edge (its 3x3 neighbourhood sees more than one face)
supersampled with ``supersample x supersample`` rays (anti-aliased silhouettes and creases). Shading is a constant
factor per face, so the scene obeys brightness constancy: a surface point has the same radiance in every view (up
to the exposure, vignetting and noise applied on top, all known and recorded, and to the view-dependent texture
filtering every anti-aliased renderer has).

Conventions (the project's):

- Camera frame x right, y down, z forward. Poses are ``cam_to_world`` 4x4 (``X_w = R X_c + t``).
- Pixel centres at integer coordinates: pixel (0, 0) is centred at (0, 0) and covers [-0.5, 0.5]^2; ``K`` uses that
  convention, so a centred principal point is ``((W - 1) / 2, (H - 1) / 2)``.
- ``depth`` is **z-depth** (the camera-frame z of the surface point seen at the pixel centre), not ray length:
  ``X_c = depth * K^-1 [u, v, 1]``.
- World frame: y points down too (a level camera has the identity rotation); the floor is the plane
  ``y = room_max[1]`` = +1.2 m, the camera path stays around y = 0, looking towards +z.
- Images are float32 RGB in [0, 1]. Photometric model of a recorded frame i (TUM monoVO's, with a linear response):
  ``I_i(x) = clip(g_i V(x) L(x) + n, 0, 1)`` with L the scene radiance (what :func:`render` returns), the gain
  ``g_i = exposure_ms[i] / base_exposure_ms``, the vignette ``V(x) = 1 - strength * (r(x) / r_corner)^2`` (r: the
  distance from the principal point, r_corner: that of the farthest image corner) and ``n`` Gaussian noise of std
  ``noise_sigma`` (seeded per frame).

Main entry points: :func:`make_scene`, :func:`render`, :func:`camera_path`, :func:`make_sequence` (in memory),
:func:`write_tum_rgbd` (a TUM RGB-D style folder, streamed frame by frame), :func:`cached_sequence_folder`.
Everything is deterministic for a seed: the same parameters give byte-identical files.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import shutil
import string
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from .geometry import make_pose, so3_exp
from .io.trajectory import Trajectory, write_tum

__all__ = [
    "SYNTHETIC_VERSION", "SyntheticCamera", "Surface", "Box", "Scene", "SequenceSpec", "SyntheticFrame",
    "SyntheticSequence", "make_scene", "render", "camera_path", "rotation_path", "CAMERA_PATHS", "vignette_factor",
    "exposure_schedule",
    "apply_photometric", "iter_frames", "make_sequence", "write_tum_rgbd", "cached_sequence_folder",
    "default_cache_dir", "TUM_DEPTH_FACTOR", "depth_to_points",
]

#: Bumped whenever the rendered output of the same parameters changes (part of the cache key).
SYNTHETIC_VERSION = 1
#: TUM RGB-D depth PNGs store metres * 5000 as uint16 (0 = no depth).
TUM_DEPTH_FACTOR = 5000.0


# ---------------------------------------------------------------------------------------------- camera model
@dataclass(frozen=True)
class SyntheticCamera:
    """Pinhole intrinsics in pixels, pixel centres at integer coordinates (see the module text)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x_deg: float = 70.0) -> "SyntheticCamera":
        """Square pixels, principal point at the image centre ``((W-1)/2, (H-1)/2)``, horizontal field of view."""
        if width < 2 or height < 2:
            raise ValueError(f"image size must be at least 2x2, got {width}x{height}")
        if not 1.0 < fov_x_deg < 170.0:
            raise ValueError(f"fov_x_deg must be in (1, 170) degrees, got {fov_x_deg}")
        f = 0.5 * width / np.tan(np.radians(fov_x_deg) * 0.5)
        return cls(float(f), float(f), (width - 1) * 0.5, (height - 1) * 0.5, int(width), int(height))

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------------------ the scene
@dataclass(frozen=True, eq=False)
class Surface:
    """A textured rectangle: points ``origin + u * u_axis + v * v_axis`` for ``u in [0, size[0]]``,
    ``v in [0, size[1]]`` (metres). ``mips[0]`` is the texture ``[rows ~ v, cols ~ u, 3]`` covering the rectangle;
    ``mips[k]`` halves it k times."""

    name: str
    origin: np.ndarray  # [3] world, metres
    u_axis: np.ndarray  # [3] unit
    v_axis: np.ndarray  # [3] unit
    normal: np.ndarray  # [3] unit, towards the side it is seen from
    size: tuple[float, float]  # metres along u and v
    mips: tuple[np.ndarray, ...]  # float32 [h_k, w_k, 3] in [0, 1]
    shade: float  # constant shading factor of the face

    @property
    def texture(self) -> np.ndarray:
        return self.mips[0]


@dataclass(frozen=True, eq=False)
class Box:
    """An oriented box: ``centre`` [3], ``half_size`` [3] (metres, local axes), ``yaw`` (rad, about world y)."""

    centre: np.ndarray
    half_size: np.ndarray
    yaw: float

    @functools.cached_property
    def rotation(self) -> np.ndarray:
        """Local-to-world rotation (columns are the box's axes in the world)."""
        return so3_exp(np.array([0.0, self.yaw, 0.0]))

    def contains(self, point, margin: float = 0.0) -> bool:
        q = self.rotation.T @ (np.asarray(point, dtype=np.float64) - self.centre)
        return bool(np.all(np.abs(q) <= self.half_size + margin))


@dataclass(frozen=True, eq=False)
class Scene:
    """A room ``[room_min, room_max]`` (world, metres; y down, floor at ``room_max[1]``) with boxes.

    ``surfaces[0:6]`` are the room's faces (x-min wall, x-max wall, ceiling, floor, z-min wall, z-max wall); then 6
    faces per box (local -x, +x, -y (top), +y (bottom), -z, +z).
    """

    seed: int
    room_min: np.ndarray
    room_max: np.ndarray
    boxes: tuple[Box, ...]
    surfaces: tuple[Surface, ...]
    texels_per_metre: float
    photo: bool = False  # whether a photograph (matplotlib's sample image) hangs on the far wall
    atlas: _Atlas | None = field(default=None, repr=False)  # packed textures for the renderer (built on creation)

    def __post_init__(self):
        if self.atlas is None:
            object.__setattr__(self, "atlas", _Atlas.build(self.surfaces))

    def describe(self) -> str:
        lo, hi = self.room_min, self.room_max
        return (f"synthetic room {hi[0] - lo[0]:.1f} x {hi[1] - lo[1]:.1f} x {hi[2] - lo[2]:.1f} m, "
                f"{len(self.boxes)} boxes, {len(self.surfaces)} textured faces, seed {self.seed}")


@dataclass(frozen=True, eq=False)
class _Atlas:
    """All mip levels of all surfaces in one texel array, with per-level and per-surface tables, so that shading
    is a handful of vectorised operations over all rays (no loop over surfaces or levels)."""

    texels: np.ndarray  # [T, 3] float32: every level of every surface, each row-major, concatenated
    level_base: np.ndarray  # [L] int32: first texel of each (surface, level)
    level_w: np.ndarray  # [L] int32 texels
    level_sx: np.ndarray  # [L] float32 texels per metre along u
    level_sy: np.ndarray  # [L] float32 texels per metre along v
    level_xmax: np.ndarray  # [L] float32 w - 1
    level_ymax: np.ndarray  # [L] float32 h - 1
    level_x0max: np.ndarray  # [L] int32 max(w - 2, 0): the last left corner of a bilinear cell
    level_y0max: np.ndarray  # [L] int32 max(h - 2, 0)
    level_step: np.ndarray  # [L] int32 texels to the next row (0 for a one-row level)
    first_level: np.ndarray  # [S] int32: index of the surface's level 0 in the level tables
    num_levels: np.ndarray  # [S] int32
    origin: np.ndarray  # [S, 3]
    u_axis: np.ndarray  # [S, 3]
    v_axis: np.ndarray  # [S, 3]
    normal: np.ndarray  # [S, 3]
    shade: np.ndarray  # [S] float32

    @classmethod
    def build(cls, surfaces) -> "_Atlas":
        chunks, base, ws, hs, sx, sy, first, counts = [], [], [], [], [], [], [], []
        n = 0
        for s in surfaces:
            first.append(len(base))
            counts.append(len(s.mips))
            for lv in s.mips:
                h, w = lv.shape[:2]
                base.append(n)
                ws.append(w)
                hs.append(h)
                sx.append(w / s.size[0])
                sy.append(h / s.size[1])
                chunks.append(lv.reshape(-1, 3))
                n += h * w
        if n >= 2 ** 31:
            raise ValueError("textures too large for the renderer (2^31 texels); lower texels_per_metre")
        i32 = lambda x: np.asarray(x, dtype=np.int32)  # noqa: E731
        f32 = lambda x: np.asarray(x, dtype=np.float32)  # noqa: E731
        ws, hs = np.array(ws), np.array(hs)
        arrs = dict(texels=np.ascontiguousarray(np.concatenate(chunks), dtype=np.float32), level_base=i32(base),
                    level_w=i32(ws), level_sx=f32(sx), level_sy=f32(sy), level_xmax=f32(ws - 1),
                    level_ymax=f32(hs - 1), level_x0max=i32(np.maximum(ws - 2, 0)),
                    level_y0max=i32(np.maximum(hs - 2, 0)), level_step=i32(np.where(hs > 1, ws, 0)),
                    first_level=i32(first), num_levels=i32(counts),
                    origin=np.stack([s.origin for s in surfaces]), u_axis=np.stack([s.u_axis for s in surfaces]),
                    v_axis=np.stack([s.v_axis for s in surfaces]), normal=np.stack([s.normal for s in surfaces]),
                    shade=np.array([s.shade for s in surfaces], dtype=np.float32))
        for a in arrs.values():
            a.setflags(write=False)
        return cls(**arrs)


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _value_noise(rng: np.random.Generator, h: int, w: int, cell: float) -> np.ndarray:
    """Smooth noise in about [-1, 1] with features of about ``cell`` texels: a random lattice of about
    ``(h / cell + 1) x (w / cell + 1)`` values resized bicubically to ``h x w``."""
    cell = max(float(cell), 1.0)
    gh, gw = max(2, int(round(h / cell)) + 1), max(2, int(round(w / cell)) + 1)
    lattice = rng.uniform(-1.0, 1.0, size=(gh, gw)).astype(np.float32)
    return cv2.resize(lattice, (w, h), interpolation=cv2.INTER_CUBIC)


def _fractal(rng: np.random.Generator, h: int, w: int, cell: float, octaves: int, gain: float = 0.55) -> np.ndarray:
    out = np.zeros((h, w), np.float32)
    amp, norm = 1.0, 0.0
    for _ in range(octaves):
        out += amp * _value_noise(rng, h, w, cell)
        norm += amp
        amp *= gain
        cell *= 0.5
    return out / norm


def _random_colour(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.75) -> np.ndarray:
    hue = rng.uniform(0, 1)
    sat = rng.uniform(0.15, 0.65)
    val = rng.uniform(lo, hi)
    k = (np.array([5.0, 3.0, 1.0]) + hue * 6.0) % 6.0
    rgb = val - val * sat * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return rgb.astype(np.float32)


def _blend_roi(tex: np.ndarray, x0: int, y0: int, mask_u8: np.ndarray, colour: np.ndarray, opacity: float) -> None:
    """``tex <- tex + a (colour - tex)`` with ``a = opacity * mask / 255`` for the mask placed at (x0, y0) (clipped to
    the texture), in place."""
    h, w = tex.shape[:2]
    mh, mw = mask_u8.shape
    xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + mw, w), min(y0 + mh, h)
    if xb <= xa or yb <= ya:
        return
    m = mask_u8[ya - y0:yb - y0, xa - x0:xb - x0]
    roi = tex[ya:yb, xa:xb]
    a = m.astype(np.float32) * np.float32(opacity / 255.0)
    diff = colour.astype(np.float32) - roi
    diff *= a[..., None]
    roi += diff


def _make_texture(rng: np.random.Generator, h: int, w: int, rho: float, smooth_bias: float = 0.0) -> np.ndarray:
    """A procedural colour texture of ``h x w`` texels at ``rho`` texels per metre, values in [0.04, 0.86]:
    two colours mixed by 1.3 m noise; where a 1 m noise mask is on, five octaves of coloured noise (35 cm down to
    ~2 cm) and a fine grain; a patch of stripes; ellipse blobs (some blurred); text-like marks. Elsewhere the
    texture is smooth (low gradient)."""
    h, w = max(int(h), 2), max(int(w), 2)
    a, b = _random_colour(rng), _random_colour(rng)
    low = _fractal(rng, h, w, 1.3 * rho, 2)
    mix = 0.5 + 0.5 * low
    detail_mask = _smoothstep(-0.15 + smooth_bias, 0.2 + smooth_bias, _fractal(rng, h, w, 1.0 * rho, 2))
    detail = _fractal(rng, h, w, 0.35 * rho, 5)
    detail *= detail_mask
    direction = (0.6 + 0.4 * rng.uniform(-1, 1, 3)).astype(np.float32)
    grain = _value_noise(rng, h, w, max(2.0, 0.012 * rho))
    grain *= detail_mask
    stripe_mask = _smoothstep(0.3, 0.45, _fractal(rng, h, w, 0.9 * rho, 2))
    period = rng.uniform(0.05, 0.14) * rho
    ang = rng.uniform(0, np.pi)
    yy, xx = np.ogrid[0:h, 0:w]
    phase = (xx.astype(np.float32) * np.float32(np.cos(ang) * 2 * np.pi / period)
             + yy.astype(np.float32) * np.float32(np.sin(ang) * 2 * np.pi / period))
    stripes = np.sin(phase, dtype=np.float32)
    stripes *= stripe_mask
    stripe_colour = _random_colour(rng, 0.5, 1.0)
    channels = []
    for c in range(3):
        ch = mix * np.float32(b[c] - a[c])
        ch += np.float32(a[c])
        ch += detail * np.float32(0.4 * direction[c])
        ch += grain * np.float32(0.05)
        ch += stripes * np.float32(0.14 * stripe_colour[c])
        channels.append(ch)
    tex = np.ascontiguousarray(np.stack(channels, axis=-1), dtype=np.float32)
    area = (h / rho) * (w / rho)
    # Blobs: ellipses, some blurred, each drawn and blended in its own small window.
    for _ in range(int(rng.integers(3, 6 + int(5.0 * area)))):
        axes = (int(max(1, rng.uniform(0.03, 0.22) * rho)), int(max(1, rng.uniform(0.03, 0.22) * rho)))
        angle = float(rng.uniform(0, 180))
        blur = int(max(1, 0.015 * rho)) * 2 + 1 if rng.uniform() < 0.5 else 0
        r = max(axes) + 2 + blur
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        mask = np.zeros((2 * r + 1, 2 * r + 1), np.uint8)
        cv2.ellipse(mask, (r, r), axes, angle, 0, 360, 255, -1, cv2.LINE_AA)
        if blur:
            mask = cv2.GaussianBlur(mask, (blur, blur), 0)
        _blend_roi(tex, cx - r, cy - r, mask, _random_colour(rng, 0.1, 0.85), float(rng.uniform(0.6, 0.95)))
    # Text-like marks: random capitals and digits, dark or light.
    for _ in range(int(rng.integers(2, 4 + int(2.4 * area)))):
        n = int(rng.integers(3, 9))
        text = "".join(rng.choice(list(string.ascii_uppercase + string.digits), n))
        height_px = rng.uniform(0.025, 0.09) * rho
        scale = max(height_px / 22.0, 0.1)
        thick = int(max(1, round(scale * rng.uniform(1.2, 2.6))))
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
        pad = thick + 2
        mask = np.zeros((th + base + 2 * pad, tw + 2 * pad), np.uint8)
        cv2.putText(mask, text, (pad, pad + th), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, thick, cv2.LINE_AA)
        x0, y0 = int(rng.integers(-pad, max(1, w - tw))), int(rng.integers(-pad, max(1, h - th)))
        colour = np.full(3, 0.08 if rng.uniform() < 0.5 else 0.8, np.float32)
        _blend_roi(tex, x0, y0, mask, colour, 0.85)
    np.clip(tex, 0.04, 0.86, out=tex)
    return tex


def _mip_pyramid(tex: np.ndarray) -> tuple[np.ndarray, ...]:
    levels = [np.ascontiguousarray(tex, dtype=np.float32)]
    while min(levels[-1].shape[:2]) >= 4:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA))
    for lv in levels:
        lv.setflags(write=False)
    return tuple(levels)


def _photo() -> np.ndarray | None:
    """matplotlib's bundled sample photograph (Grace Hopper), float32 RGB, or None without matplotlib."""
    try:
        import matplotlib
    except ImportError:
        return None
    p = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None:
        return None
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def _surface(name, origin, u_axis, v_axis, normal, size, tex, shade) -> Surface:
    f64 = lambda x: np.asarray(x, dtype=np.float64)  # noqa: E731
    arrs = [f64(origin), f64(u_axis), f64(v_axis), f64(normal)]
    for a in arrs:
        a.setflags(write=False)
    return Surface(name, *arrs, size=(float(size[0]), float(size[1])), mips=_mip_pyramid(tex), shade=float(shade))


@functools.lru_cache(maxsize=4)
def make_scene(seed: int = 0, *, room_size: tuple[float, float, float] = (5.0, 2.6, 6.0), num_boxes: int = 3,
               texels_per_metre: float = 128.0, photo: bool = False) -> Scene:
    """Build the textured room for ``seed`` (cached: the same arguments return the same, read-only object).

    ``room_size``: (width x, height y, length z) in metres; the room spans x in [-w/2, w/2], y in [1.2 - h, 1.2]
    (floor 1.2 m below the camera path), z in [-2.5, l - 2.5]. ``num_boxes`` boxes (0.35-0.95 m) stand on the floor
    at z in [1.2, 2.9]. ``texels_per_metre``: texture resolution (128: 7.8 mm texels, detail down to ~2 cm).
    ``photo``: hang matplotlib's sample photograph on the far wall (only when matplotlib is importable; off by
    default so that output does not depend on what is installed).
    """
    W, H, L = (float(v) for v in room_size)
    if min(W, H, L) <= 0 or W < 3.0 or L < 5.0 or H < 2.0:
        raise ValueError(f"room_size must be at least (3, 2, 5) m, got {room_size}")
    if not 8.0 <= texels_per_metre <= 1024.0:
        raise ValueError(f"texels_per_metre must be in [8, 1024], got {texels_per_metre}")
    if not 0 <= num_boxes <= 8:
        raise ValueError(f"num_boxes must be in [0, 8], got {num_boxes}")
    rho = float(texels_per_metre)
    lo = np.array([-W / 2, 1.2 - H, -2.5])
    hi = np.array([W / 2, 1.2, L - 2.5])
    rng = np.random.default_rng([int(seed), 0x5CE7E])
    ex, ey, ez = np.eye(3)

    def tex_for(size_u, size_v, smooth_bias=0.0):
        return _make_texture(rng, int(round(size_v * rho)), int(round(size_u * rho)), rho, smooth_bias)

    ext = hi - lo
    mid = 0.5 * (lo + hi)
    surfaces = []

    def face(name, centre, u_axis, v_axis, normal, size, tex, shade):
        # u runs to the right and v downwards as the face is seen from the side its normal points to, so text
        # drawn into the texture reads the right way round
        origin = np.asarray(centre) - 0.5 * size[0] * u_axis - 0.5 * size[1] * v_axis
        surfaces.append(_surface(name, origin, u_axis, v_axis, normal, size, tex, shade))

    # room faces (normals point into the room), in the order _intersect_room numbers them
    face("wall x-", [lo[0], mid[1], mid[2]], ez, ey, ex, (ext[2], ext[1]), tex_for(ext[2], ext[1]), 0.85)
    face("wall x+", [hi[0], mid[1], mid[2]], -ez, ey, -ex, (ext[2], ext[1]), tex_for(ext[2], ext[1]), 0.9)
    face("ceiling", [mid[0], lo[1], mid[2]], -ex, -ez, ey, (ext[0], ext[2]), tex_for(ext[0], ext[2], 0.25), 0.8)
    face("floor", [mid[0], hi[1], mid[2]], ex, -ez, -ey, (ext[0], ext[2]), tex_for(ext[0], ext[2]), 1.0)
    face("wall z-", [mid[0], mid[1], lo[2]], -ex, ey, ez, (ext[0], ext[1]), tex_for(ext[0], ext[1]), 0.95)
    far = tex_for(ext[0], ext[1])
    use_photo = False
    if photo:
        img = _photo()
        if img is not None:
            ph, pw = int(round(1.0 * rho)), int(round(0.8 * rho))
            r0, c0 = int(round(0.5 * rho)), int(round((ext[0] * 0.5 + 0.6) * rho))
            if r0 + ph <= far.shape[0] and c0 + pw <= far.shape[1]:
                far[r0:r0 + ph, c0:c0 + pw] = 0.04 + 0.82 * cv2.resize(img, (pw, ph), interpolation=cv2.INTER_AREA)
                use_photo = True
    face("wall z+", [mid[0], mid[1], hi[2]], ex, ey, -ez, (ext[0], ext[1]), far, 1.0)

    boxes: list[Box] = []
    tries = 0
    while len(boxes) < num_boxes:
        tries += 1
        if tries > 1000:
            raise RuntimeError("make_scene: could not place the boxes without overlap")
        half = np.array([rng.uniform(0.18, 0.47), rng.uniform(0.15, 0.5), rng.uniform(0.18, 0.47)])
        centre = np.array([rng.uniform(lo[0] + 0.9, hi[0] - 0.9), hi[1] - half[1], rng.uniform(1.2, 2.9)])
        yaw = float(rng.uniform(-0.7, 0.7))
        radius = float(np.linalg.norm(half[[0, 2]]))
        if any(np.linalg.norm((centre - b.centre)[[0, 2]]) < radius + np.linalg.norm(b.half_size[[0, 2]]) + 0.1
               for b in boxes):
            continue
        box = Box(centre=centre, half_size=half, yaw=yaw)
        centre.setflags(write=False)
        half.setflags(write=False)
        boxes.append(box)
        R = box.rotation
        shades = {(0, 0): 0.75, (0, 1): 0.85, (1, 0): 1.0, (1, 1): 0.6, (2, 0): 0.9, (2, 1): 0.7}
        for axis in range(3):  # faces in the order _intersect_box numbers them: -x, +x, -y (top), +y, -z, +z
            for side in (0, 1):
                normal = (-1.0 if side == 0 else 1.0) * R[:, axis]
                if axis == 1:
                    u_axis, v_axis, size = R[:, 0], R[:, 2], (2 * half[0], 2 * half[2])
                else:
                    v_axis = R[:, 1]
                    u_axis = np.cross(v_axis, -normal)
                    size = (2 * half[2 - axis], 2 * half[1])
                face(f"box {len(boxes) - 1} {'-+'[side]}{'xyz'[axis]}", centre + half[axis] * normal, u_axis, v_axis,
                     normal, size, tex_for(*size), shades[(axis, side)])
    lo.setflags(write=False)
    hi.setflags(write=False)
    return Scene(seed=int(seed), room_min=lo, room_max=hi, boxes=tuple(boxes), surfaces=tuple(surfaces),
                 texels_per_metre=rho, photo=use_photo)


# ---------------------------------------------------------------------------------------------- ray casting
@functools.lru_cache(maxsize=8)
def _pixel_grid(fx, fy, cx, cy, width, height) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (u, v) [H * W] and camera-frame ray directions with z = 1 [H * W, 3]."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    u, v = u.reshape(-1), v.reshape(-1)
    d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=1)
    for a in (u, v, d):
        a.setflags(write=False)
    return u, v, d


def _subpixel_rays(fx, fy, cx, cy, rows, cols, ss) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ss x ss rays per listed pixel at offsets ``(k + 0.5) / ss - 0.5``: (u, v) [n * ss * ss] and directions."""
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    v = (rows[:, None, None] + offs[None, :, None] + 0.0 * offs[None, None, :]).reshape(-1)
    u = (cols[:, None, None] + 0.0 * offs[None, :, None] + offs[None, None, :]).reshape(-1)
    d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=1)
    return u, v, d


def _intersect_room(lo: np.ndarray, hi: np.ndarray, o: np.ndarray, d: np.ndarray):
    """From inside the room every ray leaves through one face: the nearest exit over the three slabs."""
    t = np.full(len(d), np.inf)
    sid = np.zeros(len(d), np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in range(3):
            da = d[:, a]
            pos = da > 0
            ta = np.where(pos, hi[a] - o[a], lo[a] - o[a]) / da
            ta = np.where(ta > 0, ta, np.inf)  # also maps nan / -inf (ray parallel to the slab) to no exit
            closer = ta < t
            t = np.where(closer, ta, t)
            sid = np.where(closer, 2 * a + pos, sid).astype(np.int32)
    return t, sid


def _intersect_box(box: Box, o: np.ndarray, d: np.ndarray):
    """Slab test in the box's frame: entry t [n], entry face (0..5 = -x, +x, -y, +y, -z, +z) [n], hit mask [n]."""
    R = box.rotation
    ol = R.T @ (o - box.centre)
    dl = d @ R
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-box.half_size - ol) / dl
        t2 = (box.half_size - ol) / dl
        tn = np.minimum(t1, t2)
        t_out = np.maximum(t1, t2).min(axis=1)
    ax = np.argmax(tn, axis=1)
    rows = np.arange(len(d))
    t_in = tn[rows, ax]
    hit = (t_in <= t_out) & (t_in > 1e-9)
    face = (2 * ax + (dl[rows, ax] < 0)).astype(np.int32)
    return t_in, face, hit


def _box_pixel_rect(box: Box, world_to_cam: np.ndarray, cam: tuple[float, float, float, float]):
    """Pixel rectangle (u0, u1, v0, v1) containing the box's image, or None when a corner is behind the camera."""
    fx, fy, cx, cy = cam
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    corners = box.centre + (signs * box.half_size) @ box.rotation.T
    pc = corners @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    if np.any(pc[:, 2] < 1e-3):
        return None
    u = fx * pc[:, 0] / pc[:, 2] + cx
    v = fy * pc[:, 1] / pc[:, 2] + cy
    return u.min() - 1.0, u.max() + 1.0, v.min() - 1.0, v.max() + 1.0


def _cast(scene: Scene, o: np.ndarray, d: np.ndarray, u: np.ndarray, v: np.ndarray, world_to_cam: np.ndarray,
          cam: tuple[float, float, float, float]):
    """Nearest hit of rays ``o + t d`` (t > 0): ``t`` [n] (in units of d) and the surface index [n] (int32). Boxes
    are tested only against the rays whose pixel (u, v) falls in the box's projected rectangle."""
    t, sid = _intersect_room(scene.room_min, scene.room_max, o, d)
    for b, box in enumerate(scene.boxes):
        rect = _box_pixel_rect(box, world_to_cam, cam)
        if rect is None:
            idx = np.arange(len(d))
        else:
            idx = np.nonzero((u >= rect[0]) & (u <= rect[1]) & (v >= rect[2]) & (v <= rect[3]))[0]
            if len(idx) == 0:
                continue
        t_in, face, hit = _intersect_box(box, o, d[idx])
        hit &= t_in < t[idx]
        sel = idx[hit]
        t[sel] = t_in[hit]
        sid[sel] = 6 + 6 * b + face[hit]
    return t, sid


def _sample_level(A: _Atlas, li: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup [n, 3] in atlas level ``li`` [n] at surface coordinates (u, v) [n] metres (texel centres at
    integer texel coordinates; clamped to the level's edge)."""
    x = u * A.level_sx[li]
    x -= np.float32(0.5)
    y = v * A.level_sy[li]
    y -= np.float32(0.5)
    np.clip(x, np.float32(0.0), A.level_xmax[li], out=x)
    np.clip(y, np.float32(0.0), A.level_ymax[li], out=y)
    x0 = np.minimum(x.astype(np.int32), A.level_x0max[li])
    y0 = np.minimum(y.astype(np.int32), A.level_y0max[li])
    x -= x0
    y -= y0
    fx, fy = x[:, None], y[:, None]
    w = A.level_w[li]
    i00 = y0 * w
    i00 += x0
    i00 += A.level_base[li]
    i01 = i00 + (x0 + 1 < w)
    step = A.level_step[li]
    # np.take along axis 0 is several times faster than texels[idx] for rows of 3 floats
    top = np.take(A.texels, i00, axis=0)
    top += (np.take(A.texels, i01, axis=0) - top) * fx
    i00 += step
    i01 += step
    bot = np.take(A.texels, i00, axis=0)
    bot += (np.take(A.texels, i01, axis=0) - bot) * fx
    top += (bot - top) * fy
    return top


def _shade(scene: Scene, o: np.ndarray, d: np.ndarray, t: np.ndarray, sid: np.ndarray,
           texel_scale: float) -> np.ndarray:
    """Radiance [n, 3] float32 of the hits: each surface's texture sampled trilinearly (mip level from the ray's
    footprint, ``texel_scale`` = radians per ray * texels per metre), times the face's shade."""
    A = scene.atlas
    q = t[:, None] * d
    q += o
    q -= np.take(A.origin, sid, axis=0)
    u = np.einsum("ij,ij->i", q, np.take(A.u_axis, sid, axis=0)).astype(np.float32)
    v = np.einsum("ij,ij->i", q, np.take(A.v_axis, sid, axis=0)).astype(np.float32)
    dn = np.sqrt(np.einsum("ij,ij->i", d, d))
    cos = np.abs(np.einsum("ij,ij->i", d, np.take(A.normal, sid, axis=0))) / dn
    footprint = (t * dn) * texel_scale / np.maximum(cos, 0.15)  # texels under one ray
    top = A.num_levels[sid] - 1
    level = np.minimum(np.log2(np.maximum(footprint, 1.0)), top).astype(np.float32)
    l0 = level.astype(np.int32)
    level -= l0
    first = A.first_level[sid]
    c = _sample_level(A, first + l0, u, v)
    blend = np.nonzero(level > 0)[0]
    if len(blend) == len(level):
        c1 = _sample_level(A, first + np.minimum(l0 + 1, top), u, v)
        c += (c1 - c) * level[:, None]
    elif len(blend):
        c1 = _sample_level(A, first[blend] + np.minimum(l0[blend] + 1, top[blend]), u[blend], v[blend])
        c[blend] += (c1 - c[blend]) * level[blend, None]
    c *= A.shade[sid][:, None]
    return c


def _edge_pixels(sid_image: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood sees more than one surface (geometric edges)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    return maximum_filter(sid_image, size=3, mode="nearest") != minimum_filter(sid_image, size=3, mode="nearest")


def render(scene: Scene, camera: SyntheticCamera, cam_to_world, *, supersample: int = 2,
           adaptive: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Render the scene's radiance and exact z-depth from a camera pose.

    ``camera``: :class:`SyntheticCamera` (or any object with ``fx, fy, cx, cy, width, height``). ``cam_to_world``: 4x4.

    Anti-aliasing: textures are mip-mapped (trilinear, level from each ray's footprint), and pixels on geometric
    edges -- whose 3x3 neighbourhood sees more than one face -- are ``supersample x supersample`` supersampled
    (regular grid at ``(k + 0.5) / n - 0.5`` pixel offsets, averaged). ``adaptive=False`` supersamples every pixel
    (slower, texture filtered for the sub-sample footprint). ``supersample=1`` turns supersampling off.

    Returns ``rgb`` float32 ``[H, W, 3]`` in [0, 1] (radiance: no exposure, vignetting or noise; see
    :func:`apply_photometric`) and ``depth`` float32 ``[H, W]``, the z-depth in metres at each pixel centre.
    """
    T = np.asarray(cam_to_world, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"render: cam_to_world must be a finite 4x4 matrix, got shape {T.shape}")
    ss = int(supersample)
    if ss < 1:
        raise ValueError(f"render: supersample must be >= 1, got {supersample}")
    R, o = T[:3, :3], T[:3, 3].copy()
    if not (np.all(o > scene.room_min) and np.all(o < scene.room_max)):
        raise ValueError(f"render: the camera centre {o.tolist()} is outside the room "
                         f"[{scene.room_min.tolist()}, {scene.room_max.tolist()}]")
    if any(b.contains(o) for b in scene.boxes):
        raise ValueError(f"render: the camera centre {o.tolist()} is inside a box")
    W, H = int(camera.width), int(camera.height)
    cam = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    world_to_cam = np.eye(4)
    world_to_cam[:3, :3] = R.T
    world_to_cam[:3, 3] = -R.T @ o
    rho = scene.texels_per_metre
    pix_angle = 1.0 / max(cam[0], cam[1])  # radians per pixel at the centre, about

    # one ray through each pixel centre; with d_cam = (x, y, 1) the ray parameter t is the z-depth
    u, v, d_cam = _pixel_grid(*cam, W, H)
    d = d_cam @ R.T
    t, sid = _cast(scene, o, d, u, v, world_to_cam, cam)
    depth = t.reshape(H, W).astype(np.float32)
    if ss == 1 or adaptive:
        rgb = _shade(scene, o, d, t, sid, pix_angle * rho).reshape(H, W, 3)
    else:
        rgb = np.empty((H, W, 3), np.float32)
    if ss > 1:
        mask = _edge_pixels(sid.reshape(H, W)) if adaptive else np.ones((H, W), bool)
        rows, cols = np.nonzero(mask)
        if len(rows):
            us, vs, ds_cam = _subpixel_rays(*cam, rows.astype(np.float64), cols.astype(np.float64), ss)
            ds = ds_cam @ R.T
            ts, sids = _cast(scene, o, ds, us, vs, world_to_cam, cam)
            scale = pix_angle * rho / (1.0 if adaptive else ss)
            cs = _shade(scene, o, ds, ts, sids, scale).reshape(len(rows), ss * ss, 3)
            rgb[rows, cols] = cs.mean(axis=1)
    return np.clip(rgb, 0.0, 1.0), depth


def depth_to_points(depth: np.ndarray, camera: SyntheticCamera, cam_to_world, image: np.ndarray | None = None,
                    stride: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """Back-project a z-depth map to world points: ``X_w = R (depth * K^-1 [u, v, 1]) + t`` for every
    ``stride``-th pixel with finite, positive depth. Returns points ``[N, 3]`` (float64) and, when ``image`` is
    given, their colours ``[N, C]`` (e.g. to seed a Gaussian map in a test)."""
    depth = np.asarray(depth)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth_to_points: depth {depth.shape} does not match the camera "
                         f"{camera.height}x{camera.width}")
    v, u = np.mgrid[0:camera.height:stride, 0:camera.width:stride]
    z = depth[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    u, v, z = u[ok], v[ok], z[ok]
    Xc = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], axis=1)
    T = np.asarray(cam_to_world, dtype=np.float64)
    pts = Xc @ T[:3, :3].T + T[:3, 3]
    cols = None if image is None else np.asarray(image)[v, u]
    return pts, cols


# --------------------------------------------------------------------------------------------- camera path
BASE_STEP = 0.02  # path parameter advance per frame at motion_scale 1 (about 1.3 cm and 0.7 degree per frame)


def _look_at(position: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    z = target - position
    z = z / np.linalg.norm(z)
    down = np.array([0.0, 1.0, 0.0])
    x = np.cross(down, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    return R @ so3_exp(np.array([0.0, 0.0, roll]))


def _path_parameters(num_frames: int, motion_scale: float, fps: float, phase: float) -> np.ndarray:
    """The camera paths' parameter of each frame, ``phase + motion_scale * BASE_STEP * i``, after the checks."""
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if not (fps > 0 and np.isfinite(motion_scale) and motion_scale >= 0):
        raise ValueError(f"need fps > 0 and motion_scale >= 0, got fps={fps}, motion_scale={motion_scale}")
    return phase + motion_scale * BASE_STEP * np.arange(num_frames)


def camera_path(num_frames: int, *, motion_scale: float = 1.0, fps: float = 30.0, start_time: float = 0.0,
                phase: float = 0.0) -> Trajectory:
    """A smooth figure-eight in front of the boxes, looking into the room (+z), with varying yaw, pitch and roll.

    Frame i is at path parameter ``s = phase + motion_scale * 0.02 * i`` (radians). The path is periodic: ``s`` in
    [0, 2 pi) is one full figure-eight (314 frames at ``motion_scale`` 1) that returns exactly to its start pose.
    At ``motion_scale`` 1 the camera moves 0.9-1.9 cm (mean 1.3 cm) and turns 0.02-1.3 degrees (mean 0.7) per frame,
    yaw within about +-30 degrees and roll +-6 degrees; inter-frame motion scales linearly with ``motion_scale``
    (the same curve, traversed faster). Camera centres stay within x in [-0.8, 0.8], y in [-0.27, 0.17],
    z in [-1.35, -0.65] m; depths seen are about 1.4-6 m.
    """
    s = _path_parameters(num_frames, motion_scale, fps, phase)
    poses = np.empty((num_frames, 4, 4))
    for i, si in enumerate(s):
        pos = np.array([0.8 * np.sin(si), -0.05 + 0.22 * np.sin(2 * si), -1.0 + 0.35 * np.sin(si + 0.7)])
        target = np.array([2.0 * np.sin(2.0 * si + 0.4), 0.55 + 0.4 * np.sin(3.0 * si + 1.0), 3.5])
        roll = np.radians(6.0) * np.sin(2.0 * si + 0.3)
        poses[i] = make_pose(_look_at(pos, target, roll), pos)
    return Trajectory(start_time + np.arange(num_frames) / fps, poses)


def rotation_path(num_frames: int, *, motion_scale: float = 1.0, fps: float = 30.0, start_time: float = 0.0,
                  phase: float = 0.0) -> Trajectory:
    """A handheld camera that stays nearly in place and rolls, pitches and yaws (TUM RGB-D ``freiburg1_rpy``'s
    motion): yaw within +-25 degrees, pitch +-12, roll +-20, each a sine of its own frequency, and the centre within
    3 cm of (0, 0, -1) m. Frame i is at ``s = phase + motion_scale * 0.02 * i``; at ``motion_scale`` 1 the camera
    turns about 0.3-1.3 degrees a frame (3 gives freiburg1_rpy's 1-4 degrees) and moves about 1 mm. Little
    parallax: the depths a monocular odometry estimates from it are poor, and it keeps coming back to the same
    views."""
    s = _path_parameters(num_frames, motion_scale, fps, phase)
    poses = np.empty((num_frames, 4, 4))
    for i, si in enumerate(s):
        yaw, pitch, roll = (np.radians(25.0) * np.sin(si), np.radians(12.0) * np.sin(1.7 * si + 0.5),
                            np.radians(20.0) * np.sin(2.3 * si + 1.0))
        R = so3_exp(np.array([0.0, yaw, 0.0])) @ so3_exp(np.array([pitch, 0.0, 0.0])) @ so3_exp(
            np.array([0.0, 0.0, roll]))
        pos = np.array([0.03 * np.sin(si), 0.02 * np.sin(1.3 * si), -1.0 + 0.02 * np.sin(0.7 * si)])
        poses[i] = make_pose(R, pos)
    return Trajectory(start_time + np.arange(num_frames) / fps, poses)


CAMERA_PATHS = {"figure_eight": camera_path, "rotation": rotation_path}


# ----------------------------------------------------------------------------------------------- photometry
def vignette_factor(width: int, height: int, strength: float, cx: float | None = None,
                    cy: float | None = None) -> np.ndarray:
    """``V = 1 - strength * (r / r_corner)^2`` per pixel, float32 ``[H, W]``; r is the distance to the principal
    point (default the image centre), r_corner that of the farthest corner (so V ranges over [1 - strength, 1])."""
    if not 0.0 <= strength < 1.0:
        raise ValueError(f"vignette strength must be in [0, 1), got {strength}")
    cx = (width - 1) * 0.5 if cx is None else cx
    cy = (height - 1) * 0.5 if cy is None else cy
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    r2 = (xx - cx) ** 2 + (yy - cy) ** 2
    corners = [(0, 0), (width - 1, 0), (0, height - 1), (width - 1, height - 1)]
    rc2 = max((x - cx) ** 2 + (y - cy) ** 2 for x, y in corners)
    return (1.0 - strength * r2 / rc2).astype(np.float32)


def exposure_schedule(num_frames: int, *, variation: float = 0.0, base_exposure_ms: float = 10.0,
                      period_frames: float = 40.0, seed: int = 0) -> np.ndarray:
    """Exposure time (ms) per frame: ``base * exp(variation * sin(2 pi i / period + phi))`` with a phase ``phi``
    drawn from ``seed``. ``variation`` 0 gives a constant exposure; 0.3 gives gains in [0.74, 1.35]."""
    if variation < 0 or base_exposure_ms <= 0 or period_frames <= 0:
        raise ValueError("exposure_schedule: need variation >= 0, base_exposure_ms > 0, period_frames > 0")
    phi = np.random.default_rng([int(seed), 0xE4905]).uniform(0, 2 * np.pi)
    i = np.arange(num_frames)
    return base_exposure_ms * np.exp(variation * np.sin(2 * np.pi * i / period_frames + phi))


def apply_photometric(radiance: np.ndarray, *, gain: float = 1.0, vignette: np.ndarray | None = None,
                      noise_sigma: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """``clip(gain * V * radiance + N(0, noise_sigma^2), 0, 1)`` as float32 (the module's photometric model)."""
    img = radiance.astype(np.float32) * np.float32(gain)
    if vignette is not None:
        img *= vignette[..., None] if img.ndim == 3 else vignette
    if noise_sigma > 0:
        if rng is None:
            raise ValueError("apply_photometric: noise needs an rng (for determinism)")
        img += rng.normal(0.0, noise_sigma, size=img.shape).astype(np.float32)
    return np.clip(img, 0.0, 1.0)


# ------------------------------------------------------------------------------------------------ sequences
@dataclass(frozen=True)
class SequenceSpec:
    """Everything that determines a synthetic sequence (and its cache key)."""

    seed: int = 0
    num_frames: int = 30
    width: int = 160
    height: int = 120
    fov_x_deg: float = 70.0
    fps: float = 30.0
    start_time: float = 0.0
    motion_scale: float = 1.0
    phase: float = 0.0
    path: str = "figure_eight"      # CAMERA_PATHS: "figure_eight" (camera_path) or "rotation" (rotation_path)
    supersample: int = 2
    exposure_variation: float = 0.0
    exposure_period_frames: float = 40.0
    base_exposure_ms: float = 10.0
    vignette_strength: float = 0.0
    noise_sigma: float = 0.0
    num_boxes: int = 3
    texels_per_metre: float = 128.0
    photo: bool = False

    def __post_init__(self):
        if self.num_frames < 1:
            raise ValueError(f"num_frames must be >= 1, got {self.num_frames}")
        if self.width < 16 or self.height < 16:
            raise ValueError(f"image size must be at least 16x16, got {self.width}x{self.height}")
        checks = [(self.noise_sigma >= 0, "noise_sigma must be >= 0"),
                  (0 <= self.vignette_strength < 1, "vignette_strength must be in [0, 1)"),
                  (self.exposure_variation >= 0, "exposure_variation must be >= 0"),
                  (self.exposure_period_frames > 0 and self.base_exposure_ms > 0,
                   "exposure_period_frames and base_exposure_ms must be > 0"),
                  (self.motion_scale >= 0 and self.fps > 0, "motion_scale must be >= 0 and fps > 0"),
                  (self.supersample >= 1, "supersample must be >= 1"),
                  (self.path in CAMERA_PATHS, f"path must be one of {sorted(CAMERA_PATHS)}")]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"synthetic sequence: {msg} ({self})")

    @classmethod
    def from_params(cls, **params) -> "SequenceSpec":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(params) - names)
        if unknown:
            raise TypeError(f"unknown synthetic sequence parameter(s) {unknown}; known: {sorted(names)}")
        return cls(**params)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if d["path"] == "figure_eight":   # the default: keys (and cached folders) of the sequences made before it
            del d["path"]
        return d

    def key(self) -> str:
        """A short hash of the parameters and :data:`SYNTHETIC_VERSION` (the cache folder name)."""
        blob = json.dumps({"version": SYNTHETIC_VERSION, **self.to_dict()}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    @property
    def intrinsics(self) -> SyntheticCamera:
        return SyntheticCamera.from_fov(self.width, self.height, self.fov_x_deg)

    def scene(self) -> Scene:
        return make_scene(self.seed, num_boxes=self.num_boxes, texels_per_metre=self.texels_per_metre,
                          photo=self.photo)

    def trajectory(self) -> Trajectory:
        return CAMERA_PATHS[self.path](self.num_frames, motion_scale=self.motion_scale, fps=self.fps,
                                       start_time=self.start_time, phase=self.phase)

    def exposures_ms(self) -> np.ndarray:
        return exposure_schedule(self.num_frames, variation=self.exposure_variation,
                                 base_exposure_ms=self.base_exposure_ms, period_frames=self.exposure_period_frames,
                                 seed=self.seed)

    def vignette(self) -> np.ndarray:
        k = self.intrinsics
        return vignette_factor(self.width, self.height, self.vignette_strength, k.cx, k.cy)


@dataclass(frozen=True, eq=False)
class SyntheticFrame:
    index: int
    timestamp: float  # seconds
    cam_to_world: np.ndarray  # [4, 4]
    image: np.ndarray  # [H, W, 3] float32 in [0, 1], photometric model applied
    depth: np.ndarray  # [H, W] float32 z-depth, metres
    radiance: np.ndarray  # [H, W, 3] float32, before exposure / vignetting / noise
    exposure_ms: float
    gain: float  # exposure_ms / base_exposure_ms


def iter_frames(spec: SequenceSpec | None = None, **params) -> Iterator[SyntheticFrame]:
    """Render the sequence one frame at a time (constant memory)."""
    spec = spec if spec is not None else SequenceSpec.from_params(**params)
    scene, cam, traj = spec.scene(), spec.intrinsics, spec.trajectory()
    exposures = spec.exposures_ms()
    vig = spec.vignette() if spec.vignette_strength > 0 else None
    for i in range(spec.num_frames):
        radiance, depth = render(scene, cam, traj.cam_to_world[i], supersample=spec.supersample)
        gain = float(exposures[i] / spec.base_exposure_ms)
        rng = np.random.default_rng([spec.seed, 0x4015E, i])
        image = apply_photometric(radiance, gain=gain, vignette=vig, noise_sigma=spec.noise_sigma, rng=rng)
        yield SyntheticFrame(i, float(traj.timestamps[i]), traj.cam_to_world[i], image, depth, radiance,
                             float(exposures[i]), gain)


@dataclass(eq=False)
class SyntheticSequence:
    """A rendered sequence in memory."""

    spec: SequenceSpec
    scene: Scene
    intrinsics: SyntheticCamera
    trajectory: Trajectory  # cam_to_world ground truth at the frame timestamps
    images: np.ndarray  # [N, H, W, 3] float32 in [0, 1], photometric model applied
    depths: np.ndarray  # [N, H, W] float32 z-depth, metres
    exposures_ms: np.ndarray  # [N]
    vignette: np.ndarray  # [H, W] float32 (all ones without vignetting)
    radiance: np.ndarray | None = field(default=None)  # [N, H, W, 3] when kept

    @property
    def K(self) -> np.ndarray:
        return self.intrinsics.K

    @property
    def timestamps(self) -> np.ndarray:
        return self.trajectory.timestamps

    @property
    def cam_to_world(self) -> np.ndarray:
        return self.trajectory.cam_to_world

    @property
    def gains(self) -> np.ndarray:
        return self.exposures_ms / self.spec.base_exposure_ms

    def __len__(self) -> int:
        return len(self.images)


def make_sequence(spec: SequenceSpec | None = None, *, keep_radiance: bool = False, **params) -> SyntheticSequence:
    """Render a whole sequence in memory. Parameters: the fields of :class:`SequenceSpec` (``seed``,
    ``num_frames``, ``width``, ``height``, ``fov_x_deg``, ``fps``, ``motion_scale``, ``exposure_variation``,
    ``vignette_strength``, ``noise_sigma``, ``supersample``, ...), or a ``spec``. ``keep_radiance`` also keeps the
    images before exposure, vignetting and noise."""
    spec = spec if spec is not None else SequenceSpec.from_params(**params)
    frames = list(iter_frames(spec))
    vig = spec.vignette() if spec.vignette_strength > 0 else np.ones((spec.height, spec.width), np.float32)
    return SyntheticSequence(
        spec=spec, scene=spec.scene(), intrinsics=spec.intrinsics, trajectory=spec.trajectory(),
        images=np.stack([f.image for f in frames]), depths=np.stack([f.depth for f in frames]),
        exposures_ms=np.array([f.exposure_ms for f in frames]), vignette=vig,
        radiance=np.stack([f.radiance for f in frames]) if keep_radiance else None)


# ------------------------------------------------------------------------------------------- folder output
def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def _depth_u16(depth: np.ndarray) -> np.ndarray:
    d = np.round(depth.astype(np.float64) * TUM_DEPTH_FACTOR)
    d[(d <= 0) | (d > 65535) | ~np.isfinite(d)] = 0
    return d.astype(np.uint16)


_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 3]


def _readme(spec: SequenceSpec, scene: Scene, k: SyntheticCamera, files: list[str]) -> str:
    params = "\n".join(f"  {n} = {np.asarray(v).tolist() if isinstance(v, (np.generic, np.ndarray)) else v!r}"
                       for n, v in spec.to_dict().items())
    return f"""mgso synthetic sequence (TUM RGB-D layout)

A rendered sequence of a procedurally textured room with boxes, with exact camera poses and depth, made by
mgso.synthetic (version {SYNTHETIC_VERSION}): {scene.describe()}.
Regenerate it byte for byte with: mgso.synthetic.write_tum_rgbd(folder, **params) with the parameters below.

Parameters:
{params}

Files:
  rgb/<timestamp>.png    8-bit RGB PNG, {k.width}x{k.height}
  depth/<timestamp>.png  uint16 PNG, z-depth (not ray length) in metres * {TUM_DEPTH_FACTOR:g}, 0 = no depth
  rgb.txt, depth.txt     'timestamp filename' per line (TUM RGB-D), timestamps in seconds
  groundtruth.txt        'timestamp tx ty tz qx qy qz qw' per line: camera-to-world, quaternion w last (TUM)
  camera.txt             DSO format, absolute pinhole intrinsics in pixels, no distortion, no crop
  synthetic.json         the parameters as JSON
{''.join(f'  {f}' + chr(10) for f in files)}
Conventions: camera x right, y down, z forward; pixel centres at integer coordinates (pixel (0,0) is centred at
(0,0)), so K = [[{k.fx:.6f}, 0, {k.cx:.6f}], [0, {k.fy:.6f}, {k.cy:.6f}], [0, 0, 1]]. World y points down.
Photometric model: I = clip(g_i * V(x) * L(x) + noise, 0, 1), linear response,
g_i = exposure_ms / {spec.base_exposure_ms:g} ms, V(x) = 1 - {spec.vignette_strength:g} * (r / r_corner)^2 (r: distance
to the principal point), noise std {spec.noise_sigma:g} (in [0, 1] units). Depth is z-depth, not ray length.
"""


_OUTPUTS = ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "camera.txt", "exposures.txt", "vignette.png",
            "pcalib.txt", "synthetic.json", "README.txt")


def write_tum_rgbd(folder: str | os.PathLike, source: "SyntheticSequence | SequenceSpec | None" = None, *,
                   overwrite: bool = False, **params) -> Path:
    """Write a TUM RGB-D style folder that the project's dataset reader opens; returns its path.

    ``source``: a :class:`SyntheticSequence` already in memory, a :class:`SequenceSpec`, or nothing and the spec's
    fields as keyword arguments (then frames are rendered and written one at a time). Layout::

        rgb/<t>.png  depth/<t>.png  rgb.txt  depth.txt  groundtruth.txt  camera.txt  synthetic.json  README.txt
        exposures.txt (when exposure_variation > 0: 'timestamp exposure_ms' per line)
        vignette.png, pcalib.txt (when vignette_strength > 0: 16-bit V(x) * 65535 and a linear response, TUM monoVO)

    ``<t>`` is the timestamp formatted ``%.6f``. Depth PNGs hold z-depth * 5000 (TUM). ``camera.txt`` is DSO's:
    ``Pinhole fx fy cx cy 0`` / ``W H`` / ``none`` / ``W H``. Same parameters give byte-identical files.

    A folder that is not empty is refused (``FileExistsError``) unless ``overwrite=True``, which first removes this
    function's outputs from it (so no stale frame or ``exposures.txt`` of an earlier run remains).
    """
    if isinstance(source, SyntheticSequence):
        if params:
            raise TypeError("write_tum_rgbd: pass either a sequence or parameters, not both")
        spec = source.spec
        frames = (SyntheticFrame(i, float(source.timestamps[i]), source.cam_to_world[i], source.images[i],
                                 source.depths[i], source.images[i], float(source.exposures_ms[i]),
                                 float(source.gains[i])) for i in range(len(source)))
    else:
        spec = source if source is not None else SequenceSpec.from_params(**params)
        frames = iter_frames(spec)
    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        if not overwrite:
            raise FileExistsError(f"write_tum_rgbd: {folder} is not empty (pass overwrite=True to replace a "
                                  f"synthetic sequence written there)")
        for name in _OUTPUTS:
            p = folder / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    k = spec.intrinsics
    traj = spec.trajectory()
    names = [f"{t:.6f}" for t in traj.timestamps]
    if len(set(names)) != len(names):
        raise ValueError(f"write_tum_rgbd: fps {spec.fps} gives timestamps that collide at 6 decimals")
    exposures = []
    for fr in frames:
        name = names[fr.index]
        ok1 = cv2.imwrite(str(folder / "rgb" / f"{name}.png"), cv2.cvtColor(_to_u8(fr.image), cv2.COLOR_RGB2BGR),
                          _PNG)
        ok2 = cv2.imwrite(str(folder / "depth" / f"{name}.png"), _depth_u16(fr.depth), _PNG)
        if not (ok1 and ok2):
            raise OSError(f"write_tum_rgbd: could not write frame {fr.index} into {folder}")
        exposures.append(fr.exposure_ms)
    header = "# {what}\n# file: 'mgso synthetic, seed {seed}'\n# timestamp filename\n"
    with open(folder / "rgb.txt", "w", encoding="utf-8", newline="\n") as fh:
        fh.write(header.format(what="color images", seed=spec.seed))
        fh.writelines(f"{n} rgb/{n}.png\n" for n in names)
    with open(folder / "depth.txt", "w", encoding="utf-8", newline="\n") as fh:
        fh.write(header.format(what="depth maps", seed=spec.seed))
        fh.writelines(f"{n} depth/{n}.png\n" for n in names)
    write_tum(folder / "groundtruth.txt", traj)
    with open(folder / "camera.txt", "w", encoding="utf-8", newline="\n") as fh:
        fh.write(f"Pinhole {k.fx:.6f} {k.fy:.6f} {k.cx:.6f} {k.cy:.6f} 0\n{k.width} {k.height}\nnone\n"
                 f"{k.width} {k.height}\n")
    extra = []
    if spec.exposure_variation > 0:
        with open(folder / "exposures.txt", "w", encoding="utf-8", newline="\n") as fh:
            fh.writelines(f"{n} {e:.6f}\n" for n, e in zip(names, exposures))
        extra.append(f"{'exposures.txt':<23}'timestamp exposure_ms' per line (gain = exposure_ms / base)")
    if spec.vignette_strength > 0:
        v16 = np.round(spec.vignette() * 65535.0).astype(np.uint16)
        cv2.imwrite(str(folder / "vignette.png"), v16, _PNG)
        with open(folder / "pcalib.txt", "w", encoding="utf-8", newline="\n") as fh:
            fh.write(" ".join(str(i) for i in range(256)) + "\n")
        extra.append(f"{'vignette.png':<23}16-bit vignette V(x) * 65535 (TUM monoVO style)")
        extra.append(f"{'pcalib.txt':<23}linear camera response (TUM monoVO: 256 values for 0..255)")
    with open(folder / "synthetic.json", "w", encoding="utf-8", newline="\n") as fh:
        json.dump({"version": SYNTHETIC_VERSION, **spec.to_dict()}, fh, indent=2, sort_keys=True)
        fh.write("\n")
    with open(folder / "README.txt", "w", encoding="utf-8", newline="\n") as fh:
        fh.write(_readme(spec, spec.scene(), k, extra))
    return folder


def default_cache_dir() -> Path:
    """``$MGSO_CACHE_DIR/synthetic`` if set, else ``<XDG cache or ~/.cache>/mgso/synthetic``."""
    env = os.environ.get("MGSO_CACHE_DIR")
    if env:
        return Path(env).expanduser() / "synthetic"
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mgso" / "synthetic"


def cached_sequence_folder(cache_dir: str | os.PathLike | None = None, **params) -> Path:
    """A TUM RGB-D folder for these parameters (:class:`SequenceSpec` fields), written once into
    ``<cache_dir>/<hash of parameters and version>`` and reused afterwards. The folder is written to a temporary
    name and renamed when complete, so an interrupted run never leaves a half-written folder in the cache."""
    spec = SequenceSpec.from_params(**params)
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    target = root / spec.key()
    if (target / "synthetic.json").is_file() and (target / "README.txt").is_file():
        return target
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{spec.key()}-", dir=root))
    try:
        write_tum_rgbd(tmp, spec)
        try:
            os.replace(tmp, target)
        except OSError:
            if not (target / "README.txt").is_file():  # a broken leftover: replace it
                shutil.rmtree(target, ignore_errors=True)
                os.replace(tmp, target)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target
