"""Factor types: prior, between (LiDAR / visual / loop), IMU, reprojection."""

from .. import _config  # noqa: F401
from ._between import BetweenFactor, PriorFactor

__all__ = ["BetweenFactor", "PriorFactor"]
