"""Trajectory accuracy: absolute trajectory error (ATE) and relative pose error (RPE), figure-for-figure as evo.

Both follow evo (Grupp, https://github.com/MichaelGrupp/evo, the tool the field reports with) so that a number printed
here is the number ``evo_ape`` / ``evo_rpe`` prints for the same files:

1. **Association.** Poses of the estimate and the reference are paired by timestamp with evo's rule
   (:func:`mgso.io.trajectory.associate`): the shorter trajectory's stamps are matched to the nearest stamp of the
   longer one, kept when within ``max_diff`` seconds (default 0.01 s, as evo's ``--t_max_diff``).
2. **Alignment.** The estimate is aligned to the reference (never the other way round) by Umeyama's least-squares
   fit of the associated camera positions (:func:`mgso.geometry.umeyama_alignment`): ``"sim3"`` (rotation,
   translation and scale: ``evo_ape -as``, what monocular results report), ``"se3"`` (``evo_ape -a``) or ``"none"``.
   ``n_to_align`` fits on the first n pairs only (evo's ``--n_to_align``).
3. **Errors.** ATE: the distance between aligned estimated and reference camera centres, per pose
   (``evo_ape`` with ``--pose_relation trans_part``); the rotation part, when wanted, is the angle of
   ``est^-1 ref`` in degrees (``-r angle_deg``). RPE: for pose pairs ``(i, j)`` ``delta`` frames (or metres of the
   estimate's path) apart, ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with Q the reference and P the aligned estimate; the
   translation error is ``|t(E)|`` (m), the rotation error the angle of ``R(E)`` (degrees). Consecutive pairs only
   (evo's default, ``--all_pairs`` off) unless ``all_pairs=True``. Rigid alignment does not change relative poses;
   Sim(3) alignment corrects the estimate's scale before relative translations are taken.
4. **Statistics.** rmse, mean, median, std (population, as NumPy's default), min, max, sse: evo's
   ``get_all_statistics``.
5. **What the ATE is worth** (not in evo). ``motionless_rmse``: the ATE an estimate that never moves would get (the
   reference positions' RMS distance from their mean, what Sim(3) and SE(3) alignment leave of a constant estimate):
   a monocular trajectory whose scale has collapsed gets about this, however small it looks (TUM freiburg1_rpy:
   0.045 m against 0.047 standing still, the reference DSO 0.043 against 0.046; docs/evaluation.md).
   ``local_scales``: the associated poses cut into ``SCALE_PARTS`` consecutive parts, each part's own Sim(3) scale
   over the whole trajectory's; ``scale_drift`` is the largest over the smallest (1 for a trajectory whose scale
   holds; parts whose reference moves less than ``SCALE_MIN_SPREAD_M`` are left out, their scale is noise).

Units: metres and degrees. Results are values (dataclasses), never prints; ``summary()`` gives a one-line text.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from ..geometry import Alignment, se3_inverse, umeyama_alignment
from ..io.trajectory import Trajectory, associate, read_trajectory

__all__ = [
    "AlignMode", "ALIGN_MODES", "EvaluationError", "ErrorStats", "AteResult", "RpeResult",
    "compute_ate", "compute_rpe", "compute_ate_files", "compute_rpe_files", "associate_checked", "local_scales",
    "motionless_rmse", "SCALE_PARTS", "SCALE_MIN_SPREAD_M",
]

AlignMode = Literal["sim3", "se3", "none"]
ALIGN_MODES: tuple[str, ...] = ("sim3", "se3", "none")

#: :func:`local_scales`: the parts a trajectory is cut into, and the least RMS spread (m) of a part's reference
#: positions about their mean for its scale to count
SCALE_PARTS = 10
SCALE_MIN_SPREAD_M = 0.01
#: AteResult.warnings: an ATE at least this share of the standing-still one, a scale drift above this many times
MOTIONLESS_SHARE = 0.8
SCALE_DRIFT_WARN = 3.0

_ALIGN_TEXT = {"sim3": "Sim(3) Umeyama alignment", "se3": "SE(3) Umeyama alignment", "none": "not aligned"}


class EvaluationError(ValueError):
    """The trajectories cannot be evaluated (too few associated poses, degenerate alignment, bad option); the
    message says what was found and what is needed."""


# ------------------------------------------------------------------------------------------------ statistics
@dataclass(frozen=True)
class ErrorStats:
    """Summary of a set of non-negative errors, as evo's ``get_all_statistics`` (std is the population std)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    count: int

    @classmethod
    def from_errors(cls, errors) -> "ErrorStats":
        e = np.asarray(errors, dtype=np.float64).reshape(-1)
        if e.size == 0:
            raise EvaluationError("no errors to summarise (empty set of poses)")
        sq = e * e
        return cls(rmse=float(math.sqrt(float(np.mean(sq)))), mean=float(np.mean(e)), median=float(np.median(e)),
                   std=float(np.std(e)), min=float(np.min(e)), max=float(np.max(e)), sse=float(np.sum(sq)),
                   count=int(e.size))

    def as_dict(self) -> dict:
        return {"rmse": self.rmse, "mean": self.mean, "median": self.median, "std": self.std, "min": self.min,
                "max": self.max, "sse": self.sse, "count": self.count}


