"""Incremental solver: batch optimum after optimize(), late loop closures, removal, priors,
fixed-lag marginalisation (exact on a linear problem), marginal covariances vs GTSAM."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import Cauchy, Gaussian, MarginalFactor, Point3Var, Pose3Var, Values
from jaxslam.errors import ConfigError, GraphError
from jaxslam.factors import BetweenFactor, PriorFactor
from jaxslam.io import read_g2o
from jaxslam.lie import SE3
from jaxslam.solvers import IncrementalConfig, IncrementalSolver, SolverConfig, optimize

gtsam = pytest.importorskip("gtsam")
from jaxslam.interop.gtsam import to_gtsam, values_to_gtsam  # noqa: E402

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "posegraph"


def _slice(f, idx):
    import jax

    return jax.tree_util.tree_map(lambda leaf: leaf[idx] if np.ndim(leaf) >= 1 else leaf, f)


def _replay(graph, config: IncrementalConfig | None = None, upto: int | None = None, solver=None):
    """Feed a pose graph vertex by vertex (file values as initial guesses) to ``solver`` (a
    new one with ``config`` by default); returns the solver and the factor list it received."""
    vt = graph.var_type
    solver = solver or IncrementalSolver(config)
    between = graph.factors[0]
    params = np.asarray(graph.values.params(vt))
    ids = graph.vertex_ids
    fed = []
    for k, (vid, edges) in enumerate(graph.incremental_order()[:upto]):
        vals = Values({vt: np.asarray([vid])}, {vt: jnp.asarray(params[np.searchsorted(ids, vid)][None])})
        if k == 0:
            facs = [PriorFactor.create(vt(np.asarray([vid])), params[0], Gaussian.isotropic(vt.tangent_dim, 1e-6))]
        else:
            facs = [_slice(between, edges)]
        solver.update(facs, vals)
        fed.extend(facs)
    return solver, fed


def _gtsam_error(factors, values) -> float:
    graph, _ = to_gtsam(factors, values)
    return float(graph.error(values_to_gtsam(values)))


ENGINES = ["window", "bayes_tree"]


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", ["tinyGrid3D.g2o", "smallGrid3D.g2o"])
def test_optimize_reaches_batch_optimum(name: str, engine: str) -> None:
    graph = read_g2o(DATA / name)
    solver, fed = _replay(graph, IncrementalConfig(engine=engine))
    running = _gtsam_error(fed, solver.estimate())
    solver.optimize()
    inc = _gtsam_error(fed, solver.estimate())
    batch = optimize(fed, graph.values, SolverConfig(max_iterations=200))
    ref = _gtsam_error(fed, batch.values)
    assert abs(inc - ref) <= 1e-6 * ref, (inc, ref)
    assert running >= inc - 1e-9 * ref  # the running estimate is a valid estimate, not better than the optimum


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", ["tinyGrid3D.g2o", "smallGrid3D.g2o"])
def test_refine_reaches_batch_optimum_without_the_batch_solver(name: str, engine: str) -> None:
    """refine(): Gauss-Newton with the incremental kernels ends at the batch optimum too."""
    graph = read_g2o(DATA / name)
    solver, fed = _replay(graph, IncrementalConfig(engine=engine))
    first, last, iterations = solver.refine()
    assert last <= first and iterations >= 1
    inc = _gtsam_error(fed, solver.estimate())
    ref = _gtsam_error(fed, optimize(fed, graph.values, SolverConfig(max_iterations=200)).values)
    assert abs(inc - ref) <= 1e-6 * ref, (inc, ref)
    assert last == pytest.approx(inc, rel=1e-9)  # its own cost is GTSAM's


def _chain_problem(n: int, seed: int = 0):
    """A noisy SE(3) chain with a prior on pose 0 and loop closures from the last poses back
    to the first ones (added late)."""
    rng = np.random.default_rng(seed)
    truth = [SE3.identity()]
    step = SE3.exp(jnp.asarray([0.0, 0.0, 0.3, 1.0, 0.0, 0.0]))
    for _ in range(n - 1):
        truth.append(truth[-1].compose(step))
    P = np.stack([np.asarray(t.params) for t in truth])
    noisy = lambda s: SE3.exp(jnp.asarray(rng.normal(scale=s, size=6)))  # noqa: E731
    odo = np.stack(
        [np.asarray(SE3(P[i]).inverse().compose(SE3(P[i + 1])).compose(noisy(0.02)).params) for i in range(n - 1)]
    )
    return P, odo


def _chain_solver(P, odo, n, config=None, results=None):
    """An incremental solver fed the chain pose by pose (``results`` collects each update's
    :class:`UpdateResult`)."""
    solver = IncrementalSolver(config)
    results = [] if results is None else results
    est = P[0]
    res = solver.update(
        [PriorFactor.create(Pose3Var(np.array([0])), P[0], Gaussian.isotropic(6, 1e-3))],
        Values.create({Pose3Var(np.array([0])): P[0][None]}),
    )
    results.append(res)
    for i in range(1, n):
        est = np.asarray(SE3(est).compose(SE3(odo[i - 1])).params)
        res = solver.update(
            [
                BetweenFactor.create(
                    Pose3Var(np.array([i - 1])), Pose3Var(np.array([i])), odo[i - 1][None], Gaussian.isotropic(6, 0.05)
                )
            ],
            Values.create({Pose3Var(np.array([i])): est[None]}),
        )
        results.append(res)
    return solver


@pytest.mark.parametrize("engine", ENGINES)
def test_late_loop_closure_propagates_to_old_variables(engine: str) -> None:
    n = 40
    P, odo = _chain_problem(n)
    solver = _chain_solver(P, odo, n, IncrementalConfig(engine=engine))
    before = np.asarray(solver.estimate().params(Pose3Var))
    # loop closure last -> 0 with the true relative pose: the whole chain must move
    z = np.asarray(SE3(P[-1]).inverse().compose(SE3(P[0])).params)
    loop = BetweenFactor.create(
        Pose3Var(np.array([n - 1])), Pose3Var(np.array([0])), z[None], Gaussian.isotropic(6, 1e-3)
    )
    res = solver.update([loop])
    after = np.asarray(solver.estimate().params(Pose3Var))
    moved = np.linalg.norm(after[:, 4:] - before[:, 4:], axis=1)
    assert res.relinearized >= 0 and len(res.handles) == 1
    assert moved[n // 2] > 1e-3, "the middle of the loop did not move"
    err_before = np.linalg.norm(before[-1, 4:] - P[-1, 4:])
    err_after = np.linalg.norm(after[-1, 4:] - P[-1, 4:])
    assert err_after < err_before


@pytest.mark.parametrize("engine", ENGINES)
def test_update_reports_what_it_re_eliminated_and_its_linearisation_time(engine: str) -> None:
    """``UpdateResult.reeliminated`` (iSAM2's ``variablesReeliminated``): an odometry step
    re-factorises the window's variables (``window``) or a few at the tree's root
    (``bayes_tree``), a loop closure back to the first pose the whole loop, and an update
    with nothing new nothing in the tree; ``linearize_s`` is part of ``time_s``."""
    n = 30
    P, odo = _chain_problem(n)
    cfg = IncrementalConfig(engine=engine)
    results: list = []
    solver = _chain_solver(P, odo, n, cfg, results)
    steps = [r.reeliminated for r in results]
    if engine == "window":
        assert steps == [min(k, cfg.window) + 1 for k in range(n)]
    else:
        assert steps[0] == 1 and all(1 <= r <= solver._tree.max_frontal + 1 for r in steps)
    z = np.asarray(SE3(P[-1]).inverse().compose(SE3(P[0])).params)
    loop = BetweenFactor.create(
        Pose3Var(np.array([n - 1])), Pose3Var(np.array([0])), z[None], Gaussian.isotropic(6, 1e-3)
    )
    res = solver.update([loop])
    assert res.reeliminated == n and res.full_solve
    assert 0.0 < res.linearize_s < res.time_s
    res = solver.update([])
    assert res.relinearized == 0 or engine == "window"
    if engine == "bayes_tree":  # nothing new, nothing relinearised (not a check update)
        assert res.reeliminated == 0 and res.linearize_s == 0.0
    assert all(0.0 <= r.linearize_s <= r.time_s for r in results)
    bat = _chain_solver(P[:5], odo[:4], 5, IncrementalConfig(mode="batch"))
    assert bat.update([]).reeliminated == 5


@pytest.mark.parametrize("engine", ENGINES)
def test_remove_factor_restores_previous_optimum(engine: str) -> None:
    n = 12
    P, odo = _chain_problem(n, seed=1)
    solver = _chain_solver(P, odo, n, IncrementalConfig(engine=engine))
    solver.optimize()
    ref = np.asarray(solver.estimate().params(Pose3Var))
    bad = np.asarray(
        SE3(P[-1]).inverse().compose(SE3(P[0])).compose(SE3.exp(jnp.asarray([0.3, 0, 0, 2.0, 0, 0]))).params
    )
    h = solver.update(
        [
            BetweenFactor.create(
                Pose3Var(np.array([n - 1])), Pose3Var(np.array([0])), bad[None], Gaussian.isotropic(6, 0.1)
            )
        ]
    ).handles
    moved = np.asarray(solver.estimate().params(Pose3Var))
    assert np.abs(moved - ref).max() > 1e-3
    solver.update(remove=h)
    solver.optimize()
    back = np.asarray(solver.estimate().params(Pose3Var))
    np.testing.assert_allclose(back, ref, atol=1e-7)
    with pytest.raises(GraphError, match="handle"):
        solver.update(remove=h)


@pytest.mark.parametrize("engine", ENGINES)
def test_variable_with_only_a_prior_and_update_without_new_variables(engine: str) -> None:
    solver = IncrementalSolver(IncrementalConfig(engine=engine))
    x = np.array([1.0, 2.0, 3.0])
    solver.update(
        [PriorFactor.create(Point3Var(np.array([5])), x, Gaussian.isotropic(3, 0.1))],
        Values.create({Point3Var(np.array([5])): np.zeros((1, 3))}),
    )
    np.testing.assert_allclose(np.asarray(solver.estimate().params(Point3Var))[0], x, atol=1e-12)
    # a second point, then a factor between existing points only
    solver.update([], Values.create({Point3Var(np.array([6])): np.zeros((1, 3))}))  # value only: stays put
    np.testing.assert_allclose(np.asarray(solver.estimate().params(Point3Var))[1], 0.0)
    solver.update(
        [
            BetweenFactor.create(
                Point3Var(np.array([5])), Point3Var(np.array([6])), np.array([[1.0, 0, 0]]), Gaussian.isotropic(3, 0.01)
            )
        ]
    )
    est = np.asarray(solver.estimate().params(Point3Var))
    np.testing.assert_allclose(est[1] - est[0], [1.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(est[0], x, atol=1e-3)


@pytest.mark.parametrize("engine", ENGINES)
def test_bad_input_raises_graph_errors(engine: str) -> None:
    solver = IncrementalSolver(IncrementalConfig(engine=engine))
    v = Values.create({Point3Var(np.array([0])): np.zeros((1, 3))})
    solver.update([PriorFactor.create(Point3Var(np.array([0])), np.zeros(3), Gaussian.isotropic(3, 1.0))], v)
    with pytest.raises(GraphError, match="already has a value"):
        solver.update([], v)
    with pytest.raises(GraphError, match="Point3Var 7"):
        solver.update(
            [
                BetweenFactor.create(
                    Point3Var(np.array([0])), Point3Var(np.array([7])), np.zeros((1, 3)), Gaussian.isotropic(3, 1.0)
                )
            ]
        )
    with pytest.raises(GraphError, match="not finite"):
        solver.update([], Values.create({Point3Var(np.array([3])): np.full((1, 3), np.nan)}))
    with pytest.raises(GraphError, match="Pose3Var"):
        solver.update([PriorFactor.create(Pose3Var(np.array([0])), SE3.identity().params, Gaussian.isotropic(6, 1.0))])
    with pytest.raises(GraphError, match="no Pose3Var"):
        solver.marginal_covariance(Pose3Var(np.array([0])))
    # a rejected update changes nothing: the new value of a bad update is not kept
    bad = BetweenFactor.create(
        Point3Var(np.array([0])), Point3Var(np.array([9])), np.zeros((1, 3)), Gaussian.isotropic(3, 1.0)
    )
    with pytest.raises(GraphError, match="Point3Var 9"):
        solver.update([bad], Values.create({Point3Var(np.array([8])): np.zeros((1, 3))}))
    assert list(solver.estimate().ids(Point3Var)) == [0]


def test_differing_shared_kernel_scales_are_refused_and_lose_nothing() -> None:
    """A group keeps one value per scalar leaf: a later factor of the same kind with another
    shared Cauchy scale would silently get the first one's. The update is refused before
    anything changes; per-constraint scales (arrays) are accepted."""
    solver = IncrementalSolver()
    p = [Point3Var(np.array([i])) for i in range(3)]
    vals = Values.create({p[0]: np.zeros((1, 3)), p[1]: np.ones((1, 3))})
    prior = PriorFactor.create(p[0], np.zeros(3), Gaussian.isotropic(3, 1.0))

    def between(a, b, robust):
        return BetweenFactor.create(a, b, np.ones((1, 3)), Gaussian.isotropic(3, 0.1), robust=robust)

    solver.update([prior, between(p[0], p[1], Cauchy(1.0))], vals)
    with pytest.raises(GraphError, match="differ"):
        solver.update([between(p[1], p[2], Cauchy(10.0))], Values.create({p[2]: np.ones((1, 3))}))
    assert list(solver.estimate().ids(Point3Var)) == [0, 1]
    with pytest.raises(GraphError, match="differ"):  # within one update, too
        fresh = IncrementalSolver()
        fresh.update([prior, between(p[0], p[1], Cauchy(1.0)), between(p[0], p[1], Cauchy(2.0))], vals)
    per = IncrementalSolver()
    per.update(
        [prior, between(p[0], p[1], Cauchy(np.full(1, 1.0))), between(p[0], p[1], Cauchy(np.full(1, 10.0)))], vals
    )
    assert list(per.estimate().ids(Point3Var)) == [0, 1]


def _linear_stream(n: int, seed: int = 3):
    """Points on a random walk: prior on 0, odometry, and short loop closures (span 3)."""
    rng = np.random.default_rng(seed)
    truth = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    updates = []
    for i in range(n):
        var = Point3Var(np.array([i]))
        if i == 0:
            facs = [PriorFactor.create(var, truth[0] + rng.normal(scale=0.1, size=3), Gaussian.isotropic(3, 0.1))]
        else:
            facs = [
                BetweenFactor.create(
                    Point3Var(np.array([i - 1])),
                    var,
                    (truth[i] - truth[i - 1] + rng.normal(scale=0.05, size=3))[None],
                    Gaussian.isotropic(3, 0.05),
                )
            ]
            if i >= 3:
                facs.append(
                    BetweenFactor.create(
                        Point3Var(np.array([i - 3])),
                        var,
                        (truth[i] - truth[i - 3] + rng.normal(scale=0.1, size=3))[None],
                        Gaussian.diagonal(np.array([0.1, 0.2, 0.3])),
                    )
                )
        updates.append((facs, Values.create({var: rng.normal(size=(1, 3))})))
    return updates


def test_fixed_lag_window_equals_batch_on_linear_problem() -> None:
    """Marginalisation is exact for a linear Gaussian problem: the fixed-lag smoother's window
    estimate equals the batch solution of the whole graph, and its marginal prior equals the
    Schur complement of the whole graph's information onto the window."""
    n, lag = 30, 6
    ups = _linear_stream(n)
    solver = IncrementalSolver(IncrementalConfig(lag=lag))
    every = []
    marg = 0
    for facs, vals in ups:
        marg += solver.update(facs, vals).marginalized
        every.extend(facs)
    assert marg == n - lag
    solver.optimize()
    window = np.arange(n - lag, n)
    est = solver.estimate()
    got = np.asarray(est.params(Point3Var))[window]
    all_vals = Values.create({Point3Var(np.arange(n)): np.zeros((n, 3))})
    batch = optimize(every, all_vals, SolverConfig(method="gn"))
    want = np.asarray(batch.values.params(Point3Var))[window]
    np.testing.assert_allclose(got, want, atol=1e-9)
    # information of the window: Schur complement of the full dense H vs the smoother's
    H = np.zeros((3 * n, 3 * n))
    for f in every:
        for k in range(f.num_constraints):
            R = np.asarray(f.noise.sqrt_info[k])
            ids = [int(np.asarray(v.ids)[k]) for v in f.variables]
            J = np.zeros((3, 3 * n))
            if len(ids) == 1:
                J[:, 3 * ids[0] : 3 * ids[0] + 3] = R
            else:
                J[:, 3 * ids[0] : 3 * ids[0] + 3] = -R
                J[:, 3 * ids[1] : 3 * ids[1] + 3] = R
            H += J.T @ J
    w = np.concatenate([np.arange(3 * i, 3 * i + 3) for i in window])
    o = np.setdiff1d(np.arange(3 * n), w)
    schur = H[np.ix_(w, w)] - H[np.ix_(w, o)] @ np.linalg.solve(H[np.ix_(o, o)], H[np.ix_(o, w)])
    Hs = np.zeros_like(schur)
    pos = {int(i): k for k, i in enumerate(window)}
    for g in solver._group_list:
        for c in np.nonzero(g.alive[: g.n])[0]:
            cols = np.concatenate(
                [3 * pos[int(solver._store_list[s].ids[g.rows[c, k]])] + np.arange(3) for k, s in enumerate(g.slots)]
            )
            J = g.J[c]
            Hs[np.ix_(cols, cols)] += J.T @ J
    assert any(g.ftype is MarginalFactor for g in solver._group_list)
    np.testing.assert_allclose(Hs, schur, rtol=1e-9, atol=1e-6)
    with pytest.raises(GraphError, match="marginalised"):
        solver.update([PriorFactor.create(Point3Var(np.array([0])), np.zeros(3), Gaussian.isotropic(3, 1.0))])


@pytest.mark.parametrize("engine", ENGINES)
def test_marginal_covariances_match_gtsam(engine: str) -> None:
    graph = read_g2o(DATA / "tinyGrid3D.g2o")
    solver, fed = _replay(graph, IncrementalConfig(engine=engine))
    solver.optimize()
    est = solver.estimate()
    gt_graph, _ = to_gtsam(fed, est)
    marg = gtsam.Marginals(gt_graph, values_to_gtsam(est))
    ids = graph.vertex_ids
    ours = solver.marginal_covariance(Pose3Var(ids))
    for k, i in enumerate(ids):
        ref = marg.marginalCovariance(int(i))
        np.testing.assert_allclose(ours[k], ref, rtol=0, atol=1e-8 * np.abs(ref).max())


def test_growth_within_a_bucket_does_not_recompile() -> None:
    from jaxslam.solvers._incremental import _KERNELS

    def compiled() -> int:
        return sum(k._cache_size() for k in _KERNELS.values())

    n = 40
    P, odo = _chain_problem(n, seed=2)
    cfg = IncrementalConfig(compiled_factors=False)  # the between factors through JAX too
    _chain_solver(P, odo, n, cfg)
    size = compiled()
    assert size > 0
    _chain_solver(P, odo, n, cfg)  # same bucket sizes: nothing new to compile
    assert compiled() == size


def test_batch_mode_has_the_same_api_and_is_optimal_after_every_update() -> None:
    n = 10
    P, odo = _chain_problem(n, seed=4)
    inc = _chain_solver(P, odo, n)
    bat = _chain_solver(P, odo, n, IncrementalConfig(mode="batch"))
    z = np.asarray(SE3(P[-1]).inverse().compose(SE3(P[0])).params)
    loop = BetweenFactor.create(
        Pose3Var(np.array([n - 1])), Pose3Var(np.array([0])), z[None], Gaussian.isotropic(6, 0.01)
    )
    inc.update([loop])
    res = bat.update([loop])
    assert res.full_solve
    c_bat = bat.cost()
    inc.optimize()
    assert abs(inc.cost() - c_bat) <= 1e-9 * max(c_bat, 1.0)


@pytest.mark.parametrize("vtype", ["Pose3Var", "Pose2Var", "Rot3Var", "Point3Var"])
def test_numpy_retract_matches_jaxslam_lie(vtype: str) -> None:
    import jaxslam.core as core
    from jaxslam.solvers._incremental import _np_retract

    vt = getattr(core, vtype)
    rng = np.random.default_rng(0)
    n = 64
    x = np.asarray(
        vt.retract(
            jnp.broadcast_to(jnp.asarray(vt.identity_params()), (n, vt.param_dim)), rng.normal(size=(n, vt.tangent_dim))
        )
    )
    # tangent steps from 0 through the series threshold to large angles
    d = rng.normal(size=(n, vt.tangent_dim)) * np.logspace(-9, 0.5, n)[:, None]
    got = _np_retract(vt, x, d)
    want = np.asarray(vt.retract(jnp.asarray(x), jnp.asarray(d)))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)


