"""Copies of the live map for whoever watches it (a viewer, a progress line), and the requests that ask for them.

The mapper owns its map and changes it on its own thread (or in its own process, :mod:`mgso.mapping.process`).
Nobody else reads the map while it trains. A watcher asks instead, without waiting:

- ``mapper.request_snapshot(max_gaussians)``: at its next safe point (between two training steps, after a message,
  or between frames in the deterministic mode) the mapper copies its map into a :class:`MapSnapshot` and publishes
  it; ``mapper.latest_snapshot()`` returns the newest published one (or ``None``).
- ``mapper.request_render(camera, world_to_cam, exposure)``: the same for a render of the map with mgso's own
  rasteriser; ``mapper.latest_render()`` returns ``(ticket, image)``.

A request made while an earlier one is still open replaces it: requests never queue, so a watcher that asks faster
than the mapper answers costs one copy per safe point at most. :class:`SnapshotBoard` holds the requests and the
answers for one mapper; both sides call it from their own threads.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["MapSnapshot", "RenderRequest", "SnapshotBoard", "snapshot_of"]


@dataclass(frozen=True, eq=False)
class MapSnapshot:
    """A copy of the Gaussian map at one moment (NumPy, float32, activated parameters).

    ``means`` (N, 3) world; ``scales`` (N, 3) standard deviations in world units; ``quats`` (N, 4) unit, w x y z;
    ``opacities`` (N,) in [0, 1]; ``colors`` (N, 3) the degree-0 colour in [0, 1]; ``keyframe_poses``
    camera-to-world (4x4) of the map's training views by keyframe id; ``steps`` training steps so far;
    ``num_gaussians`` the map's size (N is smaller when the request capped it: the most opaque are kept);
    ``time`` ``time.monotonic()`` when it was taken."""

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    keyframe_poses: dict = field(default_factory=dict)
    steps: int = 0
    num_gaussians: int = 0
    time: float = 0.0

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def covariances(self) -> np.ndarray:
        """(N, 3, 3) float32 world covariances ``R diag(s^2) R^T``."""
        q = self.quats.astype(np.float64)
        w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
        R = np.stack([
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
        ], axis=1)
        M = R * self.scales.astype(np.float64)[:, None, :]
        return (M @ np.transpose(M, (0, 2, 1))).astype(np.float32)


def snapshot_of(gmap, views, steps: int, max_gaussians: int | None = None) -> MapSnapshot:
    """A :class:`MapSnapshot` of a :class:`~mgso.mapping.gaussian_map.GaussianMap` and its
    :class:`~mgso.mapping.views.ViewSet`; ``max_gaussians`` keeps the most opaque ones."""
    n = int(gmap.n)
    if n == 0:
        z3 = np.zeros((0, 3), np.float32)
        act = None
    else:
        act = gmap.activated()
    poses = {int(k): np.array(views[k].cam_to_world, dtype=np.float64) for k in views.ids()}
    if act is None:
        return MapSnapshot(z3, z3.copy(), np.zeros((0, 4), np.float32), np.zeros(0, np.float32), z3.copy(),
                           poses, int(steps), 0, time.monotonic())
    keep = slice(None)
    if max_gaussians is not None and n > int(max_gaussians):
        keep = np.sort(np.argpartition(-act.opacities, int(max_gaussians) - 1)[: int(max_gaussians)])
    return MapSnapshot(act.means[keep], act.scales[keep], act.quats[keep], act.opacities[keep],
                       np.clip(act.rgb[keep], 0.0, 1.0), poses, int(steps), n, time.monotonic())


@dataclass(frozen=True, eq=False)
class RenderRequest:
    """A render of the map asked for by a watcher: ``camera`` (a pinhole camera), ``world_to_cam`` (4x4),
    ``exposure`` (a', b') or ``None``; ``ticket`` numbers the requests of one board."""

    ticket: int
    camera: object
    world_to_cam: np.ndarray
    exposure: tuple | None = None


class SnapshotBoard:
    """The open requests and the latest answers of one mapper (thread-safe; see the module doc).

    The watcher's side: :meth:`request_snapshot`, :meth:`latest_snapshot`, :meth:`request_render`,
    :meth:`latest_render`. The mapper's side: :meth:`take_requests` at a safe point, then :meth:`publish_snapshot`
    and :meth:`publish_render` with the answers."""

    def __init__(self):
        self._lock = threading.Lock()
        self._want_snapshot: int | None | bool = False      # False: none asked; else the cap (None: no cap)
        self._render: RenderRequest | None = None
        self._tickets = 0
        self._snapshot: MapSnapshot | None = None
        self._rendered: tuple[int, np.ndarray] | None = None
        self.snapshots_published = 0
        self.renders_published = 0

    # the watcher's side
    def request_snapshot(self, max_gaussians: int | None = None) -> None:
        if max_gaussians is not None and int(max_gaussians) < 1:
            raise ValueError(f"request_snapshot: max_gaussians must be >= 1 or None, got {max_gaussians}")
        with self._lock:
            self._want_snapshot = None if max_gaussians is None else int(max_gaussians)

    def latest_snapshot(self) -> MapSnapshot | None:
        with self._lock:
            return self._snapshot

    def request_render(self, camera, world_to_cam, exposure=None) -> int:
        T = np.array(world_to_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"request_render: world_to_cam must be a finite 4x4 matrix, got shape {T.shape}")
        with self._lock:
            self._tickets += 1
            self._render = RenderRequest(self._tickets, camera, T,
                                         None if exposure is None else (float(exposure[0]), float(exposure[1])))
            return self._tickets

    def latest_render(self) -> tuple[int, np.ndarray] | None:
        with self._lock:
            return self._rendered

    # the mapper's side
    @property
    def pending(self) -> bool:
        """Whether a request is open (a cheap check for the mapper's loop; no lock: a stale answer only delays)."""
        return self._want_snapshot is not False or self._render is not None

    def take_requests(self) -> tuple[bool, int | None, RenderRequest | None]:
        """``(snapshot asked, its cap, render request)``, and the requests are closed."""
        with self._lock:
            want, self._want_snapshot = self._want_snapshot, False
            render, self._render = self._render, None
        return want is not False, (None if want is False else want), render

    def publish_snapshot(self, snap: MapSnapshot) -> None:
        with self._lock:
            self._snapshot = snap
            self.snapshots_published += 1

    def publish_render(self, ticket: int, image: np.ndarray) -> None:
        with self._lock:
            self._rendered = (int(ticket), image)
            self.renders_published += 1
