"""Robust kernels (M-estimators) with GTSAM's definitions.

For a whitened residual of norm ``x`` a kernel gives the cost ``rho(x)`` (plain least squares
is ``x^2 / 2``) and the IRLS weight ``w(x) = rho'(x) / x``; the solver scales the whitened
residual and Jacobian by ``sqrt(w)``, as GTSAM's ``noiseModel.Robust`` does. The scale ``k``
is a leaf, so it can be learned.

References: Zhang, "Parameter estimation techniques: a tutorial" (1997); GTSAM
``linear/LossFunctions.cpp``.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from jax import Array

from .._pytree import register_typed


@dataclasses.dataclass(frozen=True)
class RobustKernel:
    k: Array | float

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        register_typed(cls, ["k"])

    def loss(self, x: Array) -> Array:
        raise NotImplementedError

    def weight(self, x: Array) -> Array:
        raise NotImplementedError


class Huber(RobustKernel):
    """``x^2/2`` inside ``k``, ``k |x| - k^2/2`` outside: convex, bounded influence."""

    def loss(self, x: Array) -> Array:
        ax = jnp.abs(x)
        return jnp.where(ax <= self.k, 0.5 * x * x, self.k * ax - 0.5 * self.k * self.k)

    def weight(self, x: Array) -> Array:
        ax = jnp.abs(x)
        return jnp.where(ax <= self.k, 1.0, self.k / jnp.where(ax <= self.k, 1.0, ax))


class Cauchy(RobustKernel):
    """``k^2/2 log(1 + x^2/k^2)``: heavy-tailed, not redescending."""

    def loss(self, x: Array) -> Array:
        return 0.5 * self.k * self.k * jnp.log1p(x * x / (self.k * self.k))

    def weight(self, x: Array) -> Array:
        return self.k * self.k / (self.k * self.k + x * x)


class GemanMcClure(RobustKernel):
    """``k^2 x^2 / (2 (k^2 + x^2))``: redescending, bounded cost (good for false loops)."""

    def loss(self, x: Array) -> Array:
        c2 = self.k * self.k
        return 0.5 * c2 * x * x / (c2 + x * x)

    def weight(self, x: Array) -> Array:
        c2 = self.k * self.k
        return c2 * c2 / (c2 + x * x) ** 2


class Tukey(RobustKernel):
    """Tukey's biweight: zero weight beyond ``k`` (redescending, hard rejection)."""

    def loss(self, x: Array) -> Array:
        c2 = self.k * self.k
        inside = jnp.abs(x) <= self.k
        t = 1.0 - jnp.where(inside, x * x / c2, 1.0)
        return jnp.where(inside, c2 / 6.0 * (1.0 - t * t * t), c2 / 6.0)

    def weight(self, x: Array) -> Array:
        inside = jnp.abs(x) <= self.k
        t = 1.0 - x * x / (self.k * self.k)
        return jnp.where(inside, t * t, 0.0)


KERNELS: dict[str, type[RobustKernel]] = {
    "huber": Huber,
    "cauchy": Cauchy,
    "geman-mcclure": GemanMcClure,
    "tukey": Tukey,
}
