"""The fused estimator: measurement records -> keyframe factor graph -> incremental solve.

:class:`Estimator` consumes records (:mod:`jaxslam.measurements`) from a recording or a live
driver; :func:`run_recording` runs it over a recording and writes a results folder
(trajectories, map, metrics, plots). Configuration: :class:`PipelineConfig` (YAML sections
``rig``, ``keyframe``, ``imu``, ``lidar``, ``vision``, ``loop``, ``solver``).
"""

from .. import _config  # noqa: F401
from ._config import (
    ImuConfig,
    KeyframeConfig,
    LidarConfig,
    LoopConfig,
    PipelineConfig,
    RigConfig,
    SolverOptions,
    VisionConfig,
    config_from_dict,
    find_rig,
    load_config,
    load_rig,
    save_config,
)
from ._estimator import Estimator, Keyframe
from ._run import run_recording

__all__ = [
    "Estimator",
    "ImuConfig",
    "Keyframe",
    "KeyframeConfig",
    "LidarConfig",
    "LoopConfig",
    "PipelineConfig",
    "RigConfig",
    "SolverOptions",
    "VisionConfig",
    "config_from_dict",
    "find_rig",
    "load_config",
    "load_rig",
    "run_recording",
    "save_config",
]