def _full_step(solver) -> np.ndarray:
    """The whole-graph linear step (all variables' deltas, concatenated); the solver's state
    is restored afterwards."""
    saved = [(s.delta.copy(), s.x.copy()) for s in solver._store_list]
    solver._window_solve(0, {})
    step = np.concatenate([s.delta[: s.n].ravel() for s in solver._store_list])
    for s, (d, x) in zip(solver._store_list, saved):
        s.delta[:], s.x[:] = d, x
    return step


def test_block_and_scalar_assembly_give_the_same_full_step() -> None:
    graph = read_g2o(DATA / "smallGrid3D.g2o")
    solver, _ = _replay(graph, IncrementalConfig(full_solve_every=10**6, window=3))
    steps = []
    for blockwise in (True, False):
        solver.block_assembly = blockwise
        steps.append(_full_step(solver))
    assert np.abs(steps[0]).max() > 1e-6
    np.testing.assert_allclose(steps[0], steps[1], rtol=0, atol=1e-9 * np.abs(steps[1]).max())


def _dense_blocks(B, nb: int) -> np.ndarray:
    """The symmetric matrix a BlockInformation holds, dense."""
    bs = B.bs
    H = np.zeros((nb * bs, nb * bs))
    for s in range(B.n):
        i, j = int(B.brow[s]), int(B.bcol[s])
        H[i * bs : (i + 1) * bs, j * bs : (j + 1) * bs] += B.data[s]
        if i != j:
            H[j * bs : (j + 1) * bs, i * bs : (i + 1) * bs] += B.data[s].T
    return H


