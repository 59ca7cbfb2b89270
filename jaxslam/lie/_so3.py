"""SO(3), rotations in 3-D.

Layout: ``params`` is a unit quaternion ``(w, x, y, z)`` of shape ``(*batch, 4)``.
Tangent: the rotation vector ``omega`` (3,), right-perturbed: ``R @ exp(omega)``.

References: Sola, Deray, Atchuthan, "A micro Lie theory for state estimation in robotics"
(2018), eqs. (143)-(146) for the Jacobians; Barfoot, "State Estimation for Robotics" (2017)
sec. 7.1 for the closed forms.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from jax import Array

from ._base import LieGroup, broadcast_params
from ._utils import batch_shape_check, mm, safe_norm, series_or, skew


def quat_multiply(a: Array, b: Array) -> Array:
    """Hamilton product of ``(*batch, 4)`` wxyz quaternions."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_rotate(q: Array, p: Array) -> Array:
    """Rotate points ``p`` (*batch, 3) by unit quaternions ``q`` (*batch, 4)."""
    w = q[..., :1]
    v = q[..., 1:]
    t = 2.0 * jnp.cross(v, p)
    return p + w * t + jnp.cross(v, t)


def _cos_half(theta_sq: Array) -> Array:
    """cos(theta/2)."""
    return series_or(
        theta_sq, lambda t: jnp.cos(0.5 * t), (1.0, -1.0 / 8.0, 1.0 / 384.0, -1.0 / 46080.0, 1.0 / 10321920.0)
    )


def _sin_half_over(theta_sq: Array) -> Array:
    """sin(theta/2) / theta."""
    return series_or(
        theta_sq, lambda t: jnp.sin(0.5 * t) / t, (0.5, -1.0 / 48.0, 1.0 / 3840.0, -1.0 / 645120.0, 1.0 / 185794560.0)
    )


def _coef_b(theta_sq: Array) -> Array:
    """(1 - cos theta) / theta^2, computed as 2 sin^2(theta/2) / theta^2 (no cancellation)."""
    return series_or(
        theta_sq,
        lambda t: 2.0 * jnp.sin(0.5 * t) ** 2 / (t * t),
        (0.5, -1.0 / 24.0, 1.0 / 720.0, -1.0 / 40320.0, 1.0 / 3628800.0),
    )


def _coef_c(theta_sq: Array) -> Array:
    """(theta - sin theta) / theta^3."""
    return series_or(
        theta_sq,
        lambda t: (t - jnp.sin(t)) / (t * t * t),
        (1.0 / 6.0, -1.0 / 120.0, 1.0 / 5040.0, -1.0 / 362880.0, 1.0 / 39916800.0),
    )


def _coef_jrinv(theta_sq: Array) -> Array:
    """1/theta^2 - (1 + cos theta) / (2 theta sin theta): the omega^2 coefficient of Jr^-1.

    Evaluated as ``1/theta^2 - cot(theta/2) / (2 theta)`` (the same function): the literal
    form divides two quantities that both vanish at pi and loses ~eps/(pi - theta) there."""
    return series_or(
        theta_sq,
        lambda t: 1.0 / (t * t) - 0.5 * jnp.cos(0.5 * t) / (t * jnp.sin(0.5 * t)),
        (1.0 / 12.0, 1.0 / 720.0, 1.0 / 30240.0, 1.0 / 1209600.0, 1.0 / 47900160.0),
    )


