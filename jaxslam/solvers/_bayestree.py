"""A Bayes tree of the incremental solver's linear system: iSAM2's partial re-elimination.

The linear system ``H delta = -b`` (``H = sum J^T J``, ``b = sum J^T r`` over every
constraint, cached by the solver at its linearisation point) is held factorised as a tree
of cliques. A clique eliminates its *frontal* variables given its *separator* (variables
eliminated later, all in its ancestors)::

    R delta_F + S delta_S = d        (the conditional; R upper triangular)

and caches the information its whole subtree leaves on the separator (the Schur complement
``(A_c, b_c)``, the "cached factor" of the iSAM2 paper). A constraint belongs to the clique
that eliminates the first of its variables.

:meth:`BayesTree.update` takes the variables an update touched (new constraints,
relinearised constraints, removed constraints, new variables):

1. the cliques holding them and all their ancestors up to the root are removed (the
   "top"); their children that stay are *orphans*, whose cached factors summarise them;
2. the top's variables are ordered again on the top's own graph: exact minimum degree for
   tops of up to 256 variables, AMD (CHOLMOD, when installed) above, with the new
   variables and those of new constraints last, so the next update's new odometry edge
   touches the root only (GTSAM's constrained ordering);
3. symbolic elimination (the elimination tree; a variable joins its parent's clique when
   that adds at most ``relax`` zero blocks to its row and the clique has fewer than
   ``max_frontal`` frontal variables: relaxed supernodes, fewer and larger dense blocks)
   and numeric elimination, clique by clique from the leaves: each clique gathers the
   cached Gram blocks of the constraints it eliminates and its children's cached factors
   (the orphans included) and runs a small dense Cholesky. The ordering, both eliminations
   and the back-substitution of the new cliques are compiled (:mod:`._treekern`, numba):
   a top is a few dozen variables in about ten cliques, where numpy calls' overhead was
   most of the time;
4. back-substitution of the new cliques from the root down. The orphans' subtrees are
   back-substituted lazily (GTSAM does the same): :meth:`solve_pending` when every offset
   is needed (the solver's estimate, its relinearisation check), descending only where a
   clique's offsets moved by more than ``wildfire`` (iSAM2's wildfire threshold; 0 = all,
   exact); :meth:`solve_path` when one variable is asked for: only the cliques on its path
   from the nearest pending ancestor.

With ``wildfire=0`` the offsets are the exact solution of the whole linear system after
every update (the tests check this against a dense solve, and the running estimate against
gtsam.ISAM2's). The cost of an update is proportional to the size of the top, not to the
size of the graph.

Written here, not taken from a library: GTSAM's Bayes tree is C++ with its own factor
graph types, and no Python package offers partial re-elimination of a sparse Cholesky.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
import scipy.sparse as sp

from . import _treekern
from ._blocks import one_blas_thread

try:  # pragma: no cover - import guard
    from sksparse.cholmod import analyze as _cholmod_analyze

    _HAVE_CHOLMOD = True
except ImportError:  # pragma: no cover
    _HAVE_CHOLMOD = False

_EMPTY1, _EMPTY2 = np.zeros(0), np.zeros((0, 0))
_SCRATCH_MIN = 1 << 21  # doubles (16 MB) of new conditionals above which a reused buffer holds them
_BUFFERS = 4  # reused buffers kept at most
_BLAS_ONE_THREAD_ABOVE = 64  # frontal matrices larger than this: BLAS held to one thread
_MD_MAX = 256  # tops up to this size are ordered by the compiled minimum degree; larger by AMD


class NotPositiveDefinite(Exception):
    """A clique's frontal block is not positive definite (an under-constrained variable)."""


