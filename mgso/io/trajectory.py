"""Trajectories: a timestamped list of camera-to-world poses, TUM and KITTI files, timestamp association.

File formats:

- TUM: one pose a line, ``timestamp tx ty tz qx qy qz qw`` (seconds; camera-to-world; quaternion w last); lines
  starting with ``#`` are comments. Commas are accepted as separators too (some tools write them).
- KITTI: one pose a line, the 12 numbers of the row-major 3x4 camera-to-world matrix; no timestamps in the file (they
  come from ``times.txt`` or are the frame index).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import make_pose, matrix_to_quat_xyzw, orthonormalize, quat_xyzw_to_matrix

__all__ = ["Trajectory", "TrajectoryError", "read_tum", "write_tum", "read_kitti", "write_kitti", "read_trajectory",
           "associate", "matching_time_indices"]


class TrajectoryError(ValueError):
    """A trajectory file is missing or malformed; the message names the file (and line) and the problem."""


@dataclass
class Trajectory:
    """Poses at times. ``timestamps``: (N,) seconds, strictly increasing; ``cam_to_world``: (N, 4, 4) float64."""

    timestamps: np.ndarray
    cam_to_world: np.ndarray

    def __post_init__(self):
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.cam_to_world = np.asarray(self.cam_to_world, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.cam_to_world):
            raise ValueError(f"Trajectory: {len(self.timestamps)} timestamps but {len(self.cam_to_world)} poses")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in world coordinates."""
        return self.cam_to_world[:, :3, 3]

    def subset(self, index) -> "Trajectory":
        return Trajectory(self.timestamps[index], self.cam_to_world[index])

    def at_times(self, timestamps) -> "Trajectory":
        """The poses whose timestamp is one of ``timestamps`` (exact, as the frames' own); itself when all are."""
        keep = np.isin(self.timestamps, np.asarray(list(timestamps), np.float64))
        return self if keep.all() else self.subset(keep)

    def path_length(self) -> float:
        p = self.positions
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def _load_rows(path: Path, ncols: int, what: str) -> tuple[np.ndarray, list[int]]:
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError(f"{path}: {what} file not found")
    rows, line_numbers = [], []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for n, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#") or s.startswith("%"):
                continue
            parts = s.replace(",", " ").split()
            if len(parts) != ncols:
                raise TrajectoryError(f"{path}:{n}: expected {ncols} numbers for {what}, got {len(parts)}: {s[:80]!r}")
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                raise TrajectoryError(f"{path}:{n}: not a number in {s[:80]!r}") from None
            if not np.all(np.isfinite(vals)):
                raise TrajectoryError(f"{path}:{n}: non-finite value in {s[:80]!r}")
            rows.append(vals)
            line_numbers.append(n)
    if not rows:
        raise TrajectoryError(f"{path}: no poses in {what} file")
    return np.asarray(rows, dtype=np.float64), line_numbers


def _check_increasing(path: Path, ts: np.ndarray, lines: list[int]) -> None:
    bad = np.nonzero(np.diff(ts) <= 0)[0]
    if len(bad):
        i = int(bad[0])
        what = "repeated" if ts[i + 1] == ts[i] else "out of order"
        raise TrajectoryError(f"{path}:{lines[i + 1]}: timestamp {what} ({float(ts[i + 1])!r} after "
                              f"{float(ts[i])!r} on line {lines[i]})")


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory (``timestamp tx ty tz qx qy qz qw``)."""
    path = Path(path)
    rows, lines = _load_rows(path, 8, "TUM trajectory")
    ts = rows[:, 0]
    _check_increasing(path, ts, lines)
    q = rows[:, 4:8]
    norms = np.linalg.norm(q, axis=1)
    if np.any(norms < 1e-6):
        i = int(np.argmin(norms))
        raise TrajectoryError(f"{path}:{lines[i]}: quaternion of zero length")
    return Trajectory(ts, make_pose(quat_xyzw_to_matrix(q), rows[:, 1:4]))


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write a TUM trajectory (camera-to-world, quaternion w last)."""
    q = matrix_to_quat_xyzw(orthonormalize(traj.cam_to_world[:, :3, :3])) if len(traj) else np.zeros((0, 4))
    with open(path, "w", encoding="utf-8") as fh:
        for t, T, qq in zip(traj.timestamps, traj.cam_to_world, q):
            x, y, z = T[:3, 3]
            fh.write(f"{t:.6f} {x:.9f} {y:.9f} {z:.9f} {qq[0]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f}\n")


