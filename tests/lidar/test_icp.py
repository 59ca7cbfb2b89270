from __future__ import annotations

import numpy as np
import pytest

from jaxslam.errors import InputFormatError
from jaxslam.lidar import IcpConfig, Registration, VoxelMap, register, voxel_downsample
from jaxslam.lidar._se3 import se3_exp, se3_log

OFFSET = np.array([0.01, -0.01, 0.015, 0.08, 0.05, -0.04])  # [rad, m] in the sensor frame


def _case(tunnel, t, offset=OFFSET, config=None):
    vmap = tunnel.map_before(t)
    pts, T_gt = tunnel.deskewed(t)
    T_init = T_gt @ se3_exp(offset)
    reg = register(voxel_downsample(pts, 0.25), vmap, T_init, config)
    err = se3_log(np.linalg.inv(T_gt) @ reg.T)  # sensor frame: x along the tunnel (+-)
    return reg, err, T_gt


def _axis_share(reg: Registration, T_gt) -> float:
    """Largest |component| of a weak direction's translation along the tunnel axis."""
    axis = T_gt[:3, :3].T @ np.array([1.0, 0, 0])
    if not reg.degenerate:
        return 0.0
    return float(np.max(np.abs(reg.weak_directions[:, 3:] @ axis)))


def test_recovers_a_known_transform_with_the_end_wall_in_view(tunnel):
    reg, err, T_gt = _case(tunnel, 20.0)  # s ~ 8.7 m, facing the end wall 27 m ahead
    assert reg.converged and reg.fitness > 0.7 and reg.rmse < 0.02
    assert np.all(np.abs(err[4:]) < 0.01), err  # lateral, vertical
    assert np.degrees(np.linalg.norm(err[:3])) < 0.1, err
    assert abs(err[3]) < 0.02  # along: the far end wall sees it, less sharply
    assert _axis_share(reg, T_gt) < 0.5


def test_mid_tunnel_axis_is_degenerate_and_held_at_the_guess(tunnel):
    # on the way back (t = 106 s, s ~ 14 m) facing the open portal: walls, floor, ceiling only
    reg, err, T_gt = _case(tunnel, 106.0)
    assert reg.converged and reg.degenerate
    assert _axis_share(reg, T_gt) > 0.95
    assert reg.eigenvalues[0] < IcpConfig().degeneracy_threshold
    assert abs(err[3] - OFFSET[3]) < 0.002  # along the axis the estimate stays at T_init ...
    assert np.all(np.abs(err[4:]) < 0.01)  # ... the rest is recovered
    assert np.degrees(np.linalg.norm(err[:3])) < 0.1
    # the information says so: along the axis it is a tiny fraction of across
    axis = np.r_[np.zeros(3), T_gt[:3, :3].T @ [1.0, 0, 0]]
    across = np.r_[np.zeros(3), T_gt[:3, :3].T @ [0, 1.0, 0]]
    assert axis @ reg.information @ axis < 1e-2 * (across @ reg.information @ across)
    strong = reg.strong_information()  # or nothing at all along it
    np.testing.assert_allclose(reg.weak_directions @ strong @ reg.weak_directions.T, 0.0, atol=1e-6)
    assert across @ strong @ across > 0.9 * (across @ reg.information @ across)


def test_end_wall_ahead_makes_the_axis_observable(tunnel):
    reg, err, T_gt = _case(tunnel, 46.0)  # s ~ 22 m, the end wall 14 m ahead
    assert reg.converged and not reg.degenerate
    assert abs(err[3]) < 0.01 and np.all(np.abs(err[4:]) < 0.01)
    assert np.degrees(np.linalg.norm(err[:3])) < 0.1
    # 8 m before the wall the ceiling is out of the HAP's 25 degrees (floor only, from 3.6 m):
    # a pitch/height combination turns weak instead, but the axis is estimated from the wall
    reg, err, T_gt = _case(tunnel, 58.0, offset=np.r_[0, 0, 0, 0.08, 0.03, 0.0])
    assert reg.converged and _axis_share(reg, T_gt) < 0.5
    assert abs(err[3]) < 0.02 and abs(err[4]) < 0.01  # from 8 cm off


def test_information_is_the_right_perturbation_hessian(tunnel):
    cfg = IcpConfig(kernel_scale=10.0)  # weights ~1: the cost is plain least squares
    reg, _, _ = _case(tunnel, 20.0, config=cfg)
    info = reg.information
    np.testing.assert_allclose(info, info.T, rtol=0, atol=1e-9 * np.abs(info).max())
    assert np.linalg.eigvalsh(info).min() >= -1e-9 * np.abs(info).max()
    # the registration cost with the correspondences held, as a function of T Exp(xi)
    vmap = tunnel.map_before(20.0)
    src = voxel_downsample(tunnel.deskewed(20.0)[0], 0.25)
    T = reg.T
    q = src @ T[:3, :3].T + T[:3, 3]
    _, idx = vmap.neighbors(q, 1, cfg.max_correspondence_distance)
    idx = idx[:, 0]
    ok = idx >= 0
    ok[ok] = vmap.planarity[idx[ok]] >= cfg.min_planarity
    p, m, n = src[ok], vmap.points()[idx[ok]], vmap.normals[idx[ok]]
    assert len(p) == reg.n_correspondences

    def cost(T_):
        return 0.5 * np.sum(np.einsum("ij,ij->i", n, p @ T_[:3, :3].T + T_[:3, 3] - m) ** 2)

    def hessian(perturb, h=1e-4):
        H = np.zeros((6, 6))
        E = np.eye(6) * h
        for i in range(6):
            for j in range(6):
                H[i, j] = (
                    perturb(E[i] + E[j]) - perturb(E[i] - E[j]) - perturb(E[j] - E[i]) + perturb(-E[i] - E[j])
                ) / (4 * h * h)
        return H

    H_right = hessian(lambda xi: cost(T @ se3_exp(xi)))
    H_left = hessian(lambda xi: cost(se3_exp(xi) @ T))
    gn = info * reg.residual_sigma**2  # J^T W J
    scale = np.abs(H_right).max()
    assert np.abs(gn - H_right).max() < 1e-3 * scale
    assert np.abs(gn - H_left).max() > 0.1 * scale  # the test tells the conventions apart


def test_bad_input(tunnel):
    vmap = tunnel.map_before(20.0, seconds=0.3)
    pts, T_gt = tunnel.deskewed(20.0)
    with pytest.raises(InputFormatError):
        register(np.array([[np.nan, 0, 0]]), vmap, T_gt)
    with pytest.raises(InputFormatError):
        register(pts[:, :2], vmap, T_gt)
    with pytest.raises(InputFormatError):
        register(pts, vmap, 2 * T_gt)
    empty = register(np.zeros((0, 3)), vmap, T_gt)
    assert not empty.converged and "source points" in empty.message
    no_map = register(pts, VoxelMap(), T_gt)
    assert not no_map.converged and "empty" in no_map.message
    far = register(pts, vmap, T_gt @ se3_exp(np.r_[0, 0, 0, 0, 0, 50.0]))
    assert not far.converged and "correspondences" in far.message
    for r in (empty, no_map, far):
        np.testing.assert_array_equal(r.information, np.zeros((6, 6)))
        assert r.degenerate and r.weak_directions.shape == (6, 6)
