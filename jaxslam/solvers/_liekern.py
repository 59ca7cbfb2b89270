"""Compiled (numba) retractions ``x ⊕ d`` of the common variable types, row by row.

The incremental solver moves the estimate of a few variables after every update; as numpy
expressions on a few rows, SE(3)'s retraction was some forty calls of a few microseconds of
overhead each (0.1-0.2 ms per update on parking-garage), as one JAX call about as much in
dispatch. Same formulas and series thresholds as :mod:`jaxslam.lie` (tested against it):
``exp`` of the rotation part as a unit quaternion, ``x.q * exp(w)``, and for SE(3) the
translation ``x.t + x.q (V(w) rho)``, parameters ``[qw, qx, qy, qz, tx, ty, tz]``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)


@_jit
def _quat_rotate(q: np.ndarray, v: np.ndarray) -> tuple[float, float, float]:  # pragma: no cover
    """``q v q*`` for a unit quaternion ``q`` (w, x, y, z)."""
    w, ux, uy, uz = q[0], q[1], q[2], q[3]
    tx = 2.0 * (uy * v[2] - uz * v[1])
    ty = 2.0 * (uz * v[0] - ux * v[2])
    tz = 2.0 * (ux * v[1] - uy * v[0])
    return (
        v[0] + w * tx + (uy * tz - uz * ty),
        v[1] + w * ty + (uz * tx - ux * tz),
        v[2] + w * tz + (ux * ty - uy * tx),
    )


@_jit
def retract_so3_se3(x: np.ndarray, d: np.ndarray, se3: bool) -> np.ndarray:  # pragma: no cover
    """Rows of SO(3) (``x``: quaternions, ``d``: rotation vectors) or SE(3) (``x``:
    ``[q, t]``, ``d``: ``[w, rho]``) retracted."""
    n = x.shape[0]
    out = np.empty((n, 7 if se3 else 4))
    v = np.empty(3)
    for i in range(n):
        w0, w1, w2 = d[i, 0], d[i, 1], d[i, 2]
        th2 = w0 * w0 + w1 * w1 + w2 * w2
        th = math.sqrt(th2)
        small = th2 < 1e-8
        s_half = 0.5 - th2 / 48.0 if small else math.sin(0.5 * th) / th
        c_half = math.cos(0.5 * th)
        bw, bx, by, bz = c_half, s_half * w0, s_half * w1, s_half * w2
        aw, ax, ay, az = x[i, 0], x[i, 1], x[i, 2], x[i, 3]
        out[i, 0] = aw * bw - ax * bx - ay * by - az * bz
        out[i, 1] = aw * bx + ax * bw + ay * bz - az * by
        out[i, 2] = aw * by - ax * bz + ay * bw + az * bx
        out[i, 3] = aw * bz + ax * by - ay * bx + az * bw
        if not se3:
            continue
        r0, r1, r2 = d[i, 3], d[i, 4], d[i, 5]
        if small:
            b = 0.5 - th2 / 24.0
            c = 1.0 / 6.0 - th2 / 120.0
        else:
            b = (1.0 - math.cos(th)) / th2
            c = (th - math.sin(th)) / (th2 * th)
        wr0, wr1, wr2 = w1 * r2 - w2 * r1, w2 * r0 - w0 * r2, w0 * r1 - w1 * r0
        v[0] = r0 + b * wr0 + c * (w1 * wr2 - w2 * wr1)
        v[1] = r1 + b * wr1 + c * (w2 * wr0 - w0 * wr2)
        v[2] = r2 + b * wr2 + c * (w0 * wr1 - w1 * wr0)
        t0, t1, t2 = _quat_rotate(x[i, :4], v)
        out[i, 4] = x[i, 4] + t0
        out[i, 5] = x[i, 5] + t1
        out[i, 6] = x[i, 6] + t2
    return out


@_jit
def retract_se2(x: np.ndarray, d: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Rows of SE(2) (``x``: ``[cos, sin, tx, ty]``, ``d``: ``[theta, vx, vy]``) retracted."""
    n = x.shape[0]
    out = np.empty((n, 4))
    for i in range(n):
        th = d[i, 0]
        th2 = th * th
        if th2 < 1e-8:
            a = 1.0 - th2 / 6.0
            b = 0.5 * th - th * th2 / 24.0
        else:
            a = math.sin(th) / th
            b = (1.0 - math.cos(th)) / th
        lx = a * d[i, 1] - b * d[i, 2]
        ly = b * d[i, 1] + a * d[i, 2]
        c, s = math.cos(th), math.sin(th)
        xc, xs = x[i, 0], x[i, 1]
        out[i, 0] = xc * c - xs * s
        out[i, 1] = xs * c + xc * s
        out[i, 2] = x[i, 2] + xc * lx - xs * ly
        out[i, 3] = x[i, 3] + xs * lx + xc * ly
    return out
