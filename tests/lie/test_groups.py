"""SO2, SE2, SO3, SE3: group axioms, round trips, Jacobians three ways, singular points.

Jacobians are checked three ways (STYLE 6): ``jacfwd == jacrev``; autodiff == a central
difference on the manifold; the hand-written ``jr``, ``jr_inv``, ``jl``, ``jl_inv`` and
``adjoint`` == autodiff. Singular points (STYLE 5): rotation angles exactly 0, 1e-9, 1e-5,
either side of the series threshold, near pi and exactly pi.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.lie import SE2, SE3, SO2, SO3, skew
from jaxslam.lie._utils import SERIES_ANGLE

GROUPS = [SO2, SE2, SO3, SE3]
BATCH_SHAPES = [(), (5,), (2, 3)]
ROT = {SO2: slice(0, 1), SE2: slice(0, 1), SO3: slice(0, 3), SE3: slice(0, 3)}  # in the tangent
ROT_PARAMS = {SO2: slice(0, 2), SE2: slice(0, 2), SO3: slice(0, 4), SE3: slice(0, 4)}  # in params

# Rotation angles where a closed form has a removable singularity or switches branch.
SINGULAR_ANGLES = np.array(
    [0.0, 1e-12, 1e-9, 1e-5, SERIES_ANGLE - 1e-12, SERIES_ANGLE, SERIES_ANGLE + 1e-12, 1.0, np.pi - 1e-6, np.pi]
)
BELOW_PI = np.pi - 1e-3 > SINGULAR_ANGLES  # where log is smooth enough for central differences

group_ids = [g.__name__ for g in GROUPS]
shape_ids = [str(s) for s in BATCH_SHAPES]


# --- sampling ---------------------------------------------------------------------------
def tangent_with_angles(rng: np.random.Generator, group: type, angles: np.ndarray) -> jnp.ndarray:
    """Tangents whose rotation part has the given angles (random axis / sign) and a random
    translation part, shape ``(*angles.shape, tangent_dim)``."""
    angles = np.asarray(angles, dtype=np.float64)
    t = rng.normal(size=(*angles.shape, group.tangent_dim))
    rot = ROT[group]
    if rot.stop == 1:
        t[..., 0] = angles * rng.choice([-1.0, 1.0], size=angles.shape)
    else:
        axis = rng.normal(size=(*angles.shape, 3))
        t[..., rot] = axis / np.linalg.norm(axis, axis=-1, keepdims=True) * angles[..., None]
    return jnp.asarray(t)


def random_tangent(rng: np.random.Generator, group: type, shape: tuple[int, ...]) -> jnp.ndarray:
    return tangent_with_angles(rng, group, rng.uniform(0.0, 3.0, size=shape))


def random_element(rng: np.random.Generator, group: type, shape: tuple[int, ...]):
    return group.exp(random_tangent(rng, group, shape))


def flat(x: jnp.ndarray, trailing: int = 1) -> jnp.ndarray:
    """Collapse the batch axes to one, so per-element functions can be vmapped."""
    return jnp.reshape(x, (-1, *x.shape[x.ndim - trailing :]))


def assert_same_element(a, b, atol: float = 1e-12) -> None:
    """Compare two group elements through their matrices (quaternion sign free)."""
    np.testing.assert_allclose(np.asarray(a.as_matrix()), np.asarray(b.as_matrix()), rtol=0, atol=atol)


# --- algebra ----------------------------------------------------------------------------
@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=shape_ids)
@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_exp_log_round_trip(group, shape, rng):
    t = random_tangent(rng, group, shape)
    x = group.exp(t)
    assert x.batch_shape == shape
    assert x.params.shape == (*shape, group.param_dim)
    np.testing.assert_allclose(np.asarray(x.log()), np.asarray(t), rtol=0, atol=1e-12)
    assert_same_element(group.exp(x.log()), x)


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=shape_ids)
@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_compose_inverse_identity(group, shape, rng):
    a, b, c = (random_element(rng, group, shape) for _ in range(3))
    e = group.identity(shape)
    assert e.batch_shape == shape
    assert_same_element(a @ e, a)
    assert_same_element(e @ a, a)
    assert_same_element(a @ a.inverse(), e)
    assert_same_element(a.inverse() @ a, e)
    assert_same_element((a @ b) @ c, a @ (b @ c))
    assert_same_element(a.between(b), a.inverse() @ b)
    np.testing.assert_allclose(np.asarray(a.local(a.retract(b.log()))), np.asarray(b.log()), atol=1e-12)
    ma, mb = np.asarray(a.as_matrix()), np.asarray(b.as_matrix())
    np.testing.assert_allclose(np.asarray((a @ b).as_matrix()), ma @ mb, atol=1e-12)
    np.testing.assert_allclose(np.asarray(a.inverse().as_matrix()), np.linalg.inv(ma), atol=1e-12)


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=shape_ids)
@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_act_matches_matrix_and_round_trip(group, shape, rng):
    x = random_element(rng, group, shape)
    p = rng.normal(size=(*shape, group.space_dim))
    m = np.asarray(x.as_matrix())
    assert m.shape == (*shape, group.matrix_dim, group.matrix_dim)
    if group.matrix_dim == group.space_dim:  # rotations
        expected = np.einsum("...ij,...j->...i", m, p)
    else:
        expected = np.einsum("...ij,...j->...i", m[..., :-1, :-1], p) + m[..., :-1, -1]
    np.testing.assert_allclose(np.asarray(x.act(jnp.asarray(p))), expected, atol=1e-12)
    # from_matrix(as_matrix(x)) is x (a quaternion may come back negated).
    y = group.from_matrix(jnp.asarray(m))
    assert y.batch_shape == shape
    assert_same_element(y, x)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(y.params[..., ROT_PARAMS[group]]), axis=-1), 1.0, atol=1e-14)


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=shape_ids)
@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_adjoint_identity(group, shape, rng):
    """``x @ exp(d) == exp(Ad(x) d) @ x``."""
    x = random_element(rng, group, shape)
    d = 0.7 * random_tangent(rng, group, shape)
    ad = x.adjoint()
    assert ad.shape == (*shape, group.tangent_dim, group.tangent_dim)
    ad_d = jnp.einsum("...ij,...j->...i", ad, d)
    assert_same_element(x @ group.exp(d), group.exp(ad_d) @ x, atol=1e-11)


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_normalize(group, rng):
    x = random_element(rng, group, (4,))
    rot = ROT_PARAMS[group]
    scale = rng.uniform(0.5, 2.0, size=(4, 1))
    noisy = np.asarray(x.params).copy()
    noisy[:, rot] *= scale
    y = group(jnp.asarray(noisy)).normalize()
    np.testing.assert_allclose(np.asarray(y.params), np.asarray(x.params), atol=1e-14)
    assert_same_element(y, x)


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_broadcasting_mismatched_batches(group, rng):
    a = random_element(rng, group, (2, 3))
    b = random_element(rng, group, (3,))
    c = random_element(rng, group, ())
    b_full = group(jnp.broadcast_to(b.params, (2, 3, group.param_dim)))
    c_full = group(jnp.broadcast_to(c.params, (2, 3, group.param_dim)))
    assert (a @ b).batch_shape == (2, 3)
    assert_same_element(a @ b, a @ b_full)
    assert_same_element(b @ a, b_full @ a)
    assert_same_element(c @ a, c_full @ a)
    assert_same_element(a.between(c), a.between(c_full))
    p = jnp.asarray(rng.normal(size=(2, 3, group.space_dim)))
    np.testing.assert_allclose(np.asarray(c.act(p)), np.asarray(c_full.act(p)), atol=1e-14)
    np.testing.assert_allclose(np.asarray(b.act(p)), np.asarray(b_full.act(p)), atol=1e-14)
    np.testing.assert_allclose(np.asarray(a.act(p[0, 0])), np.asarray(a.act(jnp.broadcast_to(p[0, 0], p.shape))))


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_wrong_trailing_dims_raise(group):
    with pytest.raises(ValueError, match=rf"exp expects .*\(\*batch, {group.tangent_dim}\)"):
        group.exp(jnp.zeros((4, group.tangent_dim + 1)))
    with pytest.raises(ValueError, match=r"act expects"):
        group.identity((2,)).act(jnp.zeros((2, group.space_dim + 1)))
    with pytest.raises(ValueError, match=r"from_matrix expects"):
        group.from_matrix(jnp.zeros((2, group.matrix_dim + 1, group.matrix_dim + 1)))


# --- Jacobians three ways ---------------------------------------------------------------
POINT = {2: jnp.array([0.7, -1.3]), 3: jnp.array([0.7, -1.3, 2.1])}


def _manifold_functions(group, t):
    """Functions of a perturbation ``d`` (one element, no batch), each with the Jacobian at
    ``d = 0`` that the hand-written code claims."""
    x = group.exp(t)
    y = group.exp(-0.5 * t[::-1])
    p = POINT[group.space_dim]
    m = x.as_matrix()[: group.space_dim, : group.space_dim]
    if group.space_dim == 3:
        act_rot = -m @ skew(p)  # d/dw R Exp(w) p = -R [p]x
    else:
        act_rot = (m @ jnp.array([[0.0, -1.0], [1.0, 0.0]]) @ p)[:, None]
    act_hand = act_rot if group.tangent_dim == act_rot.shape[1] else jnp.concatenate([act_rot, m], axis=1)
    return {
        # d -> Exp(t)^-1 Exp(t + d): the right Jacobian.
        "jr": (lambda d: x.local(group.exp(t + d)), group.jr(t)),
        # d -> Log(Exp(t + d) Exp(t)^-1): the left Jacobian.
        "jl": (lambda d: (group.exp(t + d) @ x.inverse()).log(), group.jl(t)),
        # d -> Log(x Exp(d)): Jr^-1(Log x).
        "jr_inv": (lambda d: x.retract(d).log(), group.jr_inv(x.log())),
        # d -> Log(Exp(d) x): Jl^-1(Log x). (At pi, Log x may be -t: use what log returns.)
        "jl_inv": (lambda d: (group.exp(d) @ x).log(), group.jl_inv(x.log())),
        # d -> local(x^-1, (x Exp(d))^-1): -Ad(x).
        "inverse": (lambda d: x.inverse().local(x.retract(d).inverse()), -x.adjoint()),
        # d -> local(x y, x Exp(d) y): Ad(y^-1).
        "compose": (lambda d: (x @ y).local(x.retract(d) @ y), y.inverse().adjoint()),
        # d -> (x Exp(d)) p: [-R [p]x, R] (3-D) / [R J p, R] (2-D).
        "act": (lambda d: x.retract(d).act(p), act_hand),
    }


def _raw_functions(group, t):
    """Functions of raw arrays (parameters or tangents) for the jacfwd == jacrev check."""
    x = group.exp(t)
    y = group.exp(-0.5 * t[::-1])
    p = POINT[group.space_dim]
    return {
        "exp": (lambda v: group.exp(v).params, t),
        "log": (lambda q: group(q).log(), x.params),
        "act": (lambda q: group(q).act(p), x.params),
        "compose": (lambda q: (group(q) @ y).params, x.params),
    }


CD_STEP = 1e-6
# jl / jl_inv are checked against the same autodiff that jr / jr_inv are checked against
# central differences with; repeating the differences only costs compile time.
NO_CD = ("jl", "jl_inv")


def _jacobian_table(group):
    """One jitted, vmapped computation of every Jacobian of one group:
    ``{name: (jacfwd, hand-written, central difference)}`` on the manifold functions and
    ``{"raw_" + name: (jacfwd, jacrev)}`` on the raw ones (the manifold functions are
    compositions of those, so jacrev is not repeated on them: it doubles compile time)."""
    n = group.tangent_dim
    zero = jnp.zeros(n)
    steps = jnp.concatenate([CD_STEP * jnp.eye(n), -CD_STEP * jnp.eye(n)])

    def one(t):
        out = {}
        for name, (fun, hand) in _manifold_functions(group, t).items():
            if name in NO_CD:
                cd = jnp.full((hand.shape[0], n), jnp.nan)
            else:
                vals = jax.vmap(fun)(steps)
                cd = ((vals[:n] - vals[n:]) / (2 * CD_STEP)).T
            out[name] = (jax.jacfwd(fun)(zero), hand, cd)
        for name, (fun, arg) in _raw_functions(group, t).items():
            out["raw_" + name] = (jax.jacfwd(fun)(arg), jax.jacrev(fun)(arg))
        return out

    return jax.vmap(one)


N_RANDOM = 4


@pytest.fixture(scope="module")
def jacobians(fast_jit):
    """``jacobians(group) -> (tangents, table)``: rows ``:N_RANDOM`` are random tangents, the
    rest the SINGULAR_ANGLES in order. Compiled once per group."""
    cache = {}

    def get(group):
        if group not in cache:
            rng = np.random.default_rng(11)
            t = jnp.concatenate(
                [random_tangent(rng, group, (N_RANDOM,)), tangent_with_angles(rng, group, SINGULAR_ANGLES)]
            )
            cache[group] = (t, jax.tree.map(np.asarray, fast_jit(_jacobian_table(group))(t)))
        return cache[group]

    return get


def _check_jacobians(table, rows, cd_rows):
    for name, val in table.items():
        assert np.all(np.isfinite(val[0][rows])), name
        if name.startswith("raw_"):
            np.testing.assert_allclose(val[0][rows], val[1][rows], rtol=0, atol=1e-12, err_msg=f"{name}: fwd vs rev")
            continue
        j_ad, j_hand, j_cd = val
        np.testing.assert_allclose(j_hand[rows], j_ad[rows], rtol=0, atol=1e-10, err_msg=f"{name}: hand vs ad")
        if name not in NO_CD:
            np.testing.assert_allclose(j_cd[cd_rows], j_ad[cd_rows], rtol=0, atol=1e-8, err_msg=f"{name}: cd vs ad")


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_jacobians_three_ways(group, jacobians):
    _, table = jacobians(group)
    rows = np.arange(N_RANDOM)
    _check_jacobians(table, rows, rows)


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_singular_jacobians(group, jacobians):
    """At every singular angle: finite, fwd == rev, hand-written == autodiff; central
    differences where the map is smooth across the stencil (log wraps at pi)."""
    _, table = jacobians(group)
    rows = N_RANDOM + np.arange(len(SINGULAR_ANGLES))
    _check_jacobians(table, rows, N_RANDOM + np.nonzero(BELOW_PI)[0])


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_handwritten_jacobians_batch_shapes(group, jacobians):
    """jr, jr_inv, jl, jl_inv and adjoint broadcast over batch axes element by element (the
    table holds them evaluated one element at a time under vmap), and jr_inv / jl_inv are
    the inverses of jr / jl."""
    t, table = jacobians(group)
    shape = (2, t.shape[0] // 2)
    tb = jnp.reshape(t, (*shape, group.tangent_dim))
    n = group.tangent_dim
    for name, f in (("jr", group.jr), ("jl", group.jl), ("compose", None)):
        if f is None:  # Ad(y^-1) with y = Exp(-t/2 reversed)
            batched = group.exp(-0.5 * tb[..., ::-1]).inverse().adjoint()
        else:
            batched = f(tb)
        assert batched.shape == (*shape, n, n)
        np.testing.assert_allclose(np.asarray(batched).reshape(-1, n, n), table[name][1], rtol=0, atol=1e-14)
    eye = np.broadcast_to(np.eye(n), (*shape, n, n))
    np.testing.assert_allclose(np.asarray(group.jr(tb) @ group.jr_inv(tb)), eye, atol=1e-12)
    np.testing.assert_allclose(np.asarray(group.jl(tb) @ group.jl_inv(tb)), eye, atol=1e-12)


# --- singular points --------------------------------------------------------------------
@pytest.fixture(scope="module")
def singular_tangents():
    rng = np.random.default_rng(3)
    return {g: tangent_with_angles(rng, g, SINGULAR_ANGLES) for g in GROUPS}


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_singular_exp_log(group, singular_tangents):
    t = singular_tangents[group]
    x = group.exp(t)
    log = np.asarray(x.log())
    assert np.all(np.isfinite(np.asarray(x.params)))
    assert np.all(np.isfinite(log))
    # log(exp(t)) == t below pi; at pi the rotation vector may come back negated.
    np.testing.assert_allclose(log[:-1], np.asarray(t[:-1]), rtol=0, atol=1e-12)
    assert_same_element(group.exp(jnp.asarray(log)), x, atol=1e-12)
    rot = ROT[group]
    np.testing.assert_allclose(np.linalg.norm(log[:, rot], axis=-1), SINGULAR_ANGLES, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_series_threshold_is_continuous(group):
    """Either side of SERIES_ANGLE the series and closed forms agree (exp, log, jr, jr_inv)."""
    below, above = (
        tangent_with_angles(np.random.default_rng(5), group, np.array([a]))[0]
        for a in (SERIES_ANGLE * (1 - 1e-13), SERIES_ANGLE * (1 + 1e-13))
    )
    funs = (lambda v: group.exp(v).params, lambda v: group.exp(v).log(), group.jr, group.jr_inv, group.jl_inv)
    for f in funs:
        np.testing.assert_allclose(np.asarray(f(below)), np.asarray(f(above)), rtol=0, atol=1e-12)


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_second_derivatives_finite_at_identity(group, fast_jit):
    """The double-where branches keep even second derivatives of exp and log finite at the
    identity (first derivatives at every singular angle are in the Jacobian table)."""
    weights_t = jnp.arange(1.0, group.tangent_dim + 1.0)
    weights_p = jnp.arange(1.0, group.param_dim + 1.0)

    def hessians(p, v):
        def log_sum(q):
            return jnp.sum(group(q).log() * weights_t)

        def exp_sum(u):
            return jnp.sum(group.exp(u).params * weights_p)

        return jax.hessian(log_sum)(p), jax.hessian(exp_sum)(v)

    for h in fast_jit(hessians)(group.identity().params, jnp.zeros(group.tangent_dim)):
        assert np.all(np.isfinite(np.asarray(h)))


def _exact_pi(group: type) -> object:
    """Elements at exactly pi, built without trigonometry (w == 0 / cos == -1 exactly)."""
    if group is SO2:
        return SO2(jnp.array([[-1.0, 0.0], [-1.0, -0.0]]))
    if group is SE2:
        return SE2(jnp.array([[-1.0, 0.0, 0.3, -2.0], [-1.0, -0.0, 1.0, 0.5]]))
    axis = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.6, -0.8, 0.0]])
    q = np.concatenate([np.zeros((3, 1)), axis], axis=-1)
    if group is SO3:
        return SO3(jnp.asarray(q))
    return SE3(jnp.asarray(np.concatenate([q, [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [-1.0, 0.5, 2.0]]], axis=-1)))


@pytest.mark.parametrize("group", GROUPS, ids=group_ids)
def test_exactly_pi(group, fast_jit):
    x = _exact_pi(group)
    log = x.log()
    assert np.all(np.isfinite(np.asarray(log)))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(log[..., ROT[group]]), axis=-1), np.pi, rtol=1e-15)
    assert_same_element(group.exp(log), x, atol=1e-12)

    # The raw Jacobian of log at w == 0 / cos == -1 is finite, and the derivative of
    # d -> Log(x Exp(d)) is Jr^-1(Log x) on the branch that log returns.
    def derivatives(p, d):
        j_raw = jax.jacfwd(lambda q: group(q).log())(p)
        j_rev = jax.jacrev(lambda q: group(q).log())(p)  # reverse mode meets 0 * inf
        dparams = jax.jacfwd(lambda e: group(p).retract(e).params)(d)
        return j_raw, j_rev, j_raw @ dparams

    zero = jnp.zeros((x.batch_shape[0], group.tangent_dim))
    j_raw, j_rev, j = fast_jit(jax.vmap(derivatives))(x.params, zero)
    assert np.all(np.isfinite(np.asarray(j_raw)))
    np.testing.assert_allclose(np.asarray(j_rev), np.asarray(j_raw), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(j), np.asarray(group.jr_inv(log)), atol=1e-10)


def test_so3_log_of_negated_quaternion(rng):
    """q and -q are the same rotation; log returns the angle in [0, pi] for both."""
    t = random_tangent(rng, SO3, (6,))
    x = SO3.exp(t)
    np.testing.assert_allclose(np.asarray(SO3(-x.params).log()), np.asarray(t), atol=1e-12)


@pytest.mark.parametrize("group", [SO3, SE3], ids=["SO3", "SE3"])
def test_log_ignores_quaternion_scale(group, singular_tangents):
    """log(s q) == log(q): both the closed form and the small-angle series use v / w."""
    x = group.exp(singular_tangents[group])
    scaled = np.asarray(x.params).copy()
    scaled[:, :4] *= np.linspace(0.5, 2.0, len(scaled))[:, None]
    np.testing.assert_allclose(np.asarray(group(jnp.asarray(scaled)).log()), np.asarray(x.log()), atol=1e-12)