def read_kitti(path: str | Path, timestamps=None) -> Trajectory:
    """Read KITTI poses (12 numbers a row). Timestamps: given (e.g. from ``times.txt``) or the row index."""
    path = Path(path)
    rows, lines = _load_rows(path, 12, "KITTI poses")
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :4] = rows.reshape(-1, 3, 4)
    if timestamps is None:
        ts = np.arange(len(rows), dtype=np.float64)
    else:
        ts = np.asarray(timestamps, dtype=np.float64)
        if len(ts) != len(rows):
            raise TrajectoryError(f"{path}: {len(rows)} poses but {len(ts)} timestamps")
        _check_increasing(path, ts, lines)
    return Trajectory(ts, T)


def write_kitti(path: str | Path, traj: Trajectory) -> None:
    """Write KITTI poses (row-major 3x4 camera-to-world, no timestamps)."""
    with open(path, "w", encoding="utf-8") as fh:
        for T in traj.cam_to_world:
            fh.write(" ".join(f"{v:.9e}" for v in T[:3, :4].reshape(-1)) + "\n")


def read_trajectory(path: str | Path, timestamps=None) -> Trajectory:
    """Read a TUM (8 columns) or KITTI (12 columns) trajectory, told apart by the first data line."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryError(f"{path}: trajectory file not found")
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for line in fh:
            s = line.strip()
            if s and not s.startswith("#"):
                n = len(s.replace(",", " ").split())
                break
        else:
            raise TrajectoryError(f"{path}: no poses in trajectory file")
    if n == 8:
        return read_tum(path)
    if n == 12:
        return read_kitti(path, timestamps)
    raise TrajectoryError(f"{path}: {n} columns; expected 8 (TUM: timestamp tx ty tz qx qy qz qw) or 12 (KITTI 3x4)")


def matching_time_indices(stamps_1, stamps_2, max_diff: float = 0.01, offset_2: float = 0.0):
    """For each stamp of ``stamps_1``, the nearest stamp of ``stamps_2`` (+ offset) if within ``max_diff`` seconds.

    The same rule as evo's ``matching_time_indices``, so that ATE figures agree with ``evo_ape``.
    """
    s1 = np.asarray(stamps_1, dtype=np.float64)
    s2 = np.asarray(stamps_2, dtype=np.float64) + offset_2
    if len(s1) == 0 or len(s2) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.argsort(s2, kind="stable")
    s2s = s2[order]
    pos = np.clip(np.searchsorted(s2s, s1), 1, len(s2s) - 1) if len(s2s) > 1 else np.zeros(len(s1), dtype=np.int64)
    left = np.clip(pos - 1, 0, len(s2s) - 1)
    right = np.clip(pos, 0, len(s2s) - 1)
    dl, dr = np.abs(s2s[left] - s1), np.abs(s2s[right] - s1)
    nearest = np.where(dr < dl, right, left)
    diff = np.minimum(dl, dr)
    keep = diff <= max_diff
    return np.nonzero(keep)[0].astype(np.int64), order[nearest[keep]].astype(np.int64)


def associate(est: Trajectory, ref: Trajectory, max_diff: float = 0.01,
              offset: float = 0.0) -> tuple[Trajectory, Trajectory]:
    """Pairs of poses of ``est`` and ``ref`` at matching times (nearest within ``max_diff`` s), as evo associates:
    the shorter trajectory is matched against the longer one. ``offset`` is added to ``ref``'s timestamps."""
    if len(ref) >= len(est):  # evo: the estimate is the short side unless it has more poses
        i_est, i_ref = matching_time_indices(est.timestamps, ref.timestamps, max_diff, offset)
    else:
        i_ref, i_est = matching_time_indices(ref.timestamps, est.timestamps, max_diff, -offset)
    return est.subset(i_est), ref.subset(i_ref)
