"""Reflectivity-aided registration: the relative reflectivity is a property of the surface (not
of the viewpoint), the map's local reflectivity model recovers a known ramp, and in a corridor
whose geometry cannot see its axis the reflectance pattern pins it."""

from __future__ import annotations

import numpy as np
import pytest

from jaxslam.errors import InputFormatError
from jaxslam.lidar import IcpConfig, VoxelMap, VoxelMapConfig, register, relative_reflectivity
from jaxslam.lidar._se3 import se3_inverse, se3_log


def _albedo(x: np.ndarray) -> np.ndarray:
    """A reflectance pattern along the corridor axis: smooth 'stains' of a few decimetres."""
    return 0.45 + 0.12 * np.sin(2 * np.pi * x / 1.3) + 0.08 * np.sin(2 * np.pi * x / 0.7 + 1.0)


def _corridor(origin: np.ndarray, rng: np.random.Generator, n: int = 6000, noise: float = 0.005):
    """Points of a 3 m x 3 m box corridor along x (walls, floor, ceiling; no end walls) seen
    from ``origin`` (world frame), x in [origin - 2, origin + 12]; returns world points,
    intensity ``255 albedo (0.3 + 0.7 cos(incidence))`` and the sensor-frame points (sensor
    axes = world axes)."""
    x = origin[0] + rng.uniform(-2.0, 12.0, n)
    side = rng.integers(0, 4, n)
    a = rng.uniform(-1.5, 1.5, n)
    P = np.zeros((n, 3))
    P[:, 0] = x
    P[:, 1] = np.where(side == 0, -1.5, np.where(side == 1, 1.5, a))
    P[:, 2] = np.where(side == 2, 0.0, np.where(side == 3, 3.0, a + 1.5))
    normals = np.zeros((n, 3))
    normals[side == 0, 1] = normals[side == 1, 1] = 1.0
    normals[side >= 2, 2] = 1.0
    d = P - origin
    rng_ = np.linalg.norm(d, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", normals, d)) / rng_
    keep = (rng_ > 0.5) & (cos > 0.08)
    P = P[keep] + noise * rng.standard_normal((int(keep.sum()), 3))
    inten = 255 * _albedo(P[:, 0]) * (0.3 + 0.7 * cos[keep])
    return P, inten, P - origin


def test_relative_reflectivity_follows_the_surface_not_the_viewpoint(rng):
    near, i_near, s_near = _corridor(np.array([0.0, -0.3, 1.2]), rng)
    far, i_far, s_far = _corridor(np.array([-4.0, 0.4, 1.0]), rng)
    r_near = relative_reflectivity(s_near, i_near)
    r_far = relative_reflectivity(s_far, 3.0 * i_far)  # another gain, another viewpoint
    for P, r in ((near, r_near), (far, r_far)):
        ok = np.isfinite(r)
        assert ok.mean() > 0.8
        truth = _albedo(P[ok, 0])
        assert np.corrcoef(r[ok], truth)[0, 1] > 0.8
    # the same surface spot from both viewpoints: close values (not the raw intensities)
    sel = (near[:, 0] > 2.0) & (near[:, 0] < 6.0) & np.isfinite(r_near)
    from scipy.spatial import cKDTree

    d, j = cKDTree(far).query(near[sel], 1)
    close = (d < 0.05) & np.isfinite(r_far[j])
    assert close.sum() > 100
    assert np.median(np.abs(r_near[sel][close] - r_far[j][close])) < 0.05
    assert np.median(np.abs(i_near[sel][close] - i_far[j][close] * 3.0)) > 20  # raw ones differ


def test_map_reflectivity_model_recovers_a_linear_ramp(rng):
    xy = rng.uniform(-2, 2, (4000, 2))
    P = np.c_[xy, np.zeros(len(xy))]
    refl = 0.1 * P[:, 0] - 0.05 * P[:, 1]
    vm = VoxelMap(VoxelMapConfig(voxel_size=0.2, max_points_per_voxel=10))
    vm.add(P, np.zeros(3), intensity=refl)
    assert vm.has_intensity
    inner = np.all(np.abs(vm.points()[:, :2]) < 1.5, axis=1)
    np.testing.assert_allclose(vm.intensity_gradient[inner], np.tile([0.1, -0.05, 0.0], (inner.sum(), 1)), atol=2e-3)
    np.testing.assert_allclose(
        vm.intensity[inner], 0.1 * vm.points()[inner, 0] - 0.05 * vm.points()[inner, 1], atol=1e-3
    )
    # points without reflectivity: no model, no gradient
    vm2 = VoxelMap()
    vm2.add(P, np.zeros(3), intensity=np.full(len(P), np.nan))
    assert not vm2.has_intensity and np.all(np.isnan(vm2.intensity)) and not vm2.intensity_gradient.any()


def test_reflectance_pins_the_axis_the_geometry_cannot_see(rng):
    map_pts, map_i, map_s = _corridor(np.array([0.0, -0.3, 1.2]), rng, n=20000)
    vm = VoxelMap(VoxelMapConfig(voxel_size=0.2, max_points_per_voxel=10))
    vm.add(map_pts, np.zeros(3), intensity=relative_reflectivity(map_s, map_i))
    origin = np.array([1.0, -0.2, 1.25])
    _, src_i, src = _corridor(origin, rng, n=4000)
    T_true = np.eye(4)
    T_true[:3, 3] = origin
    T_init = T_true.copy()
    T_init[0, 3] += 0.12  # off along the axis
    geo = register(src, vm, T_init, IcpConfig())
    assert geo.degenerate and abs(se3_log(se3_inverse(T_true) @ geo.T)[3] - 0.12) < 1e-3  # held at the guess
    refl = relative_reflectivity(src, src_i)
    reg = register(src, vm, T_init, IcpConfig(), source_intensity=refl)
    e = se3_log(se3_inverse(T_true) @ reg.T)
    assert reg.converged and not reg.degenerate and reg.intensity_correspondences > 1000
    assert abs(e[3]) < 0.01 and np.all(np.abs(e[3:]) < 0.01) and np.all(np.abs(e[:3]) < 2e-3), e
    # a weight of 0 is geometry only
    off = register(src, vm, T_init, IcpConfig(intensity_weight=0.0), source_intensity=refl)
    assert off.degenerate and off.intensity_correspondences == 0


def test_bad_input(rng):
    pts = rng.normal(size=(50, 3))
    with pytest.raises(InputFormatError, match="intensity"):
        relative_reflectivity(pts, np.ones(49))
    with pytest.raises(InputFormatError, match="NaN or infinite"):
        relative_reflectivity(pts, np.r_[np.ones(49), np.nan])
    assert np.all(np.isnan(relative_reflectivity(pts[:5], np.ones(5))))  # too few points: none
    vm = VoxelMap()
    with pytest.raises(InputFormatError, match="intensity"):
        vm.add(pts, np.zeros(3), intensity=np.ones(3))
    vm.add(pts, np.zeros(3), intensity=np.ones(50))
    with pytest.raises(InputFormatError, match="source_intensity"):
        register(pts, vm, np.eye(4), source_intensity=np.ones(7))
    with pytest.raises(InputFormatError, match="source_intensity"):
        register(pts, vm, np.eye(4), source_intensity=np.r_[np.ones(49), np.inf])
