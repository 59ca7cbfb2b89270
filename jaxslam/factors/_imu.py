"""IMU preintegration (SPEC eq. 3), the IMU factor (eq. 4) and the bias random-walk factor.

Parity target: ``gtsam.PreintegratedImuMeasurements`` and ``gtsam.ImuFactor`` of the pinned
gtsam 4.3.0 wheel. That wheel is built with **tangent-space preintegration**
(``GTSAM_TANGENT_PREINTEGRATION``: its ``PreintegratedImuMeasurements`` equals
``PreintegratedImuMeasurementsTangent`` to the last bit and differs from ``...Manifold``), and
its ``ImuFactor`` uses the ``ImuFactorErrorMode.Logmap`` chart (the default of fresh 4.3
parameters) with the *residual-chart* covariance as its noise model. Both are reproduced here.

Tangent preintegration (Forster, Carlone, Dellaert, Scaramuzza, "On-Manifold Preintegration
for Real-Time Visual-Inertial Odometry", T-RO 2017, with the tangent-space variant of GTSAM's
``TangentPreintegration`` / ImuFactor.lyx). The state is ``x = [theta, dp, dv]`` (9,), all in
the body frame at ``t_i``, with ``dR = Exp(theta)``. For each bias-corrected sample
``a = a_meas - b_a``, ``w = w_meas - b_g`` held for ``dt``::

    theta' = theta + Jr(theta)^-1 w dt
    dp'    = dp + dv dt + 1/2 Exp(theta) a dt^2
    dv'    = dv + Exp(theta) a dt

with ``Jr`` the SO(3) right Jacobian. Its Jacobians ``A = dx'/dx`` (9x9), ``B = dx'/da``,
``C = dx'/dw`` (9x3) propagate the bias Jacobians ``H' = A H - [B | C]`` and the covariance
``P' = A P A^T + B (Qa/dt) B^T + C (Qg/dt) C^T + diag(0, Qi dt, 0)`` (continuous-time
densities turned into discrete covariances by ``1/dt``, as GTSAM does).

The factor predicts ``x_j`` from ``x_i`` with the bias-corrected deltas
``x(b) = x(b_hat) + H (b - b_hat)`` (first order, Forster eq. 44 in tangent form)::

    R_pred = R_i Exp(theta)
    p_pred = p_i + v_i dt + 1/2 g dt^2 + R_i dp
    v_pred = v_i + g dt + R_i dv

and its 9-d error, order [rotation, position, velocity] like GTSAM's NavState tangent, is
``Log_SE2(3)(X_j^-1 X_pred) = [w, Jl(w)^-1 R_j^T (p_pred - p_j), Jl(w)^-1 R_j^T (v_pred - v_j)]``
with ``w = Log(R_j^T R_pred)`` (``error_mode="logmap"``), or the same without ``Jl(w)^-1``
(``"component_wise"``, SPEC eq. 4 and GTSAM's legacy chart for this backend). Its noise is
GTSAM's residual covariance ``J P J^T``, ``J = blockdiag(Jr(theta), dR^T, dR^T)``.

Units: seconds, metres, radians; accelerations in m/s^2, angular rates in rad/s. Noise in
Kalibr units (continuous-time densities), see :class:`PreintegrationParams`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from ..core import BiasVar, Factor, Gaussian, Pose3Var, RobustKernel, VelocityVar, factor_dataclass
from ..errors import ConfigError
from ..lie import SE3, SO3

# ---------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------


def _is_concrete(*xs: Any) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _density_vector(name: str, value: Any) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(3, float(arr))
    if arr.shape != (3,):
        raise ConfigError(f"{name} must be a scalar or per-axis (3,), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ConfigError(f"{name} must be finite and >= 0, got {arr.tolist()}")
    return arr


def _covariance_matrix(name: str, value: Any) -> np.ndarray:
    cov = np.asarray(value, dtype=np.float64)
    if cov.shape != (3, 3):
        raise ConfigError(f"{name} must be a (3, 3) covariance, got shape {cov.shape}")
    if not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T, rtol=1e-12, atol=0.0):
        raise ConfigError(f"{name} must be finite and symmetric")
    if np.linalg.eigvalsh(cov).min() < -1e-15 * max(1.0, np.abs(cov).max()):
        raise ConfigError(f"{name} must be positive semi-definite")
    return cov


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PreintegrationParams:
    """IMU noise and gravity, an immutable PyTree (GTSAM's ``PreintegrationParams``).

    Noise is given as continuous-time densities in Kalibr's units (``imu.yaml``):

    ======================================  ==========  =====================================
    field                                   shape       units
    ======================================  ==========  =====================================
    ``gravity``                             (3,)        m/s^2, navigation frame; Z-up:
                                                        ``(0, 0, -9.81)`` (``MakeSharedU``)
    ``accelerometer_covariance``            (3, 3)      (m/s^2)^2/Hz = sigma_a^2 (white noise
                                                        density squared)
    ``gyroscope_covariance``                (3, 3)      (rad/s)^2/Hz = sigma_g^2
    ``integration_covariance``              (3, 3)      m^2/s; GTSAM's position-integration
                                                        "covariance", added as ``Qi dt``
    ``accelerometer_random_walk``           (3,)        m/s^3/sqrt(Hz) (bias random walk)
    ``gyroscope_random_walk``               (3,)        rad/s^2/sqrt(Hz)
    ======================================  ==========  =====================================

    A sample held for ``dt`` seconds has discrete covariance ``Q/dt``; a bias drifts by
    ``sigma_rw * sqrt(dt_ij)`` over an interval. Build with :meth:`create`,
    :meth:`make_shared_u` or :meth:`make_shared_d`; the constructors validate, the raw
    dataclass constructor (used by PyTree unflattening) does not.
    """

    gravity: Array
    accelerometer_covariance: Array
    gyroscope_covariance: Array
    integration_covariance: Array
    accelerometer_random_walk: Array
    gyroscope_random_walk: Array

    @classmethod
    def create(
        cls,
        accelerometer_noise_density: Any = 0.0,
        gyroscope_noise_density: Any = 0.0,
        accelerometer_random_walk: Any = 0.0,
        gyroscope_random_walk: Any = 0.0,
        integration_sigma: Any = 0.0,
        gravity: Any = (0.0, 0.0, -9.81),
    ) -> PreintegrationParams:
        """From Kalibr densities: scalars (isotropic) or per-axis ``(3,)``.

        ``accelerometer_noise_density`` m/s^2/sqrt(Hz), ``gyroscope_noise_density``
        rad/s/sqrt(Hz), ``accelerometer_random_walk`` m/s^3/sqrt(Hz),
        ``gyroscope_random_walk`` rad/s^2/sqrt(Hz), ``integration_sigma`` m/sqrt(s),
        ``gravity`` (3,) m/s^2 in the navigation frame.
        """
        sa = _density_vector("accelerometer_noise_density", accelerometer_noise_density)
        sg = _density_vector("gyroscope_noise_density", gyroscope_noise_density)
        si = _density_vector("integration_sigma", integration_sigma)
        return cls.from_covariances(
            np.diag(sa**2),
            np.diag(sg**2),
            np.diag(si**2),
            accelerometer_random_walk=accelerometer_random_walk,
            gyroscope_random_walk=gyroscope_random_walk,
            gravity=gravity,
        )

    @classmethod
    def from_covariances(
        cls,
        accelerometer_covariance: Any,
        gyroscope_covariance: Any,
        integration_covariance: Any = None,
        accelerometer_random_walk: Any = 0.0,
        gyroscope_random_walk: Any = 0.0,
        gravity: Any = (0.0, 0.0, -9.81),
    ) -> PreintegrationParams:
        """From full (3, 3) continuous-time covariances (GTSAM's ``set*Covariance``); units as
        in the class table. ``integration_covariance`` defaults to zero."""
        if integration_covariance is None:
            integration_covariance = np.zeros((3, 3))
        g = np.asarray(gravity, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ConfigError(f"gravity must be a finite (3,) vector, got shape {g.shape}")
        return cls(
            gravity=jnp.asarray(g),
            accelerometer_covariance=jnp.asarray(
                _covariance_matrix("accelerometer_covariance", accelerometer_covariance)
            ),
            gyroscope_covariance=jnp.asarray(_covariance_matrix("gyroscope_covariance", gyroscope_covariance)),
            integration_covariance=jnp.asarray(_covariance_matrix("integration_covariance", integration_covariance)),
            accelerometer_random_walk=jnp.asarray(
                _density_vector("accelerometer_random_walk", accelerometer_random_walk)
            ),
            gyroscope_random_walk=jnp.asarray(_density_vector("gyroscope_random_walk", gyroscope_random_walk)),
        )

    @classmethod
    def make_shared_u(cls, g: float = 9.81, **densities: Any) -> PreintegrationParams:
        """Z-up navigation frame (ENU): gravity ``(0, 0, -g)``, GTSAM's ``MakeSharedU``."""
        return cls.create(gravity=(0.0, 0.0, -float(g)), **densities)

    @classmethod
    def make_shared_d(cls, g: float = 9.81, **densities: Any) -> PreintegrationParams:
        """Z-down navigation frame (NED): gravity ``(0, 0, g)``, GTSAM's ``MakeSharedD``."""
        return cls.create(gravity=(0.0, 0.0, float(g)), **densities)

    def bias_random_walk_sigmas(self, delta_time: Any) -> Array:
        """Per-interval bias drift sigmas ``(*batch, 6)`` (acc then gyro; m/s^2, rad/s):
        ``sigma_rw * sqrt(delta_time)``, ``delta_time`` in seconds ``(*batch,)``."""
        sq = jnp.sqrt(jnp.asarray(delta_time, dtype=jnp.float64))[..., None]
        rw = jnp.concatenate([self.accelerometer_random_walk, self.gyroscope_random_walk])
        return sq * jnp.broadcast_to(rw, (*sq.shape[:-1], 6))


# ---------------------------------------------------------------------------------------
# SO(3) coefficient functions for the tangent update (NaN-free, Taylor near 0)
# ---------------------------------------------------------------------------------------

# The update needs these at every sample, where theta (the rotation so far) is mostly
# small: the series are used below 0.5 rad and kept to theta^12, so truncation is < 1e-16
# relative there, and the closed forms lose < 2e-12 relative to cancellation above it.
_SERIES = 0.5


_SERIES_COEFFS = (
    (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880, -1 / 39916800, 1 / 6227020800),
    (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800, -1 / 479001600, 1 / 87178291200),
    (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800, -1 / 6227020800, 1 / 1307674368000),
    (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160, 691 / 1307674368000, 1 / 74724249600),
    (1 / 360, 1 / 7560, 1 / 201600, 1 / 5987520, 691 / 130767436800, 1 / 6227020800, 3617 / 762187345920000),
)


def _coefs_series(theta_sq: Array) -> tuple[Array, ...]:
    out = []
    for coeffs in _SERIES_COEFFS:
        acc = jnp.full_like(theta_sq, coeffs[-1])
        for c in reversed(coeffs[:-1]):
            acc = acc * theta_sq + c
        out.append(acc)
    return tuple(out)


def _coefs_closed(theta_sq: Array) -> tuple[Array, ...]:
    """The closed forms from ``s = sin(t/2)``, ``c = cos(t/2)``; ``theta_sq > 0``."""
    t = jnp.sqrt(theta_sq)
    s, c = jnp.sin(0.5 * t), jnp.cos(0.5 * t)
    inv_t2 = 1.0 / theta_sq
    cot_half = c / s
    return (
        2.0 * s * c / t,
        2.0 * s * s * inv_t2,
        (t - 2.0 * s * c) * inv_t2 / t,
        inv_t2 - 0.5 * cot_half / t,
        (0.25 * theta_sq / (s * s) + 0.5 * t * cot_half - 2.0) * inv_t2 * inv_t2,
    )


def _coefs(theta_sq: Array) -> tuple[Array, Array, Array, Array, Array]:
    """``(a, b, c, d, e)`` of ``Exp(W) = I + a W + b W^2``, ``Jr = I - b W + c W^2``,
    ``Jr^-1 = I + W/2 + d W^2`` and ``e = d'(theta)/theta`` (Barfoot 2017 sec. 7.1.5):
    ``a = sin t / t``, ``b = (1 - cos t)/t^2``, ``c = (t - sin t)/t^3``,
    ``d = 1/t^2 - cot(t/2)/(2t)``, ``e = (t^2/(4 sin^2(t/2)) + t cot(t/2)/2 - 2)/t^4``.
    Taylor series (coefficients from sympy) below ``_SERIES``; the closed forms are only
    evaluated when some angle needs them (a runtime branch: preintegrated angles are
    mostly small and sin/cos dominate the cost). NaN-free values and gradients at 0."""
    small = theta_sq < _SERIES * _SERIES
    series = _coefs_series(theta_sq)

    def mixed(_: None) -> tuple[Array, ...]:
        closed = _coefs_closed(jnp.where(small, 1.0, theta_sq))
        return tuple(jnp.where(small, a, b) for a, b in zip(series, closed))

    return lax.cond(jnp.all(small), lambda _: series, mixed, None)  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------
# The kernel. Arrays are lanes-LAST: one lane per interval on the last axis (K), so XLA's CPU
# loops run over the intervals innermost (SIMD); this is vmap-over-intervals written out.
# Per-sample arrays lead with the sample axis M: vectors (M, 3, K), matrices (M, 3, 3, K),
# so scans slice them without copies. 3x3 products are written as sums of broadcast
# products, which fuse into one elementwise loop per matrix.
#
# Only the rotation recurrence is nonlinear, so the update runs in stages:
#   1. scan over samples: theta_k (3 numbers per lane);
#   2. at once for all samples: R = Exp(theta), Jr^-1, F, G, R a;
#   3. scan backwards over samples: the transitions Phi_k = A_M ... A_{k+1};
#   4. at once: dp, dv, bias Jacobians and covariance as sums over the samples,
# with, in block form (rows/columns [theta, dp, dv]),
#   A = [[F, 0, 0], [dt/2 G, I, dt I], [G, 0, I]],  B = [0; R dt^2/2; R dt],  C = [Jr^-1 dt; 0; 0],
#   F = I + d(Jr^-1(theta) w)/dtheta dt,  G = R [-a]x Jr dt  (GTSAM's a_nav_H_theta dt).
# ---------------------------------------------------------------------------------------

_R3 = range(3)


def _s(x: Array) -> Array:
    """A per-sample scalar (..., K) as a matrix factor (..., 1, 1, K)."""
    return x[..., None, None, :]


def _v(x: Array) -> Array:
    """A per-sample scalar (..., K) as a vector factor (..., 1, K)."""
    return x[..., None, :]


def _eye(ndim: int) -> Array:
    """The identity as a broadcastable (1, ..., 3, 3, 1) array of rank ``ndim``."""
    return jnp.eye(3).reshape((1,) * (ndim - 3) + (3, 3, 1))


def _skew(v: Array) -> Array:
    """(..., 3, K) -> (..., 3, 3, K)."""
    x, y, z = v[..., 0, :], v[..., 1, :], v[..., 2, :]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -2), jnp.stack([z, o, -x], -2), jnp.stack([-y, x, o], -2)], -3)