class _Clique:
    __slots__ = (
        "Ac",
        "Rinv",
        "S",
        "bc",
        "children",
        "d",
        "fac",
        "fdofs",
        "frontal",
        "parent",
        "sdofs",
        "sep",
        "sep_used",
    )

    def __init__(self, frontal: np.ndarray, sep: np.ndarray, fdofs: np.ndarray, sdofs: np.ndarray, parent: int):
        self.frontal = frontal  # variable numbers, in elimination order
        self.sep = sep  # variable numbers (all eliminated later, in ancestors)
        self.fdofs = fdofs  # permanent dofs of the frontal / separator variables
        self.sdofs = sdofs
        self.parent = parent
        self.children: list[int] = []
        self.fac: list[tuple[int, np.ndarray]] = []  # (group, constraint indices) it eliminates
        # the conditional R delta_F + S delta_S = d (kept as R^-1), the cached factor
        # (Ac, bc) on the separator and the separator's offsets when it was last solved:
        # set by the numeric phase
        self.Rinv = self.S = self.Ac = _EMPTY2
        self.d = self.bc = self.sep_used = _EMPTY1


def _clique_doubles(c: _Clique) -> int:
    """Doubles a clique's conditional and cached factor hold."""
    return c.Rinv.size + c.S.size + c.d.size + c.Ac.size + 2 * c.bc.size


def _offsets(sizes: np.ndarray) -> np.ndarray:
    """Start offsets of runs of ``sizes``, with the total at the end."""
    out = np.zeros(len(sizes) + 1, np.int64)
    np.cumsum(sizes, out=out[1:])
    return out


