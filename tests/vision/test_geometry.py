"""Two-view geometry on synthetic scenes with closed-form ground truth, OpenCV as oracle:
essential-matrix RANSAC, decomposition + cheirality, DLT triangulation, bundle adjustment."""

from __future__ import annotations

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.lie import SO3
from jaxslam.vision import (
    bundle_adjust,
    decompose_essential,
    find_essential,
    normalize_pixels,
    recover_pose,
    relative_pose,
    reprojection_residuals,
    sampson_error,
    triangulate_dlt,
    triangulate_points,
)
from jaxslam.vision._geometry import essential_from_pose
from jaxslam.vision._vo import _to_params

K = np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.2], [0.0, 0.0, 1.0]])


def _scene(n=400, outliers=0.3, noise=0.5, seed=0):
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-15, 15, n), rng.uniform(-3, 3, n), rng.uniform(5, 40, n)]
    R = np.asarray(SO3.exp(jnp.asarray(rng.normal(size=3) * 0.05)).as_matrix())
    t = np.array([0.1, 0.02, 1.0])
    t /= np.linalg.norm(t)
    X2 = X @ R.T + t
    uv1 = X @ K.T
    uv1 = uv1[:, :2] / uv1[:, 2:]
    uv2 = X2 @ K.T
    uv2 = uv2[:, :2] / uv2[:, 2:]
    uv1 = uv1 + rng.normal(scale=noise, size=uv1.shape)
    uv2 = uv2 + rng.normal(scale=noise, size=uv2.shape)
    bad = rng.random(n) < outliers
    uv2[bad] = np.c_[rng.uniform(0, 1241, bad.sum()), rng.uniform(0, 376, bad.sum())]
    return uv1, uv2, R, t, ~bad, X


def _rot_err_deg(a, b):
    return np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)))


def _dir_err_deg(a, b):
    return np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_sampson_zero_for_exact_correspondences():
    uv1, uv2, R, t, _, _ = _scene(n=50, outliers=0.0, noise=0.0)
    E = essential_from_pose(R, t)
    err = np.asarray(sampson_error(E, normalize_pixels(uv1, K), normalize_pixels(uv2, K)))
    assert err.max() < 1e-20


def test_ransac_recovers_pose_and_inliers():
    uv1, uv2, R, t, inl, _ = _scene()
    res = find_essential(normalize_pixels(uv1, K), normalize_pixels(uv2, K), 1.0 / K[0, 0])
    assert _rot_err_deg(R, np.asarray(res.R)) < 0.15
    assert _dir_err_deg(t, np.asarray(res.t)) < 2.0
    found = np.asarray(res.inliers)
    assert np.sum(found & ~inl) <= 3  # outliers rarely pass a 1 px Sampson gate
    assert np.sum(found & inl) > 0.75 * inl.sum()
    assert abs(np.linalg.det(np.asarray(res.R)) - 1) < 1e-9


def test_ransac_at_least_as_accurate_as_opencv():
    """Same scenes, same 1 px threshold: ours (8-point MSAC + local optimisation + Sampson GN)
    vs cv2.findEssentialMat (5-point RANSAC) + cv2.recoverPose, mean over scenes."""
    ours, cv = [], []
    for seed in range(4):
        uv1, uv2, R, t, _, _ = _scene(seed=seed)
        for method, acc in (("jax", ours), ("opencv", cv)):
            Re, te, _ = relative_pose(uv1, uv2, K, method=method, threshold_px=1.0)
            acc.append((_rot_err_deg(R, Re), _dir_err_deg(t, te)))
    ours_m, cv_m = np.mean(ours, 0), np.mean(cv, 0)
    assert ours_m[0] <= cv_m[0] * 1.2 and ours_m[1] <= cv_m[1] * 1.2


def test_decompose_and_cheirality_match_opencv():
    uv1, uv2, R, t, _, _ = _scene(n=200, outliers=0.0, noise=0.3, seed=3)
    E = essential_from_pose(R, t)
    Rs, ts = decompose_essential(E)
    R1, R2, tc = cv2.decomposeEssentialMat(np.asarray(E))
    for cand in (R1, R2):
        assert min(np.abs(np.asarray(r) - cand).max() for r in Rs) < 1e-9
    assert min(np.abs(np.asarray(x) - tc[:, 0]).max() for x in ts) < 1e-9
    x1, x2 = normalize_pixels(uv1, K), normalize_pixels(uv2, K)
    Rr, tr, good, _X = recover_pose(E, x1, x2)
    _, Rcv, tcv, mask = cv2.recoverPose(np.asarray(E), uv1, uv2, K)
    np.testing.assert_allclose(np.asarray(Rr), Rcv, atol=1e-9)
    np.testing.assert_allclose(np.asarray(tr), tcv[:, 0], atol=1e-9)
    np.testing.assert_allclose(np.asarray(tr), t, atol=1e-9)
    assert abs(int(np.sum(good)) - int(np.sum(mask > 0))) <= 2


