"""IMU preintegration on real EuRoC V1_01 data: equal to GTSAM's on real windows, and a sane
prediction error against ground truth.

A short version of ``benchmarks/euroc_imu.py`` (every window of the run, three lengths).
Bounds are set from that benchmark's measurement on 1 s windows (median 0.023 m, 95 % 0.033 m,
max 0.041 m in position; max 0.31 deg; max 0.080 m/s) with about 2x margin.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "euroc_imu.py"
_spec = importlib.util.spec_from_file_location("jaxslam_euroc_imu", _PATH)
bench = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = bench  # dataclasses look their module up
_spec.loader.exec_module(bench)

if not (bench.DATA / "mav0" / "imu0" / "data.csv").exists():
    pytest.skip(f"EuRoC data not found at {bench.DATA}", allow_module_level=True)


@pytest.fixture(scope="module")
def data():
    return bench.load_euroc()


@pytest.fixture(scope="module")
def params(data):
    return bench.params_from(data["noise"])


def _predict(data, params, length, stride, limit=None):
    w = bench.windows(data, length, stride, limit)
    a = w["a"]
    pose, vel = bench.predict_ours(w, data["pose"][a], data["vel"][a], data["bias"][a], params)
    return w, pose, vel


def test_frames_are_the_body_frame(data):
    for name, t in data["extrinsics"].items():
        np.testing.assert_array_equal(np.asarray(t), np.eye(4), err_msg=name)
    # at rest (the first second) the accelerometer reads gravity rotated into the body frame
    r = bench.SO3(bench.jnp.asarray(data["pose"][:1, :4])).as_matrix()[0]
    still = np.asarray(data["acc"][:200]).mean(axis=0) - data["bias"][0, :3]
    np.testing.assert_allclose(still, np.asarray(r).T @ np.array([0.0, 0.0, bench.GRAVITY]), atol=0.05)


@pytest.mark.gtsam
def test_equals_gtsam_on_real_windows(data, params):
    pytest.importorskip("gtsam")
    gp = bench.gtsam_params(data["noise"])
    w, pose, vel = _predict(data, params, 1.0, stride=97, limit=30)
    a = w["a"]
    gpose, gvel = bench.predict_gtsam(w, data["pose"][a], data["vel"][a], data["bias"][a], gp)
    diff = bench.errors(pose, vel, gpose, gvel)
    assert diff["position"].max() <= 1e-9
    assert diff["rotation"].max() <= 1e-9
    assert diff["velocity"].max() <= 1e-9


def test_one_second_windows_against_ground_truth(data, params):
    w, pose, vel = _predict(data, params, 1.0, stride=2)
    err = bench.errors(pose, vel, data["pose"][w["b"]], data["vel"][w["b"]])
    assert len(w["a"]) > 1400
    assert np.median(err["position"]) <= 0.05
    assert np.percentile(err["position"], 95) <= 0.07
    assert err["position"].max() <= 0.1
    assert np.degrees(err["rotation"]).max() <= 0.7
    assert err["velocity"].max() <= 0.16
    # longer windows drift more (position error grows ~t^2..t^3)
    w2, pose2, vel2 = _predict(data, params, 2.0, stride=8)
    err2 = bench.errors(pose2, vel2, data["pose"][w2["b"]], data["vel"][w2["b"]])
    assert np.median(err2["position"]) > 2 * np.median(err["position"])
