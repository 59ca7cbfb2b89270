"""A relative pose whose translation carries an unknown length scale (visual odometry's bias).

Monocular visual odometry made metric with LiDAR depth still measures lengths a few tenths
of a percent short (the bias is in the image features, README); a between factor that trusts
each length passes that bias to the whole trajectory, step after step, where nothing else
observes the length (a LiDAR-degenerate tunnel). Here the measured translation is scaled by
``exp(lambda)``, ``lambda`` a :class:`~jaxslam.core.ScaleVar` that the graph estimates
wherever something else sees the lengths (LiDAR facing the end wall, loop closures) and a
random walk carries between them::

    e = Log(M(lambda)^-1 T_i^-1 T_j),   M(lambda) = (R_m, exp(lambda) t_m)

Jacobians (right perturbations; ``Y = M^-1 T_i^-1 T_j``, ``e = Log Y``):
``de/dT_j = Jr^-1(e)``, ``de/dT_i = -Jr^-1(e) Ad(T_j^-1 T_i)`` (as :class:`BetweenFactor`) and,
since ``M(lambda + d) = M exp([0; d exp(lambda) R_m^T t_m])``,
``de/dlambda = -Jr^-1(e) Ad(Y^-1) [0; exp(lambda) R_m^T t_m]``.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array

from ..core import Factor, Gaussian, Pose3Var, RobustKernel, ScaleVar, factor_dataclass
from ..lie import SE3, mm, mv
from ._between import _broadcast_measurement, _broadcast_noise


@factor_dataclass
class ScaledBetweenFactor(Factor):
    """``e = Log(M(lambda)^-1 T_i^-1 T_j)`` between two :class:`Pose3Var` and a
    :class:`ScaleVar` (see the module docstring); ``measured`` is ``(N, 7)`` SE(3) params."""

    measured: Array

    @classmethod
    def create(
        cls,
        pose_i: Pose3Var,
        pose_j: Pose3Var,
        scale: ScaleVar,
        measured: Any,
        noise: Gaussian,
        robust: RobustKernel | None = None,
    ) -> ScaledBetweenFactor:
        if not (isinstance(pose_i, Pose3Var) and isinstance(pose_j, Pose3Var) and isinstance(scale, ScaleVar)):
            raise TypeError(
                "ScaledBetweenFactor needs (Pose3Var, Pose3Var, ScaleVar), got "
                f"({type(pose_i).__name__}, {type(pose_j).__name__}, {type(scale).__name__})"
            )
        n = len(pose_i)
        if len(pose_j) != n or len(scale) != n:
            raise ValueError(f"ScaledBetweenFactor: {n}, {len(pose_j)} and {len(scale)} ids (must be equal)")
        if isinstance(pose_i.ids, np.ndarray) and np.any(pose_i.ids == np.asarray(pose_j.ids)):
            raise ValueError("ScaledBetweenFactor connects a pose to itself")
        return cls(
            variables=(pose_i, pose_j, scale),
            measured=_broadcast_measurement(Pose3Var, measured, n),
            noise=_broadcast_noise(noise, n, 6),
            robust=robust,
        )

    def _scaled(self, lam: Array) -> SE3:
        m = self.measured
        return SE3(jnp.concatenate([m[..., :4], jnp.exp(lam[..., :1]) * m[..., 4:]], axis=-1))

    def residual(self, xi: Any, xj: Any, lam: Any) -> Array:
        return self._scaled(jnp.asarray(lam)).local(xi.inverse() @ xj)

    def jacobians(self, xi: Any, xj: Any, lam: Any) -> tuple[Array, ...]:
        lam = jnp.asarray(lam)
        M = self._scaled(lam)
        Y = M.inverse() @ (xi.inverse() @ xj)
        e = Y.log()
        jinv = SE3.jr_inv(e)
        # d M / d lambda as a right perturbation: [0; exp(lambda) R_m^T t_m]
        t_m = self.measured[..., 4:]
        eta = jnp.concatenate(
            [jnp.zeros_like(t_m), jnp.exp(lam[..., :1]) * mv(M.rotation.inverse().as_matrix(), t_m)], -1
        )
        d_lam = -mv(mm(jinv, Y.inverse().adjoint()), eta)[..., None]
        return (-mm(jinv, (xj.inverse() @ xi).adjoint()), jinv, d_lam)