# ----------------------------------------------------------------------------------------------- association
def _span(tr: Trajectory) -> str:
    if len(tr) == 0:
        return "no poses"
    return f"{len(tr)} poses, t = [{tr.timestamps[0]:.6f}, {tr.timestamps[-1]:.6f}] s"


def associate_checked(estimate: Trajectory, reference: Trajectory, *, max_diff: float = 0.01, offset: float = 0.0,
                      min_pairs: int = 3, estimate_name: str = "estimate",
                      reference_name: str = "reference") -> tuple[Trajectory, Trajectory]:
    """:func:`mgso.io.trajectory.associate` (evo's rule), raising :class:`EvaluationError` when fewer than
    ``min_pairs`` pairs are found; the message gives the count, both time ranges and ``max_diff``."""
    if max_diff < 0:
        raise EvaluationError(f"max_diff must be >= 0 seconds, got {max_diff}")
    est, ref = associate(estimate, reference, max_diff=max_diff, offset=offset)
    if len(est) < min_pairs:
        raise EvaluationError(
            f"only {len(est)} pose pairs associate between {estimate_name} ({_span(estimate)}) and "
            f"{reference_name} ({_span(reference)}) with max_diff = {max_diff} s and offset = {offset} s; "
            f"need at least {min_pairs}. Check that both files use the same clock (seconds), or raise max_diff.")
    return est, ref


def _check_align(align: str) -> None:
    if align not in ALIGN_MODES:
        raise EvaluationError(f"align must be one of {ALIGN_MODES}, got {align!r}")


def _fit_alignment(est: Trajectory, ref: Trajectory, align: str, n_to_align: int | None) -> Alignment:
    """Umeyama fit of the estimate's positions onto the reference's (evo's ``PosePath3D.align``)."""
    if align == "none":
        return Alignment(rotation=np.eye(3), translation=np.zeros(3), scale=1.0)
    src, dst = est.positions, ref.positions
    if n_to_align is not None:
        if n_to_align < 3:
            raise EvaluationError(f"n_to_align must be at least 3 (or None for all poses), got {n_to_align}")
        src, dst = src[:n_to_align], dst[:n_to_align]
    if align == "sim3":
        spread = float(np.sqrt(((src - src.mean(0)) ** 2).sum(1).mean()))
        if spread < 1e-12:
            raise EvaluationError(
                f"Sim(3) alignment is undefined: all {len(src)} estimated positions used for the fit are the same "
                f"point (the estimate does not move); use align='se3' or 'none'")
    try:
        return umeyama_alignment(src, dst, with_scale=(align == "sim3"))
    except ValueError as e:  # pragma: no cover - the checks above catch the known cases
        raise EvaluationError(f"alignment failed: {e}") from None


def _apply(alignment: Alignment, est: Trajectory) -> Trajectory:
    return Trajectory(est.timestamps.copy(), alignment.apply_poses(est.cam_to_world))


