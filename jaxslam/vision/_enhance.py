"""Low-light image enhancement: ABA-CLAHE (SPEC §3.1, eq. 1–2), CLAHE, global histogram
equalisation and gamma, as batched JAX array ops.

Image layout: grey ``(*batch, H, W)`` or RGB ``(*batch, H, W, 3)`` (``color=None`` takes
a last axis of size 3 on an array of rank >= 3 as colour). Values: ``uint8`` in
``[0, 255]`` or floating point in ``[0, 1]`` (clipped). Outputs keep the input's kind:
uint8 in → uint8 out (hard mode), float in → float in ``[0, 1]`` out. The soft
(differentiable) mode always returns float.

ABA (adaptive brightness adjustment) on the value channel ``V = max(R, G, B)``::

    V_mid   = mean over the pixels of V                              (1)
    V'(x,y) = V_mid * V(x,y)^alpha + (1 - V_mid) * V(x,y)^beta       (2)

then ``V'' = CLAHE(V')`` and colour is rebuilt as ``RGB * V'' / V`` (equal to the HSV
round trip, as H and S are unchanged; a black pixel becomes grey ``V''``).
Reference: the tunnel-mapping article restated in SPEC §3.1; Zuiderveld (1994) for CLAHE.
"""

from __future__ import annotations

import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from ._clahe import clahe_hard_u8, clahe_soft_levels, materialise

Mode = Literal["hard", "soft"]


def _prepare(image, color: bool | None, name: str = "image") -> tuple[jax.Array | np.ndarray, bool, bool]:
    """Check an image (batch) and return ``(array, is_u8, is_color)``; raise ``ValueError``
    on an unusable one. Concrete float inputs with NaN/inf are refused; traced ones are
    sanitised in the graph (NaN → 0, clip to [0, 1])."""
    arr: jax.Array | np.ndarray
    if isinstance(image, jax.Array):
        arr = image
    else:
        try:
            arr = np.asarray(image)
        except Exception as exc:  # ragged lists and the like
            raise ValueError(f"{name}: not an array ({exc})") from exc
    dt = np.dtype(arr.dtype)
    if dt == np.uint8:
        is_u8 = True
    elif np.issubdtype(dt, np.floating):
        is_u8 = False
    else:
        raise ValueError(f"{name}: dtype must be uint8 (0..255) or floating point (0..1), got {dt}")
    shape = tuple(arr.shape)
    if len(shape) < 2:
        raise ValueError(f"{name}: expected (*batch, H, W) or (*batch, H, W, 3), got shape {shape}")
    if color is None:
        color = len(shape) >= 3 and shape[-1] == 3
    if color and (len(shape) < 3 or shape[-1] != 3):
        raise ValueError(f"{name}: a colour image needs shape (*batch, H, W, 3), got {shape}")
    hw = shape[-3:-1] if color else shape[-2:]
    if min(hw) == 0:
        raise ValueError(f"{name}: empty image of size {hw[0]}x{hw[1]}")
    if not is_u8 and not isinstance(arr, jax.core.Tracer) and not _all_finite(arr):
        raise ValueError(f"{name}: contains NaN or infinite values")
    # numpy arrays go to the jitted functions as they are (their own transfer is faster
    # than jnp.asarray's, and a jax.Array needs no conversion at all)
    return arr, is_u8, bool(color)


def _all_finite(arr) -> bool:
    if isinstance(arr, np.ndarray):
        return bool(np.all(np.isfinite(arr)))
    with jax.ensure_compile_time_eval():
        return bool(jnp.all(jnp.isfinite(arr)))


def _sanitize(x: jax.Array) -> jax.Array:
    """Float images inside the graph: NaN → 0, clip to [0, 1] (traced input is not checked)."""
    return jnp.clip(jnp.where(jnp.isnan(x), 0.0, x), 0.0, 1.0)


def _flat(x: jax.Array, color: bool) -> tuple[jax.Array, tuple[int, ...]]:
    """Collapse the batch axes: ``(B, H, W[, 3])`` and the original batch shape."""
    core = 3 if color else 2
    batch = x.shape[: x.ndim - core]
    return x.reshape((-1, *x.shape[x.ndim - core :])), batch


def aba_curve(v: jax.Array, v_mid: jax.Array | float, alpha, beta) -> jax.Array:
    """Eq. (2): ``V_mid * V^alpha + (1 - V_mid) * V^beta``, NaN-free at ``V = 0`` in value
    and gradient (double ``where``: the power is taken of 1 where ``V = 0``)."""
    pos = v > 0
    vs = jnp.where(pos, v, 1.0)
    return jnp.where(pos, v_mid * vs**alpha + (1 - v_mid) * vs**beta, 0.0)


def _recolor(rgb: jax.Array, v: jax.Array, v_new: jax.Array) -> jax.Array:
    """``RGB * V'' / V`` with a black pixel (V = 0) mapped to grey ``V''``; all in [0, 1]."""
    pos = v > 0
    ratio = v_new / jnp.where(pos, v, 1.0)
    return jnp.where(pos[..., None], rgb * ratio[..., None], v_new[..., None])


