"""The scaled between factor (visual odometry with an unknown length scale): at lambda = 0 it
is the between factor (checked against GTSAM's BetweenFactorPose3); a measurement short by a
factor s is explained exactly by lambda = -log s; Jacobians three ways (analytic, autodiff,
central differences on the manifold) over a batch; and a small graph recovers the scale that
a metric constraint observes."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import Gaussian, Pose3Var, ScaleVar, Values, autodiff_jacobians, linearize
from jaxslam.factors import BetweenFactor, PriorFactor, ScaledBetweenFactor
from jaxslam.lie import SE3, host
from jaxslam.solvers import SolverConfig, optimize

from ._numeric import manifold_central_difference

N = 6


def _poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.asarray(SE3.exp(jnp.asarray(rng.normal(size=(n, 6)) * [0.5, 0.5, 0.5, 2, 2, 2])).params)


@pytest.fixture
def problem(rng):
    xi, xj = _poses(rng, N), _poses(rng, N)
    z = _poses(rng, N)
    lam = rng.normal(size=(N, 1)) * 0.05
    noise = Gaussian.diagonal(jnp.asarray([0.01, 0.02, 0.03, 0.1, 0.2, 0.3]))
    f = ScaledBetweenFactor.create(
        Pose3Var(np.arange(N)), Pose3Var(np.arange(N, 2 * N)), ScaleVar(np.arange(N)), z, noise
    )
    return f, (jnp.asarray(xi), jnp.asarray(xj), jnp.asarray(lam)), z


def test_is_the_between_factor_at_unit_scale(problem, gtsam):
    f, (xi, xj, _), z = problem
    b = BetweenFactor.create(Pose3Var(np.arange(N)), Pose3Var(np.arange(N, 2 * N)), z, f.noise)
    r = np.asarray(f.evaluate((xi, xj, jnp.zeros((N, 1)))))
    np.testing.assert_allclose(r, np.asarray(b.evaluate((xi, xj))), atol=1e-13)
    # GTSAM's BetweenFactorPose3 error vector is Local(measured, xi^-1 xj), ours too
    for k in range(N):
        P = [gtsam.Pose3(host.params_to_matrix(np.asarray(p[k]))) for p in (xi, xj, jnp.asarray(z))]
        g = gtsam.BetweenFactorPose3(0, 1, P[2], gtsam.noiseModel.Unit.Create(6))
        vals = gtsam.Values()
        vals.insert(0, P[0])
        vals.insert(1, P[1])
        np.testing.assert_allclose(g.unwhitenedError(vals), r[k], atol=1e-9)


@pytest.mark.parametrize("s", [0.99, 1.0, 1.03])
def test_a_short_measurement_is_explained_by_the_scale(s):
    T = host.se3_exp(np.array([0.02, -0.01, 0.3, 0.25, 0.02, -0.01]))
    short = T.copy()
    short[:3, 3] *= s
    f = ScaledBetweenFactor.create(
        Pose3Var(np.array([0])),
        Pose3Var(np.array([1])),
        ScaleVar(np.array([0])),
        host.matrix_to_params(short),
        Gaussian.isotropic(6, 0.01),
    )
    xi = jnp.asarray(host.matrix_to_params(np.eye(4))[None])
    xj = jnp.asarray(host.matrix_to_params(T)[None])
    np.testing.assert_allclose(np.asarray(f.evaluate((xi, xj, jnp.full((1, 1), -np.log(s))))), 0.0, atol=1e-12)
    if s != 1.0:  # and not by the unit scale
        assert np.linalg.norm(np.asarray(f.evaluate((xi, xj, jnp.zeros((1, 1)))))) > 1e-4


def test_jacobians_three_ways(problem, fast_jit):
    f, params, _ = problem
    analytic = f.jacobians(*f.wrap_values(params))
    auto = fast_jit(autodiff_jacobians)(f, params)
    for slot, (ja, jd) in enumerate(zip(analytic, auto)):
        t = type(f.variables[slot]).tangent_dim
        assert ja.shape == jd.shape == (N, 6, t)
        np.testing.assert_allclose(np.asarray(ja), np.asarray(jd), atol=1e-10, err_msg=f"slot {slot}")
        np.testing.assert_allclose(
            np.asarray(jd), manifold_central_difference(f, params, slot), atol=1e-7, err_msg=f"slot {slot}"
        )
    lin = linearize(f, params)
    for ja, jw in zip(analytic, lin.jacobians):
        np.testing.assert_allclose(np.asarray(jw), np.asarray(f.noise.sqrt_info @ ja), rtol=1e-12, atol=1e-12)


def test_a_graph_recovers_the_scale_a_metric_constraint_sees():
    """A chain of 10 steps of 0.5 m measured 2 % short, the end pinned by a metric
    constraint: the scale variable takes the 2 % and the poses stay metric."""
    steps = 10
    true = np.stack([host.make_pose(np.eye(3), np.array([0.5 * k, 0.0, 0.0])) for k in range(steps + 1)])
    z = host.make_pose(np.eye(3), np.array([0.5 * 0.98, 0.0, 0.0]))
    ids = np.arange(steps + 1)
    factors = [
        PriorFactor.create(Pose3Var(ids[:1]), host.matrix_to_params(true[0]), Gaussian.isotropic(6, 1e-4)),
        ScaledBetweenFactor.create(
            Pose3Var(ids[:-1]),
            Pose3Var(ids[1:]),
            ScaleVar(np.zeros(steps, int)),
            host.matrix_to_params(z),
            Gaussian.isotropic(6, 1e-3),
        ),
        BetweenFactor.create(
            Pose3Var(ids[:1]),
            Pose3Var(ids[-1:]),
            host.matrix_to_params(host.inverse(true[0]) @ true[-1]),
            Gaussian.isotropic(6, 1e-4),
        ),
        PriorFactor.create(ScaleVar(np.array([0])), np.zeros(1), Gaussian.isotropic(1, 0.1)),
    ]
    init = Values.create(
        {Pose3Var(ids): np.asarray(SE3.identity((steps + 1,)).params), ScaleVar(np.array([0])): np.zeros((1, 1))}
    )
    res = optimize(factors, init, SolverConfig(method="lm"))
    lam = float(np.asarray(res.values.params(ScaleVar))[0, 0])
    assert lam == pytest.approx(-np.log(0.98), abs=1e-4)
    x = host.params_to_matrix(np.asarray(res.values.params(Pose3Var)))[:, 0, 3]
    np.testing.assert_allclose(x, 0.5 * ids, atol=1e-4)


def test_bad_input():
    p = Pose3Var(np.array([0]))
    with pytest.raises(TypeError, match="ScaledBetweenFactor needs"):
        ScaledBetweenFactor.create(
            p, Pose3Var(np.array([1])), Pose3Var(np.array([2])), np.eye(4), Gaussian.isotropic(6, 1)
        )
    with pytest.raises(ValueError, match="itself"):
        ScaledBetweenFactor.create(
            p,
            Pose3Var(np.array([0])),
            ScaleVar(np.array([0])),
            host.matrix_to_params(np.eye(4)),
            Gaussian.isotropic(6, 1),
        )
    with pytest.raises(ValueError, match="ids"):
        ScaledBetweenFactor.create(
            p,
            Pose3Var(np.array([1])),
            ScaleVar(np.array([0, 1])),
            host.matrix_to_params(np.eye(4)),
            Gaussian.isotropic(6, 1),
        )
