"""The sparse visual map after the run (the paper's Table 10): feature tracks across keyframes,
points triangulated from all their observations at the optimised camera poses, refined by a
structure-only bundle adjustment (Gauss-Newton per point, Huber; poses held), then the
reprojection residuals of every observation.

Tracks come from the visual front end: a feature matched as a RANSAC + reprojection inlier to
the previous keyframe inherits its track id. Observations are undistorted normalised
coordinates; residuals are reported in pixels (times the focal length)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..lie import host


@dataclasses.dataclass
class SparseMap:
    points: np.ndarray
    """(P, 3) world points."""
    track_lengths: np.ndarray
    """(P,) observations per point."""
    residuals_px: np.ndarray
    """(M,) reprojection error of every observation of every kept point (px)."""

    def statistics(self) -> dict[str, Any]:
        L, e = self.track_lengths, self.residuals_px
        return {
            "points": len(L),
            "residuals": len(e),
            "track_length_min": int(L.min()) if len(L) else 0,
            "track_length_mean": float(L.mean()) if len(L) else 0.0,
            "track_length_max": int(L.max()) if len(L) else 0,
            "reproj_rmse_px": float(np.sqrt(np.mean(e**2))) if len(e) else float("nan"),
            "residuals_below_1px": float(np.mean(e < 1.0)) if len(e) else float("nan"),
        }


def build_sparse_map(
    keyframes: list, poses: np.ndarray, T_bc: np.ndarray, f: float, iterations: int = 8, huber_px: float = 2.0
) -> SparseMap:
    """Triangulate and refine every track seen by at least two keyframes (see the module doc)."""
    obs_kf, obs_x, obs_track = [], [], []
    for kf in keyframes:
        if kf.features is None or not kf.registered:
            continue
        obs_kf.append(np.full(len(kf.features.track), kf.index))
        obs_x.append(kf.features.xn)
        obs_track.append(kf.features.track)
    if not obs_kf:
        return SparseMap(np.zeros((0, 3)), np.zeros(0, int), np.zeros(0))
    kfi, x, tr = np.concatenate(obs_kf), np.concatenate(obs_x), np.concatenate(obs_track)
    _, inverse, counts = np.unique(tr, return_inverse=True, return_counts=True)
    keep = counts[inverse] >= 2
    kfi, x, pid = kfi[keep], x[keep], inverse[keep]
    _, pid = np.unique(pid, return_inverse=True)
    n_pts = int(pid.max()) + 1 if len(pid) else 0
    T_cw = host.inverse(poses[kfi] @ T_bc)  # world -> camera per observation
    R, t = T_cw[:, :3, :3], T_cw[:, :3, 3]
    # linear triangulation (DLT rows: x * r3 - r1, y * r3 - r2), accumulated per point
    P = np.concatenate([R, t[:, :, None]], axis=2)  # (M, 3, 4)
    rows = np.stack([x[:, 0:1] * P[:, 2] - P[:, 0], x[:, 1:2] * P[:, 2] - P[:, 1]], axis=1)  # (M, 2, 4)
    A = np.zeros((n_pts, 4, 4))
    np.add.at(A, pid, np.einsum("mki,mkj->mij", rows, rows))
    _, vecs = np.linalg.eigh(A)
    Xh = vecs[:, :, 0]
    X = Xh[:, :3] / np.where(np.abs(Xh[:, 3:]) < 1e-12, 1e-12, Xh[:, 3:])
    delta = huber_px / f
    for _ in range(iterations):  # Gauss-Newton per point (3x3 systems), poses held
        Xc = np.einsum("mij,mj->mi", R, X[pid]) + t
        z = np.maximum(Xc[:, 2], 1e-6)
        r = Xc[:, :2] / z[:, None] - x
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= delta, 1.0, delta / np.maximum(e, 1e-12))
        dproj = np.zeros((len(x), 2, 3))
        dproj[:, 0, 0] = dproj[:, 1, 1] = 1.0 / z
        dproj[:, 0, 2] = -Xc[:, 0] / z**2
        dproj[:, 1, 2] = -Xc[:, 1] / z**2
        J = dproj @ R  # d r / d X_world
        H = np.zeros((n_pts, 3, 3))
        g = np.zeros((n_pts, 3))
        np.add.at(H, pid, w[:, None, None] * np.einsum("mki,mkj->mij", J, J))
        np.add.at(g, pid, w[:, None] * np.einsum("mki,mk->mi", J, r))
        ok = np.linalg.det(H) > 1e-18
        step = np.zeros_like(X)
        step[ok] = -np.linalg.solve(H[ok], g[ok][:, :, None])[:, :, 0]
        X = X + step
    Xc = np.einsum("mij,mj->mi", R, X[pid]) + t
    in_front = Xc[:, 2] > 0.1
    err = np.linalg.norm(Xc[:, :2] / np.where(in_front, Xc[:, 2], 1.0)[:, None] - x, axis=1) * f
    # points behind a camera or with gross outlier observations are dropped (as a BA cull)
    bad = np.zeros(n_pts, bool)
    np.logical_or.at(bad, pid, ~in_front | (err > 5.0))
    good_obs = ~bad[pid]
    lengths = np.bincount(pid[good_obs], minlength=n_pts)[~bad]
    return SparseMap(X[~bad], lengths, err[good_obs])
