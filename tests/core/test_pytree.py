"""Classes of one family (same field names) must have tree structures that differ.

jax 0.10.2's ``register_dataclass`` compares two such structures equal (only hashes differ);
a run once evaluated Rot3 between factors with the program compiled for Pose2 ones. These
check the registration jaxslam uses instead (``jaxslam._pytree.register_typed``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import Cauchy, Gaussian, Huber, Pose2Var, Pose3Var, Rot3Var
from jaxslam.factors import BetweenFactor, PriorFactor
from jaxslam.lie import SE2, SO3


def _structure(x):
    return jax.tree_util.tree_structure(x)


@pytest.mark.parametrize(
    ("a", "b"),
    [
        (SE2(jnp.zeros((3, 4))), SO3(jnp.zeros((3, 4)))),
        (Pose2Var(np.arange(3)), Rot3Var(np.arange(3))),
        (Huber(1.0), Cauchy(1.0)),
    ],
    ids=["lie", "variables", "robust"],
)
def test_same_fields_different_classes_differ(a, b):
    assert [np.shape(x) for x in jax.tree_util.tree_leaves(a)] == [np.shape(x) for x in jax.tree_util.tree_leaves(b)]
    assert _structure(a) != _structure(b)
    assert _structure(a) == _structure(type(a)(*jax.tree_util.tree_leaves(a)))


def test_factor_structures_differ_by_variable_type_and_round_trip():
    n = 4
    cov = np.tile(np.eye(3), (n, 1, 1))
    meas2 = np.asarray(SE2.exp(jnp.zeros((n, 3))).params)
    meas3 = np.asarray(SO3.exp(jnp.zeros((n, 3))).params)
    f2 = BetweenFactor.create(
        Pose2Var(np.arange(n)), Pose2Var(np.arange(n, 2 * n)), meas2, Gaussian.from_covariance(cov)
    )
    f3 = BetweenFactor.create(Rot3Var(np.arange(n)), Rot3Var(np.arange(n, 2 * n)), meas3, Gaussian.from_covariance(cov))
    assert _structure(f2) != _structure(f3)
    leaves, tree = jax.tree_util.tree_flatten(f3)
    back = jax.tree_util.tree_unflatten(tree, leaves)
    assert type(back) is BetweenFactor and type(back.variables[0]) is Rot3Var
    # key paths still name the fields (used in error messages)
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(f3)]
    assert any(".measured" in p for p in paths) and any(".ids" in p for p in paths)
    p6 = PriorFactor.create(
        Pose3Var(np.arange(n)),
        np.tile([1.0, 0, 0, 0, 0, 0, 0], (n, 1)),
        Gaussian.from_covariance(np.tile(np.eye(6), (n, 1, 1))),
    )
    assert _structure(p6) != _structure(f3)
