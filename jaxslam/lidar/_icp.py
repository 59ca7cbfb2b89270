"""Robust point-to-plane ICP on SE(3) with degeneracy detection and solution remapping.

**Problem.** Find ``T`` = world_T_sensor minimising ``sum_i rho(n_i . (T p_i - m_i))`` over
source points ``p_i`` (sensor frame) and their nearest map points ``m_i`` with map normals
``n_i`` (:class:`VoxelMap`). Gauss-Newton with iteratively reweighted least squares; the
update is on the right, ``T <- T Exp(xi)``, ``xi = [rotation, translation]`` (GTSAM's Pose3
tangent), so the Jacobian of a residual is ``[(p x R^T n)^T, (R^T n)^T]``.

**Robust kernel.** Geman-McClure, weight ``(s^2 / (s^2 + r^2))^2``. The scale ``s`` is
``IcpConfig.kernel_scale`` if given, else adaptive and annealed: ``max(1.4826 * median |r|,
min_kernel_scale, initial_kernel_scale / 2^(it - 1))`` at iteration ``it`` (a fixed small
scale would silence the few end-wall points that alone observe the tunnel axis while the
guess is off along it).

**Degeneracy (Zhang, Kaess and Singh, ICRA 2016).** Rotation and translation are made
comparable by scaling the rotation coordinates with a length ``L`` (the median source-point
range, or ``IcpConfig.rotation_length``): ``H_s = S^-1 H S^-1 / sum(w)``, ``S =
diag(L, L, L, 1, 1, 1)``. ``H_s`` is dimensionless and per correspondence: its eigenvalue in
a translation direction ``d`` is the weighted mean of ``(n . d)^2``, i.e. the fraction of
correspondences whose planes face ``d`` (a box tunnel gives ~0.3-0.6 across, ~0 along the
axis). Eigen-directions with eigenvalue below ``degeneracy_threshold`` (default 0.0025:
"fewer than 0.25 % of the points constrain it") are *weak*. On the simulated tunnel the
along-axis eigenvalue is ~1e-4 facing the open portal (the floor of normal-estimation noise),
0.004-0.005 with the closed end wall 14-27 m ahead; within ~10 m of a wall the HAP sees no
ceiling and a pitch + height combination sits at ~0.002 (flagged). Each Gauss-Newton step is
solved only in the span of the strong eigen-directions (the pseudo-inverse of ``H_s``
restricted to them: Zhang's solution remapping), and after each step the weak components of
``Log(T_init^-1 T)`` are set to zero, so along a weak direction the estimate stays at
``T_init``. Detection is redone at every iteration until the kernel has annealed, then the
split is frozen (so a direction near the threshold cannot toggle and stall convergence); the
reported split is that of the solution's Hessian. It follows the data: when the tunnel's end
wall is in view its points lift the along-axis eigenvalue above the threshold and the axis is
estimated normally.

**Reflectivity (optional).** With ``source_intensity`` (per source point, e.g.
:func:`relative_reflectivity`) and a map whose points carry a reflectivity model
(:class:`VoxelMap`), each correspondence adds a photometric residual ``I_p - (c_m + g_m . (T p -
m))`` (``c_m``, ``g_m`` the map point's value and in-plane gradient), Jacobian ``-[(p x R^T
g)^T, (R^T g)^T]``, robustly weighted like the geometric one (Geman-McClure, scale from its own
MAD, floor ``min_intensity_scale``) and whitened into the geometric residual's units (times
``intensity_weight * s_geo / s_int``), in the spirit of Park, Zhou and Koltun's coloured ICP
(ICCV 2017). On plain tunnel walls the geometry leaves the axis weak; stains, joints, pipes and
paint in the reflectance observe it, the degeneracy analysis sees that (the combined Hessian)
and the axis is estimated instead of held.

**Outputs.** ``information = H / sigma_r^2`` with ``H = J^T W J`` at the solution and
``sigma_r^2`` the weighted residual variance, in the right-perturbation tangent of ``T``,
order [rotation, translation]. Along weak directions it is left as the data make it: small
(not inflated, not zeroed), so a factor built from it barely constrains the tunnel axis;
:meth:`Registration.strong_information` removes them exactly.
Note that it treats residuals as independent, which makes it optimistic overall (thousands
of points); the estimator may scale it.

**Bad input.** Wrong shapes or non-finite source points or ``T_init`` raise
:class:`~jaxslam.errors.InputFormatError`. An empty map, an empty source, or fewer than
``min_correspondences`` correspondences return ``converged=False`` with ``T = T_init``, zero
information, every direction weak, and the reason in ``message``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ConfigError, InputFormatError
from ._preprocess import check_points
from ._se3 import orthonormalize, se3_exp, se3_inverse, se3_log
from ._voxel_map import VoxelMap


@dataclasses.dataclass(frozen=True)
class IcpConfig:
    """Point-to-plane ICP settings."""

    max_iterations: int = 30
    """Gauss-Newton iterations at most."""
    max_correspondence_distance: float = 1.0
    """A source point farther than this from its nearest map point has no correspondence (m)."""
    min_planarity: float = 0.9
    """Map points whose neighbourhood planarity (``1 - l_min / l_mid``) is below this are not
    used: edges and corners (the tunnel's, the end wall's) give tilted normals."""
    kernel_scale: float | None = None
    """Geman-McClure scale (m); ``None``: adaptive (see ``initial_kernel_scale``)."""
    initial_kernel_scale: float = 0.1
    """Adaptive scale: ``max(1.4826 MAD(r), min_kernel_scale, initial_kernel_scale / 2^(it-1))``
    at iteration ``it``: wide at first (a few points that disagree with the initial guess, like
    an end wall seen by few rays, still pull), then down to the residual spread."""
    min_kernel_scale: float = 0.02
    """Floor of the adaptive scale (m), about the range noise."""
    convergence_rotation: float = 3e-5
    """Stop when the update's rotation is below this (rad) ..."""
    convergence_translation: float = 3e-4
    """... and its translation below this (m). Not much smaller: a nearest-neighbour switch of a
    few correspondences can make the iterates cycle at the 0.1 mm level."""
    min_correspondences: int = 30
    """Fewer correspondences than this: ``converged=False``."""
    degeneracy_threshold: float = 0.0025
    """Eigenvalues of the scaled, per-correspondence Hessian below this are weak (see module doc)."""
    rotation_length: float | None = None
    """Length (m) that makes rotation comparable to translation; ``None``: median source range."""
    remap_degenerate: bool = True
    """Do not move along weak directions (solution remapping); ``False``: plain Gauss-Newton."""
    intensity_weight: float = 1.0
    """Weight of the reflectivity residuals (when ``source_intensity`` is given and the map has
    reflectivity), relative to the geometric ones after whitening each by its robust scale; 0:
    geometry only."""
    min_intensity_scale: float = 0.02
    """Floor of the reflectivity residuals' robust scale (relative reflectivity units)."""

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.min_correspondences < 6:
            raise ConfigError("max_iterations must be >= 1 and min_correspondences >= 6")
        if not (self.max_correspondence_distance > 0 and self.min_kernel_scale > 0 and self.degeneracy_threshold >= 0):
            raise ConfigError("max_correspondence_distance, min_kernel_scale must be > 0, degeneracy_threshold >= 0")
        if self.kernel_scale is not None and not self.kernel_scale > 0:
            raise ConfigError("kernel_scale must be positive or None")
        if self.rotation_length is not None and not self.rotation_length > 0:
            raise ConfigError("rotation_length must be positive or None")
        if not (self.intensity_weight >= 0 and self.min_intensity_scale > 0):
            raise ConfigError("intensity_weight must be >= 0 and min_intensity_scale > 0")


