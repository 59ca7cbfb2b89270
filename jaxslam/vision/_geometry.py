"""Two-view geometry in JAX: essential-matrix RANSAC, relative pose with cheirality, DLT
triangulation, and local bundle adjustment (SPEC §3.2).

Conventions (OpenCV's): pixels ``uv``; normalised coordinates ``x = K^-1 [u, v, 1]`` (first
two entries); the essential matrix ``E = [t]x R`` satisfies ``x2^T E x1 = 0`` for a point
``X2 = R X1 + t`` (camera-2 coordinates from camera-1 coordinates); ``|t| = 1``.

**RANSAC** (:func:`find_essential`): ``num_hypotheses`` minimal samples of 8 correspondences
are drawn at once (``lax.top_k`` of uniform keys: distinct indices, padded rows never drawn),
every hypothesis is fitted by the normalised 8-point algorithm (a batched 9x9 ``eigh``),
projected onto the essential manifold (singular values 1, 1, 0), and scored against every
correspondence in parallel with the truncated Sampson error (MSAC). The best hypothesis is
then improved by local optimisation: re-fitting on its inliers (weighted 8-point, a few
rounds) and Gauss-Newton on the Sampson error over the 5-dof manifold ``(R, t/|t|)``.
Hartley & Zisserman, "Multiple View Geometry", 2nd ed.: sec. 11.2 (8-point), 11.4.3 (Sampson),
9.6 (decomposition); Torr & Zisserman, "MLESAC", CVIU 2000 (MSAC); Chum et al., "Locally
optimized RANSAC", DAGM 2003.

**Bundle adjustment** (:func:`bundle_adjust`) builds :class:`~jaxslam.factors.ReprojectionFactor`
constraints with a Huber kernel and solves them with :func:`jaxslam.solvers.optimize`; it
takes and returns arrays, so callers never see the graph.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..lie import SO3

_W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


# --- helpers -----------------------------------------------------------------------------------


def normalize_pixels(uv: Array | np.ndarray, K: Array | np.ndarray) -> Array:
    """Pixels ``(N, 2)`` to normalised image coordinates ``(N, 2)`` with intrinsics ``K`` (3x3)."""
    uv = jnp.asarray(uv, jnp.float64)
    K = jnp.asarray(K, jnp.float64)
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return jnp.stack([x, y], axis=-1)


def _hom(x: Array) -> Array:
    return jnp.concatenate([x, jnp.ones((*x.shape[:-1], 1), x.dtype)], axis=-1)


def _skew(t: Array) -> Array:
    z = jnp.zeros_like(t[..., 0])
    return jnp.stack(
        [
            jnp.stack([z, -t[..., 2], t[..., 1]], -1),
            jnp.stack([t[..., 2], z, -t[..., 0]], -1),
            jnp.stack([-t[..., 1], t[..., 0], z], -1),
        ],
        -2,
    )


def essential_from_pose(R: Array, t: Array) -> Array:
    """``E = [t]x R`` (``t`` is used as given: normalise it for a unit-baseline E)."""
    return _skew(jnp.asarray(t)) @ jnp.asarray(R)


def sampson_residual(E: Array, x1: Array, x2: Array) -> Array:
    """Signed Sampson residual ``x2^T E x1 / |grad|`` (normalised units) of correspondences
    ``(N, 2)`` under essential matrices ``E`` ``(*H, 3, 3)``; result ``(*H, N)``. Smooth in
    ``E`` (unlike the square root of :func:`sampson_error` at zero). Written out entry by
    entry: one fused element-wise loop over ``H x N`` on CPU."""
    e = [[E[..., i, j, None] for j in range(3)] for i in range(3)]
    lead = (1,) * (E.ndim - 2)
    a, b = x1[..., 0].reshape((*lead, -1)), x1[..., 1].reshape((*lead, -1))
    c, d = x2[..., 0].reshape((*lead, -1)), x2[..., 1].reshape((*lead, -1))
    ex = [e[i][0] * a + e[i][1] * b + e[i][2] for i in range(3)]  # E x1
    etx = [e[0][j] * c + e[1][j] * d + e[2][j] for j in range(2)]  # (E^T x2)[:2]
    num = c * ex[0] + d * ex[1] + ex[2]
    den = ex[0] ** 2 + ex[1] ** 2 + etx[0] ** 2 + etx[1] ** 2
    return num / jnp.sqrt(jnp.maximum(den, 1e-300))


def sampson_error(E: Array, x1: Array, x2: Array) -> Array:
    """Squared Sampson distance (normalised units^2) of correspondences ``(N, 2)`` under
    essential matrices ``E`` ``(*H, 3, 3)``; result ``(*H, N)`` (H&Z eq. 11.9)."""
    return sampson_residual(E, x1, x2) ** 2


def project_to_essential(F: Array) -> Array:
    """Nearest essential matrix (Frobenius): singular values ``(1, 1, 0)``."""
    u, _, vt = jnp.linalg.svd(F)
    keep = jnp.array([1.0, 1.0, 0.0]).reshape((1,) * (u.ndim - 1) + (3,))
    return (u * keep) @ vt


def _eight_point(x1: Array, x2: Array, w: Array) -> Array:
    """Weighted 8-point fit (``x1, x2`` ``(*H, n, 2)``, weights ``(*H, n)``) with Hartley's
    isotropic normalisation per hypothesis; returns essential matrices ``(*H, 3, 3)``."""
    wsum = jnp.maximum(jnp.sum(w, -1, keepdims=True), 1e-12)

    def similarity(x: Array) -> tuple[Array, Array]:
        c = jnp.sum(x * w[..., None], -2, keepdims=True) / wsum[..., None]
        d = jnp.sum(jnp.linalg.norm(x - c, axis=-1) * w, -1, keepdims=True) / wsum
        s = jnp.sqrt(2.0) / jnp.maximum(d, 1e-12)
        return (x - c) * s[..., None], jnp.concatenate([s, c[..., 0, :]], -1)

    y1, n1 = similarity(x1)
    y2, n2 = similarity(x2)
    a0, a1, b0, b1 = y1[..., 0], y1[..., 1], y2[..., 0], y2[..., 1]
    one = jnp.ones_like(a0)
    A = jnp.stack([b0 * a0, b0 * a1, b0, b1 * a0, b1 * a1, b1, a0, a1, one], -1)
    M = jnp.einsum("...ni,...n,...nj->...ij", A, w, A)
    _, vecs = jnp.linalg.eigh(M)
    Fn = vecs[..., :, 0].reshape((*vecs.shape[:-2], 3, 3))

    def T(n: Array) -> Array:  # y = T x for homogeneous x
        s, cx, cy = n[..., 0], n[..., 1], n[..., 2]
        z = jnp.zeros_like(s)
        return jnp.stack(
            [jnp.stack([s, z, -s * cx], -1), jnp.stack([z, s, -s * cy], -1), jnp.stack([z, z, z + 1], -1)], -2
        )

    F = jnp.swapaxes(T(n2), -1, -2) @ Fn @ T(n1)
    return project_to_essential(F)


# --- relative pose from E ----------------------------------------------------------------------


def decompose_essential(E: Array) -> tuple[Array, Array]:
    """The four ``(R, t)`` candidates of an essential matrix: ``R`` ``(4, 3, 3)``, ``t`` ``(4, 3)``
    (unit), in the order ``(R1, t), (R1, -t), (R2, t), (R2, -t)`` (H&Z result 9.19)."""
    u, _, vt = jnp.linalg.svd(jnp.asarray(E))
    u = u * jnp.where(jnp.linalg.det(u) < 0, -1.0, 1.0)
    vt = vt * jnp.where(jnp.linalg.det(vt) < 0, -1.0, 1.0)
    W = jnp.asarray(_W)
    r1, r2 = u @ W @ vt, u @ W.T @ vt
    t = u[:, 2]
    return jnp.stack([r1, r1, r2, r2]), jnp.stack([t, -t, t, -t])


def triangulate_points(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`triangulate_dlt` for two fixed 3x4 cameras and ``(N, 2)`` NumPy inputs, compiled
    once per size class (``N`` padded to a power of two). Returns NumPy arrays."""
    n = len(x1)
    m = _bucket(n)
    pad = np.zeros((m - n, 2))
    X, fin = _triangulate_jit(
        jnp.asarray(P1, jnp.float64),
        jnp.asarray(P2, jnp.float64),
        jnp.asarray(np.concatenate([x1, pad])),
        jnp.asarray(np.concatenate([x2, pad])),
    )
    return np.array(X[:n]), np.array(fin[:n])


