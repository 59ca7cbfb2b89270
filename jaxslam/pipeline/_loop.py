"""Loop closure for a repetitive tunnel: candidates, geometric verification, consistency gate.

A uniform tunnel defeats appearance-only place recognition (every stretch of wall looks like
the next; see the LiDAR README section for Scan Context's figures on it), so candidates come
from the estimate itself: keyframes at least ``min_gap_s`` older whose estimated position is
within ``search_radius`` of the current one. Each candidate is verified by registering the
current keyframe's deskewed scan against a submap of the candidate and its neighbours (built
from their odometry poses, which are locally consistent): convergence, fitness and RMSE gates.
The measured relative pose must then agree with the current estimate within the odometry's
expected drift (a chi^2 gate on the Mahalanobis distance, the single-loop form of pairwise
consistency: each accepted loop is already in the estimate the next one is tested against).
The registration's information carries the degeneracy: along the tunnel axis a loop says
little, so a false match along the axis cannot pull the trajectory. Loop factors get a Cauchy
kernel in the graph.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..lidar import IcpConfig, VoxelMap, VoxelMapConfig, register, voxel_downsample
from ..lie import host
from ._config import LidarConfig, LoopConfig
from ._lidar_frontend import axis_weighted, information_for_factor


@dataclasses.dataclass
class Loop:
    i: int
    j: int
    T: np.ndarray
    """Measured ``T_i^-1 T_j`` (body)."""
    information: np.ndarray
    fitness: float
    rmse: float
    mahalanobis2: float
    degenerate: bool


def _reflectivity(scan) -> np.ndarray:
    """A keyframe scan's per-point reflectivity (NaN where it has none)."""
    r = getattr(scan, "reflectivity", None)
    return np.full(len(scan.points), np.nan) if r is None else np.asarray(r, dtype=np.float64)


def drift_gate(
    T_meas: np.ndarray, info: np.ndarray, T_est: np.ndarray, travelled: float, cfg: LoopConfig
) -> tuple[bool, float]:
    """The consistency gate of a loop measurement ``T_meas`` (information ``info``) against
    the estimated relative pose ``T_est``: chi^2 of their difference under the measurement's
    covariance plus the odometry drift expected over ``travelled`` metres (``drift_per_m``
    in metres, a tenth of it in radians; at least 2 cm). Returns (accepted, chi^2)."""
    e = host.se3_log(host.inverse(T_meas) @ T_est)
    drift = max(cfg.drift_per_m * travelled, 0.02)
    cov = np.linalg.inv(info) + np.diag([drift / 10] * 3 + [drift] * 3) ** 2
    m2 = float(e @ np.linalg.solve(cov, e))
    return m2 <= cfg.chi2_gate, m2


class LoopCloser:
    def __init__(self, cfg: LoopConfig, T_bl: np.ndarray, lidar_cfg: LidarConfig | None = None):
        self.cfg = cfg
        self.T_bl = T_bl
        self.lidar_cfg = lidar_cfg or LidarConfig()
        self.accepted: list[Loop] = []
        self.rejected: list[tuple[int, int, str]] = []
        self.attempts = 0

    def detect(self, k: int, keyframes: list, poses: np.ndarray, force: bool = False) -> list[Loop]:
        """Loops from keyframe ``k`` (every ``loop.every``-th, or any with ``force``: the
        recording's last keyframe) to older keyframes, given the current pose estimates
        (K, 4, 4); accepted ones are also kept in ``accepted``."""
        cfg = self.cfg
        if k % cfg.every and not force:
            return []
        cur = keyframes[k]
        if cur.scan is None or cur.scan.registration is None:
            return []
        times = np.array([kf.t for kf in keyframes])
        old = np.nonzero(times < cur.t - cfg.min_gap_s)[0]
        old = np.array([i for i in old if keyframes[i].scan is not None], dtype=int)
        if not len(old):
            return []
        d = np.linalg.norm(poses[old, :3, 3] - poses[k, :3, 3], axis=1)
        near = old[d < cfg.search_radius]
        if not len(near):
            return []
        i = int(near[np.argmin(d[d < cfg.search_radius])])
        self.attempts += 1
        loop = self._verify(i, k, keyframes, poses)
        return [loop] if loop is not None else []

    def _verify(self, i: int, k: int, keyframes: list, poses: np.ndarray) -> Loop | None:
        cfg = self.cfg
        T_i = keyframes[i].scan.T_odom
        t_k = keyframes[k].t
        vm = VoxelMap(VoxelMapConfig(voxel_size=0.2, max_points_per_voxel=10, max_distance=60.0))
        near = np.linalg.norm(poses[: len(keyframes), :3, 3] - poses[i, :3, 3], axis=1) < cfg.submap_radius
        chunks, refl = [], []
        for j in np.nonzero(near)[0]:
            sc = keyframes[j].scan
            if sc is None or keyframes[j].t >= t_k - cfg.min_gap_s:
                continue
            # odometry poses are locally consistent: use them for the submap's geometry
            pts, r = voxel_downsample(sc.points, 0.2, _reflectivity(sc))
            chunks.append(host.transform_points(host.inverse(T_i) @ sc.T_odom, pts))
            refl.append(r)
        use_i = self.lidar_cfg.intensity and any(np.isfinite(r).any() for r in refl)
        if chunks:
            vm.add(np.concatenate(chunks), np.zeros(3), intensity=np.concatenate(refl) if use_i else None)
        if len(vm) < 200:
            self.rejected.append((i, k, "submap too small"))
            return None
        T_est = host.inverse(poses[i]) @ poses[k]
        src, src_r = voxel_downsample(keyframes[k].scan.points, 0.25, _reflectivity(keyframes[k].scan))
        # only the part of the scan the submap can cover (fitness then measures agreement,
        # not overlap): within 0.8 submap radii of the candidate, at the estimated pose
        inside = np.linalg.norm(host.transform_points(T_est, src), axis=1) < 0.8 * cfg.submap_radius
        src, src_r = src[inside], src_r[inside]
        icp = IcpConfig(
            max_correspondence_distance=0.8, intensity_weight=self.lidar_cfg.intensity_weight if use_i else 0.0
        )
        reg = register(src, vm, T_est, icp, source_intensity=src_r if use_i else None)
        if not reg.converged:
            self.rejected.append((i, k, f"registration: {reg.message}"))
            return None
        if reg.fitness < cfg.min_fitness or reg.rmse > cfg.max_rmse:
            self.rejected.append((i, k, f"fitness {reg.fitness:.2f} rmse {reg.rmse:.3f}"))
            return None
        info = axis_weighted(
            information_for_factor(reg.strong_information(), np.eye(4), self.lidar_cfg, cfg.information_scale),
            cfg.axis_weights,
        )
        travelled = float(np.sum(np.linalg.norm(np.diff(poses[i : k + 1, :3, 3], axis=0), axis=1)))
        ok, m2 = drift_gate(reg.T, info, T_est, travelled, cfg)
        if not ok:
            self.rejected.append((i, k, f"inconsistent with odometry (chi2 {m2:.1f})"))
            return None
        loop = Loop(i, k, reg.T, info, reg.fitness, reg.rmse, m2, reg.degenerate)
        self.accepted.append(loop)
        return loop