def _sum(terms: list[Array]) -> Array:
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def _mm(a: Array, b: Array) -> Array:
    """(..., i, l, K) @ (..., l, j, K) -> (..., i, j, K), as a sum of outer products:
    elementwise only, so it fuses into one loop (a reduce over l runs ~2x slower here)."""
    return _sum([a[..., :, l : l + 1, :] * b[..., None, l, :, :] for l in range(a.shape[-2])])


def _mm_t(a: Array, b: Array) -> Array:
    """``a @ b^T``: (..., i, l, K), (..., j, l, K) -> (..., i, j, K)."""
    return _sum([a[..., :, l : l + 1, :] * b[..., None, :, l, :] for l in range(a.shape[-2])])


def _mv(a: Array, v: Array) -> Array:
    """(..., i, l, K) @ (..., l, K) -> (..., i, K)."""
    return _sum([a[..., :, l, :] * v[..., l : l + 1, :] for l in range(a.shape[-2])])


def _total(x: Array) -> Array:
    """Sum over the leading sample axis as a tree of pairwise adds of even and odd samples
    (log2 M levels, unrolled at trace time): XLA fuses it into one elementwise loop, where
    ``jnp.sum`` goes to a reduction kernel ~2x slower here (and contiguous halves measured
    slower than even/odd pairs)."""
    while x.shape[0] > 1:
        if x.shape[0] % 2:
            x = jnp.concatenate([x, jnp.zeros_like(x[:1])])
        x = x[0::2] + x[1::2]
    return x[0]