def triangulate_dlt(P1: Array, P2: Array, x1: Array, x2: Array) -> tuple[Array, Array]:
    """Linear (DLT) triangulation of correspondences ``x1, x2`` ``(*N, 2)`` seen by cameras
    ``P1, P2`` (3x4, or batched ``(*N, 3, 4)``). Use normalised coordinates with ``P = [R | t]``,
    or pixels with ``P = K [R | t]``. Returns ``(X (*N, 3), finite (*N,))``: ``finite`` is False
    for points at infinity (homogeneous ``w`` ~ 0). H&Z sec. 12.2 (the homogeneous method)."""
    P1 = jnp.asarray(P1, jnp.float64)
    P2 = jnp.asarray(P2, jnp.float64)
    x1 = jnp.asarray(x1, jnp.float64)
    x2 = jnp.asarray(x2, jnp.float64)
    P1 = jnp.broadcast_to(P1, (*x1.shape[:-1], 3, 4))
    P2 = jnp.broadcast_to(P2, (*x2.shape[:-1], 3, 4))
    A = jnp.stack(
        [
            x1[..., 0:1] * P1[..., 2, :] - P1[..., 0, :],
            x1[..., 1:2] * P1[..., 2, :] - P1[..., 1, :],
            x2[..., 0:1] * P2[..., 2, :] - P2[..., 0, :],
            x2[..., 1:2] * P2[..., 2, :] - P2[..., 1, :],
        ],
        axis=-2,
    )
    A = A / jnp.maximum(jnp.linalg.norm(A, axis=-1, keepdims=True), 1e-300)
    _, vecs = jnp.linalg.eigh(jnp.swapaxes(A, -1, -2) @ A)
    X = vecs[..., :, 0]
    w = X[..., 3]
    finite = jnp.abs(w) > 1e-12 * jnp.linalg.norm(X, axis=-1)
    w_safe = jnp.where(finite, w, 1.0)
    return X[..., :3] / w_safe[..., None], finite


