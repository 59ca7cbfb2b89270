"""SE(3), rigid motions in 3-D.

Layout: ``params`` is ``(qw, qx, qy, qz, x, y, z)``, shape ``(*batch, 7)``: the rotation as
a wxyz unit quaternion, then the translation.
Tangent: ``[omega, rho]`` (rotation first, like GTSAM's Pose3), right-perturbed.
``exp([omega, rho]) = (Exp(omega), Jl(omega) rho)``.

References: Barfoot, "State Estimation for Robotics" (2017) eqs. (7.83)-(7.86) for the
SE(3) Jacobians (written there for the [rho, phi] order; here the blocks are swapped).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from jax import Array

from ._base import LieGroup, broadcast_params
from ._so3 import SO3, _coef_b, _coef_c, _coef_jrinv, quat_multiply, quat_rotate
from ._utils import batch_shape_check, mm, safe_norm, series_or, skew


def _coef_q2(theta_sq: Array) -> Array:
    """(theta^2 + 2 cos theta - 2) / (2 theta^4)."""
    return series_or(
        theta_sq,
        lambda t: (t * t + 2.0 * jnp.cos(t) - 2.0) / (2.0 * t**4),
        (1.0 / 24.0, -1.0 / 720.0, 1.0 / 40320.0, -1.0 / 3628800.0, 1.0 / 479001600.0),
    )


def _coef_q3(theta_sq: Array) -> Array:
    """(2 theta - 3 sin theta + theta cos theta) / (2 theta^5)."""
    return series_or(
        theta_sq,
        lambda t: (2.0 * t - 3.0 * jnp.sin(t) + t * jnp.cos(t)) / (2.0 * t**5),
        (1.0 / 120.0, -1.0 / 2520.0, 1.0 / 120960.0, -1.0 / 9979200.0, 1.0 / 1245404160.0),
    )


def _q_matrix(omega: Array, rho: Array) -> Array:
    """Barfoot's Q(phi, rho): the off-diagonal block of the SE(3) left Jacobian."""
    theta_sq, _ = safe_norm(omega)
    w = skew(omega)
    r = skew(rho)
    wr = mm(w, r)
    rw = mm(r, w)
    wrw = mm(wr, w)
    ww = mm(w, w)
    c1 = _coef_c(theta_sq)[..., None, None]
    c2 = _coef_q2(theta_sq)[..., None, None]
    c3 = _coef_q3(theta_sq)[..., None, None]
    return 0.5 * r + c1 * (wr + rw + wrw) + c2 * (mm(ww, r) + mm(rw, w) - 3.0 * wrw) + c3 * (mm(wrw, w) + mm(w, wrw))