def _aba_clahe_u8(img, alpha, beta, clip_limit, tile_grid):
    """Hard ABA-CLAHE of uint8 grey ``(B, H, W)`` or RGB ``(B, H, W, 3)``: eq. (2) is a 256-entry
    table per image (exact for 8-bit input), then OpenCV CLAHE on the quantised V'."""
    color = img.ndim == 4
    v8 = jnp.max(img, axis=-1) if color else img
    levels = jnp.arange(256, dtype=jnp.float32)

    def curve(hist):  # eq. (1) from the image histogram, eq. (2) as a 256-entry table
        v_mid = jnp.sum(hist * levels[None, :], axis=-1, keepdims=True) / (255.0 * v8.shape[-1] * v8.shape[-2])
        table = aba_curve(levels[None, :] / 255.0, v_mid, alpha, beta)
        return jnp.clip(jnp.round(table * 255.0), 0, 255).astype(jnp.uint8)

    out = clahe_hard_u8(v8, clip_limit, tile_grid, table=curve)
    return _recolor_u8(img, v8, out) if color else out


def _recolor_u8(img, v8, out):
    rgb = _recolor(img.astype(jnp.float32), v8.astype(jnp.float32), out.astype(jnp.float32))
    return jnp.clip(jnp.round(rgb), 0, 255).astype(jnp.uint8)


def _clahe_float(v, clip, clip_limit, tile_grid, mode):
    if mode == "soft":
        return clahe_soft_levels(255.0 * v, clip, tile_grid) / 255.0
    q = jnp.clip(jnp.round(v * 255.0), 0, 255).astype(jnp.uint8)
    return clahe_hard_u8(q, clip_limit, tile_grid).astype(v.dtype) / 255.0


def _to_float(flat):
    return flat.astype(jnp.float64) / 255.0 if flat.dtype == jnp.uint8 else _sanitize(flat)


@functools.partial(jax.jit, static_argnames=("clip_limit", "tile_grid", "mode", "color"))
def _aba_clahe_jit(img, alpha, beta, clip, clip_limit, tile_grid, mode, color):
    flat, _ = _flat(img, color)
    if img.dtype == jnp.uint8 and mode == "hard":
        return _aba_clahe_u8(flat, alpha, beta, clip_limit, tile_grid).reshape(img.shape)
    f = _to_float(flat)
    v = jnp.max(f, axis=-1) if color else f
    v_mid = jnp.mean(v, axis=(-2, -1), keepdims=True)
    v_new = _clahe_float(aba_curve(v, v_mid, alpha, beta), clip, clip_limit, tile_grid, mode)
    return (_recolor(f, v, v_new) if color else v_new).reshape(img.shape)


def _check_options(clip_limit, tile_grid, mode) -> tuple[int, int]:
    if mode not in ("hard", "soft"):
        raise ValueError(f"mode must be 'hard' or 'soft', got {mode!r}")
    try:
        gy, gx = (int(t) for t in tile_grid)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"tile_grid must be two positive integers, got {tile_grid!r}") from exc
    if gy < 1 or gx < 1:
        raise ValueError(f"tile_grid must be two positive integers, got {tile_grid!r}")
    if mode == "hard" and not (isinstance(clip_limit, int | float) and np.isfinite(clip_limit) and clip_limit >= 0):
        raise ValueError(f"clip_limit must be a finite number >= 0 in hard mode, got {clip_limit!r}")
    return gy, gx


def _empty(img: jax.Array | np.ndarray, color: bool, mode: str) -> bool:
    return int(np.prod(img.shape[: img.ndim - (3 if color else 2)])) == 0


def aba_clahe(
    image,
    alpha=0.25,
    beta=0.4,
    clip_limit=2.0,
    tile_grid: tuple[int, int] = (8, 8),
    *,
    mode: Mode = "hard",
    color: bool | None = None,
) -> jax.Array:
    """ABA-CLAHE (SPEC eq. 1–2): brightness curve on V, CLAHE on V', colour rebuilt.

    ``mode="hard"``: CLAHE with OpenCV's semantics (integer clip, 8-bit LUTs); ``clip_limit``
    must then be a Python number; uint8 input gives uint8 output. ``mode="soft"``:
    differentiable in ``alpha``, ``beta``, ``clip_limit`` (traced) and the image (see
    :mod:`jaxslam.vision._clahe`); float output in [0, 1].
    """
    img, _, color = _prepare(image, color)
    grid = _check_options(clip_limit, tile_grid, mode)
    if _empty(img, color, mode):
        return jnp.zeros(img.shape, img.dtype if mode == "hard" else jnp.float64)
    static_clip = float(clip_limit) if mode == "hard" else 0.0
    return _aba_clahe_jit(img, alpha, beta, clip_limit, static_clip, grid, mode, color)


