"""A pose graph as read from a file: initial values, factors, and the raw edge arrays.

Layouts are jaxslam's, whatever the file used:

- 2-D: :class:`Pose2Var`, params ``(cos, sin, x, y)``, information in ``[theta, x, y]`` order.
- 3-D: :class:`Pose3Var`, params ``(qw, qx, qy, qz, x, y, z)``, information in
  ``[rotation, translation]`` order.

An edge ``(i, j)`` measures ``x_i^-1 x_j`` (GTSAM's ``BetweenFactor(i, j, measured)``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..core import Factor, Gaussian, Pose2Var, Pose3Var, Values, Variable, information_is_valid
from ..errors import GraphError
from ..factors import BetweenFactor, PriorFactor
from ..lie import SE2, SE3

FIX_SIGMA = 1e-6
"""Standard deviation (rad and m) of the prior that holds a fixed (``FIX``) vertex in place."""

_VAR_TYPES: dict[int, type[Variable]] = {2: Pose2Var, 3: Pose3Var}


@dataclasses.dataclass(frozen=True, eq=False)
class PoseGraph:
    """A 2-D or 3-D pose graph.

    Fields:
        dim: 2 (:class:`Pose2Var`, SE2) or 3 (:class:`Pose3Var`, SE3).
        values: initial estimate, keyed by the vertex ids of the file.
        factors: one vectorised :class:`BetweenFactor` holding every edge (absent when the
            graph has no edges), then a :class:`PriorFactor` on the fixed vertices (if any).
        edges_i, edges_j: ``(M,)`` int64 vertex ids of each edge, in file order.
        measured: ``(M, P)`` float64 relative poses ``x_i^-1 x_j`` in the group's params.
        information: ``(M, T, T)`` float64 information matrices in jaxslam's tangent order.
        fixed: ``(K,)`` int64 ids of fixed vertices (g2o ``FIX`` lines).
        initialised_from: ``"vertices"`` (the file's vertex lines) or ``"odometry"``
            (chained, see :func:`chain_odometry`).
        skipped: tags that were skipped on purpose, with their line counts.
        path: the file read, if any.
    """

    dim: int
    values: Values
    factors: list[Factor]
    edges_i: np.ndarray
    edges_j: np.ndarray
    measured: np.ndarray
    information: np.ndarray
    fixed: np.ndarray
    initialised_from: str = "vertices"
    skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    path: str | None = None

    @property
    def var_type(self) -> type[Variable]:
        return _VAR_TYPES[self.dim]

    @property
    def vertex_ids(self) -> np.ndarray:
        return self.values.ids(self.var_type)

    @property
    def num_edges(self) -> int:
        return int(self.edges_i.shape[0])

    def sqrt_information(self) -> np.ndarray:
        """``(M, T, T)`` upper-triangular ``R`` with ``R^T R = information``."""
        return np.swapaxes(np.linalg.cholesky(self.information), -1, -2)

    def incremental_order(self) -> list[tuple[int, np.ndarray]]:
        """The graph as an online stream (how iSAM2 examples replay it): vertices in id
        order, each arriving with the indices of its edges to earlier vertices.
        Returns ``[(vertex id, edge indices), ...]``; an edge joining a vertex to itself
        is not part of any update."""
        ids = self.vertex_ids
        pos_i = np.searchsorted(ids, self.edges_i)
        pos_j = np.searchsorted(ids, self.edges_j)
        later = np.maximum(pos_i, pos_j)
        later[pos_i == pos_j] = -1
        order = np.argsort(later, kind="stable")
        bounds = np.searchsorted(later[order], np.arange(len(ids) + 1))
        return [(int(ids[k]), order[bounds[k] : bounds[k + 1]]) for k in range(len(ids))]

    def with_values(self, values: Values) -> PoseGraph:
        """The same edges with another estimate (e.g. an optimised one), for writing."""
        return dataclasses.replace(self, values=values)

    @classmethod
    def from_arrays(
        cls,
        dim: int,
        values: Values,
        edges_i: np.ndarray,
        edges_j: np.ndarray,
        measured: np.ndarray,
        information: np.ndarray,
        fixed: Sequence[int] | np.ndarray = (),
        fix_sigma: float = FIX_SIGMA,
        *,
        initialised_from: str = "vertices",
        skipped: dict[str, int] | None = None,
        path: str | None = None,
    ) -> PoseGraph:
        """Build the factors from raw edge arrays (layouts as in the class docstring).

        Raises ValueError for wrong shapes or an information matrix that is not symmetric
        positive definite (naming the edge), GraphError for ids without a value.
        """
        if dim not in _VAR_TYPES:
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        edges_i, edges_j = np.asarray(edges_i, np.int64), np.asarray(edges_j, np.int64)
        measured, information = np.asarray(measured, np.float64), np.asarray(information, np.float64)
        _check_edge_arrays(_VAR_TYPES[dim], edges_i, edges_j, measured, information)
        fixed_ids = np.asarray(fixed, dtype=np.int64).reshape(-1)
        for ids in (edges_i, edges_j, fixed_ids):
            values.rows(_VAR_TYPES[dim](ids))  # GraphError naming an id without a value
        factors = make_factors(dim, values, edges_i, edges_j, measured, information, fixed_ids, fix_sigma)
        return cls(
            dim,
            values,
            factors,
            edges_i,
            edges_j,
            measured,
            information,
            fixed_ids,
            initialised_from,
            dict(skipped or {}),
            path,
        )


def _check_edge_arrays(
    vtype: type[Variable], edges_i: np.ndarray, edges_j: np.ndarray, measured: np.ndarray, information: np.ndarray
) -> None:
    m, p, t = len(edges_i), vtype.param_dim, vtype.tangent_dim
    shapes = {"edges_i": edges_i.shape, "edges_j": edges_j.shape, "measured": measured.shape}
    expect = {"edges_i": (m,), "edges_j": (m,), "measured": (m, p)}
    for name, shape in shapes.items():
        if shape != expect[name]:
            raise ValueError(f"{name} must have shape {expect[name]} for {m} edges, got {shape}")
    if information.shape != (m, t, t):
        raise ValueError(f"information must have shape {(m, t, t)}, got {information.shape}")
    with np.errstate(all="ignore"):
        ok = information_is_valid(information)
    if not ok.all():
        raise ValueError(f"information[{int(np.flatnonzero(~ok)[0])}] is not symmetric positive definite")


def make_factors(
    dim: int,
    values: Values,
    edges_i: np.ndarray,
    edges_j: np.ndarray,
    measured: np.ndarray,
    information: np.ndarray,
    fixed: np.ndarray,
    fix_sigma: float,
) -> list[Factor]:
    """One BetweenFactor for all edges and a PriorFactor (isotropic ``fix_sigma``) holding the
    fixed vertices at their current values."""
    vtype = _VAR_TYPES[dim]
    factors: list[Factor] = []
    if len(edges_i):
        sqrt_info = np.swapaxes(np.linalg.cholesky(information), -1, -2)
        noise = Gaussian.from_sqrt_information(jnp.asarray(sqrt_info))
        factors.append(BetweenFactor.create(vtype(edges_i), vtype(edges_j), jnp.asarray(measured), noise))
    if len(fixed):
        var = vtype(fixed)
        noise = Gaussian.isotropic(vtype.tangent_dim, fix_sigma, len(fixed))
        factors.append(PriorFactor.create(var, values.get(var), noise))
    return factors


def chain_odometry(
    dim: int, edges_i: np.ndarray, edges_j: np.ndarray, measured: np.ndarray, source: str = "pose graph"
) -> tuple[np.ndarray, np.ndarray]:
    """Initial poses by composing odometry edges from the first vertex at the identity.

    The vertices are every id an edge names; the first is the smallest. Vertex ``k`` is reached
    from ``k - 1`` by the first edge ``(k-1, k)`` in file order, or else by inverting the first
    edge ``(k, k-1)``. Returns ``(ids, params)`` sorted by id, params as numpy ``(n, P)``. A
    vertex no such edge reaches (a gap in the ids, or a missing odometry edge) raises
    :class:`GraphError` naming it.

    The running products are an inclusive scan in log2(n) batched steps (Hillis-Steele), in
    numpy: eager JAX would compile every intermediate shape anew.
    """
    ids = np.unique(np.concatenate([edges_i, edges_j]))
    prefix = _odometry_steps(dim, ids, edges_i, edges_j, np.asarray(measured, np.float64), source)
    shift = 1
    with np.errstate(all="ignore"):
        while shift < len(prefix):
            prefix = np.concatenate([prefix[:shift], _compose(dim, prefix[:-shift], prefix[shift:])])
            shift *= 2
        identity = np.asarray((SE2 if dim == 2 else SE3).identity((1,)).params)
        params = _normalized(dim, np.concatenate([identity, prefix]))
    bad = np.flatnonzero(~np.all(np.isfinite(params), axis=-1))
    if bad.size:
        raise GraphError(f"{source}: chaining odometry overflowed at vertex {int(ids[bad[0]])} (edges too large)")
    return ids, params


def _odometry_steps(dim: int, ids: np.ndarray, edges_i, edges_j, measured, source: str) -> np.ndarray:  # type: ignore[no-untyped-def]
    """``(n-1, P)`` relative poses ``x_{k-1}^-1 x_k`` for ids[1:], from forward edges or the
    inverse of backward ones."""
    targets = ids[1:]
    step = np.full((len(targets), measured.shape[-1]), np.nan)
    found = np.zeros(len(targets), dtype=bool)
    for forward in (True, False):
        a, b = (edges_i, edges_j) if forward else (edges_j, edges_i)
        sel = np.flatnonzero((b == a + 1) & (b > ids[0]))
        first_rows, first = np.unique(np.searchsorted(targets, b[sel]), return_index=True)
        new = ~found[first_rows]
        z = measured[sel[first[new]]]
        step[first_rows[new]] = z if forward else _inverse(dim, z)
        found[first_rows[new]] = True
    if not found.all():
        k = int(targets[np.flatnonzero(~found)[0]])
        raise GraphError(
            f"{source}: cannot initialise vertex {k} by chaining odometry: no edge between vertex "
            f"{k - 1} and {k} (files without vertex lines need consecutive odometry edges)"
        )
    return step


# --- numpy group operations on params (SE2: cos sin x y; SE3: qw qx qy qz x y z) ---------------


def _rotate(dim: int, p: np.ndarray, v: np.ndarray, inverse: bool = False) -> np.ndarray:
    if dim == 2:
        c, s = p[:, 0:1], p[:, 1:2] * (-1.0 if inverse else 1.0)
        return np.concatenate([c * v[:, :1] - s * v[:, 1:], s * v[:, :1] + c * v[:, 1:]], axis=-1)
    w, u = p[:, :1], p[:, 1:4] * (-1.0 if inverse else 1.0)
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _compose(dim: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    k = 2 if dim == 2 else 4
    if dim == 2:
        ca, sa, cb, sb = a[:, 0], a[:, 1], b[:, 0], b[:, 1]
        r = np.stack([ca * cb - sa * sb, sa * cb + ca * sb], axis=-1)
    else:
        aw, av, bw, bv = a[:, :1], a[:, 1:4], b[:, :1], b[:, 1:4]
        r = np.concatenate([aw * bw - np.sum(av * bv, -1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], -1)
    return np.concatenate([r, a[:, k:] + _rotate(dim, a, b[:, k:])], axis=-1)


def _inverse(dim: int, p: np.ndarray) -> np.ndarray:
    k = 2 if dim == 2 else 4
    conj = np.array([1.0, -1.0] if dim == 2 else [1.0, -1.0, -1.0, -1.0])
    return np.concatenate([p[:, :k] * conj, -_rotate(dim, p, p[:, k:], inverse=True)], axis=-1)


def _normalized(dim: int, p: np.ndarray) -> np.ndarray:
    k = 2 if dim == 2 else 4
    return np.concatenate([p[:, :k] / np.linalg.norm(p[:, :k], axis=-1, keepdims=True), p[:, k:]], axis=-1)
