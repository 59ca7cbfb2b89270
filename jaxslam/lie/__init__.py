"""Matrix Lie groups as batched, immutable JAX PyTrees.

=====  ==========================  ===================  ==========================
group  params (last axis)          tangent              notes
=====  ==========================  ===================  ==========================
SO2    (cos, sin)                  (theta,)
SE2    (cos, sin, x, y)            (theta, rx, ry)      GTSAM Pose2 uses (x, y, theta)
SO3    (qw, qx, qy, qz)            (wx, wy, wz)
SE3    (qw, qx, qy, qz, x, y, z)   (wx, wy, wz, rx..)   same order as GTSAM Pose3
=====  ==========================  ===================  ==========================

All perturbations are on the right: ``x.retract(d) == x @ G.exp(d)``.
"""

from .. import _config  # noqa: F401  (enables float64)
from ._base import LieGroup
from ._se2 import SE2
from ._se3 import SE3
from ._so2 import SO2
from ._so3 import SO3
from ._utils import mm, mT, mv, skew

__all__ = ["SE2", "SE3", "SO2", "SO3", "LieGroup", "mT", "mm", "mv", "skew"]
