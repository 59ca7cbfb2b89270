"""Gradients through the least-squares optimum (jaxslam.tune.DifferentiableSolver) against
central finite differences of re-solved optima, on small graphs and on a pose graph of a few
hundred poses; Gauss-Newton adjoint = exact adjoint where residuals vanish; unrolling."""

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import Cauchy, Gaussian, Pose3Var, Values
from jaxslam.errors import GraphError, SolverError
from jaxslam.factors import BetweenFactor, PriorFactor
from jaxslam.lie import SE3
from jaxslam.sim import tunnel_pose_graph
from jaxslam.tune import DifferentiableSolver, ImplicitConfig


def _graph(length, robust=False, noise_free=False, seed=1):
    g = tunnel_pose_graph(length=length, step=0.5, seed=seed)
    n = len(g.ground_truth)
    odo = ~g.is_loop
    meas = g.measured
    if noise_free:
        gt = SE3(jnp.asarray(g.ground_truth))
        meas = np.asarray((gt[g.edges_i].inverse() @ gt[g.edges_j]).params)

    def factor_fn(theta):
        shift = SE3.exp(jnp.concatenate([jnp.zeros(3), theta["prior"]])[None])
        prior = SE3(jnp.asarray(g.ground_truth[:1])).compose(shift)
        fs = [PriorFactor.create(Pose3Var(np.array([0])), prior, Gaussian.diagonal(jnp.full(6, 1e-2)))]
        for mask, key in ((odo, "odo"), (g.is_loop, "loop")):
            ls = theta[key]
            sig = jnp.concatenate([jnp.full(3, jnp.exp(ls[0])), jnp.full(3, jnp.exp(ls[1]))])
            kernel = Cauchy(theta["k"]) if (robust and key == "loop") else None
            fs.append(
                BetweenFactor.create(
                    Pose3Var(g.edges_i[mask]),
                    Pose3Var(g.edges_j[mask]),
                    SE3(jnp.asarray(meas[mask])),
                    Gaussian.diagonal(sig, n=int(mask.sum())),
                    robust=kernel,
                )
            )
        return fs

    theta0 = {
        "odo": jnp.log(jnp.array([0.004, 0.01])),
        "loop": jnp.log(jnp.array([0.01, 0.03])),
        "k": jnp.asarray(1.0),
        "prior": jnp.array([0.01, -0.02, 0.005]),
    }
    # initial values: dead reckoning along the odometry (not the ground truth)
    init = [SE3(jnp.asarray(g.ground_truth[:1]))]
    for m in meas[odo]:
        init.append(init[-1].compose(SE3(jnp.asarray(m[None]))))
    values = Values.create({Pose3Var(np.arange(n)): SE3(jnp.concatenate([x.params for x in init]))})
    target = jnp.asarray(g.ground_truth[:, 4:])

    def loss_of(x):
        p = x.params(Pose3Var)[:, 4:]
        return jnp.mean(jnp.sum((p - target) ** 2, axis=1))

    return factor_fn, values, theta0, loss_of


def _fd(ds, loss_of, theta, h=1e-5, which=None):
    flat, unravel = jax.flatten_util.ravel_pytree(theta)
    idx = range(len(flat)) if which is None else which
    out = {}
    for i in idx:
        e = np.zeros(len(flat))
        e[i] = h
        out[i] = (float(loss_of(ds.solve(unravel(flat + e)))) - float(loss_of(ds.solve(unravel(flat - e))))) / (2 * h)
    return out


def _check(grad, fd, rtol=1e-5):
    g = np.asarray(jax.flatten_util.ravel_pytree(grad)[0])
    scale = max(abs(v) for v in fd.values())
    for i, v in fd.items():
        assert abs(g[i] - v) <= rtol * scale, (i, g[i], v)


@pytest.mark.parametrize("robust", [False, True])
def test_adjoint_matches_finite_differences_small(robust):
    factor_fn, values, theta0, loss_of = _graph(20.0, robust=robust)
    ds = DifferentiableSolver(factor_fn, values, theta0)
    loss, grad = jax.value_and_grad(lambda th: loss_of(ds(th)))(theta0)
    assert np.isfinite(float(loss))
    assert ds.backward.cg_iterations >= 1 and ds.backward.cg_residual < 1e-8 and not ds.backward.fallback
    fd = _fd(DifferentiableSolver(factor_fn, values, theta0), loss_of, theta0)
    if not robust:  # the kernel scale does not enter the non-robust graph
        assert abs(float(grad["k"])) == 0.0
    _check(grad, fd)


def test_adjoint_matches_finite_differences_few_hundred_poses():
    factor_fn, values, theta0, loss_of = _graph(150.0, robust=True)  # 300 poses, loops
    ds = DifferentiableSolver(factor_fn, values, theta0)
    assert values.ids(Pose3Var).size >= 300
    grad = jax.grad(lambda th: loss_of(ds(th)))(theta0)
    fd = _fd(DifferentiableSolver(factor_fn, values, theta0), loss_of, theta0, which=[0, 1, 3, 5])
    _check(grad, fd)


def test_gauss_newton_adjoint_is_exact_without_residuals():
    factor_fn, values, theta0, loss_of = _graph(20.0, noise_free=True)
    theta0 = {**theta0, "prior": jnp.zeros(3)}
    g_exact = jax.grad(lambda th: loss_of(DifferentiableSolver(factor_fn, values, th)(th)))(theta0)
    ds = DifferentiableSolver(factor_fn, values, theta0, ImplicitConfig(adjoint="gauss-newton"))
    g_gn = jax.grad(lambda th: loss_of(ds(th)))(theta0)
    a = jax.flatten_util.ravel_pytree(g_exact)[0]
    b = jax.flatten_util.ravel_pytree(g_gn)[0]
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=1e-9 * float(jnp.max(jnp.abs(a))) + 1e-14)


def test_unrolled_gradient_approaches_implicit():
    factor_fn, values, theta0, loss_of = _graph(20.0)
    exact = jax.grad(lambda th: loss_of(DifferentiableSolver(factor_fn, values, theta0)(th)))(theta0)
    errs = []
    for steps in (1, 5):
        ds = DifferentiableSolver(factor_fn, values, theta0, ImplicitConfig(adjoint="unroll", unroll_steps=steps))
        g = jax.grad(lambda th, d=ds: loss_of(d(th)))(theta0)
        diff = jax.flatten_util.ravel_pytree(g)[0] - jax.flatten_util.ravel_pytree(exact)[0]
        errs.append(float(jnp.max(jnp.abs(diff))))
    assert errs[1] < 1e-6 * float(jnp.max(jnp.abs(jax.flatten_util.ravel_pytree(exact)[0]))) + 1e-12
    assert errs[1] < errs[0]


def test_structure_change_and_free_gauge_are_refused():
    factor_fn, values, theta0, _ = _graph(20.0)
    ds = DifferentiableSolver(factor_fn, values, theta0)
    with pytest.raises(GraphError):
        ds.problem.group_data_for(factor_fn(theta0)[1:])  # no prior: other kinds
    with pytest.raises(SolverError, match="gauge"):
        DifferentiableSolver(lambda th: factor_fn(th)[1:], values, theta0)
