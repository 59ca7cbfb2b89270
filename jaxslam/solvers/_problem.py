"""Problem analysis: done once per graph structure, reused by every iteration.

Data flow of one Gauss-Newton iteration::

    Values arrays ──gather rows──▶ factor groups ──linearize (jit)──▶ whitened r, J
        ──J_a^T J_b blocks, scatter by precomputed targets (jit)──▶ H (CSC lower data), g
        ──sparse Cholesky (CHOLMOD, symbolic analysis reused)──▶ delta ──retract (jit)──▶ Values

What is analysed here (numpy, once):

* factors of the same class are concatenated into one *group* and padded to a capacity
  bucket (padding rows are masked out), so similar graphs reuse compiled code;
* every variable type's array is padded to a bucket too; the padded variables get a unit
  diagonal in H (they are decoupled, their step is 0);
* the global tangent layout: a block-level fill-reducing ordering (AMD on the variable graph)
  decides each variable's scalar offset, so CHOLMOD's supernodes follow the 6x6 (3x3, ...)
  blocks;
* the sparsity pattern of the lower triangle of H in CSC order, and for every entry of every
  Jacobian product ``J_a^T J_b`` its index in the CSC data array (``targets``). The numeric
  assembly is then one scatter-add.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..core import Factor, Values, Variable, factor_cost, linearize
from ..errors import GraphError
from ..lie import mm, mT


def bucket(n: int, minimum: int = 8) -> int:
    """Capacity for ``n`` items: the next of 8, 12, 16, 24, 32, 48, ... (at most 1.5x)."""
    if n <= minimum:
        return minimum
    p = 2 ** math.floor(math.log2(n))
    if n == p:
        return n
    return int(1.5 * p) if n <= 1.5 * p else 2 * p


def _pad_leaf(leaf: Any, n: int, cap: int) -> Any:
    if jnp.ndim(leaf) == 0 or cap == n:
        return leaf
    arr = leaf
    reps = jnp.broadcast_to(arr[:1], (cap - n, *arr.shape[1:])) if isinstance(arr, jax.Array) else None
    if reps is None:
        arr = np.asarray(arr)
        return np.concatenate([arr, np.repeat(arr[:1], cap - n, axis=0)], axis=0)
    return jnp.concatenate([arr, reps], axis=0)


def group_key(f: Factor) -> tuple[Any, ...]:
    """What puts factors in one group: class, variable types, residual size, PyTree shape."""
    return (type(f), f.variable_types(), f.residual_dim, jax.tree_util.tree_structure(f))


def shared_leaves(f: Factor) -> list[Any]:
    """``f``'s leaves shared by all its constraints (scalars: a robust kernel's scale), None
    in place of per-constraint ones; a group keeps these of its first factor."""
    return [None if jnp.ndim(leaf) >= 1 else leaf for leaf in jax.tree_util.tree_leaves(f)]


def check_shared_leaves(shared: list[Any], f: Factor) -> None:
    """Raise :class:`GraphError` when ``f``'s shared leaves differ from ``shared`` (those of
    the group it joins, :func:`shared_leaves`): the group keeps one value per scalar leaf,
    and the solver would otherwise use the first factor's scale for all. Per-constraint
    scales are arrays of length N."""
    leaves = jax.tree_util.tree_leaves(f)
    # the common case first, without the leaves' paths (which cost more than the check):
    # every per-constraint leaf where the group has one, every scalar equal
    if all(
        (np.ndim(b) >= 1) if a is None else (np.ndim(b) == 0 and (a is b or _same_scalar(a, b)))
        for a, b in zip(shared, leaves)
    ):
        return
    for a, (path, b) in zip(shared, jax.tree_util.tree_leaves_with_path(f)):
        if (a is None) != (jnp.ndim(b) >= 1):
            raise GraphError(
                f"{type(f).__name__}: field {jax.tree_util.keystr(path)} is a scalar in one factor and per-constraint "
                "in another of the same kind; use one form for all"
            )
        concrete = not isinstance(a, jax.core.Tracer) and not isinstance(b, jax.core.Tracer)
        if a is not None and concrete and float(a) != float(b):
            raise GraphError(
                f"{type(f).__name__}: factors of one kind share scalar field {jax.tree_util.keystr(path)}, "
                f"but these differ ({float(a)!r} and {float(b)!r}); give it per constraint (an array of length N)"
            )


def _same_scalar(a: Any, b: Any) -> bool:
    """Two scalar leaves equal (a traced one is taken as equal: it cannot be read)."""
    if isinstance(a, jax.core.Tracer) or isinstance(b, jax.core.Tracer):
        return True
    return float(a) == float(b)


def concatenate_factors(factors: Sequence[Factor]) -> Factor:
    """One factor holding the constraints of several factors of the same class (their scalar
    leaves must agree, :func:`check_shared_leaves`)."""
    if len(factors) == 1:
        return factors[0]
    shared = shared_leaves(factors[0])
    for f in factors[1:]:
        check_shared_leaves(shared, f)
    return jax.tree_util.tree_map(
        lambda *leaves: leaves[0] if jnp.ndim(leaves[0]) == 0 else jnp.concatenate([jnp.asarray(x) for x in leaves]),
        *factors,
    )


@dataclasses.dataclass(frozen=True)
class GroupStructure:
    """Static description of one factor group (hashable parts used as jit static data)."""

    factor_type: type
    var_types: tuple[type[Variable], ...]
    slots: tuple[int, ...]  # index of each slot's type in Problem.var_types
    residual_dim: int
    num: int = dataclasses.field(compare=False)  # not part of the compiled signature
    capacity: int = 0


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GroupData:
    """Array parts of one factor group, passed to jitted code as arguments."""

    factor: Any  # the (padded) factor PyTree
    rows: tuple[Array, ...]  # per slot: row in that variable type's padded array, (cap,)
    mask: Array  # (cap,) bool
    hess_targets: Array  # (cap * sum_ab t_a t_b,) index into H data, nnz = dropped
    grad_targets: Array  # (cap * sum_a t_a,) index into g, ndof = dropped


def _check_factor(f: Factor, index: int) -> int:
    if not isinstance(f, Factor):
        raise TypeError(f"factor {index} is a {type(f).__name__}, not a jaxslam Factor")
    n = f.num_constraints
    # the leaves' shapes first (np.shape reads numpy and JAX arrays alike, without JAX's
    # dispatch); their paths, which cost more than the check, only to name a bad one
    if all(np.ndim(leaf) == 0 or np.shape(leaf)[0] == n for leaf in jax.tree_util.tree_leaves(f)):
        return n
    for path, leaf in jax.tree_util.tree_leaves_with_path(f):
        if np.ndim(leaf) >= 1 and np.shape(leaf)[0] != n:
            name = jax.tree_util.keystr(path)
            raise ValueError(
                f"{type(f).__name__} (factor {index}) has {n} constraints but field {name} has leading "
                f"dimension {np.shape(leaf)[0]}; per-constraint data must have leading axis {n}"
            )
    return n


class Problem:
    """A factor graph analysed for repeated solves.

    ``Problem(factors, values)`` checks that every factor's variables have values, groups the
    factors, computes the ordering and sparsity pattern. ``values`` may hold variables no
    factor touches; they are left unchanged.
    """

    group_data: list[GroupData]
    """Per factor group: the (padded) factor and its scatter targets (replaced by
    :meth:`set_factors`)."""

    def __init__(
        self, factors: Sequence[Factor], values: Values, *, ordering: str = "amd", fixed: Sequence[Variable] = ()
    ):
        if len(factors) == 0:
            raise GraphError("the graph has no factors")
        self.ordering_method = ordering
        self._analyse_variables(values)
        self._analyse_groups(factors, values)
        self._analyse_layout(ordering, fixed, values)
        self._analyse_pattern()

    # --- variables ----------------------------------------------------------------------
    def _analyse_variables(self, values: Values) -> None:
        self.var_types: tuple[type[Variable], ...] = tuple(sorted(values.types(), key=lambda t: t.__name__))
        self.type_index = {t: i for i, t in enumerate(self.var_types)}
        self.var_ids = {t: values.ids(t) for t in self.var_types}
        self.var_count = {t: len(self.var_ids[t]) for t in self.var_types}
        self.var_capacity = {t: bucket(self.var_count[t]) for t in self.var_types}
        self.values_template = values

    def pad_values(self, values: Values) -> tuple[Array, ...]:
        out = []
        for t in self.var_types:
            p = values.params(t)
            n, cap = self.var_count[t], self.var_capacity[t]
            if cap > n:
                ident = jnp.broadcast_to(jnp.asarray(t.identity_params(), dtype=p.dtype), (cap - n, t.param_dim))
                p = jnp.concatenate([p, ident], axis=0)
            out.append(p)
        return tuple(out)

    def unpad_values(self, params: tuple[Array, ...]) -> Values:
        return Values(
            {t: self.var_ids[t] for t in self.var_types},
            {t: p[: self.var_count[t]] for t, p in zip(self.var_types, params)},
        )

    # --- factor groups ------------------------------------------------------------------
    def _analyse_groups(self, factors: Sequence[Factor], values: Values) -> None:
        by_type = self._by_type(factors)
        self._group_keys = list(by_type)
        self.structures: list[GroupStructure] = []
        self._group_factors: list[Factor] = []
        self._group_rows: list[tuple[np.ndarray, ...]] = []
        for (ftype, vtypes, rdim, _), fs in by_type.items():
            f = concatenate_factors(fs)
            n = f.num_constraints
            rows = tuple(values.rows(v) for v in f.variables)
            for a in range(len(rows)):
                for b in range(a + 1, len(rows)):
                    if vtypes[a] is vtypes[b] and np.any(rows[a] == rows[b]):
                        k = int(np.nonzero(rows[a] == rows[b])[0][0])
                        raise GraphError(
                            f"{ftype.__name__} constraint {k} connects {vtypes[a].__name__} "
                            f"{int(np.asarray(f.variables[a].ids)[k])} to itself"
                        )
            slots = tuple(self.type_index[t] for t in vtypes)
            self.structures.append(GroupStructure(ftype, vtypes, slots, rdim, n, bucket(n)))
            self._group_factors.append(f)
            self._group_rows.append(rows)

    def _by_type(self, factors: Sequence[Factor]) -> dict[tuple[Any, ...], list[Factor]]:
        by_type: dict[tuple[Any, ...], list[Factor]] = {}
        for i, f in enumerate(factors):
            n = _check_factor(f, i)
            if n == 0:
                continue
            for v in f.variables:
                if type(v) not in self.var_ids:
                    raise GraphError(f"{type(f).__name__} (factor {i}) uses {type(v).__name__}, which has no values")
            key = group_key(f)
            by_type.setdefault(key, []).append(f)
        if not by_type:
            raise GraphError("the graph has no factors")
        return by_type

    def group_data_for(self, factors: Sequence[Factor]) -> list[GroupData]:
        """The group data of ``factors``, a graph of the same structure as the analysed one
        (same factor kinds, counts, variables, in the same order) but other measurements,
        noise or kernel scales. Traceable: the factors' leaves may be JAX tracers, so a
        loss can be differentiated through them (learned noise weights)."""
        by_type = self._by_type(factors)
        if list(by_type) != self._group_keys:
            raise GraphError("the factors' kinds differ from the analysed graph's; build a new Problem")
        out = []
        for s, g, fs, rows in zip(self.structures, self.group_data, by_type.values(), self._group_rows):
            f = concatenate_factors(fs)
            if f.num_constraints != s.num:
                raise GraphError(
                    f"{s.factor_type.__name__}: {f.num_constraints} constraints where the analysed graph has {s.num}"
                )
            for var, r, t in zip(f.variables, rows, s.var_types):
                ids = var.ids
                if not isinstance(ids, jax.core.Tracer) and not np.array_equal(np.asarray(ids), self.var_ids[t][r]):
                    raise GraphError(f"{s.factor_type.__name__}: the constraints connect other variables than analysed")
            padded = jax.tree_util.tree_map(lambda leaf, _n=s.num, _c=s.capacity: _pad_leaf(leaf, _n, _c), f)
            out.append(dataclasses.replace(g, factor=padded))
        return out

    def set_factors(self, factors: Sequence[Factor]) -> None:
        """Replace the factors by ones of the same structure (see :meth:`group_data_for`)."""
        self.group_data = self.group_data_for(factors)

    # --- layout and ordering ------------------------------------------------------------
    def _analyse_layout(self, ordering: str, fixed: Sequence[Variable], values: Values) -> None:
        # Global block index of (type, row): types in order, rows within (padded) type.
        self.block_base = {}
        nb = 0
        for t in self.var_types:
            self.block_base[t] = nb
            nb += self.var_capacity[t]
        self.num_blocks = nb
        block_dim = np.concatenate([np.full(self.var_capacity[t], t.tangent_dim) for t in self.var_types])
        self.block_dim = block_dim
        # Fixed (constant) variables keep their values: they get no degrees of freedom, and
        # their dofs map to the dump index ``ndof`` everywhere below.
        self.fixed_blocks = np.zeros(nb, bool)
        for var in fixed:
            if type(var) not in self.block_base:
                raise GraphError(f"fixed {type(var).__name__} variables have no values")
            self.fixed_blocks[self.block_base[type(var)] + values.rows(var)] = True
        # Block adjacency from the factors.
        pairs_i, pairs_j = [np.arange(nb)], [np.arange(nb)]
        for s, rows in zip(self.structures, self._group_rows):
            gb = [self.block_base[t] + r for t, r in zip(s.var_types, rows)]
            for a in range(len(gb)):
                for b in range(len(gb)):
                    if a != b:
                        pairs_i.append(gb[a])
                        pairs_j.append(gb[b])
        bi, bj = np.concatenate(pairs_i), np.concatenate(pairs_j)
        self._block_pairs = (bi, bj)
        perm = block_ordering(bi, bj, nb, ordering)
        # position of each block in the elimination order -> scalar offset
        free_dim = np.where(self.fixed_blocks, 0, block_dim)
        offset_in_order = np.concatenate([[0], np.cumsum(free_dim[perm])[:-1]])
        self.block_offset = np.empty(nb, dtype=np.int64)
        self.block_offset[perm] = offset_in_order
        self.ndof = int(free_dim.sum())
        # scalar index of each tangent component, per variable type: (cap, t); ndof if fixed
        self.dof_index = {}
        for t in self.var_types:
            blocks = slice(self.block_base[t], self.block_base[t] + self.var_capacity[t])
            idx = self.block_offset[blocks][:, None] + np.arange(t.tangent_dim)[None, :]
            self.dof_index[t] = np.where(self.fixed_blocks[blocks][:, None], self.ndof, idx)
        self.dof_index_jax = tuple(jnp.asarray(self.dof_index[t], dtype=jnp.int32) for t in self.var_types)

    # --- sparsity pattern and scatter targets -------------------------------------------
    def _analyse_pattern(self) -> None:
        n = self.ndof
        keys_per_group: list[list[np.ndarray]] = []
        all_keys = [self._diag_keys()]
        for s, rows in zip(self.structures, self._group_rows):
            dofs = [self.dof_index[t][r] for t, r in zip(s.var_types, rows)]  # (num, t_a)
            gk = []
            for a in range(len(dofs)):
                for b in range(len(dofs)):
                    if b < a:
                        continue
                    ra = dofs[a][:, :, None]
                    cb = dofs[b][:, None, :]
                    rr, cc = np.broadcast_arrays(ra, cb)
                    lo_r, lo_c = np.maximum(rr, cc), np.minimum(rr, cc)
                    key = lo_c.astype(np.int64) * n + lo_r
                    key = np.where(lo_r >= n, -1, key)  # an entry of a fixed variable: dropped
                    if a == b:  # symmetric diagonal block: keep p >= q entries only
                        ta = dofs[a].shape[1]
                        keep = np.tril(np.ones((ta, ta), bool))[None]
                        key = np.where(keep, key, -1)
                    gk.append(key.reshape(s.num, -1))
            keys_per_group.append(gk)
            all_keys.extend(k[k >= 0] for k in (x.ravel() for x in gk))
        uniq = np.unique(np.concatenate(all_keys))
        self.nnz = len(uniq)
        self.nnz_capacity = bucket(self.nnz + 1)  # compiled size of the H data buffer
        cols = uniq // n
        self.csc_indices = (uniq % n).astype(np.int32)
        self.csc_indptr = np.searchsorted(cols, np.arange(n + 1)).astype(np.int32)
        diag_keys = np.arange(n, dtype=np.int64) * n + np.arange(n)
        self.diag_pos = np.searchsorted(uniq, diag_keys)
        # Per variable type: the H-data index of every entry of each diagonal block (for the
        # block-Jacobi preconditioner); entries that are structurally zero point past the end.
        self.diag_blocks: list[tuple[np.ndarray, np.ndarray]] = []
        for t in self.var_types:
            d = self.dof_index[t]  # (cap, td)
            rr = np.maximum(d[:, :, None], d[:, None, :])
            cc = np.minimum(d[:, :, None], d[:, None, :])
            key = cc.astype(np.int64) * n + rr
            pos = np.minimum(np.searchsorted(uniq, key), len(uniq) - 1)
            self.diag_blocks.append((d, np.where(uniq[pos] == key, pos, len(uniq))))
        # Which dofs are padding (no factor touches them): they get a unit diagonal.
        touched = np.zeros(n, bool)
        for s, rows in zip(self.structures, self._group_rows):
            for t, r in zip(s.var_types, rows):
                d = self.dof_index[t][r].ravel()
                touched[d[d < n]] = True
        self.untouched_dofs = np.nonzero(~touched)[0]

        self.group_data = []
        for s, f, rows, gk in zip(self.structures, self._group_factors, self._group_rows, keys_per_group):
            cap = s.capacity
            tgt_blocks = []
            for key in gk:
                tg = np.where(key >= 0, np.searchsorted(uniq, np.maximum(key, 0)), self.nnz)
                tg = np.concatenate([tg, np.full((cap - s.num, tg.shape[1]), self.nnz)], axis=0)
                tgt_blocks.append(tg)
            hess_targets = np.concatenate(tgt_blocks, axis=1).reshape(-1)
            grad_t = np.concatenate([self.dof_index[t][r] for t, r in zip(s.var_types, rows)], axis=1)
            grad_t = np.concatenate([grad_t, np.full((cap - s.num, grad_t.shape[1]), n)], axis=0).reshape(-1)
            prow = tuple(jnp.asarray(np.concatenate([r, np.full(cap - s.num, r[0])]), dtype=jnp.int32) for r in rows)
            mask = np.zeros(cap, bool)
            mask[: s.num] = True
            padded = jax.tree_util.tree_map(lambda leaf, _n=s.num, _c=cap: _pad_leaf(leaf, _n, _c), f)
            self.group_data.append(
                GroupData(
                    factor=padded,
                    rows=prow,
                    mask=jnp.asarray(mask),
                    hess_targets=jnp.asarray(hess_targets, dtype=jnp.int32),
                    grad_targets=jnp.asarray(grad_t, dtype=jnp.int32),
                )
            )
        self.static = tuple(self.structures)
        self.unary_blocks = self._unary_blocks()

    def _diag_keys(self) -> np.ndarray:
        n = self.ndof
        return np.arange(n, dtype=np.int64) * n + np.arange(n)

    def _unary_blocks(self) -> np.ndarray:
        """Blocks touched by a single-variable factor (priors): they fix a gauge."""
        out = []
        for s, rows in zip(self.structures, self._group_rows):
            if len(s.var_types) == 1:
                out.append(self.block_base[s.var_types[0]] + rows[0])
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    # --- diagnostics --------------------------------------------------------------------
    def free_gauge_components(self) -> list[str]:
        """Connected components of the variable graph with no unary factor: their gauge
        (global position/orientation) is not fixed. Returns a description of each."""
        return [self.describe_block(int(b)) + f" and {n - 1} more" for b, n in zip(*self._free_gauge())]

    def free_gauge_blocks(self) -> list[int]:
        """The first variable (block) of every component whose gauge is free."""
        return [int(b) for b in self._free_gauge()[0]]

    def block_variable(self, b: int) -> tuple[type[Variable], int]:
        """(variable type, row in its values array) of a block."""
        for t in reversed(self.var_types):
            if b >= self.block_base[t]:
                return t, b - self.block_base[t]
        raise IndexError(b)

    def _free_gauge(self) -> tuple[list[int], list[int]]:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        bi, bj = self._block_pairs
        nb = self.num_blocks
        adj = coo_matrix((np.ones(len(bi)), (bi, bj)), shape=(nb, nb)).tocsr()
        ncomp, labels = connected_components(adj, directed=False)
        touched = np.zeros(nb, bool)
        for s, rows in zip(self.structures, self._group_rows):
            for t, r in zip(s.var_types, rows):
                touched[self.block_base[t] + r] = True
        fixed = np.zeros(ncomp, bool)
        fixed[labels[self.unary_blocks]] = True
        fixed[labels[self.fixed_blocks]] = True  # a constant variable anchors its component
        first, sizes = [], []
        for c in range(ncomp):
            members = np.nonzero((labels == c) & touched)[0]
            if fixed[c] or members.size == 0:
                continue
            first.append(int(members[0]))
            sizes.append(int(members.size))
        return first, sizes

    def describe_block(self, b: int) -> str:
        t, row = self.block_variable(b)
        return f"{t.__name__} {int(self.var_ids[t][row])}"

    def block_of(self, var: Variable) -> np.ndarray:
        return self.block_base[type(var)] + self.values_template.rows(var)


def block_ordering(bi: np.ndarray, bj: np.ndarray, nb: int, method: str) -> np.ndarray:
    """Fill-reducing elimination order of the variable (block) graph."""
    if method == "natural" or nb < 3:
        return np.arange(nb)
    from scipy.sparse import coo_matrix

    adj = coo_matrix((np.ones(len(bi)), (bi, bj)), shape=(nb, nb)).tocsc()
    adj.sum_duplicates()
    adj = adj + coo_matrix((np.full(nb, float(nb)), (np.arange(nb), np.arange(nb))), shape=(nb, nb)).tocsc()
    try:
        from sksparse.cholmod import analyze

        return np.asarray(analyze(adj.tocsc(), ordering_method=method).P(), dtype=np.int64)
    except ImportError:
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        return np.asarray(reverse_cuthill_mckee(adj.tocsr(), symmetric_mode=True), dtype=np.int64)


# --- jitted numeric kernels ---------------------------------------------------------------
def _gather(params: tuple[Array, ...], s: GroupStructure, g: GroupData) -> tuple[Array, ...]:
    return tuple(params[k][r] for k, r in zip(s.slots, g.rows))


def _block_products(lin_j: tuple[Array, ...], nvar: int) -> list[Array]:
    out = []
    for a in range(nvar):
        for b in range(a, nvar):
            out.append(mm(mT(lin_j[a]), lin_j[b]).reshape(lin_j[a].shape[0], -1))
    return out


@functools.partial(jax.jit, static_argnames=("static", "nnz", "ndof"))
def assemble(
    params: tuple[Array, ...],
    groups: list[GroupData],
    *,
    static: tuple[GroupStructure, ...],
    nnz: int,
    ndof: int,
) -> tuple[Array, Array, Array]:
    """Linearise every group and assemble ``(H data in CSC lower order, g, cost)``."""
    hdata = jnp.zeros(nnz)  # nnz is the bucketed capacity; entries past the real nnz are dropped
    grad = jnp.zeros(ndof + 1)
    cost = jnp.zeros(())
    for s, g in zip(static, groups):
        lin = linearize(g.factor, _gather(params, s, g), g.mask)
        blocks = jnp.concatenate(_block_products(lin.jacobians, len(s.var_types)), axis=1).reshape(-1)
        hdata = hdata.at[g.hess_targets].add(blocks)
        gvec = jnp.concatenate([jnp.sum(j * lin.residual[:, :, None], axis=1) for j in lin.jacobians], axis=1).reshape(
            -1
        )
        grad = grad.at[g.grad_targets].add(gvec)
        cost = cost + jnp.sum(lin.cost)
    return hdata, grad[:ndof], cost


@functools.partial(jax.jit, static_argnames=("static",))
def total_cost(params: tuple[Array, ...], groups: list[GroupData], *, static: tuple[GroupStructure, ...]) -> Array:
    cost = jnp.zeros(())
    for s, g in zip(static, groups):
        cost = cost + jnp.sum(factor_cost(g.factor, _gather(params, s, g), g.mask))
    return cost


@functools.partial(jax.jit, static_argnames=("var_types",))
def retract_all(
    params: tuple[Array, ...],
    delta: Array,
    dof_index: tuple[Array, ...],
    *,
    var_types: tuple[type[Variable], ...],
) -> tuple[Array, ...]:
    padded = jnp.concatenate([delta, jnp.zeros(1, delta.dtype)])  # index ndof: fixed variables
    return tuple(t.retract(p, padded[idx]) for t, p, idx in zip(var_types, params, dof_index))
