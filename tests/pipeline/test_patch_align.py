"""``align_patches`` (``vision.patch_refine``): where a textured plane's patches seen in one
image appear in another, against the closed-form projection of the same surface points."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from jaxslam.lie import host
from jaxslam.pipeline._visual import align_patches, distort_normalized, undistort_normalized

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
SIZE = (240, 320)
# a wall to the left, seen obliquely (camera a frame: x right, y down, z forward)
NORMAL = np.array([0.8, 0.0, -0.6]) / np.linalg.norm([0.8, 0.0, -0.6])
POINT = np.array([-1.5, 0.0, 4.0])
TEXTURE = ndimage.gaussian_filter(np.random.default_rng(0).uniform(0, 255, (600, 600)), 2.0)


def _plane_hit(x: np.ndarray, T_ca: np.ndarray) -> np.ndarray:
    """Points (camera a frame) where the rays ``x`` (normalised, camera c) meet the plane."""
    R, t = T_ca[:3, :3], T_ca[:3, 3]  # X_a = R X_c + t
    rays = np.concatenate([x, np.ones((len(x), 1))], 1) @ R.T
    lam = (NORMAL @ POINT - NORMAL @ t) / (rays @ NORMAL)
    return t + rays * lam[:, None]


def _render(T_ca: np.ndarray, dist: tuple[float, ...], gain: float = 1.0, offset: float = 0.0) -> np.ndarray:
    """Image of the textured plane from camera c (``T_ca``: camera a <- c)."""
    v, u = np.mgrid[0 : SIZE[0], 0 : SIZE[1]].astype(np.float64)
    x = undistort_normalized(np.stack([u.ravel(), v.ravel()], 1), K, dist)
    X = _plane_hit(x, T_ca)
    e1 = np.cross(NORMAL, [0.0, 1.0, 0.0])
    e2 = np.cross(NORMAL, e1)
    s, r = (X - POINT) @ e1 * 60 + 300, (X - POINT) @ e2 * 60 + 300  # 60 texels per metre
    grey = ndimage.map_coordinates(TEXTURE, [r, s], order=1, mode="mirror")
    return np.clip(gain * grey + offset, 0, 255).reshape(SIZE).astype(np.uint8)


def _project(X: np.ndarray, T_ba: np.ndarray, dist: tuple[float, ...]) -> np.ndarray:
    Xb = host.transform_points(T_ba, X)
    return distort_normalized(Xb[:, :2] / Xb[:, 2:3], dist) * K[[0, 1], [0, 1]] + K[:2, 2]


@pytest.mark.parametrize("dist", [(0.0, 0.0, 0.0, 0.0), (-0.2, 0.05, 0.001, -0.001)])
def test_patches_land_on_the_surface_points_despite_a_pose_error_and_exposure(dist) -> None:
    T_ab = host.make_pose(host.so3_exp(np.radians([0.5, 3.0, 0.0])), np.array([0.05, 0.0, 0.3]))  # a <- b
    T_ba = host.inverse(T_ab)
    img_a = _render(np.eye(4), dist)
    img_b = _render(T_ab, dist, gain=0.6, offset=25.0)  # another exposure and black level
    rng = np.random.default_rng(1)
    uv_a = rng.uniform([40, 40], [150, 200], (60, 2))  # the wall's side of image a
    X_a = _plane_hit(undistort_normalized(uv_a, K, dist), np.eye(4))
    truth = _project(X_a, T_ba, dist)
    # the motion handed over is off by 1 cm and 0.2 degrees: its projections miss by ~1 px
    wrong = host.make_pose(host.so3_exp(np.radians([0.0, 0.2, 0.0])), np.array([0.01, 0.0, 0.0])) @ T_ba
    start = _project(X_a, wrong, dist)
    assert np.median(np.linalg.norm(start - truth, axis=1)) > 0.5
    uv_b, ok = align_patches(img_a, img_b, uv_a, X_a, np.tile(NORMAL, (60, 1)), wrong, K, dist)
    assert ok.mean() > 0.9
    err = np.linalg.norm(uv_b[ok] - truth[ok], axis=1)
    assert np.median(err) < 0.05 and err.max() < 0.2, (np.median(err), err.max())


def test_patches_of_another_surface_do_not_align() -> None:
    dist = (0.0, 0.0, 0.0, 0.0)
    img_a = _render(np.eye(4), dist)
    img_b = np.random.default_rng(2).uniform(0, 255, SIZE).astype(np.uint8)  # nothing in common
    uv_a = np.random.default_rng(3).uniform([40, 40], [150, 200], (40, 2))
    X_a = _plane_hit(undistort_normalized(uv_a, K, dist), np.eye(4))
    _, ok = align_patches(img_a, img_b, uv_a, X_a, np.tile(NORMAL, (40, 1)), np.eye(4), K, dist)
    assert ok.mean() < 0.1


def test_patches_that_cannot_be_aligned_are_refused_without_failing() -> None:
    """A plane seen edge-on (no depth along the patch), a patch behind the other camera and a
    flat image (no gradient) give ``ok`` False, not an exception or NaN."""
    dist = (0.0, 0.0, 0.0, 0.0)
    img_a = _render(np.eye(4), dist)
    uv_a = np.array([[100.0, 120.0], [120.0, 100.0], [140.0, 130.0]])
    X_a = _plane_hit(undistort_normalized(uv_a, K, dist), np.eye(4))
    edge_on = np.cross(X_a[0], [0.0, 1.0, 0.0])
    normals = np.stack([edge_on / np.linalg.norm(edge_on), NORMAL, NORMAL])
    behind = host.make_pose(np.eye(3), np.array([0.0, 0.0, -10.0]))  # camera b 10 m ahead
    uv, ok = align_patches(img_a, img_a, uv_a, X_a, normals, behind, K, dist)
    assert not ok.any() and uv.shape == (3, 2)
    flat = np.full(SIZE, 90, np.uint8)
    uv, ok = align_patches(img_a, flat, uv_a, X_a, np.tile(NORMAL, (3, 1)), np.eye(4), K, dist)
    assert not ok.any() and np.all(np.isfinite(uv))


def test_larger_patches_align_where_sensor_noise_caps_the_small_ones() -> None:
    """A dark, noisy pair (texture at 15 % of its contrast, noise sigma 1.5 grey levels):
    13x13 patches at NCC 0.7 (the defaults) mostly fail, 21x21 patches at 0.5
    (``vision.patch_half`` 10, ``vision.patch_min_ncc`` 0.5) align and land closer to the truth
    than the motion handed over puts them."""
    dist = (0.0, 0.0, 0.0, 0.0)
    T_ab = host.make_pose(host.so3_exp(np.radians([0.5, 3.0, 0.0])), np.array([0.05, 0.0, 0.3]))
    T_ba = host.inverse(T_ab)

    def dark(img: np.ndarray, seed: int) -> np.ndarray:
        noise = np.random.default_rng(seed).normal(0.0, 1.5, img.shape)
        return np.clip(0.15 * img.astype(np.float64) + 4.0 + noise, 0, 255).round().astype(np.uint8)

    img_a, img_b = dark(_render(np.eye(4), dist), 5), dark(_render(T_ab, dist), 6)
    uv_a = np.random.default_rng(1).uniform([40, 40], [150, 200], (80, 2))
    X_a = _plane_hit(undistort_normalized(uv_a, K, dist), np.eye(4))
    truth = _project(X_a, T_ba, dist)
    wrong = host.make_pose(host.so3_exp(np.radians([0.0, 0.2, 0.0])), np.array([0.01, 0.0, 0.0])) @ T_ba
    start_err = np.median(np.linalg.norm(_project(X_a, wrong, dist) - truth, axis=1))
    normals = np.tile(NORMAL, (80, 1))
    _, ok_small = align_patches(img_a, img_b, uv_a, X_a, normals, wrong, K, dist)
    uv, ok = align_patches(img_a, img_b, uv_a, X_a, normals, wrong, K, dist, half=10, min_ncc=0.5)
    assert ok_small.mean() < 0.5 and ok.mean() > 0.9, (ok_small.mean(), ok.mean())
    err = np.median(np.linalg.norm(uv[ok] - truth[ok], axis=1))
    assert err < 0.35 and err < 0.5 * start_err, (err, start_err)


def test_the_frontend_hands_the_patch_settings_to_the_alignment(monkeypatch) -> None:
    from jaxslam.pipeline import _visual
    from jaxslam.pipeline._config import RigConfig, VisionConfig

    seen = []

    def spy(img_a, img_b, uv_a, X_a, n_a, T_ba, K_, dist, half=6, iterations=10, max_shift_px=2.5, min_ncc=0.7):
        seen.append((half, min_ncc))
        return np.asarray(uv_a, np.float64), np.zeros(len(uv_a), bool)

    monkeypatch.setattr(_visual, "align_patches", spy)
    fe = _visual.VisualFrontend(VisionConfig(patch_half=10, patch_min_ncc=0.45), RigConfig())
    n = 30
    rng = np.random.default_rng(0)

    def feats(kf: int) -> _visual.KeyframeFeatures:
        uv = rng.uniform(50, 150, (n, 2))
        X = np.concatenate([rng.uniform(-1, 1, (n, 2)), np.full((n, 1), 4.0)], 1)
        return _visual.KeyframeFeatures(
            kf, float(kf), uv, uv / 300.0, np.zeros((n, 64)), np.ones(n), X, np.arange(n),
            normal=np.tile([0.0, 0.0, -1.0], (n, 1)), image=np.zeros(SIZE, np.uint8),
        )  # fmt: skip

    idx = np.arange(n)
    assert fe._refine_by_patches(feats(0), feats(1), idx, idx, np.eye(4)) is None  # nothing aligned
    assert seen == [(10, 0.45)]  # no retry by default
    seen.clear()
    fe = _visual.VisualFrontend(VisionConfig(patch_retry_half=9, patch_retry_min_ncc=0.4), RigConfig())
    assert fe._refine_by_patches(feats(0), feats(1), idx, idx, np.eye(4)) is None
    assert seen == [(6, 0.7), (9, 0.4)] and fe.patch_retried == 0  # the retry failed as well

    # a retry that aligns: the pose is fitted on its positions and counted
    def retry_aligns(
        img_a, img_b, uv_a, X_a, n_a, T_ba, K_, dist, half=6, iterations=10, max_shift_px=2.5, min_ncc=0.7
    ):
        return np.asarray(uv_a, np.float64), np.full(len(uv_a), half == 9)

    monkeypatch.setattr(_visual, "align_patches", retry_aligns)
    a, b = feats(0), feats(1)
    b.uv = distort_normalized(a.X[:, :2] / a.X[:, 2:], fe.rig.camera_distortion) * fe.K[[0, 1], [0, 1]] + fe.K[:2, 2]
    a.uv = b.uv  # a static camera: b sees a's points where a does
    out = fe._refine_by_patches(a, b, idx, idx, np.eye(4))
    assert out is not None and fe.patch_retried == 1
    assert np.allclose(out[0], np.eye(4), atol=1e-9)
