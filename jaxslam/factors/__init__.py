"""Factor types: prior, between (LiDAR / visual / loop), IMU, reprojection."""

from .. import _config  # noqa: F401
from ._between import BetweenFactor, PriorFactor
from ._direction import RelativeDirectionFactor
from ._imu import BiasRandomWalkFactor, ImuFactor, ImuFactorComponentWise, predict_imu_state
from ._imu_params import PreintegrationParams
from ._preintegration import ImuIntervals, PreintegratedImu, cut_imu_stream, preintegrate, preintegrate_stream
from ._reprojection import ReprojectionFactor, pinhole_project, project_pinhole
from ._scaled import ScaledBetweenFactor

__all__ = ["BetweenFactor", "PriorFactor", "RelativeDirectionFactor", "ScaledBetweenFactor"]
__all__ += ["ReprojectionFactor", "pinhole_project", "project_pinhole"]
__all__ += [
    "BiasRandomWalkFactor",
    "ImuFactor",
    "ImuFactorComponentWise",
    "ImuIntervals",
    "PreintegratedImu",
    "PreintegrationParams",
    "cut_imu_stream",
    "predict_imu_state",
    "preintegrate",
    "preintegrate_stream",
]
