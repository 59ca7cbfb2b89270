"""Gradients through the nonlinear least-squares optimum (SPEC §6).

The solution ``x*(theta)`` of ``min_x C(x, theta)`` (``theta``: noise weights, prior means,
robust-kernel scales, anything the factors are built from) depends on ``theta`` only through
the optimality condition. Parameterise the optimum locally, ``x = x* ⊕ delta``; at
``delta = 0`` the gradient ``g(delta, theta) = ∇_delta C(x* ⊕ delta, theta)`` vanishes, so by the
implicit function theorem::

    d delta / d theta = -H^-1 ∂g/∂theta,        H = ∇²_delta C   (exact Hessian, tangent space)

and for a scalar loss ``L(x*(theta))`` (the adjoint method, one linear solve per loss)::

    H lambda = ∇_delta L(x* ⊕ delta)                       (adjoint solve)
    dL/dtheta = -∂/∂theta <∇_delta C(x* ⊕ delta, theta), lambda>   (one VJP over theta)

Data flow of :class:`DifferentiableSolver`::

    theta ──factor_fn──▶ factors ──Problem.group_data_for──▶ group data (same structure:
        analysis and compiled kernels reused) ──Solver (Gauss-Newton, host sparse Cholesky,
        warm-started)──▶ x*
    backward: ∂L/∂x* ──VJP of the retraction──▶ ∇_delta L ──adjoint solve──▶ lambda
        ──VJP over theta of the directional derivative of C──▶ dL/dtheta

The adjoint solve (``adjoint="exact"``) is preconditioned conjugate gradients on the exact
Hessian, whose products come from forward-over-reverse autodiff of the total cost; the
preconditioner is the sparse Cholesky of the Gauss-Newton matrix ``JᵀJ`` at ``x*`` (the
forward solve's matrix: one factorisation, then one back-substitution per CG step). The
two differ by the residual curvature ``Σ r_i ∇² r_i``, which is small where the fit is
good, so CG needs a handful of steps. ``adjoint="gauss-newton"`` skips CG and uses ``JᵀJ``
alone (exact only for zero residuals; cheaper). ``adjoint="unroll"`` differentiates through
``unroll_steps`` Gauss-Newton iterations from the initial values instead (dense solves,
small graphs: truncated unrolling, an approximation of the optimum's derivative).

Design references: the implicit-function / adjoint derivation follows Blondel et al.,
"Efficient and modular implicit differentiation" (NeurIPS 2022) and Pineda et al.,
"Theseus" (NeurIPS 2022, its implicit and truncated backward modes); the code is jaxslam's.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..core import Factor, Values, Variable
from ..errors import SolverError
from ..solvers import Solver, SolverConfig
from ..solvers._problem import GroupData, assemble, retract_all, total_cost

Adjoint = Literal["exact", "gauss-newton", "unroll"]

# JAX traces ``jax.grad``'s forward and backward passes with an empty abstract mesh in its
# context, and an eager call with none: the context is part of every jit cache key, so the
# host-side solves would compile each kernel (the Hessian-vector product, the assembly) once
# per context. All host work here runs under this one mesh instead: one compile each.
_HOST_MESH = jax.sharding.AbstractMesh((), ())


def _tight() -> SolverConfig:
    return SolverConfig(
        method="gn", max_iterations=50, relative_tol=1e-15, absolute_tol=0.0, step_tol=1e-11, linear_solver="auto"
    )


@dataclasses.dataclass(frozen=True)
class ImplicitConfig:
    """Options of :class:`DifferentiableSolver`."""

    adjoint: Adjoint = "exact"
    """``exact``: implicit differentiation with the exact Hessian (CG preconditioned by the
    Gauss-Newton factorisation); ``gauss-newton``: the Gauss-Newton matrix alone; ``unroll``:
    truncated unrolling of ``unroll_steps`` Gauss-Newton steps (dense; small graphs)."""
    solver: SolverConfig = dataclasses.field(default_factory=_tight)
    """Forward solver; tight tolerances, since the adjoint assumes the gradient vanishes."""
    cg_tol: float = 1e-10
    """Relative residual at which the adjoint's conjugate gradients stop."""
    cg_maxiter: int = 100
    unroll_steps: int = 5
    unroll_max_dof: int = 6000
    """``unroll`` forms the dense Hessian: refuse larger graphs (use ``exact``)."""
    polish_steps: int = 4
    """Newton steps (exact Hessian, CG) after the Gauss-Newton solve, until the gradient's
    max-norm is below ``grad_tol``."""
    grad_tol: float = 1e-10
    warm_start: bool = True
    """Start each forward solve from the previous optimum (a learning loop moves theta a
    little per step)."""