def _angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles in degrees of (N, 3, 3) rotations, accurate near 0 (``atan2(sin, cos)``; ``arccos`` of the
    trace alone loses ~1e-6 degree there)."""
    sin = 0.5 * np.linalg.norm(np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]],
                                        axis=1), axis=1)
    cos = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    return np.degrees(np.arctan2(sin, cos))


def _rotation_angles_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Angles (degrees) of ``A_k^T B_k`` for rotation stacks (N, 3, 3)."""
    return _angle_deg(np.einsum("nji,njk->nik", A, B))


def motionless_rmse(reference_positions) -> float:
    """The ATE (m) of an estimate that stays at one point, under Sim(3) or SE(3) alignment: the RMS distance of the
    reference positions from their mean."""
    p = np.asarray(reference_positions, dtype=np.float64).reshape(-1, 3)
    return float(np.sqrt(((p - p.mean(0)) ** 2).sum(1).mean()))


def local_scales(estimate_positions, reference_positions, *, parts: int = SCALE_PARTS,
                 min_spread: float = SCALE_MIN_SPREAD_M) -> np.ndarray:
    """Each of ``parts`` consecutive parts' own Sim(3) scale (Umeyama, estimate onto reference) over the whole
    trajectory's, (K,) for the K <= ``parts`` parts that count: at least 3 poses, the reference's RMS spread at least
    ``min_spread`` metres and the estimate not at one point (a scale that collapsed to 0 gives inf). Positions (N, 3)
    associated pose by pose. A trajectory whose scale holds gives values near 1; a monocular odometry whose scale
    drifts gives values that fall or rise along the trajectory."""
    est = np.asarray(estimate_positions, dtype=np.float64).reshape(-1, 3)
    ref = np.asarray(reference_positions, dtype=np.float64).reshape(-1, 3)
    if len(est) != len(ref):
        raise EvaluationError(f"local_scales needs associated positions, got {len(est)} and {len(ref)}")
    if len(est) < 3:
        return np.zeros(0)
    try:
        whole = umeyama_alignment(est, ref, with_scale=True).scale
    except ValueError:          # the estimate at one point: no scale to compare the parts with
        return np.zeros(0)
    if not (math.isfinite(whole) and whole > 0):
        return np.zeros(0)
    out = []
    for idx in np.array_split(np.arange(len(est)), max(int(parts), 1)):
        if len(idx) < 3 or motionless_rmse(ref[idx]) < min_spread:
            continue
        try:
            out.append(umeyama_alignment(est[idx], ref[idx], with_scale=True).scale / whole)
        except ValueError:      # this part's estimate at one point: its scale collapsed to nothing
            out.append(math.inf)
    return np.asarray(out, dtype=np.float64)


