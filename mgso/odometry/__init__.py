"""DSO's odometry: frames in one by one, a pose for every frame out, and the messages for the Gaussian map.

The parts, split by concern as DSO splits its ``FullSystem``:

- :mod:`~mgso.odometry.odometry`: :class:`Odometry`, the loop (tracking half and mapping half, the initialisation,
  keyframes, tracking loss and the chaining of segments);
- :mod:`~mgso.odometry.records`: what it keeps of each frame and keyframe and what it tells its observers;
- :mod:`~mgso.odometry.segments`: the similarities that put the segments after a tracking loss into one world;
- :mod:`~mgso.odometry.outbox`: its messages to the mapper (:mod:`mgso.messages`), made from the window;
- :mod:`~mgso.odometry.map_thread`: the mapping half on a thread of its own (real time);
- :mod:`~mgso.odometry.back_end`: what it asks of the window's back end (the bundle adjustment or the fixed one).

The kernels it drives are in :mod:`mgso.tracking` (front end) and :mod:`mgso.window` (the window and its bundle
adjustment).
"""

from .back_end import WindowBackEnd, make_back_end
from .odometry import Odometry, geometry_for
from .records import (FrameRecord, FrameResult, FrameStatus, KeyframeEvent, KeyframeRecord, LossReason,
                      TrackedFrame, TrackingLost, WindowUpdate)

__all__ = [
    "Odometry", "FrameStatus", "FrameResult", "FrameRecord", "KeyframeRecord", "TrackedFrame", "TrackingLost",
    "LossReason", "KeyframeEvent", "WindowUpdate", "WindowBackEnd", "make_back_end", "geometry_for",
]
