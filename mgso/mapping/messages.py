"""Moved: the odometry-mapper messages are :mod:`mgso.messages` (a neutral module both halves import, issue 44).

This name stays so that code and pickled recordings (``profiles/mapping.py``'s cache) made before the move still
find the classes; new code imports :mod:`mgso.messages`.
"""

from mgso.messages import (KeyframeMessage, LoopCorrection, MapperMessage, PointKind,  # noqa: F401
                           PointsMessage, PoseUpdate, Stop, check_points, frozen_array, map_exposure,
                           sim3_apply_to_pose)

__all__ = ["KeyframeMessage", "PoseUpdate", "PointsMessage", "LoopCorrection", "Stop", "MapperMessage",
           "PointKind", "map_exposure", "sim3_apply_to_pose"]
