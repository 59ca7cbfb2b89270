"""IMU + GPS on real KITTI data (the gtsam wheel's example data): jaxslam's IncrementalSolver
against gtsam.ISAM2 on the same stream, and the same factors scored by both libraries.

A short prefix of ``benchmarks/kitti_imu_gps.py`` (which runs the whole 469-fix stream); the
problem, the local ``GpsFactor`` and the stream logic are that file's.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from jaxslam.core import BiasVar, Pose3Var, VelocityVar, autodiff_jacobians, factor_cost  # noqa: E402

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "kitti_imu_gps.py"
_spec = importlib.util.spec_from_file_location("jaxslam_kitti_imu_gps", _PATH)
bench = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = bench  # dataclasses look their module up
_spec.loader.exec_module(bench)

pytestmark = pytest.mark.gtsam

FIXES = 60
INIT = 20


@pytest.fixture(scope="module")
def problem():
    return bench.build_problem(bench.load_kitti(), max_fixes=FIXES)


@pytest.fixture(scope="module")
def streamed(problem):
    return bench.run(problem, INIT, "own")


def test_trajectory_matches_isam2(problem, streamed):
    n = len(problem)
    ours = bench.states_from_ours(streamed["solver"].estimate(), n)
    theirs = bench.states_from_gtsam(streamed["isam"].calculateEstimate(), n)
    diff = ours[0][:, 4:7] - theirs[0][:, 4:7]
    assert bench.rms(diff) <= 0.05
    # both follow the GPS equally well (measured: 1.086 m each on this prefix)
    to_gps = [bench.rms(s[0][:, 4:7] - problem.gps) for s in (ours, theirs)]
    assert abs(to_gps[0] - to_gps[1]) <= 0.05
    assert len(streamed["lat_ours"]) == len(streamed["lat_isam"]) == n - INIT + 1


def test_final_cost_close_to_isam2(problem, streamed):
    graph = bench.full_graph(problem, INIT)
    n = len(problem)
    ours = float(graph.error(bench.states_to_gtsam(*bench.states_from_ours(streamed["solver"].estimate(), n))))
    theirs = float(graph.error(streamed["isam"].calculateEstimate()))
    assert ours <= 1.01 * theirs


def _random_states(problem, rng):
    """States near the GPS track with random attitude, velocity and bias (the factors are
    compared away from their optimum)."""
    n = len(problem)
    rot = gtsam.Rot3.Expmap
    poses = np.stack(
        [
            bench.pose_from_gtsam(gtsam.Pose3(rot(rng.normal(size=3)), problem.gps[k] + rng.normal(size=3)))
            for k in range(n)
        ]
    )
    vel = rng.normal(scale=5.0, size=(n, 3))
    bias = rng.normal(scale=[0.05] * 3 + [1e-3] * 3, size=(n, 6))
    return poses, vel, bias


def test_factor_errors_equal_gtsam(problem):
    """Every factor of the problem (priors, ImuFactor, bias random walk, GPS) has the same
    error in both libraries at the same values, 1e-8 relative."""
    rng = np.random.default_rng(3)
    states = _random_states(problem, rng)
    n = len(problem)
    ours = bench.ours_factors(problem, np.arange(n), True)
    graph = bench.gtsam_factors(problem, np.arange(n), True)
    gvals = bench.states_to_gtsam(*states)
    params = {Pose3Var: states[0], VelocityVar: states[1], BiasVar: states[2]}
    mine, kinds = [], []
    for f in ours:
        x = tuple(params[type(v)][np.asarray(v.ids)] for v in f.variables)
        mine.append(np.asarray(factor_cost(f, x)))
        kinds += [type(f).__name__] * len(f)
    mine = np.concatenate(mine)
    ref = np.array([graph.at(i).error(gvals) for i in range(graph.size())])
    # the same factors, listed in another order: match them by kind
    assert len(mine) == len(ref) == 3 + 3 * (n - 1) + 1
    g_kinds = [type(graph.at(i)).__name__ for i in range(graph.size())]
    name = {
        "PriorFactor": ("PriorFactorPose3", "PriorFactorVector", "PriorFactorConstantBias"),
        "ImuFactor": ("ImuFactor",),
        "BiasRandomWalkFactor": ("BetweenFactorConstantBias",),
        "GpsFactor": ("GPSFactor",),
    }
    for kind, gnames in name.items():
        a = mine[np.array([k == kind for k in kinds])]
        b = ref[np.array([k in gnames for k in g_kinds])]
        assert len(a) == len(b) > 0
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=0.0, err_msg=kind)


def test_gps_factor_jacobian_is_autodiff(problem):
    rng = np.random.default_rng(4)
    poses = _random_states(problem, rng)[0][:8]
    fac = bench.GpsFactor.create(Pose3Var(np.arange(8)), problem.gps[:8], bench.Gaussian.isotropic(3, bench.GPS_SIGMA))
    analytic = fac.jacobians(fac.wrap_values((poses,))[0])[0]
    auto = autodiff_jacobians(fac, (jax.numpy.asarray(poses),))[0]
    np.testing.assert_allclose(analytic, auto, atol=1e-12)
    err = np.asarray(fac.evaluate((poses,)))
    np.testing.assert_allclose(err, poses[:, 4:7] - problem.gps[:8], atol=1e-12)
