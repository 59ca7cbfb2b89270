"""NumPy SO(3) / SE(3) for the LiDAR hot loop: the shared host-side helpers of
:mod:`jaxslam.lie.host` under the names this package uses (tangent [rotation, translation],
poses as 4 x 4 matrices, right perturbation)."""

from __future__ import annotations

from ..lie.host import inverse as se3_inverse
from ..lie.host import make_poses as make_pose
from ..lie.host import orthonormalize, se3_exp, se3_log, so3_exp, so3_left_jacobian, so3_log, transform_points
from ..lie.host import skew as hat

__all__ = [
    "hat",
    "make_pose",
    "orthonormalize",
    "se3_exp",
    "se3_inverse",
    "se3_log",
    "so3_exp",
    "so3_left_jacobian",
    "so3_log",
    "transform_points",
]