def test_blocks_stay_current_and_give_the_assembled_full_step() -> None:
    """The pose-graph full step reads H from blocks updated in place (constraints added,
    relinearised, removed); they must equal a fresh sum over the live constraints, and the
    step must equal the one from assembling the system."""
    from jaxslam.solvers._blocks import BlockInformation

    graph = read_g2o(DATA / "smallGrid3D.g2o")
    solver, _ = _replay(graph, IncrementalConfig(relinearize_threshold=0.01))
    assert solver._blocks is not None
    # a factor removed after the blocks exist
    bad = BetweenFactor.create(
        Pose3Var(np.array([int(graph.vertex_ids[-1])])),
        Pose3Var(np.array([int(graph.vertex_ids[0])])),
        SE3.identity().params[None],
        Gaussian.isotropic(6, 1.0),
    )
    h = solver.update([bad]).handles
    solver.update(remove=h)
    B = solver._blocks
    fresh = BlockInformation(6)
    for g in solver._group_list:
        idx = np.nonzero(g.alive[: g.n])[0]
        var = solver._block_vars(g, idx)
        fresh.add(fresh.slots(var), var, g.G[idx])
    nb = solver._ndof // 6
    want = _dense_blocks(fresh, nb)
    np.testing.assert_allclose(_dense_blocks(B, nb), want, rtol=0, atol=1e-9 * np.abs(want).max())
    steps = []
    for off in (False, True):
        solver._blocks_off = off
        steps.append(_full_step(solver))
    solver._blocks_off = False
    assert np.abs(steps[0]).max() > 1e-8
    np.testing.assert_allclose(steps[0], steps[1], rtol=0, atol=1e-8 * np.abs(steps[1]).max())


