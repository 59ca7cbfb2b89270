"""The vectorised factor base class.

One factor object holds ``N`` constraints of one kind: for each variable slot an id array of
length ``N``, and per-constraint data (measurements, noise) with leading axis ``N``. Scalar
leaves (a robust kernel's scale) are shared by all ``N``. A factor is a PyTree, so it can be
passed through ``jit``/``grad``; the solver analyses the ids once and afterwards only sees
arrays.

Writing a factor::

    @factor_dataclass
    class MyFactor(Factor):
        measured: Array            # (N, ...)

        def residual(self, x_a, x_b):     # Lie groups / arrays with batch (N,)
            return ...                     # (N, r), not whitened

        # optional: analytic Jacobians w.r.t. right perturbations of each slot
        def jacobians(self, x_a, x_b):
            return (J_a, J_b)              # (N, r, t_a), (N, r, t_b)

The solver whitens with ``noise`` and applies ``robust``; subclasses never do.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, TypeVar, dataclass_transform

import jax
import jax.numpy as jnp
from jax import Array

from .._pytree import register_typed
from ._noise import Gaussian
from ._robust import RobustKernel
from ._variables import Variable

F = TypeVar("F", bound=type)


@dataclass_transform(kw_only_default=True, frozen_default=True)
def factor_dataclass(cls: F) -> F:
    """Make a Factor subclass a frozen keyword-only dataclass registered as a PyTree."""
    dc: Any = dataclasses.dataclass(frozen=True, kw_only=True)(cls)
    names = [f.name for f in dataclasses.fields(dc)]
    register_typed(dc, names)
    return dc


@dataclasses.dataclass(frozen=True, kw_only=True)
class Factor:
    """Base of every factor type. Fields: ``variables`` (one :class:`Variable` per slot),
    ``noise`` (:class:`Gaussian`, ``(N, r, r)``), ``robust`` (optional kernel)."""

    variables: tuple[Variable, ...]
    noise: Gaussian
    robust: RobustKernel | None = None

    # --- to implement -------------------------------------------------------------------
    def residual(self, *values: Any) -> Array:
        raise NotImplementedError

    def jacobians(self, *values: Any) -> tuple[Array, ...] | None:
        """Analytic Jacobians; ``None`` (the default) means autodiff on the manifold."""
        return None

    # --- derived ------------------------------------------------------------------------
    @property
    def num_constraints(self) -> int:
        return int(jnp.shape(self.variables[0].ids)[0])

    @property
    def residual_dim(self) -> int:
        return self.noise.dim

    def __len__(self) -> int:
        return self.num_constraints

    def variable_types(self) -> tuple[type[Variable], ...]:
        return tuple(type(v) for v in self.variables)

    def wrap_values(self, params: tuple[Array, ...]) -> tuple[Any, ...]:
        return tuple(type(v).wrap(p) for v, p in zip(self.variables, params))

    def evaluate(self, params: tuple[Array, ...]) -> Array:
        """Unwhitened residual from raw parameter arrays, one ``(N, P)`` per slot."""
        return self.residual(*self.wrap_values(params))

    def with_noise(self, noise: Gaussian) -> Factor:
        return dataclasses.replace(self, noise=noise)

    def with_robust(self, robust: RobustKernel | None) -> Factor:
        return dataclasses.replace(self, robust=robust)


def batch_in_axes(tree: Any) -> Any:
    """vmap axes for a factor: per-constraint leaves (ndim >= 1) on axis 0, scalars shared."""
    return jax.tree_util.tree_map(lambda leaf: 0 if jnp.ndim(leaf) >= 1 else None, tree)


def autodiff_jacobians(factor: Factor, params: tuple[Array, ...]) -> tuple[Array, ...]:
    """Jacobians of ``factor.residual`` w.r.t. a right perturbation of each slot, by forward
    mode autodiff, one constraint at a time under vmap."""
    types = factor.variable_types()

    def one(fac: Factor, *p: Array) -> tuple[Array, ...]:
        def f(*deltas: Array) -> Array:
            moved = tuple(t.retract(pi[None], d[None]) for t, pi, d in zip(types, p, deltas))
            return fac_batched(fac).evaluate(moved)[0]

        zeros = tuple(jnp.zeros(t.tangent_dim, dtype=pi.dtype) for t, pi in zip(types, p))
        return jax.jacfwd(f, argnums=tuple(range(len(types))))(*zeros)

    return jax.vmap(one, in_axes=(batch_in_axes(factor), *([0] * len(params))))(factor, *params)


def fac_batched(fac: Factor) -> Factor:
    """Give every leaf of one constraint (as seen inside ``vmap``) a leading axis of 1, so the
    batched ``residual`` code runs on it unchanged. Shared scalars become ``(1,)`` arrays,
    which broadcast the same way."""
    return jax.tree_util.tree_map(lambda leaf: jnp.expand_dims(leaf, 0), fac)


@dataclasses.dataclass(frozen=True)
class Linearized:
    """Whitened, robust-weighted linearisation of one factor group."""

    residual: Array  # (N, r)
    jacobians: tuple[Array, ...]  # (N, r, t_k)
    cost: Array  # (N,) rho(||whitened r||), GTSAM's convention (x^2/2 without a kernel)


def whiten_and_weight(
    factor: Factor, r: Array, jacs: tuple[Array, ...] | None, mask: Array | None = None
) -> Linearized:
    rw = factor.noise.whiten(r)
    jw = tuple(factor.noise.whiten_jacobian(j) for j in jacs) if jacs is not None else ()
    sq = jnp.sum(rw * rw, axis=-1)
    if factor.robust is None:
        cost = 0.5 * sq
    else:
        zero = sq == 0.0
        x = jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, sq)))
        cost = factor.robust.loss(x)
        s = jnp.sqrt(factor.robust.weight(x))
        rw = rw * s[:, None]
        jw = tuple(j * s[:, None, None] for j in jw)
    if mask is not None:
        m = mask.astype(rw.dtype)
        rw = rw * m[:, None]
        jw = tuple(j * m[:, None, None] for j in jw)
        cost = cost * m
    return Linearized(rw, jw, cost)


def linearize(factor: Factor, params: tuple[Array, ...], mask: Array | None = None) -> Linearized:
    """Residual and Jacobians (analytic when the factor gives them), whitened and weighted."""
    values = factor.wrap_values(params)
    r = factor.residual(*values)
    jacs = factor.jacobians(*values)
    if jacs is None:
        jacs = autodiff_jacobians(factor, params)
    return whiten_and_weight(factor, r, tuple(jacs), mask)


def factor_cost(factor: Factor, params: tuple[Array, ...], mask: Array | None = None) -> Array:
    """Per-constraint cost ``rho(||R r||)`` without Jacobians."""
    r = factor.evaluate(params)
    return whiten_and_weight(factor, r, None, mask).cost


ResidualFn = Callable[..., Array]