# -------------------------------------------------------------------------------------------------------- ATE
@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error. Positions in metres, angles in degrees.

    ``errors[k]`` is the distance between ``aligned_estimate.positions[k]`` and ``reference.positions[k]``;
    ``reference`` and ``aligned_estimate`` hold only the associated poses, in the same order.
    """

    stats: ErrorStats  # translation error statistics, metres
    rotation_stats: ErrorStats  # rotation error statistics (angle of est^-1 ref), degrees
    errors: np.ndarray  # [N] metres, per associated pose
    rotation_errors_deg: np.ndarray  # [N] degrees
    num_pairs: int
    align: str
    alignment: Alignment  # reference ~= scale * rotation @ estimate + translation
    aligned_estimate: Trajectory
    reference: Trajectory
    max_diff: float
    n_to_align: int | None = None
    num_estimate_poses: int = 0
    num_reference_poses: int = 0
    label: str = field(default="")
    motionless_rmse: float = math.nan   # the ATE of an estimate standing still (module doc, 5.)
    local_scales: np.ndarray = field(default_factory=lambda: np.zeros(0))   # each part's scale over the whole's

    @property
    def scale_drift(self) -> float | None:
        """The largest local scale over the smallest (module doc, 5.); None with fewer than two parts that count."""
        ls = self.local_scales
        if len(ls) < 2:
            return None
        lo = float(ls.min())
        return math.inf if lo <= 0 else float(ls.max()) / lo

    @property
    def rmse(self) -> float:
        return self.stats.rmse

    @property
    def mean(self) -> float:
        return self.stats.mean

    @property
    def median(self) -> float:
        return self.stats.median

    @property
    def std(self) -> float:
        return self.stats.std

    @property
    def min(self) -> float:
        return self.stats.min

    @property
    def max(self) -> float:
        return self.stats.max

    @property
    def scale(self) -> float:
        return self.alignment.scale

    @property
    def alignment_text(self) -> str:
        text = _ALIGN_TEXT[self.align]
        if self.n_to_align is not None and self.align != "none":
            text += f" on the first {self.n_to_align} poses"
        return text

    def summary(self) -> str:
        what = f" of {self.label}" if self.label else ""
        scale = f", scale {self.alignment.scale:.6g}" if self.align == "sim3" else ""
        still = (f"; standing still {self.motionless_rmse:.6f} m" if self.align != "none"
                 and math.isfinite(self.motionless_rmse) else "")
        drift = self.scale_drift
        drift = f"; the scale drifts {drift:.3g}x along it" if drift is not None else ""
        return (f"ATE RMSE{what} {self.rmse:.6f} m ({self.alignment_text}{scale}, {self.num_pairs} poses; "
                f"mean {self.mean:.6f}, median {self.median:.6f}, max {self.max:.6f} m{still}{drift})")

    def warning_items(self) -> list[tuple[str, str]]:
        """What makes this ATE worth little, as (a few words, the full line) each: an error near what standing
        still would get (``MOTIONLESS_SHARE``), a scale that drifts more than ``SCALE_DRIFT_WARN`` times along the
        trajectory."""
        out = []
        what = f" of {self.label}" if self.label else ""
        if self.align != "none" and self.motionless_rmse > 0 and self.rmse >= MOTIONLESS_SHARE * self.motionless_rmse:
            out.append(("positions not estimated",
                        f"the ATE{what} ({self.rmse:.4f} m) is {100 * self.rmse / self.motionless_rmse:.0f} % of "
                        f"what a camera standing still would get ({self.motionless_rmse:.4f} m): the positions are "
                        "not estimated (docs/evaluation.md, \"What an ATE is worth\")"))
        drift = self.scale_drift
        if drift is not None and drift > SCALE_DRIFT_WARN:
            out.append(("scale drifts",
                        f"the scale{what} drifts {drift:.3g}x along the trajectory (each tenth's own Sim(3) scale, "
                        f"{self.local_scales.min():.3g} to {self.local_scales.max():.3g} of the whole's): one "
                        "alignment cannot fit it (docs/evaluation.md, \"What an ATE is worth\")"))
        return out

    def warnings(self) -> list[str]:
        """:meth:`warning_items`' full lines."""
        return [line for _, line in self.warning_items()]

    def as_dict(self) -> dict:
        return {"metric": "ATE", "label": self.label, "align": self.align, "n_to_align": self.n_to_align,
                "max_diff_s": self.max_diff, "num_pairs": self.num_pairs,
                "num_estimate_poses": self.num_estimate_poses, "num_reference_poses": self.num_reference_poses,
                "translation_m": self.stats.as_dict(), "rotation_deg": self.rotation_stats.as_dict(),
                "alignment": {"rotation": self.alignment.rotation.tolist(),
                              "translation": self.alignment.translation.tolist(), "scale": self.alignment.scale},
                "motionless_rmse_m": self.motionless_rmse,
                "local_scales": [float(x) for x in self.local_scales], "scale_drift": self.scale_drift}


