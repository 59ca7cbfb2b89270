"""IMU noise and gravity parameters (GTSAM's ``PreintegrationParams``), in Kalibr units.

See :mod:`jaxslam.factors._preintegration` for the method."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..errors import ConfigError

# ---------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------


def _is_concrete(*xs: Any) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _density_vector(name: str, value: Any) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(3, float(arr))
    if arr.shape != (3,):
        raise ConfigError(f"{name} must be a scalar or per-axis (3,), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ConfigError(f"{name} must be finite and >= 0, got {arr.tolist()}")
    return arr


def _covariance_matrix(name: str, value: Any) -> np.ndarray:
    cov = np.asarray(value, dtype=np.float64)
    if cov.shape != (3, 3):
        raise ConfigError(f"{name} must be a (3, 3) covariance, got shape {cov.shape}")
    if not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T, rtol=1e-12, atol=0.0):
        raise ConfigError(f"{name} must be finite and symmetric")
    if np.linalg.eigvalsh(cov).min() < -1e-15 * max(1.0, np.abs(cov).max()):
        raise ConfigError(f"{name} must be positive semi-definite")
    return cov


# GTSAM's example IMU metadata (``KittiEquivBiasedImu_metadata.txt``) -> our densities
_GTSAM_METADATA = {
    "AccelerometerSigma": "accelerometer_noise_density",
    "GyroscopeSigma": "gyroscope_noise_density",
    "IntegrationSigma": "integration_sigma",
    "AccelerometerBiasSigma": "accelerometer_random_walk",
    "GyroscopeBiasSigma": "gyroscope_random_walk",
}


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PreintegrationParams:
    """IMU noise and gravity, an immutable PyTree (GTSAM's ``PreintegrationParams``).

    Noise is given as continuous-time densities in Kalibr's units (``imu.yaml``):

    ======================================  ==========  =====================================
    field                                   shape       units
    ======================================  ==========  =====================================
    ``gravity``                             (3,)        m/s^2, navigation frame; Z-up:
                                                        ``(0, 0, -9.81)`` (``MakeSharedU``)
    ``accelerometer_covariance``            (3, 3)      (m/s^2)^2/Hz = sigma_a^2 (white noise
                                                        density squared)
    ``gyroscope_covariance``                (3, 3)      (rad/s)^2/Hz = sigma_g^2
    ``integration_covariance``              (3, 3)      m^2/s; GTSAM's position-integration
                                                        "covariance", added as ``Qi dt``
    ``accelerometer_random_walk``           (3,)        m/s^3/sqrt(Hz) (bias random walk)
    ``gyroscope_random_walk``               (3,)        rad/s^2/sqrt(Hz)
    ======================================  ==========  =====================================

    A sample held for ``dt`` seconds has discrete covariance ``Q/dt``; a bias drifts by
    ``sigma_rw * sqrt(dt_ij)`` over an interval. Build with :meth:`create`,
    :meth:`make_shared_u` or :meth:`make_shared_d`; the constructors validate, the raw
    dataclass constructor (used by PyTree unflattening) does not.
    """

    gravity: Array
    accelerometer_covariance: Array
    gyroscope_covariance: Array
    integration_covariance: Array
    accelerometer_random_walk: Array
    gyroscope_random_walk: Array

    @classmethod
    def create(
        cls,
        accelerometer_noise_density: Any = 0.0,
        gyroscope_noise_density: Any = 0.0,
        accelerometer_random_walk: Any = 0.0,
        gyroscope_random_walk: Any = 0.0,
        integration_sigma: Any = 0.0,
        gravity: Any = (0.0, 0.0, -9.81),
    ) -> PreintegrationParams:
        """From Kalibr densities: scalars (isotropic) or per-axis ``(3,)``.

        ``accelerometer_noise_density`` m/s^2/sqrt(Hz), ``gyroscope_noise_density``
        rad/s/sqrt(Hz), ``accelerometer_random_walk`` m/s^3/sqrt(Hz),
        ``gyroscope_random_walk`` rad/s^2/sqrt(Hz), ``integration_sigma`` m/sqrt(s),
        ``gravity`` (3,) m/s^2 in the navigation frame.
        """
        sa = _density_vector("accelerometer_noise_density", accelerometer_noise_density)
        sg = _density_vector("gyroscope_noise_density", gyroscope_noise_density)
        si = _density_vector("integration_sigma", integration_sigma)
        return cls.from_covariances(
            np.diag(sa**2),
            np.diag(sg**2),
            np.diag(si**2),
            accelerometer_random_walk=accelerometer_random_walk,
            gyroscope_random_walk=gyroscope_random_walk,
            gravity=gravity,
        )

    @classmethod
    def from_covariances(
        cls,
        accelerometer_covariance: Any,
        gyroscope_covariance: Any,
        integration_covariance: Any = None,
        accelerometer_random_walk: Any = 0.0,
        gyroscope_random_walk: Any = 0.0,
        gravity: Any = (0.0, 0.0, -9.81),
    ) -> PreintegrationParams:
        """From full (3, 3) continuous-time covariances (GTSAM's ``set*Covariance``); units as
        in the class table. ``integration_covariance`` defaults to zero."""
        if integration_covariance is None:
            integration_covariance = np.zeros((3, 3))
        g = np.asarray(gravity, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ConfigError(f"gravity must be a finite (3,) vector, got shape {g.shape}")
        return cls(
            gravity=jnp.asarray(g),
            accelerometer_covariance=jnp.asarray(
                _covariance_matrix("accelerometer_covariance", accelerometer_covariance)
            ),
            gyroscope_covariance=jnp.asarray(_covariance_matrix("gyroscope_covariance", gyroscope_covariance)),
            integration_covariance=jnp.asarray(_covariance_matrix("integration_covariance", integration_covariance)),
            accelerometer_random_walk=jnp.asarray(
                _density_vector("accelerometer_random_walk", accelerometer_random_walk)
            ),
            gyroscope_random_walk=jnp.asarray(_density_vector("gyroscope_random_walk", gyroscope_random_walk)),
        )

    @classmethod
    def make_shared_u(cls, g: float = 9.81, **densities: Any) -> PreintegrationParams:
        """Z-up navigation frame (ENU): gravity ``(0, 0, -g)``, GTSAM's ``MakeSharedU``."""
        return cls.create(gravity=(0.0, 0.0, -float(g)), **densities)

    @classmethod
    def make_shared_d(cls, g: float = 9.81, **densities: Any) -> PreintegrationParams:
        """Z-down navigation frame (NED): gravity ``(0, 0, g)``, GTSAM's ``MakeSharedD``."""
        return cls.create(gravity=(0.0, 0.0, float(g)), **densities)

    @classmethod
    def from_gtsam_metadata(cls, meta: dict[str, float], g: float = 9.81) -> PreintegrationParams:
        """Z-up parameters from GTSAM's example IMU metadata (the header/value lines of
        ``KittiEquivBiasedImu_metadata.txt`` as a dict): ``AccelerometerSigma``,
        ``GyroscopeSigma``, ``IntegrationSigma``, ``AccelerometerBiasSigma``,
        ``GyroscopeBiasSigma``. A missing name raises :class:`ConfigError`."""
        missing = [k for k in _GTSAM_METADATA if k not in meta]
        if missing:
            raise ConfigError(f"IMU metadata lacks {', '.join(missing)} (has {', '.join(meta) or 'nothing'})")
        return cls.make_shared_u(g, **{ours: meta[theirs] for theirs, ours in _GTSAM_METADATA.items()})

    def bias_random_walk_sigmas(self, delta_time: Any) -> Array:
        """Per-interval bias drift sigmas ``(*batch, 6)`` (acc then gyro; m/s^2, rad/s):
        ``sigma_rw * sqrt(delta_time)``, ``delta_time`` in seconds ``(*batch,)``."""
        sq = jnp.sqrt(jnp.asarray(delta_time, dtype=jnp.float64))[..., None]
        rw = jnp.concatenate([self.accelerometer_random_walk, self.gyroscope_random_walk])
        return sq * jnp.broadcast_to(rw, (*sq.shape[:-1], 6))