def test_reused_symbolic_factorisation_gives_the_fresh_answer() -> None:
    """Same block pattern, new values: the second factorisation reuses the block ordering
    and CHOLMOD's analysis, and solves exactly like a freshly analysed one (and dense
    algebra)."""
    pytest.importorskip("sksparse")
    from jaxslam.solvers._blocks import BlockInformation

    rng = np.random.default_rng(7)
    nb, bs = 60, 3
    # a chain, a loop and two shortcuts, one listed with its later variable second
    pairs_ = np.array([[i + 1, i] for i in range(nb - 1)] + [[nb - 1, 0], [40, 10], [5, 33]])
    prior = np.array([[0]])

    def gram(m: int, k: int) -> np.ndarray:
        J = rng.normal(size=(m, k * bs, k * bs))
        return np.einsum("mra,mrb->mab", J, J)

    B = BlockInformation(bs)
    slots, pslots = B.slots(pairs_), B.slots(prior)
    B.add(slots, pairs_, gram(len(pairs_), 2))
    B.add(pslots, prior, gram(1, 1))
    rhs = rng.normal(size=nb * bs)
    B.factorize(nb)(rhs)
    G2, P2 = gram(len(pairs_), 2), gram(1, 1)
    B.clear()
    B.add(slots, pairs_, G2)
    B.add(pslots, prior, P2)
    x = B.factorize(nb)(rhs)
    assert B.analyses == 1  # reused
    fresh = BlockInformation(bs)
    fresh.add(fresh.slots(pairs_), pairs_, G2)
    fresh.add(fresh.slots(prior), prior, P2)
    y = fresh.factorize(nb)(rhs)
    z = np.linalg.solve(_dense_blocks(fresh, nb), rhs)
    np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * np.abs(y).max())
    np.testing.assert_allclose(y, z, rtol=0, atol=1e-8 * np.abs(z).max())


