"""Typed messages from the odometry to the mapping thread (DSO habit 10: threads talk through typed messages).

The contract between the two halves lives here, outside both: the odometry, the loop closer and the observers
import it without importing the map (:mod:`mgso.mapping`), and the mapper imports it to apply the messages.

The odometry (tracking + window) never touches the Gaussian map; it emits these frozen values, the system puts them
on the mapper's bounded queue, and the mapper (:mod:`mgso.mapping.mapper`) applies them between training steps:

- :class:`KeyframeMessage`: a new keyframe: its RGB image, pinhole camera, refined ``cam_to_world``, DSO's affine
  brightness (a, b) and exposure time, and DSO's points hosted by it (pixel, inverse depth, kind). The mapper seeds
  Gaussians from the points where the map is still empty and adds the keyframe as a training view.
- :class:`PoseUpdate`: the window refined keyframes that already reached the map: new ``cam_to_world`` (and
  affine) per keyframe id. The mapper moves the training views (the map follows the odometry).
- :class:`PointsMessage`: points left the window for good (final depth): world positions, colours, the host
  keyframe. They join the DSO point cloud (``points.ply``), and the mapper seeds from them as from a keyframe's
  points (where the map is still empty, seen from the host keyframe).
- :class:`LoopCorrection`: loop closure moved keyframes (a Sim(3) each, world to corrected world): the mapper moves
  their views and the Gaussians anchored to them (:mod:`mgso.loop`).
- :class:`Stop`: the end of the stream (``refine``: run the final refinement first; an interrupted run does not).

Every array is copied, made read-only and checked at construction; bad input raises ``ValueError`` naming the field,
so a broken odometry fails where it emits, not deep inside the mapping thread.

Conventions (the project's): poses ``cam_to_world`` 4x4 float64 rigid (``X_w = R X_c + t``); camera x right, y down,
z forward; pixel centres at integer coordinates; inverse depth = 1 / camera z. DSO's photometric model is
``I = t e^a L + b`` on the 0-255 scale (``t`` the exposure time, 1 when unknown); :meth:`KeyframeMessage.map_exposure`
converts it to the trainer's ``image = exp(a') render + b'`` on the [0, 1] scale.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, Union

import numpy as np

from mgso.camera import PinholeCamera
from mgso.geometry import check_sim3, orthonormalize, se3_inverse, sim3_to_parts

__all__ = ["KeyframeMessage", "PoseUpdate", "PointsMessage", "LoopCorrection", "Stop", "MapperMessage",
           "PointKind", "map_exposure", "sim3_apply_to_pose", "check_points", "frozen_array"]


# ------------------------------------------------------------------------------------------- DSO's points
class PointKind(enum.IntEnum):
    """Where a seed comes from (DSO's point states, plus the Delaunay fill)."""

    ACTIVE = 0          # in the window's optimisation
    MARGINALIZED = 1    # marginalised with its host keyframe (final depth)
    IMMATURE = 2        # immature point whose depth interval is good enough (traced, not yet activated)
    FILL = 3            # made by the Delaunay fill (never given by the caller)


def frozen_array(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def check_points(where: str, points_uv, idepths, kinds=None, weights=None, colors=None):
    """DSO's points of one keyframe as read-only arrays ``(uv [M, 2] float64, idepths [M] float64, kinds [M] int8,
    weights [M] float64 | None, colors [M, 3] float32 | None)``, or a ValueError naming ``where`` and the field.
    An empty ``points_uv`` is zero points. (The seed input and the mapper's keyframe message both take points.)"""
    uv = np.array(points_uv, dtype=np.float64)
    if uv.size == 0:
        uv = uv.reshape(0, 2)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"{where}.points_uv: expected (M, 2) pixel coordinates, got {uv.shape}")
    m = len(uv)
    idepths = np.array(idepths, dtype=np.float64).reshape(-1)
    if idepths.shape != (m,):
        raise ValueError(f"{where}.idepths: expected ({m},) for {m} points, got {idepths.shape}")
    kinds = np.zeros(m, np.int8) if kinds is None else np.array(kinds).reshape(-1)
    if kinds.shape != (m,):
        raise ValueError(f"{where}.kinds: expected ({m},), got {kinds.shape}")
    valid = {int(PointKind.ACTIVE), int(PointKind.MARGINALIZED), int(PointKind.IMMATURE)}
    if m and not set(np.unique(kinds).tolist()) <= valid:
        raise ValueError(f"{where}.kinds: values must be PointKind ACTIVE/MARGINALIZED/IMMATURE "
                         f"({sorted(valid)}), got {sorted(set(np.unique(kinds).tolist()) - valid)}")
    out = [frozen_array(uv), frozen_array(idepths), frozen_array(kinds.astype(np.int8))]
    for name, v, dtype, shape in (("weights", weights, np.float64, (m,)), ("colors", colors, np.float32, (m, 3))):
        if v is None:
            out.append(None)
            continue
        arr = np.array(v, dtype=dtype)
        if name == "weights":
            arr = arr.reshape(-1)
        if arr.shape != shape:
            raise ValueError(f"{where}.{name}: expected {shape}, got {arr.shape}")
        out.append(frozen_array(arr))
    return tuple(out)


_frozen = frozen_array


def _rigid(T, where: str) -> np.ndarray:
    M = np.array(T, dtype=np.float64)
    if M.shape == (3, 4):
        M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise ValueError(f"{where}: expected a finite 4x4 cam_to_world, got shape {M.shape}")
    R = M[:3, :3]
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > 1e-2 or np.linalg.det(R) < 0 or np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ValueError(f"{where}: not a rigid transform (rotation not orthonormal: error {err:.2g}, or last row "
                         "not 0 0 0 1; convert a Sim3 to SE3 first)")
    if err > 1e-12:          # round-off of a long chain of float products: the nearest rotation
        M[:3, :3] = orthonormalize(R)
    return _frozen(M)


def _affine(ab, where: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in ab)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected a pair (a, b), got {_plain(ab)!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise ValueError(f"{where}: (a, b) must be finite, got ({a}, {b})")
    return a, b


def _plain(x):
    """NumPy values as plain Python ones for messages (``(nan, 1.0)``, not ``(np.float64(nan), ...)``)."""
    try:
        return np.asarray(x).tolist()
    except Exception:  # noqa: BLE001 - whatever it is, its repr
        return x


def map_exposure(affine: tuple[float, float], exposure_ms: float | None,
                 reference_exposure_ms: float | None) -> tuple[float, float]:
    """The trainer's per-view exposure ``(a', b')`` (``image = exp(a') render + b'``, [0, 1] units) of a frame with
    DSO's affine brightness ``affine = (a, b)`` (``I = t e^a L + b``, 0-255 units) and exposure time ``t``.

    ``a' = a + ln(t / t_ref)``, ``b' = b / 255``: the map then stores ``L t_ref / 255``, the radiance seen at the
    reference exposure (the first keyframe's), and every view's brightness is the odometry's. Unknown exposures
    (``None`` or <= 0, on either side) count as equal (DSO sets both to 1).
    """
    a, b = affine
    gain = 0.0
    if exposure_ms and reference_exposure_ms and exposure_ms > 0 and reference_exposure_ms > 0:
        gain = math.log(exposure_ms / reference_exposure_ms)
    return float(a) + gain, float(b) / 255.0


@dataclass(frozen=True, eq=False)
class KeyframeMessage:
    """A new keyframe for the map.

    - ``keyframe_id``: the odometry's id (unique, increasing); ``frame_index``: position of the frame in the
      sequence; ``timestamp``: seconds.
    - ``image``: (H, W, 3) float RGB in [0, 1] as recorded (undistorted, in the odometry's image geometry);
      ``camera``: its pinhole intrinsics (:class:`~mgso.camera.PinholeCamera` or anything with ``fx fy cx cy
      width height``).
    - ``cam_to_world``: 4x4 rigid pose at the time the keyframe was made (refined later by :class:`PoseUpdate`).
    - ``affine``: DSO's (a, b) of the keyframe (0-255 scale); ``exposure_ms``: its exposure time (``None`` when the
      dataset has none).
    - ``points_uv`` (M, 2) pixels, ``idepths`` (M,) inverse depths, ``kinds`` (M,) :class:`PointKind` codes (active,
      marginalised, immature), optional ``weights`` (M,) (DSO's inverse-depth Hessian) and ``colors`` (M, 3) RGB in
      [0, 1] (default: sampled from ``image`` over DSO's pattern by the seeding).
    - ``mask``: optional (H, W) loss weights (0 = ignore the pixel, e.g. black undistortion borders).
    - ``segment``: the odometry's segment number (a new one starts after a tracking loss).
    """

    keyframe_id: int
    frame_index: int
    timestamp: float
    image: np.ndarray
    camera: PinholeCamera
    cam_to_world: np.ndarray
    points_uv: np.ndarray
    idepths: np.ndarray
    kinds: np.ndarray | None = None
    affine: tuple[float, float] = (0.0, 0.0)
    exposure_ms: float | None = None
    weights: np.ndarray | None = None
    colors: np.ndarray | None = None
    mask: np.ndarray | None = None
    segment: int = 0

    def __post_init__(self):
        where = f"KeyframeMessage(keyframe {self.keyframe_id})"
        cam = self.camera
        if not isinstance(cam, PinholeCamera):
            try:
                cam = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
            except AttributeError:
                raise TypeError(f"{where}.camera: expected a PinholeCamera (fx, fy, cx, cy, width, height), got "
                                f"{type(cam).__name__}") from None
            object.__setattr__(self, "camera", cam)
        object.__setattr__(self, "keyframe_id", int(self.keyframe_id))
        object.__setattr__(self, "frame_index", int(self.frame_index))
        object.__setattr__(self, "timestamp", float(self.timestamp))
        object.__setattr__(self, "segment", int(self.segment))
        img = np.asarray(self.image)
        if img.shape != (cam.height, cam.width, 3):
            raise ValueError(f"{where}.image: expected ({cam.height}, {cam.width}, 3) RGB for a {cam.width}x"
                             f"{cam.height} camera, got {img.shape}")
        if not np.issubdtype(img.dtype, np.floating):
            raise ValueError(f"{where}.image: expected float RGB in [0, 1], got {img.dtype} (divide uint8 by 255)")
        if not np.all(np.isfinite(img)):
            raise ValueError(f"{where}.image: non-finite values")
        object.__setattr__(self, "image", _frozen(img.astype(np.float32, copy=True)))
        object.__setattr__(self, "cam_to_world", _rigid(self.cam_to_world, f"{where}.cam_to_world"))
        uv, idepths, kinds, weights, colors = check_points(where, self.points_uv, self.idepths, self.kinds,
                                                           self.weights, self.colors)
        for name, v in (("points_uv", uv), ("idepths", idepths), ("kinds", kinds), ("weights", weights),
                        ("colors", colors)):
            object.__setattr__(self, name, v)
        if self.mask is not None:
            mk = np.array(self.mask, dtype=np.float32)
            if mk.shape != (cam.height, cam.width) or not np.all(np.isfinite(mk)) or np.any(mk < 0):
                raise ValueError(f"{where}.mask: expected ({cam.height}, {cam.width}) finite weights >= 0")
            object.__setattr__(self, "mask", _frozen(mk))
        object.__setattr__(self, "affine", _affine(self.affine, f"{where}.affine"))
        if self.exposure_ms is not None:
            e = float(self.exposure_ms)
            if not math.isfinite(e):
                raise ValueError(f"{where}.exposure_ms: must be finite, got {self.exposure_ms!r}")
            object.__setattr__(self, "exposure_ms", e if e > 0 else None)

    @property
    def num_points(self) -> int:
        return int(self.points_uv.shape[0])

    @property
    def world_to_cam(self) -> np.ndarray:
        return se3_inverse(self.cam_to_world)

    def map_exposure(self, reference_exposure_ms: float | None) -> tuple[float, float]:
        """This keyframe's exposure for the trainer (see :func:`map_exposure`)."""
        return map_exposure(self.affine, self.exposure_ms, reference_exposure_ms)


@dataclass(frozen=True, eq=False)
class PoseUpdate:
    """Keyframe poses refined by the window: ``cam_to_world`` maps keyframe id -> 4x4 rigid pose; ``affine`` maps
    keyframe id -> DSO's refined (a, b) (only for those whose affine changed; may be empty). Ids the map does not
    know (a keyframe whose message has not arrived or that was never sent) are counted by the mapper and ignored."""

    cam_to_world: Mapping[int, np.ndarray]
    affine: Mapping[int, tuple[float, float]] = field(default_factory=dict)

    def __post_init__(self):
        poses = {int(k): _rigid(v, f"PoseUpdate.cam_to_world[{k}]") for k, v in dict(self.cam_to_world).items()}
        aff = {int(k): _affine(v, f"PoseUpdate.affine[{k}]") for k, v in dict(self.affine).items()}
        object.__setattr__(self, "cam_to_world", MappingProxyType(poses))
        object.__setattr__(self, "affine", MappingProxyType(aff))

    def __reduce__(self):
        # read-only mappings do not pickle; the message crosses to the mapper's process (mgso.mapping.process)
        return (PoseUpdate, (dict(self.cam_to_world), dict(self.affine)))

    @property
    def keyframe_ids(self) -> list[int]:
        return sorted(set(self.cam_to_world) | set(self.affine))


@dataclass(frozen=True, eq=False)
class PointsMessage:
    """Points that left the window for good: ``points`` (N, 3) world positions, ``colors`` (N, 3) RGB in [0, 1]
    (DSO: the mean over the pattern), ``host_keyframe_id`` (the keyframe they were hosted by; -1 when they are not
    from one keyframe), optional ``idepths`` (N,) in the host and ``weights`` (N,)."""

    points: np.ndarray
    colors: np.ndarray
    host_keyframe_id: int = -1
    weights: np.ndarray | None = None

    def __post_init__(self):
        where = f"PointsMessage(host {self.host_keyframe_id})"
        p = np.array(self.points, dtype=np.float64)
        if p.size == 0:
            p = p.reshape(0, 3)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"{where}.points: expected (N, 3), got {p.shape}")
        n = len(p)
        c = np.array(self.colors, dtype=np.float32)
        if c.size == 0:
            c = c.reshape(0, 3)
        if c.shape != (n, 3):
            raise ValueError(f"{where}.colors: expected ({n}, 3) RGB in [0, 1], got {c.shape}")
        object.__setattr__(self, "points", _frozen(p))
        object.__setattr__(self, "colors", _frozen(c))
        object.__setattr__(self, "host_keyframe_id", int(self.host_keyframe_id))
        if self.weights is not None:
            w = np.array(self.weights, dtype=np.float64).reshape(-1)
            if w.shape != (n,):
                raise ValueError(f"{where}.weights: expected ({n},), got {w.shape}")
            object.__setattr__(self, "weights", _frozen(w))

    def __len__(self) -> int:
        return int(self.points.shape[0])


def sim3_apply_to_pose(S: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """A camera pose moved by a Sim(3) of the world: the camera's centre maps as a point, its axes turn by R (the
    result is rigid: a similarity changes the scale of the world, not of the camera)."""
    R, t, s = sim3_to_parts(S)
    out = np.eye(4)
    out[:3, :3] = orthonormalize(R @ cam_to_world[:3, :3])
    out[:3, 3] = s * (R @ cam_to_world[:3, 3]) + t
    return out


@dataclass(frozen=True, eq=False)
class LoopCorrection:
    """Loop closure moved keyframes: ``transforms`` maps keyframe id -> 4x4 Sim(3) from the world the map has to the
    corrected one (``X' = s R X + t``); the mapper moves each keyframe's view (:func:`sim3_apply_to_pose`), its
    depth points and the Gaussians anchored to it. ``loop``: the loop's number (1 for the first)."""

    transforms: Mapping[int, np.ndarray]
    loop: int = 0

    def __post_init__(self):
        tf = {int(k): _frozen(check_sim3(v, f"LoopCorrection.transforms[{k}]"))
              for k, v in dict(self.transforms).items()}
        object.__setattr__(self, "transforms", MappingProxyType(tf))
        object.__setattr__(self, "loop", int(self.loop))

    def __reduce__(self):
        return (LoopCorrection, (dict(self.transforms), self.loop))


@dataclass(frozen=True)
class Stop:
    """End of the message stream. ``refine``: run the final refinement before stopping (false when the run was
    interrupted: the outputs of what was done are written at once)."""

    refine: bool = True


MapperMessage = Union[KeyframeMessage, PoseUpdate, PointsMessage, LoopCorrection, Stop]
