"""A synthetic tunnel pose graph: out along a gently curving, sloping corridor and back.

The robot drives ``length / 2`` metres out, turns round, and drives back along the same
route offset sideways, so the return leg revisits the outbound places: loop closures join
each return keyframe to the outbound keyframe nearest to it (when within ``loop_radius``).
Odometry and loop measurements are the true relative poses perturbed on the manifold by
Gaussian noise of the given sigmas. Deterministic by ``seed``.

Returns arrays only (no factors), so any layer can build a graph from it.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..lie import SE3


@dataclasses.dataclass(frozen=True)
class SyntheticPoseGraph:
    """Ground truth and measurements. Poses are SE3 params ``(qw, qx, qy, qz, x, y, z)``."""

    ground_truth: np.ndarray  # (N, 7)
    edges_i: np.ndarray  # (M,)
    edges_j: np.ndarray  # (M,)
    measured: np.ndarray  # (M, 7)
    sigmas: np.ndarray  # (M, 6) [rot rad x3, trans m x3]
    is_loop: np.ndarray  # (M,) bool
    timestamps: np.ndarray  # (N,) s


def _yaw_pitch_quat(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    # q = q_z(yaw) * q_y(pitch)
    return np.stack([cy * cp, -sy * sp, cy * sp, sy * cp], axis=-1)


def tunnel_pose_graph(
    length: float = 60.0,
    step: float = 0.5,
    seed: int = 0,
    odom_sigma: tuple[float, float] = (0.004, 0.01),
    loop_sigma: tuple[float, float] = (0.01, 0.03),
    loop_radius: float = 1.2,
    loop_every: int = 2,
    speed: float = 0.5,
) -> SyntheticPoseGraph:
    """Keyframes every ``step`` metres; ``odom_sigma``/``loop_sigma`` = (rad, m)."""
    if length <= 4 * step or step <= 0:
        raise ValueError(f"length ({length} m) must exceed 4 steps of {step} m")
    rng = np.random.default_rng(seed)
    half = length / 2
    s_out = np.arange(0.0, half, step)

    # centre line: gentle curve and slope
    def centre(s: np.ndarray) -> np.ndarray:
        return np.stack([s, 1.5 * np.sin(s / half * np.pi), 0.02 * s], axis=-1)

    def heading(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dx = np.ones_like(s)
        dy = 1.5 * np.pi / half * np.cos(s / half * np.pi)
        return np.arctan2(dy, dx), np.full_like(s, -np.arctan(0.02))

    out_p = centre(s_out) + np.array([0.0, -0.4, 0.0])
    yaw_o, pitch_o = heading(s_out)
    s_back = s_out[::-1]
    back_p = centre(s_back) + np.array([0.0, 0.4, 0.0])
    yaw_b, pitch_b = heading(s_back)
    positions = np.concatenate([out_p, back_p])
    quats = np.concatenate([_yaw_pitch_quat(yaw_o, pitch_o), _yaw_pitch_quat(yaw_b + np.pi, -pitch_b)])
    gt = np.concatenate([quats, positions], axis=1)
    n = len(gt)
    gt_se3 = SE3(jnp.asarray(gt))

    def noisy_between(i: np.ndarray, j: np.ndarray, sig: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        rel = gt_se3[i].inverse() @ gt_se3[j]
        s = np.concatenate([np.full(3, sig[0]), np.full(3, sig[1])])
        noise = rng.normal(size=(len(i), 6)) * s
        return np.asarray((rel @ SE3.exp(noise)).params), np.broadcast_to(s, (len(i), 6))

    oi = np.arange(n - 1)
    om, osig = noisy_between(oi, oi + 1, odom_sigma)
    # loops: return keyframes to the nearest outbound keyframe
    n_out = len(s_out)
    ret = np.arange(n_out, n, loop_every)
    d = np.linalg.norm(positions[ret][:, None, :] - positions[None, :n_out, :], axis=-1)
    near = np.argmin(d, axis=1)
    keep = (d[np.arange(len(ret)), near] < loop_radius) & (ret - near > 5)
    li, lj = near[keep], ret[keep]
    lm, lsig = noisy_between(li, lj, loop_sigma)
    return SyntheticPoseGraph(
        ground_truth=gt,
        edges_i=np.concatenate([oi, li]),
        edges_j=np.concatenate([oi + 1, lj]),
        measured=np.concatenate([om, lm]),
        sigmas=np.concatenate([osig, lsig]),
        is_loop=np.concatenate([np.zeros(len(oi), bool), np.ones(len(li), bool)]),
        timestamps=np.arange(n) * step / speed,
    )
