"""Return intensity as a surface pattern that registration can use (the tunnel axis).

A LiDAR's intensity mixes what belongs to the surface (its reflectance: stains, joints, pipes,
paint) with what belongs to the viewing geometry (incidence angle, range, the sensor's gain).
Only the first is the same from every viewpoint, so :func:`relative_reflectivity` removes the
second in two steps:

1. **Incidence**: over the scan, fit ``I ≈ a + b cos(theta)`` (``theta`` between the ray and
   the local PCA normal) by least squares on the planar points, and divide it out (a
   Lambertian surface with a sensor offset follows this model; the fit adapts to the sensor).
2. **Local contrast**: divide by the mean over the neighbourhood (a cube of side ``2 radius``)
   and subtract 1:
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
    normal_neighbors: int = 12,
    min_planarity: float = 0.7,
    smooth: float = 0.0,
    max_range: float = np.inf,
    balance: float = 0.25,
) -> np.ndarray:
    """Relative surface reflectivity ``(N,)`` of a scan's points ``(N, 3)`` (sensor frame:
    rays from the origin) with raw ``intensity`` ``(N,)``; ``NaN`` where undefined. See the
    module docstring. The local mean is taken over the cube of side ``2 radius`` around each
    point (3 x 3 x 3 voxels of side ``2/3 radius``: linear time); ``smooth`` > 0 then averages
    each value over the ``normal_neighbors`` nearest points within that radius."""
    p = check_points(points, "points")
    inten = np.asarray(intensity, dtype=np.float64).reshape(-1)
    if inten.shape != (len(p),):
        raise InputFormatError(f"intensity must have shape ({len(p)},) to match the points, got {inten.shape}")
    if not np.all(np.isfinite(inten)):
        raise InputFormatError("intensity contains NaN or infinite values")
    out = np.full(len(p), np.nan)
    rng = np.linalg.norm(p, axis=1)
    sel = np.nonzero(rng <= max_range + radius)[0]  # what the range limit keeps, and its neighbourhoods
    q, qi = p[sel], inten[sel]
    if len(q) < max(normal_neighbors, 8):
        return out
    dist, idx = cKDTree(q).query(q, k=min(normal_neighbors, len(q)), workers=1)
    normals, planarity = estimate_normals(q[idx])
    rays = q / np.maximum(rng[sel, None], 1e-9)
    cos = np.abs(np.einsum("ij,ij->i", normals, rays))
    planar = planarity >= min_planarity
    if planar.sum() < 8:
        return out
    A = np.stack([np.ones(int(planar.sum())), cos[planar]], axis=1)
    coef, *_ = np.linalg.lstsq(A, qi[planar], rcond=None)
    model = coef[0] + coef[1] * cos
    floor = 0.05 * max(float(np.mean(qi[planar])), 1e-9)
    corrected = qi / np.maximum(model, floor)
    cnt, local, centroid, centre = _block_means(q, corrected, 2.0 * radius / 3.0)
    # a neighbourhood cut by the edge of what the scan covers (its field of view, a range
    # limit) is one-sided: its mean is biased by the pattern on one side, and that edge moves
    # with the sensor, so the pattern would move with it. Keep centred neighbourhoods only.
    off = centroid - centre  # ~0 where the surface fills the block
    off -= np.einsum("ij,ij->i", off, normals)[:, None] * normals
    centred = np.linalg.norm(off, axis=1) <= balance * radius
    ok = planar & (local > 1e-9) & (cnt >= normal_neighbors) & centred & (rng[sel] <= max_range)
    val = np.full(len(q), np.nan)
    val[ok] = corrected[ok] / local[ok] - 1.0
    if smooth > 0:
        vals = np.where(dist <= smooth, val[idx], np.nan)
        fin = np.isfinite(vals)
        n = fin.sum(axis=1)
        avg = np.where(fin, vals, 0.0).sum(axis=1) / np.maximum(n, 1)
        val = np.where(np.isfinite(val) & (n >= 3), avg, np.nan)
    out[sel] = val
    return out


def _block_means(p: np.ndarray, v: np.ndarray, voxel: float) -> tuple[np.ndarray, ...]:
    """Per point: the count, the mean of ``v`` and the centroid of the points in its voxel's
    3 x 3 x 3 block (voxels of side ``voxel``), and the centre of that voxel."""
    ijk0 = np.floor(p / voxel).astype(np.int64)
    centre = (ijk0 + 0.5) * voxel
    ijk = ijk0 - (ijk0.min(axis=0) - 1)  # >= 1: every neighbour index stays >= 0
    dims = ijk.max(axis=0) + 2
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    uniq, inv = np.unique(key, return_inverse=True)
    sums = np.zeros((len(uniq), 5))
    np.add.at(sums, inv, np.c_[np.ones(len(p)), v, p])
    block = np.zeros_like(sums)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                nk = uniq + (dx * dims[1] + dy) * dims[2] + dz
                j = np.searchsorted(uniq, nk)
                hit = (j < len(uniq)) & (uniq[np.minimum(j, len(uniq) - 1)] == nk)
                block[hit] += sums[j[hit]]
    b = block[inv]
    n = b[:, 0]
    return n, b[:, 1] / np.maximum(n, 1), b[:, 2:] / np.maximum(n, 1)[:, None], centre
