"""Compiled (numba) linearisation of the commonest factor: ``BetweenFactor`` on Pose3 / Pose2
with Gaussian noise and no robust kernel, row by row.

The incremental solver relinearises a handful of constraints per update. Through JAX that is
one call of the factor class's jitted kernel, whose compiled program for ``BetweenFactor`` on
Pose3 runs some sixty fused loops (the series-or-closed-form branches of the Lie maps are
both evaluated, and XLA splits fusions at every shared transcendental): about 0.1 ms for 8
rows alone and 0.3 ms inside an update, most of the parking-garage stream's time. Written
out per row it is a few microseconds. The JAX factors stay the reference and the general
path (every other factor class, robust kernels, autodiff, differentiation through the
batch solver); these kernels follow :mod:`jaxslam.lie`'s formulas and series thresholds
and are tested equal to :func:`jaxslam.core.linearize`.

Outputs are whitened: ``J = L [dE/dx_i, dE/dx_j]``, ``r = L e``, ``cost = |r|^2 / 2`` with
``e = Log(Z^-1 x_i^-1 x_j)`` and ``L`` the noise's square-root information.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ._liekern import _quat_rotate

_jit = numba.njit(cache=True, nogil=True)

_SERIES_SQ = 0.2 * 0.2  # jaxslam.lie._utils.SERIES_ANGLE squared


@_jit
def _series(t2: float, c0: float, c1: float, c2: float, c3: float, c4: float) -> float:  # pragma: no cover
    return (((c4 * t2 + c3) * t2 + c2) * t2 + c1) * t2 + c0


@_jit
def _coef_b(t2: float) -> float:  # pragma: no cover
    """(1 - cos t) / t^2."""
    if t2 < _SERIES_SQ:
        return _series(t2, 0.5, -1.0 / 24.0, 1.0 / 720.0, -1.0 / 40320.0, 1.0 / 3628800.0)
    t = math.sqrt(t2)
    s = math.sin(0.5 * t)
    return 2.0 * s * s / (t * t)


@_jit
def _coef_c(t2: float) -> float:  # pragma: no cover
    """(t - sin t) / t^3."""
    if t2 < _SERIES_SQ:
        return _series(t2, 1.0 / 6.0, -1.0 / 120.0, 1.0 / 5040.0, -1.0 / 362880.0, 1.0 / 39916800.0)
    t = math.sqrt(t2)
    return (t - math.sin(t)) / (t * t * t)


@_jit
def _coef_a(t2: float) -> float:  # pragma: no cover
    """sin t / t."""
    if t2 < _SERIES_SQ:
        return _series(t2, 1.0, -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0, 1.0 / 362880.0)
    t = math.sqrt(t2)
    return math.sin(t) / t


@_jit
def _coef_jrinv(t2: float) -> float:  # pragma: no cover
    """1/t^2 - cot(t/2) / (2 t): the W^2 coefficient of SO(3)'s Jr^-1."""
    if t2 < _SERIES_SQ:
        return _series(t2, 1.0 / 12.0, 1.0 / 720.0, 1.0 / 30240.0, 1.0 / 1209600.0, 1.0 / 47900160.0)
    t = math.sqrt(t2)
    return 1.0 / (t * t) - 0.5 * math.cos(0.5 * t) / (t * math.sin(0.5 * t))


@_jit
def _coef_q2(t2: float) -> float:  # pragma: no cover
    """(t^2 + 2 cos t - 2) / (2 t^4)."""
    if t2 < _SERIES_SQ:
        return _series(t2, 1.0 / 24.0, -1.0 / 720.0, 1.0 / 40320.0, -1.0 / 3628800.0, 1.0 / 479001600.0)
    t = math.sqrt(t2)
    return (t * t + 2.0 * math.cos(t) - 2.0) / (2.0 * t**4)


