"""SO(2), rotations in the plane.

Layout: ``params`` is ``(cos theta, sin theta)``, shape ``(*batch, 2)``. Tangent: ``theta``
as a length-1 vector. The group is commutative, so its Jacobians are the identity.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from jax import Array

from ._base import LieGroup, broadcast_params
from ._utils import batch_shape_check


@dataclasses.dataclass(frozen=True)
class SO2(LieGroup):
    """Planar rotation ``(cos, sin)``, shape ``(*batch, 2)``; tangent ``(theta,)``."""

    param_dim = 2
    tangent_dim = 1
    matrix_dim = 2
    space_dim = 2

    @classmethod
    def identity(cls, batch_shape: tuple[int, ...] = ()) -> SO2:
        return cls(jnp.broadcast_to(jnp.array([1.0, 0.0]), (*batch_shape, 2)))

    @classmethod
    def from_angle(cls, theta: Array) -> SO2:
        theta = jnp.asarray(theta)
        return cls(jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=-1))

    @classmethod
    def exp(cls, tangent: Array) -> SO2:
        tangent = jnp.asarray(tangent)
        batch_shape_check("SO2.exp", tangent, 1)
        return cls.from_angle(tangent[..., 0])

    def angle(self) -> Array:
        return jnp.arctan2(self.params[..., 1], self.params[..., 0])

    def log(self) -> Array:
        return self.angle()[..., None]

    def compose(self, other: SO2) -> SO2:
        a, b = broadcast_params(self.params, other.params)
        c = a[..., 0] * b[..., 0] - a[..., 1] * b[..., 1]
        s = a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0]
        return SO2(jnp.stack([c, s], axis=-1))

    def inverse(self) -> SO2:
        return SO2(jnp.concatenate([self.params[..., :1], -self.params[..., 1:]], axis=-1))

    def act(self, points: Array) -> Array:
        points = jnp.asarray(points)
        batch_shape_check("SO2.act", points, 2)
        params, points = broadcast_params(self.params, points)
        c, s = params[..., 0], params[..., 1]
        x, y = points[..., 0], points[..., 1]
        return jnp.stack([c * x - s * y, s * x + c * y], axis=-1)

    def as_matrix(self) -> Array:
        c, s = self.params[..., 0], self.params[..., 1]
        return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)

    @classmethod
    def from_matrix(cls, matrix: Array) -> SO2:
        m = jnp.asarray(matrix)
        if m.ndim < 2 or m.shape[-2:] != (2, 2):
            raise ValueError(f"SO2.from_matrix expects (*batch, 2, 2), got {tuple(m.shape)}")
        return cls(jnp.stack([m[..., 0, 0], m[..., 1, 0]], axis=-1)).normalize()

    def adjoint(self) -> Array:
        return jnp.ones((*self.batch_shape, 1, 1))

    def normalize(self) -> SO2:
        return SO2(self.params / jnp.linalg.norm(self.params, axis=-1, keepdims=True))

    @staticmethod
    def jr(tangent: Array) -> Array:
        return jnp.ones((*tangent.shape[:-1], 1, 1), dtype=tangent.dtype)

    @staticmethod
    def jr_inv(tangent: Array) -> Array:
        return jnp.ones((*tangent.shape[:-1], 1, 1), dtype=tangent.dtype)
