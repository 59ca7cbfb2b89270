"""Brute-force descriptor matching in JAX: nearest neighbour, Lowe's ratio test, cross-check
and SURF's Laplacian-sign gate (SPEC §3.2).

Descriptors are either float vectors (SURF, SIFT: L2 distance) or packed binary strings
(ORB: ``uint8`` rows, Hamming distance). The core, :func:`match_arrays`, is a pure function of
fixed-shape arrays (``jit``-able, with optional validity masks for padded inputs) and returns
one candidate per query row plus a mask; :func:`match_descriptors` is the NumPy convenience
that returns the accepted ``(M, 2)`` index pairs. The distances equal ``cv2.BFMatcher``'s
(``NORM_L2`` / ``NORM_HAMMING``), which is the oracle in the tests.

Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 2004 (ratio test);
Bay et al., "SURF", CVIU 2008, sec. 4.3 (sign of the Laplacian).
"""

from __future__ import annotations

import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

Metric = Literal["l2", "hamming"]

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.int32)


def default_metric(descriptors: np.ndarray | Array) -> Metric:
    """``hamming`` for ``uint8`` descriptors (ORB, BRIEF), else ``l2``."""
    return "hamming" if np.dtype(descriptors.dtype) == np.uint8 else "l2"


def distance_matrix(d1: Array, d2: Array, metric: Metric = "l2") -> Array:
    """All pairwise distances ``(N1, N2)`` between rows of ``d1`` and ``d2``.

    ``l2``: Euclidean, through ``|a|^2 + |b|^2 - 2 a.b`` in float64 (clamped at 0).
    ``hamming``: number of differing bits of packed ``uint8`` rows, computed as
    ``|a| + |b| - 2 a.b`` on the unpacked bits (exact integers in float64).
    """
    if metric == "hamming":
        b1 = jnp.unpackbits(jnp.asarray(d1, jnp.uint8), axis=-1).astype(jnp.float64)
        b2 = jnp.unpackbits(jnp.asarray(d2, jnp.uint8), axis=-1).astype(jnp.float64)
        return b1.sum(-1)[:, None] + b2.sum(-1)[None, :] - 2.0 * (b1 @ b2.T)
    if metric != "l2":
        raise ValueError(f"metric must be 'l2' or 'hamming', got {metric!r}")
    a = jnp.asarray(d1, jnp.float64)
    b = jnp.asarray(d2, jnp.float64)
    sq = jnp.sum(a * a, -1)[:, None] + jnp.sum(b * b, -1)[None, :] - 2.0 * (a @ b.T)
    return jnp.sqrt(jnp.maximum(sq, 0.0))


@functools.partial(jax.jit, static_argnames=("metric", "cross_check"))
def match_arrays(
    d1: Array,
    d2: Array,
    *,
    metric: Metric = "l2",
    ratio: Array | float = 0.8,
    cross_check: bool = True,
    max_distance: Array | float = jnp.inf,
    sign1: Array | None = None,
    sign2: Array | None = None,
    valid1: Array | None = None,
    valid2: Array | None = None,
) -> tuple[Array, Array, Array]:
    """Match every row of ``d1`` (queries) to ``d2`` (train); fixed shapes, jittable.

    Returns ``(index (N1,) int, distance (N1,), ok (N1,) bool)``: the nearest train row, its
    distance, and whether the match passes every gate:

    * ratio test: ``best < ratio * second best`` (``ratio >= 1`` disables it; with a single
      candidate the test passes, as OpenCV's ``knnMatch`` + ratio code does);
    * cross-check: the query is also the nearest neighbour of its match in ``d1``;
    * ``distance <= max_distance``;
    * Laplacian-sign gate: with ``sign1``/``sign2`` given, only rows of equal sign compete
      (the sign is part of the SURF keypoint; different signs never match);
    * ``valid1``/``valid2`` masks drop padded rows.
    """
    dist = distance_matrix(d1, d2, metric)
    n1, n2 = dist.shape
    allowed = jnp.ones((n1, n2), bool)
    if sign1 is not None and sign2 is not None:
        allowed = allowed & (jnp.asarray(sign1)[:, None] == jnp.asarray(sign2)[None, :])
    if valid1 is not None:
        allowed = allowed & jnp.asarray(valid1, bool)[:, None]
    if valid2 is not None:
        allowed = allowed & jnp.asarray(valid2, bool)[None, :]
    dist = jnp.where(allowed, dist, jnp.inf)
    if n2 == 0 or n1 == 0:
        return jnp.zeros((n1,), jnp.int32), jnp.full((n1,), jnp.inf), jnp.zeros((n1,), bool)
    best = jnp.argmin(dist, axis=1).astype(jnp.int32)
    rows = jnp.arange(n1)
    d_best = dist[rows, best]
    ok = jnp.isfinite(d_best) & (d_best <= max_distance)
    if n2 > 1:
        d_second = jnp.min(dist.at[rows, best].set(jnp.inf), axis=1)
        ok = ok & ((d_best < ratio * d_second) | ~jnp.isfinite(d_second) | (ratio >= 1.0))
    if cross_check:
        back = jnp.argmin(dist, axis=0)
        ok = ok & (back[best] == rows)
    return best, d_best, ok


