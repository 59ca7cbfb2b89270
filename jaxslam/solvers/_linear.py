"""Linear solvers for the Gauss-Newton normal equations ``H delta = -g``.

* ``cholmod`` (default where available): CHOLMOD's supernodal Cholesky through
  scikit-sparse. The symbolic analysis (elimination tree, supernodes) is done once per
  sparsity pattern and reused by every numeric factorisation. The matrix arrives already in
  a block fill-reducing order (see ``_problem.block_ordering``), so CHOLMOD is told to keep
  it ("natural"). With OpenBLAS this is the fastest CPU path measured here (FIELD-NOTES).
* ``pardiso`` (default where the ``mkl`` wheel is installed): Intel MKL PARDISO through a
  small ctypes binding (``_pardiso.py``); measured faster than CHOLMOD+OpenBLAS here.
* ``splu``: scipy's SuperLU on the symmetric matrix, for machines without SuiteSparse.
* ``pcg``: preconditioned conjugate gradients in pure JAX (matrix-free over the stored lower
  triangle, scalar Jacobi preconditioner): no host round trip, runs on GPU.

All return ``None`` when the system is not positive definite (the caller reports the status).
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jax import Array

try:  # pragma: no cover - import guard
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

    HAVE_CHOLMOD = True
except ImportError:  # pragma: no cover
    HAVE_CHOLMOD = False


from ._pardiso import Pardiso, PardisoNotPositiveDefinite, pardiso_available


def _finite_or_none(solve: Callable[[np.ndarray], np.ndarray]) -> Callable[[Array | np.ndarray], np.ndarray | None]:
    def run(rhs: Array | np.ndarray) -> np.ndarray | None:
        x = np.asarray(solve(np.asarray(rhs, dtype=np.float64)))
        return x if np.all(np.isfinite(x)) else None

    return run


def available_linear_solvers() -> list[str]:
    return (["pardiso"] if pardiso_available() else []) + (["cholmod"] if HAVE_CHOLMOD else []) + ["splu", "pcg"]


def default_linear_solver() -> str:
    return available_linear_solvers()[0]


class SparseSystem:
    """The lower-triangular CSC pattern of ``H`` and a solver bound to it."""

    def __init__(
        self,
        indices: np.ndarray,
        indptr: np.ndarray,
        n: int,
        diag_pos: np.ndarray,
        method: str,
        diag_blocks: list[tuple[np.ndarray, np.ndarray]] | None = None,
    ):
        if method == "auto":
            method = default_linear_solver()
        if method == "cholmod" and not HAVE_CHOLMOD:
            raise ValueError("linear solver 'cholmod' needs scikit-sparse (pip install 'jaxslam[cholmod]')")
        if method == "pardiso" and not pardiso_available():
            raise ValueError("linear solver 'pardiso' needs Intel MKL (pip install 'jaxslam[mkl]')")
        if method not in ("pardiso", "cholmod", "splu", "pcg"):
            raise ValueError(f"unknown linear solver {method!r}; choose from {available_linear_solvers()}")
        self.method = method
        self.n = n
        self.indices = indices
        self.indptr = indptr
        self.diag_pos = diag_pos
        self._factor: Any = None
        self._cols = None
        if method == "pcg":
            counts = np.diff(indptr)
            self._cols = jnp.asarray(np.repeat(np.arange(n), counts), dtype=jnp.int32)
            self._rows = jnp.asarray(indices, dtype=jnp.int32)
            self._diag = jnp.asarray(diag_pos, dtype=jnp.int32)
            if diag_blocks is None:  # scalar Jacobi: 1x1 blocks
                diag_blocks = [(np.arange(n)[:, None], np.asarray(diag_pos)[:, None, None])]
            self._blocks = tuple((jnp.asarray(d, jnp.int32), jnp.asarray(p, jnp.int32)) for d, p in diag_blocks)

    def matrix(self, hdata: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((hdata, self.indices, self.indptr), shape=(self.n, self.n))

    def solve(
        self, hdata: Array | np.ndarray, rhs: Array | np.ndarray, damping: np.ndarray | None = None
    ) -> np.ndarray | None:
        """Solve ``(H + diag(damping)) x = rhs``; ``None`` if not positive definite."""
        solve = self.factorize(hdata, damping)
        return None if solve is None else solve(rhs)

    def factorize(
        self, hdata: Array | np.ndarray, damping: np.ndarray | None = None
    ) -> Callable[[Array | np.ndarray], np.ndarray | None] | None:
        """Factorise ``H + diag(damping)`` once; returns ``solve(rhs)`` (reusable for several
        right-hand sides, e.g. an adjoint's preconditioner) or ``None`` if not positive definite.
        The returned function is valid until the next ``factorize``/``solve`` call."""
        if self.method == "pcg":
            d = jnp.zeros(self.n) if damping is None else jnp.asarray(damping)
            h = jnp.asarray(hdata)

            def pcg(rhs: Array | np.ndarray) -> np.ndarray | None:
                x, ok = pcg_solve(h, self._rows, self._cols, self._diag, self._blocks, d, jnp.asarray(rhs))
                return np.asarray(x) if bool(ok) else None

            return pcg
        data = np.array(hdata, dtype=np.float64, copy=True)
        if damping is not None:
            data[self.diag_pos] += damping
        if self.method == "pardiso":
            if self._factor is None:
                self._factor = Pardiso(self.indptr, self.indices, self.n)
            try:
                self._factor.factorize(data)
            except PardisoNotPositiveDefinite:
                return None
            return _finite_or_none(self._factor.solve)
        a = self.matrix(data)
        if self.method == "cholmod":
            try:
                if self._factor is None:
                    self._factor = analyze(a, mode="supernodal", ordering_method="natural")
                self._factor.cholesky_inplace(a)
            except CholmodNotPositiveDefiniteError:
                return None
            return _finite_or_none(self._factor)
        full = (a + sp.tril(a, -1).T).tocsc()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                # Symmetric mode: no row pivoting, so the fill-reducing order is kept;
                # a non-positive pivot then means H is not positive definite.
                lu = sp.linalg.splu(
                    full, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
                )
            except RuntimeError:
                return None
        if np.any(lu.U.diagonal() <= 0):
            return None
        return _finite_or_none(lu.solve)

    def matvec(self, hdata: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``H x`` from the stored lower triangle."""
        a = self.matrix(np.asarray(hdata))
        return a @ x + a.T @ x - np.asarray(hdata)[self.diag_pos] * x


@functools.partial(jax.jit, static_argnames=("maxiter",))
def pcg_solve(
    hdata: Array,
    rows: Array,
    cols: Array,
    diag_pos: Array,
    blocks: tuple[tuple[Array, Array], ...],
    damping: Array,
    rhs: Array,
    tol: float = 1e-10,
    maxiter: int = 2000,
) -> tuple[Array, Array]:
    """Block-Jacobi-preconditioned CG on the symmetric matrix stored as its lower triangle.
    ``blocks``: per variable type, the dof indices ``(cap, t)`` and H-data positions
    ``(cap, t, t)`` of every diagonal block (position ``len(hdata)`` = structural zero)."""
    n = rhs.shape[0]
    hpad = jnp.concatenate([hdata, jnp.zeros(1, hdata.dtype)])
    inverses = []
    for dofs, pos in blocks:
        b = hpad[pos] + jax.vmap(jnp.diag)(damping[dofs])
        # padded (untouched) variables have a zero block: use the identity there
        bad = jnp.abs(jnp.linalg.det(b)) <= 0
        b = jnp.where(bad[:, None, None], jnp.eye(b.shape[-1]), b)
        inverses.append(jnp.linalg.inv(b))

    def precondition(r: Array) -> Array:
        z = jnp.zeros_like(r)
        for (dofs, _), inv in zip(blocks, inverses):
            z = z.at[dofs].set(jnp.sum(inv * r[dofs][:, None, :], axis=-1))
        return z

    def matvec(x: Array) -> Array:
        lower = jax.ops.segment_sum(hdata * x[cols], rows, num_segments=n)
        upper = jax.ops.segment_sum(hdata * x[rows], cols, num_segments=n)
        return lower + upper - hdata[diag_pos] * x + damping * x

    x0 = jnp.zeros_like(rhs)
    r0 = rhs
    z0 = precondition(r0)
    rz0 = r0 @ z0
    bnorm = jnp.linalg.norm(rhs)

    def cond(state: Any) -> Array:
        _, r, _, _, k, bad = state
        return (jnp.linalg.norm(r) > tol * bnorm) & (k < maxiter) & ~bad

    def body(state: Any) -> Any:
        x, r, p, rz, k, _ = state
        ap = matvec(p)
        pap = p @ ap
        bad = pap <= 0
        alpha = rz / jnp.where(bad, 1.0, pap)
        x = x + alpha * p
        r = r - alpha * ap
        z = precondition(r)
        rz_new = r @ z
        p = z + (rz_new / rz) * p
        return x, r, p, rz_new, k + 1, bad

    x, _, _, _, _, bad = jax.lax.while_loop(cond, body, (x0, r0, z0, rz0, jnp.array(0), jnp.array(False)))
    # An inexact (maxiter) step is still a descent direction for LM; only breakdown fails.
    ok = ~bad & jnp.all(jnp.isfinite(x))
    return x, ok
