"""Free the compiled programs of each tuning test module: they differentiate whole graphs
(Hessian-vector products, VJPs) and would otherwise stay in the test process's memory."""

import jax
import pytest


@pytest.fixture(autouse=True, scope="module")
def _clear_jax_caches():
    yield
    jax.clear_caches()
