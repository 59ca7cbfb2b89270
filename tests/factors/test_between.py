"""Prior and between factors on Pose3Var, Pose2Var, Rot3Var and Point3Var.

Against GTSAM (golden values at test time): the unwhitened residual equals
``unwhitenedError`` and the cost equals ``error()`` (= ½‖R r‖², or rho(‖R r‖) with a robust
model). Pose2 residuals are permuted: ours ``[theta, x, y]``, GTSAM's ``[x, y, theta]``.
Jacobians three ways: analytic == autodiff (``autodiff_jacobians``) == central differences
on the manifold.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import (
    Gaussian,
    Huber,
    Point3Var,
    Pose2Var,
    Pose3Var,
    Rot3Var,
    autodiff_jacobians,
    factor_cost,
    linearize,
)
from jaxslam.factors import BetweenFactor, PriorFactor
from jaxslam.lie import SE2, SE3, SO3

from ._numeric import manifold_central_difference

N = 5
VAR_TYPES = [Pose3Var, Pose2Var, Rot3Var, Point3Var]
GTSAM_NAME = {Pose3Var: "Pose3", Pose2Var: "Pose2", Rot3Var: "Rot3", Point3Var: "Point3"}
IDS = [GTSAM_NAME[v] for v in VAR_TYPES]
# GTSAM Pose2 [x, y, theta] -> ours [theta, x, y]: ours = gtsam[PERM].
PERM = {Pose2Var: np.array([2, 0, 1])}


def _perm(vtype) -> np.ndarray:
    return PERM.get(vtype, np.arange(vtype.tangent_dim))


def random_params(rng: np.random.Generator, vtype, n: int, scale: float = 1.0) -> np.ndarray:
    if vtype.group is None:
        return rng.normal(size=(n, vtype.param_dim)) * 3.0 * scale
    t = rng.normal(size=(n, vtype.tangent_dim)) * scale
    return np.asarray(vtype.group.exp(jnp.asarray(t)).params)


def to_gtsam(gtsam, vtype, row: np.ndarray):
    row = np.asarray(row, dtype=np.float64)
    if vtype is Pose3Var:
        return gtsam.Pose3(gtsam.Rot3.Quaternion(*row[:4]), row[4:])
    if vtype is Pose2Var:
        return gtsam.Pose2(row[2], row[3], np.arctan2(row[1], row[0]))
    if vtype is Rot3Var:
        return gtsam.Rot3.Quaternion(*row)
    return row


def relative(vtype, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Parameters of ``a^-1 b`` (``b - a`` for points)."""
    if vtype.group is None:
        return b - a
    g = vtype.group
    return np.asarray(g(jnp.asarray(a)).between(g(jnp.asarray(b))).params)


