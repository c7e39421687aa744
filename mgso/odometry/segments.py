"""The common world of a run whose tracking was lost and started again (DSO resets; mgso chains).

After a tracking loss the odometry starts a new *segment* in a frame of its own, as DSO does after a reset: the
segment's first keyframe at the origin, inverse depths of mean 1 (DSO's thresholds assume that scale). For output
the segments are chained: segment ``k > 0`` is mapped into the common world by a similarity ``[[s R, t], [0, 1]]``
that the odometry computes when the segment starts (``Odometry._chain_segment``: its first keyframe at the last
reliable pose of segment ``k - 1``, its scale matched to that segment's last median depth). :class:`Segments` holds
those similarities and moves poses and points from a segment's frame into the common world.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Segments"]


class Segments:
    """Segment number -> the 4x4 similarity from its frame to the common world (segment 0: the identity)."""

    def __init__(self):
        self._sim: dict[int, np.ndarray] = {0: np.eye(4)}

    def __contains__(self, segment: int) -> bool:
        return int(segment) in self._sim

    def set(self, segment: int, similarity: np.ndarray) -> None:
        self._sim[int(segment)] = np.asarray(similarity, np.float64)

    def similarity(self, segment: int) -> np.ndarray:
        """4x4 similarity ``[[s R, t], [0, 1]]`` from a segment's frame to the common world (identity for 0 and for a
        segment not chained yet)."""
        return self._sim.get(int(segment), np.eye(4))

    def to_world(self, segment: int, cam_to_world: np.ndarray) -> np.ndarray:
        """A camera pose of ``segment`` in the common world (a rigid pose: the similarity's scale moves the camera
        centre only)."""
        S = self.similarity(segment)
        if segment == 0 or np.allclose(S, np.eye(4)):
            return np.asarray(cam_to_world, dtype=np.float64).copy()
        sc = float(np.cbrt(np.linalg.det(S[:3, :3])))
        R = S[:3, :3] / sc
        out = np.eye(4)
        out[:3, :3] = R @ cam_to_world[:3, :3]
        out[:3, 3] = S[:3, :3] @ cam_to_world[:3, 3] + S[:3, 3]
        return out

    def points_to_world(self, positions: np.ndarray, segment: int) -> np.ndarray:
        """Points ``[M, 3]`` of one segment in the common world (float64)."""
        S = self.similarity(segment)
        return np.asarray(positions, np.float64) @ S[:3, :3].T + S[:3, 3]

    def mixed_to_world(self, positions: np.ndarray, segments: np.ndarray) -> np.ndarray:
        """Points ``[M, 3]`` each of its own segment (``segments [M]``) in the common world (float64)."""
        pos = np.asarray(positions, np.float64)
        out = pos.copy()
        for sg in np.unique(segments):
            S = self.similarity(int(sg))
            m = segments == sg
            out[m] = pos[m] @ S[:3, :3].T + S[:3, 3]
        return out
