"""Place recognition on keyframes (docs/loop.md, "Place recognition and verification").

Every keyframe that reaches the loop closer becomes a :class:`KeyframeFeatures`: ORB keypoints and descriptors
(OpenCV) on its gray image, each keypoint with the inverse depth of the nearest DSO point within
``loop.depth_radius_px`` (LDSO puts its features on DSO's points; here the features are OpenCV's and borrow the
points' depths, so a keypoint with no DSO point near it has no depth, NaN), the gray image itself and DSO's points
(the photometric check of :mod:`mgso.loop.verify` tracks against them).

:class:`PlaceDatabase` keeps every keyframe's features and answers "which old keyframes look like this one": exact
brute-force Hamming matching (``cv2.BFMatcher``, two nearest neighbours, Lowe's ratio test ``loop.match_ratio``)
against every stored keyframe; those with at least ``loop.min_matches`` matches are candidates, most matches first,
at most ``loop.max_candidates``, plus the ids the caller names in ``extra`` (the closer's candidates from pose
proximity), never the ``exclude`` ids (the active window and its neighbours). Nothing is downloaded and nothing is
learned: exact matching against 500 keyframes of 1000 features costs what docs/loop.md measures.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Collection

import cv2
import numpy as np
from scipy.spatial import cKDTree

from mgso.camera import PinholeCamera
from mgso.config import LoopConfig

__all__ = ["KeyframeFeatures", "Candidate", "PlaceDatabase", "extract_features", "to_gray", "ratio_matches"]


@dataclass(frozen=True, eq=False)
class KeyframeFeatures:
    """What place recognition and verification keep of a keyframe (arrays read-only).

    ``keypoints (N, 2)`` float pixels, ``descriptors (N, 32)`` uint8 ORB, ``idepths (N,)`` inverse depth of the
    nearest DSO point within ``depth_radius_px`` (NaN when none), ``gray (H, W)`` uint8, ``points_uv (M, 2)`` and
    ``points_idepth (M,)``: DSO's points of the keyframe (finite, positive inverse depths only)."""

    keyframe_id: int
    camera: PinholeCamera
    keypoints: np.ndarray
    descriptors: np.ndarray
    idepths: np.ndarray
    gray: np.ndarray
    points_uv: np.ndarray
    points_idepth: np.ndarray

    @property
    def num_features(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def num_with_depth(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.idepths)))


