"""Scale-free relative pose from monocular two-view geometry (SPEC §3.3, the honest option
when no metric depth exists): the essential matrix gives the relative rotation and the
*direction* of the translation, never its length.

Between body poses ``X_i``, ``X_j`` seen through a camera mounted at ``T_bc`` (body from
camera), the predicted camera motion is ``T = T_bc^-1 X_i^-1 X_j T_bc`` (camera j in camera
i). Residual (5,): ``[Log(R_meas^T R_T) (3), B^T t_T / |t_T| (2)]`` where ``B`` (3, 2) spans
the plane orthogonal to the measured unit direction ``u`` — zero when the predicted
translation points along ``u``, whatever its length. ``|t|`` is smoothed by a 1 mm floor so
the residual and its autodiff Jacobians stay finite when the bodies coincide (add the factor
only when the bodies moved). Jacobians by autodiff.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array

from ..core import Factor, Gaussian, Pose3Var, RobustKernel, factor_dataclass
from ..lie import SE3, SO3


def _orthonormal_basis(u: np.ndarray) -> np.ndarray:
    """(N, 3, 2): two unit vectors orthogonal to each unit ``u`` (N, 3) and to each other."""
    helper = np.where(np.abs(u[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    a = np.cross(u, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(u, a)
    return np.stack([a, b], axis=2)


@factor_dataclass
class RelativeDirectionFactor(Factor):
    """Relative rotation + translation direction between two Pose3 (see the module doc).
    Fields per constraint: ``rotation`` (N, 4) measured camera rotation (wxyz), ``basis``
    (N, 3, 2), ``body_T_camera`` (N, 7)."""

    rotation: Array
    basis: Array
    body_T_camera: Array

    @classmethod
    def create(
        cls,
        pose_i: Pose3Var,
        pose_j: Pose3Var,
        rotation: Any,
        direction: Any,
        body_T_camera: Any,
        noise: Gaussian,
        robust: RobustKernel | None = None,
    ) -> RelativeDirectionFactor:
        """``rotation`` (N, 3, 3) or (3, 3) camera j's rotation in camera i; ``direction``
        (N, 3) or (3,) camera j's position in camera i (normalised here); ``body_T_camera``
        SE(3) params (7,); ``noise`` of dimension 5 (rotation rad, then direction rad)."""
        for name, var in (("pose_i", pose_i), ("pose_j", pose_j)):
            if type(var) is not Pose3Var:
                raise TypeError(f"RelativeDirectionFactor {name} must be a Pose3Var, got {type(var).__name__}")
        n = len(pose_i)
        R = np.broadcast_to(np.asarray(rotation, np.float64), (n, 3, 3))
        u = np.broadcast_to(np.asarray(direction, np.float64), (n, 3))
        norm = np.linalg.norm(u, axis=1, keepdims=True)
        if np.any(~np.isfinite(norm)) or np.any(norm < 1e-12):
            raise ValueError("RelativeDirectionFactor: the measured direction must be a finite non-zero vector")
        u = u / norm
        if noise.dim != 5:
            raise ValueError(f"RelativeDirectionFactor: noise must have dimension 5, got {noise.dim}")
        from ..lie.host import matrix_to_quat

        tbc = np.broadcast_to(np.asarray(body_T_camera, np.float64), (n, 7))
        return cls(
            variables=(pose_i, pose_j),
            noise=noise if len(noise) == n else noise.broadcast(n),
            robust=robust,
            rotation=jnp.asarray(matrix_to_quat(R)),
            basis=jnp.asarray(_orthonormal_basis(u)),
            body_T_camera=jnp.asarray(tbc),
        )

    def residual(self, xi: SE3, xj: SE3) -> Array:
        tbc = SE3(self.body_T_camera)
        T = tbc.inverse() @ xi.inverse() @ xj @ tbc
        e_rot = (SO3(self.rotation).inverse() @ T.rotation).log()
        t = T.translation
        unit = t / jnp.sqrt(jnp.sum(t * t, axis=-1, keepdims=True) + 1e-6)
        e_dir = jnp.einsum("nij,ni->nj", self.basis, unit)
        return jnp.concatenate([e_rot, e_dir], axis=-1)
