"""Observer protocol: how the core reports what happens without printing or drawing.

The core (tracking, window, mapping, system) calls these hooks; viewers, writers, progress bars and timers subclass
:class:`Observer` and override what they need. Every hook is a no-op by default (DSO's ``Output3DWrapper``). Hooks
are called from the thread that produced the event (the mapping thread for map events) and must not block for long
or mutate what they are given.
"""

from __future__ import annotations

import logging
from typing import Any, Iterable

__all__ = ["Observer", "ObserverList", "no_progress"]

log = logging.getLogger(__name__)


class Observer:
    """No-op base class. Arguments are typed result/message objects from the subsystem that emits them."""

    def on_sequence_start(self, info: Any) -> None:
        """A run starts: ``info`` describes the sequence (layout, frame count, calibration)."""

    def on_frame(self, result: Any) -> None:
        """A frame was tracked (or failed to be): ``result`` is the tracker's result value."""

    def on_keyframe(self, keyframe: Any) -> None:
        """A new keyframe was created."""

    def on_tracking_lost(self, event: Any) -> None:
        """Tracking was lost; the system re-initialises and starts a new segment."""

    def on_window_optimized(self, update: Any) -> None:
        """The sliding window was optimised: refined keyframe poses and points."""

    def on_points_marginalized(self, points: Any) -> None:
        """Points left the window for good (the DSO point cloud grows)."""

    def on_loop_closed(self, correction: Any) -> None:
        """Loop closure moved keyframes (a :class:`~mgso.messages.LoopCorrection`: each keyframe's Sim(3)
        from the world it had to the corrected one). Messages before this one were in the old world, those after
        it are in the corrected one; the odometry's own frame results stay in its world."""

    def on_map_updated(self, stats: Any) -> None:
        """The Gaussian map trained / densified; ``stats`` says how."""

    def on_sequence_end(self, summary: Any) -> None:
        """The run finished; ``summary`` carries the final figures."""


class ObserverList(Observer):
    """Fans every hook out to several observers; an observer that raises is logged and does not stop the core."""

    def __init__(self, observers: Iterable[Observer] = ()):
        self._observers = list(observers)

    def add(self, observer: Observer) -> None:
        self._observers.append(observer)

    def __iter__(self):
        return iter(self._observers)

    def __len__(self) -> int:
        return len(self._observers)

    def _call(self, name: str, arg: Any) -> None:
        for obs in self._observers:
            try:
                getattr(obs, name)(arg)
            except Exception:  # an observer must never take the SLAM core down
                log.exception("observer %s failed in %s", type(obs).__name__, name)

    def on_sequence_start(self, info):
        self._call("on_sequence_start", info)

    def on_frame(self, result):
        self._call("on_frame", result)

    def on_keyframe(self, keyframe):
        self._call("on_keyframe", keyframe)

    def on_tracking_lost(self, event):
        self._call("on_tracking_lost", event)

    def on_window_optimized(self, update):
        self._call("on_window_optimized", update)

    def on_points_marginalized(self, points):
        self._call("on_points_marginalized", points)

    def on_loop_closed(self, correction):
        self._call("on_loop_closed", correction)

    def on_map_updated(self, stats):
        self._call("on_map_updated", stats)

    def on_sequence_end(self, summary):
        self._call("on_sequence_end", summary)


class _NoBar:
    """A progress bar that shows nothing (``update``, ``set_postfix``, ``close``, a context manager)."""

    def update(self, n=1):
        pass

    def set_postfix(self, *args, **kwargs):
        pass

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def no_progress(total: int, desc: str) -> _NoBar:
    """The default of every ``progress(total, desc)`` argument (the CLI passes tqdm bars): shows nothing."""
    return _NoBar()
