"""Compiled (numba) kernels of the Bayes tree's re-elimination (:mod:`._bayestree`).

An update of the tree re-eliminates a few dozen variables in about ten small cliques. Written
as numpy calls, each clique costs some twenty calls of a few microseconds of overhead each,
which made the Python bookkeeping, not the arithmetic, most of an update's time. These
kernels run the ordering (minimum degree), the symbolic phase (elimination tree, relaxed
supernodes), the numeric phase (assembly of children's cached factors, dense Cholesky of
each clique, back-substitution of the new cliques) and one clique's step of the lazy
back-substitution (the wildfire) in compiled loops; the tree's state stays in the Python
cliques.

Written here, not taken from a library: no package offers partial re-elimination of a sparse
Cholesky factor. The frontal matrices and cached factors keep their lower triangles only;
the Schur complement is SciPy's BLAS ``dsyrk`` (half of a full product's arithmetic), called
in place by address (:func:`_fcall`).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import get_cython_function_address, intrinsic

_jit = numba.njit(cache=True, nogil=True)

# SciPy's BLAS and LAPACK (those numba's np.dot and np.linalg use), called by address: dsyrk
# and dgemm write the Schur complement and the conditional in place, where np.dot's
# temporaries (megabytes per clique on large tops, fresh pages each) cost more than the
# arithmetic; dpotrf and dtrtri factorise and invert a clique's frontal block. The addresses
# are passed to the kernels at run time (a compiled-in address would not survive numba's
# cache).
BLAS = np.asarray(
    [get_cython_function_address("scipy.linalg.cython_blas", f) for f in ("dsyrk", "dgemm")]
    + [get_cython_function_address("scipy.linalg.cython_lapack", f) for f in ("dpotrf", "dtrtri")],
    np.int64,
)
_SYRK, _GEMM, _POTRF, _TRTRI = 0, 1, 2, 3


def _fcall_typing(typingctx, addr, ptrs):  # pragma: no cover - compiled
    """Call the Fortran-convention function at ``addr`` with the pointers ``ptrs`` (a tuple
    of addresses as integers)."""
    if not isinstance(ptrs, types.BaseTuple) or not all(isinstance(t, types.Integer) for t in ptrs):
        return None

    def codegen(context, builder, sig, args):
        p8 = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [p8] * len(ptrs))
        fn = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(fn, [builder.inttoptr(v, p8) for v in cgutils.unpack_tuple(builder, args[1])])
        return context.get_dummy_value()

    return types.void(types.int64, ptrs), codegen


_fcall: Any = intrinsic(_fcall_typing)  # typed Any: numba's stub wants the typing context too


@_jit
def min_degree(m: int, h_ptr: np.ndarray, h_vars: np.ndarray, last: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Minimum-degree elimination order of ``m`` variables whose graph joins every pair
    within each hyperedge ``h_vars[h_ptr[k]:h_ptr[k+1]]`` (a constraint's variables, a
    cached factor's separator), on the explicit elimination graph; the variables with
    ``last`` set come after all others (GTSAM's constrained ordering), and ties go to the
    lower index. Exact minimum degree: O(m^2) plus the fill, for tops of a few hundred
    variables."""
    adj = np.zeros((m, m), np.bool_)
    for k in range(len(h_ptr) - 1):
        for a in range(h_ptr[k], h_ptr[k + 1]):
            for b in range(h_ptr[k], h_ptr[k + 1]):
                adj[h_vars[a], h_vars[b]] = True
    deg = np.zeros(m, np.int64)
    for v in range(m):
        adj[v, v] = False
        for u in range(m):
            if adj[v, u]:
                deg[v] += 1
    done = np.zeros(m, np.bool_)
    perm = np.empty(m, np.int64)
    nb = np.empty(m, np.int64)
    nlast = 0
    for v in range(m):
        if last[v]:
            nlast += 1
    for k in range(m):
        phase_last = k >= m - nlast
        best = -1
        for v in range(m):
            if not done[v] and last[v] == phase_last and (best < 0 or deg[v] < deg[best]):
                best = v
        v = best
        perm[k] = v
        done[v] = True
        n = 0
        for u in range(m):
            if adj[v, u]:
                nb[n] = u
                n += 1
        for a in range(n):
            x = nb[a]
            adj[x, v] = False
            deg[x] -= 1
            for b in range(a + 1, n):
                y = nb[b]
                if not adj[x, y]:
                    adj[x, y] = True
                    adj[y, x] = True
                    deg[x] += 1
                    deg[y] += 1
    return perm


