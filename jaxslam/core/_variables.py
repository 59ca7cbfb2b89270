"""Typed variable keys.

A variable *type* declares a manifold (its parameter layout, tangent dimension, retraction);
a variable *instance* names a batch of ids of that type: ``PoseVar(np.arange(10))`` is the
poses 0..9. Ids are arbitrary non-negative integers (g2o vertex ids, keyframe indices).

==============  =======================  =====  =======================================
type            parameters               dof    notes
==============  =======================  =====  =======================================
Pose3Var        SE3 (qw qx qy qz x y z)  6      tangent [rotation, translation]
Pose2Var        SE2 (cos sin x y)        3      tangent [theta, x, y]
Rot3Var         SO3 (qw qx qy qz)        3
Point3Var       R^3                      3
Point2Var       R^2                      2
VelocityVar     R^3                      3      world-frame velocity
BiasVar         R^6                      6      IMU bias (acc xyz, gyro xyz), GTSAM order
ScaleVar        R^1                      1      log of a length scale (a sensor's scale bias)
==============  =======================  =====  =======================================
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax.numpy as jnp
import numpy as np
from jax import Array

from .._pytree import register_typed
from ..lie import SE2, SE3, SO3, LieGroup


@dataclasses.dataclass(frozen=True, eq=False)
class Variable:
    """A batch of ids of one variable type. A PyTree with the ids as its one leaf.

    Compared and hashed by identity (``eq=False``), so instances can key the dict given to
    :meth:`Values.create` (a field-wise hash would fail on the id array)."""

    ids: Any

    group: ClassVar[type[LieGroup] | None] = None
    param_dim: ClassVar[int]
    tangent_dim: ClassVar[int]

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        register_typed(cls, ["ids"])  # see jaxslam._pytree: types must not compare equal

    def __post_init__(self) -> None:
        # Only user-facing containers are validated: PyTree unflattening passes tracers,
        # vmap axis specs and other placeholders through here too.
        if (isinstance(self.ids, (np.ndarray, list, tuple)) and not isinstance(self.ids, np.ndarray)) or (
            isinstance(self.ids, np.ndarray) and self.ids.dtype != object
        ):
            ids = np.asarray(self.ids)
            if ids.dtype.kind not in "iu":
                raise TypeError(f"{type(self).__name__} ids must be integers, got dtype {ids.dtype}")
            if ids.ndim > 1:
                raise ValueError(f"{type(self).__name__} ids must be a scalar or 1-D, got shape {ids.shape}")
            if ids.size and ids.min() < 0:
                raise ValueError(f"{type(self).__name__} ids must be >= 0, got {int(ids.min())}")
            object.__setattr__(self, "ids", ids.astype(np.int64).reshape(-1))

    def __len__(self) -> int:
        return int(np.shape(self.ids)[0])

    # --- manifold operations on raw parameter arrays (*batch, param_dim) ----------------
    @classmethod
    def identity_params(cls) -> np.ndarray:
        if cls.group is None:
            return np.zeros(cls.param_dim)
        return np.asarray(cls.group.identity().params)

    @classmethod
    def wrap(cls, params: Array) -> Any:
        """Parameters as the object a residual function sees (a Lie group or the array)."""
        return params if cls.group is None else cls.group(params)

    @classmethod
    def unwrap(cls, value: Any) -> Array:
        if cls.group is not None and isinstance(value, cls.group):
            return value.params
        return jnp.asarray(value)

    @classmethod
    def retract(cls, params: Array, delta: Array) -> Array:
        if cls.group is None:
            return params + delta
        return cls.group(params).retract(delta).params

    @classmethod
    def local(cls, a: Array, b: Array) -> Array:
        """Tangent ``d`` with ``retract(a, d) == b``."""
        if cls.group is None:
            return b - a
        return cls.group(a).local(cls.group(b))


class Pose3Var(Variable):
    group = SE3
    param_dim = 7
    tangent_dim = 6


class Pose2Var(Variable):
    group = SE2
    param_dim = 4
    tangent_dim = 3


class Rot3Var(Variable):
    group = SO3
    param_dim = 4
    tangent_dim = 3


class Point3Var(Variable):
    param_dim = 3
    tangent_dim = 3


class Point2Var(Variable):
    param_dim = 2
    tangent_dim = 2


class VelocityVar(Variable):
    param_dim = 3
    tangent_dim = 3


class BiasVar(Variable):
    """IMU bias ``(acc_x, acc_y, acc_z, gyro_x, gyro_y, gyro_z)`` (GTSAM's ConstantBias order)."""

    param_dim = 6
    tangent_dim = 6


class ScaleVar(Variable):
    """The natural log of a length scale, e.g. the factor by which a visual odometry's
    translations are short (``exp(0) = 1``: unbiased)."""

    param_dim = 1
    tangent_dim = 1


PoseVar = Pose3Var