@dataclasses.dataclass(frozen=True)
class Registration:
    """Result of :func:`register`. Tangent order everywhere: [rotation, translation], right
    perturbation of ``T`` (``T Exp(xi)``)."""

    T: np.ndarray
    """(4, 4) world_T_sensor."""
    information: np.ndarray
    """(6, 6) ``J^T W J / sigma_r^2`` at the solution (symmetric PSD)."""
    eigenvalues: np.ndarray
    """(6,) ascending eigenvalues of the scaled per-correspondence Hessian ``H_s`` (dimensionless)."""
    eigenvectors: np.ndarray
    """(6, 6) their eigenvectors as *columns*, in the scaled tangent ``[L * rotation, translation]``."""
    condition_number: float
    """``eigenvalues[-1] / eigenvalues[0]`` (inf when the smallest is 0)."""
    degenerate: bool
    """Some eigenvalue is below ``IcpConfig.degeneracy_threshold``."""
    weak_directions: np.ndarray
    """(k, 6) unit rows: the weak eigen-directions mapped back to the tangent [rad, m]."""
    fitness: float
    """Fraction of source points with an inlier correspondence (|r| < 3 kernel scales)."""
    rmse: float
    """Root mean square point-to-plane residual of the inliers (m)."""
    iterations: int
    n_correspondences: int
    converged: bool
    message: str = ""
    """Why ``converged`` is False ("" otherwise)."""
    residual_sigma: float = 0.0
    """``sigma_r`` (m): the weighted residual standard deviation that scales ``information``."""
    rotation_length: float = 1.0
    """``L`` (m) used to scale rotations for the degeneracy analysis."""
    intensity_correspondences: int = 0
    """Correspondences that also had a reflectivity residual (0: geometry only)."""

    def strong_information(self) -> np.ndarray:
        """``information`` with the weak directions removed (exactly zero information along
        them): ``P^T I P`` with ``P = S^-1 (1 - W W^T) S`` the projector, in the scaled tangent,
        onto the strong eigen-directions. For a factor that should say nothing at all along
        the tunnel axis rather than the little the data say."""
        s = np.array([self.rotation_length] * 3 + [1.0] * 3)
        W = self.eigenvectors[:, : len(self.weak_directions)]  # ascending: the weak ones come first
        P = (np.eye(6) - W @ W.T) * s[None, :] / s[:, None]
        return P.T @ self.information @ P


