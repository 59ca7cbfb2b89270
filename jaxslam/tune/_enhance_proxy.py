"""A differentiable front-end objective for ABA-CLAHE's ``alpha``, ``beta`` and clip limit
(SPEC §3.1 eq. 2, §6), its optimiser, and the discrete end-to-end check.

SURF detection and matching are discrete, so the registration metric gives no gradient to
the enhancement. :func:`enhancement_objective` is a smooth stand-in built from what the
discrete pipeline does with an enhanced image. Data flow::

    frames (N, H, W) uint8 ──► soft ABA-CLAHE (alpha, beta, clip) ──► 255·E (float)
      [+ twins: the same views, an independent sensor-noise realisation; or frame k+1]
    ──► integral image ──► SURF's box-filter det(H) at SURF's sizes (2 octaves, 3 layers)
    ──► soft keypoints q = sigmoid(above threshold) · sigmoid(above its 26 neighbours)
    ──► repeatable count (q of view a times the 3x3 max of q of view b, and vice versa),
        spread (entropy over a grid of cells), amplified noise (E_a − E_b)
    ──► scalar, lower is better

:func:`tune_enhancement` minimises it with Adam (a few lines, no new dependency) on
training frames; :func:`evaluate_registration` runs the real discrete pipeline (hard
ABA-CLAHE → SURF → matching → essential-matrix RANSAC) on consecutive frame pairs, which is
what decides whether tuning helped (on held-out frames). :func:`simulate_frames` renders
frames (and noise twins) with ground truth from :mod:`jaxslam.sim`.

References: Bay et al., "Speeded-Up Robust Features", CVIU 2008 (box-filter Hessian);
Mikolajczyk & Schmid (2005), repeatability as the detector criterion; Kingma & Ba (2015),
Adam.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError, InputFormatError
from ..vision import aba_clahe, detect_and_describe, find_essential, match_descriptors, sampson_error
from ..vision._surf import layer_plan

ALPHA_RANGE = (0.05, 1.25)
"""Bounds of alpha and beta. Eq. (2) continues past 1 (a darkening curve); the upper bound
leaves room so that the no-brightening start ``alpha = beta = 1`` sits at a finite,
well-conditioned logit instead of at the edge of a sigmoid."""
CLIP_RANGE = (0.5, 8.0)
"""Bounds of the CLAHE clip limit (OpenCV units); 0.5 is close to no equalisation."""


# --- parameterisation ---------------------------------------------------------------------------


def _logit(x: float, lo: float, hi: float) -> float:
    s = (x - lo) / (hi - lo)
    s = min(max(s, 1e-6), 1 - 1e-6)
    return float(np.log(s / (1 - s)))


def to_params(alpha: float, beta: float, clip: float) -> jax.Array:
    """Unconstrained parameters ``(3,)``: logits of alpha, beta in :data:`ALPHA_RANGE` and of
    the clip in :data:`CLIP_RANGE` (values outside are clamped into the open range)."""
    return jnp.asarray([_logit(alpha, *ALPHA_RANGE), _logit(beta, *ALPHA_RANGE), _logit(clip, *CLIP_RANGE)])


def from_params(params: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(alpha, beta, clip)`` of unconstrained ``params`` ``(3,)`` (inverse of :func:`to_params`)."""
    lo, hi = ALPHA_RANGE
    c0, c1 = CLIP_RANGE
    s = jax.nn.sigmoid(params)
    return lo + (hi - lo) * s[0], lo + (hi - lo) * s[1], c0 + (c1 - c0) * s[2]


# --- input checks -------------------------------------------------------------------------------


