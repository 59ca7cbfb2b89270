"""The Bayes-tree engine (``IncrementalConfig(engine="bayes_tree")``): after every update its
offsets are the exact solution of the whole linear system (wildfire 0; checked against a
dense solve), also with mixed tangent sizes and after a removal; its running estimate is
gtsam.ISAM2's with the same settings; a single variable's value is brought up to date
through its path only; bad configurations and an under-constrained system raise clear
errors. The API tests shared with the window engine are in ``test_incremental.py``."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import BiasVar, Gaussian, Point3Var, Pose3Var, Values, VelocityVar
from jaxslam.errors import ConfigError, GraphError
from jaxslam.factors import (
    BetweenFactor,
    BiasRandomWalkFactor,
    ImuFactor,
    PriorFactor,
)
from jaxslam.io import read_g2o
from jaxslam.lie import SE3
from jaxslam.solvers import IncrementalConfig, IncrementalSolver, _bayestree

from ._imu_chain import imu_chain
from .test_incremental import DATA, _slice

TREE = IncrementalConfig(engine="bayes_tree", wildfire=0.0)


def _dense_offsets(solver: IncrementalSolver) -> np.ndarray:
    """The whole linear system ``H delta = -b`` from the solver's cached constraints, solved
    densely (by permanent dof)."""
    n = solver._ndof
    H = np.zeros((n, n))
    b = np.zeros(n)
    for g in solver._group_list:
        for c in np.nonzero(g.alive[: g.n])[0]:
            dofs = np.concatenate(
                [solver._store_list[si].dof[g.rows[c, k]] + np.arange(g.tds[k]) for k, si in enumerate(g.slots)]
            )
            H[np.ix_(dofs, dofs)] += g.G[c]
            b[dofs] += g.b[c]
    return np.linalg.solve(H, -b)


def _offsets(solver: IncrementalSolver) -> np.ndarray:
    out = np.zeros(solver._ndof)
    for s in solver._store_list:
        rows = np.arange(s.n)
        out[(s.dof[rows][:, None] + np.arange(s.td)).ravel()] = s.delta[rows].ravel()
    return out


def _feed(graph, solver: IncrementalSolver, k: int, vid, edges) -> None:
    vt = graph.var_type
    params = np.asarray(graph.values.params(vt))
    vals = Values({vt: np.asarray([vid])}, {vt: jnp.asarray(params[np.searchsorted(graph.vertex_ids, vid)][None])})
    if k == 0:
        facs = [PriorFactor.create(vt(np.asarray([vid])), params[0], Gaussian.isotropic(vt.tangent_dim, 1e-6))]
    else:
        facs = [_slice(graph.factors[0], edges)]
    solver.update(facs, vals)


@pytest.mark.parametrize(
    "md_max, buffers", [(256, False), (0, False), (256, True)], ids=["min_degree", "amd_or_natural", "reused_buffers"]
)
def test_offsets_are_the_exact_solution_after_every_update(
    md_max: int, buffers: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    # md_max 0: every top ordered by CHOLMOD's AMD (natural order without CHOLMOD), the path
    # of tops above 256 variables; buffers: every top's conditionals in the reused buffers
    # (the path of tops above 16 MB), two kept at most, so cliques are copied out and
    # buffers reused and dropped all along
    monkeypatch.setattr(_bayestree, "_MD_MAX", md_max)
    if buffers:
        monkeypatch.setattr(_bayestree, "_SCRATCH_MIN", 0)
        monkeypatch.setattr(_bayestree, "_BUFFERS", 2)
    graph = read_g2o(DATA / "smallGrid3D.g2o")
    solver = IncrementalSolver(TREE)
    worst = 0.0
    partial = 0
    for k, (vid, edges) in enumerate(graph.incremental_order()[:60]):
        _feed(graph, solver, k, vid, edges)
        partial += solver._tree.last_reeliminated < solver._store_list[0].n
        solver.estimate()  # brings every offset up to date
        ref = _dense_offsets(solver)
        worst = max(worst, float(np.abs(_offsets(solver) - ref).max() / max(np.abs(ref).max(), 1e-12)))
    assert worst < 1e-9, worst
    assert partial >= 20, partial  # most updates re-eliminate only a part of the tree
    if buffers:
        tree = solver._tree
        assert 1 <= len(tree._bufs) <= 2
        shared = [c for c in tree.cliques.values() if c.Ac.base is not None and c.Ac.base is tree._bufs[-1][0]]
        assert shared  # the newest cliques live in the newest buffer


def test_value_brings_one_variable_up_to_date_through_its_path() -> None:
    graph = read_g2o(DATA / "smallGrid3D.g2o")
    solver = IncrementalSolver(IncrementalConfig(engine="bayes_tree", wildfire=0.0, relinearize_skip=1000))
    order = graph.incremental_order()
    tree = solver._tree
    for k, (vid, edges) in enumerate(order):
        _feed(graph, solver, k, vid, edges)
        if k >= 30 and tree.pending:  # subtrees left to back-substitute
            break
    assert tree.pending
    ref = _dense_offsets(solver)
    s = solver._store_list[0]
    vid = int(order[0][0])  # the oldest variable: deepest in the tree
    before = len(tree.pending)
    got = solver.value(graph.var_type, vid)
    row = s.row_of[vid]
    np.testing.assert_allclose(s.delta[row], ref[s.dof[row] + np.arange(6)], rtol=0, atol=1e-9 * np.abs(ref).max())
    np.testing.assert_allclose(got, s.x[row])
    assert tree.pending or before == 0  # the rest stays pending
    est = np.asarray(solver.estimate().params(graph.var_type))
    np.testing.assert_allclose(est[np.searchsorted(np.sort(s.ids[: s.n]), vid)], got, atol=1e-12)
    assert not tree.pending


def _imu_stream(n_kf: int = 7):
    """An IMU chain (pose 6, velocity 3, bias 6 dofs): its states and factors."""
    params, pim, P, V = imu_chain(n_kf, 20)
    i, j = np.arange(n_kf - 1), np.arange(1, n_kf)
    imu = ImuFactor.create(Pose3Var(i), VelocityVar(i), Pose3Var(j), VelocityVar(j), BiasVar(i), pim, params)
    rw = BiasRandomWalkFactor.create(BiasVar(i), BiasVar(j), pim.delta_time, params)
    return P, V, imu, rw


def test_mixed_tangent_sizes_and_removal_stay_exact() -> None:
    rng = np.random.default_rng(0)
    P, V, imu, rw = _imu_stream()
    solver = IncrementalSolver(TREE)

    def vals(k: int) -> Values:
        x = np.asarray(SE3(jnp.asarray(P[k])).retract(jnp.asarray(0.01 * rng.normal(size=6))).params)
        i = np.array([k])
        return Values.create(
            {Pose3Var(i): x[None], VelocityVar(i): V[k : k + 1] + 0.05, BiasVar(i): 1e-3 * rng.normal(size=(1, 6))}
        )

    i0 = np.array([0])
    solver.update(
        [
            PriorFactor.create(Pose3Var(i0), P[:1], Gaussian.isotropic(6, 1e-3)),
            PriorFactor.create(VelocityVar(i0), V[:1], Gaussian.isotropic(3, 1e-2)),
            PriorFactor.create(BiasVar(i0), np.zeros((1, 6)), Gaussian.isotropic(6, 1e-3)),
        ],
        vals(0),
    )
    handles = []
    for k in range(len(P) - 1):
        res = solver.update([_slice(imu, np.array([k])), _slice(rw, np.array([k]))], vals(k + 1))
        handles.append(res.handles)
        solver.estimate()
        ref = _dense_offsets(solver)
        np.testing.assert_allclose(_offsets(solver), ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    assert set(solver._tree.dim[: solver._tree.nvar].tolist()) == {3, 6}  # mixed tangent sizes in one tree
    # a velocity prior late, then removed again: exact both times
    late = PriorFactor.create(VelocityVar(np.array([3])), V[3:4], Gaussian.isotropic(3, 1e-2))
    h = solver.update([late]).handles
    solver.estimate()
    np.testing.assert_allclose(_offsets(solver), _dense_offsets(solver), rtol=0, atol=1e-9)
    solver.update(remove=h)
    solver.estimate()
    ref = _dense_offsets(solver)
    np.testing.assert_allclose(_offsets(solver), ref, rtol=0, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize(
    ("cfg", "threshold", "skip"),
    [
        (IncrementalConfig(engine="bayes_tree", wildfire=0.0, relinearize_threshold=0.0, relinearize_skip=1), 0.0, 1),
        # iSAM2's default relinearisation (threshold 0.1, checked at every 10th update)
        (IncrementalConfig(engine="bayes_tree", wildfire=0.0), 0.1, 10),
        # the window engine solving the whole system at every update, with fluid
        # relinearisation: the same variables cross the threshold at the same updates
        (
            IncrementalConfig(engine="window", full_solve_every=1, relinearize_threshold=0.05, relinearize_skip=1),
            0.05,
            1,
        ),
    ],
    ids=["bayes_tree", "bayes_tree_isam2_defaults", "window_full_every_update"],
)
def test_running_estimate_is_gtsam_isam2s(cfg: IncrementalConfig, threshold: float, skip: int) -> None:
    """Relinearising the variables that moved by more than the threshold and solving exactly
    (wildfire 0), both run one Gauss-Newton step per update: the estimates agree after every
    update."""
    gtsam = pytest.importorskip("gtsam")
    from jaxslam.interop.gtsam import to_gtsam

    graph = read_g2o(DATA / "smallGrid3D.g2o")
    vt = graph.var_type
    ours = IncrementalSolver(cfg)
    p = gtsam.ISAM2Params()
    p.setRelinearizeThreshold(threshold)
    p.relinearizeSkip = skip
    gn = gtsam.ISAM2GaussNewtonParams()
    gn.setWildfireThreshold(0.0)
    p.setOptimizationParams(gn)
    isam = gtsam.ISAM2(p)
    params = np.asarray(graph.values.params(vt))
    worst = 0.0
    relin = 0
    for k, (vid, edges) in enumerate(graph.incremental_order()[:40]):
        x0 = params[np.searchsorted(graph.vertex_ids, vid)]
        vals = Values({vt: np.asarray([vid])}, {vt: jnp.asarray(x0[None])})
        if k == 0:
            facs = [PriorFactor.create(vt(np.asarray([vid])), params[0], Gaussian.isotropic(6, 1e-6))]
        else:
            facs = [_slice(graph.factors[0], edges)]
        relin += ours.update(facs, vals).relinearized
        g, v = to_gtsam(facs, vals)
        isam.update(g, v)
        est = isam.calculateEstimate()
        mine = ours.estimate()
        for i, x in zip(np.asarray(mine.ids(vt)).tolist(), np.asarray(mine.params(vt))):
            ref = est.atPose3(i)
            d = np.asarray(SE3(jnp.asarray(x)).local(SE3(jnp.asarray(_gtsam_params(ref)))))
            worst = max(worst, float(np.abs(d).max()))
    assert worst < 1e-7, worst
    assert relin > 0  # the comparison covers relinearisation


def _gtsam_params(pose) -> np.ndarray:
    q = pose.rotation().toQuaternion()
    return np.concatenate([[q.w(), q.x(), q.y(), q.z()], pose.translation()])


def test_under_constrained_raises_and_a_later_update_recovers() -> None:
    solver = IncrementalSolver(TREE)
    a, b = Point3Var(np.array([0])), Point3Var(np.array([1]))
    solver.update(
        [PriorFactor.create(a, np.zeros(3), Gaussian.isotropic(3, 1.0))], Values.create({a: np.zeros((1, 3))})
    )
    c, d = Point3Var(np.array([2])), Point3Var(np.array([3]))
    # two points tied only to each other: a gauge freedom, not a missing variable
    with pytest.raises(GraphError, match="not positive definite"):
        solver.update(
            [BetweenFactor.create(c, d, np.ones((1, 3)), Gaussian.isotropic(3, 1.0))],
            Values.create({c: np.zeros((1, 3)), d: np.zeros((1, 3))}),
        )
    solver.update(
        [PriorFactor.create(c, np.full(3, 2.0), Gaussian.isotropic(3, 0.1))], Values.create({b: np.ones((1, 3))})
    )
    est = np.asarray(solver.estimate().params(Point3Var))
    np.testing.assert_allclose(est[2], 2.0, atol=1e-9)
    np.testing.assert_allclose(est[3], 3.0, atol=1e-9)


@pytest.mark.parametrize(
    "cfg, match",
    [
        (dict(engine="bayes_tree", lag=5), "lag"),
        (dict(engine="bayes_tree", wildfire=-1.0), "wildfire"),
        (dict(engine="cholesky"), "engine"),
    ],
)
def test_bad_configurations_are_refused(cfg: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        IncrementalSolver(IncrementalConfig(**cfg))
