"""The robot's path: a smooth out-and-back drive through the tunnel with exact derivatives.

Schedule: stand still, drive ``length`` out along the route (smooth speed ramps to
``speed``: velocity follows a minimum-jerk step, so acceleration and jerk are continuous),
stop, turn on the spot by 180 degrees (minimum-jerk yaw), drive back to the start, stand
still. A slow lateral wander (zero at both ends) and body vibration (sums of sines whose
amplitude scales with speed) ride on top. The path ends where it started: a loop.

The pose ``T_world_body(t)`` is a closed-form JAX function of ``t`` (body = IMU frame: x
forward, y left, z up), so velocity, acceleration and body angular rate are exact (forward-
mode autodiff), never finite differences.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._tunnel import Tunnel


@dataclasses.dataclass(frozen=True)
class MotionConfig:
    """How the robot drives."""

    speed: float = 0.5
    """Cruise speed (m/s)."""
    ramp: float = 3.0
    """Time (s) to reach cruise speed from rest (and to stop)."""
    still: float = 1.5
    """Standing still at the start, at the far end (before and after the turn) and at the end (s)."""
    turn: float = 6.0
    """Duration of the 180-degree turn on the spot (s)."""
    lateral: float = -0.35
    """Lateral offset of the path from the centreline (m, left positive)."""
    wander: float = 0.08
    """Amplitude of the slow lateral wander (m)."""
    height: float = 0.35
    """IMU height above the floor (m)."""
    vibration: float = 1.0
    """Scale of the body vibration (0 = none)."""


def _minjerk(x):
    x = jnp.clip(x, 0.0, 1.0)
    return x**3 * (10 - 15 * x + 6 * x * x)


def _minjerk_integral(x):
    return x**4 * (2.5 - 3 * x + x * x)


class TunnelTrajectory:
    """Pose, velocity, acceleration and body rates of the simulated robot at any time."""

    def __init__(self, tunnel: Tunnel, motion: MotionConfig, seed: int = 0):
        self.tunnel, self.motion = tunnel, motion
        m, length = motion, tunnel.config.length
        self.t_leg = length / m.speed + m.ramp
        self.t_out = m.still
        self.t_turn = self.t_out + self.t_leg + m.still
        self.t_back = self.t_turn + m.turn + m.still
        self.duration = self.t_back + self.t_leg + m.still
        rng = np.random.default_rng([seed, 101])
        # vibration: (component, frequency Hz, amplitude, phase); components roll, pitch, yaw (rad), z (m)
        freqs = rng.uniform(4.0, 14.0, size=(4, 3))
        amps = np.array([0.0008, 0.0012, 0.0005, 0.00015])[:, None] * rng.uniform(0.5, 1.0, size=(4, 3))
        self._vib = (
            jnp.asarray(freqs),
            jnp.asarray(amps * m.vibration),
            jnp.asarray(rng.uniform(0, 2 * np.pi, (4, 3))),
        )
        self._jit_state = jax.jit(jax.vmap(self._state))
        self._jit_pose = jax.jit(jax.vmap(self._pose))

    # --- scalar schedule -------------------------------------------------------------------------

    def _leg(self, tau):
        m, D, T = self.motion, self.tunnel.config.length, self.t_leg
        v, r = m.speed, m.ramp
        up = v * r * _minjerk_integral(tau / r)
        cruise = v * r / 2 + v * (tau - r)
        down = D - v * r * _minjerk_integral((T - tau) / r)
        return jnp.where(
            tau <= 0, 0.0, jnp.where(tau < r, up, jnp.where(tau <= T - r, cruise, jnp.where(tau < T, down, D)))
        )

    def _speed_scale(self, t):
        r, T = self.motion.ramp, self.t_leg

        def ramp(tau):
            return _minjerk(tau / r) * _minjerk((T - tau) / r)

        return ramp(t - self.t_out) + ramp(t - self.t_back)

    def _pose(self, t):
        """``(R (3, 3), p (3,))`` of the body in the world at scalar ``t``."""
        m, cfg = self.motion, self.tunnel.config
        s = self._leg(t - self.t_out) - self._leg(t - self.t_back)
        psi = jnp.pi * _minjerk((t - self.t_turn) / m.turn)
        x = jnp.clip(t / self.duration, 0.0, 1.0)
        u = m.lateral + m.wander * jnp.sin(3 * jnp.pi * x) * jnp.sin(jnp.pi * x)
        freqs, amps, phases = self._vib
        scale = self._speed_scale(t)
        vib = jnp.sum(amps * jnp.sin(2 * jnp.pi * freqs * t + phases), axis=-1) * scale
        roll, pitch_v, yaw_v, dz = vib[0], vib[1], vib[2], vib[3]
        p = self.tunnel.to_world(s, u, m.height + dz, xp=jnp)
        phi = self.tunnel.k * s
        yaw = phi + psi + yaw_v
        pitch = -jnp.arctan(cfg.slope * jnp.cos(psi)) + pitch_v
        roll = roll + jnp.arctan(cfg.slope * jnp.sin(psi))
        return _rpy_matrix(roll, pitch, yaw), p

    def _state(self, t):
        (R, p), (dR, dp) = jax.jvp(self._pose, (t,), (jnp.ones_like(t),))
        ddp = jax.jvp(
            lambda tt: jax.jvp(lambda x: self._pose(x)[1], (tt,), (jnp.ones_like(tt),))[1], (t,), (jnp.ones_like(t),)
        )[1]
        W = R.T @ dR
        omega = jnp.stack([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]]) / 2
        return R, p, dp, ddp, omega

    @functools.cached_property
    def _chunk(self) -> int:
        return 4096

    def pose(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """At times ``t`` (N,): ``R`` (N, 3, 3) world-from-body and ``p`` (N, 3) only (cheaper)."""
        R, p = self._batched(self._jit_pose, t)
        return {"R": R, "p": p}

    def state(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """At times ``t`` (N,): ``R`` (N, 3, 3) world-from-body, ``p`` (N, 3), world velocity ``v``
        and acceleration ``a`` (N, 3), body angular rate ``omega`` (N, 3)."""
        R, p, v, a, w = self._batched(self._jit_state, t)
        return {"R": R, "p": p, "v": v, "a": a, "omega": w}

    def _batched(self, fun, t: np.ndarray) -> list[np.ndarray]:
        """``fun`` over ``t`` in power-of-two padded chunks (few compiled shapes)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        n = len(t)
        size = 1 if n == 1 else self._chunk  # two compiled shapes per function
        outs = []
        for i in range(0, max(n, 1), size):
            tt = t[i : i + size]
            pad = np.pad(tt, (0, size - len(tt)), mode="edge")
            res = fun(jnp.asarray(pad))
            outs.append([np.asarray(r)[: len(tt)] for r in res])
        return [np.concatenate(x, axis=0) for x in zip(*outs)]