def test_block_sums_and_gathered_matrix_are_exact() -> None:
    """``BlockInformation.add`` sums repeated slots in order, bit for bit as ``np.add.at``;
    the CSC lower triangle (diagonal blocks whole) read through the pattern's map equals
    the dense permuted matrix exactly, with a variable without factors given a unit diagonal."""
    pytest.importorskip("sksparse")
    from jaxslam.solvers._blocks import BlockInformation

    rng = np.random.default_rng(3)
    nb, bs = 30, 3
    var = np.concatenate([rng.integers(0, nb - 1, size=(120, 2)), [[4, 4 + 1]] * 5, [[7, 2]] * 3])
    var = var[var[:, 0] != var[:, 1]]
    G = rng.normal(size=(len(var), 2 * bs, 2 * bs)) * 10.0 ** rng.integers(-8, 8, size=(len(var), 1, 1))
    B = BlockInformation(bs)
    slots = B.slots(var)
    assert len(np.unique(slots)) < slots.size  # repeated blocks (shared diagonals, repeated pairs)
    ref = B.data.copy()
    Gb = G.reshape(len(var), 2, bs, 2, bs)
    for m in range(len(var)):  # the reference: one block at a time, in order
        for (a, b), sl in zip([(0, 0), (0, 1), (1, 1)], slots[m]):
            blk = Gb[m, a, :, b, :] if var[m, a] >= var[m, b] else Gb[m, b, :, a, :]
            np.add.at(ref, [sl], blk[None])
    B.add(slots, var, G)
    np.testing.assert_array_equal(B.data, ref)
    B.factorize(nb)  # variable nb - 1 has no factor: it gets a diagonal block of zeros
    A = B._lower(nb).toarray()
    ip = B._symbolic[1]
    perm = (np.argsort(ip)[:, None] * bs + np.arange(bs)).ravel()  # position -> dof
    H = _dense_blocks(B, nb)[np.ix_(perm, perm)]
    blk = np.arange(nb * bs) // bs
    want = np.where(np.tril(np.ones_like(H), 0) + (blk[:, None] == blk[None, :]) > 0, H, 0.0)  # + whole diagonal blocks
    zero = np.diag(want) == 0.0
    assert zero.sum() == bs
    want[zero, zero] = 1.0
    np.testing.assert_array_equal(A, want)