def test_triangulation_closed_form_and_opencv():
    _, _, R, t, _, X = _scene(n=100, outliers=0.0, noise=0.0, seed=4)
    P1 = np.c_[np.eye(3), np.zeros(3)]
    P2 = np.c_[R, t]
    x1 = X[:, :2] / X[:, 2:]
    X2 = X @ R.T + t
    x2 = X2[:, :2] / X2[:, 2:]
    Xe, fin = triangulate_dlt(P1, P2, x1, x2)
    assert np.all(np.asarray(fin))
    np.testing.assert_allclose(np.asarray(Xe), X, rtol=1e-7, atol=1e-7)
    # pixels with K [R | t], against cv2.triangulatePoints on noisy input
    rng = np.random.default_rng(0)
    uv1 = x1 @ K[:2, :2].T + K[:2, 2] + rng.normal(scale=0.5, size=x1.shape)
    uv2 = x2 @ K[:2, :2].T + K[:2, 2] + rng.normal(scale=0.5, size=x2.shape)
    Xh = cv2.triangulatePoints(K @ P1, K @ P2, uv1.T, uv2.T)
    Xn, _ = triangulate_points(K @ P1, K @ P2, uv1, uv2)
    Xcv = (Xh[:3] / Xh[3]).T
    # rows of A are normalised here (OpenCV's are not): close, and no less accurate
    assert np.median(np.linalg.norm(Xn - Xcv, axis=1) / np.linalg.norm(X, axis=1)) < 5e-3
    assert np.mean(np.linalg.norm(Xn - X, axis=1)) <= 1.05 * np.mean(np.linalg.norm(Xcv - X, axis=1))
    # a point at infinity is flagged, not divided by zero
    _, fin = triangulate_dlt(
        P1, np.c_[np.eye(3), np.array([1.0, 0, 0])], np.array([[0.1, 0.0]]), np.array([[0.1, 0.0]])
    )
    assert not bool(np.asarray(fin)[0])


def test_bundle_adjust_recovers_truth_with_outliers():
    rng = np.random.default_rng(5)
    n_cam, n_pt = 4, 150
    X = np.c_[rng.uniform(-8, 8, n_pt), rng.uniform(-2, 2, n_pt), rng.uniform(8, 30, n_pt)]
    T_cw = np.tile(np.eye(4), (n_cam, 1, 1))
    T_cw[:, 2, 3] = -np.arange(n_cam) * 1.0  # camera c at z = c, looking along +z
    poses = _to_params(T_cw)
    cam = np.repeat(np.arange(n_cam), n_pt)
    pt = np.tile(np.arange(n_pt), n_cam)
    Xc = X[pt] + T_cw[cam, :3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2] + rng.normal(scale=0.3, size=(len(cam), 2))
    out = rng.choice(len(cam), 20, replace=False)
    uv[out] += rng.uniform(20, 40, size=(20, 2))  # gross outliers: Huber bounds their pull
    p0 = poses.copy()
    p0[2:, 4:] += rng.normal(scale=0.05, size=(n_cam - 2, 3))
    X0 = X + rng.normal(scale=0.2, size=X.shape)
    res = bundle_adjust(p0, X0, cam, pt, uv, K, fixed_cameras=[0, 1], huber_px=1.0)
    assert res.final_cost < res.initial_cost
    assert np.abs(res.poses[:, 4:] - poses[:, 4:]).max() < 0.02
    inl = ~np.isin(pt, pt[out])  # observations of points that no outlier touches
    r = reprojection_residuals(res.poses, res.points, cam, pt, uv, K)
    np.testing.assert_allclose(r, res.residuals)
    assert np.sqrt(np.mean(r[inl] ** 2)) < 0.4
    with pytest.raises(ValueError, match="no observations"):
        bundle_adjust(p0, X0, cam[:0], pt[:0], uv[:0], K)


def test_no_ransac_path_on_clean_matches():
    uv1, uv2, R, t, _, _ = _scene(n=300, outliers=0.0, noise=0.3, seed=6)
    Re, te, good = relative_pose(uv1, uv2, K, method="none")
    assert _rot_err_deg(R, Re) < 0.3 and _dir_err_deg(t, te) < 3.0 and good.mean() > 0.95
    with pytest.raises(ValueError, match="method"):
        relative_pose(uv1, uv2, K, method="magsac")