def compute_ate(estimate: Trajectory, reference: Trajectory, *, align: AlignMode = "sim3", max_diff: float = 0.01,
                offset: float = 0.0, n_to_align: int | None = None, label: str = "",
                estimate_name: str = "estimate", reference_name: str = "reference") -> AteResult:
    """ATE of ``estimate`` against ``reference`` (the ground truth), as ``evo_ape tum REF EST [-a | -as]``.

    ``align``: ``"sim3"`` (monocular; ``-as``), ``"se3"`` (``-a``) or ``"none"``. ``max_diff``: association tolerance
    in seconds (evo ``--t_max_diff``). ``offset``: seconds added to the reference's timestamps before association
    (note: evo's ``--t_offset`` is added to the estimate's, so it is the negative of this). ``n_to_align``: fit the
    alignment on the first n associated pairs only (evo ``--n_to_align``). ``label`` names the poses evaluated
    (e.g. "all frames", "keyframes") in summaries.
    """
    _check_align(align)
    est, ref = associate_checked(estimate, reference, max_diff=max_diff, offset=offset, min_pairs=3,
                                 estimate_name=estimate_name, reference_name=reference_name)
    alignment = _fit_alignment(est, ref, align, n_to_align)
    aligned = _apply(alignment, est)
    errors = np.linalg.norm(aligned.positions - ref.positions, axis=1)
    rot_err = _rotation_angles_deg(aligned.cam_to_world[:, :3, :3], ref.cam_to_world[:, :3, :3])
    return AteResult(stats=ErrorStats.from_errors(errors), rotation_stats=ErrorStats.from_errors(rot_err),
                     errors=errors, rotation_errors_deg=rot_err, num_pairs=len(est), align=align,
                     alignment=alignment, aligned_estimate=aligned, reference=ref, max_diff=max_diff,
                     n_to_align=n_to_align, num_estimate_poses=len(estimate), num_reference_poses=len(reference),
                     label=label, motionless_rmse=motionless_rmse(ref.positions),
                     local_scales=local_scales(est.positions, ref.positions))


def compute_ate_files(estimate_path: str | Path, reference_path: str | Path, **kwargs) -> AteResult:
    """:func:`compute_ate` on two trajectory files (TUM, or KITTI with frame indices as times); the ground truth is
    ``reference_path``, and error messages name both files."""
    est = read_trajectory(estimate_path)
    ref = read_trajectory(reference_path)
    kwargs.setdefault("estimate_name", str(estimate_path))
    kwargs.setdefault("reference_name", str(reference_path))
    return compute_ate(est, ref, **kwargs)