@_jit
def _coef_q3(t2: float) -> float:  # pragma: no cover
    """(2 t - 3 sin t + t cos t) / (2 t^5)."""
    if t2 < _SERIES_SQ:
        return _series(t2, 1.0 / 120.0, -1.0 / 2520.0, 1.0 / 120960.0, -1.0 / 9979200.0, 1.0 / 1245404160.0)
    t = math.sqrt(t2)
    return (2.0 * t - 3.0 * math.sin(t) + t * math.cos(t)) / (2.0 * t**5)


@_jit
def _qmul(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """Hamilton product of wxyz quaternions."""
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    out[0] = aw * bw - ax * bx - ay * by - az * bz
    out[1] = aw * bx + ax * bw + ay * bz - az * by
    out[2] = aw * by - ax * bz + ay * bw + az * bx
    out[3] = aw * bz + ax * by - ay * bx + az * bw


@_jit
def _relative3(a: np.ndarray, b: np.ndarray, out: np.ndarray, s: np.ndarray) -> None:  # pragma: no cover
    """``a^-1 b`` of SE(3) parameters ``[q, t]`` (``s``: at least 4 floats of scratch)."""
    s[0] = a[0]
    s[1] = -a[1]
    s[2] = -a[2]
    s[3] = -a[3]
    _qmul(s[:4], b[:4], out[:4])
    a0, a1, a2 = _quat_rotate(s[:4], a[4:7])
    b0, b1, b2 = _quat_rotate(s[:4], b[4:7])
    out[4], out[5], out[6] = -a0 + b0, -a1 + b1, -a2 + b2


@_jit
def _skew(v0: float, v1: float, v2: float, out: np.ndarray) -> None:  # pragma: no cover
    out[0, 0], out[0, 1], out[0, 2] = 0.0, -v2, v1
    out[1, 0], out[1, 1], out[1, 2] = v2, 0.0, -v0
    out[2, 0], out[2, 1], out[2, 2] = -v1, v0, 0.0


@_jit
def _mm3(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    for p in range(3):
        for q in range(3):
            out[p, q] = a[p, 0] * b[0, q] + a[p, 1] * b[1, q] + a[p, 2] * b[2, q]


@_jit
def _whiten(L: np.ndarray, e: np.ndarray, Jraw: np.ndarray, J: np.ndarray, r: np.ndarray) -> float:  # pragma: no cover
    """``J = L Jraw``, ``r = L e``; returns ``|r|^2 / 2``."""
    m, T = Jraw.shape
    sq = 0.0
    for p in range(m):
        acc = 0.0
        for k in range(m):
            acc += L[p, k] * e[k]
        r[p] = acc
        sq += acc * acc
        for c in range(T):
            acc = 0.0
            for k in range(m):
                acc += L[p, k] * Jraw[k, c]
            J[p, c] = acc
    return 0.5 * sq


@_jit
def between_se3(
    xi: np.ndarray, xj: np.ndarray, z: np.ndarray, L: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Whitened ``(J (n, 6, 12), r (n, 6), cost (n,))`` of SE(3) between constraints:
    ``e = Log(z^-1 xi^-1 xj)``, ``de/dxj = Jr^-1(e)``, ``de/dxi = -Jr^-1(e) Ad(xj^-1 xi)``."""
    n = xi.shape[0]
    J = np.empty((n, 6, 12))
    r = np.empty((n, 6))
    cost = np.empty(n)
    rel = np.empty(7)
    err = np.empty(7)
    ji_rel = np.empty(7)
    s = np.empty(4)
    e = np.empty(6)
    W = np.empty((3, 3))
    R = np.empty((3, 3))
    WR = np.empty((3, 3))
    RW = np.empty((3, 3))
    WRW = np.empty((3, 3))
    WW = np.empty((3, 3))
    t1 = np.empty((3, 3))
    t2 = np.empty((3, 3))
    Q = np.empty((3, 3))
    Ji = np.empty((3, 3))
    Rot = np.empty((3, 3))
    Jraw = np.empty((6, 12))
    jj = np.empty((6, 6))
    ad = np.empty((6, 6))
    for i in range(n):
        _relative3(xi[i], xj[i], rel, s)
        _relative3(z[i], rel, err, s)
        # Log of SE(3): omega from the quaternion (w >= 0), rho = V^-1 t
        sign = -1.0 if err[0] < 0.0 else 1.0
        w = sign * err[0]
        v0, v1, v2 = sign * err[1], sign * err[2], sign * err[3]
        n_sq = v0 * v0 + v1 * v1 + v2 * v2
        if n_sq < 1e-12:
            f = 2.0 / w * (1.0 - n_sq / (3.0 * w * w))
        else:
            nn = math.sqrt(n_sq)
            f = 2.0 * math.atan2(nn, w) / nn
        o0, o1, o2 = f * v0, f * v1, f * v2
        th2 = o0 * o0 + o1 * o1 + o2 * o2
        tx, ty, tz = err[4], err[5], err[6]
        wt0, wt1, wt2 = o1 * tz - o2 * ty, o2 * tx - o0 * tz, o0 * ty - o1 * tx
        d = _coef_jrinv(th2)
        e[0], e[1], e[2] = o0, o1, o2
        e[3] = tx - 0.5 * wt0 + d * (o1 * wt2 - o2 * wt1)
        e[4] = ty - 0.5 * wt1 + d * (o2 * wt0 - o0 * wt2)
        e[5] = tz - 0.5 * wt2 + d * (o0 * wt1 - o1 * wt0)
        # Jr^-1(e) = [[Ji, 0], [-Ji Q(-omega, -rho) Ji, Ji]]
        _skew(o0, o1, o2, W)
        _mm3(W, W, WW)
        for p in range(3):
            for q in range(3):
                Ji[p, q] = (1.0 if p == q else 0.0) + 0.5 * W[p, q] + d * WW[p, q]
        _skew(-o0, -o1, -o2, W)
        _skew(-e[3], -e[4], -e[5], R)
        _mm3(W, R, WR)
        _mm3(R, W, RW)
        _mm3(WR, W, WRW)
        _mm3(W, W, WW)
        c1, c2, c3 = _coef_c(th2), _coef_q2(th2), _coef_q3(th2)
        _mm3(WW, R, t1)
        _mm3(RW, W, t2)
        for p in range(3):
            for q in range(3):
                Q[p, q] = (
                    0.5 * R[p, q]
                    + c1 * (WR[p, q] + RW[p, q] + WRW[p, q])
                    + c2 * (t1[p, q] + t2[p, q] - 3.0 * WRW[p, q])
                )
        _mm3(WRW, W, t1)
        _mm3(W, WRW, t2)
        for p in range(3):
            for q in range(3):
                Q[p, q] += c3 * (t1[p, q] + t2[p, q])
        _mm3(Ji, Q, t1)
        _mm3(t1, Ji, t2)
        for p in range(3):
            for q in range(3):
                jj[p, q] = Ji[p, q]
                jj[p, q + 3] = 0.0
                jj[p + 3, q] = -t2[p, q]
                jj[p + 3, q + 3] = Ji[p, q]
        # Ad(xj^-1 xi) = [[Rot, 0], [t^ Rot, Rot]]
        _relative3(xj[i], xi[i], ji_rel, s)
        qw, qx, qy, qz = ji_rel[0], ji_rel[1], ji_rel[2], ji_rel[3]
        Rot[0, 0], Rot[0, 1], Rot[0, 2] = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        Rot[1, 0], Rot[1, 1], Rot[1, 2] = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        Rot[2, 0], Rot[2, 1], Rot[2, 2] = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        _skew(ji_rel[4], ji_rel[5], ji_rel[6], W)
        _mm3(W, Rot, t1)
        for p in range(3):
            for q in range(3):
                ad[p, q] = Rot[p, q]
                ad[p, q + 3] = 0.0
                ad[p + 3, q] = t1[p, q]
                ad[p + 3, q + 3] = Rot[p, q]
        for p in range(6):
            for q in range(6):
                acc = 0.0
                for k in range(6):
                    acc += jj[p, k] * ad[k, q]
                Jraw[p, q] = -acc
                Jraw[p, q + 6] = jj[p, q]
        cost[i] = _whiten(L[i], e, Jraw, J[i], r[i])
    return J, r, cost


@_jit
def _relative2(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``a^-1 b`` of SE(2) parameters ``[cos, sin, x, y]``."""
    c, s = a[0], -a[1]
    out[0] = c * b[0] - s * b[1]
    out[1] = c * b[1] + s * b[0]
    ix = -(c * a[2] - s * a[3])
    iy = -(s * a[2] + c * a[3])
    out[2] = ix + (c * b[2] - s * b[3])
    out[3] = iy + (s * b[2] + c * b[3])


@_jit
def between_se2(
    xi: np.ndarray, xj: np.ndarray, z: np.ndarray, L: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Whitened ``(J (n, 3, 6), r (n, 3), cost (n,))`` of SE(2) between constraints (tangent
    ``[theta, x, y]``)."""
    n = xi.shape[0]
    J = np.empty((n, 3, 6))
    r = np.empty((n, 3))
    cost = np.empty(n)
    rel = np.empty(4)
    err = np.empty(4)
    ji_rel = np.empty(4)
    e = np.empty(3)
    Jraw = np.empty((3, 6))
    jj = np.empty((3, 3))
    ad = np.empty((3, 3))
    for i in range(n):
        _relative2(xi[i], xj[i], rel)
        _relative2(z[i], rel, err)
        th = math.atan2(err[1], err[0])
        t2 = th * th
        a = _coef_a(t2)
        b2 = _coef_b(t2)
        b = th * b2
        det = a * a + b * b
        x, y = err[2], err[3]
        e[0] = th
        e[1] = (a * x + b * y) / det
        e[2] = (-b * x + a * y) / det
        # Jr(e) = [[1, 0], [v, M]], M = [[a, b], [-b, a]]: Jr^-1 = [[1, 0], [-M^-1 v, M^-1]]
        c3 = _coef_c(t2)
        v0 = e[1] * th * c3 - e[2] * b2
        v1 = e[1] * b2 + e[2] * th * c3
        dm = a * a + b * b
        m00, m01, m10, m11 = a / dm, -b / dm, b / dm, a / dm
        jj[0, 0], jj[0, 1], jj[0, 2] = 1.0, 0.0, 0.0
        jj[1, 0], jj[1, 1], jj[1, 2] = -(m00 * v0 + m01 * v1), m00, m01
        jj[2, 0], jj[2, 1], jj[2, 2] = -(m10 * v0 + m11 * v1), m10, m11
        # Ad(xj^-1 xi) = [[1, 0, 0], [y, c, -s], [-x, s, c]]
        _relative2(xj[i], xi[i], ji_rel)
        ad[0, 0], ad[0, 1], ad[0, 2] = 1.0, 0.0, 0.0
        ad[1, 0], ad[1, 1], ad[1, 2] = ji_rel[3], ji_rel[0], -ji_rel[1]
        ad[2, 0], ad[2, 1], ad[2, 2] = -ji_rel[2], ji_rel[1], ji_rel[0]
        for p in range(3):
            for q in range(3):
                Jraw[p, q] = -(jj[p, 0] * ad[0, q] + jj[p, 1] * ad[1, q] + jj[p, 2] * ad[2, q])
                Jraw[p, q + 3] = jj[p, q]
        cost[i] = _whiten(L[i], e, Jraw, J[i], r[i])
    return J, r, cost


@_jit
def gram(J: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Per constraint ``J^T J`` and ``J^T r`` of ``J (n, m, T)``, ``r (n, m)``."""
    n, m, T = J.shape
    G = np.empty((n, T, T))
    b = np.empty((n, T))
    for i in range(n):
        for p in range(T):
            acc = 0.0
            for k in range(m):
                acc += J[i, k, p] * r[i, k]
            b[i, p] = acc
            for q in range(p + 1):
                acc = 0.0
                for k in range(m):
                    acc += J[i, k, p] * J[i, k, q]
                G[i, p, q] = acc
                G[i, q, p] = acc
    return G, b
