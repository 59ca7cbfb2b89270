"""Pose-graph initialisation better than chaining odometry: chordal relaxation.

1. Rotations (Martinec & Pajdla 2007; Carlone et al., "Initialization techniques for 3D SLAM",
   ICRA 2015 — the method of GTSAM's ``InitializePose3``): every edge says
   ``R_j = R_i R_ij``, i.e. ``R_ij^T r_i - r_j = 0`` for each of the three rows ``r`` of the
   rotation matrices. That is linear: one sparse least-squares problem with three right-hand
   sides, the anchor's rotation fixed. Each 3x3 solution is projected onto SO(3) by SVD.
   In 2-D the same with ``(cos, sin)`` pairs.
2. Translations, with the rotations fixed: ``t_j - t_i = R_i t_ij`` is linear too.

Edges are weighted by the mean of the rotational / translational information diagonal. The
result is an initial guess for Gauss-Newton, not an optimum; it avoids the poor local minima
that LM falls into from chained odometry on graphs such as torus3D or cubicle.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import GraphError
from ..lie.host import matrix_to_quat as _matrix_to_quat
from ..lie.host import quat_to_matrix as _quat_to_matrix


def _solve_anchored(
    rows: np.ndarray,
    cols: np.ndarray,
    vals: np.ndarray,
    nrow: int,
    n_unknown: int,
    rhs: np.ndarray,
    fixed: np.ndarray,
    fixed_value: np.ndarray,
) -> np.ndarray:
    """Least squares ``A x = rhs`` with the unknowns ``fixed`` set to ``fixed_value``."""
    a = sp.csr_matrix((vals, (rows, cols)), shape=(nrow, n_unknown))
    free = np.ones(n_unknown, bool)
    free[fixed] = False
    b = rhs - a[:, fixed] @ fixed_value
    af = a[:, free].tocsc()
    normal = (af.T @ af).tocsc()
    try:
        lu = spla.splu(normal, permc_spec="MMD_AT_PLUS_A")
    except RuntimeError as exc:
        raise GraphError("chordal initialisation: the graph is not connected to the anchor") from exc
    x = np.zeros((n_unknown, *rhs.shape[1:]))
    x[fixed] = fixed_value
    x[free] = lu.solve(af.T @ b)
    return x


def _index(ids: np.ndarray, edges: np.ndarray) -> np.ndarray:
    pos = np.searchsorted(ids, edges)
    pos_c = np.minimum(pos, len(ids) - 1)
    if np.any(ids[pos_c] != edges):
        raise GraphError(f"edge refers to vertex {int(edges[ids[pos_c] != edges][0])}, which has no value")
    return pos_c


def _check_connected(n: int, ei: np.ndarray, ej: np.ndarray, anchor: int, ids: np.ndarray) -> None:
    from scipy.sparse.csgraph import connected_components

    adj = sp.coo_matrix((np.ones(len(ei)), (ei, ej)), shape=(n, n))
    _, labels = connected_components(adj, directed=False)
    bad = np.nonzero(labels != labels[anchor])[0]
    if bad.size:
        raise GraphError(
            f"chordal initialisation: vertex {int(ids[bad[0]])} (and {bad.size - 1} more) is not connected "
            f"to the anchor vertex {int(ids[anchor])}"
        )


def _edge_rows(ids: np.ndarray, edges_i: np.ndarray, edges_j: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted ids, and each edge's end points as rows of them; checks connectivity."""
    ids = np.asarray(ids)
    ei, ej = _index(ids, np.asarray(edges_i)), _index(ids, np.asarray(edges_j))
    _check_connected(len(ids), ei, ej, 0, ids)
    return ids, ei, ej


def _weights(information: np.ndarray | None, e: int, rot: slice, trans: slice) -> tuple[np.ndarray, np.ndarray]:
    if information is None:
        return np.ones(e), np.ones(e)
    d = np.diagonal(information, axis1=-2, axis2=-1)
    return np.sqrt(np.maximum(d[:, rot].mean(-1), 1e-12)), np.sqrt(np.maximum(d[:, trans].mean(-1), 1e-12))


