"""Second derivatives of exp at the identity (the implicit-differentiation Hessian is taken
there) against central differences of the Jacobian."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.lie import SE3, SO3


@pytest.mark.parametrize("group,dim", [(SO3, 3), (SE3, 6)])
@pytest.mark.parametrize("at_zero", [True, False])
def test_exp_hessian_matches_differences(group, dim, at_zero):
    x0 = jnp.zeros(dim) if at_zero else jnp.asarray(np.random.default_rng(0).normal(size=dim) * 0.3)

    def f(x):
        return group.exp(x).params

    hess = np.asarray(jax.hessian(f)(x0))
    eps = 1e-5
    fd = np.zeros_like(hess)
    for i in range(dim):
        e = np.zeros(dim)
        e[i] = eps
        fd[..., i] = (np.asarray(jax.jacfwd(f)(x0 + e)) - np.asarray(jax.jacfwd(f)(x0 - e))) / (2 * eps)
    np.testing.assert_allclose(hess, fd, atol=1e-8)