def _fence(tree: Any, one: Array) -> Any:
    """Identity on every leaf (``x / 1`` is exact in IEEE arithmetic) that stops XLA:CPU from
    recomputing a shared intermediate inside each consumer loop: its fusion pass treats
    division as expensive and stores the value once instead. ``one`` must be a runtime
    value (a jit argument), or the division folds away. ``lax.optimization_barrier`` does
    not survive XLA:CPU's pipeline."""
    return jax.tree_util.tree_map(lambda x: x / one, tree)


def _theta_step(th: Array, sample: tuple[Array, Array]) -> tuple[Array, Array]:
    """Stage 1: ``theta' = theta + Jr(theta)^-1 w dt``, with ``Jr^-1 w = w + (theta x w)/2
    + d theta x (theta x w)``; emits theta before the update. ``th`` (3, K). A padded sample
    (dt = 0, w = 0) leaves theta exactly unchanged."""
    w, dt = sample
    cd = _coefs(jnp.sum(th * th, axis=0))[3]
    tw = jnp.cross(th, w, axis=0)
    wt = w + 0.5 * tw + cd[None] * jnp.cross(th, tw, axis=0)
    return th + wt * dt[None], th


def _sample_blocks(th: Array, a: Array, w: Array, dt: Array, one: Array) -> dict[str, Array]:
    """Stage 2 (no recurrence), for all samples at once: ``th`` (rotation vector *before*
    each sample), ``a``, ``w`` (M, 3, K); ``dt`` (M, K). Returns F, G, R, C_rot = Jr^-1 dt
    (M, 3, 3, K) and R a (M, 3, K)."""
    eye = _eye(4)
    th_sq = jnp.sum(th * th, axis=-2)
    ca, cb, cc, cd, ce = (_s(x) for x in _fence(_coefs(th_sq), one))
    w_hat = _skew(th)
    w_hat2 = th[..., :, None, :] * th[..., None, :, :] - _s(th_sq) * eye  # W^2 = t t^T - |t|^2 I
    rot = _fence(eye + ca * w_hat + cb * w_hat2, one)  # Exp(theta)
    jr = eye - cb * w_hat + cc * w_hat2
    jr_inv = eye + 0.5 * w_hat + cd * w_hat2

    # d(Jr^-1(theta) w)/dtheta = -[w]x/2 + d (theta w^T + (theta.w) I - 2 w theta^T)
    #                            + e (W^2 w) theta^T,   e = d'(|theta|)/|theta|.
    tw = jnp.sum(th * w, axis=-2)
    w2w = th * _v(tw) - w * _v(th_sq)
    outer_tw = th[..., :, None, :] * w[..., None, :, :]
    outer_wt = w[..., :, None, :] * th[..., None, :, :]
    h_theta = (
        -0.5 * _skew(w)
        + cd * (outer_tw - 2.0 * outer_wt + _s(tw) * eye)
        + ce * w2w[..., :, None, :] * th[..., None, :, :]
    )
    dt2 = _s(dt)
    out = _fence(
        {
            "f": eye + h_theta * dt2,
            "g": _mm(_mm(rot, _skew(-a)), jr) * dt2,
            "c": jr_inv * dt2,  # the rotation rows of C
            "a_nav": _mv(rot, a),
        },
        one,
    )
    return {**out, "rot": rot}


