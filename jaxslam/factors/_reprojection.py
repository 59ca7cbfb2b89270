"""Reprojection factor for bundle adjustment: a pinhole camera with Cal3_S2 intrinsics.

One constraint ties a camera pose ``world_T_body`` (:class:`Pose3Var`) and a world point
(:class:`Point3Var`) to a measured pixel ``(u, v)``. With an optional ``body_T_sensor`` the
camera sits at ``world_T_body @ body_T_sensor``. In the camera frame (z along the optical
axis, x right, y down; GTSAM / OpenCV convention) a point ``(X, Y, Z)`` projects to

    u = fx X/Z + s Y/Z + cx,    v = fy Y/Z + cy

and the residual (2-d, pixels, not whitened) is ``(u, v) - measured``: the same as
``gtsam.GenericProjectionFactorCal3_S2``. The calibration is stored per constraint as
``(fx, fy, s, cx, cy)``, GTSAM's ``Cal3_S2.vector()`` order.

**Cheirality.** A point with depth ``Z <= min_depth`` (behind the camera, or on its centre
plane) has no projection. Its residual is the constant ``(2 fx, 2 fx)`` and its Jacobians
are zero: the cost stays finite and bounded, carries no gradient (so it neither pulls the
point further behind nor produces NaN), and equals what GTSAM's factor returns for a point
behind the camera (``Z <= 0``). :meth:`ReprojectionFactor.in_front` reports which
constraints are valid, for a caller that wants to drop or re-triangulate the others.

Jacobians are analytic (right perturbation of the pose, plain for the point):
``d p_s / d delta = R_bs^T [[p_b]x, -I]``, ``d p_s / d p = (R_wb R_bs)^T`` and
``d uv / d p_s = [[fx, s], [0, fy]] [[1/Z, 0, -X/Z^2], [0, 1/Z, -Y/Z^2]]``
(Hartley & Zisserman, "Multiple View Geometry", 2nd ed., sec. 6.1 for the camera model).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array

from ..core import Factor, Gaussian, Point3Var, Pose3Var, RobustKernel, Variable, factor_dataclass
from ..lie import SE3, skew
from ._between import _broadcast_noise

MIN_DEPTH = 1e-8
"""Default smallest depth (in the units of the map) that still counts as in front."""


def project_pinhole(
    calibration: Array, points_camera: Array, min_depth: Array | float = MIN_DEPTH
) -> tuple[Array, Array]:
    """Project camera-frame points ``(*batch, 3)`` with intrinsics ``(*batch, 5)`` =
    ``(fx, fy, s, cx, cy)``. Returns ``(uv, in_front)``: pixels ``(*batch, 2)`` (finite;
    meaningless where ``in_front`` is False) and ``Z > min_depth`` ``(*batch,)``. Value and
    gradients are NaN-free for every input (double ``where`` on the depth)."""
    calibration = jnp.asarray(calibration)
    points_camera = jnp.asarray(points_camera)
    z = points_camera[..., 2]
    in_front = z > min_depth
    z_safe = jnp.where(in_front, z, 1.0)
    x = jnp.where(in_front, points_camera[..., 0], 0.0) / z_safe
    y = jnp.where(in_front, points_camera[..., 1], 0.0) / z_safe
    fx, fy, s, cx, cy = (calibration[..., i] for i in range(5))
    uv = jnp.stack([fx * x + s * y + cx, fy * y + cy], axis=-1)
    return uv, in_front


def pinhole_project(
    world_T_camera: SE3, points_world: Array, calibration: Array, min_depth: Array | float = MIN_DEPTH
) -> tuple[Array, Array]:
    """Project world points through cameras at ``world_T_camera``; see :func:`project_pinhole`.
    The batch axes of the poses and points broadcast together; ``calibration`` is ``(5,)``
    (shared) or has the points' batch axes."""
    return project_pinhole(calibration, world_T_camera.inverse().act(points_world), min_depth)


def _per_constraint(name: str, value: Any, n: int, width: int) -> Array:
    arr = jnp.asarray(value, dtype=jnp.float64)
    if arr.ndim == 1:
        arr = jnp.broadcast_to(arr, (n, arr.shape[0]))
    if arr.shape != (n, width):
        raise ValueError(
            f"{name} for {n} reprojection constraints must have shape ({width},) or ({n}, {width}), "
            f"got {tuple(arr.shape)}"
        )
    return arr