def test_full_solves_skipped_without_new_information_and_loop_closure_still_propagates() -> None:
    """Odometry-only updates bring nothing a full solve could improve (the window absorbs a
    new edge exactly), so scheduled full solves are skipped; a late loop closure makes the
    next scheduled one happen and its correction reaches the middle of the chain (the
    chi^2 widening of the window is off here, so only the full solve can carry it)."""
    n, every = 40, 5
    P, odo = _chain_problem(n, seed=6)
    cfg = IncrementalConfig(full_solve_every=every, window=3, loop_chi2=np.inf)
    skip = _chain_solver(P, odo, n, cfg)
    always = _chain_solver(P, odo, n, dataclasses.replace(cfg, full_solve_tol=-1.0))
    # the first updates' windows reach back to update 0 (whole-system solves) in both
    assert skip.full_solves + (n - 4) // every - 1 <= always.full_solves, (skip.full_solves, always.full_solves)
    before = np.asarray(skip.estimate().params(Pose3Var))
    z = np.asarray(SE3(P[-1]).inverse().compose(SE3(P[0])).params)
    loop = BetweenFactor.create(
        Pose3Var(np.array([n - 1])), Pose3Var(np.array([0])), z[None], Gaussian.isotropic(6, 1e-3)
    )
    full = [skip.update([loop]).full_solve]
    always.update([loop])
    mid = np.asarray(skip.estimate().params(Pose3Var))[n // 2].copy()
    for _ in range(every):
        full.append(skip.update().full_solve)
        always.update()
    assert any(full)
    assert full[0] or not np.allclose(np.asarray(skip.estimate().params(Pose3Var))[n // 2], mid)
    after = np.asarray(skip.estimate().params(Pose3Var))
    assert np.linalg.norm(after[n // 2, 4:] - before[n // 2, 4:]) > 1e-3
    assert skip.cost() <= always.cost() * (1 + 1e-6) + 1e-9


def test_excess_bound_holds_on_a_linear_problem() -> None:
    """What a full solve could still gain (g^T H^-1 g / 2 over the whole system) never
    exceeds the solver's bound, which decides whether a scheduled full solve is skipped."""
    solver = IncrementalSolver(IncrementalConfig(full_solve_every=7))
    checked = 0
    for facs, vals in _linear_stream(50, seed=9):
        solver.update(facs, vals)
        system = solver._window_system(0, {})
        assert system is not None
        _, _, solve, grad, model = system
        gain = 0.5 * float(grad @ solve(grad))
        assert gain <= solver._excess_bound * (1 + 1e-9) + 1e-12 * max(model, 1.0), (gain, solver._excess_bound)
        checked += np.isfinite(solver._excess_bound) and solver._excess_bound > 0
    assert checked > 10


def test_chunk_sizes_change_padding_not_results() -> None:
    """Kernels padded to other row counts (one size: several chunks per batch) give the same
    estimates; a bad list of sizes is refused."""
    n = 30
    P, odo = _chain_problem(n, seed=5)
    z = np.asarray(SE3(P[-1]).inverse().compose(SE3(P[0])).params)
    loop = BetweenFactor.create(
        Pose3Var(np.array([n - 1])), Pose3Var(np.array([0])), z[None], Gaussian.isotropic(6, 1e-3)
    )
    out = []
    for sizes in ((8, 64, 512), (4,)):  # the between factors through the padded JAX kernels too
        solver = _chain_solver(P, odo, n, IncrementalConfig(chunk_sizes=sizes, compiled_factors=False))
        solver.update([loop])
        solver.optimize()
        out.append(np.asarray(solver.estimate().params(Pose3Var)))
    np.testing.assert_allclose(out[1], out[0], rtol=0, atol=1e-10)
    for bad in ((), (64, 8), (0, 8), (8, 8)):
        with pytest.raises(ConfigError, match="chunk_sizes"):
            IncrementalSolver(IncrementalConfig(chunk_sizes=bad))


def test_one_blas_thread_limits_every_blas_and_restores() -> None:
    import scipy.linalg  # noqa: F401 - its BLAS loaded
    from threadpoolctl import threadpool_info

    from jaxslam.solvers._blocks import one_blas_thread

    def counts() -> list[int]:
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    import jaxslam.solvers._blocks as blocks

    before = counts()
    with one_blas_thread():
        inside = counts()
    assert inside and all(n == 1 for n in inside)
    assert counts() == before
    # a BLAS loaded after the libraries were listed (an import since) is limited too
    blocks._BLAS_LIBS = (len(sys.modules) - 1, [])  # listed before the last import, saw none
    with one_blas_thread():
        inside = counts()
    assert inside and all(n == 1 for n in inside)
    assert counts() == before


def test_relinearize_skip_checks_only_every_kth_update() -> None:
    """iSAM2's ``relinearizeSkip``: variables are relinearised only at every k-th update
    (at others the linearisation stays, however far a variable moved), and ``optimize()``
    still reaches the batch optimum; a skip below 1 is refused."""
    graph = read_g2o(str(DATA / "smallGrid3D.g2o"))
    counts = {}
    for skip in (1, 4):
        solver = IncrementalSolver(IncrementalConfig(relinearize_skip=skip, relinearize_threshold=0.01))
        seen = []
        orig = solver.update

        def update(*a, _orig=orig, _seen=seen, _s=solver, **kw):
            k = _s.updates
            res = _orig(*a, **kw)
            _seen.append((k, res.relinearized))
            return res

        solver.update = update  # type: ignore[method-assign]
        _replay(graph, solver=solver)
        counts[skip] = seen
    # checks at the 4th, 8th, ... update (0-based 3, 7, ...), as iSAM2 counts
    off_beat = [r for k, r in counts[1] if (k + 1) % 4]
    assert sum(off_beat) > 0, "the stream never relinearises between every 4th update: the test would be empty"
    assert all(r == 0 for k, r in counts[4] if (k + 1) % 4), "relinearised at an update the skip leaves out"
    assert sum(r for _, r in counts[4]) > 0
    with pytest.raises(ConfigError, match="relinearize_skip"):
        IncrementalSolver(IncrementalConfig(relinearize_skip=0))


def test_moved_variables_constraints_found_alike_by_dict_and_by_arrays(monkeypatch) -> None:
    """A relinearisation step finds the moved variables' constraints through the adjacency
    dict (few moved) or by masking every group's rows (many): same estimates either way."""
    import jaxslam.solvers._incremental as inc

    n = 30
    P, odo = _chain_problem(n, seed=7)
    z = np.asarray(SE3(P[-1]).inverse().compose(SE3(P[0])).params)
    loop = BetweenFactor.create(
        Pose3Var(np.array([n - 1])), Pose3Var(np.array([0])), z[None], Gaussian.isotropic(6, 1e-3)
    )
    out = []
    for limit in (10**9, 0):  # every step by the dict, every step by the arrays
        monkeypatch.setattr(inc, "_ADJ_LOOP_MAX", limit)
        cfg = IncrementalConfig(engine="bayes_tree", relinearize_threshold=1e-4, relinearize_skip=1)
        results: list = []
        solver = _chain_solver(P, odo, n, cfg, results)
        results.append(solver.update([loop]))
        results.append(solver.update([]))  # the loop's correction moves many: all relinearised
        assert results[-1].relinearized > 1
        out.append((np.asarray(solver.estimate().params(Pose3Var)), [r.relinearized for r in results]))
    np.testing.assert_allclose(out[1][0], out[0][0], rtol=0, atol=1e-12)
    assert out[1][1] == out[0][1]
