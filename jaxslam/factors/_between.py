"""Prior and between factors on any variable type (Lie group or Euclidean).

Between: ``e = Log(Z^-1 X_i^-1 X_j)`` (SPEC eqs. 5-10: LiDAR odometry, visual odometry and
loop closure all use it, each with its own noise). Prior: ``e = Log(Z^-1 X)``. Both match
GTSAM's ``BetweenFactor`` / ``PriorFactor`` errors (``Local(measured, h(x))``).

Analytic Jacobians (right perturbations), valid for every group:
``de/dX_j = Jr^-1(e)``, ``de/dX_i = -Jr^-1(e) Ad(X_j^-1 X_i)``, prior ``de/dX = Jr^-1(e)``
(Sola et al. 2018, eqs. 41, 44, 65-66).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array

from ..core import Factor, Gaussian, RobustKernel, Variable, factor_dataclass
from ..lie import mm


def _broadcast_measurement(var_type: type[Variable], measured: Any, n: int) -> Array:
    arr = jnp.asarray(var_type.unwrap(measured), dtype=jnp.float64)
    if arr.ndim == 1:
        arr = jnp.broadcast_to(arr, (n, arr.shape[0]))
    if arr.shape != (n, var_type.param_dim):
        raise ValueError(
            f"measured for {n} {var_type.__name__} constraints must have shape ({n}, {var_type.param_dim}), "
            f"got {tuple(arr.shape)}"
        )
    return arr


def _broadcast_noise(noise: Gaussian, n: int, dim: int) -> Gaussian:
    if noise.dim != dim:
        raise ValueError(f"noise model has dimension {noise.dim}, the residual has {dim}")
    if len(noise) == n:
        return noise
    if len(noise) == 1:
        return noise.broadcast(n)
    raise ValueError(f"noise model holds {len(noise)} matrices for {n} constraints")


@factor_dataclass
class PriorFactor(Factor):
    """``e = Local(measured, x)``; ``measured`` is ``(N, param_dim)``."""

    measured: Array

    @classmethod
    def create(cls, var: Variable, measured: Any, noise: Gaussian, robust: RobustKernel | None = None) -> PriorFactor:
        vtype = type(var)
        n = len(var)
        return cls(
            variables=(var,),
            measured=_broadcast_measurement(vtype, measured, n),
            noise=_broadcast_noise(noise, n, vtype.tangent_dim),
            robust=robust,
        )

    def residual(self, x: Any) -> Array:
        vtype = type(self.variables[0])
        return vtype.local(self.measured, vtype.unwrap(x))

    def jacobians(self, x: Any) -> tuple[Array, ...]:
        vtype = type(self.variables[0])
        if vtype.group is None:
            n = self.measured.shape[0]
            return (jnp.broadcast_to(jnp.eye(vtype.tangent_dim), (n, vtype.tangent_dim, vtype.tangent_dim)),)
        e = self.residual(x)
        return (vtype.group.jr_inv(e),)


@factor_dataclass
class BetweenFactor(Factor):
    """``e = Local(measured, x_i^-1 x_j)`` (``x_j - x_i - measured`` for vector spaces)."""

    measured: Array

    @classmethod
    def create(
        cls,
        var_i: Variable,
        var_j: Variable,
        measured: Any,
        noise: Gaussian,
        robust: RobustKernel | None = None,
    ) -> BetweenFactor:
        vtype = type(var_i)
        if type(var_j) is not vtype:
            raise TypeError(f"between factor needs one variable type, got {vtype.__name__} and {type(var_j).__name__}")
        n = len(var_i)
        if len(var_j) != n:
            raise ValueError(f"between factor: {n} ids for x_i but {len(var_j)} for x_j")
        if isinstance(var_i.ids, np.ndarray) and np.any(var_i.ids == np.asarray(var_j.ids)):
            bad = int(np.asarray(var_i.ids)[var_i.ids == np.asarray(var_j.ids)][0])
            raise ValueError(f"between factor connects {vtype.__name__} {bad} to itself")
        return cls(
            variables=(var_i, var_j),
            measured=_broadcast_measurement(vtype, measured, n),
            noise=_broadcast_noise(noise, n, vtype.tangent_dim),
            robust=robust,
        )

    def _relative(self, xi: Any, xj: Any) -> Any:
        vtype = type(self.variables[0])
        if vtype.group is None:
            return xj - xi
        return xi.inverse() @ xj

    def residual(self, xi: Any, xj: Any) -> Array:
        vtype = type(self.variables[0])
        return vtype.local(self.measured, vtype.unwrap(self._relative(xi, xj)))

    def jacobians(self, xi: Any, xj: Any) -> tuple[Array, ...]:
        vtype = type(self.variables[0])
        n = self.measured.shape[0]
        if vtype.group is None:
            eye = jnp.broadcast_to(jnp.eye(vtype.tangent_dim), (n, vtype.tangent_dim, vtype.tangent_dim))
            return (-eye, eye)
        e = self.residual(xi, xj)
        jinv = vtype.group.jr_inv(e)
        return (-mm(jinv, (xj.inverse() @ xi).adjoint()), jinv)
