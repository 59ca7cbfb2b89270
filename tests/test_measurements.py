"""Measurement records validate their fields and name what is wrong."""

from __future__ import annotations

import numpy as np
import pytest

from jaxslam.errors import InputFormatError
from jaxslam.measurements import Image, ImuSample, LidarScan, PoseStamped, PositionFix


def test_valid_records_pass() -> None:
    ImuSample(1.0, np.zeros(3), np.ones(3)).validate()
    Image(1.0, np.zeros((4, 5), np.uint8)).validate()
    LidarScan(1.0, np.zeros((10, 3)), np.zeros(10), np.linspace(0, 0.1, 10)).validate()
    PositionFix(1.0, np.zeros(3)).validate()
    PoseStamped(1.0, np.array([1.0, 0, 0, 0, 0, 0, 0])).validate()


@pytest.mark.parametrize(
    ("record", "needle"),
    [
        (ImuSample(float("nan"), np.zeros(3), np.zeros(3)), "timestamp"),
        (ImuSample(0.0, np.array([np.nan, 0, 0]), np.zeros(3)), "acc"),
        (ImuSample(0.0, np.zeros(3), np.zeros(4)), "gyro"),
        (Image(0.0, np.zeros((0, 0))), "non-empty"),
        (Image(0.0, np.full((2, 2), np.nan)), "NaN"),
        (LidarScan(0.0, np.zeros((5, 3)), np.zeros(4), np.zeros(5)), "intensity"),
        (PositionFix(0.0, np.zeros(3), sigma=0.0), "sigma"),
        (PoseStamped(0.0, np.zeros(6)), "pose"),
    ],
)
def test_bad_records_name_the_field(record: object, needle: str) -> None:
    with pytest.raises(InputFormatError, match=needle):
        record.validate()  # type: ignore[attr-defined]
