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
