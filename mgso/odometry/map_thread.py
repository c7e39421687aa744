"""The odometry's mapping half on a thread of its own (DSO's ``mappingLoop``, for real time).

:class:`MappingThread` is fed :class:`~mgso.odometry.records.TrackedFrame` messages by the tracking thread and maps
them in order with the odometry's ``map_frame``. When frames wait, the older ones are mapped as non-keyframes (traced
only) and the newest takes their keyframe request (DSO ``needToKetchupMapping``): a keyframe's window optimisation
no longer delays the frames behind it. With ``newest_keyframe`` a request counts only if its frame was tracked
against the window's newest keyframe (DSO ``needNewKFAfter >= frameHessians.back()->shell->id``): while the thread
makes a keyframe the tracker still tracks against the one before, the flow to it grows, and every frame tracked
then would ask for a keyframe again (real-time 7-Scenes runs made 116-130 keyframes where the same stream in order
makes 79; docs/tracking.md, "Keyframe requests against an older reference"). The messages for the Gaussian mapper
that mapping makes (``drain``) wait in :meth:`MappingThread.take_ready` for the tracking thread. An error on the
thread is kept and raised on the tracking thread by the next :meth:`submit`, :meth:`wait` or :meth:`stop`; after
it, queued frames only give their pyramids back (``release``).
"""

from __future__ import annotations

import collections
import queue
import threading
from collections.abc import Callable

from .records import TrackedFrame

__all__ = ["MappingThread"]


def _frames_queued(q: queue.Queue) -> bool:
    """Whether a frame (not the stop's ``None``) waits in ``q``."""
    with q.mutex:
        return any(t is not None for t in q.queue)


class MappingThread:
    """``map_frame(tracked)`` maps a frame; ``drain()`` (or ``None``: no messages) returns the messages it made;
    ``release(pyramid)`` gives a frame's pyramid back when it is not mapped."""

    def __init__(self, map_frame: Callable[[TrackedFrame], None], drain: Callable[[], list] | None,
                 release: Callable[[object], None], newest_keyframe: Callable[[], int] | None = None):
        self._map_frame = map_frame
        self._newest_keyframe = newest_keyframe   # on the thread: the window's newest keyframe id (-1: none)
        self._request: tuple[int, str] | None = None   # the open request: (its frame's reference, reason)
        self._drain = drain
        self._release = release
        self._queue: queue.Queue | None = None
        self._worker: threading.Thread | None = None
        self._error: BaseException | None = None
        self._ready: collections.deque = collections.deque()   # messages the thread has made, in order
        self.num_keyframe_requests_merged = 0   # keyframe requests a newer request replaced in the catch-up
        self.num_keyframe_requests_stale = 0    # requests dropped: tracked against a keyframe no longer the newest

    def submit(self, tracked: TrackedFrame) -> None:
        """Queue a tracked frame (the thread starts with the first)."""
        if self._worker is None or not self._worker.is_alive():
            self._queue = queue.Queue()
            self._worker = threading.Thread(target=self._loop, name="mgso-odometry-map", daemon=True)
            self._worker.start()
        self._queue.put(tracked)

    def wait(self) -> None:
        """Wait until every queued frame is mapped (then raise the thread's error, if any)."""
        if self._queue is not None:
            self._queue.join()
        self.raise_error()

    def stop(self) -> None:
        """Map what is queued, end the thread, raise its error if any."""
        if self._worker is not None and self._worker.is_alive():
            self._queue.put(None)
            self._worker.join()
        self._worker = None
        self.raise_error()

    def raise_error(self) -> None:
        if self._error is not None:
            raise self._error

    def add_ready(self, messages: list) -> None:
        """Messages made on the tracking thread (initialisation, a loss), in order behind the thread's."""
        self._ready.extend(messages)

    def take_ready(self) -> list:
        """The messages made so far, oldest first (each once)."""
        out = []
        while True:
            try:
                out.append(self._ready.popleft())
            except IndexError:
                return out

    def _loop(self) -> None:
        q = self._queue
        while True:
            batch = [q.get()]
            while True:
                try:
                    batch.append(q.get_nowait())
                except queue.Empty:
                    break
            for i, tracked in enumerate(batch):
                try:
                    if tracked is None:
                        return
                    if self._error is not None:  # after an error: only give the pyramids back
                        if tracked.pyramid is not None:
                            self._release(tracked.pyramid)
                        continue
                    # the newest frame waiting: none behind it in the batch, and none queued since (the stop's
                    # marker is no frame: the last frame before it still makes its keyframe)
                    self._decide_keyframe(tracked, last=not any(t is not None for t in batch[i + 1:])
                                          and not _frames_queued(q))
                    self._map_frame(tracked)
                    if self._drain is not None:
                        self._ready.extend(self._drain())
                except BaseException as e:  # handed to the tracking thread (process / finish raise it)
                    self._error = e
                finally:
                    q.task_done()

    def _decide_keyframe(self, tracked: TrackedFrame, last: bool) -> None:
        """DSO's ``mappingLoop``: a request waits as the open one (a newer request replaces it) and the newest frame
        in the queue makes the keyframe, if the request's frame was tracked against the newest keyframe."""
        if tracked.need_keyframe:
            if self._request is not None:
                self.num_keyframe_requests_merged += 1
            self._request = (tracked.record.tracking_ref, tracked.reason)
            tracked.need_keyframe = False
        if not last or self._request is None:
            return
        ref, reason = self._request
        self._request = None
        if self._newest_keyframe is not None and ref < self._newest_keyframe():
            self.num_keyframe_requests_stale += 1
            return
        tracked.need_keyframe, tracked.reason = True, reason
