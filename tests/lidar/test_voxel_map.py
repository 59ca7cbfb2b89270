from __future__ import annotations

import numpy as np

from jaxslam.lidar import VoxelMap, VoxelMapConfig
from jaxslam.lidar._preprocess import voxel_keys


def test_map_caps_voxels_prunes_far_points_and_fits_normals():
    rng = np.random.default_rng(0)
    cfg = VoxelMapConfig(voxel_size=0.5, max_points_per_voxel=4, max_distance=10.0)
    vmap = VoxelMap(cfg)
    n = np.array([0.0, 0.6, 0.8])
    a = np.cross(n, [1.0, 0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    plane = rng.uniform(-8, 8, (6000, 2))
    pts = plane[:, :1] * a + plane[:, 1:] * b + 0.002 * rng.standard_normal((6000, 1)) * n
    vmap.add(pts[:3000], np.zeros(3))
    first = vmap.points()
    vmap.add(pts[3000:], np.zeros(3))
    _, counts = np.unique(voxel_keys(vmap.points(), 0.5), return_counts=True)
    assert counts.max() <= 4
    # first come, first kept: every point of the first batch survives the second add
    assert len(set(map(tuple, first)) - set(map(tuple, vmap.points()))) == 0
    ok = vmap.planarity > 0.2
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.abs(vmap.normals[ok] @ n), 1.0, atol=1e-3)
    vmap.add(np.zeros((0, 3)), np.array([6.0, 0, 0]))  # moving away prunes
    assert np.all(np.linalg.norm(vmap.points() - [6.0, 0, 0], axis=1) <= 10.0)
    d, i = vmap.neighbors(np.array([[0, 0, 100.0]]), 2, max_distance=1.0)
    assert np.all(i == -1) and np.all(np.isinf(d))