def _block(a: Array, b: Array, c: Array, d: Array) -> Array:
    """[[a, b], [c, d]] from (*batch, 3, 3) blocks."""
    top = jnp.concatenate([a, b], axis=-1)
    bottom = jnp.concatenate([c, d], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


@dataclasses.dataclass(frozen=True)
class SE3(LieGroup):
    """Rigid motion ``(qw, qx, qy, qz, x, y, z)``, shape ``(*batch, 7)``; tangent
    ``[omega, rho]``."""

    param_dim = 7
    tangent_dim = 6
    matrix_dim = 4
    space_dim = 3

    @classmethod
    def identity(cls, batch_shape: tuple[int, ...] = ()) -> SE3:
        return cls(jnp.broadcast_to(jnp.array([1.0, 0, 0, 0, 0, 0, 0]), (*batch_shape, 7)))

    @classmethod
    def from_rotation_translation(cls, rotation: SO3, translation: Array) -> SE3:
        translation = jnp.asarray(translation)
        q, t = broadcast_params(rotation.params, translation)
        return cls(jnp.concatenate([q, t], axis=-1))

    @property
    def rotation(self) -> SO3:
        return SO3(self.params[..., :4])

    @property
    def translation(self) -> Array:
        return self.params[..., 4:]

    @classmethod
    def exp(cls, tangent: Array) -> SE3:
        tangent = jnp.asarray(tangent)
        batch_shape_check("SE3.exp", tangent, 6)
        omega, rho = tangent[..., :3], tangent[..., 3:]
        theta_sq, _ = safe_norm(omega)
        # V = Jl(omega) = I + b W + c W^2
        v_rho = (
            rho
            + _coef_b(theta_sq)[..., None] * jnp.cross(omega, rho)
            + _coef_c(theta_sq)[..., None] * jnp.cross(omega, jnp.cross(omega, rho))
        )
        return cls(jnp.concatenate([SO3.exp(omega).params, v_rho], axis=-1))

    def log(self) -> Array:
        omega = self.rotation.log()
        theta_sq, _ = safe_norm(omega)
        t = self.translation
        w_t = jnp.cross(omega, t)
        # V^-1 = I - W/2 + d W^2 with the same d as SO(3)'s Jr^-1 coefficient.
        rho = t - 0.5 * w_t + _coef_jrinv(theta_sq)[..., None] * jnp.cross(omega, w_t)
        return jnp.concatenate([omega, rho], axis=-1)

    def compose(self, other: SE3) -> SE3:
        a, b = broadcast_params(self.params, other.params)
        q = quat_multiply(a[..., :4], b[..., :4])
        t = a[..., 4:] + quat_rotate(a[..., :4], b[..., 4:])
        return SE3(jnp.concatenate([q, t], axis=-1))

    def inverse(self) -> SE3:
        q_inv = jnp.concatenate([self.params[..., :1], -self.params[..., 1:4]], axis=-1)
        t = -quat_rotate(q_inv, self.params[..., 4:])
        return SE3(jnp.concatenate([q_inv, t], axis=-1))

    def act(self, points: Array) -> Array:
        points = jnp.asarray(points)
        batch_shape_check("SE3.act", points, 3)
        params, points = broadcast_params(self.params, points)
        return quat_rotate(params[..., :4], points) + params[..., 4:]

    def as_matrix(self) -> Array:
        r = self.rotation.as_matrix()
        t = self.translation[..., :, None]
        top = jnp.concatenate([r, t], axis=-1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), (*top.shape[:-2], 1, 4))
        return jnp.concatenate([top, bottom], axis=-2)

    @classmethod
    def from_matrix(cls, matrix: Array) -> SE3:
        m = jnp.asarray(matrix)
        if m.shape[-2:] not in ((4, 4), (3, 4)):
            raise ValueError(f"SE3.from_matrix expects (*batch, 4, 4) or (*batch, 3, 4), got {tuple(m.shape)}")
        return cls.from_rotation_translation(SO3.from_matrix(m[..., :3, :3]), m[..., :3, 3])

    def adjoint(self) -> Array:
        """``[[R, 0], [t^ R, R]]`` for the [omega, rho] order."""
        r = self.rotation.as_matrix()
        return _block(r, jnp.zeros_like(r), mm(skew(self.translation), r), r)

    def normalize(self) -> SE3:
        return SE3(jnp.concatenate([self.rotation.normalize().params, self.translation], axis=-1))

    @staticmethod
    def jr(tangent: Array) -> Array:
        """Right Jacobian ``[[Jr(w), 0], [Q(-w, -rho), Jr(w)]]``."""
        omega, rho = tangent[..., :3], tangent[..., 3:]
        j = SO3.jr(omega)
        return _block(j, jnp.zeros_like(j), _q_matrix(-omega, -rho), j)

    @staticmethod
    def jr_inv(tangent: Array) -> Array:
        """``[[Jr^-1, 0], [-Jr^-1 Q Jr^-1, Jr^-1]]``."""
        omega, rho = tangent[..., :3], tangent[..., 3:]
        ji = SO3.jr_inv(omega)
        q = _q_matrix(-omega, -rho)
        return _block(ji, jnp.zeros_like(ji), -mm(mm(ji, q), ji), ji)
