"""Noise models, robust kernels and Values, against GTSAM where it has the same thing.

GTSAM conventions checked here: a Gaussian model holds an upper-triangular ``R`` with
``R^T R = Sigma^-1`` and whitens ``R r``; a factor's error is ``rho(||R r||)`` with
``rho(x) = x^2 / 2`` for plain least squares; a robust model scales the whitened system by
``sqrt(w(||R r||))``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from jax import Array

from jaxslam.core import (
    KERNELS,
    Cauchy,
    Factor,
    Gaussian,
    GemanMcClure,
    Huber,
    Point3Var,
    Pose3Var,
    Values,
    factor_dataclass,
    information_is_valid,
    whiten_and_weight,
)
from jaxslam.errors import GraphError
from jaxslam.lie import SE3

TOL = 1e-12


def _spd(rng: np.random.Generator, dim: int) -> np.ndarray:
    a = rng.normal(size=(dim, dim))
    return a @ a.T + dim * np.eye(dim)


# --- Gaussian models --------------------------------------------------------------------
def _check_against(gtsam_model, ours: Gaussian, rng: np.random.Generator, k: int = 0) -> None:
    dim = ours.dim
    np.testing.assert_allclose(np.asarray(ours.sqrt_info[k]), gtsam_model.R(), rtol=0, atol=TOL)
    info = np.asarray(ours.sqrt_info[k]).T @ np.asarray(ours.sqrt_info[k])
    np.testing.assert_allclose(info, gtsam_model.information(), rtol=1e-12, atol=TOL)
    np.testing.assert_allclose(np.asarray(ours.covariance()[k]), gtsam_model.covariance(), rtol=1e-12, atol=TOL)
    r = rng.normal(size=(len(ours), dim))
    white = np.asarray(ours.whiten(jnp.asarray(r)))
    np.testing.assert_allclose(white[k], gtsam_model.whiten(r[k]), rtol=0, atol=TOL)
    jac = rng.normal(size=(len(ours), dim, 4))
    np.testing.assert_allclose(
        np.asarray(ours.whiten_jacobian(jnp.asarray(jac)))[k], gtsam_model.R() @ jac[k], rtol=0, atol=TOL
    )


@pytest.mark.gtsam
def test_isotropic(gtsam, rng):
    ours = Gaussian.isotropic(3, 0.25, n=4)
    assert ours.sqrt_info.shape == (4, 3, 3)
    for k in range(4):
        _check_against(gtsam.noiseModel.Isotropic.Sigma(3, 0.25), ours, rng, k)
    # One sigma per constraint.
    sigmas = np.array([0.1, 0.5, 2.0])
    per = Gaussian.isotropic(2, jnp.asarray(sigmas), n=3)
    for k, s in enumerate(sigmas):
        _check_against(gtsam.noiseModel.Isotropic.Sigma(2, s), per, rng, k)


@pytest.mark.gtsam
def test_diagonal(gtsam, rng):
    sigmas = np.array([0.1, 0.2, 0.3, 1.0, 2.0, 3.0])
    shared = Gaussian.diagonal(sigmas, n=3)
    assert shared.sqrt_info.shape == (3, 6, 6)
    _check_against(gtsam.noiseModel.Diagonal.Sigmas(sigmas), shared, rng, 2)
    per = rng.uniform(0.1, 2.0, size=(4, 3))
    ours = Gaussian.diagonal(per)
    for k in range(4):
        _check_against(gtsam.noiseModel.Diagonal.Sigmas(per[k]), ours, rng, k)


@pytest.mark.gtsam
def test_from_covariance_information_sqrt_information(gtsam, rng):
    covs = np.stack([_spd(rng, 6) * 0.1 for _ in range(3)])
    ours = Gaussian.from_covariance(covs)
    for k in range(3):
        _check_against(gtsam.noiseModel.Gaussian.Covariance(covs[k]), ours, rng, k)
    info = _spd(rng, 3)
    ours_info = Gaussian.from_information(info, n=2)
    assert ours_info.sqrt_info.shape == (2, 3, 3)
    _check_against(gtsam.noiseModel.Gaussian.Information(info), ours_info, rng, 1)
    r_upper = np.triu(rng.normal(size=(3, 3))) + 3 * np.eye(3)
    ours_r = Gaussian.from_sqrt_information(r_upper)
    _check_against(gtsam.noiseModel.Gaussian.SqrtInformation(r_upper), ours_r, rng, 0)


def test_broadcast_and_validity():
    g = Gaussian.isotropic(3, 1.0)
    assert len(g) == 1
    assert g.broadcast(5).sqrt_info.shape == (5, 3, 3)
    good = np.eye(3)[None].repeat(3, axis=0)
    good[1, 0, 1] = good[1, 1, 0] = 0.5
    bad = good.copy()
    bad[0, 0, 0] = -1.0  # not positive definite
    bad[2, 0, 1] = 0.3  # not symmetric
    nan = np.full((1, 3, 3), np.nan)
    np.testing.assert_array_equal(information_is_valid(good), [True, True, True])
    np.testing.assert_array_equal(information_is_valid(bad), [False, True, False])
    np.testing.assert_array_equal(information_is_valid(nan), [False])


# --- robust kernels ---------------------------------------------------------------------
RESIDUALS = np.concatenate([np.linspace(-8.0, 8.0, 41), [0.0, 1e-8, 0.999, 1.0, 1.001, 1.345, 4.685, 30.0]])
KERNEL_CASES = [("huber", "Huber", 1.345), ("cauchy", "Cauchy", 0.7), ("geman-mcclure", "GemanMcClure", 1.5)]
KERNEL_CASES += [("tukey", "Tukey", 4.685), ("huber", "Huber", 1.0), ("tukey", "Tukey", 1.0)]


@pytest.mark.gtsam
@pytest.mark.parametrize(("name", "gtsam_name", "k"), KERNEL_CASES)
def test_kernel_loss_and_weight(gtsam, name, gtsam_name, k):
    ours = KERNELS[name](k)
    theirs = getattr(gtsam.noiseModel.mEstimator, gtsam_name).Create(k)
    loss = np.asarray(ours.loss(jnp.asarray(RESIDUALS)))
    weight = np.asarray(ours.weight(jnp.asarray(RESIDUALS)))
    for x, lo, w in zip(RESIDUALS, loss, weight):
        assert lo == pytest.approx(theirs.loss(x), rel=1e-13, abs=1e-15), f"{name} loss at {x}"
        assert w == pytest.approx(theirs.weight(x), rel=1e-13, abs=1e-15), f"{name} weight at {x}"
    # Near 0 every kernel is least squares: rho(x) ~ x^2 / 2, w(0) = 1.
    assert float(ours.weight(jnp.asarray(0.0))) == 1.0
    assert float(ours.loss(jnp.asarray(1e-4))) == pytest.approx(0.5e-8, rel=1e-6)


def test_kernel_scale_is_a_leaf():
    import jax

    leaves = jax.tree.leaves(Huber(jnp.asarray(2.0)))
    assert len(leaves) == 1
    g = jax.grad(lambda k: Cauchy(k).loss(jnp.asarray(3.0)))(jnp.asarray(1.0))
    assert np.isfinite(float(g))


@factor_dataclass
class _PointFactor(Factor):
    """``r = A x - b`` on Point3Var: a linear factor, so GTSAM's linearisation is exact."""

    a: Array  # (N, 3, 3)
    b: Array  # (N, 3)

    def residual(self, x: Array) -> Array:
        return jnp.einsum("nij,nj->ni", self.a, x) - self.b

    def jacobians(self, x: Array) -> tuple[Array, ...]:
        return (self.a,)


