"""Scan Context place recognition (Kim and Kim, IROS 2018), and submaps to feed it.

A descriptor is a ``num_rings x num_sectors`` polar grid around the sensor in its x-y plane
(rings by horizontal range up to ``max_radius``, sectors by azimuth from -pi), each bin
holding the maximum point height ``z + height_offset`` (0 for an empty bin, heights clipped
at 0). The ring key (fraction of occupied sectors per ring) is yaw-invariant and picks
candidates; the distance is the mean cosine distance between matching columns, minimised
over column shifts, i.e. over yaw. Columns empty in both are skipped; a column occupied in
only one counts as distance 1 (the original skips those too, which lets two sparse
descriptors that overlap in a single column look identical).

Yaw convention: ``distance(query, candidate)`` returns ``(d, yaw)`` with ``yaw`` the rotation
about z of the query frame in the candidate frame (``candidate_R_query ~ Rz(yaw)``), a
multiple of ``2 pi / num_sectors``.

A forward-looking sensor (the HAP's 120 degrees) fills a third of the sectors, and the same
place seen in the opposite direction shares none of them; build the descriptor from an
aggregated submap (:func:`submap_points`: several registered scans moved into one pose's
frame) instead.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..errors import InputFormatError
from ._preprocess import check_points, voxel_downsample


@dataclasses.dataclass(frozen=True)
class ScanContext:
    """A Scan Context descriptor."""

    descriptor: np.ndarray
    """(num_rings, num_sectors) max height per bin (m), 0 where empty."""
    ring_key: np.ndarray
    """(num_rings,) fraction of occupied sectors per ring (yaw-invariant)."""

    def distance(self, other: ScanContext) -> tuple[float, float]:
        """``(d, yaw)``: mean column cosine distance in [0, 1] at the best column shift and
        the yaw of this (query) frame in ``other``'s frame (see the module docstring)."""
        return _sc_distance(self.descriptor, other.descriptor)


class PlaceMatch(NamedTuple):
    """A database answer."""

    id: int
    distance: float
    yaw: float


def scan_context(
    points,
    num_rings: int = 20,
    num_sectors: int = 60,
    max_radius: float = 20.0,
    height_offset: float = 2.0,
) -> ScanContext:
    """The Scan Context of points ``(N, 3)`` in the sensor (or submap centre) frame."""
    p = check_points(points)
    if num_rings < 1 or num_sectors < 2 or not max_radius > 0:
        raise InputFormatError("scan_context needs num_rings >= 1, num_sectors >= 2, max_radius > 0")
    r = np.hypot(p[:, 0], p[:, 1])
    keep = (r < max_radius) & (r > 0)
    p, r = p[keep], r[keep]
    ring = np.minimum((r / max_radius * num_rings).astype(np.int64), num_rings - 1)
    az = np.arctan2(p[:, 1], p[:, 0])
    sector = np.minimum(((az + np.pi) / (2 * np.pi) * num_sectors).astype(np.int64), num_sectors - 1)
    flat = np.zeros(num_rings * num_sectors)
    np.maximum.at(flat, ring * num_sectors + sector, np.maximum(p[:, 2] + height_offset, 0.0))
    desc = flat.reshape(num_rings, num_sectors)
    return ScanContext(desc, np.mean(desc > 0, axis=1))


def submap_points(
    clouds: Sequence[np.ndarray], world_T_sensors, world_T_center, voxel: float | None = 0.2
) -> np.ndarray:
    """Scans ``clouds[k]`` ``(N_k, 3)`` (sensor frames, deskewed) at poses ``world_T_sensors``
    ``(K, 4, 4)`` gathered in the frame of ``world_T_center`` ``(4, 4)``, voxel-downsampled
    (``voxel`` m; ``None`` keeps all)."""
    Ts = np.asarray(world_T_sensors, dtype=np.float64)
    Tc = np.asarray(world_T_center, dtype=np.float64)
    if Ts.shape != (len(clouds), 4, 4) or Tc.shape != (4, 4):
        raise InputFormatError(f"need ({len(clouds)}, 4, 4) scan poses and a (4, 4) centre, got {Ts.shape}, {Tc.shape}")
    Rc, tc = Tc[:3, :3], Tc[:3, 3]
    parts = [(check_points(c) @ T[:3, :3].T + T[:3, 3] - tc) @ Rc for c, T in zip(clouds, Ts)]
    out = np.concatenate(parts) if parts else np.zeros((0, 3))
    if voxel is None:
        return out
    return np.asarray(voxel_downsample(out, voxel))


class ScanContextDatabase:
    """Descriptors by integer id; queries by ring key, then full Scan Context distance."""

    def __init__(self, num_candidates: int = 10):
        self.num_candidates = num_candidates
        self._ids: list[int] = []
        self._descs: list[ScanContext] = []

    def __len__(self) -> int:
        return len(self._ids)

    def add(self, id: int, descriptor: ScanContext) -> None:
        """Store ``descriptor`` under ``id`` (insertion order defines "recent")."""
        if self._descs and descriptor.descriptor.shape != self._descs[0].descriptor.shape:
            raise InputFormatError(
                f"descriptor shape {descriptor.descriptor.shape} differs from {self._descs[0].descriptor.shape}"
            )
        self._ids.append(int(id))
        self._descs.append(descriptor)

    def query(self, descriptor: ScanContext, k: int = 1, exclude_recent: int = 0) -> list[PlaceMatch]:
        """The ``k`` best matches (smallest distance first) among all but the
        ``exclude_recent`` most recently added; ``num_candidates`` are preselected by ring key."""
        n = len(self._ids) - max(exclude_recent, 0)
        if n <= 0:
            return []
        keys = np.stack([d.ring_key for d in self._descs[:n]])
        kd = np.linalg.norm(keys - descriptor.ring_key, axis=1)
        cand = np.argsort(kd, kind="stable")[: max(self.num_candidates, k)]
        matches = [PlaceMatch(self._ids[i], *descriptor.distance(self._descs[i])) for i in cand]
        return sorted(matches, key=lambda m: m.distance)[:k]


def _sc_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    ns = a.shape[1]
    shifts = np.arange(ns)
    rolled = np.stack([np.roll(a, s, axis=1) for s in shifts])  # (S, R, C)
    na = np.linalg.norm(rolled, axis=1)  # (S, C)
    nb = np.linalg.norm(b, axis=0)  # (C,)
    dot = np.einsum("src,rc->sc", rolled, b)
    both = (na > 0) & (nb > 0)
    cos = np.where(both, dot / np.where(both, na * nb, 1.0), 0.0)
    cnt = ((na > 0) | (nb > 0)).sum(axis=1)
    dist = np.where(cnt > 0, 1.0 - cos.sum(axis=1) / np.maximum(cnt, 1), 1.0)
    best = int(np.argmin(dist))
    yaw = best * 2 * np.pi / ns
    return float(dist[best]), float((yaw + np.pi) % (2 * np.pi) - np.pi)