_triangulate_jit = jax.jit(triangulate_dlt)


def _depths(R: Array, t: Array, X: Array) -> tuple[Array, Array]:
    z1 = X[..., 2]
    z2 = X @ R[2] + t[2]
    return z1, z2


@jax.jit
def _recover_pose_jit(E, x1, x2, mask, distance_thresh):
    Rs, ts = decompose_essential(E)
    P1 = jnp.concatenate([jnp.eye(3), jnp.zeros((3, 1))], 1)

    def one(R, t):
        P2 = jnp.concatenate([R, t[:, None]], 1)
        X, fin = triangulate_dlt(P1, P2, x1, x2)
        z1, z2 = _depths(R, t, X)
        good = mask & fin & (z1 > 0) & (z2 > 0) & (z1 < distance_thresh) & (z2 < distance_thresh)
        return good, X

    goods, Xs = jax.vmap(one)(Rs, ts)
    k = jnp.argmax(jnp.sum(goods, -1))
    return Rs[k], ts[k], goods[k], Xs[k]


def recover_pose(
    E: Array | np.ndarray,
    x1: Array | np.ndarray,
    x2: Array | np.ndarray,
    mask: Array | np.ndarray | None = None,
    distance_thresh: float = 50.0,
) -> tuple[Array, Array, Array, Array]:
    """Pick the ``(R, t)`` of ``E`` that puts the most points (normalised coordinates, among
    ``mask``) in front of both cameras and closer than ``distance_thresh`` baselines (OpenCV's
    ``recoverPose`` rule). Returns ``(R, t, good (N,), X (N, 3) in camera-1 coordinates)``."""
    x1 = jnp.asarray(x1, jnp.float64)
    x2 = jnp.asarray(x2, jnp.float64)
    m = jnp.ones(x1.shape[0], bool) if mask is None else jnp.asarray(mask, bool)
    return _recover_pose_jit(jnp.asarray(E, jnp.float64), x1, x2, m, distance_thresh)


