"""The common interface of jaxslam's matrix Lie groups.

Each group is an immutable PyTree holding one array ``params`` of shape ``(*batch, P)``;
every operation broadcasts over the leading batch axes. Perturbations are on the right:
``x.retract(d) = x @ exp(d)`` and ``x.local(y) = log(x^-1 @ y)`` (GTSAM's convention for
Rot3/Pose3 with the exponential map as the chart).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar, TypeVar

import jax.numpy as jnp
from jax import Array

from .._pytree import register_typed

G = TypeVar("G", bound="LieGroup")


@dataclasses.dataclass(frozen=True)
class LieGroup:
    """Base class. Subclasses set the class constants and implement the abstract methods."""

    params: Array

    param_dim: ClassVar[int]
    tangent_dim: ClassVar[int]
    matrix_dim: ClassVar[int]
    space_dim: ClassVar[int]

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        register_typed(cls, ["params"])

    # --- construction -------------------------------------------------------------------
    @classmethod
    def identity(cls: type[G], batch_shape: tuple[int, ...] = ()) -> G:
        raise NotImplementedError

    @classmethod
    def exp(cls: type[G], tangent: Array) -> G:
        raise NotImplementedError

    @classmethod
    def from_matrix(cls: type[G], matrix: Array) -> G:
        raise NotImplementedError

    # --- group operations ---------------------------------------------------------------
    def log(self) -> Array:
        raise NotImplementedError

    def compose(self: G, other: G) -> G:
        raise NotImplementedError

    def inverse(self: G) -> G:
        raise NotImplementedError

    def act(self, points: Array) -> Array:
        """Apply the group action to points of shape ``(*batch, space_dim)``; the batch axes
        of the group and the points broadcast against each other."""
        raise NotImplementedError

    def as_matrix(self) -> Array:
        raise NotImplementedError

    def adjoint(self) -> Array:
        """``Ad(x)`` with ``x @ exp(d) == exp(Ad(x) d) @ x``; shape ``(*batch, T, T)``."""
        raise NotImplementedError

    def normalize(self: G) -> G:
        """Project the parameters back onto the group (unit quaternion / complex number)."""
        raise NotImplementedError

    # --- Jacobians of exp (static, on tangent vectors) ----------------------------------
    @staticmethod
    def jr(tangent: Array) -> Array:
        """Right Jacobian: ``exp(t + d) ~= exp(t) @ exp(jr(t) d)``."""
        raise NotImplementedError

    @staticmethod
    def jr_inv(tangent: Array) -> Array:
        raise NotImplementedError

    @classmethod
    def jl(cls, tangent: Array) -> Array:
        """Left Jacobian: ``exp(t + d) ~= exp(jl(t) d) @ exp(t)``; equals ``jr(-t)``."""
        return cls.jr(-tangent)

    @classmethod
    def jl_inv(cls, tangent: Array) -> Array:
        return cls.jr_inv(-tangent)

    # --- derived ------------------------------------------------------------------------
    def __matmul__(self: G, other: G) -> G:
        return self.compose(other)

    def between(self: G, other: G) -> G:
        """``self^-1 @ other`` (GTSAM's ``between``)."""
        return self.inverse().compose(other)

    def retract(self: G, delta: Array) -> G:
        return self.compose(type(self).exp(delta))

    def local(self: G, other: G) -> Array:
        return self.between(other).log()

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.params.shape[:-1])

    def __getitem__(self: G, index: object) -> G:
        if not isinstance(index, tuple):
            index = (index,)
        return type(self)(self.params[(*index, slice(None))])

    def __repr__(self) -> str:
        return f"{type(self).__name__}(batch_shape={self.batch_shape})"


def broadcast_params(a: Array, b: Array) -> tuple[Array, Array]:
    """Broadcast two ``(*batch, P)`` parameter arrays against each other's batch axes."""
    shape = jnp.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    return (
        jnp.broadcast_to(a, (*shape, a.shape[-1])),
        jnp.broadcast_to(b, (*shape, b.shape[-1])),
    )