# -------------------------------------------------------------------------------------------------------- RPE
@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over pose pairs ``id_pairs`` (indices into the associated trajectories)."""

    translation: ErrorStats  # metres
    rotation: ErrorStats  # degrees
    translation_errors: np.ndarray  # [K] metres
    rotation_errors_deg: np.ndarray  # [K] degrees
    id_pairs: np.ndarray  # [K, 2] int, indices of (i, j) into the associated poses
    delta: float
    delta_unit: str  # "frames" or "meters"
    all_pairs: bool
    num_pairs: int  # associated poses
    align: str
    alignment: Alignment
    max_diff: float
    label: str = ""

    def summary(self) -> str:
        what = f" of {self.label}" if self.label else ""
        unit = "frame" if self.delta_unit == "frames" else "m"
        d = f"{self.delta:g} {unit}{'s' if self.delta != 1 and unit == 'frame' else ''}"
        return (f"RPE{what} (delta {d}, {_ALIGN_TEXT[self.align]}, {len(self.id_pairs)} pairs): translation RMSE "
                f"{self.translation.rmse:.6f} m, rotation RMSE {self.rotation.rmse:.6f} deg")

    def as_dict(self) -> dict:
        return {"metric": "RPE", "label": self.label, "delta": self.delta, "delta_unit": self.delta_unit,
                "all_pairs": self.all_pairs, "align": self.align, "max_diff_s": self.max_diff,
                "num_pairs": self.num_pairs, "num_deltas": int(len(self.id_pairs)),
                "translation_m": self.translation.as_dict(), "rotation_deg": self.rotation.as_dict(),
                "scale": self.alignment.scale}


def _pairs_by_frames(n: int, delta: int, all_pairs: bool) -> np.ndarray:
    if all_pairs:
        i = np.arange(max(n - delta, 0))
        return np.stack([i, i + delta], axis=1)
    ids = np.arange(0, n, delta)
    return np.stack([ids[:-1], ids[1:]], axis=1)


def _pairs_by_path(positions: np.ndarray, delta: float, tol: float, all_pairs: bool) -> np.ndarray:
    """evo's ``filter_pairs_by_path``: consecutive pairs at least ``delta`` metres of path apart, or (all pairs)
    for every start the pose whose path distance is nearest ``delta`` within ``tol``."""
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    pairs = []
    if all_pairs:
        dist = np.concatenate([[0.0], np.cumsum(steps)])
        for i in range(len(dist) - 1):
            ahead = dist[i + 1:] - dist[i]
            k = int(np.argmin(np.abs(ahead - delta)))
            if abs(ahead[k] - delta) <= tol:
                pairs.append((i, i + 1 + k))
    else:
        ids = [0]
        run = 0.0
        for i, s in enumerate(steps, start=1):
            run += float(s)
            if run >= delta:
                ids.append(i)
                run = 0.0
        pairs = list(zip(ids[:-1], ids[1:]))
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def compute_rpe(estimate: Trajectory, reference: Trajectory, *, delta: float = 1, delta_unit: str = "frames",
                align: AlignMode = "sim3", max_diff: float = 0.01, offset: float = 0.0,
                n_to_align: int | None = None, all_pairs: bool = False, rel_delta_tol: float = 0.1,
                pairs_from_reference: bool = False, label: str = "", estimate_name: str = "estimate",
                reference_name: str = "reference") -> RpeResult:
    """RPE as ``evo_rpe tum REF EST --delta D --delta_unit {f|m} [-a | -as]`` (translation and rotation parts).

    ``delta_unit``: ``"frames"`` (pairs ``delta`` associated poses apart) or ``"meters"`` (pairs ``delta`` metres of
    path apart, path measured on the aligned estimate as evo does unless ``pairs_from_reference``; in all-pairs
    mode a pair is kept within ``delta * rel_delta_tol``). ``align="sim3"`` corrects the estimate's scale (and
    pose, which does not change relative poses) before the relative motions are compared: use it for monocular
    estimates. Other arguments as :func:`compute_ate`.
    """
    _check_align(align)
    if delta_unit in ("f", "frame"):
        delta_unit = "frames"
    if delta_unit in ("m", "meter", "metres", "metre"):
        delta_unit = "meters"
    if delta_unit not in ("frames", "meters"):
        raise EvaluationError(f"delta_unit must be 'frames' or 'meters', got {delta_unit!r}")
    if not delta > 0:
        raise EvaluationError(f"delta must be positive, got {delta}")
    if delta_unit == "frames" and float(delta) != int(delta):
        raise EvaluationError(f"delta must be a whole number of frames, got {delta}")
    est, ref = associate_checked(estimate, reference, max_diff=max_diff, offset=offset,
                                 min_pairs=3 if align != "none" else 2, estimate_name=estimate_name,
                                 reference_name=reference_name)
    alignment = _fit_alignment(est, ref, align, n_to_align)
    P = alignment.apply_poses(est.cam_to_world)
    Q = ref.cam_to_world
    if delta_unit == "frames":
        pairs = _pairs_by_frames(len(est), int(delta), all_pairs)
    else:
        pairs = _pairs_by_path((Q if pairs_from_reference else P)[:, :3, 3], float(delta),
                               float(delta) * rel_delta_tol, all_pairs)
    if len(pairs) == 0:
        raise EvaluationError(
            f"RPE: delta = {delta} ({delta_unit}) gives no pose pair among {len(est)} associated poses; use a "
            f"smaller delta")
    i, j = pairs[:, 0], pairs[:, 1]
    Q_rel = se3_inverse(Q[i]) @ Q[j]
    P_rel = se3_inverse(P[i]) @ P[j]
    E = se3_inverse(Q_rel) @ P_rel
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    r_err = _angle_deg(E[:, :3, :3])
    return RpeResult(translation=ErrorStats.from_errors(t_err), rotation=ErrorStats.from_errors(r_err),
                     translation_errors=t_err, rotation_errors_deg=r_err, id_pairs=pairs, delta=float(delta),
                     delta_unit=delta_unit, all_pairs=all_pairs, num_pairs=len(est), align=align,
                     alignment=alignment, max_diff=max_diff, label=label)


def compute_rpe_files(estimate_path: str | Path, reference_path: str | Path, **kwargs) -> RpeResult:
    """:func:`compute_rpe` on two trajectory files; the ground truth is ``reference_path``."""
    est = read_trajectory(estimate_path)
    ref = read_trajectory(reference_path)
    kwargs.setdefault("estimate_name", str(estimate_path))
    kwargs.setdefault("reference_name", str(reference_path))
    return compute_rpe(est, ref, **kwargs)