@_jit
def _union(vals: np.ndarray, j: int, mark: np.ndarray, buf: np.ndarray, n: int) -> int:  # pragma: no cover
    """Append to ``buf[:n]`` the ``vals`` not yet marked with ``j`` (marking them); returns
    the new count."""
    for b in vals:
        if mark[b] != j:
            mark[b] = j
            buf[n] = b
            n += 1
    return n


@_jit
def symbolic(m, h_ptr, h_vars, pos, relax, cap):  # pragma: no cover - compiled
    """Elimination tree and relaxed supernodes of ``m`` variables eliminated in the order
    ``pos`` (the position of each variable) whose graph joins every pair within each
    hyperedge ``h_vars[h_ptr[k]:h_ptr[k+1]]``.

    ``struct[j]``, the variables after ``j`` that share a row with it once the earlier ones
    are eliminated, is its own later neighbours plus its children's structures; its parent
    is the first of them. Variable ``j`` joins its parent's clique when that adds at most
    ``relax`` zero blocks to its row and the clique has fewer than ``cap`` variables.

    Returns ``(lvp, nfr, cnt, group)``: cliques numbered leaves first, each as its frontal
    positions followed by its separator positions (ascending) in ``lvp``; ``nfr`` and
    ``cnt`` the frontal and total counts per clique; ``group[j]`` the clique of position
    ``j``.
    """
    # edges by position: each hyperedge's first variable to eliminate to the others (the
    # rest of the hyperedge's pairs appear as fill in that variable's structure)
    ne = len(h_vars)
    ea = np.empty(ne, np.int64)
    eb = np.empty(ne, np.int64)
    for k in range(len(h_ptr) - 1):
        lo = m
        for a in range(h_ptr[k], h_ptr[k + 1]):
            lo = min(lo, pos[h_vars[a]])
        for a in range(h_ptr[k], h_ptr[k + 1]):
            ea[a] = lo
            eb[a] = pos[h_vars[a]]
    # later neighbours of each position (CSR)
    deg = np.zeros(m + 1, np.int64)
    for k in range(len(ea)):
        if ea[k] != eb[k]:
            deg[ea[k] + 1] += 1
    aptr = np.cumsum(deg)
    adj = np.empty(aptr[m], np.int64)
    fill = aptr[:m].copy()
    for k in range(len(ea)):
        if ea[k] != eb[k]:
            adj[fill[ea[k]]] = eb[k]
            fill[ea[k]] += 1
    # structures (CSR, grown column by column), elimination tree
    sptr = np.zeros(m + 1, np.int64)
    spool = np.empty(max(16, 4 * m), np.int64)
    parent = np.full(m, -1, np.int64)
    head = np.full(m, -1, np.int64)  # first child of each position
    nxt = np.full(m, -1, np.int64)  # next sibling
    mark = np.full(m, -1, np.int64)
    buf = np.empty(m, np.int64)
    for j in range(m):
        mark[j] = j
        n = _union(adj[aptr[j] : aptr[j + 1]], j, mark, buf, 0)  # its later neighbours
        c = head[j]
        while c >= 0:  # and its children's structures
            n = _union(spool[sptr[c] : sptr[c + 1]], j, mark, buf, n)
            c = nxt[c]
        s = np.sort(buf[:n])
        if sptr[j] + n > len(spool):
            grown = np.empty(2 * (sptr[j] + n), np.int64)
            grown[: sptr[j]] = spool[: sptr[j]]
            spool = grown
        spool[sptr[j] : sptr[j] + n] = s
        sptr[j + 1] = sptr[j] + n
        if n:
            p = s[0]
            parent[j] = p
            nxt[j] = head[p]
            head[p] = j
    # relaxed supernodes, from the roots down
    group = np.empty(m, np.int64)
    gsize = np.zeros(m, np.int64)
    ngroup = 0
    for j in range(m - 1, -1, -1):
        p = parent[j]
        if p >= 0 and (sptr[p + 1] - sptr[p]) + 1 - (sptr[j + 1] - sptr[j]) <= relax and gsize[group[p]] < cap:
            group[j] = group[p]
            gsize[group[p]] += 1
        else:
            group[j] = ngroup
            gsize[ngroup] = 1
            ngroup += 1
    # cliques leaves first (clique i = group ngroup - 1 - i), frontal ascending
    nfr = np.zeros(ngroup, np.int64)
    last = np.full(ngroup, -1, np.int64)
    for j in range(m):
        i = ngroup - 1 - group[j]
        nfr[i] += 1
        last[i] = j  # the clique's last frontal variable: its structure is the separator
    cnt = np.empty(ngroup, np.int64)
    for i in range(ngroup):
        j = last[i]
        cnt[i] = nfr[i] + sptr[j + 1] - sptr[j]
    start = np.zeros(ngroup + 1, np.int64)
    for i in range(ngroup):
        start[i + 1] = start[i] + cnt[i]
    lvp = np.empty(start[ngroup], np.int64)
    put = start[:ngroup].copy()
    for j in range(m):
        i = ngroup - 1 - group[j]
        lvp[put[i]] = j
        put[i] += 1
    for i in range(ngroup):
        j = last[i]
        lvp[put[i] : put[i] + sptr[j + 1] - sptr[j]] = spool[sptr[j] : sptr[j + 1]]
    return lvp, nfr, cnt, group[:m]


