"""Posed training views of the Gaussian map, and the policies that choose which one to train on next.

A :class:`TrainView` is one posed image (a keyframe in MGSO, a training frame in ``mgso fit``): RGB in [0, 1], the
pinhole camera it was taken with (:class:`mgso.camera.PinholeCamera`, pixel centres at integer coordinates),
``world_to_cam``, an optional per-pixel weight mask, and the per-view state training keeps: the affine exposure
``(a, b)`` (the loss compares ``exp(a) * render + b`` with the image) with its Adam moments, the optional pose
refinement's Adam moments, and how often the view was used.

Who may change what (the owner says it next to the field, DSO's habit):

- ``image``, ``camera``, ``mask``: fixed at construction.
- ``world_to_cam``: :meth:`ViewSet.set_pose` (MGSO's mapper, when the window refines a keyframe) and the trainer's
  pose refinement (off by default). Nobody else.
- ``exposure`` and its moments: :meth:`ViewSet.set_exposure` (e.g. DSO's affine brightness) and the trainer when it
  learns exposures.
- ``uses``: the trainer, once per training step on the view (the pyramid schedule and the samplers read it).

Gaussian-pyramid levels (Photo-SLAM's coarse-to-fine training) are made on demand by 2x2 averaging, the project's
pyramid rule (``PinholeCamera.scaled(0.5)``: ``cx' = (cx + 0.5) / 2 - 0.5``, sizes floored; docs/datasets.md), and
kept with the view.

Samplers (:class:`ViewSampler`): ``next_view(views) -> view_id``. :class:`RandomEpochSampler` is 3DGS's: a random
permutation of all views, drawn again when used up (``mgso fit``). :class:`LeastUsedSampler` picks among the views
used least, and the newest view more often (the shape of MGSO's keyframe choice).
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Iterator, Protocol

import numpy as np
import warp as wp

from mgso.camera import PinholeCamera
from mgso.geometry import se3_inverse

__all__ = ["TrainView", "ViewSet", "ViewSampler", "RandomEpochSampler", "LeastUsedSampler", "NewestOrRandomSampler",
           "AdamState",
           "downsample_2x2"]

log = logging.getLogger(__name__)


@dataclass
class AdamState:
    """Adam moments of a small per-view parameter vector (exposure (a, b), pose delta (v, w))."""

    m: np.ndarray
    v: np.ndarray
    steps: int = 0

    @classmethod
    def zeros(cls, n: int) -> "AdamState":
        return cls(np.zeros(n), np.zeros(n), 0)

    def update(self, grad: np.ndarray, lr: np.ndarray | float, beta1: float = 0.9, beta2: float = 0.999,
               eps: float = 1e-15) -> np.ndarray:
        """One torch.optim.Adam step with bias correction; returns the increment to add to the parameter."""
        g = np.asarray(grad, dtype=np.float64)
        self.steps += 1
        self.m = beta1 * self.m + (1.0 - beta1) * g
        self.v = beta2 * self.v + (1.0 - beta2) * g * g
        bc1 = 1.0 - beta1 ** self.steps
        bc2 = 1.0 - beta2 ** self.steps
        return -np.asarray(lr, dtype=np.float64) / bc1 * self.m / (np.sqrt(self.v) / np.sqrt(bc2) + eps)


def downsample_2x2(image: np.ndarray) -> np.ndarray:
    """Average 2x2 blocks (an odd last row / column is dropped): one level of the project's image pyramid."""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    a = image[: 2 * h, : 2 * w].astype(np.float32)
    return (0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2])).astype(np.float32)


