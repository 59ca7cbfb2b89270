"""Motion compensation ("deskew") of a scan whose points were measured at different times.

A LiDAR frame's points are each in the sensor frame *at their own time* ``point_times[i]``
(seconds from the frame stamp; drivers stamp the frame start). Given the sensor's motion
during the frame, :func:`deskew` re-expresses every point in the sensor frame at one
``reference_time`` (default ``0.0``: the frame start, i.e. the frame stamp, which is the time
the pose estimated by registration then belongs to; pass the frame period for the frame end).

The motion is given one of two ways:

* **sampled poses** ``(rotations (K, 3, 3), translations (K, 3), times (K,))``: the sensor's
  pose ``F_T_sensor(t_k)`` in any fixed frame ``F`` (the sensor frame at the frame start, the
  odometry frame, IMU-propagated poses ...), ``times`` increasing, in the same clock as
  ``point_times``. Per point the rotation is slerped and the translation linearly
  interpolated between the bracketing samples. Points may lie at most ``tolerance`` seconds
  outside ``[times[0], times[-1]]`` (they take the end sample's pose); further out raises.
* **a constant twist** ``(6,)`` = ``[omega (rad/s), v (m/s)]`` in the sensor frame:
  ``F_T_sensor(t) = Exp(t * twist)`` with ``F`` the sensor at ``t = 0`` (a constant-velocity
  model, e.g. ``se3_log(T_prev^-1 T_curr) / dt`` from the last two registrations).

Then ``p_ref = F_T_sensor(reference_time)^-1 F_T_sensor(t_i) p_i``.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputFormatError
from ._preprocess import check_points
from ._se3 import se3_exp, so3_exp, so3_log

Motion = tuple[np.ndarray, np.ndarray, np.ndarray] | np.ndarray


def deskew(points, point_times, motion: Motion, reference_time: float = 0.0, tolerance: float = 1e-3) -> np.ndarray:
    """Points ``(N, 3)`` re-expressed in the sensor frame at ``reference_time`` (see the module
    docstring for ``motion``). ``point_times`` ``(N,)`` seconds, same clock as the motion."""
    p = check_points(points)
    tau = np.asarray(point_times, dtype=np.float64)
    if tau.shape != (len(p),):
        raise InputFormatError(f"point_times must have shape ({len(p)},), got {tau.shape}")
    if not np.all(np.isfinite(tau)):
        raise InputFormatError("point_times has non-finite values")
    if isinstance(motion, tuple | list):
        Rk, wf, t = _sampled(motion, np.append(tau, reference_time), tolerance)
        R_ref = Rk[-1] @ so3_exp(wf[-1])
        world = np.einsum("nij,nj->ni", Rk[:-1], _rotate(wf[:-1], p)) + t[:-1]
        return (world - t[-1]) @ R_ref
    else:
        xi = np.asarray(motion, dtype=np.float64)
        if xi.shape != (6,) or not np.all(np.isfinite(xi)):
            raise InputFormatError(f"a twist must be 6 finite numbers [omega, v], got shape {xi.shape}")
        T_ref = se3_exp(reference_time * xi)
        world = _screw(p, tau, xi)
        return (world - T_ref[:3, 3]) @ T_ref[:3, :3]


def _rotate(w: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``Exp(w_i) p_i`` per point by Rodrigues' formula on vectors (no per-point matrices)."""
    th = np.linalg.norm(w, axis=1)
    small = th < 1e-8
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(safe) / safe)[:, None]
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)[:, None]
    wxp = np.cross(w, p)
    return p + a * wxp + b * np.cross(w, wxp)


def _sampled(motion, times: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per time: the bracketing sample's rotation ``R_k`` (N, 3, 3), the slerp increment
    ``f w_k`` (N, 3) (the rotation is ``R_k Exp(f w_k)``) and the translation (N, 3)."""
    if len(motion) != 3:
        raise InputFormatError("sampled motion must be (rotations (K,3,3), translations (K,3), times (K,))")
    Rs, ts, tk = (np.asarray(m, dtype=np.float64) for m in motion)
    K = len(tk)
    if tk.shape != (K,) or Rs.shape != (K, 3, 3) or ts.shape != (K, 3) or K < 1:
        raise InputFormatError(
            f"sampled motion shapes must be (K,3,3), (K,3), (K,); got {Rs.shape}, {ts.shape}, {tk.shape}"
        )
    if not (np.all(np.isfinite(Rs)) and np.all(np.isfinite(ts)) and np.all(np.isfinite(tk))):
        raise InputFormatError("sampled motion has non-finite values")
    if K > 1 and np.any(np.diff(tk) <= 0):
        raise InputFormatError("sampled motion times must be strictly increasing")
    lo, hi = times.min(), times.max()
    if lo < tk[0] - tolerance or hi > tk[-1] + tolerance:
        raise InputFormatError(
            f"point times [{lo:.4f}, {hi:.4f}] s fall outside the motion samples [{tk[0]:.4f}, {tk[-1]:.4f}] s"
        )
    tc = np.clip(times, tk[0], tk[-1])
    if K == 1:
        return np.broadcast_to(Rs[0], (len(tc), 3, 3)), np.zeros((len(tc), 3)), np.broadcast_to(ts[0], (len(tc), 3))
    # slerp per point: R_k Exp(f w_k), w_k = Log(R_k^T R_k+1), vectorised (scipy's Slerp costs
    # ~7 ms per 11k-point scan, this ~1 ms)
    k = np.clip(np.searchsorted(tk, tc, side="right") - 1, 0, K - 2)
    f = (tc - tk[k]) / (tk[k + 1] - tk[k])
    w = so3_log(np.einsum("kji,kjl->kil", Rs[:-1], Rs[1:]))
    t = ts[k] + f[:, None] * (ts[k + 1] - ts[k])
    return Rs[k], f[:, None] * w[k], t


def _screw(p: np.ndarray, tau: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``Exp(tau_i xi) p_i`` for a fixed twist: the axis is shared, so Rodrigues' formula and
    the left Jacobian reduce to per-point scalars (no per-point matrices)."""
    w, v = xi[:3], xi[3:]
    wn = float(np.linalg.norm(w))
    if wn < 1e-12:
        return p + tau[:, None] * v
    k = w / wn
    th = tau * wn
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    kxp = np.cross(k, p)
    rot = p * c + kxp * s + np.outer(p @ k, k) * (1.0 - c)
    kxv = np.cross(k, v)
    kkv = np.cross(k, kxv)
    trans = tau[:, None] * v + (1.0 - c) / wn * kxv + (tau[:, None] - s / wn) * kkv
    return rot + trans
