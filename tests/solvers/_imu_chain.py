"""A smoothly turning, accelerating IMU chain and its generating states, shared by the
mixed-variable solver tests."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxslam.factors import PreintegrationParams, predict_imu_state, preintegrate
from jaxslam.lie import SE3


def imu_chain(n_kf: int, m: int, rate: float = 200.0):
    """``n_kf`` keyframes, ``m`` IMU samples between consecutive ones (gravity plus varying
    body readings): the preintegration parameters and measurements, and the poses (params)
    and velocities that chaining the predictions from a known start (zero bias) gives."""
    params = PreintegrationParams.make_shared_u(
        9.81,
        accelerometer_noise_density=0.02,
        gyroscope_noise_density=0.002,
        accelerometer_random_walk=1e-3,
        gyroscope_random_walk=1e-4,
        integration_sigma=1e-4,
    )
    t = np.arange((n_kf - 1) * m) / rate
    gyro = np.stack([0.2 * np.sin(t), 0.1 * np.cos(0.5 * t), 0.3 + 0.0 * t], axis=1)
    acc = np.stack([0.5 * np.cos(t), 0.2 * np.sin(t), 9.81 + 0.1 * np.sin(2 * t)], axis=1)
    pim = preintegrate(
        acc.reshape(n_kf - 1, m, 3), gyro.reshape(n_kf - 1, m, 3), np.full((n_kf - 1, m), 1 / rate), params
    )
    poses, vels = [SE3.exp(jnp.asarray([0.1, -0.2, 0.3, 1.0, 2.0, 0.5]))], [jnp.asarray([1.0, 0.0, 0.2])]
    for k in range(n_kf - 1):
        p, v = predict_imu_state(
            pim.preintegrated[k : k + 1],
            pim.delta_time[k : k + 1],
            params.gravity[None],
            poses[-1][None],
            vels[-1][None],
        )
        poses.append(p[0])
        vels.append(v[0])
    P = np.stack([np.asarray(p.params) for p in poses])
    V = np.stack([np.asarray(v) for v in vels])
    return params, pim, P, V
