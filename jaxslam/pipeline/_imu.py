"""IMU bookkeeping for the estimator: a growing sample buffer, interval extraction (samples
held until the next, GTSAM's convention), host-side propagation for front-end predictions and
deskewing, preintegration into factors (padded to size buckets so the jitted kernel compiles a
handful of times per run), and the still-start initialisation."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..factors import PreintegratedImu, PreintegrationParams, preintegrate
from ..lie import host


class ImuBuffer:
    """Time-ordered IMU samples (append-only, capacity doubling)."""

    def __init__(self) -> None:
        self.t = np.zeros(1024)
        self.acc = np.zeros((1024, 3))
        self.gyro = np.zeros((1024, 3))
        self.n = 0

    def append(self, t: float, acc: np.ndarray, gyro: np.ndarray) -> bool:
        """Add a sample; returns False (and drops it) when it does not move time forward."""
        if self.n and t <= self.t[self.n - 1]:
            return False
        if self.n == len(self.t):
            self.t = np.concatenate([self.t, np.zeros_like(self.t)])
            self.acc = np.concatenate([self.acc, np.zeros_like(self.acc)])
            self.gyro = np.concatenate([self.gyro, np.zeros_like(self.gyro)])
        self.t[self.n], self.acc[self.n], self.gyro[self.n] = t, acc, gyro
        self.n += 1
        return True

    @property
    def last_time(self) -> float:
        return float(self.t[self.n - 1]) if self.n else -np.inf

    def interval(self, ta: float, tb: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Samples covering ``[ta, tb]``: ``(acc, gyro, dt, max_gap)``; each sample is held
        until the next one (the first from ``ta``, the last until ``tb``). ``max_gap`` is the
        longest time without a sample inside the interval (s)."""
        if self.n == 0:
            raise ValueError("no IMU samples yet")
        t = self.t[: self.n]
        i0 = max(int(np.searchsorted(t, ta, side="right")) - 1, 0)
        i1 = int(np.searchsorted(t, tb, side="left"))
        idx = np.arange(i0, max(i1, i0 + 1))
        ts = np.clip(t[idx], ta, tb)
        edges = np.append(ts, tb)
        edges[0] = ta
        dt = np.diff(edges)
        keep = dt > 0
        if not np.any(keep):  # no sample inside: hold the nearest one over the whole interval
            j = min(max(i0, 0), self.n - 1)
            return self.acc[j : j + 1].copy(), self.gyro[j : j + 1].copy(), np.array([tb - ta]), tb - ta
        return self.acc[idx][keep], self.gyro[idx][keep], dt[keep], float(dt.max())

    def mean(self, ta: float, tb: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Mean acc, mean gyro, acc std (per axis) and count of the samples with ``ta <= t < tb``."""
        t = self.t[: self.n]
        sel = (t >= ta) & (t < tb)
        a, g = self.acc[: self.n][sel], self.gyro[: self.n][sel]
        if not len(a):
            return np.zeros(3), np.zeros(3), np.full(3, np.inf), 0
        return a.mean(0), g.mean(0), a.std(0), int(sel.sum())


@dataclasses.dataclass
class NavState:
    """World-frame pose (4x4), velocity (3,) and bias (6,: acc, gyro) at time ``t``."""

    t: float
    T: np.ndarray
    v: np.ndarray
    bias: np.ndarray


def propagate(buf: ImuBuffer, state: NavState, t_end: float, gravity: np.ndarray, times: np.ndarray | None = None):
    """Integrate the IMU from ``state`` to ``t_end`` (host-side, exact for piecewise-constant
    readings in rotation, trapezoid-free Euler in velocity/position like the preintegration).
    Returns the end :class:`NavState`, and the poses (K, 4, 4) at ``times`` when given."""
    acc, gyro, dt, _ = (
        buf.interval(state.t, t_end) if t_end > state.t else (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), 0.0)
    )
    R, p, v = state.T[:3, :3].copy(), state.T[:3, 3].copy(), state.v.copy()
    ba, bg = state.bias[:3], state.bias[3:]
    out_R, out_p, stamps = [R.copy()], [p.copy()], [state.t]
    t = state.t
    dR = host.so3_exp((gyro - bg) * dt[:, None])  # all increments at once (one call, not per sample)
    for k in range(len(dt)):
        a_w = R @ (acc[k] - ba) + gravity
        p = p + v * dt[k] + 0.5 * a_w * dt[k] ** 2
        v = v + a_w * dt[k]
        R = R @ dR[k]
        t += dt[k]
        if times is not None:
            out_R.append(R.copy())
            out_p.append(p.copy())
            stamps.append(t)
    end = NavState(t_end, host.make_pose(R, p), v, state.bias.copy())
    if times is None:
        return end, None
    stamps_a = np.asarray(stamps)
    Rs, ps = np.asarray(out_R), np.asarray(out_p)
    poses = np.zeros((len(times), 4, 4))
    for i, tq in enumerate(np.asarray(times)):
        j = int(np.clip(np.searchsorted(stamps_a, tq, side="right") - 1, 0, len(stamps_a) - 1))
        if j + 1 < len(stamps_a) and stamps_a[j + 1] > stamps_a[j]:
            s = float(np.clip((tq - stamps_a[j]) / (stamps_a[j + 1] - stamps_a[j]), 0, 1))
        else:
            s = 0.0
        T0 = host.make_pose(Rs[j], ps[j])
        T1 = host.make_pose(Rs[min(j + 1, len(Rs) - 1)], ps[min(j + 1, len(ps) - 1)])
        poses[i] = host.interpolate_pose(T0, T1, np.array([s]))[0]
    return end, poses


_BUCKETS = (256, 1024, 4096)
"""Sample-count buckets: a keyframe interval (<= 1 s at 200 Hz) fits the first, so the
kernel compiles once per run; longer ones (sensor gaps) take the next."""


def preintegrate_interval(
    acc: np.ndarray, gyro: np.ndarray, dt: np.ndarray, params: PreintegrationParams, bias_hat: np.ndarray
) -> PreintegratedImu:
    """One interval preintegrated, padded to a size bucket (so the kernel compiles once per
    bucket, not once per sample count)."""
    n = len(dt)
    m = next((b for b in _BUCKETS if b >= n), None)
    if m is None:  # very long interval (a sensor gap): thin to the largest bucket by merging samples
        m = _BUCKETS[-1]
        groups = np.array_split(np.arange(n), m)
        w = [dt[g] for g in groups]
        acc = np.stack([np.average(acc[g], axis=0, weights=wi) for g, wi in zip(groups, w)])
        gyro = np.stack([np.average(gyro[g], axis=0, weights=wi) for g, wi in zip(groups, w)])
        dt = np.array([wi.sum() for wi in w])
        n = m
    A = np.zeros((1, m, 3))
    G = np.zeros((1, m, 3))
    D = np.zeros((1, m))
    A[0, :n], G[0, :n], D[0, :n] = acc, gyro, dt
    return preintegrate(A, G, D, params, bias_hat=np.asarray(bias_hat, np.float64)[None])


def gravity_alignment(mean_acc: np.ndarray) -> np.ndarray:
    """Body-to-world rotation with yaw 0 that maps the measured specific force of a still IMU
    to +z (gravity along -z)."""
    f = mean_acc / np.linalg.norm(mean_acc)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(f, z)
    s, c = np.linalg.norm(axis), float(f @ z)
    if s < 1e-12:
        R = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        R = host.so3_exp(axis / s * np.arctan2(s, c))
    # remove yaw: keep the body x axis's heading at 0
    x_w = R[:, 0]
    yaw = np.arctan2(x_w[1], x_w[0])
    return host.so3_exp(np.array([0.0, 0.0, -yaw])) @ R
