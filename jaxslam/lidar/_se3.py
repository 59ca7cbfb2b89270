"""Small numpy SO(3) / SE(3) helpers for the LiDAR front end (float64, batched where cheap).

Tangent order is [rotation, translation] like :mod:`jaxslam.lie` and GTSAM's Pose3; poses are
4 x 4 homogeneous matrices. The closed forms are the usual ones (Rodrigues' formula and the
SE(3) left Jacobian ``V``; Barfoot, *State Estimation for Robotics*, 2017, eq. 7.85), with
Taylor branches below ``1e-8`` rad. These are numpy twins of :mod:`jaxslam.lie` for the
per-scan hot loop, where tracing JAX would cost more than the arithmetic.
"""

from __future__ import annotations

import numpy as np

_SMALL = 1e-8


def hat(w: np.ndarray) -> np.ndarray:
    """Skew matrices ``(..., 3, 3)`` of vectors ``(..., 3)``: ``hat(w) @ v == cross(w, v)``."""
    w = np.asarray(w, dtype=np.float64)
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
    """Rotation matrices ``(..., 3, 3)`` of rotation vectors ``(..., 3)`` (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < _SMALL**2
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = hat(w)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` of rotation matrices ``(..., 3, 3)``; stable near 0 and pi."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.sin(th)
    small = th < 1e-6
    scale = np.where(small, 0.5 + th * th / 12.0, th / (2.0 * np.where(small, 1.0, sin)))
    out = v * scale[..., None]
    near_pi = th > np.pi - 1e-4
    if np.any(near_pi):
        # Near pi, sin ~ 0: take the axis from the symmetric part R + R^T = 2 cos I + 2 (1 - cos) a a^T.
        Rp = R[near_pi]
        B = (Rp + np.swapaxes(Rp, -1, -2)) / 2.0 - cos[near_pi][..., None, None] * np.eye(3)
        col = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        axis = np.take_along_axis(B, col[:, None, None], axis=-1)[..., 0]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        sign = np.where(np.sum(axis * v[near_pi], -1) < 0, -1.0, 1.0)
        out[near_pi] = axis * (th[near_pi] * sign)[:, None]
    return out


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian ``V(w)`` ``(..., 3, 3)``: ``Exp([w, rho])`` has translation ``V rho``."""
    w = np.asarray(w, dtype=np.float64)
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < 1e-10
    safe = np.where(small, 1.0, th)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    c = np.where(small, 1.0 / 6.0 - th2 / 120.0, (safe - np.sin(safe)) / (safe**3))
    K = hat(w)
    return np.eye(3) + b * K + c * (K @ K)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Poses ``(..., 4, 4)`` of tangents ``(..., 6)`` = [rotation, translation]."""
    xi = np.asarray(xi, dtype=np.float64)
    T = np.zeros((*xi.shape[:-1], 4, 4))
    T[..., :3, :3] = so3_exp(xi[..., :3])
    T[..., :3, 3] = np.einsum("...ij,...j->...i", so3_left_jacobian(xi[..., :3]), xi[..., 3:])
    T[..., 3, 3] = 1.0
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Tangents ``(..., 6)`` = [rotation, translation] of poses ``(..., 4, 4)``."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[..., :3, :3])
    rho = np.linalg.solve(so3_left_jacobian(w), T[..., :3, 3:4])[..., 0]
    return np.concatenate([w, rho], axis=-1)


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of poses ``(..., 4, 4)``."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses ``(..., 4, 4)`` from rotations ``(..., 3, 3)`` and translations ``(..., 3)``."""
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = R, t, 1.0
    return T


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``T (4, 4)`` applied to points ``(N, 3)``."""
    return points @ T[:3, :3].T + T[:3, 3]


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """``T (4, 4)`` with its rotation block projected onto SO(3) (nearest in Frobenius norm).

    Products of poses gather rounding error; chained predictions (constant velocity) amplify
    it, so registration results are re-projected."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out