class TrainView:
    """One posed image the map trains on.

    ``image``: (H, W, 3) float RGB in [0, 1]; ``camera``: its pinhole camera (size must match); ``world_to_cam``:
    4x4 rigid transform (float64); ``mask``: optional (H, W) weights >= 0 (0 = pixel ignored by the loss, e.g.
    black undistortion borders); ``exposure``: initial affine brightness (a, b) of this view (``exp(a) * render +
    b`` is compared with the image); ``view_id``: the key in a :class:`ViewSet` (frame index in ``mgso fit``,
    keyframe id in MGSO); ``timestamp`` and ``name`` are for messages and outputs.
    """

    def __init__(self, view_id: int, image: np.ndarray, camera: PinholeCamera, world_to_cam: np.ndarray, *,
                 mask: np.ndarray | None = None, exposure: tuple[float, float] = (0.0, 0.0),
                 timestamp: float | None = None, name: str = ""):
        img = np.asarray(image)
        where = name or f"view {view_id}"
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"{where}: image must be (H, W, 3) RGB, got shape {img.shape}")
        if not np.issubdtype(img.dtype, np.floating):
            raise ValueError(f"{where}: image must be float RGB in [0, 1], got {img.dtype} (divide uint8 by 255)")
        if (img.shape[1], img.shape[0]) != (camera.width, camera.height):
            raise ValueError(f"{where}: image is {img.shape[1]}x{img.shape[0]} but its camera is "
                             f"{camera.width}x{camera.height}")
        if not np.all(np.isfinite(img)):
            raise ValueError(f"{where}: image has non-finite values")
        if mask is not None:
            mask = np.ascontiguousarray(mask, dtype=np.float32)
            if mask.shape != img.shape[:2]:
                raise ValueError(f"{where}: mask must be {img.shape[:2]}, got {mask.shape}")
            if not np.all(np.isfinite(mask)) or np.any(mask < 0):
                raise ValueError(f"{where}: mask weights must be finite and >= 0")
        self._set(view_id, np.ascontiguousarray(img, dtype=np.float32), camera, mask, world_to_cam, exposure,
                  timestamp, name)

    def _set(self, view_id, image, camera, mask, world_to_cam, exposure, timestamp, name) -> None:
        self.view_id = int(view_id)
        self.name = name or f"view {view_id}"
        self.timestamp = timestamp
        self.image = image
        self.camera = camera
        self.mask = mask
        # ONLY changed by ViewSet.set_pose and the trainer's pose refinement.
        self.world_to_cam = _check_pose(world_to_cam, self.name)
        # ONLY changed by ViewSet.set_exposure and the trainer (learned exposure).
        self.exposure = np.array([float(exposure[0]), float(exposure[1])], dtype=np.float64)
        self.exposure_adam = AdamState.zeros(2)
        # ONLY changed by the trainer's pose refinement.
        self.pose_adam = AdamState.zeros(6)
        # Set once by the owner: the trainer's pose refinement leaves this view where it is (the map's gauge: MGSO's
        # mapper fixes its first keyframe, as the odometry does).
        self.fixed_pose = False
        # ONLY changed by the trainer: training steps run on this view.
        self.uses = 0
        # Optional sparse depth of this view: (M, 2) pixels and (M,) camera z (MGSO: the odometry's points seen by
        # the keyframe); set once by the owner (the mapper) before training, read by the trainer's depth term.
        self.depth_uv: np.ndarray | None = None
        self.depth_z: np.ndarray | None = None
        self._levels: dict[int, tuple[np.ndarray, PinholeCamera, np.ndarray | None]] = (
            {} if image is None else {0: (image, camera, mask)})
        self._device_arrays: dict[tuple[int, str], tuple[wp.array, wp.array | None]] = {}

    @classmethod
    def pose_only(cls, view_id: int, camera: PinholeCamera, world_to_cam: np.ndarray, *,
                  exposure: tuple[float, float] = (0.0, 0.0), timestamp: float | None = None, name: str = "",
                  fixed_pose: bool = False, uses: int = 0) -> "TrainView":
        """A view without its image: the pose, exposure and camera of a keyframe whose image stayed with the mapper
        that trained on it (a map brought back from the mapper's process, :mod:`mgso.mapping.process`). It can be
        rendered from and moved, not trained on (:meth:`level` raises)."""
        v = cls.__new__(cls)
        v._set(view_id, None, camera, None, world_to_cam, exposure, timestamp, name)
        v.fixed_pose = bool(fixed_pose)
        v.uses = int(uses)
        return v

    @property
    def cam_to_world(self) -> np.ndarray:
        return se3_inverse(self.world_to_cam)

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return self.cam_to_world[:3, 3]

    @property
    def size(self) -> tuple[int, int]:
        return self.camera.width, self.camera.height

    def level(self, level: int) -> tuple[np.ndarray, PinholeCamera, np.ndarray | None]:
        """(image, camera, mask) at pyramid ``level`` (0 = full resolution; each level halves, 2x2 averages)."""
        level = int(level)
        if level < 0:
            raise ValueError(f"pyramid level must be >= 0, got {level}")
        if self.image is None:
            raise ValueError(f"{self.name}: a view without its image (TrainView.pose_only) cannot be trained on")
        if level not in self._levels:
            img, cam, mask = self.level(level - 1)
            if cam.width < 2 or cam.height < 2:
                raise ValueError(f"{self.name}: image {cam.width}x{cam.height} is too small for pyramid level "
                                 f"{level}")
            self._levels[level] = (downsample_2x2(img), cam.scaled(0.5),
                                   None if mask is None else downsample_2x2(mask[..., None])[..., 0])
        return self._levels[level]

    def set_depth_points(self, uv: np.ndarray, z: np.ndarray) -> None:
        """Sparse depth of the view (``uv`` (M, 2) level-0 pixels, ``z`` (M,) camera z > 0), for the trainer's depth
        term (``mapping.train.depth_weight``); points outside the image or with a bad depth are dropped."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        z = np.asarray(z, np.float64).reshape(-1)
        ok = (np.isfinite(z) & (z > 0) & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > -0.5) & (uv[:, 1] > -0.5)
              & (uv[:, 0] < self.camera.width - 0.5) & (uv[:, 1] < self.camera.height - 0.5))
        self.depth_uv, self.depth_z = uv[ok], z[ok]

    def device_arrays(self, level: int, device: str) -> tuple[wp.array, wp.array | None]:
        """Warp arrays of the image (``vec3 [H, W]``) and mask (``float32 (H, W)``) at ``level`` on ``device``:
        zero-copy views on the CPU, one upload per level on a GPU (kept)."""
        key = (int(level), str(device))
        if key not in self._device_arrays:
            img, _, mask = self.level(level)
            is_cpu = wp.get_device(device).is_cpu
            a = wp.array(img, dtype=wp.vec3, device=device, copy=not is_cpu)
            m = None if mask is None else wp.array(mask, dtype=wp.float32, device=device, copy=not is_cpu)
            self._device_arrays[key] = (a, m)
        return self._device_arrays[key]

    def __repr__(self) -> str:
        return (f"TrainView(id={self.view_id}, {self.camera.width}x{self.camera.height}, uses={self.uses}, "
                f"exposure=({self.exposure[0]:.4f}, {self.exposure[1]:.4f}), name={self.name!r})")


def _check_pose(world_to_cam, where: str) -> np.ndarray:
    T = np.asarray(world_to_cam, dtype=np.float64)
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise ValueError(f"{where}: world_to_cam must be 4x4 (or 3x4), got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{where}: world_to_cam has non-finite entries")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise ValueError(f"{where}: world_to_cam's rotation is not a rotation (orthonormality error "
                         f"{np.abs(R @ R.T - np.eye(3)).max():.2g}, det {np.linalg.det(R):.3f})")
    return T.copy()


class ViewSet:
    """The views the map trains on, in the order they were added (oldest first), keyed by ``view_id``.

    ``version`` counts changes of membership and poses (the trainer recomputes the scene extent when it moves).
    """

    def __init__(self, views=()):
        self._views: OrderedDict[int, TrainView] = OrderedDict()
        self.version = 0
        for v in views:
            self.add(v)

    def add(self, view: TrainView) -> None:
        if view.view_id in self._views:
            raise ValueError(f"ViewSet: a view with id {view.view_id} is already there ({self._views[view.view_id]})")
        self._views[view.view_id] = view
        self.version += 1

    def remove(self, view_id: int) -> TrainView:
        view = self._views.pop(int(view_id))
        self.version += 1
        return view

    def set_pose(self, view_id: int, world_to_cam: np.ndarray) -> None:
        """Replace a view's pose (e.g. the window refined the keyframe). Adam moments of the pose refinement are
        kept: they describe the optimiser's recent steps, not the pose itself."""
        v = self._views[int(view_id)]
        v.world_to_cam = _check_pose(world_to_cam, v.name)
        self.version += 1

    def set_exposure(self, view_id: int, a: float, b: float) -> None:
        """Set a view's affine brightness (``exp(a) * render + b`` is compared with its image)."""
        v = self._views[int(view_id)]
        v.exposure[:] = (float(a), float(b))

    def __getitem__(self, view_id: int) -> TrainView:
        try:
            return self._views[int(view_id)]
        except KeyError:
            raise KeyError(f"ViewSet: no view with id {view_id}") from None

    def __contains__(self, view_id) -> bool:
        return int(view_id) in self._views

    def __len__(self) -> int:
        return len(self._views)

    def __iter__(self) -> Iterator[TrainView]:
        return iter(self._views.values())

    def ids(self) -> list[int]:
        """View ids, oldest first."""
        return list(self._views)

    def camera_centres(self) -> np.ndarray:
        """(V, 3) camera centres in world coordinates, oldest first."""
        return np.array([v.centre for v in self._views.values()]).reshape(-1, 3)


