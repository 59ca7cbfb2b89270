"""Host-side (NumPy) SO(3)/SE(3) helpers for front ends that work on single small poses.

Front ends (LiDAR odometry, visual odometry, the estimator's bookkeeping) handle one pose at
a time at sensor rate; dispatching eager JAX ops per pose would cost more than the maths.
These functions are plain float64 NumPy with the same conventions as :mod:`jaxslam.lie`:
quaternions ``(w, x, y, z)``, SE(3) parameters ``(qw, qx, qy, qz, x, y, z)``, tangent order
``[rotation, translation]`` and right perturbations ``T · Exp(xi)`` (GTSAM's Pose3). Tests
check them against :mod:`jaxslam.lie` to 1e-12.
"""

from __future__ import annotations

import numpy as np


def skew(w: np.ndarray) -> np.ndarray:
    """``[w]x`` (…, 3, 3)."""
    w = np.asarray(w, np.float64)
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrices (…, 3, 3) from rotation vectors (…, 3)."""
    w = np.asarray(w, np.float64)
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < 1e-16
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = skew(w)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (…, 3) of rotation matrices (…, 3, 3) (via the quaternion: accurate
    near 0 and π)."""
    q = matrix_to_quat(R)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    w = q[..., :1]
    ang = 2.0 * np.arctan2(n, w)
    scale = np.where(n < 1e-12, 2.0 / np.maximum(w, 1e-300), ang / np.where(n < 1e-12, 1.0, n))
    return v * scale


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (…, 3, 3) of quaternions (…, 4) ``(w, x, y, z)`` (normalised first)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternions (…, 4) ``(w, x, y, z)``, ``w >= 0``, of rotation matrices (…, 3, 3)
    (Shepperd's method: the largest diagonal term picks the branch)."""
    R = np.asarray(R, np.float64)
    m = R.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    k = np.argmax(cand, axis=-1)
    q = np.empty((len(m), 4))
    for branch in range(4):
        sel = k == branch
        if not np.any(sel):
            continue
        a = m[sel]
        if branch == 0:
            s = 2.0 * np.sqrt(1.0 + tr[sel])
            q[sel] = np.stack(
                [0.25 * s, (a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 1, 0] - a[:, 0, 1]) / s],
                -1,
            )
        else:
            i = branch - 1
            j, l = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(np.maximum(1.0 + a[:, i, i] - a[:, j, j] - a[:, l, l], 1e-300))
            out = np.empty((len(a), 4))
            out[:, 0] = (a[:, l, j] - a[:, j, l]) / s
            out[:, 1 + i] = 0.25 * s
            out[:, 1 + j] = (a[:, j, i] + a[:, i, j]) / s
            out[:, 1 + l] = (a[:, l, i] + a[:, i, l]) / s
            q[sel] = out
    q = np.where(q[:, :1] < 0, -q, q)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q.reshape(*R.shape[:-2], 4)


def params_to_matrix(params: np.ndarray) -> np.ndarray:
    """4x4 matrices (…, 4, 4) of SE(3) parameters (…, 7) ``(qw, qx, qy, qz, x, y, z)``."""
    params = np.asarray(params, np.float64)
    T = np.zeros((*params.shape[:-1], 4, 4))
    T[..., :3, :3] = quat_to_matrix(params[..., :4])
    T[..., :3, 3] = params[..., 4:]
    T[..., 3, 3] = 1.0
    return T


def matrix_to_params(T: np.ndarray) -> np.ndarray:
    """SE(3) parameters (…, 7) of 4x4 matrices (…, 4, 4)."""
    T = np.asarray(T, np.float64)
    return np.concatenate([matrix_to_quat(T[..., :3, :3]), T[..., :3, 3]], axis=-1)


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 from a rotation (3, 3) and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid 4x4 transforms (…, 4, 4)."""
    T = np.asarray(T, np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """The left Jacobian of SO(3) (``V`` of SE(3)'s exp: ``Exp([w, rho])`` has translation
    ``V rho``) (…, 3, 3)."""
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < 1e-4  # below 0.01 rad the closed forms cancel; the series is exact to ~1e-17
    safe = np.where(small, 1.0, th)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(safe)) / (safe * safe))
    c = np.where(small, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0, (safe - np.sin(safe)) / (safe**3))
    K = skew(w)
    return np.eye(3) + b * K + c * (K @ K)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 transforms (…, 4, 4) of tangents (…, 6) ``[rotation, translation]``."""
    xi = np.asarray(xi, np.float64)
    T = np.zeros((*xi.shape[:-1], 4, 4))
    T[..., :3, :3] = so3_exp(xi[..., :3])
    T[..., :3, 3] = np.einsum("...ij,...j->...i", so3_left_jacobian(xi[..., :3]), xi[..., 3:])
    T[..., 3, 3] = 1.0
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Tangents (…, 6) ``[rotation, translation]`` of 4x4 transforms (…, 4, 4)."""
    T = np.asarray(T, np.float64)
    w = so3_log(T[..., :3, :3])
    u = np.linalg.solve(so3_left_jacobian(w), T[..., :3, 3][..., None])[..., 0]
    return np.concatenate([w, u], axis=-1)


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint (…, 6, 6) in ``[rotation, translation]`` order: ``T Exp(xi) T^-1 = Exp(Ad xi)``."""
    T = np.asarray(T, np.float64)
    R, p = T[..., :3, :3], T[..., :3, 3]
    A = np.zeros((*T.shape[:-2], 6, 6))
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., 3:, :3] = skew(p) @ R
    return A


def make_poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses (…, 4, 4) from rotations (…, 3, 3) and translations (…, 3)."""
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = R, t, 1.0
    return T


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """``T`` (4, 4) with its rotation block projected onto SO(3) (nearest in Frobenius norm):
    chained products of poses gather rounding error."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``R p + t`` for points (N, 3) and one 4x4 ``T``."""
    return np.asarray(points, np.float64) @ T[:3, :3].T + T[:3, 3]


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Poses (K, 4, 4) between ``T0`` and ``T1`` at fractions ``s`` (K,): rotation by slerp
    (``R0 Exp(s Log(R0^T R1))``), translation linear."""
    s = np.asarray(s, np.float64)
    dw = so3_log(T0[:3, :3].T @ T1[:3, :3])
    out = np.zeros((len(s), 4, 4))
    out[:, :3, :3] = T0[:3, :3] @ so3_exp(s[:, None] * dw)
    out[:, :3, 3] = (1 - s)[:, None] * T0[:3, 3] + s[:, None] * T1[:3, 3]
    out[:, 3, 3] = 1.0
    return out
