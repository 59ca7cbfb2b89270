"""The Gauss-Newton information of a growing graph, kept as blocks between full solves.

For graphs whose variables share one tangent dimension ``bs`` (pose graphs), the
incremental solver's full step used to assemble ``H = sum J^T J`` from every constraint's
cached Gram block, run AMD on the scalar matrix and factorise: on parking-garage (10k dofs)
that was ~12 ms of assembly and ~4 ms of ordering per solve. :class:`BlockInformation`
instead holds one dense ``(bs, bs)`` block per connected pair of variables (lower triangle,
block row >= block column) and is updated in place whenever a constraint is added,
relinearised or removed, so a full solve starts from the finished matrix. The
fill-reducing order is computed on the block graph (``nb`` nodes instead of ``bs * nb``),
the lower triangle is built directly in that order, and the symbolic analysis (ordering
and CHOLMOD's ``analyze``) is reused for as long as the block pattern stays the same (in a
growing stream every full solve brings new variables, so that is mostly ``refine``'s
repeated solves). CHOLMOD factorises simplicially unless the factor turns out dense
(sphere2500), where its supernodal kernels are ~2.5x faster; the other way round on
parking-garage.

Variables are numbered ``0 .. nb-1`` by the caller (the incremental solver uses the
permanent dof divided by ``bs``); block ``(i, j)`` couples variables ``i >= j``.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.sparse as sp

try:  # pragma: no cover - import guard
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

    HAVE_CHOLMOD = True
except ImportError:  # pragma: no cover
    HAVE_CHOLMOD = False


# threadpoolctl's controllers of the loaded BLAS libraries, and len(sys.modules) when they
# were listed: an import since may have loaded another BLAS (torch, scikit-learn, ...)
_BLAS_LIBS: tuple[int, list[Any]] | None = None


class _OneBlasThread:
    """Each loaded BLAS at one thread inside, its thread count restored after: the two
    calls per library that ``ThreadpoolController.limit`` makes, without its bookkeeping
    (5 us against 32 us per use here; the solver enters it once per dense factorisation)."""

    def __init__(self, libs: list[Any]):
        self.libs = libs
        self.saved: list[tuple[Any, int]] = []

    def __enter__(self) -> None:
        self.saved = [(lib, lib.num_threads) for lib in self.libs]
        for lib, n in self.saved:
            if n != 1:
                lib.set_num_threads(1)

    def __exit__(self, *exc: object) -> None:
        for lib, n in self.saved:
            if n != 1:
                lib.set_num_threads(n)


def one_blas_thread() -> Any:
    """A context with OpenBLAS/MKL limited to one thread. Small dense factorisations (a few
    hundred unknowns) run 10-100x slower when BLAS threads contend with JAX's on a loaded
    2-core CPU (measured on the KITTI IMU+GPS stream: 89 ms vs 0.07 ms per 165x165 Cholesky);
    CHOLMOD's supernodal factorisation of sphere2500 (15k dofs) was as fast or faster on one
    thread than on two on this shared machine. The libraries are listed again whenever a
    module was imported since the last listing (a BLAS comes with an import; listing costs
    ~1 ms, the check nothing)."""
    global _BLAS_LIBS
    if _BLAS_LIBS is None or _BLAS_LIBS[0] != len(sys.modules):
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:  # pragma: no cover - threadpoolctl is a core dependency
            return contextlib.nullcontext()
        _BLAS_LIBS = (len(sys.modules), list(ThreadpoolController().select(user_api="blas").lib_controllers))
    return _OneBlasThread(_BLAS_LIBS[1])


class NotPositiveDefinite(Exception):
    """The assembled information is not positive definite."""


def pairs(k: int) -> list[tuple[int, int]]:
    """The unordered slot pairs ``(a, b), a <= b`` of a constraint on ``k`` variables."""
    return [(a, b) for a in range(k) for b in range(a, k)]


# Factor density (nonzeros of L per unknown) above which the supernodal factorisation is
# used. Measured here (final systems, this 2-core machine): parking-garage 42 per unknown,
# simplicial 9-13 ms vs supernodal 16-28; city10000 35, 33 vs 37 ms; sphere2500 101,
# simplicial 115-190 ms vs supernodal 43-70.
_SUPERNODAL_DENSITY = 64.0
_DECIDE_MIN = 2000  # unknowns: below, simplicial (the choice is not worth a second analysis)


class BlockInformation:
    """Block-sparse lower triangle of ``H`` with in-place updates (see the module docstring)."""

    def __init__(self, bs: int):
        self.bs = bs
        self.n = 0  # blocks in use
        self._slot: dict[int, int] = {}  # key i * _KEY + j -> slot
        cap = 256
        self.brow = np.zeros(cap, np.int64)
        self.bcol = np.zeros(cap, np.int64)
        self.data = np.zeros((cap, bs, bs))
        self._has_diag = np.zeros(0, bool)  # per variable: its diagonal block has a slot
        self._symbolic: tuple[Any, ...] | None = None  # (key, *_analyze's results)
        self.analyses = 0  # symbolic analyses done (the rest were reused)
        # CHOLMOD's factorisation: supernodal (dense BLAS kernels on column groups) pays off
        # when the factor is dense enough, simplicial otherwise. Simplicial until the factor's
        # density (checked whenever the system has grown by a quarter) says otherwise; a
        # growing graph's factor only gets denser, so there is no way back.
        self.mode = "simplicial"
        self._mode_nb = 0

    _KEY = 1 << 31

    def _grow(self, need: int) -> None:
        cap = len(self.brow)
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in ("brow", "bcol", "data"):
            old = getattr(self, name)
            arr = np.zeros((new, *old.shape[1:]), old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def slots(self, var: np.ndarray) -> np.ndarray:
        """Slots ``(m, len(pairs(k)))`` of the blocks that constraints on variables ``var``
        ``(m, k)`` add to (allocated on first use)."""
        var = np.asarray(var, np.int64)
        m, k = var.shape
        pp = pairs(k)
        out = np.empty((m, len(pp)), np.int64)
        hi = np.stack([np.maximum(var[:, a], var[:, b]) for a, b in pp], axis=1)
        lo = np.stack([np.minimum(var[:, a], var[:, b]) for a, b in pp], axis=1)
        keys = (hi * self._KEY + lo).ravel().tolist()
        flat = out.reshape(-1)
        get = self._slot.get
        fresh: list[int] = []
        for pos, key in enumerate(keys):
            s = get(key)
            if s is None:
                s = self.n + len(fresh)
                self._slot[key] = s
                fresh.append(key)
            flat[pos] = s
        if fresh:
            f = np.asarray(fresh, np.int64)
            self._grow(self.n + len(f))
            self.brow[self.n : self.n + len(f)] = f // self._KEY
            self.bcol[self.n : self.n + len(f)] = f % self._KEY
            self.n += len(f)
            d = f[f // self._KEY == f % self._KEY] // self._KEY
            if d.size:
                if d.max() >= len(self._has_diag):
                    grown = np.zeros(max(int(d.max()) + 1, 2 * len(self._has_diag)), bool)
                    grown[: len(self._has_diag)] = self._has_diag
                    self._has_diag = grown
                self._has_diag[d] = True
        return out

    def add(self, slots: np.ndarray, var: np.ndarray, G: np.ndarray, sign: float = 1.0) -> None:
        """Add ``sign *`` the Gram blocks ``G`` ``(m, k*bs, k*bs)`` of constraints on ``var``
        ``(m, k)`` to their ``slots`` (from :meth:`slots`)."""
        m = len(slots)
        if m == 0:
            return
        bs = self.bs
        k = var.shape[1]
        Gb = G.reshape(m, k, bs, k, bs)
        pp = pairs(k)
        a = np.array([p[0] for p in pp])
        b = np.array([p[1] for p in pp])
        # the block (later variable, earlier variable): rows of the later one
        swap = var[:, a] < var[:, b]  # (m, pairs)
        rows = np.where(swap, b, a)
        cols = np.where(swap, a, b)
        blk = Gb[np.arange(m)[:, None], rows, :, cols, :]  # (m, pairs, bs, bs)
        if sign != 1.0:
            blk = sign * blk
        np.add.at(self.data, slots.ravel(), blk.reshape(-1, bs, bs))

    def clear(self) -> None:
        """Zero every block (the pattern stays)."""
        self.data[: self.n] = 0.0

    # --- factorisation ------------------------------------------------------------------------
    def factorize(self, nb: int) -> Callable[[np.ndarray], np.ndarray]:
        """Factorise ``H`` over variables ``0 .. nb-1`` (a zero diagonal entry, a variable
        without factors, becomes 1 so it stays put); returns ``solve(rhs)`` in the natural
        dof order. Raises :class:`NotPositiveDefinite`."""
        bs = self.bs
        known = np.zeros(nb, bool)
        m = min(nb, len(self._has_diag))
        known[:m] = self._has_diag[:m]
        if not np.all(known):  # every variable needs its diagonal block in the pattern
            self.slots(np.nonzero(~known)[0][:, None])
        key = (self.n, nb)
        decide = False
        if self._symbolic is None or self._symbolic[0] != key:
            decide = self.mode == "simplicial" and nb >= 1.25 * self._mode_nb and nb * self.bs >= _DECIDE_MIN
            self._symbolic = (key, *self._analyze(nb, self.mode))
            self.analyses += 1
        ip, factor = self._symbolic[1], self._symbolic[-1]
        A = self._lower(nb)
        try:
            with one_blas_thread() if self.mode == "supernodal" else contextlib.nullcontext():
                factor.cholesky_inplace(A)
                if decide:  # columns of L per unknown, from the simplicial factor
                    density = factor.LD().nnz / (nb * bs)
                    self.mode = "supernodal" if density > _SUPERNODAL_DENSITY else "simplicial"
                    self._mode_nb = nb
                    if self.mode == "supernodal":
                        factor = analyze(A, mode="supernodal", ordering_method="natural")
                        self._symbolic = (key, *self._symbolic[1:-1], factor)
                        factor.cholesky_inplace(A)
        except CholmodNotPositiveDefiniteError as err:
            raise NotPositiveDefinite from err
        perm = (np.argsort(ip)[:, None] * bs + np.arange(bs)).ravel()  # new position -> old dof

        def solve(rhs: np.ndarray) -> np.ndarray:
            x = np.empty_like(rhs)
            x[perm] = factor(rhs[perm])
            return x

        return solve

    def _lower(self, nb: int) -> sp.csc_matrix:
        """The scalar lower triangle of ``H`` (diagonal blocks whole) in the current symbolic
        analysis's order, as CSC, read straight from the blocks through the map made with the
        pattern: the same matrix as assembling it block by block, 0.33 ms against 2.2 ms on
        parking-garage's final system. A zero diagonal entry (a variable without factors)
        becomes 1 so it stays put."""
        if self._symbolic is None:
            raise ValueError("no symbolic analysis yet: factorize() makes one")
        _, _, gather, indices, indptr, dpos, _ = self._symbolic
        vals = self.data[: self.n].reshape(-1)[gather]
        dv = vals[dpos]
        if np.any(dv == 0.0):
            vals[dpos[dv == 0.0]] = 1.0
        return sp.csc_matrix((vals, indices, indptr), shape=(nb * self.bs, nb * self.bs))

    def _analyze(self, nb: int, mode: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, Any]:
        """Block AMD order (``ip``: variable -> position), the pattern of the scalar lower
        triangle in that order as CSC (``indices``, ``indptr``) with, per stored entry, its
        position in the flattened blocks ``data[:n]`` (``gather``; a block stored as (earlier,
        later) is read transposed) and the positions of the diagonal (``dpos``), and
        CHOLMOD's symbolic analysis of that pattern."""
        n = self.n
        br, bc = self.brow[:n], self.bcol[:n]
        graph = sp.csc_matrix((np.ones(n), (br, bc)), shape=(nb, nb))
        p = np.asarray(analyze(graph, ordering_method="amd").P(), np.int64) if nb > 2 else np.arange(nb)
        ip = np.empty(nb, np.int64)
        ip[p] = np.arange(nb)
        r, c = ip[br], ip[bc]
        lo, hi = np.maximum(r, c), np.minimum(r, c)
        order = np.lexsort((hi, lo))
        bs = self.bs
        # each block's entries numbered by their place in data[:n] (+1: a stored 0 is kept
        # apart from a missing entry), arranged as the factorisation reads them
        where = np.arange(1, n * bs * bs + 1, dtype=np.float64).reshape(n, bs, bs)[order]
        swap = (r < c)[order]
        where[swap] = np.swapaxes(where[swap], 1, 2)
        lo, hi = lo[order], hi[order]
        indptr = np.searchsorted(lo, np.arange(nb + 1)).astype(np.int32)
        A = sp.bsr_matrix((where, hi.astype(np.int32), indptr), shape=(nb * bs, nb * bs)).tocsc()
        gather = A.data.astype(np.int64) - 1
        rows = A.indices.astype(np.int64)
        cols = np.repeat(np.arange(nb * bs), np.diff(A.indptr))
        dpos = np.nonzero(rows == cols)[0]
        factor = analyze(A, mode=mode, ordering_method="natural")
        return ip, gather, A.indices, A.indptr, dpos, factor
