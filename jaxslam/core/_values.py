"""Values: the current estimate of every variable, one array per variable type.

``Values`` is an immutable PyTree. Its leaves are ``(N_type, param_dim)`` arrays; the sorted
ids of each type are static. Look-ups by id happen in numpy at trace time.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..errors import GraphError
from ._variables import Variable


class _Ids:
    """Hashable wrapper of a sorted id array, so ids can be PyTree static data."""

    __slots__ = ("_hash", "array")

    def __init__(self, array: np.ndarray):
        self.array = array
        self._hash = hash((array.shape, array.tobytes()))

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Ids) and np.array_equal(self.array, other.array)


@jax.tree_util.register_pytree_node_class
class Values:
    """Estimates keyed by variable type and id.

    Build with :meth:`Values.create`::

        vals = Values.create({Pose3Var(np.arange(3)): SE3.identity((3,))})
        vals.get(Pose3Var(np.array([0, 2])))  # SE3 with batch (2,)
    """

    def __init__(self, ids: Mapping[type[Variable], np.ndarray], params: Mapping[type[Variable], Array]):
        self._ids = dict(ids)
        self._params = dict(params)

    # --- PyTree -------------------------------------------------------------------------
    def tree_flatten(self) -> tuple[list[Array], tuple[Any, ...]]:
        types = tuple(sorted(self._params, key=lambda t: t.__name__))
        return [self._params[t] for t in types], (types, tuple(_Ids(self._ids[t]) for t in types))

    @classmethod
    def tree_unflatten(cls, aux: tuple[Any, ...], leaves: list[Array]) -> Values:
        types, ids = aux
        return cls({t: i.array for t, i in zip(types, ids)}, dict(zip(types, leaves)))

    # --- construction -------------------------------------------------------------------
    @classmethod
    def create(cls, entries: Mapping[Variable, Any]) -> Values:
        """From ``{VarType(ids): values}``, values a Lie group batch or an ``(N, P)`` array.
        Several entries of one type are merged; repeated ids raise :class:`GraphError`."""
        ids: dict[type[Variable], list[np.ndarray]] = {}
        params: dict[type[Variable], list[Array]] = {}
        for var, value in entries.items():
            vtype = type(var)
            arr = jnp.asarray(vtype.unwrap(value), dtype=jnp.float64)
            var_ids = np.asarray(var.ids).reshape(-1)
            arr = jnp.broadcast_to(arr, (len(var_ids), vtype.param_dim)) if arr.ndim == 1 else arr
            if arr.shape != (len(var_ids), vtype.param_dim):
                raise ValueError(
                    f"{vtype.__name__}: {len(var_ids)} ids need values of shape "
                    f"({len(var_ids)}, {vtype.param_dim}), got {tuple(arr.shape)}"
                )
            ids.setdefault(vtype, []).append(var_ids)
            params.setdefault(vtype, []).append(arr)
        out_ids = {}
        out_params = {}
        for vtype in ids:
            all_ids = np.concatenate(ids[vtype])
            order = np.argsort(all_ids, kind="stable")
            sorted_ids = all_ids[order]
            dup = np.nonzero(np.diff(sorted_ids) == 0)[0]
            if dup.size:
                raise GraphError(f"{vtype.__name__} id {int(sorted_ids[dup[0]])} is given more than once")
            out_ids[vtype] = sorted_ids
            out_params[vtype] = jnp.concatenate(params[vtype], axis=0)[order]
        return cls(out_ids, out_params)

    # --- access -------------------------------------------------------------------------
    def types(self) -> list[type[Variable]]:
        return list(self._params)

    def ids(self, vtype: type[Variable]) -> np.ndarray:
        return self._ids[vtype]

    def params(self, vtype: type[Variable]) -> Array:
        return self._params[vtype]

    def __contains__(self, vtype: object) -> bool:
        return vtype in self._params

    def __len__(self) -> int:
        return sum(len(i) for i in self._ids.values())

    def __iter__(self) -> Iterator[type[Variable]]:
        return iter(self._params)

    def rows(self, var: Variable) -> np.ndarray:
        """Row of each id of ``var`` in this type's array; GraphError for a missing id."""
        vtype = type(var)
        if vtype not in self._ids:
            raise GraphError(f"no {vtype.__name__} variables in these values")
        return lookup_rows(self._ids[vtype], np.asarray(var.ids), vtype.__name__)

    def get(self, var: Variable) -> Any:
        """The values of ``var``'s ids, wrapped as the type's Lie group (or array)."""
        rows = self.rows(var)  # first: GraphError, not KeyError, for a type with no values
        return type(var).wrap(self._params[type(var)][rows])

    def with_params(self, vtype: type[Variable], params: Array) -> Values:
        new = dict(self._params)
        new[vtype] = params
        return Values(self._ids, new)

    def update(self, var: Variable, value: Any) -> Values:
        """Copy with the given ids' values replaced."""
        vtype = type(var)
        rows = self.rows(var)
        arr = jnp.asarray(vtype.unwrap(value))
        return self.with_params(vtype, self._params[vtype].at[rows].set(arr))

    def merge(self, other: Values) -> Values:
        """Union of two Values; ``other`` wins nothing: repeated ids raise GraphError."""
        entries: dict[Variable, Any] = {}
        for v in (self, other):
            for t in v.types():
                entries[t(v.ids(t))] = v.params(t)
        return Values.create(entries)

    def __repr__(self) -> str:
        parts = ", ".join(f"{t.__name__}: {len(i)}" for t, i in self._ids.items())
        return f"Values({parts})"


def lookup_rows(sorted_ids: np.ndarray, query: np.ndarray, name: str) -> np.ndarray:
    """Positions of ``query`` in ``sorted_ids``; GraphError naming the first missing id."""
    rows = np.searchsorted(sorted_ids, query)
    rows_c = np.minimum(rows, max(len(sorted_ids) - 1, 0))
    ok = (rows < len(sorted_ids)) & (sorted_ids[rows_c] == query) if len(sorted_ids) else np.zeros(query.shape, bool)
    if not np.all(ok):
        missing = int(np.asarray(query)[~ok][0])
        raise GraphError(f"a factor refers to {name} {missing}, which has no value")
    return rows_c