def _rpy_matrix(roll, pitch, yaw):
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, sr = jnp.cos(roll), jnp.sin(roll)
    cp, sp = jnp.cos(pitch), jnp.sin(pitch)
    cy, sy = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` rotation matrices -> ``(N, 4)`` unit quaternions ``wxyz`` (w >= 0)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R, axis1=-2, axis2=-1)
    cand = np.stack(
        [
            1 + tr,
            1 + R[..., 0, 0] - R[..., 1, 1] - R[..., 2, 2],
            1 - R[..., 0, 0] + R[..., 1, 1] - R[..., 2, 2],
            1 - R[..., 0, 0] - R[..., 1, 1] + R[..., 2, 2],
        ],
        axis=-1,
    )
    i = np.argmax(cand, axis=-1)
    w = np.sqrt(np.maximum(np.take_along_axis(cand, i[..., None], -1)[..., 0], 1e-300)) / 2
    f = 1 / (4 * w)
    r = R
    q0 = np.stack(
        [w, (r[..., 2, 1] - r[..., 1, 2]) * f, (r[..., 0, 2] - r[..., 2, 0]) * f, (r[..., 1, 0] - r[..., 0, 1]) * f], -1
    )
    q1 = np.stack(
        [(r[..., 2, 1] - r[..., 1, 2]) * f, w, (r[..., 0, 1] + r[..., 1, 0]) * f, (r[..., 0, 2] + r[..., 2, 0]) * f], -1
    )
    q2 = np.stack(
        [(r[..., 0, 2] - r[..., 2, 0]) * f, (r[..., 0, 1] + r[..., 1, 0]) * f, w, (r[..., 1, 2] + r[..., 2, 1]) * f], -1
    )
    q3 = np.stack(
        [(r[..., 1, 0] - r[..., 0, 1]) * f, (r[..., 0, 2] + r[..., 2, 0]) * f, (r[..., 1, 2] + r[..., 2, 1]) * f, w], -1
    )
    q = np.select([i[..., None] == k for k in range(4)], [q0, q1, q2, q3])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)
