"""SE(2), rigid motions in the plane.

Layout: ``params`` is ``(cos theta, sin theta, x, y)``, shape ``(*batch, 4)``.
Tangent: ``[theta, rho_x, rho_y]`` (rotation first, like jaxslam's SE(3); note that GTSAM's
Pose2 orders its tangent ``[x, y, theta]``), right-perturbed.

Reference: Sola et al., "A micro Lie theory" (2018), eqs. (156)-(163), with the tangent
reordered.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from jax import Array

from ._base import LieGroup, broadcast_params
from ._so2 import SO2
from ._so3 import _coef_b, _coef_c
from ._utils import batch_shape_check, series_or


def _coef_a(theta_sq: Array) -> Array:
    """sin(theta) / theta."""
    return series_or(theta_sq, lambda t: jnp.sin(t) / t, (1.0, -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0, 1.0 / 362880.0))


@dataclasses.dataclass(frozen=True)
class SE2(LieGroup):
    """Planar rigid motion ``(cos, sin, x, y)``, shape ``(*batch, 4)``; tangent
    ``[theta, rho_x, rho_y]``."""

    param_dim = 4
    tangent_dim = 3
    matrix_dim = 3
    space_dim = 2

    @classmethod
    def identity(cls, batch_shape: tuple[int, ...] = ()) -> SE2:
        return cls(jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0, 0.0]), (*batch_shape, 4)))

    @classmethod
    def from_xy_theta(cls, x: Array, y: Array, theta: Array) -> SE2:
        x, y, theta = jnp.broadcast_arrays(jnp.asarray(x), jnp.asarray(y), jnp.asarray(theta))
        return cls(jnp.stack([jnp.cos(theta), jnp.sin(theta), x, y], axis=-1))

    @property
    def rotation(self) -> SO2:
        return SO2(self.params[..., :2])

    @property
    def translation(self) -> Array:
        return self.params[..., 2:]

    def xy_theta(self) -> Array:
        """``(*batch, 3)`` array ``(x, y, theta)`` as g2o and GTSAM write Pose2."""
        return jnp.concatenate([self.translation, self.rotation.angle()[..., None]], axis=-1)

    @classmethod
    def exp(cls, tangent: Array) -> SE2:
        tangent = jnp.asarray(tangent)
        batch_shape_check("SE2.exp", tangent, 3)
        theta = tangent[..., 0]
        rx, ry = tangent[..., 1], tangent[..., 2]
        theta_sq = theta * theta
        a = _coef_a(theta_sq)
        b = theta * _coef_b(theta_sq)  # (1 - cos) / theta
        x = a * rx - b * ry
        y = b * rx + a * ry
        return cls(jnp.stack([jnp.cos(theta), jnp.sin(theta), x, y], axis=-1))

    def log(self) -> Array:
        theta = self.rotation.angle()
        theta_sq = theta * theta
        a = _coef_a(theta_sq)
        b = theta * _coef_b(theta_sq)
        det = a * a + b * b
        x, y = self.params[..., 2], self.params[..., 3]
        rx = (a * x + b * y) / det
        ry = (-b * x + a * y) / det
        return jnp.stack([theta, rx, ry], axis=-1)

    def compose(self, other: SE2) -> SE2:
        a, b = broadcast_params(self.params, other.params)
        rot = SO2(a[..., :2])
        r = rot.compose(SO2(b[..., :2])).params
        t = a[..., 2:] + rot.act(b[..., 2:])
        return SE2(jnp.concatenate([r, t], axis=-1))

    def inverse(self) -> SE2:
        rinv = self.rotation.inverse()
        t = -rinv.act(self.translation)
        return SE2(jnp.concatenate([rinv.params, t], axis=-1))

    def act(self, points: Array) -> Array:
        points = jnp.asarray(points)
        batch_shape_check("SE2.act", points, 2)
        params, points = broadcast_params(self.params, points)
        return SO2(params[..., :2]).act(points) + params[..., 2:]

    def as_matrix(self) -> Array:
        r = self.rotation.as_matrix()
        top = jnp.concatenate([r, self.translation[..., :, None]], axis=-1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), (*top.shape[:-2], 1, 3))
        return jnp.concatenate([top, bottom], axis=-2)

    @classmethod
    def from_matrix(cls, matrix: Array) -> SE2:
        m = jnp.asarray(matrix)
        if m.ndim < 2 or m.shape[-2:] != (3, 3):
            raise ValueError(f"SE2.from_matrix expects (*batch, 3, 3), got {tuple(m.shape)}")
        rot = SO2.from_matrix(m[..., :2, :2])
        rp, tp = broadcast_params(rot.params, m[..., :2, 2])
        return cls(jnp.concatenate([rp, tp], axis=-1))

    def adjoint(self) -> Array:
        """``[[1, 0], [(y, -x), R]]`` for the [theta, x, y] order."""
        r = self.rotation.as_matrix()
        x, y = self.params[..., 2], self.params[..., 3]
        one = jnp.ones_like(x)
        zero = jnp.zeros_like(x)
        return jnp.stack(
            [
                jnp.stack([one, zero, zero], -1),
                jnp.stack([y, r[..., 0, 0], r[..., 0, 1]], -1),
                jnp.stack([-x, r[..., 1, 0], r[..., 1, 1]], -1),
            ],
            -2,
        )

    def normalize(self) -> SE2:
        return SE2(jnp.concatenate([self.rotation.normalize().params, self.translation], axis=-1))

    @staticmethod
    def jr(tangent: Array) -> Array:
        theta = tangent[..., 0]
        r1, r2 = tangent[..., 1], tangent[..., 2]
        theta_sq = theta * theta
        a = _coef_a(theta_sq)
        b2 = _coef_b(theta_sq)  # (1 - cos) / theta^2
        c3 = _coef_c(theta_sq)  # (theta - sin) / theta^3
        b1 = theta * b2  # (1 - cos) / theta
        one = jnp.ones_like(theta)
        zero = jnp.zeros_like(theta)
        return jnp.stack(
            [
                jnp.stack([one, zero, zero], -1),
                jnp.stack([r1 * theta * c3 - r2 * b2, a, b1], -1),
                jnp.stack([r1 * b2 + r2 * theta * c3, -b1, a], -1),
            ],
            -2,
        )

    @staticmethod
    def jr_inv(tangent: Array) -> Array:
        return jnp.linalg.inv(SE2.jr(tangent))
