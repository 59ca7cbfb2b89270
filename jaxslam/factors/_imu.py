"""The IMU factor (SPEC eq. 4, GTSAM's ``ImuFactor``) and the bias random-walk factor.

Preintegration itself is in ``_preintegration.py`` (method, references, GTSAM parity notes),
its kernel in ``_imu_kernel.py``, the noise parameters in ``_imu_params.py``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..core import BiasVar, Factor, Gaussian, Pose3Var, RobustKernel, VelocityVar, factor_dataclass
from ..lie import SE3, SO3
from ._imu_params import PreintegrationParams, _is_concrete
from ._preintegration import (
    PreintegratedImu,
)

# ---------------------------------------------------------------------------------------
# Prediction and the factors
# ---------------------------------------------------------------------------------------


def predict_imu_state(
    preintegrated: Array,
    delta_time: Array,
    gravity: Array,
    pose_i: SE3,
    vel_i: Array,
) -> tuple[SE3, Array]:
    """State at ``t_j`` from the state at ``t_i`` and bias-corrected deltas (GTSAM's
    ``PreintegrationBase::predict`` without Coriolis): ``preintegrated`` (N, 9),
    ``delta_time`` (N,) s, ``gravity`` (N, 3) m/s^2, ``pose_i`` SE3 (N,), ``vel_i`` (N, 3)
    m/s (world frame). Returns ``(pose_pred, vel_pred)``."""
    dt = delta_time[..., None]
    rot_i = pose_i.rotation
    rot_pred = rot_i @ SO3.exp(preintegrated[..., 0:3])
    p_pred = pose_i.translation + vel_i * dt + 0.5 * gravity * dt * dt + rot_i.act(preintegrated[..., 3:6])
    v_pred = vel_i + gravity * dt + rot_i.act(preintegrated[..., 6:9])
    return SE3.from_rotation_translation(rot_pred, p_pred), v_pred


@jax.jit
def _residual_covariance(pim: Any) -> Array:
    """``pim.residual_covariance()`` as one compiled program (the factor is built once per
    keyframe: op by op, its first call compiled ~20 small programs)."""
    return pim.residual_covariance()


@jax.jit
def _sqrt_information(cov: Array) -> Array:
    """Upper-triangular ``R`` with ``R^T R = cov^-1`` (N, r, r), without forming the inverse:
    ``cov = U U^T`` (U upper, a Cholesky of the index-reversed matrix), ``R = U^-1``. The
    information route (invert, then Cholesky) loses ~cond(cov) eps, and IMU covariances mix
    rad^2 ~1e-10 with m^2/s^2 ~1e-4."""
    flipped = cov[..., ::-1, ::-1]
    upper = jnp.linalg.cholesky(0.5 * (flipped + jnp.swapaxes(flipped, -1, -2)))[..., ::-1, ::-1]
    eye = jnp.broadcast_to(jnp.eye(cov.shape[-1]), cov.shape)
    return jax.scipy.linalg.solve_triangular(upper, eye, lower=False)


_ERROR_MODES = ("logmap", "component_wise")


@factor_dataclass
class ImuFactor(Factor):
    """GTSAM's ``ImuFactor`` on (Pose3 i, velocity i, Pose3 j, velocity j, bias i), N of them.

    Error (9,), order [rotation, position, velocity]: ``Log_SE2(3)(X_j^-1 X_pred)`` with
    ``X_pred`` predicted by :func:`predict_imu_state` from the first-order bias-corrected deltas
    (module docstring; GTSAM 4.3 ``ImuFactorErrorMode.Logmap``). Noise: the residual-chart
    covariance of the preintegration (:meth:`PreintegratedImu.residual_covariance`), so
    ``factor_cost`` equals GTSAM's ``ImuFactor.error``. Jacobians by autodiff.

    Fields (per constraint, leading axis N): ``preintegrated`` (N, 9), ``bias_jacobian``
    (N, 9, 6), ``bias_hat`` (N, 6), ``delta_time`` (N,) s, ``gravity`` (N, 3) m/s^2.
    """

    preintegrated: Array
    bias_jacobian: Array
    bias_hat: Array
    delta_time: Array
    gravity: Array

    error_mode: ClassVar[str] = "logmap"

    @classmethod
    def create(
        cls,
        pose_i: Pose3Var,
        vel_i: VelocityVar,
        pose_j: Pose3Var,
        vel_j: VelocityVar,
        bias_i: BiasVar,
        pim: PreintegratedImu,
        params: PreintegrationParams,
        robust: RobustKernel | None = None,
        error_mode: str = "logmap",
    ) -> ImuFactor:
        """One factor per interval of ``pim`` (batch shape ``(N,)`` or ``()``).
        ``error_mode``: ``"logmap"`` (GTSAM 4.3 default) or ``"component_wise"`` (SPEC eq. 4,
        GTSAM's ``ImuFactorErrorMode.ComponentWise``)."""
        expected = (Pose3Var, VelocityVar, Pose3Var, VelocityVar, BiasVar)
        slots = (pose_i, vel_i, pose_j, vel_j, bias_i)
        names = ("pose_i", "vel_i", "pose_j", "vel_j", "bias_i")
        for name, var, typ in zip(names, slots, expected):
            if type(var) is not typ:
                raise TypeError(f"ImuFactor {name} must be a {typ.__name__}, got {type(var).__name__}")
        if error_mode not in _ERROR_MODES:
            raise ValueError(f"error_mode must be one of {_ERROR_MODES}, got {error_mode!r}")
        if pim.preintegrated.ndim == 1:
            pim = jax.tree_util.tree_map(lambda leaf: leaf[None], pim)
        if pim.preintegrated.ndim != 2:
            raise ValueError(f"pim must hold a 1-D batch of intervals, got batch shape {pim.batch_shape}")
        n = pim.preintegrated.shape[0]
        lengths = [len(v) for v in slots]
        if any(length != n for length in lengths):
            raise ValueError(
                f"ImuFactor: pim holds {n} intervals but the variables hold {dict(zip(names, lengths))} ids"
            )
        if _is_concrete(pim.valid) and not bool(np.all(np.asarray(pim.valid))):
            bad = np.nonzero(~np.asarray(pim.valid))[0].tolist()
            raise ValueError(f"ImuFactor: intervals {bad[:10]} were preintegrated from invalid samples")
        cov = _residual_covariance(pim)
        sqrt_info = _sqrt_information(cov)
        if _is_concrete(sqrt_info):
            r = np.asarray(sqrt_info)
            with np.errstate(invalid="ignore", over="ignore"):
                identity_err = np.abs(r @ np.asarray(cov) @ np.swapaxes(r, -1, -2) - np.eye(9)).max(axis=(-1, -2))
            singular = ~np.all(np.isfinite(r), axis=(-1, -2)) | ~(identity_err < 1e-6)
        else:
            singular = np.zeros(n, bool)
        if np.any(singular):
            bad = np.nonzero(singular)[0].tolist()
            raise ValueError(
                f"ImuFactor: the preintegrated covariance of intervals {bad[:10]} is singular "
                "(too few samples, or zero noise densities; set integration_sigma > 0)"
            )
        target = cls if error_mode == "logmap" else ImuFactorComponentWise
        return target(
            variables=slots,
            noise=Gaussian(sqrt_info),
            robust=robust,
            preintegrated=pim.preintegrated,
            bias_jacobian=pim.bias_jacobian,
            bias_hat=pim.bias_hat,
            delta_time=pim.delta_time,
            gravity=jnp.broadcast_to(jnp.asarray(params.gravity, dtype=jnp.float64), (n, 3)),
        )

    def predict(self, pose_i: SE3, vel_i: Array, bias_i: Array) -> tuple[SE3, Array]:
        db = bias_i - self.bias_hat
        corrected = self.preintegrated + jnp.einsum("nij,nj->ni", self.bias_jacobian, db)
        return predict_imu_state(corrected, self.delta_time, self.gravity, pose_i, vel_i)

    def residual(self, pose_i: SE3, vel_i: Array, pose_j: SE3, vel_j: Array, bias_i: Array) -> Array:
        pose_pred, vel_pred = self.predict(pose_i, vel_i, bias_i)
        rj_inv = pose_j.rotation.inverse()
        w = (rj_inv @ pose_pred.rotation).log()
        dp = rj_inv.act(pose_pred.translation - pose_j.translation)
        dv = rj_inv.act(vel_pred - vel_j)
        if self.error_mode == "logmap":
            jl_inv = SO3.jl_inv(w)
            dp = jnp.einsum("nij,nj->ni", jl_inv, dp)
            dv = jnp.einsum("nij,nj->ni", jl_inv, dv)
        return jnp.concatenate([w, dp, dv], axis=-1)


@factor_dataclass
class ImuFactorComponentWise(ImuFactor):
    """:class:`ImuFactor` with the component-wise chart (SPEC eq. 4, GTSAM
    ``ImuFactorErrorMode.ComponentWise``): ``[Log(R_j^T R_pred), R_j^T (p_pred - p_j),
    R_j^T (v_pred - v_j)]``. Build with ``ImuFactor.create(..., error_mode="component_wise")``."""

    error_mode: ClassVar[str] = "component_wise"


@factor_dataclass
class BiasRandomWalkFactor(Factor):
    """``e = b_j - b_i`` (6,), (acc, gyro), with sigmas ``sigma_rw sqrt(dt_ij)``: GTSAM's
    ``BetweenFactor<imuBias::ConstantBias>(b_i, b_j, ConstantBias())`` as used beside
    ``ImuFactor``."""

    @classmethod
    def create(
        cls,
        bias_i: BiasVar,
        bias_j: BiasVar,
        delta_time: Any,
        params: PreintegrationParams,
        robust: RobustKernel | None = None,
    ) -> BiasRandomWalkFactor:
        """``delta_time`` (N,) or scalar, seconds (``PreintegratedImu.delta_time``)."""
        for name, var in (("bias_i", bias_i), ("bias_j", bias_j)):
            if type(var) is not BiasVar:
                raise TypeError(f"BiasRandomWalkFactor {name} must be a BiasVar, got {type(var).__name__}")
        n = len(bias_i)
        if len(bias_j) != n:
            raise ValueError(f"BiasRandomWalkFactor: {n} ids for bias_i but {len(bias_j)} for bias_j")
        dt = jnp.broadcast_to(jnp.asarray(delta_time, dtype=jnp.float64), (n,))
        sigmas = params.bias_random_walk_sigmas(dt)
        if _is_concrete(sigmas) and not bool(np.all(np.asarray(sigmas) > 0)):
            raise ValueError("BiasRandomWalkFactor needs delta_time > 0 and random-walk densities > 0")
        return cls(variables=(bias_i, bias_j), noise=Gaussian.diagonal(sigmas), robust=robust)

    def residual(self, b_i: Array, b_j: Array) -> Array:
        return b_j - b_i

    def jacobians(self, b_i: Array, b_j: Array) -> tuple[Array, Array]:
        eye = jnp.broadcast_to(jnp.eye(6), (b_i.shape[0], 6, 6))
        return (-eye, eye)
