"""Input and output: datasets (frames, calibration, ground truth), trajectories.

``open_sequence(path, calib=None, config=None)`` detects the layout of a dataset folder (TUM RGB-D, TUM monoVO,
EuRoC, KITTI, Replica, 7-Scenes, an image folder) or opens a video file, and returns a :class:`Sequence` of
:class:`Frame` (undistorted, photometrically corrected). See docs/datasets.md.
"""

from .detect import LAYOUTS, detect_layout, open_sequence
from .errors import DatasetError
from .euroc import EurocSequence
from .folder import ImageFolderSequence, VideoSequence
from .kitti import KittiSequence
from .paths import shared_data_dir
from .replica import ReplicaSequence
from .sequence import Frame, Sequence, poses_at_times
from .sevenscenes import SevenScenesSequence
from .trajectory import (Trajectory, TrajectoryError, associate, matching_time_indices, read_kitti, read_trajectory,
                         read_tum, write_kitti, write_tum)
from .tum import TumMonoSequence, TumRgbdSequence

__all__ = [
    "open_sequence", "detect_layout", "LAYOUTS", "DatasetError", "Frame", "Sequence", "poses_at_times",
    "TumRgbdSequence", "TumMonoSequence", "EurocSequence", "KittiSequence", "ReplicaSequence", "SevenScenesSequence",
    "ImageFolderSequence", "VideoSequence",
    "Trajectory", "TrajectoryError", "associate", "matching_time_indices", "read_kitti", "read_trajectory",
    "read_tum", "write_kitti", "write_tum", "shared_data_dir",
]
