"""Factor types: prior, between (LiDAR / visual / loop), IMU, reprojection."""

from .. import _config  # noqa: F401
from ._between import BetweenFactor, PriorFactor
from ._reprojection import ReprojectionFactor, pinhole_project, project_pinhole

__all__ = ["BetweenFactor", "PriorFactor"]
__all__ += ["ReprojectionFactor", "pinhole_project", "project_pinhole"]