def _transition_step(phi: Array, sample: tuple[Array, Array, Array]) -> tuple[Array, Array]:
    """Stage 3, run backwards over the samples. The transition ``Phi_k = A_M ... A_{k+1}``
    from after sample k to the end is ``[[Pi, 0, 0], [X, I, T I], [Y, 0, I]]`` (T = time
    after sample k), and ``Phi_{k-1} = Phi_k A_k`` gives ``Pi' = Pi F``,
    ``X' = X F + (dt/2 + T) G``, ``Y' = Y F + G``. ``phi`` = [Pi, X, Y] (3, 3, 3, K);
    emits ``Phi_k``. A padded sample has F = I and G = 0 exactly: an exact no-op."""
    f, g, coef = sample  # (3, 3, K), (3, 3, K), (3, K) = [0, dt/2 + T, 1]
    return _mm(phi, f[None]) + coef[:, None, None] * g[None], phi


# Lanes per block: the kernel runs block by block (lax.map) so that its temporaries, about
# 2 kB per sample, stay in cache and the per-call scratch memory stays small (large fresh
# allocations cost page faults on every call). 192..384 measured alike on KITTI.
_BLOCK_LANES = 256


def _preintegrate_lanes(
    acc: Array,
    gyro: Array,
    dt: Array,
    use: Array,
    bias_hat: Array,
    params: PreintegrationParams,
    one: Array,
    isotropic: bool = False,
) -> tuple[Array, Array, Array, Array]:
    """``acc``/``gyro`` (K, M, 3), ``dt``/``use`` (K, M), ``bias_hat`` (K, 6) -> the lane
    results: preintegrated (K, 9), bias Jacobian (K, 9, 6), covariance (K, 9, 9), dt (K,).
    ``one`` is a runtime 1.0 (see :func:`_fence`)."""
    k = dt.shape[0]
    blocks = -(-k // _BLOCK_LANES)
    lanes = -(-k // blocks)
    pad = blocks * lanes - k

    def split(x: Array) -> Array:
        x = jnp.concatenate([x, jnp.zeros((pad, *x.shape[1:]), x.dtype)]) if pad else x
        return x.reshape(blocks, lanes, *x.shape[1:])

    outs = lax.map(
        lambda b: _preintegrate_block(b[0], b[1], b[2], b[3], b[4], params, one, isotropic),
        tuple(split(x) for x in (acc, gyro, dt, use, bias_hat)),
    )
    return tuple(o.reshape(blocks * lanes, *o.shape[2:])[:k] for o in outs)  # type: ignore[return-value]


def _preintegrate_block(
    acc: Array,
    gyro: Array,
    dt: Array,
    use: Array,
    bias_hat: Array,
    params: PreintegrationParams,
    one: Array,
    isotropic: bool = False,
) -> tuple[Array, Array, Array, Array]:
    """One block of lanes, the arguments and results of :func:`_preintegrate_lanes`.

    Same result as GTSAM's per-sample ``TangentPreintegration::update`` +
    ``PreintegratedImuMeasurements::integrateMeasurement`` loop, with the linear recurrences
    unrolled (``x_M = A_M ... A_1 x_0 + sum_k Phi_k (B_k a_k + C_k w_k)``):
    ``H = -sum_k Phi_k [B_k | C_k]`` and ``P = sum_k Phi_k (B Qa/dt B^T + C Qg/dt C^T +
    E Qi dt E^T)_k Phi_k^T``, so only theta (forwards) and Phi (backwards) are sequential.
    """
    k, m = dt.shape
    use_l = jnp.transpose(use)  # (M, K)
    # Bias-corrected readings (M, 3, K); unused slots become exact no-ops: a = w = dt = 0.
    a = jnp.where(use_l[:, None], jnp.transpose(acc - bias_hat[:, None, 0:3], (1, 2, 0)), 0.0)
    w = jnp.where(use_l[:, None], jnp.transpose(gyro - bias_hat[:, None, 3:6], (1, 2, 0)), 0.0)
    dt_l = jnp.where(use_l, jnp.transpose(dt), 0.0)
    inv_dt = jnp.where(use_l, 1.0 / jnp.where(use_l, dt_l, 1.0), 0.0)

    # 1. theta before each sample (forward scan).
    theta_end, theta = lax.scan(_theta_step, jnp.zeros((3, k)), (w, dt_l))

    # 2. per-sample blocks.
    blk = _sample_blocks(theta, a, w, dt_l, one)
    rot, a_nav = blk["rot"], blk["a_nav"]
    t_after = jnp.cumsum(dt_l[::-1], axis=0)[::-1] - dt_l  # time after each sample
    wp = dt_l * (0.5 * dt_l + t_after)  # weight of sample k in dp (and in Phi_k B_k)

    # 3. transitions Phi_k (backward scan).
    coef = jnp.stack([jnp.zeros_like(dt_l), 0.5 * dt_l + t_after, jnp.ones_like(dt_l)], axis=1)  # (M, 3, K)
    init = jnp.concatenate([jnp.broadcast_to(jnp.eye(3)[None, :, :, None], (1, 3, 3, k)), jnp.zeros((2, 3, 3, k))])
    _, phi = lax.scan(_transition_step, init, (blk["f"], blk["g"], coef), reverse=True)
    phi = phi.reshape(m, 9, 3, k)  # rows [Pi; X; Y]

    # 4. sums over the samples: Phi_k B_k = [0; R wp; R dt],  Phi_k C_k = [Pi; X; Y] C_rot =: Z_k.
    z = _fence(_mm(phi, blk["c"]), one)  # (M, 9, 3, K)
    h_gyro = -_total(z)  # (9, 3, K)
    h_acc = jnp.concatenate([jnp.zeros((3, 3, k)), -_total(rot * _s(wp)), -_total(rot * _s(dt_l))])
    # Gyro noise sum_k Z (Qg/dt) Z^T; accelerometer noise S = R Qa R^T enters [dp, dv] with
    # weights [wp^2, wp dt; wp dt, dt^2] / dt; integration noise Qi dt enters dp.
    if isotropic:  # Qg = sg^2 I: Z Qg / dt = (sg^2 / dt) Z, no product needed
        zq = _fence(z * _s(params.gyroscope_covariance[0, 0] * inv_dt), one)
    else:
        qg = jnp.broadcast_to(params.gyroscope_covariance[None, :, :, None], (m, 3, 3, k))
        zq = _fence(_mm(z, qg) * _s(inv_dt), one)  # Z Qg / dt, Qg symmetric
    # Symmetric: the 6 upper 3x3 blocks of the 9x9 only.
    upper = {
        (b, c): _total(_mm_t(zq[:, 3 * b : 3 * b + 3], z[:, 3 * c : 3 * c + 3])) for b in _R3 for c in _R3 if b <= c
    }
    cov_g = jnp.concatenate(
        [
            jnp.concatenate([upper[(b, c)] if b <= c else jnp.swapaxes(upper[(c, b)], 0, 1) for c in _R3], axis=1)
            for b in _R3
        ]
    )  # (9, 9, K)
    if isotropic:  # Qa = sa^2 I: R Qa R^T = sa^2 I for every sample
        s_acc = _s(jnp.broadcast_to(params.accelerometer_covariance[0, 0], dt_l.shape)) * _eye(4)
    else:
        qa = jnp.broadcast_to(params.accelerometer_covariance[None, :, :, None], rot.shape)
        s_acc = _mm_t(_mm(rot, qa), rot)
    s_pp = _total(s_acc * _s(wp * wp * inv_dt)) + params.integration_covariance[:, :, None] * _total(dt_l)[None, None]
    s_pv = _total(s_acc * _s(wp))
    s_vv = _total(s_acc * _s(dt_l))
    z33 = jnp.zeros((3, 3, k))
    acc_cov = jnp.concatenate(
        [
            jnp.zeros((3, 9, k)),
            jnp.concatenate([z33, s_pp, s_pv], axis=1),
            jnp.concatenate([z33, jnp.swapaxes(s_pv, 0, 1), s_vv], axis=1),
        ]
    )
    dpdv = jnp.concatenate([_total(a_nav * _v(wp)), _total(a_nav * _v(dt_l))])
    preint = jnp.concatenate([theta_end, dpdv])  # (9, K)
    hb = jnp.concatenate([h_acc, h_gyro], axis=1)  # (9, 6, K)
    return (
        jnp.transpose(preint),
        jnp.transpose(hb, (2, 0, 1)),
        jnp.transpose(cov_g + acc_cov, (2, 0, 1)),
        _total(dt_l),
    )


# ---------------------------------------------------------------------------------------
# Result PyTree and the public preintegration functions
# ---------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PreintegratedImu:
    """Preintegrated IMU measurements of a batch of intervals (GTSAM's PIM), a PyTree.

    ==================  ===============  =================================================
    field               shape            meaning
    ==================  ===============  =================================================
    ``preintegrated``   (*batch, 9)      tangent state ``[theta, dp, dv]`` at ``bias_hat``
                                         (rad, m, m/s; frame of body at t_i) =
                                         GTSAM's ``preintegrated()``
    ``delta_rotation``  SO3 (*batch,)    ``dR = Exp(theta)`` (``deltaRij``)
    ``delta_time``      (*batch,)        s (``deltaTij``)
    ``bias_jacobian``   (*batch, 9, 6)   d preintegrated / d bias, rows [theta, dp, dv],
                                         columns [acc, gyro] (GTSAM's
                                         ``preintegrated_H_biasAcc | _H_biasOmega``)
    ``covariance``      (*batch, 9, 9)   of ``preintegrated``, order [dR, dP, dV]
                                         (``preintMeasCov``)
    ``bias_hat``        (*batch, 6)      bias used to integrate, (acc, gyro)
    ``valid``           (*batch,) bool   every used sample had finite dt > 0 and finite
                                         readings (checked eagerly too, see
                                         :func:`preintegrate`)
    ==================  ===============  =================================================
    """

    preintegrated: Array
    delta_rotation: SO3
    delta_time: Array
    bias_jacobian: Array
    covariance: Array
    bias_hat: Array
    valid: Array

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.delta_time.shape)

    @property
    def rotation_vector(self) -> Array:
        """``theta`` (*batch, 3), rad."""
        return self.preintegrated[..., 0:3]

    @property
    def delta_position(self) -> Array:
        """``dp`` (*batch, 3), m (``deltaPij``)."""
        return self.preintegrated[..., 3:6]

    @property
    def delta_velocity(self) -> Array:
        """``dv`` (*batch, 3), m/s (``deltaVij``)."""
        return self.preintegrated[..., 6:9]

    def __getitem__(self, index: Any) -> PreintegratedImu:
        return jax.tree_util.tree_map(lambda leaf: leaf[index], self)

    def bias_corrected(self, bias: Any) -> Array:
        """``preintegrated + H (bias - bias_hat)`` (*batch, 9), the first-order correction
        (GTSAM's ``biasCorrectedDelta``); ``bias`` (*batch, 6) in (acc, gyro) order."""
        db = jnp.broadcast_to(jnp.asarray(bias), self.bias_hat.shape) - self.bias_hat
        return self.preintegrated + jnp.einsum("...ij,...j->...i", self.bias_jacobian, db)

    def residual_covariance(self) -> Array:
        """Covariance of the factor residual (*batch, 9, 9), GTSAM's
        ``residualCovariance()``: ``J P J^T``, ``J = blockdiag(Jr(theta), dR^T, dR^T)``
        maps the additive tangent perturbation into the NavState chart at ``dR``."""
        jr = SO3.jr(self.rotation_vector)
        rt = jnp.swapaxes(self.delta_rotation.as_matrix(), -1, -2)
        z = jnp.zeros_like(jr)
        jac = jnp.concatenate(
            [
                jnp.concatenate([jr, z, z], axis=-1),
                jnp.concatenate([z, rt, z], axis=-1),
                jnp.concatenate([z, z, rt], axis=-1),
            ],
            axis=-2,
        )
        return jac @ self.covariance @ jnp.swapaxes(jac, -1, -2)


def _check_finite_positive(dt: np.ndarray, use: np.ndarray, acc: np.ndarray, gyro: np.ndarray) -> None:
    """Eager validation (numpy); locates the first offending sample only on failure."""
    if not (np.isfinite(dt).all() and (dt >= 0).all()):
        where = tuple(int(i) for i in np.argwhere(~np.isfinite(dt) | (dt < 0))[0])
        raise ValueError(f"dt must be finite and >= 0 (0 marks padding); dt{list(where)} = {dt[where]}")
    if not (dt[use] > 0).all():
        where = tuple(int(i) for i in np.argwhere(use & (dt <= 0))[0])
        raise ValueError(f"dt must be > 0 for every sample the mask uses; dt{list(where)} = {dt[where]}")
    for name, x in (("acc", acc), ("gyro", gyro)):
        if not np.isfinite(x).all():
            bad = use & ~np.all(np.isfinite(x), axis=-1)
            if np.any(bad):
                where = tuple(int(i) for i in np.argwhere(bad)[0])
                raise ValueError(f"{name}{list(where)} is not finite: {x[where].tolist()}")


def preintegrate(
    acc: Any,
    gyro: Any,
    dt: Any,
    params: PreintegrationParams,
    bias_hat: Any = None,
    mask: Any = None,
) -> PreintegratedImu:
    """Preintegrate a batch of intervals at once (tangent preintegration, GTSAM 4.3).

    Args:
      acc: ``(*batch, M, 3)`` accelerometer readings (specific force, m/s^2, IMU = body frame).
      gyro: ``(*batch, M, 3)`` gyroscope readings, rad/s.
      dt: ``(*batch, M)`` seconds each sample is held (integrated) for. Intervals of unequal
        length are padded; without ``mask``, ``dt == 0`` marks padding.
      params: noise densities (:class:`PreintegrationParams`).
      bias_hat: ``(6,)`` or ``(*batch, 6)`` bias (acc, gyro) to integrate with; default 0.
      mask: optional ``(*batch, M)`` bool, True for the samples to use.

    All intervals are integrated at once by one jitted kernel, vectorised over the
    flattened batch (the intervals are SIMD lanes; ``lax.scan`` only over the samples of the
    rotation recurrence and of the transition matrices, see the kernel notes above); it
    compiles once per (batch, M) shape. The result equals GTSAM's sample-by-sample loop to
    rounding (~1e-15 relative). Raises ``ValueError`` for mismatched shapes and, when the
    inputs are concrete arrays, for a used sample with non-finite or non-positive ``dt`` or
    non-finite readings. Under an outer ``jit`` the same condition is returned in ``valid``
    instead (and :meth:`ImuFactor.create` refuses such intervals).
    """
    shape = tuple(np.shape(acc))
    if len(shape) < 2 or shape[-1] != 3:
        raise ValueError(f"acc must have shape (*batch, M, 3), got {shape}")
    if tuple(np.shape(gyro)) != shape:
        raise ValueError(f"gyro must have the shape of acc {shape}, got {tuple(np.shape(gyro))}")
    if tuple(np.shape(dt)) != shape[:-1]:
        raise ValueError(f"dt must have shape (*batch, M) = {shape[:-1]}, got {tuple(np.shape(dt))}")
    batch = shape[:-2]
    if shape[-2] == 0:
        raise ValueError("acc holds no samples (M = 0)")
    if mask is not None:
        if tuple(np.shape(mask)) != shape[:-1]:
            raise ValueError(f"mask must have the shape of dt {shape[:-1]}, got {tuple(np.shape(mask))}")
        if np.result_type(mask) != np.bool_:
            raise ValueError(f"mask must be boolean, got dtype {np.result_type(mask)}")
    if bias_hat is None:
        bias_hat = np.zeros(6)
    bshape = tuple(np.shape(bias_hat))
    if bshape[-1:] != (6,) or len(bshape) > len(batch) + 1 or bshape[:-1] != batch[len(batch) - len(bshape) + 1 :]:
        raise ValueError(f"bias_hat must have shape (6,) or (*batch, 6) with batch {batch}, got {bshape}")
    if _is_concrete(acc, gyro, dt, mask):
        dt_np = np.asarray(dt, dtype=np.float64)
        use_np = dt_np > 0 if mask is None else np.asarray(mask)
        _check_finite_positive(dt_np, use_np, np.asarray(acc, dtype=np.float64), np.asarray(gyro, dtype=np.float64))
    return _preintegrate_jit(acc, gyro, dt, mask, bias_hat, params, jnp.ones(()), _isotropic(params))


def _isotropic(params: PreintegrationParams) -> bool:
    """True when both white-noise covariances are multiples of the identity (the usual
    Kalibr case: one density per sensor) and known now; the kernel then skips the products
    with them. Traced parameters (under an outer jit or grad) take the general path."""
    if not _is_concrete(params.accelerometer_covariance, params.gyroscope_covariance):
        return False
    qa = np.asarray(params.accelerometer_covariance)
    qg = np.asarray(params.gyroscope_covariance)
    return bool(np.array_equal(qa, qa[0, 0] * np.eye(3)) and np.array_equal(qg, qg[0, 0] * np.eye(3)))


@functools.partial(jax.jit, static_argnames=("isotropic",))
def _preintegrate_jit(
    acc: Any,
    gyro: Any,
    dt: Any,
    mask: Any,
    bias_hat: Any,
    params: PreintegrationParams,
    one: Array,
    isotropic: bool = False,
) -> PreintegratedImu:
    acc = jnp.asarray(acc, dtype=jnp.float64)
    gyro = jnp.asarray(gyro, dtype=jnp.float64)
    dt = jnp.asarray(dt, dtype=jnp.float64)
    batch, m = tuple(acc.shape[:-2]), acc.shape[-2]
    use = dt > 0 if mask is None else jnp.asarray(mask)
    bias_hat = jnp.broadcast_to(jnp.asarray(bias_hat, dtype=jnp.float64), (*batch, 6))
    used_dt_ok = jnp.where(use, jnp.isfinite(dt) & (dt > 0), jnp.isfinite(dt) & (dt >= 0))
    used_xyz_ok = ~use | (jnp.all(jnp.isfinite(acc), axis=-1) & jnp.all(jnp.isfinite(gyro), axis=-1))
    k = int(np.prod(batch)) if batch else 1
    preint, hb, cov, t_sum = _preintegrate_lanes(
        acc.reshape(k, m, 3),
        gyro.reshape(k, m, 3),
        dt.reshape(k, m),
        use.reshape(k, m),
        bias_hat.reshape(k, 6),
        params,
        one,
        isotropic,
    )
    preint = preint.reshape(*batch, 9)
    return PreintegratedImu(
        preintegrated=preint,
        delta_rotation=SO3.exp(preint[..., 0:3]),
        delta_time=t_sum.reshape(batch),
        bias_jacobian=hb.reshape(*batch, 9, 6),
        covariance=cov.reshape(*batch, 9, 9),
        bias_hat=bias_hat,
        valid=jnp.all(used_dt_ok & used_xyz_ok, axis=-1),
    )


@dataclasses.dataclass(frozen=True)
class ImuIntervals:
    """IMU samples cut into keyframe intervals and padded (numpy).

    ``acc``/``gyro`` (K, M, 3), ``dt`` (K, M) s (0 where padded), ``mask`` (K, M) bool,
    ``t_start``/``t_end`` (K,) the keyframe times, ``index`` (K, M) the source sample
    index of each slot (-1 where padded).
    """

    acc: np.ndarray
    gyro: np.ndarray
    dt: np.ndarray
    mask: np.ndarray
    t_start: np.ndarray
    t_end: np.ndarray
    index: np.ndarray

    def __len__(self) -> int:
        return int(self.dt.shape[0])

    @property
    def num_samples(self) -> int:
        """Samples integrated in all (a sample split by a keyframe counts twice)."""
        return int(self.mask.sum())


def cut_imu_stream(t: Any, acc: Any, gyro: Any, keyframe_times: Any, max_samples: int | None = None) -> ImuIntervals:
    """Cut a timestamped IMU stream into the intervals between consecutive keyframes.

    Each sample is held constant (zero-order hold) from its time stamp to the next sample's,
    which is how GTSAM users feed ``integrateMeasurement(acc, gyro, t[k+1] - t[k])``. A hold
    that straddles a keyframe is split there: interval ``[t_a, t_b]`` integrates the last
    sample at or before ``t_a`` from ``t_a`` to the next stamp, then every sample with
    ``t_a < t_k < t_b`` up to ``min(t_{k+1}, t_b)``; so ``delta_time == t_b - t_a`` exactly.

    Args:
      t: ``(N,)`` strictly increasing sample times, s. ``acc``/``gyro``: ``(N, 3)``.
      keyframe_times: ``(K + 1,)`` strictly increasing, inside ``[t[0], t[-1]]``.
      max_samples: pad M to this many samples (raises if an interval needs more).
    """
    t = np.asarray(t, dtype=np.float64)
    acc = np.asarray(acc, dtype=np.float64)
    gyro = np.asarray(gyro, dtype=np.float64)
    kf = np.asarray(keyframe_times, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] < 2:
        raise ValueError(f"t must have shape (N,) with N >= 2, got {t.shape}")
    n = t.shape[0]
    if acc.shape != (n, 3) or gyro.shape != (n, 3):
        raise ValueError(f"acc and gyro must have shape ({n}, 3) to match t, got {acc.shape} and {gyro.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        bad = int(np.argmax(~np.isfinite(t[1:]) | (np.diff(t) <= 0))) + 1
        raise ValueError(f"t must be finite and strictly increasing; t[{bad - 1}] = {t[bad - 1]}, t[{bad}] = {t[bad]}")
    if not (np.all(np.isfinite(acc)) and np.all(np.isfinite(gyro))):
        raise ValueError("acc and gyro must be finite")
    if kf.ndim != 1 or kf.shape[0] < 2:
        raise ValueError(f"keyframe_times must have shape (K + 1,) with K >= 1, got {kf.shape}")
    if not np.all(np.isfinite(kf)) or np.any(np.diff(kf) <= 0):
        raise ValueError("keyframe_times must be finite and strictly increasing")
    if kf[0] < t[0] or kf[-1] > t[-1]:
        raise ValueError(f"keyframe_times [{kf[0]}, {kf[-1]}] must lie inside the stream [{t[0]}, {t[-1]}]")

    t_a, t_b = kf[:-1], kf[1:]
    first = np.searchsorted(t, t_a, side="right") - 1  # last sample at or before t_a
    last = np.searchsorted(t, t_b, side="left") - 1  # last sample before t_b
    count = last - first + 1
    m = int(count.max())
    if max_samples is not None:
        if m > max_samples:
            raise ValueError(f"an interval needs {m} samples, more than max_samples = {max_samples}")
        m = int(max_samples)
    slot = np.arange(m)[None, :]
    mask = slot < count[:, None]
    idx = np.where(mask, first[:, None] + slot, 0)
    start = np.maximum(t[idx], t_a[:, None])
    end = np.minimum(t[np.minimum(idx + 1, n - 1)], t_b[:, None])
    dt = np.where(mask, end - start, 0.0)
    zeros = np.zeros(3)
    return ImuIntervals(
        acc=np.where(mask[..., None], acc[idx], zeros),
        gyro=np.where(mask[..., None], gyro[idx], zeros),
        dt=dt,
        mask=mask,
        t_start=t_a,
        t_end=t_b,
        index=np.where(mask, idx, -1),
    )


def preintegrate_stream(
    t: Any, acc: Any, gyro: Any, keyframe_times: Any, params: PreintegrationParams, bias_hat: Any = None
) -> PreintegratedImu:
    """:func:`cut_imu_stream` then :func:`preintegrate`: one result per keyframe interval."""
    iv = cut_imu_stream(t, acc, gyro, keyframe_times)
    return preintegrate(iv.acc, iv.gyro, iv.dt, params, bias_hat=bias_hat, mask=iv.mask)


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
        cov = pim.residual_covariance()
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