@functools.partial(jax.jit, static_argnames=("clip_limit", "tile_grid", "mode", "color"))
def _clahe_jit(img, clip, clip_limit, tile_grid, mode, color):
    flat, _ = _flat(img, color)
    if img.dtype == jnp.uint8 and mode == "hard":
        v8 = jnp.max(flat, axis=-1) if color else flat
        out = clahe_hard_u8(v8, clip_limit, tile_grid)
        return (_recolor_u8(flat, v8, out) if color else out).reshape(img.shape)
    f = _to_float(flat)
    v = jnp.max(f, axis=-1) if color else f
    v_new = _clahe_float(v, clip, clip_limit, tile_grid, mode)
    return (_recolor(f, v, v_new) if color else v_new).reshape(img.shape)


def clahe(
    image,
    clip_limit=2.0,
    tile_grid: tuple[int, int] = (8, 8),
    *,
    mode: Mode = "hard",
    color: bool | None = None,
) -> jax.Array:
    """Plain CLAHE of grey images, or of V of RGB images (colour rebuilt as ``RGB * V''/V``).

    Hard mode on uint8 grey input equals ``cv2.createCLAHE(clip_limit, tile_grid[::-1])
    .apply(image)`` (within ±1 grey level on float32 rounding ties). ``tile_grid`` is
    (rows, columns).
    """
    img, _, color = _prepare(image, color)
    grid = _check_options(clip_limit, tile_grid, mode)
    if _empty(img, color, mode):
        return jnp.zeros(img.shape, img.dtype if mode == "hard" else jnp.float64)
    static_clip = float(clip_limit) if mode == "hard" else 0.0
    return _clahe_jit(img, clip_limit, static_clip, grid, mode, color)


@jax.jit
def _equalize_u8(v8: jax.Array) -> jax.Array:
    b = v8.shape[0]
    flat = v8.reshape(b, -1).astype(jnp.int32)
    total = flat.shape[1]
    hist = jax.vmap(lambda r: jnp.bincount(r, length=256))(flat)
    first = jnp.argmax(hist > 0, axis=-1)
    h0 = jnp.take_along_axis(hist, first[:, None], axis=1)
    cdf = jnp.cumsum(hist, axis=-1)
    scale = np.float32(255.0) / jnp.maximum(total - h0, 1).astype(jnp.float32)
    lut = jnp.clip(jnp.round((cdf - h0).astype(jnp.float32) * scale), 0, 255)
    lut = materialise(jnp.where(h0 == total, first[:, None].astype(jnp.float32), lut).astype(jnp.uint8))
    return jnp.take_along_axis(lut, flat, axis=1).reshape(v8.shape)


def equalize_hist(image, *, color: bool | None = None) -> jax.Array:
    """Global histogram equalisation (OpenCV ``equalizeHist`` semantics) of grey images or V.

    ``lut[k] = round(255 * (cdf[k] - h[k0]) / (N - h[k0]))`` with ``k0`` the darkest level
    present; a constant image is returned unchanged. Float input is quantised to 8 bits.
    """
    img, _, color = _prepare(image, color)
    if _empty(img, color, "hard"):
        return jnp.zeros(img.shape, img.dtype)
    return _equalize_jit(img, color)


@functools.partial(jax.jit, static_argnames=("color",))
def _equalize_jit(img, color):
    flat, _ = _flat(img, color)
    is_u8 = img.dtype == jnp.uint8
    u8 = flat if is_u8 else jnp.clip(jnp.round(_sanitize(flat) * 255.0), 0, 255).astype(jnp.uint8)
    v8 = jnp.max(u8, axis=-1) if color else u8
    out = _equalize_u8(v8).astype(jnp.float32)
    if color:
        out = _recolor(u8.astype(jnp.float32), v8.astype(jnp.float32), out)
    out = out.reshape(img.shape)
    if is_u8:
        return jnp.clip(jnp.round(out), 0, 255).astype(jnp.uint8)
    return (out / 255.0).astype(img.dtype)


def gamma_correct(image, gamma=0.5, *, color: bool | None = None) -> jax.Array:
    """Gamma curve ``out = in^gamma`` on [0, 1] values, per channel (gamma < 1 brightens).

    uint8 input goes through a 256-entry table (rounded). NaN-free at 0.
    """
    img, _, color = _prepare(image, color)
    if not (isinstance(gamma, jax.core.Tracer) or float(gamma) > 0):
        raise ValueError(f"gamma must be > 0, got {gamma!r}")
    return _gamma_jit(img, gamma)


@jax.jit
def _gamma_jit(img, gamma):
    if img.dtype == jnp.uint8:
        table = aba_curve(jnp.arange(256, dtype=jnp.float32) / 255.0, 1.0, gamma, gamma)
        table = jnp.clip(jnp.round(table * 255.0), 0, 255).astype(jnp.uint8)
        return materialise(table)[img.astype(jnp.int32)]
    return aba_curve(_sanitize(img), 1.0, gamma, gamma)
