"""SURF (Bay et al., "Speeded-Up Robust Features", CVIU 2008) as JAX array code, written to
reproduce OpenCV's ``xfeatures2d::SURF`` (``modules/xfeatures2d/src/surf.cpp``) on 8-bit images.

Pipeline (all under one ``jit``; fixed-size outputs with a validity mask):

1. **Integral image** in int32 (wrap-around arithmetic, as OpenCV's ``CV_32S``: a box sum is
   exact whenever the true sum fits in 31 bits). float32 sums lose detector parity.
2. **Hessian layers**: octave ``o``, layer ``l`` in ``0..L+1`` uses box filters of size
   ``(9 + 6 l) << o`` sampled every ``2**o`` pixels; each lobe is weighted by 1/area (float32),
   terms summed in double, then ``det = Dxx Dyy - 0.81 Dxy^2`` in float32 (8-bit intensity
   units squared: OpenCV's ``hessianThreshold`` meaning), ``trace = Dxx + Dyy``.
3. **Detection** on the ``L`` middle layers: ``det > threshold`` and strictly greater than its 26
   neighbours (3x3x3), inside OpenCV's margin; then one Newton step of a 3-D quadratic fit
   (Brown & Lowe) — kept only if every offset is within one sample; the size is rounded.
   At most ``max_keypoints`` survive, by OpenCV's keypoint order (response, then size, ...).
4. **Orientation**: Haar responses (wavelet ``4s``, ``s = 1.2 size / 9``) at the 113 integer
   points of a radius-6 disc, Gaussian (sigma 2.5) weighted; a 60° window slid in 5° steps
   over the rounded sample angles; the direction of the longest window sum. ``upright``
   fixes it at 270° like OpenCV.
5. **Descriptor**: a ``int(21 s)`` pixel window rotated to the keypoint direction (bilinear,
   rounded to 8 bits), area-resized to 21x21 (OpenCV's ``INTER_AREA`` table), 2x2 Haar
   gradients weighted by a 20x20 Gaussian (sigma 3.3), sums of ``dx, dy, |dx|, |dy|`` over 4x4
   cells, normalised to unit length. Keypoints are sorted by window size; each static window
   class (15 sizes, 28..768 px) runs its own loop over chunks of its keypoints.

Keypoint columns: ``x, y, size, angle_deg, response, octave, laplacian_sign`` (OpenCV's
``KeyPoint`` with ``class_id`` = sign of the Laplacian).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

HAAR_SIZE0 = 9
HAAR_SIZE_INC = 6
ORI_RADIUS = 6
ORI_WIN = 60
ORI_SEARCH_INC = 5
ORI_SIGMA = 2.5
DESC_SIGMA = 3.3
PATCH_SZ = 20
CHUNK_SAMPLES = 96 * 96 * 16  # window samples per descriptor chunk
WINDOW_CLASS_STEP = 1.2  # ratio of consecutive descriptor window classes
BAND_MIN_WINDOW = 92  # window classes from here up sample only the INTER_AREA row bands
SAMPLE_COLUMNS = 8  # window rows are sampled in multiples of this many columns (vector width)

_F32 = jnp.float32
_f32 = np.float32
# OpenCV's fastAtan2 polynomial (degrees), coefficients rounded to float32 as in core.
_ATAN_P = [
    _f32(_f32(c) * _f32(180 / math.pi))
    for c in (0.9997878412794807, -0.3258083974640975, 0.1555786518463281, -0.04432655554792128)
]
_DBL_EPS_F32 = _f32(np.finfo(np.float64).eps)
_FLT_EPS = _f32(np.finfo(np.float32).eps)


# OpenCV 5's getGaussianKernel(20, 3.3, CV_32F) (first half; symmetric). For an even length it
# is not the sampled Gaussian (up to 0.9 % off it); the descriptor weights need its exact taps.
_DESC_TAPS_CV5 = np.array(
    [
        0.0019170277519151568,
        0.004380760248750448,
        0.009132515639066696,
        0.017368055880069733,
        0.030132275074720383,
        0.04769057035446167,
        0.06885777413845062,
        0.09069708734750748,
        0.10898169875144958,
        0.12084222584962845,
    ],
    np.float32,
)


def gaussian_kernel(n: int, sigma: float) -> np.ndarray:
    """``cv::getGaussianKernel(n, sigma, CV_32F)`` for the two kernels SURF uses: odd ``n`` is
    the sampled Gaussian, float32 taps normalised in double; ``(20, 3.3)`` is OpenCV 5's table."""
    if (n, sigma) == (PATCH_SZ, DESC_SIGMA):
        return np.concatenate([_DESC_TAPS_CV5, _DESC_TAPS_CV5[::-1]])
    x = np.arange(n, dtype=np.float64) - (n - 1) * 0.5
    t = np.exp((-0.5 / (sigma * sigma)) * x * x).astype(np.float32)
    s = 1.0 / float(np.sum(t.astype(np.float64)))
    return (t.astype(np.float64) * s).astype(np.float32)


def _resize_pattern(src, old: int, new: int):
    """OpenCV ``resizeHaarPattern`` without the pointer offsets: boxes
    ``(dx1, dy1, dx2, dy2, weight_f32)`` scaled from an ``old``- to a ``new``-pixel filter."""
    ratio = _f32(new) / _f32(old)
    out = []
    for dx1, dy1, dx2, dy2, w in src:
        x1, y1, x2, y2 = (int(np.rint(_f32(ratio * _f32(v)))) for v in (dx1, dy1, dx2, dy2))
        out.append((x1, y1, x2, y2, _f32(_f32(w) / (_f32(x2 - x1) * _f32(y2 - y1)))))
    return out


_DX9 = ((0, 2, 3, 7, 1), (3, 2, 6, 7, -2), (6, 2, 9, 7, 1))
_DY9 = ((2, 0, 7, 3, 1), (2, 3, 7, 6, -2), (2, 6, 7, 9, 1))
_DXY9 = ((1, 1, 4, 4, 1), (5, 1, 8, 4, -1), (1, 5, 4, 8, -1), (5, 5, 8, 8, 1))


