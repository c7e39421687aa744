"""Input and output: datasets (frames, calibration, ground truth), trajectories.

``open_sequence(path, calib=None, config=None)`` detects the layout of a dataset folder (TUM RGB-D, TUM monoVO,
EuRoC, KITTI, Replica, 7-Scenes, an image folder) or opens a video file, and returns a :class:`Sequence` of
:class:`Frame` (undistorted, photometrically corrected, with the mask of pixels that have a source); a live camera or
stream (``camera:N``, ``rtsp://...``) opens as a :class:`LiveSource` (frames as they come, no length; docs/live.md). Calibration files
are read here too (:func:`read_camera_file`; each dataset's format beside its reader). See docs/datasets.md.
"""

from .calibration import load_calibration, read_camera_file, read_dso_camera_txt, read_plain_intrinsics
from .detect import LAYOUTS, detect_layout, open_sequence
from .errors import DatasetError
from .euroc import EurocSequence, read_euroc_sensor_yaml
from .folder import ImageFolderSequence, VideoSequence
from .kitti import KittiSequence, read_kitti_calib
from .live import LiveSource, is_live_source
from .paths import shared_data_dir
from .replica import REPLICA_NICE_SLAM, ReplicaSequence, read_replica_cam_params
from .sequence import Frame, Sequence, poses_at_times
from .sevenscenes import SEVEN_SCENES_COLOR, SevenScenesSequence
from .trajectory import (Trajectory, TrajectoryError, associate, matching_time_indices, read_kitti, read_trajectory,
                         read_tum, write_kitti, write_tum)
from .tum import TUM_RGBD_FREIBURG, TumMonoSequence, TumRgbdSequence, tum_rgbd_default

__all__ = [
    "open_sequence", "detect_layout", "LAYOUTS", "DatasetError", "Frame", "Sequence", "poses_at_times",
    "TumRgbdSequence", "TumMonoSequence", "EurocSequence", "KittiSequence", "ReplicaSequence", "SevenScenesSequence",
    "ImageFolderSequence", "VideoSequence", "LiveSource", "is_live_source",
    "Trajectory", "TrajectoryError", "associate", "matching_time_indices", "read_kitti", "read_trajectory",
    "read_tum", "write_kitti", "write_tum", "shared_data_dir",
    "read_camera_file", "read_dso_camera_txt", "read_plain_intrinsics", "load_calibration", "read_euroc_sensor_yaml",
    "read_kitti_calib", "read_replica_cam_params", "tum_rgbd_default", "TUM_RGBD_FREIBURG", "REPLICA_NICE_SLAM",
    "SEVEN_SCENES_COLOR",
]