def _pad_rows(d: np.ndarray, sign: np.ndarray | None, multiple: int = 256) -> tuple[np.ndarray, np.ndarray | None]:
    m = -(-len(d) // multiple) * multiple
    pad = np.zeros((m - len(d), d.shape[1]), d.dtype)
    padded_sign = (
        None if sign is None else np.concatenate([np.asarray(sign), np.zeros(m - len(d), np.asarray(sign).dtype)])
    )
    return np.concatenate([d, pad]), padded_sign


def match_descriptors(
    d1: np.ndarray,
    d2: np.ndarray,
    *,
    metric: Metric | None = None,
    ratio: float = 0.8,
    cross_check: bool = True,
    max_distance: float = np.inf,
    sign1: np.ndarray | None = None,
    sign2: np.ndarray | None = None,
    block: int = 4096,
) -> tuple[np.ndarray, np.ndarray]:
    """Accepted matches as ``(pairs (M, 2) int [query, train], distances (M,))``, sorted by
    query index. ``metric`` defaults to :func:`default_metric`. Queries are processed in
    blocks of ``block`` rows (the distance matrix is the memory bound); cross-checking still
    looks at every query, through a second pass over ``d2``."""
    d1 = np.asarray(d1)
    d2 = np.asarray(d2)
    if d1.ndim != 2 or d2.ndim != 2 or (len(d1) and len(d2) and d1.shape[1] != d2.shape[1]):
        raise ValueError(f"descriptors must be 2-D with equal widths, got {d1.shape} and {d2.shape}")
    metric = metric or default_metric(d1)
    if len(d1) == 0 or len(d2) == 0:
        return np.zeros((0, 2), np.int64), np.zeros((0,), np.float64)
    if len(d1) <= block and len(d2) <= block:
        # pad both sets to a multiple of 256 rows (masked): one compilation per size class
        n1, n2 = len(d1), len(d2)
        p1, p2 = _pad_rows(d1, sign1), _pad_rows(d2, sign2)
        idx, dist, ok = match_arrays(
            p1[0],
            p2[0],
            metric=metric,
            ratio=ratio,
            cross_check=cross_check,
            max_distance=max_distance,
            sign1=p1[1],
            sign2=p2[1],
            valid1=np.arange(len(p1[0])) < n1,
            valid2=np.arange(len(p2[0])) < n2,
        )
        idx, dist, ok = np.asarray(idx)[:n1], np.asarray(dist)[:n1], np.asarray(ok)[:n1]
    else:
        parts = [
            match_arrays(
                d1[s : s + block],
                d2,
                metric=metric,
                ratio=ratio,
                cross_check=False,
                max_distance=max_distance,
                sign1=None if sign1 is None else sign1[s : s + block],
                sign2=sign2,
            )
            for s in range(0, len(d1), block)
        ]
        idx, dist, ok = (np.concatenate([np.asarray(p[k]) for p in parts]) for k in range(3))
        if cross_check:
            back = np.concatenate(
                [
                    np.asarray(
                        match_arrays(
                            d2[s : s + block],
                            d1,
                            metric=metric,
                            ratio=1.0,
                            cross_check=False,
                            sign1=None if sign2 is None else sign2[s : s + block],
                            sign2=sign1,
                        )[0]
                    )
                    for s in range(0, len(d2), block)
                ]
            )
            ok = ok & (back[idx] == np.arange(len(d1)))
    q = np.nonzero(ok)[0]
    return np.stack([q, idx[q]], axis=1).astype(np.int64), dist[q].astype(np.float64)