@_jit
def layout(order, lvp, nfr, cnt, group, top, dim, dof, clique_of, base):  # pragma: no cover - compiled
    """The new cliques' layout after :func:`symbolic` (clique ``i`` has id ``base + i``): each
    entry's variable number ``v_all`` (cliques side by side, frontal first) and its dof offset
    within its clique's matrix ``off_all``; per clique its entry segment ``seg``, its dof
    segment ``dseg`` (of ``dofs_all``, the entries' permanent dofs), its frontal size ``nfs``
    and parent id (-1: a root); and the offsets of its pieces in the pools of conditionals
    ``R^-1`` (nf x nf), ``S`` (nf x ns), ``d`` (nf) and cached factors ``A_c`` (ns x ns), ``b_c``
    (ns). Sets ``clique_of`` of the frontal variables."""
    ng = len(nfr)
    ne = len(lvp)
    seg = np.zeros(ng + 1, np.int64)
    for i in range(ng):
        seg[i + 1] = seg[i] + cnt[i]
    lv_all = np.empty(ne, np.int64)
    v_all = np.empty(ne, np.int64)
    off_all = np.empty(ne, np.int64)
    dseg = np.zeros(ng + 1, np.int64)
    nfs = np.zeros(ng, np.int64)
    parent = np.full(ng, -1, np.int64)
    ptr = np.zeros((5, ng + 1), np.int64)  # rptr, sptr, dptr, aptr, bptr
    for i in range(ng):
        off = 0
        for e in range(seg[i], seg[i + 1]):
            lv = order[lvp[e]]
            v = top[lv]
            lv_all[e] = lv
            v_all[e] = v
            off_all[e] = off
            if e - seg[i] < nfr[i]:
                clique_of[v] = base + i
                nfs[i] += dim[v]
            off += dim[v]
        dseg[i + 1] = dseg[i] + off
        if cnt[i] > nfr[i]:  # the first separator variable's clique: symbolic groups are
            # numbered from the root, new clique ids from the leaves
            parent[i] = base + ng - 1 - group[lvp[seg[i] + nfr[i]]]
        nf = nfs[i]
        ns = off - nf
        ptr[0, i + 1] = ptr[0, i] + nf * nf
        ptr[1, i + 1] = ptr[1, i] + nf * ns
        ptr[2, i + 1] = ptr[2, i] + nf
        ptr[3, i + 1] = ptr[3, i] + ns * ns
        ptr[4, i + 1] = ptr[4, i] + ns
    dofs_all = np.empty(dseg[ng], np.int64)
    k = 0
    for e in range(ne):
        v = v_all[e]
        for j in range(dim[v]):
            dofs_all[k] = dof[v] + j
            k += 1
    return seg, lv_all, v_all, off_all, dseg, nfs, parent, ptr, dofs_all


