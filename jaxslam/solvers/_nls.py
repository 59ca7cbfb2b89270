"""Batch nonlinear least squares: Gauss-Newton and Levenberg-Marquardt.

Cost convention (GTSAM's): ``sum_i rho_i(||R_i r_i||)``, ``rho(x) = x^2 / 2`` without a robust
kernel. Both solvers stop on a relative or absolute cost decrease below tolerance, a step
below ``step_tol``, or ``max_iterations``, and report a :class:`Status` instead of raising
(``throw=True`` raises :class:`~jaxslam.errors.SolverError` on failure).

LM is a trust-region method with Nielsen's damping update (Madsen, Nielsen, Tingleff,
"Methods for non-linear least squares problems", 2004, sec. 3.2): the damping shrinks by
``max(lambda_decrease, 1 - (2 rho - 1)^3)`` after a good step (Nielsen uses 1/3; 1/30 by
default here) and doubles (then quadruples, ...) after a rejected one. The damping is
``lambda * I`` by default (as GTSAM's), or Marquardt's ``lambda * clip(diag(H), min_diag,
max_diag)`` (``damping="marquardt"``), which is invariant to the units of each variable.
"""

from __future__ import annotations

import dataclasses
import enum
import time
from collections.abc import Callable, Sequence
from typing import Literal

import jax.numpy as jnp
import numpy as np

from ..core import Factor, Values, Variable
from ..errors import GraphError, SolverError
from ._linear import SparseSystem
from ._problem import Problem, assemble, retract_all, total_cost


class Status(enum.Enum):
    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    INDEFINITE = "indefinite"  # the linear system was not positive definite
    GAUGE_FREE = "gauge_free"  # some variables are not anchored by any prior
    NONFINITE = "nonfinite"  # NaN / inf in the cost (bad input values)


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """Options of the batch solvers."""

    method: Literal["gn", "lm"] = "lm"
    """Gauss-Newton or Levenberg-Marquardt."""
    linear_solver: Literal["auto", "pardiso", "cholmod", "splu", "pcg"] = "auto"
    """Sparse linear solver; ``auto`` = PARDISO (MKL) or CHOLMOD when installed, else SuperLU."""
    max_iterations: int = 100
    """Outer iterations (LM counts accepted and rejected steps)."""
    relative_tol: float = 1e-10
    """Stop when the cost decreases by less than this fraction."""
    absolute_tol: float = 1e-12
    """Stop when the cost decreases by less than this."""
    step_tol: float = 1e-10
    """Stop when the step's infinity norm is below this."""
    initial_lambda: float = 1e-5
    """LM: initial damping factor (relative to diag(H))."""
    damping: Literal["marquardt", "identity"] = "identity"
    """LM: damp with lambda * I (GTSAM's default; measured fewer iterations on sphere2500 here)
    or lambda * clip(diag(H)) (Marquardt's scale-invariant variant)."""
    lambda_decrease: float = 1.0 / 30.0
    """LM: smallest factor the damping is multiplied by after a good step. Nielsen's 1/3 took
    up to 2x more iterations on the benchmark pose graphs; 1/30 was the best of 1/3, 1/10,
    1/30 there (chosen on those files: see README)."""
    min_diag: float = 1e-6
    """LM: clamp of diag(H) in the damping term."""
    max_diag: float = 1e32
    fix_gauge: bool = False
    """Add a tight prior on one variable of every unanchored component (at its initial value)
    instead of failing with GAUGE_FREE."""
    ordering: Literal["amd", "metis", "colamd", "natural"] = "amd"
    """Block fill-reducing ordering of the variable graph."""
    verbose: bool = False


