"""Typed variables, values, noise models, robust kernels and the vectorised factor base."""

from .. import _config  # noqa: F401
from ._factor import (
    Factor,
    Linearized,
    autodiff_jacobians,
    factor_cost,
    factor_dataclass,
    linearize,
    whiten_and_weight,
)
from ._marginal import MarginalFactor
from ._noise import Gaussian, information_is_valid
from ._robust import KERNELS, Cauchy, GemanMcClure, Huber, RobustKernel, Tukey
from ._values import Values, lookup_rows
from ._variables import (
    BiasVar,
    Point2Var,
    Point3Var,
    Pose2Var,
    Pose3Var,
    PoseVar,
    Rot3Var,
    ScaleVar,
    Variable,
    VelocityVar,
)

__all__ = [
    "KERNELS",
    "BiasVar",
    "Cauchy",
    "Factor",
    "Gaussian",
    "GemanMcClure",
    "Huber",
    "Linearized",
    "MarginalFactor",
    "Point2Var",
    "Point3Var",
    "Pose2Var",
    "Pose3Var",
    "PoseVar",
    "RobustKernel",
    "Rot3Var",
    "ScaleVar",
    "Tukey",
    "Values",
    "Variable",
    "VelocityVar",
    "autodiff_jacobians",
    "factor_cost",
    "factor_dataclass",
    "information_is_valid",
    "linearize",
    "lookup_rows",
    "whiten_and_weight",
]