@dataclass(frozen=True)
class Candidate:
    """An old keyframe that may show the same place: ``matches`` ratio-test ORB matches with the query,
    ``score`` = matches / the smaller of the two feature counts (0-1); ``by_pose``: it came from ``extra``."""

    keyframe_id: int
    matches: int
    score: float
    by_pose: bool = False


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB float in [0, 1] (a :class:`~mgso.mapping.messages.KeyframeMessage`'s image), (H, W) float
    0-255 or uint8 -> (H, W) uint8 gray (OpenCV's luma weights, as the readers make the odometry's gray)."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        if np.issubdtype(img.dtype, np.floating):
            img = np.clip(np.nan_to_num(img) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_RGB2GRAY)
    if img.ndim == 2:
        if img.dtype == np.uint8:
            return img.copy()
        return np.clip(np.nan_to_num(img.astype(np.float64)) + 0.5, 0, 255).astype(np.uint8)
    raise ValueError(f"expected an (H, W, 3) RGB or (H, W) gray image, got shape {img.shape}")


def extract_features(keyframe_id: int, image: np.ndarray, camera, points_uv: np.ndarray, idepths: np.ndarray,
                     settings: LoopConfig) -> KeyframeFeatures:
    """ORB features of a keyframe with DSO's depths (see the module text).

    ``image``: the keyframe's RGB in [0, 1] (or gray, :func:`to_gray`), in the odometry's image geometry;
    ``camera``: its pinhole intrinsics; ``points_uv (M, 2)`` pixels and ``idepths (M,)`` inverse depths of DSO's
    points (non-finite or non-positive ones are dropped). A keypoint takes the inverse depth of the nearest point
    within ``settings.depth_radius_px`` pixels, NaN when there is none. Raises ``ValueError`` (naming the keyframe)
    on an image that does not match the camera."""
    cam = camera if isinstance(camera, PinholeCamera) else PinholeCamera(
        camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    gray = to_gray(image)
    if gray.shape != (cam.height, cam.width):
        raise ValueError(f"keyframe {keyframe_id}: image is {gray.shape[1]}x{gray.shape[0]}, its camera "
                         f"{cam.width}x{cam.height}")
    uv = np.asarray(points_uv, dtype=np.float64).reshape(-1, 2)
    idp = np.asarray(idepths, dtype=np.float64).reshape(-1)
    if len(uv) != len(idp):
        raise ValueError(f"keyframe {keyframe_id}: {len(uv)} DSO points but {len(idp)} inverse depths")
    ok = np.isfinite(idp) & (idp > 0) & np.all(np.isfinite(uv), axis=1)
    uv, idp = uv[ok], idp[ok]
    orb = cv2.ORB_create(nfeatures=int(settings.orb_features))
    kps, desc = orb.detectAndCompute(gray, None)
    if desc is None or not kps:
        kp = np.zeros((0, 2))
        desc = np.zeros((0, 32), np.uint8)
    else:
        kp = np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2)
    kid = np.full(len(kp), np.nan)
    if len(kp) and len(uv):
        dist, idx = cKDTree(uv).query(kp, k=1, distance_upper_bound=float(settings.depth_radius_px))
        near = np.isfinite(dist)
        kid[near] = idp[idx[near]]
    return KeyframeFeatures(int(keyframe_id), cam, _readonly(kp), _readonly(desc.astype(np.uint8)),
                            _readonly(kid), _readonly(gray), _readonly(uv), _readonly(idp))


def ratio_matches(query: np.ndarray, train: np.ndarray, ratio: float, matcher=None) -> list[tuple[int, int, int]]:
    """Lowe's ratio-test matches ``(query index, train index, Hamming distance)`` of ORB descriptors: the nearest
    train descriptor of each query one, kept when its distance is below ``ratio`` x the second nearest's. Empty when
    either side has fewer than 2 descriptors."""
    if len(query) < 1 or len(train) < 2:
        return []
    bf = matcher or cv2.BFMatcher(cv2.NORM_HAMMING)
    out = []
    for pair in bf.knnMatch(query, train, k=2):
        if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance:
            out.append((pair[0].queryIdx, pair[0].trainIdx, int(pair[0].distance)))
    return out


class PlaceDatabase:
    """Every keyframe's features, queried by appearance (see the module text). Thread-safe: the closer may add
    from one thread and query from another."""

    def __init__(self):
        self._features: dict[int, KeyframeFeatures] = {}
        self._lock = threading.Lock()
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def __len__(self) -> int:
        return len(self._features)

    def __contains__(self, keyframe_id) -> bool:
        return int(keyframe_id) in self._features

    def get(self, keyframe_id: int) -> KeyframeFeatures | None:
        return self._features.get(int(keyframe_id))

    def add(self, features: KeyframeFeatures) -> None:
        """Store (or replace) a keyframe's features."""
        with self._lock:
            self._features[int(features.keyframe_id)] = features

    def remove(self, keyframe_id: int) -> None:
        with self._lock:
            self._features.pop(int(keyframe_id), None)

    def query(self, features: KeyframeFeatures, exclude: Collection[int], settings: LoopConfig,
              extra: Collection[int] = ()) -> list[Candidate]:
        """The stored keyframes that may show the place ``features`` shows: those with at least
        ``settings.min_matches`` ratio-test matches, most matches first, at most ``settings.max_candidates``; then
        the ``extra`` ids (pose proximity) that are stored and not already among them, whatever their matches
        (``by_pose``), most matches first. ``exclude`` ids (and the query's own id) never come back."""
        skip = {int(k) for k in exclude} | {int(features.keyframe_id)}
        want = {int(k) for k in extra} - skip
        with self._lock:
            stored = [f for k, f in self._features.items() if k not in skip]
        n_q = features.num_features
        scored = []
        for f in stored:
            m = len(ratio_matches(features.descriptors, f.descriptors, settings.match_ratio, self._matcher))
            denom = min(n_q, f.num_features)
            scored.append(Candidate(f.keyframe_id, m, m / denom if denom else 0.0))
        scored.sort(key=lambda c: (-c.matches, c.keyframe_id))
        chosen = [c for c in scored if c.matches >= settings.min_matches][: settings.max_candidates]
        have = {c.keyframe_id for c in chosen}
        chosen += [Candidate(c.keyframe_id, c.matches, c.score, by_pose=True) for c in scored
                   if c.keyframe_id in want and c.keyframe_id not in have]
        return chosen
