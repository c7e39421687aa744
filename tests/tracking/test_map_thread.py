"""The odometry's mapping thread (mgso.odometry.map_thread), driven by stand-in frames: DSO's catch-up and errors."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest

from mgso.odometry.map_thread import MappingThread


def _frame(i, keyframe=True, ref=0):
    return SimpleNamespace(index=i, need_keyframe=keyframe, reason="flow" if keyframe else "",
                           record=SimpleNamespace(tracking_ref=ref), pyramid=f"pyramid {i}")


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


def _keyframe_maker(newest, gate=None, started=None):
    """A stand-in map_frame: a frame mapped with its request open makes the next keyframe (newest id + 1)."""
    mapped = []

    def map_frame(t):
        if started is not None:
            started.set()
        if gate is not None:
            gate.wait(10)
        mapped.append((t.index, t.need_keyframe, t.reason if t.need_keyframe else ""))
        if t.need_keyframe:
            newest[0] += 1
    return map_frame, mapped


@pytest.mark.parametrize("current_only", [True, False])
def test_requests_made_against_an_older_keyframe_are_dropped(current_only):
    """Frame 0 (tracked against keyframe 0) makes keyframe 1 while frames 1 and 2 wait, tracked against keyframe 0 as
    well, each asking again (the flow to keyframe 0 only grows): DSO drops their request (needNewKFAfter 0 < the
    newest keyframe 1), and frame 3, tracked against keyframe 1, makes keyframe 2. The control
    (``newest_keyframe=None``, every request counts) makes a keyframe of frame 2 as well."""
    newest = [0]
    gate, started = threading.Event(), threading.Event()
    map_frame, mapped = _keyframe_maker(newest, gate, started)
    mt = MappingThread(map_frame, None, release=lambda p: None,
                       newest_keyframe=(lambda: newest[0]) if current_only else None)
    mt.submit(_frame(0, ref=0))
    assert started.wait(10)
    mt.submit(_frame(1, ref=0))
    mt.submit(_frame(2, ref=0))
    gate.set()
    mt.wait()
    mt.submit(_frame(3, ref=newest[0]))
    mt.stop()
    assert mapped[:2] == [(0, True, "flow"), (1, False, "")]
    assert mt.num_keyframe_requests_merged == 1
    if current_only:
        assert mapped[2:] == [(2, False, ""), (3, True, "flow")] and newest[0] == 2
        assert mt.num_keyframe_requests_stale == 1
    else:
        assert mapped[2:] == [(2, True, "flow"), (3, True, "flow")] and newest[0] == 3
        assert mt.num_keyframe_requests_stale == 0


def test_the_newest_frame_takes_a_request_it_did_not_make():
    """Frame 1 asks for a keyframe (against the newest, 0) while frame 2, queued behind it, does not: the newest frame
    waiting makes the keyframe, with frame 1's reason (DSO keeps needNewKFAfter, and maps the last frame)."""
    newest = [0]
    gate, started = threading.Event(), threading.Event()
    map_frame, mapped = _keyframe_maker(newest, gate, started)
    mt = MappingThread(map_frame, None, release=lambda p: None, newest_keyframe=lambda: newest[0])
    mt.submit(_frame(0, keyframe=False))
    assert started.wait(10)
    asks = _frame(1, ref=0)
    asks.reason = "brightness"
    mt.submit(asks)
    mt.submit(_frame(2, keyframe=False))
    gate.set()
    mt.stop()
    assert mapped == [(0, False, ""), (1, False, ""), (2, True, "brightness")]
    assert mt.num_keyframe_requests_merged == 0 and mt.num_keyframe_requests_stale == 0


def test_the_stops_marker_is_no_frame_behind_the_last():
    """The thread asks whether a frame waits behind the one it maps: the stop's ``None`` is not one (the last frame
    before a stop keeps its keyframe request, whenever the marker arrives), a frame is."""
    import queue

    from mgso.odometry.map_thread import _frames_queued

    q = queue.Queue()
    assert not _frames_queued(q)
    q.put(None)
    assert not _frames_queued(q)
    q.put(_frame(7))
    assert _frames_queued(q)