# ------------------------------------------------------------------------------------------------ samplers
class ViewSampler(Protocol):
    """Chooses the view of the next training step. Must return an id present in ``views`` (non-empty). A sampler
    may also have ``observe(view_id, loss, level)``, which :meth:`Trainer.step` calls after each step with the step's
    loss and pyramid level (:class:`NewestOrRandomSampler` weighs its draw by them)."""

    def next_view(self, views: ViewSet) -> int: ...


@dataclass
class RandomEpochSampler:
    """3DGS's choice: a random permutation of every view, drawn again when it is used up, so each view is used once
    per epoch. Views added mid-epoch join the next permutation; removed ones are skipped."""

    seed: int = 0
    rng: np.random.Generator = field(init=False, repr=False)
    _stack: list[int] = field(default_factory=list, init=False, repr=False)

    def __post_init__(self):
        self.rng = np.random.default_rng(self.seed)

    def next_view(self, views: ViewSet) -> int:
        if len(views) == 0:
            raise ValueError("next_view: the view set is empty")
        while True:
            if not self._stack:
                ids = np.array(views.ids())
                self._stack = [int(i) for i in ids[self.rng.permutation(len(ids))]][::-1]
            vid = self._stack.pop()
            if vid in views:
                return vid


@dataclass
class LeastUsedSampler:
    """Least used first, the newest more often (the shape of MGSO's and Photo-SLAM's keyframe choice).

    With probability ``newest_probability`` the newest view is chosen (a fresh keyframe is where the map is
    worst); otherwise one at random among the views with the fewest uses.
    """

    newest_probability: float = 0.2
    seed: int = 0
    rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self):
        if not 0.0 <= self.newest_probability <= 1.0:
            raise ValueError(f"newest_probability must be in [0, 1], got {self.newest_probability}")
        self.rng = np.random.default_rng(self.seed)

    def next_view(self, views: ViewSet) -> int:
        if len(views) == 0:
            raise ValueError("next_view: the view set is empty")
        ids = views.ids()
        if self.rng.random() < self.newest_probability:
            return ids[-1]
        return self._other(views, ids)

    def _other(self, views: ViewSet, ids: list[int]) -> int:
        uses = np.array([views[i].uses for i in ids])
        least = np.flatnonzero(uses == uses.min())
        return ids[int(least[self.rng.integers(len(least))])]