@dataclasses.dataclass
class BackwardStats:
    """What the last backward pass did (for benchmarks and diagnostics)."""

    cg_iterations: int = 0
    cg_residual: float = 0.0
    fallback: bool = False
    """The exact Hessian was not positive definite along a CG direction (robust kernels far
    out): the Gauss-Newton adjoint was used instead."""
    time_s: float = 0.0


@functools.partial(jax.jit, static_argnames=("static", "var_types"))
def _cost_at(
    delta: Array,
    params: tuple[Array, ...],
    groups: list[GroupData],
    dof_index: tuple[Array, ...],
    *,
    static: tuple[Any, ...],
    var_types: tuple[type[Variable], ...],
) -> Array:
    """Total cost at ``x ⊕ delta`` (the local parameterisation the implicit function uses)."""
    return total_cost(retract_all(params, delta, dof_index, var_types=var_types), groups, static=static)


@functools.partial(jax.jit, static_argnames=("static", "var_types"))
def _hvp(
    v: Array,
    params: tuple[Array, ...],
    groups: list[GroupData],
    dof_index: tuple[Array, ...],
    *,
    static: tuple[Any, ...],
    var_types: tuple[type[Variable], ...],
) -> Array:
    """Exact Hessian-vector product ``∇²_delta C · v`` at ``delta = 0`` (forward over reverse)."""

    def grad(d: Array) -> Array:
        return jax.grad(_cost_at)(d, params, groups, dof_index, static=static, var_types=var_types)

    return jax.jvp(grad, (jnp.zeros_like(v),), (v,))[1]