@dataclasses.dataclass(frozen=True)
class SO3(LieGroup):
    """3-D rotation as a wxyz unit quaternion, shape ``(*batch, 4)``; tangent ``omega``."""

    param_dim = 4
    tangent_dim = 3
    matrix_dim = 3
    space_dim = 3

    @classmethod
    def identity(cls, batch_shape: tuple[int, ...] = ()) -> SO3:
        return cls(jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0, 0.0]), (*batch_shape, 4)))

    @classmethod
    def from_quaternion_xyzw(cls, xyzw: Array) -> SO3:
        xyzw = jnp.asarray(xyzw)
        return cls(jnp.concatenate([xyzw[..., 3:4], xyzw[..., :3]], axis=-1)).normalize()

    def quaternion_xyzw(self) -> Array:
        return jnp.concatenate([self.params[..., 1:], self.params[..., :1]], axis=-1)

    @classmethod
    def exp(cls, tangent: Array) -> SO3:
        tangent = jnp.asarray(tangent)
        batch_shape_check("SO3.exp", tangent, 3)
        theta_sq, _ = safe_norm(tangent)
        # cos(theta/2) as a series in theta^2 near 0: exact second derivatives at the
        # identity (the implicit-differentiation Hessian is taken there)
        w = _cos_half(theta_sq)
        xyz = _sin_half_over(theta_sq)[..., None] * tangent
        return cls(jnp.concatenate([w[..., None], xyz], axis=-1))

    def log(self) -> Array:
        q = self.params
        # q and -q are the same rotation; take w >= 0 so the angle is in [0, pi].
        q = jnp.where(q[..., :1] < 0.0, -q, q)
        w = q[..., 0]
        v = q[..., 1:]
        n_sq, n = safe_norm(v)
        small = n_sq < 1e-12
        n_safe = jnp.where(small, 1.0, n)
        w_safe = jnp.where(small, w, 1.0)  # the series sees w only where it is taken
        exact = 2.0 * jnp.arctan2(n_safe, w) / n_safe
        # 2 atan(n / w) / n for n -> 0, with w ~ 1.
        series = 2.0 / w_safe * (1.0 - n_sq / (3.0 * w_safe * w_safe))
        return jnp.where(small, series, exact)[..., None] * v

    def compose(self, other: SO3) -> SO3:
        a, b = broadcast_params(self.params, other.params)
        return SO3(quat_multiply(a, b))

    def inverse(self) -> SO3:
        return SO3(jnp.concatenate([self.params[..., :1], -self.params[..., 1:]], axis=-1))

    def act(self, points: Array) -> Array:
        points = jnp.asarray(points)
        batch_shape_check("SO3.act", points, 3)
        params, points = broadcast_params(self.params, points)
        return quat_rotate(params, points)

    def as_matrix(self) -> Array:
        w, x, y, z = (self.params[..., i] for i in range(4))
        return jnp.stack(
            [
                jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
            ],
            axis=-2,
        )

    @classmethod
    def from_matrix(cls, matrix: Array) -> SO3:
        """Rotation matrix ``(*batch, 3, 3)`` to quaternion (Shepperd's method, branch-free:
        all four candidates are formed and the best-conditioned one is kept)."""
        m = jnp.asarray(matrix)
        if m.shape[-2:] != (3, 3):
            raise ValueError(f"SO3.from_matrix expects (*batch, 3, 3), got {tuple(m.shape)}")
        m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
        m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
        m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
        tr = m00 + m11 + m22
        cands = jnp.stack(
            [
                jnp.stack([1 + tr, m21 - m12, m02 - m20, m10 - m01], -1),
                jnp.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
                jnp.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
                jnp.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
            ],
            axis=-2,
        )
        diag = jnp.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
        best = jnp.argmax(diag, axis=-1)
        q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
        q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
        q = jnp.where(q[..., :1] < 0.0, -q, q)
        return cls(q)

    def adjoint(self) -> Array:
        return self.as_matrix()

    def normalize(self) -> SO3:
        return SO3(self.params / jnp.linalg.norm(self.params, axis=-1, keepdims=True))

    @staticmethod
    def jr(tangent: Array) -> Array:
        """Right Jacobian ``I - b W + c W^2``, W = skew(omega)."""
        theta_sq, _ = safe_norm(tangent)
        w = skew(tangent)
        eye = jnp.broadcast_to(jnp.eye(3), w.shape)
        return eye - _coef_b(theta_sq)[..., None, None] * w + _coef_c(theta_sq)[..., None, None] * mm(w, w)

    @staticmethod
    def jr_inv(tangent: Array) -> Array:
        """``I + W/2 + d W^2``, d = 1/theta^2 - (1 + cos)/(2 theta sin). Singular at 2 pi."""
        theta_sq, _ = safe_norm(tangent)
        w = skew(tangent)
        eye = jnp.broadcast_to(jnp.eye(3), w.shape)
        return eye + 0.5 * w + _coef_jrinv(theta_sq)[..., None, None] * mm(w, w)
