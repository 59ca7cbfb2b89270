"""Incremental smoothing: online Gauss-Newton as measurements arrive (iSAM2's job).

State (everything host-side numpy, append-only, capacity-doubling buffers)::

    variables   x (estimate), x_lin (linearisation point), delta (tangent, x = x_lin ⊕ delta)
    factors     grouped by class as in batch solves; per constraint the cached whitened
                Jacobian J and residual r at the x_lin of its variables
    the linear system   H = sum J^T J,  b = sum J^T r,  solved for delta

One :meth:`IncrementalSolver.update`:

1. adds variables and factors (handles returned), removes factors by handle;
2. *fluid relinearisation*: variables whose ``|delta|_inf`` exceeds the threshold get
   ``x_lin <- x, delta <- 0``; only their factors (and the new ones) are relinearised by a
   jitted kernel per factor class on chunks padded to 8, 64 or 512 rows (so a growing graph
   compiles each kernel at most three times);
3. a **windowed step**: the exact minimiser of the linear system over a window of
   variables with every other variable held at its current offset (one block Gauss-Seidel
   step, assembled from the cached blocks and solved by a dense or sparse Cholesky). The
   window is the variables of the last ``window`` updates plus every variable the update
   touched. A new factor that reaches further back (a loop closure) and disagrees with the
   current estimate (whitened chi^2 per residual dimension above ``loop_chi2``) widens the
   window back to its oldest variable, so the correction spreads over the whole loop; every
   ``full_solve_every`` updates the window is the whole graph. iSAM2 reaches the same end
   through its Bayes tree (re-eliminating the cliques from the touched variables to the
   root); here the solve of a window is a small sparse factorisation, fast enough to redo.
4. a scheduled full solve is skipped while it cannot gain anything: the solver keeps an
   upper bound on how far the linear model's cost is above its minimum (what new and
   relinearised constraints added since the last full solve, minus what windowed steps
   took off; a window absorbs a new odometry edge exactly, so a stretch without loop
   closures adds nothing; a strict bound for a linear problem, relinearisation counted as
   the change of the model's cost where it is). For pose graphs (one tangent size) the full step reads H from
   :class:`~jaxslam.solvers._blocks.BlockInformation`, kept current block by block as
   constraints are added, relinearised and removed, and factorised in a block
   fill-reducing order (no assembly, no scalar ordering: ~3x faster on parking-garage).

:meth:`IncrementalSolver.optimize` relinearises everything and runs the batch
Levenberg-Marquardt solver to convergence (the batch optimum). With ``lag`` set, variables
older than ``lag`` updates are marginalised (Schur complement) into a
:class:`~jaxslam.core.MarginalFactor` on the variables that remain, so the cost per update
stays bounded on a long tunnel (fixed-lag smoothing).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Sequence
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.sparse as sp

from ..core import Factor, Gaussian, MarginalFactor, Pose2Var, Pose3Var, Values, Variable, linearize
from ..errors import ConfigError, GraphError
from ..factors import BetweenFactor
from . import _factorkern, _liekern
from ._bayestree import BayesTree
from ._bayestree import NotPositiveDefinite as TreeNotPositiveDefinite
from ._blocks import BlockInformation, NotPositiveDefinite, pairs
from ._blocks import one_blas_thread as _one_blas_thread
from ._nls import Solver, SolverConfig, SolverResult
from ._problem import _check_factor, check_shared_leaves, group_key, shared_leaves

try:  # pragma: no cover - import guard
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, cholesky

    _HAVE_CHOLMOD = True
except ImportError:  # pragma: no cover
    _HAVE_CHOLMOD = False


@dataclasses.dataclass(frozen=True)
class IncrementalConfig:
    """Options of :class:`IncrementalSolver` (defaults chosen on sphere2500 and
    parking-garage, city10000 held out; see README)."""

    mode: Literal["incremental", "batch"] = "incremental"
    """``batch``: every update re-solves the whole graph with Levenberg-Marquardt (the
    reference, GTSAM's batch smoother); same API, so a pipeline switches by config."""
    engine: Literal["window", "bayes_tree"] = "window"
    """How an incremental update solves the linear system. ``window``: an exact step over a
    window of recent variables with the rest held, widened over a loop that disagrees, and a
    full solve every ``full_solve_every`` updates. ``bayes_tree``: iSAM2's algorithm, the
    system kept factorised as a Bayes tree whose top (the cliques above the touched
    variables) is re-eliminated at every update, then back-substituted with the
    ``wildfire`` threshold (``window``, ``loop_*`` and ``full_solve_*`` do not apply)."""
    wildfire: float = 0.001
    """``bayes_tree``: below the re-eliminated top, a subtree is back-substituted further
    only where a clique's offsets changed by more than this (iSAM2's wildfire threshold,
    0.001 by default there); 0 solves every clique at every update (exact, O(graph))."""
    relinearize_threshold: float | None = None
    """Relinearise a variable when its tangent offset from the linearisation point exceeds
    this (infinity norm). None: 0.05 for ``window`` (0.05 ended closer to the optimum on
    parking-garage at no measurable cost), 0.1 for ``bayes_tree`` (iSAM2's default)."""
    relinearize_skip: int | None = None
    """Check for variables to relinearise only every this many updates (iSAM2's
    ``relinearizeSkip``); 1 = at every update. None: 1 for ``window``, 10 for ``bayes_tree``
    (iSAM2's default: a check brings every offset up to date, and the relinearisations of
    ten updates re-eliminate their shared ancestors once)."""
    window: int = 10
    """Every update re-solves the variables of the last ``window`` updates (and all the
    update touched) with the rest held."""
    loop_chi2: float = 0.5
    """A factor reaching further back than ``window`` updates whose whitened chi^2 per
    residual dimension (at the current estimate) exceeds this widens the window over the
    whole loop (back to its oldest variable, minus ``loop_margin`` updates)."""
    loop_margin: int = 0
    full_solve_every: int = 10
    """Solve the whole linear system every this many updates (between full solves the cost
    drifts above the optimum of the linearised system: on sphere2500 by ~1 per update; 10
    kept the running cost at or below iSAM2's on sphere2500 and parking-garage). 20 halves
    the full solves and ended sphere2500 lower (1151.8, and 1147.6 with
    ``relinearize_threshold=0.1``) but left the running cost higher at most checkpoints of
    sphere2500 and city10000 (see README)."""
    full_solve_tol: float = 1e-9
    """Skip a scheduled full solve when it could lower the linearised cost by no more than
    this fraction, i.e. when it would change nothing: the solver bounds what a full solve
    can gain by what constraints added or relinearised since the last one brought minus
    what the windowed steps took off, and a window absorbs a new odometry edge exactly, so
    a stretch without loop closures adds nothing. The schedule keeps its phase. Negative:
    never skip."""
    linear_solver: Literal["auto", "cholmod", "splu"] = "auto"
    """Sparse solver of the full step (``auto``: CHOLMOD when installed)."""
    lag: int | None = None
    """Fixed-lag smoothing: marginalise variables added more than ``lag`` updates ago."""
    max_iterations: int = 100
    """:meth:`IncrementalSolver.optimize`: Levenberg-Marquardt iterations at most."""
    relative_tol: float = 1e-12
    """:meth:`IncrementalSolver.optimize`: stop when the cost decreases by less than this fraction."""
    chunk_sizes: tuple[int, ...] = (8, 64, 512)
    """Row counts the compiled kernels are padded to (ascending): each kernel compiles once
    per size and factor class, and a batch runs in chunks of the largest. Fewer sizes
    compile less (a cold start) and pad more (small updates do more work)."""
    compiled_factors: bool = True
    """Linearise ``BetweenFactor`` on Pose3 / Pose2 with Gaussian noise and no robust kernel
    with compiled per-row code (numba) instead of its JAX kernel: the same formulas, equal to
    1e-12, a few microseconds instead of ~0.1-0.3 ms per call. False: every factor through
    JAX."""


@dataclasses.dataclass
class UpdateResult:
    handles: list[int]
    """One handle per factor object passed in ``new_factors`` (for ``remove``)."""
    full_solve: bool
    """A fresh factorisation of the whole linear system was solved in this update."""
    relinearized: int
    """Number of variables relinearised in this update."""
    marginalized: int
    """Number of variables marginalised into the fixed-lag prior in this update."""
    time_s: float
    """Wall time of the update."""
    reeliminated: int = 0
    """Variables whose part of the linear system was factorised again in this update
    (iSAM2's ``variablesReeliminated``): ``bayes_tree``, the re-eliminated top; ``window``,
    the window's variables (every variable on a full solve); ``batch``, every variable."""
    linearize_s: float = 0.0
    """Of ``time_s``, the time spent linearising new and relinearised constraints (the
    compiled factor kernels and their Gram blocks; in ``batch`` mode the Levenberg-Marquardt
    iterations' own linearisations are not counted)."""


# --- storage --------------------------------------------------------------------------------
class _Store:
    """Values of one variable type: append-only rows."""

    def __init__(self, vtype: type[Variable], index: int):
        self.t = vtype
        self.index = index
        self.td = vtype.tangent_dim
        self.n = 0
        cap = 16
        self.ids = np.zeros(cap, np.int64)
        self.x = np.zeros((cap, vtype.param_dim))
        self.x_lin = np.zeros((cap, vtype.param_dim))
        self.delta = np.zeros((cap, self.td))
        self.dof = np.zeros(cap, np.int64)  # first global dof of each row (permanent)
        self.born = np.zeros(cap, np.int64)  # update number that added it
        self.live = np.zeros(cap, bool)  # False once marginalised
        self.vnum = np.zeros(cap, np.int64)  # the solver-wide variable number of each row
        self.row_of: dict[int, int] = {}

    def _grow(self, need: int) -> None:
        cap = len(self.ids)
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in ("ids", "x", "x_lin", "delta", "dof", "born", "live", "vnum"):
            old = getattr(self, name)
            arr = np.zeros((new, *old.shape[1:]), old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def add(self, ids: np.ndarray, params: np.ndarray, dof0: int, born: int) -> np.ndarray:
        for i in ids.tolist():
            if i in self.row_of:
                raise GraphError(f"{self.t.__name__} {i} already has a value (update it through factors)")
        k = len(ids)
        self._grow(self.n + k)
        rows = np.arange(self.n, self.n + k)
        at = slice(self.n, self.n + k)  # slices: cheaper than the index array for a row or two
        self.ids[at] = ids
        self.x[at] = params
        self.x_lin[at] = params
        self.delta[at] = 0.0
        self.dof[at] = dof0 + self.td * rows - self.td * self.n
        self.born[at] = born
        self.live[at] = True
        for i, r in zip(ids.tolist(), rows.tolist()):
            self.row_of[i] = r
        self.n += k
        return rows

    def rows(self, ids: np.ndarray, what: str) -> np.ndarray:
        out = np.empty(len(ids), np.int64)
        for k, i in enumerate(np.asarray(ids).reshape(-1).tolist()):
            r = self.row_of.get(i)
            if r is None:
                raise GraphError(f"{what} refers to {self.t.__name__} {i}, which has no value")
            out[k] = r
        return out


class _Group:
    """The constraints of one factor class (same slot types and residual dimension)."""

    def __init__(self, f: Factor, slots: tuple[int, ...]):
        self.ftype = type(f)
        self.index = 0  # its place in the solver's group list
        self.var_types = f.variable_types()
        self.slots = slots
        self.rdim = f.residual_dim
        self.tds = tuple(t.tangent_dim for t in self.var_types)
        self.col0 = np.concatenate([[0], np.cumsum(self.tds)]).astype(np.int64)
        self.T = int(self.col0[-1])
        leaves, self.treedef = jax.tree_util.tree_flatten(f)
        self.batched = [jnp.ndim(leaf) >= 1 for leaf in leaves]
        self.shared = shared_leaves(f)
        self.n = 0
        cap = 16
        self.buffers = [
            np.zeros((cap, *np.shape(leaf)[1:]), np.asarray(leaf).dtype) if b else None
            for leaf, b in zip(leaves, self.batched)
        ]
        self.rows = np.zeros((cap, len(slots)), np.int64)
        self.vars = np.zeros((cap, len(slots)), np.int64)  # solver-wide variable numbers
        self.alive = np.zeros(cap, bool)
        self.newest = np.zeros(cap, np.int64)  # latest update that added one of its variables
        self.J = np.zeros((cap, self.rdim, self.T))
        self.r = np.zeros((cap, self.rdim))
        # lower-triangle entries of the (T x T) Gram matrix emitted per constraint
        sel_p, sel_q = [], []
        for a in range(len(self.tds)):
            for b in range(a, len(self.tds)):
                for p in range(self.tds[a]):
                    for q in range(self.tds[b]):
                        if a == b and q > p:
                            continue
                        sel_p.append(self.col0[a] + p)
                        sel_q.append(self.col0[b] + q)
        self.sel_p = np.asarray(sel_p, np.int64)
        self.sel_q = np.asarray(sel_q, np.int64)
        self.G = np.zeros((cap, self.T, self.T))  # J^T J per constraint (cached: no delta in it)
        self.b = np.zeros((cap, self.T))  # J^T r per constraint (at x_lin)
        # slots of its Gram blocks in the solver's BlockInformation (-1: not there yet)
        self.bslots = np.full((cap, len(pairs(len(slots)))), -1, np.int64)
        # BetweenFactor on Pose3 / Pose2, Gaussian, no robust kernel: the compiled kernel
        # (_factorkern) and the leaf positions of its measurement and square-root information
        self.compiled: Any = None
        kern = {Pose3Var: _factorkern.between_se3, Pose2Var: _factorkern.between_se2}.get(self.var_types[0])
        if type(f) is BetweenFactor and kern is not None and f.robust is None and type(f.noise) is Gaussian:
            at = {id(leaf): k for k, leaf in enumerate(leaves)}
            kz, kl = at.get(id(f.measured)), at.get(id(f.noise.sqrt_info))
            if kz is not None and kl is not None and self.buffers[kz] is not None and self.buffers[kl] is not None:
                self.compiled = (kern, kz, kl)

    def _grow(self, need: int) -> None:
        cap = len(self.alive)
        if need <= cap:
            return
        new = max(need, 2 * cap)

        def g(old: np.ndarray) -> np.ndarray:
            arr = np.zeros((new, *old.shape[1:]), old.dtype)
            arr[:cap] = old
            return arr

        self.buffers = [None if b is None else g(b) for b in self.buffers]
        self.rows, self.alive, self.J, self.r = g(self.rows), g(self.alive), g(self.J), g(self.r)
        self.G, self.b, self.vars = g(self.G), g(self.b), g(self.vars)
        self.newest = g(self.newest)
        bslots = np.full((new, self.bslots.shape[1]), -1, np.int64)
        bslots[:cap] = self.bslots
        self.bslots = bslots

    def add(self, f: Factor, rows: np.ndarray, newest: np.ndarray) -> np.ndarray:
        leaves = jax.tree_util.tree_leaves(f)
        k = f.num_constraints
        self._grow(self.n + k)
        idx = np.arange(self.n, self.n + k)
        for buf, leaf in zip(self.buffers, leaves):
            if buf is not None:
                buf[idx] = np.asarray(leaf)
        self.rows[idx] = rows
        self.newest[idx] = newest
        self.alive[idx] = True
        self.n += k
        return idx

    def subset(self, idx: np.ndarray) -> Factor:
        return jax.tree_util.tree_unflatten(self.treedef, self.subset_leaves(idx))

    def subset_leaves(self, idx: np.ndarray) -> list[Any]:
        return [s if b is None else b[idx] for s, b in zip(self.shared, self.buffers)]


_KERNELS: dict[Any, Any] = {}  # factor treedef -> its jitted linearisation


def _linearize_kernel(treedef: Any) -> Any:
    """The jitted linearisation of one factor class, on its flat leaves: ``(leaves, params,
    mask) -> (m, rdim * T + rdim + 1)`` rows ``[J | r | cost]``. Taking the leaves (not a
    factor object) skips building and flattening a factor per call, and one output is one
    transfer (8 rows of ``BetweenFactor`` on Pose3, loaded machine: 130-160 us per call
    against 165-177 us through a factor pytree and three outputs; the arithmetic is the
    same, results equal to the bit)."""
    cached = _KERNELS.get(treedef)
    if cached is not None:
        return cached

    @jax.jit
    def kernel(leaves: list[Any], params: tuple[jax.Array, ...], mask: jax.Array) -> jax.Array:
        lin = linearize(jax.tree_util.tree_unflatten(treedef, leaves), params, mask)
        J = jnp.concatenate(lin.jacobians, axis=2)
        m = J.shape[0]
        return jnp.concatenate([J.reshape(m, -1), lin.residual, lin.cost[:, None]], axis=1)

    _KERNELS[treedef] = kernel
    return kernel


@functools.partial(jax.jit, static_argnames=("vtype",))
def _retract(vtype: type[Variable], x: jax.Array, d: jax.Array) -> jax.Array:
    return vtype.retract(x, d)


def _np_retract(vtype: type[Variable], x: np.ndarray, d: np.ndarray) -> np.ndarray | None:
    """``x ⊕ d`` without JAX for the common types (a few rows per update: no JAX dispatch;
    compiled, :mod:`._liekern`); None for other types. Same formulas as ``jaxslam.lie``
    (tested against it)."""
    name = getattr(vtype.group, "__name__", None)
    if vtype.group is None:
        return x + d
    if name in ("SO3", "SE3"):
        return _liekern.retract_so3_se3(np.ascontiguousarray(x), np.ascontiguousarray(d), name == "SE3")
    if name == "SE2":
        return _liekern.retract_se2(np.ascontiguousarray(x), np.ascontiguousarray(d))
    return None


def _pad_rows(a: np.ndarray, cap: int) -> np.ndarray:
    if len(a) == cap:
        return a
    out = np.empty((cap, *a.shape[1:]), a.dtype)
    out[: len(a)] = a
    out[len(a) :] = a[:1] if len(a) else 0
    return out


_DENSE_MAX = 240  # systems up to this many dofs are solved densely
_ADJ_LOOP_MAX = 32  # moved variables up to this many: their constraints through the adjacency dict


def _chunks(m: int, sizes: tuple[int, ...]):
    """``(lo, hi, cap)`` pieces covering ``range(m)``, each padded to one of the compiled
    ``sizes``, so an ever-growing graph compiles each kernel at most ``len(sizes)`` times per
    factor class."""
    lo = 0
    while lo < m:
        rest = m - lo
        cap = next((c for c in sizes if rest <= c), sizes[-1])
        hi = min(m, lo + cap)
        yield lo, hi, cap
        lo = hi


class IncrementalSolver:
    """Online nonlinear least squares with GTSAM's ISAM2 usage pattern::

    solver = IncrementalSolver()
    solver.update([prior, odometry], Values.create({Pose3Var(np.array([0, 1])): ...}))
    ...
    handles = solver.update([loop_closure]).handles
    solver.estimate()                 # Values of every variable
    solver.marginal_covariance(Pose3Var(np.array([7])))
    solver.update(remove=handles)     # remove factors by handle
    solver.optimize()                 # full relinearisation to the batch optimum
    """

    def __init__(self, config: IncrementalConfig | None = None):
        self.config = config or IncrementalConfig()
        if self.config.linear_solver == "cholmod" and not _HAVE_CHOLMOD:
            raise ValueError("linear solver 'cholmod' needs scikit-sparse (pip install 'jaxslam[cholmod]')")
        self._method = "cholmod" if self.config.linear_solver in ("auto", "cholmod") and _HAVE_CHOLMOD else "splu"
        tree = self.config.engine == "bayes_tree"
        thr, skip = self.config.relinearize_threshold, self.config.relinearize_skip
        self._relin_threshold = float((0.1 if tree else 0.05) if thr is None else thr)
        self._relin_skip = int((10 if tree else 1) if skip is None else skip)
        if self._relin_skip < 1:
            raise ConfigError(f"relinearize_skip must be >= 1 (1: check at every update), got {self._relin_skip}")
        cs = tuple(self.config.chunk_sizes)
        if not cs or any(c < 1 for c in cs) or list(cs) != sorted(set(cs)):
            raise ConfigError(f"chunk_sizes must be distinct positive row counts in ascending order, got {cs}")
        self.stores: dict[type[Variable], _Store] = {}
        self.groups: dict[Any, _Group] = {}
        self._group_list: list[_Group] = []
        self._adj: dict[tuple[int, int], list[tuple[int, int]]] = {}  # (store, row) -> [(group, constraint)]
        self._handles: dict[int, tuple[int, np.ndarray]] = {}
        self._next_handle = 0
        self._ndof = 0
        self.updates = 0
        self._since_full = 0
        self.full_solves = 0
        # Upper bound on how much a full solve could lower the linear model's cost: what new
        # and relinearised constraints added since the last full solve, minus what windowed
        # steps took off (inf: unknown). And the model's cost right after that full solve.
        self._excess_bound = np.inf
        self._model_at_full = 0.0
        self.block_assembly = True  # block (BSR) assembly of large windows when all tangents match
        # pose graphs (one tangent size, no marginalisation): H kept as blocks between full
        # solves (created at the first large full solve; None until then or when off)
        self._blocks: BlockInformation | None = None
        self._blocks_off = self.config.lag is not None or self._method != "cholmod"
        self._store_list: list[_Store] = []
        if self.config.engine not in ("window", "bayes_tree"):
            raise ConfigError(f"engine must be 'window' or 'bayes_tree', got {self.config.engine!r}")
        if self.config.engine == "bayes_tree" and self.config.lag is not None:
            raise ConfigError("fixed-lag smoothing (lag) needs engine='window'")
        if not self.config.wildfire >= 0.0:
            raise ConfigError(f"wildfire must be >= 0, got {self.config.wildfire}")
        self._tree = BayesTree(self.config.wildfire) if self.config.engine == "bayes_tree" else None
        self._tree_stale = False  # every linearisation changed: re-eliminate all at the next update
        self._nvar = 0
        self._lin_s = 0.0  # linearisation time of the current update
        self._reelim = 0  # variables re-factorised by the current update

    # --- variables and factors -------------------------------------------------------------
    def _store(self, vtype: type[Variable]) -> _Store:
        s = self.stores.get(vtype)
        if s is None:
            s = _Store(vtype, len(self._store_list))
            if any(o.td != s.td for o in self._store_list):
                self._blocks, self._blocks_off = None, True
            self.stores[vtype] = s
            self._store_list.append(s)
        return s

    def _add_values(
        self, values: list[tuple[type[Variable], np.ndarray, np.ndarray]]
    ) -> list[tuple[_Store, np.ndarray]]:
        """Add the variables ``(type, ids, params)`` that :meth:`_validate` checked."""
        out = []
        for vtype, ids, params in values:
            s = self._store(vtype)
            rows = s.add(ids, params, self._ndof, self.updates)
            if self._tree is not None:
                s.vnum[rows] = self._tree.add_vars(s.dof[rows], s.td)
            else:
                s.vnum[rows] = np.arange(self._nvar, self._nvar + len(rows))
            self._nvar += len(rows)
            self._ndof += s.td * len(ids)
            out.append((s, rows))
        return out

    def _add_factor(
        self, f: Factor, index: int, checked: tuple[int, Any] | None = None
    ) -> tuple[int, list[tuple[int, int]]]:
        """Add factor ``f`` (``checked``: its constraint count and group key from
        :meth:`_validate`, else found here)."""
        n, key = checked if checked is not None else (_check_factor(f, index), group_key(f))
        rows = []
        slots = []
        for v in f.variables:
            s = self.stores.get(type(v))
            if s is None:
                raise GraphError(f"{type(f).__name__} (factor {index}) uses {type(v).__name__}, which has no values")
            r = s.rows(np.asarray(v.ids), f"{type(f).__name__} (factor {index})")
            if not np.all(s.live[r]):
                dead = int(np.asarray(v.ids).reshape(-1)[~s.live[r]][0])
                raise GraphError(
                    f"{type(f).__name__} (factor {index}) uses {type(v).__name__} {dead}, which was marginalised"
                )
            rows.append(r)
            slots.append(s.index)
        g = self.groups.get(key)
        if g is None:
            g = _Group(f, tuple(slots))
            g.index = len(self._group_list)
            self.groups[key] = g
            self._group_list.append(g)
        gi = g.index
        born = [self._store_list[si].born[r] for si, r in zip(slots, rows)]
        newest = np.max(np.stack(born, axis=1), axis=1) if n else np.zeros(0, np.int64)
        idx = g.add(f, np.stack(rows, axis=1) if n else np.zeros((0, len(rows)), np.int64), newest)
        for k, (si, r) in enumerate(zip(slots, rows)):
            g.vars[idx, k] = self._store_list[si].vnum[r]
        for slot, r in zip(slots, rows):
            for c, vr in zip(idx.tolist(), r.tolist()):
                self._adj.setdefault((slot, vr), []).append((gi, c))
        h = self._next_handle
        self._next_handle += 1
        self._handles[h] = (gi, idx)
        return h, [(gi, int(c)) for c in idx]

    # --- linearisation -----------------------------------------------------------------------
    def _linearize_rows(
        self, g: _Group, idx: np.ndarray, at: str, want_cost: bool = False
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """Whitened J, r (and total cost) of constraints ``idx`` at x_lin (``at="lin"``) or at
        the estimate (``at="x"``)."""
        if g.compiled is not None and self.config.compiled_factors:
            kern, kz, kl = g.compiled
            xi, xj = (
                getattr(self._store_list[s], "x_lin" if at == "lin" else "x")[g.rows[idx, k]]
                for k, s in enumerate(g.slots)
            )
            Jc, rc, costs = kern(xi, xj, g.buffers[kz][idx], g.buffers[kl][idx])
            return Jc, rc, float(costs.sum()) if want_cost else 0.0
        J = np.empty((len(idx), g.rdim, g.T))
        r = np.empty((len(idx), g.rdim))
        cost = 0.0
        kernel = _linearize_kernel(g.treedef)
        nj = g.rdim * g.T
        for lo, hi, cap in _chunks(len(idx), self.config.chunk_sizes):
            pidx = _pad_rows(idx[lo:hi], cap)
            params = tuple(
                getattr(self._store_list[s], "x_lin" if at == "lin" else "x")[g.rows[pidx, k]]
                for k, s in enumerate(g.slots)
            )
            out = np.asarray(kernel(g.subset_leaves(pidx), params, np.arange(cap) < hi - lo))
            J[lo:hi] = out[: hi - lo, :nj].reshape(hi - lo, g.rdim, g.T)
            r[lo:hi] = out[: hi - lo, nj:-1]
            if want_cost:  # over the padded rows too (masked: 0), summed as before
                cost += float(np.ascontiguousarray(out[:, -1]).sum())
        return J, r, cost

    def _relinearize(self, gi: int, idx: np.ndarray) -> None:
        """Recompute J, r of constraints ``idx`` of group ``gi`` at their variables' x_lin."""
        g = self._group_list[gi]
        idx = np.unique(idx)
        idx = idx[g.alive[idx]]
        if idx.size == 0:
            return
        t0 = time.perf_counter()
        J, g.r[idx], _ = self._linearize_rows(g, idx, "lin")
        g.J[idx] = J
        G, g.b[idx] = self._gram(J, g.r[idx])
        self._lin_s += time.perf_counter() - t0
        B = self._blocks
        if B is not None:  # the blocks change by new - old (a new constraint's old G is 0)
            var = self._block_vars(g, idx)
            fresh = g.bslots[idx, 0] < 0
            if np.any(fresh):
                g.bslots[idx[fresh]] = B.slots(var[fresh])
            B.add(g.bslots[idx], var, G - g.G[idx])
        g.G[idx] = G

    def _set_estimate(self, s: _Store, rows: np.ndarray) -> None:
        fast = _np_retract(s.t, s.x_lin[rows], s.delta[rows])
        if fast is not None:
            s.x[rows] = fast
            return
        for lo, hi, cap in _chunks(len(rows), self.config.chunk_sizes):
            pr = _pad_rows(rows[lo:hi], cap)
            s.x[rows[lo:hi]] = np.asarray(_retract(s.t, s.x_lin[pr], s.delta[pr]))[: hi - lo]

    # --- update ------------------------------------------------------------------------------
    def update(
        self,
        new_factors: Sequence[Factor] = (),
        new_values: Values | None = None,
        *,
        remove: Sequence[int] = (),
    ) -> UpdateResult:
        """Add ``new_values`` (variables not seen before) and ``new_factors``, remove the
        factors with handles ``remove``, and update the estimate."""
        t0 = time.perf_counter()
        self._lin_s, self._reelim = 0.0, 0
        cfg = self.config
        affected: dict[int, set[int]] = {}  # store -> rows
        dirty: dict[int, list[int]] = {}  # group -> constraints to relinearise
        dirty_arrays: dict[int, list[np.ndarray]] = {}  # more of them, as arrays
        removed_vars: list[np.ndarray] = []
        new_vars: list[np.ndarray] = []
        checked_values, checked_factors = self._validate(new_factors, new_values, remove)
        if checked_values:
            for s, rows in self._add_values(checked_values):
                affected.setdefault(s.index, set()).update(rows.tolist())
                new_vars.append(s.vnum[rows])
        handles = []
        new_refs: list[tuple[int, int]] = []
        for i, f in enumerate(new_factors):
            h, refs = self._add_factor(f, i, checked_factors[i])
            handles.append(h)
            new_refs.extend(refs)
        for h in remove:
            gi, idx = self._handles.pop(h)
            g = self._group_list[gi]
            if self._blocks is not None:
                live = idx[g.alive[idx] & (g.bslots[idx, 0] >= 0)]
                self._blocks.add(g.bslots[live], self._block_vars(g, live), g.G[live], -1.0)
            g.alive[idx] = False
            g.J[idx] = 0.0
            g.r[idx] = 0.0
            g.G[idx] = 0.0
            g.b[idx] = 0.0
            removed_vars.append(g.vars[idx].ravel())
            for k, si in enumerate(g.slots):
                affected.setdefault(si, set()).update(g.rows[idx, k].tolist())
        for gi, c in new_refs:
            dirty.setdefault(gi, []).append(c)
            g = self._group_list[gi]
            for k, si in enumerate(g.slots):
                affected.setdefault(si, set()).add(int(g.rows[c, k]))
        # fluid relinearisation
        nrelin = 0
        moved_rows = []
        # every k-th update, counting from 1 as iSAM2 does (its 10th, 20th, ... update)
        check = (self.updates + 1) % self._relin_skip == 0
        if check:
            self.flush()
        for s in self._store_list:
            moved = np.zeros(0, np.int64)
            if s.n and check:
                moved = np.nonzero(s.live[: s.n] & (np.max(np.abs(s.delta[: s.n]), axis=1) > self._relin_threshold))[0]
            moved_rows.append(moved)
            nrelin += moved.size
            if moved.size <= _ADJ_LOOP_MAX:
                for r in moved.tolist():
                    for gi, c in self._adj.get((s.index, r), ()):
                        dirty.setdefault(gi, []).append(c)
                continue
            # many moved (a relinearisation step moves most of a drifting graph): every
            # group's constraints on them at once instead of a dict lookup per variable
            hit = np.zeros(s.n, bool)
            hit[moved] = True
            for g in self._group_list:
                for k, si in enumerate(g.slots):
                    if si == s.index and g.n:
                        dirty_arrays.setdefault(g.index, []).append(np.nonzero(hit[g.rows[: g.n, k]])[0])
        dirty_idx = {
            gi: np.unique(np.concatenate([np.asarray(dirty.get(gi, ()), np.int64), *dirty_arrays.get(gi, ())]))
            for gi in sorted(dirty.keys() | dirty_arrays.keys())
        }
        # the linear model's cost changes by what the new and relinearised constraints
        # bring (a new constraint had J = r = 0): the bound on what a full solve can gain
        window = self._tree is None
        model_before = 0.0
        if window:
            model_before = sum(self._model_cost(self._group_list[gi], idx) for gi, idx in dirty_idx.items())
        for s, moved in zip(self._store_list, moved_rows):
            if moved.size:
                s.x_lin[moved] = s.x[moved]
                s.delta[moved] = 0.0
                if self._tree is not None:
                    self._tree.dx[(s.dof[moved][:, None] + np.arange(s.td)).ravel()] = 0.0
        for gi, idx in dirty_idx.items():
            self._relinearize(gi, idx)
        model_after = 0.0
        if window:
            model_after = sum(self._model_cost(self._group_list[gi], idx) for gi, idx in dirty_idx.items())
        self._excess_bound += max(0.0, model_after - model_before)
        if len(remove):
            self._excess_bound = np.inf  # removing a factor can lower the optimum: no bound
        # windowed step: the recent variables and everything the update touched; a loop
        # closure that disagrees with the estimate widens the window over the whole loop;
        # every ``full_solve_every`` updates the whole system is solved.
        if cfg.mode == "batch":
            self.optimize()
            nmarg = self._marginalize() if cfg.lag is not None else 0
            self.updates += 1
            return self._result(handles, True, nrelin, nmarg, t0, self._live_vars())
        if self._tree is not None:
            new_fac: dict[int, list[int]] = {}
            for gi, c in new_refs:
                new_fac.setdefault(gi, []).append(c)
            marked = list(new_vars)
            marked += [self._group_list[gi].vars[idx].ravel() for gi, idx in dirty_idx.items()]
            full = self._tree_update(marked + removed_vars, new_fac)
            self.updates += 1
            return self._result(handles, full, nrelin, 0, t0, self._tree.last_reeliminated)
        loop_t0 = self._loop_window(new_refs)
        due = self._since_full + 1 >= cfg.full_solve_every
        full = due and self._full_solve_needed()  # a skipped one would have changed nothing
        if full:
            w0 = 0
        elif loop_t0 is not None:
            w0 = max(0, loop_t0 - cfg.loop_margin)
        else:
            w0 = max(0, self.updates - cfg.window)
        self._window_solve(w0, affected)
        if full or w0 == 0:
            self.full_solves += 1
        # the schedule keeps its phase through a skipped full solve
        self._since_full = 0 if due or w0 == 0 else self._since_full + 1
        nmarg = self._marginalize() if cfg.lag is not None else 0
        if nmarg:
            self._excess_bound = np.inf
        self.updates += 1
        return self._result(handles, full, nrelin, nmarg, t0, self._reelim)

    def _result(self, handles: list[int], full: bool, nrelin: int, nmarg: int, t0: float, reelim: int) -> UpdateResult:
        return UpdateResult(handles, full, nrelin, nmarg, time.perf_counter() - t0, reelim, self._lin_s)

    def _live_vars(self) -> int:
        return sum(int(s.live[: s.n].sum()) for s in self._store_list)

    def _tree_update(self, marked: list[np.ndarray], new_fac: dict[int, list[int]]) -> bool:
        """The Bayes tree's step: re-eliminate above the ``marked`` variables (adding the
        constraints ``new_fac``), back-substitute, and move the estimate of every variable
        whose offset was recomputed. True when every variable was re-eliminated."""
        tree = self._tree
        if tree is None:
            return False
        fac = {gi: np.asarray(cs, np.int64) for gi, cs in new_fac.items()}
        if self._tree_stale:  # every linearisation changed: eliminate everything afresh
            tree.clear()
            fac = {gi: np.nonzero(g.alive[: g.n])[0] for gi, g in enumerate(self._group_list) if g.n}
            marked = [s.vnum[np.nonzero(s.live[: s.n])[0]] for s in self._store_list]
            self._tree_stale = False
        allm = np.concatenate(marked) if marked else np.zeros(0, np.int64)
        try:
            changed = tree.update(allm, fac, self._group_list)
        except TreeNotPositiveDefinite as err:
            self._tree_stale = True  # the tree lost its top: rebuild it at the next update
            raise GraphError(
                "the linear system is not positive definite: some variables are under-constrained "
                "(add a prior on one variable of each connected component)"
            ) from err
        self._sync_offsets(changed)
        return tree.last_reeliminated == self._live_vars()

    def _sync_offsets(self, vnums: np.ndarray) -> None:
        """Copy the Bayes tree's offsets of variables ``vnums`` into the stores and move
        their estimates."""
        tree = self._tree
        if tree is None or vnums.size == 0:
            return
        for s in self._store_list:
            if s.n == 0:
                continue
            lo, hi = s.vnum[0], s.vnum[s.n - 1]
            # a store's variable numbers increase with its rows
            mine = vnums[(vnums >= lo) & (vnums <= hi)]
            if mine.size == 0:
                continue
            rows = np.searchsorted(s.vnum[: s.n], mine)
            ok = s.vnum[rows] == mine
            rows = rows[ok]
            if rows.size == 0:
                continue
            s.delta[rows] = tree.dx[s.dof[rows][:, None] + np.arange(s.td)]
            self._set_estimate(s, rows)

    def flush(self) -> None:
        """Bring every offset and estimate up to date: the Bayes tree engine back-substitutes
        lazily (:meth:`estimate`, :meth:`cost` and the relinearisation check call this;
        :meth:`value` updates only the one variable's path). Nothing to do for ``window``."""
        if self._tree is not None and self._tree.pending:
            self._sync_offsets(self._tree.solve_pending())

    def _tree_full(self) -> None:
        """Re-eliminate and solve everything now (the exact Gauss-Newton step)."""
        if self._tree is None:
            return
        self._tree_stale = True  # every variable re-eliminated, every clique solved
        self._tree_update([], {})

    def _validate(
        self, factors: Sequence[Factor], values: Values | None, remove: Sequence[int]
    ) -> tuple[list[tuple[type[Variable], np.ndarray, np.ndarray]], list[tuple[int, Any]]]:
        """Reject a bad update before anything changes (so a rejected update loses nothing).
        Returns the new values as numpy ``(type, ids, params)`` and each factor's constraint
        count and group key."""
        fresh: dict[type[Variable], set[int]] = {}
        checked_values = []
        checked_factors = []
        if values is not None:
            for vtype in values.types():
                ids = np.asarray(values.ids(vtype), np.int64)
                params = np.asarray(values.params(vtype), np.float64)
                if not np.all(np.isfinite(params)):
                    raise GraphError(f"{vtype.__name__} values are not finite (NaN or inf)")
                if len(ids):
                    checked_values.append((vtype, ids, params))
                s = self.stores.get(vtype)
                for i in ids.tolist():
                    if s is not None and i in s.row_of:
                        raise GraphError(f"{vtype.__name__} {i} already has a value (update it through factors)")
                fresh[vtype] = set(ids.tolist())
        for h in remove:
            if h not in self._handles:
                raise GraphError(f"no factor with handle {h} (already removed?)")
        shared: dict[Any, list[Any]] = {}  # per group key: the shared leaves the group keeps
        for k, f in enumerate(factors):
            n = _check_factor(f, k)
            key = group_key(f)
            checked_factors.append((n, key))
            g = self.groups.get(key)
            check_shared_leaves(g.shared if g is not None else shared.setdefault(key, shared_leaves(f)), f)
            for v in f.variables:
                vt = type(v)
                s = self.stores.get(vt)
                new = fresh.get(vt, set())
                for i in np.asarray(v.ids).reshape(-1).tolist():
                    if i in new:
                        continue
                    r = None if s is None else s.row_of.get(i)
                    if s is None or r is None:
                        raise GraphError(
                            f"{type(f).__name__} (factor {k}) refers to {vt.__name__} {i}, which has no value"
                        )
                    if not s.live[r]:
                        raise GraphError(
                            f"{type(f).__name__} (factor {k}) uses {vt.__name__} {i}, which was marginalised"
                        )
        return checked_values, checked_factors

    def _loop_window(self, refs: list[tuple[int, int]]) -> int | None:
        """Update number of the oldest variable on a loop that a new factor closes with a
        large residual (whitened chi^2 per dimension above ``loop_chi2``), else None."""
        cfg = self.config
        oldest = None
        for gi, c in refs:
            g = self._group_list[gi]
            born = min(int(self._store_list[s].born[g.rows[c, k]]) for k, s in enumerate(g.slots))
            if self.updates - born < cfg.window:
                continue
            e = g.r[c] + g.J[c] @ self._stacked_delta(g, np.asarray([c]))[0]
            if float(e @ e) > cfg.loop_chi2 * g.rdim:
                oldest = born if oldest is None else min(oldest, born)
        return oldest

    def _full_solve_needed(self) -> bool:
        """Whether a full solve could lower the linear model's cost by more than
        ``full_solve_tol`` of it (:attr:`_excess_bound` says by how much at most; below 1e-12,
        a millionth of a standard deviation squared, is rounding)."""
        tol = self.config.full_solve_tol
        if tol < 0:
            return True
        return not self._excess_bound <= tol * (self._model_at_full + self._excess_bound) + 1e-12

    def _model_cost(self, g: _Group, idx: np.ndarray) -> float:
        """The linear model's cost ``|r + J delta|^2 / 2`` of constraints ``idx``."""
        if idx.size == 0:
            return 0.0
        e = self._linear_residual(g, idx)
        return 0.5 * float(np.einsum("mr,mr->", e, e))

    def _linear_residual(self, g: _Group, idx: np.ndarray) -> np.ndarray:
        """``r + J delta`` of constraints ``idx`` (the linear model's whitened residual)."""
        return g.r[idx] + np.einsum("mrt,mt->mr", g.J[idx], self._stacked_delta(g, idx))

    def _stacked_delta(self, g: _Group, idx: np.ndarray) -> np.ndarray:
        return np.concatenate([self._store_list[s].delta[g.rows[idx, k]] for k, s in enumerate(g.slots)], axis=1)

    # --- windowed step ----------------------------------------------------------------------
    def _window_solve(self, t0: int, extra: dict[int, set[int]]) -> None:
        """Exact minimiser of the linear model over the variables added at update ``t0`` or
        later plus ``extra`` (store -> rows), all other variables held (a block Gauss-Seidel
        step; ``t0 = 0`` solves the whole system)."""
        if t0 == 0 and self._full_solve_blocks():
            return
        system = self._window_system(t0, extra)
        if system is None:
            return
        wmap, _, solve, grad, model = system
        self._reelim = sum(int(np.count_nonzero(w >= 0)) for w in wmap)
        step = solve(-grad)
        decrease = max(0.0, -0.5 * float(grad @ step))  # the exact minimiser's: g^T H^-1 g / 2
        if t0 == 0:
            self._excess_bound, self._model_at_full = 0.0, model - decrease
        else:
            self._excess_bound = max(0.0, self._excess_bound - decrease)
        for s, w in zip(self._store_list, wmap):
            rows = np.nonzero(w >= 0)[0]
            if rows.size == 0:
                continue
            s.delta[rows] += step[w[rows][:, None] + np.arange(s.td)]
            self._set_estimate(s, rows)

    def _window_system(
        self, t0: int, extra: dict[int, set[int]]
    ) -> tuple[list[np.ndarray], int, Any, np.ndarray, float] | None:
        """The linear system of a window (see :meth:`_window_solve`), factorised: per store
        the compact dof of each row (-1 = held), its size, ``solve(rhs)``, the gradient of
        the linear model there and the model's cost over the window's constraints; None for
        an empty window."""
        wmap: list[np.ndarray] = []  # per store: compact dof start of each row, -1 = held
        n = 0
        for s in self._store_list:
            m = s.live[: s.n] & (s.born[: s.n] >= t0)
            ex = extra.get(s.index)
            if ex:
                rows = np.fromiter(ex, np.int64, len(ex))
                m[rows[s.live[rows]]] = True
            idx = np.nonzero(m)[0]
            w = np.full(s.n, -1, np.int64)
            w[idx] = n + s.td * np.arange(len(idx))
            n += s.td * len(idx)
            wmap.append(w)
        if n == 0:
            return None
        extra_fac: dict[int, set[int]] = {}
        for si, ex_rows in extra.items():
            for r in ex_rows:
                for gi, c in self._adj.get((si, r), ()):
                    extra_fac.setdefault(gi, set()).add(c)
        tds = {s.td for s in self._store_list if s.n}
        # One tangent size (pose graphs): assemble 6x6 (3x3) blocks, not scalar entries.
        blockwise = n > _DENSE_MAX and len(tds) == 1 and self.block_assembly
        bt = next(iter(tds)) if blockwise else 1
        nb = n // bt
        rows_l, cols_l, data_l = [], [], []
        grad = np.zeros(n)
        model = 0.0
        for gi, g in enumerate(self._group_list):
            sel = g.alive[: g.n] & (g.newest[: g.n] >= t0)
            ef = extra_fac.get(gi)
            if ef:
                sel[np.fromiter(ef, np.int64, len(ef))] = True
                sel &= g.alive[: g.n]
            idx = np.nonzero(sel)[0]
            if idx.size == 0:
                continue
            J = g.J[idx]
            e = self._linear_residual(g, idx)
            model += 0.5 * float(np.einsum("mr,mr->", e, e))
            base = np.stack([wmap[si][g.rows[idx, k]] for k, si in enumerate(g.slots)], axis=1)  # (m, k)
            col = np.concatenate([base[:, k : k + 1] + np.arange(g.tds[k]) for k in range(len(g.slots))], axis=1)
            for k in range(len(g.slots)):
                col[base[:, k] < 0, g.col0[k] : g.col0[k + 1]] = -1
            gv = np.einsum("mra,mr->ma", J, e)
            kg = col >= 0
            grad += np.bincount(col[kg], weights=gv[kg], minlength=n)
            G = g.G[idx]
            if blockwise:
                for a in range(len(g.slots)):
                    for b in range(len(g.slots)):
                        ok = (base[:, a] >= 0) & (base[:, b] >= 0)
                        rows_l.append(base[ok, a] // bt * nb + base[ok, b] // bt)
                        data_l.append(G[ok][:, g.col0[a] : g.col0[a + 1], g.col0[b] : g.col0[b + 1]])
                continue
            gp, gq = col[:, g.sel_p], col[:, g.sel_q]
            keep = (gp >= 0) & (gq >= 0)
            rows_l.append(np.maximum(gp, gq)[keep])
            cols_l.append(np.minimum(gp, gq)[keep])
            data_l.append(G[:, g.sel_p, g.sel_q][keep])
        if blockwise:
            keys = np.concatenate(rows_l)
            blocks = np.concatenate(data_l)
            order = np.argsort(keys, kind="stable")
            uniq, start = np.unique(keys[order], return_index=True)
            data = np.add.reduceat(blocks[order], start, axis=0)
            brow = uniq // nb
            indptr = np.searchsorted(brow, np.arange(nb + 1)).astype(np.int32)
            H = sp.bsr_matrix((data, (uniq % nb).astype(np.int32), indptr), shape=(n, n)).tocsc()
            if self._method != "cholmod":  # the other paths take the lower triangle only
                H = sp.tril(H, format="csc")
            diag = H.diagonal()
            if np.any(diag == 0.0):
                H = H + sp.diags((diag == 0.0).astype(float), format="csc")
            solve = self._factorize(H)
        else:
            rr = np.concatenate([*rows_l, np.arange(n)])
            cc = np.concatenate([*cols_l, np.arange(n)])
            dd = np.concatenate([*data_l, np.zeros(n)])
            if n <= _DENSE_MAX:  # a few variables: dense Cholesky, no sparse bookkeeping
                Hd = np.bincount(rr * n + cc, weights=dd, minlength=n * n).reshape(n, n)
                Hd += np.tril(Hd, -1).T
                dz = np.diag(Hd) == 0.0
                Hd[dz, dz] = 1.0  # variables without factors stay put
                solve = self._dense_factorize(Hd)
            else:
                H = sp.csc_matrix((dd, (rr, cc)), shape=(n, n))
                diag = H.diagonal()
                if np.any(diag == 0.0):  # variables without factors stay put
                    H = H + sp.diags((diag == 0.0).astype(float), format="csc")
                solve = self._factorize(H)
        return wmap, n, solve, grad, model

    # --- full step of a pose graph: H kept as blocks --------------------------------------------
    def _block_vars(self, g: _Group, idx: np.ndarray) -> np.ndarray:
        """Variable numbers ``(m, k)`` of constraints ``idx`` in the block system (permanent
        dof / tangent size)."""
        return np.stack([self._store_list[si].dof[g.rows[idx, k]] // g.tds[k] for k, si in enumerate(g.slots)], axis=1)

    def _full_solve_blocks(self) -> bool:
        """The full step through :class:`BlockInformation` (pose graphs above the dense size);
        False when that path does not apply (the caller assembles the system instead)."""
        if self._blocks_off or self._ndof <= _DENSE_MAX:
            return False
        td = self._store_list[0].td
        B = self._blocks
        if B is None:  # first time: every live constraint's Gram blocks in
            B = self._blocks = BlockInformation(td)
            for g in self._group_list:
                idx = np.nonzero(g.alive[: g.n])[0]
                if idx.size:
                    var = self._block_vars(g, idx)
                    g.bslots[idx] = B.slots(var)
                    B.add(g.bslots[idx], var, g.G[idx])
        grad = np.zeros(self._ndof)
        model = 0.0
        for g in self._group_list:
            if g.n == 0:
                continue
            # every constraint (a removed one has J = r = 0 and adds nothing)
            e = self._linear_residual(g, np.arange(g.n))
            model += 0.5 * float(np.einsum("mr,mr->", e, e))
            cols = np.concatenate(
                [
                    self._store_list[si].dof[g.rows[: g.n, k]][:, None] + np.arange(g.tds[k])
                    for k, si in enumerate(g.slots)
                ],
                axis=1,
            )
            grad += np.bincount(
                cols.ravel(), weights=np.einsum("mrt,mr->mt", g.J[: g.n], e).ravel(), minlength=self._ndof
            )
        try:
            solve = B.factorize(self._ndof // td)
        except NotPositiveDefinite as err:
            raise GraphError(
                "the linear system is not positive definite: some variables are under-constrained "
                "(add a prior on one variable of each connected component)"
            ) from err
        step = solve(-grad)
        self._reelim = self._live_vars()
        self._excess_bound = 0.0
        self._model_at_full = model - max(0.0, -0.5 * float(grad @ step))
        for st in self._store_list:
            if st.n == 0:
                continue
            rows = np.arange(st.n)
            st.delta[rows] += step[st.dof[rows][:, None] + np.arange(st.td)]
            self._set_estimate(st, rows)
        return True

    def _relinearize_all(self) -> None:
        """Relinearise every constraint at its variables' x_lin (and rebuild the blocks from
        scratch rather than by differences, so no rounding accumulates)."""
        B, self._blocks = self._blocks, None
        for gi, g in enumerate(self._group_list):
            self._relinearize(gi, np.arange(g.n))
        if B is not None:
            B.clear()
            for g in self._group_list:
                idx = np.nonzero(g.alive[: g.n] & (g.bslots[: g.n, 0] >= 0))[0]
                B.add(g.bslots[idx], self._block_vars(g, idx), g.G[idx])
                new = np.nonzero(g.alive[: g.n] & (g.bslots[: g.n, 0] < 0))[0]
                if new.size:
                    var = self._block_vars(g, new)
                    g.bslots[new] = B.slots(var)
                    B.add(g.bslots[new], var, g.G[new])
        self._blocks = B
        self._tree_stale = self._tree is not None

    def _gram(self, J: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per constraint ``J^T J`` and ``J^T e`` (compiled loops: a relinearisation step's
        thousand 6x12 blocks in ~0.3 ms, where the padded JAX kernel took milliseconds)."""
        return _factorkern.gram(np.ascontiguousarray(J), np.ascontiguousarray(e))

    # --- full step -------------------------------------------------------------------------------
    def _dof_map(self) -> tuple[np.ndarray, int]:
        """Compact numbering of the live dofs: map from permanent dof to system index."""
        live = np.zeros(self._ndof + 1, bool)
        for s in self._store_list:
            rows = np.nonzero(s.live[: s.n])[0]
            if rows.size:
                live[(s.dof[rows][:, None] + np.arange(s.td)).ravel()] = True
        n = int(live.sum())
        m = np.cumsum(live) - 1
        m[~live] = -1
        return m, n

    def _information_at_estimate(self) -> tuple[sp.csc_matrix, np.ndarray, int]:
        """Lower-triangular Gauss-Newton information of the live system, every factor
        linearised at the current estimate (not the cache); with the dof map and size."""
        dmap, n = self._dof_map()
        rows_l, cols_l, data_l = [], [], []
        for g in self._group_list:
            idx = np.nonzero(g.alive[: g.n])[0]
            if idx.size == 0:
                continue
            J, r, _ = self._linearize_rows(g, idx, "x")
            G = self._gram(J, r)[0]
            cols = np.concatenate(
                [self._store_list[s].dof[g.rows[idx, k]][:, None] + np.arange(g.tds[k]) for k, s in enumerate(g.slots)],
                axis=1,
            )
            cols = dmap[cols]
            gp, gq = cols[:, g.sel_p], cols[:, g.sel_q]
            rows_l.append(np.maximum(gp, gq).ravel())
            cols_l.append(np.minimum(gp, gq).ravel())
            data_l.append(G[:, g.sel_p, g.sel_q].ravel())
        rr = np.concatenate([*rows_l, np.arange(n)])
        cc = np.concatenate([*cols_l, np.arange(n)])
        dd = np.concatenate([*data_l, np.zeros(n)])
        H = sp.csc_matrix((dd, (rr, cc)), shape=(n, n))
        diag = H.diagonal()
        if np.any(diag == 0.0):  # variables without factors stay put
            H = H + sp.diags((diag == 0.0).astype(float), format="csc")
        return H, dmap, n

    @staticmethod
    def _dense_factorize(H: np.ndarray) -> Any:
        """``solve(rhs)`` by a dense Cholesky factorisation of the (full, symmetric) ``H``."""
        try:
            # OpenBLAS factorises below 64 unknowns on one thread anyway; above, limit it
            # (the context costs ~5 us, so only where it matters)
            with _one_blas_thread() if len(H) >= 64 else contextlib.nullcontext():
                c = scipy.linalg.cho_factor(H, lower=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise GraphError(
                "the linear system is not positive definite: some variables are under-constrained "
                "(add a prior on one variable of each connected component)"
            ) from err

        def solve(rhs: np.ndarray) -> np.ndarray:  # triangular solves: level-2 BLAS, one thread
            return scipy.linalg.cho_solve(c, rhs, check_finite=False)

        return solve

    def _factorize(self, H: sp.csc_matrix) -> Any:
        """``solve(rhs)`` by a sparse Cholesky factorisation of ``H`` (lower triangle, or both
        triangles for CHOLMOD)."""
        if H.shape[0] <= _DENSE_MAX:
            d = H.toarray()
            return self._dense_factorize(d + np.tril(d, -1).T)
        if self._method == "cholmod":
            try:
                return cholesky(H, ordering_method="amd")
            except CholmodNotPositiveDefiniteError as err:
                raise GraphError(
                    "the linear system is not positive definite: some variables are under-constrained "
                    "(add a prior on one variable of each connected component)"
                ) from err
        full = (H + sp.tril(H, -1).T).tocsc()
        lu = sp.linalg.splu(full, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        if np.any(lu.U.diagonal() <= 0):
            raise GraphError("the linear system is not positive definite: some variables are under-constrained")
        return lu.solve

    def _solve(self, H: sp.csc_matrix, rhs: np.ndarray) -> np.ndarray:
        return np.asarray(self._factorize(H)(rhs))

    # --- batch optimum ---------------------------------------------------------------------------
    def optimize(self, config: SolverConfig | None = None) -> SolverResult:
        """Relinearise everything and solve the whole graph to convergence with the batch
        solver (Levenberg-Marquardt by default): afterwards the estimate is the batch optimum
        from the current estimate, the linearisation is fresh and the offsets are zero."""
        self.flush()
        factors = []
        for g in self._group_list:
            idx = np.nonzero(g.alive[: g.n])[0]
            if idx.size:
                factors.append(g.subset(idx))
        ids, params = {}, {}
        for s in self._store_list:
            rows = np.nonzero(s.live[: s.n])[0]
            if rows.size:
                ids[s.t] = s.ids[rows]
                params[s.t] = jnp.asarray(s.x[rows])
        order = {t: np.argsort(i, kind="stable") for t, i in ids.items()}
        values = Values({t: ids[t][o] for t, o in order.items()}, {t: params[t][o] for t, o in order.items()})
        cfg = config or SolverConfig(
            method="lm", max_iterations=self.config.max_iterations, relative_tol=self.config.relative_tol
        )
        result = Solver(factors, values, cfg).solve()
        for s in self._store_list:
            if s.t not in ids:
                continue
            rows = np.asarray([s.row_of[int(i)] for i in result.values.ids(s.t)], np.int64)
            s.x[rows] = np.asarray(result.values.params(s.t))
            s.x_lin[rows] = s.x[rows]
            s.delta[rows] = 0.0
        self._relinearize_all()
        self._since_full = 0
        self._excess_bound = np.inf  # a new linear model: nothing known about it
        if self._tree is not None:
            self._tree.dx[:] = 0.0
        return result

    def refine(self, max_iterations: int = 10, relative_tol: float = 1e-10) -> tuple[float, float, int]:
        """Gauss-Newton on the whole graph with this solver's own compiled kernels: relinearise
        every factor at the estimate, solve the full linear system, repeat until the cost
        decreases by less than ``relative_tol`` (a step that raises the cost is undone).
        Reaches the batch optimum like :meth:`optimize` from a good estimate, without
        compiling the batch solver's programs (tens of seconds on a fresh process). Returns
        ``(initial cost, final cost, iterations)``."""
        self.flush()
        first = prev = self.cost()
        it = 0
        for it in range(1, max_iterations + 1):  # noqa: B007 - reported
            saved = [(s.x[: s.n].copy(), s.x_lin[: s.n].copy(), s.delta[: s.n].copy()) for s in self._store_list]
            for s in self._store_list:
                live = np.nonzero(s.live[: s.n])[0]
                s.x_lin[live] = s.x[live]
                s.delta[live] = 0.0
            self._relinearize_all()
            if self._tree is not None:
                self._tree.dx[:] = 0.0
                self._tree_full()
            else:
                self._window_solve(0, {})
            self._since_full = 0
            cost = self.cost()
            if not cost <= prev:  # worse (or NaN): undo the step and stop
                for s, (x, xl, d) in zip(self._store_list, saved):
                    s.x[: s.n], s.x_lin[: s.n], s.delta[: s.n] = x, xl, d
                    if self._tree is not None:
                        self._tree.dx[(s.dof[: s.n][:, None] + np.arange(s.td)).ravel()] = d.ravel()
                self._relinearize_all()
                self._excess_bound = np.inf
                break
            done = prev - cost <= relative_tol * max(prev, 1e-300)
            prev = cost
            if done:
                break
        return first, prev, it

    # --- queries ---------------------------------------------------------------------------------
    def cost(self) -> float:
        """Total cost of the current estimate (GTSAM's ``graph.error``)."""
        self.flush()
        total = 0.0
        for g in self._group_list:
            idx = np.nonzero(g.alive[: g.n])[0]
            if idx.size == 0:
                continue
            total += self._linearize_rows(g, idx, "x", want_cost=True)[2]
        return total

    def estimate(self) -> Values:
        """Current estimate of every variable (marginalised ones at their last estimate)."""
        self.flush()
        ids = {}
        params = {}
        for s in self._store_list:
            order = np.argsort(s.ids[: s.n], kind="stable")
            ids[s.t] = s.ids[: s.n][order]
            params[s.t] = jnp.asarray(s.x[: s.n][order])
        return Values(ids, params)

    def value(self, vtype: type[Variable], id_: int) -> np.ndarray:
        """Current estimate of one variable's parameters (host numpy; no JAX dispatch)."""
        s = self.stores.get(vtype)
        if s is None:
            raise GraphError(f"no {vtype.__name__} variables")
        row = s.rows(np.array([id_]), "value")[0]
        if self._tree is not None and self._tree.pending:  # only the cliques on its path
            self._sync_offsets(self._tree.solve_path(int(s.vnum[row])))
        return s.x[row].copy()

    def marginal_covariance(self, var: Variable) -> np.ndarray:
        """Marginal covariances ``(K, t, t)`` of the ids of ``var`` (in its tangent order),
        from the Gauss-Newton information of the whole graph linearised at the current
        estimate (``gtsam.Marginals``)."""
        s = self.stores.get(type(var))
        if s is None:
            raise GraphError(f"no {type(var).__name__} variables")
        self.flush()
        rows = s.rows(np.asarray(var.ids).reshape(-1), "marginal_covariance")
        if not np.all(s.live[rows]):
            raise GraphError(f"{type(var).__name__}: marginalised variables have no covariance here")
        H, dmap, n = self._information_at_estimate()
        cols = dmap[s.dof[rows][:, None] + np.arange(s.td)]  # (K, t)
        E = np.zeros((n, cols.size))
        E[cols.ravel(), np.arange(cols.size)] = 1.0
        X = self._solve(H, E)
        out = np.empty((len(rows), s.td, s.td))
        for k in range(len(rows)):
            out[k] = X[cols[k]][:, k * s.td : (k + 1) * s.td]
        return 0.5 * (out + np.swapaxes(out, 1, 2))

    # --- fixed-lag marginalisation ---------------------------------------------------------------
    def _marginalize(self) -> int:
        lag = self.config.lag
        assert lag is not None
        victims: dict[int, np.ndarray] = {}
        for s in self._store_list:
            rows = np.nonzero(s.live[: s.n] & (s.born[: s.n] <= self.updates - lag))[0]
            if rows.size:
                victims[s.index] = rows
        if not victims:
            return 0
        is_victim = {(si, int(r)) for si, rows in victims.items() for r in rows}
        # factors touching a victim, and the variables they connect to (separator)
        fac: dict[int, set[int]] = {}
        for key in is_victim:
            for gi, c in self._adj.get(key, ()):
                if self._group_list[gi].alive[c]:
                    fac.setdefault(gi, set()).add(c)
        order: dict[tuple[int, int], int] = {}
        dim = 0
        sep: list[tuple[int, int]] = []
        for gi, cs in fac.items():
            g = self._group_list[gi]
            for c in cs:
                for k, si in enumerate(g.slots):
                    key = (si, int(g.rows[c, k]))
                    if key not in order:
                        order[key] = -1
                        if key not in is_victim:
                            sep.append(key)
        keys = [k for k in order if k in is_victim] + sep
        for key in keys:
            order[key] = dim
            dim += self._store_list[key[0]].td
        nm = sum(self._store_list[k[0]].td for k in keys if k in is_victim)
        H = np.zeros((dim, dim))
        bvec = np.zeros(dim)
        for gi, cs in fac.items():
            g = self._group_list[gi]
            idx = np.asarray(sorted(cs), np.int64)
            # linear model around the *current* estimate: e = r + J delta
            e = self._linear_residual(g, idx)
            col = np.concatenate(
                [
                    np.asarray([order[(si, int(r))] for r in g.rows[idx, k]])[:, None] + np.arange(g.tds[k])
                    for k, si in enumerate(g.slots)
                ],
                axis=1,
            )
            G = np.einsum("mra,mrb->mab", g.J[idx], g.J[idx])
            np.add.at(H, (col[:, :, None], col[:, None, :]), G)
            np.add.at(bvec, col, np.einsum("mra,mr->ma", g.J[idx], e))
            g.alive[idx] = False
            g.J[idx] = 0.0
            g.r[idx] = 0.0
            g.G[idx] = 0.0
        for h, (gi, idx) in list(self._handles.items()):
            if not np.any(self._group_list[gi].alive[idx]):
                del self._handles[h]
        for si, rows in victims.items():
            self._store_list[si].live[rows] = False
        if sep:
            Hmm, Hms, Hss = H[:nm, :nm], H[:nm, nm:], H[nm:, nm:]
            bm, bs = bvec[:nm], bvec[nm:]
            # Schur complement (pseudo-inverse: a marginalised gauge direction carries nothing)
            Hmm_inv = np.linalg.pinv(Hmm, hermitian=True)
            Hp = Hss - Hms.T @ Hmm_inv @ Hms
            bp = bs - Hms.T @ Hmm_inv @ bm
            # e above is the linear model at the current delta, so (Hp, bp) is the marginal
            # cost around the current estimate x_S: 1/2 d^T Hp d + bp^T d, d = Local(x_S, .)
            # (to first order; Local's Jacobian is I at d = 0).
            variables = tuple(self._store_list[si].t(np.asarray([self._store_list[si].ids[r]])) for si, r in sep)
            x0 = tuple(self._store_list[si].x[r] for si, r in sep)
            mf = MarginalFactor.from_information(variables, x0, Hp, bp)
            self._add_factor(mf, 0)
            g = self.groups[group_key(mf)]
            self._relinearize(self._group_list.index(g), np.asarray([g.n - 1]))
        return len(is_victim)
