"""Readers and writers: pose graphs (g2o and GTSAM's text formats) and trajectories (TUM,
KITTI). Every reader raises :class:`~jaxslam.errors.InputFormatError` naming the file and line
for bad input, and writes floats at full float64 precision."""

from .. import _config  # noqa: F401
from ._g2o import GTSAM_SUFFIXES, IGNORED_TAGS, TAGS, quaternion_from_rpy, read_g2o, rpy_from_quaternion, write_g2o
from ._parse import QUATERNION_NORM_TOLERANCE
from ._posegraph import FIX_SIGMA, PoseGraph, chain_odometry
from ._trajectory import ROTATION_TOLERANCE, Trajectory, read_kitti, read_trajectory, read_tum, write_kitti, write_tum

__all__ = [
    "FIX_SIGMA",
    "GTSAM_SUFFIXES",
    "IGNORED_TAGS",
    "QUATERNION_NORM_TOLERANCE",
    "ROTATION_TOLERANCE",
    "TAGS",
    "PoseGraph",
    "Trajectory",
    "chain_odometry",
    "quaternion_from_rpy",
    "read_g2o",
    "read_kitti",
    "read_trajectory",
    "read_tum",
    "rpy_from_quaternion",
    "write_g2o",
    "write_kitti",
    "write_tum",
]
from ._kitti import KittiRecording
from ._recording import (
    EurocRecording,
    Recording,
    StreamInfo,
    open_recording,
    read_image_file,
    recording_formats,
    register_format,
)
from ._rosbag import LIVOX_CUSTOM_MSG, LIVOX_CUSTOM_POINT, RosbagRecording, livox_types
from ._writers import (
    TOPICS,
    EurocWriter,
    RecordingWriter,
    RosbagWriter,
    image_topic,
    open_writer,
    read_pcd,
    read_ply,
    write_pcd,
    write_ply,
)

__all__ += [
    "LIVOX_CUSTOM_MSG",
    "LIVOX_CUSTOM_POINT",
    "EurocRecording",
    "KittiRecording",
    "Recording",
    "RosbagRecording",
    "StreamInfo",
    "livox_types",
    "open_recording",
    "read_image_file",
    "recording_formats",
    "register_format",
]

__all__ += [
    "TOPICS",
    "EurocWriter",
    "RecordingWriter",
    "RosbagWriter",
    "image_topic",
    "open_writer",
    "read_pcd",
    "read_ply",
    "write_pcd",
    "write_ply",
]
