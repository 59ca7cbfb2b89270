"""The IMU: exact specific force and angular rate from the trajectory, plus MEMS noise.

``acc = R^T (a - g) + b_a + n_a`` and ``gyro = omega + b_g + n_g`` in the body (= IMU)
frame, gravity ``g = (0, 0, -9.81)``. Noise comes from continuous-time densities (Kalibr
units): a sample at rate ``f`` has white noise ``sigma * sqrt(f)`` and the biases walk by
``sigma_rw / sqrt(f)`` per sample, starting from a random turn-on bias.

Defaults are an HWT901B-class MEMS unit (its accelerometer/gyro chip's datasheet densities,
rounded up as Kalibr users do): accelerometer 2.0e-3 m/s^2/sqrt(Hz), gyro 1.7e-4
rad/s/sqrt(Hz) (0.01 deg/s/sqrt(Hz)), bias walks 3e-4 m/s^3/sqrt(Hz) and 2e-5
rad/s^2/sqrt(Hz), turn-on bias 0.05 m/s^2 and 0.2 deg/s (1 sigma).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ConfigError

GRAVITY = np.array([0.0, 0.0, -9.81])


@dataclasses.dataclass(frozen=True)
class ImuConfig:
    """IMU rate and noise (Kalibr units)."""

    rate: float = 200.0
    accelerometer_noise_density: float = 2.0e-3
    gyroscope_noise_density: float = 1.7e-4
    accelerometer_random_walk: float = 3.0e-4
    gyroscope_random_walk: float = 2.0e-5
    accelerometer_bias: float = 0.05
    """Turn-on accelerometer bias, 1 sigma per axis (m/s^2)."""
    gyroscope_bias: float = 0.0035
    """Turn-on gyro bias, 1 sigma per axis (rad/s)."""
    noise: bool = True
    """False: exact readings (no noise, no bias), for consistency checks."""

    def __post_init__(self) -> None:
        if not self.rate > 0:
            raise ConfigError("imu rate must be positive")
        vals = (
            self.accelerometer_noise_density,
            self.gyroscope_noise_density,
            self.accelerometer_random_walk,
            self.gyroscope_random_walk,
        )
        if min(vals) < 0 or min(self.accelerometer_bias, self.gyroscope_bias) < 0:
            raise ConfigError("imu noise densities and biases must be >= 0")


def synthesize_imu(state: dict[str, np.ndarray], config: ImuConfig, seed: int = 0) -> dict[str, np.ndarray]:
    """IMU readings for the states of :meth:`TunnelTrajectory.state` (at the IMU times).

    Returns ``acc``, ``gyro`` (N, 3) and the true biases ``bias_acc``, ``bias_gyro`` (N, 3)."""
    R, a, w = state["R"], state["a"], state["omega"]
    acc = np.einsum("nji,nj->ni", R, a - GRAVITY)
    gyro = w.copy()
    n = len(acc)
    if not config.noise:
        z = np.zeros_like(acc)
        return {"acc": acc, "gyro": gyro, "bias_acc": z, "bias_gyro": z}
    rng = np.random.default_rng([seed, 11])
    f = config.rate
    ba0 = config.accelerometer_bias * rng.standard_normal(3)
    bg0 = config.gyroscope_bias * rng.standard_normal(3)
    ba = ba0 + np.cumsum(config.accelerometer_random_walk / np.sqrt(f) * rng.standard_normal((n, 3)), axis=0)
    bg = bg0 + np.cumsum(config.gyroscope_random_walk / np.sqrt(f) * rng.standard_normal((n, 3)), axis=0)
    acc = acc + ba + config.accelerometer_noise_density * np.sqrt(f) * rng.standard_normal((n, 3))
    gyro = gyro + bg + config.gyroscope_noise_density * np.sqrt(f) * rng.standard_normal((n, 3))
    return {"acc": acc, "gyro": gyro, "bias_acc": ba, "bias_gyro": bg}
