"""The vectorised tangent-preintegration kernel (intervals as SIMD lanes).

See :mod:`jaxslam.factors._preintegration` for the method and its references."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax import Array, lax

from ._imu_params import PreintegrationParams

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
# allocations cost page faults on every call). On the KITTI stream (4696 intervals, same
# process, interleaved): 256 lanes 14.7 ms, 512 12.7, 1024 11.5, 2048 12.4, one block 23 ms;
# after the lanes-last inputs and fences (session 30): 256 11.4, 512 10.5, 1024 10.6, 2048 11.9.
_BLOCK_LANES = 1024


def _preintegrate_lanes(
    acc: Array,
    gyro: Array,
    dt: Array,
    use: Array,
    bias_hat: Array,
    params: PreintegrationParams,
    one: Array,
    isotropic: bool = False,
    block_lanes: int = _BLOCK_LANES,
) -> tuple[Array, Array, Array, Array]:
    """``acc``/``gyro`` (K, M, 3), ``dt``/``use`` (K, M), ``bias_hat`` (K, 6) -> the lane
    results: preintegrated (K, 9), bias Jacobian (K, 9, 6), covariance (K, 9, 9), dt (K,).
    ``one`` is a runtime 1.0 (see :func:`_fence`); at most ``block_lanes`` lanes per block."""
    k = dt.shape[0]
    blocks = -(-k // block_lanes)
    lanes = -(-k // blocks)
    pad = blocks * lanes - k

    def split(x: Array) -> Array:
        """(K, ...) -> lanes-last blocks (blocks, ..., lanes), transposed here once: inside
        the block loop XLA fused the transposition into every consumer, whose loops then
        read across lanes and were left scalar."""
        x = jnp.concatenate([x, jnp.zeros((pad, *x.shape[1:]), x.dtype)]) if pad else x
        return jnp.moveaxis(x.reshape(blocks, lanes, *x.shape[1:]), 1, -1)

    outs = lax.map(
        lambda b: _preintegrate_block(b[0], b[1], b[2], b[3], b[4], params, one, isotropic),
        tuple(split(x) for x in (acc, gyro, dt, use, bias_hat)),
    )
    # (blocks, ..., lanes) -> (K, ...), the results' one transposition
    return tuple(jnp.moveaxis(o, -1, 1).reshape(blocks * lanes, *o.shape[1:-1])[:k] for o in outs)  # type: ignore[return-value]


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
    """One block of lanes, lanes last: ``acc``/``gyro`` (M, 3, K), ``dt``/``use`` (M, K),
    ``bias_hat`` (6, K) -> preintegrated (9, K), bias Jacobian (9, 6, K), covariance
    (9, 9, K), dt (K,) (see :func:`_preintegrate_lanes`).

    Same result as GTSAM's per-sample ``TangentPreintegration::update`` +
    ``PreintegratedImuMeasurements::integrateMeasurement`` loop, with the linear recurrences
    unrolled (``x_M = A_M ... A_1 x_0 + sum_k Phi_k (B_k a_k + C_k w_k)``):
    ``H = -sum_k Phi_k [B_k | C_k]`` and ``P = sum_k Phi_k (B Qa/dt B^T + C Qg/dt C^T +
    E Qi dt E^T)_k Phi_k^T``, so only theta (forwards) and Phi (backwards) are sequential.
    """
    m, k = dt.shape
    # Bias-corrected readings (M, 3, K); unused slots become exact no-ops: a = w = dt = 0.
    a = jnp.where(use[:, None], acc - bias_hat[None, 0:3], 0.0)
    w = jnp.where(use[:, None], gyro - bias_hat[None, 3:6], 0.0)
    dt_l = jnp.where(use, dt, 0.0)
    inv_dt = jnp.where(use, 1.0 / jnp.where(use, dt_l, 1.0), 0.0)
    # Stored once per block: fused into their consumers, the block's slice of the inputs
    # is taken inside each loop, whose index XLA:CPU reloads per element (LLVM cannot
    # prove the loop's stores leave it unchanged), and those loops stay scalar.
    a, w, dt_l, inv_dt = _fence((a, w, dt_l, inv_dt), one)

    # 1. theta before each sample (forward scan). Both scans store each step's sample first
    # (the fence; a scan slices its inputs like the block loop above).
    theta_end, theta = lax.scan(lambda th, smp: _theta_step(th, _fence(smp, one)), jnp.zeros((3, k)), (w, dt_l))

    # 2. per-sample blocks.
    blk = _sample_blocks(theta, a, w, dt_l, one)
    rot, a_nav = blk["rot"], blk["a_nav"]
    t_after = jnp.cumsum(dt_l[::-1], axis=0)[::-1] - dt_l  # time after each sample
    wp = dt_l * (0.5 * dt_l + t_after)  # weight of sample k in dp (and in Phi_k B_k)

    # 3. transitions Phi_k (backward scan).
    coef = jnp.stack([jnp.zeros_like(dt_l), 0.5 * dt_l + t_after, jnp.ones_like(dt_l)], axis=1)  # (M, 3, K)
    init = jnp.concatenate([jnp.broadcast_to(jnp.eye(3)[None, :, :, None], (1, 3, 3, k)), jnp.zeros((2, 3, 3, k))])
    _, phi = lax.scan(
        lambda p, smp: _transition_step(p, _fence(smp, one)), init, (blk["f"], blk["g"], coef), reverse=True
    )
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
    return preint, hb, cov_g + acc_cov, _total(dt_l)