@dataclass
class NewestOrRandomSampler(LeastUsedSampler):
    """The newest view with probability ``newest_probability``, otherwise one drawn uniformly from all views (the
    newest included): every view keeps being trained as long as the map grows (MonoGS trains its window and random
    older keyframes at every mapping step). :class:`LeastUsedSampler` with a fixed number of steps a keyframe gives
    the newest view every step until it has as many uses as the others, so an old view is not trained again before
    the final refinement and the map forgets it (docs/mapping.md)."""

    #: the share of each choice made in proportion to the views' latest losses (0: uniform over all views)
    loss_share: float = 0.0
    _loss: dict = field(default_factory=dict, init=False, repr=False)   # view id -> (pyramid level, loss)
    _level: int = field(default=0, init=False, repr=False)              # the level of the latest step

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.loss_share <= 1.0:
            raise ValueError(f"loss_share must be in [0, 1], got {self.loss_share}")

    def observe(self, view_id: int, loss: float, level: int = 0) -> None:
        """The loss of a step on ``view_id`` at pyramid ``level`` (what :attr:`loss_share` weighs by). Losses are
        compared only at one level (a coarser render has a lower loss): a view without a loss at the latest step's
        level weighs as much as the highest there, so that each view is scored again soon after the level changes,
        and a new view soon after it comes."""
        if math.isfinite(loss):
            self._loss[int(view_id)] = (int(level), float(loss))
            self._level = int(level)

    def other_probabilities(self, ids: list[int]) -> np.ndarray:
        """The chance of each of ``ids`` when the newest is not taken: ``1 - loss_share`` of it uniform, the rest in
        proportion to the latest losses at the latest step's level."""
        n = len(ids)
        if self.loss_share <= 0.0 or n < 2:
            return np.full(n, 1.0 / max(n, 1))
        at = [self._loss.get(i) for i in ids]
        known = [x[1] for x in at if x is not None and x[0] == self._level]
        top = max(known) if known else 1.0
        w = np.array([x[1] if x is not None and x[0] == self._level else top for x in at], np.float64)
        p = (1.0 - self.loss_share) / n + self.loss_share * w / max(float(w.sum()), 1e-30)
        return p / p.sum()

    def _other(self, views: ViewSet, ids: list[int]) -> int:
        if self.loss_share <= 0.0 or len(ids) < 2:
            return ids[int(self.rng.integers(len(ids)))]   # the uniform draw as before (the same random stream)
        return ids[int(self.rng.choice(len(ids), p=self.other_probabilities(ids)))]