ROBUST_CASES = [None, ("Huber", Huber, 1.2), ("Cauchy", Cauchy, 0.8), ("GemanMcClure", GemanMcClure, 1.1)]


@pytest.mark.gtsam
@pytest.mark.parametrize("robust", ROBUST_CASES, ids=["none", "huber", "cauchy", "geman"])
def test_whiten_and_weight_vs_gtsam_factor(gtsam, rng, robust):
    """Cost, whitened residual and Jacobian vs a GTSAM factor with the same (robust) noise:
    ``error()`` and ``linearize()`` (whose ``b`` is ``-R r`` scaled by ``sqrt(w)``)."""
    n = 5
    x = rng.normal(size=(n, 3)) * 2.0
    measured = rng.normal(size=(n, 3)) * 2.0
    covs = np.stack([_spd(rng, 3) * 0.3 for _ in range(n)])
    factor = _PointFactor(
        variables=(Point3Var(np.arange(n)),),
        noise=Gaussian.from_covariance(covs),
        robust=None if robust is None else robust[1](robust[2]),
        a=jnp.broadcast_to(jnp.eye(3), (n, 3, 3)),
        b=jnp.asarray(measured),
    )
    r = factor.residual(jnp.asarray(x))
    lin = whiten_and_weight(factor, r, factor.jacobians(jnp.asarray(x)))
    for k in range(n):
        model = gtsam.noiseModel.Gaussian.Covariance(covs[k])
        if robust is not None:
            est = getattr(gtsam.noiseModel.mEstimator, robust[0]).Create(robust[2])
            model = gtsam.noiseModel.Robust.Create(est, model)
        gf = gtsam.PriorFactorPoint3(k, measured[k], model)
        values = gtsam.Values()
        values.insert(k, x[k])
        np.testing.assert_allclose(np.asarray(r[k]), gf.unwhitenedError(values), rtol=0, atol=TOL)
        assert float(lin.cost[k]) == pytest.approx(gf.error(values), rel=1e-12)
        jf = gf.linearize(values)
        np.testing.assert_allclose(np.asarray(lin.residual[k]), -jf.getb(), rtol=1e-12, atol=TOL)
        np.testing.assert_allclose(np.asarray(lin.jacobians[0][k]), jf.getA(), rtol=1e-12, atol=TOL)