@dataclasses.dataclass
class _Terms:
    n: int
    H: np.ndarray
    g: np.ndarray
    wsum: float
    r: np.ndarray
    w: np.ndarray
    scale: float
    n_intensity: int = 0


def register(
    source_points, voxel_map: VoxelMap, T_init, config: IcpConfig | None = None, source_intensity=None
) -> Registration:
    """Align ``source_points`` ``(N, 3)`` (sensor frame, deskewed) to ``voxel_map`` starting
    from ``T_init`` ``(4, 4)`` world_T_sensor; ``source_intensity`` ``(N,)`` (``NaN`` for none)
    adds the reflectivity term when the map has reflectivity. See the module docstring."""
    cfg = config or IcpConfig()
    src = check_points(source_points, "source_points")
    src_i = None
    if source_intensity is not None:
        src_i = np.asarray(source_intensity, dtype=np.float64).reshape(-1)
        if src_i.shape != (len(src),):
            raise InputFormatError(f"source_intensity must have shape ({len(src)},), got {src_i.shape}")
        if np.isinf(src_i).any():
            raise InputFormatError("source_intensity contains infinite values (NaN marks none)")
        if cfg.intensity_weight == 0 or not voxel_map.has_intensity or not np.isfinite(src_i).any():
            src_i = None
    T0 = np.asarray(T_init, dtype=np.float64)
    if T0.shape != (4, 4) or not np.all(np.isfinite(T0)):
        raise InputFormatError(f"T_init must be a finite (4, 4) matrix, got shape {T0.shape}")
    R0 = T0[:3, :3]
    if not np.allclose(R0.T @ R0, np.eye(3), atol=1e-6) or np.linalg.det(R0) < 0:
        raise InputFormatError("T_init's rotation block is not a rotation matrix")
    if len(voxel_map) == 0:
        return _failed(T0, src, "the map is empty (add a scan first)")
    if len(src) < cfg.min_correspondences:
        return _failed(T0, src, f"only {len(src)} source points (< min_correspondences {cfg.min_correspondences})")
    T0 = orthonormalize(T0)
    L = cfg.rotation_length or max(float(np.median(np.linalg.norm(src, axis=1))), 0.1)
    s_inv = np.array([1 / L] * 3 + [1.0] * 3)
    T = T0.copy()
    converged, it = False, 0
    basis: tuple[np.ndarray, np.ndarray] | None = None
    T_prev: np.ndarray | None = None
    for it in range(1, cfg.max_iterations + 1):
        terms = _linearize(T, src, voxel_map, cfg, it, src_i)
        if terms.n < cfg.min_correspondences:
            return _failed(T0, src, f"{terms.n} correspondences (< min_correspondences {cfg.min_correspondences})", it)
        Hs = terms.H * np.outer(s_inv, s_inv) / terms.wsum
        gs = terms.g * s_inv / terms.wsum
        if basis is None:
            lam, V = np.linalg.eigh(Hs)
            strong = lam >= cfg.degeneracy_threshold if cfg.remap_degenerate else lam > 1e-12 * lam[-1]
            B, W = V[:, strong], V[:, ~strong]
            if _annealed(cfg, it):
                basis = (B, W)  # from here on the split is frozen: no toggling at the threshold
        else:
            B, W = basis
        y = -B @ np.linalg.solve(B.T @ Hs @ B, B.T @ gs) if B.shape[1] else np.zeros(6)
        T_new = T @ se3_exp(s_inv * y)
        if cfg.remap_degenerate and W.shape[1]:
            # hold the weak components of the displacement from T_init at zero (exactly, in
            # T_init's log coordinates; the right-perturbation step alone leaks into them)
            d = se3_log(se3_inverse(T0) @ T_new) / s_inv
            T_new = T0 @ se3_exp(s_inv * (d - W @ (W.T @ d)))
        xi = se3_log(se3_inverse(T) @ T_new)
        # a 2-cycle (the step back to where it was two iterations ago) is a standstill too: the
        # weak-direction remapping can leave a step of ~6e-5 rad going back and forth for ever
        xi2 = se3_log(se3_inverse(T_prev) @ T_new) if T_prev is not None else xi
        T_prev, T = T, orthonormalize(T_new)
        small = any(
            np.linalg.norm(x[:3]) < cfg.convergence_rotation and np.linalg.norm(x[3:]) < cfg.convergence_translation
            for x in (xi, xi2)
        )
        if small and _annealed(cfg, it):
            converged = True
            break
    terms = _linearize(T, src, voxel_map, cfg, cfg.max_iterations, src_i)
    if terms.n < cfg.min_correspondences:
        return _failed(T0, src, f"{terms.n} correspondences at the solution", it)
    return _result(T, src, terms, cfg, L, it, converged)


