"""Place recognition on keyframes (docs/loop.md, "Place recognition and verification").

Every keyframe that reaches the loop closer becomes a :class:`KeyframeFeatures`: ORB descriptors (OpenCV) at
two kinds of keypoints on its gray image, each with an inverse depth from DSO's points:

- **DSO's points themselves** (LDSO puts its features on DSO's points): the ``loop.orb_features`` most corner-like
  (Shi-Tomasi score; DSO also selects edge pixels, whose descriptors match poorly), oriented by ORB's intensity
  centroid; each carries its own point's depth. Verification needs matches with a depth in both keyframes: with
  OpenCV's corners alone (borrowing the depth of a DSO point within 2 pixels) only 19 % of the features of a
  7-Scenes keyframe had one and true revisits kept 0-9 such matches (docs/loop.md).
- **OpenCV's own ORB corners** (up to half as many, over its scale pyramid) where no chosen point lies within
  ``loop.depth_radius_px``: appearance where DSO has no point; each takes the inverse depth of the nearest DSO point
  within that radius, NaN when none.

So every keypoint's inverse depth is that of the nearest DSO point within ``depth_radius_px`` (its own, for the
first kind), NaN beyond. The gray image and DSO's points are kept too (the photometric check of
:mod:`mgso.loop.verify` tracks against them).

:class:`PlaceDatabase` keeps every keyframe's features and answers "which old keyframes look like this one": exact
brute-force Hamming matching (``cv2.BFMatcher``, two nearest neighbours, Lowe's ratio test ``loop.match_ratio``)
against every stored keyframe; those with at least ``loop.min_matches`` matches are candidates, most matches first,
at most ``loop.max_candidates``, plus the ids the caller names in ``extra`` (the closer's candidates from pose
proximity), never the ``exclude`` ids (the active window and its neighbours).

Exact matching costs about 3.3 ms a stored keyframe of 1000 features against a query of 1000 on one core (0.34 s a
query against 100, 1.7 s against 500: docs/loop.md), so beyond :data:`PREFILTER_ABOVE` stored keyframes a prefilter
picks which ones are matched exactly: a bag of binary words (:class:`BinaryVocabulary`, LDSO's DBoW3 idea without
its downloaded vocabulary) learned from the running sequence's own descriptors by k-majority clustering once the
database holds :data:`PREFILTER_ABOVE` keyframes, and learned again each time it has doubled since; each keyframe is
a tf-idf histogram over its words, and the :data:`PREFILTER_KEEP` stored keyframes most similar to the query
(cosine), plus the ``extra`` ids, go on to the exact matching. Nothing is downloaded at run time.
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

__all__ = ["KeyframeFeatures", "Candidate", "PlaceDatabase", "BinaryVocabulary", "extract_features", "to_gray",
           "ratio_matches", "PREFILTER_ABOVE", "PREFILTER_KEEP", "VOCABULARY_WORDS"]

#: PlaceDatabase's prefilter when built without settings (the closer passes loop.prefilter_above, prefilter_keep and
#: vocabulary_words, whose defaults are 20, 10 and 512: docs/loop.md): exact matching against more than this many
#: stored keyframes costs more than 0.2 s a query (3.3 ms each, measured) ...
PREFILTER_ABOVE = 60
#: ... so only this many, the most similar by bag of words, are matched exactly (about 0.1 s) ...
PREFILTER_KEEP = 30
#: ... with a vocabulary of this many binary words learned from the sequence (assigning 1000 descriptors costs about
#: 1.5 ms)
VOCABULARY_WORDS = 512


@dataclass(frozen=True, eq=False)
class KeyframeFeatures:
    """What place recognition and verification keep of a keyframe (arrays read-only).

    ``keypoints (N, 2)`` float pixels (DSO's points first, then OpenCV's corners), ``descriptors (N, 32)`` uint8
    ORB, ``idepths (N,)`` inverse depth of the nearest DSO point within ``depth_radius_px`` (NaN when none),
    ``gray (H, W)`` uint8, ``points_uv (M, 2)`` and ``points_idepth (M,)``: DSO's points of the keyframe (finite,
    positive inverse depths only)."""

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
    """(H, W, 3) RGB float in [0, 1] (a :class:`~mgso.messages.KeyframeMessage`'s image), (H, W) float
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
    """ORB features of a keyframe with DSO's depths (see the module text): descriptors at up to
    ``settings.orb_features`` of DSO's points, then OpenCV's corners (up to half as many) not within
    ``settings.depth_radius_px`` of those.

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
    n = int(settings.orb_features)
    # descriptors on DSO's points (LDSO): the most corner-like up to orb_features, each with its own depth
    sel, desc_p = _descriptors_at(gray, uv, n)
    # OpenCV's own corners (up to half as many more) where no chosen point is near: appearance where DSO has none
    orb = cv2.ORB_create(nfeatures=max(1, n // 2))
    kps, desc_c = orb.detectAndCompute(gray, None)
    kp_c = np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2) if kps else np.zeros((0, 2))
    desc_c = np.zeros((0, 32), np.uint8) if desc_c is None or not kps else desc_c
    radius = float(settings.depth_radius_px)
    if len(kp_c) and len(sel):
        d_sel, _ = cKDTree(uv[sel]).query(kp_c, k=1, distance_upper_bound=radius)
        keep = ~np.isfinite(d_sel)
        kp_c, desc_c = kp_c[keep], desc_c[keep]
    id_c = np.full(len(kp_c), np.nan)
    if len(kp_c) and len(uv):
        dist, idx = cKDTree(uv).query(kp_c, k=1, distance_upper_bound=radius)
        near = np.isfinite(dist)
        id_c[near] = idp[idx[near]]
    kp = np.concatenate([uv[sel], kp_c])
    desc = np.concatenate([desc_p, desc_c]).astype(np.uint8)
    kid = np.concatenate([idp[sel], id_c])
    return KeyframeFeatures(int(keyframe_id), cam, _readonly(kp), _readonly(desc), _readonly(kid), _readonly(gray),
                            _readonly(uv), _readonly(idp))


_HALF_PATCH = 15  # ORB's orientation patch radius (HALF_PATCH_SIZE)
_pv, _pu = np.mgrid[-_HALF_PATCH:_HALF_PATCH + 1, -_HALF_PATCH:_HALF_PATCH + 1]
_circle = _pu ** 2 + _pv ** 2 <= _HALF_PATCH ** 2
_PATCH_U, _PATCH_V = _pu[_circle].astype(np.float64), _pv[_circle].astype(np.float64)


def _descriptors_at(gray: np.ndarray, uv: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """ORB descriptors at given pixels: the ``n`` with the largest Shi-Tomasi score (the most corner-like; DSO also
    selects edges, whose descriptors match poorly), oriented by ORB's intensity centroid (OpenCV's ``compute`` keeps a
    given keypoint's angle). Returns (indices into ``uv`` that got one, descriptors (K, 32)); pixels closer to the
    border than ORB's patch get none."""
    h, w = gray.shape
    if len(uv) == 0 or n <= 0:
        return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
    x = np.floor(uv[:, 0] + 0.5).astype(np.int64)
    y = np.floor(uv[:, 1] + 0.5).astype(np.int64)
    m = _HALF_PATCH + 1
    idx = np.flatnonzero((x >= m) & (y >= m) & (x < w - m) & (y < h - m))
    if len(idx) > n:
        score = cv2.cornerMinEigenVal(gray, 5)[y[idx], x[idx]]
        idx = np.sort(idx[np.argsort(-score, kind="stable")[:n]])
    if len(idx) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
    patch = gray[y[idx, None] + _PATCH_V.astype(np.int64)[None], x[idx, None] + _PATCH_U.astype(np.int64)[None]]
    patch = patch.astype(np.float64)
    angle = np.degrees(np.arctan2(patch @ _PATCH_V, patch @ _PATCH_U)) % 360.0
    kps = [cv2.KeyPoint(float(uv[i, 0]), float(uv[i, 1]), 31.0, float(a), 0.0, 0, j)
           for j, (i, a) in enumerate(zip(idx, angle))]
    kps, desc = cv2.ORB_create().compute(gray, kps)
    if desc is None or not kps:
        return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
    return idx[np.array([k.class_id for k in kps], dtype=np.int64)], desc


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


def _nearest_word(descriptors: np.ndarray, words: np.ndarray) -> np.ndarray:
    _, idx = cv2.batchDistance(descriptors, words, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=1)
    return idx.reshape(-1).astype(np.int64)


class BinaryVocabulary:
    """A flat vocabulary of binary words (``words (K, 32)`` uint8) with inverse document frequencies ``idf (K,)``;
    :meth:`bow` turns a keyframe's ORB descriptors into an L2-normalised tf-idf histogram (Galvez-Lopez and Tardos'
    bag of binary words, flat instead of a tree: a few hundred words are cheap to search exhaustively)."""

    def __init__(self, words: np.ndarray, idf: np.ndarray):
        self.words = _readonly(np.asarray(words, dtype=np.uint8))
        self.idf = _readonly(np.asarray(idf, dtype=np.float64))

    @classmethod
    def learn(cls, descriptors: list[np.ndarray], num_words: int = VOCABULARY_WORDS, iterations: int = 6,
              max_samples: int = 20000, seed: int = 0) -> "BinaryVocabulary":
        """k-majority clustering (k-means for Hamming space: each word the bitwise majority of its descriptors) of up
        to ``max_samples`` descriptors drawn from ``descriptors`` (one array per keyframe); idf over those
        keyframes. Deterministic for a seed."""
        return _learn(descriptors, num_words, iterations, max_samples, seed)[0]

    def counts(self, descriptors: np.ndarray) -> np.ndarray:
        """How many of ``descriptors`` fall on each word (K,)."""
        if not len(descriptors):
            return np.zeros(len(self.words))
        return np.bincount(_nearest_word(descriptors, self.words), minlength=len(self.words)).astype(np.float64)

    def bow_from_counts(self, counts: np.ndarray) -> np.ndarray:
        total = counts.sum()
        v = counts / total * self.idf if total > 0 else np.zeros(len(self.words))
        nrm = np.linalg.norm(v)
        return v / nrm if nrm > 0 else v

    def bow(self, descriptors: np.ndarray) -> np.ndarray:
        """L2-normalised tf-idf histogram (K,) of a keyframe's descriptors (zeros when it has none)."""
        return self.bow_from_counts(self.counts(descriptors))


def _learn(descriptors: list[np.ndarray], num_words: int, iterations: int, max_samples: int,
           seed: int) -> tuple[BinaryVocabulary, list[np.ndarray]]:
    """:meth:`BinaryVocabulary.learn`, also returning each keyframe's word counts (the idf needs them)."""
    rng = np.random.default_rng(seed)
    allx = np.concatenate([d for d in descriptors if len(d)]) if any(len(d) for d in descriptors) else \
        np.zeros((0, 32), np.uint8)
    if len(allx) > max_samples:
        allx = allx[np.sort(rng.choice(len(allx), max_samples, replace=False))]
    uniq = np.unique(allx, axis=0)
    k = int(min(num_words, len(uniq)))
    if k == 0:
        raise ValueError("BinaryVocabulary.learn: no descriptors")
    words = uniq[np.sort(rng.choice(len(uniq), k, replace=False))].copy()
    for _ in range(iterations):
        assign = _nearest_word(allx, words)
        order = np.argsort(assign, kind="stable")
        bits = np.unpackbits(allx[order], axis=1).astype(np.int32)
        counts = np.bincount(assign, minlength=k)
        used = np.flatnonzero(counts)
        starts = np.concatenate([[0], np.cumsum(counts[used])[:-1]])
        ones = np.add.reduceat(bits, starts, axis=0)
        new = words.copy()
        new[used] = np.packbits(2 * ones > counts[used][:, None], axis=1)
        if np.array_equal(new, words):
            break
        words = new
    vocab = BinaryVocabulary(words, np.zeros(k))
    counts = [vocab.counts(d) for d in descriptors]
    df = np.sum([c > 0 for c in counts], axis=0) if counts else np.zeros(k)
    idf = np.log(max(len(descriptors), 1) / np.maximum(df, 1.0)) + 1e-3
    return BinaryVocabulary(words, idf), counts


class PlaceDatabase:
    """Every keyframe's features, queried by appearance (see the module text). Thread-safe: the closer may add
    from one thread and query from another.

    ``prefilter_above``: stored keyframes beyond which the bag-of-words prefilter chooses which are matched exactly
    (0 = never: always exact); ``prefilter_keep``: how many it keeps; ``vocabulary_words``: its vocabulary's size."""

    def __init__(self, prefilter_above: int = PREFILTER_ABOVE, prefilter_keep: int = PREFILTER_KEEP,
                 vocabulary_words: int = VOCABULARY_WORDS):
        self._features: dict[int, KeyframeFeatures] = {}
        self._lock = threading.Lock()
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.prefilter_above = int(prefilter_above)
        self.prefilter_keep = max(1, int(prefilter_keep))
        self.vocabulary_words = int(vocabulary_words)
        self.vocabulary: BinaryVocabulary | None = None
        self._learned_at = 0
        self._bows: dict[int, np.ndarray] = {}
        self.last_exact = 0  # stored keyframes matched exactly by the last query (for tests and profiles)

    def __len__(self) -> int:
        return len(self._features)

    def __contains__(self, keyframe_id) -> bool:
        return int(keyframe_id) in self._features

    def get(self, keyframe_id: int) -> KeyframeFeatures | None:
        return self._features.get(int(keyframe_id))

    def add(self, features: KeyframeFeatures) -> None:
        """Store (or replace) a keyframe's features; learns the prefilter's vocabulary when the database reaches
        ``prefilter_above`` keyframes and again whenever it has doubled since."""
        kid = int(features.keyframe_id)
        with self._lock:
            self._features[kid] = features
            n = len(self._features)
            if self.prefilter_above > 0 and n >= self.prefilter_above and n >= 2 * self._learned_at:
                ids = sorted(self._features)
                self.vocabulary, counts = _learn([self._features[k].descriptors for k in ids],
                                                 self.vocabulary_words, 6, 20000, 0)
                self._bows = {k: self.vocabulary.bow_from_counts(c) for k, c in zip(ids, counts)}
                self._learned_at = n
            elif self.vocabulary is not None:
                self._bows[kid] = self.vocabulary.bow(features.descriptors)

    def remove(self, keyframe_id: int) -> None:
        with self._lock:
            self._features.pop(int(keyframe_id), None)
            self._bows.pop(int(keyframe_id), None)

    def query(self, features: KeyframeFeatures, exclude: Collection[int], settings: LoopConfig,
              extra: Collection[int] = ()) -> list[Candidate]:
        """The stored keyframes that may show the place ``features`` shows: those with at least
        ``settings.min_matches`` ratio-test matches, most matches first, at most ``settings.max_candidates``; then
        the ``extra`` ids (pose proximity) that are stored and not already among them, whatever their matches
        (``by_pose``), most matches first. ``exclude`` ids (and the query's own id) never come back. With the
        prefilter on, only the ``prefilter_keep`` most similar by bag of words (and the ``extra`` ids) are matched."""
        skip = {int(k) for k in exclude} | {int(features.keyframe_id)}
        want = {int(k) for k in extra} - skip
        with self._lock:
            stored = [f for k, f in self._features.items() if k not in skip]
            vocab, bows = self.vocabulary, dict(self._bows)
        if vocab is not None and len(stored) > self.prefilter_keep:
            q = vocab.bow(features.descriptors)
            sims = np.array([float(bows[f.keyframe_id] @ q) if f.keyframe_id in bows else np.inf for f in stored])
            order = sorted(range(len(stored)), key=lambda i: (-sims[i], stored[i].keyframe_id))
            top = set(order[: self.prefilter_keep])
            stored = [f for i, f in enumerate(stored) if i in top or f.keyframe_id in want]
        self.last_exact = len(stored)
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
