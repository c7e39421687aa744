"""Stand-ins around an odometry that the system tests share."""

import os
import signal
import threading
import time


class _Wrapped:
    """Everything but what a subclass overrides goes to the wrapped odometry."""

    def __init__(self, odo):
        self.odo = odo

    def __getattr__(self, name):
        return getattr(self.odo, name)


class SlowOdometry(_Wrapped):
    """An odometry that takes ``seconds`` a frame (frames arrive faster than it can take them)."""

    def __init__(self, odo, seconds):
        super().__init__(odo)
        self.seconds = seconds

    def process(self, frame):
        time.sleep(self.seconds)
        return self.odo.process(frame)


class KeyframeRequestingOdometry(_Wrapped):
    """DSO's mapping thread (real time): the tracker asks for a keyframe on frame after frame while the thread is
    busy, and the thread makes only the newest waiting frame a keyframe. Here every frame asks (``is_keyframe``);
    the wrapped odometry's keyframes are the ones made, and the requests it did not grant are counted as the
    mapping thread counts them (``num_keyframe_requests_merged``)."""

    map_thread = True

    def __init__(self, odo):
        super().__init__(odo)
        self.num_keyframe_requests_merged = 0

    def process(self, frame):
        import dataclasses

        r = self.odo.process(frame)
        self.num_keyframe_requests_merged += not r.is_keyframe
        return dataclasses.replace(r, is_keyframe=True)


class ThreadsSeenOdometry(_Wrapped):
    """An odometry that records the CPU threads its kernel launches would use at each frame."""

    def __init__(self, odo):
        super().__init__(odo)
        self.threads = []

    def process(self, frame):
        from mgso_kernels import runtime

        self.threads.append(runtime.cpu_threads())
        return self.odo.process(frame)


class LoadOrderOdometry(_Wrapped):
    """An odometry with ``load_kernels`` that records, in order, when its kernels were loaded and each frame."""

    def __init__(self, odo):
        super().__init__(odo)
        self.events = []

    def load_kernels(self):
        self.events.append("load")

    def process(self, frame):
        self.events.append("frame")
        return self.odo.process(frame)


class PausedMapperOdometry(_Wrapped):
    """An odometry that, before its first frame, stops the mapper's process (SIGSTOP, POSIX) of ``system`` (set it
    after building the System) for ``seconds``: the keyframes then pile up in the image ring and the queue whatever
    the machine's speed. ``timer`` resumes the process; join it before checking the run."""

    def __init__(self, odo, seconds):
        super().__init__(odo)
        self.seconds = seconds
        self.system = None
        self.timer = None

    def process(self, frame):
        if self.timer is None:
            pid = self.system.mapper._proc.pid
            os.kill(pid, signal.SIGSTOP)
            self.timer = threading.Timer(self.seconds, os.kill, (pid, signal.SIGCONT))
            self.timer.start()
        return self.odo.process(frame)
