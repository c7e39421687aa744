"""The odometry's mapping thread (mgso.odometry.map_thread), driven by stand-in frames: DSO's catch-up and errors."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest

from mgso.odometry.map_thread import MappingThread


def _frame(i, keyframe=True):
    return SimpleNamespace(index=i, need_keyframe=keyframe, pyramid=f"pyramid {i}")


def test_frames_that_waited_give_their_keyframe_request_to_the_newest():
    """The first frame is mapped while three more wait; they come out of the queue together, and only the newest of
    them keeps its keyframe request (DSO needToKetchupMapping). The control: frames queued one at a time after the
    previous is mapped each keep theirs."""
    gate, started = threading.Event(), threading.Event()
    mapped, made = [], []

    def map_frame(t):
        started.set()
        gate.wait(10)
        mapped.append((t.index, t.need_keyframe))
        made.append(f"message {t.index}")

    def drain():
        out = list(made)
        made.clear()
        return out

    mt = MappingThread(map_frame, drain, release=lambda p: None)
    mt.submit(_frame(0))
    assert started.wait(10)
    for i in (1, 2, 3):
        mt.submit(_frame(i))
    gate.set()
    mt.wait()
    assert mapped == [(0, True), (1, False), (2, False), (3, True)]
    assert mt.num_keyframe_requests_merged == 2
    assert mt.take_ready() == [f"message {i}" for i in range(4)] and mt.take_ready() == []
    mt.add_ready(["from the tracking thread"])
    for i in (4, 5):                                   # the control: nothing waits behind them
        mt.submit(_frame(i))
        mt.wait()
    mt.stop()
    assert mapped[4:] == [(4, True), (5, True)] and mt.num_keyframe_requests_merged == 2
    assert mt.take_ready() == ["from the tracking thread", "message 4", "message 5"]


def test_an_error_on_the_thread_is_raised_on_the_tracking_thread_and_later_frames_give_their_pyramids_back():
    gate = threading.Event()
    released = []

    def map_frame(t):
        gate.wait(10)
        if t.index == 1:
            raise RuntimeError("window broke at frame 1")

    mt = MappingThread(map_frame, None, release=released.append)
    for i in range(4):
        mt.submit(_frame(i, keyframe=False))
    gate.set()
    with pytest.raises(RuntimeError, match="frame 1"):
        mt.wait()
    assert released == ["pyramid 2", "pyramid 3"]
    with pytest.raises(RuntimeError, match="frame 1"):
        mt.stop()
    assert mt.take_ready() == []