def _check_frames(frames: Any, name: str = "frames", min_count: int = 1) -> np.ndarray:
    """``(N, H, W)`` grey frames as a numpy array (uint8, or float in [0, 1]); raises
    :class:`InputFormatError` on anything else."""
    if isinstance(frames, jax.core.Tracer):
        raise InputFormatError(f"{name}: pass concrete frames (the parameters are what is traced)")
    try:
        arr = np.asarray(frames)
    except Exception as exc:  # ragged lists and the like
        raise InputFormatError(f"{name}: not an array ({exc})") from exc
    if arr.ndim != 3:
        raise InputFormatError(f"{name}: expected grey frames (N, H, W), got shape {arr.shape}")
    if arr.shape[0] < min_count:
        raise InputFormatError(f"{name}: need at least {min_count} frame(s), got {arr.shape[0]}")
    if min(arr.shape[1:]) < 32:
        raise InputFormatError(f"{name}: frames must be at least 32x32, got {arr.shape[1]}x{arr.shape[2]}")
    if arr.dtype == np.uint8:
        return arr
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputFormatError(f"{name}: dtype must be uint8 or floating point in [0, 1], got {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise InputFormatError(f"{name}: contains NaN or infinite values")
    return arr


# --- the soft detector --------------------------------------------------------------------------


@functools.lru_cache(maxsize=16)
def _plan(h: int, w: int, n_octaves: int) -> tuple[dict, ...]:
    return layer_plan(h, w, n_octaves, 3)


def _box_response(S: jax.Array, boxes, step: int, ni: int, nj: int) -> jax.Array:
    """SURF's weighted box sums (``calcHaarPattern``) on a strided grid of float integral
    images ``S`` ``(B, H+1, W+1)`` → ``(B, ni, nj)``. Boxes sharing rows share one strided
    row difference (fewer full-size slices in the backward pass)."""
    acc = jnp.zeros((S.shape[0], ni, nj), S.dtype)
    rows: dict[tuple[int, int], jax.Array] = {}
    for x1, y1, x2, y2, wgt in boxes:
        if (y1, y2) not in rows:
            top = S[:, y1 : y1 + step * (ni - 1) + 1 : step]
            rows[(y1, y2)] = S[:, y2 : y2 + step * (ni - 1) + 1 : step] - top
        r = rows[(y1, y2)]
        box = r[:, :, x2 : x2 + step * (nj - 1) + 1 : step] - r[:, :, x1 : x1 + step * (nj - 1) + 1 : step]
        acc = acc + float(wgt) * box
    return acc


def _shift_max(a: jax.Array, axis: int, centre: bool) -> jax.Array:
    """Maximum over the neighbours at offsets -1, +1 (and 0 if ``centre``) along ``axis``,
    -inf outside. Separable slices: far cheaper to differentiate than a window reduction."""
    pad = [(0, 0)] * a.ndim
    pad[axis] = (1, 1)
    p = jnp.pad(a, pad, constant_values=-jnp.inf)
    n = a.shape[axis]
    lo = jax.lax.slice_in_dim(p, 0, n, axis=axis)
    hi = jax.lax.slice_in_dim(p, 2, n + 2, axis=axis)
    return jnp.maximum(jnp.maximum(lo, hi), a) if centre else jnp.maximum(lo, hi)


def _max3x3(a: jax.Array) -> jax.Array:
    """3x3 maximum over the last two axes (centre included), -inf outside."""
    return _shift_max(_shift_max(a, -1, True), -2, True)


def _max8(a: jax.Array) -> jax.Array:
    """Maximum of the 8 spatial neighbours (last two axes, centre excluded), -inf outside."""
    return jnp.maximum(_shift_max(_shift_max(a, -1, True), -2, False), _shift_max(a, -1, False))


def soft_keypoints(
    images: jax.Array, hessian_threshold: float = 100.0, n_octaves: int = 2, temperature: float = 0.1
) -> list[jax.Array]:
    """Soft SURF keypoint maps of float images ``(B, H, W)`` in 8-bit units: one map
    ``(B, rows, cols)`` per detection layer (octave-major, 3 layers per octave), each in
    [0, 1]. The response is SURF's box-filter ``det(H) = Dxx Dyy − 0.81 Dxy²`` (same boxes,
    sizes and strides as :mod:`jaxslam.vision._surf`), compressed as ``l = asinh(det / T)``
    (log-like, sign-keeping); a keypoint is soft-on where ``l`` exceeds ``asinh(1)`` (the
    threshold) and exceeds the maximum of its 26 scale-space neighbours, each by a sigmoid
    of width ``temperature``. Pixels where the filter does not fit count as off."""
    b, h, w = images.shape
    S = jnp.pad(jnp.cumsum(jnp.cumsum(images, axis=-2), axis=-1), ((0, 0), (1, 0), (1, 0)))
    plan = _plan(h, w, n_octaves)
    per = len(plan) // n_octaves
    t = float(hessian_threshold)
    out = []
    for o in range(n_octaves):
        layers = []
        for lp in plan[o * per : (o + 1) * per]:
            rows, cols, m = lp["rows"], lp["cols"], lp["margin"]
            if not lp["computed"]:
                layers.append(jnp.full((b, rows, cols), -jnp.inf))
                continue
            args = (lp["step"], lp["ni"], lp["nj"])
            dxx = _box_response(S, lp["dx"], *args)
            dyy = _box_response(S, lp["dy"], *args)
            dxy = _box_response(S, lp["dxy"], *args)
            ell = jnp.arcsinh((dxx * dyy - 0.81 * dxy * dxy) / t)
            pad = ((0, 0), (m, rows - m - lp["ni"]), (m, cols - m - lp["nj"]))
            layers.append(jnp.pad(ell, pad, constant_values=-jnp.inf))
        m3 = [_max3x3(x) for x in layers]
        for k in range(1, per - 1):
            nb = jnp.maximum(_max8(layers[k]), jnp.maximum(m3[k - 1], m3[k + 1]))
            ell = layers[k]
            ok = jnp.isfinite(ell) & jnp.isfinite(nb)
            e = jnp.where(ok, ell, 0.0)
            n = jnp.where(ok, nb, 0.0)
            q = jax.nn.sigmoid((e - np.arcsinh(1.0)) / temperature) * jax.nn.sigmoid((e - n) / temperature)
            out.append(jnp.where(ok, q, 0.0))
    return out


def _cell_sums(q: jax.Array, grid: tuple[int, int]) -> jax.Array:
    """Sums of ``q`` ``(B, h, w)`` over a ``grid`` of cells (edge rows/columns cropped) → ``(B, gy, gx)``."""
    gy, gx = grid
    b, h, w = q.shape
    ch, cw = h // gy, w // gx
    return q[:, : ch * gy, : cw * gx].reshape(b, gy, ch, gx, cw).sum(axis=(2, 4))


# --- the objective ------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ProxyWeights:
    """Weights and scales of :func:`enhancement_objective`'s terms."""

    count_scale: float = 100.0
    """Repeatable keypoints per pair at which the log-count term has gained log(2)."""
    spread: float = 0.5
    """Weight of the spread entropy (normalised to [0, 1])."""
    noise: float = 0.035
    """Weight per grey level of amplified-noise standard deviation. Calibrated once on the
    training seeds of ``benchmarks/tune_enhance.py`` (10, 11, "uneven") so that the proxy's
    minimum over a grid of (alpha, beta, clip) sits where the discrete pipeline's mean inlier
    count peaks there (clip ~2); never on held-out frames."""
    temperature: float = 0.1
    """Width of the soft threshold and soft non-maximum suppression (in asinh units)."""
    grid: tuple[int, int] = (4, 4)
    """Cells (rows, columns) of the spread entropy."""


def _objective_terms(
    params: jax.Array,
    frames_a: jax.Array,
    frames_b: jax.Array,
    hessian_threshold: float,
    tile_grid: tuple[int, int],
    n_octaves: int,
    weights: ProxyWeights,
) -> dict[str, jax.Array]:
    alpha, beta, clip = from_params(params)
    n = frames_a.shape[0]
    both = jnp.concatenate([frames_a, frames_b], axis=0)
    e = 255.0 * aba_clahe(both, alpha, beta, clip, tile_grid, mode="soft")
    ea, eb = e[:n], e[n:]
    maps = soft_keypoints(e, hessian_threshold, n_octaves, weights.temperature)
    rep = jnp.zeros((n,))
    count = jnp.zeros((n,))
    cells = jnp.zeros((n, *weights.grid))
    for q in maps:
        qa, qb = q[:n], q[n:]
        ra = qa * _max3x3(qb)  # a keypoint of view a found again (within one sample) in view b
        rb = qb * _max3x3(qa)
        rep = rep + 0.5 * jnp.sum(ra + rb, axis=(-2, -1))
        count = count + 0.5 * jnp.sum(qa + qb, axis=(-2, -1))
        cells = cells + 0.5 * _cell_sums(ra + rb, weights.grid)
    p = cells.reshape(n, -1) / (jnp.sum(cells.reshape(n, -1), axis=-1, keepdims=True) + 1e-9)
    entropy = -jnp.sum(p * jnp.log(p + 1e-12), axis=-1) / np.log(p.shape[-1])
    noise = jnp.sqrt(0.5 * jnp.mean((ea - eb) ** 2) + 1e-12)
    gain = jnp.mean(jnp.log1p(rep / weights.count_scale))
    value = -gain - weights.spread * jnp.mean(entropy) + weights.noise * noise
    return {
        "value": value,
        "repeatable": jnp.mean(rep),
        "count": jnp.mean(count),
        "entropy": jnp.mean(entropy),
        "noise": noise,
    }


@functools.partial(jax.jit, static_argnames=("hessian_threshold", "tile_grid", "n_octaves", "weights"))
def _objective_jit(params, frames_a, frames_b, hessian_threshold, tile_grid, n_octaves, weights):
    return _objective_terms(params, frames_a, frames_b, hessian_threshold, tile_grid, n_octaves, weights)


@functools.partial(jax.jit, static_argnames=("hessian_threshold", "tile_grid", "n_octaves", "weights"))
def _value_and_grad_jit(params, frames_a, frames_b, hessian_threshold, tile_grid, n_octaves, weights):
    def value(p):
        return _objective_terms(p, frames_a, frames_b, hessian_threshold, tile_grid, n_octaves, weights)["value"]

    return jax.value_and_grad(value)(params)


def _pair_views(frames: Any, twins: Any | None) -> tuple[jax.Array, jax.Array]:
    fa = _check_frames(frames, "frames", 1 if twins is not None else 2)
    if twins is None:
        a, b = fa[:-1], fa[1:]
    else:
        fb = _check_frames(twins, "twins")
        if fb.shape != fa.shape:
            raise InputFormatError(f"twins must have the frames' shape {fa.shape}, got {fb.shape}")
        a, b = fa, fb
    return _as_float(a), _as_float(b)


def _as_float(x: np.ndarray) -> jax.Array:
    if x.dtype == np.uint8:
        return jnp.asarray(x, jnp.float64) / 255.0
    return jnp.clip(jnp.asarray(x, jnp.float64), 0.0, 1.0)


def enhancement_objective(
    params: jax.Array,
    frames: Any,
    twins: Any | None = None,
    *,
    hessian_threshold: float = 100.0,
    tile_grid: tuple[int, int] = (8, 8),
    n_octaves: int = 2,
    weights: ProxyWeights = ProxyWeights(),
    terms: bool = False,
) -> jax.Array | dict[str, jax.Array]:
    """Smooth front-end objective (lower is better) of unconstrained ``params`` ``(3,)`` (see
    :func:`to_params`) on grey ``frames`` ``(N, H, W)`` (uint8, or float in [0, 1]).

    The views compared are ``(frames, twins)`` — ``twins`` the same views under an independent
    sensor-noise realisation (simulation; or two exposures of a still camera) — or, without
    ``twins``, consecutive frames ``(k, k+1)`` (small motion: a keypoint that moved more than
    one sample does not count as repeated). With ``R`` the soft repeatable count per pair,
    ``H`` the normalised entropy of where the repeatable keypoints lie and ``sigma`` the
    standard deviation (grey levels) of ``E_a − E_b`` over ``sqrt 2``::

        J = −mean log(1 + R / count_scale) − spread · mean H + noise · sigma

    * ``R`` (soft SURF keypoints of one view that reappear in the other): the discrete
      pipeline registers a pair when enough *repeatable* keypoints match; brightening and
      equalising create keypoints in dark areas, while keypoints created by amplified noise
      mostly do not reappear under new noise. The log saturates: the pipeline needs tens of
      inliers, not thousands.
    * ``H``: an essential matrix from keypoints clustered in one bright patch is poorly
      conditioned and RANSAC's inliers there are unreliable; keypoints over the whole image
      (dark gaps included) constrain it.
    * ``sigma``: a fidelity term. ``R`` alone keeps growing with the clip limit past the
      discrete pipeline's optimum (at a one-sample tolerance some noise keypoints do
      repeat, and neither descriptor noise nor the pipeline's cap on keypoints, which lets
      noise keypoints displace good ones, is modelled); ``sigma`` charges for the amplified
      sensor noise that causes both (weight: :class:`ProxyWeights`).

    Limits: without ``twins`` the difference ``E_a − E_b`` includes motion, so ``sigma``
    over-charges contrast; and the objective is meant for whole frames — on small crops the
    CLAHE tiles and the global mean ``V_mid`` of eq. (1) change, and it can prefer darkening
    where the whole frame prefers brightening.

    Differentiable in ``params`` in reverse mode (``jax.grad``, ``jax.value_and_grad``; a
    ``custom_vjp`` runs one jitted value-and-gradient program; the frames are constants);
    usable under ``jax.jit``. ``terms=True`` returns every term in a dict (``value``,
    ``repeatable``, ``count``, ``entropy``, ``noise``), differentiable by plain autodiff."""
    a, b = _pair_views(frames, twins)
    static = (float(hessian_threshold), tuple(tile_grid), int(n_octaves), weights)
    p = jnp.asarray(params, jnp.float64)
    if terms:
        return _objective_jit(p, a, b, *static)

    # reverse mode through one jitted value-and-gradient program (fused, far less memory than
    # differentiating the jitted forward from outside; shared with tune_enhancement)
    @jax.custom_vjp
    def value(q):
        return _objective_jit(q, a, b, *static)["value"]

    def value_fwd(q):
        return _value_and_grad_jit(q, a, b, *static)

    def value_bwd(g, ct):
        return (ct * g,)

    value.defvjp(value_fwd, value_bwd)
    return value(p)


# --- the optimiser ------------------------------------------------------------------------------


@dataclasses.dataclass
class EnhancementResult:
    """Output of :func:`tune_enhancement`."""

    alpha: float
    beta: float
    clip: float
    history: list[float]
    """Objective value per step (before each update), then the final value."""
    path: list[tuple[float, float, float]]
    """``(alpha, beta, clip)`` per step, then the final one."""
    seconds: float
    """Wall time of the tuning (compilation included)."""


def tune_enhancement(
    frames: Any,
    alpha: float = 0.25,
    beta: float = 0.4,
    clip: float = 2.0,
    *,
    twins: Any | None = None,
    steps: int = 30,
    lr: float = 0.15,
    hessian_threshold: float = 100.0,
    tile_grid: tuple[int, int] = (8, 8),
    weights: ProxyWeights = ProxyWeights(),
    progress: Callable[[int, int, float], None] | None = None,
) -> EnhancementResult:
    """Minimise :func:`enhancement_objective` over ``(alpha, beta, clip)`` from the given start
    with Adam (``lr`` in logit units per step; Kingma & Ba defaults otherwise) for ``steps``
    steps; returns the best iterate seen. ``progress(step, steps, value)`` is called per step."""
    if steps < 0 or not lr > 0:
        raise ConfigError(f"steps must be >= 0 and lr > 0, got steps={steps}, lr={lr}")
    t0 = time.perf_counter()
    a, b = _pair_views(frames, twins)
    static = (float(hessian_threshold), tuple(tile_grid), 2, weights)

    def value_and_grad(p: jax.Array) -> tuple[jax.Array, jax.Array]:
        return _value_and_grad_jit(p, a, b, *static)  # the program jax.grad(enhancement_objective) runs

    p = to_params(alpha, beta, clip)
    m = jnp.zeros_like(p)
    v = jnp.zeros_like(p)
    b1, b2, eps = 0.9, 0.999, 1e-8
    history: list[float] = []
    path: list[tuple[float, float, float]] = []
    best = (np.inf, p)
    for k in range(steps + 1):
        val, g = value_and_grad(p)
        val_f = float(val)
        history.append(val_f)
        al, be, cl = from_params(p)
        path.append((float(al), float(be), float(cl)))
        if val_f < best[0]:
            best = (val_f, p)
        if progress is not None:
            progress(k, steps, val_f)
        if k == steps or not bool(jnp.all(jnp.isfinite(g))):
            break
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        p = p - lr * (m / (1 - b1 ** (k + 1))) / (jnp.sqrt(v / (1 - b2 ** (k + 1))) + eps)
    al, be, cl = from_params(best[1])
    return EnhancementResult(float(al), float(be), float(cl), history, path, time.perf_counter() - t0)


# --- the discrete end-to-end check --------------------------------------------------------------


def _undistort(uv: np.ndarray, K: np.ndarray, dist: tuple[float, ...] | None) -> np.ndarray:
    from ..pipeline._visual import undistort_normalized

    return undistort_normalized(uv, K, tuple(dist or (0.0, 0.0, 0.0, 0.0)))


def _rotation_error_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    c = (np.trace(R_est @ R_true.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def evaluate_registration(
    frames: Any,
    poses: np.ndarray | None,
    K: np.ndarray,
    alpha: float,
    beta: float,
    clip: float,
    *,
    distortion: tuple[float, ...] | None = None,
    hessian_threshold: float = 100.0,
    max_keypoints: int = 1000,
    ratio: float = 0.8,
    ransac_threshold_px: float = 1.0,
    min_inliers: int = 25,
    tile_grid: tuple[int, int] = (8, 8),
) -> dict[str, Any]:
    """The real discrete front end on consecutive pairs of ``frames`` ``(N, H, W)`` uint8: hard
    ABA-CLAHE → SURF → ratio-test + cross-check + Laplacian-sign matching → essential-matrix
    RANSAC (the settings of :class:`jaxslam.pipeline.VisionConfig`). ``poses``: world-from-
    camera rotations ``(N, 3, 3)`` or poses ``(N, 4, 4)`` for the rotation error, or None.

    Returns ``pairs``, ``registered`` (pairs with ``>= min_inliers`` RANSAC inliers),
    ``mean_inliers`` and ``mean_matches`` (over all pairs; 0 for a pair that fails),
    ``mean_keypoints``, ``sampson_px`` (median over registered pairs of the inliers' RMS
    Sampson distance, pixels), ``rot_err_deg`` (median over registered pairs of the relative
    rotation error, degrees; NaN without poses) and ``per_pair`` inlier counts."""
    f = _check_frames(frames, "frames", 2)
    if f.dtype != np.uint8:
        f = np.clip(np.rint(f * 255.0), 0, 255).astype(np.uint8)
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3):
        raise InputFormatError(f"K must be a 3x3 camera matrix, got shape {K.shape}")
    rots = None
    if poses is not None:
        P = np.asarray(poses, np.float64)
        if P.shape not in ((len(f), 3, 3), (len(f), 4, 4)):
            raise InputFormatError(f"poses must be ({len(f)}, 3, 3) or ({len(f)}, 4, 4), got {P.shape}")
        rots = P[:, :3, :3]
    enhanced = np.asarray(aba_clahe(f, float(alpha), float(beta), float(clip), tile_grid))
    feats = []
    for img in enhanced:
        kp, desc = detect_and_describe(img, "surf", hessian_threshold, max_keypoints)
        feats.append((kp, desc, _undistort(kp[:, :2], K, distortion)))
    focal = 0.5 * (K[0, 0] + K[1, 1])
    inliers, matches, sampson, rot_err = [], [], [], []
    for (ka, da, xa), (kb, db, xb), k in zip(feats[:-1], feats[1:], range(len(f) - 1)):
        n_in, n_m = 0, 0
        if len(ka) >= 8 and len(kb) >= 8:
            pairs, _ = match_descriptors(da, db, ratio=ratio, cross_check=True, sign1=ka[:, 6], sign2=kb[:, 6])
            n_m = len(pairs)
            if n_m >= 8:
                res = find_essential(xa[pairs[:, 0]], xb[pairs[:, 1]], ransac_threshold_px / focal)
                keep = np.asarray(res.inliers)
                n_in = int(keep.sum())
                if n_in >= min_inliers:
                    ia, ib = pairs[keep, 0], pairs[keep, 1]
                    e2 = np.asarray(sampson_error(res.E, jnp.asarray(xa[ia]), jnp.asarray(xb[ib])))
                    sampson.append(float(np.sqrt(np.mean(e2))) * focal)
                    if rots is not None:
                        R_true = rots[k + 1].T @ rots[k]  # camera k+1 from camera k
                        rot_err.append(_rotation_error_deg(np.asarray(res.R), R_true))
        inliers.append(n_in)
        matches.append(n_m)
    inl = np.asarray(inliers)
    return {
        "pairs": len(inl),
        "registered": int(np.sum(inl >= min_inliers)),
        "mean_inliers": float(inl.mean()),
        "mean_matches": float(np.mean(matches)),
        "mean_keypoints": float(np.mean([len(x[0]) for x in feats])),
        "sampson_px": float(np.median(sampson)) if sampson else float("nan"),
        "rot_err_deg": float(np.median(rot_err)) if rot_err else float("nan"),
        "per_pair": [int(x) for x in inl],
    }


# --- simulated frames ---------------------------------------------------------------------------


@dataclasses.dataclass
class FrameSet:
    """Consecutive simulated camera frames with ground truth (see :func:`simulate_frames`)."""

    frames: np.ndarray
    """(N, H, W) uint8."""
    twins: np.ndarray | None
    """(N, H, W) uint8: the same views and exposure, an independent sensor-noise realisation."""
    poses: np.ndarray
    """(N, 4, 4) world-from-camera."""
    K: np.ndarray
    distortion: tuple[float, ...]
    times: np.ndarray
    seed: int
    lighting: str


def simulate_frames(
    seed: int,
    lighting: str = "uneven",
    starts: float | tuple[float, ...] = 20.0,
    count: int = 10,
    *,
    twins: bool = True,
    warmup: int = 5,
) -> list[FrameSet]:
    """Render, per start time in ``starts`` (seconds into the simulated run of
    :class:`jaxslam.sim.Simulation` with ``seed`` and the ``lighting`` preset), ``count``
    consecutive frames at the camera rate, after ``warmup`` frames that let the auto-exposure
    settle; with ``twins`` each view is rendered a second time at the same exposure (new
    sensor noise). One :class:`FrameSet` per start (the world is built once)."""
    from ..sim import LightingConfig, SimConfig, Simulation

    if count < 1 or warmup < 0:
        raise ConfigError(f"count must be >= 1 and warmup >= 0, got {count}, {warmup}")
    sim = Simulation.create(SimConfig(seed=seed, lighting=LightingConfig(mode=lighting)))
    starts_t = (float(starts),) if isinstance(starts, int | float) else tuple(float(s) for s in starts)
    return [_render_stretch(sim, s, count, twins, warmup) for s in starts_t]


def _render_stretch(sim: Any, start_s: float, count: int, twins: bool, warmup: int) -> FrameSet:
    seed, lighting = sim.config.seed, sim.config.lighting.mode
    sim.camera.exposure_gain = None
    rate = sim.config.camera.rate
    t = start_s + (np.arange(-warmup, count)) / rate
    if t[0] < 0 or t[-1] > sim.trajectory.duration:
        raise ConfigError(f"frames {t[0]:.1f}..{t[-1]:.1f} s fall outside the run (0..{sim.trajectory.duration:.1f} s)")
    st = sim.trajectory.state(t)
    cam = sim.camera
    frames, twin_frames, poses = [], [], []
    for k in range(len(t)):
        args = (float(t[k]), st["R"][k], st["p"][k], st["v"][k], st["omega"][k])
        eg = cam.exposure_gain
        img, _ = cam.render(*args)
        if k < warmup:
            continue
        frames.append(img)
        if twins:
            after = cam.exposure_gain
            cam.exposure_gain = eg
            twin_frames.append(cam.render(*args)[0])
            cam.exposure_gain = after
        R_wc, p_wc = cam.pose(st["R"][k], st["p"][k])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_wc, p_wc
        poses.append(T)
    fx, fy, cx, cy = cam.K
    return FrameSet(
        np.stack(frames),
        np.stack(twin_frames) if twins else None,
        np.stack(poses),
        np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
        tuple(float(d) for d in sim.config.camera.distortion),
        t[warmup:],
        seed,
        lighting,
    )
