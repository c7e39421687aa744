"""What the odometry keeps of each frame and keyframe, what it tells its observers, and the message from its tracking
half to its mapping half (DSO's ``FrameShell`` and the arguments of its output wrapper's calls).

Poses: :attr:`FrameRecord.cam_to_world` and :attr:`KeyframeRecord.cam_to_world` are in the frame of their segment
(:mod:`mgso.odometry.segments`); :class:`FrameResult`, :class:`KeyframeEvent` and :class:`WindowUpdate` are in the
common world.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np

from mgso_kernels.image import ImagePyramid

from ..tracking.coarse_tracker import TrackResult
from ..tracking.immature_points import ActivationResult, TraceCounts
from ..tracking.initializer import InitResult

__all__ = ["FrameStatus", "LossReason", "FrameRecord", "KeyframeRecord", "TrackingLost", "KeyframeEvent",
           "WindowUpdate", "FrameResult", "TrackedFrame"]


class FrameStatus(str, Enum):
    FIRST_FRAME = "first_frame"  # became the initialiser's first frame (pose: the segment's origin once initialised)
    INITIALIZING = "initializing"  # aligned by the initialiser, no pose kept (as DSO)
    INITIALIZED = "initialized"  # the initialiser finished on this frame: the second keyframe
    TRACKED = "tracked"
    LOST = "lost"  # tracking failed on this frame; a new segment starts
    INIT_FAILED = "init_failed"  # the initialiser gave up; it restarts from this frame
    DUPLICATE = "duplicate"  # the same image as the previous frame: its pose is the previous frame's (not tracked)


class LossReason(str, Enum):
    NON_FINITE = "non_finite"  # pose, affine or RMSE not finite
    NO_HYPOTHESIS = "no_hypothesis"  # no motion hypothesis converged within the checks
    RESIDUAL = "residual"  # RMSE above lost_rmse_factor x the reference's first RMSE
    INLIERS = "inliers"  # too few reference points within the cutoff
    JUMP = "jump"  # farther from the reference than lost_max_translation x its median depth, or faster than
    # lost_max_speed_factor x the segment's recent typical step (per frame of the source)


@dataclass
class FrameRecord:
    """Per frame (DSO ``FrameShell``). ``cam_to_world`` (in its segment's frame) is None while the frame has no
    pose."""

    index: int
    timestamp: float
    segment: int
    status: FrameStatus
    cam_to_world: np.ndarray | None = None
    cam_to_tracking_ref: np.ndarray | None = None
    tracking_ref: int = -1  # keyframe id it was tracked against (-1: none)
    affine: tuple[float, float] = (0.0, 0.0)
    keyframe_id: int = -1  # its own keyframe id when it is a keyframe

    @property
    def pose_valid(self) -> bool:
        return self.cam_to_world is not None


@dataclass
class KeyframeRecord:
    """Per keyframe; ``cam_to_world`` in its segment's frame (the window's estimate while in the window)."""

    keyframe_id: int
    frame_index: int
    timestamp: float
    segment: int
    cam_to_world: np.ndarray
    in_window: bool = True


@dataclass
class TrackingLost:
    """What ``Observer.on_tracking_lost`` gets."""

    frame_index: int
    timestamp: float
    segment: int  # the segment that ended
    reason: LossReason
    rmse: float
    first_rmse: float  # the RMSE it was compared with (TrackResult.baseline_rmse)
    inlier_ratio: float
    message: str = ""


@dataclass
class KeyframeEvent:
    """What ``Observer.on_keyframe`` gets."""

    keyframe_id: int
    frame_index: int
    timestamp: float
    segment: int
    cam_to_world: np.ndarray
    reason: str
    activation: ActivationResult | None
    new_immature: int
    window: dict  # Window.describe()


@dataclass
class WindowUpdate:
    """What ``Observer.on_window_optimized`` gets: the window's keyframes after the back end ran."""

    keyframe_ids: list[int]
    cam_to_world: np.ndarray  # [k, 4, 4]
    active_points: np.ndarray  # [n, 3] world positions
    active_colors: np.ndarray  # [n, 3]
    optimization: Any  # the back end's result value


@dataclass
class FrameResult:
    """What :meth:`Odometry.process` returns for a frame (and ``Observer.on_frame`` gets)."""

    index: int
    timestamp: float
    status: FrameStatus
    segment: int
    cam_to_world: np.ndarray | None  # pose at tracking time in the common world (refined later; Odometry.frames)
    is_keyframe: bool
    keyframe_reason: str = ""
    track: TrackResult | None = None
    init: InitResult | None = None
    lost: TrackingLost | None = None
    trace: TraceCounts | None = None
    time_track_s: float = 0.0
    time_map_s: float = 0.0
    affine: tuple[float, float] = (0.0, 0.0)  # DSO's (a, b) of the frame, 0-255 scale
    keyframe_id: int = -1  # its keyframe id when it became a keyframe
    exposure_ms: float | None = None  # the frame's exposure time (None: unknown)
    messages: tuple = ()  # what it emits for the Gaussian mapper, in order (with ``emit_messages``)

    @property
    def ok(self) -> bool:
        return self.cam_to_world is not None

    @property
    def seconds(self) -> float:
        """The odometry's time on the frame (tracking and mapping halves)."""
        return self.time_track_s + self.time_map_s


@dataclass
class TrackedFrame:
    """The message from the tracking half to the mapping half (DSO ``deliverTrackedFrame``)."""

    record: FrameRecord
    pyramid: ImagePyramid | None  # owned by the message until mapped; None for a duplicate frame
    exposure: float
    rgb: Any  # callable or array giving the frame's RGB (only read for keyframes)
    need_keyframe: bool
    reason: str
    result: FrameResult
    initialize: InitResult | None = None  # the initialiser finished on this frame: map() starts the window