def spd_covariances(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    a = rng.normal(size=(n, dim, dim)) * 0.1
    return a @ np.swapaxes(a, -1, -2) + 0.05 * np.eye(dim)


@pytest.fixture(scope="module")
def problems():
    """Per variable type: a between factor and a prior factor on random values, with
    measurements near the truth (one constraint exact, so its residual is 0)."""
    rng = np.random.default_rng(99)
    out = {}
    for vtype in VAR_TYPES:
        n_dim = vtype.tangent_dim
        xi, xj = random_params(rng, vtype, N), random_params(rng, vtype, N)
        noise_b = rng.normal(size=(N, n_dim)) * 0.3
        noise_b[0] = 0.0
        meas_b = np.asarray(vtype.retract(jnp.asarray(relative(vtype, xi, xj)), jnp.asarray(noise_b)))
        noise_p = rng.normal(size=(N, n_dim)) * 0.3
        noise_p[0] = 0.0
        meas_p = np.asarray(vtype.retract(jnp.asarray(xi), jnp.asarray(noise_p)))
        # Covariances in GTSAM's tangent order, and the same model in ours.
        cov_g = spd_covariances(rng, N, n_dim)
        p = _perm(vtype)
        cov_ours = cov_g[:, p][:, :, p]
        ids_i, ids_j = np.arange(N), np.arange(N, 2 * N)
        between = BetweenFactor.create(vtype(ids_i), vtype(ids_j), meas_b, Gaussian.from_covariance(cov_ours))
        prior = PriorFactor.create(vtype(ids_i), meas_p, Gaussian.from_covariance(cov_ours))
        out[vtype] = {
            "xi": xi,
            "xj": xj,
            "meas_b": meas_b,
            "meas_p": meas_p,
            "cov_g": cov_g,
            "between": between,
            "prior": prior,
        }
    return out


def _gtsam_factors(gtsam, vtype, prob, robust=None):
    """GTSAM between and prior factors for each constraint, and one Values holding all."""
    name = GTSAM_NAME[vtype]
    values = gtsam.Values()
    betweens, priors = [], []
    for k in range(N):
        values.insert(k, to_gtsam(gtsam, vtype, prob["xi"][k]))
        values.insert(N + k, to_gtsam(gtsam, vtype, prob["xj"][k]))
        model = gtsam.noiseModel.Gaussian.Covariance(prob["cov_g"][k])
        if robust is not None:
            model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust), model)
        meas_b = to_gtsam(gtsam, vtype, prob["meas_b"][k])
        meas_p = to_gtsam(gtsam, vtype, prob["meas_p"][k])
        betweens.append(getattr(gtsam, f"BetweenFactor{name}")(k, N + k, meas_b, model))
        priors.append(getattr(gtsam, f"PriorFactor{name}")(k, meas_p, model))
    return betweens, priors, values


def _params(prob, kind: str) -> tuple:
    xi, xj = jnp.asarray(prob["xi"]), jnp.asarray(prob["xj"])
    return (xi, xj) if kind == "between" else (xi,)


@pytest.mark.gtsam
@pytest.mark.parametrize("vtype", VAR_TYPES, ids=IDS)
def test_residual_and_cost_vs_gtsam(gtsam, vtype, problems):
    prob = problems[vtype]
    betweens, priors, values = _gtsam_factors(gtsam, vtype, prob)
    p = _perm(vtype)
    for kind, gfactors in (("between", betweens), ("prior", priors)):
        factor = prob[kind]
        params = _params(prob, kind)
        r = np.asarray(factor.evaluate(params))
        cost = np.asarray(factor_cost(factor, params))
        assert r.shape == (N, vtype.tangent_dim)
        np.testing.assert_allclose(r[0], 0.0, atol=1e-12)
        for k, gf in enumerate(gfactors):
            expected = np.asarray(gf.unwhitenedError(values))[p]
            np.testing.assert_allclose(r[k], expected, rtol=0, atol=1e-12, err_msg=f"{kind} {k}")
            assert cost[k] == pytest.approx(gf.error(values), rel=1e-10, abs=1e-20), f"{kind} {k}"


@pytest.mark.gtsam
@pytest.mark.parametrize("vtype", [Pose3Var, Pose2Var], ids=["Pose3", "Pose2"])
def test_robust_cost_vs_gtsam(gtsam, vtype, problems):
    prob = problems[vtype]
    betweens, priors, values = _gtsam_factors(gtsam, vtype, prob, robust=0.8)
    for kind, gfactors in (("between", betweens), ("prior", priors)):
        factor = prob[kind].with_robust(Huber(0.8))
        cost = np.asarray(factor_cost(factor, _params(prob, kind)))
        expected = [gf.error(values) for gf in gfactors]
        np.testing.assert_allclose(cost, expected, rtol=1e-10, atol=1e-20, err_msg=kind)