@_jit
def owners(L, pos, cid_of_pos):  # pragma: no cover - compiled
    """The clique owning each constraint (the one eliminating the first of its variables;
    ``L``: the constraints' top-local variables, one row each), the constraints grouped by
    owner (a stable order, ``srt``) and the owners with the start of their runs in it."""
    n, k = L.shape
    owner = np.empty(n, np.int64)
    for i in range(n):
        p = pos[L[i, 0]]
        for j in range(1, k):
            p = min(p, pos[L[i, j]])
        owner[i] = cid_of_pos[p]
    srt = np.argsort(owner, kind="mergesort")
    uniq = np.empty(n, np.int64)
    start = np.empty(n + 1, np.int64)
    nu = 0
    for r in range(n):
        o = owner[srt[r]]
        if nu == 0 or uniq[nu - 1] != o:
            uniq[nu] = o
            start[nu] = r
            nu += 1
    start[nu] = n
    return owner, srt, uniq[:nu], start[: nu + 1]


@_jit
def _cholesky_inverse(blas: np.ndarray, A: np.ndarray, ib: np.ndarray, ch: np.ndarray) -> bool:  # pragma: no cover
    """``A`` (row-major, its lower triangle read) becomes ``L^-1`` for its lower Cholesky
    factor ``L`` (upper triangle zero), by LAPACK ``dpotrf`` and ``dtrtri`` on its
    column-major view (whose upper triangle is the row-major lower); False when ``A`` is
    not positive definite."""
    n = A.shape[0]
    for r in range(n):
        A[r, r + 1 :] = 0.0
    ib[0] = n
    ch_, ib_ = ch.ctypes.data, ib.ctypes.data
    _fcall(blas[_POTRF], (ch_, ib_, A.ctypes.data, ib_, ib_ + 12))
    if ib[3] != 0:
        return False
    _fcall(blas[_TRTRI], (ch_, ch_ + 1, ib_, A.ctypes.data, ib_, ib_ + 12))
    return ib[3] == 0


@_jit
def _dofs_in(vs: np.ndarray, dloc: np.ndarray, lo2: np.ndarray, ix: np.ndarray) -> int:  # pragma: no cover
    """Write into ``ix`` the dofs of variables ``vs`` (top-local) within the clique whose
    variables start at dof offsets ``lo2``; returns how many."""
    n = 0
    for v in vs:
        for e in range(dloc[v]):
            ix[n] = lo2[v] + e
            n += 1
    return n


@_jit
def _add(
    W: np.ndarray, A: np.ndarray, nf: int, rhs: np.ndarray, ix: np.ndarray, M: np.ndarray, g: np.ndarray, sign: float
) -> None:  # pragma: no cover
    """``F[ix, ix] += M`` on the lower triangle of a frontal matrix ``F`` held as its first
    ``nf`` columns ``W`` and its separator block ``A = F[nf:, nf:]`` (only ``M``'s lower
    triangle is read: a cached factor's upper is not kept; ``ix`` need not ascend), and
    ``rhs[ix] += sign * g`` (the first ``len(g)`` of ``ix``)."""
    m = len(g)
    kf = 0  # entries in the frontal columns, when ix ascends (a new child's separator)
    for a in range(m):
        rhs[ix[a]] += sign * g[a]
        if ix[a] < nf:
            kf = a + 1
    ascending = True
    for a in range(1, m):
        if ix[a] < ix[a - 1]:
            ascending = False
            break
    if ascending:  # row by row, without the swap and the branch
        for a in range(m):
            i = ix[a]
            for b in range(min(a + 1, kf)):
                W[i, ix[b]] += M[a, b]
            if i >= nf:
                Ar = A[i - nf]
                for b in range(kf, a + 1):
                    Ar[ix[b] - nf] += M[a, b]
        return
    for a in range(m):
        for b in range(a + 1):
            i, j = ix[a], ix[b]
            if i < j:
                i, j = j, i
            if j < nf:
                W[i, j] += M[a, b]
            else:
                A[i - nf, j - nf] += M[a, b]