def test_whiten_and_weight_mask_and_zero_residual():
    n = 3
    factor = _PointFactor(
        variables=(Point3Var(np.arange(n)),),
        noise=Gaussian.isotropic(3, 0.5, n=n),
        robust=Huber(1.0),
        a=jnp.broadcast_to(jnp.eye(3), (n, 3, 3)),
        b=jnp.zeros((n, 3)),
    )
    x = jnp.asarray([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [3.0, 0.0, 0.0]])
    lin = whiten_and_weight(factor, factor.residual(x), factor.jacobians(x), mask=jnp.asarray([True, False, True]))
    assert np.all(np.isfinite(np.asarray(lin.cost)))
    np.testing.assert_allclose(np.asarray(lin.cost), [0.0, 0.0, 1.0 * 6.0 - 0.5], atol=TOL)
    np.testing.assert_array_equal(np.asarray(lin.residual[1]), 0.0)
    np.testing.assert_array_equal(np.asarray(lin.jacobians[0][1]), 0.0)


# --- Values -----------------------------------------------------------------------------
def test_values_create_get_update_merge(rng):
    poses = SE3.exp(jnp.asarray(rng.normal(size=(4, 6))))
    points = rng.normal(size=(3, 3))
    vals = Values.create({Pose3Var(np.array([7, 2, 5, 0])): poses, Point3Var(np.array([1, 2, 3])): points})
    assert len(vals) == 7
    assert set(vals.types()) == {Pose3Var, Point3Var}
    np.testing.assert_array_equal(vals.ids(Pose3Var), [0, 2, 5, 7])
    got = vals.get(Pose3Var(np.array([5, 7])))
    assert isinstance(got, SE3)
    np.testing.assert_array_equal(np.asarray(got.params), np.asarray(poses.params)[[2, 0]])
    np.testing.assert_array_equal(np.asarray(vals.get(Point3Var(np.array([3])))), points[[2]])
    # A shared value broadcasts over several ids.
    shared = Values.create({Point3Var(np.array([0, 1])): np.array([1.0, 2.0, 3.0])})
    np.testing.assert_array_equal(np.asarray(shared.params(Point3Var)), [[1.0, 2.0, 3.0]] * 2)

    new_point = np.array([[9.0, 8.0, 7.0]])
    updated = vals.update(Point3Var(np.array([2])), new_point)
    np.testing.assert_array_equal(np.asarray(updated.get(Point3Var(np.array([2])))), new_point)
    np.testing.assert_array_equal(np.asarray(vals.get(Point3Var(np.array([2])))), points[[1]])  # immutable
    upd_pose = vals.update(Pose3Var(np.array([0])), SE3.identity((1,)))
    np.testing.assert_array_equal(np.asarray(upd_pose.get(Pose3Var(np.array([0]))).params), [[1, 0, 0, 0, 0, 0, 0]])

    other = Values.create({Pose3Var(np.array([10, 11])): SE3.identity((2,)), Point3Var(np.array([4])): points[:1]})
    merged = vals.merge(other)
    assert len(merged) == 10
    np.testing.assert_array_equal(merged.ids(Pose3Var), [0, 2, 5, 7, 10, 11])
    np.testing.assert_array_equal(np.asarray(merged.get(Pose3Var(np.array([5]))).params), np.asarray(poses.params)[[2]])


def test_values_is_a_pytree(rng):
    import jax

    vals = Values.create({Point3Var(np.array([3, 1])): rng.normal(size=(2, 3))})
    doubled = jax.tree.map(lambda a: 2 * a, vals)
    np.testing.assert_array_equal(doubled.ids(Point3Var), [1, 3])
    np.testing.assert_allclose(np.asarray(doubled.params(Point3Var)), 2 * np.asarray(vals.params(Point3Var)))
    out = jax.jit(lambda v: v.get(Point3Var(np.array([3]))))(vals)
    np.testing.assert_allclose(np.asarray(out), np.asarray(vals.get(Point3Var(np.array([3])))))


def test_values_errors():
    with pytest.raises(GraphError, match="Point3Var id 2 is given more than once"):
        Values.create({Point3Var(np.array([1, 2])): np.zeros((2, 3)), Point3Var(np.array([2])): np.zeros((1, 3))})
    with pytest.raises(GraphError, match="more than once"):
        Values.create({Point3Var(np.array([4, 4])): np.zeros((2, 3))})
    vals = Values.create({Point3Var(np.array([1, 2])): np.zeros((2, 3))})
    with pytest.raises(GraphError, match="Point3Var 9"):
        vals.get(Point3Var(np.array([1, 9])))
    with pytest.raises(GraphError, match="no Pose3Var"):
        vals.get(Pose3Var(np.array([1])))
    with pytest.raises(GraphError, match="more than once"):
        vals.merge(Values.create({Point3Var(np.array([2])): np.zeros((1, 3))}))
    with pytest.raises(ValueError, match=r"\(2, 3\)"):
        Values.create({Point3Var(np.array([1, 2])): np.zeros((3, 3))})
    with pytest.raises(TypeError, match="integers"):
        Point3Var(np.array([1.5]))
    with pytest.raises(ValueError, match=">= 0"):
        Point3Var(np.array([-1]))
