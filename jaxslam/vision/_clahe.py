"""Contrast-limited adaptive histogram equalisation (CLAHE) as JAX array ops.

Two modes share one tiling and one interpolation:

* **hard** reproduces OpenCV's ``cv2.createCLAHE(clipLimit, tileGridSize).apply(u8)``
  (``modules/imgproc/src/clahe.cpp``): an image whose size is not a multiple of the grid
  is padded at the bottom and right with ``BORDER_REFLECT_101`` by
  ``(gy - H % gy, gx - W % gx)`` (note: a full extra tile row/column of padding when only
  the other side is not a multiple); per tile a 256-bin histogram, clipped at
  ``c = max(1, int(clipLimit * tileArea / 256))``, the excess ``E`` redistributed as
  ``E // 256`` to every bin plus the residual ``E % 256`` to bins ``0, s, 2s, ...`` with
  ``s = max(256 // residual, 1)``; ``lut[k] = round(float32(cumsum(h)[k]) * float32(255 /
  tileArea))``; then bilinear interpolation between the four neighbouring tile LUTs at
  ``t = p / tileSize - 0.5`` (float32, clamped to the grid), rounded half to even.
* **soft** is differentiable in the input levels and the clip limit: each pixel adds a
  triweight kernel ``(1 - (d / 3)^2)^3`` (std 1 grey level, C2) to the bins within 3 grey
  levels (a plain linear binning gives correct but useless, bumpy gradients); the clip is
  ``h_c = c - tau * softplus((c - h) / tau)`` and the excess ``tau * softplus((h - c) / tau)``
  is spread evenly; a pixel at level ``x`` reads its tile LUTs by Catmull-Rom (C1)
  interpolation instead of an integer lookup.

Reference: K. Zuiderveld, "Contrast Limited Adaptive Histogram Equalization", Graphics
Gems IV (1994); OpenCV ``clahe.cpp``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

_BINS = 256
SOFT_RADIUS = 3.0  # triweight half-width in grey levels (std = radius / 3 = 1 grey level)


def _reflect101(i: np.ndarray, n: int) -> np.ndarray:
    """OpenCV ``borderInterpolate(p, n, BORDER_REFLECT_101)`` for indices ``i >= 0``."""
    if n == 1:
        return np.zeros_like(i)
    i = i.copy()
    while True:
        bad = (i < 0) | (i >= n)
        if not bad.any():
            return i
        i = np.where(i < 0, -i, np.where(i >= n, 2 * n - 2 - i, i))


@functools.lru_cache(maxsize=64)
def _geometry(h: int, w: int, gy: int, gx: int):
    """Static tiling of an ``h x w`` image: tile of every pixel, the padded pixels' sources,
    tile size and the float32 interpolation indices and weights (OpenCV's convention)."""
    if h % gy == 0 and w % gx == 0:
        ph = pw = 0
    else:
        ph, pw = gy - h % gy, gx - w % gx
    th, tw = (h + ph) // gy, (w + pw) // gx
    yy, xx = np.mgrid[0 : h + ph, 0 : w + pw]
    tile = (yy // th) * gx + xx // tw
    pad = (yy >= h) | (xx >= w)
    pad_src = (_reflect101(yy[pad], h) * w + _reflect101(xx[pad], w)).astype(np.int32)

    def axis(n: int, size: int, grid: int):
        t = np.arange(n, dtype=np.float32) * (np.float32(1.0) / np.float32(size)) - np.float32(0.5)
        i1 = np.floor(t).astype(np.int32)
        a = (t - i1.astype(np.float32)).astype(np.float32)
        return np.maximum(i1, 0), np.minimum(i1 + 1, grid - 1), a

    ty1, ty2, ya = axis(h, th, gy)
    tx1, tx2, xa = axis(w, tw, gx)
    pairs = [(ty1, tx1), (ty1, tx2), (ty2, tx1), (ty2, tx2)]
    # the packed tables of clahe_hard_u8: one per unclamped top-left neighbour (i, j) in
    # [-1, g - 1]^2, holding the (clamped) tiles (i, j), (i, j + 1), (i + 1, j), (i + 1, j + 1)
    ti = np.floor(np.arange(h, dtype=np.float32) / np.float32(th) - np.float32(0.5)).astype(np.int32)
    tj = np.floor(np.arange(w, dtype=np.float32) / np.float32(tw) - np.float32(0.5)).astype(np.int32)
    vi, vj = np.arange(-1, gy), np.arange(-1, gx)
    quad_tiles = [
        (np.clip(vi + di, 0, gy - 1)[:, None] * gx + np.clip(vj + dj, 0, gx - 1)[None, :]).ravel()
        for di, dj in ((0, 0), (0, 1), (1, 0), (1, 1))
    ]
    return {
        "tile": (tile[None, :h, :w] * _BINS).astype(np.int32),
        "pad_tile": (tile[pad][None] * _BINS).astype(np.int32),
        "pad_src": pad_src,
        "area": th * tw,
        "corners": [((a[None, :, None] * gx + b[None, None, :]) * _BINS).astype(np.int32) for a, b in pairs],
        "ya": ya[None, :, None],
        "xa": xa[None, None, :],
        "quad_tiles": np.stack(quad_tiles).astype(np.int32),  # (4, (gy + 1) * (gx + 1))
        "quad_row": (((ti + 1) * (gx + 1)) * _BINS)[None, :, None].astype(np.int32),
        "quad_col": ((tj + 1) * _BINS)[None, None, :].astype(np.int32),
    }


def _interpolate(read, g: dict, dtype) -> jax.Array:
    """Bilinear blend of the four tile LUTs: ``read(offset)`` reads each pixel's value in the
    LUT of the tile whose flat offset (``tile * 256``, shape ``(H, W)``) is given."""
    xa = jnp.asarray(g["xa"], dtype)
    ya = jnp.asarray(g["ya"], dtype)
    l11, l12, l21, l22 = (read(c) for c in g["corners"])
    return (l11 * (1 - xa) + l12 * xa) * (1 - ya) + (l21 * (1 - xa) + l22 * xa) * ya


def materialise(x: jax.Array) -> jax.Array:
    """``x``, computed once: XLA never fuses a scatter into its consumer, so small tables read
    by per-pixel gathers are not recomputed per pixel."""
    flat = x.reshape(-1)
    i = jnp.arange(flat.size, dtype=jnp.int32)
    return jnp.zeros_like(flat).at[i].set(flat, indices_are_sorted=True, unique_indices=True).reshape(x.shape)


def clahe_hard_u8(
    v: jax.Array,
    clip_limit: float = 2.0,
    tile_grid: tuple[int, int] = (8, 8),
    table: Callable[[jax.Array], jax.Array] | None = None,
) -> jax.Array:
    """OpenCV CLAHE of uint8 grey images ``v``, shape ``(B, H, W)`` → uint8 (equal but for rare
    ±1 differences on float32 rounding ties in the interpolation).

    ``clip_limit`` and ``tile_grid`` are static (they set integer clip counts and shapes).
    With ``table`` (a function of the image histograms ``(B, 256)`` returning a uint8 tone
    curve ``(B, 256)``) the result is ``CLAHE(curve[v])``, computed in the same pass over the
    pixels: the tile histograms of ``v`` are remapped through the curve and the LUTs are read
    at ``curve[v]``.
    """
    b, h, w = v.shape
    gy, gx = tile_grid
    g = _geometry(h, w, gy, gx)
    area = g["area"]
    per = gy * gx * _BINS
    off = jnp.arange(b, dtype=jnp.uint32)[:, None, None] * per
    flat = v.reshape(b, h * w)
    i_body = (off + g["tile"].astype(np.uint32) + v.astype(jnp.uint32)).reshape(-1)
    hist = jnp.zeros(b * per, jnp.int32).at[i_body].add(1, mode="promise_in_bounds")
    curve = None
    if table is not None:
        curve = materialise(table(jnp.sum(hist.reshape(b, gy * gx, _BINS), axis=1)).astype(jnp.int32))
    if g["pad_src"].size:
        i_pad = (off[:, :, 0] + g["pad_tile"].astype(np.uint32) + flat[:, g["pad_src"]].astype(jnp.uint32)).reshape(-1)
        hist = hist.at[i_pad].add(1, mode="promise_in_bounds")
    hist = hist.reshape(b, gy * gx, _BINS)
    if curve is not None:
        tab = jnp.broadcast_to(curve[:, None, :], hist.shape)
        base = jnp.arange(b * gy * gx, dtype=jnp.int32).reshape(b, gy * gx, 1) * _BINS
        hist = jnp.zeros(hist.size, jnp.int32).at[(base + tab).reshape(-1)].add(hist.reshape(-1)).reshape(hist.shape)
    if clip_limit > 0:
        c = max(int(clip_limit * area / _BINS), 1)
        hc = jnp.minimum(hist, c)
        excess = jnp.sum(hist - hc, axis=-1, keepdims=True, dtype=jnp.int32)
        batch = excess // _BINS
        residual = excess - batch * _BINS
        step = jnp.maximum(_BINS // jnp.maximum(residual, 1), 1)
        k = jnp.arange(_BINS, dtype=jnp.int32)[None, None, :]
        hist = hc + batch + ((k % step == 0) & (k // step < residual)).astype(jnp.int32)
    scale = np.float32(_BINS - 1) / np.float32(area)
    lut = jnp.clip(jnp.round(jnp.cumsum(hist, axis=-1).astype(jnp.float32) * scale), 0, 255).astype(jnp.uint32)
    lut = materialise(lut)  # read four times below: not recomputed (with its prefix sum)
    # The four neighbouring tiles' LUT values of every level packed in one word, so that a
    # pixel reads them with one gather (a 20k-entry table instead of 4 reads per pixel).
    qt = g["quad_tiles"]
    packed = materialise(lut[:, qt[0]] | (lut[:, qt[1]] << 8) | (lut[:, qt[2]] << 16) | (lut[:, qt[3]] << 24))
    if curve is not None:  # read the tile LUTs at curve[v]: compose the curve into the table
        packed = materialise(jnp.take_along_axis(packed, jnp.broadcast_to(curve[:, None, :], packed.shape), axis=-1))
    packed = packed.reshape(-1)
    # unsigned indices: no negative-index wrap-around select per pixel
    qoff = jnp.arange(b, dtype=jnp.uint32)[:, None, None] * (packed.size // b)
    qi = qoff + g["quad_row"].astype(np.uint32) + g["quad_col"].astype(np.uint32) + v.astype(jnp.uint32)
    q = packed.at[qi].get(mode="promise_in_bounds")
    l11, l12 = (q & 255).astype(jnp.float32), ((q >> 8) & 255).astype(jnp.float32)
    l21, l22 = ((q >> 16) & 255).astype(jnp.float32), (q >> 24).astype(jnp.float32)
    xa = jnp.asarray(g["xa"], jnp.float32)
    ya = jnp.asarray(g["ya"], jnp.float32)
    res = (l11 * (1 - xa) + l12 * xa) * (1 - ya) + (l21 * (1 - xa) + l22 * xa) * ya
    return jnp.clip(jnp.round(res), 0, 255).astype(jnp.uint8)


def _triweight_hist(x: jax.Array, tiles: jax.Array, n: int) -> jax.Array:
    """Soft histogram: every level ``x`` (any shape) adds a normalised triweight bump to the
    bins ``floor(x) - 2 .. floor(x) + 3`` of its tile (flat offsets ``tiles``); edge bins
    collect the mass that falls outside ``[0, 255]``."""
    i0 = jnp.floor(x)
    ks = [i0 + d for d in range(-2, 4)]
    ws = [jnp.clip(1.0 - ((x - k) / SOFT_RADIUS) ** 2, 0.0, None) ** 3 for k in ks]
    total = sum(ws[1:], ws[0])
    hist = jnp.zeros(n, x.dtype)
    for k, wk in zip(ks, ws):
        idx = tiles + jnp.clip(k, 0, _BINS - 1).astype(jnp.int32)
        hist = hist.at[idx.reshape(-1)].add((wk / total).reshape(-1))
    return hist


def _catmull_rom(lut: jax.Array, base: jax.Array, x: jax.Array) -> jax.Array:
    """C1 interpolation of per-tile tables ``lut`` (flat) at levels ``x``; ``base`` = flat
    offset of each pixel's table. Indices are clamped to ``[0, 255]``."""
    i = jnp.floor(x)
    t = x - i
    p = [jnp.take(lut, base + jnp.clip(i + d, 0, _BINS - 1).astype(jnp.int32), mode="clip") for d in (-1, 0, 1, 2)]
    return 0.5 * (
        2 * p[1]
        + (p[2] - p[0]) * t
        + (2 * p[0] - 5 * p[1] + 4 * p[2] - p[3]) * t**2
        + (3 * p[1] - p[0] - 3 * p[2] + p[3]) * t**3
    )


def clahe_soft_levels(
    x: jax.Array, clip_limit: jax.Array | float = 2.0, tile_grid: tuple[int, int] = (8, 8), tau: float = 1.0
) -> jax.Array:
    """Differentiable CLAHE of float grey levels ``x`` in ``[0, 255]``, shape ``(B, H, W)``.

    Same tiling and interpolation as :func:`clahe_hard_u8`; the clip ``c = clip_limit *
    tileArea / 256`` is traced (no integer floor), soft by ``tau`` counts. Returns float levels.
    """
    b, h, w = x.shape
    gy, gx = tile_grid
    g = _geometry(h, w, gy, gx)
    area = g["area"]
    per = gy * gx * _BINS
    off = jnp.arange(b, dtype=jnp.int32)[:, None, None] * per
    hist = _triweight_hist(x, off + g["tile"], b * per)
    if g["pad_src"].size:
        xp = x.reshape(b, h * w)[:, g["pad_src"]]
        hist = hist + _triweight_hist(xp, off[:, :, 0] + g["pad_tile"], b * per)
    hist = hist.reshape(b, gy * gx, _BINS)
    c = jnp.asarray(clip_limit, x.dtype) * area / _BINS
    excess = tau * jax.nn.softplus((hist - c) / tau)
    hist = hist - excess + jnp.sum(excess, axis=-1, keepdims=True) / _BINS
    lut = materialise((jnp.cumsum(hist, axis=-1) * ((_BINS - 1) / area)).reshape(-1))
    return _interpolate(lambda cnr: _catmull_rom(lut, off + cnr, x), g, x.dtype)