class BayesTree:
    """The factorised linear system of an :class:`~jaxslam.solvers.IncrementalSolver`.

    Variables are numbered ``0, 1, ...`` in the order they are added, each with its tangent
    dimension and its first permanent dof (the index of its offset in :attr:`dx`). The
    constraints are read from the solver's groups: ``g.vars`` (variable numbers per
    constraint), ``g.G`` (``J^T J``), ``g.b`` (``J^T r``), ``g.alive``, ``g.tds``.
    """

    def __init__(self, wildfire: float = 0.0):
        self.wildfire = float(wildfire)
        self.nvar = 0
        self.dim = np.zeros(16, np.int64)
        self.dof = np.zeros(16, np.int64)
        self.clique_of = np.full(16, -1, np.int64)
        self._loc = np.zeros(16, np.int64)  # scratch: a top variable's local index
        self.dx = np.zeros(64)  # offsets (delta) by permanent dof
        self.cliques: dict[int, _Clique] = {}
        self.roots: set[int] = set()
        self.pending: set[int] = set()  # cliques whose offsets may be stale (solve_pending)
        self._next = 0
        # relaxed supernodes: a variable joins its parent's clique when that adds at most
        # ``relax`` zero blocks to its row, up to ``max_frontal`` frontal variables (2 and 8
        # were fastest on parking-garage: 291 cliques instead of 1111, total time -20 %)
        self.relax = 2
        self.max_frontal = 8
        self.last_reeliminated = 0  # variables re-eliminated by the last update
        # see _buffer(): reused buffers holding large tops' conditionals, each with the ids of
        # the cliques whose pieces are views into it
        self._bufs: list[tuple[np.ndarray, list[int]]] = []

    # --- variables ------------------------------------------------------------------------
    def add_vars(self, dofs: np.ndarray, dim: int) -> np.ndarray:
        """Number ``len(dofs)`` new variables of tangent size ``dim`` whose offsets start at
        the permanent ``dofs``; returns their numbers."""
        k = len(dofs)
        need = self.nvar + k
        if need > len(self.dim):
            cap = max(need, 2 * len(self.dim))
            for name, fill in (("dim", 0), ("dof", 0), ("clique_of", -1), ("_loc", 0)):
                old = getattr(self, name)
                arr = np.full(cap, fill, np.int64)
                arr[: len(old)] = old
                setattr(self, name, arr)
        nums = np.arange(self.nvar, need)
        if k == 0:
            return nums
        self.dim[self.nvar : need] = dim
        self.dof[self.nvar : need] = dofs
        top = int(dofs.max()) + dim
        if top > len(self.dx):
            dx = np.zeros(max(top, 2 * len(self.dx)))
            dx[: len(self.dx)] = self.dx
            self.dx = dx
        self.nvar = need
        return nums

    def clear(self) -> None:
        """Forget the factorisation (every variable is re-eliminated at the next update)."""
        self.cliques.clear()
        self._bufs = [(buf, []) for buf, _ in self._bufs]
        self.roots.clear()
        self.pending.clear()
        self.clique_of[: self.nvar] = -1

    # --- update ---------------------------------------------------------------------------
    def update(self, marked: np.ndarray, new_fac: dict[int, np.ndarray], groups: list[Any]) -> np.ndarray:
        """Re-eliminate the top of the tree above the variables ``marked`` (every variable of
        a new, relinearised or removed constraint, and new variables), adding the constraints
        ``new_fac`` (group -> indices) that no clique holds yet; back-substitute. Returns the
        variable numbers whose offsets were recomputed."""
        cl = self.cliques
        marked = np.unique(np.asarray(marked, np.int64))
        # 1. the top: cliques of marked variables and their ancestors
        removed: list[int] = []
        seen: set[int] = set()
        for c in self.clique_of[marked].tolist():
            while c >= 0 and c not in seen:
                seen.add(c)
                removed.append(c)
                c = cl[c].parent
        parts = [cl[c].frontal for c in removed]
        parts.append(marked[self.clique_of[marked] < 0])
        top = np.concatenate(parts)
        m = len(top)
        self.last_reeliminated = m
        if m == 0:
            return top
        orphans = [ch for c in removed for ch in cl[c].children if ch not in seen]
        fac: dict[int, list[np.ndarray]] = {}
        for c in removed:
            for gi, idx in cl[c].fac:
                fac.setdefault(gi, []).append(idx)
            del cl[c]
            self.roots.discard(c)
            self.pending.discard(c)
        for gi, idx in new_fac.items():
            fac.setdefault(gi, []).append(np.asarray(idx, np.int64))
        facs: list[tuple[int, np.ndarray]] = []
        for gi, lst in fac.items():
            g = groups[gi]
            idx = np.concatenate(lst) if len(lst) > 1 else lst[0]
            idx = idx[g.alive[idx]]
            if idx.size:
                facs.append((gi, idx))
        loc = self._loc
        loc[top] = np.arange(m)
        # 2. ordering: AMD on the top's graph, new variables and new constraints' variables last
        last = np.zeros(m, bool)
        last[loc[parts[-1]]] = True  # new variables
        for gi, idx in new_fac.items():
            if len(idx):
                last[loc[groups[gi].vars[np.asarray(idx, np.int64)]].ravel()] = True
        con_loc = [(gi, idx, loc[groups[gi].vars[idx]]) for gi, idx in facs]
        orph_loc = [loc[cl[o].sep] for o in orphans]
        # the top's graph as hyperedges (each constraint's variables, each orphan's separator)
        h_vars = np.concatenate([np.zeros(0, np.int64), *(L.ravel() for _, _, L in con_loc), *orph_loc])
        h_len = [np.full(len(L), L.shape[1], np.int64) for _, _, L in con_loc]
        h_ptr = _offsets(
            np.concatenate([np.zeros(0, np.int64), *h_len, np.asarray([len(L) for L in orph_loc], np.int64)])
        )
        order = self._order(m, top, h_ptr, h_vars, last)
        pos = np.empty(m, np.int64)
        pos[order] = np.arange(m)
        # 3a. symbolic (compiled): the elimination tree and its relaxed supernodes
        lvp, nfr, cnt, group = _treekern.symbolic(m, h_ptr, h_vars, pos, self.relax, self.max_frontal)
        # new cliques, leaves first: clique i has id base + i, so a parent's id is above its
        # children's (here and across updates: an orphan's new parent is newer) and sorting
        # by id orders cliques from the roots down
        ngroup = len(nfr)
        base = self._next
        self._next += ngroup
        cid_of_pos = base + ngroup - 1 - group
        # every clique's variables (frontal, then separator by position) side by side, their
        # dofs, the parents and the pools' offsets (compiled)
        seg, lv_all, v_all, off_all, dseg, nfs, parent_id, ptr, dofs_all = _treekern.layout(
            order, lvp, nfr, cnt, group, top, self.dim, self.dof, self.clique_of, base
        )
        sizes = np.diff(dseg)
        new: list[_Clique] = []
        ss, nl, ds, nfl, par = seg.tolist(), nfr.tolist(), dseg.tolist(), nfs.tolist(), parent_id.tolist()
        for i in range(ngroup):
            a0, a1 = ss[i], ss[i] + nl[i]
            f0, f1 = ds[i], ds[i] + nfl[i]
            c = _Clique(v_all[a0:a1], v_all[a1 : ss[i + 1]], dofs_all[f0:f1], dofs_all[f1 : ds[i + 1]], par[i])
            cl[base + i] = c
            new.append(c)
            if par[i] < 0:
                self.roots.add(base + i)
        for i, p in enumerate(par):
            if p >= 0:
                cl[p].children.append(base + i)
        o_par = np.zeros(len(orphans), np.int64)
        for k, (o, L) in enumerate(zip(orphans, orph_loc)):
            p = int(cid_of_pos[int(pos[L].min())])
            cl[o].parent = p
            cl[p].children.append(o)
            o_par[k] = p - base
        # 3b. numeric (compiled). Each constraint goes to the clique that eliminates the first
        # of its variables: its Gram block and gradient into that clique's frontal matrix.
        own_l, nv_l, var_l, G_l, b_l = [], [], [], [], []
        for gi, idx, L in con_loc:
            g = groups[gi]
            owner, srt, u, start = _treekern.owners(L, pos, cid_of_pos)
            idx_s = idx[srt]
            st = start.tolist()
            for k, cid in enumerate(u.tolist()):
                cl[cid].fac.append((gi, idx_s[st[k] : st[k + 1]]))
            own_l.append(owner - base)
            nv_l.append(np.full(len(idx), L.shape[1], np.int64))
            var_l.append(L.ravel())
            G_l.append(g.G[idx].ravel())
            b_l.append(g.b[idx].ravel())
        c_own, c_nv, c_vars = (np.concatenate(x) if x else np.zeros(0, np.int64) for x in (own_l, nv_l, var_l))
        c_G, c_b = (np.concatenate(x) if x else np.zeros(0) for x in (G_l, b_l))
        # each clique adds its children's cached factors (new cliques' and the orphans'),
        # runs a small dense Cholesky, and the new cliques are back-substituted from the
        # root down (compiled); the orphans' subtrees wait until their offsets are asked
        # for (solve_pending, solve_path)
        nss = sizes - nfs
        rptr, sptr, dptr, aptr, bptr = ptr
        need = [int(p[-1]) for p in (rptr, sptr, dptr, aptr, bptr, bptr)]
        # A large top (hundreds of cliques) writes tens of MB of conditionals and cached
        # factors: fresh memory that large comes from mmap, and its page faults took 3-4x
        # the arithmetic on this machine. Those go into a reused buffer (_buffer) and the
        # cliques keep views into it; small tops get fresh pools.
        scratch = sum(need) > _SCRATCH_MIN
        if scratch:
            buf = self._buffer(sum(need))
            cut = _offsets(np.asarray(need, np.int64)).tolist()
            pools = [buf[cut[k] : cut[k + 1]] for k in range(6)]
            self._bufs[-1][1].extend(range(base, base + ngroup))
        else:
            pools = [np.empty(n) for n in need]
        oc = [cl[o] for o in orphans]
        o_ptr = _offsets(np.asarray([len(L) for L in orph_loc], np.int64))
        o_aptr = _offsets(np.asarray([c.Ac.size for c in oc], np.int64))
        o_sep, o_A, o_b = (
            (np.concatenate(orph_loc), np.concatenate([c.Ac.ravel() for c in oc]), np.concatenate([c.bc for c in oc]))
            if oc
            else (np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
        )
        parent_rel = np.where(parent_id >= 0, parent_id - base, -1)
        # BLAS on one thread (its threads would contend with JAX's) where a product is large
        # enough for BLAS to start them at all; setting the count costs more than a small top
        with one_blas_thread() if int(sizes.max()) > _BLAS_ONE_THREAD_ABOVE else contextlib.nullcontext():
            bad = _treekern.numeric(
                seg, nfr, lv_all, off_all, self.dim[top], sizes, nfs, c_own, c_nv, c_vars, c_G, c_b,
                parent_rel, o_par, o_ptr, o_sep, o_aptr, o_A, o_b, dofs_all, dseg, self.dx,
                rptr, pools[0], sptr, pools[1], dptr, pools[2], aptr, pools[3], bptr, pools[4], pools[5],
                _treekern.BLAS,
            )  # fmt: skip
        if bad >= 0:
            bad_vars = new[bad].frontal.tolist()
            raise NotPositiveDefinite(f"frontal block of variables {bad_vars} is not positive definite")
        Rp, Sp, dp, Ap, bp, up = pools
        rl, sl, dl, al, bl = rptr.tolist(), sptr.tolist(), dptr.tolist(), aptr.tolist(), bptr.tolist()
        nsl = nss.tolist()
        for i, c in enumerate(new):
            nf, ns = nfl[i], nsl[i]
            c.Rinv = Rp[rl[i] : rl[i + 1]].reshape(nf, nf)
            c.S = Sp[sl[i] : sl[i + 1]].reshape(nf, ns)
            c.d = dp[dl[i] : dl[i + 1]]
            c.Ac = Ap[al[i] : al[i + 1]].reshape(ns, ns)
            c.bc = bp[bl[i] : bl[i + 1]]
            c.sep_used = up[bl[i] : bl[i + 1]]
        self.pending.update(orphans)
        return top

    def _buffer(self, n: int) -> np.ndarray:
        """A buffer of at least ``n`` doubles for a large top's conditionals, moved to the end
        of ``_bufs`` (the caller records its new cliques there). Buffers are reused once no
        clique lives in them; one whose surviving cliques fill under a quarter of it has them
        copied out (their pieces are small) and is reused too; at most ``_BUFFERS`` are kept.
        Reused memory is paged in already: a fresh buffer costs its page faults, a copy out
        of every clique (what this replaced) cost a memory pass over all of them."""
        cl = self.cliques
        live: list[list[int]] = []
        for buf, ids in self._bufs:
            alive = [cid for cid in ids if cid in cl]  # ids are never reused
            used = sum(_clique_doubles(cl[cid]) for cid in alive)
            if alive and 4 * used < len(buf):
                self._copy_out(alive)
                alive = []
            live.append(alive)
        self._bufs = [(buf, ids) for (buf, _), ids in zip(self._bufs, live)]
        free = [k for k, (buf, ids) in enumerate(self._bufs) if not ids and len(buf) >= n]
        if free:
            k = min(free, key=lambda j: len(self._bufs[j][0]))
            chosen = self._bufs.pop(k)
        else:
            # a free buffer too small is dropped (its memory returned) before a larger one is made
            self._bufs = [(b, ids) for b, ids in self._bufs if ids]
            chosen = (np.empty(n + n // 4), [])  # a quarter to spare
        while len(self._bufs) >= _BUFFERS:  # the cap: empty the least-used of the others
            k = min(range(len(self._bufs)), key=lambda j: sum(_clique_doubles(cl[c]) for c in self._bufs[j][1]))
            self._copy_out(self._bufs[k][1])
            self._bufs.pop(k)
        self._bufs.append(chosen)
        return chosen[0]

    def _copy_out(self, cids: list[int]) -> None:
        """Give cliques ``cids`` their own copies of their pieces (out of a shared buffer)."""
        for cid in cids:
            c = self.cliques[cid]
            c.Rinv, c.S, c.Ac = c.Rinv.copy(), c.S.copy(), c.Ac.copy()
            c.d, c.bc, c.sep_used = c.d.copy(), c.bc.copy(), c.sep_used.copy()

    def _visit(self, c: _Clique) -> bool:
        """Wildfire at one clique (compiled: :func:`._treekern.visit`): recompute it when its
        separator's offsets drifted by more than the threshold since it was last solved (every
        time with threshold 0). Returns whether it was; then its children need a look too: a
        change of its separator, the parent keys GTSAM checks, may have moved theirs."""
        return bool(_treekern.visit(self.dx, c.fdofs, c.sdofs, c.sep_used, c.Rinv, c.S, c.d, self.wildfire))

    def solve_pending(self) -> np.ndarray:
        """Back-substitute below the cliques left pending by updates (the orphans of the
        re-eliminated tops, the children of cliques that moved), from the roots down: a
        clique is recomputed when its separator drifted by more than the wildfire threshold
        since it was last solved, and the children of a recomputed clique are looked at (all
        the way down with ``wildfire=0``). Returns the variables recomputed."""
        if not self.pending:
            return np.zeros(0, np.int64)
        cl = self.cliques
        out: list[np.ndarray] = []
        done: set[int] = set()
        for start in sorted(self.pending, reverse=True):  # ids: parents above children
            if start in done:
                continue
            stack = [start]
            while stack:
                cid = stack.pop()
                if cid in done:
                    continue
                done.add(cid)
                c = cl[cid]
                if self._visit(c):
                    out.append(c.frontal)
                    stack.extend(c.children)
        self.pending.clear()
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    def solve_path(self, v: int) -> np.ndarray:
        """Bring variable ``v``'s offset up to date through its path only: from the pending
        clique nearest its root down to its own clique (nothing when none on the path is
        pending), each recomputed as in :meth:`solve_pending`; the other children of a
        clique that moved become pending. Returns the variables recomputed."""
        cl = self.cliques
        path: list[int] = []
        top = -1  # the pending clique nearest the root on the path: above it all is current
        cur = int(self.clique_of[v])
        while cur >= 0:
            path.append(cur)
            if cur in self.pending:
                top = len(path) - 1
            cur = cl[cur].parent
        if top < 0:
            return np.zeros(0, np.int64)
        out = []
        for k in range(top, -1, -1):
            cid = path[k]
            c = cl[cid]
            solved = self._visit(c)
            self.pending.discard(cid)
            if solved:
                out.append(c.frontal)
                nxt = path[k - 1] if k else -1
                self.pending.update(ch for ch in c.children if ch != nxt)
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    def _order(self, m: int, top: np.ndarray, h_ptr: np.ndarray, h_vars: np.ndarray, last: np.ndarray) -> np.ndarray:
        """Elimination order of the top's variables (local indices), the ``last`` ones at the
        end: exact minimum degree (compiled) for tops up to ``_MD_MAX`` variables, AMD
        (CHOLMOD) above when installed, else variable-number order."""
        if m <= _MD_MAX:
            return _treekern.min_degree(m, h_ptr, h_vars, last)
        if _HAVE_CHOLMOD:
            nh = np.diff(h_ptr)
            k = np.repeat(np.arange(len(nh)), nh)  # hyperedge of each entry
            A = sp.csc_matrix((np.ones(len(h_vars)), (k, h_vars)), shape=(len(nh), m))
            G = (A.T @ A).tocsc()  # the top's graph: variables sharing a hyperedge
            G.data[:] = 0.0
            G.setdiag(1.0)
            perm = np.asarray(_cholmod_analyze(G, mode="simplicial", ordering_method="amd").P(), np.int64)
        else:
            perm = np.argsort(top, kind="stable")
        return np.concatenate([perm[~last[perm]], perm[last[perm]]])
