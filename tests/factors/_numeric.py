"""Shared numerical oracle of the factor tests."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def manifold_central_difference(factor, params: tuple, slot: int, h: float = 1e-6) -> np.ndarray:
    """``d r / d delta`` for ``x_slot <- retract(x_slot, delta)`` by central differences, all
    constraints at once: ``(N, r, t)``."""
    vtype = type(factor.variables[slot])
    n, t = len(factor), vtype.tangent_dim
    cols = []
    for i in range(t):
        d = np.zeros((n, t))
        d[:, i] = h
        plus, minus = list(params), list(params)
        plus[slot] = vtype.retract(params[slot], jnp.asarray(d))
        minus[slot] = vtype.retract(params[slot], jnp.asarray(-d))
        cols.append((np.asarray(factor.evaluate(tuple(plus))) - np.asarray(factor.evaluate(tuple(minus)))) / (2 * h))
    return np.stack(cols, axis=-1)