def _annealed(cfg: IcpConfig, it: int) -> bool:
    return cfg.kernel_scale is not None or cfg.initial_kernel_scale * 0.5 ** (it - 1) <= cfg.min_kernel_scale


def _linearize(
    T: np.ndarray, src: np.ndarray, vmap: VoxelMap, cfg: IcpConfig, it: int, src_i: np.ndarray | None = None
) -> _Terms:
    R, t = T[:3, :3], T[:3, 3]
    q = src @ R.T + t
    _, idx = vmap.neighbors(q, 1, cfg.max_correspondence_distance)
    idx = idx[:, 0]
    ok = idx >= 0
    ok[ok] = vmap.planarity[idx[ok]] >= cfg.min_planarity
    p, qi, ii = src[ok], q[ok], idx[ok]
    n_w = vmap.normals[ii]
    r = np.einsum("ij,ij->i", n_w, qi - vmap._points[ii])
    if len(r) == 0:
        return _Terms(0, np.zeros((6, 6)), np.zeros(6), 0.0, r, r, cfg.min_kernel_scale)
    if cfg.kernel_scale is not None:
        scale = cfg.kernel_scale
    else:
        anneal = cfg.initial_kernel_scale * 0.5 ** (it - 1)
        scale = max(1.4826 * float(np.median(np.abs(r))), cfg.min_kernel_scale, anneal)
    w = (scale**2 / (scale**2 + r * r)) ** 2
    n_s = n_w @ R  # R^T n, row-wise
    J = np.concatenate([np.cross(p, n_s), n_s], axis=1)
    Jw = J * w[:, None]
    terms = _Terms(len(r), Jw.T @ J, Jw.T @ r, float(w.sum()), r, w, scale)
    if src_i is not None:
        _add_intensity(terms, R, p, qi, ii, src_i[ok], vmap, cfg)
    return terms