@functools.lru_cache(maxsize=32)
def layer_plan(h: int, w: int, n_octaves: int, n_layers: int) -> tuple[dict, ...]:
    """Static description of every Hessian layer of an ``h x w`` image."""
    plan = []
    for o in range(n_octaves):
        step = 1 << o
        for layer in range(n_layers + 2):
            size = (HAAR_SIZE0 + HAAR_SIZE_INC * layer) << o
            rows, cols = h // step, w // step
            computed = size <= h and size <= w
            plan.append(
                {
                    "octave": o,
                    "layer": layer,
                    "size": size,
                    "step": step,
                    "rows": rows,
                    "cols": cols,
                    "computed": computed,
                    "ni": 1 + (h - size) // step if computed else 0,
                    "nj": 1 + (w - size) // step if computed else 0,
                    "margin": (size // 2) // step,
                    "dx": _resize_pattern(_DX9, 9, size),
                    "dy": _resize_pattern(_DY9, 9, size),
                    "dxy": _resize_pattern(_DXY9, 9, size),
                }
            )
    return tuple(plan)


def integral_image(img_u8: jax.Array) -> jax.Array:
    """``cv::integral(img, sum, CV_32S)``: ``(H+1, W+1)`` int32 with a zero first row/column.
    Prefix sums by ``associative_scan`` (exact in integers; XLA:CPU's ``cumsum`` lowering
    took ~3x longer on a KITTI frame)."""
    s = img_u8.astype(jnp.int32)
    s = lax.associative_scan(jnp.add, lax.associative_scan(jnp.add, s, axis=0), axis=1)
    return jnp.pad(s, ((1, 0), (1, 0)))


def _parity_planes(S, plan) -> dict:
    """For each octave with a step > 1, the integral image's parity planes
    ``S[a::step, b::step]`` that its box corners fall on, keyed ``(step, a, b)``: a layer's
    corners are then contiguous slices of a plane. Strided slices of ``S`` read the same
    numbers ~4x slower per output on CPU (they do not vectorise)."""
    need = set()
    for lp in plan:
        st = lp["step"]
        if lp["computed"] and st > 1:
            for x1, y1, x2, y2, _ in lp["dx"] + lp["dy"] + lp["dxy"]:
                for dy, dx in ((y1, x1), (y2, x2), (y2, x1), (y1, x2)):
                    need.add((st, dy % st, dx % st))
    return {k: S[k[1] :: k[0], k[2] :: k[0]] for k in sorted(need)}


def _corner(S, planes: dict, dy: int, dx: int, step: int, ni: int, nj: int):
    """The ``(ni, nj)`` grid of ``S[dy + step * i, dx + step * j]``."""
    if step == 1:
        return lax.slice(S, (dy, dx), (dy + ni, dx + nj))
    P = planes[(step, dy % step, dx % step)]
    return lax.slice(P, (dy // step, dx // step), (dy // step + ni, dx // step + nj))


def _haar_grid(S, planes: dict, boxes, step: int, ni: int, nj: int):
    """OpenCV ``calcHaarPattern`` on a strided grid: int box sums times float32 weights,
    accumulated in double, rounded to float32."""
    acc = jnp.zeros((ni, nj), jnp.float64)
    for x1, y1, x2, y2, wgt in boxes:
        box = (
            _corner(S, planes, y1, x1, step, ni, nj)
            + _corner(S, planes, y2, x2, step, ni, nj)
            - _corner(S, planes, y2, x1, step, ni, nj)
            - _corner(S, planes, y1, x2, step, ni, nj)
        )
        term = (box.astype(_F32) * wgt).astype(jnp.float64)
        acc = acc + term  # 0 + t1 + t2 ... in double, as OpenCV
    return acc.astype(_F32)


def _det_trace(S, planes: dict, lp: dict):
    """Determinant and trace of one layer, ``(rows, cols)`` float32; -inf (det) where the
    filter does not fit (OpenCV leaves those cells unset and never reads them). ``planes``:
    :func:`_parity_planes`."""
    rows, cols = lp["rows"], lp["cols"]
    if not lp["computed"]:
        return jnp.full((rows, cols), -jnp.inf, _F32), jnp.zeros((rows, cols), _F32)
    st, ni, nj, m = lp["step"], lp["ni"], lp["nj"], lp["margin"]
    dx = _haar_grid(S, planes, lp["dx"], st, ni, nj)
    dy = _haar_grid(S, planes, lp["dy"], st, ni, nj)
    dxy = _haar_grid(S, planes, lp["dxy"], st, ni, nj)
    det = dx * dy - (_f32(0.81) * dxy) * dxy
    pad = ((m, rows - m - ni), (m, cols - m - nj))
    return jnp.pad(det, pad, constant_values=-jnp.inf), jnp.pad(dx + dy, pad)


def _nms26(below, here, above, threshold, m: int):
    """The responses of ``here`` that are 3x3x3 maxima, over the cells at least ``m >= 1``
    from the border: ``(start, resp)``, ``resp`` 1-D over the flat (row-major) layer from
    index ``start`` to the last such cell, ``-inf`` where a cell is not above ``threshold``
    and strictly greater than its 26 neighbours in the three layers, or lies in the margin.
    One fused pass over the flattened layers, whose neighbours are contiguous slices at
    fixed offsets: no padding, and no 2-D slices flattened afterwards (XLA:CPU fuses such a
    flattening into the loop, which then runs over a linear index with divisions and scalar
    loads: 4.5 -> 2.9 ms with the top-k for a full-resolution layer on one core);
    ``reduce_window`` is slow on CPU."""
    rows, cols = here.shape
    start, end = m * cols + m, (rows - m - 1) * cols + cols - m
    flat = [x.ravel() for x in (below, here, above)]
    c = flat[1][start:end]
    ok = c > threshold
    for name, layer in enumerate(flat):
        for di in range(-1, 2):
            for dj in range(-1, 2):
                if (name, di, dj) != (1, 0, 0):
                    o = di * cols + dj
                    ok = ok & (c > layer[start + o : end + o])
    col = (jnp.arange(end - start, dtype=jnp.int32) + start) % cols
    return start, jnp.where(ok & (col >= m) & (col < cols - m), c, -jnp.inf)


def _det3(m00, m01, m02, m10, m11, m12, m20, m21, m22):
    return m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20) + m02 * (m10 * m21 - m11 * m20)


def _solve3(A, b):
    """Batched 3x3 solve by Cramer's rule in float64 (``A`` as rows of 3-tuples of arrays,
    ``b`` a 3-tuple); ``ok`` False where singular. Written out element by element: a stacked
    form (``A.at[:, k].set(b)``) makes XLA recompute the minors per output element."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = [[v.astype(jnp.float64) for v in row] for row in A]
    b0, b1, b2 = (v.astype(jnp.float64) for v in b)
    d = _det3(a00, a01, a02, a10, a11, a12, a20, a21, a22)
    ok = jnp.abs(d) > 1e-300
    dsafe = jnp.where(ok, d, 1.0)
    x0 = _det3(b0, a01, a02, b1, a11, a12, b2, a21, a22) / dsafe
    x1 = _det3(a00, b0, a02, a10, b1, a12, a20, b2, a22) / dsafe
    x2 = _det3(a00, a01, b0, a10, a11, b1, a20, a21, b2) / dsafe
    return (x0, x1, x2), ok


def _octave_keypoints(Ds, Ts, lps: list, threshold, cap: int):
    """Candidates of the middle layers of one octave (``Ds``, ``Ts``: the ``L + 2``
    determinant and trace layers, ``(rows, cols)`` each): 3x3x3 NMS inside OpenCV's margin,
    at most ``cap`` per layer (best responses), then the quadratic interpolation. Returns a
    dict of ``(L * cap,)``. The layers are not stacked (that copy costs more than the NMS)."""
    nl = len(Ds) - 2
    rows, cols, st = lps[0]["rows"], lps[0]["cols"], lps[0]["step"]
    cap = min(cap, rows * cols)
    tops, idxs, blks, traces = [], [], [], []
    for k in range(1, nl + 1):
        m = (lps[k + 1]["size"] // 2) // st + 1  # OpenCV's margin (>= 1)
        hr, wr = max(rows - 2 * m, 0), max(cols - 2 * m, 0)
        kr = min(cap, hr * wr)
        if kr > 0:  # candidates inside the margin, then their index in the whole layer
            start, resp = _nms26(Ds[k - 1], Ds[k], Ds[k + 1], threshold, m)
            top, ir = lax.top_k(resp, kr)  # row-major order: ties as OpenCV's scan
            idx = ir.astype(jnp.int32) + start
        else:
            top, idx = jnp.zeros((0,), _F32), jnp.zeros((0,), jnp.int32)
        top = jnp.pad(top, (0, cap - kr), constant_values=-jnp.inf)
        idx = jnp.pad(idx, (0, cap - kr))
        # the 3x3x3 block around each candidate (clamped for the empty slots)
        shifts = np.array([[di * cols + dj for di in (-1, 0, 1) for dj in (-1, 0, 1)]], np.int32)
        nb = jnp.clip(idx[:, None] + shifts, 0, rows * cols - 1)
        blks.append(jnp.stack([Ds[k + a].ravel()[nb] for a in (-1, 0, 1)], 1))  # (cap, 3, 9)
        traces.append(Ts[k].ravel()[idx])
        tops.append(top)
        idxs.append(idx)
    valid = jnp.concatenate(tops) > -jnp.inf
    lay = jnp.repeat(jnp.arange(nl, dtype=jnp.int32), cap)
    idx = jnp.concatenate(idxs)
    i, j = idx // cols, idx % cols
    blk = jnp.concatenate(blks)
    trace = jnp.concatenate(traces)
    N = [[blk[:, a, k] for k in range(9)] for a in range(3)]
    half = _f32(0.5)
    b = (-((N[1][5] - N[1][3]) / 2), -((N[1][7] - N[1][1]) / 2), -((N[2][4] - N[0][4]) / 2))
    dxx = N[1][3] - 2 * N[1][4] + N[1][5]
    dyy = N[1][1] - 2 * N[1][4] + N[1][7]
    dss = N[0][4] - 2 * N[1][4] + N[2][4]
    dxy = (N[1][8] - N[1][6] - N[1][2] + N[1][0]) / 4
    dxs = (N[2][5] - N[2][3] - N[0][5] + N[0][3]) / 4
    dys = (N[2][7] - N[2][1] - N[0][7] + N[0][1]) / 4
    xs, solved = _solve3(((dxx, dxy, dxs), (dxy, dyy, dys), (dxs, dys, dss)), b)
    x0, x1, x2 = (v.astype(_F32) for v in xs)
    ok = solved & ((x0 != 0) | (x1 != 0) | (x2 != 0))
    for v in (x0, x1, x2):
        ok = ok & (jnp.abs(v) <= 1) & jnp.isfinite(v)
    sizes = jnp.asarray([lp["size"] for lp in lps], jnp.int32)
    size = sizes[lay + 1]
    ds = size - sizes[lay]
    h = (size // 2) // st
    cy = (st * (i - h)).astype(_F32) + (size - 1).astype(_F32) * half
    cx = (st * (j - h)).astype(_F32) + (size - 1).astype(_F32) * half
    return {
        "x": cx + x0 * _f32(st),
        "y": cy + x1 * _f32(st),
        "size": jnp.round(size.astype(_F32) + x2 * ds.astype(_F32)),
        "response": N[1][4],
        "octave": jnp.full((nl * cap,), lps[0]["octave"], jnp.int32),
        "lap": jnp.sign(trace).astype(jnp.int32),
        "valid": valid & ok,
    }


def _lexsort_keypoints(kp, rows=None):
    """OpenCV's ``KeypointGreater`` (response desc, size desc, octave desc, y desc, x asc),
    valid entries first; over ``rows`` (indices into ``kp``) or all of ``kp``."""
    k = kp if rows is None else {key: v[rows] for key, v in kp.items()}
    order = jnp.lexsort((k["x"], -k["y"], -k["octave"], -k["size"], -k["response"], ~k["valid"]))
    return order if rows is None else rows[order]


def _keypoint_order(kp, cap: int):
    """The first ``cap`` indices of :func:`_lexsort_keypoints` over all candidates (into
    ``kp`` extended by one invalid row at index ``n``, which fills unused slots), without
    a six-key sort of every candidate slot (~30 ms for 49k on CPU). When at most ``cap``
    candidates are valid they are compacted (prefix sum) and only they are sorted;
    otherwise the strongest ``cap + 1`` responses are picked by ``top_k`` and sorted, unless
    the response at the cut is tied (``top_k`` might then keep the wrong one of equals) and
    the full sort runs. Every path gives the full sort's order."""
    n = kp["x"].shape[0]
    if n <= cap + 1:
        return _lexsort_keypoints(kp)[:cap].astype(jnp.int32)
    valid = kp["valid"]

    def compact():
        pos = jnp.where(valid, jnp.cumsum(valid.astype(jnp.int32)) - 1, cap)
        rows = jnp.full((cap,), n, jnp.int32).at[pos].set(jnp.arange(n, dtype=jnp.int32), mode="drop")
        sub = {key: jnp.pad(v, (0, 1))[rows] for key, v in kp.items()}  # row n: invalid
        return rows[_lexsort_keypoints(sub)]

    def strongest():
        key = jnp.where(valid, kp["response"], -jnp.inf)
        top, rows = lax.top_k(key, cap + 1)
        tied = (top[cap - 1] == top[cap]) & (top[cap] > -jnp.inf)
        return lax.cond(
            tied,
            lambda: _lexsort_keypoints(kp)[:cap].astype(jnp.int32),
            lambda: _lexsort_keypoints(kp, rows.astype(jnp.int32))[:cap].astype(jnp.int32),
        )

    return lax.cond(jnp.sum(valid) <= cap, compact, strongest)


def detect(img_u8: jax.Array, threshold, max_keypoints: int, n_octaves: int = 4, n_layers: int = 3):
    """Fast-Hessian detector. Returns a dict of ``(max_keypoints,)`` arrays in OpenCV's order
    (valid entries first)."""
    h, w = img_u8.shape
    plan = layer_plan(h, w, n_octaves, n_layers)
    S = integral_image(img_u8)
    planes = _parity_planes(S, plan)
    dets = [_det_trace(S, planes, lp) for lp in plan]
    # the determinants materialised once (the NMS reads each 9 to 27 times); the traces are
    # only read at the candidates
    dets = list(zip(lax.optimization_barrier([d for d, _ in dets]), [t for _, t in dets]))
    parts = []
    nl = n_layers + 2
    thr = jnp.asarray(threshold, _F32)
    for o in range(n_octaves):
        lps = list(plan[o * nl : (o + 1) * nl])
        if not lps[2]["computed"]:  # no middle layer of this octave can hold a maximum
            continue
        Ds = [dets[k][0] for k in range(o * nl, (o + 1) * nl)]
        Ts = [dets[k][1] for k in range(o * nl, (o + 1) * nl)]
        parts.append(_octave_keypoints(Ds, Ts, lps, thr, max_keypoints))
    if not parts:
        z = jnp.zeros((max_keypoints,), _F32)
        zi = jnp.zeros((max_keypoints,), jnp.int32)
        return {"x": z, "y": z, "size": z, "response": z, "octave": zi, "lap": zi, "valid": zi > 0}
    kp = {key: jnp.concatenate([p[key] for p in parts]) for key in parts[0]}
    order = _keypoint_order(kp, max_keypoints)
    out = {key: jnp.pad(v, (0, 1))[order] for key, v in kp.items()}
    if out["x"].shape[0] < max_keypoints:  # fewer candidate slots than the cap
        pad = max_keypoints - out["x"].shape[0]
        out = {key: jnp.pad(v, (0, pad)) for key, v in out.items()}
    return out


# ----------------------------------------------------------------------------- orientation


def fast_atan2_deg(y, x):
    """OpenCV ``fastAtan2`` / ``phase(..., angleInDegrees=True)``: float32, ``[0, 360)``."""
    y = y.astype(_F32)
    x = x.astype(_F32)
    ax, ay = jnp.abs(x), jnp.abs(y)
    big = ax >= ay
    c = jnp.where(big, ay / (ax + _DBL_EPS_F32), ax / (ay + _DBL_EPS_F32))
    c2 = c * c
    p = (((_ATAN_P[3] * c2 + _ATAN_P[2]) * c2 + _ATAN_P[1]) * c2 + _ATAN_P[0]) * c
    a = jnp.where(big, p, _f32(90) - p)
    a = jnp.where(x < 0, _f32(180) - a, a)
    return jnp.where(y < 0, _f32(360) - a, a)


@functools.lru_cache(maxsize=1)
def _ori_samples():
    g = gaussian_kernel(2 * ORI_RADIUS + 1, ORI_SIGMA)
    pts, wts = [], []
    for i in range(-ORI_RADIUS, ORI_RADIUS + 1):
        for j in range(-ORI_RADIUS, ORI_RADIUS + 1):
            if i * i + j * j <= ORI_RADIUS * ORI_RADIUS:
                pts.append((i, j))
                wts.append(_f32(g[i + ORI_RADIUS] * g[j + ORI_RADIUS]))
    return np.array(pts, np.int32), np.array(wts, np.float32)


@functools.lru_cache(maxsize=1)
def _window_members() -> np.ndarray:
    """``(144, 72)`` 0/1 over the histogram of :func:`orientation`: bin ``2 q`` holds the
    rounded angles ``5 q`` and bin ``2 q + 1`` the angles ``5 q + 1 .. 5 q + 4``; window
    ``k`` (start ``5 k``) takes OpenCV's ``|angle - 5 k| < 30`` (circularly; angle 360 is 0),
    i.e. ``q - k`` in ``-5..5`` for the first kind and ``-6..5`` for the second."""
    t = (np.arange(72)[:, None] - np.arange(72)[None, :] + 36) % 72 - 36  # q - k, circular
    out = np.zeros((144, 72), np.float32)
    out[0::2] = np.abs(t) <= 5
    out[1::2] = (t >= -6) & (t <= 5)
    return out


def _scale(size):
    return (size.astype(_F32) * _f32(1.2)) / _f32(9.0)


def runtime_one(x) -> jax.Array:
    """A float32 1.0 computed at run time from the traced scalar ``x`` (any value), which
    XLA cannot fold away. Dividing by it is exact and keeps a value that several loops
    read from being recomputed inside each of them: XLA:CPU's fusion treats a division as
    expensive and stores its result once (``lax.optimization_barrier`` does not survive its
    pipeline; the IMU kernel's ``_fence`` is the same trick)."""
    t = jnp.abs(jnp.asarray(x, _F32)) + _f32(1)
    return jnp.where(jnp.isfinite(t), t / t, _f32(1))


def orientation(S, x, y, size, valid, one):
    """Dominant direction (degrees) and whether it could be sampled. ``one``:
    :func:`runtime_one`."""
    pts, wts = _ori_samples()
    hs, ws = S.shape
    s = _scale(size)
    g = (2 * jnp.round(2 * s)).astype(jnp.int32)
    half = g // 2
    off = (g - 1).astype(_F32) / _f32(2)
    px = jnp.round((x[:, None] + _f32(pts[None, :, 0]) * s[:, None]) - off[:, None]).astype(jnp.int32)
    py = jnp.round((y[:, None] + _f32(pts[None, :, 1]) * s[:, None]) - off[:, None]).astype(jnp.int32)
    G, Hf = g[:, None], half[:, None]
    inb = (py >= 0) & (py < hs - G) & (px >= 0) & (px < ws - G) & valid[:, None]
    # each sample's first corner, stored once (exact in float32: < 2^24) for the eight
    # gathers below; fused into them, XLA recomputed it per corner
    base = (jnp.where(inb, py * ws + px, 0).astype(_F32) / one).astype(jnp.int32)
    flat = S.ravel()
    # the eight integral-image corners of the two Haar boxes, (n, 113) each
    z = jnp.zeros_like(g)
    c00, c0h, c0g, ch0, chg, cg0, cgh, cgg = (
        flat.at[base + (dy * ws + dx)[:, None]].get(mode="promise_in_bounds")
        for dy, dx in ((z, z), (z, half), (z, g), (half, z), (half, g), (g, z), (g, half), (g, g))
    )
    area = (Hf * G).astype(_F32)
    w_neg, w_pos = _f32(-1) / area, _f32(1) / area
    left = c00 + cgh - cg0 - c0h
    right = c0h + cgg - cgh - c0g
    top = c00 + chg - ch0 - c0g
    bottom = ch0 + cgg - cg0 - chg
    vx = ((left.astype(_F32) * w_neg).astype(jnp.float64) + (right.astype(_F32) * w_pos)).astype(_F32)
    vy = ((top.astype(_F32) * w_pos).astype(jnp.float64) + (bottom.astype(_F32) * w_neg)).astype(_F32)
    X = jnp.where(inb, vx * wts[None], 0)
    Y = jnp.where(inb, vy * wts[None], 0)
    # stored once, read by the angle bins and by the histogram (fused, XLA computed them
    # twice: 16 -> 10.5 ms for the KITTI frame's orientations on 2 cores)
    X, Y = X / one, Y / one
    ang = jnp.round(fast_atan2_deg(Y, X)).astype(jnp.int32) % 360  # 360 is 0
    # Window sums from a circular histogram of the rounded angles in 5-degree steps (two
    # bins per step, see _window_members), one scatter of the (X, Y) pairs, and a product.
    n = X.shape[0]
    kbin = 2 * (ang // ORI_SEARCH_INC) + (ang % ORI_SEARCH_INC > 0).astype(jnp.int32)
    flat_bin = lax.optimization_barrier((jnp.arange(n, dtype=jnp.int32)[:, None] * 144 + kbin).ravel())
    xy = jnp.stack([X.ravel(), Y.ravel()], -1)
    hist = jnp.zeros((n * 144, 2), _F32).at[flat_bin].add(xy, indices_are_sorted=True)
    hist = lax.optimization_barrier(hist.reshape(n, 144, 2))
    sums = jnp.einsum("nbc,bk->nck", hist, _window_members(), precision=lax.Precision.HIGHEST)
    sx, sy = sums[:, 0], sums[:, 1]
    mod = sx * sx + sy * sy
    # first window of the largest modulus (argmax is a slow variadic reduction on CPU)
    best = jnp.max(mod, -1, keepdims=True)
    idx = jnp.arange(mod.shape[-1], dtype=jnp.int32)[None, :]
    k = jnp.min(jnp.where(mod == best, idx, mod.shape[-1]), -1, keepdims=True)
    pick = (idx == k) & (best > 0)
    bx = jnp.sum(jnp.where(pick, sx, 0), -1)
    by = jnp.sum(jnp.where(pick, sy, 0), -1)
    return fast_atan2_deg(-by, bx), jnp.any(inb, -1)


# ----------------------------------------------------------------------------- descriptor


def _window_classes(max_win: int) -> tuple[int, ...]:
    """Static window sizes (multiples of 4, about 10 % apart, from 28 up to ``max_win``):
    a keypoint's window is sampled at the smallest class that holds it, so the padding costs
    at most ~20 % more samples (the sampling cost grows with the window's area)."""
    out = [28]
    while out[-1] < max_win:
        out.append(min(-(-int(out[-1] * WINDOW_CLASS_STEP) // 4) * 4, -(-max_win // 4) * 4))
    return tuple(out)


def _area_support(win):
    """OpenCV's ``computeResizeAreaTab`` terms from ``win`` samples to 21, each ``(..., 21, 1)``
    float64: ``f1``, ``f2`` (an output's interval), ``cw`` (its width), ``s1``, ``s2`` (its
    first whole sample and its last sample)."""
    m = PATCH_SZ + 1
    n = win.astype(jnp.float64)[..., None, None]
    scale = 1.0 / (m / n)
    f1 = jnp.arange(m, dtype=jnp.float64).reshape((1,) * (n.ndim - 2) + (m, 1)) * scale
    f2 = f1 + scale
    s2 = jnp.minimum(jnp.floor(f2), n - 1)
    return f1, f2, jnp.minimum(scale, n - f1), jnp.minimum(jnp.ceil(f1), s2), s2


def _area_weights(win, sidx):
    """OpenCV ``INTER_AREA`` weights from ``win`` samples to 21, evaluated at the sample
    indices ``sidx`` (float64, broadcastable against ``(..., 21, 1)``; zero off each output's
    support or beyond ``win``), float32."""
    f1, f2, cw, s1, s2 = _area_support(win)
    left = jnp.where((sidx == s1 - 1) & (s1 - f1 > 1e-3), (s1 - f1) / cw, 0.0)
    full = jnp.where((sidx >= s1) & (sidx < s2), 1.0 / cw, 0.0)
    right = jnp.where((sidx == s2) & (f2 - s2 > 1e-3), jnp.minimum(jnp.minimum(f2 - s2, 1.0), cw) / cw, 0.0)
    return (left.astype(_F32) + full.astype(_F32) + right.astype(_F32)).astype(_F32)


def _area_matrix(win, wb: int):
    """The ``INTER_AREA`` weights from ``win`` to 21 samples as a ``(..., 21, wb)`` float32
    matrix (zero beyond ``win``)."""
    lead = (1,) * win.ndim
    return _area_weights(win, jnp.arange(wb, dtype=jnp.float64).reshape((*lead, 1, wb)))


def _band_length(wb: int) -> int:
    """Rows in the support of one ``INTER_AREA`` output, for any window up to ``wb``: the
    support of output ``d`` is ``[ceil(d s) - 1, floor((d + 1) s)]`` with ``s = win / 21``."""
    return wb // (PATCH_SZ + 1) + 2


def _area_band(win, wb: int):
    """Each ``INTER_AREA`` output row's band of window rows: ``(rows, weights)``, both
    ``(C, 21, L)`` (``L`` = :func:`_band_length`). Rows are clamped to the ``wb`` grid; a
    clamped row is off its output's support, and its weight (from the unclamped index) is 0."""
    s1 = _area_support(win)[3]  # (C, 21, 1)
    sidx = jnp.maximum(s1 - 1, 0) + jnp.arange(_band_length(wb), dtype=jnp.float64)[None, None]
    rows = jnp.minimum(sidx, wb - 1).astype(jnp.int32)
    return rows, _area_weights(win, sidx)


def pack_quads(img):
    """``(H, W)`` uint32 holding each pixel's 2x2 neighbourhood (x, x+1, y+1, both; clamped
    at the last row/column) in its four bytes, so that a bilinear sample is one gather."""
    i = img.astype(jnp.uint32)
    right = jnp.concatenate([i[:, 1:], i[:, -1:]], 1)
    down = jnp.concatenate([i[1:], i[-1:]], 0)
    diag = jnp.concatenate([right[1:], right[-1:]], 0)
    return i | (right << 8) | (down << 16) | (diag << 24)


def _rotation(cx, cy, win, ang):
    """OpenCV's window start ``(start_x, start_y)`` and direction ``(sin_dir, cos_dir)``."""
    off = -((win - 1).astype(_F32) / _f32(2))
    rad = ang * _f32(math.pi / 180)
    sin_d = -jnp.sin(rad)
    cos_d = jnp.cos(rad)
    return (cx + off * cos_d) + off * sin_d, (cy - off * sin_d) + off * cos_d, sin_d, cos_d


def _window_inside(cx, cy, win, ang, wb: int, h: int, w: int):
    """Whether every sample of a keypoint's rotated ``wb x wb`` grid falls in the image's
    bilinear area with a pixel to spare (so no sample needs OpenCV's border fallback). The
    grid positions are affine in the sample indices, so the extremes are at its corners."""
    start_x, start_y, sin_d, cos_d = _rotation(cx, cy, win, ang)
    e = _f32(wb - 1)
    xs = [start_x, start_x + e * sin_d, start_x + e * cos_d, (start_x + e * sin_d) + e * cos_d]
    ys = [start_y, start_y + e * cos_d, start_y - e * sin_d, (start_y + e * cos_d) - e * sin_d]
    lo_x, hi_x = functools.reduce(jnp.minimum, xs), functools.reduce(jnp.maximum, xs)
    lo_y, hi_y = functools.reduce(jnp.minimum, ys), functools.reduce(jnp.maximum, ys)
    return (lo_x >= 1) & (hi_x <= w - 3) & (lo_y >= 1) & (hi_y <= h - 3)


def _sample_window(img, quad, cx, cy, win, ang, wb: int, upright: bool, inside: bool = False, rows=None, cols=None):
    """The ``wb x wb`` window of one batch of keypoints (OpenCV's rotated/bilinear or upright
    nearest extraction, 8-bit rounded); beyond ``win`` the values are finite but arbitrary
    (their area weights are zero). ``(C, wb, cols)`` float32 (``cols`` defaults to ``wb``), or
    ``(C, R, cols)`` with ``rows`` ``(C, R)``: those rows of each window only (in ``[0, wb)``).
    ``cols > wb`` pads each row
    with copies of column ``wb - 1`` (for vector loops without a scalar tail; a padded
    column is beyond ``win`` and has zero weight). ``inside=True`` promises that
    :func:`_window_inside` holds for every keypoint: the border fallback is left out (~1.3x
    faster; the same formulas, though XLA may round a rare tie to the other 8-bit level:
    4 of 1.8M samples in the test)."""
    h, w = img.shape
    flat = img.ravel()
    ii = jnp.arange(wb)[None, :, None] if rows is None else rows[:, :, None]
    jj = jnp.minimum(jnp.arange(cols or wb), wb - 1)[None, None, :]
    off = -((win - 1).astype(_F32) / _f32(2))
    if upright:
        sx = jnp.round(cx + off).astype(jnp.int32)[:, None, None]
        sy = jnp.round(cy - off).astype(jnp.int32)[:, None, None]
        xx = jnp.clip(sx + ii, 0, w - 1)
        yy = jnp.clip(sy - jj, 0, h - 1)
        v = flat[yy * w + xx].astype(_F32)
    else:
        start_x, start_y, sin_d, cos_d = _rotation(cx, cy, win, ang)
        sd, cd = sin_d[:, None, None], cos_d[:, None, None]
        fi, fj = ii.astype(_F32), jj.astype(_F32)
        px = (start_x[:, None, None] + fi * sd) + fj * cd
        py = (start_y[:, None, None] + fi * cd) - fj * sd
        fx, fy = jnp.floor(px), jnp.floor(py)
        ix, iy = fx.astype(jnp.int32), fy.astype(jnp.int32)  # float32 here (OpenCV: double)
        if inside:
            a, b, idx = px - fx, py - fy, iy * w + ix
        else:
            inner = (ix >= 0) & (ix < w - 1) & (iy >= 0) & (iy < h - 1)
            # Outside the bilinear area OpenCV takes the nearest clamped pixel: the same
            # formula with zero weights at that pixel.
            nx = jnp.clip(jnp.round(px), 0, w - 1).astype(jnp.int32)
            ny = jnp.clip(jnp.round(py), 0, h - 1).astype(jnp.int32)
            a = jnp.where(inner, px - fx, 0)
            b = jnp.where(inner, py - fy, 0)
            idx = jnp.where(inner, iy, ny) * w + jnp.where(inner, ix, nx)
        # One gather of the packed 2x2 neighbourhood, kept apart from the index and the
        # interpolation arithmetic (the barriers steer XLA's fusion; ~1.5x faster on CPU).
        idx, a, b = lax.optimization_barrier((idx, a, b))
        q = lax.optimization_barrier(quad.ravel().at[idx].get(mode="promise_in_bounds"))
        i00, i01 = (q & 255).astype(_F32), ((q >> 8) & 255).astype(_F32)
        i10, i11 = ((q >> 16) & 255).astype(_F32), (q >> 24).astype(_F32)
        one = _f32(1)
        bil = i00 * (one - a) * (one - b) + i01 * a * (one - b) + i10 * (one - a) * b + i11 * a * b
        v = jnp.round(bil)
    # samples past ``win`` are finite (clamped indices) and meet zero area weights
    return v


@functools.lru_cache(maxsize=1)
def _desc_weights() -> np.ndarray:
    g = gaussian_kernel(PATCH_SZ, DESC_SIGMA)
    return (g[:, None] * g[None, :]).astype(np.float32)


def _resize_batch(img, quad, cx, cy, win, ang, wb: int, upright: bool, inside: bool = False):
    """The ``(C, 21, 21)`` INTER_AREA-resized windows (before rounding) of a batch of
    keypoints whose windows fit in ``wb`` (``inside``: see :func:`_sample_window`). From
    ``BAND_MIN_WINDOW`` up, only each output row's band of window rows is sampled (about
    ``wb + 42`` rows, some twice) and reduced with its few weights, instead of a dense
    ``21 x wb`` product over all ``wb`` rows (21 multiply-adds a sample)."""
    hi = lax.Precision.HIGHEST
    cols = -(-wb // SAMPLE_COLUMNS) * SAMPLE_COLUMNS
    if wb >= BAND_MIN_WINDOW:
        rows, wts = _area_band(win, wb)  # (C, 21, L)
        c, m, band = rows.shape
        W = _sample_window(img, quad, cx, cy, win, ang, wb, upright, inside, rows.reshape(c, m * band), cols)
        T = jnp.einsum("cpl,cplj->cpj", wts, W.reshape(c, m, band, cols), precision=hi)
    else:
        W = _sample_window(img, quad, cx, cy, win, ang, wb, upright, inside, cols=cols)
        # two explicit products (rows, then columns): XLA's own order for the three-operand
        # einsum is several times slower on CPU
        T = jnp.einsum("cpi,cij->cpj", _area_matrix(win, wb), W, precision=hi)
    return jnp.einsum("cpj,cqj->cpq", T, _area_matrix(win, cols), precision=hi)


def _patch_descriptor(g, win):
    """64-d descriptors from the resized windows ``g`` ``(N, 21, 21)``: 8-bit rounding
    (OpenCV's integer ``resizeAreaFast`` when the scale is exactly 2), 2x2 Haar gradients
    weighted by the 20x20 Gaussian, sums of ``dx, dy, |dx|, |dy|`` over 4x4 cells, unit
    length."""
    g = g.astype(jnp.float64)
    scale = win.astype(jnp.float64) / (PATCH_SZ + 1)
    two = (jnp.abs(scale - 2.0) < 1e-12)[:, None, None]
    block = jnp.round(g * 4.0)  # exact 2x2 sums when scale == 2
    P = jnp.where(two, jnp.floor((block + 2) / 4), jnp.round(g))
    P = jnp.clip(P, 0, 255).astype(jnp.int32)
    dw = _desc_weights()
    dx = (P[:, :-1, 1:] - P[:, :-1, :-1] + P[:, 1:, 1:] - P[:, 1:, :-1]).astype(_F32) * dw[None]
    dy = (P[:, 1:, :-1] - P[:, :-1, :-1] + P[:, 1:, 1:] - P[:, :-1, 1:]).astype(_F32) * dw[None]
    cells = jnp.stack([dx, dy, jnp.abs(dx), jnp.abs(dy)], -1).astype(jnp.float64)  # (N, 20, 20, 4)
    c = cells.shape[0]
    # 5x5 cell sums as shifted strided slices added in one elementwise pass (a reduce over
    # the inner axes of this small block is slow on CPU)
    acc = sum(cells[:, a::5, b::5] for a in range(5) for b in range(5))  # (N, 4, 4, 4)
    vec = acc.astype(_F32).reshape(c, 64)
    mag = jnp.sum((vec * vec).astype(jnp.float64), -1)
    sc = (1.0 / (jnp.sqrt(mag) + float(_FLT_EPS))).astype(_F32)
    return vec * sc[:, None]


def describe(img, x, y, size, ang, valid, upright: bool, max_win: int, fast_inside: bool = True):
    """Descriptors ``(N, 64)`` of the keypoints. Keypoints are sorted by window size; each
    static window class runs a loop (dynamic trip count) over chunks of its own keypoints,
    with chunks of about ``CHUNK_SAMPLES`` window samples; the loops write into one buffer.
    Within a class of windows up to half the image's shorter side, rotated windows that lie
    inside the image come first, so that whole chunks of them skip the border fallback
    (``fast_inside=False`` never skips it; the descriptors agree to ~1e-5)."""
    n = x.shape[0]
    s = _scale(size)
    win = jnp.where(valid, (_f32(PATCH_SZ + 1) * s).astype(jnp.int32), 0)
    classes = _window_classes(max_win)
    bounds = jnp.asarray(classes, jnp.int32)
    cls = jnp.where(valid, jnp.searchsorted(bounds, win, side="left"), len(classes))
    # Classes whose windows often lie inside the image get a second loop without the border
    # fallback (each costs compile time; larger windows are mostly at the border).
    fast = [] if upright or not fast_inside else [wb for wb in classes if 2 * wb <= min(img.shape)]
    border = jnp.zeros(n, bool)
    wb_kp = bounds[jnp.minimum(cls, len(classes) - 1)]
    for wb in fast:  # each keypoint's grid at its own class size
        border = jnp.where(wb_kp == wb, ~_window_inside(x, y, win, ang, wb, *img.shape), border)
    border = border.astype(jnp.int32)
    key = 2 * cls + border  # class, then inside (0) before border (1)
    order = jnp.argsort(key, stable=True)
    skey = key[order]
    cmax = max(max(1, CHUNK_SAMPLES // (wb * wb)) for wb in classes)

    def prep(a):
        return jnp.pad(a[order], (0, cmax))

    cx, cy, wn, an = prep(x), prep(y), prep(win), prep(ang)
    quad = None if upright else pack_quads(img)
    acc = jnp.zeros((n + cmax, 64), _F32)
    for c, wb in enumerate(classes):
        csz = max(1, CHUNK_SAMPLES // (wb * wb))
        lo = jnp.searchsorted(skey, 2 * c, side="left").astype(jnp.int32)
        mid = jnp.searchsorted(skey, 2 * c, side="right").astype(jnp.int32)
        hi = jnp.searchsorted(skey, 2 * c + 1, side="right").astype(jnp.int32)

        def body(it, acc, lo=lo, hi=hi, csz=csz, wb=wb, inside=False):
            start = lo + it * csz
            bx, by, bw, ba = (lax.dynamic_slice(a, (start,), (csz,)) for a in (cx, cy, wn, an))
            mine = start + jnp.arange(csz, dtype=jnp.int32) < hi
            # rows past the segment repeat its first row (their results are dropped), so
            # that every row of a chunk of inside windows is inside too
            bx, by, bw, ba = (jnp.where(mine, a, a[0]) for a in (bx, by, bw, ba))
            g = _resize_batch(img, quad, bx, by, bw, ba, wb, upright, inside)
            d = _patch_descriptor(g, bw)
            z = jnp.int32(0)
            old = lax.dynamic_slice(acc, (start, z), (csz, 64))
            return lax.dynamic_update_slice(acc, jnp.where(mine[:, None], d, old), (start, z))

        if wb in fast:  # the inside windows of this class, then those at the border
            inside = functools.partial(body, lo=lo, hi=mid, inside=True)
            acc = lax.fori_loop(0, (mid - lo + csz - 1) // csz, inside, acc)
            acc = lax.fori_loop(0, (hi - mid + csz - 1) // csz, functools.partial(body, lo=mid), acc)
        else:
            acc = lax.fori_loop(0, (hi - lo + csz - 1) // csz, body, acc)
    return jnp.zeros((n, 64), _F32).at[order].set(acc[:n])


describe_jit = jax.jit(describe, static_argnames=("upright", "max_win", "fast_inside"))
""":func:`describe` compiled on its own (the descriptor parts of :func:`jaxslam.vision.surf`)."""


def max_window(plan) -> int:
    """Largest descriptor window a keypoint of this pyramid can ask for (0 if none can be
    detected): the largest middle layer whose upper neighbour fits, plus one size step."""
    nl = sum(1 for lp in plan if lp["octave"] == 0)
    best = 0
    for k, lp in enumerate(plan):
        if 0 < lp["layer"] < nl - 1 and plan[k + 1]["computed"]:
            size = _f32(lp["size"] + (lp["size"] - plan[k - 1]["size"]))
            s = (size * _f32(1.2)) / _f32(9.0)
            best = max(best, int(_f32(PATCH_SZ + 1) * s) + 1)
    return best


@functools.partial(jax.jit, static_argnames=("max_keypoints", "n_octaves", "n_layers", "upright", "descriptors"))
def surf_u8(
    img_u8: jax.Array,
    threshold,
    max_keypoints: int = 8192,
    n_octaves: int = 4,
    n_layers: int = 3,
    upright: bool = False,
    descriptors: bool = True,
):
    """SURF on one 8-bit grey image ``(H, W)``. Returns ``(keypoints (N, 7) float32,
    descriptors (N, 64) float32, valid (N,) bool)`` with ``N = max_keypoints``; valid rows come
    first, in OpenCV's order. Invalid rows are zero."""
    kp = detect(img_u8, threshold, max_keypoints, n_octaves, n_layers)
    S = integral_image(img_u8)
    hs, ws = S.shape
    s = _scale(kp["size"])
    g = 2 * jnp.round(2 * s).astype(jnp.int32)
    valid = kp["valid"] & (hs >= g) & (ws >= g)
    if upright:
        ang = jnp.full(kp["x"].shape, 270.0, _F32)
    else:
        ang, sampled = orientation(S, kp["x"], kp["y"], kp["size"], valid, runtime_one(threshold))
        valid = valid & sampled
    # Compact: deleted keypoints leave, order kept.
    order = jnp.argsort(~valid, stable=True)
    valid = valid[order]
    x, y, size, ang = kp["x"][order], kp["y"][order], kp["size"][order], ang[order]
    cols = [x, y, size, ang, kp["response"][order], kp["octave"][order].astype(_F32), kp["lap"][order].astype(_F32)]
    keypoints = jnp.where(valid[:, None], jnp.stack(cols, -1), 0)
    mw = max_window(layer_plan(*img_u8.shape, n_octaves, n_layers))
    if descriptors and mw > 0:
        desc = describe(img_u8, x, y, size, ang, valid, upright, mw)
        desc = jnp.where(valid[:, None], desc, 0)
    else:
        desc = jnp.zeros((x.shape[0], 64), _F32)
    return keypoints, desc, valid