@_jit
def _blas_args(ib: np.ndarray, db: np.ndarray, ch: np.ndarray) -> None:  # pragma: no cover
    """The constant arguments the BLAS calls read by pointer (``ch``: 'U', 'N', 'T')."""
    ch[0], ch[1], ch[2] = ord("U"), ord("N"), ord("T")
    db[0], db[1], db[2] = -1.0, 1.0, 0.0


@_jit
def _schur(
    blas: np.ndarray,
    W: np.ndarray,
    nf: int,
    Li: np.ndarray,
    S: np.ndarray,
    A: np.ndarray,
    ib: np.ndarray,
    db: np.ndarray,
    ch: np.ndarray,
) -> None:  # pragma: no cover
    """From the first ``nf`` columns ``W`` of a frontal matrix ``F`` (lower triangle) and
    ``Li = L^-1`` of its frontal block: ``S = Li F[:nf, nf:]`` (``nf x ns``), and ``A``
    (``F[nf:, nf:]``, lower triangle) becomes the Schur complement ``A - S^T S``, in place
    (dgemm, dsyrk)."""
    ns = W.shape[0] - nf
    ib[0], ib[1], ib[2] = ns, nf, nf
    ch_, ib_, db_ = ch.ctypes.data, ib.ctypes.data, db.ctypes.data
    # column-major: S^T (ns x nf, ld ns) = B Li^T, B = W[nf:] (stored as B^T, ld nf)
    _fcall(blas[_GEMM], (ch_ + 2, ch_ + 1, ib_, ib_ + 4, ib_ + 4, db_ + 8,
                         W.ctypes.data + 8 * nf * nf, ib_ + 8, Li.ctypes.data, ib_ + 8,
                         db_ + 16, S.ctypes.data, ib_))  # fmt: skip
    # column-major upper of A (its row-major lower) -= (S^T)(S^T)^T
    _fcall(blas[_SYRK], (ch_, ch_ + 1, ib_, ib_ + 4, db_, S.ctypes.data, ib_,
                         db_ + 8, A.ctypes.data, ib_))  # fmt: skip


