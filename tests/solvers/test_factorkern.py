"""The compiled between-factor linearisation (``solvers._factorkern``) against JAX's
``linearize`` of the same factor, and the incremental solver with and without it."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import Cauchy, Gaussian, Pose2Var, Pose3Var, Values, linearize
from jaxslam.factors import BetweenFactor, PriorFactor
from jaxslam.lie import SE2, SE3
from jaxslam.solvers import IncrementalConfig, IncrementalSolver, _factorkern

# rotation scales: at the identity, inside the series branch, past it, and up to near pi
SCALES = (0.0, 1e-9, 0.05, 0.19, 0.21, 1.0, 3.0)


def _poses(vtype, rng, n: int) -> np.ndarray:
    """``n`` poses per rotation scale in SCALES (rotation part of the tangent drawn at that scale)."""
    td = vtype.tangent_dim
    rot = 3 if vtype is Pose3Var else 1
    d = rng.normal(size=(len(SCALES) * n, td)) * 3.0
    d[:, :rot] *= np.repeat(SCALES, n)[:, None] / 3.0
    if vtype is Pose3Var:
        return np.asarray(SE3.exp(jnp.asarray(d)).params)
    return np.asarray(SE2.exp(jnp.asarray(d)).params)


@pytest.mark.parametrize("vtype", [Pose3Var, Pose2Var])
def test_compiled_between_matches_jax_linearize(vtype) -> None:
    rng = np.random.default_rng(3)
    group = SE3 if vtype is Pose3Var else SE2
    n = 20
    xi = _poses(vtype, rng, n)
    step = _poses(vtype, rng, n)
    xj = np.asarray(group(xi).compose(group(step)).params)
    # measurements near the true relative pose, so the error crosses the series threshold too
    z = np.asarray(group(step).compose(group(_poses(vtype, rng, n))).params)
    m = len(xi)
    td = vtype.tangent_dim
    L = np.triu(rng.normal(size=(m, td, td))) + 3.0 * np.eye(td)  # full upper-triangular sqrt information
    f = BetweenFactor.create(vtype(np.arange(m)), vtype(np.arange(m) + m), z, Gaussian(jnp.asarray(L)))
    want = linearize(f, (jnp.asarray(xi), jnp.asarray(xj)))
    kern = _factorkern.between_se3 if vtype is Pose3Var else _factorkern.between_se2
    J, r, cost = kern(xi, xj, z, L)
    Jw = np.concatenate([np.asarray(j) for j in want.jacobians], axis=2)
    scale = np.abs(Jw).max(axis=(1, 2))[:, None, None]
    np.testing.assert_allclose(J / scale, Jw / scale, rtol=0, atol=1e-12)
    rw = np.asarray(want.residual)
    np.testing.assert_allclose(r, rw, rtol=0, atol=1e-12 * np.abs(rw).max())
    np.testing.assert_allclose(cost, np.asarray(want.cost), rtol=1e-12, atol=0)
    G, b = _factorkern.gram(J, r)
    np.testing.assert_allclose(G, np.einsum("nka,nkb->nab", J, J), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(b, np.einsum("nka,nk->na", J, r), rtol=1e-13, atol=1e-13)


def _stream(solver: IncrementalSolver, robust_loop: bool) -> np.ndarray:
    """A noisy SE(3) chain of 25 poses, then two loop closures (one robust when asked), then
    optimize(); returns the final estimate."""
    rng = np.random.default_rng(11)
    n = 25
    step = SE3.exp(jnp.asarray([0.0, 0.0, 0.25, 1.0, 0.0, 0.0]))
    P = [SE3.identity()]
    for _ in range(n - 1):
        P.append(P[-1].compose(step))
    solver.update(
        [PriorFactor.create(Pose3Var(np.array([0])), np.asarray(P[0].params), Gaussian.isotropic(6, 1e-3))],
        Values.create({Pose3Var(np.array([0])): np.asarray(P[0].params)[None]}),
    )
    est = P[0]
    for i in range(1, n):
        z = P[i - 1].inverse().compose(P[i]).compose(SE3.exp(jnp.asarray(rng.normal(scale=0.02, size=6))))
        est = est.compose(z)
        solver.update(
            [
                BetweenFactor.create(
                    Pose3Var(np.array([i - 1])),
                    Pose3Var(np.array([i])),
                    np.asarray(z.params)[None],
                    Gaussian.isotropic(6, 0.05),
                )
            ],
            Values.create({Pose3Var(np.array([i])): np.asarray(est.params)[None]}),
        )
    for a, b, robust in ((n - 1, 0, None), (n - 2, 3, Cauchy(1.0) if robust_loop else None)):
        z = np.asarray(P[a].inverse().compose(P[b]).params)
        solver.update(
            [
                BetweenFactor.create(
                    Pose3Var(np.array([a])), Pose3Var(np.array([b])), z[None], Gaussian.isotropic(6, 0.01), robust
                )
            ]
        )
    mid = np.asarray(solver.estimate().params(Pose3Var))
    solver.optimize()
    return np.concatenate([mid, np.asarray(solver.estimate().params(Pose3Var))])


@pytest.mark.parametrize("engine", ["window", "bayes_tree"])
def test_solver_with_compiled_factors_equals_the_jax_path(engine: str, monkeypatch) -> None:
    """Same estimates after every kind of update with the compiled between factors as with
    every factor through JAX; a robust between factor keeps the JAX path."""
    calls = []
    kern = _factorkern.between_se3

    def spy(*args):
        calls.append(len(args[0]))
        return kern(*args)

    monkeypatch.setattr(_factorkern, "between_se3", spy)
    got = {}
    for compiled in (True, False):
        calls.clear()
        solver = IncrementalSolver(IncrementalConfig(engine=engine, compiled_factors=compiled))
        got[compiled] = _stream(solver, robust_loop=True)
        assert bool(calls) == compiled
        # the plain between factors can take the compiled kernel, the robust one cannot
        kinds = {g.compiled is not None for g in solver._group_list if g.ftype is BetweenFactor}
        assert kinds == {True, False}
    np.testing.assert_allclose(got[True], got[False], rtol=0, atol=1e-9)
