"""One entry point for local features: SURF (JAX, OpenCV-exact) and OpenCV's SIFT and ORB.

``detect_and_describe(image, detector=...)`` returns ``(keypoints, descriptors)`` as numpy
arrays: keypoints ``(N, 7)`` float64 with the columns ``x, y, size, angle_deg, response,
octave, laplacian_sign`` (OpenCV's ``KeyPoint``; the Laplacian sign is 0 for SIFT and ORB),
descriptors ``(N, 64)`` float32 for SURF, ``(N, 128)`` float32 for SIFT, ``(N, 32)`` uint8 for
ORB. For jit-composable SURF use :func:`surf`, which returns fixed-size arrays and a mask.

The SURF patent (US 8,165,401) may still be in force in some places until about 2027; SIFT
(patent expired) is the alternative.
"""

from __future__ import annotations

from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from .._threads import parallel_map, workers
from ..errors import InputFormatError
from ._surf import describe_jit, layer_plan, max_window, surf_u8

Detector = Literal["surf", "sift", "orb"]
DETECTORS = ("surf", "sift", "orb")
DEFAULT_MAX_KEYPOINTS = 4096


def to_gray_u8(image, name: str = "image") -> np.ndarray:
    """Check an image and return it as 8-bit grey ``(H, W)``.

    Accepts uint8 grey ``(H, W)`` / ``(H, W, 1)``, uint8 RGB(A) ``(H, W, 3|4)`` (grey by
    PIL's ``convert('L')`` weights, as the golden files were made) and floating point in
    ``[0, 1]`` (scaled to 0..255 and rounded). Raises :class:`InputFormatError` on other
    dtypes, shapes, empty images or non-finite values."""
    try:
        arr = np.asarray(image)
    except Exception as exc:  # ragged lists and the like
        raise InputFormatError(f"{name}: not an array ({exc})") from exc
    dt = arr.dtype
    if arr.ndim == 3 and arr.shape[-1] in (1, 3, 4):
        pass
    elif arr.ndim != 2:
        raise InputFormatError(f"{name}: expected an (H, W) or (H, W, 3) image, got shape {arr.shape}")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise InputFormatError(f"{name}: empty image of size {arr.shape[0]}x{arr.shape[1]}")
    if dt == np.uint8:
        u8 = arr
    elif np.issubdtype(dt, np.floating):
        if not np.all(np.isfinite(arr)):
            raise InputFormatError(f"{name}: contains NaN or infinite values")
        u8 = np.clip(np.rint(arr.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    else:
        raise InputFormatError(f"{name}: dtype must be uint8 (0..255) or floating point (0..1), got {dt}")
    if u8.ndim == 3:
        if u8.shape[-1] == 1:
            u8 = u8[..., 0]
        else:  # PIL convert('L'): (19595 R + 38470 G + 7471 B + 0x8000) >> 16
            rgb = u8[..., :3].astype(np.uint32)
            u8 = ((rgb[..., 0] * 19595 + rgb[..., 1] * 38470 + rgb[..., 2] * 7471 + 0x8000) >> 16).astype(np.uint8)
    return np.ascontiguousarray(u8)


def surf(
    image,
    hessian_threshold: float = 100.0,
    max_keypoints: int = DEFAULT_MAX_KEYPOINTS,
    upright: bool = False,
    n_octaves: int = 4,
    n_layers: int = 3,
    parallel: bool = True,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """SURF with OpenCV's semantics on an 8-bit grey image (``hessian_threshold`` in 8-bit
    intensity units, like ``cv2.xfeatures2d.SURF_create``). Returns fixed-size
    ``(keypoints (max_keypoints, 7), descriptors (max_keypoints, 64), valid (max_keypoints,))``
    float32/float32/bool, valid rows first in OpenCV's order (best response first). Traceable
    in ``image`` (uint8) and ``hessian_threshold``. With concrete inputs on a machine with
    more than one core the descriptors are computed in one part per core (every part-th
    keypoint) on a thread pool, the same numbers as one call (XLA:CPU runs one call's loops
    on one core; KITTI frame, 2-core AMD EPYC: 130 -> 101 ms); ``parallel=False`` keeps one
    call."""
    if max_keypoints < 1:
        raise ValueError(f"max_keypoints must be >= 1, got {max_keypoints}")
    if n_octaves < 1 or n_layers < 1:
        raise ValueError(f"n_octaves and n_layers must be >= 1, got {n_octaves}, {n_layers}")
    if isinstance(image, jax.Array) and image.dtype == jnp.uint8 and image.ndim == 2:
        img = image
    else:
        img = jnp.asarray(to_gray_u8(image))
    h, w = img.shape
    if max_window(layer_plan(h, w, n_octaves, n_layers)) == 0:  # too small for any filter
        return (
            jnp.zeros((max_keypoints, 7), jnp.float32),
            jnp.zeros((max_keypoints, 64), jnp.float32),
            jnp.zeros((max_keypoints,), bool),
        )
    concrete = not any(isinstance(a, jax.core.Tracer) for a in (img, hessian_threshold))
    split = parallel and concrete and workers() > 1  # descriptors in parts, after detection
    kp, desc, valid = surf_u8(
        img,
        hessian_threshold,
        max_keypoints=max_keypoints,
        n_octaves=n_octaves,
        n_layers=n_layers,
        upright=upright,
        descriptors=not split,
    )
    if split:
        desc = _describe_parts(img, kp, valid, upright, max_window(layer_plan(h, w, n_octaves, n_layers)))
    return kp, desc, valid


def _describe_parts(img: jax.Array, kp: jax.Array, valid: jax.Array, upright: bool, max_win: int) -> jax.Array:
    """Descriptors of the keypoint rows ``kp`` in ``workers()`` parts of every part-th row
    (padded to one size, so one compile; each part holds the same mix of window sizes), on
    the shared thread pool, joined in row order."""
    parts = workers()
    n = kp.shape[0]
    size = -(-n // parts)
    cols = jnp.pad(kp[:, :4], ((0, size * parts - n), (0, 0)))
    ok = jnp.pad(valid, (0, size * parts - n))

    def part(i: int) -> jax.Array:
        c = cols[i::parts]
        return jax.block_until_ready(
            describe_jit(img, c[:, 0], c[:, 1], c[:, 2], c[:, 3], ok[i::parts], upright=upright, max_win=max_win)
        )

    return _join_parts(parallel_map(part, range(parts)), valid)


@jax.jit
def _join_parts(descs: list[jax.Array], valid: jax.Array) -> jax.Array:
    d = jnp.stack(descs, 1).reshape(-1, descs[0].shape[-1])[: valid.shape[0]]
    return jnp.where(valid[:, None], d, 0.0)


def _cv_keypoints(kps) -> np.ndarray:
    out = np.zeros((len(kps), 7), np.float64)
    for k, kp in enumerate(kps):
        out[k] = (kp.pt[0], kp.pt[1], kp.size, kp.angle, kp.response, kp.octave, 0.0)
    return out


def detect_and_describe(
    image,
    detector: Detector = "surf",
    hessian_threshold: float = 100.0,
    max_keypoints: int = DEFAULT_MAX_KEYPOINTS,
    upright: bool = False,
    parallel: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints ``(N, 7)`` (x, y, size, angle°, response, octave, Laplacian sign) and
    descriptors of one image with ``detector`` = ``"surf"`` (this package), ``"sift"`` or
    ``"orb"`` (OpenCV). ``hessian_threshold``, ``upright`` and ``parallel`` (descriptors on
    every core, see :func:`surf`) apply to SURF; ``max_keypoints`` caps every detector (best
    responses kept)."""
    if detector not in DETECTORS:
        raise ValueError(f"detector must be one of {', '.join(DETECTORS)}, got {detector!r}")
    if max_keypoints < 1:
        raise ValueError(f"max_keypoints must be >= 1, got {max_keypoints}")
    gray = to_gray_u8(image)
    if detector == "surf":
        kp, desc, valid = surf(
            gray, float(hessian_threshold), max_keypoints=max_keypoints, upright=upright, parallel=parallel
        )
        n = int(np.sum(np.asarray(valid)))
        return np.asarray(kp, np.float64)[:n], np.asarray(desc)[:n]  # numpy slices: no compile per n
    import cv2

    dim, dtype = (128, np.dtype(np.float32)) if detector == "sift" else (32, np.dtype(np.uint8))
    create = cv2.SIFT_create if detector == "sift" else cv2.ORB_create  # type: ignore[attr-defined]
    det = create(nfeatures=max_keypoints)
    kps, desc = det.detectAndCompute(gray, None)
    kps = list(kps)[:max_keypoints]
    if desc is None or not kps:
        return np.zeros((0, 7)), np.zeros((0, dim), dtype)
    return _cv_keypoints(kps), np.asarray(desc[: len(kps)], dtype)