@_jit
def numeric(  # pragma: no cover - compiled
    seg, nfr, lv_all, off_all, dloc, sizes, nfs, c_own, c_nv, c_vars, c_G, c_b,
    parent_rel, o_par, o_ptr, o_sep, o_aptr, o_A, o_b,
    dofs_all, dseg, dx,
    rptr, Rpool, sptr, Spool, dptr, dpool, aptr, Apool, bptr, bpool, upool, blas,
):  # fmt: skip
    """Eliminate the new cliques, leaves first, and back-substitute them from the roots.

    Clique ``i``'s frontal matrix is ``sizes[i]`` square, frontal dofs first (``nfs[i]``
    of them); its variables (top-local indices) are ``lv_all[seg[i]:seg[i+1]]``, frontal
    first, at dof offsets ``off_all`` within the matrix; ``dloc`` is each top-local
    variable's tangent size. It gathers the constraints it eliminates (``c_own[q]`` is
    constraint ``q``'s clique; its ``c_nv[q]`` variables are the next run of ``c_vars``,
    its Gram block ``J^T J`` and gradient ``J^T r`` the next runs of ``c_G`` and ``c_b``)
    and its children's cached factors: new cliques (``parent_rel``, relative index, -1 =
    root) and orphans (``o_par``; separator ``o_sep[o_ptr[k]:o_ptr[k+1]]``, factor ``o_A``
    from ``o_aptr`` and ``o_b`` from the separator dof offsets).

    Writes each clique's ``Rinv`` (``R^-1``), ``S``, ``d``, cached factor ``(Ac, bc)`` and
    the separator offsets used by its back-substitution into the pools at the given
    offsets (of ``Ac``, the lower triangle only), and the new frontal offsets into ``dx``
    (by permanent dof ``dofs_all``, clique ``i``'s from ``dseg[i]``). Returns -1, or the
    first clique whose frontal block is not positive definite (then ``dx`` is untouched).
    ``blas``: :data:`BLAS`.
    """
    ng = len(nfr)
    ib = np.empty(4, np.int32)
    db = np.empty(3)
    ch = np.empty(3, np.uint8)
    _blas_args(ib, db, ch)
    nor = len(o_par)
    # children of each clique, new ones then orphans (linked lists)
    head = np.full(ng, -1, np.int64)
    nxt = np.full(ng + nor, -1, np.int64)
    for k in range(ng):
        p = parent_rel[k]
        if p >= 0:
            nxt[k] = head[p]
            head[p] = k
    for k in range(nor):
        p = o_par[k]
        nxt[ng + k] = head[p]
        head[p] = ng + k
    lo2 = np.zeros(len(dloc), np.int64)
    ix = np.empty(max(1, np.max(sizes)) if ng else 1, np.int64)
    # the constraints by clique (counting sort), and where each one's data starts
    nc = len(c_own)
    qv = np.zeros(nc + 1, np.int64)
    qg = np.zeros(nc + 1, np.int64)
    qb = np.zeros(nc + 1, np.int64)
    qcount = np.zeros(ng + 1, np.int64)
    for q in range(nc):
        qv[q + 1] = qv[q] + c_nv[q]
        t = np.sum(dloc[c_vars[qv[q] : qv[q + 1]]])
        qg[q + 1] = qg[q] + t * t
        qb[q + 1] = qb[q] + t
        qcount[c_own[q] + 1] += 1
    qstart = np.cumsum(qcount)
    qput = qstart[:ng].copy()
    qorder = np.empty(nc, np.int64)
    for q in range(nc):
        qorder[qput[c_own[q]]] = q
        qput[c_own[q]] += 1
    # one frontal matrix at a time: a workspace for the frontal columns of the largest (a
    # fresh buffer for all of them at once costs page faults that took longer than the
    # arithmetic on big tops)
    nmax = max(1, np.max(sizes)) if ng else 1
    work = np.empty(max(1, np.max(sizes * nfs)) if ng else 1)
    rwork = np.empty(nmax)
    o_bptr = np.zeros(nor + 1, np.int64)  # orphans' bc: one run of dofs per orphan
    for k in range(nor):
        o_bptr[k + 1] = o_bptr[k] + np.sum(dloc[o_sep[o_ptr[k] : o_ptr[k + 1]]])
    for i in range(ng):
        n = sizes[i]
        nf = nfs[i]
        ns = n - nf
        # the frontal matrix's lower triangle: its first nf columns in the workspace, its
        # separator block straight in the clique's cached-factor slot (the Schur complement
        # is computed there in place)
        W = work[: n * nf].reshape(n, nf)
        W[:, :] = 0.0
        A = Apool[aptr[i] : aptr[i + 1]].reshape(ns, ns)
        for r in range(ns):
            A[r, : r + 1] = 0.0
        rhs = rwork[:n]
        rhs[:] = 0.0
        for q in range(seg[i], seg[i + 1]):
            lo2[lv_all[q]] = off_all[q]
        for w in range(qstart[i], qstart[i + 1]):  # its constraints: + J^T J, - J^T r
            q = qorder[w]
            t = _dofs_in(c_vars[qv[q] : qv[q + 1]], dloc, lo2, ix)
            _add(W, A, nf, rhs, ix, c_G[qg[q] : qg[q + 1]].reshape(t, t), c_b[qb[q] : qb[q + 1]], -1.0)
        c = head[i]
        while c >= 0:  # its children's cached factors, on their separators
            if c < ng:
                nc = _dofs_in(lv_all[seg[c] + nfr[c] : seg[c + 1]], dloc, lo2, ix)
                _add(W, A, nf, rhs, ix, Apool[aptr[c] : aptr[c + 1]].reshape(nc, nc), bpool[bptr[c] : bptr[c + 1]], 1.0)
            else:
                k = c - ng
                nc = _dofs_in(o_sep[o_ptr[k] : o_ptr[k + 1]], dloc, lo2, ix)
                oA = o_A[o_aptr[k] : o_aptr[k + 1]].reshape(nc, nc)
                _add(W, A, nf, rhs, ix, oA, o_b[o_bptr[k] : o_bptr[k + 1]], 1.0)
            c = nxt[c]
        Aff = np.empty((nf, nf))
        for a in range(nf):
            for b in range(a + 1):
                Aff[a, b] = W[a, b]
            if Aff[a, a] == 0.0:  # a variable without any information stays put
                Aff[a, a] = 1.0
        Li = Aff
        if not _cholesky_inverse(blas, Li, ib, ch):
            return i
        Rinv = Rpool[rptr[i] : rptr[i + 1]].reshape(nf, nf)
        Rinv[:, :] = Li.T
        d = dpool[dptr[i] : dptr[i + 1]]
        for a in range(nf):
            t = 0.0
            for b in range(a + 1):
                t += Li[a, b] * rhs[b]
            d[a] = t
        if ns:
            S = Spool[sptr[i] : sptr[i + 1]].reshape(nf, ns)
            _schur(blas, W, nf, Li, S, A, ib, db, ch)
            bc = bpool[bptr[i] : bptr[i + 1]]
            for a in range(ns):
                bc[a] = rhs[nf + a]
            for b in range(nf):
                for a in range(ns):
                    bc[a] -= S[b, a] * d[b]
    # back-substitution, roots first (a parent's index is above its children's)
    for i in range(ng - 1, -1, -1):
        nf = nfs[i]
        ns = sizes[i] - nf
        f0 = dseg[i]
        Rinv = Rpool[rptr[i] : rptr[i + 1]].reshape(nf, nf)
        y = dpool[dptr[i] : dptr[i + 1]].copy()
        if ns:
            sep = upool[bptr[i] : bptr[i + 1]]
            for a in range(ns):
                sep[a] = dx[dofs_all[f0 + nf + a]]
            S = Spool[sptr[i] : sptr[i + 1]].reshape(nf, ns)
            y -= np.dot(S, np.ascontiguousarray(sep))
        new = np.dot(Rinv, y)
        for a in range(nf):
            dx[dofs_all[f0 + a]] = new[a]
    return -1


@_jit
def visit(dx, fdofs, sdofs, sep_used, Rinv, S, d, wf):  # pragma: no cover - compiled
    """Wildfire at one clique: when its separator's offsets ``dx[sdofs]`` drifted from
    ``sep_used`` (those it was last solved with) by more than ``wf`` (always, for ``wf``
    0), back-substitute it: ``dx[fdofs] = Rinv (d - S sep)``, ``sep_used = sep``. Returns
    whether it did (then its children need a look too)."""
    nf = len(fdofs)
    ns = len(sdofs)
    drift = 0.0
    for a in range(ns):
        drift = max(drift, abs(dx[sdofs[a]] - sep_used[a]))
    if wf > 0.0 and drift <= wf:
        return False
    for a in range(ns):
        sep_used[a] = dx[sdofs[a]]
    y = np.empty(nf)
    for r in range(nf):
        t = d[r]
        for a in range(ns):
            t -= S[r, a] * sep_used[a]
        y[r] = t
    for r in range(nf):
        t = 0.0
        for k in range(r, nf):  # Rinv = R^-1 is upper triangular
            t += Rinv[r, k] * y[k]
        dx[fdofs[r]] = t
    return True