class DifferentiableSolver:
    """Solve a factor graph built from parameters ``theta`` and differentiate its optimum.

    ``factor_fn(theta) -> list[Factor]`` builds the graph (JAX code: ``theta`` any PyTree of
    arrays); every call must give the same structure (same factor kinds, counts and
    variables). ``values`` is the initial estimate. Then::

        ds = DifferentiableSolver(factor_fn, values, theta0)
        x = ds(theta)                         # Values at the optimum (host sparse solver)
        loss, g = jax.value_and_grad(lambda th: my_loss(ds(th)))(theta)

    ``ds(theta)`` is a ``jax.custom_vjp`` function: use it eagerly (not under ``jit`` or
    ``vmap``: the forward solve runs on the host). The gauge must be fixed by factors (a
    prior), and the graph must be well-posed at the optimum (H positive definite).
    """

    def __init__(
        self,
        factor_fn: Callable[[Any], Sequence[Factor]],
        values: Values,
        theta0: Any,
        config: ImplicitConfig | None = None,
        *,
        fixed: Sequence[Variable] = (),
    ):
        self.config = config or ImplicitConfig()
        self.factor_fn = factor_fn
        self._solver = Solver(list(factor_fn(theta0)), values, self.config.solver, fixed=fixed)
        if self._solver.gauge_free:
            free = "; ".join(self._solver.gauge_free)
            raise SolverError(f"the graph's gauge is free ({free}): add a prior to differentiate it")
        self.problem = self._solver.problem
        self.initial_values = values
        self._last: Values | None = None
        self.forward_time_s = 0.0
        self.forward_iterations = 0
        self.polish_steps = 0
        self.backward = BackwardStats()
        self._solve = self._make_custom_vjp()

    # --- forward ------------------------------------------------------------------------
    def groups(self, theta: Any) -> list[GroupData]:
        """The graph's group data for ``theta`` (traceable). Leaves are made strongly typed
        first: a weakly typed scalar (``jnp.asarray(1.0)``) and the array an optimiser hands
        back are the same parameter and must reuse the same compiled kernels."""
        theta = jax.tree_util.tree_map(lambda a: jax.lax.convert_element_type(a, jnp.result_type(a)), theta)
        return self.problem.group_data_for(list(self.factor_fn(theta)))

    def solve(self, theta: Any) -> Values:
        """The optimum for ``theta`` (no gradient): Gauss-Newton to tight tolerances."""
        with jax.sharding.use_abstract_mesh(_HOST_MESH):
            return self._solve_host(theta)

    def _solve_host(self, theta: Any) -> Values:
        t0 = time.perf_counter()
        self.problem.group_data = self.groups(theta)
        start = self._last if (self.config.warm_start and self._last is not None) else self.initial_values
        res = self._solver.solve(start)
        if not res.success:
            raise SolverError(f"forward solve failed: {res.message}")
        values, self.polish_steps = self._polish(res.values)
        self._last = values
        self.forward_time_s = time.perf_counter() - t0
        self.forward_iterations = res.iterations
        return values

    def __call__(self, theta: Any) -> Values:
        if self.config.adjoint == "unroll":
            return self.unrolled(theta)
        return self._solve(theta)

    def reset(self) -> None:
        """Forget the warm start."""
        self._last = None

    # --- backward -----------------------------------------------------------------------
    def _make_custom_vjp(self) -> Callable[[Any], Values]:
        @jax.custom_vjp
        def optimum(theta: Any) -> Values:
            return self.solve(theta)

        def fwd(theta: Any) -> tuple[Values, tuple[Any, Values]]:
            x = self.solve(theta)
            return x, (theta, x)

        def bwd(res: tuple[Any, Values], ct: Values) -> tuple[Any]:
            theta, x = res
            return (self.adjoint(theta, x, ct),)

        optimum.defvjp(fwd, bwd)
        return optimum

    def adjoint(self, theta: Any, x: Values, ct: Values) -> Any:
        """``dL/dtheta`` from ``ct = dL/dx*`` (cotangent on the parameter arrays of ``x``)."""
        with jax.sharding.use_abstract_mesh(_HOST_MESH):
            return self._adjoint_host(theta, x, ct)

    def _adjoint_host(self, theta: Any, x: Values, ct: Values) -> Any:
        t0 = time.perf_counter()
        p = self.problem
        params = p.pad_values(x)
        dof = p.dof_index_jax
        zero = jnp.zeros(p.ndof)

        # 1. the loss gradient in the tangent space: VJP of delta -> unpadded x ⊕ delta
        def moved(d: Array) -> Values:
            return p.unpad_values(retract_all(params, d, dof, var_types=p.var_types))

        _, pull = jax.vjp(moved, zero)
        (g_delta,) = pull(_ct_like(ct, x))
        g_delta = np.asarray(g_delta)
        # 2. the adjoint solve H lambda = g
        groups = self.groups(jax.lax.stop_gradient(theta))
        lam = self._adjoint_solve(params, groups, g_delta)
        # 3. -d/dtheta <grad_delta C, lambda>
        grad = self._mixed(theta, params, jnp.asarray(lam))
        self.backward.time_s = time.perf_counter() - t0
        return grad

    @functools.cached_property
    def _mixed(self) -> Callable[[Any, tuple[Array, ...], Array], Any]:
        """``theta, x, lambda -> -∂/∂theta <∇_delta C(x ⊕ delta, theta), lambda>``, compiled
        once (``factor_fn`` is traced: variable ids must be numpy, not derived from theta)."""
        p = self.problem

        def directional(th: Any, params: tuple[Array, ...], lam: Array) -> Array:
            gs = self.groups(th)
            return jax.jvp(
                lambda d: _cost_at(d, params, gs, p.dof_index_jax, static=p.static, var_types=p.var_types),
                (jnp.zeros_like(lam),),
                (lam,),
            )[1]

        def mixed(th: Any, params: tuple[Array, ...], lam: Array) -> Any:
            return jax.tree_util.tree_map(jnp.negative, jax.grad(directional)(th, params, lam))

        return jax.jit(mixed)

    def _adjoint_solve(self, params: tuple[Array, ...], groups: list[GroupData], rhs: np.ndarray) -> np.ndarray:
        p, s = self.problem, self._solver
        p.group_data = groups
        hdata, _, _ = s.linearize(params)
        precond = s.system.factorize(hdata)
        if precond is None:
            raise SolverError("the Gauss-Newton matrix at the optimum is not positive definite")
        self.backward = BackwardStats()
        if self.config.adjoint == "gauss-newton":
            x = precond(rhs)
            if x is None:
                raise SolverError("the adjoint solve failed (non-finite)")
            return x
        x, it, res, ok = self._newton_system(params, groups, rhs, precond)
        self.backward.cg_iterations, self.backward.cg_residual, self.backward.fallback = it, res, not ok
        return x

    def _newton_system(
        self,
        params: tuple[Array, ...],
        groups: list[GroupData],
        rhs: np.ndarray,
        precond: Callable[[np.ndarray], np.ndarray | None],
    ) -> tuple[np.ndarray, int, float, bool]:
        """Solve ``H x = rhs`` with the exact Hessian by conjugate gradients preconditioned
        by the Gauss-Newton factorisation, started at the Gauss-Newton solution. Returns
        ``(x, iterations, relative residual, ok)``; ``ok`` is False (and ``x`` the
        Gauss-Newton solution) when H is not positive definite along a CG direction."""
        p = self.problem
        extra = self._extra_diagonal()

        def hess(v: np.ndarray) -> np.ndarray:
            hv = _hvp(jnp.asarray(v), params, groups, p.dof_index_jax, static=p.static, var_types=p.var_types)
            return np.asarray(hv) + extra * v

        def pre(r: np.ndarray) -> np.ndarray:
            z = precond(r)
            if z is None:
                raise SolverError("the adjoint's preconditioner failed (non-finite)")
            return z

        x0 = pre(rhs)
        x = x0
        r = rhs - hess(x)
        z = pre(r)
        d = z.copy()
        rz = float(r @ z)
        norm_b = float(np.linalg.norm(rhs)) or 1.0
        it = 0
        for it in range(self.config.cg_maxiter):
            if float(np.linalg.norm(r)) / norm_b <= self.config.cg_tol:
                break
            hd = hess(d)
            dhd = float(d @ hd)
            if dhd <= 0:  # not convex along d (robust kernels far out): keep Gauss-Newton's
                return x0, it, float(np.linalg.norm(rhs - hess(x0))) / norm_b, False
            a = rz / dhd
            x = x + a * d
            r = r - a * hd
            z = pre(r)
            rz_new = float(r @ z)
            d = z + (rz_new / rz) * d
            rz = rz_new
        else:
            it = self.config.cg_maxiter
        return x, it, float(np.linalg.norm(r)) / norm_b, True

    def _polish(self, x: Values) -> tuple[Values, int]:
        """Newton steps (exact Hessian) after Gauss-Newton: with robust kernels or large
        residuals Gauss-Newton converges only linearly, and the implicit function theorem
        needs the gradient to vanish. Stops at ``grad_tol`` (max-norm of the gradient)."""
        p, s = self.problem, self._solver
        params = p.pad_values(x)
        steps = 0
        for steps in range(self.config.polish_steps + 1):
            hdata, grad, _ = s.linearize(params)
            if float(np.max(np.abs(grad), initial=0.0)) <= self.config.grad_tol or steps == self.config.polish_steps:
                break
            precond = s.system.factorize(hdata)
            if precond is None:
                break
            step, _, _, ok = self._newton_system(params, p.group_data, -grad, precond)
            if not ok:
                break
            params = s.retract(params, step)
        return p.unpad_values(params), steps

    def _extra_diagonal(self) -> np.ndarray:
        """Hessian terms outside the factors: unit diagonal on padding dofs, gauge anchors."""
        p, s = self.problem, self._solver
        e = np.zeros(p.ndof)
        e[p.untouched_dofs] = 1.0
        for a in s.anchors:
            e[a.dofs] += a.weight
        return e

    # --- truncated unrolling ------------------------------------------------------------
    def unrolled(self, theta: Any) -> Values:
        """``unroll_steps`` Gauss-Newton steps from the initial values, differentiable end to
        end by ordinary autodiff (dense normal equations)."""
        p = self.problem
        if p.ndof > self.config.unroll_max_dof:
            raise SolverError(
                f"unroll forms a dense {p.ndof}x{p.ndof} Hessian; above unroll_max_dof="
                f"{self.config.unroll_max_dof} use adjoint='exact'"
            )
        groups = self.groups(theta)
        params = p.pad_values(self.initial_values)
        rows = jnp.asarray(p.csc_indices)
        cols = jnp.asarray(np.repeat(np.arange(p.ndof), np.diff(p.csc_indptr)))
        extra = jnp.asarray(self._extra_diagonal())
        for _ in range(self.config.unroll_steps):
            hdata, g, _ = assemble(params, groups, static=p.static, nnz=p.nnz_capacity, ndof=p.ndof)
            lower = jnp.zeros((p.ndof, p.ndof)).at[rows, cols].add(hdata[: p.nnz])
            h = lower + lower.T - jnp.diag(jnp.diag(lower)) + jnp.diag(extra)
            step = -jnp.linalg.solve(h, g)
            params = retract_all(params, step, p.dof_index_jax, var_types=p.var_types)
        return p.unpad_values(params)


def _ct_like(ct: Values, x: Values) -> Values:
    """The cotangent as a Values of ``x``'s structure (symbolic zeros become arrays)."""
    leaves, tree = jax.tree_util.tree_flatten(x)
    ct_leaves = jax.tree_util.tree_leaves(ct)
    if len(ct_leaves) != len(leaves):
        ct_leaves = [jnp.zeros_like(leaf) for leaf in leaves]
    return jax.tree_util.tree_unflatten(tree, ct_leaves)