@factor_dataclass
class ReprojectionFactor(Factor):
    """Pixel reprojection error of a world point in a pinhole camera; see the module doc.

    Fields: ``measured`` ``(N, 2)`` pixels, ``calibration`` ``(N, 5)`` = ``(fx, fy, s, cx,
    cy)``, ``body_T_sensor`` ``(N, 7)`` SE3 parameters (identity when the pose variable is
    the camera itself), ``min_depth`` (shared scalar). Variables: ``(Pose3Var, Point3Var)``.
    """

    measured: Array
    calibration: Array
    body_T_sensor: Array
    min_depth: Array | float = MIN_DEPTH

    @classmethod
    def create(
        cls,
        pose_var: Variable,
        point_var: Variable,
        measured: Any,
        calibration: Any,
        noise: Gaussian,
        body_T_sensor: SE3 | Any | None = None,
        robust: RobustKernel | None = None,
        min_depth: float = MIN_DEPTH,
    ) -> ReprojectionFactor:
        """``calibration`` is ``(fx, fy, s, cx, cy)``, shared ``(5,)`` or ``(N, 5)``;
        ``measured`` ``(N, 2)`` (or ``(2,)`` shared); ``noise`` 2-d, in pixels."""
        if not isinstance(pose_var, Pose3Var) or not isinstance(point_var, Point3Var):
            raise TypeError(
                f"reprojection factor needs (Pose3Var, Point3Var), got ({type(pose_var).__name__}, "
                f"{type(point_var).__name__})"
            )
        n = len(pose_var)
        if len(point_var) != n:
            raise ValueError(f"reprojection factor: {n} pose ids but {len(point_var)} point ids")
        calib = _per_constraint("calibration", calibration, n, 5)
        if isinstance(calibration, (np.ndarray, list, tuple)) and np.any(np.asarray(calib)[:, :2] <= 0):
            raise ValueError("calibration focal lengths fx, fy must be > 0")
        if body_T_sensor is None:
            body = SE3.identity((n,)).params
        else:
            body = body_T_sensor.params if isinstance(body_T_sensor, SE3) else body_T_sensor
        return cls(
            variables=(pose_var, point_var),
            noise=_broadcast_noise(noise, n, 2),
            robust=robust,
            measured=_per_constraint("measured", measured, n, 2),
            calibration=calib,
            body_T_sensor=_per_constraint("body_T_sensor", body, n, 7),
            min_depth=min_depth,
        )

    # --- geometry -----------------------------------------------------------------------
    def _sensor_points(self, pose: SE3, point: Array) -> tuple[Array, Array]:
        """The point in the body frame and in the sensor (camera) frame, ``(N, 3)`` each."""
        p_body = pose.inverse().act(point)
        p_sensor = SE3(self.body_T_sensor).inverse().act(p_body)
        return p_body, p_sensor

    def _behind_residual(self) -> Array:
        fx2 = 2.0 * self.calibration[:, 0]
        return jnp.stack([fx2, fx2], axis=-1)

    def in_front(self, pose: SE3, point: Array) -> Array:
        """``(N,)`` bool: the point is at depth ``> min_depth`` in its camera."""
        return self._sensor_points(pose, point)[1][:, 2] > self.min_depth

    # --- Factor interface ---------------------------------------------------------------
    def residual(self, pose: SE3, point: Array) -> Array:
        _, p_sensor = self._sensor_points(pose, point)
        uv, front = project_pinhole(self.calibration, p_sensor, self.min_depth)
        return jnp.where(front[:, None], uv - self.measured, self._behind_residual())

    def jacobians(self, pose: SE3, point: Array) -> tuple[Array, Array]:
        p_body, p_s = self._sensor_points(pose, point)
        front = p_s[:, 2] > self.min_depth
        z = jnp.where(front, p_s[:, 2], 1.0)
        x, y = p_s[:, 0] / z, p_s[:, 1] / z
        fx, fy, s = self.calibration[:, 0], self.calibration[:, 1], self.calibration[:, 2]
        zero = jnp.zeros_like(z)
        # d(u, v) / d p_sensor = K2 @ d(x_n, y_n) / d p_sensor
        d_uv = jnp.stack(
            [
                jnp.stack([fx / z, s / z, -(fx * x + s * y) / z], axis=-1),
                jnp.stack([zero, fy / z, -fy * y / z], axis=-1),
            ],
            axis=-2,
        )
        d_uv = jnp.where(front[:, None, None], d_uv, 0.0)
        r_bs_t = jnp.swapaxes(SE3(self.body_T_sensor).rotation.as_matrix(), -1, -2)
        r_wb_t = jnp.swapaxes(pose.rotation.as_matrix(), -1, -2)
        eye = jnp.broadcast_to(jnp.eye(3), r_bs_t.shape)
        d_pose = d_uv @ r_bs_t @ jnp.concatenate([skew(p_body), -eye], axis=-1)
        d_point = d_uv @ r_bs_t @ r_wb_t
        return d_pose, d_point
