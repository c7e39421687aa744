"""Geometric and photometric verification of a loop candidate (docs/loop.md, "Place recognition and verification").

A wrong loop bends the whole trajectory and the map with it, so a candidate from :mod:`mgso.loop.place` is accepted
only after five checks, each with a threshold of ``loop`` (:class:`~mgso.config.LoopConfig`):

1. **Matches with depth.** ORB descriptors matched both ways with Lowe's ratio test (``match_ratio``), kept when
   mutual and when at least one of the two keypoints has a DSO depth. Pairs with a depth on both sides (3D-3D)
   make and test hypotheses; pairs with one depth can only test one. Fewer than 3 3D-3D pairs, or fewer than
   ``min_inliers`` pairs with a depth in all, cannot pass step 2: rejected as ``"too few matches"``.
2. **Sim(3) RANSAC** (LDSO verifies its candidates by a Sim(3) on the points' depths; monocular scale drifts, so the
   two keyframes' depths differ by an unknown factor). ``ransac_iterations`` hypotheses from 3 random 3D-3D pairs
   each (Umeyama's closed form, :func:`mgso.geometry.umeyama_alignment`); a 3D-3D pair is an inlier when it
   reprojects within ``inlier_px`` in *both* keyframes (the current point mapped into the candidate's image and
   the candidate's into the current one: ORB-SLAM's Sim3Solver test), which a 3D distance would not give: depth
   errors grow with depth, pixels do not lie; a one-sided pair is an inlier when its point reprojects within
   ``inlier_px`` in the other keyframe. The best hypothesis is refitted on its 3D-3D inliers (twice, while that
   adds inliers). Fewer than ``min_inliers`` inliers in all: ``"too few inliers"``; no usable hypothesis
   (collinear or coincident points everywhere): ``"degenerate"``. A look-alike place whose 3D layout differs
   gives matches but no Sim(3) that reprojects them.
3. **Photometric check** (DSO's residual): a :class:`~mgso.tracking.coarse_tracker.TrackingReference` is built from
   the candidate's gray image and its DSO points, their inverse depths multiplied by the Sim(3) scale (the
   candidate's camera shrunk to the current keyframe's scale, so the motion between them is rigid), and the current
   keyframe's image pyramid is tracked against it by DSO's coarse tracker
   (:meth:`~mgso.tracking.coarse_tracker.CoarseTracker.track_levels`, coarse to fine, pose and affine brightness)
   from the RANSAC pose. Rejected when the tracker fails (``"photometric tracking failed"``), when the level-0 RMSE
   ends above ``max_photometric_rmse`` (``"photometric rmse"``) or when fewer than ``min_photometric_inliers`` of
   the reference's level-0 points end within the tracker's cutoff (``"photometric inliers"``). The refined rigid
   motion with the RANSAC scale is the accepted relative Sim(3).
4. **Depth consistency.** The photometric check cannot tell a place from a flat photograph of it: a plane and a
   rigid motion reproduce any view of the photograph (synthetic test: a picture of the room hung in another room,
   seen from 5 directions, passed steps 2 and 3 with 35-91 inliers, RMSE 2.8-3.0 and 60-70 % of the points within
   the cutoff). Only the current
   keyframe's own depths show it: its DSO points, moved by the refined motion into the candidate's camera, must
   land on the candidate's depth map (level 0 of the reference) with the same inverse depth within
   :data:`DEPTH_TOLERANCE`, for at least :data:`MIN_DEPTH_CONSISTENT` of those compared (``"depth
   inconsistent"``), and at least :data:`MIN_DEPTH_COMPARED` must be compared (``"depth unverified"``); the
   settings ``loop.depth_tolerance``, ``loop.min_depth_consistent`` and ``loop.min_depth_compared`` (the module
   constants are their defaults for callers without them).

**The geometry of the current keyframe alone** (``loop.geometry = "current"``, the default; ``"both"`` is the above).
On a real revisit the old keyframe's depths are the loosest of the map (on the out-and-back 7-Scenes recording the
first pass's depths, even its marginalised ones, are uncorrelated with the true structure: docs/loop.md), and the
3D-3D pairs of step 2 disagree beyond any Sim(3). ORB-SLAM and LDSO take the geometry from the well-constrained side:

2'a. **Epipolar check** (``loop.epipolar_check``, on by default; :func:`epipolar_inliers`): every match, with a
    depth or not, against one rigid motion (an essential matrix, RANSAC, ``inlier_px`` from the epipolar lines);
    fewer than ``min_inliers`` matches: ``"too few matches"``, fewer inliers: ``"too few inliers"``. At a new
    viewpoint the matches that carry a depth (the descriptors at DSO's points, projected into the keyframe, not at
    repeatable corners) are the fewest right ones: on TUM freiburg1_rpy's keyframe pairs 5-18 degrees apart, 4 of
    the 24 with a depth are right (median), against 20 among those without one (on ORB's own corners)
    (docs/loop.md). Step 2' then takes the epipolar inliers with a current depth and needs ``min_pnp_inliers`` of
    them (``"too few with depth"``): the consensus is the epipolar check's. Off: PnP on the matches with a current
    depth, ``min_inliers`` of them (``"too few matches"`` before, ``"too few inliers"`` after).
2'. **PnP RANSAC** (:func:`pnp_ransac`, OpenCV's AP3P hypotheses, ``ransac_iterations``, ``inlier_px``) of the
    current keyframe's 3D points (its pairs with a current depth) on the candidate's keypoints: the rigid motion
    into the candidate's camera at the current keyframe's scale. Fewer than ``min_inliers`` (``min_pnp_inliers``
    after the epipolar check): ``"too few inliers"`` (``"too few with depth"``).
    The loop's scale is the median ratio of the candidate's depths to the predicted ones over the inliers that have a
    candidate depth (at least :data:`MIN_SCALE_PAIRS`, else ``"scale unknown"``): one robust number from the
    loose side, where step 2 needed every pair to agree.
3'. **Photometric check the other way** (:func:`photometric_check_from_current`): the tracking reference is the
    current keyframe (its image and its own points), the candidate's image is tracked against it from the PnP pose.
4'. **Depth consistency** of the candidate's points (inverse depths times the scale) against the current keyframe's
    depth map, with the same thresholds. On the out-and-back recording this check refuses every true revisit (their
    old depths agree within 15 % for 4-46 % of the points): off by default (``loop.min_depth_consistent`` 0).

5. **Planar check** (either geometry; ``loop.planar_fraction``, 0 = off): a photograph of the place is a plane seen
   as the current keyframe's 3D scene. :func:`planar_fraction` of each keyframe's DSO points (the largest fraction
   within :data:`PLANE_TOLERANCE` of their depth of one plane); the candidate is rejected (``"planar look-alike"``)
   when its fraction is at least the setting and the current keyframe's is below it. The test's photograph:
   0.98-1.0; views of a room 0.3-0.5; the out-and-back recording's true revisits 0.13-0.42 (docs/loop.md). The
   defaults since 2026-12-05 are ``"current"``, the depth check off and this check on: the out-and-back recording
   closes 55 loops along the whole way back (ATE 0.554 -> 0.240 m), the forward recordings none.

Nothing here raises on bad luck (no features, no depths, degenerate points, a candidate from another camera): the
candidate is rejected with its reason, which the closer counts.

Conventions: ``relative`` is the 4x4 Sim(3) ``S = [[s R, t], [0, 1]]`` with ``X_cand = S @ X_cur`` (camera
coordinates of the current keyframe to the candidate's), i.e. the pose-graph edge ``pose_cand^-1 @ pose_cur`` of
the two keyframes' Sim(3) camera-to-world poses; ``scale`` is its ``s`` (> 1 when the candidate's map is larger).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mgso.config import LoopConfig, TrackingConfig
from mgso.geometry import se3_inverse, sim3_from_parts, sim3_inverse, umeyama_alignment
from mgso.loop.place import KeyframeFeatures, ratio_matches
from mgso_kernels import runtime
from mgso_kernels.image import ImagePyramid, Pinhole, PyramidGeometry, plan_pyramid
from mgso_kernels.photometric import make_frame_pair
from mgso_kernels.track import track_system

#: The depth-consistency check's thresholds (step 4 of the module text) for settings objects without the fields
#: ``depth_tolerance``, ``min_depth_consistent``, ``min_depth_compared`` (LoopConfig has them; its
#: ``min_depth_consistent`` is 0, off, since 2026-12-05): the relative inverse-depth difference within which a
#: current point agrees with the candidate's depth map (DSO's depths of good points are within a few percent; 15 %
#: leaves room for depth edges and the dilated map), the fraction of compared points that must agree (true revisits
#: measured 0.95-0.98 on synthetic scenes, a photograph of the place hung elsewhere 0.41-0.54: docs/loop.md) and the
#: fewest points compared.
DEPTH_TOLERANCE = 0.15
MIN_DEPTH_CONSISTENT = 0.75
MIN_DEPTH_COMPARED = 30

#: The planar check (step 5): a DSO point lies on a plane when it is within this fraction of its depth of it (DSO's
#: depths of good points are within a few percent), and planes are hypothesised from this many random point triples.
PLANE_TOLERANCE = 0.02
PLANE_ITERATIONS = 200

__all__ = ["Verification", "verify", "mutual_matches", "sim3_ransac", "OneSided", "photometric_check", "REASONS",
           "pnp_ransac", "epipolar_inliers", "photometric_check_from_current", "planar_fraction"]

#: Every reason a verification gives (the closer counts them).
REASONS = ("accepted", "camera mismatch", "too few matches", "degenerate", "too few inliers", "too few with depth",
           "scale unknown",
           "photometric no points", "photometric tracking failed", "photometric rmse", "photometric inliers",
           "depth unverified", "depth inconsistent", "planar look-alike")


@dataclass(frozen=True)
class Verification:
    """The verdict on one candidate (see the module text). ``matches``: mutual ratio-test matches;
    ``matches_with_depth``: those with a depth in at least one keyframe (RANSAC's input), ``matches_3d3d``: in both;
    ``inliers``: RANSAC's after the refit (3D-3D and one-sided); ``depth_compared``, ``depth_consistent``: the depth
    check's points compared and fraction agreeing; ``rmse``, ``inlier_fraction``: the photometric check's level-0
    RMSE and fraction of the reference's points within the cutoff (``None`` when it did not run); ``scale``: the
    Sim(3)'s ``s`` (``None`` before RANSAC); ``relative``: the final Sim(3) when accepted, RANSAC's when the
    photometric, the depth or the planar check rejected it, else ``None``; ``planar_current``, ``planar_candidate``:
    the planar check's fractions of each keyframe's DSO points on one plane (``None`` when it did not run)."""

    accepted: bool
    reason: str
    relative: np.ndarray | None
    matches: int
    inliers: int
    rmse: float | None
    inlier_fraction: float | None
    scale: float | None
    matches_with_depth: int = 0
    matches_3d3d: int = 0
    depth_compared: int = 0
    depth_consistent: float | None = None
    epipolar_inliers: int | None = None
    planar_current: float | None = None
    planar_candidate: float | None = None


# -------------------------------------------------------------------------------------------------- matching
def mutual_matches(a: np.ndarray, b: np.ndarray, ratio: float) -> np.ndarray:
    """``(K, 2)`` index pairs ``(i in a, j in b)`` of ORB descriptors that pass the ratio test both ways and are
    each other's nearest neighbour."""
    fwd = ratio_matches(a, b, ratio)
    bwd = {q: t for q, t, _ in ratio_matches(b, a, ratio)}
    pairs = [(i, j) for i, j, _ in fwd if bwd.get(j) == i]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def _backproject(cam, uv: np.ndarray, idepth: np.ndarray) -> np.ndarray:
    z = 1.0 / idepth
    return np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], axis=1)