def _add_intensity(
    terms: _Terms, R: np.ndarray, p: np.ndarray, q: np.ndarray, ii: np.ndarray, ip: np.ndarray, vmap: VoxelMap, cfg
) -> None:
    """Add the reflectivity residuals of the correspondences (in place; see the module doc)."""
    c = vmap.intensity[ii]
    use = np.isfinite(ip) & np.isfinite(c)
    if use.sum() < cfg.min_correspondences:
        return
    g = vmap.intensity_gradient[ii[use]]
    r = ip[use] - (c[use] + np.einsum("ij,ij->i", g, q[use] - vmap._points[ii[use]]))
    s_i = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), cfg.min_intensity_scale)
    w = (s_i**2 / (s_i**2 + r * r)) ** 2
    k = cfg.intensity_weight * terms.scale / s_i  # whiten into the geometric residual's units
    g_s = g @ R
    J = -k * np.concatenate([np.cross(p[use], g_s), g_s], axis=1)
    Jw = J * w[:, None]
    terms.H = terms.H + Jw.T @ J
    terms.g = terms.g + Jw.T @ (k * r)
    terms.n_intensity = int(use.sum())


def _result(T, src, terms: _Terms, cfg: IcpConfig, L: float, it: int, converged: bool) -> Registration:
    s_inv = np.array([1 / L] * 3 + [1.0] * 3)
    lam, V = np.linalg.eigh(terms.H * np.outer(s_inv, s_inv) / terms.wsum)
    lam = np.maximum(lam, 0.0)
    weak = lam < cfg.degeneracy_threshold
    dirs = (V[:, weak] * s_inv[:, None]).T
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) if len(dirs) else np.zeros((0, 6))
    var = float(np.sum(terms.w * terms.r**2) / max(terms.wsum - 6.0, 1.0))
    var = max(var, 1e-12)
    info = terms.H / var
    info = (info + info.T) / 2
    inl = np.abs(terms.r) < 3 * terms.scale
    return Registration(
        T=T,
        information=info,
        eigenvalues=lam,
        eigenvectors=V,
        condition_number=float(lam[-1] / lam[0]) if lam[0] > 0 else float("inf"),
        degenerate=bool(np.any(weak)),
        weak_directions=dirs,
        fitness=float(inl.sum() / len(src)),
        rmse=float(np.sqrt(np.mean(terms.r[inl] ** 2))) if inl.any() else float("inf"),
        iterations=it,
        n_correspondences=terms.n,
        converged=converged,
        message="" if converged else f"no convergence in {cfg.max_iterations} iterations",
        residual_sigma=float(np.sqrt(var)),
        rotation_length=L,
        intensity_correspondences=terms.n_intensity,
    )


def _failed(T0: np.ndarray, src: np.ndarray, message: str, it: int = 0) -> Registration:
    return Registration(
        T=T0.copy(),
        information=np.zeros((6, 6)),
        eigenvalues=np.zeros(6),
        eigenvectors=np.eye(6),
        condition_number=float("inf"),
        degenerate=True,
        weak_directions=np.eye(6),
        fitness=0.0,
        rmse=float("inf"),
        iterations=it,
        n_correspondences=0,
        converged=False,
        message=message,
    )