@dataclasses.dataclass
class SolverResult:
    values: Values
    status: Status
    message: str
    initial_cost: float
    final_cost: float
    iterations: int
    linear_solves: int
    time_s: float
    cost_history: list[float]
    time_history: list[float] = dataclasses.field(default_factory=list)
    """Seconds since the start of ``solve`` at which each ``cost_history`` entry was known."""

    def time_to_reach(self, cost: float) -> float | None:
        """First time the cost was at or below ``cost`` (None if never)."""
        for c, t in zip(self.cost_history, self.time_history):
            if c <= cost:
                return t
        return None

    @property
    def success(self) -> bool:
        return self.status in (Status.CONVERGED, Status.MAX_ITERATIONS)


@dataclasses.dataclass(frozen=True)
class _GaugeAnchor:
    """A tight prior on one variable, applied directly to the normal equations:
    cost ``w/2 |local(x0, x)|^2``, Jacobian ``I`` (exact at the anchor), ``w = 1/sigma^2``.
    Solvers never import a concrete factor, so the gauge is fixed here rather than by adding
    a PriorFactor (GTSAM's examples fix the first pose with sigma 1e-6 the same way)."""

    type_index: int
    row: int
    x0: np.ndarray
    dofs: np.ndarray
    weight: float


class Solver:
    """A batch solver bound to one graph structure (analysis and compiled code reused).

    ``Solver(factors, values, config).solve()``; call :meth:`solve` again with new initial
    values (same ids) or after :meth:`set_factors` with the same structure without
    re-analysis.
    """

    def __init__(
        self,
        factors: Sequence[Factor],
        values: Values,
        config: SolverConfig | None = None,
        *,
        fixed: Sequence[Variable] = (),
    ):
        """``fixed``: variables held constant at their values in ``values`` (GTSAM users add
        a tight prior or leave them out of the graph; here they keep no degrees of freedom)."""
        self.config = config or SolverConfig()
        factors = list(factors)
        self.problem = Problem(factors, values, ordering=self.config.ordering, fixed=fixed)
        self.anchors: list[_GaugeAnchor] = []
        self.gauge_free = self.problem.free_gauge_components()
        if self.gauge_free and self.config.fix_gauge:
            self.anchors = self._make_anchors(values)
            self.gauge_free = []
        p = self.problem
        self.system = SparseSystem(
            p.csc_indices, p.csc_indptr, p.ndof, p.diag_pos, self.config.linear_solver, p.diag_blocks
        )
        self._untouched = p.untouched_dofs
        self.initial_values = values

    def set_factors(self, factors: Sequence[Factor]) -> None:
        """New measurements, noise or kernels on the same graph structure: no re-analysis,
        no recompilation (a learning loop re-solves with new noise weights this way)."""
        self.problem.set_factors(list(factors))

    def _make_anchors(self, values: Values, sigma: float = 1e-6) -> list[_GaugeAnchor]:
        p = self.problem
        out = []
        for block in p.free_gauge_blocks():
            vtype, row = p.block_variable(block)
            k = p.type_index[vtype]
            x0 = np.asarray(values.params(vtype))[row]
            out.append(_GaugeAnchor(k, row, x0, p.dof_index[vtype][row], 1.0 / sigma**2))
        return out

    def _anchor_terms(self, params: tuple) -> list[tuple[_GaugeAnchor, np.ndarray]]:
        out = []
        for a in self.anchors:
            vtype = self.problem.var_types[a.type_index]
            x = params[a.type_index][a.row]
            out.append((a, np.asarray(vtype.local(jnp.asarray(a.x0)[None], x[None]))[0]))
        return out

    # --- compiled pieces ----------------------------------------------------------------
    def linearize(self, params: tuple) -> tuple[np.ndarray, np.ndarray, float]:
        p = self.problem
        hdata, grad, cost = assemble(params, p.group_data, static=p.static, nnz=p.nnz_capacity, ndof=p.ndof)
        hdata = np.asarray(hdata)[: p.nnz]
        grad = np.asarray(grad)
        cost = float(cost)
        if self._untouched.size or self.anchors:
            hdata = hdata.copy()
            grad = grad.copy()
            hdata[p.diag_pos[self._untouched]] = 1.0
            for a, d in self._anchor_terms(params):
                hdata[p.diag_pos[a.dofs]] += a.weight
                grad[a.dofs] += a.weight * d
                cost += 0.5 * a.weight * float(d @ d)
        return hdata, grad, cost

    def cost(self, params: tuple) -> float:
        c = float(total_cost(params, self.problem.group_data, static=self.problem.static))
        return c + sum(0.5 * a.weight * float(d @ d) for a, d in self._anchor_terms(params))

    def retract(self, params: tuple, delta: np.ndarray) -> tuple:
        p = self.problem
        return retract_all(params, jnp.asarray(delta), p.dof_index_jax, var_types=p.var_types)

    def evaluate(self, values: Values) -> float:
        """Total cost of ``values`` (GTSAM's ``graph.error``)."""
        return self.cost(self.problem.pad_values(values))

    # --- solve --------------------------------------------------------------------------
    def solve(
        self,
        values: Values | None = None,
        *,
        throw: bool = False,
        callback: Callable[[int, float], None] | None = None,
    ) -> SolverResult:
        """Optimise from ``values`` (default: the values given at construction).
        ``callback(iteration, cost)`` is called after every accepted step (progress bars)."""
        values = self.initial_values if values is None else values
        self._callback = callback
        self._times: list[float] = []
        self._t0 = time.perf_counter()
        t0 = time.perf_counter()
        params = self.problem.pad_values(values)
        if self.gauge_free:
            cost0 = self.cost(params)
            msg = (
                "the gauge is free: no prior anchors "
                + "; ".join(self.gauge_free)
                + " (a rigid motion of them leaves the cost unchanged). Add a PriorFactor on one "
                "variable of each, or set fix_gauge=True"
            )
            return self._finish(values, Status.GAUGE_FREE, msg, cost0, cost0, 0, 0, t0, [cost0], throw)
        if self.config.method == "gn":
            return self._gauss_newton(params, t0, throw)
        return self._levenberg_marquardt(params, t0, throw)

    def _finish(
        self,
        values: Values,
        status: Status,
        message: str,
        c0: float,
        c1: float,
        iters: int,
        solves: int,
        t0: float,
        history: list[float],
        throw: bool,
    ) -> SolverResult:
        res = SolverResult(
            values, status, message, c0, c1, iters, solves, time.perf_counter() - t0, history, list(self._times)
        )
        if throw and not res.success:
            raise (GraphError if status is Status.GAUGE_FREE else SolverError)(message)
        return res

    def _damping_diag(self, hdata: np.ndarray) -> np.ndarray:
        c = self.config
        if c.damping == "identity":
            return np.ones(self.problem.ndof)
        return np.clip(hdata[self.problem.diag_pos], c.min_diag, c.max_diag)

    def _report(self, it: int, cost: float) -> None:
        self._times.append(time.perf_counter() - self._t0)
        if self.config.verbose:
            print(f"iteration {it}: cost {cost:.10g}")
        callback = getattr(self, "_callback", None)
        if callback is not None:
            callback(it, cost)

    def _converged(self, old: float, new: float, step: np.ndarray) -> bool:
        c = self.config
        dec = old - new
        return (
            (dec >= 0 and dec < c.relative_tol * max(old, 1e-300))
            or (dec >= 0 and dec < c.absolute_tol)
            or float(np.max(np.abs(step), initial=0.0)) < c.step_tol
        )

    def _start(
        self, params: tuple, t0: float, throw: bool
    ) -> tuple[np.ndarray, np.ndarray, float, SolverResult | None]:
        """First linearisation; a NONFINITE result instead when the initial cost is NaN/inf."""
        hdata, grad, cost = self.linearize(params)
        self._times.append(time.perf_counter() - self._t0)
        if np.isfinite(cost):
            return hdata, grad, cost, None
        values = self.problem.unpad_values(params)
        msg = "initial cost is not finite (NaN or inf in the initial values or measurements)"
        return hdata, grad, cost, self._finish(values, Status.NONFINITE, msg, cost, cost, 0, 0, t0, [cost], throw)

    def _gauss_newton(self, params: tuple, t0: float, throw: bool) -> SolverResult:
        c = self.config
        hdata, grad, cost, early = self._start(params, t0, throw)
        if early is not None:
            return early
        c0, history = cost, [cost]
        status, msg = Status.MAX_ITERATIONS, f"stopped after {c.max_iterations} iterations"
        it = 0
        for it in range(1, c.max_iterations + 1):
            step = self.system.solve(hdata, -grad)
            if step is None:
                status, msg = (
                    Status.INDEFINITE,
                    "the Gauss-Newton system is not positive definite (a variable is under-constrained)",
                )
                break
            params = self.retract(params, step)
            new_h, new_g, new_cost = self.linearize(params)
            history.append(new_cost)
            self._report(it, new_cost)
            if not np.isfinite(new_cost):
                status, msg = Status.NONFINITE, "the cost became non-finite"
                break
            done = self._converged(cost, new_cost, step)
            hdata, grad, cost = new_h, new_g, new_cost
            if done:
                status, msg = Status.CONVERGED, "converged"
                break
        return self._finish(self.problem.unpad_values(params), status, msg, c0, cost, it, it, t0, history, throw)

    def _levenberg_marquardt(self, params: tuple, t0: float, throw: bool) -> SolverResult:
        c = self.config
        hdata, grad, cost, early = self._start(params, t0, throw)
        if early is not None:
            return early
        c0, history = cost, [cost]
        lam, nu = c.initial_lambda, 2.0
        status, msg = Status.MAX_ITERATIONS, f"stopped after {c.max_iterations} iterations"
        solves = 0
        it = 0
        diag_h = self._damping_diag(hdata)
        for it in range(1, c.max_iterations + 1):
            step = self.system.solve(hdata, -grad, lam * diag_h)
            solves += 1
            if step is None:
                lam, nu = lam * nu, nu * 2.0
                if lam > 1e20:
                    status, msg = Status.INDEFINITE, "damping grew without bound: the system stays indefinite"
                    break
                continue
            # Model decrease -(g.d + d.H.d/2); with (H + lambda D) d = -g this is
            # (-g.d + lambda d.D.d) / 2, so no product with H is needed.
            damp = lam * diag_h
            predicted = 0.5 * (-(grad @ step) + step @ (damp * step))
            new_params = self.retract(params, step)
            # Linearise the candidate at once: the assembly returns its cost too, and most
            # steps are accepted, so an accepted step needs no separate cost evaluation.
            new_h, new_g, new_cost = self.linearize(new_params)
            actual = cost - new_cost
            rho = actual / predicted if predicted > 0 else -1.0
            if np.isfinite(new_cost) and rho > 0:
                done = self._converged(cost, new_cost, step)
                params = new_params
                lam *= max(c.lambda_decrease, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                hdata, grad, cost = new_h, new_g, new_cost
                diag_h = self._damping_diag(hdata)
                history.append(cost)
                self._report(it, cost)
                if done:
                    status, msg = Status.CONVERGED, "converged"
                    break
            else:
                if predicted <= 0 and abs(actual) <= c.absolute_tol + c.relative_tol * cost:
                    status, msg = Status.CONVERGED, "converged (no further decrease possible)"
                    break
                lam, nu = lam * nu, nu * 2.0
                if lam > 1e20:
                    status, msg = Status.CONVERGED, "converged (damping saturated: no decreasing step)"
                    break
        return self._finish(self.problem.unpad_values(params), status, msg, c0, cost, it, solves, t0, history, throw)


def optimize(
    factors: Sequence[Factor],
    values: Values,
    config: SolverConfig | None = None,
    *,
    throw: bool = False,
    fixed: Sequence[Variable] = (),
) -> SolverResult:
    """Analyse and solve in one call (GTSAM's ``optimizer.optimize()``); ``fixed`` variables
    are held constant."""
    return Solver(factors, values, config, fixed=fixed).solve(throw=throw)
