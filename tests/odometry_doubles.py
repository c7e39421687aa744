"""Stand-ins around an odometry that the system tests share."""

import time


class SlowOdometry:
    """An odometry that takes ``seconds`` a frame (frames arrive faster than it can take them)."""

    def __init__(self, odo, seconds):
        self.odo, self.seconds = odo, seconds

    def process(self, frame):
        time.sleep(self.seconds)
        return self.odo.process(frame)

    def __getattr__(self, name):
        return getattr(self.odo, name)


class ThreadsSeenOdometry:
    """An odometry that records the CPU threads its kernel launches would use at each frame."""

    def __init__(self, odo):
        self.odo, self.threads = odo, []

    def process(self, frame):
        from mgso_kernels import runtime

        self.threads.append(runtime.cpu_threads())
        return self.odo.process(frame)

    def __getattr__(self, name):
        return getattr(self.odo, name)


class LoadOrderOdometry:
    """An odometry with ``load_kernels`` that records, in order, when its kernels were loaded and each frame."""

    def __init__(self, odo):
        self.odo, self.events = odo, []

    def load_kernels(self):
        self.events.append("load")

    def process(self, frame):
        self.events.append("frame")
        return self.odo.process(frame)

    def __getattr__(self, name):
        return getattr(self.odo, name)
