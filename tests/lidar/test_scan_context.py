from __future__ import annotations

import numpy as np

from jaxslam.lidar import ScanContextDatabase, scan_context, submap_points
from jaxslam.lidar._se3 import make_pose, so3_exp


def _room(rng, n=4000):
    """An asymmetric cloud: a few boxes of different heights around the origin."""
    pts = []
    for cx, cy, h in [(5, 1, 2.0), (-3, 6, 1.0), (8, -7, 3.0), (-9, -4, 0.5)]:
        xy = rng.uniform(-1, 1, (n // 4, 2)) + np.array([cx, cy])
        pts.append(np.c_[xy, rng.uniform(0, h, n // 4)])
    return np.concatenate(pts)


def test_descriptor_and_yaw():
    rng = np.random.default_rng(0)
    pts = _room(rng)
    sc = scan_context(pts)
    assert sc.descriptor.shape == (20, 60) and sc.ring_key.shape == (20,)
    assert sc.descriptor.max() <= 3.0 + 2.0 and sc.descriptor.min() >= 0.0
    yaw = np.radians(66.0)  # the query frame turned by +66 degrees in the candidate frame
    query = pts @ so3_exp(np.array([0, 0, yaw]))  # points seen from the turned frame
    d, est = scan_context(query).distance(sc)
    assert d < 0.05
    assert abs(est - yaw) <= np.radians(6.0) + 1e-9
    d_self, yaw_self = sc.distance(sc)
    assert d_self < 1e-12 and yaw_self == 0.0
    other = scan_context(_room(np.random.default_rng(1)) * [1.0, -1.0, 1.0])
    assert other.distance(sc)[0] > 5 * d


def test_database_topk_and_exclusion():
    rng = np.random.default_rng(2)
    scenes = [_room(rng) * rng.uniform(0.6, 1.4, 3) for _ in range(8)]
    db = ScanContextDatabase(num_candidates=8)
    for i, s in enumerate(scenes):
        db.add(100 + i, scan_context(s))
    q = scan_context(scenes[3])
    top = db.query(q, k=3)
    assert top[0].id == 103 and top[0].distance < 1e-12
    assert [m.distance for m in top] == sorted(m.distance for m in top)
    assert all(m.id != 103 for m in db.query(q, k=3, exclude_recent=5))  # 103..107 excluded
    assert db.query(q, exclude_recent=8) == []


def test_submap_points_in_the_centre_frame():
    rng = np.random.default_rng(3)
    world = rng.uniform(-5, 5, (100, 3))
    poses = np.stack([make_pose(so3_exp(rng.normal(size=3) * 0.3), rng.normal(size=3)) for _ in range(2)])
    clouds = [(world - T[:3, 3]) @ T[:3, :3] for T in poses]  # the same points seen from two poses
    centre = make_pose(so3_exp(np.array([0, 0, 1.0])), np.array([1.0, 2, 0]))
    out = submap_points(clouds, poses, centre, voxel=None)
    expect = (world - centre[:3, 3]) @ centre[:3, :3]
    np.testing.assert_allclose(out, np.concatenate([expect, expect]), atol=1e-12)