# --- RANSAC ------------------------------------------------------------------------------------


class EssentialResult(NamedTuple):
    """Output of :func:`find_essential`: ``E`` (3x3), ``R``, ``t`` (unit), ``inliers`` (N,) bool
    (Sampson and cheirality), ``score`` (MSAC cost of the returned model)."""

    E: Array
    R: Array
    t: Array
    inliers: Array
    score: Array


def _sample(key: Array, n_valid: Array, num: int, k: int = 8) -> tuple[Array, Array]:
    """``num`` samples of ``k`` indices in ``[0, n_valid)`` (uniform, with replacement) and
    whether each sample's indices are distinct (samples with a repeat are discarded: ~3 % of
    them at N = 1000, far cheaper than sampling without replacement on CPU)."""
    idx = jax.random.randint(key, (num, k), 0, n_valid)
    srt = jnp.sort(idx, axis=-1)
    return idx, jnp.all(srt[:, 1:] != srt[:, :-1], axis=-1)


def _tangent_basis(t: Array) -> Array:
    """Two unit vectors ``(3, 2)`` orthogonal to the unit vector ``t``."""
    a = jnp.where(jnp.abs(t[0]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
    b1 = jnp.cross(t, a)
    b1 = b1 / jnp.linalg.norm(b1)
    b2 = jnp.cross(t, b1)
    return jnp.stack([b1, b2], axis=1)


def _refine_sampson(R: Array, t: Array, x1: Array, x2: Array, w: Array, iterations: int) -> tuple[Array, Array]:
    """Gauss-Newton on the weighted Sampson residuals over ``(R, t/|t|)`` (5 dof)."""

    def update(R, t, d):
        R_new = R @ SO3.exp(d[:3]).as_matrix()
        t_new = t + _tangent_basis(t) @ d[3:]
        return R_new, t_new / jnp.linalg.norm(t_new)

    def residual(d, R, t):
        Rn, tn = update(R, t, d)
        return jnp.sqrt(w) * sampson_residual(essential_from_pose(Rn, tn), x1, x2)

    def step(_, state):
        R, t = state
        d0 = jnp.zeros(5)
        r = residual(d0, R, t)
        J = jax.jacfwd(residual)(d0, R, t)
        H = J.T @ J + 1e-9 * jnp.eye(5)
        d = -jnp.linalg.solve(H, J.T @ r)
        Rn, tn = update(R, t, d)
        better = jnp.sum(residual(jnp.zeros(5), Rn, tn) ** 2) < jnp.sum(r**2)
        return jnp.where(better, Rn, R), jnp.where(better, tn, t)

    return jax.lax.fori_loop(0, iterations, step, (R, t))


@functools.partial(
    jax.jit,
    static_argnames=("num_hypotheses", "num_polish", "lo_rounds", "gn_rounds", "gn_iterations"),
)
def _find_essential_jit(x1, x2, valid, key, threshold, num_hypotheses, num_polish, lo_rounds, gn_rounds, gn_iterations):
    thr2 = threshold * threshold
    idx, distinct = _sample(key, jnp.sum(valid), num_hypotheses)
    Es = _eight_point(x1[idx], x2[idx], jnp.ones(idx.shape))

    def msac(E: Array) -> Array:
        err = sampson_error(E, x1, x2)
        return jnp.sum(jnp.where(jnp.broadcast_to(valid, err.shape), jnp.minimum(err, thr2), 0.0), axis=-1)

    cost = jnp.where(distinct, msac(Es), jnp.inf)

    def polish(E: Array) -> tuple[Array, Array, Array]:
        def lo(_, E):  # local optimisation: re-fit on the inliers of the current model
            inl = valid & (sampson_error(E, x1, x2) < thr2)
            E_new = _eight_point(x1, x2, inl.astype(jnp.float64))
            return jnp.where(msac(E_new) < msac(E), E_new, E)

        E = jax.lax.fori_loop(0, lo_rounds, lo, E)
        inl = valid & (sampson_error(E, x1, x2) < thr2)
        R, t, good, _ = _recover_pose_jit(E, x1, x2, inl, 50.0)

        def gn_round(_, state):  # Gauss-Newton on the inliers, then re-select them
            R, t, good = state
            R, t = _refine_sampson(R, t, x1, x2, good.astype(jnp.float64), gn_iterations)
            return R, t, valid & (sampson_error(essential_from_pose(R, t), x1, x2) < thr2)

        return jax.lax.fori_loop(0, gn_rounds, gn_round, (R, t, good))

    # polish the best few hypotheses (forward motion has nearby local minima), keep the best
    top = jax.lax.top_k(-cost, num_polish)[1]
    Rs, ts, inls = jax.vmap(polish)(Es[top])
    k = jnp.argmin(msac(jax.vmap(essential_from_pose)(Rs, ts)))
    R, t, inl = Rs[k], ts[k], inls[k]
    E = essential_from_pose(R, t)
    R, t, good, _ = _recover_pose_jit(E, x1, x2, inl, 1e6)
    return E, R, t, good, msac(E)


@jax.jit
def _fit_all_jit(x1, x2, valid, threshold):
    """No RANSAC: one 8-point fit on every match, then Gauss-Newton on the Sampson error with
    Cauchy weights (IRLS, scale ``threshold``); every match in front of both cameras is kept."""
    w = valid.astype(jnp.float64)
    E = _eight_point(x1, x2, w)
    R, t, _, _ = _recover_pose_jit(E, x1, x2, valid, 1e6)

    def irls(_, state):
        R, t = state
        r = sampson_residual(essential_from_pose(R, t), x1, x2)
        return _refine_sampson(R, t, x1, x2, w / (1.0 + (r / threshold) ** 2), 8)

    R, t = jax.lax.fori_loop(0, 5, irls, (R, t))
    R, t, good, _ = _recover_pose_jit(essential_from_pose(R, t), x1, x2, valid, 1e6)
    return R, t, good


def _bucket(n: int) -> int:
    """Padded size for ``n`` correspondences: powers of two from 64 (few recompilations)."""
    return max(64, 1 << int(np.ceil(np.log2(max(n, 1)))))


def find_essential(
    x1: Array | np.ndarray,
    x2: Array | np.ndarray,
    threshold: float,
    *,
    num_hypotheses: int = 1024,
    num_polish: int = 4,
    seed: int = 0,
    lo_rounds: int = 2,
    gn_rounds: int = 3,
    gn_iterations: int = 8,
) -> EssentialResult:
    """Vectorised RANSAC (MSAC + local optimisation) for the essential matrix of normalised
    correspondences ``x1, x2`` ``(N, 2)``; see the module doc. ``threshold`` is the Sampson
    distance in normalised units (pixels / focal length). Needs ``N >= 8``; inputs are padded
    to a power of two so repeated calls compile once per size class."""
    x1 = np.asarray(x1, np.float64)
    x2 = np.asarray(x2, np.float64)
    if x1.shape != x2.shape or x1.ndim != 2 or x1.shape[1] != 2:
        raise ValueError(f"x1, x2 must both be (N, 2), got {x1.shape} and {x2.shape}")
    n = x1.shape[0]
    if n < 8:
        raise ValueError(f"find_essential needs at least 8 correspondences, got {n}")
    m = _bucket(n)
    pad = np.zeros((m - n, 2))
    valid = np.arange(m) < n
    E, R, t, good, score = _find_essential_jit(
        jnp.asarray(np.concatenate([x1, pad])),
        jnp.asarray(np.concatenate([x2, pad])),
        jnp.asarray(valid),
        jax.random.PRNGKey(seed),
        float(threshold),
        num_hypotheses,
        num_polish,
        lo_rounds,
        gn_rounds,
        gn_iterations,
    )
    return EssentialResult(E, R, t, np.asarray(good)[:n], score)  # type: ignore[arg-type]  # numpy slice: no compile per n


def relative_pose(
    uv1: np.ndarray,
    uv2: np.ndarray,
    K: np.ndarray,
    *,
    method: str = "jax",
    threshold_px: float = 1.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Relative pose ``(R, t (unit), inliers (N,) bool)`` of camera 2 w.r.t. camera 1
    (``X2 = R X1 + t``) from pixel matches. ``method``: ``jax`` (:func:`find_essential`),
    ``opencv`` (``cv2.findEssentialMat`` 5-point RANSAC + ``cv2.recoverPose``) or ``none`` (no
    RANSAC: one 8-point fit on every match, Cauchy-weighted Sampson refinement, and every
    match in front of both cameras counted as an inlier)."""
    uv1 = np.asarray(uv1, np.float64)
    uv2 = np.asarray(uv2, np.float64)
    K = np.asarray(K, np.float64)
    f = 0.5 * (K[0, 0] + K[1, 1])
    if method == "opencv":
        import cv2

        E, mask = cv2.findEssentialMat(uv1, uv2, K, method=cv2.RANSAC, prob=0.999, threshold=threshold_px)
        if E is None or E.shape != (3, 3):
            raise ValueError("cv2.findEssentialMat found no model")
        _, R, t, mask = cv2.recoverPose(E, uv1, uv2, K, mask=mask)
        return R, t[:, 0], mask[:, 0] > 0
    Kinv = np.linalg.inv(K)  # NumPy here: eager JAX ops would compile once per match count
    x1 = uv1 @ Kinv[:2, :2].T + Kinv[:2, 2]
    x2 = uv2 @ Kinv[:2, :2].T + Kinv[:2, 2]
    if method == "jax":
        res = find_essential(x1, x2, threshold_px / f, seed=seed)
        return np.asarray(res.R), np.asarray(res.t), np.asarray(res.inliers)
    if method == "none":
        n = len(x1)
        m = _bucket(n)
        pad = np.zeros((m - n, 2))
        R, t, good = _fit_all_jit(
            jnp.asarray(np.concatenate([x1, pad])),
            jnp.asarray(np.concatenate([x2, pad])),
            jnp.asarray(np.arange(m) < n),
            threshold_px / f,
        )
        return np.asarray(R), np.asarray(t), np.asarray(good)[:n]
    raise ValueError(f"method must be 'jax', 'opencv' or 'none', got {method!r}")


# --- bundle adjustment -------------------------------------------------------------------------


@dataclasses.dataclass
class BundleResult:
    """Output of :func:`bundle_adjust`: refined ``poses`` ``(C, 7)`` (``world_T_camera``, SE3
    params), ``points`` ``(P, 3)``, per-observation pixel ``residuals`` ``(O, 2)``, and the
    solver's ``initial_cost``, ``final_cost``, ``iterations``, ``status``."""

    poses: np.ndarray
    points: np.ndarray
    residuals: np.ndarray
    initial_cost: float
    final_cost: float
    iterations: int
    status: str


def reprojection_residuals(
    poses: np.ndarray, points: np.ndarray, cam_idx: np.ndarray, pt_idx: np.ndarray, uv: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """Pixel residuals ``(O, 2)`` = projection - measurement of ``points[pt_idx]`` in cameras
    ``poses[cam_idx]`` (``world_T_camera`` SE3 params); points behind a camera give ``inf``."""
    cam_idx = np.asarray(cam_idx, np.int64)
    n = len(cam_idx)
    m = _bucket(n)
    pose_rows = np.asarray(poses, np.float64)[np.concatenate([cam_idx, np.zeros(m - n, np.int64)])]
    pose_rows[n:] = [1.0, 0, 0, 0, 0, 0, 0]
    pts = np.concatenate([np.asarray(points, np.float64)[np.asarray(pt_idx, np.int64)], np.ones((m - n, 3))])
    calib = np.array([K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]], np.float64)
    uvp, front = _project_jit(jnp.asarray(pose_rows), jnp.asarray(pts), jnp.asarray(calib))
    r = np.array(uvp[:n]) - np.asarray(uv)
    r[~np.asarray(front[:n])] = np.inf
    return r


@jax.jit
def _project_jit(pose_rows: Array, points: Array, calib: Array) -> tuple[Array, Array]:
    from ..factors import pinhole_project
    from ..lie import SE3

    return pinhole_project(SE3(pose_rows), points, calib)


def bundle_adjust(
    poses: np.ndarray,
    points: np.ndarray,
    cam_idx: np.ndarray,
    pt_idx: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    *,
    fixed_cameras: np.ndarray | list[int] | tuple[int, ...] = (0,),
    scale_prior: tuple[int, int] | None = None,
    sigma_px: float = 1.0,
    huber_px: float | None = 2.0,
    max_iterations: int = 30,
    pad: bool = True,
) -> BundleResult:
    """Bundle adjustment of ``world_T_camera`` poses ``(C, 7)`` and points ``(P, 3)`` from
    observations ``(cam_idx, pt_idx, uv)`` with a pinhole ``K``: :class:`ReprojectionFactor`
    (isotropic ``sigma_px``) with a Huber kernel (threshold ``huber_px`` pixels; ``None``:
    plain least squares), Levenberg-Marquardt from :func:`jaxslam.solvers.optimize`.

    ``fixed_cameras`` are held constant (the gauge). A monocular problem also has a free
    scale: with one fixed camera, pass ``scale_prior=(a, b)`` to hold ``|c_b - c_a|`` near its
    initial value (a tight prior on camera ``b``'s translation only, loose on its rotation).
    """
    from ..core import Factor, Gaussian, Huber, Point3Var, Pose3Var, Values
    from ..factors import PriorFactor, ReprojectionFactor
    from ..solvers import SolverConfig, bucket, optimize

    poses = np.asarray(poses, np.float64)
    points = np.asarray(points, np.float64)
    cam_idx = np.asarray(cam_idx, np.int64)
    pt_idx = np.asarray(pt_idx, np.int64)
    if len(cam_idx) == 0:
        raise ValueError("bundle_adjust: no observations")
    calib = np.array([K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]], np.float64)
    robust = None if huber_px is None else Huber(huber_px / sigma_px)
    factor = ReprojectionFactor.create(
        Pose3Var(cam_idx), Point3Var(pt_idx), uv, calib, Gaussian.isotropic(2, sigma_px), robust=robust
    )
    factors: list[Factor] = [factor]
    if scale_prior is not None:
        b = int(scale_prior[1])
        sig = np.array([10.0, 10.0, 10.0, 1e-4, 1e-4, 1e-4])
        factors.append(
            PriorFactor.create(Pose3Var(np.array([b])), poses[b : b + 1], Gaussian.diagonal(jnp.asarray(sig), 1))
        )
    cams = np.unique(cam_idx)
    pts = np.unique(pt_idx)
    fixed_ids = np.intersect1d(np.asarray(fixed_cameras, np.int64), cams)
    # The solver compiles once per (bucketed) problem size, but its unknown count is exact:
    # pad the points with unconstrained dummies (held fixed) up to the solver's own bucket so
    # that windowed BAs of similar size reuse one compilation.
    n_pad = bucket(len(pts)) - len(pts) if pad else 0
    dummy = np.arange(n_pad) + (int(pts.max()) + 1 if len(pts) else 0)
    values = Values.create(
        {
            Pose3Var(cams): poses[cams],
            Point3Var(np.concatenate([pts, dummy])): np.concatenate([points[pts], np.zeros((n_pad, 3))]),
        }
    )
    fixed = [Pose3Var(fixed_ids)] if len(fixed_ids) else []
    config = SolverConfig(method="lm", max_iterations=max_iterations, relative_tol=1e-8)
    result = optimize(factors, values, config, fixed=fixed)
    out_poses = poses.copy()
    out_points = points.copy()
    out_poses[cams] = np.asarray(result.values.params(Pose3Var))
    out_points[pts] = np.asarray(result.values.params(Point3Var))[: len(pts)]
    res = reprojection_residuals(out_poses, out_points, cam_idx, pt_idx, uv, K)
    return BundleResult(
        out_poses,
        out_points,
        res,
        float(result.initial_cost),
        float(result.final_cost),
        int(result.iterations),
        result.status.value,
    )