def chordal_initialize_se3(
    ids: np.ndarray,
    edges_i: np.ndarray,
    edges_j: np.ndarray,
    measured: np.ndarray,
    information: np.ndarray | None = None,
    anchor_pose: np.ndarray | None = None,
) -> np.ndarray:
    """Initial SE(3) params ``(N, 7)`` for vertex ``ids`` (sorted) from between edges
    (``measured`` ``(E, 7)``, ``information`` ``(E, 6, 6)`` in [rot, trans] order). The first
    id is the anchor, placed at ``anchor_pose`` (identity by default)."""
    ids, ei, ej = _edge_rows(ids, edges_i, edges_j)
    n = len(ids)
    e = len(ei)
    meas = np.asarray(measured, dtype=np.float64)
    rij = _quat_to_matrix(meas[:, :4])  # (E, 3, 3)
    tij = meas[:, 4:]
    wr, wt = _weights(information, e, slice(0, 3), slice(3, 6))
    anchor = np.array([1.0, 0, 0, 0, 0, 0, 0]) if anchor_pose is None else np.asarray(anchor_pose, dtype=np.float64)
    r0 = _quat_to_matrix(anchor[None, :4])[0]

    # rotations: unknown x[3 * v + c] is column c of R_v^T (i.e. row c of R_v), stacked over
    # the three right-hand sides (the rows of the rotation).
    eq = np.arange(3 * e).reshape(e, 3)
    rows = np.concatenate([np.repeat(eq, 3, axis=1).ravel(), eq.ravel()])
    cols_i = (3 * ei[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    vals_i = np.swapaxes(rij, 1, 2) * wr[:, None, None]  # R_ij^T r_i
    cols = np.concatenate([cols_i.ravel(), (3 * ej[:, None] + np.arange(3)[None, :]).ravel()])
    vals = np.concatenate([vals_i.ravel(), (-np.ones((e, 3)) * wr[:, None]).ravel()])
    rhs = np.zeros((3 * e, 3))
    x = _solve_anchored(rows, cols, vals, 3 * e, 3 * n, rhs, np.arange(3), r0.T)
    # x[3v:3v+3, k] = row k of R_v  ->  R_v[k, :] = x[3v:3v+3, k]
    mats = np.swapaxes(x.reshape(n, 3, 3), 1, 2)
    u, _, vt = np.linalg.svd(mats)
    det = np.linalg.det(u @ vt)
    u[:, :, -1] *= det[:, None]
    rots = u @ vt

    # translations: t_j - t_i = R_i t_ij
    rhs_t = np.einsum("eab,eb->ea", rots[ei], tij) * wt[:, None]
    rows_t = np.concatenate([np.arange(e), np.arange(e)])
    cols_t = np.concatenate([ei, ej])
    vals_t = np.concatenate([-wt, wt])
    t = _solve_anchored(rows_t, cols_t, vals_t, e, n, rhs_t, np.array([0]), anchor[None, 4:])
    q = _matrix_to_quat(rots)
    return np.concatenate([q, t], axis=1)


def chordal_initialize_se2(
    ids: np.ndarray,
    edges_i: np.ndarray,
    edges_j: np.ndarray,
    measured: np.ndarray,
    information: np.ndarray | None = None,
    anchor_pose: np.ndarray | None = None,
) -> np.ndarray:
    """The 2-D version: params ``(N, 4)`` (cos, sin, x, y); information in [theta, x, y]."""
    ids, ei, ej = _edge_rows(ids, edges_i, edges_j)
    n = len(ids)
    e = len(ei)
    meas = np.asarray(measured)
    c, s = meas[:, 0], meas[:, 1]
    wr, wt = _weights(information, e, slice(0, 1), slice(1, 3))
    a0 = np.array([1.0, 0, 0, 0]) if anchor_pose is None else np.asarray(anchor_pose, dtype=np.float64)
    # (c_j, s_j) = rot(theta_ij) applied on the right: c_j = c_i c - s_i s, s_j = s_i c + c_i s
    eq = np.arange(2 * e).reshape(e, 2)
    rows = np.concatenate([eq[:, 0], eq[:, 0], eq[:, 0], eq[:, 1], eq[:, 1], eq[:, 1]])
    cols = np.concatenate([2 * ei, 2 * ei + 1, 2 * ej, 2 * ei, 2 * ei + 1, 2 * ej + 1])
    vals = np.concatenate([c * wr, -s * wr, -wr, s * wr, c * wr, -wr])
    x = _solve_anchored(rows, cols, vals, 2 * e, 2 * n, np.zeros(2 * e), np.array([0, 1]), a0[:2])
    cs = x.reshape(n, 2)
    cs = cs / np.maximum(np.linalg.norm(cs, axis=1, keepdims=True), 1e-12)
    ci, si = cs[ei, 0], cs[ei, 1]
    tx, ty = meas[:, 2], meas[:, 3]
    rhs = np.stack([ci * tx - si * ty, si * tx + ci * ty], axis=1) * wt[:, None]
    rows_t = np.concatenate([np.arange(e), np.arange(e)])
    cols_t = np.concatenate([ei, ej])
    vals_t = np.concatenate([-wt, wt])
    t = _solve_anchored(rows_t, cols_t, vals_t, e, n, rhs, np.array([0]), a0[None, 2:])
    return np.concatenate([cs, t], axis=1)
