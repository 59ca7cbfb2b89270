"""Synthetic data with ground truth: the low-light tunnel recording and its pose graph."""

from .. import _config  # noqa: F401
from ._camera import CameraConfig, CameraSimulator
from ._faults import (
    CameraDark,
    NanSamples,
    SensorDropout,
    TimeJump,
    Truncate,
    inject_faults,
    truncate_file,
    write_faulty,
)
from ._imu import ImuConfig, synthesize_imu
from ._lidar import LidarConfig, LidarSimulator, scan_pattern
from ._posegraph import SyntheticPoseGraph, tunnel_pose_graph
from ._recording import T0_NS, SimConfig, Simulation, simulate_tunnel
from ._texture import LightingConfig, SurfaceAtlas
from ._trajectory import MotionConfig, TunnelTrajectory
from ._tunnel import Tunnel, TunnelConfig

__all__ = ["SyntheticPoseGraph", "tunnel_pose_graph"]
__all__ += [
    "T0_NS",
    "CameraConfig",
    "CameraSimulator",
    "ImuConfig",
    "LidarConfig",
    "LidarSimulator",
    "LightingConfig",
    "MotionConfig",
    "SimConfig",
    "Simulation",
    "SurfaceAtlas",
    "Tunnel",
    "TunnelConfig",
    "TunnelTrajectory",
    "scan_pattern",
    "simulate_tunnel",
    "synthesize_imu",
]
__all__ += [
    "CameraDark",
    "NanSamples",
    "SensorDropout",
    "TimeJump",
    "Truncate",
    "inject_faults",
    "truncate_file",
    "write_faulty",
]
