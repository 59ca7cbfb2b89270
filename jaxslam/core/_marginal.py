"""A Gaussian density on several variables in local coordinates: the marginal prior that
variable elimination (fixed-lag smoothing, Schur complement) leaves on the variables it keeps.

Residual (unwhitened): ``concat_k Local(x0_k, x_k) - mean``; noise: square-root information
``R`` (``R^T R`` = the marginal information, possibly rank-deficient). So the cost is
``1/2 |R (Local(x0, x) - mean)|^2`` — GTSAM's ``LinearContainerFactor`` on a
``HessianFactor`` plays the same role. The factor is generic (any variable types, any number
of slots); one object holds ``N`` such densities with the same slot types.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array

from ._factor import Factor, factor_dataclass
from ._noise import Gaussian
from ._variables import Variable


@factor_dataclass
class MarginalFactor(Factor):
    """``x0``: one ``(N, param_dim_k)`` array per slot (the linearisation point);
    ``mean``: ``(N, sum_k tangent_dim_k)``; ``noise``: its square-root information."""

    x0: tuple[Array, ...]
    mean: Array

    @classmethod
    def from_information(
        cls,
        variables: tuple[Variable, ...],
        x0: tuple[Any, ...],
        information: np.ndarray,
        gradient: np.ndarray,
        eig_floor: float = 1e-12,
    ) -> MarginalFactor:
        """One density with cost ``1/2 d^T H d + b^T d`` (+ const), ``d = Local(x0, x)``:
        ``information`` H ``(D, D)`` (symmetric positive semi-definite), ``gradient`` b
        ``(D,)``. Directions with eigenvalue below ``eig_floor * max eig`` carry no
        information (a free gauge stays free)."""
        h = 0.5 * (np.asarray(information, np.float64) + np.asarray(information, np.float64).T)
        b = np.asarray(gradient, np.float64)
        w, v = np.linalg.eigh(h)
        keep = w > eig_floor * max(float(w.max(initial=0.0)), 1e-300)
        ws = np.where(keep, w, 1.0)
        sqrt_info = np.where(keep[:, None], np.sqrt(ws)[:, None] * v.T, 0.0)  # rows: sqrt(l_i) v_i^T
        mean = -(v * np.where(keep, 1.0 / ws, 0.0)) @ (v.T @ b)  # -H^+ b
        dims = [type(var).tangent_dim for var in variables]
        if sum(dims) != h.shape[0]:
            raise ValueError(f"information is {h.shape[0]}x{h.shape[0]}, the variables have {sum(dims)} dofs")
        return cls(
            variables=tuple(type(var)(np.asarray(var.ids).reshape(1)) for var in variables),
            x0=tuple(
                jnp.asarray(np.asarray(type(var).unwrap(p), np.float64).reshape(1, -1)) for var, p in zip(variables, x0)
            ),
            mean=jnp.asarray(mean[None]),
            noise=Gaussian(jnp.asarray(sqrt_info[None])),
        )

    def residual(self, *values: Any) -> Array:
        parts = [type(var).local(x0, type(var).unwrap(val)) for var, x0, val in zip(self.variables, self.x0, values)]
        return jnp.concatenate(parts, axis=-1) - self.mean
