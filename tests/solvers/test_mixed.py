"""End-to-end solves over several variable types at once (6-, 3- and 6-dof blocks; points).

Noise-free measurements generated from a known state: the solver must return to that state
from perturbed initial values (cost ~0), through the same sparse machinery as pose graphs.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxslam.core import BiasVar, Gaussian, Point3Var, Pose3Var, Values, VelocityVar
from jaxslam.factors import (
    BiasRandomWalkFactor,
    ImuFactor,
    PriorFactor,
    ReprojectionFactor,
    pinhole_project,
)
from jaxslam.lie import SE3
from jaxslam.solvers import SolverConfig, Status, optimize

from ._imu_chain import imu_chain


def test_imu_chain_recovers_the_generating_states() -> None:
    rng = np.random.default_rng(3)
    n_kf = 8
    params, pim, truth_p, truth_v = imu_chain(n_kf, 40)
    ids = np.arange(n_kf)
    i, j = ids[:-1], ids[1:]
    factors = [
        ImuFactor.create(Pose3Var(i), VelocityVar(i), Pose3Var(j), VelocityVar(j), BiasVar(i), pim, params),
        BiasRandomWalkFactor.create(BiasVar(i), BiasVar(j), pim.delta_time, params),
        PriorFactor.create(Pose3Var(ids[:1]), truth_p[:1], Gaussian.isotropic(6, 1e-4)),
        PriorFactor.create(VelocityVar(ids[:1]), truth_v[:1], Gaussian.isotropic(3, 1e-3)),
        PriorFactor.create(BiasVar(ids[:1]), np.zeros((1, 6)), Gaussian.isotropic(6, 1e-3)),
    ]
    perturbed = np.asarray(SE3(jnp.asarray(truth_p)).retract(jnp.asarray(0.05 * rng.normal(size=(n_kf, 6)))).params)
    values = Values.create(
        {
            Pose3Var(ids): perturbed,
            VelocityVar(ids): truth_v + 0.1 * rng.normal(size=(n_kf, 3)),
            BiasVar(ids): 1e-3 * rng.normal(size=(n_kf, 6)),
        }
    )
    res = optimize(factors, values, SolverConfig(method="lm"), throw=True)
    assert res.status is Status.CONVERGED
    assert res.final_cost < 1e-10 * res.initial_cost
    got = res.values.get(Pose3Var(ids))
    err = np.asarray(SE3(jnp.asarray(truth_p)).local(got))
    assert np.abs(err).max() < 1e-6
    np.testing.assert_allclose(np.asarray(res.values.params(VelocityVar)), truth_v, atol=1e-6)
    np.testing.assert_allclose(np.asarray(res.values.params(BiasVar)), 0.0, atol=1e-6)


def test_bundle_adjustment_recovers_cameras_and_points() -> None:
    rng = np.random.default_rng(5)
    n_cam, n_pt = 4, 30
    cal = np.array([400.0, 400.0, 0.0, 320.0, 240.0])
    # cameras along x looking down +z (camera frame z forward), points in front of them
    cams = SE3.exp(
        jnp.asarray(
            np.column_stack(
                [0.02 * rng.normal(size=(n_cam, 3)), np.arange(n_cam) * 0.5, np.zeros(n_cam), np.zeros(n_cam)]
            )
        )
    )
    pts = np.column_stack([rng.uniform(-2, 3, n_pt), rng.uniform(-1.5, 1.5, n_pt), rng.uniform(4, 8, n_pt)])
    ci, pi = np.meshgrid(np.arange(n_cam), np.arange(n_pt), indexing="ij")
    ci, pi = ci.ravel(), pi.ravel()
    uv, front = pinhole_project(cams[ci], jnp.asarray(pts[pi]), jnp.asarray(cal))
    assert bool(np.all(front))
    factors = [
        ReprojectionFactor.create(Pose3Var(ci), Point3Var(pi), uv, cal, Gaussian.isotropic(2, 1.0)),
        # gauge (7 dof): the first camera, and the distance to the second one through a prior
        # on its position
        PriorFactor.create(Pose3Var(np.array([0])), cams[:1], Gaussian.isotropic(6, 1e-6)),
        PriorFactor.create(Point3Var(np.array([0])), pts[:1], Gaussian.isotropic(3, 1e-6)),
    ]
    init = Values.create(
        {
            Pose3Var(np.arange(n_cam)): cams.retract(jnp.asarray(0.02 * rng.normal(size=(n_cam, 6)))),
            Point3Var(np.arange(n_pt)): pts + 0.1 * rng.normal(size=pts.shape),
        }
    )
    res = optimize(factors, init, SolverConfig(method="lm"), throw=True)
    assert res.final_cost < 1e-12
    np.testing.assert_allclose(np.asarray(res.values.params(Point3Var)), pts, atol=1e-6)
    err = np.asarray(cams.local(res.values.get(Pose3Var(np.arange(n_cam)))))
    assert np.abs(err).max() < 1e-7