def _reproj_error(cam, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixel distance of the projections of camera points ``X`` to ``uv``; inf behind the camera."""
    z = X[:, 2]
    ok = z > 1e-9
    zs = np.where(ok, z, 1.0)
    u = cam.fx * X[:, 0] / zs + cam.cx
    v = cam.fy * X[:, 1] / zs + cam.cy
    err = np.hypot(u - uv[:, 0], v - uv[:, 1])
    return np.where(ok, err, np.inf)


def _apply(S: np.ndarray, X: np.ndarray) -> np.ndarray:
    return X @ S[:3, :3].T + S[:3, 3]


def _inliers(S: np.ndarray, Xc: np.ndarray, Xk: np.ndarray, cam_c, cam_k, uv_c: np.ndarray, uv_k: np.ndarray,
             px: float) -> np.ndarray:
    """Pairs that reproject within ``px`` in both keyframes under ``X_cand = S X_cur``."""
    e_k = _reproj_error(cam_k, _apply(S, Xc), uv_k)
    e_c = _reproj_error(cam_c, _apply(sim3_inverse(S), Xk), uv_c)
    return (e_k < px) & (e_c < px)


def _fit(Xc: np.ndarray, Xk: np.ndarray) -> np.ndarray | None:
    """Umeyama Sim(3) with ``Xk ~= S Xc``; None for a degenerate set (coincident or collinear points)."""
    for X in (Xc, Xk):
        d = X - X.mean(0)
        sv = np.linalg.svd(d, compute_uv=False)
        if not sv[0] > 0 or sv[1] < 1e-6 * sv[0]:
            return None
    try:
        al = umeyama_alignment(Xc, Xk, with_scale=True)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not (np.isfinite(al.scale) and al.scale > 1e-6 and np.all(np.isfinite(al.translation))):
        return None
    return al.matrix()


@dataclass(frozen=True)
class OneSided:
    """Matches with a depth on one side only: current points ``Xc (A, 3)`` seen at candidate pixels ``uv_k (A, 2)``,
    candidate points ``Xk (B, 3)`` seen at current pixels ``uv_c (B, 2)``. They cannot make a hypothesis but each
    can confirm one, by its one reprojection."""

    Xc: np.ndarray
    uv_k: np.ndarray
    Xk: np.ndarray
    uv_c: np.ndarray

    @classmethod
    def empty(cls) -> "OneSided":
        z3, z2 = np.zeros((0, 3)), np.zeros((0, 2))
        return cls(z3, z2, z3, z2)

    def inliers(self, S: np.ndarray, cam_c, cam_k, px: float) -> tuple[np.ndarray, np.ndarray]:
        a = _reproj_error(cam_k, _apply(S, self.Xc), self.uv_k) < px if len(self.Xc) else np.zeros(0, bool)
        b = _reproj_error(cam_c, _apply(sim3_inverse(S), self.Xk), self.uv_c) < px if len(self.Xk) else \
            np.zeros(0, bool)
        return a, b


def sim3_ransac(Xc: np.ndarray, Xk: np.ndarray, uv_c: np.ndarray, uv_k: np.ndarray, cam_c, cam_k,
                iterations: int, inlier_px: float, rng_seed: int = 0,
                one_sided: OneSided | None = None) -> tuple[np.ndarray | None, np.ndarray, int]:
    """Sim(3) RANSAC ``X_cand = S X_cur`` over point pairs ``Xc[i] <-> Xk[i]`` (the current and the candidate
    keyframe's camera coordinates, observed at ``uv_c[i]``, ``uv_k[i]``), each hypothesis from 3 such pairs; a pair
    is an inlier when it reprojects within ``inlier_px`` in both images, a ``one_sided`` match when its one point
    does in the other image. Returns ``(S, inlier mask of the pairs, inliers in all)`` after refitting on the
    pairs' inliers, ``(None, all False, 0)`` when no 3-pair sample gives a usable hypothesis. Deterministic for a
    seed."""
    n = len(Xc)
    none = np.zeros(n, bool)
    one = one_sided or OneSided.empty()
    if n < 3:
        return None, none, 0

    def score(S):
        inl = _inliers(S, Xc, Xk, cam_c, cam_k, uv_c, uv_k, inlier_px)
        a, b = one.inliers(S, cam_c, cam_k, inlier_px)
        return inl, int(inl.sum()) + int(a.sum()) + int(b.sum())

    rng = np.random.default_rng(rng_seed)
    best_S, best_in, best_n = None, none, 0
    for _ in range(int(iterations)):
        idx = rng.choice(n, 3, replace=False)
        S = _fit(Xc[idx], Xk[idx])
        if S is None:
            continue
        inl, k = score(S)
        if k > best_n:
            best_S, best_in, best_n = S, inl, k
    if best_S is None:
        return None, none, 0
    for _ in range(2):  # refit on the pairs' inliers while that adds some
        if best_in.sum() < 3:
            break
        S = _fit(Xc[best_in], Xk[best_in])
        if S is None:
            break
        inl, k = score(S)
        if k < best_n:
            break
        grew = k > best_n
        best_S, best_in, best_n = S, inl, k
        if not grew:
            break
    return best_S, best_in, best_n


# -------------------------------------------------------------------------------------------- photometric
def _same_camera(a, b) -> bool:
    return (int(a.width), int(a.height)) == (int(b.width), int(b.height)) and np.allclose(
        [a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=1e-6, atol=1e-6)


def _geometry(cam, tracking: TrackingConfig) -> PyramidGeometry:
    return plan_pyramid(int(cam.width), int(cam.height), Pinhole(cam.fx, cam.fy, cam.cx, cam.cy),
                        levels=tracking.pyramid_levels, max_levels=tracking.pyramid_max_levels,
                        min_area=tracking.pyramid_min_area, mode=tracking.pyramid_size_mode)


def _pyramid(geom: PyramidGeometry, gray: np.ndarray, device: str) -> ImagePyramid:
    return ImagePyramid(geom, device=device).build(np.ascontiguousarray(geom.adjust(gray), dtype=np.float32))


@dataclass(frozen=True)
class PhotometricResult:
    ok: bool  # the tracker converged within its checks
    relative: np.ndarray  # X_cand = relative @ X_cur, the refined rigid motion with the given scale
    rmse: float  # level-0 RMSE at the final pose, at DSO's cutoff (tracking.coarse_cutoff_th; NaN: none in view)
    inlier_fraction: float  # level-0 residuals within that cutoff / reference points at level 0
    num_points: int  # reference points at level 0
    depth_compared: int = 0  # current keyframe's points that land on a candidate pixel with a depth
    depth_consistent: float = 0.0  # fraction of those whose inverse depths agree within DEPTH_TOLERANCE
    tracker_rmse: float = float("nan")  # the tracker's own level-0 RMSE (at its possibly raised cutoff)


def _reference(feats: KeyframeFeatures, geom: PyramidGeometry, tracking: TrackingConfig, device: str,
               idepth_scale: float = 1.0):
    """The tracking reference of a keyframe: its gray pyramid and its DSO points (inverse depths times
    ``idepth_scale``)."""
    from mgso.tracking.coarse_tracker import reference_from_points

    uv = feats.points_uv - np.array([geom.offset_x, geom.offset_y], dtype=np.float64)
    return reference_from_points(geom, _pyramid(geom, feats.gray, device), uv, feats.points_idepth * idepth_scale,
                                 None, tracking, keyframe_id=feats.keyframe_id, device=device)


def _track_and_score(ref, geom: PyramidGeometry, new_gray: np.ndarray, ref_to_new: np.ndarray,
                     tracking: TrackingConfig, device: str):
    """Track ``new_gray`` against ``ref`` (which has points at level 0) from ``ref_to_new``, coarse to fine (pose
    and affine brightness). Returns ``(converged, finite, T, rmse, inlier_fraction, tracker_rmse)``: ``T`` the
    tracked ``ref_to_new`` (the start when the result is not finite), the level-0 RMSE and the fraction of the
    reference's level-0 points within DSO's own cutoff (NaN and 0 when not finite)."""
    from mgso.tracking.coarse_tracker import CoarseTracker

    new_pyr = _pyramid(geom, new_gray, device)
    tracker = CoarseTracker(geom, tracking, device=device)
    tracker.set_reference(ref)
    res = tracker.track_levels(new_pyr, 0.0, ref_to_new, (0.0, 0.0), np.full(geom.levels, np.nan))
    finite = bool(np.all(np.isfinite(res.ref_to_new)) and np.all(np.isfinite(res.affine)))
    rmse, inl = float("nan"), 0.0
    if finite:
        # the verdict at DSO's own cutoff: the tracker raises its cutoff (x2, x4, ...) while most residuals
        # saturate, and within a raised cutoff a wrong image's residuals would count as inliers
        L = ref.levels[0]
        pair = make_frame_pair(res.ref_to_new, ref.affine[0], ref.affine[1], res.affine[0], res.affine[1],
                               ref.exposure, 0.0)
        st = track_system(L.uv, L.idepth, L.color, pair, tracker.cams[0], new_pyr.dI[0], tracker.workspaces[0],
                          cutoff_th=tracking.coarse_cutoff_th, huber_th=tracking.huber_th, flow_stride=0)
        if st.num_terms:
            rmse = float(np.sqrt(st.energy / st.num_terms))
        inl = st.num_inliers / int(ref.num_points_l0)
    T = res.ref_to_new if finite else ref_to_new
    return bool(res.ok), finite, T, rmse, float(inl), float(res.rmse[0])


def photometric_check(current: KeyframeFeatures, candidate: KeyframeFeatures, S: np.ndarray,
                      tracking: TrackingConfig | None = None, device: str | None = None,
                      depth_tolerance: float | None = None) -> PhotometricResult:
    """Track the current keyframe's image against the candidate's DSO points (inverse depths times the scale of
    ``S``) from the rigid part of ``S``, then compare the current keyframe's points with the candidate's depth map
    under the refined motion (:func:`depth_consistency`; see the module text). Both keyframes must have the same
    camera."""
    tracking = tracking or TrackingConfig()
    device = runtime.device_or_cpu(device)
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    R, t = S[:3, :3] / s, S[:3, 3]
    # Y = X_cand / s = R X_cur + t / s: the candidate's camera at the current keyframe's scale; the tracker's
    # ref_to_new maps Y to X_cur
    cur_to_ref = np.eye(4)
    cur_to_ref[:3, :3], cur_to_ref[:3, 3] = R, t / s
    geom = _geometry(candidate.camera, tracking)
    ref = _reference(candidate, geom, tracking, device, idepth_scale=s)
    n0 = int(ref.num_points_l0)
    if n0 == 0:
        return PhotometricResult(False, S, float("nan"), 0.0, 0)
    ok, finite, ref_to_new, rmse, inl, tracker_rmse = _track_and_score(ref, geom, current.gray,
                                                                        se3_inverse(cur_to_ref), tracking, device)
    T = se3_inverse(ref_to_new) if finite else cur_to_ref
    rel = sim3_from_parts(T[:3, :3], s * T[:3, 3], s)
    n_cmp, frac = depth_consistency(current, T, ref.idepth_maps[0], geom, depth_tolerance)
    return PhotometricResult(ok, rel, rmse, inl, n0, n_cmp, frac, tracker_rmse)


def depth_consistency(current: KeyframeFeatures, cur_to_ref: np.ndarray, idepth_map: np.ndarray,
                      geom: PyramidGeometry, tolerance: float | None = None, *, idepth_scale: float = 1.0
                      ) -> tuple[int, float]:
    """How far ``current``'s DSO points (inverse depths times ``idepth_scale``) agree with the other keyframe's depth
    map: each point moved by ``cur_to_ref`` (rigid, into the other keyframe's camera at that scale) and projected;
    where it lands on a pixel of ``idepth_map`` (level 0 of the reference, -1 where none) its inverse depth is
    compared with the map's. Returns (points compared, fraction within ``tolerance`` relative inverse depth)."""
    tol = DEPTH_TOLERANCE if tolerance is None else tolerance
    if len(current.points_uv) == 0:
        return 0, 0.0
    X = _backproject(current.camera, current.points_uv, current.points_idepth * idepth_scale)
    Y = X @ cur_to_ref[:3, :3].T + cur_to_ref[:3, 3]
    cam = geom.camera
    z = Y[:, 2]
    ok = z > 1e-9
    zs = np.where(ok, z, 1.0)
    u = np.floor(cam.fx * Y[:, 0] / zs + cam.cx + 0.5)
    v = np.floor(cam.fy * Y[:, 1] / zs + cam.cy + 0.5)
    h, w = idepth_map.shape
    ok &= (u >= 0) & (v >= 0) & (u < w) & (v < h)
    ui, vi = u[ok].astype(np.int64), v[ok].astype(np.int64)
    m = idepth_map[vi, ui].astype(np.float64)
    has = m > 0
    pred = 1.0 / zs[ok][has]
    m = m[has]
    n = int(len(m))
    if n == 0:
        return 0, 0.0
    return n, float(np.mean(np.abs(pred - m) <= tol * m))



# ------------------------------------------------------------------------------------- 2D-3D (geometry "current")
#: Fewest PnP inliers with a candidate depth for the loop's scale (their median depth ratio)
MIN_SCALE_PAIRS = 5


def pnp_ransac(X: np.ndarray, uv: np.ndarray, cam, iterations: int, inlier_px: float
               ) -> tuple[np.ndarray | None, np.ndarray]:
    """The rigid motion ``T`` (4x4) with ``uv ~ project(T X)``: OpenCV's PnP RANSAC (AP3P hypotheses; its random
    generator has a fixed seed, so the result is deterministic), refined by Levenberg-Marquardt on the inliers.
    Returns ``(T, inlier mask)``, ``(None, all False)`` when it finds none."""
    import cv2

    n = len(X)
    none = np.zeros(n, bool)
    if n < 4:
        return None, none
    K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
    Xf, uvf = np.ascontiguousarray(X, np.float64), np.ascontiguousarray(uv, np.float64)
    try:
        ok, rvec, tvec, idx = cv2.solvePnPRansac(Xf, uvf, K, None, iterationsCount=int(iterations),
                                                 reprojectionError=float(inlier_px), confidence=0.999,
                                                 flags=cv2.SOLVEPNP_AP3P)
    except cv2.error:
        return None, none
    if not ok or idx is None or len(idx) < 4:
        return None, none
    inl = none.copy()
    inl[idx.ravel()] = True
    try:
        rvec, tvec = cv2.solvePnPRefineLM(Xf[inl], uvf[inl], K, None, rvec, tvec)
    except cv2.error:
        pass
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.asarray(tvec, np.float64).ravel()
    if not np.all(np.isfinite(T)):
        return None, none
    return T, _reproj_error(cam, X @ T[:3, :3].T + T[:3, 3], uv) < inlier_px


def epipolar_inliers(uv_a: np.ndarray, uv_b: np.ndarray, cam_a, cam_b, px: float) -> np.ndarray:
    """Matches ``uv_a[i] <-> uv_b[i]`` (pixels of ``cam_a`` and ``cam_b``) consistent with one rigid motion: the
    inliers of an essential matrix (OpenCV's five-point RANSAC, a fixed seed, so deterministic) within ``px`` pixels
    of their epipolar lines. No depth is needed, so every match counts; a pure rotation (any translation fits it)
    passes as well. All False with fewer than 5 matches or where RANSAC finds none."""
    import cv2

    n = len(uv_a)
    none = np.zeros(n, bool)
    if n < 5:
        return none

    def norm(uv, c):
        return np.c_[(uv[:, 0] - c.cx) / c.fx, (uv[:, 1] - c.cy) / c.fy].astype(np.float64)

    f = 0.25 * (cam_a.fx + cam_a.fy + cam_b.fx + cam_b.fy)     # the threshold in normalised coordinates
    try:
        E, mask = cv2.findEssentialMat(norm(uv_a, cam_a), norm(uv_b, cam_b), np.eye(3), method=cv2.RANSAC,
                                       prob=0.999, threshold=float(px) / f)
    except cv2.error:
        return none
    if E is None or mask is None:
        return none
    return mask.ravel().astype(bool)[:n]


def photometric_check_from_current(current: KeyframeFeatures, candidate: KeyframeFeatures, T: np.ndarray,
                                   scale: float, tracking: TrackingConfig | None = None, device: str | None = None,
                                   depth_tolerance: float | None = None) -> PhotometricResult:
    """The photometric and depth checks of the 2D-3D verification: the tracking reference is the current keyframe
    (its image and its own DSO points, the well-constrained side), and the candidate's image is tracked against it
    from ``T`` (rigid, current camera to the candidate's at the current keyframe's scale); then the candidate's
    points, their inverse depths times ``scale`` (the candidate's coordinates divided by the loop's scale are at
    the current keyframe's), are compared with the current keyframe's depth map. ``relative`` is the Sim(3)
    ``X_cand = S X_cur`` of the refined motion and ``scale``."""
    tracking = tracking or TrackingConfig()
    device = runtime.device_or_cpu(device)
    s = float(scale)
    geom = _geometry(current.camera, tracking)
    ref = _reference(current, geom, tracking, device)
    n0 = int(ref.num_points_l0)
    if n0 == 0:
        return PhotometricResult(False, sim3_from_parts(T[:3, :3], s * T[:3, 3], s), float("nan"), 0.0, 0)
    ok, finite, Tf, rmse, inl, tracker_rmse = _track_and_score(ref, geom, candidate.gray, T, tracking, device)
    rel = sim3_from_parts(Tf[:3, :3], s * Tf[:3, 3], s)
    n_cmp, frac = depth_consistency(candidate, se3_inverse(Tf), ref.idepth_maps[0], geom, depth_tolerance,
                                    idepth_scale=s)
    return PhotometricResult(ok, rel, rmse, inl, n0, n_cmp, frac, tracker_rmse)


def planar_fraction(feats: KeyframeFeatures, rng: np.random.Generator, tolerance: float = PLANE_TOLERANCE,
                    iterations: int = PLANE_ITERATIONS) -> float:
    """The largest fraction of ``feats``' DSO points (in its camera) within ``tolerance`` x their depth of one plane,
    over ``iterations`` planes through three random points (RANSAC); 0 with fewer than 3 points. A photograph or a
    wall: about 1; a view of a room: 0.3-0.5; a first pass's loose depths: below 0.45 (docs/loop.md)."""
    X = _backproject(feats.camera, feats.points_uv, feats.points_idepth)
    n = len(X)
    if n < 3:
        return 0.0
    tol = tolerance * X[:, 2]
    best = 0
    for _ in range(iterations):
        i, j, k = rng.choice(n, 3, replace=False)
        normal = np.cross(X[j] - X[i], X[k] - X[i])
        norm = float(np.linalg.norm(normal))
        if norm < 1e-12:
            continue
        best = max(best, int(np.count_nonzero(np.abs((X - X[i]) @ (normal / norm)) < tol)))
    return best / n


# ---------------------------------------------------------------------------------------------------- verify
def verify(current: KeyframeFeatures, candidate: KeyframeFeatures, settings: LoopConfig, device: str | None = None,
           rng_seed: int = 0, tracking: TrackingConfig | None = None, *, depth_tolerance: float | None = None,
           min_depth_consistent: float | None = None, min_depth_compared: int | None = None) -> Verification:
    """Accept or reject ``candidate`` as the place ``current`` shows (see the module text). ``tracking``: the
    pyramid and coarse tracker's settings for the photometric check (default ``TrackingConfig()``; pass the run's
    ``config.tracking``). The depth check's thresholds: the arguments, else ``settings``' fields of those names
    when it has them, else :data:`DEPTH_TOLERANCE`, :data:`MIN_DEPTH_CONSISTENT`, :data:`MIN_DEPTH_COMPARED`
    (``min_depth_consistent=0`` and ``min_depth_compared=0`` switch it off); the planar check's from
    ``settings.planar_fraction`` (0 or absent: off). Deterministic for ``rng_seed`` (on one device)."""
    cfg = settings

    def pick(value, name, default):
        return value if value is not None else getattr(cfg, name, default)

    tol = float(pick(depth_tolerance, "depth_tolerance", DEPTH_TOLERANCE))
    min_consistent = float(pick(min_depth_consistent, "min_depth_consistent", MIN_DEPTH_CONSISTENT))
    min_compared = int(pick(min_depth_compared, "min_depth_compared", MIN_DEPTH_COMPARED))

    def reject(reason, **kw):
        base = dict(relative=None, matches=0, inliers=0, rmse=None, inlier_fraction=None, scale=None)
        base.update(kw)
        return Verification(False, reason, **base)

    if not _same_camera(current.camera, candidate.camera) or current.gray.shape != candidate.gray.shape:
        return reject("camera mismatch")
    pairs = mutual_matches(current.descriptors, candidate.descriptors, cfg.match_ratio)
    n_match = len(pairs)
    dc, dk = current.idepths[pairs[:, 0]], candidate.idepths[pairs[:, 1]]
    hc, hk = np.isfinite(dc) & (dc > 0), np.isfinite(dk) & (dk > 0)
    both, cur_only, cand_only = pairs[hc & hk], pairs[hc & ~hk], pairs[~hc & hk]
    n_both = len(both)
    n_depth = n_both + len(cur_only) + len(cand_only)
    if getattr(cfg, "geometry", "both") == "current":
        n_depth = int(np.count_nonzero(hc))                    # the 2D-3D pairs: a current depth
        # with the epipolar check every match counts (it needs no depth), else those with a current depth
        if (n_match if getattr(cfg, "epipolar_check", False) else n_depth) < cfg.min_inliers:
            return reject("too few matches", matches=n_match, matches_with_depth=n_depth, matches_3d3d=n_both)
    elif n_both < 3 or n_depth < cfg.min_inliers:
        return reject("too few matches", matches=n_match, matches_with_depth=n_depth, matches_3d3d=n_both)
    cc, kc = current.camera, candidate.camera
    if getattr(cfg, "geometry", "both") == "current":
        return _verify_from_current(current, candidate, cfg, pairs, hc, hk, device, tracking, tol, min_consistent,
                                    min_compared, reject, rng_seed)
    uv_c, uv_k = current.keypoints[both[:, 0]], candidate.keypoints[both[:, 1]]
    Xc = _backproject(cc, uv_c, current.idepths[both[:, 0]])
    Xk = _backproject(kc, uv_k, candidate.idepths[both[:, 1]])
    one = OneSided(_backproject(cc, current.keypoints[cur_only[:, 0]], current.idepths[cur_only[:, 0]]),
                   candidate.keypoints[cur_only[:, 1]],
                   _backproject(kc, candidate.keypoints[cand_only[:, 1]], candidate.idepths[cand_only[:, 1]]),
                   current.keypoints[cand_only[:, 0]])
    S, inl, n_in = sim3_ransac(Xc, Xk, uv_c, uv_k, cc, kc, cfg.ransac_iterations, cfg.inlier_px, rng_seed, one)
    if S is None:
        return reject("degenerate", matches=n_match, matches_with_depth=n_depth, matches_3d3d=n_both)
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    common = dict(matches=n_match, matches_with_depth=n_depth, matches_3d3d=n_both, inliers=n_in, scale=scale)
    if n_in < cfg.min_inliers:
        return reject("too few inliers", **common)
    ph = photometric_check(current, candidate, S, tracking, device, depth_tolerance=tol)
    common["relative"] = S
    return _verdict(ph, common, cfg, min_compared, min_consistent, reject, current, candidate, rng_seed)


def _verdict(ph: PhotometricResult, common: dict, cfg: LoopConfig, min_compared: int, min_consistent: float,
             reject, current: KeyframeFeatures, candidate: KeyframeFeatures, rng_seed: int) -> Verification:
    """Steps 3-5's verdict on a candidate whose geometry passed (``common``: its figures so far)."""
    common = dict(common, rmse=ph.rmse, inlier_fraction=ph.inlier_fraction, depth_compared=ph.depth_compared,
                  depth_consistent=ph.depth_consistent)
    for failed, reason in ((ph.num_points == 0, "photometric no points"),
                           (not ph.ok or not np.isfinite(ph.rmse), "photometric tracking failed"),
                           (ph.rmse > cfg.max_photometric_rmse, "photometric rmse"),
                           (ph.inlier_fraction < cfg.min_photometric_inliers, "photometric inliers"),
                           (ph.depth_compared < min_compared, "depth unverified"),
                           (ph.depth_consistent < min_consistent, "depth inconsistent")):
        if failed:
            return reject(reason, **common)
    limit = float(getattr(cfg, "planar_fraction", 0.0))
    if limit > 0:
        # step 5: a plane (the old keyframe's points) seen as the new keyframe's 3D scene is a photograph of it
        rng = np.random.default_rng([int(rng_seed), 0x504C])
        common["planar_candidate"] = fk = planar_fraction(candidate, rng)
        common["planar_current"] = fc = planar_fraction(current, rng)
        if fk >= limit > fc:
            return reject("planar look-alike", **common)
    return Verification(True, "accepted", **dict(common, relative=ph.relative))


def _verify_from_current(current, candidate, cfg, pairs, hc, hk, device, tracking, tol, min_consistent,
                         min_compared, reject, rng_seed: int = 0) -> Verification:
    """Steps 2-5 with the geometry of the current keyframe alone (``loop.geometry = "current"``; module text)."""
    n_match = len(pairs)
    common = dict(matches=n_match, matches_with_depth=int(np.count_nonzero(hc)),
                  matches_3d3d=int(np.count_nonzero(hc & hk)))
    need, short = cfg.min_inliers, "too few inliers"
    if getattr(cfg, "epipolar_check", False):
        # step 2a: every match, depth or not, against one rigid motion; PnP then takes those of its inliers with a
        # current depth, of which it needs only min_pnp_inliers (the epipolar inliers are the consensus)
        epi = epipolar_inliers(current.keypoints[pairs[:, 0]], candidate.keypoints[pairs[:, 1]], current.camera,
                               candidate.camera, cfg.inlier_px)
        common["epipolar_inliers"] = int(epi.sum())
        if common["epipolar_inliers"] < cfg.min_inliers:
            return reject("too few inliers", **common)
        pairs, hc, hk = pairs[epi], hc[epi], hk[epi]
        need, short = int(cfg.min_pnp_inliers), "too few with depth"
        if int(np.count_nonzero(hc)) < need:
            return reject(short, **common)
    cur = pairs[hc]                     # the current keyframe's 3D points seen at the candidate's keypoints
    cand_depth = hk[hc]
    X = _backproject(current.camera, current.keypoints[cur[:, 0]], current.idepths[cur[:, 0]])
    uv_k = candidate.keypoints[cur[:, 1]]
    T, inl = pnp_ransac(X, uv_k, candidate.camera, cfg.ransac_iterations, cfg.inlier_px)
    if T is None:
        return reject("degenerate", **common)
    n_in = int(inl.sum())
    common["inliers"] = n_in
    if n_in < need:
        return reject(short, **common)
    # the loop's scale: the candidate's depths over the current points' depths in the candidate's camera (at the
    # current keyframe's scale), their median over the inliers with a candidate depth
    both = inl & cand_depth
    z_pred = (X[both] @ T[:3, :3].T + T[:3, 3])[:, 2]
    z_cand = 1.0 / candidate.idepths[cur[both, 1]]
    ok = z_pred > 1e-9
    if int(ok.sum()) < MIN_SCALE_PAIRS:
        return reject("scale unknown", **common)
    scale = float(np.median(z_cand[ok] / z_pred[ok]))
    common["scale"] = scale
    ph = photometric_check_from_current(current, candidate, T, scale, tracking, device, depth_tolerance=tol)
    common["relative"] = sim3_from_parts(T[:3, :3], scale * T[:3, 3], scale)
    return _verdict(ph, common, cfg, min_compared, min_consistent, reject, current, candidate, rng_seed)