@pytest.mark.parametrize("kind", ["between", "prior"])
@pytest.mark.parametrize("vtype", VAR_TYPES, ids=IDS)
def test_jacobians_three_ways(vtype, kind, problems, fast_jit):
    prob = problems[vtype]
    factor = prob[kind]
    params = _params(prob, kind)
    analytic = factor.jacobians(*factor.wrap_values(params))
    auto = fast_jit(autodiff_jacobians)(factor, params)
    assert len(analytic) == len(auto) == len(params)
    for slot, (ja, jd) in enumerate(zip(analytic, auto)):
        t = type(factor.variables[slot]).tangent_dim
        assert ja.shape == jd.shape == (N, vtype.tangent_dim, t)
        np.testing.assert_allclose(np.asarray(ja), np.asarray(jd), rtol=0, atol=1e-10, err_msg=f"slot {slot}")
        cd = manifold_central_difference(factor, params, slot)
        np.testing.assert_allclose(np.asarray(jd), cd, rtol=0, atol=1e-7, err_msg=f"slot {slot}")
    # linearize whitens the analytic Jacobians with R.
    lin = linearize(factor, params)
    r = factor.noise.sqrt_info
    for ja, jw in zip(analytic, lin.jacobians):
        np.testing.assert_allclose(np.asarray(jw), np.asarray(r @ ja), rtol=1e-12, atol=1e-12)


def test_between_of_chain_is_consistent():
    """Between factors on an exact odometry chain have zero residual and cost."""
    rng = np.random.default_rng(1)
    poses = SE3.exp(jnp.asarray(rng.normal(size=(6, 6))))
    rel = poses[:-1].between(poses[1:])
    f = BetweenFactor.create(Pose3Var(np.arange(5)), Pose3Var(np.arange(1, 6)), rel, Gaussian.isotropic(6, 0.1))
    params = (poses.params[:-1], poses.params[1:])
    np.testing.assert_allclose(np.asarray(f.evaluate(params)), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(factor_cost(f, params)), 0.0, atol=1e-20)
    # A shared measurement broadcasts to every constraint; so does a single noise model.
    g = PriorFactor.create(Pose2Var(np.arange(3)), SE2.identity(), Gaussian.diagonal(np.array([0.1, 1.0, 1.0])))
    assert g.measured.shape == (3, 4)
    assert g.noise.sqrt_info.shape == (3, 3, 3)
    h = PriorFactor.create(Rot3Var(np.arange(2)), SO3.identity((2,)), Gaussian.isotropic(3, 1.0))
    assert len(h) == 2


def test_bad_input_raises():
    noise6 = Gaussian.isotropic(6, 1.0)
    two = SE3.identity((2,))
    with pytest.raises(ValueError, match="Pose3Var 1 to itself"):
        BetweenFactor.create(Pose3Var(np.array([0, 1])), Pose3Var(np.array([2, 1])), two, noise6)
    with pytest.raises(ValueError, match="2 ids for x_i but 3 for x_j"):
        BetweenFactor.create(Pose3Var(np.array([0, 1])), Pose3Var(np.array([2, 3, 4])), two, noise6)
    with pytest.raises(ValueError, match="noise model has dimension 3, the residual has 6"):
        BetweenFactor.create(Pose3Var(np.array([0, 1])), Pose3Var(np.array([2, 3])), two, Gaussian.isotropic(3, 1.0))
    with pytest.raises(ValueError, match="noise model has dimension 6, the residual has 3"):
        PriorFactor.create(Point3Var(np.array([0])), np.zeros(3), noise6)
    with pytest.raises(ValueError, match="noise model holds 3 matrices for 2 constraints"):
        PriorFactor.create(Pose3Var(np.array([0, 1])), two, noise6.broadcast(3))
    with pytest.raises(ValueError, match=r"must have shape \(2, 7\), got \(3, 7\)"):
        PriorFactor.create(Pose3Var(np.array([0, 1])), SE3.identity((3,)), noise6)
    with pytest.raises(ValueError, match=r"must have shape \(1, 3\)"):
        PriorFactor.create(Point3Var(np.array([0])), np.zeros(2), Gaussian.isotropic(3, 1.0))
    with pytest.raises(TypeError, match="one variable type"):
        BetweenFactor.create(Pose3Var(np.array([0])), Rot3Var(np.array([1])), SE3.identity((1,)), noise6)
