"""Measurement records: what drivers (live hardware) and readers (recordings) both emit.

The estimator consumes these records and cannot tell live data from a recording. Each
record carries its timestamp ``t`` in seconds (float64, the sensor or host clock the source
documents) and numpy arrays (not JAX: records cross threads, sockets and files). Frames:
IMU readings in the IMU frame; LiDAR points in the LiDAR frame; images as recorded.

Records are immutable dataclasses; ``validate()`` raises :class:`~jaxslam.errors.InputFormatError`
naming the field when a value is malformed (NaN, wrong shape), so a source can count and skip
a bad sample instead of passing it on.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from .errors import InputFormatError


def _finite(name: str, value: np.ndarray, shape: tuple[int | None, ...], source: str) -> None:
    arr = np.asarray(value)
    if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape)):
        raise InputFormatError(f"{name} must have shape {shape}, got {arr.shape}", source)
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise InputFormatError(f"{name} contains NaN or inf", source)


@dataclasses.dataclass(frozen=True)
class ImuSample:
    """One IMU reading: specific force ``acc`` (m/s^2, 3) and angular rate ``gyro`` (rad/s, 3)."""

    t: float
    acc: np.ndarray
    gyro: np.ndarray
    kind: ClassVar[str] = "imu"

    def validate(self, source: str = "imu") -> ImuSample:
        if not np.isfinite(self.t):
            raise InputFormatError("timestamp is not finite", source)
        _finite("acc", self.acc, (3,), source)
        _finite("gyro", self.gyro, (3,), source)
        return self


@dataclasses.dataclass(frozen=True)
class Image:
    """One camera frame: ``data`` (H, W) grey or (H, W, 3) RGB, uint8 or float in [0, 1]."""

    t: float
    data: np.ndarray
    camera: str = "cam0"
    kind: ClassVar[str] = "image"

    def validate(self, source: str = "camera") -> Image:
        if not np.isfinite(self.t):
            raise InputFormatError("timestamp is not finite", source)
        d = np.asarray(self.data)
        if d.ndim not in (2, 3) or (d.ndim == 3 and d.shape[2] != 3) or d.size == 0:
            raise InputFormatError(f"image must be (H, W) or (H, W, 3) and non-empty, got {d.shape}", source)
        if d.dtype.kind == "f" and not np.all(np.isfinite(d)):
            raise InputFormatError("image contains NaN or inf", source)
        return self


@dataclasses.dataclass(frozen=True)
class LidarScan:
    """One LiDAR frame: ``points`` (N, 3) m in the LiDAR frame, ``intensity`` (N,),
    ``point_times`` (N,) s relative to ``t`` (for deskewing); ``ring`` (N,) where known."""

    t: float
    points: np.ndarray
    intensity: np.ndarray
    point_times: np.ndarray
    ring: np.ndarray | None = None
    kind: ClassVar[str] = "lidar"

    def validate(self, source: str = "lidar") -> LidarScan:
        if not np.isfinite(self.t):
            raise InputFormatError("timestamp is not finite", source)
        _finite("points", self.points, (None, 3), source)
        n = np.shape(self.points)[0]
        _finite("intensity", self.intensity, (n,), source)
        _finite("point_times", self.point_times, (n,), source)
        return self


@dataclasses.dataclass(frozen=True)
class PositionFix:
    """A surveyed position (total station prism) ``xyz`` (m, 3) with standard deviation ``sigma``."""

    t: float
    xyz: np.ndarray
    sigma: float = 0.005
    kind: ClassVar[str] = "position"

    def validate(self, source: str = "position") -> PositionFix:
        if not np.isfinite(self.t):
            raise InputFormatError("timestamp is not finite", source)
        _finite("xyz", self.xyz, (3,), source)
        if not self.sigma > 0:
            raise InputFormatError(f"sigma must be positive, got {self.sigma}", source)
        return self


@dataclasses.dataclass(frozen=True)
class PoseStamped:
    """A full 6-DoF pose (ground truth): ``pose`` as SE(3) params (qw qx qy qz x y z)."""

    t: float
    pose: np.ndarray
    kind: ClassVar[str] = "pose"

    def validate(self, source: str = "pose") -> PoseStamped:
        if not np.isfinite(self.t):
            raise InputFormatError("timestamp is not finite", source)
        _finite("pose", self.pose, (7,), source)
        return self


Measurement = ImuSample | Image | LidarScan | PositionFix | PoseStamped
