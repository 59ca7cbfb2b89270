"""Scan preprocessing: input checks, range crop and voxel downsampling.

Voxels are cubes of side ``voxel`` anchored at the origin of the points' frame; a voxel is
keyed by its integer coordinates packed into one int64 (21 bits per axis, so +-1,048,575
voxels: +-52 km at 5 cm). Downsampling keeps the *first* point (in input order) of every
occupied voxel: deterministic, no averaging (a kept point is a real measurement, attributes
stay consistent), and the output stays in input order.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputFormatError

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def check_points(points, name: str = "points", allow_empty: bool = True) -> np.ndarray:
    """``points`` as a float64 ``(N, 3)`` array; raises :class:`InputFormatError` on a wrong
    shape, non-finite values, or (``allow_empty=False``) no points."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputFormatError(f"{name} must have shape (N, 3), got {p.shape}")
    if not allow_empty and len(p) == 0:
        raise InputFormatError(f"{name} is empty")
    if not np.all(np.isfinite(p)):
        bad = int(np.sum(~np.all(np.isfinite(p), axis=1)))
        raise InputFormatError(f"{name} has {bad} non-finite rows (drop them with crop_range first)")
    return p


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """int64 key ``(N,)`` of the voxel of side ``voxel`` holding each point ``(N, 3)``."""
    if not voxel > 0:
        raise InputFormatError(f"voxel size must be positive, got {voxel}")
    ijk = np.floor(points / voxel).astype(np.int64) + _OFFSET
    if len(ijk) and (ijk.min() < 0 or ijk.max() > _MASK):
        raise InputFormatError(f"points beyond +-{_OFFSET * voxel:.0f} m do not fit the voxel key")
    return (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]


def voxel_downsample_indices(points, voxel: float) -> np.ndarray:
    """Sorted indices of the points :func:`voxel_downsample` keeps (first point per voxel)."""
    p = check_points(points)
    if len(p) == 0:
        return np.zeros(0, dtype=np.int64)
    _, first = np.unique(voxel_keys(p, voxel), return_index=True)
    return np.sort(first)


def voxel_downsample(points, voxel: float, *attrs: np.ndarray) -> np.ndarray | tuple[np.ndarray, ...]:
    """One point per occupied voxel of side ``voxel`` (m): the first in input order.

    ``attrs`` (per-point arrays with leading axis N: times, intensity, rings) are filtered
    alike. Returns the points ``(M, 3)`` alone when no ``attrs`` are given, else the tuple
    ``(points, *attrs)``. Deterministic; output in input order; at most one point per voxel.
    """
    p = check_points(points)
    keep = voxel_downsample_indices(p, voxel)
    if not attrs:
        return p[keep]
    return (p[keep], *(_attr(a, len(p))[keep] for a in attrs))


def crop_range(
    points, min_range: float = 0.5, max_range: float = 100.0, *attrs: np.ndarray
) -> np.ndarray | tuple[np.ndarray, ...]:
    """Keep finite points with ``min_range <= |p| <= max_range`` (m, from the frame origin).

    Non-finite rows are dropped here (the one place they are tolerated). Returns like
    :func:`voxel_downsample`."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputFormatError(f"points must have shape (N, 3), got {p.shape}")
    finite = np.all(np.isfinite(p), axis=1)
    r = np.linalg.norm(np.where(finite[:, None], p, 0.0), axis=1)
    keep = finite & (r >= min_range) & (r <= max_range)
    if not attrs:
        return p[keep]
    return (p[keep], *(_attr(a, len(p))[keep] for a in attrs))


def _attr(a, n: int) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim == 0 or a.shape[0] != n:
        raise InputFormatError(f"per-point attribute has shape {a.shape}, expected leading axis {n}")
    return a
