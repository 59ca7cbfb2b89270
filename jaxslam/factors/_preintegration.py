"""IMU preintegration (SPEC eq. 3); the factors that use it are in ``_imu.py``.

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
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._threads import parallel_map, workers
from ..lie import SO3
from ._imu_kernel import _BLOCK_LANES, _preintegrate_lanes
from ._imu_params import PreintegrationParams, _is_concrete

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
    parallel: bool = True,
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
      parallel: False keeps a large batch in one call on the calling thread (see below).

    All intervals are integrated at once by one jitted kernel, vectorised over the
    flattened batch (the intervals are SIMD lanes; ``lax.scan`` only over the samples of the
    rotation recurrence and of the transition matrices, see the kernel notes above); it
    compiles once per (batch, M) shape. A concrete batch of at least
    ``PARALLEL_MIN_INTERVALS`` intervals is cut into one equal part per core, run on a
    thread pool so that all cores work (the same numbers to 1 ulp). The result equals
    GTSAM's sample-by-sample loop to rounding (~1e-15 relative). Raises ``ValueError`` for
    mismatched shapes and, when the inputs are concrete arrays, for a used sample with
    non-finite or non-positive ``dt`` or non-finite readings. Under an outer ``jit`` the
    same condition is returned in ``valid`` instead (and :meth:`ImuFactor.create` refuses
    such intervals).
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
    concrete = _is_concrete(acc, gyro, dt, mask, bias_hat, *jax.tree_util.tree_leaves(params))
    k = int(np.prod(batch)) if batch else 1
    if parallel and concrete and k >= PARALLEL_MIN_INTERVALS and workers() > 1:
        out = _preintegrate_parts(acc, gyro, dt, mask, bias_hat, params, batch, k)
    else:
        out = _preintegrate_jit(acc, gyro, dt, mask, bias_hat, params, jnp.ones(()), _isotropic(params))
    # Concrete inputs are checked through the kernel's own ``valid`` flags (the same
    # conditions, computed in the same pass over the data); numpy only locates the first
    # offending sample when one is there, so the usual case pays no second pass.
    if concrete and not bool(np.all(np.asarray(out.valid))):
        dt_np = np.asarray(dt, dtype=np.float64)
        use_np = dt_np > 0 if mask is None else np.asarray(mask)
        _check_finite_positive(dt_np, use_np, np.asarray(acc, dtype=np.float64), np.asarray(gyro, dtype=np.float64))
        bad = int(np.argmin(np.asarray(out.valid).reshape(-1)))
        raise ValueError(f"interval {bad} (flattened batch index) holds a non-finite or non-positive sample")
    return out


# Large concrete batches are cut into equal parts that run on a thread pool: XLA:CPU runs
# one program's loops on one core (a second call dispatched asynchronously waits for the
# first), while calls from separate threads run side by side. The parts use smaller blocks
# of lanes than the single call. On the KITTI stream (4696 intervals, 2-core AMD EPYC, one
# process, 25 interleaved rounds): one call 12.9 ms; 4 parts of 128-lane blocks 9.9 ms
# (256: 10.4, 512: 10.9), 2 parts 9.9 ms; the same numbers to 1 ulp. One part per core:
# in three later A/Bs (40 interleaved rounds each) 2 parts took 12.6 / 11.3 / 13.9 ms
# against 13.5 / 11.7 / 14.3 for 4 (3 parts 12.7 / 14.4, 8 parts 11.9 / 15.1). Parts are
# padded to one shape (one compile); below ``PARALLEL_MIN_INTERVALS`` intervals the single
# call is used (hand-offs between threads would cost more than they bring).
PARALLEL_MIN_INTERVALS = 2048
_PART_BLOCK_LANES = 128


def _parts() -> int:
    return workers()


def _preintegrate_parts(
    acc: Any,
    gyro: Any,
    dt: Any,
    mask: Any,
    bias_hat: Any,
    params: PreintegrationParams,
    batch: tuple[int, ...],
    k: int,
) -> PreintegratedImu:
    """:func:`_preintegrate_jit` on ``k`` concrete intervals cut into equal parts (padded with
    empty intervals), run on the thread pool and joined."""
    m = np.shape(acc)[-2]
    acc = np.asarray(acc, dtype=np.float64).reshape(k, m, 3)
    gyro = np.asarray(gyro, dtype=np.float64).reshape(k, m, 3)
    dt = np.asarray(dt, dtype=np.float64).reshape(k, m)
    use = (dt > 0) if mask is None else np.asarray(mask).reshape(k, m)
    bias = np.broadcast_to(np.asarray(bias_hat, dtype=np.float64), (*batch, 6)).reshape(k, 6)
    parts = _parts()
    size = -(-k // parts)
    pad = parts * size - k

    def padded(x: np.ndarray) -> np.ndarray:
        return np.concatenate([x, np.zeros((pad, *x.shape[1:]), x.dtype)]) if pad else x

    acc, gyro, dt, use, bias = (padded(x) for x in (acc, gyro, dt, use, bias))
    one, iso = jnp.ones(()), _isotropic(params)

    def part(i: int) -> PreintegratedImu:
        sl = slice(i * size, (i + 1) * size)
        return jax.block_until_ready(
            _preintegrate_jit(acc[sl], gyro[sl], dt[sl], use[sl], bias[sl], params, one, iso, _PART_BLOCK_LANES)
        )

    outs = parallel_map(part, range(parts))
    return _join(outs, k, batch)


@functools.partial(jax.jit, static_argnames=("k", "batch"))
def _join(outs: list[PreintegratedImu], k: int, batch: tuple[int, ...]) -> PreintegratedImu:
    return jax.tree_util.tree_map(
        lambda *xs: jnp.concatenate(xs)[:k].reshape(*batch, *xs[0].shape[1:]),
        *outs,
    )


def _isotropic(params: PreintegrationParams) -> bool:
    """True when both white-noise covariances are multiples of the identity (the usual
    Kalibr case: one density per sensor) and known now; the kernel then skips the products
    with them. Traced parameters (under an outer jit or grad) take the general path."""
    if not _is_concrete(params.accelerometer_covariance, params.gyroscope_covariance):
        return False
    qa = np.asarray(params.accelerometer_covariance)
    qg = np.asarray(params.gyroscope_covariance)
    return bool(np.array_equal(qa, qa[0, 0] * np.eye(3)) and np.array_equal(qg, qg[0, 0] * np.eye(3)))


@functools.partial(jax.jit, static_argnames=("isotropic", "block_lanes"))
def _preintegrate_jit(
    acc: Any,
    gyro: Any,
    dt: Any,
    mask: Any,
    bias_hat: Any,
    params: PreintegrationParams,
    one: Array,
    isotropic: bool = False,
    block_lanes: int = _BLOCK_LANES,
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
        block_lanes,
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
