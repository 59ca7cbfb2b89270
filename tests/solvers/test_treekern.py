"""The Bayes tree's compiled kernels against independent oracles: the elimination tree and
clique structures against a dense Cholesky factor's nonzero pattern (numpy), the
minimum-degree order against the fill of other orders, and the numeric kernel's
conditionals and back-substitution against a dense solve."""

from __future__ import annotations

import numpy as np
import pytest

from jaxslam.solvers import _treekern


def _random_graph(rng: np.random.Generator, m: int, extra: int) -> list[np.ndarray]:
    """A connected random graph as hyperedges: a chain plus ``extra`` random 2- and 3-sets."""
    edges = [np.asarray([i, i + 1]) for i in range(m - 1)]
    for _ in range(extra):
        edges.append(rng.choice(m, size=int(rng.integers(2, 4)), replace=False))
    return edges


def _hyper(edges: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    ptr = np.zeros(len(edges) + 1, np.int64)
    np.cumsum([len(e) for e in edges], out=ptr[1:])
    return ptr, np.concatenate(edges).astype(np.int64)


def _pattern(m: int, edges: list[np.ndarray]) -> np.ndarray:
    A = np.eye(m, dtype=bool)
    for e in edges:
        A[np.ix_(e, e)] = True
    return A


def _fill_pattern(A: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """Nonzero pattern of the Cholesky factor of ``A[perm][:, perm]`` (lower), by symbolic
    elimination on a dense boolean matrix."""
    P = A[np.ix_(perm, perm)].copy()
    m = len(P)
    for j in range(m):
        nz = np.nonzero(P[j + 1 :, j])[0] + j + 1
        P[np.ix_(nz, nz)] = True
    return np.tril(P)


@pytest.mark.parametrize("seed", range(6))
def test_symbolic_matches_a_dense_factors_pattern(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = int(rng.integers(5, 60))
    edges = _random_graph(rng, m, int(rng.integers(0, m)))
    ptr, hv = _hyper(edges)
    perm = rng.permutation(m)
    pos = np.empty(m, np.int64)
    pos[perm] = np.arange(m)
    lvp, nfr, cnt, group = _treekern.symbolic(m, ptr, hv, pos, 2, 8)
    Lp = _fill_pattern(_pattern(m, edges), perm)
    struct = [set((np.nonzero(Lp[j + 1 :, j])[0] + j + 1).tolist()) for j in range(m)]
    seg = np.concatenate([[0], np.cumsum(cnt)])
    seen = []
    for i in range(len(nfr)):
        fr = lvp[seg[i] : seg[i] + nfr[i]].tolist()
        sep = lvp[seg[i] + nfr[i] : seg[i + 1]].tolist()
        seen += fr
        assert fr == sorted(fr) and sep == sorted(sep)
        assert all(group[j] == group[fr[0]] for j in fr)
        # the clique's rows: every frontal variable's structure is in the clique, and the
        # separator is exactly the last frontal variable's structure
        assert set(sep) == struct[fr[-1]]
        for j in fr:
            assert struct[j] <= set(fr) | set(sep)
        # the frontal variables are a subtree of the elimination tree rooted at the last
        for j in fr[:-1]:
            assert min(struct[j]) in fr
        assert len(fr) <= 8
    assert sorted(seen) == list(range(m))
    # leaves first: a clique's parent (the clique of its first separator variable) comes later
    for i in range(len(nfr)):
        if cnt[i] > nfr[i]:
            parent = len(nfr) - 1 - group[lvp[seg[i] + nfr[i]]]
            assert parent > i


def _fill(A: np.ndarray, perm: np.ndarray) -> int:
    return int(_fill_pattern(A, perm).sum())


@pytest.mark.parametrize("seed", range(6))
def test_min_degree_orders_with_little_fill_and_keeps_last_at_the_end(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    m = int(rng.integers(8, 120))
    edges = _random_graph(rng, m, int(rng.integers(0, 2 * m)))
    ptr, hv = _hyper(edges)
    last = np.zeros(m, bool)
    last[rng.choice(m, size=int(rng.integers(0, 4)), replace=False)] = True
    perm = _treekern.min_degree(m, ptr, hv, last)
    assert sorted(perm.tolist()) == list(range(m))
    k = int(last.sum())
    assert np.all(last[perm[m - k :]]) and not np.any(last[perm[: m - k]])
    A = _pattern(m, edges)
    natural = np.concatenate([np.nonzero(~last)[0], np.nonzero(last)[0]])
    assert _fill(A, perm) <= _fill(A, natural)
    for _ in range(5):  # and no worse than random orders with the same constraint
        r = rng.permutation(m)
        r = np.concatenate([r[~last[r]], r[last[r]]])
        assert _fill(A, perm) <= _fill(A, r)


def test_min_degree_eliminates_a_chain_without_fill_and_a_stars_centre_last() -> None:
    m = 12
    chain = [np.asarray([i, i + 1]) for i in range(m - 1)]
    ptr, hv = _hyper(chain)
    perm = _treekern.min_degree(m, ptr, hv, np.zeros(m, bool))
    assert _fill(_pattern(m, chain), perm) == m + (m - 1)  # the diagonal and the chain
    star = [np.asarray([0, i]) for i in range(1, m)]
    ptr, hv = _hyper(star)
    perm = _treekern.min_degree(m, ptr, hv, np.zeros(m, bool))
    assert perm[-2:].tolist().count(0) == 1  # the centre goes with the last leaf


def test_numeric_solves_a_dense_system_and_reports_an_indefinite_block() -> None:
    rng = np.random.default_rng(7)
    m, d = 9, 2  # variables of 2 dofs
    edges = _random_graph(rng, m, 6)
    ptr, hv = _hyper(edges)
    pos = np.arange(m)
    lvp, nfr, cnt, group = _treekern.symbolic(m, ptr, hv, pos, 2, 3)
    ng = len(nfr)
    seg = np.concatenate([[0], np.cumsum(cnt)]).astype(np.int64)
    dloc = np.full(m, d, np.int64)
    sizes = cnt * d
    nfs = nfr * d
    off_all = (np.arange(len(lvp)) - np.repeat(seg[:-1], cnt)) * d
    dofs_all = (lvp[:, None] * d + np.arange(d)).ravel()
    dseg = seg * d
    # one constraint per hyperedge, owned by the clique of its first variable
    H, g = np.zeros((m * d, m * d)), np.zeros(m * d)
    c_own, c_G, c_b = [], [], []
    for e in edges:
        J = rng.normal(size=(len(e) * d + 1, len(e) * d))
        r = rng.normal(size=len(e) * d + 1)
        G, b = J.T @ J, J.T @ r
        ix = (e[:, None] * d + np.arange(d)).ravel()
        H[np.ix_(ix, ix)] += G
        g[ix] += b
        c_own.append(ng - 1 - group[min(e)])
        c_G.append(G.ravel())
        c_b.append(b)
    H += 1e-3 * np.eye(m * d)  # the chain's ends need not be determined: a small prior
    for v in range(m):
        ix = v * d + np.arange(d)
        c_own.append(ng - 1 - group[v])
        c_G.append((1e-3 * np.eye(d)).ravel())
        c_b.append(np.zeros(d))
    c_nv = np.asarray([len(e) for e in edges] + [1] * m, np.int64)
    c_vars = np.concatenate([*edges, np.arange(m)]).astype(np.int64)
    parent_rel = np.asarray(
        [ng - 1 - group[lvp[seg[i] + nfr[i]]] if cnt[i] > nfr[i] else -1 for i in range(ng)], np.int64
    )
    nss = sizes - nfs

    def offs(x: np.ndarray) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(x)]).astype(np.int64)

    ptrs = [offs(x) for x in (nfs * nfs, nfs * nss, nfs, nss * nss, nss)]
    pools = [np.empty(int(p[-1])) for p in (*ptrs, ptrs[-1])]
    e0, f0 = np.zeros(0, np.int64), np.zeros(0)

    def run(cG: np.ndarray, dx: np.ndarray) -> int:
        return _treekern.numeric(
            seg, nfr, lvp, off_all, dloc, sizes.astype(np.int64), nfs.astype(np.int64),
            np.asarray(c_own, np.int64), c_nv, c_vars, cG, np.concatenate(c_b),
            parent_rel, e0, np.zeros(1, np.int64), e0, np.zeros(1, np.int64), f0, f0,
            dofs_all, dseg, dx,
            ptrs[0], pools[0], ptrs[1], pools[1], ptrs[2], pools[2], ptrs[3], pools[3], ptrs[4], pools[4], pools[5],
            _treekern.BLAS,
        )  # fmt: skip

    dx = np.zeros(m * d)
    assert run(np.concatenate(c_G), dx) == -1
    np.testing.assert_allclose(dx, np.linalg.solve(H, -g), rtol=1e-9, atol=1e-9)
    # a negative definite constraint makes some frontal block indefinite; dx is untouched
    bad = [G.copy() for G in c_G]
    bad[0] = -10.0 * np.abs(bad[0])
    dx2 = np.full(m * d, 5.0)
    assert run(np.concatenate(bad), dx2) >= 0
    assert np.all(dx2 == 5.0)


def test_visit_back_substitutes_one_clique_only_when_its_separator_drifted() -> None:
    """The wildfire's step against numpy: ``dx[F] = R^-1 (d - S dx[S])`` when the separator
    moved by more than the threshold since ``sep_used`` (always with threshold 0), nothing
    otherwise."""
    rng = np.random.default_rng(3)
    nf, ns = 4, 5
    Rinv = np.triu(rng.normal(size=(nf, nf))) + 3 * np.eye(nf)
    S, d = rng.normal(size=(nf, ns)), rng.normal(size=nf)
    fdofs, sdofs = np.asarray([7, 2, 5, 0]), np.asarray([1, 3, 4, 6, 8])
    dx0 = rng.normal(size=9)
    used0 = dx0[sdofs] + 1e-4  # solved with a separator 1e-4 away from the current one

    def run(wf: float) -> tuple[bool, np.ndarray, np.ndarray]:
        dx, used = dx0.copy(), used0.copy()
        done = _treekern.visit(dx, fdofs, sdofs, used, Rinv, S, d, wf)
        return done, dx, used

    done, dx, used = run(1e-3)  # drift 1e-4 below the threshold: left alone
    assert not done and np.array_equal(dx, dx0) and np.array_equal(used, used0)
    want = dx0.copy()
    want[fdofs] = Rinv @ (d - S @ dx0[sdofs])
    for wf in (1e-5, 0.0):  # drifted past the threshold; threshold 0: always
        done, dx, used = run(wf)
        assert done
        np.testing.assert_allclose(dx, want, rtol=1e-13, atol=1e-13)
        assert np.array_equal(used, dx0[sdofs])
