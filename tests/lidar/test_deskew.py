from __future__ import annotations

import numpy as np
import pytest

from jaxslam.errors import InputFormatError
from jaxslam.lidar import deskew
from jaxslam.lidar._se3 import se3_exp, transform_points


def _world_error(points, T):
    return lambda world: np.linalg.norm(transform_points(T, points) - world, axis=1)


@pytest.mark.parametrize(("t", "gain"), [(30.0, 1.8), (69.0, 4.0)])  # cruising at 0.5 m/s; turning on the spot
def test_deskew_with_ground_truth_restores_the_surface(tunnel, t, gain):
    sc = tunnel.scan(t)
    tk = np.linspace(0.0, 0.1, 6)
    T = tunnel.sensor_pose(t + tk)
    fixed = deskew(sc["points"], sc["point_times"], (T[:, :3, :3], T[:, :3, 3], tk))
    err_fixed = np.median(_world_error(fixed, T[0])(sc["world"]))
    err_raw = np.median(_world_error(sc["points"], T[0])(sc["world"]))
    assert err_fixed < 0.016  # the 2 cm range noise: median |N(0, 0.02)| = 1.35 cm
    assert err_raw > gain * err_fixed
    # referenced to the frame end instead
    end = deskew(sc["points"], sc["point_times"], (T[:, :3, :3], T[:, :3, 3], tk), reference_time=0.1)
    assert np.median(_world_error(end, T[-1])(sc["world"])) < 0.016


def test_twist_model_is_exact_on_a_constant_twist():
    rng = np.random.default_rng(1)
    xi = np.array([0.1, -0.2, 0.8, 0.5, 0.1, -0.05])
    tau = np.sort(rng.uniform(0, 0.1, 500))
    ref = rng.uniform(-10, 10, (500, 3))  # points in the frame at t = 0
    T = se3_exp(tau[:, None] * xi)
    meas = np.einsum("nji,nj->ni", T[:, :3, :3], ref - T[:, :3, 3])  # seen from the moving sensor
    np.testing.assert_allclose(deskew(meas, tau, xi), ref, atol=1e-12)
    # the same motion sampled finely and interpolated (slerp + linear) agrees closely
    tk = np.linspace(0, 0.1, 41)
    Tk = se3_exp(tk[:, None] * xi)
    np.testing.assert_allclose(deskew(meas, tau, (Tk[:, :3, :3], Tk[:, :3, 3], tk)), ref, atol=2e-5)


def test_deskew_rejects_bad_motion():
    pts, tau = np.ones((3, 3)), np.array([0.0, 0.05, 0.1])
    tk = np.array([0.0, 0.05])
    with pytest.raises(InputFormatError, match="outside"):
        deskew(pts, tau, (np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3)), tk))
    with pytest.raises(InputFormatError):
        deskew(pts, tau, np.array([0.0, np.nan, 0, 0, 0, 0]))
    with pytest.raises(InputFormatError):
        deskew(pts, tau[:2], np.zeros(6))
