"""A tiny simulated world shared by the simulator tests (short route, low resolution)."""

from __future__ import annotations

import dataclasses

import pytest

from jaxslam.sim import CameraConfig, LidarConfig, MotionConfig, SimConfig, TunnelConfig


def tiny_config(seed: int = 0, **over) -> SimConfig:
    cfg = SimConfig(
        seed=seed,
        tunnel=TunnelConfig(length=4.0, texel=0.02, margin_start=3.0, margin_end=3.0, plain=((0.5, 1.0),)),
        motion=MotionConfig(still=0.5, ramp=1.0, turn=3.0),
        camera=CameraConfig(width=96, height=64),
        lidar=LidarConfig(decimation=16),
        map_every=0,
    )
    return dataclasses.replace(cfg, **over)


@pytest.fixture(scope="session")
def tiny():
    return tiny_config()
