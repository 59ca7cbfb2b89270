"""Return intensity as a surface pattern that registration can use (the tunnel axis).

A LiDAR's intensity mixes what belongs to the surface (its reflectance: stains, joints, pipes,
paint) with what belongs to the viewing geometry (incidence angle, range, the sensor's gain).
Only the first is the same from every viewpoint, so :func:`relative_reflectivity` removes the
second in two steps:

1. **Incidence**: over the scan, fit ``I ≈ a + b cos(theta)`` (``theta`` between the ray and
   the local PCA normal) by least squares on the planar points, and divide it out (a
   Lambertian surface with a sensor offset follows this model; the fit adapts to the sensor).
2. **Local contrast**: divide by the mean over the neighbours within ``radius`` (at most
   ``max_neighbors`` of them) and subtract 1:
   what remains is the surface's relative pattern (``-0.45`` on a stain 45 % darker than its
   surroundings, ``0`` on uniform concrete), blind to a smooth change of gain or incidence
   across the scan.

Points whose neighbourhood is not planar or too small, and points beyond ``max_range``, get
``NaN`` (registration skips them). Far returns meet the surface at grazing angles and sparsely:
their pattern comes out shifted towards the sensor by centimetres, by more the farther (on the
simulated tunnel a scan registered to a map of views 0-1.5 m behind it came out ~2 cm short
with all ranges, unbiased within 4-6 m), so keep ``max_range`` to a few metres.
Used by :func:`jaxslam.lidar.register` (``source_intensity``) and :class:`VoxelMap`
(``add(..., intensity=...)``): in a tunnel of plain walls the geometry cannot see the axis,
the reflectance pattern can.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputFormatError
from ._preprocess import check_points
from ._voxel_map import estimate_normals


def relative_reflectivity(
    points,
    intensity,
    radius: float = 0.6,
    max_neighbors: int = 96,
    normal_neighbors: int = 12,
    min_planarity: float = 0.7,
    smooth: float = 0.0,
    max_range: float = np.inf,
    balance: float = 0.25,
) -> np.ndarray:
    """Relative surface reflectivity ``(N,)`` of a scan's points ``(N, 3)`` (sensor frame:
    rays from the origin) with raw ``intensity`` ``(N,)``; ``NaN`` where undefined. See the
    module docstring."""
    p = check_points(points, "points")
    inten = np.asarray(intensity, dtype=np.float64).reshape(-1)
    if inten.shape != (len(p),):
        raise InputFormatError(f"intensity must have shape ({len(p)},) to match the points, got {inten.shape}")
    if not np.all(np.isfinite(inten)):
        raise InputFormatError("intensity contains NaN or infinite values")
    out = np.full(len(p), np.nan)
    if len(p) < max(normal_neighbors, 8):
        return out
    tree = cKDTree(p)
    k = min(max_neighbors, len(p))
    dist, idx = tree.query(p, k=k, distance_upper_bound=radius, workers=1)
    near = np.isfinite(dist)
    idx = np.where(near, idx, 0)
    kn = min(normal_neighbors, k)
    normals, planarity = estimate_normals(p[idx[:, :kn]], near[:, :kn])
    rays = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
    cos = np.abs(np.einsum("ij,ij->i", normals, rays))
    planar = planarity >= min_planarity
    if planar.sum() < 8:
        return out
    A = np.stack([np.ones(int(planar.sum())), cos[planar]], axis=1)
    coef, *_ = np.linalg.lstsq(A, inten[planar], rcond=None)
    model = coef[0] + coef[1] * cos
    floor = 0.05 * max(float(np.mean(inten[planar])), 1e-9)
    corrected = inten / np.maximum(model, floor)
    cnt = near.sum(axis=1)
    local = np.where(near, corrected[idx], 0.0).sum(axis=1) / np.maximum(cnt, 1)
    # a neighbourhood cut by the edge of what the scan covers (its field of view, a range
    # limit) is one-sided: its mean is biased by the pattern on one side, and that edge moves
    # with the sensor, so the pattern would move with it. Keep centred neighbourhoods only.
    centroid = np.where(near[..., None], p[idx], 0.0).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    off = centroid - p
    off -= np.einsum("ij,ij->i", off, normals)[:, None] * normals
    centred = np.linalg.norm(off, axis=1) <= balance * radius
    ok = planar & (local > 1e-9) & (cnt >= normal_neighbors) & centred
    out[ok] = corrected[ok] / local[ok] - 1.0
    out[np.linalg.norm(p, axis=1) > max_range] = np.nan
    if smooth > 0:
        within = near & (dist <= smooth)
        vals = np.where(within, out[idx], np.nan)
        fin = np.isfinite(vals)
        n = fin.sum(axis=1)
        avg = np.where(fin, vals, 0.0).sum(axis=1) / np.maximum(n, 1)
        out = np.where(np.isfinite(out) & (n >= 3), avg, np.nan)
    return out
