"""A simulated tunnel for the LiDAR tests: ground-truth sensor poses, scans and maps.

The default route (30 m out along +x from t = 1.5 s, stop at t ~ 64.5 s, turn, back from
t = 73.5 s; the end wall at s = 36 m, the open portal at s = -6 m) with the HAP decimated 4x
(~11k points per scan). Scans are deskewed with the ground-truth motion so maps are exact up
to the range noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from jaxslam.lidar import VoxelMap, deskew, voxel_downsample
from jaxslam.lidar._se3 import make_pose
from jaxslam.sim import LidarConfig, SimConfig, Simulation


class TunnelScans:
    def __init__(self):
        self.sim = Simulation.create(SimConfig(seed=0, lidar=LidarConfig(decimation=4)))
        self.t_bl = np.asarray(self.sim.config.lidar.translation)
        self._cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def sensor_pose(self, t) -> np.ndarray:
        """Ground-truth world_T_sensor ``(N, 4, 4)`` at times ``t``."""
        st = self.sim.trajectory.pose(np.atleast_1d(np.asarray(t, dtype=np.float64)))
        return make_pose(st["R"], st["p"] + np.einsum("nij,j->ni", st["R"], self.t_bl))

    def scan(self, t: float) -> dict[str, np.ndarray]:
        """The scan starting at ``t``; its noise depends on ``t`` only (not on call order)."""
        self.sim.lidar.rng = np.random.default_rng([0, round(float(t) * 1000)])
        return self.sim.lidar.scan(float(t), self.sim.trajectory.pose)

    def deskewed(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """A scan at ``t`` deskewed to its frame start with ground truth, and its pose (cached)."""
        key = round(float(t), 6)
        if key not in self._cache:
            self._cache[key] = self._deskewed(t)
        return self._cache[key]

    def _deskewed(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        sc = self.scan(t)
        tk = np.linspace(0.0, 0.1, 5)
        T = self.sensor_pose(t + tk)
        pts = deskew(sc["points"], sc["point_times"], (T[:, :3, :3], T[:, :3, 3], tk))
        return pts, T[0]

    def map_before(self, t: float, seconds: float = 2.0) -> VoxelMap:
        """A map from the scans in ``[t - seconds, t)`` at their true poses."""
        vmap = VoxelMap()
        for tt in np.arange(t - seconds, t - 0.05, 0.1):
            pts, T = self.deskewed(tt)
            vmap.add(voxel_downsample(pts, 0.1) @ T[:3, :3].T + T[:3, 3], T[:3, 3])
        return vmap


@pytest.fixture(scope="session")
def tunnel() -> TunnelScans:
    return TunnelScans()
